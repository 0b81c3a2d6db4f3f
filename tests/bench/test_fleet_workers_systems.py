"""bench/bench_fleet_workers.py gives each system what it names: a system's engine environment
(uvloop in place of asyncio's loop) reaches the engine it runs."""

from __future__ import annotations

import pytest

from bench.bench_fleet_workers import ENGINE_ENV, SYSTEMS, mode_arguments
from bench.fleet import REFERENCE

pytestmark = pytest.mark.fast  # no broker, no engine: the arguments a step hands bench/fleet.py


def test_each_system_runs_its_mode_workers_and_engine_environment() -> None:
    assert set(ENGINE_ENV) <= set(SYSTEMS)
    assert mode_arguments("1 worker uvloop") == {"mode": "templated", "workers": 1, "engine_env": {"RABBITROS_LOOP": "uvloop"}}
    assert mode_arguments("1 worker") == {"mode": "templated", "workers": 1, "engine_env": None}
    assert mode_arguments("2 workers")["workers"] == 2
    assert mode_arguments("reference") == {"mode": REFERENCE, "workers": 0, "engine_env": None}
