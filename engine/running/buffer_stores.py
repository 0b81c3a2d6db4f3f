"""Where a route's buffer (engine/running/buffer.py) keeps what it holds: in memory, or in
spill files (append-only JSON-lines segments of ``SEGMENT_MESSAGES`` messages and a cursor
replaced atomically; the format is described in engine/running/buffer.py's docstring), and
the encoding of one held message as a line.
"""

from __future__ import annotations

import base64
import logging
import collections
import os
import time
from pathlib import Path
from typing import Iterator

import orjson

from engine.common.json_bytes import json_bytes
from engine.common.schemas import parse_json

from engine.endpoints.base import Outbound

log = logging.getLogger("engine.running.buffer")

SEGMENT_MESSAGES = 1_000
"""Messages per spill segment: a delivered segment is deleted whole."""

Held = tuple[Outbound, int | None]
"""A held message and when it was received (wall-clock ns, so it survives a restart), or None."""


def encode(message: Outbound, received_at_ns: int | None = None) -> bytes:
    """One JSON line for a held message."""
    try:
        body: dict[str, str] = {"b": message.body.decode("utf-8")}
    except UnicodeDecodeError:
        body = {"b64": base64.b64encode(message.body).decode()}
    record = {**body, "id": message.message_id, "c": message.canonical, "m": dict(message.meta)}
    if message.fields is not message.canonical:
        record["f"] = message.fields
    if message.captured:
        record["v"] = message.captured
    if received_at_ns is not None:
        record["t"] = received_at_ns
    return json_bytes(record, orjson.OPT_APPEND_NEWLINE)  # an integer beyond 64 bits kept exactly (json_bytes.py)


def decode(line: bytes) -> Outbound:
    return decode_held(line)[0]


def decode_held(line: bytes) -> Held:
    record = parse_json(line)  # the engine's one parser: an integer beyond 64 bits comes back exact
    body = record["b"].encode() if "b" in record else base64.b64decode(record["b64"])
    canonical = record["c"]
    received_at = record.get("t")  # wall clock ns (it outlives the process); the sink's clock is monotonic
    received_ns = None if received_at is None else time.monotonic_ns() - (time.time_ns() - received_at)
    return Outbound(body, canonical, record.get("f", canonical), record["id"], record["m"],
                    received_ns=received_ns, captured=record.get("v")), received_at


class MemoryStore:
    def __init__(self) -> None:
        self._messages: collections.deque[Held] = collections.deque()

    def load(self) -> tuple[int, int]:
        return len(self._messages), 0

    def append(self, held: Held) -> None:
        self._messages.append(held)

    def peek(self, count: int) -> list[Held]:
        return [self._messages[i] for i in range(min(count, len(self._messages)))]

    def pop(self, count: int) -> None:
        for _ in range(count):
            self._messages.popleft()

    def close(self) -> None:
        pass


class SpillStore:
    """Append-only JSON-lines segments plus a cursor; see the module docstring."""

    def __init__(self, directory: Path, fsync_interval: float) -> None:
        self.directory = directory
        self.fsync_interval = fsync_interval
        self._segments: list[int] = []  # first sequence numbers, oldest first
        self._write_fd: int | None = None
        self._write_count = 0
        self._next_seq = 0
        self._dirty = False
        self._last_sync = time.monotonic()
        self._read: tuple[int, int] = (0, 0)  # (segment, byte offset) of the oldest held message
        self._peeked: list[tuple[Held, int, int]] = []  # message, segment, offset after it

    def load(self) -> tuple[int, int]:
        self.directory.mkdir(parents=True, exist_ok=True)
        self._segments = sorted(int(p.stem) for p in self.directory.glob("*.jsonl") if p.stem.isdigit())
        segment, offset = 0, 0
        try:
            cursor = orjson.loads((self.directory / "cursor.json").read_bytes())
            segment, offset = int(cursor["segment"]), int(cursor["offset"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        for stale in [s for s in self._segments if s < segment]:
            self._path(stale).unlink(missing_ok=True)
        self._segments = [s for s in self._segments if s >= segment]
        if self._segments and self._segments[0] != segment:
            offset = 0
        self._read = (self._segments[0], offset) if self._segments else (0, 0)
        found = corrupt = 0
        for seg in self._segments:
            start = offset if seg == self._read[0] else 0
            for line in self._lines(seg, start):
                if _valid(line):
                    found += 1
                else:
                    corrupt += 1
        if self._segments:
            last = self._segments[-1]
            self._next_seq = last + sum(1 for _ in self._lines(last, 0))
        return found, corrupt

    def _path(self, segment: int) -> Path:
        return self.directory / f"{segment:020d}.jsonl"

    def _lines(self, segment: int, offset: int) -> Iterator[bytes]:
        try:
            with open(self._path(segment), "rb") as file:
                file.seek(offset)
                for line in file:
                    yield line
        except FileNotFoundError:
            return

    def append(self, held: Held) -> None:
        if self._write_fd is None or self._write_count >= SEGMENT_MESSAGES:
            self._roll()
        assert self._write_fd is not None
        os.write(self._write_fd, encode(*held))
        self._write_count += 1
        self._next_seq += 1
        self._dirty = True
        now = time.monotonic()
        if now - self._last_sync >= self.fsync_interval:
            self._sync(now)

    def _roll(self) -> None:
        if self._write_fd is not None:
            os.fsync(self._write_fd)
            os.close(self._write_fd)
        segment = self._next_seq
        self._write_fd = os.open(self._path(segment), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
        self._write_count = 0
        if not self._segments or self._segments[-1] != segment:
            self._segments.append(segment)
            if len(self._segments) == 1:
                self._read = (segment, 0)
        _fsync_dir(self.directory)

    def _sync(self, now: float) -> None:
        if self._write_fd is not None and self._dirty:
            os.fsync(self._write_fd)
        self._dirty = False
        self._last_sync = now

    def peek(self, count: int) -> list[Held]:
        """The oldest ``count`` messages (skipping torn lines), remembering where each ends."""
        self._peeked = []
        segment_index = 0
        segment, offset = self._read
        while len(self._peeked) < count and segment_index < len(self._segments):
            seg = self._segments[segment_index]
            if seg < segment:
                segment_index += 1
                continue
            start = offset if seg == segment else 0
            position = start
            for line in self._lines(seg, start):
                if not line.endswith(b"\n") and seg == self._segments[-1]:
                    break  # being written
                position += len(line)
                try:
                    message = decode_held(line)
                except (ValueError, KeyError, TypeError):
                    log.error("spill: skipping a corrupt line", extra={"file": str(self._path(seg))})
                    continue
                self._peeked.append((message, seg, position))
                if len(self._peeked) >= count:
                    break
            segment_index += 1
        return [message for message, _, _ in self._peeked]

    def pop(self, count: int) -> None:
        _, segment, offset = self._peeked[count - 1]
        self._peeked = []
        self._read = (segment, offset)
        for old in [s for s in self._segments if s < segment]:
            self._segments.remove(old)
            self._path(old).unlink(missing_ok=True)
        if self._segments and segment != self._segments[-1] and offset >= self._path(segment).stat().st_size:
            self._segments.remove(segment)  # fully delivered and no longer written
            self._path(segment).unlink(missing_ok=True)
            self._read = (self._segments[0], 0) if self._segments else (0, 0)
        self._write_cursor()

    def _write_cursor(self) -> None:
        segment, offset = self._read
        tmp = self.directory / "cursor.json.tmp"
        tmp.write_bytes(orjson.dumps({"segment": segment, "offset": offset}))
        os.replace(tmp, self.directory / "cursor.json")

    def close(self) -> None:
        if self._write_fd is not None:
            os.fsync(self._write_fd)
            os.close(self._write_fd)
            self._write_fd = None


def _valid(line: bytes) -> bool:
    if not line.endswith(b"\n"):
        return False
    try:
        decode(line)
    except (ValueError, KeyError, TypeError):
        return False
    return True


def _fsync_dir(directory: Path) -> None:
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)
