"""The engine runs on uvloop where it is installed, and on asyncio's loop when told."""

from __future__ import annotations

import asyncio

import pytest

from engine.running import loop

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def running_loop_module() -> str:
    async def which() -> str:
        return type(asyncio.get_running_loop()).__module__

    return loop.run(which())


def test_uvloop_runs_the_engine_where_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    import uvloop  # noqa: F401  (the "fast" extra, installed by scripts/setup.sh: missing = red)
    monkeypatch.delenv("RABBITROS_LOOP", raising=False)
    assert loop.loop_name() == "uvloop"
    assert running_loop_module().startswith("uvloop")


def test_asyncio_loop_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RABBITROS_LOOP", "asyncio")
    assert loop.loop_factory() is None and loop.loop_name() == "asyncio"
    assert running_loop_module().startswith("asyncio")
