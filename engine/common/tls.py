"""TLS for broker connections (AMQP, MQTT): the options, the client context, the checks
of the files, and what a failed handshake means.

One declaration (:class:`TlsOptions`, ``tls: {ca_file, cert_file, key_file,
server_hostname, verify}``) serves every protocol that connects to a broker over TLS, so
its keys, its defaults and its error words are the same everywhere. The context is built
when a connection opens, from the files; the files are the connection's key files
(Transport.key_files), so a renewed certificate changes the connection's fingerprint and the
watcher's reload reopens it. A verification failure arrives as OpenSSL's text, often
wrapped by the client library; :func:`tls_failure` names the check that failed (unknown CA,
hostname mismatch, expired, no client certificate, not a TLS port), for the log and
``/healthz``.
"""

from __future__ import annotations

import logging
import ssl
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

from engine.common.options import option


@dataclass(frozen=True, kw_only=True)
class TlsOptions:
    """``tls:`` of a broker connection."""

    __schema_description__ = ("TLS: the CA the broker's certificate must chain to, the client certificate; files read when the "
                              "connection opens, a renewed one reopens it. A failed check is a connection error naming it, never plain TCP")

    ca_file: str | None = option(None, description="CA certificates (PEM) the broker's certificate must chain to; default: the system's CAs")
    cert_file: str | None = option(None, description="client certificate (PEM) presented to the broker")
    key_file: str | None = option(None, description="private key (PEM) of cert_file; default: cert_file holds it too")
    server_hostname: str | None = option(None, description="name the broker's certificate must be valid for; default: the URL's host")
    verify: bool = option(True, description="verify the broker's certificate and name; false only for a throwaway test broker")


_ERROR_MEANINGS = (
    (("unable to get local issuer certificate", "self-signed certificate", "self signed certificate",
      "unable to verify the first certificate"),
     "unknown CA: the broker's certificate is not signed by a CA in tls.ca_file"),
    (("hostname mismatch", "ip address mismatch"),
     "hostname mismatch: the broker's certificate is not valid for {host} (tls.server_hostname)"),
    (("certificate has expired",), "the broker's certificate has expired"),
    (("certificate is not yet valid",), "the broker's certificate is not yet valid (check the clock)"),
    (("certificate required", "peer did not return a certificate"),
     "no client certificate: the broker requires one (tls.cert_file, tls.key_file)"),
    (("unknown ca", "bad certificate", "certificate unknown"),
     "client certificate refused: the broker does not trust the CA that signed tls.cert_file"),
    (("wrong version number", "record layer failure", "packet length too long"),
     "not a TLS port: the broker answered without TLS (use the port of its TLS listener)"),
)


@dataclass(frozen=True)
class ThrowawayCertificates:
    """A CA made for one run and a server certificate it signed (``--local-broker-tls``)."""

    ca_file: Path
    cert_file: Path
    key_file: Path


def throwaway_certificates(directory: Path, host: str = "localhost") -> ThrowawayCertificates:
    """A new CA (its key beside it) and a certificate for ``host`` and 127.0.0.1 signed by it,
    in ``directory``, valid two days: a private broker's TLS listener for tests and demos,
    which its clients verify against the CA. Made with the ``openssl`` command (the
    ``cryptography`` package is not among the dependencies); P-256 keys, ~0.1 s in all.
    RuntimeError naming the step if openssl is missing or fails."""
    directory.mkdir(parents=True, exist_ok=True)
    ca, ca_key = directory / "ca.pem", directory / "ca.key"
    cert, key, request = directory / "server.pem", directory / "server.key", directory / "server.csr"
    extensions = directory / "server.ext"
    extensions.write_text(f"subjectAltName=DNS:{host},IP:127.0.0.1\nextendedKeyUsage=serverAuth\n")
    ec_key = ("-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256", "-nodes")
    _openssl("req", "-x509", *ec_key, "-days", "2", "-subj", "/CN=rabbitros throwaway CA", "-keyout", str(ca_key),
             "-out", str(ca), "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    _openssl("req", *ec_key, "-subj", f"/CN={host}", "-keyout", str(key), "-out", str(request))
    _openssl("x509", "-req", "-in", str(request), "-CA", str(ca), "-CAkey", str(ca_key), "-CAcreateserial",
             "-days", "2", "-extfile", str(extensions), "-out", str(cert))
    return ThrowawayCertificates(ca, cert, key)


def _openssl(*args: str) -> None:
    try:
        subprocess.run(["openssl", *args], check=True, capture_output=True, text=True, timeout=30)
    except FileNotFoundError:
        raise RuntimeError("openssl is not installed (apt-get install -y openssl): it makes the throwaway certificates") from None
    except subprocess.CalledProcessError as exc:
        raise RuntimeError(f"openssl {args[0]} failed: {exc.stderr.strip()[-300:]}") from None
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"openssl {args[0]} did not finish within 30 s") from None


class _ServerNameContext(ssl.SSLContext):
    """A context that verifies (and sends as SNI) ``server_hostname`` whatever host the URL
    names: asyncio passes the URL's host to ``wrap_bio``, and neither aio-pika nor aiormq
    lets a caller pass another."""

    expected_name: str | None = None

    def wrap_bio(self, incoming: Any, outgoing: Any, server_side: bool = False,
                 server_hostname: str | bytes | None = None, session: Any = None) -> ssl.SSLObject:
        return super().wrap_bio(incoming, outgoing, server_side=server_side,
                                server_hostname=self.expected_name or server_hostname, session=session)


def key_files(tls: TlsOptions | None) -> list[str]:
    """The files a connection with these TLS options reads when it opens."""
    if tls is None:
        return []
    return [str(Path(name).expanduser()) for name in (tls.ca_file, tls.cert_file, tls.key_file) if name]


def file_problems(tls: TlsOptions | None) -> Iterator[str]:
    """Static checks of the files: each readable (named, never shown), a key with its certificate."""
    if tls is None:
        return
    if tls.key_file and not tls.cert_file:
        yield "tls.key_file without tls.cert_file"
    for key in ("ca_file", "cert_file", "key_file"):
        name = getattr(tls, key)
        if name:
            try:
                Path(name).expanduser().read_bytes()
            except OSError as exc:
                yield f"tls.{key} {name}: cannot read it ({exc.strerror})"


def tls_context(tls: TlsOptions | None) -> ssl.SSLContext:
    """The client context of an amqps:// connection: TLS 1.2 or later, the broker's
    certificate verified against ``ca_file`` (or the system's CAs) and its name, the client
    certificate presented when given. Raises ValueError naming the file at fault."""
    tls = tls or TlsOptions()
    context = _ServerNameContext(ssl.PROTOCOL_TLS_CLIENT)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        if tls.ca_file:
            context.load_verify_locations(cafile=str(Path(tls.ca_file).expanduser()))
        else:
            context.load_default_certs(ssl.Purpose.SERVER_AUTH)
    except (OSError, ssl.SSLError) as exc:
        raise ValueError(f"tls.ca_file {tls.ca_file}: {getattr(exc, 'strerror', None) or exc}") from None
    if tls.cert_file:
        try:
            context.load_cert_chain(str(Path(tls.cert_file).expanduser()),
                                    str(Path(tls.key_file).expanduser()) if tls.key_file else None)
        except (OSError, ssl.SSLError) as exc:
            raise ValueError(f"tls.cert_file {tls.cert_file} / key_file {tls.key_file}: "
                             f"{getattr(exc, 'strerror', None) or exc}") from None
    context.expected_name = tls.server_hostname
    if not tls.verify:
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
    return context


def tls_failure(error: BaseException, host: str | None, also: str = "") -> str | None:
    """Which TLS check ``error`` (or an error it wraps, or ``also``: what a client library
    logged instead of raising) reports, in words; None when it is not a TLS failure."""
    texts: list[str] = [also]
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        texts.append(str(current))
        texts.extend(str(arg) for arg in getattr(current, "args", ()))
        if isinstance(current, ssl.SSLCertVerificationError) and current.verify_message:
            texts.append(current.verify_message)
        current = current.__cause__ or current.__context__
    text = " ".join(texts).lower()
    for needles, meaning in _ERROR_MEANINGS:
        if any(needle in text for needle in needles):
            return meaning.format(host=host or "the URL's host")
    if "ssl" in text or "tls" in text or "certificate" in text:
        return "TLS handshake failed"
    return None


class LastTlsError(logging.Filter):
    """Keeps the last TLS error a client library only logs (paho-mqtt logs "failed to receive
    on socket: [SSL: TLSV13_ALERT_CERTIFICATE_REQUIRED]" and then reports a timeout), so the
    connection's error can still name the check that failed. Lets every record through."""

    def __init__(self) -> None:
        super().__init__()
        self.text = ""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if "SSL" in message or "certificate" in message:
            self.text = message
        return True

    @classmethod
    def on(cls, logger: logging.Logger) -> LastTlsError:
        """The one instance on ``logger`` (added once however many times a connection opens)."""
        for existing in logger.filters:
            if isinstance(existing, cls):
                return existing
        added = cls()
        logger.addFilter(added)
        return added
