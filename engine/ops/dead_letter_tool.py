"""``rabbitros-engine dead-letters list|show|replay``: the dead letters an engine stored, read and sent again.

Dead letters are where engine/running/dead_letters.py put them: the queue ``rabbitros.dead-letter``
of the routes' ``dead_letters.connection`` (a broker), and the local spool (its ``spool_dir``,
default ``$XDG_STATE_HOME/rabbitros-engine/dead-letters``), where they go with no broker or while
it is down; this tool reads both. Each letter keeps the original body and headers naming its
route, stage, error and the source's metadata (``x-source-*``), and when it was stored.

``replay`` sends the selected letters into their route **as it is now** (the route files read
again, so a fixed mapping applies): each body goes through the route's conversion (decode,
mapping, schema, ``when:``, sink mapping) and its sink, on connections this tool opens itself,
in batches. A letter is removed from its store only once the sink accepted it (or the route's
``when:`` filtered it: settled), so each is settled once: one that fails again (a mapping still
wrong, the sink down) stays where it was, with the reason printed, and is never dead-lettered a
second time. The AMQP queue is read with ``basic.get`` unacknowledged: a letter is acknowledged
when sent, the rest go back to the queue when the tool closes its channel; the spool is
rewritten without the lines sent, under the lock the engine's writes take.

What replay does not do: the route's ``throttle``, ``buffer`` and ``dedupe`` (the running
engine's key file is its own) are not applied, and a sink on a link only one process can hold
(a MAVLink serial port or UDP port the engine listens on) cannot be opened while the engine runs.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import json
import re
import sys
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterable, Sequence

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import DeadLetterReader, EndpointError, Inbound, NotSent, Outbound, StoredLetter
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig, RouteSpec
from engine.language.stores import Stores
from engine.running.connections import ConnectionPool
from engine.running.dead_letters import DeadLetterSpool, SpoolReader, default_spool_dir
from engine.running.fanout import open_sinks
from engine.running.pipeline import ConversionError, Filtered, Pipeline

DEFAULT_LIMIT = 10_000
"""Letters read from each store at most in one run."""
SOURCE_PREFIX = "x-source-"
_DURATION = re.compile(r"^(\d+(?:\.\d+)?)([smhd])$")
_UNITS = {"s": 1, "m": 60, "h": 3600, "d": 86400}


@dataclass
class Selection:
    """Which letters a command takes: by route, stage, id and time stored (all must hold)."""

    routes: frozenset[str] = frozenset()
    stages: frozenset[str] = frozenset()
    ids: frozenset[str] = frozenset()
    since: float | None = None
    until: float | None = None

    def __call__(self, letter: StoredLetter) -> bool:
        headers = letter.headers
        if self.routes and headers.get("x-rabbitros-route") not in self.routes:
            return False
        if self.stages and headers.get("x-rabbitros-stage") not in self.stages:
            return False
        if self.ids and letter_id(letter) not in self.ids:
            return False
        if self.since is not None and (letter.at is None or letter.at < self.since):
            return False
        return self.until is None or (letter.at is not None and letter.at <= self.until)


def parse_time(text: str, now: float | None = None) -> float:
    """``2026-11-27T14:00:00`` (ISO 8601; UTC unless it says) or a time ago: ``90s``, ``30m``, ``2h``, ``1d``."""
    match = _DURATION.match(text.strip())
    if match:
        return (time.time() if now is None else now) - float(match.group(1)) * _UNITS[match.group(2)]
    try:
        moment = datetime.fromisoformat(text.strip())
    except ValueError:
        raise ValueError(f"not a time: {text!r} (give 2026-11-27T14:00:00 or a time ago: 90s, 30m, 2h, 1d)") from None
    return (moment if moment.tzinfo else moment.replace(tzinfo=timezone.utc)).timestamp()


def letter_id(letter: StoredLetter) -> str:
    """A short id for a letter, the same in every run (its body, headers and time stored)."""
    digest = hashlib.sha256(letter.body)
    digest.update(json.dumps(dict(letter.headers), sort_keys=True, default=str).encode())
    digest.update(repr(letter.at).encode())
    return digest.hexdigest()[:12]


async def readers(config: RoutesConfig, pool: ConnectionPool, unreachable: list[str]) -> list[DeadLetterReader]:
    """Every store the routes' dead letters can be in: the broker's queue (``dead_letters.connection``)
    and the local spool (where they go without a broker, or while it is down); a broker that
    cannot be reached is said on stderr and appended to ``unreachable``."""
    spec = config.dead_letters
    found: list[DeadLetterReader] = []
    if spec.connection is not None:
        try:
            connection = await pool.get(config.connections[spec.connection], retry_in_background=False)
            found.append(await connection.dead_letter_reader())
        except EndpointError as error:  # the spool is read all the same; the exit status says what was missed
            print(f"dead letters: {error} (its dead letters are not read; the local spool is)", file=sys.stderr)
            unreachable.append(str(error))
    spool = DeadLetterSpool(Path(spec.spool_dir) if spec.spool_dir else default_spool_dir(), spec.spool_max_bytes)
    found.append(SpoolReader(spool))
    return found


def _at(letter: StoredLetter) -> str:
    if letter.at is None:
        return "-"
    return datetime.fromtimestamp(letter.at, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def summary_line(letter: StoredLetter) -> str:
    headers = letter.headers
    error = str(headers.get("x-rabbitros-error", "")).replace("\n", " ")
    return (f"{letter_id(letter)}  {_at(letter)}  {headers.get('x-rabbitros-route', '?')}  "
            f"{headers.get('x-rabbitros-stage', '?')}  {error[:100]}")


def full_record(letter: StoredLetter) -> dict[str, Any]:
    record: dict[str, Any] = {"id": letter_id(letter), "at": _at(letter), "where": letter.where,
                              "route": letter.headers.get("x-rabbitros-route"), "stage": letter.headers.get("x-rabbitros-stage"),
                              "error": letter.headers.get("x-rabbitros-error"), "headers": dict(letter.headers)}
    try:
        record["body"] = letter.body.decode("utf-8")
    except UnicodeDecodeError:
        record["body_base64"] = base64.b64encode(letter.body).decode("ascii")
    return record


async def show(config: RoutesConfig, selection: Selection, full: bool, limit: int = DEFAULT_LIMIT) -> int:
    """``list`` (one line a letter) and ``show`` (a JSON document a line, body included)."""
    pool = ConnectionPool(require_connections=True)
    count = 0
    unreachable: list[str] = []
    try:
        for reader in await readers(config, pool, unreachable):
            try:
                for letter in filter(selection, await reader.read(limit)):
                    count += 1
                    print(json.dumps(full_record(letter), ensure_ascii=False, default=str) if full else summary_line(letter))
            finally:
                await reader.close()
    finally:
        await pool.close_all()
    print(f"{count} dead letters", file=sys.stderr)
    return 1 if unreachable else 0


@dataclass
class Replayed:
    """What a replay did: counts, and why each letter kept was kept."""

    sent: int = 0
    filtered: int = 0
    kept: list[tuple[str, str]] = field(default_factory=list)
    """(letter id, reason) of each letter left in its store."""
    unreachable: list[str] = field(default_factory=list)
    """Stores that could not be read (a broker down)."""


async def replay(config: RoutesConfig, schemas: SchemaRegistry, selection: Selection, limit: int = DEFAULT_LIMIT,
                 ready_timeout: float = 10.0) -> Replayed:
    """Send the selected letters into their routes as they are now (see the module docstring)."""
    pool = ConnectionPool(require_connections=True)
    done = Replayed()
    try:
        for reader in await readers(config, pool, done.unreachable):
            try:
                letters = [letter for letter in await reader.read(limit) if selection(letter)]
                by_route: dict[str, list[StoredLetter]] = {}
                for letter in letters:
                    by_route.setdefault(str(letter.headers.get("x-rabbitros-route")), []).append(letter)
                for route, group in by_route.items():
                    settled = await _replay_route(config, schemas, pool, route, group, done, ready_timeout)
                    if settled:
                        await reader.remove(settled)
            finally:
                await reader.close()
    finally:
        await pool.close_all()
    return done


async def _replay_route(config: RoutesConfig, schemas: SchemaRegistry, pool: ConnectionPool, route: str,
                        letters: list[StoredLetter], done: Replayed, ready_timeout: float) -> list[StoredLetter]:
    """The letters of one route that its sink accepted now (or its ``when:`` filtered)."""
    spec = config.routes.get(route)
    if spec is None:
        done.kept.extend((letter_id(letter), f"route {route!r} is not in the routes any more") for letter in letters)
        return []
    schema = schemas.get(spec.schema)
    assert schema is not None  # the routes loaded
    reply_schema = schemas.get(spec.reply.schema) if spec.reply is not None and spec.reply.schema else None
    stores = Stores()  # several sinks: a letter goes again only to those that did not take it (engine/running/fanout.py)
    sink, _, _ = await open_sinks(spec, lambda end: pool.get(config.connections[end.connection], retry_in_background=False),
                                  pool.is_open, stores)
    pipeline = Pipeline.compile(spec, 0, schema, sink, reply_schema, stores)
    try:
        settled: list[StoredLetter] = []
        sending: list[tuple[StoredLetter, Outbound]] = []
        for letter in letters:
            if "x-rabbitros-truncated" in letter.headers:
                done.kept.append((letter_id(letter), f"its body was cut to max_message_bytes when stored "
                                                     f"({letter.headers['x-rabbitros-truncated']} bytes): it cannot be sent again"))
                continue
            try:
                sending.append((letter, pipeline.convert(_inbound(spec, letter))))
            except Filtered:
                done.filtered += 1
                settled.append(letter)
            except ConversionError as error:
                done.kept.append((letter_id(letter), f"{error.stage}: {error.detail}"))
        if sending:
            if not await _ready(pipeline, ready_timeout):
                reason = pipeline.sink.not_ready_reason() or "the sink cannot take messages"
                done.kept.extend((letter_id(letter), f"sink: {reason}") for letter, _ in sending)
                return settled
            results = await pipeline.sink.send_batch([outbound for _, outbound in sending])
            for (letter, _), outcome in zip(sending, results):
                if outcome is None or isinstance(outcome, NotSent):
                    done.sent += outcome is None
                    settled.append(letter)
                else:
                    done.kept.append((letter_id(letter), f"sink: {outcome}"))
        return settled
    finally:
        await pipeline.sink.close()


def _inbound(spec: RouteSpec, letter: StoredLetter) -> Inbound:
    """The letter as the route's source would hand it over: its body (for a typed source, the
    fields it was rendered from), and the source's metadata from the ``x-source-*`` headers."""
    meta = {key[len(SOURCE_PREFIX):]: value for key, value in letter.headers.items() if key.startswith(SOURCE_PREFIX)}
    typed = endpoints.transport(spec.source.protocol).test_input(spec.source.options)
    if typed is None:
        return Inbound(body=bytes(letter.body), meta=meta)
    try:
        return Inbound(fields=typed(json.loads(letter.body)), meta=meta)
    except (EndpointError, ValueError, TypeError) as exc:
        raise ConversionError("input", f"the stored fields are no longer a valid source message: {exc}") from None


async def _ready(pipeline: Pipeline, timeout: float) -> bool:
    """Whether the sink can take messages within ``timeout`` (a ROS 2 topic's reader matching)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while not pipeline.sink.ready:
        if asyncio.get_running_loop().time() > deadline:
            return False
        await asyncio.sleep(0.05)
    return True


def load(routes: Path, schemas_dir: Path) -> tuple[RoutesConfig, SchemaRegistry] | None:
    schemas = SchemaRegistry(schemas_dir)
    try:
        return load_routes(routes, schemas), schemas
    except RoutesInvalid as invalid:
        for problem in invalid.problems:
            print(problem, file=sys.stderr)
        return None


def selection_of(route: Sequence[str] | None, stage: Sequence[str] | None, ids: Iterable[str] | None,
                 since: str | None, until: str | None) -> Selection:
    return Selection(frozenset(route or ()), frozenset(stage or ()), frozenset(ids or ()),
                     parse_time(since) if since else None, parse_time(until) if until else None)


def run_command(command: str, routes: Path, schemas_dir: Path, selection: Selection, limit: int, ready_timeout: float) -> int:
    """``dead-letters list|show|replay``: 0 done (replay: every selected letter settled), 1 some
    letter kept or a store unreachable, 2 the routes are invalid."""
    loaded = load(routes, schemas_dir)
    if loaded is None:
        return 2
    config, schemas = loaded
    try:
        if command in ("list", "show"):
            return asyncio.run(show(config, selection, command == "show", limit))
        done = asyncio.run(replay(config, schemas, selection, limit, ready_timeout))
    except EndpointError as error:
        print(f"dead letters: {error}", file=sys.stderr)
        return 1
    for identity, reason in done.kept:
        print(f"kept  {identity}  {reason}")
    print(f"{done.sent} sent, {done.filtered} filtered, {len(done.kept)} kept"
          + (f", {len(done.unreachable)} store not read" if done.unreachable else ""))
    return 1 if done.kept or done.unreachable else 0
