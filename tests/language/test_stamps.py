"""One canonical stamp, {sec, nanosec}: the conversions mappings use, and the schema that
accepts that form only."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from engine.common.placeholders import MappingError
from engine.common.schemas import SchemaError, SchemaRegistry
from engine.language.mapping import compile_mapping

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


def close_to_now(stamp: dict[str, int]) -> bool:
    return set(stamp) == {"sec", "nanosec"} and abs(stamp["sec"] + stamp["nanosec"] / 1e9 - time.time()) < 5


def test_to_stamp_converts_unix_seconds_and_keeps_ros_stamps():
    to_stamp = compile_mapping("to_stamp(t)")
    assert to_stamp({"t": 1.5}) == {"sec": 1, "nanosec": 500_000_000}
    assert to_stamp({"t": 1_700_000_000}) == {"sec": 1_700_000_000, "nanosec": 0}
    assert to_stamp({"t": 1_700_000_000.123456}) == {"sec": 1_700_000_000, "nanosec": 123_456_000}
    assert to_stamp({"t": {"sec": 12, "nanosec": 34}}) == {"sec": 12, "nanosec": 34}
    for bad in (-1, {"sec": 1.5, "nanosec": 0}, {"sec": 1, "nanosec": 1_000_000_000}, {"nanosec": 3}):
        with pytest.raises(MappingError):
            to_stamp({"t": bad})


def test_mavlink_times():
    usec = compile_mapping("stamp_usec(time_usec)")
    assert usec({"time_usec": 1_700_000_000_123_456}) == {"sec": 1_700_000_000, "nanosec": 123_456_000}
    assert close_to_now(usec({"time_usec": 42_000_000})), "time since boot: the reception time"
    assert close_to_now(compile_mapping("stamp_boot_ms(time_boot_ms)")({"time_boot_ms": 123456}))
    assert close_to_now(compile_mapping("stamp()")(None))
    with pytest.raises(MappingError):
        compile_mapping("stamp_boot_ms(`-5`)")(None)


def test_every_canonical_schema_takes_the_one_form(schemas_dir: Path):
    position = SchemaRegistry(schemas_dir).get("position")
    assert position is not None
    message = {"agent_id": "uav1", "lat": 1.0, "lon": 2.0}
    position.validate({**message, "stamp": {"sec": 1, "nanosec": 2}})
    for other in (1700000000.5, {"sec": 1}, {"sec": 1, "nanosec": 2, "frac": 0}):
        with pytest.raises(SchemaError, match="stamp"):
            position.validate({**message, "stamp": other})
