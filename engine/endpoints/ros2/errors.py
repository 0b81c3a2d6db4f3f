"""The one place where rclpy's and the message conversion's failures become the engine's two
edge errors.

As httpx's ``map_httpcore_exceptions`` does for its transport, a call that handles one message
(building it from the fields, naming a topic from it, publishing it) runs inside
:func:`mapped`, which looks the failure up in :data:`EXCEPTIONS`: what this message can never
be (a field the type lacks, a null from a sink mapping, a topic its fields make invalid) is
:class:`MessageRejected` and is dead-lettered; anything else rcl raises (a publisher gone, the
context shut down) is :class:`EndpointError` and is retried. Setting up (a node, a
subscription) is never one message's fault: :func:`setup_error` makes every failure transient.
"""

from __future__ import annotations

import re
from typing import Callable

from rclpy.exceptions import NameValidationException

from engine.endpoints.base import EndpointError, ExceptionTable, MessageRejected
from engine.endpoints.ros2.rosmsg import MessageError, NullValue


def _in_sink_mapping(message: str) -> EndpointError:
    return MessageRejected(message, stage="sink mapping")


_EXCEPTIONS: tuple[tuple[type[BaseException], Callable[[str], EndpointError]], ...] = (
    (NullValue, _in_sink_mapping),  # a null from the sink mapping: no default stands in for it
    (MessageError, MessageRejected),  # a field the type lacks, a value out of its range
    (UnicodeDecodeError, MessageRejected),  # a String sink given bytes that are not UTF-8
    (NameValidationException, MessageRejected),  # a topic built from this message's fields
    (ValueError, MessageRejected),  # rcl: an invalid topic name from this message
    (Exception, EndpointError),  # rcl: RCLError, InvalidHandle, a context shut down
)
"""Library exception -> edge error (a class, or a function of the text), first match wins."""

_OURS = (MessageError, UnicodeDecodeError)
"""Failures whose text is written for people already; rcl's is trimmed by :func:`rcl_reason`."""


def rcl_reason(exc: BaseException) -> str:
    """rcl's first line without its repeated prefix and the C source location."""
    line = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    line = re.sub(r"^(Invalid [a-z ]+: |[a-z ]+ '[^']*' is invalid: )", "", line)
    return re.sub(r", at /\S+:\d+$", "", line).rstrip(":")


def _reason(exc: BaseException) -> str:
    return str(exc) if isinstance(exc, _OURS) else rcl_reason(exc)


EXCEPTIONS = ExceptionTable(_EXCEPTIONS, describe=_reason)
edge_error = EXCEPTIONS.edge_error
mapped = EXCEPTIONS.mapped
"""Handle one message; a failure leaves as the edge error naming ``where`` (the table ends with
``Exception``: whatever rcl raises is one of the two edge errors)."""


def setup_error(exc: BaseException, where: str) -> EndpointError:
    """A node or subscription that could not be made: transient, whatever rcl raised."""
    return EndpointError(f"{where}: {rcl_reason(exc)}")
