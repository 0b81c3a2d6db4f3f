"""Emulated pair of SiK telemetry radios joined by a lossy half-duplex air link.

Each radio shows up as a pseudo-terminal that a client opens like ``/dev/ttyUSB0``. Kernel ptys
ignore the baud rate and buffer tens of kilobytes, so everything that makes a SiK link hard to
use is modelled here in user space, after the SiK firmware defaults (``parameters.c``, ``tdm.c``,
``packet.c``; see ``shared/research/mavlink.md`` section 5):

* 57,600 baud serial on both ends: bytes are taken from and given to a client at no more than
  5,760 bytes/s, so a client that writes faster blocks in ``write`` like on a real UART;
* a 2,048-byte radio buffer per side; bytes arriving while it is full are dropped and counted,
  which is what happens when the serial input exceeds what the air can carry;
* 64 kbps air rate (144 us per air byte plus a per-packet preamble), a fixed TDM round of
  ~236 ms in which each radio owns a 114 ms transmit window, and air packets of at most 252 bytes
  that must end inside their window;
* MAVLink-aware packet forming like SiK's ``MAVLINK=1``: whole frames are packed into one air
  packet whenever they fit, so a lost packet loses whole frames; frames too big for SiK
  (payload >= 230 B or payload + 25 > packet size) and frames stalled half-written are sent
  unaligned ("we will lose framing");
* per-packet Bernoulli loss with a seed, and outage windows during which every packet is lost;
* RADIO_STATUS (sysid 51, compid 68, MAVLink 2, unsigned) injected periodically into each
  radio's local serial output, with ``txbuf`` = percentage of the radio buffer that is free.

Not modelled: slot yielding by an idle radio (each side keeps its half of the round, so one
direction gets at most ~48 % of the air time), frequency hopping, ECC and RTS/CTS.

Use :class:`SikRadioPair` in-process (a background thread) or run the module as a process::

    python -m rabbitros_sim.sik_radio --link-a /tmp/gcs --link-b /tmp/uav --loss 0.05 --outage 10:2
"""

from __future__ import annotations

import argparse
import json
import os
import random
import select
import signal
import sys
import termios
import threading
import time
import tty
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from types import TracebackType

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

SERIAL_BAUD = 57_600
SERIAL_BYTES_PER_S = SERIAL_BAUD / 10
AIR_BYTE_S = 144e-6
PACKET_OVERHEAD_S = 2.1e-3
TX_WINDOW_S = 0.114
SILENCE_S = 0.0042
TDM_ROUND_S = 2 * (TX_WINDOW_S + SILENCE_S)
MAX_AIR_PACKET = 252
SERIAL_BUFFER = 2048
RADIO_SYSID = 51
RADIO_COMPID = 68

_STX_V1 = 0xFE
_STX_V2 = 0xFD
_SIK_FRAME_OVERHEAD = 8 + 4 + 13
_PARTIAL_FRAME_TIMEOUT_S = 0.05
_TICK_S = 0.004
_SERIAL_BURST = 128
_IDLE_WAIT_S = 0.25


def sik_packet_length(buf: bytes | bytearray, room: int, flush: bool = False,
                      max_packet: int = MAX_AIR_PACKET) -> int:
    """How many bytes from the head of ``buf`` SiK would put into its next air packet.

    ``room`` is the largest packet that still fits the transmit window. Returns 0 when the radio
    should wait: the head is an incomplete MAVLink frame (unless ``flush``, set once the serial
    line has been quiet long enough that the rest is not coming) or a whole frame does not fit
    into ``room`` yet will fit a later window.
    """
    size = len(buf)
    limit = min(room, max_packet)
    n = 0
    while n < size and n < limit:
        stx = buf[n]
        if stx not in (_STX_V1, _STX_V2):
            while n < size and n < limit and buf[n] not in (_STX_V1, _STX_V2):
                n += 1
            continue
        header = 3 if stx == _STX_V2 else 2
        if size - n < header:
            break
        payload_len = buf[n + 1]
        if stx == _STX_V2:
            frame_len = payload_len + 12 + (13 if buf[n + 2] & 0x01 else 0)
        else:
            frame_len = payload_len + 8
        if payload_len >= 255 - _SIK_FRAME_OVERHEAD or payload_len + _SIK_FRAME_OVERHEAD > max_packet:
            return n if n else min(size, limit)
        if frame_len > size - n:
            break
        if n + frame_len > limit:
            return n
        n += frame_len
    if n == 0 and flush:
        return min(size, limit)
    return n


@dataclass
class RadioStats:
    """Counters of one radio; ``serial_*`` concern its local client, ``air_*`` what it sent."""

    serial_rx_bytes: int = 0
    serial_rx_dropped: int = 0
    serial_tx_bytes: int = 0
    serial_tx_dropped: int = 0
    air_packets: int = 0
    air_bytes: int = 0
    air_packets_lost: int = 0
    air_bytes_lost: int = 0
    air_packets_outage: int = 0
    radio_status_sent: int = 0


@dataclass
class _Radio:
    """One side: its pty, its two serial buffers and the state its RADIO_STATUS reports."""

    name: str
    master: int
    slave: int
    device: str
    link: str
    rx: bytearray = field(default_factory=bytearray)
    tx: bytearray = field(default_factory=bytearray)
    in_t: float = 0.0
    out_t: float = 0.0
    in_budget: float = 0.0
    out_budget: float = 0.0
    last_rx_at: float = float("-inf")
    next_status_at: float = 0.0
    rssi: int = 0
    noise: int = 0
    rx_errors: int = 0
    stats: RadioStats = field(default_factory=RadioStats)
    mav: mavlink2.MAVLink = field(default_factory=lambda: mavlink2.MAVLink(None, RADIO_SYSID, RADIO_COMPID))

    def busy(self, now: float) -> bool:
        """Whether the loop must keep ticking; ``last_rx_at`` is the last sign of serial input."""
        return bool(self.rx or self.tx) or now - self.last_rx_at < _PARTIAL_FRAME_TIMEOUT_S


@dataclass
class _AirPacket:
    sender: _Radio
    receiver: _Radio
    data: bytes
    start: float
    end: float


class SikRadioPair:
    """Two emulated SiK radios on pseudo-terminals, shaped by a background thread.

    Usable as ``with SikRadioPair(...) as pair:`` or ``async with``; ``link_a``/``link_b`` are the
    paths clients open (symlinks when paths were given, else the pty devices). Outage starts are
    seconds after :meth:`start`; :meth:`elapsed` tells where the link is on that clock.
    """

    def __init__(
        self,
        link_a: str | None = None,
        link_b: str | None = None,
        *,
        loss: float = 0.0,
        outages: Sequence[tuple[float, float]] = (),
        radio_status_interval: float | None = 1.0,
        seed: int | None = None,
        serial_buffer: int = SERIAL_BUFFER,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 0.0 <= loss <= 1.0:
            raise ValueError(f"loss must be within [0, 1], got {loss}")
        self._paths = (link_a, link_b)
        self.loss = loss
        self._outages: list[tuple[float, float]] = [(float(s), float(d)) for s, d in outages]
        self.radio_status_interval = radio_status_interval
        self.serial_buffer = serial_buffer
        self._loss_rng = random.Random(seed)
        self._noise_rng = random.Random(None if seed is None else seed + 1)
        self._clock = clock
        self._radios: list[_Radio] = []
        self._inflight: _AirPacket | None = None
        self._stop = threading.Event()
        self._wake_r = self._wake_w = -1
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.started_at = 0.0

    @property
    def link_a(self) -> str:
        return self._radios[0].link

    @property
    def link_b(self) -> str:
        return self._radios[1].link

    @property
    def device_a(self) -> str:
        return self._radios[0].device

    @property
    def device_b(self) -> str:
        return self._radios[1].device

    def elapsed(self) -> float:
        return self._clock() - self.started_at

    def add_outage(self, start: float, duration: float) -> None:
        """Lose every air packet sent between ``start`` and ``start + duration`` (link clock)."""
        self._outages.append((float(start), float(duration)))

    def stats(self) -> dict[str, RadioStats]:
        return {r.name: RadioStats(**asdict(r.stats)) for r in self._radios}

    def start(self) -> SikRadioPair:
        if self._thread is not None:
            raise RuntimeError("already started")
        now = self._clock()
        self.started_at = now
        for name, path in zip("ab", self._paths):
            master, slave = os.openpty()
            tty.setraw(slave, termios.TCSANOW)
            os.set_blocking(master, False)
            device = os.ttyname(slave)
            link = device
            if path:
                if os.path.lexists(path):
                    os.unlink(path)
                os.symlink(device, path)
                link = path
            radio = _Radio(name, master, slave, device, link, in_t=now, out_t=now)
            radio.rssi, radio.noise = self._link_quality(up=True)
            if self.radio_status_interval:
                radio.next_status_at = now + self.radio_status_interval
            self._radios.append(radio)
        self._wake_r, self._wake_w = os.pipe()
        self._thread = threading.Thread(target=self._run, name="sik-radio-pair", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread, close the ptys (clients then read EOF/EIO) and remove the symlinks."""
        if self._thread is None:
            return
        self._stop.set()
        os.write(self._wake_w, b"x")
        self._thread.join(timeout=5)
        self._thread = None
        for fd in (self._wake_r, self._wake_w):
            os.close(fd)
        for radio in self._radios:
            os.close(radio.master)
            os.close(radio.slave)
            if radio.link != radio.device and os.path.islink(radio.link) \
                    and os.readlink(radio.link) == radio.device:
                os.unlink(radio.link)
        if self._error is not None:
            raise RuntimeError("SiK emulator thread failed") from self._error

    def __enter__(self) -> SikRadioPair:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.stop()

    async def __aenter__(self) -> SikRadioPair:
        return self.start()

    async def __aexit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                        tb: TracebackType | None) -> None:
        self.stop()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                now = self._clock()
                for radio in self._radios:
                    self._serial_in(radio, now)
                self._air(now)
                for radio in self._radios:
                    self._radio_status(radio, now)
                    self._serial_out(radio, now)
                self._wait(now)
        except Exception as exc:  # surfaced by stop(): a dead link must not look idle
            self._error = exc

    def _wait(self, now: float) -> None:
        if self._inflight is not None or any(r.busy(now) for r in self._radios):
            select.select([self._wake_r], [], [], _TICK_S)
            return
        timeout = _IDLE_WAIT_S
        if self.radio_status_interval:
            timeout = min(timeout, min(r.next_status_at for r in self._radios) - now)
        readable, _, _ = select.select([self._wake_r] + [r.master for r in self._radios], [], [],
                                       max(timeout, _TICK_S))
        woke = self._clock()
        for radio in self._radios:
            if radio.master in readable:
                radio.in_t = radio.last_rx_at = woke

    def _serial_in(self, radio: _Radio, now: float) -> None:
        """Take what the client wrote, at the serial rate, into the radio buffer."""
        radio.in_budget = min(radio.in_budget + (now - radio.in_t) * SERIAL_BYTES_PER_S, _SERIAL_BURST)
        radio.in_t = now
        want = int(radio.in_budget)
        if want <= 0:
            return
        try:
            data = os.read(radio.master, want)
        except OSError:
            data = b""
        radio.in_budget = radio.in_budget - len(data) if len(data) == want else 0.0
        if not data:
            return
        radio.stats.serial_rx_bytes += len(data)
        space = self.serial_buffer - len(radio.rx)
        radio.rx += data[:space]
        radio.stats.serial_rx_dropped += max(0, len(data) - space)
        radio.last_rx_at = now

    def _serial_out(self, radio: _Radio, now: float) -> None:
        """Hand received bytes to the client no faster than the serial rate."""
        elapsed, radio.out_t = now - radio.out_t, now
        if not radio.tx:
            radio.out_budget = 0.0
            return
        radio.out_budget = min(radio.out_budget + elapsed * SERIAL_BYTES_PER_S, _SERIAL_BURST)
        want = min(int(radio.out_budget), len(radio.tx))
        if want <= 0:
            return
        try:
            written = os.write(radio.master, radio.tx[:want])
        except OSError:
            return
        del radio.tx[:written]
        radio.out_budget -= written
        radio.stats.serial_tx_bytes += written

    def _air(self, now: float) -> None:
        """Finish the packet on the air, then start the next one if a window is open."""
        while True:
            packet = self._inflight
            if packet is not None:
                if now < packet.end:
                    return
                self._deliver(packet)
                self._inflight = None
            owner, window_end = self._window(now)
            if owner is None:
                return
            sender = self._radios[owner]
            if not sender.rx:
                return
            room = int((window_end - now - PACKET_OVERHEAD_S) / AIR_BYTE_S)
            flush = now - sender.last_rx_at >= _PARTIAL_FRAME_TIMEOUT_S
            length = sik_packet_length(sender.rx, room, flush=flush) if room > 0 else 0
            if length <= 0:
                return
            data = bytes(sender.rx[:length])
            del sender.rx[:length]
            sender.stats.air_packets += 1
            sender.stats.air_bytes += length
            self._inflight = _AirPacket(sender, self._radios[1 - owner], data, now,
                                        now + PACKET_OVERHEAD_S + length * AIR_BYTE_S)

    def _window(self, now: float) -> tuple[int | None, float]:
        phase = (now - self.started_at) % TDM_ROUND_S
        slot = TX_WINDOW_S + SILENCE_S
        if phase < TX_WINDOW_S:
            return 0, now + TX_WINDOW_S - phase
        if slot <= phase < slot + TX_WINDOW_S:
            return 1, now + slot + TX_WINDOW_S - phase
        return None, now

    def _in_outage(self, start: float, end: float) -> bool:
        t0, t1 = start - self.started_at, end - self.started_at
        return any(s <= t1 and t0 < s + d for s, d in self._outages)

    def _deliver(self, packet: _AirPacket) -> None:
        sender, receiver = packet.sender, packet.receiver
        outage = self._in_outage(packet.start, packet.end)
        if outage or self._loss_rng.random() < self.loss:
            sender.stats.air_packets_lost += 1
            sender.stats.air_bytes_lost += len(packet.data)
            sender.stats.air_packets_outage += outage
            receiver.rx_errors = (receiver.rx_errors + 1) & 0xFFFF
            if outage:
                receiver.rssi = receiver.noise + self._noise_rng.randint(0, 4)
            return
        receiver.rssi, receiver.noise = self._link_quality(up=True)
        self._to_client(receiver, packet.data)

    def _to_client(self, radio: _Radio, data: bytes) -> None:
        space = self.serial_buffer - len(radio.tx)
        radio.tx += data[:space]
        radio.stats.serial_tx_dropped += max(0, len(data) - space)

    def _link_quality(self, up: bool) -> tuple[int, int]:
        noise = 40 + self._noise_rng.randint(-3, 3)
        rssi = 190 + self._noise_rng.randint(-6, 6) if up else noise + self._noise_rng.randint(0, 4)
        return rssi, noise

    def _radio_status(self, radio: _Radio, now: float) -> None:
        """Inject RADIO_STATUS into the local serial output, as SiK does with ``MAVLINK=1``."""
        if not self.radio_status_interval or now < radio.next_status_at:
            return
        radio.next_status_at = max(radio.next_status_at + self.radio_status_interval, now)
        peer = self._radios[1 - self._radios.index(radio)]
        free = 100 * (self.serial_buffer - len(radio.rx)) // self.serial_buffer
        msg = radio.mav.radio_status_encode(
            rssi=radio.rssi, remrssi=peer.rssi, txbuf=free, noise=radio.noise,
            remnoise=peer.noise, rxerrors=radio.rx_errors, fixed=0)
        frame = msg.pack(radio.mav)
        radio.mav.seq = (radio.mav.seq + 1) % 256
        radio.stats.radio_status_sent += 1
        self._to_client(radio, frame)


def _parse_outage(text: str) -> tuple[float, float]:
    try:
        start, duration = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:DURATION in seconds, got {text!r}") from None
    if start < 0 or duration <= 0:
        raise argparse.ArgumentTypeError(f"outage needs START >= 0 and DURATION > 0: {text!r}")
    return start, duration


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m rabbitros_sim.sik_radio", description=__doc__.split("\n")[0])
    parser.add_argument("--link-a", required=True, help="symlink to create for radio A's serial port")
    parser.add_argument("--link-b", required=True, help="symlink to create for radio B's serial port")
    parser.add_argument("--loss", type=float, default=0.0, help="probability that an air packet is lost")
    parser.add_argument("--outage", type=_parse_outage, action="extend", nargs="+", default=[],
                        metavar="START:DURATION", help="seconds after start during which nothing passes")
    parser.add_argument("--radio-status-interval", type=float, default=1.0,
                        help="seconds between injected RADIO_STATUS frames (0 disables)")
    parser.add_argument("--seed", type=int, default=None, help="seed for loss and RSSI noise")
    parser.add_argument("--duration", type=float, default=None, help="exit after this many seconds")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the pair until SIGTERM/SIGINT; print a ready line and final counters as JSON."""
    args = _parser().parse_args(argv)
    done = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: done.set())
    pair = SikRadioPair(args.link_a, args.link_b, loss=args.loss, outages=args.outage,
                        radio_status_interval=args.radio_status_interval or None, seed=args.seed)
    pair.start()
    try:
        print(json.dumps({"event": "ready", "link_a": pair.link_a, "link_b": pair.link_b,
                          "device_a": pair.device_a, "device_b": pair.device_b}), flush=True)
        done.wait(args.duration)
    finally:
        pair.stop()
    print(json.dumps({"event": "stopped", "stats": {k: asdict(v) for k, v in pair.stats().items()}}),
          flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
