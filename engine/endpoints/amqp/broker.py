"""Private RabbitMQ nodes (one, or a cluster) for demos, tests and ``--local-broker``
(engine/ops/local_broker.py asks :func:`private_broker`), on a machine with no broker set up.

Debian's ``rabbitmq-server`` wrapper switches user and drops the environment, so the
package's own ``sbin/rabbitmq-server`` is run instead, with its own HOME (the Erlang
cookie), node name, ports, data and log directories in a temporary directory. The node
runs in its own process group so it can be stopped, and killed if it will not stop.

A :class:`LocalCluster` runs several such nodes with one cookie and joins them with
``rabbitmqctl join_cluster``; a node can be killed with -9 and restarted on its data
directory, which is how the tests lose a broker node mid-stream.
"""

from __future__ import annotations

import glob
import os
import shutil
import subprocess
import tempfile
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable
from urllib.parse import urlsplit

from engine.common.processes import BrokerError, ServerProcess, listening_port
from engine.common.tls import throwaway_certificates

SERVER_GLOB = "/usr/lib/rabbitmq/lib/rabbitmq_server-*/sbin/rabbitmq-server"
QUIET_SCHEDULERS = "+sbwt none +sbwtdcpu none +sbwtdio none"
"""Erlang schedulers spin while idle by default; on a small shared machine three idle nodes
would burn a core between them doing nothing."""


URL_ENV = "RABBITROS_AMQP_URL"
"""The default connection's URL; ``run --local-broker`` sets it to the private node's."""
URLS_ENV = "RABBITROS_AMQP_URLS"
"""Every node's URL of ``run --local-broker --cluster N`` (space-separated)."""
CA_ENV = "RABBITROS_AMQP_CA_FILE"
"""The CA the default connection verifies the broker against; ``run --local-broker
--local-broker-tls`` sets it to the private node's throwaway CA."""
ALWAYS = True
"""Started by every ``--local-broker`` (the default connection, and the dead letters' broker)."""
CHECK_ENV: dict[str, str | None] = {URL_ENV: "amqp://guest:guest@local-broker.invalid/", URLS_ENV: None, CA_ENV: None}
"""``check --local-broker``'s stand-in for the private node's URL (``.invalid`` is never a host)."""
PLUGINS = ("rabbitmq_consistent_hash_exchange",)
"""Plugins every private node runs: the consistent-hash exchange partitioned ordered routes
declare (``ordered: {partitions: N}``, partitions.py); it ships with rabbitmq-server 3.10."""
_LOOPBACK = frozenset({"localhost", "127.0.0.1", "::1", "ip6-localhost"})


def node_address(url: str) -> tuple[str, int]:
    """``(host, port)`` a URL connects to; every loopback name is one host."""
    try:
        parts = urlsplit(url)
        host, port = (parts.hostname or "localhost").lower(), parts.port
    except ValueError:
        return url, 0
    return ("localhost" if host in _LOOPBACK else host), port or (5671 if parts.scheme == "amqps" else 5672)


def elsewhere(urls: Iterable[str], private: Iterable[str]) -> list[str]:
    """The URLs among ``urls`` that lead to none of the ``private`` nodes' URLs."""
    nodes = {node_address(url) for url in private}
    return [url for url in urls if node_address(url) not in nodes]


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


@dataclass(frozen=True)
class BrokerTls:
    """A TLS listener for the private node (tests and demos of ``amqps://``): the node's
    certificate and key, the CA its clients' certificates must chain to, whether it asks
    for (``verify_peer``) and insists on (``fail_if_no_peer_cert``) a client certificate,
    and whether a client certificate may log in by itself (EXTERNAL, the common name as
    the user name, plugin rabbitmq_auth_mechanism_ssl)."""

    ca_file: Path
    cert_file: Path
    key_file: Path
    verify_peer: bool = True
    fail_if_no_peer_cert: bool = True
    external_auth: bool = False

    def config(self, port: int) -> str:
        """The node's rabbitmq.conf (new-style sysctl format) for this listener."""
        lines = [
            f"listeners.ssl.1 = 127.0.0.1:{port}",
            f"ssl_options.cacertfile = {self.ca_file}",
            f"ssl_options.certfile = {self.cert_file}",
            f"ssl_options.keyfile = {self.key_file}",
            f"ssl_options.verify = {'verify_peer' if self.verify_peer else 'verify_none'}",
            f"ssl_options.fail_if_no_peer_cert = {'true' if self.fail_if_no_peer_cert else 'false'}",
        ]
        if self.external_auth:
            lines += ["auth_mechanisms.1 = PLAIN", "auth_mechanisms.2 = AMQPLAIN", "auth_mechanisms.3 = EXTERNAL",
                      "ssl_cert_login_from = common_name"]
        return "\n".join(lines) + "\n"


class LocalBroker(ServerProcess):
    """``with LocalBroker() as broker: broker.url``; stopped and deleted on exit.
    ``LocalBroker(tls=BrokerTls(...))`` adds a TLS listener: ``broker.tls_url``.
    ``lifetime`` (seconds; default $RABBITROS_PRIVATE_BROKER_LIFETIME, else none) kills the
    node from outside if its owner never stops it (a killed test run)."""

    def __init__(
        self,
        keep_dir: bool = False,
        directory: Path | None = None,
        node: str | None = None,
        cookie: str | None = None,
        tls: BrokerTls | None = None,
        lifetime: float | None = None,
    ) -> None:
        super().__init__(directory or Path(tempfile.mkdtemp(prefix="rabbitros-broker-")), keep_dir, lifetime)
        self.tls = tls
        self.port = listening_port()
        self.dist_port = listening_port(exclude={self.port})
        self.tls_port = listening_port(exclude={self.port, self.dist_port}) if tls is not None else None
        self.node = node or f"rabbitros-{uuid.uuid4().hex[:8]}@localhost"
        self.cookie = cookie

    @property
    def url(self) -> str:
        return f"amqp://guest:guest@127.0.0.1:{self.port}/"

    @property
    def tls_url(self) -> str:
        """The TLS listener's URL, by name (``localhost``, as a certificate names a host)."""
        if self.tls_port is None:
            raise BrokerError("this node has no TLS listener (LocalBroker(tls=BrokerTls(...)))")
        return f"amqps://guest:guest@localhost:{self.tls_port}/"

    @property
    def log_file(self) -> Path:
        return self.directory / "server.out"

    def environment(self) -> dict[str, str]:
        home = self.directory
        external = self.tls is not None and self.tls.external_auth
        plugins = [*PLUGINS, *(["rabbitmq_auth_mechanism_ssl"] if external else [])]
        (home / "enabled_plugins").write_text(f"[{','.join(plugins)}].\n")
        if self.tls is not None and self.tls_port is not None:
            (home / "rabbitmq.conf").write_text(self.tls.config(self.tls_port))
        if self.cookie is not None:
            _write_cookie(home / ".erlang.cookie", self.cookie)
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
            "RABBITMQ_SERVER_ADDITIONAL_ERL_ARGS": QUIET_SCHEDULERS,
        }

    def start(self, timeout: float = 90.0) -> str:
        """Start the node (again, after :meth:`kill` or :meth:`halt`: same data directory,
        node name and ports, so durable queues and persistent messages come back)."""
        self._launch([find_server()], self.log_file, env=self.environment())
        self._wait_listening("rabbitmq-server", [port for port in (self.port, self.tls_port) if port is not None],
                             timeout, poll=0.25)
        return self.url

    def ctl(self, *args: str, timeout: float = 120.0) -> str:
        """``rabbitmqctl -n NODE ARGS`` with this node's HOME (hence its cookie)."""
        ctl = str(Path(find_server()).with_name("rabbitmqctl"))
        result = subprocess.run(
            ["timeout", "-s", "KILL", str(int(timeout)), ctl, "-n", self.node, *args],
            env=self.environment(), cwd=self.directory, capture_output=True, text=True,
        )
        if result.returncode != 0:
            raise BrokerError(f"rabbitmqctl -n {self.node} {' '.join(args)}: {(result.stderr or result.stdout).strip()[-800:]}")
        return result.stdout

    def _tail(self) -> str:
        try:
            return " | ".join(self.log_file.read_text(errors="replace").splitlines()[-5:])
        except OSError:
            return ""


def _write_cookie(path: Path, cookie: str) -> None:
    """Erlang refuses a cookie file others can read: mode 400, as rabbitmq's docs require."""
    if path.exists():
        if path.read_text() == cookie:
            return
        path.chmod(0o600)
    path.write_text(cookie)
    path.chmod(0o400)


class LocalCluster:
    """``with LocalCluster(3) as cluster: cluster.urls``: private nodes joined in one cluster.

    Every node gets the same cookie (a mode-400 ``.erlang.cookie`` in its own HOME) and its
    own free AMQP and distribution ports; the first node is started, then the others, and
    each joins the first with ``stop_app; join_cluster; start_app``. :meth:`kill` and
    :meth:`restart` lose a node with -9 and bring it back on its data directory and ports.
    """

    def __init__(self, size: int = 3, keep_dir: bool = False, lifetime: float | None = None) -> None:
        if size < 1:
            raise BrokerError("a cluster needs at least one node")
        self.keep_dir = keep_dir
        self.directory = Path(tempfile.mkdtemp(prefix="rabbitros-cluster-"))
        cookie = uuid.uuid4().hex.upper()
        tag = uuid.uuid4().hex[:6]
        self.nodes = [
            LocalBroker(keep_dir=True, directory=self.directory / f"node{index + 1}",
                        node=f"rabbitros-{tag}-{index + 1}@localhost", cookie=cookie, lifetime=lifetime)
            for index in range(size)
        ]

    @property
    def urls(self) -> list[str]:
        return [node.url for node in self.nodes]

    def start(self, timeout: float = 180.0) -> list[str]:
        deadline = time.monotonic() + timeout
        first, *others = self.nodes
        try:
            self._start_nodes(self.nodes, deadline)
            for node in others:
                node.ctl("stop_app")
                node.ctl("join_cluster", first.node)
                node.ctl("start_app")
            self.wait_running(len(self.nodes), max(5.0, deadline - time.monotonic()))
        except BaseException:
            self.stop()
            raise
        return self.urls

    @staticmethod
    def _start_nodes(nodes: list[LocalBroker], deadline: float) -> None:
        """Start nodes side by side (each takes 10-20 s to boot, mostly waiting)."""
        errors: list[BaseException] = []

        def boot(node: LocalBroker) -> None:
            try:
                node.start(max(5.0, deadline - time.monotonic()))
            except BaseException as exc:  # reported by the caller
                errors.append(exc)

        threads = [threading.Thread(target=boot, args=(node,)) for node in nodes]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        if errors:
            raise errors[0]

    def running_nodes(self) -> list[str]:
        """The cluster's running nodes, as seen by the first node that answers."""
        for node in self.nodes:
            if not node.running:
                continue
            try:
                out = node.ctl("eval", "rabbit_nodes:all_running().", timeout=30)
            except BrokerError:
                continue
            return [name for name in _atoms(out)]
        return []

    def wait_running(self, count: int, timeout: float = 90.0) -> None:
        deadline = time.monotonic() + timeout
        seen: list[str] = []
        while time.monotonic() < deadline:
            seen = self.running_nodes()
            if len(seen) >= count:
                return
            time.sleep(0.5)
        raise BrokerError(f"cluster has {len(seen)} running nodes, wanted {count}: {seen}")

    def kill(self, index: int) -> None:
        """Lose node ``index`` with SIGKILL; its data directory and ports stay for a restart."""
        self.nodes[index].kill()

    def restart(self, index: int, timeout: float = 120.0) -> None:
        """Start a killed node again on its data directory; it rejoins the cluster by itself."""
        node = self.nodes[index]
        node.start(timeout)
        node.ctl("await_startup", timeout=timeout)

    def stop(self) -> None:
        for node in reversed(self.nodes):
            node.stop()
        if not self.keep_dir:
            shutil.rmtree(self.directory, ignore_errors=True)

    def __enter__(self) -> LocalCluster:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _atoms(erlang_term: str) -> list[str]:
    """Node names from an Erlang list printed by ``rabbitmqctl eval``: ['a@h','b@h']."""
    return [part.strip(" '\n[]") for part in erlang_term.strip().strip("[]").split(",") if "@" in part]


class PrivateRabbitMQ:
    """``--local-broker``'s RabbitMQ: one node, or ``cluster`` nodes joined (quorum queues);
    with ``tls`` (``--local-broker-tls``, one node) the node also listens with TLS, with a
    certificate for ``localhost`` from a CA made at start in its directory, and the default
    connection is that listener's ``amqps://`` URL, verified against the CA."""

    def __init__(self, cluster: int = 1, tls: bool = False) -> None:
        if tls and cluster > 1:
            raise BrokerError("--local-broker-tls starts one node: leave out --cluster")
        self.tls_directory: Path | None = None
        if tls:
            directory = Path(tempfile.mkdtemp(prefix="rabbitros-broker-"))
            self.tls_directory = directory / "tls"
            ca_file, cert_file, key_file = (self.tls_directory / name for name in ("ca.pem", "server.pem", "server.key"))
            # the client needs no certificate: the throwaway CA signs only the node's
            node_tls = BrokerTls(ca_file, cert_file, key_file, verify_peer=False, fail_if_no_peer_cert=False)
            self.broker: LocalBroker | LocalCluster = LocalBroker(directory=directory, tls=node_tls)
        else:
            self.broker = LocalCluster(cluster) if cluster > 1 else LocalBroker()

    @property
    def nodes(self) -> list[str]:
        return [node.node for node in self.broker.nodes] if isinstance(self.broker, LocalCluster) else [self.broker.node]

    @property
    def urls(self) -> list[str]:
        if isinstance(self.broker, LocalCluster):
            return self.broker.urls
        return [self.broker.tls_url if self.broker.tls is not None else self.broker.url]

    @property
    def environment(self) -> dict[str, str]:
        urls = self.urls
        environment = {URL_ENV: urls[0], **({URLS_ENV: " ".join(urls)} if len(urls) > 1 else {})}
        if isinstance(self.broker, LocalBroker) and self.broker.tls is not None:
            environment[CA_ENV] = str(self.broker.tls.ca_file)
        return environment

    def start(self) -> object:
        if self.tls_directory is not None:
            try:
                throwaway_certificates(self.tls_directory, "localhost")
            except RuntimeError as exc:
                self.broker.stop()
                raise BrokerError(f"--local-broker-tls: {exc}") from None
        return self.broker.start()

    def stop(self) -> None:
        self.broker.stop()


def private_broker(cluster: int = 1, tls: bool = False) -> PrivateRabbitMQ:
    return PrivateRabbitMQ(cluster, tls)
