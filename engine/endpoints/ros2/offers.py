"""What a topic's publishers offer, and the QoS a source asks for in return.

A DDS reader matches a writer only when the writer offers at least what the reader requests:
a reliable reader never matches a best-effort writer (the ``sensor_data`` QoS most sensor
drivers publish with), a transient_local reader never matches a volatile one. A source that
asked for reliable by default therefore received nothing from such a robot, and nothing said
so. A source whose route leaves ``qos.reliability`` or ``qos.durability`` unstated takes that
policy from its publishers instead, as rosbag2's recorder does (``adapt_request_to_offers`` in
rosbag2_transport's qos.cpp; foxglove_bridge and zenoh-bridge-ros2dds do the same):

- reliable only if every publisher offers reliable, else best-effort (a best-effort reader
  matches both kinds; a reliable publisher's messages are then not resent when lost);
- transient_local only if every publisher offers it (then the publishers' kept messages are
  received on matching), else volatile (matches both);
- without any publisher: the route's default (reliable, volatile), until one appears.

Deadline and liveliness stay at their defaults (infinite, automatic), which match every
writer. A stated policy is kept as written; a publisher whose offer cannot match it is named
(:func:`refusals`): rclpy's ``qos_check_compatible`` gives the verdict, as ``ros2 doctor``'s.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Sequence

from rclpy.qos import DurabilityPolicy, QoSCompatibility, QoSProfile, ReliabilityPolicy, qos_check_compatible

POLICIES = frozenset({"reliability", "durability"})
"""The policies that decide whether a reader matches a writer and that a source adapts."""


@dataclass(frozen=True)
class Offer:
    """One publisher of the source's type: which node, on which topic, offering what."""

    topic: str
    node: str
    profile: QoSProfile

    @property
    def policies(self) -> str:
        return describe(self.profile)


def describe(profile: QoSProfile) -> str:
    """``best_effort volatile``: the two policies in the route file's words."""
    return f"{_word(profile.reliability)} {_word(profile.durability)}"


def _word(policy: Any) -> str:
    return policy.name.lower() if hasattr(policy, "name") else str(policy)


def offers_of(topic: str, infos: Iterable[Any], type_name: str) -> list[Offer]:
    """The offers of ``topic``'s publishers of ``type_name`` (rclpy's ``TopicEndpointInfo``)."""
    return [Offer(topic, f"{info.node_namespace.rstrip('/')}/{info.node_name}", info.qos_profile)
            for info in infos if info.topic_type == type_name]


def adapted(requested: QoSProfile, stated: frozenset[str], offers: Sequence[Offer]) -> QoSProfile:
    """``requested`` with each policy the route did not state taken from ``offers`` (the
    module's rules); ``requested`` itself when there is nothing to adapt or no offer."""
    if not offers or stated >= POLICIES:
        return requested
    reliability, durability = requested.reliability, requested.durability
    if "reliability" not in stated:
        every = all(offer.profile.reliability == ReliabilityPolicy.RELIABLE for offer in offers)
        reliability = ReliabilityPolicy.RELIABLE if every else ReliabilityPolicy.BEST_EFFORT
    if "durability" not in stated:
        every = all(offer.profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for offer in offers)
        durability = DurabilityPolicy.TRANSIENT_LOCAL if every else DurabilityPolicy.VOLATILE
    return QoSProfile(history=requested.history, depth=requested.depth, reliability=reliability, durability=durability)


def same_policies(one: QoSProfile, other: QoSProfile) -> bool:
    return one.reliability == other.reliability and one.durability == other.durability


def refusals(requested: QoSProfile, offers: Iterable[Offer]) -> list[str]:
    """Each offer the reader cannot match, named: ``/robot9/gps on /robot9/fix offers
    best_effort volatile, the route requests reliable volatile (Best effort publisher and
    reliable subscription)``."""
    out = []
    for offer in offers:
        verdict, reason = qos_check_compatible(offer.profile, requested)
        if verdict == QoSCompatibility.ERROR:
            why = reason.removeprefix("ERROR:").strip().rstrip(";")
            out.append(f"{offer.node} on {offer.topic} offers {offer.policies}, the route requests "
                       f"{describe(requested)} ({why})")
    return out
