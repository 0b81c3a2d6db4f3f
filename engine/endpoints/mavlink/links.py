"""Byte pipes under a MAVLink connection: serial device, UDP (``udpin``/``udpout``), TCP
(``tcp`` client, ``tcpin`` server), all driven by asyncio.

A link hands every received chunk to ``on_bytes(data, peer)`` and writes whole frames with
``transmit``; it translates OS errors into :class:`EndpointError` (through errors.py, the
package's one table) and reconnects on its own
(a serial device that disappears is reopened, a TCP client reconnects, both waiting with the
engine's one backoff, :mod:`engine.common.backoff`). Used by the engine's connections and by the
simulated vehicle alike.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import termios
import time
from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

from engine.common.backoff import Backoff
from engine.endpoints.base import EndpointError
from engine.endpoints.mavlink.errors import edge_error, mapped
from engine.endpoints.mavlink.settings import Address

PEER_TTL = 30.0
MAX_PEERS = 256
"""Peers a ``udpin`` link remembers (the least recently heard goes first): one per MAVLink system
id and then some. It was 8, and a fleet of 50 vehicles on a few links (bench/fleet.py) made a
command for a forgotten vehicle go to every remembered peer instead of its own."""
READ_CHUNK = 4096
UDP_CLOSE_TIMEOUT = 1.0
"""Bound on waiting for asyncio to close a UDP socket (it takes one loop turn)."""
UDP_RECEIVE_BUFFER = 4 << 20
"""Bytes of kernel receive buffer asked for a UDP link (the kernel caps it at
``net.core.rmem_max``). The default (~200 KB) holds about 250 small datagrams, 40 ms of
telemetry at 6,000 msg/s: any longer pause of the loop (a reload, a busy CPU) drops frames."""

REOPEN_FIRST_S = 0.5
REOPEN_CAP_S = 2.0
"""A serial device that went away is tried again after 0.25-0.5 s, then at most every 1-2 s:
a USB radio plugged back in is read again within about two seconds, and a device that stays
away costs an open() call per second or two."""
RECONNECT_FIRST_S = 1.0
RECONNECT_CAP_S = 10.0
"""A TCP client whose server went away tries again after 0.5-1 s, doubling to 5-10 s: an
autopilot or SITL restarting takes seconds, and many links do not retry in step."""

OnBytes = Callable[[bytes, Hashable], None]


class Link:
    """A byte pipe: received chunks go to ``on_bytes(data, peer)``; ``transmit`` writes a frame
    (to ``peer`` alone where the link can tell peers apart and has heard it lately: a ``udpin``
    link shared by several vehicles; everywhere else to every peer)."""

    datagrams = False
    """True where each chunk is a datagram, parsed on its own (framing.py); else a byte stream."""
    relayed = False
    """True where another process writes what is transmitted (a worker's end of a link split
    over workers, split.py): it counts ``split_sent``, the writer ``frames_sent``."""

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> None:
        self.address = address
        self.on_bytes = on_bytes
        self.stats = stats
        self.closed = False
        self.local_address: tuple[str, int] | None = None
        self.on_lost: Callable[[], None] | None = None
        """Called when the device went away (the peer of a pty closed it, a USB radio unplugged)."""

    async def open(self) -> None:
        raise NotImplementedError

    @property
    def ready(self) -> bool:
        """Whether a frame written now has somewhere to go."""
        return not self.closed

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
        raise NotImplementedError

    def peer_for(self, system: int, heard: dict[int, Hashable]) -> Hashable | None:
        """Where a frame for ``system`` goes: the peer its last accepted frame came from
        (``heard``, the port's); None: every peer."""
        return heard.get(system)

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


class SerialLink(Link):
    """A tty read with ``add_reader``; reopened every second after the device disappears."""

    _fd: int | None = None
    _reopen: asyncio.Task[None] | None = None

    async def open(self) -> None:
        with mapped(f"cannot open {self.address.device}"):
            self._open()

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
        if self.on_lost is not None:
            self.on_lost()
        if not self.closed and self._reopen is None:
            self._reopen = loop.create_task(self._reopen_loop())

    async def _reopen_loop(self) -> None:
        backoff = Backoff(REOPEN_FIRST_S, REOPEN_CAP_S)
        try:
            while not self.closed:
                await asyncio.sleep(backoff.next())
                with contextlib.suppress(OSError, termios.error):
                    self._open()
                    return
        finally:
            self._reopen = None

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
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
                raise edge_error(exc, f"write to {self.address.device} failed") from None

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
    def __init__(self, link: UdpLink) -> None:
        self.link = link
        self.lost: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        """Done once asyncio closed the socket (the loop turn after ``transport.close()``)."""

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.lost.done():
            self.lost.set_result(None)

    def datagram_received(self, data: bytes, addr: Any) -> None:
        self.link.received(data, addr)

    def error_received(self, exc: Exception) -> None:
        """ICMP port unreachable while the peer is not up yet; the next datagram may succeed."""
        self.link._count("udp_errors")


class UdpLink(Link):
    """``udpout`` sends to its remote; ``udpin`` answers every peer heard in the last 30 s."""

    datagrams = True

    _transport: asyncio.DatagramTransport | None = None
    _protocol: _Datagrams | None = None

    def __init__(self, address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> None:
        super().__init__(address, on_bytes, stats)
        self.peers: OrderedDict[Any, float] = OrderedDict()

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        where = (self.address.host, self.address.port)
        try:
            if self.address.kind == "udpin":
                transport, protocol = await loop.create_datagram_endpoint(lambda: _Datagrams(self), local_addr=where)
            else:
                transport, protocol = await loop.create_datagram_endpoint(lambda: _Datagrams(self), remote_addr=where)
        except OSError as exc:
            raise edge_error(exc, f"cannot open {self.address.kind}:{where[0]}:{where[1]}") from None
        with contextlib.suppress(OSError, AttributeError):
            transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RECEIVE_BUFFER)
        self._transport = transport
        self._protocol = protocol
        self.local_address = transport.get_extra_info("sockname")[:2]

    @property
    def ready(self) -> bool:
        if self.address.kind == "udpout":
            return self._transport is not None
        now = time.monotonic()
        return any(now - seen < PEER_TTL for seen in self.peers.values())

    def received(self, data: bytes, addr: Any) -> None:
        self.heard(addr)
        self.on_bytes(data, addr)

    def heard(self, addr: Any) -> None:
        """A ``udpin`` link remembers who wrote to it last (the peers it answers)."""
        if self.address.kind == "udpin":
            self.peers[addr] = time.monotonic()
            self.peers.move_to_end(addr)
            while len(self.peers) > MAX_PEERS:
                self.peers.popitem(last=False)

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
        if self._transport is None or self._transport.is_closing():
            raise EndpointError("udp link is closed")
        if self.address.kind == "udpout":
            self._transport.sendto(data)
            return
        now = time.monotonic()
        if peer is not None and now - self.peers.get(peer, -PEER_TTL) < PEER_TTL:
            assert isinstance(peer, tuple)  # a key of self.peers: a (host, port) address
            self._transport.sendto(data, peer)  # a targeted message: only where its vehicle was heard
            return
        peers = [addr for addr, seen in self.peers.items() if now - seen < PEER_TTL]
        if not peers:
            raise EndpointError(self._no_peer(now))
        for addr in peers:
            self._transport.sendto(data, addr)

    def _no_peer(self, now: float) -> str:
        """Why a ``udpin`` link has nowhere to write: nobody was ever heard, or every peer
        expired (issue 31: it said "not heard from any peer yet" though it had)."""
        where = f"udpin:{self.address.host}:{self.address.port}"
        if not self.peers:
            return f"{where} has not heard from any peer yet (a udpin link writes only to peers it has heard)"
        last, heard = next(reversed(self.peers.items()))
        peer = ":".join(map(str, last[:2])) if isinstance(last, tuple) else str(last)
        return (f"{where}: no peer heard in the last {PEER_TTL:g} s (a peer expires {PEER_TTL:g} s after its last "
                f"datagram); the last, {peer}, was heard {now - heard:.1f} s ago")

    async def close(self) -> None:
        """Return once the socket is closed, so the port is free for a connection that takes
        it over (break-before-make); asyncio closes it a loop turn after ``transport.close``."""
        await super().close()
        if self._transport is not None:
            self._transport.close()
        if self._protocol is not None:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.shield(self._protocol.lost), UDP_CLOSE_TIMEOUT)


class TcpLink(Link):
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
            raise edge_error(exc, f"cannot open {self.address.kind}:{host}:{port}") from None

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
        backoff = Backoff(RECONNECT_FIRST_S, RECONNECT_CAP_S)
        while not self.closed:
            await self._pump(reader, writer)
            self._count("link_lost")
            backoff.reset()
            while not self.closed:
                await asyncio.sleep(backoff.next())
                try:
                    reader, writer = await asyncio.open_connection(self.address.host, self.address.port)
                    break
                except OSError:
                    pass

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

    async def transmit(self, data: bytes, peer: Hashable | None = None) -> None:
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


def make_link(address: Address, on_bytes: OnBytes, stats: dict[str, int]) -> Link:
    if address.kind == "serial":
        return SerialLink(address, on_bytes, stats)
    if address.kind in ("udpin", "udpout"):
        return UdpLink(address, on_bytes, stats)
    return TcpLink(address, on_bytes, stats)

