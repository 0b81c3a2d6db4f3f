"""Cost of the conversion module alone: Pipeline.convert per message, no I/O.

Times decode -> JMESPath mapping -> schema validation -> canonical encoding for the routes
the throughput benches use (the GNSS position route from MAVLink fields, the weed route
from AMQP JSON, an identity raw_json route), in microseconds per message (best of 5).

    .venv/bin/python -m bench.bench_convert
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

from engine.common.schemas import SchemaRegistry
from engine.endpoints.base import Inbound, Outbound, Sink
from engine.language.routes import load_routes
from engine.language.specs import RouteSpec
from engine.running.pipeline import Pipeline

REPO = Path(__file__).resolve().parent.parent

POSITION_MAPPING = (
    "{type: 'position', agent_id: 'uav1', stamp: stamp(), time_boot_ms: time_boot_ms, "
    "lat: deg_e7_to_deg(lat), lon: deg_e7_to_deg(lon), alt_msl: mm_to_m(alt), alt_rel: mm_to_m(relative_alt), "
    "velocity_enu: ned_to_enu([cm_to_m(vx), cm_to_m(vy), cm_to_m(vz)]), heading: heading_cdeg_to_deg(hdg)}"
)
WEEDS_MAPPING = "{agent_id: agent, points: detections[].{lat: lat, lon: lon, p: confidence}}"
GLOBAL_POSITION_INT = {"time_boot_ms": 123456, "lat": -224123456, "lon": -475654321, "alt": 612340,
                       "relative_alt": 35000, "vx": 120, "vy": -35, "vz": 4, "hdg": 27000}
WEEDS_BODY = json.dumps({"agent": "uav1", "detections": [{"lat": -22.0, "lon": -47.9, "confidence": 0.8}] * 2}).encode()


ROUTES = f"""\
connections:
  bus: {{amqp: "amqp://guest:guest@127.0.0.1:5672/"}}
routes:
  - name: position
    source: {{amqp: {{connection: bus, queue: bench-position}}}}
    mapping: "{POSITION_MAPPING}"
    schema: position
    sink: {{amqp: {{connection: bus, routing_key: position}}}}
  - name: weeds
    source: {{amqp: {{connection: bus, queue: bench-weeds}}}}
    mapping: "{WEEDS_MAPPING}"
    schema: weed_detection
    sink: {{amqp: {{connection: bus, routing_key: weeds}}}}
  - name: identity
    source: {{amqp: {{connection: bus, queue: bench-identity}}}}
    schema: raw_json
    sink: {{amqp: {{connection: bus, routing_key: identity}}}}
"""


class NullSink(Sink):
    async def send(self, message: Outbound) -> None:
        return None


def pipelines(registry: SchemaRegistry) -> dict[str, Pipeline]:
    """The three routes compiled by the engine's own loader (as ``check`` and ``run`` do)."""
    with tempfile.TemporaryDirectory() as directory:
        (Path(directory) / "bench.yaml").write_text(ROUTES)
        config = load_routes(Path(directory), registry)
    out = {}
    for name, spec in config.routes.items():
        schema = registry.get(spec.schema)
        assert schema is not None
        out[name] = Pipeline.compile(spec, 1, schema, NullSink())
    return out


def per_message_us(convert: Any, make: Any, count: int = 20_000) -> float:
    best = float("inf")
    for _ in range(5):
        inbounds = [make() for _ in range(count)]
        began = time.perf_counter()
        for inbound in inbounds:
            convert(inbound)
        best = min(best, time.perf_counter() - began)
    return best / count * 1e6


def measure(count: int = 20_000) -> dict[str, float]:
    compiled = pipelines(SchemaRegistry(REPO / "schemas"))
    position, weeds, identity = compiled["position"], compiled["weeds"], compiled["identity"]
    return {
        "position_from_fields_us": per_message_us(position.convert, lambda: Inbound(fields=dict(GLOBAL_POSITION_INT)), count),
        "weeds_from_json_us": per_message_us(weeds.convert, lambda: Inbound(body=WEEDS_BODY, meta={"routing_key": "w"}), count),
        "identity_raw_json_us": per_message_us(identity.convert, lambda: Inbound(body=WEEDS_BODY), count),
    }


if __name__ == "__main__":
    for name, value in measure().items():
        print(f"{name:26} {value:7.2f} us/message")


__all__ = ["GLOBAL_POSITION_INT", "POSITION_MAPPING", "WEEDS_MAPPING", "RouteSpec", "measure"]
