"""The engine's one dead-letter destination, and the dead letter a failed message becomes.

``dead_letters:`` names an AMQP connection (exchange and queue ``rabbitros.dead-letter``,
routing key = route name, bounded by ``max_length``); without one, or while the broker cannot
take them, dead letters go to a local spool of rotated JSON-lines files, bounded in bytes.
All dead letters of a batch are stored together (AMQP: one confirm round). Which messages
become dead letters is the delivery policy's decision (engine/running/delivery.py).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import fcntl
import json
import logging
import os
import time
from collections import Counter
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from engine.common.logs import ReportLimiter
from engine.common.state import state_dir
from engine.endpoints.base import Connection, DeadLetterReader, EndpointError, Inbound, StoredLetter
from engine.language.stage_options import DEFAULT_SPOOL_MAX_BYTES, DeadLetterSpec
from engine.running.delivery import ATTEMPTS_HEADER, Failure

log = logging.getLogger("engine.running.dead_letters")

SPOOL_FILES = 4
"""The spool keeps its current file and SPOOL_FILES - 1 rotated ones, each at most
``spool_max_bytes / SPOOL_FILES``: bounded, and the newest dead letters are kept."""
ERROR_HEADER_LIMIT = 1000

Letter = tuple[bytes, Mapping[str, Any]]
"""A dead letter: the original body and the headers saying why."""


def default_spool_dir() -> Path:
    return state_dir() / "dead-letters"


def dead_letter_message(route: str, route_file: str, inbound: Inbound, failure: Failure, attempts: int,
                        limit: int) -> Letter:
    """The original body (typed messages rendered as JSON), at most ``limit`` bytes, and the
    headers saying why (``route_file`` is ``file:line`` of the route)."""
    body = inbound.body
    if body is None and inbound.fields is None:
        body = b""
    elif body is None:
        try:
            body = json.dumps(inbound.fields, default=str, ensure_ascii=False).encode("utf-8")
        except (ValueError, RecursionError) as exc:
            body = repr(exc).encode()
    headers: dict[str, Any] = {
        "x-rabbitros-route": route,
        "x-rabbitros-stage": failure.stage,
        "x-rabbitros-error": failure.error[:ERROR_HEADER_LIMIT],
        ATTEMPTS_HEADER: attempts,
        "x-rabbitros-route-file": route_file,
    }
    if len(body) > limit:
        headers["x-rabbitros-truncated"] = len(body)
        body = body[:limit]
    for key, value in inbound.meta.items():
        if key not in ("headers", "route", "generation") and isinstance(value, (str, int, float)) and not isinstance(value, bool):
            headers[f"x-source-{key}"] = value
    return body, headers


class DeadLetterSpool:
    """Dead letters as JSON lines in rotated files: ``dead-letters.jsonl`` then ``.1`` .. ``.N``.
    One line: ``{"ts", "route", "headers", "body"}`` (``body_base64`` for bytes that are not
    UTF-8)."""

    def __init__(self, directory: Path, max_bytes: int = DEFAULT_SPOOL_MAX_BYTES) -> None:
        self.directory = Path(directory)
        self.file_limit = max(4096, max_bytes // SPOOL_FILES)
        self.path = self.directory / "dead-letters.jsonl"

    def write(self, route: str, messages: Sequence[Letter]) -> None:
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            with self._locked():
                self._write(route, messages)
        except OSError as exc:
            raise EndpointError(f"dead-letter spool {self.directory}: {exc.strerror or exc}") from exc

    @contextlib.contextmanager
    def _locked(self) -> Iterator[None]:
        """The spool's lock (``flock`` on ``.lock`` in its directory): an engine appending and
        ``dead-letters replay`` removing what it sent never interleave."""
        with open(self.directory / ".lock", "a") as lock:
            fcntl.flock(lock.fileno(), fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(lock.fileno(), fcntl.LOCK_UN)

    def _write(self, route: str, messages: Sequence[Letter]) -> None:
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

    def _files(self) -> list[Path]:
        """The spool's files, oldest first."""
        return [self.path if index == 0 else self.path.with_name(f"{self.path.name}.{index}")
                for index in range(SPOOL_FILES - 1, -1, -1)]

    def read(self) -> list[dict[str, Any]]:
        """Every spooled record, oldest first (for operators and tests)."""
        return [json.loads(line) for line in self._lines()]

    def _lines(self) -> list[bytes]:
        lines: list[bytes] = []
        for path in self._files():
            try:
                lines += [line for line in path.read_bytes().splitlines() if line.strip()]
            except FileNotFoundError:
                continue
        return lines

    def letters(self) -> list[StoredLetter]:
        """Every spooled record as a :class:`StoredLetter` (its handle: the line, which
        :meth:`remove` looks for), oldest first; a line that is not a record is left alone."""
        letters = []
        where = f"spool {self.directory}"
        for line in self._lines():
            try:
                record = json.loads(line)
                body = base64.b64decode(record["body_base64"]) if "body_base64" in record else record["body"].encode("utf-8")
                headers = dict(record.get("headers") or {})
                headers.setdefault("x-rabbitros-route", record.get("route"))
            except (ValueError, KeyError, TypeError, AttributeError):
                continue
            letters.append(StoredLetter(body, headers, record.get("ts"), line, where))
        return letters

    def remove(self, lines: Sequence[bytes]) -> None:
        """Rewrite the spool without ``lines`` (each once), under the spool's lock."""
        unwanted = Counter(lines)
        try:
            with self._locked():
                for path in self._files():
                    try:
                        kept = path.read_bytes().splitlines(keepends=True)
                    except FileNotFoundError:
                        continue
                    left = []
                    for line in kept:
                        if unwanted[line.rstrip(b"\n")] > 0:
                            unwanted[line.rstrip(b"\n")] -= 1
                        else:
                            left.append(line)
                    if len(left) != len(kept):
                        temporary = path.with_name(f".{path.name}.new")
                        temporary.write_bytes(b"".join(left))
                        os.replace(temporary, path)
        except OSError as exc:
            raise EndpointError(f"dead-letter spool {self.directory}: {exc.strerror or exc}") from exc


class SpoolReader(DeadLetterReader):
    """The spool as a :class:`~engine.endpoints.base.DeadLetterReader`: a letter is removed by
    rewriting its file without its line, under the lock the engine's writes take too."""

    def __init__(self, spool: DeadLetterSpool) -> None:
        self.spool = spool

    async def read(self, limit: int) -> list[StoredLetter]:
        return (await asyncio.to_thread(self.spool.letters))[:limit]

    async def remove(self, letters: Sequence[StoredLetter]) -> None:
        await asyncio.to_thread(self.spool.remove, [letter.handle for letter in letters])

    async def close(self) -> None:
        return None


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
        self._report = ReportLimiter(5.0)

    @property
    def where(self) -> str:
        if self.connection is not None:
            return self.connection.dead_letter_destination()
        return f"spool {self.spool.directory}"

    def status(self) -> dict[str, Any]:
        return {"destination": self.where, "stored": self.stored, "spooled": self.spooled}

    async def prepare(self) -> None:
        if self.connection is not None:
            await self.connection.prepare_dead_letters(self.spec.max_length)

    async def put(self, route: str, messages: Sequence[Letter]) -> None:
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
