"""The contract's errors (engine/endpoints/base.py): what a protocol package raises at its edge
(:class:`EndpointError` transient, :class:`MessageRejected` permanent), its table translating
its library's exceptions into them (:class:`ExceptionTable`), and the outcomes of a message a
sink settled without sending it (:class:`NotSent`). Protocol packages import them through
engine/endpoints/base.py, the contract's one face.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Callable, Iterator

class EndpointError(Exception):
    """A protocol library failed; the message names the connection or endpoint.

    Treated as transient: the message is handed back to its source for redelivery."""


class MessageRejected(EndpointError):
    """This message can never be accepted by this sink (a field the type lacks, a value out
    of range). Retrying cannot help, so the engine dead-letters it instead of redelivering.

    ``stage`` is what the dead letter names: ``sink`` by default, ``sink mapping`` when the
    sink mapping's output is what cannot be carried (a typed field it set to null)."""

    def __init__(self, message: str, stage: str = "sink") -> None:
        super().__init__(message)
        self.stage = stage


class Unroutable(EndpointError):
    """The destination took the message and routed it to nobody (an AMQP exchange with no
    queue bound for its routing key, published ``mandatory``): not delivered. Transient (the
    sink holds the route's messages until something is bound); the route counts it
    ``unroutable``. A sink that dead-letters such messages instead raises
    :class:`UnroutableRejected`."""


class UnroutableRejected(MessageRejected, Unroutable):
    """An unroutable message the sink refuses for good: dead-lettered, counted ``unroutable``."""


@dataclass(frozen=True)
class ExceptionTable:
    """One protocol's library exceptions -> the two edge errors, first match wins (as httpx's
    ``map_httpcore_exceptions``). Each protocol's ``errors.py`` declares its table and how it
    words a failure; how a failure is looked up and raised is decided here, once."""

    entries: tuple[tuple[type[BaseException], Callable[[str], EndpointError]], ...]
    """Library exception -> edge error (a class, or a function of the text)."""
    describe: Callable[[BaseException], str] = str
    """The failure in words, after ``where: `` (a protocol trims its library's text, hides passwords)."""

    @property
    def catches(self) -> tuple[type[BaseException], ...]:
        """Every library exception the table names (anything else is a bug, not an edge error)."""
        return tuple(cls for cls, _ in self.entries)

    def edge_error(self, error: BaseException, where: str) -> EndpointError:
        """``error`` as the edge error the table maps it to (EndpointError if it names none)."""
        if isinstance(error, EndpointError):
            return error
        kind = next((edge for cls, edge in self.entries if isinstance(error, cls)), EndpointError)
        mapped_error = kind(f"{where}: {self.describe(error)}")
        mapped_error.__cause__ = error
        return mapped_error

    @contextlib.contextmanager
    def mapped(self, where: str) -> Iterator[None]:
        """Run library calls; their failures leave as the edge error naming ``where``."""
        try:
            yield
        except EndpointError:
            raise
        except self.catches as exc:
            raise self.edge_error(exc, where) from exc


class NotSent(Exception):
    """Not a failure: the sink settled this message without delivering it. A sink returns one
    of the kinds below in ``send_batch``'s results; the route settles the message and counts it."""


class Conflated(NotSent):
    """A newer message with the same key took this one's place while it waited (a radio
    link's budget: only the newest telemetry is worth sending); counted ``conflated``."""


class Expired(NotSent):
    """The message became older than its route's ``max_age`` while the sink was still
    trying to deliver it (a tunnel's retransmissions); counted ``expired``."""


class Refused(NotSent):
    """The destination answered, and its answer is no (a vehicle's COMMAND_ACK ``DENIED``): an
    answer, not a failure, so not a dead letter. The sink has replied with the refusal already
    (through the route's ``reply.mapping``, as any answer); the route counts it ``refused``.
    Issue 31: as dead letters, every operator refusal filled the dead-letter queue and callers
    had two reply shapes to handle."""
