"""Cost of the ops hooks on the hot path: one RouteObserver call per message.

Prints microseconds per message with no tap (the normal case), with a tap attached and read,
and with a tap whose client is stuck (buffer full), for a small and a 4 KB message, and the
ratio against the bare pipeline conversion of the same message; then the same observer on a
``position`` route, which also keeps each agent's last position for the web console's map
(engine/running/recent.py), over 100 agents.

    .venv/bin/python -m bench.bench_observer
"""

from __future__ import annotations

import asyncio
import json
import time

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Inbound
from engine.language.specs import EndpointSpec, RouteSpec
from engine.ops.route_tests import DrySink
from engine.endpoints.base import Outbound
from engine.running.observe import DELIVERED, Observers, RouteObserver, Tap
from engine.running.pipeline import Pipeline

N = 20_000


def per_message(fn, n: int = N) -> float:
    began = time.perf_counter()
    for _ in range(n):
        fn()
    return (time.perf_counter() - began) / n * 1e6


async def main() -> None:
    schemas = SchemaRegistry(__import__("pathlib").Path("schemas"))
    endpoint = EndpointSpec("amqp", "gcs", {})
    spec = RouteSpec("bench", endpoint, "{agent_id: agent, seq: seq, pad: pad}", "raw_json", endpoint, None, "x")
    schema = schemas.get("raw_json")
    assert schema is not None, "schemas/raw_json is the repository's own schema"
    pipeline = Pipeline.compile(spec, 1, schema, DrySink())
    for label, pad in (("small", ""), ("4 KB", "x" * 4000)):
        inbound = Inbound(body=json.dumps({"agent": "uav1", "seq": 1, "pad": pad}).encode())
        outbound = pipeline.convert(inbound)
        convert = per_message(lambda: pipeline.convert(inbound))
        observer = RouteObserver("bench")
        bare = per_message(lambda: observer(inbound, outbound, DELIVERED, None))
        tap = Tap("bench", size=16)
        observer.attach(tap)

        def tapped_and_read() -> None:  # a client that keeps up
            observer(inbound, outbound, DELIVERED, None)
            tap.lines.get_nowait()

        tapped = per_message(tapped_and_read)
        stuck = Tap("bench", size=1)
        observer.detach(tap)
        observer.attach(stuck)
        stuck.offer(b"x")
        full = per_message(lambda: observer(inbound, outbound, DELIVERED, None))
        print(f"{label:6} message: conversion {convert:6.2f} us; observer: no tap {bare:5.2f} us "
              f"({bare / convert:.1%} of conversion), tap {tapped:5.2f} us, stuck tap {full:5.2f} us")
    positions = [Outbound(b"{}", {"agent_id": f"uav{n}", "lat": 48.15, "lon": 11.58}, None, "m", {}) for n in range(100)]
    plain, position = Observers().get("plain"), Observers().get("position")
    position.carries("position")
    for label, observer in (("route of another schema", plain), ("position route", position)):
        turn = iter(range(1 << 62))
        cost = per_message(lambda observer=observer: observer.accepted(None, positions[next(turn) % 100], 1000), 200_000)
        print(f"a position message delivered, {label:23}: observer {cost:5.2f} us")


if __name__ == "__main__":
    asyncio.run(main())
