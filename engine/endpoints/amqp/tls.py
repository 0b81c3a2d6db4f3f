"""TLS for ``amqps://`` connections: what only AMQP adds to engine/common/tls.py.

aio-pika hands the ``ssl.SSLContext`` to aiormq, which speaks TLS for every ``amqps://`` URL
and plain TCP for ``amqp://``, by the URL's scheme alone, so there is no path on which a
failed handshake falls back to plain TCP: ``check`` refuses ``tls`` options on an
``amqp://`` URL, and a failed verification is a connection error.
"""

from __future__ import annotations

from typing import Iterator

from engine.common import tls as tls_common
from engine.endpoints.amqp.options import AmqpConnectionOptions


def key_files(settings: AmqpConnectionOptions) -> list[str]:
    """The TLS files the connection reads when it opens."""
    return tls_common.key_files(settings.tls)


def tls_problems(settings: AmqpConnectionOptions, urls: list[str]) -> Iterator[tuple[str | None, str]]:
    """Static checks: tls only with amqps://, external auth only with a client certificate,
    every file readable."""
    plain = [index + 1 for index, url in enumerate(urls) if url.lower().startswith("amqp://")]
    tls = settings.tls
    if tls is not None and plain:
        yield "tls", (f"tls applies to amqps:// URLs; URL {plain[0]} is amqp:// (plain TCP), which would never use it: "
                      "write amqps:// and the broker's TLS port")
    if settings.auth == "external" and (tls is None or not tls.cert_file):
        yield "auth", "auth: external logs in with the client certificate: give tls.cert_file (and tls.key_file)"
    for problem in tls_common.file_problems(tls):
        yield "tls", problem
