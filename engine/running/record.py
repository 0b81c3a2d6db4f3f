"""Recording (``--record DIR``): what each route received and the canonical message it sent, in MCAP.

Per route two channels: ``/routes/NAME/in`` (what the source handed over, as received: the
bytes, or a typed source's fields, with the source's metadata and the receive time; a JSON
envelope, :data:`INPUT_SCHEMA`) and ``/routes/NAME/canonical`` (the canonical message the sink
took, its JSON as sent, the route's JSON Schema as the channel's schema, encoding
``jsonschema``). A message's ``sequence`` is the same on both channels (its number among the
route's inputs), which is how ``rabbitros-engine replay`` (engine/ops/replay.py) pairs them;
``log_time`` is when the engine received (``in``) or sent (``canonical``) it, ``publish_time``
when it was received on both.

Files are written by the ``mcap`` library (PyPI ``mcap``, the format's reference Python
writer) rather than the Foxglove SDK's writer: the SDK's ``foxglove.open_mcap`` logs through the
SDK's global channels (one process-wide context, every channel also offered to a live
WebSocket server), offers no flush we call at the time we choose (we need a chunk out every
second so a ``kill -9`` loses at most a second) and no rotation; ``mcap.writer.Writer`` is a
plain object per file with ``flush()``, zstd or lz4 chunks, and is what the reader our tests
use is tested against.

Recording never holds a route: the route appends a reference to a bounded deque (a few
hundred nanoseconds, no lock, no serialisation: the canonical bytes are the ones the sink
got, the input is serialised by the writer) and a writer thread drains it every
``POLL_S``, writes chunks (zstd, else lz4, else none), flushes one at least every
``limits.flush_s`` and rotates files by size and age; when the files together exceed
``limits.total_bytes`` the oldest are removed. A full deque (a disk slower than the routes)
drops the recorded copy, counted per route (status and ``rabbitros_recording_dropped_total``),
never the message. A route with ``record: false``, or an engine without ``--record``, has no
:class:`RouteRecording` and pays one ``is None`` test per batch and per sent message.

Cost (bench/bench_record.py, measured on a shared 2-CPU machine): the route's part 1.2 us a
message; the writer thread about 8.5 us (``add_message`` 2.9 us each for the input and the
canonical message, the input's envelope 0.7 us); end to end 11-30 % more engine CPU per message
than without (74-105 us), above the issue's 10 % goal: the pure-Python writer is the lever left.
"""

from __future__ import annotations

import base64
import hashlib
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import IO, Any, Sequence

import orjson
from mcap.writer import CompressionType, Writer

from engine import __version__
from engine.endpoints.base import Inbound, Outbound

log = logging.getLogger("engine.running.record")

FILE_PATTERN = "rabbitros-*.mcap"
IN_TOPIC = "/routes/{route}/in"
CANONICAL_TOPIC = "/routes/{route}/canonical"
POLL_S = 0.05
"""How often the writer thread drains the queue: the route never wakes it (no per-message
notify), so this bounds both the delay and how much one drain writes."""
INPUT_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "rabbitros.Received",
    "description": "A message as a route's source received it: exactly one of text (bytes that are UTF-8), base64 "
                   "(other bytes) or fields (a typed source's message); meta is the source's metadata (topic, "
                   "routing_key, system_id, ...)",
    "type": "object",
    "required": ["received_at", "meta"],
    "properties": {
        "received_at": {"type": "number", "description": "seconds since the epoch"},
        "meta": {"type": "object"},
        "text": {"type": "string"},
        "base64": {"type": "string", "contentEncoding": "base64"},
        "fields": {"type": "object"},
        "undecodable": {"type": "string", "description": "why the source could not make a message of it"},
    },
}
_INPUT_SCHEMA_BYTES = orjson.dumps(INPUT_SCHEMA)
_JSON_OPTIONS = orjson.OPT_NON_STR_KEYS | orjson.OPT_SERIALIZE_NUMPY


def _compression() -> CompressionType:
    for kind, module in ((CompressionType.ZSTD, "zstandard"), (CompressionType.LZ4, "lz4.frame")):
        try:
            __import__(module)
        except ImportError:
            continue
        return kind
    return CompressionType.NONE


@dataclass(frozen=True)
class RecordLimits:
    file_bytes: int = 256 * 2**20
    """A file is closed and the next one opened past this size."""
    file_seconds: float = 3600.0
    """... or once it is this old."""
    total_bytes: int = 4 * 2**30
    """The oldest files are removed while the directory's recordings exceed this."""
    queue: int = 20000
    """Messages waiting for the writer thread; beyond it, recorded copies are dropped (counted)."""
    flush_s: float = 0.5
    """A chunk is written at least this often: after ``kill -9`` all but the last ``flush_s`` (and
    the writer's ``POLL_S``) is in the file."""
    chunk_bytes: int = 1 * 2**20


@dataclass(frozen=True, eq=False)
class _Channels:
    """One route's two channels, as declared (a reload with another schema declares new ones)."""

    route: str
    schema_name: str
    schema: bytes


class RouteRecording:
    """What a route calls, on the event loop: a reference appended to the recorder's queue."""

    __slots__ = ("recorder", "channels")

    def __init__(self, recorder: Recorder, channels: _Channels) -> None:
        self.recorder = recorder
        self.channels = channels

    def received(self, inbounds: Sequence[Inbound]) -> None:
        recorder = self.recorder
        queue = recorder.queue
        if len(queue) + len(inbounds) > recorder.limits.queue:
            recorder.drop(self.channels.route, len(inbounds))
            return
        channels = self.channels
        for inbound in inbounds:
            queue.append((channels, inbound, None, 0))

    def sent(self, outbound: Outbound) -> None:
        recorder = self.recorder
        queue = recorder.queue
        if len(queue) >= recorder.limits.queue:
            recorder.drop(self.channels.route, 1)
            return
        queue.append((self.channels, None, outbound, time.time_ns()))


class Recorder:
    """The recording of an engine: the queue the routes fill and the thread writing it out."""

    def __init__(self, directory: Path, limits: RecordLimits | None = None) -> None:
        self.directory = directory
        self.limits = limits or RecordLimits()
        self.queue: deque[tuple[_Channels, Inbound | None, Outbound | None, int]] = deque()
        self.dropped: dict[str, int] = {}
        self.written = 0
        self.files_removed = 0
        self.write_errors = 0
        self.last_error: str | None = None
        self._compression = _compression()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._file: _File | None = None
        self._sequence: dict[str, int] = {}
        self._pending: dict[str, dict[int, int]] = {}
        """Per route: an input's receive time (monotonic ns, which its outbound carries) -> its sequence."""
        self._routes: dict[str, RouteRecording] = {}

    # -- the event loop's side

    def route(self, name: str, schema_name: str, schema: dict[str, Any]) -> RouteRecording:
        """The handle route ``name`` records through (the same while its schema is the same)."""
        data = orjson.dumps(schema, option=orjson.OPT_SORT_KEYS)
        current = self._routes.get(name)
        if current is not None and current.channels.schema == data and current.channels.schema_name == schema_name:
            return current
        recording = self._routes[name] = RouteRecording(self, _Channels(name, schema_name, data))
        return recording

    def drop(self, route: str, count: int) -> None:
        self.dropped[route] = self.dropped.get(route, 0) + count

    def start(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        log.info("recording", extra={"directory": str(self.directory), "compression": self._compression.name.lower()})

    def stop(self) -> None:
        """Write what is queued and close the file with its summary (blocking: call it in a thread)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join()

    def status(self) -> dict[str, Any]:
        current = self._file
        return {"directory": str(self.directory), "file": None if current is None else str(current.path),
                "written": self.written, "queued": len(self.queue), "dropped": sum(self.dropped.values()),
                "dropped_by_route": dict(self.dropped), "files_removed": self.files_removed,
                "write_errors": self.write_errors, "last_error": self.last_error}

    # -- the writer thread

    def _run(self) -> None:
        last_flush = time.monotonic()
        while True:
            stopping = self._stop.wait(POLL_S)
            try:
                self._drain()
                now = time.monotonic()
                current = self._file
                if current is not None and (stopping or now - last_flush >= self.limits.flush_s):
                    current.writer.flush()
                    last_flush = now
                    if current.full(self.limits, now):
                        self._close()
                        self._remove_oldest()
            except OSError as error:  # a full or vanished disk: what was queued is lost, counted; try again
                self._failed(error)
            except Exception as error:  # a message the writer could not serialise: that one is lost, the thread goes on
                self.write_errors += 1
                if self.last_error != repr(error):
                    log.exception("recording: a message could not be written")
                self.last_error = repr(error)
            if stopping:
                break
        try:
            self._close()
        except OSError as error:
            self._failed(error)

    def _failed(self, error: OSError) -> None:
        self.write_errors += 1
        if self.last_error != str(error):
            log.error("recording failed; recorded copies are dropped until a file can be written", extra={"error": str(error)})
        self.last_error = str(error)
        while self.queue:
            channels, *_ = self.queue.popleft()
            self.drop(channels.route, 1)
        self._file = None  # the next message opens a new file

    def _drain(self) -> None:
        """Write what is queued. Per message this is the cost of recording beside the route's
        append: measured 8.5 us per input and canonical pair (the ``mcap`` writer's
        ``add_message``, 2.9 us each, is most of it; the input's JSON envelope 0.7 us)."""
        queue = self.queue
        if not queue:
            return
        current = self._file or self._open()
        add = current.writer.add_message
        offset_ns = time.time_ns() - time.monotonic_ns()
        sequences, pending_by_route, most = self._sequence, self._pending, self.limits.queue
        last: _Channels | None = None
        in_id = canonical_id = 0
        written = 0
        try:
            while queue:
                channels, inbound, outbound, sent_at_ns = queue.popleft()
                if channels is not last:
                    in_id, canonical_id = current.channel_ids(channels)
                    last = channels
                route = channels.route
                if inbound is not None:
                    sequence = sequences[route] = (sequences.get(route, 0) + 1) & 0xFFFFFFFF
                    received_at_ns = inbound.received_ns + offset_ns
                    pending = pending_by_route.get(route)
                    if pending is None:
                        pending = pending_by_route[route] = {}
                    pending[inbound.received_ns] = sequence
                    if len(pending) > most:  # inputs never sent (dead-lettered, dropped): forget the oldest
                        del pending[next(iter(pending))]
                    add(in_id, received_at_ns, _input_json(inbound, received_at_ns), received_at_ns, sequence)
                elif outbound is not None:
                    received_ns = outbound.received_ns
                    pending = pending_by_route.get(route)
                    sequence = 0 if received_ns is None or pending is None else pending.pop(received_ns, 0)
                    add(canonical_id, sent_at_ns, outbound.body, sent_at_ns if received_ns is None else received_ns + offset_ns,
                        sequence)
                written += 1
        finally:
            self.written += written

    def _open(self) -> _File:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
        path = self.directory / f"rabbitros-{stamp}.mcap"
        self._file = _File(path, self.limits.chunk_bytes, self._compression)
        self._remove_oldest()
        return self._file

    def _close(self) -> None:
        current, self._file = self._file, None
        if current is not None:
            current.finish()

    def _remove_oldest(self) -> None:
        files = sorted(self.directory.glob(FILE_PATTERN))
        sizes = {path: _size(path) for path in files}
        total = sum(sizes.values())
        for path in files:
            if total <= self.limits.total_bytes or (self._file is not None and path == self._file.path):
                break
            path.unlink(missing_ok=True)
            total -= sizes[path]
            self.files_removed += 1


class _File:
    """One MCAP file being written, with the channels declared in it so far."""

    def __init__(self, path: Path, chunk_bytes: int, compression: CompressionType) -> None:
        self.path = path
        self.opened = time.monotonic()
        self.stream: IO[bytes] = open(path, "wb")  # closed by finish()
        self.writer = Writer(self.stream, chunk_size=chunk_bytes, compression=compression)
        self.writer.start(profile="", library=f"rabbitros-engine {__version__}")
        self.writer.add_metadata("rabbitros", {"engine_version": __version__, "layout": "routes/NAME/in, routes/NAME/canonical"})
        self.input_schema = self.writer.register_schema("rabbitros.Received", "jsonschema", _INPUT_SCHEMA_BYTES)
        self._ids: dict[_Channels, tuple[int, int]] = {}
        self._schemas: dict[bytes, int] = {}

    def channel_ids(self, channels: _Channels) -> tuple[int, int]:
        ids = self._ids.get(channels)
        if ids is None:
            digest = hashlib.sha256(channels.schema).digest()
            schema_id = self._schemas.get(digest)
            if schema_id is None:
                schema_id = self._schemas[digest] = self.writer.register_schema(channels.schema_name, "jsonschema", channels.schema)
            route = channels.route
            ids = self._ids[channels] = (
                self.writer.register_channel(IN_TOPIC.format(route=route), "json", self.input_schema, {"route": route}),
                self.writer.register_channel(CANONICAL_TOPIC.format(route=route), "json", schema_id,
                                             {"route": route, "schema": channels.schema_name}),
            )
        return ids

    def full(self, limits: RecordLimits, now: float) -> bool:
        return self.stream.tell() >= limits.file_bytes or now - self.opened >= limits.file_seconds

    def finish(self) -> None:
        try:
            self.writer.finish()
        finally:
            self.stream.close()


def _input_json(inbound: Inbound, received_at_ns: int) -> bytes:
    record: dict[str, Any] = {"received_at": received_at_ns / 1e9, "meta": inbound.meta}
    if inbound.body is not None:
        try:
            record["text"] = inbound.body.decode("utf-8")
        except UnicodeDecodeError:
            record["base64"] = base64.b64encode(inbound.body).decode("ascii")
    else:
        record["fields"] = inbound.fields
    if inbound.undecodable is not None:
        record["undecodable"] = inbound.undecodable
    return orjson.dumps(record, default=str, option=_JSON_OPTIONS)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0
