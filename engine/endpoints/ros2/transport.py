"""ROS 2 endpoint: one rclpy node per connection, run in step with the engine's asyncio loop
without an executor. This module is the protocol's face to the registry (the
:class:`Ros2Transport`: options, checks, dry runs, the contract's questions); the parts are
one module per concern: options.py (typed options), checks.py (static checks), topics.py
(topic names and their placeholders), errors.py (rclpy's failures as the two edge errors),
waiter.py (the thread that replaces an executor, and why), node.py (the node and what its
sources and sinks share), connection.py (the connection that makes them), source.py and
sink.py (a topic's two ends), calls.py (services and actions), discovery.py (topics found by
pattern), rosmsg.py (messages as dicts) and contract.py (what the core's checks ask of a type).
"""

from __future__ import annotations

from dataclasses import replace as evolve
from typing import Any, Callable, Iterable, Mapping

from engine.endpoints.base import CheckResult, Connection, FieldProblem, MessageRejected, Outbound, Transport
from engine.endpoints.ros2 import calls as ros2_calls, checks, contract as ros2_contract, rosmsg
from engine.endpoints.ros2.connection import Ros2Connection
from engine.endpoints.ros2.options import (
    STRING_TYPE, Ros2ConnectionOptions, Ros2EndpointOptions, Ros2SinkOptions, Ros2SourceOptions, env_domain_id,
)
from engine.endpoints.ros2.sink import typed_message
from engine.endpoints.ros2.topics import topic_fields, topic_template


class Ros2Transport(Transport):
    name = "ros2"
    connection_type = Ros2Connection
    default_settings = {"node": "rabbitros_engine", "namespace": "", "domain_id": env_domain_id()}
    connection_options = Ros2ConnectionOptions
    replies = True
    """A source that offers a service answers its callers (engine.endpoints.ros2.calls.py)."""
    source_options = Ros2SourceOptions
    sink_options = Ros2SinkOptions
    source_meta = ("topic",)

    def source_variables(self, options: Ros2SourceOptions) -> tuple[str, ...]:
        """A topic's ``{var}`` segments (engine/endpoints/ros2/discovery.py)."""
        return checks.source_variables(options)

    def meta_names(self, options: Ros2SourceOptions) -> tuple[str, ...]:
        return (*self.source_meta, *self.source_variables(options))

    def splits_over_workers(self, options: Ros2SourceOptions) -> bool:
        """A topic pattern (``/{agent}/fix``): each worker follows its share of the topics discovered."""
        return options.service is None and bool(self.source_variables(options))

    def split_source(self, options: Ros2SourceOptions, share: int, shares: int) -> Ros2SourceOptions:
        return evolve(options, share=(share, shares))

    def connection_problems(self, options: Ros2ConnectionOptions) -> CheckResult:
        return checks.connection_problems(options)

    def source_answers(self, options: Ros2EndpointOptions) -> bool:
        return options.service is not None  # a topic's publishers await no answer

    def queues_per_agent(self, options: Ros2EndpointOptions) -> bool:
        return options.service is None  # a topic's messages wait in the route's inbox

    def source_problems(self, options: Ros2SourceOptions, mapping: str | None) -> CheckResult:
        return checks.source_problems(options, mapping)

    def sink_problems(self, options: Ros2SinkOptions, mapping: str | None) -> CheckResult:
        return checks.sink_problems(options, mapping)

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
        return [("topic", name) for name in topic_fields(options.topic)]

    # What the core's checks and dry runs ask (contract.py).

    def sink_dry_run(self, route: str, options: Ros2SinkOptions) -> Callable[[Outbound], str | None]:
        name = options.service or options.action
        if name is not None:  # a call: the request or goal built as the sink builds it
            cls, kind = checks.sink_class(options), "service" if options.service else "action"
            where = f"route {route!r}, ros2 {kind} {name!r}"
            return lambda outbound: (typed_message(cls, outbound, where), name)[1]
        topic = options.topic
        assert topic is not None  # a sink names a topic, a service or an action (checked at load)
        return ros2_contract.sink_dry_run(route, topic, options.type, topic_template(topic), typed_message)

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
