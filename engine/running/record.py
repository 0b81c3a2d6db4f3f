"""Recording (``--record DIR``): what each route received and the canonical message it sent, in MCAP.

Per route two channels: ``/routes/NAME/in`` (what the source handed over, as received: the
bytes, or a typed source's fields, with the source's metadata and the receive time; a JSON
envelope, :data:`INPUT_SCHEMA`) and ``/routes/NAME/canonical`` (the canonical message the sink
took, its JSON as sent, the route's JSON Schema as the channel's schema, encoding
``jsonschema``). ``log_time`` (= ``publish_time``) is when the engine received the input, on
both channels: an input and the canonical message made of it share it, which is how
``rabbitros-engine replay`` (engine/ops/replay.py) pairs them (a window's message, made of no
one input, carries the time it was sent). The ``in`` channel's ``sequence`` numbers the route's
inputs within the file, from 1 (the SDK counts per channel and file).

Files are written by the Foxglove SDK's MCAP writer (``foxglove-sdk``: a Rust writer,
``foxglove.open_mcap``), on a :class:`foxglove.Context` of the recorder's own (nothing else
logged through the SDK, such as the ``--foxglove`` live view, lands in the file), with
``flush()`` called when we choose (a chunk out every ``flush_s``, so a ``kill -9`` loses at most
about a second) and rotation done here (one writer per file). It replaced the ``mcap`` library's
pure-Python ``Writer``: ``add_message`` cost 2.5 us a message (zstd, 1 MiB chunks; lz4, no
message index or no CRCs saved at most 0.3 us), the SDK's ``log`` 0.4-0.6 us (measured in one
process, 100,000 messages each). The files are read by the ``mcap`` library's reader (tests,
``replay``) as before.

Recording never holds a route: the route appends a reference to a bounded deque (a few
hundred nanoseconds, no lock, no serialisation: the canonical bytes are the ones the sink
got, the input is serialised by the writer) and a writer thread drains it every
``POLL_S``, writes chunks (zstd), flushes one at least every ``limits.flush_s`` and rotates
files by size and age; when the files together exceed ``limits.total_bytes`` the oldest are
removed. A full deque (a disk slower than the routes) drops the recorded copy, counted per route
(status and ``rabbitros_recording_dropped_total``), never the message. A route with ``record:
false``, or an engine without ``--record``, has no :class:`RouteRecording` and pays one ``is
None`` test per batch and per sent message.

Cost (bench/bench_record.py: an engine with and one without ``--record`` at the same time, on a
shared 2-CPU machine): +7 to +8 % engine CPU per message (medians of two sessions of 7 rounds,
every round +6 % to +11 %; the ``mcap`` writer gave +10.9 %, +5 % to +26 %). In process 3.7-5.3
us a message: the route's two appends 1.2 us, the writer thread's drain 2.4 us, the rest the
thread's turns and flushes. lz4 or zstd level 1 instead of zstd's default saved 0.1-0.3 us, within
the noise: zstd stays (65 bytes a message on disk).
"""

from __future__ import annotations

import base64
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Sequence

import orjson

from engine import __version__
from engine.endpoints.base import Inbound, Outbound

if TYPE_CHECKING:  # imported when a recording starts: the SDK's import costs some 40 ms every command would pay
    import foxglove

_Log = Callable[[Any, int, Any], None]
"""A channel's ``log(message, log_time, sink_id)`` (foxglove.Channel.log)."""


def _unlogged(message: Any, log_time: int, sink_id: Any) -> None:
    """Where the writer loop starts, before its first entry names its channels."""
    raise AssertionError("a recorded entry before its channels")

log = logging.getLogger("engine.running.record")

FILE_PATTERN = "rabbitros-*.mcap"
IN_TOPIC = "/routes/{route}/in"
CANONICAL_TOPIC = "/routes/{route}/canonical"
POLL_S = 0.05
RETRY_S = 1.0
"""After a file could not be written, the next is opened no sooner than this (recorded copies
meanwhile dropped, counted): a full disk is not hammered with a new empty file every ``POLL_S``."""
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
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._file: _File | None = None
        self._context: foxglove.Context | None = None
        """The recorder's own SDK context, made by the writer thread; its channels outlive a file."""
        self._inputs: dict[str, foxglove.Channel] = {}
        """Per route: its ``in`` channel (the same whatever the route's schema: its ``sequence`` goes on)."""
        self._canonical: dict[_Channels, foxglove.Channel] = {}
        self._logs: dict[_Channels, tuple[_Log, _Log]] = {}
        self._unflushed: dict[str, int] = {}
        self._retry_at = 0.0
        """Monotonic time before which no new file is opened after a failure (:data:`RETRY_S`)."""
        """Per route: messages logged to the file since its last flush (``written`` once flushed)."""
        """Per route's channels: the ``log`` of its ``in`` and ``canonical`` SDK channels."""
        self._offset_ns = time.time_ns() - time.monotonic_ns()
        """Receive times are monotonic; recorded as wall time with one offset for the recorder's
        life, so an input and its canonical message (written in different drains) carry the same
        time, which pairs them."""
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
        import foxglove  # here, not with the first message: its import (26 ms of CPU) is the engine's start-up

        self.directory.mkdir(parents=True, exist_ok=True)
        self._context = foxglove.Context()
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()
        log.info("recording", extra={"directory": str(self.directory), "compression": "zstd"})

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
                    current.flush()
                    self._flushed()
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
            self._flushed()
        except OSError as error:
            self._failed(error)

    def _flushed(self) -> None:
        """What was logged since the last flush is in the file: counted written."""
        self.written += sum(self._unflushed.values())
        self._unflushed.clear()

    def _failed(self, error: OSError) -> None:
        """The file cannot be written: what is queued, and what was logged to the file since its
        last flush, is dropped, counted by route (chunks of it that filled up and reached the
        file before the one the disk refused are readable nonetheless: the SDK says nothing of
        which did); the file is abandoned and, after :data:`RETRY_S`, the next message opens a
        new one."""
        self.write_errors += 1
        if self.last_error != str(error):
            log.error("recording failed; recorded copies are dropped until a file can be written", extra={"error": str(error)})
        self.last_error = str(error)
        for route, count in self._unflushed.items():
            self.drop(route, count)
        self._unflushed.clear()
        while self.queue:
            channels, *_ = self.queue.popleft()
            self.drop(channels.route, 1)
        self._retry_at = time.monotonic() + RETRY_S
        current, self._file = self._file, None
        if current is not None:
            current.abandon()

    def _drain(self) -> None:
        """Write what is queued. Per message this is the cost of recording beside the route's
        append: the SDK's ``log`` (0.4-0.6 us, the serialisation and zstd included) for the input
        and for the canonical message, and the input's JSON envelope (0.7 us)."""
        queue = self.queue
        if not queue:
            return
        if self._file is None and time.monotonic() < self._retry_at:
            while queue:
                channels, *_ = queue.popleft()
                self.drop(channels.route, 1)
            return
        stream = (self._file or self._open()).stream
        offset_ns = self._offset_ns
        unflushed = self._unflushed
        last: _Channels | None = None
        log_input: _Log = _unlogged
        log_canonical: _Log = _unlogged
        route = ""
        while queue:
            if stream.error is not None:  # the disk refused a chunk: stop logging into a writer that failed
                raise stream.error
            channels, inbound, outbound, sent_at_ns = queue.popleft()
            if channels is not last:
                log_input, log_canonical = self._logs.get(channels) or self._channels(channels)
                last, route = channels, channels.route
            if inbound is not None:
                received_at_ns = inbound.received_ns + offset_ns
                log_input(_input_json(inbound, received_at_ns), received_at_ns, None)
            elif outbound is not None:
                received_ns = outbound.received_ns
                log_canonical(outbound.body, sent_at_ns if received_ns is None else received_ns + offset_ns, None)
            unflushed[route] = unflushed.get(route, 0) + 1

    def _channels(self, channels: _Channels) -> tuple[_Log, _Log]:
        """The ``log`` of the route's two SDK channels (declared on first use; a route whose
        schema changed gets a new canonical channel, the old one closed)."""
        import foxglove

        context = self._context
        assert context is not None  # made by start()
        route = channels.route
        inputs = self._inputs.get(route)
        if inputs is None:
            inputs = self._inputs[route] = foxglove.Channel(
                IN_TOPIC.format(route=route), message_encoding="json", context=context, metadata={"route": route},
                schema=foxglove.Schema(name="rabbitros.Received", encoding="jsonschema", data=_INPUT_SCHEMA_BYTES))
        canonical = self._canonical.get(channels)
        if canonical is None:
            for old in [other for other in self._canonical if other.route == route]:
                self._canonical.pop(old).close()
                self._logs.pop(old, None)
            canonical = self._canonical[channels] = foxglove.Channel(
                CANONICAL_TOPIC.format(route=route), message_encoding="json", context=context,
                metadata={"route": route, "schema": channels.schema_name},
                schema=foxglove.Schema(name=channels.schema_name, encoding="jsonschema", data=channels.schema))
        logs = self._logs[channels] = (inputs.base.log, canonical.base.log)
        return logs

    def _open(self) -> _File:
        assert self._context is not None  # made by start()
        stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S-%f")
        path = self.directory / f"rabbitros-{stamp}.mcap"
        self._file = _File(path, self.limits.chunk_bytes, self._context)
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


class _Stream:
    """The file as the SDK's writer writes it (``write``, ``seek``, ``flush``; a chunk at a time,
    buffered): it keeps the first error, which the SDK only logs (``log`` raises nothing), so the
    writer thread sees a full or vanished disk at once and abandons the file."""

    def __init__(self, path: Path) -> None:
        self.file = open(path, "wb")  # closed by close()
        self.error: OSError | None = None

    def write(self, data: bytes | bytearray) -> int:
        try:
            return self.file.write(data)
        except OSError as error:
            self.error = self.error or error
            raise

    def seek(self, offset: int, whence: int = 0) -> int:
        try:
            return self.file.seek(offset, whence)
        except OSError as error:
            self.error = self.error or error
            raise

    def flush(self) -> None:
        try:
            self.file.flush()
        except OSError as error:
            self.error = self.error or error
            raise

    def close(self) -> None:
        try:
            self.file.close()
        except OSError:  # its disk failed: what it says next adds nothing
            pass


class _File:
    """One MCAP file being written: the SDK's writer on the recorder's context (every channel of
    the context is written to it from its first message in this file)."""

    def __init__(self, path: Path, chunk_bytes: int, context: foxglove.Context) -> None:
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.path = path
        self.opened = time.monotonic()
        self.stream = _Stream(path)
        options = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=chunk_bytes, compression_threads=0,
                                   profile="")
        try:
            self.writer = foxglove.open_mcap(self.stream, context=context, writer_options=options)
            self.writer.write_metadata("rabbitros", {"engine_version": __version__, "layout": "routes/NAME/in, routes/NAME/canonical"})
        except Exception as error:  # the SDK's FoxgloveError: a disk that refused the header
            self.stream.close()
            path.unlink(missing_ok=True)  # nothing of it could be read
            raise self.stream.error or OSError(str(error)) from None

    def flush(self) -> None:
        """Write the chunk in progress; an OSError when the disk refused it (now or before)."""
        try:
            self.writer.flush()
        except Exception as error:  # the SDK's FoxgloveError: the stream knows the OSError behind it
            raise self.stream.error or OSError(str(error)) from None
        if self.stream.error is not None:
            raise self.stream.error

    def full(self, limits: RecordLimits, now: float) -> bool:
        return _size(self.path) >= limits.file_bytes or now - self.opened >= limits.file_seconds

    def finish(self) -> None:
        """Write the summary and close the file (detached from the context)."""
        try:
            self.writer.close()
        except Exception as error:  # the SDK's FoxgloveError, after a write the disk refused
            raise self.stream.error or OSError(str(error)) from None
        finally:
            self.stream.close()
        if self.stream.error is not None:
            raise self.stream.error

    def abandon(self) -> None:
        """Detach a file whose disk failed from the context; what it holds is what it holds."""
        try:
            self.writer.close()
        except Exception:  # noqa: BLE001 - the failure was counted already
            pass
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
