"""The one place where the MAVLink link's failures become the engine's two edge errors.

As httpx's ``map_httpcore_exceptions`` does for its transport: the operating system's failures
on a serial device, a UDP socket or a TCP stream (``OSError``, ``termios.error``) are transient
(:class:`EndpointError`: the link may come back, the message is tried again), and pymavlink's
encoding failures (``struct.error`` for a value its field cannot hold, ``TypeError`` and
``ValueError``) are permanent for that message (:class:`MessageRejected`: dead-lettered).
Protocol outcomes (a COMMAND_ACK that denies, a MISSION_ACK that refuses) are decided where the
conversation is, not here: they are answers, not exceptions.
"""

from __future__ import annotations

import contextlib
import struct
import termios
from typing import Iterator

from engine.endpoints.base import EndpointError, MessageRejected

EXCEPTIONS: tuple[tuple[type[BaseException] | tuple[type[BaseException], ...], type[EndpointError]], ...] = (
    ((struct.error, TypeError, ValueError), MessageRejected),  # pymavlink: a value its field cannot carry
    ((OSError, termios.error), EndpointError),  # the device, socket or stream (timeouts are OSErrors)
)
"""Library exception -> edge error, first match wins."""


def edge_error(what: str, exc: BaseException) -> EndpointError:
    """``exc`` as the edge error its kind maps to, its message starting with ``what``."""
    for kinds, edge in EXCEPTIONS:
        if isinstance(exc, kinds):
            return edge(f"{what}: {reason(exc)}")
    return MessageRejected(f"{what}: {type(exc).__name__}: {exc}")  # unforeseen: retrying cannot help


def reason(exc: BaseException) -> str:
    """What went wrong, in the operating system's words where it has some."""
    return (exc.strerror if isinstance(exc, OSError) else None) or str(exc) or type(exc).__name__


@contextlib.contextmanager
def mapped(what: str) -> Iterator[None]:
    """Run a call into the link's libraries; what they raise leaves as an edge error."""
    try:
        yield
    except EndpointError:
        raise
    except (*EXCEPTIONS[0][0], *EXCEPTIONS[1][0]) as exc:
        raise edge_error(what, exc) from None
