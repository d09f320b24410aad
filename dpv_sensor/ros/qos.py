"""The QoS of the node's topics and what is said about it: the profiles (reliability, history depth), the
incompatible-QoS events of every subscription and publisher (counted per topic for /diagnostics and warned about),
and the topic name of an input or output (``topic_names``: a camera_info or transport follows its remapped image)."""
from __future__ import annotations

import collections

from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from dpv_sensor.ros.fault_kinds import INCOMPATIBLE_QOS
from dpv_sensor.ros.topic_names import topic_name

RELIABILITY = {'best_effort': ReliabilityPolicy.BEST_EFFORT, 'reliable': ReliabilityPolicy.RELIABLE}


def profile(reliability: str, depth: int) -> QoSProfile:
    """Keep-last `depth`, volatile, at `reliability` ('best_effort' or 'reliable')."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=RELIABILITY[reliability],
                      durability=DurabilityPolicy.VOLATILE)


def offered_reliability(info) -> str:
    """'reliable' or 'best_effort': what a publisher (``TopicEndpointInfo``) offers."""
    return 'reliable' if info.qos_profile.reliability == ReliabilityPolicy.RELIABLE else 'best_effort'


def resolve(node, name: str) -> str:
    """The topic name of `name` on `node`: a camera_info or transport follows its remapped image topic."""
    return topic_name(name, lambda topic, expand: node.resolve_topic_name(topic, only_expand=expand))


class QosEvents:
    """Event callbacks that count (``counts``, per topic) and report incompatible QoS: a peer whose QoS cannot match
    receives or sends nothing, so it is worth a warning."""

    def __init__(self, faults):
        self.faults = faults
        self.counts: collections.Counter = collections.Counter()

    def _on_incompatible(self, info, topic: str, role: str) -> None:
        self.counts[topic] += max(1, int(getattr(info, 'total_count_change', 1)))
        kind = getattr(info, 'last_policy_kind', '?')
        policy = getattr(kind, 'name', str(kind))
        self.faults.report(INCOMPATIBLE_QOS, f"incompatible QoS on '{topic}' ({policy}): a peer of this {role} "
                           'cannot match it and receives or sends nothing (e.g. a best-effort subscriber of a '
                           'reliable-only topic; see input_reliability / output_reliability)',
                           key=f'{INCOMPATIBLE_QOS}:{topic}')

    def subscription(self, topic: str, **events) -> SubscriptionEventCallbacks:
        """The subscription's callbacks: incompatible QoS, plus `events` (matched, message_lost ...)."""
        return SubscriptionEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible(info, topic, 'subscription'), **events)

    def publisher(self, topic: str, **events) -> PublisherEventCallbacks:
        """The publisher's callbacks: incompatible QoS, plus `events` (matched ...)."""
        return PublisherEventCallbacks(
            incompatible_qos=lambda info: self._on_incompatible(info, topic, 'publisher'), **events)
