"""MAVLink endpoint over real sockets and pseudo-terminals, with real pymavlink peers."""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections.abc import Awaitable
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import EndpointError, Inbound, MessageRejected, Outbound  # noqa: E402
from engine.endpoints.mavlink.connection import MavlinkConnection  # noqa: E402
from tests.support.waiting import wait_for
from tests.support.collecting_deliver import CollectingDeliver

TRANSPORT = mavlink.TRANSPORT
KEY = bytes(range(32))
WRONG_KEY = bytes(range(1, 33))


def run(coro: Awaitable[Any], timeout: float = 30.0) -> Any:
    async def bounded() -> Any:
        return await asyncio.wait_for(coro, timeout)

    return asyncio.run(bounded())


def outbound(fields: Any = None, body: bytes = b"{}") -> Outbound:
    return Outbound(body=body, canonical=None, fields=fields, message_id="m", meta={})


def bound_port(connection: MavlinkConnection) -> int:
    """The port a ``udpin``/``tcpin`` connection bound (it asked for port 0)."""
    address = connection.address
    assert address is not None, f"connection {connection.name} is bound to no address"
    return address[1]


class UdpPeer(asyncio.DatagramProtocol):
    """A plain socket speaking MAVLink through pymavlink, standing in for a vehicle or a GCS."""

    def __init__(self) -> None:
        self.frames: asyncio.Queue[Any] = asyncio.Queue()
        self.raw: list[bytes] = []
        self.parser = mavlink2.MAVLink(None)
        self.transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def bind(cls) -> UdpPeer:
        loop = asyncio.get_running_loop()
        _, peer = await loop.create_datagram_endpoint(cls, local_addr=("127.0.0.1", 0))
        return peer

    def connection_made(self, transport: Any) -> None:
        self.transport = transport

    @property
    def port(self) -> int:
        assert self.transport is not None
        return self.transport.get_extra_info("sockname")[1]

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.raw.append(data)
        for msg in self.parser.parse_buffer(data) or ():
            self.frames.put_nowait(msg)

    def send(self, data: bytes, port: int) -> None:
        assert self.transport is not None
        self.transport.sendto(data, ("127.0.0.1", port))

    async def expect(self, name: str, timeout: float = 3.0) -> Any:
        async def first() -> Any:
            while True:
                msg = await self.frames.get()
                if msg.get_type() == name:
                    return msg

        return await asyncio.wait_for(first(), timeout)

    def close(self) -> None:
        assert self.transport is not None
        self.transport.close()


def packer(sysid: int, compid: int, key: bytes | None = None, link_id: int = 0) -> mavlink2.MAVLink:
    mav = mavlink2.MAVLink(None, sysid, compid)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.link_id = link_id
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = mavlink.signing_now()
    return mav


def gpi(mav: mavlink2.MAVLink, lat: int = 473977418) -> bytes:
    msg = mav.global_position_int_encode(123456, lat, 85455440, 488123, 12345, -153, 250, 31, 9000)
    data = msg.pack(mav)
    mav.seq = (mav.seq + 1) % 256
    return data


# -- static checks ----------------------------------------------------------------------------


def test_parse_address_variants() -> None:
    assert mavlink.parse_address("udpin:0.0.0.0:14550") == mavlink.Address("udpin", "0.0.0.0", 14550)
    assert mavlink.parse_address("udp::14550").kind == "udpin"
    assert mavlink.parse_address("tcp:10.0.0.2:5760") == mavlink.Address("tcp", "10.0.0.2", 5760)
    assert mavlink.parse_address("/dev/ttyUSB0", 57600) == mavlink.Address("serial", device="/dev/ttyUSB0", baud=57600)
    assert mavlink.parse_address("/dev/ttyACM0,115200").baud == 115200
    for bad in ("udpin:host", "udpout::14550", "ttyUSB0", "udpinn:1.2.3.4:5", "tcp:h:99999", ""):
        with pytest.raises(ValueError):
            mavlink.parse_address(bad)
    with pytest.raises(ValueError, match="baud"):
        mavlink.parse_address("/dev/ttyUSB0", 12345)


def test_check_connection_reports_each_problem(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    check = TRANSPORT.check_connection
    assert list(check({"url": "udpin:0.0.0.0:14550"})) == []
    assert list(check({"url": "/dev/ttyUSB0", "baud": 57600, "source_system": 1, "source_component": 191})) == []
    assert [k for k, _ in check({"url": "nonsense"})] == ["url"]
    assert [k for k, _ in check({"url": "/dev/ttyUSB0", "baud": 12345})] == ["baud"]
    assert [k for k, _ in check({"url": "udpin::1", "source_system": 0})] == ["source_system"]
    assert [k for k, _ in check({"url": "udpin::1", "bogus": 1})] == ["bogus"]
    monkeypatch.delenv("RABBITROS_TEST_KEY", raising=False)
    problems = list(check({"url": "udpin::1", "signing": {"key_env": "RABBITROS_TEST_KEY"}}))
    assert problems and problems[0][0] == "signing" and "missing" in problems[0][1]
    problems = list(check({"url": "udpin::1", "signing": {"key_file": str(tmp_path / "absent.key")}}))
    assert problems and "missing" in problems[0][1]
    (tmp_path / "short.key").write_bytes(b"abc")
    assert list(check({"url": "udpin::1", "signing": {"key_file": str(tmp_path / "short.key")}}))
    (tmp_path / "hex.key").write_text(KEY.hex() + "\n")
    assert list(check({"url": "udpin::1", "signing": {"key_file": str(tmp_path / "hex.key"), "link_id": 3}})) == []
    monkeypatch.setenv("RABBITROS_TEST_KEY", KEY.hex())
    assert list(check({"url": "udpin::1", "signing": {"key_env": "RABBITROS_TEST_KEY"}})) == []
    assert [k for k, _ in check({"url": "udpin::1", "tunnel": {"fragment_size": 500}})] == ["tunnel"]
    with pytest.raises(EndpointError, match="url"):
        TRANSPORT.connect("bad", {"url": "nonsense"})


def test_check_source_and_sink_options() -> None:
    assert list(TRANSPORT.check_source({"message": "GLOBAL_POSITION_INT", "system_id": 1}, None)) == []
    assert [k for k, _ in TRANSPORT.check_source({"message": "GLOBAL_POSITION_INTT"}, None)] == ["message"]
    assert [k for k, _ in TRANSPORT.check_source({"message": "ATTITUDE", "system_id": 300}, None)] == ["system_id"]
    assert list(TRANSPORT.check_source({"json_tunnel": True, "payload_type": 43264}, None)) == []
    assert [k for k, _ in TRANSPORT.check_source({"json_tunnel": True, "payload_type": 200}, None)] == ["payload_type"]

    good = "{command: `400`, param1: `1`, confirmation: `0`}"
    assert list(TRANSPORT.check_sink({"message": "COMMAND_LONG", "target_system": 1}, good)) == []
    assert list(TRANSPORT.check_sink({"message": "COMMAND_LONG"}, "payload")) == []
    problems = list(TRANSPORT.check_sink({"message": "COMMAND_LONG"}, "{command: `400`, param8: `1`}"))
    assert len(problems) == 1 and "param8" in problems[0][1]
    [(_, typo)] = TRANSPORT.check_sink({"message": "COMMAND_LONG"}, "{command: `400`, parma1: `1`}")
    assert "sets 'parma1', which COMMAND_LONG does not have; did you mean 'param1'?" in typo
    [(_, null)] = TRANSPORT.check_sink({"message": "COMMAND_LONG"}, "{command: `400`, param1: `null`}")
    assert null.startswith("sink mapping sets 'param1' to `null`: every message would be refused; a MAVLink field is never guessed")
    [(_, unused)] = TRANSPORT.check_sink({"mission": "upload"}, "{item: x}")
    names = list(TRANSPORT.check_sink({"message": "COMMAND_INT"}, "{command: mav_enum_value('COMPONENT_ARM_DISARN', "
                                      "'MAV_CMD'), frame: 'GLOBAL_RELATIVE_ALT_INTT'}"))
    assert [text for _, text in names] == [
        "sink mapping 'command': 'COMPONENT_ARM_DISARN' is not a MAV_CMD name; did you mean 'MAV_CMD_COMPONENT_ARM_DISARM'?",
        "sink mapping 'frame': 'GLOBAL_RELATIVE_ALT_INTT' is not a MAV_FRAME name; "
        "did you mean 'MAV_FRAME_GLOBAL_RELATIVE_ALT_INT'?"]
    assert list(TRANSPORT.check_sink({"message": "COMMAND_INT"}, "{command: 'DO_REPOSITION', frame: mav_enum_value("
                                     "'GLOBAL_INT', 'MAV_FRAME'), param4: nan()}")) == []
    assert unused.endswith("'item' is not used; did you mean 'items'?")
    assert [k for k, _ in TRANSPORT.check_sink({"message": "COMMAND_LONGG"}, None)] == ["message"]
    assert [k for k, _ in TRANSPORT.check_sink({"message": "HEARTBEAT", "target_system": 1}, None)] == ["target_system"]
    assert list(TRANSPORT.check_sink({}, None))
    assert list(TRANSPORT.check_sink({"json_tunnel": True, "target_system": 1}, None)) == []


def test_build_message_defaults_types_and_errors() -> None:
    cls = mavlink.MESSAGES["COMMAND_LONG"]
    msg = mavlink.build_message(cls, {"command": 400, "param1": 1, "param2": 21196.0}, {"target_system": 1})
    assert (msg.target_system, msg.target_component, msg.command, msg.param1, msg.param7) == (1, 0, 400, 1.0, 0.0)
    text = mavlink.build_message(mavlink.MESSAGES["STATUSTEXT"], {"severity": 6, "text": "hello"})
    assert text.text == "hello"
    tunnel = mavlink.build_message(mavlink.MESSAGES["TUNNEL"], {"payload": [1, 2, 3], "payload_length": 3})
    assert len(tunnel.payload) == 128 and tunnel.payload[:4] == [1, 2, 3, 0]
    with pytest.raises(MessageRejected, match="no field"):
        mavlink.build_message(cls, {"command": 400, "bogus": 1})
    with pytest.raises(MessageRejected, match="outside"):
        mavlink.build_message(cls, {"command": 70000})
    with pytest.raises(MessageRejected, match="number"):
        mavlink.build_message(cls, {"command": 400, "confirmation": "1"})
    with pytest.raises(MessageRejected, match="object"):
        mavlink.build_message(cls, [1, 2])


def test_build_message_refuses_nulls_and_takes_enum_names() -> None:
    """A null is never a 0 (param1 0 of COMPONENT_ARM_DISARM disarms); a field left out is 0;
    NaN passes where the mapping says nan(); an enum field takes a name, a misspelt one gets
    the close names, as does a field the message lacks."""
    cls = mavlink.MESSAGES["COMMAND_LONG"]
    for fields, named in (({"command": 400, "param1": None}, "field 'param1' is null"),
                          ({"command": None}, "field 'command' is null"),
                          ({"command": 400, "param1": None, "param2": None}, "fields 'param1', 'param2' are null")):
        with pytest.raises(MessageRejected, match=named):
            mavlink.build_message(cls, fields, {"target_system": 1})
    with pytest.raises(MessageRejected, match=r"field 'target_system' is null"):
        mavlink.build_message(cls, {"command": 400, "param1": 1, "target_system": None}, {"target_system": 1})
    with pytest.raises(MessageRejected, match=r"field 'payload\[1\]' is null"):
        mavlink.build_message(mavlink.MESSAGES["TUNNEL"], {"payload": [1, None], "payload_length": 2})
    with pytest.raises(MessageRejected, match="field 'text' is null"):
        mavlink.build_message(mavlink.MESSAGES["STATUSTEXT"], {"severity": 6, "text": None})
    left_out = mavlink.build_message(cls, {"command": "MAV_CMD_COMPONENT_ARM_DISARM", "param1": 1})
    assert (left_out.command, left_out.param1, left_out.param2, left_out.target_system) == (400, 1.0, 0.0, 0)
    unset = mavlink.build_message(cls, {"command": "DO_REPOSITION", "param4": math.nan, "param5": 1.5})
    assert unset.command == mavlink2.MAV_CMD_DO_REPOSITION and math.isnan(unset.param4) and unset.param5 == 1.5
    with pytest.raises(MessageRejected, match=r"'MAV_CMD_COMPONENT_ARM_DISARN' is not a MAV_CMD name; "
                                              r"did you mean 'MAV_CMD_COMPONENT_ARM_DISARM'\?"):
        mavlink.build_message(cls, {"command": "MAV_CMD_COMPONENT_ARM_DISARN", "param1": 1})
    with pytest.raises(MessageRejected, match=r"no field\(s\) 'paramm1'; did you mean 'param1'\?"):
        mavlink.build_message(cls, {"command": 400, "paramm1": 1})
    with pytest.raises(MessageRejected, match="not an integer"):
        mavlink.build_message(cls, {"command": math.nan})


# -- sources and sinks over UDP -------------------------------------------------------------------


def test_source_delivers_fields_and_filters_by_system() -> None:
    async def scenario() -> None:
        conn = TRANSPORT.connect("gcs", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
        await conn.open()
        peer = await UdpPeer.bind()
        got = CollectingDeliver()
        everything = CollectingDeliver()
        source = conn.source("telemetry", {"message": "GLOBAL_POSITION_INT", "system_id": 1})
        raw_source = conn.source("all", {})
        await source.start(got)
        await raw_source.start(everything)
        try:
            vehicle1, vehicle2 = packer(1, 1), packer(2, 1)
            port = bound_port(conn)
            chunk = gpi(vehicle2, lat=1) + gpi(vehicle1) + vehicle1.heartbeat_encode(2, 3, 0, 0, 4, 3).pack(vehicle1)
            peer.send(chunk, port)
            await got.wait_for(1)
            await everything.wait_for(3)
            await asyncio.sleep(0.1)  # quiet window: a second item for the route would arrive now
            assert len(got.items) == 1
            item = got.items[0]
            assert item.body is None
            assert item.fields == {
                "time_boot_ms": 123456, "lat": 473977418, "lon": 85455440, "alt": 488123,
                "relative_alt": 12345, "vx": -153, "vy": 250, "vz": 31, "hdg": 9000,
            }
            assert item.meta == {"message": "GLOBAL_POSITION_INT", "system_id": 1, "component_id": 1, "connection": "gcs", "signed": False}
            assert [i.meta["message"] for i in everything.items] == ["GLOBAL_POSITION_INT", "GLOBAL_POSITION_INT", "HEARTBEAT"]
            assert conn.stats["frames_accepted"] == 3 and conn.stats["bad_crc"] == 0
            corrupt = bytearray(gpi(vehicle1))
            corrupt[-1] ^= 0xFF
            peer.send(bytes(corrupt), port)
            await wait_for(lambda: conn.stats["bad_crc"] == 1)
        finally:
            await source.stop()
            await raw_source.stop()
            peer.close()
            await conn.close()

    run(scenario())


def test_sources_of_one_vehicle_each_hear_only_theirs_and_stop_hearing_when_stopped() -> None:
    """Per-vehicle sources on one link are listened to by system id (connection.py ``listen``):
    each gets its own vehicle's messages only; a stopped one gets nothing more while the
    other and a source of every vehicle keep theirs."""
    async def scenario() -> None:
        conn = TRANSPORT.connect("gcs", {"url": "udpin:127.0.0.1:0", "heartbeat": 0})
        await conn.open()
        peer = await UdpPeer.bind()
        got1, got2, every = CollectingDeliver(), CollectingDeliver(), CollectingDeliver()
        one = conn.source("uav1", {"message": "GLOBAL_POSITION_INT", "system_id": 1})
        two = conn.source("uav2", {"message": "GLOBAL_POSITION_INT", "system_id": 2})
        both = conn.source("all", {"message": "GLOBAL_POSITION_INT"})
        for source, collector in ((one, got1), (two, got2), (both, every)):
            await source.start(collector)
        try:
            vehicle1, vehicle2 = packer(1, 1), packer(2, 1)
            port = bound_port(conn)
            peer.send(gpi(vehicle2, lat=2) + gpi(vehicle1, lat=1) + gpi(vehicle2, lat=3), port)
            await every.wait_for(3)
            await got2.wait_for(2)
            await got1.wait_for(1)
            assert [fields["lat"] for fields in got1.fields()] == [1]
            assert [fields["lat"] for fields in got2.fields()] == [2, 3]
            await one.stop()
            peer.send(gpi(vehicle1, lat=4) + gpi(vehicle2, lat=5), port)
            await every.wait_for(5)
            await got2.wait_for(3)
            assert [fields["lat"] for fields in got1.fields()] == [1]
            assert [fields["lat"] for fields in got2.fields()] == [2, 3, 5]
            assert [fields["lat"] for fields in every.fields()] == [2, 1, 3, 4, 5]
        finally:
            await two.stop()
            await both.stop()
            peer.close()
            await conn.close()

    run(scenario())


def test_sink_encodes_command_long_from_fields() -> None:
    async def scenario() -> None:
        peer = await UdpPeer.bind()
        conn = TRANSPORT.connect("radio", {"url": f"udpout:127.0.0.1:{peer.port}", "source_system": 250,
                                           "source_component": 191, "heartbeat": 0})
        await conn.open()
        try:
            sink = conn.sink("arm", {"message": "COMMAND_LONG", "target_system": 1, "target_component": 1})
            await sink.send(outbound({"command": 400, "param1": 1.0, "confirmation": 2}))
            msg = await peer.expect("COMMAND_LONG")
            assert (msg.target_system, msg.target_component, msg.command, msg.confirmation) == (1, 1, 400, 2)
            assert (msg.param1, msg.param2, msg.param7) == (1.0, 0.0, 0.0)
            header = msg.get_header()
            assert (header.srcSystem, header.srcComponent) == (250, 191)
            with pytest.raises(EndpointError, match="no field"):
                await sink.send(outbound({"command": 400, "param9": 1}))
            with pytest.raises(EndpointError):
                await sink.send(outbound({"command": -1}))
            assert conn.stats["frames_sent"] == 1
        finally:
            peer.close()
            await conn.close()

    run(scenario())


def test_tcp_server_and_client_share_messages() -> None:
    async def scenario() -> None:
        server = TRANSPORT.connect("srv", {"url": "tcpin:127.0.0.1:0", "heartbeat": 0})
        await server.open()
        client = TRANSPORT.connect("cli", {"url": f"tcp:127.0.0.1:{bound_port(server)}", "source_system": 1,
                                           "heartbeat": 0})
        await client.open()
        got = CollectingDeliver()
        source = server.source("r", {"message": "COMMAND_LONG"})
        await source.start(got)
        try:
            sink = client.sink("r", {"message": "COMMAND_LONG", "target_system": 255})
            for i in range(20):
                await sink.send(outbound({"command": i}))
            await got.wait_for(20)
            assert [fields["command"] for fields in got.fields()] == list(range(20))
        finally:
            await source.stop()
            await client.close()
            await server.close()

    run(scenario())


def test_tcp_client_reconnects_to_a_restarted_server() -> None:
    """The server goes away and comes back on the same port: the client counts the loss and
    reconnects with the engine's backoff (first wait 0.5-1 s), and messages flow again."""
    async def scenario() -> None:
        server = TRANSPORT.connect("srv", {"url": "tcpin:127.0.0.1:0", "heartbeat": 0})
        await server.open()
        port = bound_port(server)
        client = TRANSPORT.connect("cli", {"url": f"tcp:127.0.0.1:{port}", "source_system": 1, "heartbeat": 0})
        await client.open()
        sink = client.sink("r", {"message": "COMMAND_LONG", "target_system": 255})
        try:
            await server.close()
            await wait_for(lambda: client.stats.get("link_lost") == 1, 5, "the client to notice the server left")
            lost_at = time.monotonic()
            server = TRANSPORT.connect("srv", {"url": f"tcpin:127.0.0.1:{port}", "heartbeat": 0})
            await server.open()
            got = CollectingDeliver()
            source = server.source("r", {"message": "COMMAND_LONG"})
            await source.start(got)
            await wait_for(lambda: client.port.ready, 5, "the client to reconnect")
            reconnected_s = time.monotonic() - lost_at
            await sink.send(outbound({"command": 7}))
            await got.wait_for(1)
            await source.stop()
            assert got.fields()[0]["command"] == 7
            assert reconnected_s < 2.5, f"reconnected after {reconnected_s:.2f} s"
        finally:
            await client.close()
            await server.close()

    run(scenario())


# -- serial link over a pseudo-terminal -----------------------------------------------------------


def test_serial_reads_chunks_with_garbage_and_paces_writes() -> None:
    async def scenario() -> None:
        master, slave = os.openpty()
        os.set_blocking(master, False)
        conn = TRANSPORT.connect("radio", {"url": os.ttyname(slave), "baud": 57600, "heartbeat": 0})
        await conn.open()
        got = CollectingDeliver()
        source = conn.source("pos", {"message": "GLOBAL_POSITION_INT"})
        await source.start(got)
        try:
            vehicle = packer(1, 1)
            stream = b"\x00garbage" + b"".join(gpi(vehicle, lat=i) for i in range(50))
            for start in range(0, len(stream), 97):
                os.write(master, stream[start:start + 97])
            await got.wait_for(50)
            assert [fields["lat"] for fields in got.fields()] == list(range(50))
            assert conn.stats["bad_data"] >= 1

            sink = conn.sink("cmd", {"message": "COMMAND_LONG", "target_system": 1})
            started = time.monotonic()
            await asyncio.gather(*(sink.send(outbound({"command": i})) for i in range(40)))
            elapsed = time.monotonic() - started
            sent = conn.stats["bytes_sent"]
            assert elapsed >= 0.9 * (sent - 45) / 5760, (sent, elapsed)
            parser = mavlink2.MAVLink(None)
            received: list[Any] = []

            def all_read() -> bool:
                try:
                    received.extend(parser.parse_buffer(os.read(master, 4096)) or ())
                except BlockingIOError:
                    pass
                return len(received) >= 40

            await wait_for(all_read, 20, "40 COMMAND_LONG at the serial port", lambda: len(received))
            assert [m.command for m in received] == list(range(40))
        finally:
            await source.stop()
            await conn.close()
            os.close(master)
            os.close(slave)

    run(scenario())


# -- signing ----------------------------------------------------------------------------------------


def test_signing_rejects_unsigned_forged_and_replayed_frames(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("RABBITROS_TEST_KEY", KEY.hex())
    stamp_file = tmp_path / "signing.ts"

    async def scenario() -> None:
        conn = TRANSPORT.connect("gcs", {
            "url": "udpin:127.0.0.1:0", "heartbeat": 0,
            "signing": {"key_env": "RABBITROS_TEST_KEY", "link_id": 2, "timestamp_file": str(stamp_file)},
        })
        await conn.open()
        peer = await UdpPeer.bind()
        port = bound_port(conn)
        positions, radio = CollectingDeliver(), CollectingDeliver()
        source = conn.source("pos", {"message": "GLOBAL_POSITION_INT"})
        radio_source = conn.source("radio", {"message": "RADIO_STATUS"})
        await source.start(positions)
        await radio_source.start(radio)
        try:
            good = packer(1, 1, KEY, link_id=5)
            signed = gpi(good, lat=1)
            peer.send(signed, port)
            await positions.wait_for(1)
            assert positions.items[0].meta["signed"] is True

            peer.send(gpi(packer(1, 1), lat=2), port)
            forger = packer(1, 1, WRONG_KEY, link_id=5)
            forger.signing.timestamp = good.signing.timestamp + 10**9
            peer.send(gpi(forger, lat=3), port)
            peer.send(signed, port)
            sik = packer(51, 68)
            peer.send(sik.radio_status_encode(200, 190, 87, 40, 38, 0, 0).pack(sik), port)
            await radio.wait_for(1)
            assert radio.fields()[0]["txbuf"] == 87
            peer.send(gpi(good, lat=4), port)
            await positions.wait_for(2)
            await asyncio.sleep(0.1)  # quiet window: a refused frame would be delivered by now

            assert [fields["lat"] for fields in positions.fields()] == [1, 4]
            stats = conn.stats
            assert (stats["unsigned_rejected"], stats["bad_signature"], stats["replayed"]) == (1, 1, 1)
            assert stats["unsigned_accepted"] == 1

            stale = packer(9, 1, KEY)
            stale.signing.timestamp = mavlink.signing_now() - 100 * 100_000
            peer.send(gpi(stale), port)
            await wait_for(lambda: conn.stats["replayed"] == 2)

            sink = conn.sink("cmd", {"message": "COMMAND_LONG", "target_system": 1})
            await sink.send(outbound({"command": 400}))
            reply = await peer.expect("COMMAND_LONG")
            buf = reply.get_msgbuf()
            assert buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED and buf[-13] == 2
            stamp = int.from_bytes(buf[-12:-6], "little")
            assert stamp >= mavlink.signing_now() - 200_000
            assert int(stamp_file.read_text()) > stamp
        finally:
            await source.stop()
            await radio_source.stop()
            peer.close()
            await conn.close()

    run(scenario())


def test_signing_timestamps_never_go_back_across_restarts(tmp_path: Path) -> None:
    key_file = tmp_path / "link.key"
    key_file.write_bytes(KEY)
    stamp_file = tmp_path / "signing.ts"
    ahead = mavlink.signing_now() + 3600 * 100_000
    stamp_file.write_text(f"{ahead}\n")

    async def one_frame() -> int:
        peer = await UdpPeer.bind()
        conn = TRANSPORT.connect("radio", {"url": f"udpout:127.0.0.1:{peer.port}", "heartbeat": 0,
                                           "signing": {"key_file": str(key_file), "timestamp_file": str(stamp_file)}})
        await conn.open()
        try:
            await conn.sink("c", {"message": "COMMAND_LONG"}).send(outbound({"command": 1}))
            msg = await peer.expect("COMMAND_LONG")
            return int.from_bytes(msg.get_msgbuf()[-12:-6], "little")
        finally:
            peer.close()
            await conn.close()

    first = run(one_frame())
    assert first >= ahead
    second = run(one_frame())
    assert second > first


def test_engines_talk_signed_and_a_wrong_key_is_rejected(tmp_path: Path) -> None:
    (tmp_path / "a.key").write_bytes(KEY)
    (tmp_path / "b.key").write_bytes(WRONG_KEY)

    async def scenario(receiver_key: str) -> tuple[list[Inbound], dict[str, int]]:
        receiver = TRANSPORT.connect("uav", {"url": "udpin:127.0.0.1:0", "source_system": 1, "heartbeat": 0,
                                             "signing": {"key_file": str(tmp_path / receiver_key)}})
        await receiver.open()
        sender = TRANSPORT.connect("gcs", {"url": f"udpout:127.0.0.1:{bound_port(receiver)}", "heartbeat": 0,
                                           "signing": {"key_file": str(tmp_path / "a.key")}})
        await sender.open()
        got = CollectingDeliver()
        source = receiver.source("cmd", {"message": "COMMAND_LONG", "system_id": 255})
        await source.start(got)
        try:
            sink = sender.sink("cmd", {"message": "COMMAND_LONG", "target_system": 1})
            for i in range(5):
                await sink.send(outbound({"command": i}))
            await wait_for(lambda: receiver.stats["frames_received"] == 5, what="5 frames received")
            await wait_for(lambda: len(got.items) + receiver.stats.get("bad_signature", 0) >= 5, 10,
                           "each frame delivered or refused", lambda: (len(got.items), dict(receiver.stats)))
            return got.items, dict(receiver.stats)
        finally:
            await source.stop()
            await sender.close()
            await receiver.close()

    items, stats = run(scenario("a.key"))
    assert [i.fields["command"] for i in items] == list(range(5)) and all(i.meta["signed"] for i in items)
    items, stats = run(scenario("b.key"))
    assert items == [] and stats["bad_signature"] == 5
