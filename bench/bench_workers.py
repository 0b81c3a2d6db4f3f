"""A backlog drain AMQP -> AMQP or AMQP -> ROS 2 through the engine with 1 and 2 workers, in one
run (issue 34).

``python -m bench.bench_workers [--kind amqp-amqp|amqp-ros2] [--count 20000] [--rounds 3]``: a
private RabbitMQ node; each round runs ``rabbitros-engine run --workers 1`` and ``--workers 2``
(their order alternating from round to round, so a drift of the machine's load weighs on both)
on the throughput section's route (bench/throughput.py: a JSON mapping to the canonical
position, schema-checked, published with confirms to AMQP, or published on a ROS 2 topic with
``transient_local`` durability, where a plain rclpy subscription counts it; each worker is
then a publisher of that topic, and the drain starts once the subscription matched every
one). Each drain:

1. the engine starts on an empty queue and is running (its status file says so, every worker
   up), then its workers are stopped (SIGSTOP) so that none starts before the other;
2. ``count`` messages are published to its queue, each confirmed by the broker;
3. the workers continue (SIGCONT) and the sink queue is counted until every message arrived.

The rate is taken at the sink from 10 % of the messages to the last (the start of the drain
is left out); the CPU seconds of each process of the engine (supervisor and workers) over the
same span; lost = published - arrived. The figure is the ratio of the medians, 2 workers over
1, measured in the same run: this machine has 2 cores, which the broker (and the publisher of
the next round, nothing else of ours) shares with the workers, so the ratio is bounded by
that, not by the engine; the CPU per process says where the time went.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any, Awaitable, Callable

from bench.systems import gnss_json
from bench.throughput import Broker, RosCounter, domain_id, process_cpu_seconds, routes_file
from engine.common.processes import process_usage

REPO = Path(__file__).resolve().parent.parent
BROKER_GROUP = [0]
"""The process group of the broker node (set by :func:`main`), whose CPU is measured beside the engine's."""
STALL_S = 15.0
"""A drain that moves no message for this long is over (its lost are counted)."""


class EngineRun:
    """``rabbitros-engine run --workers N`` as a child, in its own process group."""

    def __init__(self, routes: Path, workers: int, work: Path, stats_interval: float = 0.2, env: dict[str, str] | None = None) -> None:
        """``stats_interval``: how often the status file is written (0.2 s: a drain of a few
        seconds is seen running at once; bench/fleet.py, whose load runs 30-60 s, asks 1 s).
        ``env``: more environment for the engine (e.g. ``RABBITROS_LOOP=asyncio``)."""
        self.status_file = work / f"status-{workers}.json"
        self.log = open(work / f"engine-{workers}.log", "w")
        self.workers = workers
        self.process = subprocess.Popen(
            [sys.executable, "-m", "engine", "run", "--routes", str(routes), "--schemas", str(REPO / "schemas"),
             "--workers", str(workers), "--status-file", str(self.status_file), "--stats-interval", str(stats_interval),
             "--no-watch", "--log-level", "warning"],
            cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO), **(env or {})}, stdout=self.log, stderr=subprocess.STDOUT,
            start_new_session=True)

    async def running(self, timeout: float = 120.0) -> list[int]:
        """The pids that carry routes (the workers; the engine itself with one), once all run."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"engine --workers {self.workers} exited {self.process.returncode}")
            try:
                status = json.loads(self.status_file.read_text())
            except (OSError, ValueError):
                status = {}
            if status.get("generation", 0) >= 1:
                if self.workers == 1:
                    return [self.process.pid]
                workers = status.get("workers") or []
                if len(workers) == self.workers and all(w["up"] and w.get("status") for w in workers):
                    return [w["pid"] for w in workers]
            await asyncio.sleep(0.05)
        raise RuntimeError(f"engine --workers {self.workers} did not start within {timeout:.0f} s")

    def signal(self, pids: list[int], signum: int) -> None:
        for pid in pids:
            os.kill(pid, signum)

    async def stop(self) -> int:
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            deadline = time.monotonic() + 60
            while self.process.poll() is None and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            if self.process.poll() is None:
                os.killpg(self.process.pid, signal.SIGKILL)
        self.log.close()
        return self.process.wait()


async def drain(broker: Broker, workers: int, count: int, kind: str = "amqp-amqp", env: dict[str, str] | None = None) -> dict[str, Any]:
    tag = uuid.uuid4().hex[:8]
    names = await broker.topology(tag)
    domain = domain_id()
    counter = RosCounter(domain, f"/bench/{names['queue'].replace('-', '_')}") if kind == "amqp-ros2" else None
    try:
        with tempfile.TemporaryDirectory() as work:
            routes = routes_file(Path(work), kind, names, broker.url, domain).parent
            engine = EngineRun(routes, workers, Path(work), env=env)
            pids: list[int] = []
            try:
                pids = await engine.running()
                if counter is not None:
                    await matched(counter, workers)
                engine.signal(pids, signal.SIGSTOP)
                await broker.prefill_confirmed(names["queue"], [gnss_json(i) for i in range(count)])
                processes = [engine.process.pid, *(pid for pid in pids if pid != engine.process.pid)]
                engine.signal(pids, signal.SIGCONT)
                sunk = counter.value if counter is not None else (lambda: broker.count(names["sink"]))
                result = await observe(sunk, count, processes)
            finally:
                for pid in pids:  # a stopped worker would not see its SIGTERM
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGCONT)
                result_exit = await engine.stop()
            return {"workers": workers, "kind": kind, **result, "exit": result_exit}
    finally:
        if counter is not None:
            counter.close()
        await broker.drop(names)


async def matched(counter: RosCounter, publishers: int, timeout: float = 60.0) -> None:
    """Until the counting subscription matched every worker's publisher (the engine holds a
    message until a reader matched: a worker still discovering would start its drain late)."""
    deadline = time.monotonic() + timeout
    while counter.subscription.get_publisher_count() < publishers:
        if time.monotonic() > deadline:
            raise RuntimeError(f"the counter matched {counter.subscription.get_publisher_count()} of {publishers} publishers")
        await asyncio.sleep(0.05)


def group_cpu_seconds(group: int) -> float:
    """CPU time of every process of process group ``group`` (the broker node under ``timeout``)."""
    usages = (process_usage(int(entry.name)) for entry in Path("/proc").iterdir() if entry.name.isdigit())
    return sum(usage.cpu_s for usage in usages if usage is not None and usage.group == group)


async def observe(sunk: Callable[[], Awaitable[int]], total: int, pids: list[int]) -> dict[str, Any]:
    """Count the sink until ``total`` arrived or it stalls: the rate and each process's CPU
    seconds (and the broker node's) from 10 % of the messages to the last."""
    samples: list[tuple[float, int, list[float]]] = []
    last_change, last = time.monotonic(), 0
    while True:
        now, seen = time.monotonic(), await sunk()
        samples.append((now, seen, [process_cpu_seconds(pid) for pid in pids] + [group_cpu_seconds(BROKER_GROUP[0])]))
        if seen != last:
            last_change, last = now, seen
        if seen >= total or now - last_change > STALL_S:
            break
        await asyncio.sleep(0.02)
    start = next(sample for sample in samples if sample[1] >= total * 0.1)
    end = next(sample for sample in samples if sample[1] >= seen)
    carried, seconds = end[1] - start[1], end[0] - start[0]
    cpu = [round(b - a, 2) for a, b in zip(start[2], end[2])]
    broker_cpu = cpu.pop()
    return {"msg_per_s": carried / seconds if seconds > 0 else float("nan"), "lost": total - seen, "seconds": round(seconds, 2),
            "broker_cpu_s": broker_cpu,
            "cpu_s_by_process": dict(zip(["supervisor" if len(pids) > 1 else "engine", *(f"worker {k}" for k in range(len(pids) - 1))],
                                         cpu)),
            "cpu_us_per_msg": round(sum(cpu) * 1e6 / carried, 1) if carried else float("nan")}


async def alternating(url: str, count: int, rounds: int, broker_group: int, kind: str,
                      systems: dict[str, tuple[int, dict[str, str] | None]]) -> list[dict[str, Any]]:
    """``rounds`` rounds of one drain by each system (name -> its workers and engine
    environment), back to back, their order reversed every other round: a drift of the shared
    machine's load weighs on each alike."""
    BROKER_GROUP[0] = broker_group
    broker = Broker(url)
    await broker.open()
    runs: list[dict[str, Any]] = []
    names = list(systems)
    try:
        for round_index in range(rounds):
            for name in (names if round_index % 2 == 0 else names[::-1]):
                workers, env = systems[name]
                result = {"system": name, **await drain(broker, workers, count, kind, env)}
                print(f"  round {round_index + 1}, {name}: {result['msg_per_s']:.0f} msg/s, {result['cpu_us_per_msg']} us/msg, "
                      f"lost {result['lost']}, {result['seconds']} s, CPU s {result['cpu_s_by_process']}, "
                      f"broker {result['broker_cpu_s']}", flush=True)
                runs.append(result)
    finally:
        await broker.close()
    return runs


def round_ratios(runs: list[dict[str, Any]], key: str, over: str, under: str) -> list[float]:
    """Per round (two runs back to back), ``key`` of system ``over`` divided by ``under``'s."""
    pairs = [runs[i:i + 2] for i in range(0, len(runs), 2)]
    return [round(next(r for r in pair if r["system"] == over)[key] / next(r for r in pair if r["system"] == under)[key], 2)
            for pair in pairs]


async def measure(url: str, count: int, rounds: int, broker_group: int = 0, kind: str = "amqp-amqp") -> dict[str, Any]:
    """``rounds`` pairs of drains, 1 and 2 workers alternating first; the ratio of the medians,
    and each round's own ratio (its two drains ran back to back, under the same load)."""
    runs = await alternating(url, count, rounds, broker_group, kind, {"1 worker": (1, None), "2 workers": (2, None)})
    median = {k: statistics.median(r["msg_per_s"] for r in runs if r["workers"] == k) for k in (1, 2)}
    return {"kind": kind, "count": count, "rounds": rounds, "runs": runs, "median_msg_per_s": median,
            "ratio_2_over_1": round(median[2] / median[1], 2), "round_ratios": round_ratios(runs, "msg_per_s", "2 workers", "1 worker"),
            "lost": sum(r["lost"] for r in runs), "cpus": os.cpu_count(), "loadavg": os.getloadavg()}


LOOPS = {"uvloop": {"RABBITROS_LOOP": "uvloop"}, "asyncio": {"RABBITROS_LOOP": "asyncio"}}
"""``--loops``: one engine on each event loop (engine/running/loop.py)."""


async def measure_loops(url: str, count: int, rounds: int, broker_group: int = 0, kind: str = "amqp-amqp") -> dict[str, Any]:
    """``rounds`` pairs of drains by one engine on uvloop and on asyncio's own loop, alternating
    first: the engine's CPU per message on each, and each round's asyncio / uvloop ratio (issue
    34: keep uvloop only if it saves at least 15 % per message)."""
    runs = await alternating(url, count, rounds, broker_group, kind, {loop: (1, env) for loop, env in LOOPS.items()})
    cpu = {loop: statistics.median(r["cpu_us_per_msg"] for r in runs if r["system"] == loop) for loop in LOOPS}
    return {"kind": kind, "count": count, "rounds": rounds, "runs": runs, "median_cpu_us_per_msg": cpu,
            "round_cpu_ratios_asyncio_over_uvloop": round_ratios(runs, "cpu_us_per_msg", "asyncio", "uvloop"),
            "lost": sum(r["lost"] for r in runs), "loadavg": os.getloadavg()}


def report(result: dict[str, Any]) -> list[str]:
    """The section's lines for bench/report.py (and this module's own output)."""
    lines = [f"{result.get('kind', 'amqp-amqp')}: {result['count']} messages a drain, {result['rounds']} rounds (1 and 2 workers back to back, the order "
             f"alternating); {result['cpus']} CPUs, load average {'/'.join(f'{x:.1f}' for x in result['loadavg'])} after.", "",
             "| round | workers | msg/s | lost | s | CPU s by process | broker CPU s | engine µs/msg |", "|---|---|---|---|---|---|---|---|"]
    for index, run in enumerate(result["runs"]):
        cpu = ", ".join(f"{name} {seconds}" for name, seconds in run["cpu_s_by_process"].items())
        lines.append(f"| {index // 2 + 1} | {run['workers']} | {run['msg_per_s']:.0f} | {run['lost']} | {run['seconds']} | {cpu} | "
                     f"{run['broker_cpu_s']} | {run['cpu_us_per_msg']} |")
    median = result["median_msg_per_s"]
    lines += ["", f"Median: 1 worker {median['1' if '1' in median else 1]:.0f} msg/s, 2 workers "
              f"{median['2' if '2' in median else 2]:.0f} msg/s: **2 workers / 1 = {result['ratio_2_over_1']}** "
              f"(each round: {', '.join(map(str, result['round_ratios']))}); lost {result['lost']}.", ""]
    return lines


def main() -> None:
    from engine.endpoints.amqp.broker import LocalBroker

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kind", choices=("amqp-amqp", "amqp-ros2"), default="amqp-amqp", help="the route drained")
    parser.add_argument("--count", type=int, default=20_000, help="messages per drain")
    parser.add_argument("--rounds", type=int, default=3, help="pairs of drains (1 and 2 workers)")
    parser.add_argument("--loops", action="store_true", help="one worker on uvloop against one on asyncio's loop, instead of 1 and 2 workers")
    parser.add_argument("--out", type=Path, help="write the results as JSON to this file")
    args = parser.parse_args()
    with LocalBroker() as node:
        group = node._process.pid if node._process is not None else 0  # the node's own process group (start_new_session)
        if args.loops:
            result = asyncio.run(measure_loops(node.url, args.count, args.rounds, group, args.kind))
            print(json.dumps({k: v for k, v in result.items() if k != "runs"}))
        else:
            result = asyncio.run(measure(node.url, args.count, args.rounds, group, args.kind))
            print("\n".join(report(result)))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
