"""Timing the ROS layer for ``nanostage bench`` (never a pass/fail test).

:func:`rclpy_roundtrip_hz`: the middleware's own cost, raw rclpy publish -> subscribe
round trips between two nodes in one process; :func:`graph_loop_hz`: control samples
per second of the whole node graph, in one process or one process per node, timed by a
listener in its own context from the events it hears.
"""
from __future__ import annotations

import os
import tempfile
import threading
import time
from pathlib import Path
from experiment_runner.core.experiment import EXPERIMENT_DIR, build_trials, load_experiment
from experiment_runner.core.recording import read_recording
from experiment_runner.ros.launch import run_one_process, run_processes
from experiment_runner.ros.qos import qos_profile
from experiment_runner.ros.run import isolate, make_executor
from msg_defs import cdr, convert
from msg_defs.topics import EVENTS, MEASURED


def _bench_domain() -> int:
    """A ROS domain in 1..100 for this run (never the default 0)."""
    return 1 + (os.getpid() * 7 + int(time.time())) % 100


def rclpy_roundtrip_hz(n: int = 5000, executor: str | None = None, domain_id: int | None = None,
                       serialized: bool = False) -> float:
    """Raw rclpy round trips per wall-clock second: two nodes in one process (own context),
    ``ping`` publishes a ``JointState`` on a lockstep-QoS topic, ``pong`` republishes it
    on another, ``ping`` sends the next when it comes back, all in one spin of the executor
    (as the graph spins); ``executor`` as
    :func:`experiment_runner.ros.run.make_executor` (``None``: the graph's default).
    ``serialized``: the message travels as CDR bytes both ways (``publish(bytes)``, ``raw``
    subscriptions), as the graph's per-sample messages do, instead of as message objects."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node
    from rclpy.task import Future
    from sensor_msgs.msg import JointState


    domain_id = domain_id or _bench_domain()
    isolate(domain_id)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    try:
        qos = qos_profile(MEASURED)
        ping, pong = Node("bench_ping", context=ctx), Node("bench_pong", context=ctx)
        ping_pub = ping.create_publisher(JointState, "/bench/ping", qos)
        pong_pub = pong.create_publisher(JointState, "/bench/pong", qos)
        msg = JointState(name=["table"], position=[0.0])
        count = [0]
        done = Future()

        def back(m):
            count[0] += 1
            if count[0] < n:
                if serialized:
                    ping_pub.publish(cdr.joint_state(count[0], ("table",), position=(float(count[0]),)))
                else:
                    msg.header.stamp.nanosec = count[0]
                    msg.position[0] = float(count[0])
                    ping_pub.publish(msg)
            else:
                done.set_result(True)

        pong.create_subscription(JointState, "/bench/ping", pong_pub.publish, qos, raw=serialized)
        ping.create_subscription(JointState, "/bench/pong", back, qos, raw=serialized)
        if serialized:
            msg = cdr.joint_state(0, ("table",), position=(0.0,))
        ex = make_executor(ctx, executor)
        ex.add_node(ping)
        ex.add_node(pong)
        deadline = time.monotonic() + 10.0
        while (ping_pub.get_subscription_count() < 1 or pong_pub.get_subscription_count() < 1) \
                and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        for _ in range(20):                       # let discovery finish
            ex.spin_once(timeout_sec=0.01)
        t0 = time.perf_counter()
        ping_pub.publish(msg)
        ex.spin_until_future_complete(done, timeout_sec=120.0)     # one spin, as the graph's
        hz = count[0] / (time.perf_counter() - t0)
        ex.shutdown()
        ping.destroy_node()
        pong.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    return hz


class _EventClock:
    """Wall-clock arrival times of ``/experiment/events`` (own context, own thread)."""

    def __init__(self, domain_id: int):
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.node import Node

        self.events: list[tuple[float, dict]] = []
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=domain_id)
        self.node = Node("bench_event_clock", context=self.ctx)
        self.node.create_subscription(
            convert.message_class(None, EVENTS.msg_type), EVENTS.name,
            lambda m: self.events.append((time.perf_counter(), convert.parse_event(m.data))), qos_profile(EVENTS))
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        while not self.stop and self.ctx.ok():
            self.ex.spin_once(timeout_sec=0.05)

    def close(self):
        import rclpy
        time.sleep(0.3)                           # the last events are on their way
        self.stop = True
        self.thread.join(timeout=5.0)
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)

    def rate(self, lengths: dict[int, int], skip: int = 1) -> tuple[float, int]:
        """Control samples per wall second from the first trial_start heard to the last
        trial_end (trials in between are contiguous), and the samples counted; the first
        ``skip`` trials are left out (warm-up: numba caches, first messages of each type)."""
        starts = {e["trial"]: t for t, e in self.events if e["event"] == "trial_start"}
        ends = {e["trial"]: t for t, e in self.events if e["event"] == "trial_end"}
        done = sorted(i for i in starts if i in ends and i >= skip)
        if not done:
            return float("nan"), 0
        first, last = done[0], done[-1]
        samples = sum(lengths[i] for i in range(first, last + 1))
        return samples / (ends[last] - starts[first]), samples


def graph_loop_hz(processes: bool, trials: int = 6, domain_id: int | None = None) -> dict:
    """Control samples per wall-clock second of the whole node graph (plant, servo, dither,
    SAI manager, recorder, sequencer) on ``fi_p2p_5um`` with ``trials`` trials, over the
    trial portion only (trial 0 is a warm-up, not timed); one process
    (:func:`~experiment_runner.ros.launch.run_one_process`) or one per node
    (:func:`~experiment_runner.ros.launch.run_processes`). ``hz`` is None if the run failed.

    ``messages_per_sample``: messages the graph published per control sample, counted in the
    run's recording (every topic the graph publishes is recorded except the internal
    ``/sai/command``, which the FI stage does not use), over all trials."""
    import yaml

    domain_id = domain_id or _bench_domain()
    isolate(domain_id)
    with tempfile.TemporaryDirectory(prefix="nanostage_bench_") as tmp:
        doc = yaml.safe_load((EXPERIMENT_DIR / "fi_p2p_5um.yaml").read_text())
        doc.update(name="bench_fi_p2p", trials=int(trials))
        exp_path = Path(tmp) / "bench_fi_p2p.yaml"
        exp_path.write_text(yaml.safe_dump(doc))
        lengths = {t.index: len(t.x_ref) for t in build_trials(load_experiment(exp_path))}
        clock = _EventClock(domain_id)
        try:
            if processes:
                code = run_processes(str(exp_path), Path(tmp) / "run", timeout=300.0, domain_id=domain_id)
                ok = code == 0
            else:
                summary = run_one_process(str(exp_path), Path(tmp) / "run", timeout=300.0, domain_id=domain_id)
                ok = summary["done"] and not summary["aborted"]
        finally:
            clock.close()
        hz, samples = clock.rate(lengths)
        per_sample = None
        if ok:
            rec = read_recording(Path(tmp) / "run")
            per_sample = sum(rec.counts.values()) / sum(lengths.values())
    return {"hz": hz if ok and samples else None, "samples": samples, "ok": ok, "messages_per_sample": per_sample}
