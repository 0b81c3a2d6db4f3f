"""orjson on the hot path keeps canonical JSON byte-identical to the standard library's.

The reference is what the engine did before orjson: ``json.dumps(sort_keys=True,
separators=(",", ":"), ensure_ascii=False, allow_nan=False)`` as UTF-8, and ``json.loads`` of
the body decoded as strict UTF-8, rejecting NaN/Infinity.
"""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from engine.common.schemas import SchemaError, SchemaRegistry, canonical_bytes, parse_json
from tests.support.repo import REPO
from tests.support.schemas import known_schema

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

SCHEMAS = REPO / "schemas"
HEADER = {"id": "0f4c2a", "type": "x", "stamp": {"sec": 1732320000, "nanosec": 123456789}}

VDA_HEADER = {"headerId": 1763917200123, "timestamp": "2026-11-23T17:00:00.123Z", "version": "2.0.0",
              "manufacturer": "rabbitros", "serialNumber": "uav1"}
# VDA 5050 2.0, the VDA's own schemas (schemas/vda5050/): what examples/vda5050 sends and receives
VDA_BODIES: dict[str, dict[str, Any]] = {
    "order": {"orderId": "spray-1", "orderUpdateId": 0, "edges": [
        {"edgeId": "e1", "sequenceId": 1, "released": True, "startNodeId": "p1", "endNodeId": "p2", "actions": []}],
        "nodes": [{"nodeId": "p1", "sequenceId": 0, "released": True, "nodePosition": {"x": 1032.6215, "y": -1e-7, "mapId": "farm"},
                   "actions": [{"actionType": "flyAt", "actionId": "f1", "blockingType": "NONE",
                                "actionParameters": [{"key": "altRel", "value": 15}]}]},
                  {"nodeId": "p2", "sequenceId": 2, "released": False, "actions": []}]},
    "instant_actions": {"actions": [{"actionType": "startPause", "actionId": "a1", "blockingType": "HARD"}]},
    "state": {"orderId": "", "orderUpdateId": 0, "lastNodeId": "", "lastNodeSequenceId": 0, "nodeStates": [],
              "edgeStates": [], "actionStates": [], "driving": False, "operatingMode": "AUTOMATIC",
              "batteryState": {"batteryCharge": 87, "charging": False, "batteryVoltage": 12.4},
              "errors": [{"errorType": "MAV_SYS_STATUS_SENSOR_GPS", "errorLevel": "FATAL", "errorReferences": []}],
              "safetyState": {"eStop": "NONE", "fieldViolation": False}},
    "connection": {"connectionState": "ONLINE"},
    "factsheet": {"typeSpecification": {"seriesName": "x500", "agvKinematic": "OMNI", "agvClass": "CARRIER",
                                        "maxLoadMass": 0.0, "localizationTypes": ["GNSS"], "navigationTypes": ["AUTONOMOUS"]},
                  "physicalParameters": {"speedMin": 0.0, "speedMax": 12.0, "accelerationMax": 3.0, "decelerationMax": 3.0,
                                         "heightMax": 120.0, "heightMin": 0.0, "width": 0.8, "length": 0.8},
                  "protocolLimits": {"maxStringLens": {}, "maxArrayLens": {},
                                     "timing": {"minOrderInterval": 1.0, "minStateInterval": 1.0}},
                  "protocolFeatures": {"optionalParameters": [{"parameter": "order.nodes.nodePosition.theta", "support": "SUPPORTED"}],
                                       "agvActions": [{"actionType": "flyAt", "actionScopes": ["NODE"],
                                                       "actionParameters": [{"key": "altRel", "valueDataType": "FLOAT"}]}]},
                  "agvGeometry": {}, "loadSpecification": {}},
    "visualization": {"agvPosition": {"x": 3.5, "y": -1.25, "theta": 1.5707963267948966, "mapId": "map",
                                      "positionInitialized": True}},
}
EXAMPLES: dict[str, list[Any]] = {
    "ack": [{**HEADER, "agent_id": "robot1", "ref_id": "m-1", "result": "accepted", "detail": "ok ✓"}],
    "attitude": [{**HEADER, "agent_id": "uav1", "quaternion": {"x": 0.0, "y": -0.0, "z": 0.7071067811865476, "w": 0.7071067811865475},
                  "roll": 1e-05, "pitch": -3.5e-07, "yaw": 179.99999999999997, "angular_velocity": [0.1, 2e-10, -1e16]}],
    "battery": [{**HEADER, "agent_id": "uav1", "voltage": 12.6, "current": None, "remaining": 0.5},
                {"agent_id": "uav1", "voltage": 0, "current": -1.25, "remaining": None}],
    "command": [{**HEADER, "agent_id": "gcs", "command": "arm", "target": "uav1",
                 "params": {"force": True, "nested": {"deep": [1, [2, [3, {"z": None, "a": "é"}]]]}}}],
    "envelope": [{"id": "1", "agent_id": "a", "type": "t", "stamp": 1732320000.25}],
    "mission": [{**HEADER, "agent_id": "robot1", "mission_id": "m-42", "task": "spray",
                 "waypoints": [{"lat": -22.000001, "lon": -47.9, "seq": 0, "action": "spray", "hold_s": 2.5},
                               {"lat": 90, "lon": -180, "seq": 18446744073709551615},
                               {"lat": -22.0, "lon": -47.9, "alt_msl": 612.5}, {"lat": -22.0, "lon": -47.9, "alt_rel": 20}]}],
    "position": [{**HEADER, "agent_id": "uav1", "lat": -22.4123456, "lon": -47.5654321, "alt_msl": 612.34,
                  "alt_rel": 35.0, "velocity_enu": [0.5, -1.25, 0.0], "heading": None},
                 {"agent_id": "robot1", "lat": 0, "lon": 1e-07, "heading": 359.99}],
    "raw_json": [{"anything": ["goes", 1, 2.5, None, True, {"日本": "語", "\u2028": "\x7f\x1f\n\t\"\\/"}]},
                 {"big": 12345678901234567890123, "neg": -0.0, "list": [1, "two", 3.0, 1e300]}],
    "status": [{**HEADER, "agent_id": "uav1", "state": "ACTIVE", "armed": False, "mode": "AUTO",
                "autopilot": "PX4", "vehicle_type": "QUADROTOR"}],
    "weed_detection": [{**HEADER, "agent_id": "uav1", "points": [{"lat": -22.0, "lon": -47.9, "p": 0.8, "species": "Amaranthus 🌱"},
                                                                  {"lat": 1.5e-5, "lon": 123.0, "p": 1}]}],
    # VDA 5050 2.0 (VDA_BODIES above)
    **{f"vda5050/{name}": [{**VDA_HEADER, **body}] for name, body in VDA_BODIES.items()},
}


def reference_bytes(data: Any) -> bytes:
    return json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode("utf-8")


def reference_parse(body: bytes) -> Any:
    def reject(name: str) -> float:
        raise ValueError(name)

    return json.loads(body.decode("utf-8"), parse_constant=reject)  # strict UTF-8 first, as the engine did


def test_every_schema_has_examples_that_validate_and_serialise_identically() -> None:
    registry = SchemaRegistry(SCHEMAS)
    assert not registry.problems
    names = {name for name in registry.names() if ".v" not in name}
    missing = sorted(names - EXAMPLES.keys())
    assert not missing, f"schemas without canonical-JSON examples in this test: {missing}"
    for name in sorted(names):
        # VDA 5050's families hold two major versions side by side, the unpinned name meaning the
        # newest (3.0); these examples are 2.0's (3.0 traffic: tests/examples/test_vda5050_v3.py)
        schema = known_schema(registry, f"{name}.v2" if name.startswith("vda5050/") else name)
        examples = json.loads(schema.path.read_text()).get("examples", []) + EXAMPLES[name]
        for example in examples:
            if name != "envelope":  # the envelope is a library of $defs, not a message type
                schema.validate(example)
            expected = reference_bytes(example)
            assert canonical_bytes(example) == expected, (name, example)
            assert parse_json(expected) == reference_parse(expected)
            assert canonical_bytes(parse_json(expected)) == expected


@pytest.mark.parametrize(
    "value",
    [
        1e-07, 1e16, 1e22, 5e-324, 1.7976931348623157e308, 0.1 + 0.2, -0.0, 1e15, 123456789.123456789,
        2**63 - 1, -(2**63), 2**64 - 1, 2**64, -(2**63) - 1, 10**40, True, False, None,
        "", "é", "\U0001f600", "\x00\x1f\x7f\u2028\u2029", "quote \" backslash \\ slash /", "\ud800x",
        {"b": 1, "a": 2, "é": 3, "z": 4, "\U0001f600": 5, "\uffff": 6, "A": 7, "": 8},
        {"n": {"m": [{"k": [[], {}, [None]]}]}}, [1, [2, [3, [4, [5]]]]], (1, 2), {1: "int key"},
        {"x": float("nan")}, {"x": [float("inf")]}, {"x": None, "y": -float("inf")},
    ],
)
def test_tricky_values_serialise_like_the_standard_library(value: Any) -> None:
    try:
        expected: Any = reference_bytes(value)
    except ValueError:
        expected = SchemaError
    if expected is SchemaError:
        with pytest.raises(SchemaError):
            canonical_bytes(value)
    else:
        assert canonical_bytes(value) == expected


@pytest.mark.parametrize(
    "body",
    [
        b"123456789012345678901234567890", b"18446744073709551616", b"-9223372036854775809", b"1e400",
        b'{"t_ns":1795000000123456789}', b"9999999999999999999", b"-9999999999999999999", b"-1000000000000000000",
        b"18446744073709551615", b"[0.12345678901234567890123]",
        b'{"a":1,"a":2}', b"\xef\xbb\xbf{}", b"[1E5, 1e-5, -0.0, 0.30000000000000004]", b'"\\ud800"',
        b'{"x": NaN}', b"[Infinity]", b"{oops}", b"\xff", b"", b" [1] ", b"[1,]", b'"\xed\xa0\x80"',
    ],
)
def test_parse_matches_the_standard_library(body: bytes) -> None:
    try:
        expected = reference_parse(body)
    except ValueError:  # including UnicodeDecodeError
        with pytest.raises(SchemaError):
            parse_json(body)
        return
    result = parse_json(body)
    assert result == expected or (isinstance(expected, float) and math.isinf(expected) and result == expected)
    assert json.dumps(result) == json.dumps(expected)  # same types (int stays int)


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=6), children, max_size=4),
    max_leaves=20,
)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(JSON_VALUES)
def test_generated_values_serialise_and_parse_like_the_standard_library(value: Any) -> None:
    try:
        expected = reference_bytes(value)
    except ValueError:  # NaN, Infinity, lone surrogates
        with pytest.raises(SchemaError):
            canonical_bytes(value)
        return
    assert canonical_bytes(value) == expected
    assert json.dumps(parse_json(expected)) == json.dumps(reference_parse(expected))


@settings(max_examples=3000, deadline=None)
@given(st.lists(st.sampled_from([b"0", b"1", b"9", b"5", b"-", b".", b'"', b"e", b" ", b"\xe9"]), max_size=60)
       .map(b"".join) | st.builds(lambda a, n, b: a + b"7" * n + b, st.binary(max_size=8), st.integers(17, 22),
                                  st.binary(max_size=8)))
def test_the_long_number_check_answers_what_its_expression_does(body: bytes) -> None:
    """``_may_hold_long_number`` searches the digits-as-zeros body instead of running
    ``_LONG_NUMBER`` (engine/common/schemas.py): the same answer for every body, bytes or bytearray."""
    from engine.common.schemas import _LONG_NUMBER, _may_hold_long_number

    assert _may_hold_long_number(body) == (_LONG_NUMBER.search(body) is not None)
    assert _may_hold_long_number(bytearray(body)) == (_LONG_NUMBER.search(body) is not None)
