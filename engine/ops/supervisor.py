"""``run --workers N``: one supervisor, N engine worker processes on one routes directory.

One engine process cannot use more than one core (the client libraries and the mappings run
under one GIL; rclpy does not run free-threaded), so the supervisor starts N ordinary engine
processes, each with its index (engine/running/worker.py), which run the routes placed on them
by one pure function (engine/running/placement.py): AMQP queues are consumed by every worker,
a device or a link by one. The supervisor itself runs no route; it owns:

* **the routes' check**: it compiles the directory once at start and at every change (the
  watch is its own; workers run with ``--no-watch``), so a directory that does not compile
  reaches no worker;
* **the workers' lives**: each runs in its own process group (a terminal's Ctrl-C reaches the
  supervisor, which stops them in order) and dies with the supervisor (``PR_SET_PDEATHSIG``);
  one that exits while the engine runs (a crash, ``kill -9``) is started again after a
  backoff, and its ``restarts`` count in the status. Nothing is lost by the death: what the
  worker had taken from a broker and not acknowledged is handed back by the broker when its
  connection drops, to the other workers or to the restarted one (at-least-once, as across a
  restart of a single engine); what a push source (ROS 2, MAVLink) had queued in the dead
  worker is lost as it is when a single engine is killed;
* **the one admin endpoint** (engine/ops/supervisor_admin.py: status, metrics, health, taps
  and the web console of the whole engine) and **the Foxglove view** of ``--foxglove``
  (engine/ops/supervisor_foxglove.py), both read from the workers: the workers serve their own
  admin on private loopback ports the supervisor alone reads (chosen over a pipe protocol:
  the worker's admin already answers status, metrics, health and taps, so the supervisor
  merges documents instead of a second encoding of them). A worker tells its port over a pipe
  (``--worker-channel FD``) once its routes run;
* **reloads** (:meth:`Supervisor.reload`), one generation for all workers or none, see there;
* **a clean stop**: SIGTERM (or SIGINT) to the supervisor sends SIGTERM to every worker,
  each drains as a single engine does (``--drain-timeout``), and the supervisor waits for all;
* **a private runtime directory** (``--runtime-dir``, made at start, removed at the stop) where
  the workers bind the local sockets of a connection split over them (placement rule 1b: a
  MAVLink link's vehicles, engine/endpoints/mavlink/split.py); a workers' own, not the user's.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import shutil
import signal
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any, AsyncIterator, Callable

import aiohttp

from engine.common.backoff import Backoff
from engine.common.processes import process_usage
from engine.language.routes import RoutesInvalid
from engine.language.specs import RoutesConfig
from engine.running.placement import WorkerPlacement, place_routes
from engine.running.reload_stats import ReloadStats
from engine.running.worker import ROLL_BACK_SIGNAL

log = logging.getLogger("engine.ops.supervisor")

READY_TIMEOUT_S = 120.0
"""How long a worker may take from its start to running its routes (loading 1,000 routes and
connecting took some 10 s here; a worker that needs more is reported, and started again)."""
RELOAD_TIMEOUT_S = 60.0
"""How long the supervisor waits for every worker to report a reload's outcome."""
STOP_GRACE_S = 5.0
"""Beyond the drain timeout, how long a stop waits for a worker before SIGKILL."""
STEADY_S = 30.0
"""A worker up this long has recovered: the next death restarts it without waiting."""
POLL_S = 0.05
"""Between two questions to a worker while a reload settles."""
FOLLOW_AGAIN_S = 0.5
"""After a worker's tap ended (it stopped, or was started again), before it is opened again."""


SUPERVISOR_OWN_OPTIONS = frozenset((
    "--workers", "--no-watch", "--status-file", "--admin", "--admin-tls-cert", "--admin-tls-key",  # one watch, one admin
    "--local-broker", "--broker-url-file", "--cluster", "--local-broker-tls",  # started once; the workers read its environment
    "--foxglove", "--foxglove-tls-cert", "--foxglove-tls-key",  # one view of the whole engine (engine/ops/supervisor_foxglove.py)
))
"""The ``run`` options the supervisor keeps for itself; every other one reaches each worker
through :meth:`Supervisor.command` (a fast test holds the two lists to the parser, so a new
run option cannot be silently dropped for workers)."""


def worker_count(text: str) -> int:
    """``--workers N`` or ``auto``: one per core this process may run on (its CPU affinity: a
    container's cpuset, ``taskset``), else ``os.cpu_count()`` where the system does not say."""
    if text == "auto":
        return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    if not text.isdigit() or int(text) < 1:
        raise argparse.ArgumentTypeError(f"--workers {text!r}: a number of processes (1 or more) or auto")
    return int(text)


@dataclass
class Worker:
    """What the supervisor knows of one worker."""

    index: int
    process: asyncio.subprocess.Process | None = None
    admin_port: int | None = None
    up: bool = False
    restarts: int = 0
    started_at: float = 0.0
    last_exit: int | None = None
    ready: asyncio.Event = field(default_factory=asyncio.Event)
    backoff: Backoff = field(default_factory=lambda: Backoff(first=0.2, cap=10.0))
    channel: asyncio.Task[None] | None = None
    """Reading the worker's pipe until it says it runs."""

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None

    def status(self, placement: WorkerPlacement | None) -> dict[str, Any]:
        return {"index": self.index, "pid": self.pid, "up": self.up, "restarts": self.restarts,
                "admin_port": self.admin_port, "last_exit": self.last_exit,
                "uptime_s": round(time.monotonic() - self.started_at, 1) if self.up else 0.0,
                **(usage_fields(self.pid) if self.up and self.pid is not None else {}),
                "routes": sorted(placement.on(self.index)) if placement is not None else []}


def usage_fields(pid: int) -> dict[str, float]:
    """The CPU seconds a worker used since it started and its resident memory (MiB): how the
    load spreads over the workers; empty where /proc does not say."""
    usage = process_usage(pid)
    return {} if usage is None else {"cpu_s": round(usage.cpu_s, 2), "rss_mib": round(usage.rss_bytes / 2**20, 1)}


@dataclass
class SupervisorReloads(ReloadStats):
    """The engine's reload counts (one rule: ReloadStats.reject), and the workers left apart."""

    split: dict[int, str] = field(default_factory=dict)
    """Workers that did not take the last generation: index -> the config hash they run."""


class Supervisor:
    """N worker processes of one engine (see the module docstring)."""

    def __init__(self, args: argparse.Namespace, workers: int, compile_routes: Callable[[], RoutesConfig],
                 token: bytes | None = None) -> None:
        self.args = args
        self.compile_routes = compile_routes
        """Load (and vet) the routes as a worker will: blocking, run in a thread."""
        self.token = token
        self.workers = [Worker(index) for index in range(workers)]
        self.config: RoutesConfig | None = None
        self.placement: WorkerPlacement | None = None
        self.generation = 0
        self.reloads = SupervisorReloads()
        self.started_at = time.time()
        self.stopping = False
        self._lock = asyncio.Lock()
        self._tasks: list[asyncio.Task[None]] = []
        self._session: aiohttp.ClientSession | None = None
        self.runtime_dir: str | None = None
        """The workers' private directory of this run (see the module docstring)."""

    # -- starting

    async def start(self) -> None:
        """Check the routes, start every worker and wait until each runs its routes; raises
        RoutesInvalid, or RuntimeError naming a worker that could not start (the others are
        stopped again)."""
        self.config = await asyncio.to_thread(self.compile_routes)
        self.placement = place_routes(self.config, len(self.workers))
        self.generation = 1
        self.runtime_dir = tempfile.mkdtemp(prefix="rabbitros-")
        self._session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=10))
        for worker in self.workers:
            await self._spawn(worker)
        started = await asyncio.gather(*(self._wait_ready(worker) for worker in self.workers))
        if not all(started):
            failed = [w.index for w, ok in zip(self.workers, started) if not ok]
            await self.stop(0.0)
            raise RuntimeError(f"worker {', '.join(map(str, failed))} did not start (its log above says why)")
        self._tasks = [asyncio.create_task(self._keep(worker), name=f"worker-{worker.index}") for worker in self.workers]
        log.info("workers running", extra={"workers": len(self.workers), "pids": [w.pid for w in self.workers],
                                           "generation": self.generation})

    def command(self, worker: Worker, channel: int) -> list[str]:
        """The worker's command line: the supervisor's run options a worker uses, its index,
        a private admin port, no watch (the supervisor reloads it)."""
        args = self.args
        command = [sys.executable, "-m", "engine", "run", "--routes", str(args.routes), "--no-watch",
                   "--workers", str(len(self.workers)), "--worker", str(worker.index), "--worker-channel", str(channel),
                   "--supervisor-pid", str(os.getpid()),
                   "--admin", "127.0.0.1:0", "--log-level", args.log_level, "--log-format", args.log_format,
                   "--stats-interval", str(args.stats_interval), "--drain-timeout", str(args.drain_timeout)]
        for directory in args.schemas or ():
            command += ["--schemas", str(directory)]
        if args.instance:
            command += ["--instance", args.instance]
        if self.runtime_dir is not None:
            command += ["--runtime-dir", self.runtime_dir]
        if args.admin_token_file:
            command += ["--admin-token-file", str(args.admin_token_file)]
        command += [flag for flag, on in (("--require-connections", args.require_connections),
                                          ("--test-on-reload", args.test_on_reload)) if on]
        if args.record is not None:  # one directory a worker: two writers never share a file
            command += ["--record", str(args.record / f"worker-{worker.index}"), "--record-file-mb", str(args.record_file_mb),
                        "--record-file-minutes", str(args.record_file_minutes), "--record-total-mb", str(args.record_total_mb)]
        return command

    async def _spawn(self, worker: Worker) -> None:
        read, write = os.pipe()
        try:
            worker.process = await asyncio.create_subprocess_exec(
                *self.command(worker, write), pass_fds=(write,), start_new_session=True)
        except BaseException:
            os.close(read)
            raise
        finally:
            os.close(write)
        worker.ready.clear()
        worker.admin_port, worker.up, worker.started_at = None, False, time.monotonic()
        # held by the worker: a task nobody references may be collected mid-read, closing the pipe under the worker
        worker.channel = asyncio.create_task(self._read_channel(worker, read), name=f"worker-{worker.index}-channel")

    async def _read_channel(self, worker: Worker, fd: int) -> None:
        """The worker's one line once its routes run: ``{"admin_port": P}``; EOF before it
        means it exited first."""
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader()
        transport, _ = await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), os.fdopen(fd, "rb"))
        try:
            line = await reader.readline()
        finally:
            transport.close()
        if line:
            worker.admin_port = int(json.loads(line)["admin_port"])
            worker.up = True
            worker.ready.set()

    async def _wait_ready(self, worker: Worker) -> bool:
        assert worker.process is not None
        exited = asyncio.ensure_future(worker.process.wait())
        ready = asyncio.ensure_future(worker.ready.wait())
        await asyncio.wait({exited, ready}, timeout=READY_TIMEOUT_S, return_when=asyncio.FIRST_COMPLETED)
        exited.cancel()
        ready.cancel()
        if worker.ready.is_set():
            return True
        if worker.process.returncode is None:
            log.error("worker did not start in time", extra={"worker": worker.index, "timeout_s": READY_TIMEOUT_S})
            with contextlib.suppress(ProcessLookupError):
                os.killpg(worker.process.pid, signal.SIGKILL)
            await worker.process.wait()
        worker.last_exit = worker.process.returncode
        return False

    async def _keep(self, worker: Worker) -> None:
        """Start the worker again whenever it exits while the engine runs."""
        while True:
            assert worker.process is not None
            code = await worker.process.wait()
            worker.up, worker.last_exit = False, code
            if self.stopping or not await self._start_again(worker, f"exit {code}"):
                return
            if await self._wait_ready(worker):
                log.info("worker running again", extra={"worker": worker.index, "pid": worker.pid, "restarts": worker.restarts})

    async def _start_again(self, worker: Worker, why: str) -> bool:
        """Start a worker that exited, after the backoff (none when it had run :data:`STEADY_S`);
        a start that fails itself (no process slot or file descriptor left: ``OSError``) is
        tried again after the next backoff, so a worker is never left down for good. False
        when the engine stops meanwhile."""
        while True:
            steady = time.monotonic() - worker.started_at > STEADY_S
            if steady:
                worker.backoff.reset()
            delay = 0.0 if steady else worker.backoff.next()
            log.error("worker is down; starting it again", extra={"worker": worker.index, "pid": worker.pid, "why": why,
                                                                   "restart_in_s": round(delay, 2)})
            await asyncio.sleep(delay)
            if self.stopping:
                return False
            worker.restarts += 1
            try:
                await self._spawn(worker)
                return True
            except OSError as error:
                worker.started_at, why = time.monotonic(), f"cannot start: {error}"

    # -- asking workers

    async def ask(self, worker: Worker, path: str) -> tuple[int, bytes]:
        """GET ``path`` of the worker's admin: (HTTP status, body); (0, b"") when it is not up."""
        if not worker.up or worker.admin_port is None or self._session is None:
            return 0, b""
        headers = {"Authorization": f"Bearer {self.token.decode()}"} if self.token else {}
        try:
            async with self._session.get(f"http://127.0.0.1:{worker.admin_port}{path}", headers=headers) as response:
                return response.status, await response.read()
        except (aiohttp.ClientError, asyncio.TimeoutError, OSError):
            return 0, b""

    async def documents(self, path: str) -> list[tuple[Worker, int, bytes]]:
        """``path`` of every worker, asked at once."""
        answers = await asyncio.gather(*(self.ask(worker, path) for worker in self.workers))
        return [(worker, code, body) for worker, (code, body) in zip(self.workers, answers)]

    async def tap_lines(self, worker: Worker, route: str) -> AsyncIterator[bytes]:
        """The worker's ``/tap/{route}`` lines as they come, until its stream ends (the worker
        stopped or was restarted) or it does not answer: the supervisor's ``/tap`` passes them on
        as the worker wrote them, its Foxglove view takes the canonical messages from them."""
        if not worker.up or worker.admin_port is None:
            return
        headers = {"Authorization": f"Bearer {self.token.decode()}"} if self.token else {}
        endless = aiohttp.ClientTimeout(total=None, sock_read=None)  # a quiet route sends nothing for long
        with contextlib.suppress(aiohttp.ClientError, OSError):
            # a session of its own: a tap holds its connection for as long as it is read, and the
            # shared session's pool (asked for status, metrics, health) must never run out for it
            async with aiohttp.ClientSession(timeout=endless) as session, \
                    session.get(f"http://127.0.0.1:{worker.admin_port}/tap/{route}", headers=headers) as answer:
                if answer.status != 200:
                    return
                pending = b""
                async for chunk in answer.content.iter_any():  # not by line: aiohttp refuses a line over 64 KiB (an image)
                    *lines, pending = (pending + chunk).split(b"\n")
                    for line in lines:
                        yield line + b"\n"

    async def follow_tap(self, worker: Worker, route: str) -> AsyncIterator[bytes]:
        """:meth:`tap_lines`, opened again whenever it ended (the worker was killed and started
        again, or did not run the route yet), until the reader stops: the supervisor's ``/tap``
        (its console's live tap) and its Foxglove view both follow a restarted worker so."""
        while True:
            async for line in self.tap_lines(worker, route):
                yield line
            await asyncio.sleep(FOLLOW_AGAIN_S)

    async def worker_status(self, worker: Worker) -> dict[str, Any] | None:
        code, body = await self.ask(worker, "/status")
        return json.loads(body) if code == 200 else None

    # -- reloading

    async def reload(self) -> bool:
        """Apply the routes as they are now to every worker, as one generation: all or none.

        The supervisor compiles, vets and places the directory once: a directory that does not
        compile (or whose route tests fail under ``--test-on-reload``) reaches no worker. One
        that compiles goes to every worker (SIGHUP), each applying it all or nothing for itself
        (engine/running/runtime.py). A worker can still refuse it for a reason of its own
        process (a connection that cannot open under ``--require-connections``, a device not yet
        released): then the workers that did switch are told to go back (:data:`ROLL_BACK_SIGNAL`:
        each applies again the generation it ran before, kept in memory, engine/running/worker.py)
        and the reload counts as rejected, naming the worker and its reason; every worker runs
        the previous generation again. What is not guaranteed: an atomic switch. Between a
        worker's switch and its rollback it converts messages with the new generation, and a
        rollback that fails itself (rare: the old generation ran a moment ago) leaves that
        worker on the new one, named in ``reloads.split``. A worker down during the reload
        starts again on the files as they are (the new generation), and one that read the files
        after a further edit reports another hash: the watch saw that edit too, and the next
        reload brings every worker to it."""
        async with self._lock:
            try:
                config = await asyncio.to_thread(self.compile_routes)
            except RoutesInvalid as invalid:
                return self._rejected([str(problem) for problem in invalid.problems])
            except Exception as error:  # the supervisor must outlive whatever the loader did not foresee
                return self._rejected([f"{self.args.routes}: cannot load: {type(error).__name__}: {error}"])
            old = self.config.content_hash if self.config is not None else None
            if config.content_hash == old:
                return True
            before = {worker.index: await self.worker_status(worker) for worker in self.workers}
            for worker in self.workers:
                if worker.up and worker.process is not None:
                    with contextlib.suppress(ProcessLookupError):
                        worker.process.send_signal(signal.SIGHUP)
            outcomes = await asyncio.gather(*(self._applied(worker, before[worker.index], config.content_hash)
                                              for worker in self.workers))
            refused = {index: errors for index, (found, errors) in enumerate(outcomes) if found == old}
            if refused:
                switched = [self.workers[index] for index, (found, _) in enumerate(outcomes) if found == config.content_hash]
                back = await self._roll_back(switched, str(old))
                self.reloads.split = {index: found for index, found in back.items() if found != old}
                if self.reloads.split:
                    log.error("a worker could not go back to the previous generation", extra={"workers": self.reloads.split})
                return self._rejected([f"worker {index} refused generation {config.content_hash}: "
                                       + ("; ".join(errors) or "no reason given") for index, errors in refused.items()])
            self.config, self.placement = config, place_routes(config, len(self.workers))
            self.generation += 1
            self.reloads.split = {index: found for index, (found, _) in enumerate(outcomes) if found != config.content_hash}
            for index, found in self.reloads.split.items():
                if found == "timed out":  # still applying, or stuck: started again on the files as they are
                    await self._restart(self.workers[index])
            self.reloads.succeeded += 1
            self.reloads.last_error = []
            log.info("reload applied on every worker", extra={"generation": self.generation, "config_hash": config.content_hash,
                                                              **({"split": self.reloads.split} if self.reloads.split else {})})
            return True

    async def _applied(self, worker: Worker, before: dict[str, Any] | None, wanted: str) -> tuple[str, list[str]]:
        """The config hash ``worker`` runs once its reload settled (``wanted``, or what it kept
        when its reload was rejected, then with the worker's reasons), ``"down"`` or ``"timed out"``."""
        rejected = before["reloads"]["rejected"] if before else 0
        deadline = time.monotonic() + RELOAD_TIMEOUT_S
        while time.monotonic() < deadline:
            status = await self.worker_status(worker)
            if status is None:
                if not worker.up:
                    return "down", []  # it starts again on the files as they are (Supervisor._keep)
            elif status["config_hash"] == wanted:
                return wanted, []
            elif status["reloads"]["rejected"] > rejected:
                return str(status["config_hash"]), list(status["reloads"]["last_error"])
            await asyncio.sleep(POLL_S)
        return "timed out", []

    async def _roll_back(self, workers: list[Worker], old: str) -> dict[int, str]:
        """Tell ``workers`` to go back to generation ``old``; the hash each runs then."""
        for worker in workers:
            if worker.process is not None and worker.process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    worker.process.send_signal(ROLL_BACK_SIGNAL)
        hashes = {}
        for worker in workers:
            deadline, found = time.monotonic() + RELOAD_TIMEOUT_S, "timed out"
            while time.monotonic() < deadline:
                status = await self.worker_status(worker)
                found = "down" if status is None and not worker.up else str(status["config_hash"]) if status else found
                if found in (old, "down"):
                    break
                await asyncio.sleep(POLL_S)
            hashes[worker.index] = found
        log.warning("rolled back: a worker refused the generation", extra={"workers": [w.index for w in workers], "config_hash": old})
        return hashes

    async def _restart(self, worker: Worker) -> None:
        if worker.process is not None and worker.process.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(worker.process.pid, signal.SIGTERM)  # drains; _keep starts it again

    def _rejected(self, problems: list[str]) -> bool:
        if self.reloads.reject(problems):
            log.error("reload rejected; every worker keeps its routes", extra={"generation": self.generation, "problems": problems})
        return False

    # -- stopping

    async def stop(self, drain_timeout: float) -> None:
        """SIGTERM to every worker, each drains; SIGKILL to one still running after the drain
        timeout and :data:`STOP_GRACE_S`."""
        self.stopping = True
        running = [w.process for w in self.workers if w.process is not None and w.process.returncode is None]
        for process in running:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.pid, signal.SIGTERM)
        waits = [asyncio.ensure_future(process.wait()) for process in running]
        if waits:
            _, late = await asyncio.wait(waits, timeout=drain_timeout + STOP_GRACE_S)
            for process in running:
                if process.returncode is None:
                    log.error("worker did not drain in time; killed", extra={"pid": process.pid})
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(process.pid, signal.SIGKILL)
            await asyncio.gather(*waits, return_exceptions=True)
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for worker in self.workers:
            worker.up = False
        if self._session is not None:
            await self._session.close()
        if self.runtime_dir is not None:
            shutil.rmtree(self.runtime_dir, ignore_errors=True)

    def status(self) -> dict[str, Any]:
        """The supervisor's own part of the status (the admin merges the workers' into it)."""
        return {
            "pid": os.getpid(),
            "routes_dir": str(self.args.routes),
            "generation": self.generation,
            "config_hash": self.config.content_hash if self.config else None,
            "reloads": {"succeeded": self.reloads.succeeded, "rejected": self.reloads.rejected,
                        "last_error": self.reloads.last_error, "split": self.reloads.split},
            "workers": [worker.status(self.placement) for worker in self.workers],
            "placement": {name: list(place.workers) for name, place in sorted(self.placement.routes.items())}
            if self.placement else {},
            "split_connections": dict(sorted(self.placement.owners.items())) if self.placement else {},
            # a connection split over the workers -> the worker holding it (placement rule 1b)
        }


