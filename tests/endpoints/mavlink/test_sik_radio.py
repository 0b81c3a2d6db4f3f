"""The SiK pair emulator must pass MAVLink like a SiK pair: intact, slow, lossy, with RADIO_STATUS."""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from rabbitros_sim.sik_radio import (  # noqa: E402
    MAX_AIR_PACKET,
    RADIO_COMPID,
    RADIO_SYSID,
    SikRadioPair,
    sik_packet_length,
)
from rabbitros_sim.vehicle import open_serial  # noqa: E402
from tests.support.repo import REPO

TUNNEL_TYPE = 0xA900
SERIAL_BYTES_PER_S = 57600 / 10


class Port:
    """A client on one radio's serial port: queues frames to write, parses what it reads."""

    def __init__(self, path: str, clock: Callable[[], float], sysid: int = 255) -> None:
        self.fd = open_serial(path)
        self.clock = clock
        self.mav = mavlink2.MAVLink(None, sysid, 190)
        self.mav.robust_parsing = True
        self.out = bytearray()
        self.raw_bytes = 0
        self.received: list[tuple[float, Any]] = []

    def frame(self, msg: Any) -> bytes:
        data: bytes = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return data

    def send(self, msg: Any) -> None:
        self.out += self.frame(msg)

    def pump(self, readable: bool, writable: bool) -> None:
        if writable and self.out:
            try:
                del self.out[:os.write(self.fd, self.out)]
            except BlockingIOError:
                pass
        if readable:
            chunk = os.read(self.fd, 4096)
            self.raw_bytes += len(chunk)
            now = self.clock()
            self.received.extend((now, m) for m in self.mav.parse_buffer(chunk) or ())

    def of_type(self, kind: str) -> list[tuple[float, Any]]:
        return [(t, m) for t, m in self.received if m.get_type() == kind]

    def close(self) -> None:
        os.close(self.fd)


def run_for(ports: list[Port], seconds: float, step: Callable[[float], None] | None = None) -> None:
    """Drive all ports for ``seconds``, calling ``step(now)`` each turn to queue more traffic."""
    clock = ports[0].clock
    end = clock() + seconds
    while (now := clock()) < end:
        if step:
            step(now)
        readable, writable, _ = select.select(
            [p.fd for p in ports], [p.fd for p in ports if p.out], [], min(0.01, end - now))
        for p in ports:
            p.pump(p.fd in readable, p.fd in writable)


def tunnel(port: Port, index: int, size: int = 100) -> Any:
    """A TUNNEL whose payload starts with its index and ends in zeros (MAVLink 2 truncates them)."""
    payload = index.to_bytes(2, "little") + bytes((index * 7 + k) % 251 for k in range(size - 6)) + bytes(4)
    return port.mav.tunnel_encode(1, 191, TUNNEL_TYPE, size, list(payload) + [0] * (128 - size))


def payload_of(msg: Any) -> bytes:
    return bytes(msg.payload[:msg.payload_length])


def expected_payload(index: int, size: int = 100) -> bytes:
    return index.to_bytes(2, "little") + bytes((index * 7 + k) % 251 for k in range(size - 6)) + bytes(4)


PairFactory = Callable[..., tuple[SikRadioPair, Port, Port]]


@pytest.fixture
def pair_factory(tmp_path: Path) -> Iterator[PairFactory]:
    pairs: list[SikRadioPair] = []
    ports: list[Port] = []

    def make(**kwargs: Any) -> tuple[SikRadioPair, Port, Port]:
        pair = SikRadioPair(str(tmp_path / "radio_a"), str(tmp_path / "radio_b"), **kwargs).start()
        pairs.append(pair)
        a, b = Port(pair.link_a, pair.elapsed), Port(pair.link_b, pair.elapsed, sysid=1)
        ports.extend((a, b))
        return pair, a, b

    yield make
    for port in ports:
        port.close()
    for pair in pairs:
        pair.stop()


def test_packet_forming_keeps_mavlink_frames_whole() -> None:
    mav = mavlink2.MAVLink(None, 1, 1)
    frame = mav.tunnel_encode(1, 1, TUNNEL_TYPE, 100, [1] * 100 + [0] * 28).pack(mav)
    assert len(frame) == 117
    assert sik_packet_length(frame * 3, room=252) == 234
    assert sik_packet_length(frame * 3, room=200) == 117
    assert sik_packet_length(frame * 3, room=100) == 0, "a frame waits for a window it fits in"
    assert sik_packet_length(frame[:60], room=252) == 0, "a half-written frame waits"
    assert sik_packet_length(frame[:60], room=252, flush=True) == 60, "unless the line went quiet"
    assert sik_packet_length(b"\x01\x02\x03" + frame, room=252) == 3 + 117, "non-MAVLink bytes go raw"

    mav.signing.secret_key = bytes(32)
    mav.signing.sign_outgoing = True
    signed = mav.heartbeat_encode(2, 0, 0, 0, 4).pack(mav)
    assert sik_packet_length(signed * 2, room=252) == 2 * len(signed) == 2 * (9 + 12 + 13)

    big = mav.v2_extension_encode(0, 1, 1, 0, list(range(1, 250))).pack(mav)
    assert len(big) > MAX_AIR_PACKET
    assert sik_packet_length(frame + big, room=252) == 117, "frames before a too-big one go alone"
    assert sik_packet_length(big, room=252) == MAX_AIR_PACKET, "a too-big frame loses framing"


def test_frames_cross_intact_both_ways_without_loss(pair_factory: PairFactory) -> None:
    pair, a, b = pair_factory(loss=0.0, seed=1)
    count = 30
    sent = {"n": 0}

    def step(now: float) -> None:
        while sent["n"] < count and now >= sent["n"] / 15:
            a.send(tunnel(a, sent["n"]))
            b.send(tunnel(b, 1000 + sent["n"], size=60))
            sent["n"] += 1

    run_for([a, b], count / 15 + 1.5, step)

    at_b = [payload_of(m) for _, m in b.of_type("TUNNEL")]
    at_a = [payload_of(m) for _, m in a.of_type("TUNNEL")]
    assert at_b == [expected_payload(i) for i in range(count)]
    assert at_a == [expected_payload(1000 + i, 60) for i in range(count)]
    assert not a.of_type("BAD_DATA") and not b.of_type("BAD_DATA")
    stats = pair.stats()
    assert stats["a"].air_packets_lost == stats["b"].air_packets_lost == 0
    assert stats["a"].serial_rx_dropped == stats["b"].serial_rx_dropped == 0


def test_throughput_is_bounded_by_the_radio(pair_factory: PairFactory) -> None:
    pair, a, b = pair_factory(radio_status_interval=0.5, seed=2)
    index = {"n": 0}

    def flood(now: float) -> None:
        while now < 3.0 and len(a.out) < 4096:
            a.send(tunnel(a, index["n"] % 60000))
            index["n"] += 1

    run_for([a, b], 3.5, flood)

    data = [t for t, _ in b.received]
    span = data[-1] - data[0]
    rate = b.raw_bytes / span
    assert 0.3 * SERIAL_BYTES_PER_S < rate < SERIAL_BYTES_PER_S, rate
    good = sum(len(m.get_msgbuf()) for _, m in b.of_type("TUNNEL")) / span
    assert good > 0.2 * SERIAL_BYTES_PER_S, good
    stats = pair.stats()["a"]
    assert stats.serial_rx_dropped > 0, "the 2 KB radio buffer must overflow under a flood"
    assert stats.serial_rx_bytes / 3.5 < SERIAL_BYTES_PER_S * 1.05
    assert min(m.txbuf for _, m in a.of_type("RADIO_STATUS")) < 50, "txbuf must show the full buffer"


def test_loss_drops_whole_frames_and_keeps_the_rest_intact(pair_factory: PairFactory) -> None:
    pair, a, b = pair_factory(loss=0.3, seed=7)
    count = 60
    sent = {"n": 0}

    def step(now: float) -> None:
        while sent["n"] < count and now >= sent["n"] / 20:
            a.send(tunnel(a, sent["n"]))
            sent["n"] += 1

    run_for([a, b], count / 20 + 1.0, step)

    got = [payload_of(m) for _, m in b.of_type("TUNNEL")]
    assert 0 < len(got) < count
    indices = [int.from_bytes(p[:2], "little") for p in got]
    assert indices == sorted(set(indices))
    assert all(p == expected_payload(i) for i, p in zip(indices, got))
    assert not b.of_type("BAD_DATA"), "frame-aligned packets must not leave partial frames"
    assert 0.1 < 1 - len(got) / count < 0.6
    stats = pair.stats()["a"]
    assert stats.air_packets_lost > 0 and stats.air_packets_outage == 0


def test_outage_passes_nothing(pair_factory: PairFactory) -> None:
    pair, a, b = pair_factory(outages=[(1.0, 1.0)], radio_status_interval=0.25, seed=3)
    sent_at: dict[int, float] = {}

    def step(now: float) -> None:
        n = len(sent_at)
        if now < 3.0 and now >= n / 20:
            a.send(tunnel(a, n, size=40))
            sent_at[n] = now

    run_for([a, b], 3.5, step)

    arrivals = {int.from_bytes(payload_of(m)[:2], "little"): t for t, m in b.of_type("TUNNEL")}
    times = sorted(arrivals.values())
    assert any(t < 1.0 for t in times) and any(t > 2.0 for t in times)
    assert not [t for t in times if 1.1 <= t <= 2.0], "something crossed during the outage"
    mid_outage = [i for i, t in sent_at.items() if 1.05 <= t <= 1.7]
    assert mid_outage and not set(mid_outage) & set(arrivals), "frames sent into the outage must be lost"
    assert [t for t, _ in b.of_type("RADIO_STATUS") if 1.1 <= t <= 2.0], "local RADIO_STATUS continues"
    assert pair.stats()["a"].air_packets_outage > 0
    assert max(m.rxerrors for _, m in b.of_type("RADIO_STATUS")) > 0


def test_radio_status_is_injected_on_both_sides(pair_factory: PairFactory) -> None:
    _, a, b = pair_factory(radio_status_interval=0.3, seed=4)
    run_for([a, b], 1.5)
    for port in (a, b):
        statuses = [m for _, m in port.of_type("RADIO_STATUS")]
        assert len(statuses) >= 3
        for m in statuses:
            assert (m.get_srcSystem(), m.get_srcComponent()) == (RADIO_SYSID, RADIO_COMPID)
            assert m.get_msgbuf()[0] == 0xFD and not m.get_signed()
            assert m.txbuf == 100 and m.fixed == 0
            assert m.rssi > m.noise and m.remrssi > m.remnoise
        assert [m.get_seq() for m in statuses] == list(range(len(statuses)))
    assert not a.of_type("BAD_DATA") and not b.of_type("BAD_DATA")


def test_cli_runs_as_a_process_and_stops_on_sigterm(tmp_path: Path) -> None:
    link_a, link_b = tmp_path / "gcs", tmp_path / "uav"
    proc = subprocess.Popen(
        ["timeout", "-s", "KILL", "20", sys.executable, "-m", "rabbitros_sim.sik_radio",
         "--link-a", str(link_a), "--link-b", str(link_b), "--radio-status-interval", "0.2",
         "--seed", "5", "--loss", "0"],
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=subprocess.PIPE,
        start_new_session=True, text=True)
    try:
        assert proc.stdout is not None
        assert select.select([proc.stdout], [], [], 10)[0], "no ready line"
        ready = json.loads(proc.stdout.readline())
        assert ready["event"] == "ready" and os.readlink(link_a) == ready["device_a"]
        start = time.monotonic()
        a = Port(str(link_a), time.monotonic)
        b = Port(str(link_b), time.monotonic, sysid=1)
        try:
            a.send(tunnel(a, 42))
            run_for([a, b], 1.0)
        finally:
            a.close()
            b.close()
        assert [payload_of(m) for _, m in b.of_type("TUNNEL")] == [expected_payload(42)]
        assert a.of_type("RADIO_STATUS") and b.of_type("RADIO_STATUS")
        assert time.monotonic() - start < 5
        os.kill(proc.pid, signal.SIGTERM)
        out, _ = proc.communicate(timeout=5)
        assert proc.returncode == 0
        stopped = json.loads(out.strip().splitlines()[-1])
        assert stopped["stats"]["a"]["air_packets"] >= 1
        assert not link_a.exists() and not link_b.exists()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
