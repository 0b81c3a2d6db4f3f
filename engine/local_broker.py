"""A private RabbitMQ node for demos and tests, on a machine with no broker set up.

Debian's ``rabbitmq-server`` wrapper switches user and drops the environment, so the
package's own ``sbin/rabbitmq-server`` is run instead, with its own HOME (the Erlang
cookie), node name, ports, data and log directories in a temporary directory. The node
runs in its own process group so it can be stopped, and killed if it will not stop.
"""

from __future__ import annotations

import glob
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

SERVER_GLOB = "/usr/lib/rabbitmq/lib/rabbitmq_server-*/sbin/rabbitmq-server"


class BrokerError(RuntimeError):
    pass


def find_server() -> str:
    configured = os.environ.get("RABBITMQ_SERVER_BIN")
    if configured:
        return configured
    found = sorted(glob.glob(SERVER_GLOB))
    if not found:
        raise BrokerError(
            "rabbitmq-server is not installed (apt-get install -y rabbitmq-server), "
            "or set RABBITMQ_SERVER_BIN to its sbin/rabbitmq-server"
        )
    return found[-1]


def _free_port(preferred: int | None = None) -> int:
    with socket.socket() as sock:
        try:
            sock.bind(("127.0.0.1", preferred or 0))
        except OSError:
            sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


class LocalBroker:
    """``with LocalBroker() as broker: broker.url``; stopped and deleted on exit."""

    def __init__(self, keep_dir: bool = False) -> None:
        self.keep_dir = keep_dir
        self.directory = Path(tempfile.mkdtemp(prefix="rabbitros-broker-"))
        self.port = _free_port()
        self.dist_port = _free_port(self.port + 20000 if self.port + 20000 < 65536 else None)
        self.node = f"rabbitros-{uuid.uuid4().hex[:8]}@localhost"
        self._process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"amqp://guest:guest@127.0.0.1:{self.port}/"

    @property
    def log_file(self) -> Path:
        return self.directory / "server.out"

    def environment(self) -> dict[str, str]:
        home = self.directory
        (home / "enabled_plugins").write_text("[].\n")
        return {
            **os.environ,
            "HOME": str(home),
            "RABBITMQ_NODENAME": self.node,
            "RABBITMQ_NODE_IP_ADDRESS": "127.0.0.1",
            "RABBITMQ_NODE_PORT": str(self.port),
            "RABBITMQ_DIST_PORT": str(self.dist_port),
            "RABBITMQ_MNESIA_BASE": str(home / "mnesia"),
            "RABBITMQ_LOG_BASE": str(home / "log"),
            "RABBITMQ_ENABLED_PLUGINS_FILE": str(home / "enabled_plugins"),
            "RABBITMQ_CONFIG_FILE": str(home / "rabbitmq"),
            "RABBITMQ_PID_FILE": str(home / "rabbitmq.pid"),
        }

    def start(self, timeout: float = 90.0) -> str:
        """Start the node (again, after :meth:`kill` or :meth:`halt`: same data directory,
        node name and ports, so durable queues and persistent messages come back)."""
        server = find_server()
        with open(self.log_file, "ab") as out:
            self._process = subprocess.Popen(
                [server],
                env=self.environment(),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                cwd=self.directory,
                start_new_session=True,
            )
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._process.poll() is not None:
                raise BrokerError(f"rabbitmq-server exited with {self._process.returncode}: {self._tail()}")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5):
                    return self.url
            except OSError:
                time.sleep(0.25)
        self.stop()
        raise BrokerError(f"rabbitmq-server did not listen on {self.port} within {timeout:.0f}s: {self._tail()}")

    def ctl(self, *args: str, timeout: float = 60.0) -> str:
        """Run ``rabbitmqctl`` against this node (e.g. ``add_user``); returns its output."""
        ctl = str(Path(find_server()).with_name("rabbitmqctl"))
        done = subprocess.run(
            [ctl, "-n", self.node, *args], env=self.environment(), capture_output=True, text=True, timeout=timeout,
        )
        if done.returncode != 0:
            raise BrokerError(f"rabbitmqctl {args[0]} failed: {done.stderr.strip() or done.stdout.strip()}")
        return done.stdout

    def _tail(self) -> str:
        try:
            return " | ".join(self.log_file.read_text(errors="replace").splitlines()[-5:])
        except OSError:
            return ""

    @property
    def running(self) -> bool:
        return self._process is not None and self._process.poll() is None

    def kill(self) -> None:
        """``kill -9`` the node (its whole process group), keeping its data for a restart."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            process.wait()

    def halt(self, timeout: float = 20.0) -> None:
        """Stop the node cleanly (SIGTERM), keeping its data for a restart."""
        process, self._process = self._process, None
        if process is not None and process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGTERM)
                process.wait(timeout)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            except ProcessLookupError:
                pass

    def stop(self, timeout: float = 20.0) -> None:
        self.halt(timeout)
        if not self.keep_dir:
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> LocalBroker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
