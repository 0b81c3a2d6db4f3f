"""TLS for ``amqps://`` connections: the context, the static checks, and what a failure means.

aio-pika hands an ``ssl.SSLContext`` to aiormq, which speaks TLS for every ``amqps://`` URL
and plain TCP for ``amqp://``, by the URL's scheme alone, so there is no path on which a
failed handshake falls back to plain TCP: ``check`` refuses ``tls`` options on an
``amqp://`` URL, and a failed verification is a connection error. The context is built
when the connection opens, from the files named in ``tls``; those files are the
connection's key files (:func:`key_files`), so a renewed certificate changes the
connection's fingerprint and the watcher's reload reopens it (make before break).

A verification failure reaches us as OpenSSL's text inside aiormq's
``AMQPConnectionError``; :func:`tls_failure` turns it into the check that failed (unknown
CA, hostname mismatch, expired, no client certificate, not a TLS port), for the log and
``/healthz``.
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Any, Iterator

from engine.endpoints.amqp.options import AmqpConnectionOptions, AmqpTls

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
     "not a TLS port: the broker answered in plain AMQP (use its amqps listener, usually 5671)"),
)


class _ServerNameContext(ssl.SSLContext):
    """A context that verifies (and sends as SNI) ``server_hostname`` whatever host the URL
    names: asyncio passes the URL's host to ``wrap_bio``, and neither aio-pika nor aiormq
    lets a caller pass another."""

    expected_name: str | None = None

    def wrap_bio(self, incoming: Any, outgoing: Any, server_side: bool = False,
                 server_hostname: str | None = None, session: Any = None) -> ssl.SSLObject:
        return super().wrap_bio(incoming, outgoing, server_side=server_side,
                                server_hostname=self.expected_name or server_hostname, session=session)


def key_files(settings: AmqpConnectionOptions) -> list[str]:
    """The TLS files the connection reads when it opens."""
    tls = settings.tls
    if tls is None:
        return []
    return [str(Path(name).expanduser()) for name in (tls.ca_file, tls.cert_file, tls.key_file) if name]


def tls_problems(settings: AmqpConnectionOptions, urls: list[str]) -> Iterator[tuple[str | None, str]]:
    """Static checks: tls only with amqps://, external auth only with a client certificate,
    every file readable (named, never shown)."""
    plain = [index + 1 for index, url in enumerate(urls) if url.lower().startswith("amqp://")]
    tls = settings.tls
    if tls is not None and plain:
        yield "tls", (f"tls applies to amqps:// URLs; URL {plain[0]} is amqp:// (plain TCP), which would never use it: "
                      "write amqps:// and the broker's TLS port")
    if settings.auth == "external" and (tls is None or not tls.cert_file):
        yield "auth", "auth: external logs in with the client certificate: give tls.cert_file (and tls.key_file)"
    if tls is None:
        return
    if tls.key_file and not tls.cert_file:
        yield "tls", "tls.key_file without tls.cert_file"
    for key in ("ca_file", "cert_file", "key_file"):
        name = getattr(tls, key)
        if name:
            try:
                Path(name).expanduser().read_bytes()
            except OSError as exc:
                yield "tls", f"tls.{key} {name}: cannot read it ({exc.strerror})"


def tls_context(tls: AmqpTls | None) -> ssl.SSLContext:
    """The client context of an amqps:// connection: TLS 1.2 or later, the broker's
    certificate verified against ``ca_file`` (or the system's CAs) and its name, the client
    certificate presented when given. Raises ValueError naming the file at fault."""
    tls = tls or AmqpTls()
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


def tls_failure(error: BaseException, host: str | None) -> str | None:
    """Which TLS check ``error`` (or an error it wraps) reports, in words; None when it is not
    a TLS failure."""
    texts: list[str] = []
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
