"""The tests' one way to wait (tests/support/waiting.py): it returns the moment the condition
holds, and a condition that never holds fails naming what was waited for and what was seen."""

from __future__ import annotations

import asyncio

import pytest

from tests.support.waiting import probe_until, wait_for, wait_for_sync

pytestmark = pytest.mark.fast


def test_wait_for_returns_the_value_and_awaits_an_async_predicate():
    async def scenario() -> tuple[object, object]:
        polls = iter([None, 0, "ready"])

        async def asked() -> str | int | None:
            return next(polls)

        return await wait_for(lambda: [1], 1, "a list"), await wait_for(asked, 1, "the third answer")

    assert asyncio.run(scenario()) == ([1], "ready")


def test_a_wait_that_never_holds_fails_naming_what_and_what_was_seen():
    with pytest.raises(AssertionError, match=r"timed out after 0.1 s waiting for 3 messages: 2 arrived"):
        asyncio.run(wait_for(lambda: False, 0.1, "3 messages", lambda: "2 arrived"))
    with pytest.raises(AssertionError, match=r"waiting for the status file: None"):
        wait_for_sync(lambda: None, 0.1, "the status file", lambda: None)


def test_probe_until_sends_again_until_one_gets_through_and_no_more():
    async def scenario() -> int:
        sent: list[int] = []

        async def probe() -> None:
            sent.append(len(sent))

        await probe_until(lambda: len(sent) >= 3, probe, 5, "the third probe", every=0.01)
        await asyncio.sleep(0.05)  # quiet window: no probe is sent once one got through
        return len(sent)

    assert asyncio.run(scenario()) == 3
    with pytest.raises(AssertionError, match="waiting for an echo"):
        asyncio.run(probe_until(lambda: False, lambda: None, 0.1, "an echo", every=0.02))
