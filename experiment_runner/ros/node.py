"""What every nanostage node shares: publishers and subscriptions made from the topic
contract, validated parameters, the run configuration, and lockstep sample bookkeeping.

Nodes are thin adapters: they convert messages to the arrays the compiled core
steps take (``msg_defs.convert``) and back; no algorithm lives here.

Start-up: :meth:`StageNode.warm_up` loads the compiled kernels a node steps per sample before
the node spins, so none is loaded (or compiled) inside the lockstep.

Faults: :meth:`StageNode.fault_event` is how a node reports one (``cause``, ``reason``,
``responsible``); the test-only ``fault.*`` parameters of every node drop, delay or
NaN-fill the messages it publishes on one topic (:class:`FaultyPublisher`; off by default).
"""
from __future__ import annotations

import array
import math
import time

import numpy as np
import yaml
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.node import Node
from rclpy.parameter import Parameter

from experiment_runner.core.batch import Models
from experiment_runner.ros.qos import qos_profile, subscription_qos
from experiment_runner.ros.run import params_source
from msg_defs import cdr, convert
from msg_defs.topics import FAULT_CAUSES, TRAJECTORY, Topic, get_topic
from stage_sim.config import ConfigError, load_preset
from stage_sim.validation import field_line

FAULT_MODES = ("drop", "delay", "nan")
"""What the test-only ``fault.*`` parameters can do to the messages of one topic."""

WARM_UP_PRESET = "fi_stage"
"""The preset whose models :meth:`StageNode.warm_up` steps once. The kernels' argument types
depend on the structure of the models, not on a preset's values (every shipped preset gives the
same ones: ``test/test_graph.py``), so this loads what a run of any preset calls."""


class StageNode(Node):
    """Base class: contract publishers/subscriptions, validated parameters, run config."""

    def __init__(self, name: str, **kwargs):
        super().__init__(name, **kwargs)
        self._validators = {}
        self.add_on_set_parameters_callback(self._validate)
        self.config = None            # the run's configuration (dict) once received
        self.on_config = None
        self.fault = self._fault_params()
        self._events = self.publisher("/experiment/events")    # made early: matched before a fault

    @classmethod
    def warm_up(cls) -> None:
        """Load the compiled kernels this node calls for each sample (from the on-disk cache;
        compiled into it first where the cache is cold: seconds each, tens of seconds on a
        loaded machine). Called once the node is made, before it spins
        (:func:`~experiment_runner.ros.run.run_node`,
        :func:`~experiment_runner.ros.launch.run_one_process`), hence before it joins a run: a
        kernel loaded at a trial's first sample would stall the lockstep there, and a stalled
        plant sends nothing, not even its waiting sample again, which the sequencer's
        ``sample_timeout`` takes for a dead plant. Nothing to load here; the plant and the
        controllers step their kernels once on a throwaway trial (:func:`warm_up_models`)."""

    # ----------------------------------------------------------------- fault injection (tests)
    def _fault_params(self) -> dict | None:
        """The test-only fault injection of this node (``None``: off, the default).

        ``fault.topic`` names one topic this node publishes; its first ``fault.after``
        messages go out as usual, the ``fault.count`` messages after them (-1: all) are
        dropped (``fault.mode`` "drop"), published ``fault.delay_ms`` later ("delay") or
        published with every float field NaN ("nan"). Read once at start; the normal
        path is untouched when ``fault.topic`` is empty (a plain publisher is returned).
        """
        topic = self.param("fault.topic", "", "TEST ONLY: topic whose messages this node corrupts "
                           "(empty = off)")
        mode = self.param("fault.mode", "drop", "TEST ONLY: drop | delay | nan",
                          check=lambda v: None if v in FAULT_MODES else f"expected one of {FAULT_MODES}")
        after = self.param("fault.after", 0, "TEST ONLY: messages published normally first", 0, 2**31 - 1)
        count = self.param("fault.count", -1, "TEST ONLY: messages affected then (-1 = all)", -1, 2**31 - 1)
        delay = self.param("fault.delay_ms", 0.0, "TEST ONLY: delay of mode 'delay' [ms]", 0.0, 3.6e6)
        if not topic:
            return None
        self.get_logger().warning(f"TEST FAULT INJECTION on {topic}: {mode} {'all' if count < 0 else count} "
                                  f"messages after the first {after}" + (f", {delay} ms" if mode == "delay" else ""))
        return {"topic": topic, "mode": mode, "after": after, "count": count, "delay_s": delay * 1e-3}

    # ----------------------------------------------------------------- topics
    def publisher(self, topic):
        t = topic if isinstance(topic, Topic) else get_topic(topic)
        pub = self.create_publisher(convert.message_class(None, t.msg_type), t.name, qos_profile(t.qos))
        if self.fault is not None and self.fault["topic"] == t.name:
            return FaultyPublisher(self, pub, **{k: v for k, v in self.fault.items() if k != "topic"})
        return pub

    def subscribe(self, topic, callback, record: bool = False, raw: bool = False):
        """Subscribe with the topic's QoS (:func:`experiment_runner.ros.qos.subscription_qos`;
        ``record``: also get the per-sample messages sent before this subscription was matched;
        ``raw``: ``callback`` gets the CDR bytes, e.g. for :mod:`msg_defs.cdr`)."""
        t = get_topic(topic)
        return self.create_subscription(convert.message_class(None, t.msg_type), t.name, callback,
                                        subscription_qos(t, record), raw=raw)

    def subscribe_samples(self, topic, callback, record: bool = False):
        """Subscribe to a per-sample JointState topic: ``callback(stamp_ns, names, position,
        velocity, effort)`` (tuples), read from the CDR bytes (:class:`msg_defs.cdr.JointStateReader`)."""
        read = cdr.JointStateReader().read
        return self.subscribe(topic, lambda data: callback(*read(data)), record=record, raw=True)

    def join_runs(self, callback, ready=None, ready_timeout: float = 0.0):
        """Subscribe ``callback`` to ``/experiment/trajectory`` -- the subscription the sequencer
        counts before it starts a run -- at the first spin, after every endpoint the constructor
        made: discovery announces a node's subscriptions in the order they are made, so a
        sequencer that has matched this one has matched the node's others too.

        ``ready``: a further condition to wait for (polled every 20 ms), at most ``ready_timeout``
        seconds (then the node joins anyway: a node started deliberately late must not block the run).
        """
        start = time.monotonic()

        def join():
            if ready is not None and not ready() and time.monotonic() - start < ready_timeout:
                return
            timer.cancel()
            self.subscribe(TRAJECTORY, callback)
        timer = self.create_timer(0.0 if ready is None else 0.02, join)

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
        try:
            if isinstance(default, list):           # a list of floats, possibly empty: typed statically
                value = self.declare_parameter(name, Parameter.Type.DOUBLE_ARRAY, desc).value
                value = default if value is None else list(value)
            else:
                value = self.declare_parameter(name, default, desc).value
        except (InvalidParameterValueException, InvalidParameterTypeException):
            given = self._parameter_overrides.get(name)
            kind = {bool: "true/false", int: "an integer", float: "a number", str: "a string",
                    list: "a list of numbers with a decimal point"}.get(type(default), type(default).__name__)
            allowed = f"{kind} from {lo} to {hi}" if lo is not None else kind
            value = given.value if given else default
            problem = check(value) if check and isinstance(value, type(default)) else None
            message = self._param_error(name, value, problem or f"expected {allowed} -- {description}")
            raise ValueError(message) from None
        if check:
            problem = check(value)
            if problem:
                raise ValueError(self._param_error(name, value, problem))
        return value

    def _param_error(self, name, value, problem: str) -> str:
        """The one input-error format (:func:`stage_sim.validation.field_line`): source, then the line."""
        import sys

        return (f"{self.get_name()} ({params_source(sys.argv)}): invalid parameters\n"
                + field_line(name, value, problem))

    def _validate(self, params):
        for p in params:
            check = self._validators.get(p.name)
            problem = check(p.value) if check else None
            if problem:
                return SetParametersResult(successful=False, reason=f"{p.name}: got {p.value!r}; {problem}")
        return SetParametersResult(successful=True)

    def _follow(self, params):
        for p in params:
            if p.name in self._live:
                setattr(self, self._live[p.name], p.value)

    def event(self, kind, **fields):
        """Publish an ``/experiment/events`` record from this node."""
        self._events.publish(convert.event_msg(None, kind, node=self.get_name(), **fields))

    def fault_event(self, cause: str, reason: str, responsible, **fields):
        """Publish a ``fault`` event: ``cause`` (one of :data:`FAULT_CAUSES`), a readable
        ``reason`` and the node(s) ``responsible`` (the sequencer aborts the run naming them)."""
        if cause not in FAULT_CAUSES:
            raise ValueError(f"fault cause {cause!r}: expected one of {FAULT_CAUSES}")
        nodes = [responsible] if isinstance(responsible, str) else sorted(responsible)
        self.get_logger().error(f"{cause}: {reason}")
        self.event("fault", reason=f"{cause}: {reason}", cause=cause, responsible=nodes, **fields)


def warm_up_models():
    """The models of :data:`WARM_UP_PRESET` (:class:`experiment_runner.core.batch.Models`), for a
    node's :meth:`StageNode.warm_up`."""
    return Models.from_preset(load_preset(WARM_UP_PRESET))


def check_preset(name):
    """Parameter validator: None if ``name`` is empty or a loadable preset, else why not."""
    if not name:
        return None
    try:
        load_preset(name)
    except ConfigError as err:
        return str(err)
    return None


def finite(*values) -> bool:
    """Whether every value (floats or arrays) is finite."""
    for v in values:
        if isinstance(v, float):
            if not math.isfinite(v):
                return False
        elif not np.isfinite(v).all():
            return False
    return True


class FaultyPublisher:
    """TEST ONLY: a publisher that drops, delays or NaN-fills some of its messages (see
    :meth:`StageNode._fault_params`); everything else is passed to the wrapped publisher."""

    def __init__(self, node, pub, mode: str, after: int, count: int, delay_s: float):
        self._node, self._pub = node, pub
        self.mode, self.after, self.count, self.delay_s = mode, after, count, delay_s
        self.seen = 0
        self._fired = []                    # one-shot timers of delayed messages, to destroy

    def __getattr__(self, name):
        return getattr(self._pub, name)

    def publish(self, msg):
        while self._fired:                  # (not from inside their own callbacks)
            self._node.destroy_timer(self._fired.pop())
        n, self.seen = self.seen, self.seen + 1
        if n < self.after or (self.count >= 0 and n >= self.after + self.count):
            self._pub.publish(msg)
        elif self.mode == "nan":
            self._pub.publish(cdr.nan_filled(msg) if isinstance(msg, bytes) else _nan_copy(msg))
        elif self.mode == "delay":
            from rclpy.serialization import serialize_message
            data = msg if isinstance(msg, bytes) else serialize_message(msg)   # as it is now
            timer = None

            def later():
                timer.cancel()
                self._fired.append(timer)
                self._pub.publish(data)
            timer = self._node.create_timer(self.delay_s, later)
        # mode "drop": nothing goes out


def _nan_copy(msg):
    """A copy of ``msg`` with every float array field (position, velocity, effort, data) NaN."""
    from rclpy.serialization import deserialize_message, serialize_message
    out = deserialize_message(serialize_message(msg), type(msg))
    for name in ("position", "velocity", "effort", "data"):
        val = getattr(out, name, None)
        if val is not None and len(val):
            setattr(out, name, array.array("d", [math.nan] * len(val)))
    return out


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


class JointStateOut:
    """Publisher of a per-sample ``sensor_msgs/JointState`` topic, as canonical CDR bytes
    (:func:`msg_defs.cdr.joint_state`): no message object is built, converted to C and
    serialized for every sample, and what the subscribers (the recorder) get is already
    what a recording holds."""

    def __init__(self, node: StageNode, topic):
        self.pub = node.publisher(topic)
        self._pack = cdr.JointStateWriter().pack
        self.last = None                    # the bytes published last

    def republish(self):
        """Publish the last message again (an answer to a sample the plant sent again)."""
        if self.last is not None:
            self.pub.publish(self.last)

    def publish(self, stamp_ns: int, names, position=(), velocity=(), effort=()):
        """Publish one sample; ``names`` a tuple, the value sequences floats (empty or one per name)."""
        self.last = self._pack(stamp_ns, names, position, velocity, effort)
        self.pub.publish(self.last)
