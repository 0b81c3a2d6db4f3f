"""``check`` knows the fields of typed sources and suggests the name meant."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from engine.common.schemas import SchemaRegistry
from engine.language.fieldcheck import mapping_reads
from engine.language.routes import RoutesInvalid, load_routes
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

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
        "position, raw_json, status, vda5050/connection, vda5050/factsheet, vda5050/instant_actions, vda5050/order, vda5050/state, "
        "vda5050/visualization, weed_detection); did you mean 'position'?",
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


def test_shipped_routes_and_examples_pass_check_without_a_warning(tmp_path: Path):
    """``check --routes examples/`` (the farm and its tests), ``routes/``, the fragment alone and
    the fragment beside routes/gcs.yaml, as its header says to use it."""
    beside = tmp_path / "gcs"
    beside.mkdir()
    for source in (REPO / "routes" / "gcs.yaml", REPO / "examples" / "fragments" / "farm_routes_mavlink.yaml"):
        (beside / source.name).write_text(source.read_text())
    for routes in ("routes/", "examples/", "examples/fragments/farm_routes_mavlink.yaml", str(beside)):
        result = subprocess.run([sys.executable, "-m", "engine", "check", "--routes", routes, "--schemas", "schemas"],
                                capture_output=True, text=True, timeout=120, cwd=REPO)
        assert result.returncode == 0 and result.stderr == "" and result.stdout.endswith(": ok\n"), (routes, result.stderr)
    cases = len(yaml.safe_load((REPO / "examples" / "farm_uav_gcs.test.yaml").read_text())["tests"])
    assert f"13 routes, 3 connections, {cases} tests" in subprocess.run(
        [sys.executable, "-m", "engine", "check", "--routes", "examples/"], capture_output=True, text=True, timeout=120, cwd=REPO).stdout


def test_two_versions_of_one_example_side_by_side_say_why_they_collide(tmp_path: Path):
    for name in ("farm.yaml", "farm_copy.yaml"):
        (tmp_path / name).write_text((REPO / "examples" / "fragments" / "farm_routes_mavlink.yaml").read_text())
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    first = str(invalid.value.problems[0]).removeprefix(f"{tmp_path}/")
    assert first == (f"farm_copy.yaml:16: connection 'radio' is already defined at {tmp_path}/farm.yaml:16 "
                     "(every file of a routes directory is loaded together: keep alternative files in separate directories)")


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


EVERYTHING_WRONG = """connections:
  ros: {ros2: {domain_id: 3}}
  gcs: {amqp: "amqp://localhost/"}
  radio: {mavlink: "udpin:127.0.0.1:14998"}
dead_letters: {connection: gsc}
routes:
  - name: fix
    source:
      ros2: {topic: /fix, type: sensor_msgs/msg/NavSatFix}
    schema: position
    sink: {amqp: {exchange: farm, routing_key: x, prefetchh: 3}}
    mapping: "{agent_id: 'r', lat: latitude, lon: longitud}"
  - name: other
    source:
      ros2: {topic: /fix2, type: sensor_msgs/msg/NavSatFix, qos: {depth: "5"}}
    schema: position
    overflow: drop_olest
    sink: {amqp: {exchange: farm, routing_key: x, connection: radio}}
    mapping: "{agent_id: 'r', lat: latitude, lon: longitud, heding: `1`}"
  - name: leased
    source:
      ros2: {topic: /fix3, type: sensor_msgs/msg/NavSatFix}
    schema: postion
    active_standby: true
    lease: {connection: ros}
    sink: {amqp: {exchange: farm, routing_key: x}}
    mapping: "{agent_id: 'r', lat: latitude, lon: longitude, alt: altitude}"
"""


def test_check_reports_every_problem_of_a_file_in_one_run(tmp_path: Path):
    """Option errors (the schema's) no longer hide the rest of the file: field, connection,
    schema and lease problems of every route come in the same run, each name with a hint."""
    (tmp_path / "r.yaml").write_text(EVERYTHING_WRONG)
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert problems == [
        "r.yaml:5: dead_letters: unknown connection 'gsc'; did you mean 'gcs'?",
        "r.yaml:11: unknown key 'prefetchh' at routes[0].sink.amqp "
        "(allowed: connection, content_type, durable, exchange, exchange_type, mandatory, persistent, routing_key, timeout, unroutable)",
        "r.yaml:12: route 'fix': mapping reads 'longitud', which sensor_msgs/msg/NavSatFix does not have; did you mean 'longitude'?",
        "r.yaml:15: routes[1].source.ros2.qos.depth: '5' is not of type 'integer'",
        "r.yaml:17: routes[1].overflow: 'drop_olest' is not one of ['block', 'drop_oldest', 'drop_newest']; did you mean 'drop_oldest'?",
        "r.yaml:18: route 'other': connection 'radio' is mavlink, not amqp (amqp connections: gcs)",
        "r.yaml:19: route 'other': mapping reads 'longitud', which sensor_msgs/msg/NavSatFix does not have; did you mean 'longitude'?",
        "r.yaml:23: route 'leased': unknown schema 'postion' (known: ack, attitude, battery, command, envelope, mission, "
        "position, raw_json, status, vda5050/connection, vda5050/factsheet, vda5050/instant_actions, vda5050/order, vda5050/state, "
        "vda5050/visualization, weed_detection); did you mean 'position'?",
        "r.yaml:25: route 'leased': lease: connection 'ros' (ros2) is not one that holds leases (connections that do: gcs)",
    ]
    warnings = [str(w).removeprefix(f"{tmp_path}/") for w in invalid.value.warnings]
    assert warnings == ["r.yaml:19: route 'other': mapping sets 'heding', which schema 'position' does not declare; did you mean 'heading'?"]

    # and nothing was hidden: with those fixed, the file loads
    fixed = (EVERYTHING_WRONG.replace("gsc", "gcs").replace(", prefetchh: 3", "").replace('"5"', "5")
             .replace("drop_olest", "drop_oldest").replace(", connection: radio", "").replace("longitud,", "longitude,").replace("longitud}", "longitude}")
             .replace("postion", "position").replace("connection: ros}", "connection: gcs}"))
    (tmp_path / "r.yaml").write_text(fixed)
    assert sorted(load_routes(tmp_path, SchemaRegistry(REPO / "schemas")).routes) == ["fix", "leased", "other"]


def test_keys_a_mapping_sets_that_the_schema_does_not_declare(tmp_path: Path):
    """A misspelt optional canonical field passes validation (the schemas allow extra keys):
    ``check`` warns, top-level, nested (through $ref), in list elements and in merge(); and
    about fields a throttle or a sink's routing key or topic reads that the schema lacks."""
    (tmp_path / "r.yaml").write_text("""connections:
  gcs: {amqp: "amqp://localhost/"}
routes:
  - name: pos
    source: {amqp: {queue: a}}
    schema: position
    mapping: "{agent_id: 'r', lat: lat, lon: lon, heding: h, stamp: {sec: s, nanosecs: n}, velocity_enu: v}"
    sink: {amqp: {exchange: farm}}
  - name: weeds
    source: {amqp: {queue: b}}
    schema: weed_detection
    mapping: "merge(@, {agnt_id: a, points: detections[].{lat: lat, lon: lon, p: p, specis: s}})"
    sink: {amqp: {exchange: farm}}
  - name: raw
    source: {amqp: {queue: c}}
    schema: raw_json
    mapping: "{anything: a, goes: b}"
    sink: {amqp: {exchange: farm}}
  - name: cmd
    source: {amqp: {queue: d}}
    schema: command
    mapping: "{agent_id: a, command: c, params: {whatever: `1`}, targte: t}"
    sink: {amqp: {exchange: farm}}
  - name: templates
    source: {amqp: {queue: e}}
    schema: position
    throttle: {max_rate: 1, per: agentid}
    sink: {amqp: {exchange: farm, routing_key: "canonical.{stamp.secs}.{agent_id}"}}
  - name: topic
    source: {amqp: {queue: f}}
    schema: mission
    sink: {ros2: {topic: "/{agent}/mission"}}
""")
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    # the stamp allows no other keys (additionalProperties: false): a read of one is always null
    assert [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems] == [
        "r.yaml:28: route 'templates': sink routing_key reads 'stamp.secs', which schema 'position' does not declare and "
        "allows no other key there (always null); did you mean 'stamp.sec'?"]
    assert [str(w).removeprefix(f"{tmp_path}/") for w in invalid.value.warnings] == [
        "r.yaml:7: route 'pos': mapping sets 'heding', which schema 'position' does not declare; did you mean 'heading'?",
        "r.yaml:7: route 'pos': mapping sets 'stamp.nanosecs', which schema 'position' does not declare; did you mean 'stamp.nanosec'?",
        "r.yaml:12: route 'weeds': mapping sets 'agnt_id', which schema 'weed_detection' does not declare; did you mean 'agent_id'?",
        "r.yaml:12: route 'weeds': mapping sets 'points[].specis', which schema 'weed_detection' does not declare; did you mean 'points[].species'?",
        "r.yaml:22: route 'cmd': mapping sets 'targte', which schema 'command' does not declare; did you mean 'target'?",
        "r.yaml:27: route 'templates': throttle per reads 'agentid', which schema 'position' does not declare; did you mean 'agent_id'?",
        "r.yaml:32: route 'topic': sink topic reads 'agent', which schema 'mission' does not declare; did you mean 'agent_id'?",
    ]


def test_check_prints_problems_and_warnings_together(tmp_path: Path):
    (tmp_path / "r.yaml").write_text(EVERYTHING_WRONG)
    result = subprocess.run([sys.executable, "-m", "engine", "check", "--routes", str(tmp_path), "--schemas", str(REPO / "schemas")],
                            capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 1
    lines = [line.removeprefix(f"{tmp_path}/") for line in result.stderr.splitlines()]
    assert len(lines) == 10 and lines[6].startswith("r.yaml:19: route 'other': mapping reads") \
        and lines[7].startswith("r.yaml:19: warning: route 'other': mapping sets 'heding'"), lines


CALL_REPLIES = """connections:
  ros: {ros2: {domain_id: 3}}
  gcs: {amqp: "amqp://localhost/"}
routes:
  - name: spray
    source: {amqp: {queue: calls.spray, connection: gcs}}
    schema: raw_json
    sink:
      ros2: {connection: ros, service: /robot1/set_spray, type: std_srvs/srv/SetBool, timeout: 5}
      mapping: "{data: spray}"
    reply: {mapping: "{ok: sucess, why: message}"}
  - name: fib
    source: {amqp: {queue: calls.fib, connection: gcs}}
    schema: raw_json
    sink:
      ros2: {connection: ros, action: /fib, type: test_msgs/action/Fibonacci}
      mapping: "{order: n}"
    reply:
      mapping: "{k: kind, s: status, f: feedback.sequense, r: result.sequence[-1], x: feedbak}"
  - name: right
    source: {amqp: {queue: calls.right, connection: gcs}}
    schema: raw_json
    sink:
      ros2: {connection: ros, service: /robot1/set_spray, type: std_srvs/srv/SetBool}
    reply: {mapping: "{ok: success, why: message}"}
  - name: right-goal
    source: {amqp: {queue: calls.right-goal, connection: gcs}}
    schema: raw_json
    sink:
      ros2: {connection: ros, action: /fib, type: test_msgs/action/Fibonacci}
    reply: {mapping: "{k: kind, s: status, f: feedback.sequence[-1], r: result.sequence}"}
"""


def test_a_reply_mapping_reads_only_what_the_service_or_action_answers(tmp_path: Path):
    """A call's ``reply.mapping`` reads the service's Response, or an action's ``{kind, status,
    feedback, result}`` with the Feedback and Result below: a field they lack is an error at
    the route's ``reply`` with a did-you-mean; the right fields pass."""
    (tmp_path / "r.yaml").write_text(CALL_REPLIES)
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert problems == [
        ("r.yaml:11: route 'spray': reply: mapping reads 'sucess', which std_srvs/srv/SetBool_Response does not have; "
         "did you mean 'success'?"),
        ("r.yaml:19: route 'fib': reply: mapping reads 'feedback.sequense', which test_msgs/action/Fibonacci_Feedback "
         "does not have; did you mean 'feedback.sequence'?"),
        "r.yaml:19: route 'fib': reply: mapping reads 'feedbak', which an action's answer does not have; did you mean 'feedback'?",
    ]


MAVLINK_CALL_REPLIES = """connections:
  uav: {mavlink: "udpin:127.0.0.1:14999"}
  gcs: {amqp: "amqp://localhost/"}
routes:
  - name: arm
    source: {amqp: {queue: calls.arm, connection: gcs}}
    schema: command
    sink:
      mavlink: {connection: uav, message: COMMAND_LONG, acknowledged: true}
      mapping: "{command: `400`, param1: `1`}"
    reply: {mapping: "{k: kind, r: reslt, c: command, p: progres}"}
  - name: upload
    source: {amqp: {queue: calls.upload, connection: gcs}}
    schema: mission
    sink:
      mavlink: {connection: uav, mission: upload}
    reply: {mapping: "{k: kind, r: result, n: item}"}
  - name: right
    source: {amqp: {queue: calls.right, connection: gcs}}
    schema: command
    sink:
      mavlink: {connection: uav, message: COMMAND_LONG, acknowledged: true}
      mapping: "{command: `400`, param1: `1`}"
    reply: {mapping: "{k: kind, r: result, c: command, p: progress}"}
  - name: right-upload
    source: {amqp: {queue: calls.right-upload, connection: gcs}}
    schema: mission
    sink:
      mavlink: {connection: uav, mission: upload}
    reply: {mapping: "{k: kind, r: result, n: items}"}
"""


def test_a_reply_mapping_reads_only_what_a_mavlink_command_or_mission_answers(tmp_path: Path):
    """An acknowledged command answers ``{kind, result, command, progress}``, a mission upload
    ``{kind, result, items}``: a reply mapping reading another key is an error with a did-you-mean."""
    (tmp_path / "r.yaml").write_text(MAVLINK_CALL_REPLIES)
    with pytest.raises(RoutesInvalid) as invalid:
        load_routes(tmp_path, SchemaRegistry(REPO / "schemas"))
    problems = [str(p).removeprefix(f"{tmp_path}/") for p in invalid.value.problems]
    assert problems == [
        "r.yaml:11: route 'arm': reply: mapping reads 'progres', which an acknowledged command's answer does not have; "
        "did you mean 'progress'?",
        "r.yaml:11: route 'arm': reply: mapping reads 'reslt', which an acknowledged command's answer does not have; "
        "did you mean 'result'?",
        "r.yaml:17: route 'upload': reply: mapping reads 'item', which a mission upload's answer does not have; "
        "did you mean 'items'?",
    ]
