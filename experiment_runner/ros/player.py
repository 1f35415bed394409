"""Republish a recording on its topics (what ``nanostage replay`` does, like ``ros2 bag play``).

:func:`replay` republishes every message of a recording (the raw CDR bytes, so exactly
what was recorded) with the contract QoS, and ``/clock`` at each new stage time, paced
at ``rate`` x real time (``rate=0``: as fast as the subscribers acknowledge). It runs an
rclpy node in its own context; the domain comes from ``ROS_DOMAIN_ID`` (or
``domain_id``), so a test or a lab can isolate it, and discovery is a node's
(:func:`~experiment_runner.ros.run.apply_graph_defaults`: localhost-only, every socket on
127.0.0.1, unless the environment opens the graph: ``docs/security.md``).
"""
from __future__ import annotations

import time

from experiment_runner.core.recording import RecordingError
from experiment_runner.core.recording.mcap import load_raw
from experiment_runner.ros.qos import qos_profile
from experiment_runner.ros.run import apply_graph_defaults, check_domain_id
from msg_defs import convert
from msg_defs.topics import CLOCK, CONTRACT_TOPICS, TOPICS, Qos

__all__ = ["replay"]


def _qos_from_metadata(text: str | None) -> Qos:
    """QoS of a non-contract topic from its channel's offered_qos_profiles (default: reliable, 100)."""
    import yaml
    try:
        prof = (yaml.safe_load(text) or [{}])[0]
        depth = int(prof.get("depth") or 100)
        rel = prof.get("reliability")
        dur = prof.get("durability")
        return Qos("best_effort" if rel in ("best_effort", 2) else "reliable",
                   "transient_local" if dur in ("transient_local", 1) else "volatile", max(depth, 1))
    except Exception:                     # noqa: BLE001 - absent or foreign metadata
        return Qos(depth=100)


def replay(path, rate: float = 1.0, *, domain_id: int | None = None,
           topics=None, clock: bool = True, wait_for: int = 0, wait_timeout: float = 10.0,
           node_name: str = "nanostage_replay", log=None) -> dict:
    """Republish a recording on its topics.

    Parameters
    ----------
    path : str or Path
        Recording (MCAP file or bag directory); a file cut short is replayed up to its
        last complete chunk.
    rate : float
        Speed relative to stage time (1 = real time, 2 = twice as fast); 0 = as fast as
        possible (publishers wait for their subscribers' DDS acknowledgements every 200
        messages; a subscriber whose callbacks are slower than the replay still drops
        what overflows its keep-last queue, 1000 samples on the per-sample topics).
    domain_id : int, optional
        ROS domain (default: ``ROS_DOMAIN_ID`` of the environment, else 42); ``ValueError``
        outside 0..232.
    topics : iterable of str, optional
        Only these topics (default all); a :class:`~experiment_runner.core.recording.RecordingError`
        names those the recording does not have.
    clock : bool
        Publish ``rosgraph_msgs/Clock`` at each new log time (recorded ``/clock``
        messages are then not republished, since they carry the same time).
    wait_for : int
        Wait (up to ``wait_timeout`` s) until this many subscriptions match one of the
        contract topics (any of them) before publishing.
    log : callable, optional
        Called with progress strings.

    Returns
    -------
    dict
        ``published`` (messages per topic), ``skipped`` (topics whose type is not
        importable), ``stage_time_s``, ``wall_time_s``, ``salvaged``.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.node import Node

    raw = load_raw(path)
    wanted = None if topics is None else set(topics)
    present = {ch.topic for ch in raw.channels.values()}
    if wanted is not None and wanted - present:
        raise RecordingError(f"{path}: no topic {', '.join(sorted(wanted - present))} in the recording "
                             f"(its topics: {', '.join(sorted(present))})")
    domain_id = check_domain_id(domain_id)
    apply_graph_defaults()                    # localhost-only, on loopback, unless the environment opens it
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    out = {"published": {}, "skipped": {}, "salvaged": raw.salvaged}
    try:
        node = Node(node_name, context=ctx)
        pubs, names = {}, {}
        for ch in raw.channels.values():
            if (wanted is not None and ch.topic not in wanted) or (clock and ch.topic == CLOCK.name):
                continue
            schema = raw.schemas.get(ch.schema_id)
            msg_type = schema.name if schema else "?"
            try:
                cls = convert.message_class(None, msg_type)
            except (ImportError, AttributeError, ValueError) as err:
                out["skipped"][ch.topic] = f"{msg_type}: {err}"
                continue
            qos = TOPICS[ch.topic].qos if ch.topic in TOPICS else _qos_from_metadata(
                ch.metadata.get("offered_qos_profiles"))
            pubs[ch.id] = node.create_publisher(cls, ch.topic, qos_profile(qos))
            names[ch.id] = ch.topic
        clock_pub = (node.create_publisher(convert.message_class(None, CLOCK.msg_type), CLOCK.name,
                                           qos_profile(CLOCK)) if clock else None)
        if wait_for:
            watched = [p for cid, p in pubs.items() if names[cid] in CONTRACT_TOPICS] or list(pubs.values())
            deadline = time.monotonic() + wait_timeout
            while (time.monotonic() < deadline
                   and max((p.get_subscription_count() for p in watched), default=wait_for) < wait_for):
                time.sleep(0.02)
        every_pub = list(pubs.values()) + ([clock_pub] if clock_pub else [])

        def settle():
            for p in every_pub:
                p.wait_for_all_acked(Duration(seconds=5))

        counts: dict[str, int] = {}
        msgs = [m for m in raw.messages if m.channel_id in pubs]
        t0 = msgs[0].log_time if msgs else 0
        wall0 = time.monotonic()
        last = None
        for n, m in enumerate(msgs):
            if rate > 0:
                delay = wall0 + (m.log_time - t0) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            elif n and n % 200 == 0:
                settle()
            if clock_pub is not None and m.log_time != last:
                clock_pub.publish(convert.clock_msg(None, m.log_time))
                last = m.log_time
            pubs[m.channel_id].publish(bytes(m.data))
            topic = names[m.channel_id]
            counts[topic] = counts.get(topic, 0) + 1
            if log is not None and n and n % 10000 == 0:
                log(f"replayed {n} of {len(msgs)} messages (stage time {(m.log_time - t0) * 1e-9:.3f} s)")
        settle()
        out["published"] = counts
        out["stage_time_s"] = (msgs[-1].log_time - t0) * 1e-9 if msgs else 0.0
        out["wall_time_s"] = time.monotonic() - wall0
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    return out
