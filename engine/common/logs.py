"""Structured logging to stderr that never blocks the event loop.

Records go through a QueueHandler; a listener thread formats and writes them, so a slow
terminal or pipe cannot stall message routing. Fields passed as ``extra=`` are printed
as ``key=value`` (logfmt) or as JSON members.
"""

from __future__ import annotations

import json
import logging
import logging.handlers
import queue
import sys
import time
from typing import Any

from engine.common.redaction import redact_urls

_STANDARD = set(vars(logging.makeLogRecord({}))) | {"message", "asctime"}


def _fields(record: logging.LogRecord) -> dict[str, Any]:
    return {key: value for key, value in vars(record).items() if key not in _STANDARD}


def _timestamp(record: logging.LogRecord) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z"


class LogfmtFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        parts = {
            "ts": _timestamp(record),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
            **_fields(record),
        }
        line = " ".join(f"{key}={_logfmt_value(value)}" for key, value in parts.items())
        if record.exc_info:
            line += "\n" + self.formatException(record.exc_info)
        return redact_urls(line)  # a library's message or traceback may name a URL with its password


def _logfmt_value(value: Any) -> str:
    text = value if isinstance(value, str) else json.dumps(value, default=str)
    if text and not any(c in text for c in ' ="\n'):
        return text
    return json.dumps(text)


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        document = {
            "ts": _timestamp(record),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
            **_fields(record),
        }
        if record.exc_info:
            document["exception"] = self.formatException(record.exc_info)
        return redact_urls(json.dumps(document, default=str))


def setup_logging(level: str = "info", fmt: str = "text") -> logging.handlers.QueueListener:
    """Route the root logger through a queue; the caller stops the returned listener."""
    stream = logging.StreamHandler(sys.stderr)
    stream.setFormatter(JsonFormatter() if fmt == "json" else LogfmtFormatter())
    records: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    root = logging.getLogger()
    root.handlers[:] = [logging.handlers.QueueHandler(records)]
    root.setLevel(level.upper())
    for noisy in ("aio_pika", "aiormq", "watchfiles"):
        logging.getLogger(noisy).setLevel(max(logging.WARNING, root.level))
    listener = logging.handlers.QueueListener(records, stream)
    listener.start()
    return listener


class ReportLimiter:
    """Allows one report per ``interval`` seconds and counts what it held back, so a flood
    of bad messages is reported without logging each one. (A route's ``throttle:`` is
    engine/running/throttle.py; this one limits log lines.)"""

    def __init__(self, interval: float = 1.0) -> None:
        self.interval = interval
        self.suppressed = 0
        self._next = 0.0

    def ready(self) -> bool:
        now = time.monotonic()
        if now >= self._next:
            self._next = now + self.interval
            return True
        self.suppressed += 1
        return False

    def take_suppressed(self) -> int:
        count, self.suppressed = self.suppressed, 0
        return count
