"""Discovery: a ROS 2 source topic with ``{var}`` segments follows every matching topic.

``/{agent}/fix`` is a pattern: each ``{var}`` stands for exactly one name segment (``/robot3/fix``
matches with ``agent = robot3``; ``/farm/robot3/fix`` does not match). The source subscribes to
every topic of the graph that matches and has a publisher of the route's type, as it appears,
with the route's QoS (policies it leaves out: what the publishers offer, source.py); each message carries the captured values as metadata (``meta('agent')``),
which sink templates read too (``farm.{agent}.fix``). A followed topic that has had no
publisher of that type for ``forget_after`` seconds is let go (its subscription destroyed); if a
publisher comes back it is followed again. A matching topic of another type is reported once
(a warning in the log, and the status), never subscribed: a wide pattern (``/{name}``) matches
``/rosout`` and ``/parameter_events`` too, which is no failure. Which ``{var}`` is a discovery
variable is decided at load: ``for_each`` variables are filled in before the endpoint sees the
topic, so any ``{var}`` left in a ROS 2 source topic is one (``check`` warns in a ``for_each``
route, where it may be a misspelt item variable).

How the graph is read. rclpy (Jazzy) exposes no graph event to Python (rcl's graph guard
condition is not bound), so the connection polls ``Node.get_topic_names_and_types()`` every
:data:`DISCOVERY_INTERVAL`, once for all its discovering sources. Measured on the 2-core
development machine: 40 us per call with 20 topics in the graph, 170 us with 100, 820 us with
300 (0.02 %, 0.07 % and 0.3 % of a core at 4 scans/s). The publishers of a matching topic are read
with ``get_publishers_info_by_topic`` only where the topic's types include the route's (a topic
that has only subscribers is not followed: nothing would ever arrive). A followed topic's
publishers are its subscription's matched publishers (``get_publisher_count()``, a counter rcl
keeps: no graph query), read at every scan, so a topic is let go between ``forget_after`` and
``forget_after`` + one scan after DDS has said its last publisher left (at once for one that
closed; at its liveliness lease's end for one that crashed), never sooner.

Latency from a publisher's creation to its first message at the sink is DDS discovery of the
publisher, up to one scan interval, then DDS matching of the new subscription (the publisher's
side must discover it too): bench/bench_discovery.py measures it. What a publisher sends before
the subscription has matched is not received (a volatile DDS writer keeps nothing for readers
that join later); a publisher that must lose nothing waits for ``get_subscription_count() > 0``
or publishes transient_local to a route whose ``qos.durability`` is transient_local or left out.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

from rclpy.expand_topic_name import expand_topic_name

from engine.common.placeholders import Placeholder, TemplateError, capture_levels, scan_placeholders
from engine.common.shares import share_of

log = logging.getLogger("engine.ros2")

DISCOVERY_INTERVAL = 0.25
"""Seconds between two reads of the graph (see the module for what one costs)."""
DEFAULT_FORGET_AFTER = 30.0
"""Seconds a followed topic may go without a publisher before it is let go: a robot that
restarts (tens of seconds) keeps its subscription, one that left the farm does not hold it."""

RCL_SUBSTITUTIONS = frozenset({"node", "ns", "namespace"})
"""``{node}``, ``{ns}``, ``{namespace}``: rcl fills them from the node; never variables."""
RESERVED = frozenset({"topic", "type", "route", "generation", "test"})
"""Metadata names a message already carries (the source's topic and type, the route's name and
generation, a route test's mark): a variable of that name would overwrite them."""
_MARKER = "rabbitrosvar{}x"
"""A valid name token standing for variable ``i`` while the topic is expanded by rcl's rules."""


def topic_variables(topic: str | None) -> tuple[str, ...]:
    """The discovery variables of a source topic, in order, each once (rcl's own substitutions
    aside), read by the engine's one placeholder grammar (engine/common/placeholders.py)."""
    if not topic:
        return ()
    return tuple(dict.fromkeys(found.name for found in scan_placeholders(topic) if found.name not in RCL_SUBSTITUTIONS))


def pattern_problem(topic: str) -> str | None:
    """Why ``topic`` is no valid pattern: a variable inside a segment (``/robot{n}/fix``), one
    with a format spec or a dotted path (placeholders.capture_levels), or one whose name the
    message's metadata already uses."""
    try:
        levels = capture_levels(topic, keep=RCL_SUBSTITUTIONS, level="name segment", example="/{name}/fix")
    except TemplateError as exc:
        return str(exc)
    for level in levels:
        if isinstance(level, Placeholder) and level.name in RESERVED:
            return (f"topic {topic!r}: variable {{{level.name}}} would hide the message's own meta({level.name!r}); "
                    f"name it otherwise (reserved: {', '.join(sorted(RESERVED))})")
    return None


def _replace_variables(topic: str) -> tuple[str, dict[str, str]]:
    """The topic with each variable's level replaced by a marker rcl accepts as a name."""
    markers: dict[str, str] = {}
    levels = capture_levels(topic, keep=RCL_SUBSTITUTIONS)
    sample = "/".join(markers.setdefault(level.name, _MARKER.format(len(markers))) if isinstance(level, Placeholder)
                      else level for level in levels)
    return sample, markers


@dataclass(frozen=True)
class TopicPattern:
    """A source topic's pattern, expanded as rcl expands the topic of a subscription (relative
    names in the node's namespace, ``~`` and ``{node}`` from the node), compiled once."""

    text: str
    regex: re.Pattern[str]
    variables: tuple[str, ...]

    def match(self, topic: str) -> dict[str, str] | None:
        """The captured values of a fully qualified topic name, or None."""
        found = self.regex.match(topic)
        return None if found is None else {name: found.group(name) for name in self.variables}


def compile_pattern(topic: str, node: str, namespace: str) -> TopicPattern:
    sample, markers = _replace_variables(topic)
    expanded = expand_topic_name(sample, node, namespace if namespace.startswith("/") else "/" + namespace)
    variable_of = {marker: name for name, marker in markers.items()}
    seen: set[str] = set()
    parts = []
    for segment in expanded.split("/"):
        name = variable_of.get(segment)
        if name is None:
            parts.append(re.escape(segment))
        elif name in seen:
            parts.append(f"(?P={name})")  # the same variable twice: the same segment twice
        else:
            seen.add(name)
            parts.append(f"(?P<{name}>[^/]+)")
    return TopicPattern(topic, re.compile("/".join(parts) + r"\Z"), tuple(markers))


PublisherTypes = Callable[[str], Sequence[str]]
"""The message types of a topic's publishers (``get_publishers_info_by_topic``)."""
Matched = Callable[[str], int]
"""How many publishers a followed topic's subscription has matched."""


@dataclass(eq=False)
class Discovery:
    """Which topics one source follows, decided from each read of the graph.

    ``follow(topic, captured)`` subscribes (False if it could not: tried again at the next
    scan, reported once); ``matched(topic)`` counts a followed topic's matched publishers;
    ``let_go(topic)`` unsubscribes. Runs on the engine's loop.
    """

    pattern: TopicPattern
    type_name: str
    forget_after: float
    where: str
    follow: Callable[[str, Mapping[str, str]], bool]
    matched: Matched
    let_go: Callable[[str], None]
    followed: dict[str, float | None] = field(default_factory=dict)
    """Followed topic -> since when its subscription has matched no publisher (monotonic), or
    None while it has one."""
    mismatched: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Matching topics of another type -> their types (reported once, never subscribed)."""
    unmatched: set[str] = field(default_factory=set)
    """Followed topics whose publishers of the route's type the subscription has not matched
    for ``forget_after`` (an incompatible QoS): kept, reported once."""
    share: tuple[int, int] | None = None
    """(index, count) of a worker of ``run --workers N``: only the topics whose stable hash falls
    in this share are followed (every other worker follows the rest); None: every topic."""
    discovered: int = 0
    forgotten: int = 0
    _failed: set[str] = field(default_factory=set)

    def scan(self, topics: Iterable[tuple[str, Sequence[str]]], publisher_types: PublisherTypes, now: float) -> None:
        present: set[str] = set()
        for topic, types in topics:
            if topic in self.followed:
                continue
            captured = self.pattern.match(topic)
            if captured is None or (self.share is not None and share_of(topic, self.share[1]) != self.share[0]):
                continue
            present.add(topic)
            if self.type_name not in types:
                self._mismatch(topic, tuple(sorted(types)))
            elif self.type_name in publisher_types(topic):
                self._follow(topic, captured)
        for topic in set(self.mismatched) - present - set(self.followed):
            del self.mismatched[topic]  # gone from the graph: reported again if it comes back
        self._check_liveness(publisher_types, now)

    def _mismatch(self, topic: str, types: tuple[str, ...]) -> None:
        if self.mismatched.get(topic) != types:
            self.mismatched[topic] = types
            log.warning("%s: topic %s matches but has type %s, not %s; not subscribed",
                        self.where, topic, ", ".join(types), self.type_name)

    def _follow(self, topic: str, captured: Mapping[str, str]) -> None:
        if not self.follow(topic, captured):
            if topic not in self._failed:
                self._failed.add(topic)
                log.error("%s: cannot subscribe to discovered topic %s; trying again", self.where, topic)
            return
        self._failed.discard(topic)
        self.mismatched.pop(topic, None)
        self.followed[topic] = None
        self.discovered += 1
        log.info("%s: following %s (%s)", self.where, topic,
                 ", ".join(f"{name}={value}" for name, value in captured.items()))

    def _check_liveness(self, publisher_types: PublisherTypes, now: float) -> None:
        for topic, absent_since in list(self.followed.items()):
            if self.matched(topic) > 0:
                self.followed[topic] = None
                self.unmatched.discard(topic)
            elif absent_since is None:
                self.followed[topic] = now
            elif now - absent_since < self.forget_after:
                continue
            elif self.type_name in publisher_types(topic):  # published, yet never matched: QoS
                self.followed[topic] = now  # kept (a publisher with a compatible QoS may come), said once
                if topic not in self.unmatched:
                    self.unmatched.add(topic)
                    log.warning("%s: %s has a publisher of %s that the subscription does not match (incompatible QoS?); "
                                "kept", self.where, topic, self.type_name)
            else:
                del self.followed[topic]
                self.unmatched.discard(topic)
                self.let_go(topic)
                self.forgotten += 1
                log.info("%s: let go of %s (no publisher for %.1f s)", self.where, topic, now - absent_since)

    def status(self) -> dict[str, Any]:
        return {"discovered": self.discovered, "forgotten": self.forgotten,
                "mismatched_topics": {topic: list(types) for topic, types in sorted(self.mismatched.items())},
                "unmatched_topics": sorted(self.unmatched)}
