"""Server processes the engine starts for itself: private brokers, and the ports they listen on.

The process side of ``--local-broker`` (engine/ops/local_broker.py starts the brokers the
protocol packages describe): a bounded server process, a free port to give it, and what a
private broker must offer. Kept below the protocol packages, which import it to say how
their broker is started (engine/endpoints/*/broker.py).
"""

from __future__ import annotations

import os
import random
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path
from dataclasses import dataclass
from typing import Collection, Iterable, Mapping, Protocol, Self, Sequence

LOCAL_BROKER_ENV = "RABBITROS_LOCAL_BROKER"
"""Set by ``run --local-broker`` to the private brokers' names (``check --local-broker``:
empty, as none is started), beside the variables each broker sets for its transport."""


LIFETIME_ENV = "RABBITROS_PRIVATE_BROKER_LIFETIME"
"""Seconds after which every private broker started in this environment is killed from outside
(``timeout -s KILL``), whoever started it: the tests set it, so a broker started by a test or by
an engine the test ran cannot outlive a killed run by more than that. Unset: no bound."""


class BrokerError(RuntimeError):
    pass


PORT_FLOOR = 10000
"""The lowest port :func:`listening_port` gives (below: well-known and registered services)."""
EPHEMERAL_RANGE = Path("/proc/sys/net/ipv4/ip_local_port_range")


def listening_port(kind: socket.SocketKind = socket.SOCK_STREAM, exclude: Collection[int] = ()) -> int:
    """A free port on 127.0.0.1 for a server of ours (a private broker, an admin endpoint;
    ``SOCK_DGRAM``: a MAVLink ``udpin`` link), chosen at random below the kernel's ephemeral
    range, and none of ``exclude`` (the ports one server already has: each is free only until
    that server binds it).

    Why not ``bind(0)``: that port is in the ephemeral range, which every outgoing connection on
    the machine draws its local port from. Once our server is down (a test kills a broker and
    starts it again on the same port), a client elsewhere may hold that port, or a client
    retrying to connect to it may connect to itself (a TCP self-connect); the server then
    cannot listen again (``eaddrinuse``). Below the range neither can happen. Drawn from the
    system's randomness (not ``random``'s seeded state, which forked test workers share), so
    parallel workers seldom pick one port; bound once, so that it is free now."""
    ceiling = ephemeral_low()
    if ceiling - PORT_FLOOR >= 1000:
        draw = random.SystemRandom()
        for _ in range(100):
            port = draw.randrange(PORT_FLOOR, ceiling)
            if port in exclude:
                continue
            with socket.socket(socket.AF_INET, kind) as sock:
                try:
                    sock.bind(("127.0.0.1", port))
                except OSError:
                    continue
                return port
    while True:
        with socket.socket(socket.AF_INET, kind) as sock:
            sock.bind(("127.0.0.1", 0))
            port = int(sock.getsockname()[1])
        if port not in exclude:
            return port


def ephemeral_low() -> int:
    """The low end of the kernel's ephemeral port range (Linux's default, 32768, where unknown)."""
    try:
        return int(EPHEMERAL_RANGE.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return 32768


def lifetime_from_environment() -> float | None:
    """:data:`LIFETIME_ENV` in seconds, or None (unset or empty: private brokers live until stopped)."""
    value = os.environ.get(LIFETIME_ENV, "").strip()
    if not value:
        return None
    try:
        seconds = float(value)
    except ValueError:
        raise BrokerError(f"{LIFETIME_ENV}={value!r} is not a number of seconds") from None
    if seconds <= 0:
        raise BrokerError(f"{LIFETIME_ENV}={value!r} must be more than 0 seconds")
    return seconds


def bounded(command: list[str], lifetime: float | None) -> list[str]:
    """``command`` under ``timeout -s KILL lifetime`` (none: as it is). ``timeout`` runs it in its
    own process group and kills the whole group when the time is up, helpers included; a SIGTERM
    to ``timeout`` reaches the command, and ``timeout`` waits for it, so a clean stop stays clean."""
    if lifetime is None:
        return command
    return ["timeout", "-s", "KILL", str(max(1, int(lifetime))), *command]


class ServerProcess:
    """One broker process of our own, from start to stop, the same way for every protocol:
    started in its own process group under the lifetime bound (:func:`bounded`), ready once
    every port it serves accepts a connection, halted with SIGTERM to the group (the broker
    saves what it keeps), killed with SIGKILL as in a power cut, its directory removed on
    :meth:`stop` unless ``keep_dir``. Subclasses say how to run the broker (:meth:`start`
    calls :meth:`_launch` and :meth:`_wait_listening`) and what their log says (:meth:`_tail`)."""

    error: type[Exception] = BrokerError
    """Raised when the process exits or never listens (the subclass's own error type)."""

    def __init__(self, directory: Path, keep_dir: bool, lifetime: float | None) -> None:
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)
        self.keep_dir = keep_dir
        self.lifetime = lifetime if lifetime is not None else lifetime_from_environment()
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def start(self) -> str:
        raise NotImplementedError

    def _tail(self) -> str:
        """The last lines of the broker's log, for an error message."""
        return ""

    def _launch(self, command: list[str], output: Path, env: Mapping[str, str] | None = None) -> None:
        with open(output, "ab") as out:
            self._process = subprocess.Popen(
                bounded(command, self.lifetime), env=env, stdin=subprocess.DEVNULL, stdout=out,
                stderr=subprocess.STDOUT, cwd=self.directory, start_new_session=True,
            )

    def _wait_listening(self, name: str, ports: Iterable[int], timeout: float, poll: float) -> None:
        """Until every port takes a connection; the error (the log's tail in it) if the
        process exits first or ``timeout`` passes (then it is killed)."""
        assert self._process is not None
        ports = list(ports)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise self.error(f"{name} exited with {self._process.returncode}: {self._tail()}")
            try:
                for port in ports:
                    with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                        pass
                return
            except OSError:
                time.sleep(poll)
        self.kill()
        raise self.error(f"{name} did not listen on {ports[0]} within {timeout:.0f}s: {self._tail()}")

    def halt(self, timeout: float = 20.0) -> None:
        """Stop cleanly (SIGTERM to the group), keeping the data for a restart."""
        process, self._process = self._process, None
        if process is None or process.poll() is not None:
            return
        try:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
        except ProcessLookupError:
            pass

    def kill(self) -> None:
        """SIGKILL the whole group at once: what was not saved yet is lost; the data stays."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            process.wait()

    def stop(self, timeout: float = 20.0) -> None:
        self.halt(timeout)
        if not self.keep_dir:
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


class PrivateBroker(Protocol):
    """One protocol's private broker (or cluster of nodes)."""

    nodes: Sequence[str]
    """What logs and load warnings call it (node names)."""

    @property
    def urls(self) -> list[str]: ...

    @property
    def environment(self) -> Mapping[str, str]:
        """What the protocol's default connection reads to use this broker."""

    def start(self) -> object:
        """Start and wait until it serves; BrokerError if it cannot."""

    def stop(self) -> None: ...


@dataclass(frozen=True)
class ProcessUsage:
    """What a process has used, as Linux's /proc tells it."""

    cpu_s: float
    """User + system seconds of every thread since it started."""
    rss_bytes: int
    """Resident memory now."""
    group: int
    """Its process group (a broker node under ``timeout``, a supervisor's worker)."""


def process_usage(pid: int) -> ProcessUsage | None:
    """Process ``pid``'s use of the machine from /proc/PID/stat; None once it is gone, or
    where there is no /proc. One reader for the supervisor's status of its workers and the
    benchmarks' CPU per message."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()  # the name may hold spaces
        return ProcessUsage(cpu_s=(int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK"),
                            rss_bytes=int(fields[21]) * os.sysconf("SC_PAGE_SIZE"), group=int(fields[2]))
    except (OSError, IndexError, ValueError):
        return None
