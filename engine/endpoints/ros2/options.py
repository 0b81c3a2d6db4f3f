"""What a ROS 2 connection, source and sink are declared with (YAML ``connections.<name>.ros2``
and a route's ``ros2:`` ends): typed options that generate the route-file schema and the key
reference, and the QoS profile they describe. Apart from the endpoints so the checks
(checks.py) and the transport read them without importing rclpy's node machinery."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any, Literal, Mapping

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from engine.common.options import option
from engine.endpoints.base import EndpointOptions
from engine.endpoints.ros2 import calls as ros2_calls, discovery

STRING_TYPE = "std_msgs/msg/String"
DEFAULT_DEPTH = 10_000
"""KEEP_LAST depth for both ends: the buffer that covers a stall of the engine or of a reader.
Measured here, a reader stalled for 8 s under 2,000 msg/s lost 40 % of 12,000 messages at
depth 1,000 and none at 10,000 (an earlier project measurement: none at 100,000 either).
10,000 covers about 1 s at the 10,000 msg/s target and 20 s at 500 msg/s, while memory
stays bounded by depth x message size per endpoint (+12 MB after 50,000 messages of 200 B,
against +35 MB at 100,000)."""
_RELIABILITY = {"reliable": ReliabilityPolicy.RELIABLE, "best_effort": ReliabilityPolicy.BEST_EFFORT}
_DURABILITY = {"volatile": DurabilityPolicy.VOLATILE, "transient_local": DurabilityPolicy.TRANSIENT_LOCAL}


def env_domain_id() -> int:
    """``ROS_DOMAIN_ID``, else 0, as every ROS 2 program."""
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
    __schema_description__ = ("the topic's quality of service; a reader and a writer match only when theirs are compatible. "
                              "A source that leaves reliability or durability out takes it from its publishers' offers "
                              "(rosbag2's adaptive QoS), re-matched when they change")

    reliability: Literal["reliable", "best_effort"] = option(
        "reliable", description="reliable: lost samples are resent to matched readers; best_effort: never resent. A source "
                                "without it: reliable if every publisher offers it, else best_effort (no publisher yet: reliable)")
    durability: Literal["volatile", "transient_local"] = option(
        "volatile", description="transient_local: a sink keeps its last depth messages for readers that join later. A "
                                "source without it: transient_local if every publisher offers it (their kept messages "
                                "arrive on matching), else volatile")
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
    share: tuple[int, int] | None = option(None, internal=True)
    """Set by a worker of ``run --workers N`` for a topic pattern: (its index, N). The source
    follows only the discovered topics whose stable hash falls in its share (engine/common/shares.py)."""


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



def topic_of(options: Ros2EndpointOptions | Mapping[str, Any]) -> Any:
    """The topic, for error messages, before the options are known to parse."""
    return options.topic if isinstance(options, Ros2EndpointOptions) else options.get("topic")


def qos_profile(options: Ros2EndpointOptions) -> QoSProfile:
    """The rclpy profile of an endpoint's ``qos`` (always KEEP_LAST: a KEEP_ALL writer could
    block the loop, so it is not offered)."""
    qos = options.qos
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=qos.depth,
        reliability=_RELIABILITY[qos.reliability],
        durability=_DURABILITY[qos.durability],
    )
