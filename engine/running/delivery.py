"""The delivery policy: what happens to a message that fails, decided here and nowhere else.

Every failure is classified once (:func:`classify`), where a route settles its messages
(engine/running/runner.py) and where its buffer retries them (engine/running/buffer.py):

* **permanent for this message** - it cannot be decoded, mapped, validated or encoded
  (:class:`ConversionError`), the sink rejected it (:class:`MessageRejected`), it is larger
  than ``max_message_bytes``, or anything unexpected went wrong while converting it (a
  ``RecursionError`` from deeply nested JSON is as permanent as a syntax error). It goes to
  the dead letters at once;
* **transient** - an :class:`EndpointError`: a connection or link is down, the far end did
  not answer. The sink is tried again with the engine's one backoff (engine/common/backoff.py:
  exponential from 0.1 s, at most 5 s, jittered), up to the route's ``max_attempts`` (counted
  across redeliveries: ``x-rabbitros-attempts``, a quorum queue's ``x-delivery-count``, or at
  least one earlier attempt when the broker says it redelivers), then the message is
  dead-lettered with the last error. While the sink cannot take messages (its connection
  reports itself down) the route waits for it instead of spending attempts. A route with a
  buffer (engine/running/buffer.py: ROS 2 and MAVLink sources by default) hands such messages to its
  buffer instead, and its source moves on.

Sources and sinks never decide this; they raise the two error types at their edge. Where
dead letters go is engine/running/dead_letters.py.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping

from engine.common.backoff import backoff_delay
from engine.endpoints.base import EndpointError, MessageRejected

BACKOFF_FIRST = 0.1
BACKOFF_MAX = 5.0
HEALTH_POLL = 0.2
"""Seconds between looks at a sink that cannot take messages: a look costs nothing, and it
bounds the time from the sink's return to the first message sent."""
ATTEMPTS_HEADER = "x-rabbitros-attempts"


class ConversionError(Exception):
    """A message cannot be converted; ``stage`` says where (decode, mapping, schema, ...).
    ``canonical``: the canonical message when the failure came after the mapping gave one (the
    schema, ``when:`` or sink-mapping stage), so ``remember ... when: failed`` can read it (an
    order the schema refused still names its headerId); None before."""

    def __init__(self, stage: str, detail: str, canonical: Any = None) -> None:
        super().__init__(f"{stage}: {detail}")
        self.stage = stage
        self.detail = detail
        self.canonical = canonical


@dataclass(slots=True)
class Failure:
    stage: str
    error: str
    permanent: bool


def classify(error: BaseException, stage: str = "sink") -> Failure:
    """The one classification: only an EndpointError that is not a MessageRejected is transient."""
    if isinstance(error, ConversionError):
        return Failure(error.stage, error.detail, True)
    if isinstance(error, MessageRejected):
        return Failure(error.stage, str(error), True)
    if isinstance(error, EndpointError):
        return Failure(stage, str(error), False)
    text = str(error)
    return Failure(stage, f"{type(error).__name__}: {text}" if text else type(error).__name__, True)


def given_up(failure: Failure, attempts: int) -> Failure:
    """A transient failure that used the message's last attempt: dead-lettered with it."""
    return Failure(failure.stage, f"gave up after {attempts} attempts: {failure.error}", False)


def retry_delay(attempt: int) -> float:
    """Seconds to wait after failed attempt ``attempt`` (1-based), with the engine's one backoff."""
    return backoff_delay(attempt, BACKOFF_FIRST, BACKOFF_MAX)


def prior_attempts(meta: Mapping[str, Any]) -> int:
    """Delivery attempts made before this reception: our own header, a quorum queue's
    delivery count, or at least one when the broker marks the message redelivered."""
    headers = meta.get("headers")
    if not headers:  # most messages: no header to look through
        return 1 if meta.get("redelivered") else 0
    for key in (ATTEMPTS_HEADER, "x-delivery-count"):
        value = headers.get(key)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
    return 1 if meta.get("redelivered") else 0
