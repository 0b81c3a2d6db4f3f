"""The one position route the observer benchmarks (bench_record.py, bench_foxglove.py) run:
AMQP queue -> position mapping -> AMQP, with the inputs they prefill and the status they poll."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

ROUTES = """
connections:
  bus: {{amqp: "{url}"}}
routes:
  - name: position
    source: {{amqp: {{connection: bus, queue: {queue}, prefetch: 1000}}}}
    mapping: "{{type: 'position', agent_id: agent, stamp: stamp, lat: lat, lon: lon, alt_msl: alt, id: to_string(seq)}}"
    schema: position
    sink: {{amqp: {{connection: bus, routing_key: {out}}}}}
"""


def routes_yaml(url: str, queue: str, out: str) -> str:
    return ROUTES.format(url=url, queue=queue, out=out)


def body(seq: int) -> bytes:
    return json.dumps({"seq": seq, "agent": f"uav{seq % 20}", "lat": 48.0 + seq / 1e6, "lon": 11.0, "alt": 500.0,
                       "stamp": {"sec": 1_700_000_000 + seq, "nanosec": 0}}).encode()


def status(path: Path) -> dict[str, Any]:
    """The engine's status file, or {} while it is being written."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
