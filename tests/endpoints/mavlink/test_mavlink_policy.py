"""MAVLink endpoints under the engine's delivery policy: bounded sources with the route's
overflow policy, tunnel acknowledgements after settling, reload identity and option checks."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import Inbound, MessageRejected, Outbound, Transport  # noqa: E402
from rabbitros_sim.deliver import FunctionDeliver  # noqa: E402
from tests.endpoints.mavlink.test_mavlink_endpoint import UdpPeer, bound_port, packer, run  # noqa: E402
from tests.support.waiting import wait_for


class GatedDeliver(FunctionDeliver):
    """Settles nothing until ``gate`` opens, so the source's inbox fills up behind it."""

    def __init__(self, **deliver: Any) -> None:
        super().__init__(**deliver)
        self.gate = asyncio.Event()
        self.entered = asyncio.Event()
        self.stamps: list[int] = []

    async def __call__(self, inbound: Inbound) -> None:
        self.entered.set()
        await self.gate.wait()
        assert inbound.fields is not None
        self.stamps.append(inbound.fields["time_boot_ms"])


def positions(mav: mavlink2.MAVLink, stamps: range) -> bytes:
    return b"".join(mav.global_position_int_encode(n, 1, 2, 3, 4, 5, 6, 7, 8).pack(mav) for n in stamps)


async def flood(overflow: str, *, stop_while_queued: bool = False) -> tuple[GatedDeliver, dict[str, Any]]:
    """One message in flight (held at the gate), then 100 more into an inbox of 10."""
    conn = mavlink.TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
    await conn.open()
    peer = await UdpPeer.bind()
    deliver = GatedDeliver(overflow=overflow, queue_limit=10)
    source = conn.source("telemetry", {"message": "GLOBAL_POSITION_INT"})
    await source.start(deliver)
    try:
        mav = packer(1, 1)
        peer.send(positions(mav, range(1)), bound_port(conn))
        await asyncio.wait_for(deliver.entered.wait(), 5)
        peer.send(positions(mav, range(1, 101)), bound_port(conn))
        await wait_for(lambda: source.status()["received"] == 101, 5)
        if stop_while_queued:
            stopping = asyncio.create_task(source.stop())
            await asyncio.sleep(0.05)  # settle: the stop begins while the batch is queued (the race under test)
            deliver.gate.set()
            await asyncio.wait_for(stopping, 5)
        else:
            deliver.gate.set()
            await wait_for(lambda: len(deliver.stamps) == 11, 5)
        return deliver, source.status()
    finally:
        await source.stop()
        peer.close()
        await conn.close()


@pytest.mark.parametrize(("overflow", "kept"), [
    ("drop_oldest", list(range(91, 101))),
    ("block", list(range(91, 101))),  # a radio link cannot be paused: block drops the oldest
    ("drop_newest", list(range(1, 11))),
])
def test_flooded_source_follows_the_overflow_policy_and_counts_drops(overflow: str, kept: list[int]) -> None:
    deliver, status = run(flood(overflow))
    assert deliver.stamps == [0, *kept]
    assert deliver.drops == 90 and status["dropped"] == 90
    assert status["received"] == 101 and status["queued"] == 0
    assert status["overflow"] == ("drop_oldest" if overflow == "block" else overflow)


def test_stop_hands_queued_telemetry_to_the_route() -> None:
    deliver, status = run(flood("drop_oldest", stop_while_queued=True))
    assert deliver.stamps == [0, *range(91, 101)], "what was queued at stop is delivered, not thrown away"
    assert status["dropped"] == 90 and status["queued"] == 0


def test_unsettled_messages_are_counted_as_dropped() -> None:
    async def scenario() -> dict[str, Any]:
        conn = mavlink.TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
        await conn.open()
        peer = await UdpPeer.bind()

        async def refuse(inbound: Inbound) -> None:
            raise RuntimeError("route stopping")

        deliver = FunctionDeliver(refuse)
        source = conn.source("telemetry", {"message": "GLOBAL_POSITION_INT"})
        await source.start(deliver)
        try:
            peer.send(positions(packer(1, 1), range(5)), bound_port(conn))
            await wait_for(lambda: deliver.drops == 5, 5)
            return source.status()
        finally:
            await source.stop()
            peer.close()
            await conn.close()

    assert run(scenario())["dropped"] == 5


# -- tunnel: acknowledged to the sender only once the route settled it ------------------------


class HeldBatches(FunctionDeliver):
    """Holds each batch until ``release(settled)``; single messages are not how tunnels deliver."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: asyncio.Queue[tuple[list[Inbound], asyncio.Future[bool]]] = asyncio.Queue()

    async def __call__(self, inbound: Inbound) -> None:
        raise AssertionError("the tunnel settles with Deliver.batch")

    async def batch(self, inbounds: Any) -> list[bool]:
        verdict: asyncio.Future[bool] = asyncio.get_running_loop().create_future()
        self.batches.put_nowait((list(inbounds), verdict))
        return [await verdict] * len(inbounds)


def test_tunnel_message_is_acknowledged_only_after_the_route_settled_it() -> None:
    from tests.endpoints.mavlink.test_mavlink_tunnel import is_delivered_ack, outbound, udp_pair

    async def scenario() -> None:
        acks: list[Any] = []

        def watch(direction: str, msg: Any) -> bool:
            if is_delivered_ack(direction, msg):
                acks.append(msg)
            return False

        gcs, uav, _ = await udp_pair(drop=watch)
        deliver = HeldBatches()
        source = uav.source("json", {"json_tunnel": True})
        sink = gcs.sink("json", {"json_tunnel": True, "target_system": 1})
        await source.start(deliver)
        try:
            body = b'{"n":1,"pad":"' + b"x" * 400 + b'"}'
            sending = asyncio.create_task(sink.send(outbound(body)))
            inbounds, verdict = await asyncio.wait_for(deliver.batches.get(), 5)
            assert [i.body for i in inbounds] == [body]
            await asyncio.sleep(0.3)  # quiet window: the sender's retransmissions meanwhile earn no DELIVERED
            assert not sending.done() and acks == [] and uav.stats.get("tunnel_delivered", 0) == 0
            verdict.set_result(False)  # not settled: no acknowledgement, the sender sends again
            inbounds, verdict = await asyncio.wait_for(deliver.batches.get(), 10)
            assert [i.body for i in inbounds] == [body] and not sending.done() and acks == []
            assert uav.stats["tunnel_deliver_failed"] == 1
            verdict.set_result(True)
            await asyncio.wait_for(sending, 10)
            assert len(acks) >= 1 and uav.stats["tunnel_delivered"] == 1
        finally:
            await source.stop()
            await gcs.close()
            await uav.close()

    run(scenario())


# -- errors at the edge: permanent failures are MessageRejected, silence is EndpointError -----


def test_encode_failures_are_rejected_and_an_oversize_tunnel_message_too() -> None:
    async def scenario() -> None:
        peer = await UdpPeer.bind()
        conn = mavlink.TRANSPORT.connect("radio", {"url": f"udpout:127.0.0.1:{peer.port}", "heartbeat": 0})
        await conn.open()
        try:
            sink = conn.sink("cmd", {"message": "COMMAND_LONG", "target_system": 1})
            for fields in ({"command": 400, "param1": 1e39}, {"command": 400, "param1": 10**400},
                           {"command": 400, "param9": 1}, {"command": -1}):
                with pytest.raises(MessageRejected):
                    await sink.send(Outbound(b"{}", fields, fields, "m", {}))
            unpackable = mavlink2.MAVLink_command_long_message(1, 1, 400, 0, 1e39, 0, 0, 0, 0, 0, 0)
            with pytest.raises(MessageRejected, match="cannot encode"):
                await conn.send_message(unpackable)
            tunnel = conn.sink("json", {"json_tunnel": True})
            with pytest.raises(MessageRejected, match="exceeds"):
                await tunnel.send(Outbound(bytes(40_000), None, None, "m", {}))
            assert conn.stats["frames_sent"] == 0
        finally:
            peer.close()
            await conn.close()

    run(scenario())


# -- the status shows per-connection link counters and per-route drops --------------------------

STATUS_ROUTES = """
dead_letters: {{spool_dir: {spool}}}
connections:
  radio: {{mavlink: "udpin:127.0.0.1:{port}", heartbeat: 0}}
  out: {{mavlink: "udpout:127.0.0.1:{peer}", heartbeat: 0}}
routes:
  - name: telemetry
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{time_boot_ms: time_boot_ms, value: relative_alt}}"
    schema: raw_json
    overflow: drop_oldest
    sink: {{mavlink: {{connection: out, message: NAMED_VALUE_INT}}}}
"""


def test_engine_status_shows_link_rejections_and_source_counters(tmp_path: Path, schemas_dir: Path) -> None:
    from rich.console import Console

    from engine.ops.admin import status_document
    from engine.ops.opsview import status_table
    from engine.running.runtime import Engine
    from tests.support.udp_vehicle import free_udp_port

    async def scenario() -> dict[str, Any]:
        peer = await UdpPeer.bind()
        port = free_udp_port()
        routes = tmp_path / "routes"
        routes.mkdir()
        (routes / "radio.yaml").write_text(STATUS_ROUTES.format(spool=tmp_path / "spool", port=port, peer=peer.port))
        engine = Engine(routes, schemas_dir)
        await engine.start()
        try:
            mav = packer(1, 1)
            corrupt = bytearray(positions(mav, range(1)))
            corrupt[-1] ^= 0xFF
            peer.send(positions(mav, range(3)) + bytes(corrupt), port)
            for _ in range(3):
                await peer.expect("NAMED_VALUE_INT", 10)
            await wait_for(lambda: status_document(engine)["connections"]["radio"]["rejected"]["bad_crc"] == 1, 5)
            return status_document(engine)
        finally:
            await engine.stop(drain_timeout=1.0)
            peer.close()

    document = run(scenario())
    radio = document["connections"]["radio"]
    assert radio["protocol"] == "mavlink" and radio["up"]
    assert radio["rejected"]["bad_crc"] == 1 and radio["counters"]["frames_accepted"] == 3
    route = document["routes"]["telemetry"]
    assert route["source"] == {"received": 3, "dropped": 0, "queued": 0, "overflow": "drop_oldest"}
    assert route["dropped"] == 0 and route["delivered"] == 3
    console = Console(width=200, record=True)
    console.print(status_table(document))
    assert "radio: bad_crc 1" in console.export_text()


# -- reload identity comes from the MAVLink package ------------------------------------------------


def test_exclusive_resource_and_key_files_come_from_the_mavlink_transport(tmp_path: Path) -> None:
    from engine.language import identity

    assert not hasattr(identity, "mavlink_exclusive_resource") and not hasattr(identity, "mavlink_key_files")
    transport = mavlink.TRANSPORT
    assert type(transport).exclusive_resource is not Transport.exclusive_resource
    assert transport.exclusive_resource({"url": "udpin:0.0.0.0:14550"}) == "udp:14550"
    assert transport.exclusive_resource({"url": "tcpin:127.0.0.1:5760"}) == "tcp:5760"
    assert transport.exclusive_resource({"url": "udpout:10.0.0.2:14550"}) is None
    assert transport.exclusive_resource({"url": "udpin:0.0.0.0:nope"}) is None, "check reports a bad url"
    key = tmp_path / "key"
    key.write_bytes(bytes(range(32)))
    settings = {"url": "udpin:0.0.0.0:14550", "signing": {"key_file": str(key)}}
    assert list(transport.key_files(settings)) == [str(key)]
    assert list(transport.key_files({"url": "udpin:0.0.0.0:14550", "signing": {"key_env": "K"}})) == []
    before = identity.connection_fingerprint("mavlink", settings)
    key.write_bytes(bytes(range(1, 33)))
    assert identity.connection_fingerprint("mavlink", settings) != before, "a new key reopens the connection"
    assert identity.exclusive_resource("mavlink", settings) == "udp:14550"


def test_closing_a_udpin_connection_frees_its_port_before_close_returns() -> None:
    import socket

    async def scenario() -> None:
        conn = mavlink.TRANSPORT.connect("radio", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
        await conn.open()
        port = bound_port(conn)
        await conn.close()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.bind(("127.0.0.1", port))  # no retry: the old socket is gone

    run(scenario())


# -- check: a MAVLink option the endpoint does not use is an error, with file:line --------------

UNUSED_OPTIONS = """\
dead_letters: {spool_dir: /tmp/rabbitros-unused-spool}
connections:
  radio: {mavlink: "udpin:127.0.0.1:14999", heartbeat: 0}
routes:
  - name: telemetry
    source: {mavlink: {connection: radio, message: GLOBAL_POSITION_INT, payload_type: 43264}}
    schema: raw_json
    sink: {mavlink: {connection: radio, message: NAMED_VALUE_INT, acknowledged: true}}
  - name: goto
    source: {mavlink: {connection: radio, json_tunnel: true, target_system: 1}}
    schema: raw_json
    sink: {mavlink: {connection: radio, message: COMMAND_LONG, home_placeholder: true, retries: 3}}
  - name: echo
    source: {mavlink: {connection: radio, json_tunnel: true}}
    schema: raw_json
    sink: {mavlink: {connection: radio, json_tunnel: true, system_id: 1}}
"""


def test_check_reports_mavlink_options_the_endpoint_does_not_use(
        tmp_path: Path, schemas_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from engine.ops.cli import check

    routes = tmp_path / "routes"
    routes.mkdir()
    (routes / "radio.yaml").write_text(UNUSED_OPTIONS)
    assert check(routes, schemas_dir) != 0
    err = capsys.readouterr().err
    for line, text in ((6, "'payload_type' is not used by a message source: it applies to json_tunnel"),
                       (8, "acknowledged applies to COMMAND_LONG and COMMAND_INT sinks"),
                       (10, "'target_system' is not used by a json_tunnel source"),
                       (12, "'home_placeholder' is not used by a message sink: it applies to mission sinks"),
                       (12, "'retries' is not used by a message sink: it applies to acknowledged commands"),
                       (16, "'system_id' is not used by a json_tunnel sink")):
        assert any(f"radio.yaml:{line}" in row and text in row for row in err.splitlines()), (line, text, err)
