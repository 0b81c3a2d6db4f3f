"""Placement of a connection split over the workers (placement rule 1b, issue 34): a MAVLink
``udpin`` link with ``split_over_workers`` whose vehicles are split over ``run --workers N``
by system id (engine/endpoints/mavlink/split.py).

Real parts: the route loader on real route files (loading connects to nothing) and the CLI's
``check`` as an operator runs it; and the MAVLink header reading the owner hands frames on
by, on frames pymavlink packs."""

from __future__ import annotations

from pathlib import Path

import pytest
from pymavlink.dialects.v10 import common as mavlink1
from pymavlink.dialects.v20 import common as mavlink2

from engine.common.schemas import SchemaRegistry
from engine.endpoints.mavlink.framing import crc_holds, frame_headers
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig
from engine.ops.cli import main
from engine.running.placement import PlacementError, place_routes, stable_worker
from tests.support.repo import REPO

pytestmark = pytest.mark.fast

CONNECTIONS = """\
connections:
  bus: {amqp: "amqp://guest:guest@localhost:5672/"}
  fleet: {mavlink: "udpin:0.0.0.0:14660", split_over_workers: true}
  radio: {mavlink: /tmp/rabbitros-split-radio, baud: 57600}
routes:
"""
TELEMETRY = """\
  - name: position
    source: {mavlink: {connection: fleet, message: GLOBAL_POSITION_INT}}
    mapping: "{vehicle: meta('system_id'), lat: lat}"
    schema: raw_json
    sink: {amqp: {connection: bus, exchange: out, routing_key: position}}
"""
COMMANDS = """\
  - name: commands
    source: {amqp: {connection: bus, queue: commands}}
    schema: raw_json
    sink:
      mavlink: {connection: fleet, message: COMMAND_LONG, acknowledged: true, target_system: "{vehicle}", target_component: 1}
      mapping: "{command: `400`, param1: `1`}"
"""
RELAY = """\
  - name: relay
    source: {mavlink: {connection: radio, message: COMMAND_LONG}}
    schema: raw_json
    mapping: "{command: command, target_system: target_system, target_component: target_component}"
    sink:
      mavlink: {connection: fleet, message: COMMAND_LONG}
      mapping: "{command: command, target_system: target_system, target_component: target_component}"
"""


def config(tmp_path: Path, routes: str, connections: str = CONNECTIONS) -> RoutesConfig:
    (tmp_path / "routes.yaml").write_text(connections + routes)
    return load_routes(tmp_path / "routes.yaml", SchemaRegistry([REPO / "schemas"]))


def test_a_split_links_routes_run_on_every_worker_and_one_worker_holds_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    """Telemetry from the link and commands to it (a competing queue) run on every worker; the
    socket is held by the worker its resource hashes to; ``check --workers 3`` prints both."""
    placement = place_routes(config(tmp_path, TELEMETRY + COMMANDS), 3)
    assert main(["check", "--routes", str(tmp_path / "routes.yaml"), "--schemas", str(REPO / "schemas"), "--workers", "3"]) == 0
    printed = capsys.readouterr().out
    assert "  position: every worker (each worker with its share of connection fleet, held by worker" in printed, printed
    assert "  connection fleet: split over every worker, held by worker" in printed, printed
    assert placement.routes["position"].workers == placement.routes["commands"].workers == (0, 1, 2)
    owner = stable_worker("udp:14660", 3)
    assert placement.owners == {"fleet": owner}
    assert placement.routes["position"].reason == f"each worker with its share of connection fleet, held by worker {owner}"
    assert placement.routes["commands"].reason == "competing consumers"
    assert f"  connection fleet: split over every worker, held by worker {owner}" in placement.lines()


def test_a_route_writing_to_a_split_link_from_one_worker_runs_on_the_worker_holding_it(tmp_path: Path):
    """A route from a serial radio to the split link is held with both: the radio's worker holds
    the link too, so the link's owner always runs one of its routes."""
    placement = place_routes(config(tmp_path, TELEMETRY + RELAY), 4)
    assert placement.routes["relay"].workers == (placement.owners["fleet"],)
    assert placement.routes["position"].workers == (0, 1, 2, 3)


def test_without_the_option_the_link_is_one_workers(tmp_path: Path):
    plain = CONNECTIONS.replace(", split_over_workers: true", "")
    placement = place_routes(config(tmp_path, TELEMETRY + COMMANDS, plain), 2)
    assert placement.owners == {}
    assert placement.routes["position"].workers == placement.routes["commands"].workers == (stable_worker("udp:14660", 2),)


def test_a_route_reading_a_split_link_with_state_of_its_own_is_refused_naming_it(tmp_path: Path,
                                                                                  capsys: pytest.CaptureFixture[str]):
    routes = TELEMETRY.replace("    schema: raw_json\n", "    schema: raw_json\n    dedupe: {key: lat, ttl: 60}\n")
    loaded = config(tmp_path, routes)
    with pytest.raises(PlacementError) as caught:
        place_routes(loaded, 2)
    assert caught.value.file.endswith("routes.yaml") and caught.value.line == 6  # the route item
    assert "route 'position': reads connection 'fleet', split over the workers" in str(caught.value)
    assert "dedupe keys" in str(caught.value)
    assert main(["check", "--routes", str(tmp_path / "routes.yaml"), "--schemas", str(REPO / "schemas"), "--workers", "2"]) == 1
    assert "route 'position': reads connection 'fleet'" in capsys.readouterr().err
    assert main(["check", "--routes", str(tmp_path / "routes.yaml"), "--schemas", str(REPO / "schemas")]) == 0  # one process


@pytest.mark.parametrize(("connection", "sink", "wanted"), [
    ('{mavlink: "tcpin:0.0.0.0:14661", split_over_workers: true}', None, "split_over_workers applies to udpin links only"),
    ('{mavlink: "udpin:0.0.0.0:14662", split_over_workers: true}', "{mavlink: {connection: fleet, json_tunnel: true}}",
     "a json_tunnel sink cannot write to a connection with split_over_workers"),
], ids=["tcpin", "json-tunnel-sink"])
def test_check_refuses_what_a_split_link_cannot_do(tmp_path: Path, connection: str, sink: str | None, wanted: str):
    connections = CONNECTIONS.replace('{mavlink: "udpin:0.0.0.0:14660", split_over_workers: true}', connection)
    routes = TELEMETRY if sink is None else TELEMETRY + (
        "  - name: tunnel\n    source: {amqp: {connection: bus, queue: t}}\n    schema: raw_json\n"
        f"    sink: {sink}\n")
    with pytest.raises(RoutesInvalid) as caught:
        config(tmp_path, routes, connections)
    assert any(wanted in str(problem) for problem in caught.value.problems), caught.value.problems


def test_the_owner_reads_each_frames_sender_from_its_header():
    """MAVLink 2 and 1 frames, several in one datagram, with bytes that are no frame between:
    each frame's span, system id and message id, without decoding."""
    v2 = mavlink2.MAVLink(None, srcSystem=7, srcComponent=1)
    v1 = mavlink1.MAVLink(None, srcSystem=200, srcComponent=1)
    heartbeat = v2.heartbeat_encode(2, 3, 0, 0, 4).pack(v2)
    position = v2.global_position_int_encode(1, 2, 3, 4, 5, 0, 0, 0, 0).pack(v2)
    old = v1.heartbeat_encode(2, 3, 0, 0, 4).pack(v1)
    data = heartbeat + b"\x00\x01" + position + old + b"\xfd\x1e"  # the last: a start byte and a length, cut off
    start = len(heartbeat) + 2
    assert frame_headers(data) == [
        (0, len(heartbeat), 7, mavlink2.MAVLINK_MSG_ID_HEARTBEAT),
        (start, start + len(position), 7, mavlink2.MAVLINK_MSG_ID_GLOBAL_POSITION_INT),
        (start + len(position), start + len(position) + len(old), 200, mavlink1.MAVLINK_MSG_ID_HEARTBEAT),
    ]
    assert frame_headers(b"noise") == []
    assert all(crc_holds(data, start, end, msg_id) for start, end, _, msg_id in frame_headers(data))
    damaged = bytearray(position)
    damaged[5] = 9  # the system id: the CRC no longer holds
    assert [crc_holds(bytes(damaged), start, end, msg_id) for start, end, _, msg_id in frame_headers(bytes(damaged))] == [False]
