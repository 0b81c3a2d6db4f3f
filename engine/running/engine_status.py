"""The engine's status document: what the status file, ``/routes/status`` and the console show.

Built on demand (once a second by the status writer, and per admin request), never on the
message path; apart from engine/running/runtime.py so the reload phases read as one sequence.
"""

from __future__ import annotations

import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Protocol

from engine.endpoints.base import Connection
from engine.language.specs import RoutesConfig
from engine.language.stores import Stores
from engine.running.connections import ConnectionPool
from engine.running.dead_letters import DeadLetters
from engine.running.dedupe import DedupeKeys
from engine.running.record import Recorder
from engine.running.reload_stats import ReloadStats
from engine.running.runner import RouteRunner


class Reporting(Protocol):
    """What the status reads: the engine (engine/running/runtime.py) as this module sees it."""

    routes_dir: Path
    config: RoutesConfig | None
    generation: int
    reloads: ReloadStats
    dead_letters: DeadLetters | None
    instance: str
    connections: ConnectionPool
    elsewhere: list[str]
    stores: Stores
    dedupe: DedupeKeys
    recorder: Recorder | None
    runners: dict[str, RouteRunner]

    def is_open(self, connection: Connection) -> bool: ...

    def open_connections(self) -> list[tuple[str, Connection]]: ...


def engine_status(engine: Reporting) -> dict[str, Any]:
    config = engine.config
    return {
        "pid": os.getpid(),
        "routes_dir": str(engine.routes_dir),
        "generation": engine.generation,
        "config_hash": config.content_hash if config else None,
        "reloads": asdict(engine.reloads),
        "dead_letters": None if engine.dead_letters is None else engine.dead_letters.status(),
        "instance": engine.instance,
        "brokers": _brokers(engine),
        "elsewhere": engine.elsewhere,
        "stores": engine.stores.status(),
        "dedupe": engine.dedupe.status(),
        **({} if engine.recorder is None else {"recording": engine.recorder.status()}),
        "routes": {name: runner.status() for name, runner in sorted(engine.runners.items())},
        "connections": _connections(engine),
    }


def _brokers(engine: Reporting) -> dict[str, Any]:
    """``connection name -> endpoint`` of the connections that name a broker endpoint (a
    protocol's connection says so by having an ``endpoint``; the core names no protocol)."""
    endpoints = ((key[0], getattr(connection, "endpoint", None)) for key, connection in engine.connections.items())
    return {name: endpoint for name, endpoint in endpoints if endpoint}


def _connections(engine: Reporting) -> dict[str, Any]:
    return {
        connection.name: {
            "protocol": protocol,
            "healthy": connection.healthy and engine.is_open(connection),
            **connection.health(),
            **({} if engine.is_open(connection) else {"state": "retrying"}),
        }
        for protocol, connection in engine.open_connections()
    }
