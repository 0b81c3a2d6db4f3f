"""The reload plan as a value, without a broker: what each kind of edit changes.

Configurations are loaded from real route and schema files (tmp directories), so the
fingerprints under test are the ones the engine computes."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from engine.common.schemas import SchemaRegistry
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig
from engine.running.plan import ReloadPlan, plan_reload

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

BASE = """
connections:
  gcs: {amqp: "amqp://guest:guest@localhost:5672/"}
  radio: {mavlink: "udpin:127.0.0.1:14999", heartbeat: 1}
routes:
  - name: weeds
    source: {amqp: {connection: gcs, exchange: farm, binding_key: "weeds.#", queue: weeds-in}}
    mapping: "{id: id, type: 'weed_detection', agent_id: agent, stamp: stamp(), points: points}"
    schema: weed_detection
    sink: {amqp: {connection: gcs, exchange: farm, routing_key: "canonical.weeds.{agent_id}"}}
  - name: raw
    source: {amqp: {connection: gcs, queue: raw-in}}
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: farm, routing_key: raw}}
  - name: position
    source: {mavlink: {connection: radio, message: GLOBAL_POSITION_INT}}
    mapping: "{lat: deg_e7_to_deg(lat)}"
    schema: raw_json
    sink: {amqp: {connection: gcs, exchange: farm, routing_key: position}}
  - name: command
    source: {amqp: {connection: gcs, queue: command-in}}
    schema: raw_json
    sink: {mavlink: {connection: radio, message: COMMAND_LONG}}
"""


class Workspace:
    """A routes and a schemas directory that tests edit between loads."""

    def __init__(self, root: Path, schemas: Path) -> None:
        self.routes = root / "routes"
        self.schemas = root / "schemas"
        self.routes.mkdir()
        shutil.copytree(schemas, self.schemas)

    def load(self, text: str, **files: str) -> RoutesConfig:
        (self.routes / "farm.yaml").write_text(text)
        for name, content in files.items():
            (self.routes / name).write_text(content)
        return load_routes(self.routes, SchemaRegistry(self.schemas))


@pytest.fixture
def ws(tmp_path: Path, schemas_dir: Path) -> Workspace:
    return Workspace(tmp_path, schemas_dir)


def conns(keys: tuple[tuple[str, str], ...]) -> list[str]:
    return [name for name, _ in keys]


def test_initial_plan_adds_everything_and_opens_used_connections(ws: Workspace):
    plan = plan_reload(None, ws.load(BASE))
    assert plan.add == ("command", "position", "raw", "weeds")
    assert conns(plan.open) == ["gcs", "radio"] and plan.close == () and plan.handovers == ()
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.add = ()  # type: ignore[misc]  # assigning a frozen field is the error under test


def test_unchanged_configuration_is_an_empty_plan(ws: Workspace):
    old = ws.load(BASE)
    plan = plan_reload(old, ws.load(BASE + "\n# a comment\n"))
    assert plan.empty and plan.keep == ("command", "position", "raw", "weeds")
    assert plan == ReloadPlan(keep=plan.keep)


def test_mapping_or_sink_change_swaps_the_pipeline_only(ws: Workspace):
    old = ws.load(BASE)
    new = ws.load(BASE.replace("{lat: deg_e7_to_deg(lat)}", "{lat: deg_e7_to_deg(lat), lon: lon}")
                  .replace("routing_key: raw}", "routing_key: raw2}"))
    plan = plan_reload(old, new)
    assert plan.swap_pipeline == ("position", "raw")
    assert plan.keep == ("command", "weeds")
    assert plan.replace_source == plan.add == plan.remove == plan.open == plan.close == ()


def test_source_change_replaces_the_source(ws: Workspace):
    old = ws.load(BASE)
    plan = plan_reload(old, ws.load(BASE.replace('binding_key: "weeds.#"', 'binding_key: "weed.#"')))
    assert plan.replace_source == ("weeds",) and plan.swap_pipeline == ()


def test_routes_added_and_removed(ws: Workspace):
    old = ws.load(BASE)
    extra = "routes:\n  - {name: extra, source: {amqp: {connection: gcs, queue: x}}, schema: raw_json, sink: {amqp: {connection: gcs, routing_key: y}}}\n"
    added = ws.load(BASE, **{"extra.yaml": extra})
    assert plan_reload(old, added).add == ("extra",)
    (ws.routes / "extra.yaml").unlink()
    plan = plan_reload(added, ws.load(BASE))
    assert plan.remove == ("extra",) and plan.close == () and plan.add == ()


def test_last_route_of_a_connection_removed_closes_it(ws: Workspace):
    old = ws.load(BASE)
    without_radio = BASE.split("  - name: position")[0]
    plan = plan_reload(old, ws.load(without_radio))
    assert plan.remove == ("command", "position")
    assert conns(plan.close) == ["radio"] and plan.handovers == ()


def test_schema_edit_changes_the_routes_that_use_it_even_through_a_ref(ws: Workspace):
    old = ws.load(BASE)
    envelope = ws.schemas / "envelope.v1.json"
    document = json.loads(envelope.read_text())
    document["$defs"]["header"]["properties"]["agent_id"]["maxLength"] = 64
    envelope.write_text(json.dumps(document))
    new = ws.load(BASE)
    plan = plan_reload(old, new)
    assert plan.swap_pipeline == ("weeds",), "weed_detection refers to the envelope"
    assert plan.keep == ("command", "position", "raw"), "raw_json does not"
    assert new.content_hash != old.content_hash


def test_amqp_connection_change_is_make_before_break(ws: Workspace):
    old = ws.load(BASE)
    plan = plan_reload(old, ws.load(BASE.replace("localhost:5672/", "127.0.0.1:5672/")))
    assert plan.replace_source == ("command", "raw", "weeds")
    assert plan.swap_pipeline == ("position",), "its source is on the radio, its sink on gcs"
    assert conns(plan.open) == conns(plan.close) == ["gcs"]
    assert plan.handovers == ()


def test_udpin_change_hands_the_port_over_break_before_make(ws: Workspace):
    old = ws.load(BASE)
    plan = plan_reload(old, ws.load(BASE.replace("heartbeat: 1", "heartbeat: 2")))
    assert conns(plan.open) == conns(plan.close) == ["radio"]
    (handover,) = plan.handovers
    assert handover.resource == "udp:14999"
    assert handover.close == plan.close[0] and handover.open == plan.open[0]
    assert handover.routes == ("command", "position")
    assert plan.break_before_make == {"command", "position"}
    assert plan.replace_source == ("command", "position"), "the AMQP->radio route restarts whole"
    assert plan.keep == ("raw", "weeds"), "routes on other connections are untouched"


def test_renamed_connection_on_the_same_port_is_a_handover(ws: Workspace):
    old = ws.load(BASE)
    plan = plan_reload(old, ws.load(BASE.replace("radio", "radio2")))
    (handover,) = plan.handovers
    assert handover.close[0] == "radio" and handover.open[0] == "radio2"


def test_udpout_change_is_not_exclusive(ws: Workspace):
    text = BASE.replace("udpin:127.0.0.1:14999", "udpout:127.0.0.1:14999")
    old = ws.load(text)
    plan = plan_reload(old, ws.load(text.replace("heartbeat: 1", "heartbeat: 2")))
    assert plan.handovers == () and conns(plan.open) == ["radio"]


def test_signing_key_file_contents_are_part_of_the_connection(ws: Workspace, tmp_path: Path):
    key = tmp_path / "key"
    key.write_bytes(b"a" * 32)
    text = BASE.replace("heartbeat: 1", f"heartbeat: 1, signing: {{key_file: {key}}}")
    old = ws.load(text)
    assert plan_reload(old, ws.load(text)).empty
    key.write_bytes(b"b" * 32)
    plan = plan_reload(old, ws.load(text))
    assert [h.resource for h in plan.handovers] == ["udp:14999"]


def test_two_connections_on_one_port_are_rejected(ws: Workspace):
    text = BASE.replace('  radio: {mavlink: "udpin:127.0.0.1:14999", heartbeat: 1}\n',
                        '  radio: {mavlink: "udpin:127.0.0.1:14999", heartbeat: 1}\n'
                        '  other: {mavlink: "udpin:0.0.0.0:14999"}\n')
    with pytest.raises(RoutesInvalid, match=r"farm.yaml:5: connection 'other': udp:14999 is already used by connection 'radio'"):
        ws.load(text)


def test_two_routes_on_one_queue_warn(ws: Workspace):
    config = ws.load(BASE.replace("queue: raw-in", "queue: weeds-in"))
    (warning,) = config.warnings
    assert warning.line == 11 and "'raw' consumes queue 'weeds-in', as route 'weeds' does" in warning.message
    assert ws.load(BASE).warnings == ()


def test_recursive_alias_and_broken_ref_are_problems_not_crashes(ws: Workspace):
    with pytest.raises(RoutesInvalid, match=r"farm.yaml:2: invalid YAML: alias \*a inside its own anchor &a"):
        ws.load("routes: []\nloop: &a [1, *a]\n")
    (ws.routes / "farm.yaml").unlink()
    position = ws.schemas / "position.v1.json"
    position.write_text(position.read_text().replace("envelope.v1.json#", "missing.v1.json#"))
    with pytest.raises(RoutesInvalid) as raised:
        ws.load(BASE)
    text = str(raised.value)
    assert "position.v1.json:0: $ref 'missing.v1.json#/$defs/header' does not resolve" in text


def test_options_the_endpoint_does_not_use_are_errors(ws: Workspace):
    text = BASE.replace("sink: {amqp: {connection: gcs, exchange: farm, routing_key: raw}}",
                        "sink: {amqp: {connection: gcs, routing_key: raw, exchange_type: fanout}}")
    with pytest.raises(RoutesInvalid, match=r"farm.yaml:14: route 'raw': sink: exchange_type is not used"):
        ws.load(text)
    text = BASE.replace("source: {amqp: {connection: gcs, queue: raw-in}}",
                        "source: {amqp: {connection: gcs, queue: raw-in, exchange_type: direct}}")
    with pytest.raises(RoutesInvalid, match=r"farm.yaml:12: route 'raw': source: exchange_type is not used"):
        ws.load(text)
    text = BASE.replace("source: {amqp: {connection: gcs, queue: raw-in}}",
                        "source: {ros2: {topic: /raw, depth: 5}}")
    with pytest.raises(RoutesInvalid, match=r"farm.yaml:12: unknown key 'depth'"):
        ws.load(text)


def test_check_prints_warnings_and_still_succeeds(ws: Workspace, capsys: pytest.CaptureFixture[str]):
    from engine.ops.cli import check

    ws.load(BASE.replace("queue: raw-in", "queue: weeds-in"))
    assert check(ws.routes, ws.schemas) == 0
    err = capsys.readouterr().err
    assert "farm.yaml:11: warning: route 'raw' consumes queue 'weeds-in'" in err


def test_exclusive_resources_of_mavlink_links(tmp_path: Path):
    from engine.language.identity import exclusive_resource

    device = tmp_path / "ttyUSB0"
    device.touch()
    (tmp_path / "radio").symlink_to(device)
    assert exclusive_resource("mavlink", {"url": "udpin:0.0.0.0:14550"}) == "udp:14550"
    assert exclusive_resource("mavlink", {"url": "udp::14551"}) == "udp:14551"
    assert exclusive_resource("mavlink", {"url": "tcpin:127.0.0.1:5760"}) == "tcp:5760"
    assert exclusive_resource("mavlink", {"url": f"{tmp_path}/radio", "baud": 57600}) == f"serial:{device}"
    assert exclusive_resource("mavlink", {"url": f"{device},115200"}) == f"serial:{device}"
    for shared in ("udpin:127.0.0.1:0", "udpout:10.0.0.2:14550", "tcp:10.0.0.2:5760"):
        assert exclusive_resource("mavlink", {"url": shared}) is None, shared
    assert exclusive_resource("amqp", {"url": "amqp://localhost/"}) is None
