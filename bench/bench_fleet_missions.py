"""Missions to several vehicles on one UDP link: one batch of uploads, one per vehicle, with the
mission sink's per-target transactions at once against the same batch one after the other (the
sink's former behaviour, ``Sink.send_batch``), in the same run. Three simulated vehicles
(rabbitros_sim, systems 1-3) on one ``udpin`` link, in one event loop with the engine's sink.
Then the same with vehicle 1 silent (timeout 1 s, 3 retries): how long vehicles 2 and 3 wait
for theirs.

    .venv/bin/python -m bench.bench_fleet_missions [--vehicles 3] [--waypoints 50] [--repeat 3]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import time
import uuid
from typing import Any

from engine.endpoints import mavlink
from engine.endpoints.base import Outbound, Sink
from rabbitros_sim.vehicle import SimVehicle
from tests.endpoints.mavlink.test_mavlink_transactions import canonical_mission, free_udp_port


def _outbound(system_id: int, waypoints: int) -> Outbound:
    canonical: dict[str, Any] = {**canonical_mission([(-22.0 - n / 1e5, -47.9) for n in range(waypoints)]), "vehicle": system_id}
    return Outbound(json.dumps(canonical).encode(), canonical, canonical, uuid.uuid4().hex, {})


async def _run(vehicles: int, waypoints: int, repeat: int) -> dict[str, list[float]]:
    port = free_udp_port()
    gcs = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}"})
    await gcs.open()
    sims = [SimVehicle(f"udpout:127.0.0.1:{port}", system_id=system_id) for system_id in range(1, vehicles + 1)]
    stop = asyncio.Event()
    running = [asyncio.create_task(sim.run(stop)) for sim in sims]
    times: dict[str, list[float]] = {"one vehicle": [], "concurrent": [], "one after the other": []}
    try:
        sink = gcs.sink("missions", {"mission": "upload", "target_system": "{vehicle}"})
        while not all(gcs.has_heard(s) for s in range(1, vehicles + 1)):
            await asyncio.sleep(0.05)
        for _ in range(repeat):
            for kind in times:
                batch = [_outbound(s, waypoints) for s in (range(1, 2) if kind == "one vehicle" else range(1, vehicles + 1))]
                started = time.perf_counter()
                send = Sink.send_batch(sink, batch) if kind == "one after the other" else sink.send_batch(batch)
                results = await send
                times[kind].append(time.perf_counter() - started)
                assert results == [None] * len(batch), results
    finally:
        stop.set()
        await asyncio.gather(*running)
        await gcs.close()
    times.update(await _silent_first(waypoints))
    return times


async def _silent_first(waypoints: int) -> dict[str, list[float]]:
    """Seconds until vehicles 2 and 3 accepted theirs while vehicle 1 never answers."""
    times: dict[str, list[float]] = {}
    for kind in ("silent vehicle 1, concurrent", "silent vehicle 1, one after the other"):
        port = free_udp_port()
        gcs = mavlink.TRANSPORT.connect("gcs", {"url": f"udpin:127.0.0.1:{port}"})
        await gcs.open()
        sims = [SimVehicle(f"udpout:127.0.0.1:{port}", system_id=s, mission_result="silent" if s == 1 else "MAV_MISSION_ACCEPTED")
                for s in (1, 2, 3)]
        stop = asyncio.Event()
        running = [asyncio.create_task(sim.run(stop)) for sim in sims]
        try:
            sink = gcs.sink("missions", {"mission": "upload", "target_system": "{vehicle}", "timeout": 1.0, "retries": 3})
            while not all(gcs.has_heard(s) for s in (1, 2, 3)):
                await asyncio.sleep(0.05)
            batch = [_outbound(s, waypoints) for s in (1, 2, 3)]
            started = time.perf_counter()
            task = asyncio.ensure_future(Sink.send_batch(sink, batch) if "after" in kind else sink.send_batch(batch))
            while not all(sim.autopilot.stats["missions_accepted"] for sim in sims[1:]):
                await asyncio.sleep(0.01)
            times[kind] = [time.perf_counter() - started]
            await task
        finally:
            stop.set()
            await asyncio.gather(*running)
            await gcs.close()
    return times


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_fleet_missions", description=__doc__.split("\n\n")[0])
    parser.add_argument("--vehicles", type=int, default=3)
    parser.add_argument("--waypoints", type=int, default=50)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args(argv)
    times = asyncio.run(_run(args.vehicles, args.waypoints, args.repeat))
    for kind, seconds in times.items():
        print(f"{kind}: median {statistics.median(seconds) * 1000:.0f} ms of {len(seconds)} "
              f"({', '.join(f'{s * 1000:.0f}' for s in seconds)} ms), {args.waypoints} waypoints each")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
