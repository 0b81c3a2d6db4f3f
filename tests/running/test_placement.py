"""Placement over ``run --workers N`` (engine/running/placement.py): one pure function of the
compiled routes, and ``check --workers N`` printing it.

Real parts: the route loader on real route files (no broker is reached: loading connects to
nothing), the CLI's ``check`` as an operator runs it, and a second interpreter with another
hash seed for the stability of the hash."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import load_routes
from engine.language.specs import RoutesConfig
from engine.ops.cli import main
from engine.running.placement import PlacementError, place_routes, stable_worker
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

CONNECTIONS = """\
connections:
  bus: {amqp: "amqp://guest:guest@localhost:5672/"}
  radio: {mavlink: /tmp/rabbitros-placement-radio, baud: 57600}
  field: {mavlink: "udpin:0.0.0.0:14650"}
  gcs: {mavlink: "udpout:127.0.0.1:14651"}
  ros: {ros2: {domain_id: 0, node: placement_test}}
"""


def config(tmp_path: Path, routes: str, connections: str = CONNECTIONS) -> RoutesConfig:
    (tmp_path / "routes.yaml").write_text(connections + "routes:\n" + routes)
    return load_routes(tmp_path / "routes.yaml", SchemaRegistry([REPO / "schemas"]))


def amqp_route(name: str, extra: str = "") -> str:
    return (f"  - name: {name}\n    source: {{amqp: {{connection: bus, queue: {name}-q}}}}\n    schema: raw_json\n{extra}"
            f"    sink: {{amqp: {{connection: bus, exchange: out, routing_key: {name}}}}}\n")


def radio_route(name: str, connection: str = "radio", sink: str = "{amqp: {connection: bus, exchange: out, routing_key: r}}") -> str:
    return (f"  - name: {name}\n    source: {{mavlink: {{connection: {connection}, message: HEARTBEAT}}}}\n    schema: raw_json\n"
            f"    mapping: '{{type: type}}'\n    sink: {sink}\n")


def ros_route(name: str) -> str:
    return (f"  - name: {name}\n    source: {{ros2: {{connection: ros, topic: /{name.replace('-', '_')}, type: std_msgs/msg/String}}}}\n"
            f"    schema: raw_json\n    mapping: '{{data: data}}'\n    sink: {{amqp: {{connection: bus, exchange: out, routing_key: {name}}}}}\n")


def test_a_broker_queue_runs_on_every_worker_and_a_subscription_on_one(tmp_path: Path):
    placement = place_routes(config(tmp_path, amqp_route("orders") + ros_route("fix-a") + ros_route("fix-b")), 3)
    assert placement.routes["orders"].workers == (0, 1, 2)
    assert placement.routes["orders"].reason == "competing consumers"
    for name in ("fix-a", "fix-b"):
        assert placement.routes[name].workers == (stable_worker(name, 3),)
        assert placement.routes[name].reason == "hash of the route name"
    assert placement.on(0) | placement.on(1) | placement.on(2) == {"orders", "fix-a", "fix-b"}


def test_an_ordered_queue_and_its_partitions_run_on_every_worker(tmp_path: Path):
    """``ordered: true``: every worker waits on the single-active-consumer queue, one consumes;
    ``ordered: {partitions: 4}``: each worker's source names itself (host, pid), so the
    partitions spread over the workers as over instances (engine/endpoints/amqp/partitions.py)."""
    routes = (amqp_route("commands", "    ordered: true\n")
              + "  - name: telemetry\n    source: {amqp: {connection: bus, exchange: farm, binding_key: 't.#'}}\n"
                "    ordered: {partitions: 4}\n    schema: raw_json\n"
                "    sink: {amqp: {connection: bus, exchange: out, routing_key: t}}\n")
    placement = place_routes(config(tmp_path, routes), 2)
    assert placement.routes["commands"].workers == placement.routes["telemetry"].workers == (0, 1)


def test_an_mqtt_shared_subscription_spreads_and_a_session_stays_on_one_worker(tmp_path: Path):
    """``shared: GROUP``: the broker hands each message to one member of the group, so every
    worker subscribes; a plain subscription gives each subscriber every message (one worker);
    a connection with a client_id is one session (one worker, with its other routes)."""
    connections = CONNECTIONS + ('  mq: {mqtt: "mqtt://127.0.0.1:1883"}\n'
                                 '  kept: {mqtt: {url: "mqtt://127.0.0.1:1883", client_id: gcs-1}}\n')

    def mqtt_route(name: str, connection: str, shared: str = "") -> str:
        return (f"  - name: {name}\n    source: {{mqtt: {{connection: {connection}, topic: farm/+/weather{shared}}}}}\n"
                f"    schema: raw_json\n    sink: {{amqp: {{connection: bus, exchange: out, routing_key: {name}}}}}\n")

    routes = (mqtt_route("weather-shared", "mq", ", shared: engines") + mqtt_route("weather-plain", "mq")
              + mqtt_route("weather-kept", "kept", ", shared: engines") + mqtt_route("weather-kept-2", "kept"))
    placement = place_routes(config(tmp_path, routes, connections), 3)
    assert placement.routes["weather-shared"].workers == (0, 1, 2)
    assert placement.routes["weather-plain"].workers == (stable_worker("weather-plain", 3),)
    session = "mqtt:127.0.0.1:1883/gcs-1"
    assert placement.routes["weather-kept"].workers == placement.routes["weather-kept-2"].workers == (stable_worker(session, 3),)
    assert placement.routes["weather-kept"].reason == f"holds {session}"


def test_one_worker_holds_every_route_of_a_device_whatever_their_sources(tmp_path: Path):
    """The radio's telemetry routes and a command route fed by a broker queue (which alone
    would run everywhere) all run where the serial device is open, so it is opened once."""
    command = ("  - name: commands\n    source: {amqp: {connection: bus, queue: commands-q}}\n    schema: raw_json\n"
               "    sink: {mavlink: {connection: radio, json_tunnel: true, target_system: 1}}\n")
    routes = "".join(radio_route(f"uav-{k}") for k in range(6)) + command
    placement = place_routes(config(tmp_path, routes), 4)
    device = f"serial:{Path('/tmp/rabbitros-placement-radio').resolve()}"
    owners = {placement.routes[name].workers for name in [*(f"uav-{k}" for k in range(6)), "commands"]}
    assert owners == {(stable_worker(device, 4),)}, owners
    assert placement.routes["commands"].reason == f"holds {device}"


def test_a_fallback_on_a_device_places_the_route_with_the_device(tmp_path: Path):
    """A queue route (alone: every worker) whose second sink's fallback writes to the radio
    runs where the radio is open, once."""
    routes = ("  - name: orders\n    source: {amqp: {connection: bus, queue: orders-q}}\n    schema: raw_json\n"
              "    sinks:\n      - amqp: {connection: bus, exchange: out, routing_key: a}\n"
              "      - amqp: {connection: bus, exchange: out2, routing_key: b}\n"
              "        fallback:\n          mavlink: {connection: radio, json_tunnel: true, target_system: 1}\n"
              + radio_route("uav"))
    placement = place_routes(config(tmp_path, routes), 3)
    assert placement.routes["orders"].workers == placement.routes["uav"].workers
    assert len(placement.routes["orders"].workers) == 1 and "serial:" in placement.routes["orders"].reason


def test_a_route_joining_two_links_puts_both_on_one_worker(tmp_path: Path):
    """field (udpin: a listening port) -> gcs (udpout: a link the vehicle answers): owned
    together, so a route on the gcs link alone runs with them, wherever the hash of either
    key alone would have put it."""
    routes = (radio_route("relay", "field", "{mavlink: {connection: gcs, message: HEARTBEAT}}")
              + radio_route("gcs-only", "gcs") + radio_route("field-only", "field"))
    placement = place_routes(config(tmp_path, routes), 5)
    assert placement.routes["relay"].workers == placement.routes["gcs-only"].workers == placement.routes["field-only"].workers
    assert "mavlink link 'gcs'" in placement.routes["relay"].reason and "udp:14650" in placement.routes["relay"].reason


def test_state_in_the_process_keeps_a_route_on_one_worker(tmp_path: Path):
    """dedupe keys, a sequence and a buffer's spill files live in one process: a queue route
    with them runs on one worker; the routes that write and read the stores run together."""
    routes = (amqp_route("deduped", "    dedupe: {key: id, ttl: 60}\n")
              + amqp_route("writer", "    remember: {store: positions, per: agent}\n")
              + amqp_route("reader", "    mapping: \"{agent: agent, last: recall('positions', agent)}\"\n")
              + amqp_route("counted", "    mapping: '{n: sequence()}'\n")
              + amqp_route("spilled", f"    buffer: {{spill_dir: {tmp_path / 'spill'}}}\n"))
    placement = place_routes(config(tmp_path, routes), 4)
    assert placement.routes["deduped"].workers == (stable_worker("deduped", 4),)
    assert placement.routes["deduped"].reason == "keeps dedupe keys in the process"
    assert placement.routes["counted"].reason == "keeps a sequence in the process"
    assert placement.routes["spilled"].reason == "keeps a spill directory in the process"
    assert placement.routes["writer"].workers == placement.routes["reader"].workers == (stable_worker("stores", 4),)


def test_one_worker_runs_everything_and_zero_is_refused(tmp_path: Path):
    loaded = config(tmp_path, amqp_route("orders") + radio_route("uav") + ros_route("fix"))
    assert place_routes(loaded, 1).on(0) == {"orders", "uav", "fix"}
    with pytest.raises(PlacementError, match="at least 1"):
        place_routes(loaded, 0)


def test_the_hash_is_the_same_in_another_process():
    """``hash()`` of a str differs between interpreters: placement must not."""
    script = "from engine.running.placement import stable_worker; print([stable_worker(f'route-{k}', 7) for k in range(50)])"
    here = str([stable_worker(f"route-{k}", 7) for k in range(50)])
    other = subprocess.run([sys.executable, "-c", script], cwd=REPO, env={"PYTHONHASHSEED": "12345", "PYTHONPATH": str(REPO)},
                           capture_output=True, text=True, check=True).stdout.strip()
    assert other == here
    assert len(set(eval(here))) == 7  # every worker gets some of 50 names


def test_check_prints_the_farm_examples_placement(capsys: pytest.CaptureFixture[str]):
    code = main(["check", "--routes", str(REPO / "examples" / "farm_uav_gcs.yaml"), "--schemas", str(REPO / "schemas"),
                 "--workers", "2"])
    out = capsys.readouterr().out
    assert code == 0, out
    lines = {line.split(":")[0].strip(): line for line in out.splitlines() if line.startswith("  ")}
    radio = {line.split(": ", 1)[1] for name, line in lines.items() if name.startswith("uav1-")}
    assert len(radio) == 1 and "holds serial:" in radio.pop(), out  # every route of the radio on the same worker
    assert lines["robot-missions"].endswith("every worker (competing consumers)"), out
    assert "placement on 2 workers" in out


def test_check_refuses_a_serial_device_claimed_twice(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    """Two connections on one device would be opened by two owners: refused with the file,
    the line and both connections, before any placement is printed."""
    connections = CONNECTIONS + "  radio2: {mavlink: /tmp/rabbitros-placement-radio, baud: 57600}\n"
    path = tmp_path / "routes.yaml"
    path.write_text(connections + "routes:\n" + radio_route("uav-a") + radio_route("uav-b", "radio2"))
    code = main(["check", "--routes", str(path), "--schemas", str(REPO / "schemas"), "--workers", "2"])
    captured = capsys.readouterr()
    assert code == 1
    assert f"{path}:" in captured.err and "radio2" in captured.err and "serial:" in captured.err
    assert "already used by connection 'radio'" in captured.err
    assert "placement" not in captured.out


def test_a_topic_pattern_runs_on_every_worker_each_following_its_share(tmp_path: Path):
    pattern = ("  - name: fixes\n    source: {ros2: {connection: ros, topic: '/{agent}/fix', type: std_msgs/msg/String}}\n"
               "    schema: raw_json\n    sink: {amqp: {connection: bus, exchange: out, routing_key: 'fix.{agent}'}}\n")
    placement = place_routes(config(tmp_path, pattern + ros_route("one-topic")), 2)
    assert placement.routes["fixes"].workers == (0, 1) and placement.routes["fixes"].split
    assert placement.routes["one-topic"].workers == (stable_worker("one-topic", 2),) and not placement.routes["one-topic"].split
