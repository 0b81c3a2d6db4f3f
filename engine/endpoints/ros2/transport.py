"""ROS 2 endpoint: one rclpy node per connection, run in step with the engine's asyncio loop.

Executor design. rclpy's executors do not fit an asyncio program: SingleThreadedExecutor
tops out near 2,000 msg/s, polling ``spin_once(0)`` from the loop costs 45 % of a core while
idle, and EventsExecutor spinning in a thread deadlocks the first ``create_publisher`` made
from another thread (in ``Node._wake_executor``). So a connection uses no executor at all:

* a *waiter* thread blocks in ``rcl_wait`` (GIL released) on a wait set holding the node's
  subscriptions and one guard condition (``_rclpy.WaitSet``, what rclpy's own executors use).
  When subscriptions are ready it hands their handles to the loop with
  ``call_soon_threadsafe`` and sleeps until the loop has taken them, as the wait set is
  level-triggered. It never calls into the node or user code and costs nothing while idle;
* everything else runs on the asyncio thread: taking messages (at most ``_TAKE_BUDGET`` per
  subscription per wake-up, so a flood cannot starve AMQP), converting and queueing them,
  publishing, and creating or destroying publishers and subscriptions. With no executor
  attached to the node, ``Node._wake_executor`` is a no-op and there is no lock to take.
  A change of subscriptions triggers the guard condition so the waiter rebuilds its wait
  set; a subscription destroyed while the waiter holds it is freed when the waiter lets go.

Measured on the 2-core development machine (bench/bench_ros2_executor.py): 10,000 msg/s
received without loss (String and NavSatFix), 0.1 % CPU while idle, p50 latency under 1 ms.
Not serviced: QoS event handlers (e.g. rclpy's incompatible-QoS warning).

A source topic with ``{var}`` segments subscribes to every matching topic as it appears in the
graph (engine/endpoints/ros2/discovery.py): one source, many subscriptions, one queue.

Each source has a bounded queue and one task that hands it to the route in batches; a
full queue follows the route's ``overflow`` (block: stop taking; or drop and count), and
DDS history (``qos.depth``) is what buffers while the loop itself is busy.
Publishing is synchronous on the loop (a few microseconds for a String; KEEP_LAST never
blocks, which is why KEEP_ALL is not offered). A message that cannot fit its sink (a field
the type lacks, a bad value, a topic placeholder it does not fill) raises MessageRejected;
rclpy failures raise EndpointError, naming the route and topic.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import queue
import re
import threading
import time
from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Literal, Mapping, Sequence

import jmespath
import rclpy
from rclpy.context import Context
from rclpy.duration import Duration
from rclpy.exceptions import InvalidHandle
from rclpy.expand_topic_name import expand_topic_name
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.validate_full_topic_name import validate_full_topic_name
from rclpy.validate_namespace import validate_namespace
from rclpy.validate_node_name import validate_node_name

from engine.common.options import given, option
from engine.common.placeholders import template_problem
from engine.common.suggest import did_you_mean
from engine.endpoints.base import (
    CheckResult, Connection, FieldProblem, Deliver, EndpointError, EndpointOptions, Inbound, Inbox, MessageRejected, Outbound, Sink,
    Source, Transport, typed,
)
from engine.endpoints.ros2 import calls as ros2_calls, contract as ros2_contract, discovery, rosmsg
from engine.endpoints.ros2.errors import EXCEPTIONS, mapped, rcl_reason, setup_error
from engine.running.fairness import route_inbox

log = logging.getLogger("engine.ros2")

STRING_TYPE = "std_msgs/msg/String"
DEFAULT_DEPTH = 10_000
"""KEEP_LAST depth for both ends: the buffer that covers a stall of the engine or of a reader.
Measured here, a reader stalled for 8 s under 2,000 msg/s lost 40 % of 12,000 messages at
depth 1,000 and none at 10,000 (an earlier project measurement: none at 100,000 either).
10,000 covers about 1 s at the 10,000 msg/s target and 20 s at 500 msg/s, while memory
stays bounded by depth x message size per endpoint (+12 MB after 50,000 messages of 200 B,
against +35 MB at 100,000)."""
SOURCE_QUEUE = 10_000
"""Messages a source holds between taking them and the pipeline, unless the route says
otherwise (``Deliver.queue_limit``); beyond it, the route's ``overflow`` applies."""
_TAKE_BUDGET = 1024
"""Most messages taken from one subscription per wake-up: everything ready, within reason."""
_BATCH = 1024
"""Most messages handed to the route in one ``Deliver.batch``. A batch waits for its sink (an
AMQP sink: the broker's confirms) before the next one starts, so a backlogged route carries
at most _BATCH per confirm round trip, which reaches tens of ms on a loaded machine: the
MAVLink source's batch of 1,024 (engine/endpoints/mavlink/messages.py) for the same reason;
the reference (bench/systems.py) publishes all it has taken at once."""
_TYPE_CHECK_INTERVAL = 2.0
_RELIABILITY = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {"volatile": DurabilityPolicy.VOLATILE, "transient_local": DurabilityPolicy.TRANSIENT_LOCAL}
_PLACEHOLDER = re.compile(r"\{([^{}]*)\}")
_RCL_SUBSTITUTIONS = frozenset({"node", "ns", "namespace"})


def _env_domain_id() -> int:
    try:
        return int(os.environ.get("ROS_DOMAIN_ID", "0"))
    except ValueError:
        return 0


@dataclass(frozen=True, kw_only=True)
class Ros2ConnectionOptions:
    """``connections.<name>.ros2``: the node the engine creates, in its own DDS domain."""

    __schema_description__ = "one rclpy context and node per connection"

    domain_id: int | None = option(None, schema={"minimum": 0, "maximum": 232},
                                   description="DDS domain; default $ROS_DOMAIN_ID, else 0 (as every ROS 2 program)")
    """None: ``ROS_DOMAIN_ID`` (else 0), as every ROS 2 program. The bounds are checked with
    the node name (``connection_problems``), so both are reported."""
    node: str = option("rabbitros_engine", description="name of the engine's node (what ros2 node list shows)")
    namespace: str = option("", description="namespace of the node: relative topic names resolve in it")


@dataclass(frozen=True, kw_only=True)
class Ros2Qos:
    __schema_description__ = "the topic's quality of service; a reader and a writer match only when theirs are compatible"

    reliability: Literal["reliable", "best_effort"] = option(
        "reliable", description="reliable: lost samples are resent to matched readers; best_effort: never resent")
    durability: Literal["volatile", "transient_local"] = option(
        "volatile", description="transient_local: a sink keeps its last depth messages for readers that join later")
    depth: int = option(DEFAULT_DEPTH, minimum=1, description="keep-last history of the reader or writer (a transient_local sink resends up to this many to late joiners)")


@dataclass(frozen=True, kw_only=True)
class Ros2EndpointOptions(EndpointOptions):
    """A ROS 2 source or sink: one topic of one message type."""

    __schema_description__ = "a ROS 2 topic of one message type"

    topic: str | None = option(None, description="topic name (required, except for a sink that names a service); a sink's may "
                                                 "interpolate canonical fields (/{agent_id}/weeds); a source's {var} segments discover "
                                                 "every matching topic (/{agent}/fix, meta('agent')); {node} and {ns} are left to rcl")
    type: str = option(STRING_TYPE, description="any installed message type, pkg/msg/Type or pkg/Type; std_msgs/msg/String carries the "
                                                "canonical JSON in data, byte for byte; with service: the service type, pkg/srv/Type")
    qos: Ros2Qos = option(Ros2Qos())
    service: str | None = option(None, description="instead of a topic (type: pkg/srv/Type): a source offers this service, each call "
                                                   "answered by the route's reply; a sink calls it, the response is the call's reply "
                                                   "(route-language.md, Calls)")
    max_in_flight: int = option(ros2_calls.DEFAULT_MAX_IN_FLIGHT, minimum=1,
                                description="service: calls in flight at once. A source offering it takes that many at once, "
                                            "and its request queue keeps that many, so a burst of calls up to it loses none; a "
                                            "sink calls at most that many at once (the default matches ROS 2's default service "
                                            "queue depth, 10: raise it with the servers' depth)")


@dataclass(frozen=True, kw_only=True)
class Ros2SourceOptions(Ros2EndpointOptions):
    """A ROS 2 source: a topic (or a pattern of topics, discovered) or a service it offers."""

    forget_after: float = option(discovery.DEFAULT_FORGET_AFTER, exclusive_minimum=0,
                                 description="a topic with {var} segments: seconds a discovered topic may go without a publisher "
                                             "of the type before its subscription is let go (followed again when one comes back)")


@dataclass(frozen=True, kw_only=True)
class Ros2SinkOptions(Ros2EndpointOptions):
    """A ROS 2 sink: a source's options, and whether it waits for a reader."""

    require_subscriber: bool = option(
        True, description="hold the route's messages (not sent, not acknowledged) until a subscriber has "
                          "matched the topic; false publishes anyway, for topics nobody may listen to")
    """True whatever the durability: a transient_local writer keeps only ``qos.depth`` messages,
    in the engine's memory, for readers that ask for transient_local themselves, while the
    source has already acknowledged them; holding until the first reader matches loses none
    of them, and the writer's history still serves the readers that join later."""
    action: str | None = option(None, description="send each message as a goal of this action (type: pkg/action/Type): accepted, "
                                                  "feedback and result are the call's replies (route-language.md, Calls)")
    timeout: float = option(ros2_calls.DEFAULT_CALL_TIMEOUT, exclusive_minimum=0,
                            description="service: seconds from sending a request to its response; action: from sending the goal to "
                                        "its result (then the goal is canceled); waiting for a server included; then the caller "
                                        "gets an error reply")


# ---------------------------------------------------------------- static checks

def _check_topic(topic: Any, placeholders: Literal["none", "fields", "variables"]) -> Iterator[str]:
    """A topic name valid by rcl's rules; ``placeholders``: what a ``{name}`` in it may be (a
    sink's canonical fields, a source's discovery variables, or nothing: a service's name)."""
    if not isinstance(topic, str) or not topic:
        yield "topic is required (a ROS topic name such as /uav1/weeds)"
        return
    names = [n for n in _PLACEHOLDER.findall(topic) if n not in _RCL_SUBSTITUTIONS]
    if names and placeholders == "none":
        yield f"topic {topic!r}: placeholders ({{{names[0]}}}) are not allowed here"
        return
    problem = template_problem(topic) if placeholders == "fields" else discovery.pattern_problem(topic)
    if problem:
        yield problem if placeholders == "variables" else f"topic {problem}"
        return
    sample = _PLACEHOLDER.sub(lambda m: m.group(0) if m.group(1) in _RCL_SUBSTITUTIONS else "x", topic)
    try:
        validate_full_topic_name(expand_topic_name(sample, "node", "/"))
    except Exception as exc:  # rcl raises ValueError or InvalidTopicNameException
        yield f"invalid topic name {topic!r}: {rcl_reason(exc)}"


def _check_type(name: Any) -> Iterator[tuple[str, str]]:
    try:
        rosmsg.resolve_type(name)
    except rosmsg.MessageError as exc:
        yield "type", str(exc)


def _check_endpoint(options: Ros2EndpointOptions, sink: bool) -> Iterator[tuple[str | None, str]]:
    for message in _check_topic(options.topic, "fields" if sink else "variables"):
        yield "topic", message
    yield from _check_type(options.type)


def _check_service(options: Ros2SinkOptions) -> Iterator[tuple[str | None, str]]:
    """A service or action sink: one valid name, an installed pkg/srv/Type or pkg/action/Type."""
    key = "service" if options.service is not None else "action"
    if sum(value is not None for value in (options.topic, options.service, options.action)) > 1:
        yield key, "a ros2 sink names one of topic, service or action"
    if key == "action" and "max_in_flight" in given(options):
        yield "max_in_flight", "max_in_flight applies to a sink that calls a service (goals are bounded by the server)"
    for message in _check_topic(getattr(options, key), "none"):
        yield key, message.replace("topic", key)
    try:
        (ros2_calls.resolve_service if key == "service" else ros2_calls.resolve_action)(options.type)
    except rosmsg.MessageError as exc:
        yield "type", str(exc)


def _sink_class(options: Ros2SinkOptions) -> type:
    """What a sink's mapping builds: the message of its topic, its service's request, its action's goal."""
    if options.service is not None:
        return ros2_calls.resolve_service(options.type).Request
    if options.action is not None:
        return ros2_calls.resolve_action(options.type).Goal
    return rosmsg.resolve_type(options.type)


def _check_mapping_keys(node: Mapping[str, Any], cls: type, prefix: str) -> Iterator[str]:
    """Keys of a JMESPath multiselect hash (``{a: x, b: {c: y}}``) against message fields,
    descending into nested hashes for nested message fields."""
    fields = rosmsg.field_names(cls)
    for pair in node.get("children", ()):
        key = pair.get("value")
        if key not in fields:
            yield (f"mapping key {prefix}{key!r} is not a field of {rosmsg.type_name(cls)} "
                   f"(fields: {', '.join(fields)}){did_you_mean(key, fields)}")
            continue
        value = (pair.get("children") or [{}])[0]
        nested = rosmsg.nested_type(cls, key)
        if value.get("type") == "multi_select_dict" and nested is not None:
            yield from _check_mapping_keys(value, nested, f"{prefix}{key}.")


def _topic_of(options: Ros2EndpointOptions | Mapping[str, Any]) -> Any:
    """The topic, for error messages, before the options are known to parse."""
    return options.topic if isinstance(options, Ros2EndpointOptions) else options.get("topic")


def _qos(options: Ros2EndpointOptions) -> QoSProfile:
    qos = options.qos
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=_RELIABILITY[qos.reliability],
        durability=_DURABILITY[qos.durability],
    )


class Ros2Transport(Transport):
    name = "ros2"
    default_settings = {"node": "rabbitros_engine", "namespace": "", "domain_id": _env_domain_id()}
    connection_options = Ros2ConnectionOptions
    replies = True
    """A source that offers a service answers its callers (engine.endpoints.ros2.calls.py)."""
    source_options = Ros2SourceOptions
    sink_options = Ros2SinkOptions
    source_meta = ("topic",)

    def source_variables(self, options: Ros2SourceOptions) -> tuple[str, ...]:
        """A topic's ``{var}`` segments (engine/endpoints/ros2/discovery.py)."""
        return () if options.service is not None else discovery.topic_variables(options.topic)

    def meta_names(self, options: Ros2SourceOptions) -> tuple[str, ...]:
        return (*self.source_meta, *self.source_variables(options))

    def connection_problems(self, options: Ros2ConnectionOptions) -> CheckResult:
        node, namespace, domain_id = options.node, options.namespace, options.domain_id
        try:
            validate_node_name(node)
        except Exception as exc:
            yield "node", f"invalid node name {node!r}: {rcl_reason(exc)}"
        if namespace:
            try:
                validate_namespace(namespace if namespace.startswith("/") else "/" + namespace)
            except Exception as exc:
                yield "namespace", f"invalid namespace {namespace!r}: {rcl_reason(exc)}"
        if domain_id is not None and not 0 <= domain_id <= 232:
            yield "domain_id", f"domain_id must be an integer in 0..232, not {domain_id!r}"

    def source_answers(self, options: Ros2EndpointOptions) -> bool:
        return options.service is not None  # a topic's publishers await no answer

    def queues_per_agent(self, options: Ros2EndpointOptions) -> bool:
        return options.service is None  # a topic's messages wait in the route's inbox

    def source_problems(self, options: Ros2SourceOptions, mapping: str | None) -> CheckResult:
        if "forget_after" in given(options) and not self.source_variables(options):
            yield "forget_after", "forget_after applies to a topic with {var} segments (discovered topics, as /{agent}/fix)"
        if options.service is None:
            yield from _check_endpoint(options, sink=False)
            if "max_in_flight" in given(options):
                yield "max_in_flight", "max_in_flight applies to a source that offers a service"
            return
        if options.topic is not None:
            yield "service", "a ros2 source names a topic or a service, not both"
        for message in _check_topic(options.service, "none"):
            yield "service", message.replace("topic", "service")
        try:
            ros2_calls.resolve_service(options.type)
        except rosmsg.MessageError as exc:
            yield "type", str(exc)

    def sink_problems(self, options: Ros2SinkOptions, mapping: str | None) -> CheckResult:
        if options.service is not None or options.action is not None:
            yield from _check_service(options)
        else:
            yield from _check_endpoint(options, sink=True)
            for key in ("timeout", "max_in_flight"):
                if key in given(options):
                    yield key, f"{key} applies to a sink that calls a service"
        if not mapping or options.type == STRING_TYPE:
            return
        try:
            cls = _sink_class(options)
            tree = jmespath.compile(mapping).parsed
        except (rosmsg.MessageError, jmespath.exceptions.JMESPathError):
            return  # reported by the type check and by the route loader
        if tree.get("type") == "multi_select_dict":
            for message in _check_mapping_keys(tree, cls, ""):
                yield "mapping", message

    def sink_field_check(self, options: Ros2SinkOptions, mapping: str | None = None) -> Callable[[Any], None] | None:
        """A typed sink with a sink mapping refuses a null anywhere in the mapping's output (a
        ``sink mapping`` error naming the field; see :func:`typed_message`), before the route
        waits for a reader or throttles. A String sink carries JSON, where null is a value;
        without a sink mapping a null float is NaN (the canonical form of a ROS NaN)."""
        calls = options.service is not None or options.action is not None
        if mapping is None or not calls and rosmsg.type_name(rosmsg.resolve_type(options.type)) == STRING_TYPE:
            return None
        where = (f"ros2 service {options.service!r}" if options.service is not None else
                 f"ros2 action {options.action!r}" if options.action is not None else f"ros2 topic {options.topic!r}")

        def refuse_nulls(fields: Any) -> None:
            path = rosmsg.null_path(fields)
            if path is not None:
                raise MessageRejected(f"{where}: {rosmsg.NullValue(path)}", stage="sink mapping")

        return refuse_nulls

    def connect(self, name: str, settings: Ros2ConnectionOptions | Mapping[str, Any]) -> Connection:
        return Ros2Connection(name, settings)

    def canonical_fields(self, options: Ros2EndpointOptions) -> Iterable[tuple[str, str]]:
        return [("topic", name) for name in _PLACEHOLDER.findall(options.topic or "") if name not in _RCL_SUBSTITUTIONS]

    # What the core's checks and dry runs ask (contract.py).

    def sink_dry_run(self, route: str, options: Ros2SinkOptions) -> Callable[[Outbound], str | None]:
        name = options.service or options.action
        if name is not None:  # a call: the request or goal built as the sink builds it
            cls, kind = _sink_class(options), "service" if options.service else "action"
            where = f"route {route!r}, ros2 {kind} {name!r}"
            return lambda outbound: (typed_message(cls, outbound, where), name)[1]
        return ros2_contract.sink_dry_run(route, options.topic, options.type, _topic_template(options.topic), typed_message)

    def test_input(self, options: Ros2EndpointOptions) -> Callable[[Any], dict[str, Any]] | None:
        if options.service is not None:
            return None  # an offered service's request as JSON: the case's input is its field dict
        return ros2_contract.test_input(options.type)

    def field_problem(self, options: Ros2EndpointOptions) -> FieldProblem | None:
        if options.service is not None:  # an offered service: the mapping reads its request
            try:
                cls = ros2_calls.resolve_service(options.type).Request
            except rosmsg.MessageError:
                return None
            return ros2_contract.message_field_problem(cls)
        return ros2_contract.field_problem(options.type)

    def reply_field_problem(self, options: Ros2SinkOptions) -> FieldProblem | None:
        try:
            if options.service is not None:  # the reply mapping reads the response
                return ros2_contract.message_field_problem(ros2_calls.resolve_service(options.type).Response)
            if options.action is not None:  # {kind, status, feedback, result}
                return ros2_contract.action_answer_problem(ros2_calls.resolve_action(options.type))
        except rosmsg.MessageError:  # not installed or misspelt: reported by the type check
            return None
        return None

    def suggest(self, key: str, value: str) -> str | None:
        return ros2_contract.suggest_type(value) if key == "type" else None


TRANSPORT = Ros2Transport()


# ---------------------------------------------------------------- connection

class Ros2Connection(Connection):
    """One rclpy Context (own domain id) and one node, plus the waiter thread."""

    settings: Ros2ConnectionOptions

    def __init__(self, name: str, settings: Ros2ConnectionOptions | Mapping[str, Any]) -> None:
        super().__init__(name, typed(Ros2ConnectionOptions, settings, f"ros2 connection {name!r}"))
        self.domain_id = self.settings.domain_id if self.settings.domain_id is not None else _env_domain_id()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._context: Context | None = None
        self._node: Node | None = None
        self._guard: GuardCondition | None = None
        self._waiter: threading.Thread | None = None
        self._taken: queue.SimpleQueue[None] = queue.SimpleQueue()
        """One token per hand-over the loop finished (and one at close): what the waiter waits
        on. A C queue: ``threading.Event``'s set ran its Condition's notify in Python on the
        loop at every hand-over (1.3 % of the engine's GIL samples in bench/fleet.py)."""
        self._closing = False
        self._readers: dict[int, _Reader] = {}
        """Subscription handle pointer -> its reader (what the waiter reports ready)."""
        self._waited: tuple[Any, ...] = ()
        self._sources: set[Ros2Source] = set()
        self._discovering: set[Ros2Source] = set()
        self._discovery: asyncio.Task[None] | None = None
        self._sinks: set[Ros2Sink] = set()
        self._publishers: dict[tuple[str, str, tuple[Any, ...]], tuple[Any, int]] = {}
        self._calls: ros2_calls.CallNode | None = None

    @property
    def node(self) -> Node:
        if self._node is None or self._closing:
            raise EndpointError(f"ros2 connection {self.name!r} is not open")
        return self._node

    async def open(self) -> None:
        self._loop = asyncio.get_running_loop()
        await asyncio.to_thread(self._open_node)
        self._taken = queue.SimpleQueue()  # no token left from an earlier close
        self._waiter = threading.Thread(target=self._wait_loop, name=f"ros2-wait-{self.name}", daemon=True)
        self._waiter.start()

    def _open_node(self) -> None:
        """DDS participant creation takes tens of milliseconds, so it runs off the loop."""
        context = Context()
        try:
            rclpy.init(args=[], context=context, domain_id=self.domain_id,
                       signal_handler_options=SignalHandlerOptions.NO)
            node = Node(
                self.settings.node, namespace=self.settings.namespace, context=context,
                start_parameter_services=False,
                parameter_overrides=[Parameter("start_type_description_service", value=False)],
            )
            guard = GuardCondition(None, None, context=context)
        except Exception as exc:
            context.try_shutdown()
            raise setup_error(exc, f"ros2 connection {self.name!r}: cannot create node {self.settings.node!r}") from exc
        self._context, self._node, self._guard = context, node, guard

    def source(self, route: str, options: Ros2EndpointOptions | Mapping[str, Any]) -> Source:
        typed_options = typed(Ros2SourceOptions, options, f"route {route!r}: ros2 source")
        if typed_options.service is not None:
            return ros2_calls.ServiceSource(self.calls(), route, typed_options.service, typed_options.type,
                                            typed_options.max_in_flight)
        return Ros2Source(self, route, options)

    def sink(self, route: str, options: Ros2SinkOptions | Mapping[str, Any]) -> Sink:
        typed_options = typed(Ros2SinkOptions, options, f"route {route!r}: ros2 sink")
        if typed_options.service is not None:
            return ros2_calls.ServiceSink(self.calls(), route, typed_options.service, typed_options.type,
                                          typed_options.timeout, typed_options.max_in_flight)
        if typed_options.action is not None:
            return ros2_calls.ActionSink(self.calls(), route, typed_options.action, typed_options.type, typed_options.timeout)
        sink = Ros2Sink(self, route, options)
        self._sinks.add(sink)
        return sink

    def calls(self) -> ros2_calls.CallNode:
        """The node of this connection's service calls, made on first use (engine.endpoints.ros2.calls.py)."""
        if self._calls is None:
            self.node  # raises EndpointError when not open
            self._calls = ros2_calls.CallNode(self._context, self.settings.node, self.settings.namespace)
        return self._calls

    def acquire_publisher(self, cls: type, topic: str, qos: QoSProfile) -> Any:
        """Publishers are shared by every sink of the connection with the same topic, type and
        QoS, so a reload that swaps a route's sink keeps the DDS writer the subscribers have
        already matched: a new writer would drop what it publishes before matching."""
        key = (topic, rosmsg.type_name(cls), (qos.history, qos.depth, qos.reliability, qos.durability))
        publisher, users = self._publishers.get(key, (None, 0))
        if publisher is None:
            publisher = self.node.create_publisher(cls, topic, qos)
        self._publishers[key] = (publisher, users + 1)
        return publisher

    async def release_publisher(self, publisher: Any) -> None:
        """The last user gone, wait (bounded) for reliable readers to acknowledge what was
        published before destroying the writer, so a removed route loses nothing in flight."""
        for key, (shared, users) in list(self._publishers.items()):
            if shared is not publisher:
                continue
            if users > 1:
                self._publishers[key] = (shared, users - 1)
                return
            del self._publishers[key]
            await _all_acked(publisher, RELEASE_ACK_WAIT)
            if self._node is not None:
                self._node.destroy_publisher(publisher)
            return

    async def close(self) -> None:
        if self._node is None or self._closing:
            return
        for source in list(self._sources):
            await source.stop()
        if self._discovery is not None:
            self._discovery.cancel()
            await asyncio.gather(self._discovery, return_exceptions=True)
        for sink in list(self._sinks):
            await sink.close()
        if self._calls is not None:
            calls, self._calls = self._calls, None
            await asyncio.to_thread(calls.close)
        self._closing = True
        self._guard.trigger()
        self._taken.put(None)
        if self._waiter is not None:
            await asyncio.to_thread(self._waiter.join, 5.0)
            if self._waiter.is_alive():
                log.warning("ros2 connection %r: wait thread did not stop", self.name)
        await asyncio.to_thread(self._close_node)

    def _close_node(self) -> None:
        try:
            self._guard.destroy()
            self._node.destroy_node()
        finally:
            self._context.try_shutdown()
            self._node = None

    # -- discovery: one read of the graph per interval for every discovering source

    def discover(self, source: Ros2Source) -> None:
        """Scan the graph for ``source`` now, then at every interval until :meth:`forget`."""
        self._discovering.add(source)
        source._scan(self.node.get_topic_names_and_types(), time.monotonic())
        if self._discovery is None or self._discovery.done():
            self._discovery = asyncio.create_task(self._discover(), name=f"ros2-discovery-{self.name}")

    def forget(self, source: Ros2Source) -> None:
        self._discovering.discard(source)

    async def _discover(self) -> None:
        while self._discovering and not self._closing:
            await asyncio.sleep(discovery.DISCOVERY_INTERVAL)
            try:
                topics = self.node.get_topic_names_and_types()
            except Exception as exc:  # the node is closing, or rcl failed: the next scan tries again
                log.warning("ros2 connection %r: cannot read the graph: %s", self.name, exc)
                continue
            now = time.monotonic()
            for source in list(self._discovering):
                try:
                    source._scan(topics, now)
                except Exception:  # a bug: the other sources keep discovering
                    log.exception("%s: discovery failed", source._where)

    def publisher_types(self, topic: str) -> list[str]:
        """The message types of ``topic``'s publishers (none when the graph cannot be read)."""
        try:
            return [info.topic_type for info in self.node.get_publishers_info_by_topic(topic)]
        except Exception:
            return []

    # -- the waiter thread and its hand-over to the loop

    def _readers_changed(self) -> None:
        """Give the waiter a fresh tuple of subscriptions and make it rebuild its wait set."""
        self._waited = tuple(reader.subscription for reader in self._readers.values() if not reader.source.paused)
        self._guard.trigger()

    def _wait_loop(self) -> None:
        """Blocks in rcl_wait; hands ready subscription handles to the loop, then waits for
        the loop to take them (the wait set is level-triggered).

        The wait set and the hold on its subscriptions' handles are kept until the
        subscriptions change (``_readers_changed``), not rebuilt at every wake-up: rebuilding
        entered every handle in Python, O(subscriptions) with the GIL held at every message
        of a fleet's 100 topics at 10 Hz (15 % of the engine's samples in bench/fleet.py)."""
        context, guard = self._context, self._guard
        held = ExitStack()
        waited: tuple[Any, ...] | None = None
        handles: list[Any] = []
        wait_set: Any = None
        try:
            while not self._closing:
                try:
                    if waited is not self._waited:  # (re)build: hold the handles, size the wait set
                        held.close()
                        held = ExitStack()
                        waited = self._waited
                        handles = []
                        for sub in waited:
                            try:
                                held.enter_context(sub.handle)
                            except InvalidHandle:
                                continue
                            handles.append(sub.handle)
                        held.enter_context(guard.handle)
                        held.enter_context(context.handle)
                        wait_set = _rclpy.WaitSet(len(handles), 1, 0, 0, 0, 0, context.handle)
                    wait_set.clear_entities()
                    for handle in handles:
                        wait_set.add_subscription(handle)
                    wait_set.add_guard_condition(guard.handle)
                    wait_set.wait(-1)
                    ready = wait_set.get_ready_entities("subscription")
                except Exception as exc:
                    held.close()
                    waited = None
                    if self._closing or not context.ok():
                        return
                    log.error("ros2 connection %r: wait failed: %s", self.name, exc)
                    time.sleep(0.1)
                    continue
                if not ready or self._closing:
                    continue
                try:
                    self._loop.call_soon_threadsafe(self._take_ready, ready)
                except RuntimeError:
                    return  # the loop is closed
                self._taken.get()
        finally:
            held.close()

    def _take_ready(self, ready: list[int]) -> None:
        try:
            for pointer in ready:
                reader = self._readers.get(pointer)
                if reader is None:
                    continue
                try:
                    reader.source._take(reader)
                except Exception as exc:
                    log.error("%s: take failed: %s", reader.source._where, exc)
        finally:
            self._taken.put(None)


RELEASE_ACK_WAIT = 2.0
"""Seconds a released publisher waits for its reliable readers to acknowledge what it sent."""
_ACK_POLL = 0.02


async def _all_acked(publisher: Any, timeout: float) -> bool:
    """Whether every reliable reader of ``publisher`` acknowledged what it published, waiting
    at most ``timeout`` s without holding up the loop or the process.

    rclpy's ``wait_for_all_acked`` keeps the GIL for its whole wait: one reader that did not
    answer (a robot stopped or gone, still matched until its lease expires) froze every
    thread of the engine for the 2 s, one publisher after another, so a stop of the fleet's
    50 robot command routes took 100 s (bench/fleet.py, killed at 20 s). It is asked with a
    zero timeout instead (~160 us), between loop turns; a publisher no reader matched has
    nothing to wait for."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    now = Duration(nanoseconds=0)
    while publisher.get_subscription_count() and not publisher.wait_for_all_acked(now):
        if loop.time() >= deadline:
            return False
        await asyncio.sleep(_ACK_POLL)
    return True


# ---------------------------------------------------------------- source

class _Reader:
    """One subscription of a source, and the metadata each of its messages carries."""

    __slots__ = ("source", "subscription", "meta", "received")

    def __init__(self, source: Ros2Source, subscription: Any, meta: dict[str, Any]) -> None:
        self.source = source
        self.subscription = subscription
        self.meta = meta
        self.received = 0


class Ros2Source(Source):
    """Takes everything its subscriptions have ready in one pass into a bounded queue, and
    hands the queue to the route in batches. A full queue follows the route's ``overflow``:
    ``block`` stops taking (the subscriptions leave the wait set, so DDS history and reliable
    flow control hold the rest), ``drop_oldest`` / ``drop_newest`` drop and count.

    A topic with ``{var}`` segments is a pattern: the source subscribes to each matching topic
    as it appears in the graph, one queue for all of them (so each topic's order is kept),
    each message with the topic's captured values in its metadata (engine/endpoints/ros2/discovery.py).

    ``std_msgs/String`` is taken serialized and its CDR string read directly, so its bytes
    reach the pipeline untouched (invalid UTF-8 is then the decoder's to dead-letter, where
    rclpy would raise while taking it). A typed message rclpy cannot take is handed on as
    undecodable, to be dead-lettered. Publishers of another type on the topic never match;
    the source reports them (log and status).
    """

    def __init__(self, connection: Ros2Connection, route: str, options: Ros2SourceOptions | Mapping[str, Any]) -> None:
        self._connection = connection
        self._route = route
        self._topic = _topic_of(options)
        self._where = f"route {route!r}, ros2 topic {self._topic!r}"
        problems = [message for _, message in TRANSPORT.check_source(options, None)]
        if problems:
            raise EndpointError(f"{self._where}: {'; '.join(problems)}")
        options = typed(Ros2SourceOptions, options, self._where)
        self._cls = rosmsg.resolve_type(options.type)
        self._type_name = rosmsg.type_name(self._cls)
        self._is_string = self._type_name == STRING_TYPE
        self._qos = _qos(options)
        self._queue: Inbox[Inbound] = Inbox(SOURCE_QUEUE)
        self._deliver: Deliver | None = None
        self.paused = False
        self._readers: dict[str, _Reader] = {}
        """Topic -> its reader: the one topic, or each discovered topic being followed."""
        self._discovery: discovery.Discovery | None = None
        if discovery.topic_variables(self._topic):
            settings = connection.settings
            pattern = discovery.compile_pattern(self._topic, settings.node, settings.namespace)
            self._discovery = discovery.Discovery(pattern, self._type_name, options.forget_after, self._where,
                                                  self._follow, self._matched, self._let_go)
        self._pump: asyncio.Task[None] | None = None
        self._watch: asyncio.Task[None] | None = None
        self._stopping = False
        self.received = 0
        self.dropped = 0
        self.mismatched_publishers: list[str] = []
        self._drop_logged = 0.0

    async def start(self, deliver: Deliver) -> None:
        self._connection.node  # raises EndpointError when not open
        self._deliver = deliver
        self._queue = route_inbox(deliver, deliver.overflow)
        if self._discovery is None:
            self._subscribe(self._topic, {})
        self._pump = asyncio.create_task(self._run(deliver), name=f"ros2-source-{self._route}")
        self._connection._sources.add(self)
        if self._discovery is None:
            self._watch = asyncio.create_task(self._watch_types(), name=f"ros2-types-{self._route}")
        else:
            self._connection.discover(self)

    def _subscribe(self, topic: str, captured: Mapping[str, str]) -> _Reader:
        try:
            subscription = self._connection.node.create_subscription(self._cls, topic, _unused_callback, self._qos)
        except Exception as exc:
            raise setup_error(exc, f"{self._where}: cannot subscribe to {topic!r}") from exc
        reader = _Reader(self, subscription, {"topic": subscription.topic_name, "type": self._type_name, **captured})
        self._readers[subscription.topic_name] = reader
        self._connection._readers[subscription.handle.pointer] = reader
        self._connection._readers_changed()
        return reader

    def _scan(self, topics: Any, now: float) -> None:
        """One read of the graph (called by the connection): follow and let go (discovery only)."""
        if self._discovery is not None and not self._stopping:
            self._discovery.scan(topics, self._connection.publisher_types, now)

    def _follow(self, topic: str, captured: Mapping[str, str]) -> bool:
        try:
            self._subscribe(topic, captured)
        except EndpointError as exc:
            log.debug("%s", exc)
            return False
        return True

    def _matched(self, topic: str) -> int:
        try:
            return self._readers[topic].subscription.get_publisher_count()
        except Exception:  # destroyed meanwhile: nothing matched
            return 0

    def _let_go(self, topic: str) -> None:
        reader = self._readers.pop(topic, None)
        if reader is None:
            return
        connection = self._connection
        connection._readers.pop(reader.subscription.handle.pointer, None)
        connection._readers_changed()
        if connection._node is not None:
            connection._node.destroy_subscription(reader.subscription)  # freed once the waiter lets go of it

    def _take(self, reader: _Reader) -> None:
        """Runs on the loop: take what is ready (bounded by the queue), never waits."""
        sub, cls, queue, meta = reader.subscription, self._cls, self._queue, reader.meta
        block = queue.overflow == "block"
        taken = 0
        try:
            with sub.handle:
                for _ in range(_TAKE_BUDGET):
                    if block and queue.full:
                        self._pause()
                        break
                    try:
                        message = sub.handle.take_message(cls, self._is_string)
                    except InvalidHandle:
                        raise
                    except Exception as exc:  # rclpy could not convert what it took
                        taken += 1
                        self._put(Inbound(meta=dict(meta), undecodable=f"cannot take a {self._type_name}: {exc}"))
                        continue
                    if message is None:
                        break
                    taken += 1
                    self._put(self._inbound(message[0], meta))
        except InvalidHandle:
            return
        finally:
            if taken:
                self.received += taken
                reader.received += taken
                queue.wake()

    def _put(self, inbound: Inbound) -> None:
        if self._queue.offer(inbound):
            self._drop()

    def _inbound(self, msg: Any, meta: dict[str, Any]) -> Inbound:
        if self._is_string:
            try:
                return Inbound(body=_cdr_string(msg), meta=dict(meta))
            except ValueError as exc:
                return Inbound(body=bytes(msg), meta=dict(meta), undecodable=str(exc))
        try:
            return Inbound(fields=rosmsg.to_dict(msg), meta=dict(meta))
        except Exception as exc:
            return Inbound(meta=dict(meta), undecodable=f"cannot convert a {self._type_name}: {exc}")

    def _drop(self) -> None:
        self.dropped += 1
        if self._deliver is not None:
            self._deliver.dropped(1)
        now = time.monotonic()
        if now - self._drop_logged >= 10.0:
            self._drop_logged = now
            log.warning("%s: queue full (%d, overflow %s), dropped %d messages so far",
                        self._where, self._queue.limit, self._queue.overflow, self.dropped)

    def _pause(self) -> None:
        if not self.paused:
            self.paused = True
            self._connection._readers_changed()

    def _resume(self) -> None:
        if self.paused:
            self.paused = False
            self._connection._readers_changed()

    async def _run(self, deliver: Deliver) -> None:
        queue = self._queue
        while batch := await queue.take(_BATCH):
            if self.paused and len(queue) <= queue.limit // 2:
                self._resume()
            try:
                settled = await deliver.batch(batch)
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # a bug in the engine: ROS cannot redeliver, count the loss
                log.exception("%s: settling a batch failed: %s", self._where, exc)
                settled = [False] * len(batch)
            lost = settled.count(False)
            if lost:
                self.dropped += lost
                deliver.dropped(lost)
            if len(queue):  # a backlog must not hold the loop from other routes; an empty inbox waits in take()
                await asyncio.sleep(0)  # (at a robot's pace a yield per message is a loop round trip for nothing)

    async def _watch_types(self) -> None:
        """Publishers of another type on our topic never match: say so (log and status)."""
        reported: set[str] = set()
        topic = next(iter(self._readers))
        while not self._stopping:
            try:
                infos = self._publishers_unless_all_matched(topic)
            except Exception:
                infos = []
            wrong = sorted({f"{info.node_namespace.rstrip('/')}/{info.node_name} ({info.topic_type})"
                            for info in infos if info.topic_type != self._type_name})
            self.mismatched_publishers = wrong
            for publisher in set(wrong) - reported:
                log.error("%s: publisher %s does not match the route's type %s; its messages are not received",
                          self._where, publisher, self._type_name)
            reported = set(wrong)
            await asyncio.sleep(_TYPE_CHECK_INTERVAL)

    def _publishers_unless_all_matched(self, topic: str) -> list[Any]:
        """The topic's publishers, or none when every one of them matched our subscription
        (then none is of another type). Counting (rcl_count_publishers, and the matched count)
        builds no endpoint objects: a fleet's engine with 100 ROS 2 sources spent 11 % of its
        loop in this check with the full query every time (bench/fleet.py, py-spy)."""
        reader = self._readers.get(topic)
        node = self._connection.node
        if reader is not None and node.count_publishers(topic) <= reader.subscription.get_publisher_count():
            return []
        return node.get_publishers_info_by_topic(topic)

    def status(self) -> dict[str, Any]:
        status: dict[str, Any] = {"received": self.received, "dropped": self.dropped, "queued": len(self._queue)}
        if self._discovery is None:
            status["mismatched_publishers"] = self.mismatched_publishers
            return status
        variables = self._discovery.pattern.variables
        status["following"] = {topic: {**{name: reader.meta[name] for name in variables}, "received": reader.received}
                               for topic, reader in sorted(self._readers.items())}
        status.update(self._discovery.status())
        return status

    async def stop(self) -> None:
        if self._pump is None:
            return
        connection = self._connection
        if not self._stopping:
            self._stopping = True
            connection.forget(self)
            for reader in self._readers.values():
                connection._readers.pop(reader.subscription.handle.pointer, None)
            connection._readers_changed()
            self._queue.close()
        await self._pump
        if self._watch is not None:
            self._watch.cancel()
            await asyncio.gather(self._watch, return_exceptions=True)
        connection._sources.discard(self)
        readers, self._readers = list(self._readers.values()), {}
        if connection._node is not None:
            for reader in readers:
                connection._node.destroy_subscription(reader.subscription)


def _cdr_string(raw: bytes) -> bytes:
    """The bytes of a serialized ``std_msgs/String`` (CDR: encapsulation, uint32 length with
    the NUL, bytes, NUL), without decoding them."""
    if len(raw) < 8:
        raise ValueError(f"serialized String of {len(raw)} bytes is truncated")
    size = int.from_bytes(raw[4:8], "little" if raw[1] & 1 else "big")
    if size < 1 or 8 + size > len(raw):
        raise ValueError(f"serialized String claims {size} bytes, has {len(raw) - 8}")
    return bytes(raw[8:8 + size - 1])


def _unused_callback(msg: Any) -> None:
    """rclpy wants a callback; messages are taken by Ros2Source._take instead."""


# ---------------------------------------------------------------- sink

class Ros2Sink(Sink):
    """Publishes each message on its topic (fixed, or rendered from the canonical message).

    Readiness (``require_subscriber``, on by default). A DDS writer with no matched reader
    drops what it publishes, reliable or not, and the source has acknowledged it by then:
    an engine started on an AMQP queue of 10,000 messages for a topic lost all of them before
    discovery matched the subscriber that was waiting. So a sink whose topic no subscriber
    has matched is not :attr:`ready`, and the engine holds the route's messages as it does
    for a connection that is down. Matching is read with ``get_subscription_count()`` (2.8 us
    here), which the engine polls between batches (every 0.2 s while waiting): rclpy's
    matched-event callbacks need an executor, which this endpoint does not run (see the
    module), and a count read where it is needed cannot miss an event.

    A fixed topic's publisher is created with the sink, so discovery is under way before the
    first message. A templated topic's publisher exists only once a message names it: that
    message is refused (a transient error, which the engine does not count as an attempt
    because the sink then says it is not ready) and the sink is not ready until the topic has
    a subscriber. A subscriber that goes away makes the sink not ready
    again, at the next batch; DDS notices one that crashed only when its lease expires, and
    what was published to it meanwhile is lost (for commands that must arrive, have the
    robot answer on a topic of its own).
    """

    def __init__(self, connection: Ros2Connection, route: str, options: Ros2SinkOptions | Mapping[str, Any]) -> None:
        self._connection = connection
        self._template = _topic_of(options)
        self._where = f"route {route!r}, ros2 topic {self._template!r}"
        problems = [message for _, message in TRANSPORT.check_sink(options, None)]
        if problems:
            raise EndpointError(f"{self._where}: {'; '.join(problems)}")
        options = typed(Ros2SinkOptions, options, self._where)
        self._cls = rosmsg.resolve_type(options.type)
        self._string = self._cls() if rosmsg.type_name(self._cls) == STRING_TYPE else None
        self._qos = _qos(options)
        self._require_subscriber = options.require_subscriber
        self._publishers: dict[str, Any] = {}
        self._unmatched: dict[str, Any] = {}
        """Templated topics a message was refused for, until a subscriber matches them."""
        self._was_ready = True
        self._fixed: Any = None
        self._topic_for = _topic_template(self._template)
        if self._topic_for is None:
            self._fixed = self._publisher(self._template)  # early, so discovery is under way before the first send

    @property
    def ready(self) -> bool:
        if not self._require_subscriber:
            return True
        try:
            if self._fixed is not None:
                ready = self._fixed.get_subscription_count() > 0
            else:
                for topic, publisher in list(self._unmatched.items()):
                    if publisher.get_subscription_count() > 0:
                        del self._unmatched[topic]
                ready = not self._unmatched
        except Exception:  # the publisher is gone (the sink or the connection closed)
            ready = False
        if ready is not self._was_ready:
            self._was_ready = ready
            if ready:
                log.info("%s: a subscriber matched; publishing", self._where)
            else:
                log.warning("%s: %s; holding the route's messages", self._where, self.not_ready_reason())
        return ready

    def not_ready_reason(self) -> str | None:
        if not self._require_subscriber:
            return None
        waiting = [self._fixed] if self._fixed is not None else list(self._unmatched.values())
        reasons = []
        for publisher in waiting:
            try:
                if publisher.get_subscription_count() > 0:
                    continue
                topic = publisher.topic_name
                seen = self._connection.node.count_subscribers(topic)
            except Exception:
                continue
            reason = f"no subscriber has matched {topic}"
            if seen:
                reason += f" ({seen} on the topic did not match: incompatible QoS, or discovery under way)"
            reasons.append(reason)
        return "; ".join(reasons) + " (require_subscriber)" if reasons else None

    def _publisher(self, topic: str) -> Any:
        publisher = self._publishers.get(topic)
        if publisher is None:
            with mapped(f"{self._where}: cannot publish on {topic!r}"):
                publisher = self._connection.acquire_publisher(self._cls, topic, self._qos)
            self._publishers[topic] = publisher
        return publisher

    async def send(self, message: Outbound) -> None:
        self._publish(message)

    async def send_batch(self, messages: Sequence[Outbound]) -> list[BaseException | None]:
        """Publishing is synchronous: one pass over the batch, no coroutine per message."""
        results: list[BaseException | None] = []
        for message in messages:
            try:
                self._publish(message)
            except Exception as error:  # classified by the engine's delivery policy
                results.append(error)
            else:
                results.append(None)
        return results

    def _publish(self, message: Outbound) -> None:
        topic = self._template if self._topic_for is None else self._topic_for(message.template_data, self._where)
        publisher = self._publisher(topic)
        if self._string is not None:
            msg = self._string  # publish() serialises at once, so one instance is reused
            try:  # ``with mapped(...)`` spelt out: its generator context manager cost ~1 us a message
                msg.data = _string_data(message)
            except EndpointError:
                raise
            except EXCEPTIONS.catches as exc:
                raise EXCEPTIONS.edge_error(exc, self._where) from exc
        else:
            msg = typed_message(self._cls, message, self._where)
        if publisher is not self._fixed and self._require_subscriber and publisher.get_subscription_count() == 0:
            self._unmatched[topic] = publisher
            raise EndpointError(f"{self._where}: no subscriber has matched {topic} yet (require_subscriber)")
        try:
            publisher.publish(msg)
        except Exception as exc:  # the message was built: whatever rcl says now is not its fault
            raise setup_error(exc, f"{self._where}: publish failed") from exc

    async def close(self) -> None:
        publishers, self._publishers = list(self._publishers.values()), {}
        for publisher in publishers:
            await self._connection.release_publisher(publisher)
        self._connection._sinks.discard(self)


def typed_message(cls: type, message: Outbound, where: str) -> Any:
    """The message of a typed sink, as the sink publishes it and ``rabbitros-engine test``
    builds it. Fields the data does not name keep the message's defaults (a Header without a
    stamp is stamped now). From a sink mapping a null is refused wherever it is (a
    ``sink mapping`` error naming the field): JMESPath gives null for a path the message
    lacks, and neither a default nor NaN may stand in for a value that was not found.
    Without a sink mapping the canonical message is the data, and a null float is NaN (the
    ROS -> JSON -> ROS round trip; see rosmsg.py)."""
    with mapped(where):
        return rosmsg.from_dict(cls, message.fields, null_as_nan=message.fields is message.canonical)


def _string_data(message: Outbound) -> str:
    """The canonical JSON bytes as they came (identity routes stay byte-exact); when the route
    has a mapping, its result: a string as is, anything else as compact JSON."""
    if message.fields is message.canonical:
        return message.body.decode("utf-8")
    if isinstance(message.fields, str):
        return message.fields
    return json.dumps(message.fields, ensure_ascii=False, separators=(",", ":"))


def _topic_template(topic: str) -> Callable[[Any, str], str] | None:
    """``/{agent_id}/weeds`` -> a function of the canonical dict; None for a fixed topic.
    rcl's own substitutions ({node}, {ns}, {namespace}) are left to rcl."""
    parts = _PLACEHOLDER.split(topic)
    literals, paths = parts[0::2], [p.split(".") for p in parts[1::2]]
    if all(".".join(p) in _RCL_SUBSTITUTIONS for p in paths):
        return None

    def resolve(canonical: Any, where: str) -> str:
        out = [literals[0]]
        for path, literal in zip(paths, literals[1:]):
            if ".".join(path) in _RCL_SUBSTITUTIONS:
                out.append("{" + path[0] + "}")
            else:
                value = canonical
                for key in path:
                    value = value.get(key) if isinstance(value, Mapping) else None
                if type(value) is not str and type(value) is not int:
                    raise MessageRejected(f"{where}: field {'.'.join(path)!r} for the topic is "
                                        f"missing or not a string ({value!r})")
                out.append(str(value))
            out.append(literal)
        return "".join(out)

    return resolve


Ros2Transport.connection_type = Ros2Connection  # defined below the transport
