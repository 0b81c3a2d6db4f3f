"""The route file's own keys (``routes:`` items, ``connections.<name>`` limits, ``lease:``),
declared once with engine/common/options.py: the loader parses them and
engine/language/route_schema.py builds the route-file JSON Schema from them."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from engine import endpoints
from engine.common.options import option
from engine.language.stage_options import (DEFAULT_MAX_ATTEMPTS, DEFAULT_MAX_MESSAGE_BYTES, BufferOptions, DedupeOptions, FairOptions, ReplyOptions,
                                           ThrottleOptions)
from engine.language.stores import RememberOptions
from engine.language.window_options import WindowOptions

NAME_PATTERN = "^[A-Za-z0-9_][A-Za-z0-9_.-]*$"
"""Connection, route and lease names: safe in queue names, file names and metrics labels."""


# The route file's own keys, declared once (engine/common/options.py); engine/language/route_schema.py builds
# the route-file JSON Schema from these and from each protocol's option classes.

@dataclass(frozen=True, kw_only=True)
class ConnectionLimits:
    """Keys of ``connections.<name>`` beside the protocol key that every protocol has."""

    max_message_bytes: int = option(DEFAULT_MAX_MESSAGE_BYTES, minimum=1,
                                    description="larger messages in or out of this connection are dead-lettered unparsed")


@dataclass(frozen=True, kw_only=True)
class LeaseOptions:
    __schema_description__ = "active_standby: the lease queue's connection and timing"

    connection: str | None = option(None, description="connection holding the lease (one that holds leases: a broker); default: the sink's if it can, else the only one that can")
    heartbeat: float = option(1.0, exclusive_minimum=0, description="seconds between the active instance's heartbeats")
    name: str | None = option(None, pattern=NAME_PATTERN,
                              description="lease shared by routes that must fail over together (one robot's topics); default: the route name")


@dataclass(frozen=True, kw_only=True)
class OrderedOptions:
    """``ordered: {partitions: S, key: ...}``: order per key (an agent) kept across several
    engine instances that share the route, instead of one instance carrying all of it
    (``ordered: true``). How a source partitions is its transport's (``Transport.partition_problems``)."""

    __schema_description__ = ("partitioned order: the broker hashes each message's key to one of `partitions` queues, each "
                              "consumed by one instance at a time; the instances spread the partitions among themselves, so "
                              "messages with one key stay in order while the route scales out (docs/operations.md, Partitioned ordered routes)")

    partitions: int = option(minimum=2, maximum=256, description=(
        "how many partitions (queues rabbitros.<route>.p0..): at most this many instances share the route; classic queues, since "
        "RabbitMQ 3.10 quorum queues may hand a dead consumer's messages out after newer ones (rabbitmq-server#6804), so a "
        "quorum queue_type is refused; changing it moves keys between partitions (drain the route first)"))
    key: str = option("routing_key", description=(
        "what the broker hashes to pick a message's partition: routing_key (the cheap default: publish with the agent in "
        "the routing key, e.g. telemetry.robot7) or headers.NAME (a header the publisher sets); a field of the body needs a "
        "route before this one that republishes with routing_key: '{agent_id}' (one more hop per message)"))


ENDPOINT_DESCRIPTION = "exactly one of " + " / ".join(endpoints.PROTOCOLS)
SINK_MAPPING_DESCRIPTION = ("JMESPath from the canonical message to the sink's fields (a typed message, "
                            "a mission's items); absent or null: the canonical message")
DEFAULT_FALLBACK_AFTER = 5.0


@dataclass(frozen=True, kw_only=True)
class FallbackKeys:
    """``fallback:`` of a sink, beside its one protocol key (the fallback sink's options).
    engine/running/fanout.py acts on it."""

    __schema_description__ = (
        "where the sink's messages go while it cannot take them: what it refuses for good or returns "
        "unroutable goes here at once; while it cannot take messages (its connection down, not ready) they "
        "wait 'after' seconds, then go here until it can again (then new messages go to it: the fallback gives back); "
        "exactly one protocol key, as a sink")

    after: float = option(DEFAULT_FALLBACK_AFTER, minimum=0, description=(
        "seconds the primary may be unable to take messages before they go to the fallback (0: at once)"))
    mapping: str | None = option(None, nullable=True, description=SINK_MAPPING_DESCRIPTION + " (the fallback's own)")


@dataclass(frozen=True, kw_only=True)
class SinkKeys:
    """The keys of a sink beside its one protocol key: ``sink:`` and each item of ``sinks:``."""

    name: str | None = option(None, pattern=NAME_PATTERN, description=(
        "names the sink in dead letters, status and route tests; default: its protocol key (with its "
        "position, as in PROTOCOL.1, when two sinks of a route have the same protocol)"))
    mapping: str | None = option(None, nullable=True, description=SINK_MAPPING_DESCRIPTION)
    when: str | None = option(None, description=(
        "condition: JMESPath on the canonical message (meta(name) reads the source's metadata): the sink gets "
        "only the messages it gives true for (false, null, empty: not this sink); a message no sink takes is "
        "settled and counted filtered"))
    fallback: dict[str, Any] | None = option(None, description="see routes[].sink.fallback")


@dataclass(frozen=True, kw_only=True)
class RouteOptions:
    """One item of ``routes:``. ``source`` and ``sink`` hold one protocol key each, whose
    options the protocol's transport declares (``Transport.source_options``/``sink_options``)."""

    name: str = option(pattern=NAME_PATTERN, description="unique across the directory; names the route in logs, metrics, "
                                                         "dead-letter headers and /tap/NAME; with for_each, {var} in it takes each item's value")
    for_each: tuple[dict[str, Any], ...] | str | None = option(
        None, description="a route template: one route per item (an object of variables), listed here or in a YAML file of "
                          "such a list beside the route file (watched), or agents: one route per agent of the agents table that has "
                          "every variable the route uses ({agent} its name); {var} in the name and in any string value "
                          "takes the item's value, and mappings read it with meta('var')")
    description: str | None = option(None, description="free text")
    max_attempts: int = option(DEFAULT_MAX_ATTEMPTS, minimum=1,
                               description="deliveries tried on transient sink failures (across redeliveries) before dead-lettering")
    overflow: Literal["block", "drop_oldest", "drop_newest"] = option(
        "block", description="when the in-memory queue of a source that pushes messages is full: block stops taking (where the "
                             "protocol can be paused; each source's description says what it does otherwise), or drop the oldest / newest (counted)")
    buffer: Literal[False] | BufferOptions | None = option(
        None, description="messages held while the sink is down (default for sources that cannot redeliver: in memory, 10000); false: none")
    source: dict[str, Any] = option(description=ENDPOINT_DESCRIPTION)
    mapping: str | None = option(None, nullable=True, description="JMESPath from the source message to the canonical message; "
                                                                  "absent or null: identity (the original bytes are forwarded)")
    schema: str | None = option(None, description="required: the canonical schema the mapping's result must satisfy, NAME (newest "
                                                  "version) or NAME.vN (pinned), from schemas/; raw_json passes any object")
    when: str | None = option(None, description=(
        "condition: JMESPath on the canonical message (meta(name) reads the source's metadata); a message for which it "
        "gives false, null or an empty string, list or object is settled unsent and counted filtered, never dead-lettered"))
    dedupe: DedupeOptions | None = option(None)
    window: WindowOptions | None = option(None)
    throttle: ThrottleOptions | None = option(None)
    fair: FairOptions | None = option(None)
    remember: RememberOptions | tuple[RememberOptions, ...] | None = option(None)
    priority: Literal["high", "normal", "low"] = option(
        "normal", description="on a link several routes share (a telemetry radio), the order of what is sent next: high before "
                              "normal before low, tunnel routes included; commands and missions always go first")
    max_age: float | None = option(None, exclusive_minimum=0, description=(
        "seconds from reception after which a message is worthless (telemetry): one older when it would be sent (from "
        "the buffer after an outage, a throttle slot, a retry) is dropped and counted expired; absent: every message arrives"))
    sink: dict[str, Any] | None = option(None, description=ENDPOINT_DESCRIPTION + "; or sinks:")
    sinks: tuple[dict[str, Any], ...] | None = option(None, min_items=1, description=(
        "several sinks (instead of sink:), each as sink: with its own mapping, when and fallback: a message is "
        "converted once and settled at its source once every sink chosen for it settled it (delivered, or "
        "dead-lettered naming the sink: one dead letter for a message, whatever the number of sinks)"))
    reply: ReplyOptions | None = option(None)
    ordered: bool | OrderedOptions = option(False, description=(
        "true: one engine instance at a time carries the route, in order (sources whose broker offers it: a single active "
        "consumer); {partitions: N, key: ...}: order per key (agent), the partitions spread over the instances"))
    instances: tuple[str, ...] | None = option(None, min_items=1,
                                               description="run the route only on these engine instances (--instance NAME, default the host name)")
    active_standby: bool = option(False, description="every instance runs the source, only the holder of the broker lease forwards")
    lease: LeaseOptions | None = option(None)
    record: bool = option(True, description="with --record DIR: record what the route receives and the canonical messages it "
                                            "sends (MCAP, docs/operations.md); false leaves the route out of the recording")
