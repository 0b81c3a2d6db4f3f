"""A steady stream through the engine while its route files are rewritten, for the hot-reload
test and its benchmark. Every message carries a sequence number; every mapping stamps the
generation that wrote it, so the consumer can tell which configuration converted each copy."""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import aio_pika

from tests.engine_process import EngineProcess

ROUTE = """
routes:
  - name: stream
    source:
      amqp: {{exchange: {inbox}, binding_key: "s.#", queue: {queue}, prefetch: {prefetch}}}
    mapping: "{{seq: seq, agent_id: agent, gen: `{gen}`}}"
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "out.{{agent_id}}"}}
"""
EXTRA = """
routes:
  - name: extra
    source:
      amqp: {{exchange: {inbox}, binding_key: "x.#", queue: {queue}-extra}}
    schema: raw_json
    sink:
      amqp: {{exchange: {outbox}, routing_key: "extra"}}
"""
INVALID = ROUTE.replace("mapping: \"{{seq: seq", "mapping: \"{{seq: seq(")


@dataclass
class ReloadRun:
    sent: int = 0
    copies: dict[int, list[int]] = field(default_factory=dict)
    latencies: list[float] = field(default_factory=list)
    written_generations: list[int] = field(default_factory=list)
    rejected_reported: bool = False
    status: dict[str, Any] = field(default_factory=dict)

    @property
    def duplicates(self) -> int:
        return sum(len(gens) - 1 for gens in self.copies.values())

    def summary(self) -> str:
        lat = sorted(self.latencies)
        return (
            f"sent={self.sent} received_unique={len(self.copies)} duplicates={self.duplicates} "
            f"rewrites={len(self.written_generations)} save_to_live_ms median={statistics.median(lat) * 1e3:.0f} "
            f"max={max(lat) * 1e3:.0f}"
        )


def _write(path: Path, text: str, atomic: bool) -> None:
    if atomic:
        temporary = path.with_name(f".{path.name}.{uuid.uuid4().hex[:6]}.tmp")
        temporary.write_text(text)
        os.replace(temporary, path)
    else:
        path.write_text(text)


async def run_reloads(
    amqp_url: str, workdir: Path, rewrites: int = 50, rate: float = 500.0, interval: float = 0.25,
    extra_routes: Callable[[dict[str, str]], str] | None = None,
) -> ReloadRun:
    tag = uuid.uuid4().hex[:8]
    names = {"inbox": f"in-{tag}", "outbox": f"out-{tag}", "queue": f"q-{tag}"}
    routes = workdir / "routes"
    routes.mkdir()
    farm = routes / "farm.yaml"
    farm.write_text(ROUTE.format(gen=0, prefetch=256, **names))
    run = ReloadRun()
    engine = EngineProcess(routes, workdir / "status.json", {"RABBITROS_AMQP_URL": amqp_url})
    connection = await aio_pika.connect(amqp_url)
    try:
        await asyncio.to_thread(engine.wait_started)
        channel = await connection.channel()
        inbox = await channel.declare_exchange(names["inbox"], aio_pika.ExchangeType.TOPIC, durable=True)
        outbox = await channel.declare_exchange(names["outbox"], aio_pika.ExchangeType.TOPIC, durable=True)
        collect = await channel.declare_queue(f"collect-{tag}", exclusive=True)
        await collect.bind(outbox, "out.#")
        first_seen: dict[int, float] = {}

        async def on_message(message: aio_pika.abc.AbstractIncomingMessage) -> None:
            body = json.loads(message.body)
            run.copies.setdefault(body["seq"], []).append(body["gen"])
            first_seen.setdefault(body["gen"], time.monotonic())

        await collect.consume(on_message, no_ack=True)
        stop_publishing = asyncio.Event()

        async def publisher() -> None:
            batch, started = 10, time.monotonic()
            while not stop_publishing.is_set():
                for _ in range(batch):
                    body = json.dumps({"seq": run.sent, "agent": f"a{run.sent % 4}"}).encode()
                    await inbox.publish(aio_pika.Message(body), "s.x")
                    run.sent += 1
                await asyncio.sleep(max(0.0, started + run.sent / rate - time.monotonic()))

        publishing = asyncio.create_task(publisher())
        written_at: dict[int, float] = {}
        for gen in range(1, rewrites + 1):
            await asyncio.sleep(interval)
            prefetch = 256 if gen % 7 else 128
            text = ROUTE.format(gen=gen, prefetch=prefetch, **names)
            if gen % 10 == 3:
                (routes / "extra.yaml").write_text(EXTRA.format(**names))
            if gen % 10 == 6:
                (routes / "extra.yaml").unlink()
            if gen % 10 == 8:
                before = (engine.status() or {}).get("reloads", {}).get("rejected", 0)
                _write(farm, INVALID.format(gen=gen, prefetch=prefetch, **names), atomic=False)
                deadline = time.monotonic() + 10
                while time.monotonic() < deadline:
                    await asyncio.sleep(0.1)
                    status = engine.status() or {}
                    if status.get("reloads", {}).get("rejected", 0) > before:
                        run.rejected_reported = any("farm.yaml:" in p for p in status["reloads"]["last_error"])
                        break
            _write(farm, text, atomic=gen % 2 == 0)
            written_at[gen] = time.monotonic()
            run.written_generations.append(gen)
        await asyncio.sleep(1.0)
        stop_publishing.set()
        await publishing
        deadline = time.monotonic() + 30
        while len(run.copies) < run.sent and time.monotonic() < deadline:
            await asyncio.sleep(0.2)
        await asyncio.sleep(0.5)
        run.latencies = [first_seen[g] - written_at[g] for g in written_at if g in first_seen]
        run.status = engine.status() or {}
    finally:
        await connection.close()
        engine.stop()
    return run
