"""MAVLink 2 endpoint: telemetry in, commands out, JSON through TUNNEL, on one shared link.

A connection owns one link (serial device, ``udpin:``, ``udpout:``, ``tcp:``, ``tcpin:``)
driven by asyncio, not by pymavlink's blocking ``mavutil``: a reader hands chunks to
``MAVLink.parse_buffer`` (byte-at-a-time parsing costs ~10x more) and one writer packs and
writes every frame. Packing at write time keeps sequence numbers and signing timestamps in
wire order, which a receiver requires. The writer paces to the link rate (a SiK radio's
serial buffer is a few hundred bytes to 2 KB and overflows silently), sends control frames
before bulk tunnel fragments, and slows bulk traffic when the radio's RADIO_STATUS reports a
filling buffer.

Signing (MAVLink 2): outgoing frames are signed by pymavlink; incoming signatures are
verified here rather than by pymavlink because pymavlink records a stream's timestamp before
checking the signature, so one forged frame with a far-future timestamp would make every
genuine frame of that stream look replayed. Rejections are counted in :attr:`MavlinkConnection.stats`.

Settings (YAML ``connections.<name>.mavlink``)::

    url: /dev/ttyUSB0 | udpin:HOST:PORT | udpout:HOST:PORT | tcp:HOST:PORT | tcpin:HOST:PORT
    baud: 57600                  # serial only
    source_system: 255
    source_component: 190
    signing: {key_file: PATH | key_env: VAR, link_id: 0, timestamp_file: PATH,
              allow_unsigned: [RADIO_STATUS]}
    rate: BYTES_PER_S            # default baud/10 on serial, unpaced on networks
    heartbeat: 1.0               # Hz, 0 = none (a SiK radio injects RADIO_STATUS only after one)
    mav_type: 6                  # MAV_TYPE of our HEARTBEAT (6 GCS, 18 onboard controller)
    tunnel: {fragment_size, rto_min, rto_max, retries, sack_delay, window, rate, ...}

Source options: ``message`` (optional), ``system_id``, ``component_id``; or ``json_tunnel:
true`` with ``payload_type``. Sink options: ``message``, ``target_system``,
``target_component`` (defaults for those fields); or ``json_tunnel: true`` with
``payload_type``, ``target_system``, ``target_component``.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import math
import os
import termios
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Hashable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

os.environ["MAVLINK20"] = "1"
import jmespath  # noqa: E402
from jmespath import exceptions as jmespath_errors  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from engine.endpoints.base import (  # noqa: E402
    CheckResult,
    Connection,
    Deliver,
    EndpointError,
    Inbound,
    MessageRejected,
    Outbound,
    Sink,
    Source,
    Transport,
)
from engine.endpoints.mavlink_tunnel import (  # noqa: E402
    DEFAULT_PAYLOAD_TYPE,
    TUNNEL_PAYLOAD,
    TunnelHub,
    TunnelSettings,
    TunnelSink,
    TunnelSource,
    radio_pacing_factor,
)

MESSAGES: dict[str, type[mavlink2.MAVLink_message]] = {cls.msgname: cls for cls in mavlink2.mavlink_map.values()}
RADIO_STATUS = mavlink2.MAVLINK_MSG_ID_RADIO_STATUS
TUNNEL = mavlink2.MAVLINK_MSG_ID_TUNNEL
SIGNING_EPOCH = 1_420_070_400
"""Signing timestamps count 10 us units since 2015-01-01 UTC."""
STREAM_WINDOW = 6_000_000
"""A new signed stream may lag our timestamp by at most 60 s (MAVLink spec, pymavlink)."""
TIMESTAMP_RESERVE = 6_000_000
"""How far ahead of the last used timestamp the file is written, so a crash never reuses one."""
PEER_TTL = 30.0
READ_CHUNK = 4096
MAX_PARSERS = 32
SOURCE_QUEUE = 256

_SETTINGS = {"url", "baud", "source_system", "source_component", "signing", "rate", "heartbeat", "mav_type", "tunnel"}
_SIGNING = {"key_file", "key_env", "link_id", "timestamp_file", "allow_unsigned"}
_SOURCE_OPTIONS = {"message", "json_tunnel", "system_id", "component_id", "payload_type", "target_system", "target_component"}
_SINK_OPTIONS = _SOURCE_OPTIONS
_INT_RANGES = {
    "int8_t": (-(2**7), 2**7 - 1), "uint8_t": (0, 2**8 - 1),
    "int16_t": (-(2**15), 2**15 - 1), "uint16_t": (0, 2**16 - 1),
    "int32_t": (-(2**31), 2**31 - 1), "uint32_t": (0, 2**32 - 1),
    "int64_t": (-(2**63), 2**63 - 1), "uint64_t": (0, 2**64 - 1),
}


# -- configuration --------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Address:
    kind: str
    """serial | udpin | udpout | tcp | tcpin"""
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 57600


def parse_address(url: Any, baud: Any = None) -> Address:
    """pymavlink-style connection string -> :class:`Address`; ValueError names the problem."""
    if not isinstance(url, str) or not url.strip():
        raise ValueError("url must be a non-empty string")
    scheme, sep, rest = url.partition(":")
    if sep and scheme in ("udpin", "udpout", "udp", "tcp", "tcpin"):
        host, colon, port = rest.rpartition(":")
        if not colon or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(f"bad url {url!r}: expected {scheme}:HOST:PORT")
        kind = "udpin" if scheme == "udp" else scheme
        if not host:
            if kind in ("udpout", "tcp"):
                raise ValueError(f"bad url {url!r}: {kind} needs a host")
            host = "0.0.0.0"
        if kind in ("udpout", "tcp") and int(port) == 0:
            raise ValueError(f"bad url {url!r}: port 0")
        if baud is not None:
            raise ValueError("baud applies to serial links only")
        return Address(kind, host.strip("[]"), int(port))
    device, comma, inline_baud = url.partition(",")
    if not device.startswith("/"):
        raise ValueError(f"bad url {url!r}: not a device path nor udpin:/udpout:/tcp:/tcpin:HOST:PORT")
    if comma:
        baud = inline_baud
    baud = 57600 if baud is None else baud
    if isinstance(baud, str) and baud.isdigit():
        baud = int(baud)
    if isinstance(baud, bool) or not isinstance(baud, int) or not hasattr(termios, f"B{baud}"):
        raise ValueError(f"bad baud {baud!r}: not a serial speed this system supports")
    return Address("serial", device=device, baud=baud)


@dataclass(frozen=True, slots=True)
class SigningConfig:
    key: bytes = field(repr=False)
    link_id: int = 0
    timestamp_file: Path | None = None
    allow_unsigned: frozenset[int] = frozenset({RADIO_STATUS})


def load_signing(raw: Any) -> SigningConfig:
    """Read the 32-byte key (raw or 64 hex digits) from ``key_file`` or ``key_env``."""
    if not isinstance(raw, Mapping):
        raise ValueError("signing must be a mapping")
    unknown = set(raw) - _SIGNING
    if unknown:
        raise ValueError(f"unknown signing setting(s): {', '.join(sorted(unknown))}")
    if ("key_file" in raw) == ("key_env" in raw):
        raise ValueError("signing key missing: give exactly one of key_file, key_env")
    if "key_file" in raw:
        path = Path(str(raw["key_file"])).expanduser()
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ValueError(f"signing key missing: cannot read key_file {str(path)!r} ({exc.strerror})") from None
        key = _decode_key(data, f"key_file {str(path)!r}")
    else:
        value = os.environ.get(str(raw["key_env"]))
        if not value:
            raise ValueError(f"signing key missing: environment variable {raw['key_env']!r} is not set")
        key = _decode_key(value.encode(), f"environment variable {raw['key_env']!r}")
    link_id = raw.get("link_id", 0)
    if isinstance(link_id, bool) or not isinstance(link_id, int) or not 0 <= link_id <= 255:
        raise ValueError("signing.link_id must be 0..255")
    stamp = raw.get("timestamp_file")
    stamp_path = Path(str(stamp)).expanduser() if stamp else None
    if stamp_path is not None and not stamp_path.parent.is_dir():
        raise ValueError(f"signing.timestamp_file: directory {str(stamp_path.parent)!r} does not exist")
    allowed = raw.get("allow_unsigned", ["RADIO_STATUS"])
    if not isinstance(allowed, list) or any(name not in MESSAGES for name in allowed):
        raise ValueError("signing.allow_unsigned must be a list of MAVLink message names")
    return SigningConfig(key, link_id, stamp_path, frozenset(MESSAGES[name].id for name in allowed))


def _decode_key(data: bytes, where: str) -> bytes:
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        with contextlib.suppress(ValueError):
            return bytes.fromhex(text.decode("ascii", "replace"))
    if len(text) == 32:
        return text
    raise ValueError(f"signing key in {where} must be 32 bytes or 64 hex digits")


@dataclass(frozen=True, slots=True)
class LinkConfig:
    address: Address
    source_system: int = 255
    source_component: int = 190
    signing: SigningConfig | None = None
    rate: float = 0.0
    heartbeat: float = 1.0
    mav_type: int = mavlink2.MAV_TYPE_GCS
    tunnel: TunnelSettings = field(default_factory=TunnelSettings)

    @property
    def bulk_rate(self) -> float:
        if self.tunnel.rate:
            return self.tunnel.rate
        return self.rate / 2 if self.address.kind == "serial" else 0.0


def settings_problems(settings: Mapping[str, Any]) -> tuple[LinkConfig | None, list[tuple[str | None, str]]]:
    """Parse connection settings, collecting every problem with the key it belongs to."""
    problems: list[tuple[str | None, str]] = []
    for key in sorted(set(settings) - _SETTINGS):
        problems.append((key, f"unknown setting {key!r}"))
    address = None
    try:
        address = parse_address(settings.get("url"), settings.get("baud"))
    except ValueError as exc:
        problems.append(("baud" if "baud" in str(exc) else "url", str(exc)))
    values: dict[str, Any] = {}
    for key, low, high in (("source_system", 1, 255), ("source_component", 0, 255), ("mav_type", 0, 255)):
        if key in settings:
            value = settings[key]
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                problems.append((key, f"{key} must be an integer {low}..{high}"))
            else:
                values[key] = value
    for key in ("rate", "heartbeat"):
        if key in settings:
            value = settings[key]
            if isinstance(value, bool) or not isinstance(value, (int, float)) or value < 0 or not math.isfinite(value):
                problems.append((key, f"{key} must be a non-negative number"))
            else:
                values[key] = float(value)
    if settings.get("signing") is not None:
        try:
            values["signing"] = load_signing(settings["signing"])
        except ValueError as exc:
            problems.append(("signing", str(exc)))
    if address is not None:
        try:
            values["tunnel"] = TunnelSettings.from_settings(settings.get("tunnel"), serial=address.kind == "serial")
        except ValueError as exc:
            problems.append(("tunnel", str(exc)))
        if "rate" not in values and address.kind == "serial":
            values["rate"] = address.baud / 10
    if problems or address is None:
        return None, problems
    return LinkConfig(address, **values), problems


# -- links ------------------------------------------------------------------------------------

OnBytes = Callable[[bytes, Hashable], None]


class _Link:
    """A byte pipe: received chunks go to ``on_bytes(data, peer)``; ``transmit`` writes a frame."""

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> None:
        self.address = address
        self.on_bytes = on_bytes
        self.stats = stats
        self.closed = False
        self.local_address: tuple[str, int] | None = None

    async def open(self) -> None:
        raise NotImplementedError

    @property
    def ready(self) -> bool:
        """Whether a frame written now has somewhere to go."""
        return not self.closed

    async def transmit(self, data: bytes) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        self.closed = True

    def _count(self, key: str) -> None:
        self.stats[key] = self.stats.get(key, 0) + 1


def configure_tty(fd: int, baud: int) -> None:
    """Raw 8N1 at ``baud``, no flow control, no echo, no line discipline."""
    iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(fd)
    iflag &= ~(termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP | termios.INLCR
               | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF | termios.IXANY)
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB | getattr(termios, "CRTSCTS", 0))
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    cc[termios.VMIN] = 0
    cc[termios.VTIME] = 0
    speed = getattr(termios, f"B{baud}")
    termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])


class _SerialLink(_Link):
    """A tty read with ``add_reader``; reopened every second after the device disappears."""

    _fd: int | None = None
    _reopen: asyncio.Task[None] | None = None

    async def open(self) -> None:
        try:
            self._open()
        except OSError as exc:
            raise EndpointError(f"cannot open {self.address.device}: {exc.strerror}") from None

    @property
    def ready(self) -> bool:
        return self._fd is not None

    def _open(self) -> None:
        fd = os.open(self.address.device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            configure_tty(fd, self.address.baud)
        except (OSError, termios.error):
            os.close(fd)
            raise
        self._fd = fd
        asyncio.get_running_loop().add_reader(fd, self._readable)

    def _readable(self) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, READ_CHUNK)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if data:
            self.on_bytes(data, None)
        else:
            self._lost()

    def _lost(self) -> None:
        if self._fd is None:
            return
        loop = asyncio.get_running_loop()
        loop.remove_reader(self._fd)
        os.close(self._fd)
        self._fd = None
        self._count("link_lost")
        if not self.closed and self._reopen is None:
            self._reopen = loop.create_task(self._reopen_loop())

    async def _reopen_loop(self) -> None:
        try:
            while not self.closed:
                await asyncio.sleep(1.0)
                with contextlib.suppress(OSError, termios.error):
                    self._open()
                    return
        finally:
            self._reopen = None

    async def transmit(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            fd = self._fd
            if fd is None:
                raise EndpointError(f"serial device {self.address.device} is not open")
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                await self._writable(fd)
            except OSError as exc:
                self._lost()
                raise EndpointError(f"write to {self.address.device} failed: {exc.strerror}") from None

    async def _writable(self, fd: int) -> None:
        loop = asyncio.get_running_loop()
        ready: asyncio.Future[None] = loop.create_future()

        def wake() -> None:
            if not ready.done():
                ready.set_result(None)

        loop.add_writer(fd, wake)
        try:
            await asyncio.wait_for(ready, 1.0)
        except TimeoutError:
            pass
        finally:
            with contextlib.suppress(Exception):
                loop.remove_writer(fd)

    async def close(self) -> None:
        await super().close()
        if self._reopen is not None:
            self._reopen.cancel()
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
            os.close(self._fd)
            self._fd = None


class _Datagrams(asyncio.DatagramProtocol):
    def __init__(self, link: _UdpLink) -> None:
        self.link = link

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.link.received(data, addr)

    def error_received(self, exc: Exception) -> None:
        """ICMP port unreachable while the peer is not up yet; the next datagram may succeed."""
        self.link._count("udp_errors")


class _UdpLink(_Link):
    """``udpout`` sends to its remote; ``udpin`` answers every peer heard in the last 30 s."""

    _transport: asyncio.DatagramTransport | None = None

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> None:
        super().__init__(address, on_bytes, stats)
        self.peers: OrderedDict[Any, float] = OrderedDict()

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        where = (self.address.host, self.address.port)
        try:
            if self.address.kind == "udpin":
                transport, _ = await loop.create_datagram_endpoint(lambda: _Datagrams(self), local_addr=where)
            else:
                transport, _ = await loop.create_datagram_endpoint(lambda: _Datagrams(self), remote_addr=where)
        except OSError as exc:
            raise EndpointError(f"cannot open {self.address.kind}:{where[0]}:{where[1]}: {exc.strerror}") from None
        self._transport = transport
        self.local_address = transport.get_extra_info("sockname")[:2]

    @property
    def ready(self) -> bool:
        if self.address.kind == "udpout":
            return self._transport is not None
        now = time.monotonic()
        return any(now - seen < PEER_TTL for seen in self.peers.values())

    def received(self, data: bytes, addr: Any) -> None:
        if self.address.kind == "udpin":
            self.peers[addr] = time.monotonic()
            self.peers.move_to_end(addr)
            while len(self.peers) > 8:
                self.peers.popitem(last=False)
        self.on_bytes(data, addr)

    async def transmit(self, data: bytes) -> None:
        if self._transport is None or self._transport.is_closing():
            raise EndpointError("udp link is closed")
        if self.address.kind == "udpout":
            self._transport.sendto(data)
            return
        now = time.monotonic()
        peers = [addr for addr, seen in self.peers.items() if now - seen < PEER_TTL]
        if not peers:
            raise EndpointError(f"udpin:{self.address.host}:{self.address.port} has not heard from any peer yet")
        for addr in peers:
            self._transport.sendto(data, addr)

    async def close(self) -> None:
        await super().close()
        if self._transport is not None:
            self._transport.close()


class _TcpLink(_Link):
    """``tcp`` (client, reconnecting) or ``tcpin`` (server, writes to every client)."""

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> None:
        super().__init__(address, on_bytes, stats)
        self.writers: dict[Hashable, asyncio.StreamWriter] = {}
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()

    async def open(self) -> None:
        host, port = self.address.host, self.address.port
        try:
            if self.address.kind == "tcpin":
                self._server = await asyncio.start_server(self._serve, host, port)
                self.local_address = self._server.sockets[0].getsockname()[:2]
            else:
                reader, writer = await asyncio.open_connection(host, port)
                self._spawn(self._client(reader, writer))
        except OSError as exc:
            raise EndpointError(f"cannot open {self.address.kind}:{host}:{port}: {exc.strerror or exc}") from None

    @property
    def ready(self) -> bool:
        return bool(self.writers)

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        await self._pump(reader, writer)

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        delay = 1.0
        while not self.closed:
            await self._pump(reader, writer)
            self._count("link_lost")
            while not self.closed:
                await asyncio.sleep(delay)
                try:
                    reader, writer = await asyncio.open_connection(self.address.host, self.address.port)
                    delay = 1.0
                    break
                except OSError:
                    delay = min(delay * 2, 10.0)

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername") or id(writer)
        self.writers[peer] = writer
        try:
            while data := await reader.read(READ_CHUNK):
                self.on_bytes(data, peer)
        except OSError:
            pass
        finally:
            self.writers.pop(peer, None)
            writer.close()

    async def transmit(self, data: bytes) -> None:
        if not self.writers:
            raise EndpointError(f"{self.address.kind}:{self.address.host}:{self.address.port} has no connected peer")
        for writer in list(self.writers.values()):
            writer.write(data)
        with contextlib.suppress(OSError):
            await asyncio.gather(*(w.drain() for w in list(self.writers.values())))

    async def close(self) -> None:
        await super().close()
        if self._server is not None:
            self._server.close()
        for writer in list(self.writers.values()):
            writer.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)


def _make_link(address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> _Link:
    if address.kind == "serial":
        return _SerialLink(address, on_bytes, stats)
    if address.kind in ("udpin", "udpout"):
        return _UdpLink(address, on_bytes, stats)
    return _TcpLink(address, on_bytes, stats)


# -- signing ----------------------------------------------------------------------------------


def signing_now() -> int:
    return int((max(time.time(), SIGNING_EPOCH) - SIGNING_EPOCH) * 100_000)


class SigningClock:
    """Keeps the outgoing signing timestamp at or after wall clock and after every value used
    before, across restarts: the file holds a value reserved ahead of use, rewritten (atomically)
    when half of the reserve is spent."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self.reserved = 0

    def start(self) -> int:
        stored = 0
        if self.path is not None:
            with contextlib.suppress(OSError, ValueError):
                stored = int(self.path.read_text().strip() or 0)
        start = max(signing_now(), stored)
        self._persist(start + TIMESTAMP_RESERVE)
        return start

    def advance(self, current: int) -> int:
        stamp = max(current, signing_now())
        if stamp + TIMESTAMP_RESERVE // 2 >= self.reserved:
            self._persist(stamp + TIMESTAMP_RESERVE)
        return stamp

    def _persist(self, value: int) -> None:
        self.reserved = value
        if self.path is None:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.write(fd, f"{value}\n".encode())
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, self.path)


class SignatureCheck:
    """Verifies incoming frames; returns the stats key of the rejection, or None to accept."""

    def __init__(self, config: SigningConfig, local_timestamp: Callable[[], int]) -> None:
        self.config = config
        self.local_timestamp = local_timestamp
        self.streams: dict[tuple[int, int, int], int] = {}
        self.newest = 0

    def __call__(self, buf: bytes | bytearray) -> str | None:
        if buf[0] != mavlink2.PROTOCOL_MARKER_V2 or not buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
            msg_id = buf[5] if buf[0] != mavlink2.PROTOCOL_MARKER_V2 else buf[7] | buf[8] << 8 | buf[9] << 16
            return None if msg_id in self.config.allow_unsigned else "unsigned_rejected"
        link_id = buf[-13]
        stamp = int.from_bytes(buf[-12:-6], "little")
        if hashlib.sha256(self.config.key + bytes(buf[:-6])).digest()[:6] != bytes(buf[-6:]):
            return "bad_signature"
        stream = (link_id, buf[5], buf[6])
        last = self.streams.get(stream)
        if last is not None and stamp <= last:
            return "replayed"
        if last is None and stamp + STREAM_WINDOW < max(self.local_timestamp(), self.newest):
            return "replayed"
        self.streams[stream] = stamp
        self.newest = max(self.newest, stamp)
        return None


# -- messages ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class FieldSpec:
    type: str
    length: int
    """Array length; 0 for a scalar."""


def field_specs(cls: type[mavlink2.MAVLink_message]) -> dict[str, FieldSpec]:
    """``fieldtypes`` follows ``fieldnames`` but ``array_lengths`` follows wire order."""
    lengths = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    return {name: FieldSpec(ftype, lengths[name]) for name, ftype in zip(cls.fieldnames, cls.fieldtypes)}


def _scalar(name: str, ftype: str, value: Any) -> int | float:
    if isinstance(value, str) or not isinstance(value, (int, float)):
        raise MessageRejected(f"field {name!r}: expected a number, got {type(value).__name__}")
    if ftype in ("float", "double"):
        return float(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise MessageRejected(f"field {name!r}: {value} is not an integer")
        value = round(value)
    low, high = _INT_RANGES[ftype]
    if not low <= value <= high:
        raise MessageRejected(f"field {name!r}: {value} is outside {ftype} ({low}..{high})")
    return int(value)


def _coerce(name: str, spec: FieldSpec, value: Any) -> Any:
    if spec.type == "char":
        if value is None:
            return b""
        raw = value.encode() if isinstance(value, str) else value
        if not isinstance(raw, (bytes, bytearray)):
            raise MessageRejected(f"field {name!r}: expected a string")
        if len(raw) > max(spec.length, 1):
            raise MessageRejected(f"field {name!r}: {len(raw)} bytes exceed char[{spec.length}]")
        return bytes(raw)
    zero = 0.0 if spec.type in ("float", "double") else 0
    if not spec.length:
        return zero if value is None else _scalar(name, spec.type, value)
    if value is None:
        return [zero] * spec.length
    if isinstance(value, (bytes, bytearray)) and spec.type == "uint8_t":
        items: list[Any] = list(value)
    elif isinstance(value, (list, tuple)):
        items = [zero if v is None else _scalar(name, spec.type, v) for v in value]
    else:
        raise MessageRejected(f"field {name!r}: expected an array of {spec.length}")
    if len(items) > spec.length:
        raise MessageRejected(f"field {name!r}: {len(items)} items exceed [{spec.length}]")
    return items + [zero] * (spec.length - len(items))


def build_message(cls: type[mavlink2.MAVLink_message], fields: Any,
                  defaults: Mapping[str, Any] | None = None) -> mavlink2.MAVLink_message:
    """A message from a dict of fields; missing ones are 0 (empty for strings and arrays)."""
    if not isinstance(fields, Mapping):
        raise MessageRejected(f"{cls.msgname}: the sink mapping must produce an object of fields, got {type(fields).__name__}")
    specs = field_specs(cls)
    unknown = sorted(set(fields) - set(specs))
    if unknown:
        raise MessageRejected(f"{cls.msgname} has no field(s) {', '.join(map(repr, unknown))}")
    defaults = defaults or {}
    values = {}
    for name, spec in specs.items():
        value = fields.get(name)
        values[name] = _coerce(name, spec, defaults.get(name) if value is None else value)
    return cls(**values)


def message_fields(msg: mavlink2.MAVLink_message) -> dict[str, Any]:
    """``to_dict()`` without ``mavpackettype``: strings decoded, arrays as lists."""
    return {name: msg.format_attr(name) for name in msg.get_fieldnames()}


# -- connection -------------------------------------------------------------------------------

_STATS = (
    "bytes_received", "frames_received", "frames_accepted", "frames_lost", "bad_crc", "bad_data",
    "unknown_message", "unsigned_rejected", "unsigned_accepted", "bad_signature", "replayed",
    "not_for_us", "frames_sent", "bytes_sent", "send_errors", "source_dropped",
)
"""Keys of :attr:`MavlinkConnection.stats`. ``frames_received`` counts frames with a good CRC,
``frames_accepted`` those that also passed signing; ``frames_lost`` sums sequence gaps per
sender; rejections: ``unsigned_rejected``, ``bad_signature`` (wrong key or altered),
``replayed`` (timestamp not newer than the stream's last, or a new stream over 60 s old).
Tunnel counters (``tunnel_sent``, ``tunnel_retransmissions``, ``tunnel_delivered``,
``tunnel_deliver_failed``, ``tunnel_malformed``) appear once used."""


class MavlinkConnection(Connection):
    """One MAVLink link shared by every route that names it."""

    def __init__(self, name: str, settings: Mapping[str, Any]) -> None:
        super().__init__(name, settings)
        config, problems = settings_problems(settings)
        if config is None or problems:
            raise EndpointError(f"mavlink connection {name!r}: " + "; ".join(m for _, m in problems))
        self.config = config
        self.stats: dict[str, int] = dict.fromkeys(_STATS, 0)
        self.hub = TunnelHub(self, config.tunnel)
        self._mav = mavlink2.MAVLink(None, config.source_system, config.source_component)
        self._clock: SigningClock | None = None
        self._check: SignatureCheck | None = None
        self._link: _Link | None = None
        self._parsers: OrderedDict[Hashable, mavlink2.MAVLink] = OrderedDict()
        self._subscribers: dict[int | None, list[MessageSource]] = {}
        self._last_seq: dict[tuple[int, int], int] = {}
        self._urgent: deque[tuple[mavlink2.MAVLink_message, asyncio.Future[float]]] = deque()
        self._bulk: deque[tuple[mavlink2.MAVLink_message, asyncio.Future[float]]] = deque()
        self._wake = asyncio.Event()
        self._tx_ready = 0.0
        self._bulk_ready = 0.0
        self._radio_txbuf: tuple[float, int] | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._closed = False

    @property
    def address(self) -> tuple[str, int] | None:
        """Bound (host, port) of ``udpin``/``tcpin`` links; useful with port 0."""
        return self._link.local_address if self._link else None

    @property
    def signed(self) -> bool:
        return self.config.signing is not None

    async def open(self) -> None:
        signing = self.config.signing
        if signing is not None:
            self._clock = SigningClock(signing.timestamp_file)
            s = self._mav.signing
            s.secret_key, s.link_id, s.sign_outgoing = signing.key, signing.link_id, True
            s.timestamp = self._clock.start()
            self._check = SignatureCheck(signing, lambda: self._mav.signing.timestamp)
        self._link = _make_link(self.config.address, self._on_bytes, self.stats)
        await self._link.open()
        self._tasks.append(asyncio.create_task(self._writer(), name=f"mavlink-writer:{self.name}"))
        if self.config.heartbeat > 0:
            self._tasks.append(asyncio.create_task(self._heartbeat(), name=f"mavlink-heartbeat:{self.name}"))

    async def close(self) -> None:
        self._closed = True
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        for queue in (self._urgent, self._bulk):
            while queue:
                _, future = queue.popleft()
                if not future.done():
                    future.set_exception(EndpointError(f"mavlink connection {self.name!r} closed"))
        if self._link is not None:
            await self._link.close()

    def source(self, route: str, options: Mapping[str, Any]) -> Source:
        _raise_problems(route, "source", check_source_options(options, None))
        if options.get("json_tunnel"):
            return TunnelSource(self.hub, route=route, payload_type=options.get("payload_type", DEFAULT_PAYLOAD_TYPE),
                                system_id=options.get("system_id"), component_id=options.get("component_id"))
        name = options.get("message")
        return MessageSource(self, route, MESSAGES[name].id if name else None,
                             options.get("system_id"), options.get("component_id"))

    def sink(self, route: str, options: Mapping[str, Any]) -> Sink:
        _raise_problems(route, "sink", check_sink_options(options, None))
        target = (options.get("target_system", 0), options.get("target_component", 0))
        if options.get("json_tunnel"):
            return TunnelSink(self.hub, payload_type=options.get("payload_type", DEFAULT_PAYLOAD_TYPE), target=target)
        cls = MESSAGES[options["message"]]
        defaults = {key: options[key] for key in ("target_system", "target_component") if key in options}
        return MessageSink(self, cls, defaults)

    # writing

    def enqueue(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False) -> asyncio.Future[float]:
        """Queue a frame for the writer; the future gives the loop time it was written."""
        future: asyncio.Future[float] = asyncio.get_running_loop().create_future()
        if self._closed or self._link is None:
            future.set_exception(EndpointError(f"mavlink connection {self.name!r} is not open"))
        else:
            (self._bulk if bulk else self._urgent).append((msg, future))
            self._wake.set()
        return future

    async def send_message(self, msg: mavlink2.MAVLink_message, *, bulk: bool = False) -> float:
        return await self.enqueue(msg, bulk=bulk)

    def send_tunnel(self, payload_type: int, target: tuple[int, int], payload: bytes, *,
                    bulk: bool) -> asyncio.Future[float]:
        msg = mavlink2.MAVLink_tunnel_message(target[0], target[1], payload_type, len(payload),
                                              payload.ljust(TUNNEL_PAYLOAD, b"\0"))
        return self.enqueue(msg, bulk=bulk)

    async def _writer(self) -> None:
        loop = asyncio.get_running_loop()
        rate, bulk_rate = self.config.rate, self.config.bulk_rate
        assert self._link is not None
        while True:
            now = loop.time()
            if self._urgent:
                msg, future = self._urgent.popleft()
                bulk = False
            elif self._bulk and now >= self._bulk_ready:
                msg, future = self._bulk.popleft()
                bulk = True
            else:
                self._wake.clear()
                timeout = max(0.0, self._bulk_ready - now) if self._bulk else None
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), timeout)
                continue
            if future.done():
                continue
            if self._tx_ready > now:
                await asyncio.sleep(self._tx_ready - now)
            start = loop.time()
            try:
                data = self._pack(msg)
                await self._link.transmit(data)
            except EndpointError as exc:
                self.stats["send_errors"] += 1
                if not future.done():
                    future.set_exception(exc)
                continue
            except Exception as exc:  # pymavlink struct errors: a field out of range
                self.stats["send_errors"] += 1
                if not future.done():
                    future.set_exception(EndpointError(f"{msg.get_type()}: cannot encode: {exc}"))
                continue
            self.stats["frames_sent"] += 1
            self.stats["bytes_sent"] += len(data)
            if rate:
                self._tx_ready = max(self._tx_ready, start) + len(data) / rate
            if bulk and bulk_rate:
                self._bulk_ready = max(self._bulk_ready, start) + len(data) / (bulk_rate * radio_pacing_factor(self._radio_txbuf, start))
            if not future.done():
                future.set_result(loop.time())

    def _pack(self, msg: mavlink2.MAVLink_message) -> bytes:
        if self._clock is not None:
            signing = self._mav.signing
            signing.timestamp = self._clock.advance(max(signing.timestamp, self._check.newest if self._check else 0))
        data = msg.pack(self._mav)
        self._mav.seq = (self._mav.seq + 1) % 256
        return data

    async def _heartbeat(self) -> None:
        period = 1.0 / self.config.heartbeat
        while True:
            msg = mavlink2.MAVLink_heartbeat_message(self.config.mav_type, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
                                                     mavlink2.MAV_STATE_ACTIVE, 3)
            if self._link is not None and self._link.ready:
                with contextlib.suppress(EndpointError):
                    await self.enqueue(msg)
            await asyncio.sleep(period)

    # reading

    def _parser(self, peer: Hashable) -> mavlink2.MAVLink:
        parser = self._parsers.get(peer)
        if parser is None:
            parser = self._parsers[peer] = mavlink2.MAVLink(None)
            parser.robust_parsing = True
            while len(self._parsers) > MAX_PARSERS:
                self._parsers.popitem(last=False)
        return parser

    def _on_bytes(self, data: bytes, peer: Hashable) -> None:
        self.stats["bytes_received"] += len(data)
        parser = self._parser(peer)
        try:
            messages = parser.parse_buffer(data) or ()
        except Exception:
            self.stats["bad_data"] += 1
            self._parsers.pop(peer, None)
            return
        for msg in messages:
            self._on_message(msg)

    def _on_message(self, msg: mavlink2.MAVLink_message) -> None:
        msg_id = msg.get_msgId()
        if msg_id == mavlink2.MAVLINK_MSG_ID_BAD_DATA:
            self.stats["bad_crc" if "CRC" in getattr(msg, "reason", "") else "bad_data"] += 1
            return
        self.stats["frames_received"] += 1
        buf = msg.get_msgbuf()
        if self._check is not None:
            verdict = self._check(buf)
            if verdict is not None:
                self.stats[verdict] += 1
                return
            if buf[0] != mavlink2.PROTOCOL_MARKER_V2 or not buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED:
                self.stats["unsigned_accepted"] += 1
        if msg_id == mavlink2.MAVLINK_MSG_ID_UNKNOWN:
            self.stats["unknown_message"] += 1
            return
        self.stats["frames_accepted"] += 1
        header = msg.get_header()
        stream = (header.srcSystem, header.srcComponent)
        last = self._last_seq.get(stream)
        if last is not None:
            self.stats["frames_lost"] += (header.seq - last - 1) % 256
        self._last_seq[stream] = header.seq
        if msg_id == RADIO_STATUS:
            self._radio_txbuf = (asyncio.get_running_loop().time(), msg.txbuf)
        elif msg_id == TUNNEL:
            if msg.target_system not in (0, self.config.source_system) or \
                    msg.target_component not in (0, self.config.source_component):
                self.stats["not_for_us"] += 1
                return
            payload = bytes(msg.payload[:msg.payload_length])
            if self.hub.on_frame(msg.payload_type, stream, payload):
                return
        for key in (msg_id, None):
            for source in self._subscribers.get(key, ()):
                source.offer(msg)

    def subscribe(self, source: MessageSource) -> None:
        self._subscribers.setdefault(source.msg_id, []).append(source)

    def unsubscribe(self, source: MessageSource) -> None:
        with contextlib.suppress(KeyError, ValueError):
            self._subscribers[source.msg_id].remove(source)


class MessageSource(Source):
    """Decoded messages of one type (or all) as field dicts, filtered by sender.

    Telemetry cannot be redelivered, so a slow route drops the oldest queued messages
    (counted as ``source_dropped``) rather than delaying the link for every other route.
    """

    def __init__(self, connection: MavlinkConnection, route: str, msg_id: int | None,
                 system_id: int | None = None, component_id: int | None = None) -> None:
        self.connection = connection
        self.route = route
        self.msg_id = msg_id
        self.system_id = system_id
        self.component_id = component_id
        self._queue: asyncio.Queue[Inbound | None] = asyncio.Queue(SOURCE_QUEUE)
        self._task: asyncio.Task[None] | None = None

    async def start(self, deliver: Deliver) -> None:
        self.connection.subscribe(self)
        self._task = asyncio.create_task(self._run(deliver), name=f"mavlink-source:{self.route}")

    async def stop(self) -> None:
        self.connection.unsubscribe(self)
        if self._task is None:
            return
        while not self._queue.empty():
            self._queue.get_nowait()
        self._queue.put_nowait(None)
        await asyncio.gather(self._task, return_exceptions=True)
        self._task = None

    def offer(self, msg: mavlink2.MAVLink_message) -> None:
        header = msg.get_header()
        if self.system_id is not None and header.srcSystem != self.system_id:
            return
        if self.component_id is not None and header.srcComponent != self.component_id:
            return
        if self._queue.full():
            self._queue.get_nowait()
            self.connection.stats["source_dropped"] += 1
        buf = msg.get_msgbuf()
        meta = {
            "message": msg.get_type(), "system_id": header.srcSystem, "component_id": header.srcComponent,
            "signed": bool(buf[0] == mavlink2.PROTOCOL_MARKER_V2 and buf[2] & mavlink2.MAVLINK_IFLAG_SIGNED),
        }
        self._queue.put_nowait(Inbound(fields=message_fields(msg), meta=meta))

    async def _run(self, deliver: Deliver) -> None:
        while (inbound := await self._queue.get()) is not None:
            try:
                await deliver(inbound)
            except Exception:
                self.connection.stats["source_dropped"] += 1


class MessageSink(Sink):
    """Encodes ``Outbound.fields`` as one message; accepted once written to the link."""

    def __init__(self, connection: MavlinkConnection, cls: type[mavlink2.MAVLink_message],
                 defaults: Mapping[str, Any]) -> None:
        self.connection = connection
        self.cls = cls
        self.defaults = dict(defaults)

    async def send(self, message: Outbound) -> None:
        await self.connection.send_message(build_message(self.cls, message.fields, self.defaults))


# -- static checks ----------------------------------------------------------------------------


def _int_option(options: Mapping[str, Any], key: str, low: int, high: int) -> Iterator[tuple[str, str]]:
    if key in options:
        value = options[key]
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            yield key, f"{key} must be an integer {low}..{high}"


def _common_problems(options: Mapping[str, Any], allowed: set[str]) -> Iterator[tuple[str | None, str]]:
    for key in sorted(set(options) - allowed - {"connection"}):
        yield key, f"unknown option {key!r}"
    for key in ("system_id", "component_id", "target_system", "target_component"):
        yield from _int_option(options, key, 0, 255)
    yield from _int_option(options, "payload_type", 32768, 65535)
    name = options.get("message")
    if name is not None and name not in MESSAGES:
        yield "message", f"unknown MAVLink message {name!r} (dialect: common)"


def check_source_options(options: Mapping[str, Any], mapping: str | None) -> list[tuple[str | None, str]]:
    problems = list(_common_problems(options, _SOURCE_OPTIONS))
    if options.get("json_tunnel") and options.get("message") not in (None, "TUNNEL"):
        problems.append(("message", "a json_tunnel source reads TUNNEL frames; drop 'message'"))
    return problems


def check_sink_options(options: Mapping[str, Any], mapping: str | None) -> list[tuple[str | None, str]]:
    problems = list(_common_problems(options, _SINK_OPTIONS))
    if options.get("json_tunnel"):
        return problems
    name = options.get("message")
    if name is None:
        problems.append((None, "a mavlink sink needs 'message' (or json_tunnel: true)"))
        return problems
    cls = MESSAGES.get(name)
    if cls is None:
        return problems
    for key in ("target_system", "target_component"):
        if key in options and key not in cls.fieldnames:
            problems.append((key, f"{name} has no field {key!r}"))
    for key in _mapping_keys(mapping):
        if key not in cls.fieldnames:
            fields = ", ".join(cls.fieldnames)
            problems.append((None, f"sink mapping sets {key!r}, which {name} does not have (fields: {fields})"))
    return problems


def _mapping_keys(mapping: str | None) -> list[str]:
    if not mapping:
        return []
    try:
        node = jmespath.compile(mapping).parsed
    except jmespath_errors.JMESPathError:
        return []
    if node.get("type") != "multi_select_dict":
        return []
    return [child["value"] for child in node["children"] if child.get("type") == "key_val_pair"]


def _raise_problems(route: str, side: str, problems: list[tuple[str | None, str]]) -> None:
    if problems:
        raise EndpointError(f"route {route!r}: mavlink {side}: " + "; ".join(m for _, m in problems))


class MavlinkTransport(Transport):
    name: ClassVar[str] = "mavlink"
    default_settings: ClassVar[Mapping[str, Any]] = {"url": "udpin:0.0.0.0:14550"}

    def check_connection(self, settings: Mapping[str, Any]) -> CheckResult:
        return settings_problems(settings)[1]

    def check_source(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        return check_source_options(options, mapping)

    def check_sink(self, options: Mapping[str, Any], mapping: str | None) -> CheckResult:
        return check_sink_options(options, mapping)

    def connect(self, name: str, settings: Mapping[str, Any]) -> MavlinkConnection:
        return MavlinkConnection(name, settings)


TRANSPORT = MavlinkTransport()
