"""engine/running/buffer.py on its own: order, bounds, retries, spill files that survive a restart,
torn lines, and rejections that are dead-lettered instead of retried."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from engine.endpoints.base import EndpointError, MessageRejected, Outbound
from engine.running.buffer import Held, HoldingBuffer
from engine.running.buffer_stores import SEGMENT_MESSAGES, decode, encode
from tests.support.waiting import wait_for

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def message(index: int) -> Outbound:
    canonical = {"seq": index, "agent_id": "uav1"}
    return Outbound(f'{{"seq":{index}}}'.encode(), canonical, canonical, f"m{index}", {"route": "r", "generation": 1})


class SwitchableSink:
    """A sink whose destination can be taken down and brought back."""

    def __init__(self) -> None:
        self.up = False
        self.received: list[int] = []
        self.reject: set[int] = set()

    async def send(self, outbound: Outbound) -> None:
        await asyncio.sleep(0)
        if outbound.canonical["seq"] in self.reject:
            raise MessageRejected("too large")
        if not self.up:
            raise EndpointError("broker down")
        self.received.append(outbound.canonical["seq"])

    async def send_batch(self, messages: list[Outbound]) -> list[BaseException | None]:
        results: list[BaseException | None] = []
        for outbound in messages:
            try:
                await self.send(outbound)
            except EndpointError as error:
                results.append(error)
            else:
                results.append(None)
        return results


def test_encode_decode_round_trip_keeps_bytes_and_fields() -> None:
    original = Outbound(b"\xff\x00raw", {"a": 1}, {"b": [1, 2]}, "id-1", {"route": "r", "topic": "/x"})
    back = decode(encode(original))
    assert (back.body, back.canonical, back.fields, back.message_id, back.meta) == (
        original.body, original.canonical, original.fields, original.message_id, original.meta
    )


def test_a_held_message_with_values_orjson_refuses_round_trips_exactly() -> None:
    """An integer beyond 64 bits (valid JSON, carried exactly by the engine) and a lone
    surrogate: orjson refuses to write both; a spilled message keeps them as they were."""
    canonical = {"big": 2**70 + 1, "text": "\ud800", "nested": [{"n": -(2**65)}]}
    original = Outbound(b'{"big":1180591620717411303425}', canonical, canonical, "id-2", {"route": "r"})
    line = encode(original, 123)
    back = decode(line)
    assert back.canonical == canonical and back.fields is back.canonical
    assert back.body == original.body and back.message_id == "id-2"


@pytest.mark.parametrize("spill", [False, True])
def test_holds_in_order_while_down_and_delivers_after(tmp_path: Path, spill: bool) -> None:
    async def scenario() -> None:
        sink = SwitchableSink()
        delivered: list[list[Held]] = []
        buffer = HoldingBuffer("r", sink.send_batch, spill_dir=tmp_path if spill else None, on_delivered=delivered.append)
        buffer.start()
        for index in range(2_500):
            await buffer.hold(message(index))
        assert len(buffer) == 2_500 and sink.received == []
        sink.up = True
        await wait_for(lambda: not buffer.holding)
        assert sink.received == list(range(2_500))
        assert sum(map(len, delivered)) == 2_500 and buffer.stats.delivered == 2_500
        await buffer.close()
        if spill:
            assert [p.name for p in (tmp_path / "r").glob("*.jsonl")] in ([], [f"{2_000:020d}.jsonl"])

    asyncio.run(scenario())


def test_spilled_messages_survive_a_restart_and_nothing_is_replayed_twice(tmp_path: Path) -> None:
    async def first_run() -> list[int]:
        sink = SwitchableSink()
        buffer = HoldingBuffer("r", sink.send_batch, spill_dir=tmp_path)
        buffer.start()
        for index in range(3 * SEGMENT_MESSAGES + 10):
            await buffer.hold(message(index))
        sink.up = True
        await wait_for(lambda: len(sink.received) >= 500)
        sink.up = False
        await buffer.close()
        return sink.received

    async def second_run(expected_from: int) -> None:
        sink = SwitchableSink()
        sink.up = True
        buffer = HoldingBuffer("r", sink.send_batch, spill_dir=tmp_path)
        buffer.start()
        assert buffer.stats.replayed == 3 * SEGMENT_MESSAGES + 10 - expected_from
        await wait_for(lambda: not buffer.holding)
        assert sink.received == list(range(expected_from, 3 * SEGMENT_MESSAGES + 10))
        await buffer.close()
        third = HoldingBuffer("r", sink.send_batch, spill_dir=tmp_path)
        third.start()
        assert third.stats.replayed == 0
        await third.close()

    first = asyncio.run(first_run())
    asyncio.run(second_run(len(first)))


def test_a_torn_last_line_is_skipped_and_counted(tmp_path: Path) -> None:
    async def scenario() -> None:
        buffer = HoldingBuffer("r", SwitchableSink().send_batch, spill_dir=tmp_path)
        buffer.start()
        for index in range(5):
            await buffer.hold(message(index))
        await buffer.close()
        segment = next((tmp_path / "r").glob("*.jsonl"))
        with open(segment, "ab") as file:
            file.write(encode(message(5))[:20])  # a write cut short by a power loss
        sink = SwitchableSink()
        sink.up = True
        again = HoldingBuffer("r", sink.send_batch, spill_dir=tmp_path)
        again.start()
        assert (again.stats.replayed, again.stats.corrupt) == (5, 1)
        await wait_for(lambda: not again.holding)
        for index in range(6, 9):
            await again.hold(message(index))
        await wait_for(lambda: not again.holding)
        assert sink.received == [0, 1, 2, 3, 4, 6, 7, 8]
        await again.close()

    asyncio.run(scenario())


def test_full_buffer_makes_hold_wait_and_memory_leftovers_count_as_lost() -> None:
    async def scenario() -> None:
        sink = SwitchableSink()
        buffer = HoldingBuffer("r", sink.send_batch, max_messages=10)
        buffer.start()
        for index in range(10):
            await buffer.hold(message(index))
        blocked = asyncio.create_task(buffer.hold(message(10)))
        await asyncio.sleep(0.2)  # quiet window: the hold stays blocked while the buffer is full (the behaviour under test)
        assert not blocked.done()
        sink.up = True
        await asyncio.wait_for(blocked, 5)
        await wait_for(lambda: not buffer.holding)
        assert sink.received == list(range(11))
        sink.up = False
        await buffer.hold(message(11))
        await buffer.close(timeout=0.2)
        assert buffer.stats.lost == 1

    asyncio.run(scenario())


def test_rejected_messages_go_to_the_dead_letter_callback_once_and_the_rest_flow() -> None:
    async def scenario() -> None:
        sink = SwitchableSink()
        sink.reject = {3, 7}
        dead: list[int] = []

        async def dead_letter(outbound: Outbound, error: BaseException, attempts: int) -> None:
            dead.append(outbound.canonical["seq"])

        buffer = HoldingBuffer("r", sink.send_batch, on_rejected=dead_letter)
        buffer.start()
        for index in range(10):
            await buffer.hold(message(index))
        sink.up = True
        await wait_for(lambda: not buffer.holding)
        assert dead == [3, 7] and sink.received == [0, 1, 2, 4, 5, 6, 8, 9]
        await buffer.close()

    asyncio.run(scenario())


def test_no_attempt_while_the_connection_reports_down() -> None:
    async def scenario() -> None:
        sink = SwitchableSink()
        attempts = 0
        healthy = False

        async def counting(messages: list[Outbound]) -> list[BaseException | None]:
            nonlocal attempts
            attempts += 1
            return await sink.send_batch(messages)

        buffer = HoldingBuffer("r", counting, ready=lambda: healthy)
        buffer.start()
        await buffer.hold(message(0))
        await asyncio.sleep(0.3)  # quiet window: no attempt while the sink is not ready (the behaviour under test)
        assert attempts == 0
        sink.up = healthy = True
        await wait_for(lambda: not buffer.holding)
        assert attempts == 1
        await buffer.close()

    asyncio.run(scenario())


def test_a_message_the_healthy_sink_keeps_failing_is_given_up_after_max_attempts() -> None:
    async def scenario() -> None:
        sink = SwitchableSink()
        sink.up = True
        given_up: list[tuple[int, int]] = []

        async def send_batch(messages: list[Outbound]) -> list[BaseException | None]:
            results: list[BaseException | None] = []
            for m in messages:
                if m.canonical["seq"] == 1:
                    results.append(EndpointError("no answer"))
                else:
                    await sink.send(m)
                    results.append(None)
            return results

        async def dead_letter(outbound: Outbound, error: BaseException, attempts: int) -> None:
            given_up.append((outbound.canonical["seq"], attempts))

        buffer = HoldingBuffer("r", send_batch, max_attempts=3, on_rejected=dead_letter)
        buffer.start()
        for index in range(4):
            await buffer.hold(message(index))
        await wait_for(lambda: not buffer.holding)
        assert given_up == [(1, 3)] and sink.received == [0, 2, 3]
        await buffer.close()

    asyncio.run(scenario())


def test_route_files_parse_buffer_options_and_check_the_spill_dir(tmp_path: Path) -> None:
    from engine.common.schemas import SchemaRegistry
    from engine.language.routes import RoutesInvalid, load_routes
    from engine.language.stage_options import BufferSpec
    from tests.support.repo import REPO

    (tmp_path / "not-a-dir").write_text("")
    route = """
routes:
  - {name: held, source: {amqp: {queue: q}}, schema: raw_json, sink: {amqp: {exchange: e}}, buffer: {max_messages: 50, spill_dir: spill}}
  - {name: plain, source: {amqp: {queue: q2}}, schema: raw_json, sink: {amqp: {exchange: e}}}
  - {name: none, source: {amqp: {queue: q3}}, schema: raw_json, sink: {amqp: {exchange: e}}, buffer: false}
"""
    (tmp_path / "a.yaml").write_text(route)
    registry = SchemaRegistry(REPO / "schemas")
    config = load_routes(tmp_path, registry, env={})
    assert config.routes["held"].buffer == BufferSpec(50, (tmp_path / "spill").resolve(), 1.0)
    assert config.routes["plain"].buffer is None and config.routes["none"].buffer is None
    assert BufferSpec.parse(None, False, tmp_path) == BufferSpec() and BufferSpec.parse(False, False, tmp_path) is None
    (tmp_path / "a.yaml").write_text(route.replace("spill_dir: spill", "spill_dir: not-a-dir"))
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, registry, env={})
    assert any("a.yaml:3" in str(p) and "is not a directory" in str(p) for p in invalid.value.problems)


def test_latest_only_and_stale_messages_leave_the_buffer_unsent_and_counted() -> None:
    """Held while down: 12 messages over 3 agents; seq 1 is stale. Back up: only the newest
    per agent is sent; the older ones are conflated, the stale one expired (reported once each,
whether or not the sink was up when their turn came: neither needs the sink)."""
    async def scenario() -> None:
        sink = SwitchableSink()
        expired: list[int] = []
        conflated: list[int] = []
        buffer = HoldingBuffer("r", sink.send_batch, latest_per=("agent_id",),
                               stale=lambda held: held[0].canonical["seq"] == 10,
                               on_expired=lambda held: expired.extend(m.canonical["seq"] for m, _ in held),
                               on_conflated=lambda held: conflated.extend(m.canonical["seq"] for m, _ in held))
        buffer.start()
        for index in range(12):
            outbound = message(index)
            outbound.canonical["agent_id"] = f"uav{index % 3}"
            await buffer.hold(outbound)
        await wait_for(lambda: buffer.stats.retries > 0)  # tried while down: the newest wait
        sink.up = True
        await wait_for(lambda: not buffer.holding)
        assert sink.received == [9, 11]
        assert expired == [10] and sorted(conflated) == list(range(9))
        assert (buffer.stats.delivered, buffer.stats.expired, buffer.stats.conflated) == (2, 1, 9)
        await buffer.close()

    asyncio.run(scenario())
