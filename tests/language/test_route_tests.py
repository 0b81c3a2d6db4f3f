"""``rabbitros-engine test``: route tests run through the real conversion, with no middleware."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

NO_MIDDLEWARE = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split('.')[0] in ('rclpy', 'rosidl_parser', 'rosidl_runtime_py', 'sensor_msgs', 'std_msgs'):
            raise ImportError('blocked: ' + name)
sys.meta_path.insert(0, Block())
from engine.ops.cli import main
sys.exit(main(sys.argv[1:]))
"""


def engine_cli(*args: str, blocked: bool = False) -> subprocess.CompletedProcess[str]:
    """The CLI with no broker anywhere: the AMQP URL points nowhere and no RabbitMQ can be found."""
    env = {**os.environ, "RABBITROS_AMQP_URL": "amqp://guest:guest@nowhere.invalid:1/",
           "RABBITMQ_SERVER_BIN": "/nonexistent", "PYTHONPATH": str(REPO)}
    argv = [sys.executable, "-c", NO_MIDDLEWARE, *args] if blocked else [sys.executable, "-m", "engine", *args]
    return subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=REPO, env=env)


def test_shipped_routes_pass_without_broker_or_rclpy():
    result = engine_cli("test", "--routes", "routes/", blocked=True)
    assert result.returncode == 0, result.stdout + result.stderr
    lines = result.stdout.splitlines()
    assert len([line for line in lines if line.startswith("ok ")]) == 7
    assert lines[-1] == "7 passed, 0 failed"


def test_farm_example_passes():
    result = engine_cli("test", "--routes", "examples/farm_uav_gcs.yaml")
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stdout.splitlines()[-1] == "23 passed, 0 failed"
    routes = {line.split()[2].rstrip(":") for line in result.stdout.splitlines() if line.startswith("ok ")}
    assert routes == {"uav1-position", "uav1-attitude", "uav1-battery", "uav1-status", "uav1-commands",
                      "uav1-weeds", "uav1-missions", "uav1-mission-acks", "robot-missions", "robot1-position",
                      "robot1-acks", "robot1-spray", "robot1-rows"}, "every route of the farm example has a test"


def _copy_routes(tmp_path: Path) -> Path:
    routes = tmp_path / "routes"
    routes.mkdir()
    shutil.copy(REPO / "routes" / "gcs.yaml", routes)
    shutil.copytree(REPO / "schemas", tmp_path / "schemas")
    return routes


def test_wrong_expectation_fails_with_a_diff(tmp_path: Path):
    routes = _copy_routes(tmp_path)
    (routes / "weeds.test.yaml").write_text("""tests:
  - name: right
    route: uav-weeds
    input: {agent: uav1, id: a, stamp: 1, detections: [{lat: 1, lon: 2, confidence: 0.5}]}
    expect: {id: a, stamp: {sec: 1, nanosec: 0}, agent_id: uav1, type: weed_detection, points: [{lat: 1, lon: 2, p: 0.5}]}
  - name: wrong confidence key
    route: uav-weeds
    input: {agent: uav1, id: a, stamp: 1, detections: [{lat: 1, lon: 2, confidence: 0.5}]}
    expect: {id: a, stamp: {sec: 1, nanosec: 0}, agent_id: uav1, type: weed_detection, points: [{lat: 1, lon: 2, confidence: 0.5}]}
  - name: wrong routing key
    route: uav-weeds
    input: {agent: uav1, detections: []}
    expect_routing_key: canonical.weeds.uav2
  - name: expected an error that does not happen
    route: uav-weeds
    input: {agent: uav1, detections: []}
    expect_error: schema
""")
    result = engine_cli("test", "--routes", str(routes), blocked=True)
    assert result.returncode == 1, result.stdout + result.stderr
    out = result.stdout
    assert re.search(r"^ok +\S+weeds.test.yaml:2 +uav-weeds: right$", out, re.M), out
    assert re.search(r"^FAIL +\S+weeds.test.yaml:6 +uav-weeds: wrong confidence key: canonical message differs$", out, re.M), out
    assert '-      "confidence": 0.5,' in out and '+      "p": 0.5' in out, out
    assert "routing key/topic is 'canonical.weeds.uav1', expected 'canonical.weeds.uav2'" in out
    assert "expected a schema error, but the message converted" in out
    assert out.splitlines()[-1] == "1 passed, 3 failed"


def test_invalid_test_file_exits_2_with_file_and_line(tmp_path: Path):
    routes = _copy_routes(tmp_path)
    (routes / "bad.test.yaml").write_text("tests:\n  - route: uav-weeds\n    input: {}\n    expect: {}\n"
                                          "  - route: uav-weedz\n    input: {}\n    expect_error: schema\n")
    (routes / "worse.test.yaml").write_text("tests:\n  - route: uav-weeds\n    input: {}\n    expect_error: scheme\n")
    result = engine_cli("test", "--routes", str(routes), blocked=True)
    assert result.returncode == 2, result.stdout + result.stderr
    assert result.stderr.strip().splitlines() == [
        f"{routes}/bad.test.yaml:5: unknown route 'uav-weedz'; did you mean 'uav-weeds'?",
        f"{routes}/worse.test.yaml:4: tests[0].expect_error: 'scheme' is not one of "
        "['input', 'decode', 'mapping', 'schema', 'when', 'window', 'sink mapping', 'sink', 'reply mapping', 'reply schema']; did you mean 'schema'?",
    ]
    check = engine_cli("check", "--routes", str(routes), blocked=True)
    assert check.returncode == 1 and check.stderr == result.stderr
    (routes / "bad.test.yaml").unlink()
    (routes / "worse.test.yaml").unlink()
    assert engine_cli("check", "--routes", str(routes), blocked=True).returncode == 0


def test_test_files_are_never_loaded_as_routes(tmp_path: Path):
    routes = _copy_routes(tmp_path)
    (routes / "gcs.test.yaml").write_text("tests: []\n")
    result = engine_cli("check", "--routes", str(routes), blocked=True)
    assert result.returncode == 0, result.stderr
    assert "2 routes" in result.stdout
