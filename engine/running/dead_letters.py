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
import json
import logging
import os
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from engine.common.logs import ReportLimiter
from engine.endpoints.base import Connection, EndpointError, Inbound
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
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rabbitros-engine" / "dead-letters"


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
