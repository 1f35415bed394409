"""What every nanostage node shares: publishers and subscriptions made from the topic
contract, validated parameters, the run configuration, and lockstep sample bookkeeping.

Nodes are thin adapters: they convert messages to the arrays the compiled core
steps take (``msg_defs.convert``) and back; no algorithm lives here.
"""
from __future__ import annotations

import array
import os

import numpy as np
import yaml
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.node import Node

from msg_defs import convert
from msg_defs.topics import Qos, Topic, get_topic, qos_profile

SAI_COMMAND = Topic(
    "/sai/command", "sensor_msgs/msg/JointState", "1, m", Qos("reliable", "volatile", 1000),
    "every control sample, one sample ahead (SAI stages)",
    'name ["isolator"], position [mode] (1 compliant, 0 stiff), effort [x_correction]: the SAI '
    "manager's mode and Step II reference correction for the sample of its stamp")
"""Internal lockstep topic of the graph (not part of a recording)."""

NODE_OF_INPUT = {"/stage/command": "servo_controller", "/stage/dither": "dither_generator",
                 "/sai/command": "sai_manager", "/stage/measured": "plant_sim",
                 "/stage/reference": "servo_controller"}
"""Which node publishes each lockstep input (to name a silent node)."""


def domain_env(domain_id: int | None = None) -> dict:
    """Environment for an isolated graph: explicit domain, localhost-only discovery."""
    env = dict(os.environ)
    if domain_id is not None:
        env["ROS_DOMAIN_ID"] = str(domain_id)
    env.setdefault("ROS_DOMAIN_ID", "42")
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    env.pop("ROS_LOCALHOST_ONLY", None)
    return env


def executor_kind(kind: str | None = None) -> str:
    """``"events"`` (rclpy's C++ ``EventsExecutor``) or ``"single"`` (``SingleThreadedExecutor``):
    ``kind``, else ``NANOSTAGE_EXECUTOR``, else ``"events"`` where rclpy has it."""
    kind = kind or os.environ.get("NANOSTAGE_EXECUTOR") or "events"
    if kind not in ("events", "single"):
        raise ValueError(f"executor {kind!r}: expected 'events' or 'single'")
    if kind == "events":
        try:
            from rclpy.experimental import EventsExecutor  # noqa: F401
        except ImportError:
            return "single"
    return kind


def make_executor(context=None, kind: str | None = None):
    """The executor the nodes spin in (see :func:`executor_kind`).

    The lockstep graph is callback-bound; the ``EventsExecutor`` dispatches callbacks
    from C++ without rebuilding a wait set for each one (3-5x the callback rate of
    the ``SingleThreadedExecutor``, whose wait set here holds ~100 entities).
    """
    if executor_kind(kind) == "events":
        from rclpy.experimental import EventsExecutor
        return EventsExecutor(context=context)
    from rclpy.executors import SingleThreadedExecutor
    return SingleThreadedExecutor(context=context)


def run_node(factory, args=None, until=None, on_exit=None):
    """``main`` of a node executable: init, spin (until ``until(node)`` is true), clean up.

    Ctrl-C / SIGINT ends it cleanly; ``on_exit(node)`` runs last (e.g. close a file).
    """
    import sys

    import rclpy
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
    from rclpy.executors import ExternalShutdownException
    rclpy.init(args=args)
    node = None
    try:
        try:
            node = factory()
        except (ValueError, InvalidParameterValueException,
                InvalidParameterTypeException) as err:                 # bad parameter: say which
            print(f"error: {err}", file=sys.stderr)
            rclpy.shutdown()
            sys.exit(2)
        ex = make_executor()
        ex.add_node(node)
        while rclpy.ok() and not (until and until(node)):
            ex.spin_once(timeout_sec=0.1)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        if node is not None:
            if on_exit:
                on_exit(node)
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()


class StageNode(Node):
    """Base class: contract publishers/subscriptions, validated parameters, run config."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._validators = {}
        self.add_on_set_parameters_callback(self._validate)
        self.config = None            # the run's configuration (dict) once received
        self.on_config = None

    # ----------------------------------------------------------------- topics
    def publisher(self, topic):
        t = topic if isinstance(topic, Topic) else get_topic(topic)
        return self.create_publisher(convert.message_class(None, t.msg_type), t.name, qos_profile(t.qos))

    def subscribe(self, topic, callback):
        t = topic if isinstance(topic, Topic) else get_topic(topic)
        return self.create_subscription(convert.message_class(None, t.msg_type), t.name, callback,
                                        qos_profile(t.qos))

    def listen_config(self, callback):
        """Call ``callback(config_dict)`` when the run configuration arrives (latched)."""
        self.on_config = callback
        self.subscribe("/experiment/config", self._config)

    def _config(self, msg):
        self.config = yaml.safe_load(msg.data)
        if self.on_config:
            self.on_config(self.config)

    # ----------------------------------------------------------------- parameters
    def param(self, name, default, description, lo=None, hi=None, check=None, attr=None):
        """Declare a parameter with a description, an optional range and a validator;
        ``attr``: attribute of the node that follows the parameter when it is set at run time."""
        desc = ParameterDescriptor(description=description)
        if isinstance(default, bool) or lo is None:
            pass
        elif isinstance(default, int):
            desc.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            desc.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi), step=0.0)]
        if check:
            self._validators[name] = check
        if attr:
            if not hasattr(self, "_live"):
                self._live = {}
                self.add_post_set_parameters_callback(self._follow)
            self._live[name] = attr
        value = self.declare_parameter(name, default, desc).value
        if check:
            problem = check(value)
            if problem:
                raise ValueError(f"{self.get_name()}: parameter {name}={value!r}: {problem}")
        return value

    def _validate(self, params):
        for p in params:
            check = self._validators.get(p.name)
            problem = check(p.value) if check else None
            if problem:
                return SetParametersResult(successful=False, reason=f"{p.name}={p.value!r}: {problem}")
        return SetParametersResult(successful=True)

    def _follow(self, params):
        for p in params:
            if p.name in self._live:
                setattr(self, self._live[p.name], p.value)

    def event(self, kind, **fields):
        """Publish an ``/experiment/events`` record from this node."""
        if not hasattr(self, "_events"):
            self._events = self.publisher("/experiment/events")
        self._events.publish(convert.event_msg(None, kind, node=self.get_name(), **fields))


class Lockstep:
    """Collect per-sample inputs (by stamp) and tell when a sample has all of them."""

    def __init__(self, needed: tuple[str, ...]):
        self.needed = needed
        self.pending: dict[int, dict] = {}

    def put(self, key: int, name: str, value) -> dict | None:
        """Store one input; return the complete set for ``key`` once everything is in."""
        got = self.pending.setdefault(key, {})
        got[name] = value
        if all(n in got for n in self.needed):
            return self.pending.pop(key)
        return None

    def missing(self, key: int) -> list[str]:
        got = self.pending.get(key, {})
        return [n for n in self.needed if n not in got]

    def clear(self):
        self.pending.clear()


def _floats(x) -> array.array:
    """A float64[] field value (``array('d')``, what rclpy stores) from a sequence or array."""
    if isinstance(x, np.ndarray):
        return array.array("d", np.ascontiguousarray(x, dtype=np.float64).reshape(-1).tobytes())
    return array.array("d", x)


class JointStateOut:
    """Publisher of ``sensor_msgs/JointState`` for per-sample topics: one message per joint-name
    list is built once (:func:`msg_defs.convert.joint_state`) and refilled for every sample
    (same content, ~10x cheaper than building a message each time)."""

    def __init__(self, node: StageNode, topic):
        self.pub = node.publisher(topic)
        self._msgs: dict[tuple, object] = {}
        self.last = None                    # the message published last

    def republish(self):
        """Publish the last message again (an answer to a sample the plant sent again)."""
        if self.last is not None:
            self.pub.publish(self.last)

    def publish(self, stamp_ns: int, names, position=(), velocity=(), effort=()):
        key = tuple(names)
        msg = self._msgs.get(key)
        if msg is None:
            msg = self._msgs[key] = convert.joint_state(None, stamp_ns, key)
        stamp = msg.header.stamp
        stamp.sec, stamp.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        for field, val in (("position", position), ("velocity", velocity), ("effort", effort)):
            val = _floats(val)
            if len(val) not in (0, len(key)):
                raise ValueError(f"JointState {field} has {len(val)} values for {len(key)} names {list(key)}")
            setattr(msg, field, val)
        self.pub.publish(msg)
        self.last = msg
