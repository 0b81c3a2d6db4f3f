"""``ordered: {partitions: S, key: ...}`` at load and at check: the options reach the source, and
what would break the order (a quorum queue, no exchange to hash from, an unknown key, a source
that cannot partition) is refused naming the file, line, route and key."""

from __future__ import annotations

from pathlib import Path

import pytest

from engine.common.schemas import SchemaRegistry
from engine.endpoints.amqp.options import AmqpSourceOptions
from engine.endpoints.amqp.partitions import hash_exchange, partition_arguments, partition_queue, should_hand_over
from engine.language.routes import RoutesInvalid, load_routes
from engine.language.specs import RoutesConfig
from tests.support.repo import REPO

pytestmark = pytest.mark.fast  # no broker, no network peer, no ROS 2 node: ./scripts/test.sh's first tier

HEAD = """connections:
  bus: {amqp: {url: "amqp://guest:guest@localhost:5672/", queue_type: quorum}}
routes:
"""


def load(tmp_path: Path, routes: str) -> RoutesConfig:
    directory = tmp_path / "routes"
    directory.mkdir(exist_ok=True)
    (directory / "r.yaml").write_text(HEAD + routes)
    return load_routes(directory, SchemaRegistry(REPO / "schemas"))


def problems(tmp_path: Path, routes: str) -> list[tuple[int, str]]:
    with pytest.raises(RoutesInvalid) as caught:
        load(tmp_path, routes)
    return [(problem.line, problem.message) for problem in caught.value.problems]


def test_partitioned_route_reaches_the_source_as_classic_single_active_queues(tmp_path: Path) -> None:
    config = load(tmp_path, """  - name: telemetry
    ordered: {partitions: 4}
    source: {amqp: {exchange: farm, binding_key: "telemetry.#"}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: by-header
    ordered: {partitions: 3, key: headers.agent}
    source: {amqp: {exchange: farm, queue: q}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: single
    ordered: true
    source: {amqp: {queue: single}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
""")
    routes = config.routes
    options = routes["telemetry"].source.options
    assert isinstance(options, AmqpSourceOptions)
    assert (options.ordered, options.partitions, options.partition_key) == (True, 4, "routing_key")
    assert routes["telemetry"].placement.partitions == 4 and routes["telemetry"].placement.ordered
    assert [partition_queue("telemetry", options, i) for i in range(2)] == ["rabbitros.telemetry.p0", "rabbitros.telemetry.p1"]
    assert hash_exchange("telemetry", options) == "rabbitros.telemetry.partitions"
    # classic whatever the connection's default (quorum here), one active consumer each
    assert partition_arguments(options) == {"x-queue-type": "classic", "x-single-active-consumer": True}
    header = routes["by-header"].source.options
    assert (header.partitions, header.partition_key) == (3, "headers.agent")
    assert partition_queue("by-header", header, 2) == "q.p2"
    assert hash_exchange("by-header", header) == "q.partitions.header.agent"  # a changed key: another exchange
    single = routes["single"].source.options
    assert single.ordered and single.partitions == 1 and routes["single"].placement.partitions == 1


def test_what_breaks_partitioned_order_is_refused_at_check(tmp_path: Path) -> None:
    found = problems(tmp_path, """  - name: quorum
    ordered: {partitions: 4}
    source: {amqp: {exchange: farm, queue_type: quorum}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: no-exchange
    ordered: {partitions: 4}
    source: {amqp: {queue: q}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: body-key
    ordered: {partitions: 4, key: agent_id}
    source: {amqp: {exchange: farm}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: one
    ordered: {partitions: 1}
    source: {amqp: {exchange: farm}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
  - name: from-mqtt
    ordered: {partitions: 4}
    source: {mqtt: {topic: "a/#"}}
    schema: raw_json
    sink: {amqp: {exchange: out}}
""")
    text = "\n".join(f"{line}: {message}" for line, message in found)
    assert any(line == 5 and "'quorum': ordered: partitions are classic queues: the source's queue_type quorum is refused"
               in message and "rabbitmq-server#6804" in message for line, message in found), text
    assert any(line == 10 and "'no-exchange': ordered: partitions need the source's exchange" in message
               for line, message in found), text
    assert any(line == 15 and "'body-key': ordered: 'agent_id' is not routing_key or headers.NAME" in message
               and "routing_key: '{agent_id}'" in message for line, message in found), text
    assert any(line == 20 and "less than the minimum of 2" in message for line, message in found), text
    assert any(line == 25 and "'from-mqtt'" in message and "ordered does not apply to a mqtt source" in message
               for line, message in found), text


@pytest.mark.parametrize(("mine", "partitions", "instances", "me", "peers", "hands_over"), [
    (4, 4, 1, "a", {}, False),                        # alone: keeps everything
    (4, 4, 2, "a", {"b": 0}, True),                   # a second instance came: more than ceil(4/2)
    (2, 4, 2, "a", {"b": 2}, False),                  # its share
    (2, 4, 3, "a", {"b": 2, "c": 0}, True),           # c has none, a and b are the busiest: a, the first name, moves
    (2, 4, 3, "b", {"a": 2, "c": 0}, False),          # ... and b waits
    (2, 4, 3, "a", {"b": 1, "c": 1}, False),          # 2, 1, 1: spread
    (1, 2, 3, "a", {"b": 1, "c": 0}, False),          # more instances than partitions: one waits, no churn
    (3, 4, 2, "a", {"b": 1}, True),                   # after a kill left 3 here
    (0, 4, 3, "a", {"b": 4}, False),                  # none here: nothing to hand over (b hands over)
], ids=lambda value: str(value))
def test_the_spreading_rule(mine: int, partitions: int, instances: int, me: str, peers: dict[str, int],
                            hands_over: bool) -> None:
    assert should_hand_over(mine, partitions, instances, me, peers) is hands_over
