"""A private mosquitto broker (Debian's ``mosquitto`` 2.0) for tests, demos and ``--local-broker``.

Each broker gets its own configuration file, port, persistence directory and log in a
directory of its own, so several run side by side and none touches the system's broker.
It runs in its own process group (optionally under ``timeout -s KILL``, so a test that dies
cannot leave it behind) and can be stopped and started again on the same port and data:
a clean stop (SIGTERM) writes the persistence file, so persistent sessions, their
subscriptions and the messages queued for them come back, as after a real broker restart.

Started as root, mosquitto would switch to the ``mosquitto`` user, which cannot write the
private directory; the configuration names the current user instead (ignored when not root).

With ``tls`` (``--local-broker-tls``) its one listener speaks TLS only (mosquitto's ``cafile``,
``certfile``, ``keyfile`` after ``listener``), with a certificate for ``localhost`` from a CA
made when it starts (engine/common/tls.py, openssl); clients verify it against that CA and need no
certificate of their own, as with the private RabbitMQ node.
"""

from __future__ import annotations

import os
import pwd
import shutil
import tempfile
from pathlib import Path
from typing import Iterable

from engine.common.processes import BrokerError, ServerProcess, listening_port
from engine.common.tls import ThrowawayCertificates, throwaway_certificates

MOSQUITTO = "mosquitto"
INSTALL_HINT = "mosquitto is not installed (apt-get install -y mosquitto), or set MOSQUITTO_BIN to its path"


class MosquittoError(RuntimeError):
    """The broker could not be started (not installed, a bad configuration, no port)."""


def find_mosquitto() -> str:
    configured = os.environ.get("MOSQUITTO_BIN")
    if configured:
        return configured
    found = shutil.which(MOSQUITTO) or next(
        (path for path in ("/usr/sbin/mosquitto", "/usr/local/sbin/mosquitto") if os.access(path, os.X_OK)), None)
    if found is None:
        raise MosquittoError(INSTALL_HINT)
    return found


class LocalMosquitto(ServerProcess):
    """``with LocalMosquitto() as broker: broker.url``; stopped and its directory deleted on exit.

    ``max_queued_messages`` bounds what mosquitto keeps per offline persistent session
    (its own default, 1000, would drop messages published while an engine is down for a
    few seconds at a high rate; 0 is unlimited). ``lifetime`` (seconds; default
    $RABBITROS_PRIVATE_BROKER_LIFETIME, else none) kills the broker from outside if its owner
    never stops it. ``extra`` are more configuration lines."""

    def __init__(
        self,
        directory: Path | None = None,
        port: int | None = None,
        keep_dir: bool = False,
        max_queued_messages: int = 0,
        lifetime: float | None = None,
        extra: Iterable[str] = (),
        tls: bool = False,
    ) -> None:
        super().__init__(directory or Path(tempfile.mkdtemp(prefix="rabbitros-mosquitto-")), keep_dir, lifetime)
        self.port = port or listening_port()
        self.max_queued_messages = max_queued_messages
        self.extra = tuple(extra)
        self.tls = tls
        self.certificates: ThrowawayCertificates | None = None
        """With ``tls``: the CA and the broker's certificate, made at the first start."""

    error = MosquittoError

    @property
    def url(self) -> str:
        """With ``tls``, by name (``localhost``, as its certificate names a host)."""
        return f"mqtts://localhost:{self.port}" if self.tls else f"mqtt://127.0.0.1:{self.port}"

    @property
    def ca_file(self) -> Path | None:
        return self.certificates.ca_file if self.certificates is not None else None

    @property
    def config_file(self) -> Path:
        return self.directory / "mosquitto.conf"

    @property
    def log_file(self) -> Path:
        return self.directory / "mosquitto.log"

    def configuration(self) -> str:
        data = self.directory / "data"
        data.mkdir(exist_ok=True)
        lines = [f"listener {self.port} 127.0.0.1"]
        if self.tls:
            if self.certificates is None:
                self.certificates = throwaway_certificates(self.directory / "tls", "localhost")
            lines += [f"cafile {self.certificates.ca_file}", f"certfile {self.certificates.cert_file}",
                      f"keyfile {self.certificates.key_file}", "require_certificate false", "tls_version tlsv1.2"]
        lines += [
            "allow_anonymous true",
            f"user {pwd.getpwuid(os.getuid()).pw_name}",
            "persistence true",
            f"persistence_location {data}/",
            f"max_queued_messages {self.max_queued_messages}",
            f"log_dest file {self.log_file}",
            "log_type error",
            "log_type warning",
            "log_type notice",
            "log_type information",
            "connection_messages true",
            *self.extra,
        ]
        return "\n".join(lines) + "\n"

    def start(self, timeout: float = 20.0) -> str:
        """Start the broker (again, after :meth:`halt` or :meth:`kill`: same port and data)."""
        if self.running:
            return self.url
        try:
            configuration = self.configuration()
        except RuntimeError as exc:  # openssl missing or failing: the throwaway certificates
            raise MosquittoError(f"TLS listener: {exc}") from None
        self.config_file.write_text(configuration)
        self._launch([find_mosquitto(), "-c", str(self.config_file)], self.directory / "mosquitto.out")
        self._wait_listening("mosquitto", [self.port], timeout, poll=0.05)
        return self.url

    def _tail(self) -> str:
        lines: list[str] = []
        for name in ("mosquitto.out", "mosquitto.log"):
            try:
                lines += (self.directory / name).read_text(errors="replace").splitlines()[-5:]
            except OSError:
                continue
        return " | ".join(lines)



URL_ENV = "RABBITROS_MQTT_URL"
"""The broker of an MQTT connection that names no ``url`` (else mqtt://localhost:1883);
``run --local-broker`` sets it to the private mosquitto's."""
CA_ENV = "RABBITROS_MQTT_CA_FILE"
"""The CA an MQTT connection that names no ``url`` (nor ``tls``) verifies its broker against;
``run --local-broker --local-broker-tls`` sets it to the private mosquitto's throwaway CA."""
CHECK_ENV: dict[str, str | None] = {URL_ENV: "mqtt://local-broker.invalid:1883", CA_ENV: None}
"""``check --local-broker``'s stand-in for the private broker's URL (``.invalid`` is never a host)."""
ALWAYS = False
"""Started by ``--local-broker`` only when the routes have an MQTT connection."""


class PrivateMosquitto:
    """``--local-broker``'s MQTT broker: one mosquitto (it does not cluster); with ``tls``
    (``--local-broker-tls``) listening with TLS only, its URL ``mqtts://localhost:PORT`` and
    its CA in :data:`CA_ENV`, which connections without a url verify it against."""

    def __init__(self, cluster: int = 1, tls: bool = False) -> None:
        self.broker = LocalMosquitto(tls=tls)

    @property
    def nodes(self) -> list[str]:
        return [f"mosquitto on port {self.broker.port}"]

    @property
    def urls(self) -> list[str]:
        return [self.broker.url]

    @property
    def environment(self) -> dict[str, str]:
        ca_file = self.broker.ca_file
        return {URL_ENV: self.broker.url, **({CA_ENV: str(ca_file)} if ca_file is not None else {})}

    def start(self) -> object:
        try:
            return self.broker.start()
        except MosquittoError as exc:
            raise BrokerError(str(exc)) from exc

    def stop(self) -> None:
        self.broker.stop()


def private_broker(cluster: int = 1, tls: bool = False) -> PrivateMosquitto:
    return PrivateMosquitto(cluster, tls)
