"""rclpy QoS profiles of the contract topics (their QoS as plain data is in
:mod:`msg_defs.topics`).

>>> from rclpy.qos import DurabilityPolicy
>>> qos_profile("/experiment/config").depth
1
>>> subscription_qos("/stage/measured").durability == DurabilityPolicy.VOLATILE
True
>>> subscription_qos("/stage/measured", record=True).durability == DurabilityPolicy.TRANSIENT_LOCAL
True
"""
from __future__ import annotations

from dataclasses import replace

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from msg_defs.topics import Qos, Topic, get_topic

__all__ = ["qos_profile", "subscription_qos"]


def _qos_of(topic) -> Qos:
    return topic if isinstance(topic, Qos) else get_topic(topic).qos


def qos_profile(topic: Topic | Qos | str) -> QoSProfile:
    """The ``QoSProfile`` a topic's publishers offer."""
    q = _qos_of(topic)
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST if q.history == "keep_last" else HistoryPolicy.KEEP_ALL,
        depth=q.depth,
        reliability=ReliabilityPolicy.RELIABLE if q.reliability == "reliable" else ReliabilityPolicy.BEST_EFFORT,
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if q.durability == "transient_local"
                    else DurabilityPolicy.VOLATILE))


def subscription_qos(topic: Topic | str, record: bool = False) -> QoSProfile:
    """The ``QoSProfile`` a subscriber of ``topic`` requests: the offered one, except that on
    a per-sample topic (``Topic.stream``) only a recorder (``record``) asks for the samples
    sent before it joined; anyone else gets live samples only."""
    t = get_topic(topic)
    return qos_profile(replace(t.qos, durability="volatile") if t.stream and not record else t.qos)
