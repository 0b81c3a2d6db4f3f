"""The engine runs on asyncio's loop, on uvloop when asked, and refuses a loop it cannot run."""

from __future__ import annotations

import asyncio

import pytest

from engine.running import loop

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def running_loop_module() -> str:
    async def which() -> str:
        return type(asyncio.get_running_loop()).__module__

    return loop.run(which())


def test_asyncio_loop_by_default(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("RABBITROS_LOOP", raising=False)
    assert loop.loop_factory() is None and loop.loop_name() == "asyncio"
    assert running_loop_module().startswith("asyncio")


def test_uvloop_on_request(monkeypatch: pytest.MonkeyPatch) -> None:
    import uvloop  # noqa: F401  (the "fast" extra, installed by scripts/setup.sh: missing = red)
    monkeypatch.setenv("RABBITROS_LOOP", "uvloop")
    assert loop.loop_name() == "uvloop"
    assert running_loop_module().startswith("uvloop")


def test_an_unknown_loop_is_refused_by_name(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RABBITROS_LOOP", "trio")
    with pytest.raises(loop.LoopChoiceError, match="RABBITROS_LOOP='trio': use one of asyncio, uvloop"):
        loop.loop_factory()
