"""The delivery policy: what happens to a message that fails, decided here and nowhere else.

Every failure is classified once, where a route settles its messages:

* **permanent for this message** - it cannot be decoded, mapped, validated or encoded, the
  sink rejected it (:class:`MessageRejected`), it is larger than ``max_message_bytes``, or
  anything unexpected went wrong while converting it (a ``RecursionError`` from deeply
  nested JSON is as permanent as a syntax error). It goes to the dead letters at once;
* **transient** - an :class:`EndpointError`: a connection or link is down, the far end did
  not answer. The sink is tried again with exponential backoff and jitter, up to the
  route's ``max_attempts`` (counted across redeliveries: ``x-rabbitros-attempts``, a quorum
  queue's ``x-delivery-count``, or at least one earlier attempt when the broker says it
  redelivers), then the message is dead-lettered with the last error. While the sink's
  connection reports itself down (``Connection.healthy``) the route waits for it instead of
  spending attempts. A route with a buffer (engine/buffer.py: ROS 2 and MAVLink sources by
  default) hands such messages to its buffer instead, and its source moves on.

Sources and sinks never decide this; they raise the two error types at their edge. A batch
is settled as a whole: one pipelined ``send_batch``, the failures retried together, all
dead letters of the batch stored together (AMQP: one confirm round), so a batch costs a
constant number of round trips however large it is. No message is logged on its own: a
:class:`~engine.logs.Throttle` reports at most once per second per route, with the count it
held back.

The engine keeps one dead-letter destination (:class:`DeadLetters`): an AMQP connection
(exchange and queue ``rabbitros.dead-letter``, routing key = route name, bounded by
``max_length``) or, when the directory has no AMQP connection, or the broker cannot take
them, a local spool of rotated JSON-lines files, bounded in bytes.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import os
import random
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

from engine.endpoints.base import OVERFLOW_POLICIES, Connection, EndpointError, Inbound, MessageRejected, Outbound
from engine.logs import Throttle
from engine.options import option
from engine.pipeline import ConversionError

if TYPE_CHECKING:
    from engine.runtime import RouteRunner

log = logging.getLogger("engine.delivery")

DEFAULT_MAX_ATTEMPTS = 5
DEFAULT_MAX_MESSAGE_BYTES = 8 * 1024 * 1024
DEFAULT_QUEUE_LIMIT = 10_000
"""Messages a source may hold in memory between its protocol and the pipeline."""
DEFAULT_DEAD_LETTER_MAX_LENGTH = 100_000
DEFAULT_SPOOL_MAX_BYTES = 64 * 1024 * 1024
SPOOL_FILES = 4
"""The spool keeps its current file and SPOOL_FILES - 1 rotated ones, each at most
``spool_max_bytes / SPOOL_FILES``: bounded, and the newest dead letters are kept."""
BACKOFF_FIRST = 0.1
BACKOFF_MAX = 5.0
HEALTH_POLL = 0.2
ERROR_HEADER_LIMIT = 1000
ATTEMPTS_HEADER = "x-rabbitros-attempts"


@dataclass(frozen=True)
class RouteDelivery:
    """A route's delivery settings, parsed once from its route file."""

    max_attempts: int = DEFAULT_MAX_ATTEMPTS
    overflow: str = "block"
    queue_limit: int = DEFAULT_QUEUE_LIMIT
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    """The source connection's limit (messages larger are dead-lettered unparsed)."""
    sink_max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES

    def __post_init__(self) -> None:
        assert self.overflow in OVERFLOW_POLICIES and self.max_attempts >= 1


@dataclass(frozen=True, kw_only=True)
class DeadLettersOptions:
    """``dead_letters:`` as written in a route file (resolved into :class:`DeadLetterSpec`)."""

    __schema_description__ = "the engine's one dead-letter destination; default: the only AMQP connection, else a local spool"

    connection: str | None = option(None, description="an AMQP connection: exchange and queue rabbitros.dead-letter, routing key = route name")
    max_length: int = option(DEFAULT_DEAD_LETTER_MAX_LENGTH, minimum=1, description="x-max-length of the dead-letter queue (oldest dropped beyond it)")
    spool_dir: str | None = option(None, description="directory of rotated JSON-lines files; default ~/.local/state/rabbitros-engine/dead-letters")
    spool_max_bytes: int = option(DEFAULT_SPOOL_MAX_BYTES, minimum=4096, description="bytes of the spool's rotated files together (the newest dead letters are kept)")


@dataclass(frozen=True)
class DeadLetterSpec:
    """``dead_letters:`` of a routes directory, resolved: exactly one of connection/spool_dir."""

    connection: str | None = None
    max_length: int = DEFAULT_DEAD_LETTER_MAX_LENGTH
    spool_dir: str | None = None
    spool_max_bytes: int = DEFAULT_SPOOL_MAX_BYTES


def default_spool_dir() -> Path:
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rabbitros-engine" / "dead-letters"


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


def backoff(attempt: int, rand: Callable[[], float] = random.random) -> float:
    """Seconds to wait after failed attempt ``attempt`` (1-based): exponential, capped, with
    jitter (between half and all of it) so routes that failed together do not retry together."""
    delay = min(BACKOFF_MAX, BACKOFF_FIRST * 2 ** (attempt - 1))
    return delay * (0.5 + rand() / 2)


def prior_attempts(meta: Mapping[str, Any]) -> int:
    """Delivery attempts made before this reception: our own header, a quorum queue's
    delivery count, or at least one when the broker marks the message redelivered."""
    headers = meta.get("headers") or {}
    for key in (ATTEMPTS_HEADER, "x-delivery-count"):
        value = headers.get(key)
        if isinstance(value, int) and not isinstance(value, bool) and value > 0:
            return value
    return 1 if meta.get("redelivered") else 0


# ---------------------------------------------------------------- dead-letter destination


class DeadLetterSpool:
    """Dead letters as JSON lines in rotated files: ``dead-letters.jsonl`` then ``.1`` .. ``.N``.
    One line: ``{"ts", "route", "headers", "body"}`` (``body_base64`` for bytes that are not
    UTF-8)."""

    def __init__(self, directory: Path, max_bytes: int = DEFAULT_SPOOL_MAX_BYTES) -> None:
        self.directory = Path(directory)
        self.file_limit = max(4096, max_bytes // SPOOL_FILES)
        self.path = self.directory / "dead-letters.jsonl"

    def write(self, route: str, messages: Sequence[tuple[bytes, Mapping[str, Any]]]) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            size = self.path.stat().st_size if self.path.exists() else 0
            chunk: list[bytes] = []
            for body, headers in messages:
                line = self._line(route, body, headers)
                if size and size + len(line) > self.file_limit:
                    self._append(chunk)
                    self._rotate()
                    chunk, size = [], 0
                chunk.append(line)
                size += len(line)
            self._append(chunk)
        except OSError as exc:
            raise EndpointError(f"dead-letter spool {self.directory}: {exc.strerror or exc}") from exc

    def _append(self, lines: list[bytes]) -> None:
        if lines:
            with open(self.path, "ab") as spool:
                spool.write(b"".join(lines))
                spool.flush()
                os.fsync(spool.fileno())

    def _rotate(self) -> None:
        for index in range(SPOOL_FILES - 1, 0, -1):
            older = self.path.with_name(f"{self.path.name}.{index}")
            newer = self.path if index == 1 else self.path.with_name(f"{self.path.name}.{index - 1}")
            if newer.exists():
                os.replace(newer, older)

    @staticmethod
    def _line(route: str, body: bytes, headers: Mapping[str, Any]) -> bytes:
        record: dict[str, Any] = {"ts": time.time(), "route": route, "headers": dict(headers)}
        try:
            record["body"] = body.decode("utf-8")
        except UnicodeDecodeError:
            record["body_base64"] = base64.b64encode(body).decode("ascii")
        return json.dumps(record, ensure_ascii=False, default=str).encode("utf-8") + b"\n"

    def read(self) -> list[dict[str, Any]]:
        """Every spooled record, oldest first (for operators and tests)."""
        records = []
        for index in range(SPOOL_FILES - 1, -1, -1):
            path = self.path if index == 0 else self.path.with_name(f"{self.path.name}.{index}")
            if path.exists():
                records += [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line]
        return records


class DeadLetters:
    """The engine's one dead-letter destination. With an AMQP connection, a batch that the
    broker cannot take (it is down) goes to the spool instead, so dead-lettering only fails
    when the disk does too."""

    def __init__(self, spec: DeadLetterSpec, connection: Connection | None) -> None:
        self.spec = spec
        self.connection = connection
        self.spool = DeadLetterSpool(Path(spec.spool_dir) if spec.spool_dir else default_spool_dir(), spec.spool_max_bytes)
        self.stored = 0
        self.spooled = 0
        self._report = Throttle(5.0)

    @property
    def where(self) -> str:
        if self.connection is not None:
            return f"amqp connection {self.connection.name!r}, queue rabbitros.dead-letter"
        return f"spool {self.spool.directory}"

    async def prepare(self) -> None:
        if self.connection is not None:
            await self.connection.prepare_dead_letters(self.spec.max_length)

    async def put(self, route: str, messages: Sequence[tuple[bytes, Mapping[str, Any]]]) -> None:
        if not messages:
            return
        if self.connection is not None:
            try:
                await self.connection.dead_letter(route, messages)
                self.stored += len(messages)
                return
            except EndpointError as error:
                if self._report.ready():
                    log.error(
                        "dead letters cannot reach the broker; spooling them to disk",
                        extra={"route": route, "error": str(error), "spool": str(self.spool.directory),
                               "suppressed": self._report.take_suppressed()},
                    )
        await asyncio.to_thread(self.spool.write, route, messages)
        self.stored += len(messages)
        self.spooled += len(messages)


# ---------------------------------------------------------------- settling a batch


def dead_letter_message(
    runner: RouteRunner, inbound: Inbound, failure: Failure, attempts: int, limit: int
) -> tuple[bytes, dict[str, Any]]:
    """The original body (typed messages rendered as JSON), at most ``limit`` bytes, and the
    headers saying why."""
    spec = runner.spec
    body = inbound.body
    if body is None and inbound.fields is None:
        body = b""
    elif body is None:
        try:
            body = json.dumps(inbound.fields, default=str, ensure_ascii=False).encode("utf-8")
        except (ValueError, RecursionError) as exc:
            body = repr(exc).encode()
    headers: dict[str, Any] = {
        "x-rabbitros-route": spec.name,
        "x-rabbitros-stage": failure.stage,
        "x-rabbitros-error": failure.error[:ERROR_HEADER_LIMIT],
        ATTEMPTS_HEADER: attempts,
        "x-rabbitros-route-file": f"{spec.file}:{spec.line}",
    }
    if len(body) > limit:
        headers["x-rabbitros-truncated"] = len(body)
        body = body[:limit]
    for key, value in inbound.meta.items():
        if key != "headers" and isinstance(value, (str, int, float)) and not isinstance(value, bool):
            headers[f"x-source-{key}"] = value
    return body, headers


class _Pending:
    __slots__ = ("index", "inbound", "outbound", "attempts", "failure")

    def __init__(self, index: int, inbound: Inbound, outbound: Outbound, attempts: int) -> None:
        self.index = index
        self.inbound = inbound
        self.outbound = outbound
        self.attempts = attempts
        self.failure: Failure | None = None


async def settle(runner: RouteRunner, inbounds: Sequence[Inbound]) -> list[bool]:
    """Convert, deliver, retry and dead-letter a batch; ``result[i]`` is True once
    ``inbounds[i]`` was accepted by the sink or stored as a dead letter."""
    pipeline = runner.pipeline
    delivery = pipeline.spec.delivery
    stats = runner.stats
    settled = [False] * len(inbounds)
    dead: list[tuple[int, Inbound, Failure, int]] = []
    pending: list[_Pending] = []
    pipeline.enter()
    try:
        stats.received += len(inbounds)
        limit = delivery.max_message_bytes
        throttle = pipeline.throttle
        for index, inbound in enumerate(inbounds):
            prior = prior_attempts(inbound.meta)
            if inbound.undecodable is not None:
                dead.append((index, inbound, Failure("decode", inbound.undecodable, True), prior + 1))
                continue
            body = inbound.body
            if body is not None and len(body) > limit:
                dead.append((index, inbound, Failure("size", f"{len(body)} bytes exceed max_message_bytes {limit}", True), prior + 1))
                continue
            try:
                outbound = pipeline.convert(inbound)
            except Exception as error:  # ConversionError, or anything the pipeline did not foresee
                dead.append((index, inbound, classify(error, "convert"), prior + 1))
                continue
            if len(outbound.body) > delivery.sink_max_message_bytes:
                failure = Failure("size", f"canonical message of {len(outbound.body)} bytes exceeds the sink "
                                  f"connection's max_message_bytes {delivery.sink_max_message_bytes}", True)
                dead.append((index, inbound, failure, prior + 1))
                continue
            if prior >= delivery.max_attempts:
                failure = Failure("sink", f"already attempted {prior} times (max_attempts {delivery.max_attempts})", False)
                dead.append((index, inbound, failure, prior))
                continue
            if throttle is not None and not throttle.admit(inbound, outbound, runner):
                settled[index] = True  # parked: sent when its slot opens, or conflated by a newer one
                continue
            pending.append(_Pending(index, inbound, outbound, prior))

        while pending:
            if runner.should_hold():  # a buffered route whose sink is down: engine/buffer.py holds them
                await _hold(runner, pending, settled)
                break
            if not await runner.sink_ready():
                if runner.buffer is not None:  # kept: spilled, or delivered by the runner replacing this one
                    await _hold(runner, pending, settled)
                break  # the route is stopping: what is left stays unsettled
            results = await pipeline.sink.send_batch([p.outbound for p in pending])
            retry: list[_Pending] = []
            for item, error in zip(pending, results):
                item.attempts += 1
                if error is None:
                    settled[item.index] = True
                    runner.accepted(item.inbound, item.outbound)
                    continue
                failure = classify(error, "sink")
                if not failure.permanent:
                    stats.sink_errors += 1
                if failure.permanent or item.attempts >= delivery.max_attempts:
                    if not failure.permanent:
                        failure.error = f"gave up after {item.attempts} attempts: {failure.error}"
                    dead.append((item.index, item.inbound, failure, item.attempts))
                else:
                    item.failure = failure
                    retry.append(item)
                    runner.retrying(item.inbound, item.outbound, error)
            pending = retry
            if pending and runner.buffer is not None:  # transient: the buffer retries them, the source moves on
                await _hold(runner, pending, settled)
                break
            if pending:
                stats.retries += len(pending)
                runner.report_retry(pending[0].failure, len(pending))  # type: ignore[arg-type]
                if not await runner.pause(backoff(min(p.attempts for p in pending))):
                    break

        if dead:
            dead.sort(key=lambda item: item[0])
            letters = [dead_letter_message(runner, inbound, failure, attempts, limit)
                       for _, inbound, failure, attempts in dead]
            try:
                await runner.engine.dead_letters_for(runner).put(runner.spec.name, letters)
            except EndpointError as error:
                stats.dead_letter_errors += len(dead)
                runner.report_failure(Failure("dead-letter", str(error), False))
            else:
                for index, inbound, failure, _ in dead:
                    settled[index] = True
                    stats.failed += 1
                    stats.dead_lettered[failure.stage] = stats.dead_lettered.get(failure.stage, 0) + 1
                    runner.dead_lettered(inbound, failure)
                runner.report_failure(dead[-1][2], len(dead))
    finally:
        pipeline.leave()
    return settled


async def _hold(runner: RouteRunner, pending: list[_Pending], settled: list[bool]) -> None:
    """Hand messages to the route's buffer in order; once held they are settled for the source."""
    await runner.hold([item.outbound for item in pending])
    for item in pending:
        settled[item.index] = True
