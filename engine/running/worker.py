"""One worker of ``run --workers N``: the normal engine, running the routes placed on it.

A worker is an ordinary engine process (engine/running/runtime.py) started by the supervisor
(engine/ops/supervisor.py) with its index. Every worker loads the whole routes directory, as
the supervisor checked it, and runs only what :func:`~engine.running.placement.place_routes`
gives its index; the other routes are listed as ``elsewhere`` in its status, as the routes
pinned to other instances are. Placement is recomputed from each generation it loads, so a
reload that moves a route (a new route joins a device group) stops it here and starts it on
its new worker; both are the same pure function of the same files. A connection split over the
workers (placement rule 1b) is opened with this worker's place on it
(``Transport.split_connection``): which worker holds it, and the supervisor's runtime directory
where the workers' local sockets meet.
"""

from __future__ import annotations

import asyncio
import gc
import json
import logging
import os
import signal
import sys
import tempfile
from dataclasses import replace
from typing import Any

from engine import endpoints
from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import ConnectionShare
from engine.language.specs import ConnectionSpec, RouteSpec, RoutesConfig
from engine.running.placement import place_routes
from engine.running.runtime import Engine, _Reload

log = logging.getLogger("engine.running.worker")


ROLL_BACK_SIGNAL = signal.SIGUSR1
"""The supervisor's "go back to the generation you ran before" (engine/ops/supervisor.py)."""


class WorkerEngine(Engine):
    """An :class:`Engine` that runs the routes of worker ``index`` of ``workers``, and goes back
    to its previous generation when the supervisor asks (:data:`ROLL_BACK_SIGNAL`)."""

    def __init__(self, *args: Any, index: int, workers: int, runtime_dir: str | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.index, self.workers = index, workers
        self.runtime_dir = runtime_dir or tempfile.gettempdir()
        """The supervisor's private directory (``--runtime-dir``) for what the workers share locally."""
        self._applied: tuple[RoutesConfig, SchemaRegistry] | None = None
        self._previous: tuple[RoutesConfig, SchemaRegistry] | None = None
        """The compiled generation this worker ran before the last one it applied, kept in memory:
        the files on disk are already the new generation's when a rollback is asked for."""
        self._rolling_back: asyncio.Task[bool] | None = None

    async def start(self) -> None:
        await super().start()
        asyncio.get_running_loop().add_signal_handler(ROLL_BACK_SIGNAL, self._roll_back_asked)

    async def _apply(self, everywhere: RoutesConfig, schemas: SchemaRegistry) -> None:
        await super()._apply(everywhere, schemas)  # raises (and changes nothing) when it fails
        self._previous, self._applied = self._applied, (everywhere, schemas)

    def _roll_back_asked(self) -> None:
        if self._rolling_back is None or self._rolling_back.done():
            self._rolling_back = asyncio.create_task(self.roll_back(), name="roll-back")

    async def roll_back(self) -> bool:
        """Apply again the generation this worker ran before its last reload (another worker
        refused the new one: engine/ops/supervisor.py ``Supervisor.reload``). Messages it
        converted meanwhile were converted by the new generation; a rollback that fails leaves
        the new generation running, and says so in the log and the status's reloads."""
        gc.unfreeze()
        async with self._lock:
            previous = self._previous
            if previous is None:
                return False
            try:
                await self._apply(*previous)
            except Exception as error:  # the worker must outlive it; the supervisor sees the hash it kept
                log.exception("rollback failed")
                self._rejected([f"rollback to {previous[0].content_hash}: {type(error).__name__}: {error}"])
                return False
            log.warning("rolled back: another worker refused the generation", extra={"generation": self.generation,
                                                                                       "config_hash": previous[0].content_hash})
            return True

    def _plan(self, everywhere: RoutesConfig, schemas: SchemaRegistry) -> _Reload:
        placement = place_routes(everywhere, self.workers)
        placed = placement.on(self.index)
        connections = {name: self._split(spec, placement.owners[name]) if name in placement.owners else spec
                       for name, spec in everywhere.connections.items()}
        mine = replace(everywhere, connections=connections,
                       routes={name: self._share(spec) if placement.routes[name].split else spec
                               for name, spec in everywhere.routes.items() if name in placed})
        change = super()._plan(mine, schemas)
        change.everywhere = everywhere  # the others are listed as elsewhere (Engine._retire)
        return change

    def _share(self, spec: RouteSpec) -> RouteSpec:
        """A route every worker runs, each following its share of the streams the source discovers."""
        source = spec.source
        options = endpoints.transport(source.protocol).split_source(source.options, self.index, self.workers)
        return replace(spec, source=replace(source, options=options))

    def _split(self, spec: ConnectionSpec, owner: int) -> ConnectionSpec:
        """A connection split over the workers, as this worker opens it (its owner holds it)."""
        share = ConnectionShare(self.index, self.workers, owner, self.runtime_dir)
        options = endpoints.transport(spec.protocol).split_connection(spec.options, share)
        return replace(spec, options=options, fingerprint=f"{spec.fingerprint}:held-by-{owner}")  # a new owner: opened again

    def status(self) -> dict[str, Any]:
        return {**super().status(), "worker": {"index": self.index, "workers": self.workers}}


def die_with_parent(supervisor: int | None) -> None:
    """In a worker: SIGTERM when the supervisor dies, even by SIGKILL, so no worker outlives it
    consuming queues (Linux ``prctl(PR_SET_PDEATHSIG)``; elsewhere nothing). Set by the worker
    itself rather than in a ``preexec_fn`` (unsafe in a process with threads), so the worker
    compares its parent with the pid the supervisor gave it (``--supervisor-pid``): a
    supervisor that died while the worker was still importing (a second or so) is found here
    and the worker stops at once. (Comparing with the parent read just before missed that
    death: by then the parent was already init, and the worker ran on unsupervised.)"""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    expected = supervisor if supervisor is not None else os.getppid()
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    if os.getppid() != expected:
        os.kill(os.getpid(), signal.SIGTERM)


def tell_supervisor(channel: int, message: dict[str, Any]) -> None:
    """Write one JSON line to the supervisor's pipe and close it: the worker runs its routes,
    its admin answers on ``message["admin_port"]`` (engine/ops/supervisor.py reads it)."""
    with os.fdopen(channel, "w") as pipe:
        pipe.write(json.dumps(message) + "\n")


def log_as_worker(index: int) -> None:
    """Every log line of this process names its worker (``worker=K``): the workers write to the
    supervisor's stderr, where two workers' ``route counters`` lines were otherwise alike."""

    def named(record: logging.LogRecord) -> bool:
        if not hasattr(record, "worker"):
            record.worker = index
        return True

    for handler in logging.getLogger().handlers:
        handler.addFilter(named)
