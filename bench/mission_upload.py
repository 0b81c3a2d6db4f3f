"""Mission upload time over the emulated SiK radio (57,600 baud, 64 kbps air, ~237 ms TDM).

For 5, 50 and 200 waypoints, at 0 % and 5 % air-packet loss: the engine's mission sink
(``mission: upload``) against the simulated vehicle in its own process, and, as the reference
on the same radio in the same run, a plain pymavlink upload loop (one thread, blocking reads,
the same 1.5 s answer timeout). Prints seconds, items/s and the engine/reference ratio.

    .venv/bin/python -m bench.mission_upload [--sizes 5 50 200] [--loss 0 0.05] [--repeat 1]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import select
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from bench.roundtrip_mavlink import vehicle_process  # noqa: E402
from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import Outbound  # noqa: E402
from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402
from rabbitros_sim.vehicle import open_serial  # noqa: E402

TIMEOUT = 1.5


def waypoints(count: int) -> dict[str, Any]:
    return {"agent_id": "uav1", "waypoints": [
        {"lat": -22.0 + i * 1e-5, "lon": -47.9 + (i % 7) * 1e-5, "alt_rel": 20.0, "hold_s": 1.0} for i in range(count)]}


async def engine_upload(link: str, count: int) -> tuple[float, dict[str, int]]:
    """Seconds from the sink's send to MAV_MISSION_ACCEPTED, with the connection's counters."""
    gcs = mavlink.TRANSPORT.connect("gcs", {"url": link, "baud": 57600})
    await gcs.open()
    try:
        sink = gcs.sink("bench", {"mission": "upload", "target_system": 1, "target_component": 1, "retries": 10})
        mission = waypoints(count)
        await gcs.wait_for_vehicle(1, 1, asyncio.get_running_loop().time() + 20)
        started = time.perf_counter()
        await sink.send(Outbound(b"", mission, mission, uuid.uuid4().hex, {}))
        return time.perf_counter() - started, dict(gcs.stats)
    finally:
        await gcs.close()


def reference_upload(link: str, count: int) -> float:
    """The same protocol written directly on pymavlink: blocking, one frame per answer."""
    fd = open_serial(link)
    mav = mavlink2.MAVLink(None, 255, 190)
    mav.robust_parsing = True

    def send(msg: Any) -> None:
        data = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        view = memoryview(data)
        while view:
            select.select([], [fd], [], 1.0)
            try:
                view = view[os.write(fd, view):]
            except BlockingIOError:
                continue

    def answer(deadline: float) -> Any:
        while (left := deadline - time.monotonic()) > 0:
            if select.select([fd], [], [], left)[0]:
                for msg in mav.parse_buffer(os.read(fd, 4096)) or ():
                    if msg.get_type() in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"):
                        return msg
        return None

    try:
        points = waypoints(count)["waypoints"]
        items = [mavlink2.MAVLink_mission_item_int_message(
            1, 1, seq, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink2.MAV_CMD_NAV_WAYPOINT, 0, 1, p["hold_s"],
            0, 0, 0, round(p["lat"] * 1e7), round(p["lon"] * 1e7), p["alt_rel"], 0) for seq, p in enumerate(points)]
        answer(time.monotonic() + 1.0)  # let the vehicle's telemetry settle into the parser
        started = time.perf_counter()
        last: Any = mavlink2.MAVLink_mission_count_message(1, 1, count, 0)
        send(last)
        tries, highest = 0, -1
        while True:
            msg = answer(time.monotonic() + TIMEOUT)
            if msg is None:
                tries += 1
                if tries > 10:
                    raise RuntimeError("reference upload: no answer")
                send(last)
                continue
            if msg.get_type() == "MISSION_ACK":
                if msg.type != mavlink2.MAV_MISSION_ACCEPTED:
                    raise RuntimeError(f"reference upload refused: {msg.type}")
                return time.perf_counter() - started
            if msg.seq > highest:
                highest, tries = msg.seq, 0
            last = items[msg.seq]
            send(last)
    finally:
        os.close(fd)


async def measure(count: int, loss: float, seed: int, work: Path) -> tuple[float, float, dict[str, Any], dict[str, Any]]:
    async with SikRadioPair(loss=loss, seed=seed) as pair, vehicle_process(pair.link_b, work / "store", 600) as vehicle:
        engine_s, stats = await engine_upload(pair.link_a, count)
        reference_s = await asyncio.to_thread(reference_upload, pair.link_a, count)
    return engine_s, reference_s, stats, vehicle


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5, 50, 200])
    parser.add_argument("--loss", type=float, nargs="+", default=[0.0, 0.05])
    parser.add_argument("--repeat", type=int, default=1)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="rabbitros-mission-bench-"))
    print(f"{'items':>5} {'loss':>5} {'engine s':>9} {'items/s':>8} {'reference s':>12} {'ratio':>6} "
          f"{'resends':>8} {'items sent':>10} {'vehicle missions':>16}")
    for loss in args.loss:
        for count in args.sizes:
            runs = [asyncio.run(measure(count, loss, 100 + r, work)) for r in range(args.repeat)]
            engine_s = statistics.median(r[0] for r in runs)
            reference_s = statistics.median(r[1] for r in runs)
            stats, vehicle = runs[-1][2], runs[-1][3]
            print(f"{count:5} {loss:5.0%} {engine_s:9.2f} {count / engine_s:8.1f} {reference_s:12.2f} "
                  f"{engine_s / reference_s:6.2f} {stats.get('mission_resends', 0):8} "
                  f"{stats.get('mission_items_sent', 0):10} {vehicle.get('missions_accepted', '?'):>16}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
