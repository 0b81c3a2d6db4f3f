"""The one place where eclipse-zenoh's failures become the engine's two edge errors.

Zenoh raises one exception type, :class:`zenoh.ZError`, for everything (a key expression it
refuses, a session that is closed, an endpoint it cannot reach), so the table maps it to the
transient :class:`EndpointError`; what no retry can fix for one message (a key rendered from
the message that is no valid key expression) is decided where the key is made (keys.py
raises :class:`MessageRejected` through :func:`rejected`). Its texts end with the Rust source
location (`` at /root/.cargo/.../orchestrator.rs:447.``), which :func:`describe` trims.
"""

from __future__ import annotations

import asyncio
import re

import zenoh

from engine.endpoints.base import EndpointError, ExceptionTable, MessageRejected

_EXCEPTIONS: tuple[tuple[type[BaseException], type[EndpointError]], ...] = (
    (zenoh.ZError, EndpointError),  # every failure of the library: a closed session, an unreachable router
    (OSError, EndpointError),  # a config_file that cannot be read (it may be being renewed)
    (asyncio.TimeoutError, EndpointError),
)
"""Library exception -> edge error, first match wins."""

_RUST_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?$")


def describe(error: BaseException) -> str:
    """The library's text without the Rust source location it appends."""
    text = _RUST_LOCATION.sub("", str(error)).strip() or type(error).__name__
    return text


def rejected(error: BaseException, where: str) -> MessageRejected:
    """A key expression made from a message that Zenoh refuses: permanent for that message."""
    refused = MessageRejected(f"{where}: {describe(error)}")
    refused.__cause__ = error
    return refused


EXCEPTIONS = ExceptionTable(_EXCEPTIONS, describe=describe)
edge_error = EXCEPTIONS.edge_error
mapped = EXCEPTIONS.mapped
"""Run a library call; its exceptions leave as the edge error naming ``where``."""
