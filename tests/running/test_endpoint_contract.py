"""The core asks the endpoint contract, not the protocol's name: a source that redelivers
needs no buffer by default (per its options), and the dead-letter and lease defaults are the
connections whose class keeps dead letters / holds leases."""

from __future__ import annotations

import pytest

from pathlib import Path

from engine.common.schemas import SchemaRegistry
from engine.language.routes import load_routes
from engine.language.stage_options import BufferSpec
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier


ROUTES = """
connections:
  field: {mqtt: "mqtt://127.0.0.1:1883"}
  broker: {amqp: "amqp://guest:guest@127.0.0.1:5672/"}
routes:
  - {name: qos0, source: {mqtt: {topic: farm/+/weather, qos: 0}}, schema: raw_json, sink: {amqp: {exchange: e}}}
  - {name: qos1, source: {mqtt: {topic: farm/+/soil, qos: 1}}, schema: raw_json, sink: {amqp: {exchange: e}}}
  - {name: queue, source: {amqp: {queue: q}}, schema: raw_json, sink: {mqtt: {topic: "farm/{agent_id}/cmd"}}}
  - {name: standby, active_standby: true, source: {mqtt: {topic: farm/+/cmd, qos: 1}}, schema: raw_json, sink: {mqtt: {topic: out}}}
"""


def test_the_default_buffer_follows_whether_the_source_redelivers(tmp_path: Path):
    """An MQTT QoS 0 message is delivered once: its route keeps the buffer a QoS 1 or AMQP route
    does without (their broker keeps what the engine has not acknowledged)."""
    (tmp_path / "r.yaml").write_text(ROUTES)
    config = load_routes(tmp_path, SchemaRegistry(REPO / "schemas"), env={})
    assert config.routes["qos0"].buffer == BufferSpec()
    assert config.routes["qos1"].buffer is None and config.routes["queue"].buffer is None
    assert config.dead_letters.connection == "broker"  # the only connection that keeps dead letters
    assert config.routes["standby"].placement.lease_connection == "broker"  # the only one that holds leases


def test_each_protocols_mapping_functions_are_the_ones_it_declares():
    """A protocol's mapping functions load only for a mapping that calls one of the names the
    registry lists: a name missing there would be an unknown function until another loaded them."""
    import importlib

    from engine import endpoints
    from engine.language.mapping import compile_mapping

    from jmespath import functions

    builtin = set(functions.Functions.FUNCTION_TABLE)
    for module, names in endpoints.MAPPING_FUNCTIONS.items():
        assert set(importlib.import_module(module).Functions.FUNCTION_TABLE) - builtin == set(names), module
    assert compile_mapping("stamp_boot_ms(`5`).sec")({}) > 0


def test_local_broker_warns_about_an_mqtt_connection_naming_its_own_broker(tmp_path: Path):
    """Under --local-broker a connection without a url uses the private mosquitto; one with a url
    keeps its broker, and the loader says so (the MQTT transport's private_broker_warning)."""
    from engine.common.processes import LOCAL_BROKER_ENV

    (tmp_path / "r.yaml").write_text(
        "connections:\n  own: {mqtt: \"mqtt://10.0.0.5:1883\"}\n  private: {mqtt: {client_id: engine-1}}\n"
        "routes:\n  - {name: a, source: {mqtt: {connection: own, topic: a}}, schema: raw_json, sink: {mqtt: {connection: private, topic: b}}}\n")
    warnings = [str(w) for w in load_routes(tmp_path, SchemaRegistry(REPO / "schemas"), env={LOCAL_BROKER_ENV: ""}).warnings]
    assert len(warnings) == 1 and "r.yaml:2: connection 'own' names its own broker (mqtt://10.0.0.5:1883)" in warnings[0], warnings
    assert load_routes(tmp_path, SchemaRegistry(REPO / "schemas"), env={}).warnings == ()


def test_mavlink_failures_map_through_its_one_table() -> None:
    """The OS's failures on a link are transient, pymavlink's encoding failures permanent; a real
    serial device that is not there is a transient error naming it, in the OS's words."""
    import asyncio
    import errno
    import struct

    from engine.endpoints.base import EndpointError, MessageRejected
    from engine.endpoints.mavlink.errors import edge_error
    from engine.endpoints.mavlink.links import SerialLink
    from engine.endpoints.mavlink.settings import parse_address

    lost = edge_error(OSError(errno.EIO, "Input/output error"), "write to /dev/ttyUSB0 failed")
    assert type(lost) is EndpointError and str(lost) == "write to /dev/ttyUSB0 failed: Input/output error"
    assert type(edge_error(struct.error("ushort format requires 0 <= number <= 65535"), "COMMAND_LONG: cannot encode")) \
        is MessageRejected
    link = SerialLink(parse_address("/dev/rabbitros-no-such-radio", 57600), lambda data, peer: None, {})
    with pytest.raises(EndpointError, match="cannot open /dev/rabbitros-no-such-radio: No such file or directory") as raised:
        asyncio.run(link.open())
    assert not isinstance(raised.value, MessageRejected)
