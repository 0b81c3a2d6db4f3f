"""``rabbitros-engine replay FILE --routes DIR --to-sinks [--speed N|max]``: recorded inputs sent on.

Where plain replay (engine/ops/replay.py) converts the recorded inputs and compares, ``--to-sinks``
converts each recorded input through its route as the routes are now (the same
:class:`~engine.running.pipeline.Pipeline`: decode, mapping, schema, ``when:``, sink mapping)
and sends the result to the route's real sink, on connections this command opens itself (as
``dead-letters replay`` does, engine/ops/dead_letter_tool.py): field data played into a test
bench, a staging broker, a simulator.

Order and pace: the inputs of every route replayed are merged by their receive time and sent in
that order. ``--speed 1`` keeps the recorded pace (each input sent when its receive time, counted
from the first one, comes round again), ``--speed 10`` ten times faster, ``--speed max`` as fast as
the sinks take them: consecutive inputs of one route then go to its sink in batches (one
confirmation round for many, as the engine itself sends). An input is sent once; a send the sink
fails is reported and not retried (a replay is not the engine: no retries, no buffer, no
dead-letter queue, no throttle, no dedupe), and the command exits 1 if any input was not sent.
A route's ``reply:`` answers are not sent anywhere: the recorded caller is gone.
"""

from __future__ import annotations

import asyncio
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import EndpointError, NotSent, Outbound
from engine.language.specs import RoutesConfig
from engine.language.stores import Stores
from engine.ops.replay import Recording, inbound_of, opened
from engine.running.connections import ConnectionPool
from engine.running.fanout import open_sinks
from engine.running.pipeline import ConversionError, Filtered, Pipeline

MAX_BATCH = 500
"""At ``--speed max``: consecutive inputs of one route sent to its sink in one batch, at most this many."""
READY_TIMEOUT_S = 10.0
"""How long a sink may take to be able to send (a ROS 2 topic's reader matching) before its route is given up."""


def parse_speed(text: str) -> float | None:
    """``max`` -> None (no pacing); else a factor above 0 (1 = the recorded pace)."""
    if text.strip().lower() == "max":
        return None
    speed = float(text)
    if not speed > 0:
        raise ValueError(f"--speed must be above 0 or max, not {text!r}")
    return speed


@dataclass
class Sent:
    sent: int = 0
    filtered: int = 0
    failed: list[str] = field(default_factory=list)
    """One line per input not sent: route, input number, why."""
    skipped: dict[str, int] = field(default_factory=dict)
    """Routes of the recording not in the routes now, and their inputs."""
    span_s: float = 0.0
    """From the first recorded input to the last, as recorded."""
    took_s: float = 0.0
    """From the first send to the last."""


@dataclass(frozen=True)
class _Input:
    at_ns: int
    route: str
    sequence: int
    envelope: dict[str, Any]


def timeline(recording: Recording, config: RoutesConfig, only: str | None, done: Sent) -> list[_Input]:
    """The inputs of the routes replayed, in the order they were received."""
    inputs: list[_Input] = []
    for name, recorded in recording.routes.items():
        if only is not None and name != only:
            continue
        if name not in config.routes:
            done.skipped[name] = len(recorded.inputs)
            continue
        inputs.extend(_Input(at_ns, name, sequence, envelope) for sequence, (at_ns, envelope) in recorded.inputs.items())
    inputs.sort(key=lambda item: (item.at_ns, item.route, item.sequence))
    if inputs:
        done.span_s = (inputs[-1].at_ns - inputs[0].at_ns) / 1e9
    return inputs


async def send_recorded(inputs: list[_Input], config: RoutesConfig, schemas: SchemaRegistry, speed: float | None,
                        done: Sent) -> None:
    pool = ConnectionPool(require_connections=True)
    stores = Stores()
    pipelines: dict[str, Pipeline] = {}
    try:
        for name in dict.fromkeys(item.route for item in inputs):
            spec = config.routes[name]
            schema = schemas.get(spec.schema)
            assert schema is not None  # the routes loaded
            reply_schema = schemas.get(spec.reply.schema) if spec.reply is not None and spec.reply.schema else None
            sink, _, _ = await open_sinks(spec, lambda end: pool.get(config.connections[end.connection], retry_in_background=False),
                                          pool.is_open, stores)  # one sink, or a route's several (sinks:)
            pipelines[name] = Pipeline.compile(spec, 0, schema, sink, reply_schema, stores)
        loop = asyncio.get_running_loop()
        started = loop.time()
        first_ns = inputs[0].at_ns if inputs else 0
        batch: list[tuple[_Input, Outbound]] = []
        for item in inputs:
            if speed is not None:
                delay = started + (item.at_ns - first_ns) / 1e9 / speed - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)  # the recorded pace: when this input comes round again
            pipeline = pipelines[item.route]
            try:
                outbound = pipeline.convert(inbound_of(item.envelope))
            except Filtered:
                done.filtered += 1
                continue
            except ConversionError as error:
                done.failed.append(f"{item.route} #{item.sequence}: {error.stage} error: {error.detail}")
                continue
            if batch and (batch[0][0].route != item.route or len(batch) >= MAX_BATCH):
                await _send(pipelines, batch, done)
                batch = []
            batch.append((item, outbound))
            if speed is not None:  # paced: each goes now, not when the next one comes
                await _send(pipelines, batch, done)
                batch = []
        if batch:
            await _send(pipelines, batch, done)
        done.took_s = loop.time() - started
    finally:
        for pipeline in pipelines.values():
            await pipeline.sink.close()
        await pool.close_all()


async def _send(pipelines: dict[str, Pipeline], batch: list[tuple[_Input, Outbound]], done: Sent) -> None:
    route = batch[0][0].route
    pipeline = pipelines[route]
    if not await _ready(pipeline):
        reason = pipeline.sink.not_ready_reason() or "the sink cannot take messages"
        done.failed.extend(f"{route} #{item.sequence}: sink: {reason}" for item, _ in batch)
        return
    results = await pipeline.sink.send_batch([outbound for _, outbound in batch])
    for (item, outbound), outcome in zip(batch, results):
        if outcome is None:
            done.sent += 1
            if pipeline.remember is not None:  # as the engine does: what a later mapping recalls
                pipeline.remember.on_converted(outbound.canonical, outbound.meta)
                pipeline.remember.on_accepted(outbound.canonical, outbound.meta)
        elif isinstance(outcome, NotSent):
            done.failed.append(f"{route} #{item.sequence}: not sent: {outcome}")
        else:
            done.failed.append(f"{route} #{item.sequence}: sink: {outcome}")


async def _ready(pipeline: Pipeline) -> bool:
    loop = asyncio.get_running_loop()
    deadline = loop.time() + READY_TIMEOUT_S
    while not pipeline.sink.ready:
        if loop.time() > deadline:
            return False
        await asyncio.sleep(0.05)
    return True


def run_replay_to_sinks(paths: list[Path], routes: Path, schemas_dir: Path | Sequence[Path], only: str | None,
                        speed: float | None) -> int:
    """The command: 0 when every recorded input of the routes replayed was sent (or filtered), 1
    when one was not, 2 when the routes are invalid or nothing was recorded."""
    opening = opened(paths, routes, schemas_dir, only)
    if opening is None:
        return 2
    recording, config, schemas = opening
    done = Sent()
    inputs = timeline(recording, config, only, done)
    try:
        asyncio.run(send_recorded(inputs, config, schemas, speed, done))
    except EndpointError as error:
        print(f"replay: {error}", file=sys.stderr)
        return 1
    for line in done.failed:
        print(f"NOT SENT  {line}")
    for name, count in sorted(done.skipped.items()):
        print(f"skipped route {name!r}: not in {routes} now ({count} recorded inputs)", file=sys.stderr)
    pace = "as fast as the sinks take them" if speed is None else f"at {speed:g}x"
    print(f"{done.sent} sent, {done.filtered} filtered, {len(done.failed)} not sent, {pace}: "
          f"{done.took_s:.3f} s for {done.span_s:.3f} s recorded")
    return 1 if done.failed else 0
