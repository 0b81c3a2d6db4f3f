"""The local sockets between the owner of a split link and its workers (split.py): an
``AF_UNIX`` ``SOCK_SEQPACKET`` socket the owner listens on in the supervisor's runtime
directory, and one connection per worker, which names itself first (:data:`HELLO`).

Kept apart from split.py (what crosses them, and why): the sockets' own faults (a busy end, an
end gone, a socket file left over or removed) are handled here, the same for both ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import socket
from collections import deque
from collections.abc import Callable

from engine.common.backoff import Backoff
from engine.endpoints.base import EndpointError

HELLO = b"W"
"""A worker's first message: its index (2 bytes)."""
LOCAL_BUFFER = 4 << 20
"""Bytes of socket buffer for the local sockets, as for the UDP socket (links.py). The kernel
caps it at ``net.core.wmem_max``: measured with 61-byte messages, 10,923 fit with 4 MiB
allowed, 555 with a stock kernel's 208 KiB (a worker busy for some 0.15 s at 4,000 frames/s
then drops frames; docs/operations.md says to raise it)."""
CONNECT_FIRST_S, CONNECT_CAP_S = 0.05, 1.0
"""A worker tries the owner's socket again after 25-50 ms, at most every 0.5-1 s: workers
start together, and an owner started again is reached within a second."""
READS_PER_WAKE = 64
"""Datagrams read per readiness callback, so one busy socket cannot hold the loop."""

def socket_path(runtime_dir: str, connection: str) -> str:
    """The owner's listening socket for ``connection``: short, as ``AF_UNIX`` paths are (108
    bytes), and the same in every worker."""
    tag = hashlib.blake2b(connection.encode(), digest_size=4).hexdigest()
    return os.path.join(runtime_dir, f"mav-{tag}.sock")


def _local_socket() -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    _local_options(sock)
    return sock


def _local_options(sock: socket.socket) -> None:
    sock.setblocking(False)
    for option in (socket.SO_RCVBUF, socket.SO_SNDBUF):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, option, LOCAL_BUFFER)


def _read(sock: socket.socket, on_message: Callable[[bytes], None]) -> bool:
    """Up to :data:`READS_PER_WAKE` messages of a ready socket; False once the other end closed."""
    for _ in range(READS_PER_WAKE):
        try:
            data = sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return True
        except OSError:
            return False
        if not data:
            return False
        on_message(data)
    return True


class LocalConnection:
    """One end of a connection between the owner and a worker, as it sends. A vehicle's frame
    that finds the socket full is dropped (the other end is busy: lost, as UDP telemetry is); a
    message that must arrive (``keep``: a lock's ask, grant or release, split_leases.py) waits
    for room instead, in order: a lost grant left its worker waiting for good while the owner
    held the lock for it, a lost release held the lock from every worker."""

    def __init__(self, sock: socket.socket, on_broken: Callable[[LocalConnection], None]) -> None:
        self.sock = sock
        self.on_broken = on_broken
        """Called when a send fails for good (the other end went away)."""
        self.backlog: deque[bytes] = deque()
        """What must arrive and waits for room, oldest first (vehicles' frames wait behind it)."""

    def send(self, data: bytes, keep: bool = False) -> bool:
        """Whether ``data`` went (or, with ``keep``, waits for room); False when the other end
        cannot take it now (full: busy) or went away."""
        if self.backlog:
            if keep:
                self.backlog.append(data)
            return keep
        try:
            self.sock.send(data)
        except (BlockingIOError, InterruptedError):
            if not keep:
                return False
            self.backlog.append(data)
            asyncio.get_running_loop().add_writer(self.sock.fileno(), self._flush)
        except OSError:
            self.on_broken(self)
            return False
        return True

    def _flush(self) -> None:
        while self.backlog:
            try:
                self.sock.send(self.backlog[0])
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.on_broken(self)
                return
            self.backlog.popleft()
        asyncio.get_running_loop().remove_writer(self.sock.fileno())

    def close(self) -> None:
        if self.sock.fileno() >= 0:
            loop = asyncio.get_running_loop()
            loop.remove_reader(self.sock.fileno())
            loop.remove_writer(self.sock.fileno())
        self.backlog.clear()
        self.sock.close()


class OwnerSockets:
    """The owner's end: a listening ``AF_UNIX`` ``SOCK_SEQPACKET`` socket (message boundaries
    kept, as datagrams; chosen over ``SOCK_DGRAM``, whose receive queue holds 10 datagrams
    (``net.unix.max_dgram_qlen``): a worker busy for a few milliseconds lost frames; a 4 MiB
    connection buffer holds some 10,000 frames), and one connection per worker, which names
    itself first (:data:`HELLO`)."""

    def __init__(self, path: str, on_message: Callable[[int, bytes], None], on_gone: Callable[[int], None]) -> None:
        self.path = path
        self.on_message = on_message
        self.on_gone = on_gone
        """Called with a worker's index when its connection closed (it went away)."""
        self.workers: dict[int, LocalConnection] = {}
        self._listening: socket.socket | None = None
        self._bound: tuple[int, int] | None = None
        """(device, inode) of the socket file this owner bound: the one its close removes."""
        self._unnamed: set[LocalConnection] = set()

    def open(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)  # a predecessor's, killed before it closed it
        sock = _local_socket()
        try:
            # the supervisor makes the directory; made again (private) if it was removed meanwhile
            os.makedirs(os.path.dirname(self.path), mode=0o700, exist_ok=True)
            sock.bind(self.path)
            sock.listen(64)
            bound = os.stat(self.path)
        except OSError as exc:
            sock.close()
            raise EndpointError(f"cannot listen on the local socket {self.path}: {exc.strerror or exc}") from None
        self._listening, self._bound = sock, (bound.st_dev, bound.st_ino)
        asyncio.get_running_loop().add_reader(sock.fileno(), self._accept)

    def _accept(self) -> None:
        assert self._listening is not None
        try:
            sock, _ = self._listening.accept()
        except OSError:
            return
        _local_options(sock)
        conn = LocalConnection(sock, self._drop)
        self._unnamed.add(conn)
        asyncio.get_running_loop().add_reader(sock.fileno(), self._readable, conn)

    def _readable(self, conn: LocalConnection) -> None:
        index = next((k for k, named in self.workers.items() if named is conn), None)

        def message(data: bytes) -> None:
            nonlocal index
            if index is None:
                if data[:1] == HELLO and len(data) == 3:
                    index = int.from_bytes(data[1:3], "big")
                    self._unnamed.discard(conn)
                    old = self.workers.get(index)
                    if old is not None and old is not conn:  # its predecessor's: what it held is freed first
                        self._drop(old)
                    self.workers[index] = conn
                return
            self.on_message(index, data)

        if not _read(conn.sock, message):
            self._drop(conn)

    def _drop(self, conn: LocalConnection) -> None:
        gone = [index for index, named in self.workers.items() if named is conn]
        for index in gone:
            del self.workers[index]
        self._unnamed.discard(conn)
        conn.close()
        for index in gone:
            self.on_gone(index)

    def send(self, worker: int, data: bytes, keep: bool = False) -> bool:
        """False when the worker is not connected (down, starting) or cannot take more now
        (with ``keep``, what must arrive: only when not connected; see :class:`LocalConnection`)."""
        conn = self.workers.get(worker)
        return conn is not None and conn.send(data, keep)

    def close(self) -> None:
        for conn in [*self.workers.values(), *self._unnamed]:
            self._drop(conn)
        if self._listening is not None:
            with contextlib.suppress(Exception):
                asyncio.get_running_loop().remove_reader(self._listening.fileno())
            self._listening.close()
            self._listening = None
            with contextlib.suppress(OSError):
                now = os.stat(self.path)
                if (now.st_dev, now.st_ino) == self._bound:  # not a successor's (the owner moved on a reload)
                    os.unlink(self.path)


class WorkerSocket:
    """A worker's end: connected to the owner's socket, again whenever the owner went away (a
    restart), after the engine's backoff."""

    def __init__(self, path: str, index: int, on_message: Callable[[bytes], None], on_lost: Callable[[], None],
                 on_connected: Callable[[], None]) -> None:
        self.path = path
        self.index = index
        self.on_message = on_message
        self.on_lost = on_lost
        """Called when the connection to the owner closed."""
        self.on_connected = on_connected
        """Called once connected (and named) to an owner, the first or one started again."""
        self.connected: LocalConnection | None = None
        self._task: asyncio.Task[None] | None = None
        self._lost: asyncio.Event = asyncio.Event()

    def open(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._keep_connected(), name=f"split-link:{self.path}")

    async def _keep_connected(self) -> None:
        loop = asyncio.get_running_loop()
        backoff = Backoff(CONNECT_FIRST_S, CONNECT_CAP_S)
        while True:
            sock = _local_socket()
            try:
                await loop.sock_connect(sock, self.path)
                sock.send(HELLO + self.index.to_bytes(2, "big"))
            except OSError:
                sock.close()
                await asyncio.sleep(backoff.next())
                continue
            except BaseException:  # cancelled while connecting: the link closes
                sock.close()
                raise
            backoff.reset()
            self._lost.clear()
            conn = self.connected = LocalConnection(sock, self._disconnect)
            loop.add_reader(sock.fileno(), self._readable, conn)
            self.on_connected()
            await self._lost.wait()

    def _readable(self, conn: LocalConnection) -> None:
        if not _read(conn.sock, self.on_message):
            self._disconnect(conn)

    def _disconnect(self, conn: LocalConnection) -> None:
        conn.close()
        if self.connected is conn:
            self.connected = None
            self.on_lost()
        self._lost.set()

    def send(self, data: bytes, keep: bool = False) -> bool:
        """See :meth:`LocalConnection.send`; False while not connected."""
        conn = self.connected
        return conn is not None and conn.send(data, keep)

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
        if self.connected is not None:
            self._disconnect(self.connected)
