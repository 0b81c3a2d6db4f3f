"""Mission upload time over the emulated SiK radio (57,600 baud, 64 kbps air, ~237 ms TDM).

For 5, 20, 50 and 200 waypoints, at 0 % and 5 % air-packet loss: the engine's mission sink
(``mission: upload``) against the simulated vehicle in its own process, and, as references on
the same radio in the same run: a plain pymavlink upload loop (one thread, blocking reads, the
same 1.5 s answer timeout) and MAVSDK's own mission client (the ``mavsdk`` wheel's C++ core as
the ground station, ``MissionRaw.upload_mission`` over the radio's serial port, with MAVSDK's
default timeouts). The vehicle is the simulated one (rabbitros_sim/vehicle.py) for all three:
MAVSDK's vehicle side (tests/mavsdk_vehicle.py) listens on UDP, and the radio emulator is a
serial device, so one vehicle behind the radio serves every client alike. Prints seconds,
items/s and the ratios; ``--json`` writes them.

    .venv/bin/python -m bench.mission_upload [--sizes 5 20 50 200] [--loss 0 0.05] [--repeat 1] [--json out.json]
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


def mavsdk_upload(link: str, count: int) -> float:
    """MAVSDK's MissionRaw client as the ground station: seconds of ``upload_mission`` (the
    vehicle's MAV_MISSION_ACCEPTED), after MAVSDK found the vehicle."""
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.mission_raw.mission_raw import MissionItem, MissionRaw

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        result = sdk.add_any_connection(f"serial://{link}:57600")
        system = sdk.first_autopilot(20.0)
        if system is None:
            raise RuntimeError(f"MAVSDK did not find the vehicle behind the radio ({result})")
        points = waypoints(count)["waypoints"]
        items = [MissionItem(seq, mavlink2.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, mavlink2.MAV_CMD_NAV_WAYPOINT,
                             int(seq == 0), 1,  # MAVSDK wants exactly one current item
                             p["hold_s"], 0.0, 0.0, 0.0, round(p["lat"] * 1e7), round(p["lon"] * 1e7), p["alt_rel"], 0)
                 for seq, p in enumerate(points)]
        mission = MissionRaw(system)
        started = time.perf_counter()
        mission.upload_mission(items)
        return time.perf_counter() - started
    finally:
        sdk.destroy()


async def measure(count: int, loss: float, seed: int, work: Path) -> dict[str, Any]:
    """One upload by each client, one after the other, through the same radio and vehicle."""
    async with SikRadioPair(loss=loss, seed=seed) as pair, vehicle_process(pair.link_b, work / "store", 600) as vehicle:
        engine_s, stats = await engine_upload(pair.link_a, count)
        reference_s = await asyncio.to_thread(reference_upload, pair.link_a, count)
        try:
            mavsdk_s: float | str = await asyncio.to_thread(mavsdk_upload, pair.link_a, count)
        except Exception as exc:  # reported in the table, not fatal to the others' figures
            mavsdk_s = f"{type(exc).__name__}: {str(exc).split(';')[0]}"
    return {"engine_s": engine_s, "pymavlink_s": reference_s, "mavsdk_s": mavsdk_s, "stats": stats, "vehicle": vehicle}


def run(sizes: list[int], losses: list[float], repeat: int = 1) -> list[dict[str, Any]]:
    """Every size at every loss; the median of ``repeat`` runs of each client."""
    work = Path(tempfile.mkdtemp(prefix="rabbitros-mission-bench-"))
    rows = []
    for loss in losses:
        for count in sizes:
            runs = [asyncio.run(measure(count, loss, 100 + r, work)) for r in range(repeat)]
            row: dict[str, Any] = {"items": count, "loss": loss}
            for client in ("engine_s", "pymavlink_s", "mavsdk_s"):
                values = [r[client] for r in runs if isinstance(r[client], float)]
                row[client] = statistics.median(values) if values else next(r[client] for r in runs)
            row["mission_resends"] = runs[-1]["stats"].get("mission_resends", 0)
            row["vehicle_missions"] = runs[-1]["vehicle"].get("missions_accepted")
            rows.append(row)
            print(format_row(row), flush=True)
    return rows


def format_row(row: dict[str, Any]) -> str:
    def cell(value: Any) -> str:
        return f"{value:.2f}" if isinstance(value, float) else str(value)[:40]

    ratio = (f"{row['engine_s'] / row['mavsdk_s']:.2f}" if isinstance(row["mavsdk_s"], float) else "-")
    return (f"{row['items']:5} {row['loss']:5.0%} {cell(row['engine_s']):>9} {cell(row['pymavlink_s']):>12} "
            f"{cell(row['mavsdk_s']):>9} {row['engine_s'] / row['pymavlink_s']:8.2f} {ratio:>8}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5, 20, 50, 200])
    parser.add_argument("--loss", type=float, nargs="+", default=[0.0, 0.05])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args()
    print(f"{'items':>5} {'loss':>5} {'engine s':>9} {'pymavlink s':>12} {'mavsdk s':>9} {'e/pymav':>8} {'e/mavsdk':>8}")
    rows = run(args.sizes, args.loss, args.repeat)
    if args.json:
        import json

        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
