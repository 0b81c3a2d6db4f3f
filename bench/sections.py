"""The sections of ``python -m bench`` besides the throughput drains: the paper's latency
method, throughput against message size, many routes, and JSON over the emulated SiK radio."""

from __future__ import annotations

import asyncio
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

from bench import throughput as tp

REPO = Path(__file__).resolve().parent.parent


# ---------------------------------------------------------------- 1. the paper's latency method

async def paper_latency(url: str, rate: float, runs: int, count: int) -> dict[str, Any]:
    """CT-L1 (AMQP -> ROS 2) and CT-L2 (ROS 2 -> AMQP) as in the paper: t2 - t1 inside the
    engine, 50/150/250 B, ``runs`` x ``count`` messages at ``rate``; confirms off (the paper's
    configuration) and on."""
    from bench.bench_latency import scenario

    out: dict[str, Any] = {"rate": rate, "runs": runs, "count": count}
    for confirms in (False, True):
        parts: dict[str, dict[int, dict[str, list[float]]]] = {}
        results = await scenario(url, confirms, runs, count, rate, parts)
        setting = "confirms_on" if confirms else "confirms_off"
        out[setting] = {
            name: {str(size): {**tp.summary(samples), "samples": samples} for size, samples in sizes.items()}
            for name, sizes in results.items()
        }
        out[f"{setting}_parts"] = {
            name: {str(size): {part: tp.summary(samples) for part, samples in alone.items()} for size, alone in sizes.items()}
            for name, sizes in parts.items()
        }
    return out


# ---------------------------------------------------------------- throughput against message size

async def throughput_by_size(broker: tp.Broker, sizes: list[int], count: int) -> list[dict[str, Any]]:
    """An identity raw_json route (no mapping) against the aiormq pass-through, per body size."""
    from bench.roundtrip_ros2 import make_message

    rows = []
    for size in sizes:
        row: dict[str, Any] = {"size": size}
        for system in ("ref-amqp-amqp", "engine"):
            result = await tp.drain_amqp_source(broker, "amqp-amqp", system, count, tp.domain_id(),
                                                body=lambda i, size=size: make_message(1, size, i),
                                                schema="raw_json", mapping=None)
            row[system] = result
        row["ratio"] = row["engine"]["msg_per_s"] / row["ref-amqp-amqp"]["msg_per_s"]
        rows.append(row)
    return rows


# ---------------------------------------------------------------- many routes

def scale_routes(directory: Path, url: str, routes: int, tag: str, exchange: str) -> None:
    lines = ["connections:", f"  gcs: {{amqp: {{url: \"{url}\"}}}}", "routes:"]
    for index in range(routes):
        lines += [
            f"  - name: r{index}",
            f"    source: {{amqp: {{queue: scale-{tag}-{index}, prefetch: 1000}}}}",
            f"    mapping: \"{tp.GNSS_MAPPING}\"",
            "    schema: position",
            f"    sink: {{amqp: {{exchange: {exchange}, routing_key: \"canonical.position.{{agent_id}}\"}}}}",
        ]
    (directory / "routes.yaml").write_text("\n".join(lines) + "\n")


async def many_routes(broker: tp.Broker, counts: list[int], messages: int) -> list[dict[str, Any]]:
    """For 1, 100, 1,000 routes: ``check`` (parse, validate, compile every route, in process),
    load (engine start: connections, queues, consumers), the same load again once the queues
    exist (a restart), RSS after load, and the per-message cost of draining ``messages``
    through one route while all are loaded."""
    from engine.common.schemas import SchemaRegistry
    from engine.language.routes import load_routes

    rows = []
    for routes in [1, *counts]:  # the first, not reported, warms the broker up
        tag = uuid.uuid4().hex[:6]
        names = await broker.topology(tag)
        with tempfile.TemporaryDirectory() as work:
            scale_routes(Path(work), broker.url, routes, tag, names["exchange"])
            began = time.perf_counter()
            config = load_routes(Path(work), SchemaRegistry(REPO / "schemas"))
            check_s = time.perf_counter() - began
            assert len(config.routes) == routes
            # the last route: its source starts last, so its queue is still full when loading ends
            first = f"scale-{tag}-{routes - 1}"
            await broker.channel.queue_declare(first, durable=True)
            await broker.prefill(first, [tp.gnss_json(i) for i in range(messages)])
            engine = tp.Child("engine", {"routes": work})
            try:
                started = await engine.wait_for("started", timeout=300)
                await engine.wait_for("ready", timeout=60)
                _, load_s, rss_kib = started.split()
                cpu_before = engine.cpu_seconds()
                drained = await tp.observe_source(broker, first, messages)
                drain_cpu_s = engine.cpu_seconds() - cpu_before
                arrived = await tp.observe(lambda: broker.count(names["sink"]), messages)
            finally:
                await engine.stop(timeout=60)
            # a restart: the queues exist now, so this load is the engine's (and the broker's
            # channel and consumer set-up) without creating durable queues
            engine = tp.Child("engine", {"routes": work})
            try:
                restarted = await engine.wait_for("started", timeout=300)
                await engine.wait_for("ready", timeout=60)
            finally:
                await engine.stop(timeout=60)
            for index in range(routes):
                await broker.channel.queue_delete(f"scale-{tag}-{index}")
        await broker.drop(names)
        rows.append({"routes": routes, "check_s": check_s, "load_s": float(load_s),
                     "reload_existing_queues_s": float(restarted.split()[1]), "rss_mib": int(rss_kib) / 1024,
                     "msg_per_s": drained["msg_per_s"], "us_per_msg": 1e6 / drained["msg_per_s"],
                     "cpu_us_per_msg": drain_cpu_s * 1e6 / messages, "lost": arrived["lost"]})
    rows = rows[1:]
    base, base_cpu = rows[0]["us_per_msg"], rows[0]["cpu_us_per_msg"]
    for row in rows:
        row["cost_vs_one_route"] = row["us_per_msg"] / base
        row["cpu_vs_one_route"] = row["cpu_us_per_msg"] / base_cpu if base_cpu else None
    return rows


# ---------------------------------------------------------------- JSON over the emulated SiK radio

def link_payload_capacity() -> dict[str, float]:
    """TUNNEL payload bytes/s one direction of the emulated radio can carry at best.

    From the emulator's constants (rabbitros_sim.sik_radio): each radio owns TX_WINDOW_S of every
    TDM_ROUND_S; an air packet of n bytes (at most MAX_AIR_PACKET) takes PACKET_OVERHEAD_S +
    n * AIR_BYTE_S and must end inside the window; MAVLink frames are packed whole. A TUNNEL
    frame is 12 bytes of MAVLink 2 framing + 5 of TUNNEL fields + p payload bytes (p <= 128).
    The best p and frames per packet give the capacity; the serial side (57,600 baud) is the
    other bound."""
    from rabbitros_sim import sik_radio as radio

    best = (0.0, 0, 0)
    for payload in range(1, 129):
        frame = 12 + 5 + payload
        for per_packet in range(1, radio.MAX_AIR_PACKET // frame + 1):
            size = per_packet * frame
            left, carried = radio.TX_WINDOW_S, 0
            while left >= radio.PACKET_OVERHEAD_S + size * radio.AIR_BYTE_S:
                left -= radio.PACKET_OVERHEAD_S + size * radio.AIR_BYTE_S
                carried += per_packet * payload
            air = carried / radio.TDM_ROUND_S
            serial = radio.SERIAL_BYTES_PER_S * payload / frame
            if min(air, serial) > best[0]:
                best = (min(air, serial), payload, per_packet)
    return {"payload_bytes_per_s": best[0], "tunnel_payload": best[1], "frames_per_packet": best[2]}


def flood_capacity(payload: int, seconds: float = 10.0, warmup: float = 1.0, *,
                   telemetry: bool = False, loss: float = 0.0) -> float:
    """The reference: TUNNEL payload bytes/s one direction of the emulated radio carried in this
    run when flooded with frames of ``payload`` bytes, its buffer kept backlogged (so every air
    packet is as full as the frames allow) but never overflowing. With ``telemetry``, the
    simulated vehicle's streams (4 Hz position and attitude, 1 Hz heartbeat and status, as on
    the round trip's way back) share the link.

    The constants' figure (:func:`link_payload_capacity`) assumes each air packet starts the
    instant the window opens or the previous packet ends; the emulator starts it at its next
    tick (4 ms, later on a loaded machine), often too late for the third full packet."""
    import os
    import select

    from rabbitros_sim.sik_radio import SikRadioPair
    from rabbitros_sim.vehicle import mavlink2, open_serial
    from rabbitros_sim.vehicle import telemetry as streams

    backlog = 1700  # bytes written but not yet on the air: below the radio's 2,048-byte buffer with a burst of telemetry and a frame on top
    mav = mavlink2.MAVLink(None, 1, 1)
    parser = mavlink2.MAVLink(None)
    parser.robust_parsing = True
    frame = mavlink2.MAVLink_tunnel_message(255, 190, 0xA900, payload, [0xA5] * payload + [0] * (128 - payload))

    def pack(msg: Any) -> bytes:
        data: bytes = msg.pack(mav)
        mav.seq = (mav.seq + 1) % 256
        return data

    with SikRadioPair(radio_status_interval=None, loss=loss, seed=1) as pair:
        tx, rx = open_serial(pair.link_a), open_serial(pair.link_b)
        try:
            written, carried, start, ticks = 0, 0, time.monotonic(), 0
            while (now := time.monotonic()) < start + warmup + seconds:
                while telemetry and now >= start + ticks * 0.25:
                    written += sum(os.write(tx, pack(m)) for m in streams(ticks * 250, ticks % 4 == 0))
                    ticks += 1
                while written - pair.stats()["a"].air_bytes < backlog:
                    written += os.write(tx, pack(frame))
                if select.select([rx], [], [], 0.005)[0]:
                    for msg in parser.parse_buffer(os.read(rx, 4096)) or ():
                        if msg.get_type() == "TUNNEL" and now >= start + warmup:
                            carried += msg.payload_length
            assert pair.stats()["a"].serial_rx_dropped == 0, "the flood overflowed the radio's buffer"
        finally:
            os.close(tx)
            os.close(rx)
    return carried / seconds


async def sik_goodput(url: str, count: int, size: int, loss: float = 0.0) -> dict[str, Any]:
    """The paper's MAVLink round trip (engine -> JSON tunnel -> radio -> vehicle and back) driven
    faster than the radio carries; goodput = JSON bytes per second each way, from the first
    publish to the last message back, at ``loss``; against the constants' capacity and the
    flood reference measured in the same run at the same loss (:func:`flood_capacity`).
    The way back shares the radio with the vehicle's telemetry, so the round trip is bounded
    by the flood *with* telemetry; the way there alone (``forward_*``: the first publish to
    the last message stored by the vehicle) compares with the plain flood."""
    from bench.roundtrip_mavlink import Settings, run_experiment

    capacity = link_payload_capacity()
    payload = int(capacity["tunnel_payload"])
    flood = {"flood_payload_bytes_per_s": await asyncio.to_thread(flood_capacity, payload, loss=loss),
             "flood_with_telemetry_bytes_per_s": await asyncio.to_thread(flood_capacity, payload, telemetry=True, loss=loss)}
    with tempfile.TemporaryDirectory() as work:
        settings = Settings(runs=1, count=count, rate=40.0, sizes=(size,), loss=loss, out=Path(work),
                            exchange=f"goodput-{uuid.uuid4().hex[:6]}")
        summary = await run_experiment(settings, amqp_url=url)
    batch = summary["batches"][0]
    goodput = batch["identical"] * size / batch["seconds"]
    forward = batch["at_robot"] * size / batch["forward_seconds"] if batch.get("forward_seconds") else None
    return {"size": size, "loss": loss, "sent": batch["sent"], "identical": batch["identical"], "seconds": batch["seconds"],
            "goodput_bytes_per_s": goodput, **capacity, **flood,
            "fraction_of_capacity": goodput / capacity["payload_bytes_per_s"],
            "fraction_of_flood": goodput / flood["flood_payload_bytes_per_s"],
            "fraction_of_flood_with_telemetry": goodput / flood["flood_with_telemetry_bytes_per_s"],
            "forward_seconds": batch.get("forward_seconds"), "forward_goodput_bytes_per_s": forward,
            "forward_fraction_of_flood": forward / flood["flood_payload_bytes_per_s"] if forward else None,
            "radio": summary.get("radio"), "vehicle": summary.get("vehicle")}


__all__ = ["asyncio", "flood_capacity", "link_payload_capacity", "many_routes", "paper_latency", "sik_goodput", "throughput_by_size"]
