"""MAVLink latency over the emulated SiK radio (57,600 baud, TDM ~236 ms), the engine against
MAVSDK as the ground station, to two vehicles behind the same radio, in the same run.

* Telemetry one way: the vehicle's GLOBAL_POSITION_INT from its send to the ground station's
  consumer: for the engine an AMQP consumer behind a telemetry route (vehicle -> radio ->
  engine -> RabbitMQ); for MAVSDK its ``MavlinkDirect`` subscription (vehicle -> radio ->
  MAVSDK's C++ core -> the Python callback).
* Command round trip: for the engine an AMQP call (reply_to) -> COMMAND_LONG arm over the radio
  -> the vehicle's COMMAND_ACK -> the call's reply on AMQP; for MAVSDK ``Action.arm()`` -> the
  same COMMAND_LONG -> COMMAND_ACK -> the call returning. A MAVSDK arm that raises (its default
  0.5 s timeout, 3 retransmissions) and an engine call without reply within 15 s count as timed out.

Vehicles: the simulated one (rabbitros_sim/vehicle.py, GLOBAL_POSITION_INT at 4 Hz carrying the
``time_boot_ms`` it was built at, so its send time is ``boot + time_boot_ms``) and MAVSDK's own
(tests/support/mavsdk_vehicle.py: the ``mavsdk`` wheel as an autopilot on the radio's vehicle-side
pseudo-terminal, ``serial://``; a thread publishes a position every 0.25 s that carries its
number in ``lat`` and records when it sent it). Everything runs in this process, so one
monotonic clock stamps both ends.

Load: idle; or TUNNEL frames (128-byte payload) kept flowing toward the vehicle, the load both
stacks can make: the engine from a ``low`` route with 3,000 frames queued on AMQP before
measuring (its writer paces them to the radio and sends commands first), MAVSDK - which has no
tunnel client and no priorities - through ``MavlinkDirect`` at 2,880 B/s, the rate the engine's
link writer allows itself on a 57,600-baud radio; or the engine's JSON tunnel (a ``low`` route
with 400 messages of 2 KB queued), which needs a peer speaking its protocol: the simulated
vehicle only. Each row gives the uplink's air bytes/s and the bytes the ground radio dropped
over the measurement, so what saturated is visible. Signing: the engine and the simulated
vehicle sign (MAVLink 2, one key); the ``mavsdk`` 4.1.0 wheel has no signing (its C library
exports nothing for it), so the MAVSDK rows and the MAVSDK vehicle are unsigned only.

    .venv/bin/python -m bench.radio_latency [--seconds 10] [--json out.json]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
ROUTES = """
connections:
  gcs: {{amqp: "{url}"}}
  radio: {{mavlink: "{link}", baud: 57600{signing}}}
routes:
  - name: telemetry
    source: {{mavlink: {{connection: radio, message: GLOBAL_POSITION_INT, system_id: 1}}}}
    schema: raw_json
    mapping: "{{t: time_boot_ms, lat: lat}}"
    sink: {{amqp: {{connection: gcs, exchange: {exchange}, routing_key: pos}}}}
  - name: command
    source: {{amqp: {{connection: gcs, queue: {exchange}-cmd}}}}
    schema: raw_json
    sink:
      mavlink: {{connection: radio, message: COMMAND_LONG, acknowledged: true, target_system: 1, target_component: 1}}
      mapping: "{{command: `400`, param1: `1`}}"
  - name: bulk
    source: {{amqp: {{connection: gcs, queue: {exchange}-bulk}}}}
    schema: raw_json
    priority: low
    sink: {{mavlink: {{connection: radio, json_tunnel: true, target_system: 1, target_component: 1}}}}
  - name: frames
    source: {{amqp: {{connection: gcs, queue: {exchange}-frames}}}}
    schema: raw_json
    priority: low
    sink:
      mavlink: {{connection: radio, message: TUNNEL, target_system: 1, target_component: 1}}
      mapping: "{{payload_type: `32769`, payload_length: length(p), payload: p}}"
"""
KEY = bytes(range(32))
BULK_MESSAGES = 400
BULK_SIZE = 2000
TUNNEL_FRAMES = 3000
TUNNEL_PAYLOAD = list(range(1, 129))  # no trailing zeros: MAVLink 2 would cut them off the wire
MAVSDK_TUNNEL_RATE = 2880.0
POSITION_PERIOD = 0.25
COMMAND_GAP = 0.3
STACKS = ("engine", "mavsdk")
VEHICLES = ("simulated", "mavsdk")
LOADS = ("idle", "tunnel frames", "json tunnel")


def percentiles(samples: list[float]) -> dict[str, Any]:
    if not samples:
        return {"n": 0}
    ordered = sorted(samples)
    return {"n": len(ordered), "p50_ms": statistics.median(ordered) * 1000,
            "p99_ms": ordered[min(len(ordered) - 1, round(0.99 * (len(ordered) - 1)))] * 1000,
            "max_ms": ordered[-1] * 1000}


class Window:
    """What one measurement collects: telemetry of positions sent after it opened, command round
    trips, and the radio's counters over it."""

    def __init__(self) -> None:
        self.opened = float("inf")
        self.telemetry: list[float] = []
        self.commands: list[float] = []
        self.timeouts = 0
        self.failures: dict[str, int] = {}
        """What the commands that got no answer failed with (MAVSDK's ActionResult name, or ``no reply``)."""
        self.radio: dict[str, Any] = {}

    def fail(self, why: str) -> None:
        self.timeouts += 1
        self.failures[why] = self.failures.get(why, 0) + 1

    def position(self, sent: float | None, arrived: float) -> None:
        if sent is not None and sent >= self.opened:  # not what waited in a queue before the window
            self.telemetry.append(arrived - sent)


# -- vehicles ---------------------------------------------------------------------------------


class Vehicle:
    """A vehicle behind radio B; ``sent_at`` gives a received GLOBAL_POSITION_INT's send time."""

    sent_at: Callable[[dict[str, Any]], float | None]


@contextlib.asynccontextmanager
async def simulated_vehicle(link: str, signed: bool) -> AsyncIterator[Vehicle]:
    from rabbitros_sim.vehicle import SimVehicle

    sim = SimVehicle(link, signing_key=KEY if signed else None, position_rate_hz=1 / POSITION_PERIOD)
    await sim.open()
    stop = asyncio.Event()
    runner = asyncio.create_task(sim.run(stop))
    vehicle = Vehicle()
    # the loop time its time_boot_ms counts from (the loop's clock is time.monotonic)
    vehicle.sent_at = lambda fields: sim._boot + fields["t" if "t" in fields else "time_boot_ms"] / 1000
    try:
        yield vehicle
    finally:
        stop.set()
        await asyncio.gather(runner, return_exceptions=True)


@contextlib.asynccontextmanager
async def mavsdk_vehicle(device: str) -> AsyncIterator[Vehicle]:
    from tests.support.mavsdk_vehicle import MavsdkAutopilot, position_number

    autopilot = MavsdkAutopilot(f"serial://{device}:57600")
    sent: dict[int, float] = {}
    stop = threading.Event()

    def publish() -> None:
        number, due = 0, time.monotonic()
        while not stop.wait(max(0.0, due - time.monotonic())):
            sent[number] = time.monotonic()
            autopilot.publish_position(number)
            number, due = number + 1, due + POSITION_PERIOD

    publisher = threading.Thread(target=publish, name="mavsdk-vehicle-positions", daemon=True)
    publisher.start()
    vehicle = Vehicle()
    vehicle.sent_at = lambda fields: sent.get(position_number(fields["lat"]))
    try:
        yield vehicle
    finally:
        stop.set()
        await asyncio.to_thread(publisher.join, 5)
        autopilot.close()


def vehicle_behind(kind: str, pair: Any, signed: bool) -> contextlib.AbstractAsyncContextManager[Vehicle]:
    return simulated_vehicle(pair.link_b, signed) if kind == "simulated" else mavsdk_vehicle(pair.device_b)


# -- ground stations --------------------------------------------------------------------------


async def engine_gcs(url: str, pair: Any, vehicle: Vehicle, signed: bool, load: str, seconds: float,
                     window: Window) -> dict[str, Any]:
    """The engine on radio A with AMQP on the other side; returns the engine's own counters."""
    import aio_pika

    from engine.endpoints.mavlink.connection import MavlinkConnection
    from engine.running.runtime import Engine

    exchange = f"lat-{uuid.uuid4().hex[:6]}"
    async with contextlib.AsyncExitStack() as rig:
        work = Path(rig.enter_context(tempfile.TemporaryDirectory(prefix="rabbitros-radio-latency-")))
        signing = ""
        if signed:
            (work / "key").write_bytes(KEY)
            signing = f", signing: {{key_file: \"{work / 'key'}\"}}"
        routes = work / "routes"
        routes.mkdir()
        (routes / "r.yaml").write_text(ROUTES.format(url=url, link=pair.link_a, signing=signing, exchange=exchange))
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        stopped: dict[str, Any] = {}
        rig.push_async_callback(stop_bounded, engine, stopped)
        connection = await aio_pika.connect(url)
        rig.push_async_callback(connection.close)
        channel = await connection.channel()
        target = await channel.declare_exchange(exchange, aio_pika.ExchangeType.TOPIC, durable=True)  # as the sink does
        positions = await channel.declare_queue(exclusive=True)
        await positions.bind(target, "pos")

        async def on_position(message: Any) -> None:
            arrived = time.monotonic()
            window.position(vehicle.sent_at(json.loads(message.body)), arrived)

        replies = await channel.declare_queue(exclusive=True)
        waiting: dict[str, asyncio.Future[float]] = {}

        async def on_reply(message: Any) -> None:
            future = waiting.pop(message.correlation_id or "", None)
            if future is not None and not future.done():
                future.set_result(time.monotonic())

        await replies.consume(on_reply, no_ack=True)
        if load == "json tunnel":
            pad = "x" * (BULK_SIZE - 20)
            for n in range(BULK_MESSAGES):
                await channel.default_exchange.publish(
                    aio_pika.Message(json.dumps({"n": n, "pad": pad}).encode()), f"{exchange}-bulk")
        elif load == "tunnel frames":
            frame = json.dumps({"p": TUNNEL_PAYLOAD}).encode()
            for _ in range(TUNNEL_FRAMES):
                await channel.default_exchange.publish(aio_pika.Message(frame), f"{exchange}-frames")
        if load != "idle":
            await asyncio.sleep(3.0)  # the tunnel's window and the writer's queue are full
        await positions.consume(on_position, no_ack=True)
        await asyncio.sleep(1.0)
        async with radio_window(pair, window):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                correlation = uuid.uuid4().hex
                answered: asyncio.Future[float] = asyncio.get_running_loop().create_future()
                waiting[correlation] = answered
                sent = time.monotonic()
                await channel.default_exchange.publish(
                    aio_pika.Message(b"{}", reply_to=replies.name, correlation_id=correlation), f"{exchange}-cmd")
                try:
                    window.commands.append(await asyncio.wait_for(answered, 15) - sent)
                except TimeoutError:
                    window.fail("no reply in 15 s")
                await asyncio.sleep(COMMAND_GAP)
        link = next(c for c in engine.connections if c.name == "radio")
        assert isinstance(link, MavlinkConnection)  # the route file's "radio" is a MAVLink link
        routes = engine.status()["routes"]
        return {"bulk_delivered": routes["bulk"]["delivered"], "frames_delivered": routes["frames"]["delivered"],
                "link_frames_sent": link.stats["frames_sent"], "engine_stop": stopped}


ABANDONED: list[asyncio.Future[None]] = []
STOP_BOUND = 40.0


async def stop_bounded(engine: Any, record: dict[str, Any]) -> None:
    """Stop the engine, but give up waiting after STOP_BOUND s so one row cannot hang the bench:
    a stop with a JSON tunnel backlog was seen never to return after its drain timeout (the
    task is kept, not awaited, and the row says so in ``engine_stop``)."""
    started = time.monotonic()
    stop = asyncio.ensure_future(engine.stop())
    done, _ = await asyncio.wait({stop}, timeout=STOP_BOUND)
    record["seconds"] = round(time.monotonic() - started, 1)
    if not done:
        record["hung"] = True
        ABANDONED.append(stop)


def mavsdk_gcs(device: str, vehicle: Vehicle, load: str, seconds: float, window: Window,
               pair: Any) -> dict[str, Any]:
    """MAVSDK's C++ core as the ground station on radio A (blocking: run it in a thread)."""
    from mavsdk import ComponentType, Configuration, Mavsdk
    from mavsdk.plugins.action.action import Action, ActionError
    from mavsdk.plugins.mavlink_direct.mavlink_direct import MavlinkDirect, MavlinkMessage

    sdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    stop = threading.Event()
    loader: threading.Thread | None = None
    tunnel_frames = 0
    try:
        sdk.add_any_connection(f"serial://{device}:57600")
        system = sdk.first_autopilot(20.0)
        if system is None:
            raise RuntimeError("MAVSDK did not find the vehicle behind the radio")
        direct = MavlinkDirect(system)

        def on_position(message: Any, _: Any = None) -> None:
            arrived = time.monotonic()
            if message.system_id == 1:
                window.position(vehicle.sent_at(json.loads(message.fields_json)), arrived)

        direct.subscribe_message("GLOBAL_POSITION_INT", on_position)
        if load == "json tunnel":
            raise ValueError("MAVSDK has no JSON tunnel (no TUNNEL client at all): its load is raw frames")
        if load == "tunnel frames":
            frame = MavlinkMessage("TUNNEL", 0, 0, 1, 1, json.dumps({
                "target_system": 1, "target_component": 1, "payload_type": 32769,
                "payload_length": len(TUNNEL_PAYLOAD), "payload": TUNNEL_PAYLOAD}))
            period = (len(TUNNEL_PAYLOAD) + 4 + 12) / MAVSDK_TUNNEL_RATE  # payload, TUNNEL's fields, MAVLink 2 framing

            def send_tunnel_frames() -> None:
                nonlocal tunnel_frames
                due = time.monotonic()
                while not stop.wait(max(0.0, due - time.monotonic())):
                    direct.send_message(frame)
                    tunnel_frames += 1
                    due += period

            loader = threading.Thread(target=send_tunnel_frames, name="mavsdk-tunnel-load", daemon=True)
            loader.start()
            time.sleep(3.0)  # the radio's buffer is full
        action = Action(system)
        time.sleep(1.0)
        with radio_window_sync(pair, window):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                sent = time.monotonic()
                try:
                    action.arm()
                    window.commands.append(time.monotonic() - sent)
                except ActionError as error:  # MAVSDK gave up (TIMEOUT) or the vehicle refused
                    window.fail(error.result.name)
                time.sleep(COMMAND_GAP)
        return {"tunnel_frames_sent": tunnel_frames}
    finally:
        stop.set()
        if loader is not None:
            loader.join(5)
        sdk.destroy()


@contextlib.contextmanager
def radio_window_sync(pair: Any, window: Window) -> Any:
    """Open ``window`` and record the radio's air bytes each way and the ground radio's drops over it."""
    before, opened = pair.stats(), time.monotonic()
    window.opened = opened
    try:
        yield
    finally:
        after, spent = pair.stats(), time.monotonic() - opened
        window.radio = {
            "uplink_B_per_s": (after["a"].air_bytes - before["a"].air_bytes) / spent,
            "downlink_B_per_s": (after["b"].air_bytes - before["b"].air_bytes) / spent,
            "ground_radio_dropped_B": after["a"].serial_rx_dropped - before["a"].serial_rx_dropped,
            "uplink_packets_lost": after["a"].air_packets_lost - before["a"].air_packets_lost}


@contextlib.asynccontextmanager
async def radio_window(pair: Any, window: Window) -> AsyncIterator[None]:
    with radio_window_sync(pair, window):
        yield


async def one(url: str, stack: str, vehicle_kind: str, signed: bool, load: str, seconds: float) -> dict[str, Any]:
    from rabbitros_sim.sik_radio import SikRadioPair

    window = Window()
    async with SikRadioPair(seed=7) as pair, vehicle_behind(vehicle_kind, pair, signed) as vehicle:
        if stack == "engine":
            extra = await engine_gcs(url, pair, vehicle, signed, load, seconds, window)
        else:
            extra = await asyncio.to_thread(mavsdk_gcs, pair.device_a, vehicle, load, seconds, window, pair)
    return {"stack": stack, "vehicle": vehicle_kind, "signed": signed, "load": load,
            "telemetry": percentiles(window.telemetry), "command": percentiles(window.commands),
            "command_timeouts": window.timeouts, "command_failures": window.failures, **window.radio, **extra}


def combinations() -> list[tuple[str, str, bool, str]]:
    """Interleaved: for each load, each vehicle, the engine then MAVSDK; then the engine signed
    (to the simulated vehicle, the one that signs). The JSON tunnel needs a peer that speaks it:
    the engine to the simulated vehicle only."""
    rows = []
    for load in LOADS:
        for vehicle in VEHICLES:
            rows += [(stack, vehicle, False, load) for stack in STACKS
                     if load != "json tunnel" or (stack, vehicle) == ("engine", "simulated")]
        rows.append(("engine", "simulated", True, load))
    return rows


async def run(url: str | None = None, seconds: float = 10.0) -> list[dict[str, Any]]:
    """Every combination (:func:`combinations`); starts a private broker unless ``url``."""
    from engine.endpoints.amqp.broker import LocalBroker

    broker = None
    if url is None:
        broker = LocalBroker()
        url = await asyncio.to_thread(broker.start)
    try:
        rows = []
        for stack, vehicle, signed, load in combinations():
            try:
                row = await one(url, stack, vehicle, signed, load, seconds)
            except Exception as exc:  # one stack failing must not lose the others' rows
                row = {"stack": stack, "vehicle": vehicle, "signed": signed, "load": load,
                       "error": f"{type(exc).__name__}: {exc}"[:300]}
            row["loadavg"] = os.getloadavg()[0]
            print(format_row(row), flush=True)
            rows.append(row)
        return rows
    finally:
        if broker is not None:
            await asyncio.to_thread(broker.stop)


STACK_NAMES = {"engine": "engine (AMQP)", "mavsdk": "MAVSDK 4.1.0"}
VEHICLE_NAMES = {"simulated": "simulated", "mavsdk": "MAVSDK"}


def load_name(row: dict[str, Any]) -> str:
    """Rows of earlier runs say ``loaded`` (the JSON tunnel) instead of ``load``."""
    load = row.get("load") or ("json tunnel" if row.get("loaded") else "idle")
    return {"idle": "idle", "tunnel frames": "TUNNEL frames", "json tunnel": "JSON tunnel (engine's protocol)"}[load]


def failures(row: dict[str, Any]) -> str:
    kinds = row.get("command_failures") or {}
    return f"{row['command_timeouts']}" + (" (" + ", ".join(f"{n} {why}" for why, n in kinds.items()) + ")" if kinds else "")


def format_row(row: dict[str, Any]) -> str:
    def cell(figures: dict[str, Any], key: str) -> str:
        return f"{figures[key]:.0f}" if key in figures else "-"

    head = (f"| {STACK_NAMES.get(row.get('stack', 'engine'), row.get('stack'))} | "
            f"{VEHICLE_NAMES.get(row.get('vehicle', 'simulated'))} | {'signed' if row['signed'] else 'unsigned'} | "
            f"{load_name(row)} | ")
    if "error" in row:
        return head + f"failed: {row['error'][:80]} | | | | | | | | |"
    t, c = row["telemetry"], row["command"]
    radio = (f"{row['uplink_B_per_s']:.0f} | {row['ground_radio_dropped_B']}" if "uplink_B_per_s" in row else "- | -")
    load = f"{row['loadavg']:.1f}" if "loadavg" in row else "-"
    return (head + f"{cell(t, 'p50_ms')} | {cell(t, 'p99_ms')} | {t['n']} | {cell(c, 'p50_ms')} | {cell(c, 'p99_ms')} | "
            f"{c['n']} | {failures(row)} | {radio} | {load} |")


HEADER = ("| Ground station | Vehicle | Signing | Load | Telemetry p50 (ms) | p99 | n | Command to COMMAND_ACK p50 (ms) "
          "| p99 | n | failed | Uplink air (B/s) | Ground radio dropped (B) | Load avg |\n"
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    os.environ.setdefault("MAVLINK20", "1")
    print(HEADER)
    rows = asyncio.run(run(seconds=args.seconds))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
