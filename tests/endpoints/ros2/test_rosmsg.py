"""ROS message <-> dict conversion (rosbridge conventions) on real generated message classes.

Every message built by from_dict is also pushed through rclpy's CDR serializer, because the
converter writes slots directly and a wrongly typed slot only shows up in C.
"""

from __future__ import annotations

import base64
import json
import math
import re
import struct
import time
from typing import Any

import pytest

import rclpy  # noqa: F401,E402  (a missing rclpy fails the run, never skips it)

from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from engine.endpoints.ros2.rosmsg import (  # noqa: E402
    MessageError, NullValue, field_names, from_dict, null_path, nested_type, resolve_type, to_dict, type_name,
)

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

String = resolve_type("std_msgs/msg/String")
NavSatFix = resolve_type("sensor_msgs/msg/NavSatFix")
PoseArray = resolve_type("geometry_msgs/msg/PoseArray")
Path = resolve_type("nav_msgs/msg/Path")
Image = resolve_type("sensor_msgs/msg/Image")


def cdr_round_trip(msg):
    return deserialize_message(serialize_message(msg), type(msg))


def via_json(data):
    return json.loads(json.dumps(data, allow_nan=False))


def test_resolve_accepts_both_name_forms_and_names_missing_types():
    assert resolve_type("std_msgs/String") is resolve_type("std_msgs/msg/String") is String
    assert type_name(NavSatFix) == "sensor_msgs/msg/NavSatFix"
    with pytest.raises(MessageError, match=r"^type 'foo_msgs/msg/Bar' is not installed$"):
        resolve_type("foo_msgs/msg/Bar")
    with pytest.raises(MessageError, match="is not installed"):
        resolve_type("std_msgs/msg/NoSuchType")
    with pytest.raises(MessageError, match="not of the form"):
        resolve_type("std_msgs/srv/Empty")


def test_field_names_and_nested_type():
    assert field_names(PoseArray) == ("header", "poses")
    assert nested_type(NavSatFix, "status") is resolve_type("sensor_msgs/NavSatStatus")
    assert nested_type(NavSatFix, "latitude") is None


def test_string_round_trip():
    msg = from_dict(String, {"data": '{"agent_id": "uav1", "x": "ção ✓"}'})
    assert cdr_round_trip(msg).data == '{"agent_id": "uav1", "x": "ção ✓"}'
    assert to_dict(msg) == {"data": '{"agent_id": "uav1", "x": "ção ✓"}'}


def test_navsatfix_nonfinite_become_null_and_output_is_strict_json():
    fix = NavSatFix(latitude=-22.0, longitude=float("inf"), altitude=float("nan"))
    fix.position_covariance[4] = float("-inf")
    data = to_dict(fix)
    assert data["longitude"] is None and data["altitude"] is None
    assert data["position_covariance"][4] is None and data["position_covariance"][0] == 0.0
    assert data["status"] == {"status": fix.status.status, "service": 0}
    json.dumps(data, allow_nan=False)
    back = from_dict(NavSatFix, via_json(data))  # null reads back as NaN
    assert math.isnan(back.altitude) and math.isnan(back.position_covariance[4])


DOUBLES = [0.1, 1 / 3, -22.123456789012345, 5e-324, 1.7976931348623157e308, 2.0**53 + 2, -0.0,
           47.92816473829401]


@pytest.mark.parametrize("value", DOUBLES)
def test_doubles_round_trip_bit_exact(value):
    fix = NavSatFix(latitude=value, longitude=value, altitude=value)
    fix.position_covariance[8] = value
    back = cdr_round_trip(from_dict(NavSatFix, via_json(to_dict(cdr_round_trip(fix)))))
    bits = struct.pack("<d", value)
    assert struct.pack("<d", back.latitude) == bits
    assert struct.pack("<d", back.position_covariance[8]) == bits


def test_pose_array_nested_objects_and_int_to_float():
    data = {"header": {"frame_id": "map", "stamp": {"sec": 12, "nanosec": 34}},
            "poses": [{"position": {"x": 1, "y": 2.5}}, {"orientation": {"w": 0.5}}]}
    msg = cdr_round_trip(from_dict(PoseArray, data))
    out = to_dict(msg)
    assert out["header"] == {"stamp": {"sec": 12, "nanosec": 34}, "frame_id": "map"}
    assert out["poses"][0]["position"] == {"x": 1.0, "y": 2.5, "z": 0.0}
    assert isinstance(out["poses"][0]["position"]["x"], float)
    assert out["poses"][0]["orientation"] == {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}  # default kept
    assert out["poses"][1]["orientation"]["w"] == 0.5


def test_path_headers_stamped_now_when_absent_or_zero():
    before = time.time()
    msg = cdr_round_trip(from_dict(Path, {
        "poses": [
            {"pose": {"position": {"x": 1.0}}},                                   # header absent
            {"header": {"frame_id": "odom"}},                                      # stamp absent
            {"header": {"stamp": {"sec": 0, "nanosec": 0}}},                       # stamp zero
            {"header": {"stamp": {"sec": 100, "nanosec": 5}, "frame_id": "m"}},    # kept
            {"header": {"stamp": {"secs": 7, "nsecs": 8}}},                        # rosbridge aliases
        ],
    }))
    after = time.time()

    def seconds(header):
        return header.stamp.sec + header.stamp.nanosec / 1e9

    assert before - 1 <= seconds(msg.header) <= after + 1
    for pose in msg.poses[:3]:
        assert before - 1 <= seconds(pose.header) <= after + 1
    assert msg.poses[1].header.frame_id == "odom"
    assert (msg.poses[3].header.stamp.sec, msg.poses[3].header.stamp.nanosec) == (100, 5)
    assert (msg.poses[4].header.stamp.sec, msg.poses[4].header.stamp.nanosec) == (7, 8)
    assert to_dict(msg)["poses"][3]["header"] == {"stamp": {"sec": 100, "nanosec": 5}, "frame_id": "m"}


def test_byte_arrays_are_base64():
    image = Image(height=1, width=4, encoding="mono8", step=4, data=[0, 1, 254, 255])
    assert to_dict(image)["data"] == "AAH+/w=="
    back = cdr_round_trip(from_dict(Image, {"data": "AAH+/w==", "height": 1}))
    assert bytes(back.data) == b"\x00\x01\xfe\xff"
    assert bytes(from_dict(Image, {"data": [0, 1, 254, 255]}).data) == b"\x00\x01\xfe\xff"

    uuid_cls = resolve_type("unique_identifier_msgs/msg/UUID")  # fixed uint8[16]
    uuid = cdr_round_trip(from_dict(uuid_cls, {"uuid": "AAECAwQFBgcICQoLDA0ODw=="}))
    assert bytes(uuid.uuid) == bytes(range(16))
    assert to_dict(uuid) == {"uuid": "AAECAwQFBgcICQoLDA0ODw=="}

    octets_cls = resolve_type("std_msgs/msg/ByteMultiArray")  # byte[]: a list, as rosbridge gives it
    octets = cdr_round_trip(from_dict(octets_cls, {"data": "AP8="}))
    assert to_dict(octets)["data"] == [0, 255]
    assert to_dict(cdr_round_trip(from_dict(octets_cls, {"data": [0, 255]})))["data"] == [0, 255]

    with pytest.raises(MessageError, match="base64") as err:
        from_dict(Image, {"data": "not base64!"})
    assert err.value.field == "data"
    with pytest.raises(MessageError, match="16 items"):
        from_dict(uuid_cls, {"uuid": "AAE="})


TEST_MSGS = ("Arrays", "BasicTypes", "BoundedPlainSequences", "BoundedSequences", "Builtins", "Constants",
             "Defaults", "Empty", "MultiNested", "Nested", "Strings", "UnboundedSequences", "WStrings")


def rosbridge_base64(field_type: str) -> bool:
    """rosbridge_library message_conversion.py's rule, read from the type string rclpy gives
    (``get_fields_and_field_types``): after rewriting ``uint8[N]`` / ``char[N]`` to ``[]``,
    base64 iff the type is ``uint8[]``, ``char[]``, ``sequence<uint8>`` or ``sequence<char>``.
    A ``.msg`` ``char`` is an IDL ``uint8``; ``byte`` is ``octet``, never base64."""
    for binary, bracketed in (("uint8[]", r"uint8\[[^\]]*\]"), ("char[]", r"char\[[^\]]*\]")):
        if re.sub(bracketed, binary, field_type) in ("uint8[]", "char[]", "sequence<uint8>", "sequence<char>"):
            return True
    return False


def byte_kinds(cls: Any, prefix: str = "") -> list[tuple[str, str]]:  # a generated message class
    """(path, type string) of every uint8/octet array or sequence in ``cls``, nested included."""
    found = []
    for name, kind in cls.get_fields_and_field_types().items():
        nested = nested_type(cls, name)
        if nested is not None:
            found += byte_kinds(nested, f"{prefix}{name}.")
        elif re.match(r"^(sequence<(uint8|octet)(, \d+)?>|(uint8|octet)\[\d*\])$", kind):
            found.append((prefix + name, kind))
    return found


def at(data: dict, path: str):
    for key in path.split("."):
        data = data[key]
    return data


@pytest.mark.parametrize("name", TEST_MSGS)
def test_byte_fields_are_what_rosbridge_gives(name):
    """Every uint8/char/byte array or sequence of test_msgs (fixed, bounded, unbounded), with
    its non-trivial defaults: base64 exactly where rosbridge base64-encodes, else a list of
    ints; and either form reads back to the same message."""
    cls = resolve_type(f"test_msgs/msg/{name}")
    msg = cls()
    data = to_dict(msg)
    for path, kind in byte_kinds(cls):
        value = at(data, path)
        raw = bytes(bytearray(ord(b) if isinstance(b, bytes) else b for b in at_msg(msg, path)))
        if rosbridge_base64(kind):
            assert value == base64.b64encode(raw).decode(), (path, kind, value)
        else:
            assert value == list(raw), (path, kind, value)
    assert to_dict(cdr_round_trip(from_dict(cls, via_json(data)))) == data


def at_msg(msg, path: str):
    for key in path.split("."):
        msg = getattr(msg, key)
    return msg


def test_the_byte_rule_covers_every_kind():
    """The test messages hold all six kinds, so the parametrized test is not vacuous."""
    kinds = {kind for name in TEST_MSGS for _, kind in byte_kinds(resolve_type(f"test_msgs/msg/{name}"))}
    assert {"uint8[3]", "sequence<uint8>", "sequence<uint8, 3>", "octet[3]", "sequence<octet>",
            "sequence<octet, 3>"} <= kinds
    bounded = resolve_type("test_msgs/msg/BoundedSequences")
    assert to_dict(bounded())["char_values_default"] == [0, 1, 127]
    assert to_dict(bounded())["uint8_values_default"] == [0, 1, 255]
    assert to_dict(resolve_type("test_msgs/msg/Arrays")())["char_values_default"] == "AAF/"
    assert to_dict(resolve_type("test_msgs/msg/UnboundedSequences")())["byte_values_default"] == [0, 1, 255]


def test_time_now_is_accepted_as_rosbridge_does():
    """rosbridge reads the string "now" for a builtin_interfaces/Time as the clock now (not
    for a Duration)."""
    Builtins = resolve_type("test_msgs/msg/Builtins")
    before = time.time()
    msg = cdr_round_trip(from_dict(Builtins, {"time_value": "now", "duration_value": {"sec": 2}}))
    assert before - 1 <= msg.time_value.sec + msg.time_value.nanosec / 1e9 <= time.time() + 1
    assert msg.duration_value.sec == 2
    header = from_dict(PoseArray, {"header": {"stamp": "now", "frame_id": "map"}}).header
    assert header.frame_id == "map" and abs(header.stamp.sec - before) <= 2
    assert from_dict(Builtins, {"time_value": "now"}, null_as_nan=False).time_value.sec > 0
    with pytest.raises(MessageError, match="expected an object") as err:
        from_dict(Builtins, {"duration_value": "now"})
    assert err.value.field == "duration_value"
    with pytest.raises(MessageError, match="expected an object"):
        from_dict(Builtins, {"time_value": "later"})


def test_a_null_from_a_sink_mapping_is_refused_wherever_it_is():
    """null_as_nan=False (a sink mapping's output): no null becomes NaN or a default; the
    error names the field. Fields left out keep their defaults."""
    Odometry = resolve_type("nav_msgs/msg/Odometry")
    UnboundedSequences = resolve_type("test_msgs/msg/UnboundedSequences")
    cases: list[tuple[Any, dict[str, Any], str]] = [
        (Odometry, {"pose": {"pose": {"position": {"x": None}}}}, "pose.pose.position.x"),
        (Odometry, {"pose": None}, "pose"),
        (Odometry, {"header": {"frame_id": None}}, "header.frame_id"),
        (NavSatFix, {"position_covariance": [0.0, None] + [0.0] * 7}, "position_covariance[1]"),
        (NavSatFix, {"status": {"status": None}}, "status.status"),
        (UnboundedSequences, {"int32_values": [1, None]}, "int32_values[1]"),
        (UnboundedSequences, {"string_values": ["a", None]}, "string_values[1]"),
        (UnboundedSequences, {"uint8_values": [1, None]}, "uint8_values[1]"),
        (UnboundedSequences, {"bool_values": None}, "bool_values"),
        (PoseArray, {"poses": [{}, None]}, "poses[1]"),
    ]
    for cls, data, field in cases:
        with pytest.raises(NullValue) as err:
            from_dict(cls, data, null_as_nan=False)
        assert err.value.field == field, (data, err.value.field)
        assert str(err.value).startswith(f"field {field}: null (the sink mapping gave no value")
        assert null_path(data) == err.value.path  # what the pipeline refuses before the sink
    assert null_path({"pose": {"pose": {"position": {"x": 1.5}}}, "poses": [{}, [1, "a"]]}) is None
    odometry = cdr_round_trip(from_dict(Odometry, {"pose": {"pose": {"position": {"x": 1.5}}}}, null_as_nan=False))
    assert (odometry.pose.pose.position.x, odometry.pose.pose.orientation.w, odometry.twist.twist.linear.x) == (1.5, 1.0, 0.0)
    assert math.isnan(from_dict(NavSatFix, {"altitude": math.nan}, null_as_nan=False).altitude)  # nan() said so
    assert math.isnan(from_dict(NavSatFix, {"altitude": None}).altitude)  # the canonical round trip


def test_unknown_field_rejected_with_its_path():
    data = {"poses": [{}, {}, {"position": {"x": 1.0, "w": 2.0}}]}
    with pytest.raises(MessageError) as err:
        from_dict(PoseArray, data)
    assert err.value.field == "poses[2].position.w"
    assert "poses[2].position.w" in str(err.value) and "unknown field" in str(err.value)
    with pytest.raises(MessageError) as err:
        from_dict(PoseArray, {"header": {"stamp": {"sec": 1, "nanosecs": 2}}})
    assert err.value.field == "header.stamp.nanosecs"


def test_missing_fields_defaulted():
    fix = cdr_round_trip(from_dict(NavSatFix, {"latitude": 1.5}))
    assert (fix.latitude, fix.longitude, fix.position_covariance_type) == (1.5, 0.0, 0)
    assert list(fix.position_covariance) == [0.0] * 9
    assert fix.status.status == NavSatFix().status.status
    assert cdr_round_trip(from_dict(PoseArray, {})).poses == []


@pytest.mark.parametrize("data, field, reason", [
    ({"latitude": "1.0"}, "latitude", "expected double, got str"),
    ({"latitude": True}, "latitude", "expected double, got bool"),
    ({"position_covariance_type": 1.0}, "position_covariance_type", "expected uint8, got float"),
    ({"position_covariance_type": 256}, "position_covariance_type", "out of range for uint8"),
    ({"status": {"status": 200}}, "status.status", "out of range for int8"),
    ({"status": 3}, "status", "expected an object"),
    ({"header": {"frame_id": 7}}, "header.frame_id", "expected string, got int"),
    ({"position_covariance": [0.0] * 8}, "position_covariance", "expected 9 items"),
    ({"position_covariance": [0.0] * 8 + ["x"]}, "position_covariance[8]", "expected double, got str"),
])
def test_wrong_value_types_name_the_field(data, field, reason):
    with pytest.raises(MessageError) as err:
        from_dict(NavSatFix, data)
    assert err.value.field == field
    assert reason in str(err.value)


def test_top_level_must_be_an_object():
    with pytest.raises(MessageError, match="expected an object"):
        not_an_object: Any = [1, 2]  # the wrong kind of input under test
        from_dict(NavSatFix, not_an_object)


def test_conversion_is_fast_enough_for_10k_per_second():
    """Loose bound (25x the measured cost) so a slow shared machine does not fail it."""
    fix = NavSatFix(latitude=1.0, longitude=2.0, altitude=3.0)
    data = to_dict(fix)
    start = time.perf_counter()
    for _ in range(2000):
        from_dict(NavSatFix, to_dict(fix))
    assert time.perf_counter() - start < 1.0
    assert to_dict(from_dict(NavSatFix, data))["latitude"] == 1.0
