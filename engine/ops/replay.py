"""``rabbitros-engine replay FILE --routes DIR``: recorded field data through the routes as they are now.

A recording (``--record``, engine/running/record.py) keeps, per route, each input as received
(``/routes/NAME/in``) and the canonical message the sink took (``/routes/NAME/canonical``),
paired by their receive time (the MCAP ``publish_time`` both carry). Inputs are numbered in the
order of the files (oldest first) and within them: ``#N`` in the report is that number (the MCAP
``sequence`` of a single file's ``in`` channel). Replay converts every recorded input through the route's
conversion as it is now (the very :class:`~engine.running.pipeline.Pipeline` the engine and
``rabbitros-engine test`` run: decode, mapping, schema, sink mapping; connecting to nothing)
and compares the result with the canonical message recorded for it: one diff per message
that changed, exit 1 if any did, 0 if none (a regression check of a mapping edit against
field data). Inputs that were never sent (dead-lettered, dropped, still in flight when the
recording ended) are converted too and counted, not compared. The stores ``recall()`` reads
are filled as the engine filled them: each recorded message, in order.

The files are read with the ``mcap`` library's :class:`~mcap.stream_reader.StreamReader`,
record by record, so a file whose writer was killed (no summary, a chunk cut short at the
end) is read up to its last whole chunk; the truncated tail is reported, not an error.

``rabbitros-engine test --from-recording REC --route NAME --count N`` writes route test cases
from the same pairs (:func:`recorded_cases`): field data as regression tests.
"""

from __future__ import annotations

import base64
import difflib
import json
import struct
import sys
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator, Sequence

import yaml
from mcap.exceptions import McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Inbound
from engine.language.mapping import unrepeatable_keys
from engine.language.route_checks import source_meta_names
from engine.language.specs import RoutesConfig
from engine.language.stores import Stores
from engine.ops.route_tests import DrySink, _without, load_checked, same
from engine.running.pipeline import ConversionError, Filtered, Pipeline
from engine.running.record import FILE_PATTERN

_TOPIC_PREFIX = "/routes/"


@dataclass
class RecordedRoute:
    """One route's recorded messages, by sequence."""

    inputs: dict[int, tuple[int, dict[str, Any]]] = field(default_factory=dict)
    """number (from 1, in the order recorded) -> (log time ns, the input envelope)."""
    canonical: dict[int, Any] = field(default_factory=dict)
    """number -> the canonical message sent."""
    received: dict[int, int] = field(default_factory=dict)
    """An input's receive time (ns, its ``publish_time``) -> its number: what pairs a canonical message with it."""


@dataclass
class Recording:
    routes: dict[str, RecordedRoute] = field(default_factory=dict)
    truncated: list[str] = field(default_factory=list)
    """Files whose end was cut short (a writer killed): read up to the last whole record."""


def recording_files(paths: list[Path]) -> list[Path]:
    """The files given; a directory stands for its recordings, oldest first."""
    files: list[Path] = []
    for path in paths:
        files.extend(sorted(path.glob(FILE_PATTERN)) if path.is_dir() else [path])
    return files


def read_records(path: Path, recording: Recording) -> Iterator[tuple[Channel, Message]]:
    """Every message of one file with its channel, in file order, up to the last whole record."""
    channels: dict[int, Channel] = {}
    with path.open("rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    yield channels[record.channel_id], record
        except (McapError, EOFError, ValueError, struct.error) as error:  # a killed writer's last chunk, cut short
            recording.truncated.append(f"{path}: {type(error).__name__}: {error}")


def read_recording(paths: list[Path]) -> Recording:
    recording = Recording()
    for path in recording_files(paths):
        for channel, message in read_records(path, recording):
            if not channel.topic.startswith(_TOPIC_PREFIX):
                continue
            route_name, _, kind = channel.topic[len(_TOPIC_PREFIX):].rpartition("/")
            route = recording.routes.setdefault(route_name, RecordedRoute())
            if kind == "in":
                number = len(route.inputs) + 1
                route.inputs[number] = (message.log_time, json.loads(message.data))
                route.received[message.publish_time] = number
            elif kind == "canonical":
                sequence = route.received.get(message.publish_time, 0)
                if sequence:  # else a window's message, or one whose input is in a file removed since
                    route.canonical[sequence] = json.loads(message.data)
    return recording


def inbound_of(envelope: dict[str, Any]) -> Inbound:
    """The recorded input as the source handed it over."""
    meta = envelope.get("meta") or {}
    if "text" in envelope:
        inbound = Inbound(body=envelope["text"].encode("utf-8"), meta=meta)
    elif "base64" in envelope:
        inbound = Inbound(body=base64.b64decode(envelope["base64"]), meta=meta)
    else:
        inbound = Inbound(fields=envelope.get("fields"), meta=meta)
    inbound.undecodable = envelope.get("undecodable")
    return inbound


@dataclass
class Outcome:
    compared: int = 0
    differ: int = 0
    unsent: int = 0
    """Inputs with no recorded canonical message (dead-lettered, dropped or still in flight)."""
    skipped: dict[str, int] = field(default_factory=dict)
    """Routes of the recording the routes directory no longer has (or that have no schema now), and their inputs."""
    unrepeatable: dict[str, list[str]] = field(default_factory=dict)
    """Per route, the keys its mapping takes from the clock or a random id (``stamp()``,
    ``now()``, ``uuid()``): never the same twice, so left out of the comparison."""


def replay(recording: Recording, config: RoutesConfig, schemas: SchemaRegistry, only: str | None = None,
           ignore: tuple[str, ...] = ()) -> Iterator[str | Outcome]:
    """The report's lines (a diff per message that changed), then the :class:`Outcome`;
    ``ignore``: keys (``a.b``) left out of the comparison, besides those each route's mapping
    takes from the clock or a random id (found in the mapping: :func:`unrepeatable_keys`)."""
    outcome = Outcome()
    stores = Stores()
    for name, recorded in sorted(recording.routes.items()):
        if only is not None and name != only:
            continue
        spec = config.routes.get(name)
        schema = schemas.get(spec.schema) if spec is not None else None
        if spec is None or schema is None:
            outcome.skipped[name] = len(recorded.inputs)
            continue
        reply_schema = schemas.get(spec.reply.schema) if spec.reply is not None and spec.reply.schema else None
        pipeline = Pipeline.compile(spec, 0, schema, DrySink(), reply_schema, stores)
        unrepeatable = [key for key in unrepeatable_keys(spec.mapping) if key not in ignore]
        if unrepeatable:
            outcome.unrepeatable[name] = unrepeatable
        route_ignore = (*ignore, *unrepeatable)
        for sequence, (log_time, envelope) in sorted(recorded.inputs.items()):
            before = recorded.canonical.get(sequence)
            try:
                outbound = pipeline.convert(inbound_of(envelope))
                now: Any = _plain(outbound.canonical)
                error = None
            except ConversionError as failure:
                now, error = None, f"{failure.stage} error: {failure.detail}"
            except Filtered:
                now, error = None, "message the route's when: rejects (nothing sent)"
            if before is None:
                outcome.unsent += 1
                continue
            outcome.compared += 1
            if pipeline.remember is not None and now is not None:  # as the engine did: converted, then sent
                pipeline.remember.on_converted(outbound.canonical, outbound.meta)
                pipeline.remember.on_accepted(outbound.canonical, outbound.meta)
            if error is None:
                before, now = _without(before, route_ignore), _without(now, route_ignore)
                if same(before, now):
                    continue
            outcome.differ += 1
            when = datetime.fromtimestamp(log_time / 1e9, timezone.utc).isoformat(timespec="milliseconds")
            if error is not None:
                yield f"DIFF  {name} #{sequence} (received {when}): sent then, now a {error}"
                continue
            yield f"DIFF  {name} #{sequence} (received {when}): canonical message differs"
            yield from ("      " + line for line in _diff(before, now))
    yield outcome


def opened(paths: list[Path], routes: Path, schemas_dir: Path | Sequence[Path],
           only: str | None) -> tuple[Recording, RoutesConfig, SchemaRegistry] | None:
    """What both replays start from: the recording, the routes as they are now and their schemas;
    None (said on stderr) when there is no recording, the routes are invalid, or ``only`` names a
    route the recording lacks (the command's exit status 2)."""
    files = recording_files(paths)
    missing = [str(path) for path in files if not path.is_file()]
    if missing or not files:
        print(f"no recording: {', '.join(missing) or ' '.join(map(str, paths))}", file=sys.stderr)
        return None
    schemas = SchemaRegistry(schemas_dir)
    config, _, problems, _ = load_checked(routes, schemas)
    for problem in problems:
        print(problem, file=sys.stderr)
    if config is None or problems:
        return None
    recording = read_recording(files)
    for note in recording.truncated:
        print(f"note: {note} (read up to the last whole chunk)", file=sys.stderr)
    if only is not None and only not in recording.routes:
        print(f"route {only!r} is not in the recording (it has: {', '.join(sorted(recording.routes)) or 'none'})", file=sys.stderr)
        return None
    return recording, config, schemas


def run_replay(paths: list[Path], routes: Path, schemas_dir: Path | Sequence[Path], only: str | None = None, ignore: tuple[str, ...] = ()) -> int:
    """The command: 0 when every recorded canonical message is what the routes make now, 1 when
    one differs, 2 when the routes are invalid or nothing was recorded."""
    opening = opened(paths, routes, schemas_dir, only)
    if opening is None:
        return 2
    recording, config, schemas = opening
    outcome = Outcome()
    for item in replay(recording, config, schemas, only, ignore):
        if isinstance(item, Outcome):
            outcome = item
        else:
            print(item, flush=True)
    for name, keys in sorted(outcome.unrepeatable.items()):
        print(f"not compared in route {name!r}: {', '.join(keys)} (the mapping takes them from the clock or a random id)", file=sys.stderr)
    for name, count in sorted(outcome.skipped.items()):
        print(f"skipped route {name!r}: not in {routes} now ({count} recorded inputs)", file=sys.stderr)
    print(f"{outcome.compared} messages compared: {outcome.compared - outcome.differ} same, {outcome.differ} differ; "
          f"{outcome.unsent} inputs never sent (not compared)")
    return 1 if outcome.differ else 0


def _plain(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def _diff(before: Any, now: Any) -> list[str]:
    def lines(value: Any) -> list[str]:
        return json.dumps(value, indent=2, sort_keys=True, ensure_ascii=False).splitlines()

    return list(difflib.unified_diff(lines(before), lines(now), "recorded", "now", lineterm="", n=2))


def recorded_cases(recording: Recording, config: RoutesConfig, route: str, count: int) -> tuple[list[dict[str, Any]], int]:
    """``test --from-recording``: route test cases (the ``*.test.yaml`` form, engine/ops/route_tests.py)
    from the first ``count`` recorded inputs of ``route`` that were sent, each expecting the
    canonical message recorded for it; and how many inputs could not be written as a case
    (bytes that are not text)."""
    spec = config.routes[route]
    given = [name for name in source_meta_names(spec.source, {}) if name not in spec.variables]
    recorded = recording.routes.get(route, RecordedRoute())
    cases: list[dict[str, Any]] = []
    unwritable = 0
    for sequence, (log_time, envelope) in sorted(recorded.inputs.items()):
        if len(cases) == count:
            break
        if sequence not in recorded.canonical:
            continue
        case: dict[str, Any] = {"name": f"recorded #{sequence} at "
                                        f"{datetime.fromtimestamp(log_time / 1e9, timezone.utc).isoformat(timespec='milliseconds')}",
                                "route": route}
        if "fields" in envelope:
            case["input"] = envelope["fields"]
        elif "text" in envelope:
            try:
                case["input"] = json.loads(envelope["text"])
            except ValueError:
                case["input_raw"] = envelope["text"]
        else:
            unwritable += 1
            continue
        meta = {key: value for key, value in (envelope.get("meta") or {}).items() if key in given}
        if meta:
            case["meta"] = meta
        case["expect"] = recorded.canonical[sequence]
        cases.append(case)
    return cases, unwritable


def run_from_recording(paths: list[Path], routes: Path, schemas_dir: Path | Sequence[Path], route: str, count: int) -> int:
    """Print the cases as a test file (YAML) on stdout; 2 when the route or the recording is not there."""
    files = recording_files(paths)
    if not files or not all(path.is_file() for path in files):
        print(f"no recording: {' '.join(map(str, paths))}", file=sys.stderr)
        return 2
    config, _, problems, _ = load_checked(routes, SchemaRegistry(schemas_dir))
    for problem in problems:
        print(problem, file=sys.stderr)
    if config is None or problems:
        return 2
    if route not in config.routes:
        print(f"unknown route {route!r} in {routes}", file=sys.stderr)
        return 2
    cases, unwritable = recorded_cases(read_recording(files), config, route, count)
    if not cases:
        print(f"route {route!r}: no recorded message that was sent", file=sys.stderr)
        return 2
    if unwritable:
        print(f"route {route!r}: {unwritable} inputs left out (bytes that are not UTF-8 text: no test input can hold them)",
              file=sys.stderr)
    print(f"# route tests from {', '.join(map(str, files))}: the canonical message each input made when it was recorded")
    print(yaml.safe_dump({"tests": cases}, sort_keys=False, allow_unicode=True), end="")
    return 0
