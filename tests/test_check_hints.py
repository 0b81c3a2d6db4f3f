"""``check`` knows the fields of typed sources and suggests the name meant."""

from __future__ import annotations

from pathlib import Path

import pytest

from engine.fieldcheck import mapping_reads
from engine.routes import RoutesInvalid, load_routes
from engine.schemas import SchemaRegistry
from tests.conftest import REPO

ROUTES = """connections:
  ros: {ros2: {domain_id: 3}}
  radio: {mavlink: "udpin:127.0.0.1:14999"}
  gcs: {amqp: "amqp://localhost/"}
routes:
  - name: fix
    source:
      ros2: {topic: /fix, type: sensor_msgs/msg/NavSatFix}
    schema: position
    sink: {amqp: {exchange: farm, routing_key: x}}
    mapping: "{agent_id: 'r', lat: latitude, lon: longitud, s: header.stam.sec, c: position_covariance[0]}"
  - name: poses
    source:
      ros2: {topic: /poses, type: geometry_msgs/PoseArray}
    schema: raw_json
    mapping: "{p: poses[].positon.x, q: poses[?position.z > `0`].orientation.w, f: header.frame_id}"
    sink: {amqp: {exchange: farm, routing_key: x}}
  - name: typos
    source:
      ros2: {topic: /fix2, type: sensor_msgs/msg/NavSatFx}
    schema: positon
    sink: {amqp: {exchange: farm, routing_key: x}}
  - name: mav
    source:
      mavlink: {connection: radio, message: GLOBAL_POSITON_INT}
    schema: position
    sink: {amqp: {exchange: farm, routing_key: x}}
  - name: mav2
    source:
      mavlink: {connection: radio, message: GLOBAL_POSITION_INT}
    schema: position
    mapping: "{agent_id: 'u', lat: deg_e7_to_deg(lat), lon: deg_e7_to_degg(lonn), x: [@, `1`] | [0].anything}"
    sink: {amqp: {exchange: farm, routing_key: x}}
  - name: conn
    source: {amqp: {queue: q, connection: gcs}}
    schema: raw_json
    sink: {amqp: {exchange: farm, connection: gsc}}
"""


def test_typed_sources_and_misspelt_names(tmp_path: Path):
    (tmp_path / "r.yaml").write_text(ROUTES)
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert problems == [
        "r.yaml:11: route 'fix': mapping reads 'header.stam', which std_msgs/msg/Header does not have; did you mean 'header.stamp'?",
        "r.yaml:11: route 'fix': mapping reads 'longitud', which sensor_msgs/msg/NavSatFix does not have; did you mean 'longitude'?",
        "r.yaml:16: route 'poses': mapping reads 'poses[].positon', which geometry_msgs/msg/Pose does not have; did you mean 'poses[].position'?",
        "r.yaml:20: route 'typos': source: type 'sensor_msgs/msg/NavSatFx' is not installed; did you mean 'sensor_msgs/msg/NavSatFix'?",
        "r.yaml:21: route 'typos': unknown schema 'positon' (known: ack, attitude, battery, command, envelope, mission, "
        "position, raw_json, status, weed_detection); did you mean 'position'?",
        "r.yaml:25: route 'mav': source: unknown MAVLink message 'GLOBAL_POSITON_INT' (dialect: common); did you mean 'GLOBAL_POSITION_INT'?",
        "r.yaml:32: route 'mav2': mapping reads 'lonn', which MAVLink GLOBAL_POSITION_INT does not have; did you mean 'lon'?",
        "r.yaml:32: route 'mav2': unknown function deg_e7_to_degg() in \"{agent_id: 'u', lat: deg_e7_to_deg(lat), "
        "lon: deg_e7_to_degg(lonn), x: [@, `1`] | [0].anything}\"; did you mean 'deg_e7_to_deg'?",
        "r.yaml:37: route 'conn': unknown connection 'gsc'; did you mean 'gcs'?",
    ]


def test_unknown_key_suggests_the_allowed_one(tmp_path: Path):
    (tmp_path / "r.yaml").write_text("routes:\n  - name: a\n    source: {amqp: {queue: q, prefetchh: 3}}\n"
                                     "    schema: raw_json\n    sink: {amqp: {exchange: e}}\n")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    assert str(invalid.value.problems[0]).endswith("; did you mean 'prefetch'?")


def test_shipped_examples_read_only_fields_their_types_have():
    for routes in (REPO / "routes", REPO / "examples" / "farm_uav_gcs.yaml", REPO / "examples" / "farm_routes_mavlink.yaml"):
        load_routes(routes, SchemaRegistry(REPO / "schemas"))


def test_paths_read_from_the_source():
    assert mapping_reads("{a: x.y, b: list[].z, c: list[?k > `1`].v, d: f(g, h.i), e: [@, q] | [0].r, s: sort_by(t, &u)}") == [
        ("x",), ("x", "y"), ("list",), ("list", "[]", "z"), ("list", "[]", "v"), ("list", "[]", "k"),
        ("g",), ("h",), ("h", "i"), ("q",), ("t",)]


def test_a_level_left_out_of_a_nested_ros_path_is_suggested(tmp_path: Path):
    """``pose.orientation`` of a nav_msgs/Odometry is ``pose.pose.orientation`` (the pose
    with covariance holds the pose): the hint finds the field a level or two below, checks
    that the rest of the path holds there, and lists the choices when there are several."""
    (tmp_path / "r.yaml").write_text("""connections:
  ros: {ros2: {domain_id: 3}}
  gcs: {amqp: "amqp://localhost/"}
routes:
  - name: odom
    source:
      ros2: {topic: /odom, type: nav_msgs/msg/Odometry}
    schema: raw_json
    mapping: "{q: pose.orientation, w: pose.orientation.w, v: twist.linear.x, p: position, c: pose.covariancee, x: x}"
    sink: {amqp: {exchange: farm, routing_key: x}}
""")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/r.yaml:9: route 'odom': ") for p in invalid.value.problems]
    assert sorted(problems) == sorted([
        "mapping reads 'pose.orientation', which geometry_msgs/msg/PoseWithCovariance does not have; did you mean 'pose.pose.orientation'?",
        "mapping reads 'twist.linear', which geometry_msgs/msg/TwistWithCovariance does not have; did you mean 'twist.twist.linear'?",
        "mapping reads 'position', which nav_msgs/msg/Odometry does not have; did you mean 'pose.pose.position'?",
        "mapping reads 'pose.covariancee', which geometry_msgs/msg/PoseWithCovariance does not have; did you mean 'pose.covariance'?",
        "mapping reads 'x', which nav_msgs/msg/Odometry does not have; did you mean one of 'pose.pose.position.x', "
        "'pose.pose.orientation.x', 'twist.twist.linear.x'?",
    ])
