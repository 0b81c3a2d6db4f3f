"""One agent flooding a route many agents share, for the fairness test and benchmark.

Ten quiet vehicles (MAVLink systems 1-10) send GLOBAL_POSITION_INT at 10 Hz and one (system 11)
at 1,000 Hz, 100x its rate, to the engine's ``udpin`` link; one route carries them all to a
second link whose writer is capped at 20,000 bytes/s, about 500 of these frames a second: the
sink is slower than the flood, as a radio is. A receiver on the far side of that link reads
each frame's agent (``lat``), sequence (``lon``) and send time (``time_boot_ms``, the sender's
``time.monotonic()`` in ms: one clock, one machine), so what it records is what crossed the
wire. Built on pymavlink alone; the engine runs as a child process, as an operator runs it.
"""

from __future__ import annotations

import contextlib
import socket
import statistics
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink2

from tests.support.engine_process import EngineProcess
from tests.support.udp_vehicle import free_udp_port

QUIET, QUIET_RATE, FLOODER, FLOOD_RATE = range(1, 11), 10.0, 11, 1000.0
SINK_BYTES_PER_S = 20_000
"""The sink link's cap: ~500 GLOBAL_POSITION_INT frames (~40 bytes) a second."""


def _ms() -> int:
    return int(time.monotonic() * 1000) & 0xFFFFFFFF


class Senders(threading.Thread):
    """Every agent's stream from its own UDP socket (a peer each, as vehicles on one link are)."""

    def __init__(self, port: int, seconds: float, scale: float = 1.0) -> None:
        super().__init__(daemon=True)
        self.port, self.seconds, self.scale = port, seconds, scale
        self.sent: dict[int, int] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        agents = {system: (mavlink2.MAVLink(None, srcSystem=system, srcComponent=1),
                           socket.socket(socket.AF_INET, socket.SOCK_DGRAM),
                           (FLOOD_RATE if system == FLOODER else QUIET_RATE) * self.scale)
                  for system in (*QUIET, FLOODER)}
        self.sent = dict.fromkeys(agents, 0)
        target = ("127.0.0.1", self.port)
        started = time.monotonic()
        try:
            while not self.stop.is_set() and (now := time.monotonic()) < started + self.seconds:
                for system, (mav, sock, rate) in agents.items():
                    while self.sent[system] < (now - started) * rate:
                        frame = mav.global_position_int_encode(_ms(), system, self.sent[system], 1, 1, 1, 1, 1, 1)
                        with contextlib.suppress(OSError):
                            sock.sendto(frame.pack(mav), target)
                        self.sent[system] += 1
                time.sleep(0.002)  # pacing: the senders' tick
        finally:
            for _, sock, _ in agents.values():
                sock.close()


class Receiver(threading.Thread):
    """Records ``(agent, sequence, latency ms)`` of every frame the engine's sink link writes."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port: int = self.sock.getsockname()[1]
        self.got: list[tuple[int, int, int]] = []
        self.lock = threading.Lock()
        self.stop = threading.Event()

    def run(self) -> None:
        mav = mavlink2.MAVLink(None)
        with self.sock:
            while not self.stop.is_set():
                try:
                    data = self.sock.recv(65535)
                except (TimeoutError, OSError):
                    continue
                now = _ms()
                for msg in mav.parse_buffer(data) or ():
                    if msg.get_type() == "GLOBAL_POSITION_INT":
                        with self.lock:
                            self.got.append((msg.lat, msg.lon, (now - msg.time_boot_ms) & 0xFFFFFFFF))

    def quiet_count(self) -> int:
        with self.lock:
            return sum(1 for agent, _, _ in self.got if agent != FLOODER)


def route_file(in_port: int, out_port: int, spool: Path, fair: bool, scale: float = 1.0) -> str:
    fairness = "    fair: {per: system_id}\n" if fair else ""
    return f"""\
dead_letters: {{spool_dir: "{spool}"}}
connections:
  fleet: {{mavlink: "udpin:127.0.0.1:{in_port}", heartbeat: 0}}
  ground: {{mavlink: "udpout:127.0.0.1:{out_port}", heartbeat: 0, rate: {SINK_BYTES_PER_S * scale:g}}}
routes:
  - name: shared
    source: {{mavlink: {{connection: fleet, message: GLOBAL_POSITION_INT}}}}
    mapping: "{{t: time_boot_ms, agent: meta('system_id'), seq: lon}}"
    schema: raw_json
{fairness}    sink:
      mavlink: {{connection: ground, message: GLOBAL_POSITION_INT}}
      mapping: "{{time_boot_ms: t, lat: agent, lon: seq, alt: `1`, relative_alt: `1`, vx: `1`, vy: `1`, vz: `1`, hdg: `1`}}"
"""


@dataclass
class Outcome:
    """What the quiet agents got through the flood, and the engine's counters."""

    quiet_sent: int
    quiet_received: int
    quiet_lost: int
    quiet_p50_ms: float
    quiet_p99_ms: float
    quiet_max_ms: float
    flood_sent: int
    flood_received: int
    route: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> str:
        return (f"quiet agents: {self.quiet_received}/{self.quiet_sent} received, {self.quiet_lost} lost, latency p50 "
                f"{self.quiet_p50_ms:.0f} ms, p99 {self.quiet_p99_ms:.0f} ms, max {self.quiet_max_ms:.0f} ms; flooder: "
                f"{self.flood_received}/{self.flood_sent} received; route dropped {self.route.get('dropped')} "
                f"{self.route.get('dropped_by_agent')}")


def flood(directory: Path, fair: bool, seconds: float = 6.0, drain: float = 5.0, scale: float = 1.0) -> Outcome:
    """Run the load for ``seconds`` through a fresh engine (``fair`` or not) and measure;
    ``scale`` multiplies every rate, the sink's included (0.5: the same shape at half the CPU)."""
    in_port = free_udp_port()
    receiver = Receiver()
    routes = directory / ("fair" if fair else "fifo")
    routes.mkdir(parents=True)
    (routes / "shared.yaml").write_text(route_file(in_port, receiver.port, directory / "spool", fair, scale))
    engine = EngineProcess(routes, directory / f"{routes.name}.status.json", {})
    senders = Senders(in_port, seconds, scale)
    receiver.start()
    try:
        engine.wait_started()
        senders.start()
        senders.join(seconds + 10)
        quiet_sent = sum(senders.sent[system] for system in QUIET)
        deadline = time.monotonic() + drain  # the quiet agents' last messages: wait for them, bounded
        while receiver.quiet_count() < quiet_sent and time.monotonic() < deadline:
            time.sleep(0.05)  # poll: a drain bounded by design; what did not arrive is the measured loss (quiet_lost)
        status = engine.status() or {}
    finally:
        senders.stop.set()
        exited = engine.stop()
        receiver.stop.set()
        receiver.join(5)
    assert exited == 0, engine.log()
    with receiver.lock:
        got = list(receiver.got)
    quiet = [(agent, seq, latency) for agent, seq, latency in got if agent != FLOODER]
    latencies = sorted(latency for _, _, latency in quiet) or [0]
    distinct = {(agent, seq) for agent, seq, _ in quiet}
    return Outcome(
        quiet_sent=quiet_sent, quiet_received=len(distinct), quiet_lost=quiet_sent - len(distinct),
        quiet_p50_ms=statistics.median(latencies), quiet_p99_ms=latencies[min(len(latencies) - 1, int(len(latencies) * 0.99))],
        quiet_max_ms=latencies[-1], flood_sent=senders.sent[FLOODER],
        flood_received=sum(1 for agent, _, _ in got if agent == FLOODER),
        route=(status.get("routes") or {}).get("shared", {}),
    )
