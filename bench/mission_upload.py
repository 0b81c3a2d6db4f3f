"""Mission upload time over the emulated SiK radio (57,600 baud, 64 kbps air, ~237 ms TDM).

For 5, 20, 50 and 200 waypoints, at 0 % and 5 % air-packet loss, to two vehicles behind the
radio: the simulated vehicle (rabbitros_sim/vehicle.py, its own process) and MAVSDK's own
vehicle (tests/support/mavsdk_vehicle.py: the ``mavsdk`` wheel's C++ core as an autopilot with its
MissionRawServer, opening the radio's vehicle-side pseudo-terminal as ``serial://``). Each is
sent the same mission, one client after the other on the same radio, by: the engine's mission
sink (``mission: upload``, 1.5 s answer timeout), a plain pymavlink upload loop (one thread,
blocking reads, the same 1.5 s timeout) and MAVSDK's own mission client (the wheel's C++ core
as the ground station, ``MissionRaw.upload_mission`` over the radio's serial port) twice: with
MAVSDK's default timeout (0.5 s) and with ``Mavsdk::set_timeout_s(1.5)``, which MAVSDK advises
for slow links and which matches the engine's. A MAVSDK upload that gives up is reported as its
error (e.g. ``TIMEOUT``), the others' figures stand. Prints seconds and the ratios; ``--json``
writes them.

    .venv/bin/python -m bench.mission_upload [--sizes 5 20 50 200] [--loss 0 0.05] [--repeat 1]
                                             [--vehicles simulated mavsdk] [--json out.json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import os
import select
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path
from collections.abc import AsyncIterator
from typing import Any

os.environ["MAVLINK20"] = "1"
from pymavlink.dialects.v20 import common as mavlink2  # noqa: E402

from bench.roundtrip_mavlink import vehicle_process  # noqa: E402
from engine.endpoints import mavlink  # noqa: E402
from engine.endpoints.base import Outbound  # noqa: E402
from rabbitros_sim.sik_radio import SikRadioPair  # noqa: E402
from rabbitros_sim.vehicle import open_serial  # noqa: E402

TIMEOUT = 1.5
CLIENTS = ("engine_s", "pymavlink_s", "mavsdk_s", "mavsdk_slow_s")
VEHICLES = ("simulated", "mavsdk")


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


def set_mavsdk_timeout(sdk: Any, seconds: float) -> None:
    """``Mavsdk::set_timeout_s``: the wheel exports it from its C library but wraps it in no
    Python method."""
    function = sdk._lib.mavsdk_set_timeout_s
    function.argtypes, function.restype = [ctypes.c_void_p, ctypes.c_double], None
    function(sdk._handle, seconds)


def mavsdk_upload(link: str, count: int, timeout: float | None = None) -> float:
    """MAVSDK's MissionRaw client as the ground station: seconds of ``upload_mission`` (the
    vehicle's MAV_MISSION_ACCEPTED), after MAVSDK found the vehicle; ``timeout`` replaces
    MAVSDK's default 0.5 s for each answer."""
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.mission_raw.mission_raw import MissionItem, MissionRaw

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        if timeout is not None:
            set_mavsdk_timeout(sdk, timeout)
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


@contextlib.asynccontextmanager
async def vehicle_behind(kind: str, pair: SikRadioPair, work: Path) -> AsyncIterator[dict[str, Any]]:
    """The vehicle on radio B; yields a dict that receives its counters when it stops."""
    if kind == "simulated":
        async with vehicle_process(pair.link_b, work / "store", 600) as counters:
            yield counters
        return
    from tests.support.mavsdk_vehicle import MavsdkAutopilot

    autopilot = MavsdkAutopilot(f"serial://{pair.device_b}:57600")
    final: dict[str, Any] = {}
    try:
        yield final
    finally:
        final["missions_accepted"] = len(autopilot.missions)
        autopilot.close()


async def failed_as(upload: Any) -> float | str:
    """The seconds, or the error a client gave up with (reported, not fatal to the others)."""
    try:
        return float(await upload)
    except Exception as exc:
        return f"{type(exc).__name__}: {str(exc).split(';')[0]}"


async def measure(count: int, loss: float, seed: int, work: Path, vehicle_kind: str = "simulated") -> dict[str, Any]:
    """One upload by each client, one after the other, through the same radio to the same vehicle."""
    async with SikRadioPair(loss=loss, seed=seed) as pair, vehicle_behind(vehicle_kind, pair, work) as vehicle:
        engine_s, stats = await engine_upload(pair.link_a, count)
        row: dict[str, Any] = {"engine_s": engine_s, "stats": stats, "vehicle": vehicle}
        row["pymavlink_s"] = await failed_as(asyncio.to_thread(reference_upload, pair.link_a, count))
        row["mavsdk_s"] = await failed_as(asyncio.to_thread(mavsdk_upload, pair.device_a, count))
        row["mavsdk_slow_s"] = await failed_as(asyncio.to_thread(mavsdk_upload, pair.device_a, count, TIMEOUT))
    return row


def run(sizes: list[int], losses: list[float], repeat: int = 1,
        vehicles: tuple[str, ...] | list[str] = VEHICLES) -> list[dict[str, Any]]:
    """Every size at every loss to every vehicle; per client the median of the ``repeat`` runs
    that succeeded (every run's figure or error is kept in ``runs``)."""
    work = Path(tempfile.mkdtemp(prefix="rabbitros-mission-bench-"))
    rows = []
    for loss in losses:
        for count in sizes:
            for kind in vehicles:
                runs = [asyncio.run(measure(count, loss, 100 + r, work, kind)) for r in range(repeat)]
                row: dict[str, Any] = {"items": count, "loss": loss, "vehicle": kind, "runs": {}}
                for client in CLIENTS:
                    values = [r[client] for r in runs]
                    row["runs"][client] = values
                    done = [v for v in values if isinstance(v, float)]
                    row[client] = statistics.median(done) if done else values[0]
                    row[client.removesuffix("_s") + "_failed"] = len(values) - len(done)
                row["mission_resends"] = runs[-1]["stats"].get("mission_resends", 0)
                row["vehicle_missions"] = runs[-1]["vehicle"].get("missions_accepted")
                row["loadavg"] = os.getloadavg()[0]
                rows.append(row)
                print(format_row(row), flush=True)
    return rows


def cell(row: dict[str, Any], client: str) -> str:
    """The median seconds, with how many runs gave up and why; or the error when every run did."""
    value, failed = row[client], row.get(client.removesuffix("_s") + "_failed", 0)
    if not isinstance(value, float):
        return f"failed: {str(value)[:40]}" + (f" ({failed} of {failed})" if failed > 1 else "")
    if not failed:
        return f"{value:.2f}"
    errors = sorted({str(v).rpartition(": ")[2] for v in row["runs"][client] if not isinstance(v, float)})
    return f"{value:.2f} ({failed} of {len(row['runs'][client])} failed: {', '.join(errors)[:40]})"


def ratio(row: dict[str, Any], client: str) -> str:
    return f"{row['engine_s'] / row[client]:.2f}" if isinstance(row[client], float) else "-"


HEADER = ("| Vehicle | Items | Loss | Engine (s) | pymavlink (s) | MAVSDK, 0.5 s timeout (s) | MAVSDK, 1.5 s (s) "
          "| engine/pymavlink | engine/MAVSDK 1.5 s | Load avg |\n|---|---|---|---|---|---|---|---|---|---|")


def format_row(row: dict[str, Any]) -> str:
    return (f"| {'MAVSDK' if row.get('vehicle') == 'mavsdk' else 'simulated'} | {row['items']} | {row['loss']:.0%} | "
            + " | ".join(cell(row, c) if c in row else "-" for c in CLIENTS)
            + f" | {ratio(row, 'pymavlink_s')} | {ratio(row, 'mavsdk_slow_s') if 'mavsdk_slow_s' in row else '-'} | "
            + (f"{row['loadavg']:.1f} |" if "loadavg" in row else "- |"))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5, 20, 50, 200])
    parser.add_argument("--loss", type=float, nargs="+", default=[0.0, 0.05])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--vehicles", nargs="+", choices=VEHICLES, default=list(VEHICLES))
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args()
    print(HEADER)
    rows = run(args.sizes, args.loss, args.repeat, args.vehicles)
    if args.json:
        import json

        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
