"""The one place where the MAVLink link's failures become the engine's two edge errors.

As httpx's ``map_httpcore_exceptions`` does for its transport, and as every protocol's
``errors.py`` does through :class:`~engine.endpoints.base.ExceptionTable`: the operating
system's failures on a serial device, a UDP socket or a TCP stream (``OSError``,
``termios.error``) are transient (:class:`EndpointError`: the link may come back, the message
is tried again), and pymavlink's encoding failures (``struct.error`` for a value its field
cannot hold, ``TypeError`` and ``ValueError``) are permanent for that message
(:class:`MessageRejected`: dead-lettered). Protocol outcomes (a COMMAND_ACK that denies, a
MISSION_ACK that refuses) are decided where the conversation is, not here: they are answers,
not exceptions.
"""

from __future__ import annotations

import struct
import termios

from engine.endpoints.base import EndpointError, ExceptionTable, MessageRejected


def reason(exc: BaseException) -> str:
    """What went wrong, in the operating system's words where it has some."""
    return (exc.strerror if isinstance(exc, OSError) else None) or str(exc) or type(exc).__name__


EXCEPTIONS = ExceptionTable((
    (struct.error, MessageRejected),  # pymavlink: a value its field cannot carry
    (TypeError, MessageRejected),
    (ValueError, MessageRejected),
    (OSError, EndpointError),  # the device, socket or stream (timeouts are OSErrors)
    (termios.error, EndpointError),
), describe=reason)
"""Library exception -> edge error, first match wins."""

mapped = EXCEPTIONS.mapped
"""Run a call into the link's libraries; what they raise leaves as an edge error naming ``where``."""


def edge_error(error: BaseException, where: str) -> EndpointError:
    """``error`` as the edge error its kind maps to, its message starting with ``where``; one the
    table does not name (a message pymavlink failed to pack in a way nobody foresaw) is
    permanent: retrying cannot help."""
    if isinstance(error, EXCEPTIONS.catches):
        return EXCEPTIONS.edge_error(error, where)
    return MessageRejected(f"{where}: {type(error).__name__}: {error}")
