"""Conversions between the core's arrays/floats and the contract's messages.

Every builder takes ``types`` first, which picks the message family:

* ``None`` (or ``"rclpy"``): the rclpy message classes (``sensor_msgs.msg.JointState``...);
* a rosbags ``Typestore`` (``get_typestore(Stores.ROS2_JAZZY)``): its dataclasses;
* a message class of either family (e.g. ``sensor_msgs.msg.JointState``): its family.

Readers (:func:`stamp_ns`, :func:`joint`, :func:`trajectory_from_msg`...) accept
messages of any family, including the objects ``mcap_ros2`` decodes.
Times are integer nanoseconds of stage time; values are SI.

Examples
--------
>>> from rosbags.typesys import Stores, get_typestore
>>> ts = get_typestore(Stores.ROS2_JAZZY)
>>> m = joint_state(ts, 1_500_000_000, ["table"], position=[2e-6], velocity=[0.0])
>>> stamp_ns(m), joint(m, "table"), joint(m, "bearing")
(1500000000, 2e-06, nan)
>>> tr = trajectory_from_msg(trajectory_to_msg(ts, [0.0, 1e-6], [0.0, 0.01], trial=3, case="p2p", start=100))
>>> tr.x_ref.tolist(), tr.v_ref.tolist(), tr.trial, tr.case, tr.start
([0.0, 1e-06], [0.0, 0.01], 3, 'p2p', 100)
>>> parse_event(event_json("trial_start", trial=0, case="p2p", stamp_ns=0, window_m=25e-9))["window_m"]
2.5e-08
"""
from __future__ import annotations

import array
import dataclasses
import importlib
import json
import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from msg_defs.topics import CLOCK, EVENT_KINDS, TRAJECTORY

__all__ = [
    "message_class", "is_rosbags", "split_ns", "time_msg", "header", "joint_state", "string_msg",
    "clock_msg", "float64_multiarray", "stamp_ns", "joint", "values",
    "Trajectory", "trajectory_to_msg", "trajectory_from_msg",
    "Correction", "correction_to_msg", "correction_from_msg",
    "event", "event_json", "event_msg", "parse_event", "to_json", "from_json", "message_type_of", "to_rosbags",
]

NS = 1_000_000_000


# --------------------------------------------------------------------------- families
@lru_cache(maxsize=None)
def _jazzy_store():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


def _is_typestore(obj) -> bool:
    return hasattr(obj, "serialize_cdr") and hasattr(obj, "types")


def is_rosbags(msg_or_cls) -> bool:
    """True for rosbags message dataclasses (they carry ``__msgtype__``)."""
    return hasattr(msg_or_cls, "__msgtype__")


def message_type_of(msg) -> str:
    """``"pkg/msg/Type"`` of an rclpy or rosbags message (instance or class)."""
    if is_rosbags(msg):
        return msg.__msgtype__
    cls = msg if isinstance(msg, type) else type(msg)
    pkg, kind = cls.__module__.split(".")[:2]
    return f"{pkg}/{kind}/{cls.__name__}"


def message_class(types, msg_type: str):
    """The class of ``msg_type`` (``"pkg/msg/Type"``) in the family chosen by ``types``."""
    if types is None or types == "rclpy":
        pkg, kind, name = msg_type.split("/")
        return getattr(importlib.import_module(f"{pkg}.{kind}"), name)
    if _is_typestore(types):
        return types.types[msg_type]
    if isinstance(types, type):
        if is_rosbags(types):
            return types if types.__msgtype__ == msg_type else _jazzy_store().types[msg_type]
        return types if message_type_of(types) == msg_type else message_class(None, msg_type)
    raise TypeError(f"types must be None, 'rclpy', a rosbags Typestore or a message class, got {types!r}")


def _float_array(types, x):
    """A float64[] field value for the family: numpy for rosbags, array('d') for rclpy."""
    a = np.array(x, dtype=np.float64, copy=True).reshape(-1)
    if _rosbags_family(types):
        return a
    return array.array("d", a.tobytes())


def _rosbags_family(types) -> bool:
    return _is_typestore(types) or (isinstance(types, type) and is_rosbags(types))


def _is_message(obj) -> bool:
    """An rclpy message instance (generated classes carry ``get_fields_and_field_types``)."""
    return hasattr(type(obj), "get_fields_and_field_types")


def _rosbags_value(v, store):
    if _is_message(v) or is_rosbags(v):
        return to_rosbags(v, store)
    if isinstance(v, array.array):
        return np.array(v, dtype=np.dtype(v.typecode))
    if isinstance(v, np.ndarray):
        return v.copy()
    if isinstance(v, list) and v and isinstance(v[0], bytes):      # byte[]
        return np.frombuffer(b"".join(v), np.uint8).copy()
    if isinstance(v, (list, tuple)) and v and (_is_message(v[0]) or is_rosbags(v[0])):
        return [to_rosbags(x, store) for x in v]
    return list(v) if isinstance(v, tuple) else v


def to_rosbags(msg, store=None):
    """The same message as a rosbags dataclass (``store``: a Typestore, default ROS 2 Jazzy):
    how a ROS-free module (the recording writer) serializes an rclpy message.

    >>> m = to_rosbags(joint_state(message_class(None, "sensor_msgs/msg/JointState"), 5, ["table"], [1.5]))
    >>> m.__msgtype__, stamp_ns(m), m.position.tolist()
    ('sensor_msgs/msg/JointState', 5, [1.5])
    """
    store = store or _jazzy_store()
    if is_rosbags(msg):
        return msg
    cls = store.types[message_type_of(msg)]
    return cls(**{f.name: _rosbags_value(getattr(msg, f.name), store) for f in dataclasses.fields(cls)
                  if f.name != "__msgtype__"})


# --------------------------------------------------------------------------- builders
def split_ns(ns: int) -> tuple[int, int]:
    """``(sec, nanosec)`` of a time in ns, ``0 <= nanosec < 1e9`` (as builtin_interfaces/Time).

    >>> split_ns(1_500_000_001), split_ns(-1)
    ((1, 500000001), (-1, 999999999))
    """
    ns = int(ns)
    return ns // NS, ns % NS


def time_msg(types, ns: int):
    """``builtin_interfaces/msg/Time`` of a stage time [ns]."""
    sec, nanosec = split_ns(ns)
    return message_class(types, "builtin_interfaces/msg/Time")(sec=sec, nanosec=nanosec)


def header(types, ns: int, frame_id: str = ""):
    """``std_msgs/msg/Header`` stamped with a stage time [ns]."""
    return message_class(types, "std_msgs/msg/Header")(stamp=time_msg(types, ns), frame_id=frame_id)


def joint_state(types, stamp_ns: int, names, position=(), velocity=(), effort=()):
    """``sensor_msgs/msg/JointState`` with ``header.stamp`` = ``stamp_ns``; arrays in SI.

    Each of ``position``, ``velocity``, ``effort`` is empty or as long as ``names``.
    """
    names = [str(n) for n in names]
    fields = {}
    for key, val in (("position", position), ("velocity", velocity), ("effort", effort)):
        fields[key] = _float_array(types, val)
        if len(fields[key]) not in (0, len(names)):
            raise ValueError(f"JointState {key} has {len(fields[key])} values for {len(names)} names {names}")
    cls = message_class(types, "sensor_msgs/msg/JointState")
    return cls(header=header(types, stamp_ns), name=names, **fields)


def string_msg(types, text: str):
    """``std_msgs/msg/String``."""
    return message_class(types, "std_msgs/msg/String")(data=str(text))


def clock_msg(types, stamp_ns: int):
    """``rosgraph_msgs/msg/Clock`` at a stage time [ns]."""
    return message_class(types, CLOCK.msg_type)(clock=time_msg(types, stamp_ns))


def float64_multiarray(types, data, dims):
    """``std_msgs/msg/Float64MultiArray``; ``dims`` = [(label, size, stride), ...]."""
    dim_cls = message_class(types, "std_msgs/msg/MultiArrayDimension")
    layout = message_class(types, "std_msgs/msg/MultiArrayLayout")(
        dim=[dim_cls(label=str(lb), size=int(sz), stride=int(st)) for lb, sz, st in dims], data_offset=0)
    return message_class(types, "std_msgs/msg/Float64MultiArray")(layout=layout, data=_float_array(types, data))


# --------------------------------------------------------------------------- readers
def stamp_ns(msg) -> int:
    """Stage time [ns] of a message: ``header.stamp``, ``Clock.clock`` or a ``Time`` itself."""
    t = msg
    if hasattr(msg, "header"):
        t = msg.header.stamp
    elif hasattr(msg, "clock"):
        t = msg.clock
    if not (hasattr(t, "sec") and hasattr(t, "nanosec")):
        raise TypeError(f"{type(msg).__name__} has no header.stamp, clock or sec/nanosec")
    return int(t.sec) * NS + int(t.nanosec)


def values(field) -> np.ndarray:
    """A float64[] field (list, array('d') or numpy) as a float64 numpy array."""
    return np.asarray(field, dtype=np.float64)


def joint(msg, name: str, field: str = "position", default: float = math.nan) -> float:
    """Value of joint ``name`` in a JointState ``field``; ``default`` if absent."""
    try:
        i = list(msg.name).index(name)
        return float(getattr(msg, field)[i])
    except (ValueError, IndexError):
        return default


# --------------------------------------------------------------------------- trajectory
class Trajectory(NamedTuple):
    """Content of an ``/experiment/trajectory`` message."""
    x_ref: np.ndarray     # (N,) reference position [m]
    v_ref: np.ndarray     # (N,) reference velocity [m/s]
    trial: int            # trial number (0-based)
    case: str             # case name
    start: int            # control sample of the run at which sample 0 applies
    rate: float           # control rate [Hz]


def _label(kind: str, meta: dict) -> str:
    return f"{kind}:{json.dumps(meta, separators=(',', ':'))}"


def _parse_label(label: str, kind: str, topic: str) -> dict:
    head, _, rest = label.partition(":")
    if head != kind:
        raise ValueError(f"{topic}: layout label {label!r} does not start with {kind!r}:")
    try:
        return json.loads(rest) if rest.startswith("{") else {}
    except json.JSONDecodeError as err:
        raise ValueError(f"{topic}: layout label {label!r} is not {kind}:<JSON>: {err}") from None


def trajectory_to_msg(types, x_ref, v_ref, *, trial: int, case: str = "", start: int = 0,
                      rate: float = 10_000.0):
    """``/experiment/trajectory`` message of one trial's whole reference (see topics.TRAJECTORY)."""
    x = np.asarray(x_ref, dtype=np.float64).reshape(-1)
    v = np.asarray(v_ref, dtype=np.float64).reshape(-1)
    if x.shape != v.shape:
        raise ValueError(f"x_ref has {x.size} samples, v_ref {v.size}")
    n = x.size
    meta = {"trial": int(trial), "case": str(case), "start": int(start), "rate": float(rate)}
    return float64_multiarray(types, np.concatenate([x, v]),
                              [("signal:x_ref,v_ref", 2, 2 * n), (_label("sample", meta), n, n)])


def trajectory_from_msg(msg) -> Trajectory:
    """Inverse of :func:`trajectory_to_msg`; ``ValueError`` if the layout is not the contract's."""
    dims = list(msg.layout.dim)
    if len(dims) != 2 or dims[0].label != "signal:x_ref,v_ref" or int(dims[0].size) != 2:
        raise ValueError(f"{TRAJECTORY.name}: layout {[(d.label, d.size) for d in dims]} is not "
                         "[signal:x_ref,v_ref (2), sample:{...} (N)]")
    n = int(dims[1].size)
    meta = _parse_label(dims[1].label, "sample", TRAJECTORY.name)
    off = int(msg.layout.data_offset)
    data = values(msg.data)[off:off + 2 * n]
    if data.size != 2 * n:
        raise ValueError(f"{TRAJECTORY.name}: {data.size} values for 2 x {n} samples")
    return Trajectory(data[:n].copy(), data[n:].copy(), int(meta.get("trial", 0)), str(meta.get("case", "")),
                      int(meta.get("start", 0)), float(meta.get("rate", 10_000.0)))


# --------------------------------------------------------------------------- correction
class Correction(NamedTuple):
    """Content of a ``/stage/correction`` message (SAI Step II, ILC)."""
    values: np.ndarray    # (q,) correction added j samples after each compliant->stiff switch [m]
    iteration: int        # ILC iteration that produced it
    rate: float           # control rate [Hz]


def correction_to_msg(types, correction, *, iteration: int = 0, rate: float = 10_000.0):
    """``/stage/correction`` message (see topics.CORRECTION)."""
    c = np.asarray(correction, dtype=np.float64).reshape(-1)
    return float64_multiarray(types, c, [(_label("sample", {"iteration": int(iteration), "rate": float(rate)}),
                                          c.size, c.size)])


def correction_from_msg(msg) -> Correction:
    """Inverse of :func:`correction_to_msg`."""
    dims = list(msg.layout.dim)
    if len(dims) != 1:
        raise ValueError(f"/stage/correction: expected one dimension, got {len(dims)}")
    meta = _parse_label(dims[0].label, "sample", "/stage/correction")
    off = int(msg.layout.data_offset)
    data = values(msg.data)[off:off + int(dims[0].size)]
    return Correction(data.copy(), int(meta.get("iteration", 0)), float(meta.get("rate", 10_000.0)))


# --------------------------------------------------------------------------- JSON topics
def strict_json(obj):
    """Replace NaN/inf by None and numpy scalars by Python ones, recursively (strict JSON)."""
    if isinstance(obj, dict):
        return {str(k): strict_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict_json(v) for v in obj]
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def to_json(obj) -> str:
    """Strict JSON (NaN/inf -> null) for ``/experiment/events`` and ``/experiment/results``."""
    return json.dumps(strict_json(obj), allow_nan=False, separators=(",", ":"))


def from_json(text: str):
    """Parse JSON written by :func:`to_json` (null stays None)."""
    return json.loads(text)


_EVENT_KEYS = ("event", "trial", "case", "step_index", "stamp_ns", "window_m", "reason", "node")
_EVENT_TYPES = (("stamp_ns", int, "an integer [ns]"), ("trial", int, "an integer"), ("step_index", int, "an integer"),
                ("settle_start_ns", int, "an integer [ns]"), ("window_m", (int, float), "a number [m]"),
                ("target_m", (int, float), "a number [m]"), ("case", str, "a string"), ("reason", str, "a string"),
                ("node", str, "a string"))


def event(kind: str, *, stamp_ns: int, trial: int | None = None, case: str | None = None,
          step_index: int | None = None, window_m: float | None = None, reason: str | None = None,
          node: str = "", **extra) -> dict:
    """An ``/experiment/events`` record (dict), validated; see topics.EVENTS for the fields.

    ``extra`` may add ``target_m`` [m] and ``settle_start_ns`` [ns] (or other keys, which
    readers ignore).
    """
    if kind not in EVENT_KINDS:
        raise ValueError(f"event {kind!r}: expected one of {', '.join(EVENT_KINDS)}")
    if kind in ("trial_start", "trial_end") and trial is None:
        raise ValueError(f"{kind} event needs a trial number")
    if window_m is not None and not (math.isfinite(window_m) and window_m >= 0):
        raise ValueError(f"window_m {window_m!r}: expected a finite value >= 0 [m] or None")
    rec = {"event": kind, "trial": None if trial is None else int(trial),
           "case": None if case is None else str(case),
           "step_index": None if step_index is None else int(step_index), "stamp_ns": int(stamp_ns),
           "window_m": None if window_m is None else float(window_m),
           "reason": None if reason is None else str(reason), "node": str(node)}
    rec.update(strict_json(extra))
    return rec


def event_json(kind: str, **fields) -> str:
    """:func:`event` as a JSON string (the ``data`` of the String message)."""
    return to_json(event(kind, **fields))


def event_msg(types, kind: str, **fields):
    """``/experiment/events`` message (``std_msgs/msg/String``)."""
    return string_msg(types, event_json(kind, **fields))


def parse_event(text: str) -> dict:
    """Parse and check an ``/experiment/events`` JSON object; missing optional keys -> None."""
    try:
        rec = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"/experiment/events: not JSON ({err}): {text[:80]!r}") from None
    if not isinstance(rec, dict) or rec.get("event") not in EVENT_KINDS or "stamp_ns" not in rec:
        raise ValueError(f"/experiment/events: expected an object with event in {EVENT_KINDS} "
                         f"and stamp_ns, got {text[:120]!r}")
    for key in _EVENT_KEYS:
        rec.setdefault(key, None)
    for key, kinds, what in _EVENT_TYPES:
        val = rec.get(key)
        if val is not None and (isinstance(val, bool) or not isinstance(val, kinds)):
            raise ValueError(f"/experiment/events: {key} {val!r} is not {what}")
    return rec
