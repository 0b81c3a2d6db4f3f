"""The fleet benchmark (bench/fleet.py) with 1 and 2 engine workers and the hand-written
reference, in one run, interleaved (issue 34, "What it must show").

``python -m bench.bench_fleet_workers [--agents 100] [--rounds 2] [--larger 150] [--duration 40]``:
each step runs bench/fleet.py's :func:`~bench.fleet.run_mode` on a fresh private RabbitMQ
node (as ``fleet.fleet`` does: no step carries what another left in the broker) with half the
agents ROS 2 robots and half MAVLink vehicles, the routes written templated (``for_each``):

* ``reference``: no engine, the bridge written on rclpy, pymavlink and aiormq
  (bench/systems.py ``ref_fleet``);
* ``1 worker``: ``rabbitros-engine run --workers 1`` (one engine process, no supervisor);
* ``2 workers``: ``rabbitros-engine run --workers 2`` (a supervisor and two workers; the
  placement is the CLI's: each ROS 2 topic and each MAVLink link on one worker by a hash,
  the AMQP command queues consumed by both).

At ``--agents`` the three alternate their order from round to round (a drift of the shared
machine's load weighs on each); then, if ``--larger`` is given, 1 and 2 workers at each of
those fleet sizes (the "largest fleet" steps). Every step reports what bench/fleet.py
reports (lost, p50/p99 per stream kind, CPU per message) and each process's CPU and RSS
over the measured period: each engine process, the generators, the consumer, the RabbitMQ
node; the whole machine's busy cores (/proc/stat: other sessions' processes too, which this
one cannot see) and the load average before and after (the machine is shared).
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import os
from pathlib import Path
from typing import Any

from bench import fleet

REPO = Path(__file__).resolve().parent.parent
SYSTEMS = {"reference": 0, "1 worker": 1, "2 workers": 2, "1 worker uvloop": 1}
"""Each system's ``--workers`` (0: the reference, no engine)."""
ENGINE_ENV = {"1 worker uvloop": {"RABBITROS_LOOP": "uvloop"}}
"""A system's engine environment beyond the run's: uvloop in place of asyncio's loop (the
default, engine/running/loop.py), to measure what uvloop saves in the same run (issue 34)."""
DEFAULT_SYSTEMS = ("reference", "1 worker", "2 workers")


def schedule(agents: int, rounds: int, larger: list[int], names: list[str] | None = None) -> list[tuple[str, int]]:
    """(system, agents) in the order run: the systems (by default the reference, 1 and 2
    workers) alternating at ``agents``, then 1 and 2 workers at each larger size."""
    names = names or list(DEFAULT_SYSTEMS)
    steps = [(name, agents) for index in range(rounds) for name in (names if index % 2 == 0 else names[::-1])]
    return steps + [(name, size) for size in larger for name in ("1 worker", "2 workers")]


def mode_arguments(system: str) -> dict[str, Any]:
    """What :func:`~bench.fleet.run_mode` is given for ``system``: its mode, workers and
    engine environment (without it, "1 worker asyncio" ran on the default loop, then uvloop:
    its figures of 2026-11-27 compared uvloop with itself)."""
    workers = SYSTEMS[system]
    return {"mode": fleet.REFERENCE if workers == 0 else "templated", "workers": workers, "engine_env": ENGINE_ENV.get(system)}


async def step(system: str, agents: int, duration: float) -> dict[str, Any]:
    """One system on a fleet of ``agents`` (half robots, half vehicles) on a fresh broker."""
    from engine.endpoints.amqp.broker import LocalBroker

    node = LocalBroker()
    url = await asyncio.to_thread(node.start)
    try:
        group = node._process.pid if node._process is not None else 0  # the node's own process group (start_new_session)
        before = os.getloadavg()
        result = await fleet.run_mode(url, robots_n=agents - agents // 2, vehicles_n=agents // 2, duration=duration,
                                      broker_group=group, **mode_arguments(system))
        result.update(system=system, agents=agents, loadavg_before=before, loadavg_after=os.getloadavg())
        return result
    finally:
        await asyncio.to_thread(node.stop)


async def measure(agents: int, rounds: int, larger: list[int], duration: float, systems: list[str] | None = None) -> list[dict[str, Any]]:
    runs = []
    for system, size in schedule(agents, rounds, larger, systems):
        print(f"  fleet-workers: {system}, {size} agents, {duration:.0f} s", flush=True)
        try:
            result = await step(system, size, duration)
        except Exception as error:  # noqa: BLE001 - a failed step is reported, the run goes on
            result = {"system": system, "agents": size, "error": repr(error)}
        print("   ", summary(result), flush=True)
        runs.append(result)
    return runs


def summary(run: dict[str, Any]) -> str:
    if "error" in run:
        return f"failed: {run['error']}"
    p99 = ", ".join(f"{kind} {run['latency_ms'][kind].get('p99', float('nan')):.0f}" for kind in fleet.STREAM_KINDS)
    return (f"lost {run['lost']}, p99 ms: {p99}; {run['engine_cpu_us_per_message']:.0f} us/msg, "
            f"{run['engine_cores']:.2f} cores; load {run['loadavg_before'][0]:.1f}")


def report(runs: list[dict[str, Any]]) -> list[str]:
    """A table, one column per step in the order run."""
    good = [run for run in runs if "error" not in run]
    lines = ["| | " + " | ".join(f"{run['system']}, {run['agents']}" for run in good) + " |", "|---|" + "---|" * len(good)]

    def row(label: str, value: Any) -> None:
        lines.append(f"| {label} | " + " | ".join(value(run) for run in good) + " |")

    row("lost (telemetry + commands) / sent", lambda r: f"{r['lost']} / {r['telemetry_sent'] + r['commands_sent']}")
    for kind in fleet.STREAM_KINDS:
        row(f"{kind} p50 / p99 (ms)", lambda r, k=kind: (f"{r['latency_ms'][k]['p50']:.1f} / {r['latency_ms'][k]['p99']:.1f}"
                                                         if r["latency_ms"][k].get("n") else "-"))
    row("bridge CPU per message (us)", lambda r: f"{r['engine_cpu_us_per_message']:.0f}")
    row("bridge CPU (cores, all its processes)", lambda r: f"{r['engine_cores']:.2f}")
    names = list(dict.fromkeys(name for run in good for name in run.get("processes", {})))
    for name in names:
        row(f"{name}: CPU cores / RSS MiB", lambda r, n=name: (f"{r['processes'][n]['cores']:.2f} / {r['processes'][n]['rss_mib']:.0f}"
                                                               if n in r.get("processes", {}) else "-"))
    row("all measured processes (cores)", lambda r: f"{sum(p['cores'] for p in r['processes'].values()):.2f}")
    row("the machine: busy / of which niced / idle (cores)", lambda r: (
        f"{r['machine']['busy_cores']:.2f} / {r['machine']['niced_cores']:.2f} / {r['machine']['idle_cores']:.2f}" if "machine" in r else "-"))
    row("load average before / after", lambda r: f"{r['loadavg_before'][0]:.1f} / {r['loadavg_after'][0]:.1f}")
    failed = [run for run in runs if "error" in run]
    lines += [f"- failed: {run['system']}, {run['agents']} agents: {run['error']}" for run in failed]
    return lines


def main() -> None:
    from engine.running.loop import run as run_loop

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--agents", type=int, default=100, help="agents of the interleaved rounds (half robots, half vehicles)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of the systems at --agents")
    parser.add_argument("--systems", default=",".join(DEFAULT_SYSTEMS),
                        help=f"comma-separated systems of the rounds at --agents, of: {', '.join(SYSTEMS)}")
    parser.add_argument("--larger", default="", help="comma-separated fleet sizes run after, 1 and 2 workers each")
    parser.add_argument("--duration", type=float, default=40.0, help="seconds of load per step")
    parser.add_argument("--out", type=Path, help="output directory (results.json, report.md)")
    args = parser.parse_args()
    larger = [int(size) for size in args.larger.split(",") if size]
    systems = [name.strip() for name in args.systems.split(",") if name.strip()]
    if unknown := [name for name in systems if name not in SYSTEMS]:
        parser.error(f"--systems: unknown {', '.join(unknown)}; known: {', '.join(SYSTEMS)}")
    stamp = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    runs = run_loop(measure(args.agents, args.rounds, larger, args.duration, systems))
    commit = os.popen(f"git -C {REPO} rev-parse --short HEAD").read().strip()
    text = [f"# Fleet with engine workers\n\n{stamp}, commit {commit}, {os.cpu_count()} CPUs, {args.duration:.0f} s a step.\n",
            *report(runs)]
    print("\n".join(text))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "results.json").write_text(json.dumps({"date": stamp, "commit": commit, "duration_s": args.duration,
                                                           "cpus": os.cpu_count(), "runs": runs}, indent=1) + "\n")
        (args.out / "report.md").write_text("\n".join(text) + "\n")


if __name__ == "__main__":
    main()
