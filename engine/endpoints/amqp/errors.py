"""The one place where aio-pika's and aiormq's failures become the engine's two edge errors.

As httpx's ``map_httpcore_exceptions`` does for its transport, every call into the AMQP
libraries that can fail runs inside :func:`mapped` (a failure leaves as the edge error the
table names) or :func:`ignored` (a best-effort call during cleanup: the channel is going
anyway and the broker requeues what was not acknowledged), or catches :data:`LIBRARY_ERRORS`
where it must act on the failure first (the connection records its last error). This module
alone decides which failure is transient (:class:`EndpointError`: retried, redelivered) and
which can never succeed for this message (:class:`MessageRejected`: dead-lettered). Every
broker failure is transient today: what one message cannot carry (a routing key's missing
field) is found before the library is called.
"""

from __future__ import annotations

import asyncio
import contextlib
from typing import Iterator

import aiormq.exceptions
from aio_pika.exceptions import AMQPError

from engine.common.redaction import redact_urls
from engine.endpoints.base import EndpointError, ExceptionTable

EXCEPTIONS = ExceptionTable((
    (AMQPError, EndpointError),  # aio-pika: a closed channel or connection, a refused declaration
    (aiormq.exceptions.AMQPError, EndpointError),  # aiormq: a channel or connection closed by the broker
    (ConnectionError, EndpointError),  # the TCP connection refused or reset
    (OSError, EndpointError),  # DNS, TLS (ssl.SSLError is an OSError)
    (asyncio.TimeoutError, EndpointError),  # CONNECT_TIMEOUT, a declaration the broker does not answer
    (RuntimeError, EndpointError),  # aio-pika: an operation on a connection being closed
), describe=lambda error: redact_urls(str(error)))
"""Library exception -> edge error, first match wins; the text without URL passwords."""

LIBRARY_ERRORS: tuple[type[BaseException], ...] = EXCEPTIONS.catches
"""Every failure the AMQP libraries raise that the endpoint handles (anything else is a bug)."""

edge_error = EXCEPTIONS.edge_error
mapped = EXCEPTIONS.mapped
"""Run library calls; their failures leave as the edge error naming ``where``."""


@contextlib.contextmanager
def ignored() -> Iterator[None]:
    """A best-effort library call (closing a channel, cancelling a consumer, an ack on a channel
    that is gone): its failure changes nothing, the broker requeues what was not acknowledged."""
    with contextlib.suppress(*LIBRARY_ERRORS):
        yield

