"""The paper's second experiment: round trip between RabbitMQ and MAVLink through the SiK radio.

A generator publishes JSON messages of an exact size to RabbitMQ (exchange ``roundtrip``, key
``to_uav``); the engine carries each one as a JSON tunnel over MAVLink through an emulated pair
of SiK radios (57,600 baud, TDM, loss, outages) to the simulated vehicle, which stores it and
sends it back as a new tunnel message; the engine publishes it to RabbitMQ (key ``from_uav``).
Each message is recorded at the three points (as published, as stored by the vehicle, as it came
back) and compared byte for byte; the three versions go to one CSV per run and size.

    python -m bench.roundtrip_mavlink                                # the paper's settings: 5 runs x 100 msgs at 1 msg/s
    python -m bench.roundtrip_mavlink --loss 0.05 --outage 20:3      # 5 % packet loss, 3 s outage 20 s into each batch
    python -m bench.roundtrip_mavlink --runs 1 --rate 4              # fast

The broker is a private node started for the run (``engine.endpoints.amqp.broker``), the radios run in
this process (a thread), the vehicle in its own process on radio B, the engine in this process
on radio A. ``--outage START:DURATION`` is applied to every batch (run x size), START seconds
after its first message, so every size is measured through an outage. Exit status is 0 only if
every message came back byte-identical at all three points.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import csv
import json
import logging
import os
import random
import signal
import statistics
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
ROUTES = """
connections:
  gcs: {{amqp: "{amqp_url}"}}
  radio: {{mavlink: "{link}", baud: 57600{tunnel}}}
routes:
  - name: gcs-to-uav
    source:
      amqp: {{connection: gcs, exchange: {exchange}, binding_key: to_uav, queue: {exchange}-to-uav{prefetch}}}
    schema: raw_json
    sink:
      mavlink: {{connection: radio, json_tunnel: true, target_system: 1, target_component: 1}}
  - name: uav-to-gcs
    source:
      mavlink: {{connection: radio, json_tunnel: true, system_id: 1}}
    schema: raw_json
    sink:
      amqp: {{connection: gcs, exchange: {exchange}, routing_key: from_uav}}
"""
PROBE_TIMEOUT = 30.0
DRAIN_TIMEOUT = 60.0
"""How long after the last publish a batch may take to come back (covers an outage and the
protocol's backed-off retransmissions)."""


@dataclass(frozen=True)
class Settings:
    runs: int = 5
    count: int = 100
    rate: float | dict[int, float] = 1.0
    """Messages per second, or per size (``{50: 12, 250: 5}``): the radio carries far more
    small messages than large ones."""
    sizes: tuple[int, ...] = (50, 150, 250)
    loss: float = 0.0
    outage: tuple[float, float] | None = None
    seed: int | None = 1
    exchange: str = "roundtrip"
    window: int | None = None
    """Tunnel messages in flight per direction (engine route and vehicle); None: the default."""
    prefetch: int | None = None
    """The AMQP source's prefetch on the way to the vehicle (its batches are half of it); None: the default."""
    out: Path = REPO / "results" / "mavlink_roundtrip"

    def rate_for(self, size: int) -> float:
        return self.rate[size] if isinstance(self.rate, dict) else self.rate


@dataclass
class Batch:
    """One run x size: what was sent and what was seen where, with per-message round trips."""

    run: int
    size: int
    sent: int
    at_robot: int
    back: int
    identical: int
    duplicates_back: int
    seconds: float
    """From the first publish to the last message back: the batch's throughput."""
    forward_seconds: float | None
    """From the first publish to the last message stored by the vehicle (the store is read
    every 20 ms): the way to the vehicle alone, which no telemetry shares."""
    back_span_seconds: float | None
    """From the first message back to the last: the round trip's steady pace, without the
    first message's way there and back (the flood reference leaves out its first second too)."""
    forward_span_seconds: float | None
    """From the first message stored by the vehicle to the last."""
    latencies_ms: list[float] = field(repr=False)
    csv: str

    @property
    def ok(self) -> bool:
        return self.identical == self.sent


def make_message(run: int, size: int, seq: int) -> bytes:
    """A compact JSON object of exactly ``size`` bytes (50 at least), unique per (run, size, seq)."""
    head = json.dumps({"run": run, "size": size, "seq": seq, "pad": ""}, separators=(",", ":"))
    rng = random.Random(run * 100_000 + size * 1000 + seq)
    pad = "".join(rng.choice("abcdefghijklmnopqrstuvwxyz0123456789") for _ in range(size - len(head)))
    body = head[:-2] + pad + '"}'
    if len(body) != size:
        raise ValueError(f"cannot make a {size}-byte message (the header alone is {len(head)} bytes)")
    return body.encode()


def _key(body: bytes) -> tuple[Any, Any, Any] | None:
    try:
        data = json.loads(body)
    except ValueError:
        return None
    if not isinstance(data, dict):
        return None
    return data.get("run"), data.get("size"), data.get("seq")


class Recorder:
    """What comes back on ``from_uav``: the first copy of each message and when it arrived."""

    def __init__(self) -> None:
        self.first: dict[tuple[Any, Any, Any], tuple[bytes, float]] = {}
        self.duplicates = 0
        self.probes = 0
        self.arrived = asyncio.Event()

    async def on_message(self, message: Any) -> None:
        now = time.monotonic()
        key = _key(message.body)
        if key is None or key[0] is None:
            self.probes += 1
        elif key in self.first:
            self.duplicates += 1
        else:
            self.first[key] = (message.body, now)
        self.arrived.set()


@contextlib.asynccontextmanager
async def vehicle_process(link: str, store: Path, budget: float, window: int | None = None
                          ) -> AsyncIterator[dict[str, Any]]:
    """The simulated vehicle on radio B in its own process group, killed after ``budget`` s at
    the latest; yields a dict that receives the vehicle's final counters."""
    extra = ["--tunnel-window", str(window)] if window else []
    proc = await asyncio.create_subprocess_exec(
        "timeout", "-s", "KILL", str(int(budget)), sys.executable, "-m", "rabbitros_sim.vehicle",
        "--device", link, "--baud", "57600", "--store", str(store), *extra,
        cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}, stdout=asyncio.subprocess.PIPE,
        start_new_session=True)
    assert proc.stdout is not None
    final: dict[str, Any] = {}
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), 20)
        if json.loads(line or b"{}").get("event") != "ready":
            raise RuntimeError("the simulated vehicle did not start")
        yield final
    finally:
        if proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGTERM)
            try:
                out, _ = await asyncio.wait_for(proc.communicate(), 10)
                for raw in out.splitlines():
                    with contextlib.suppress(ValueError):
                        event = json.loads(raw)
                        if event.get("event") == "stopped":
                            final.update(event["stats"])
            except TimeoutError:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                await proc.wait()


async def run_experiment(settings: Settings, amqp_url: str | None = None) -> dict[str, Any]:
    """Run every batch; returns the batches, radio and vehicle counters. Starts a private
    broker unless ``amqp_url`` is given (tests share their session's node)."""
    from engine.endpoints.amqp.broker import LocalBroker

    if amqp_url is not None:
        return await _with_broker(settings, amqp_url)
    broker = LocalBroker()
    try:
        return await _with_broker(settings, await asyncio.to_thread(broker.start))
    finally:
        broker.stop()


async def _with_broker(settings: Settings, amqp_url: str) -> dict[str, Any]:
    import aio_pika

    from engine.running.runtime import Engine
    from rabbitros_sim.sik_radio import SikRadioPair

    out = settings.out
    out.mkdir(parents=True, exist_ok=True)
    store = out / "robot_store.jsonl"
    store.write_bytes(b"")
    async with contextlib.AsyncExitStack() as rig:
        work = Path(rig.enter_context(tempfile.TemporaryDirectory(prefix="rabbitros-mavlink-rt-")))
        pair = rig.enter_context(SikRadioPair(str(work / "gcs"), str(work / "uav"), loss=settings.loss,
                                              seed=settings.seed))
        budget = 120 + settings.runs * sum(settings.count / settings.rate_for(size) + DRAIN_TIMEOUT + 10
                                           for size in settings.sizes)
        vehicle_stats = await rig.enter_async_context(vehicle_process(pair.link_b, store, budget, settings.window))

        routes = work / "routes"
        routes.mkdir()
        tunnel = f", tunnel: {{window: {settings.window}}}" if settings.window else ""
        (routes / "roundtrip.yaml").write_text(
            ROUTES.format(amqp_url=amqp_url, link=pair.link_a, exchange=settings.exchange, tunnel=tunnel,
                          prefetch=f", prefetch: {settings.prefetch}" if settings.prefetch else ""))
        engine = Engine(routes, REPO / "schemas")
        await engine.start()
        rig.push_async_callback(engine.stop)

        connection = await aio_pika.connect(amqp_url)
        rig.push_async_callback(connection.close)
        channel = await connection.channel()
        exchange = await channel.declare_exchange(settings.exchange, aio_pika.ExchangeType.TOPIC, durable=True)
        back = await channel.declare_queue(exclusive=True)
        await back.bind(exchange, "from_uav")
        recorder = Recorder()
        await back.consume(recorder.on_message, no_ack=True)
        await _probe(exchange, recorder)

        batches = []
        for run in range(1, settings.runs + 1):
            for size in settings.sizes:
                batches.append(await _batch(settings, exchange, recorder, store, pair, run, size))
        radio = {name: asdict(stats) for name, stats in pair.stats().items()}
        routes_status = engine.status()["routes"]
    # leaving the rig stopped the vehicle: its final counters are in vehicle_stats now
    return {"settings": _jsonable(settings), "batches": [asdict(b) | {"ok": b.ok} for b in batches],
            "radio": radio, "vehicle": vehicle_stats, "engine_routes": routes_status}


async def _probe(exchange: Any, recorder: Recorder) -> None:
    """One message must come back before the clock starts: the whole path is up."""
    import aio_pika

    deadline = time.monotonic() + PROBE_TIMEOUT
    await exchange.publish(aio_pika.Message(b'{"probe":true}', content_type="application/json"), "to_uav")
    while not recorder.probes:
        if time.monotonic() > deadline:
            raise TimeoutError("no probe came back over the radio")
        recorder.arrived.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(recorder.arrived.wait(), 1.0)


async def _batch(settings: Settings, exchange: Any, recorder: Recorder, store: Path, pair: Any,
                 run: int, size: int) -> Batch:
    import aio_pika

    originals = [make_message(run, size, seq) for seq in range(settings.count)]
    duplicates_before = recorder.duplicates
    sent_at: list[float] = []
    started = time.monotonic()
    stored_at: dict[tuple[Any, Any, Any], float] = {}
    watching = asyncio.Event()
    watcher = asyncio.create_task(_watch_store(store, (run, size), stored_at, watching))
    if settings.outage is not None:
        pair.add_outage(pair.elapsed() + settings.outage[0], settings.outage[1])
    for index, body in enumerate(originals):
        sent_at.append(time.monotonic())
        await exchange.publish(
            aio_pika.Message(body, content_type="application/json", message_id=f"r{run}-{size}-{index}"), "to_uav")
        await asyncio.sleep(max(0.0, started + (index + 1) / settings.rate_for(size) - time.monotonic()))
    wanted = {(run, size, seq) for seq in range(settings.count)}
    deadline = time.monotonic() + DRAIN_TIMEOUT
    while not wanted <= recorder.first.keys() and time.monotonic() < deadline:
        recorder.arrived.clear()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(recorder.arrived.wait(), 0.5)
    await asyncio.sleep(0.3)
    watching.set()
    await watcher
    stored = sorted(stored_at.values()) if len(stored_at) == len(originals) else None
    return _record(settings.out, run, size, originals, sent_at, store, recorder,
                   recorder.duplicates - duplicates_before,
                   (stored[-1] - sent_at[0], stored[-1] - stored[0]) if stored else None)


async def _watch_store(store: Path, batch: tuple[int, int], stored_at: dict[tuple[Any, Any, Any], float],
                       done: asyncio.Event) -> None:
    """When each message of ``batch`` (run, size) appeared in the vehicle's store, read every 20 ms."""
    rest = b""
    with open(store, "rb") as handle:
        while True:
            finished = done.is_set()
            lines = (rest + handle.read()).split(b"\n")
            rest = lines.pop()
            now = time.monotonic()
            for line in lines:
                key = _key(line)
                if key is not None and key[:2] == batch:
                    stored_at.setdefault(key, now)
            if finished:
                return
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(done.wait(), 0.02)


def _record(out: Path, run: int, size: int, originals: list[bytes], sent_at: list[float], store: Path,
            recorder: Recorder, duplicates: int, forward: tuple[float, float] | None = None) -> Batch:
    at_robot: dict[tuple[Any, Any, Any], bytes] = {}
    for line in store.read_bytes().splitlines():
        key = _key(line)
        if key is not None and key[:2] == (run, size):
            at_robot.setdefault(key, line)
    path = out / f"mavlink_roundtrip_run{run}_{size}B.csv"
    identical = back = 0
    latencies = []
    last, first = sent_at[0], None
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["seq", "original", "at_robot", "back_at_gcs", "identical"])
        for seq, original in enumerate(originals):
            robot = at_robot.get((run, size, seq), b"")
            station, arrived = recorder.first.get((run, size, seq), (b"", None))
            if arrived is not None:
                back += 1
                latencies.append((arrived - sent_at[seq]) * 1000)
                last = max(last, arrived)
                first = arrived if first is None else min(first, arrived)
            same = original == robot == station
            identical += same
            writer.writerow([seq, original.decode(), robot.decode(), station.decode(), same])
    return Batch(run, size, len(originals), len(at_robot), back, identical, duplicates, last - sent_at[0],
                 forward[0] if forward else None, None if first is None else last - first,
                 forward[1] if forward else None, latencies, str(path))


def _jsonable(settings: Settings) -> dict[str, Any]:
    return {k: str(v) if isinstance(v, Path) else v for k, v in asdict(settings).items()}


def _rate(text: str) -> float | dict[int, float]:
    """``1`` (every size) or ``50:12,150:8,250:5`` (per size)."""
    try:
        if ":" not in text:
            return float(text)
        return {int(size): float(rate) for size, rate in (item.split(":") for item in text.split(","))}
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected RATE or SIZE:RATE,..., got {text!r}") from None


def latency_by_size(batches: list[dict[str, Any]]) -> dict[int, dict[str, float]]:
    """Round-trip latency (publish -> back on AMQP) per size over all runs, in ms."""
    per_size: dict[int, list[float]] = {}
    for batch in batches:
        per_size.setdefault(batch["size"], []).extend(batch["latencies_ms"])
    return {size: {"median_ms": statistics.median(v), "max_ms": max(v), "n": len(v)}
            for size, v in per_size.items() if v}


def report(summary: dict[str, Any]) -> bool:
    """Print one line per batch, the latency per size and the link counters; True if all identical."""
    ok = True
    for row in summary["batches"]:
        ok &= row["ok"]
        print(f"run {row['run']} {row['size']:>3} B: sent {row['sent']}, at robot {row['at_robot']}, "
              f"back {row['back']}, byte-identical {row['identical']} in {row['seconds']:.1f} s  -> {row['csv']}")
    for size, figures in sorted(latency_by_size(summary["batches"]).items()):
        print(f"round trip {size:>3} B: median {figures['median_ms']:.0f} ms, max {figures['max_ms']:.0f} ms "
              f"({figures['n']} messages)")
    radio, vehicle = summary["radio"], summary["vehicle"]
    print("radio: air packets lost " + ", ".join(
        f"{name} {r['air_packets_lost']}/{r['air_packets']} ({r['air_packets_outage']} in outages), "
        f"serial overflow {r['serial_rx_dropped']} B" for name, r in radio.items()))
    print(f"vehicle: stored {vehicle.get('json_received')}, echoed {vehicle.get('json_echoed')}, "
          f"retransmissions {vehicle.get('tunnel_retransmissions')}")
    print("ALL BYTE-IDENTICAL" if ok else "MISMATCH: see the CSV files")
    return ok


def _outage(text: str) -> tuple[float, float]:
    try:
        start, duration = (float(part) for part in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected START:DURATION in seconds, got {text!r}") from None
    if start < 0 or duration <= 0:
        raise argparse.ArgumentTypeError(f"outage needs START >= 0 and DURATION > 0: {text!r}")
    return start, duration


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--rate", type=_rate, default=1.0, help="messages per second, or SIZE:RATE,... per size")
    parser.add_argument("--sizes", type=lambda s: tuple(int(x) for x in s.split(",")), default=(50, 150, 250))
    parser.add_argument("--loss", type=float, default=0.0, help="probability that an air packet is lost")
    parser.add_argument("--outage", type=_outage, default=None, metavar="START:DURATION",
                        help="an outage in every batch, START seconds after its first message")
    parser.add_argument("--seed", type=int, default=1, help="seed of the radio's loss")
    parser.add_argument("--window", type=int, default=None, help="tunnel messages in flight per direction (default: the engine's)")
    parser.add_argument("--out", type=Path, default=REPO / "results" / "mavlink_roundtrip")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    settings = Settings(runs=args.runs, count=args.count, rate=args.rate, sizes=args.sizes, loss=args.loss,
                        outage=args.outage, seed=args.seed, window=args.window, out=args.out)
    summary = asyncio.run(run_experiment(settings))
    (settings.out / "summary.json").write_text(json.dumps(summary, indent=1))
    return 0 if report(summary) else 1


if __name__ == "__main__":
    sys.exit(main())
