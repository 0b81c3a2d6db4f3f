"""bench/bench_convert.py compiles its routes with the engine's own loader and converts
(it had drifted from the route spec and crashed at start without anyone seeing)."""

from __future__ import annotations

import math

import pytest

from bench.bench_convert import measure

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def test_the_conversion_bench_converts_each_route() -> None:
    figures = measure(count=200)
    assert set(figures) == {"position_from_fields_us", "weeds_from_json_us", "identity_raw_json_us"}
    assert all(math.isfinite(value) and value > 0 for value in figures.values()), figures
