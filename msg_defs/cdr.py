"""The per-sample messages as CDR bytes, without message objects.

The lockstep graph sends five to eight messages per control sample, all
``sensor_msgs/msg/JointState`` or ``rosgraph_msgs/msg/Clock``. Building an rclpy
message object for each one, converting it to C and letting the middleware serialize
it (and the reverse on every subscriber) cost more than the rest of the loop; the
nodes therefore publish and take these two types as serialized CDR (rclpy's
``publish(bytes)`` / ``raw=True`` subscriptions) with the codec here: a
:class:`struct.Struct` per joint-name layout, built once. The bytes are the canonical
XCDR1 encoding -- zero padding, nothing after the last field, exactly what rosbags
(``Typestore.serialize_cdr``) writes -- so a recorder writes them as they come, and
every ROS 2 subscriber reads them as the standard types. The readers accept any CDR
of these types (little or big endian, Fast CDR's uninitialised padding and trailing
bytes included).

Examples
--------
>>> data = joint_state(1_500_000_123, ("table", "bearing"), position=(1.0, 2.0))
>>> read_joint_state(data)
(1500000123, ('table', 'bearing'), (1.0, 2.0), (), ())
>>> stamp_ns(data), first(data, "position")
(1500000123, 1.0)
>>> stamp_ns(clock(42)), len(clock(42))
(42, 12)
"""
from __future__ import annotations

import math
import struct
from functools import lru_cache

import numpy as np

__all__ = ["JOINT_STATE", "CLOCK", "joint_state", "clock", "stamp_ns", "read_joint_state", "read_joint_states",
           "first", "JointStateReader", "JointStateWriter", "canonical", "nan_filled"]

JOINT_STATE = "sensor_msgs/msg/JointState"
CLOCK = "rosgraph_msgs/msg/Clock"

_ENC = {True: b"\x00\x01\x00\x00", False: b"\x00\x00\x00\x00"}
"""Encapsulation header: CDR little endian (what we write) / big endian."""
_NS = 1_000_000_000
_STAMP = {True: struct.Struct("<iI"), False: struct.Struct(">iI")}
_U32 = {True: struct.Struct("<I"), False: struct.Struct(">I")}
_CLOCK = struct.Struct("<4siI")
_FIELDS = ("position", "velocity", "effort")


def _string(text: str, off: int) -> tuple[bytes, int]:
    """A CDR string at body offset ``off`` (4-aligned): length (with NUL), bytes, NUL."""
    raw = text.encode() + b"\0"
    return struct.pack("<I", len(raw)) + raw, off + 4 + len(raw)


@lru_cache(maxsize=256)
def joint_state_layout(names: tuple[str, ...], lengths: tuple[int, int, int], frame_id: str = "") -> tuple:
    """The Struct of a JointState with these names and array lengths; its fields are the
    encapsulation, sec, nanosec, the static part (frame_id and names), then count and
    values of each array."""
    static, off = _string(frame_id, 8)                 # body offsets; the header stamp is 0..8
    static += b"\0" * (-off % 4)
    off += -off % 4
    static += struct.pack("<I", len(names))
    off += 4
    for name in names:
        part, off2 = _string(name, off)
        pad = -off2 % 4
        static += part + b"\0" * pad
        off = off2 + pad
    fmt = f"<4siI{len(static)}s"
    for n in lengths:
        off += -off % 4                                 # (aligned already: strings are padded)
        fmt += "I"
        off += 4
        if n:
            pad = -off % 8
            fmt += f"{pad}x{n}d"
            off += pad + 8 * n
    return struct.Struct(fmt), static


def joint_state(stamp: int, names, position=(), velocity=(), effort=(), frame_id: str = "") -> bytes:
    """Canonical CDR of a ``sensor_msgs/msg/JointState`` (``header.stamp`` = ``stamp`` [ns]).

    Each of ``position``, ``velocity``, ``effort`` (sequences of floats) is empty or as
    long as ``names``.
    """
    return JointStateWriter(frame_id).pack(stamp, tuple(names), position, velocity, effort)


class JointStateWriter:
    """:func:`joint_state` for a stream of messages (one topic): the layout of the last
    joint names and array lengths is kept, so a message in it is one ``Struct.pack``.

    >>> w = JointStateWriter()
    >>> w.pack(5, ("motor",), effort=(1.5,)) == joint_state(5, ["motor"], effort=[1.5])
    True
    """

    __slots__ = ("_frame", "_key", "_layout", "_static")

    def __init__(self, frame_id: str = ""):
        self._frame, self._key = frame_id, None

    def pack(self, stamp: int, names: tuple, position=(), velocity=(), effort=()) -> bytes:
        """One message; ``names`` a tuple of str, the arrays sequences of floats."""
        key = (names, len(position), len(velocity), len(effort))
        if key != self._key:
            for field, n in zip(_FIELDS, key[1:]):
                if n not in (0, len(names)):
                    raise ValueError(f"JointState {field} has {n} values for {len(names)} names {list(names)}")
            self._layout, self._static = joint_state_layout(tuple(names), key[1:], self._frame)
            self._key = key
        sec, nanosec = divmod(int(stamp), _NS)
        return self._layout.pack(_ENC[True], sec, nanosec, self._static, key[1], *position, key[2], *velocity,
                                 key[3], *effort)


def clock(stamp: int) -> bytes:
    """CDR of a ``rosgraph_msgs/msg/Clock`` at ``stamp`` [ns]."""
    sec, nanosec = divmod(int(stamp), _NS)
    return _CLOCK.pack(_ENC[True], sec, nanosec)


def stamp_ns(data) -> int:
    """The stamp [ns] of a JointState (``header.stamp``) or Clock in CDR."""
    sec, nanosec = _STAMP[data[1] == 1].unpack_from(data, 4)
    return sec * _NS + nanosec


def _strings(data, off: int, count: int, u32) -> tuple[tuple[str, ...], int]:
    out = []
    for _ in range(count):
        off += -(off - 4) % 4
        (n,) = u32.unpack_from(data, off)
        out.append(bytes(data[off + 4:off + 3 + n]).decode())
        off += 4 + n
    return tuple(out), off


def _arrays_at(data, le: bool) -> tuple[int, int, str, tuple[str, ...]]:
    """Offset of the first array count, after header and names; (offset, stamp, frame_id, names)."""
    u32 = _U32[le]
    sec, nanosec = _STAMP[le].unpack_from(data, 4)
    (frame,), off = _strings(data, 12, 1, u32)
    off += -(off - 4) % 4
    (count,) = u32.unpack_from(data, off)
    names, off = _strings(data, off + 4, count, u32)
    return off, sec * _NS + nanosec, frame, names


def read_joint_state(data, with_frame: bool = False):
    """``(stamp_ns, names, position, velocity, effort)`` of a JointState in CDR (tuples of
    str and float); with ``with_frame`` also ``frame_id`` last."""
    le = data[1] == 1
    e = "<" if le else ">"
    off, stamp, frame, names = _arrays_at(data, le)
    arrays = []
    for _ in _FIELDS:
        off += -(off - 4) % 4
        (n,) = struct.unpack_from(e + "I", data, off)
        off += 4
        if n:
            off += -(off - 4) % 8
            arrays.append(struct.unpack_from(f"{e}{n}d", data, off))
            off += 8 * n
        else:
            arrays.append(())
    out = (stamp, names, *arrays)
    return out + (frame,) if with_frame else out


def _array_spans(end: int, lengths) -> list[tuple[int, int, int]]:
    """Where a canonical JointState's arrays of doubles lie, its static part ending at data offset
    ``end`` (body offset + 4): ``(padding start, first value, count)`` per array of ``lengths``."""
    spans, at = [], end
    for n in lengths:
        at += 4                                           # the count
        pad = -(at - 4) % 8 if n else 0
        spans.append((at, at + pad, n))
        at += pad + 8 * n
    return spans


def read_joint_states(datas) -> tuple | None:
    """Many JointStates of one canonical layout (one topic, as a recorder writes it) at once:
    ``(stamp_ns, names, position, velocity, effort)`` with ``stamp_ns`` an int64 array of the
    header stamps and each array of values ``(len(datas), n)`` float64 (``n`` = its count in
    the messages, 0 when empty). ``None`` when any message is not byte for byte the first's
    canonical layout outside its stamp and values (other names or counts, non-zero padding,
    big endian, trailing bytes): read those one by one (:class:`JointStateReader`).

    >>> m = [joint_state(k, ("table", "bearing"), position=(k, 2 * k)) for k in range(3)]
    >>> stamps, names, pos, vel, eff = read_joint_states(m)
    >>> stamps.tolist(), names, pos.tolist(), vel.shape
    ([0, 1, 2], ('table', 'bearing'), [[0.0, 0.0], [1.0, 2.0], [2.0, 4.0]], (3, 0))
    >>> read_joint_states(m + [joint_state(3, ("table",), position=(3.0,))]) is None
    True
    """
    if not datas:
        return None
    fields = read_joint_state(datas[0], with_frame=True)
    first_bytes = bytes(datas[0])
    if canonical_fields(fields) != first_bytes:
        return None
    names, lengths = fields[1], tuple(len(a) for a in fields[2:5])
    size = len(first_bytes)
    blob = b"".join(datas)
    if len(blob) != size * len(datas):
        return None
    rows = np.frombuffer(blob, np.uint8).reshape(len(datas), size)
    spans = _array_spans(12 + len(joint_state_layout(names, lengths, fields[5])[1]), lengths)
    fixed = np.ones(size, bool)                  # every byte but the stamp and the values
    fixed[4:12] = False
    for _, o, n in spans:
        fixed[o:o + 8 * n] = False
    if not (rows[:, fixed] == rows[0, fixed]).all():
        return None
    sec = np.ascontiguousarray(rows[:, 4:8]).view("<i4")[:, 0].astype(np.int64)
    nanosec = np.ascontiguousarray(rows[:, 8:12]).view("<u4")[:, 0].astype(np.int64)
    values = [np.ascontiguousarray(rows[:, o:o + 8 * n]).view("<f8").astype(float, copy=False) for _, o, n in spans]
    return (sec * _NS + nanosec, names, *values)


class JointStateReader:
    """:func:`read_joint_state` for a stream of messages of one layout (one topic): the layout
    of the last canonical message is kept, and a message in it is read with one
    ``Struct.unpack_from`` (any other message takes the general path).

    >>> r = JointStateReader()
    >>> [r.read(joint_state(k, ("motor",), effort=(0.5 * k,)))[4] for k in range(3)]
    [(0.0,), (0.5,), (1.0,)]
    >>> r.canonical(joint_state(7, ("motor",), effort=(1.0,))) == joint_state(7, ("motor",), effort=(1.0,))
    True
    """

    __slots__ = ("_layout", "_size", "_static", "_end", "_names", "_cuts", "_pads")

    def __init__(self):
        self._layout = None

    def _learn(self, fields) -> None:
        stamp, names, pos, vel, eff, frame = fields
        layout, static = joint_state_layout(names, (len(pos), len(vel), len(eff)), frame)
        self._layout, self._size, self._static = layout, layout.size, static
        self._end = 12 + len(static)
        self._names = names
        a = 5 + len(pos)                                  # fields: enc, sec, nsec, static, n, pos..., n, vel..., n, eff...
        b = a + 1 + len(vel)
        self._cuts = (5, a, a + 1, b, b + 1)
        # alignment bytes before each array of doubles: zero in a canonical message, anything
        # in rclpy's (Fast CDR leaves them unset), so a message is "known" only if they are 0
        self._pads = tuple((a, o, bytes(o - a)) for a, o, n in _array_spans(self._end, (len(pos), len(vel), len(eff)))
                           if n and o > a)                # (start, end, zeros)

    def _known(self, data) -> bool:
        if not (self._layout is not None and len(data) == self._size and data[1] == 1
                and data[12:self._end] == self._static):
            return False
        for a, b, zeros in self._pads:
            if data[a:b] != zeros:
                return False
        return True

    def read(self, data) -> tuple:
        """``(stamp_ns, names, position, velocity, effort)`` as :func:`read_joint_state`."""
        if not self._known(data):
            fields = read_joint_state(data, with_frame=True)
            if canonical_fields(fields) == bytes(data):
                self._learn(fields)
            return fields[:5]
        t = self._layout.unpack_from(data)
        c = self._cuts
        return t[1] * _NS + t[2], self._names, t[c[0]:c[1]], t[c[2]:c[3]], t[c[4]:]

    def canonical(self, data) -> bytes:
        """:func:`canonical` of ``data`` (returned as is when it is canonical already)."""
        if self._known(data):
            return bytes(data)
        fields = read_joint_state(data, with_frame=True)
        out = canonical_fields(fields)
        if out == bytes(data):
            self._learn(fields)
        return out


def canonical_fields(fields) -> bytes:
    """:func:`joint_state` of the fields :func:`read_joint_state` gives (``with_frame``)."""
    stamp, names, pos, vel, eff, frame = fields
    return joint_state(stamp, names, pos, vel, eff, frame_id=frame)


def first(data, field: str) -> float:
    """``field[0]`` (``"position"``, ``"velocity"`` or ``"effort"``) of a JointState in CDR
    (nan if the array is empty)."""
    values = read_joint_state(data)[2 + _FIELDS.index(field)]
    return values[0] if values else math.nan


def canonical(data, msg_type: str = JOINT_STATE) -> bytes:
    """The canonical CDR (zero padding, no trailing bytes, little endian) of a JointState or
    Clock in any CDR: what :func:`joint_state` / :func:`clock` write for the same values."""
    if msg_type == CLOCK:
        return clock(stamp_ns(data))
    return canonical_fields(read_joint_state(data, with_frame=True))


def nan_filled(data) -> bytes:
    """A JointState in CDR with every position, velocity and effort value NaN (fault injection)."""
    stamp, names, pos, vel, eff, frame = read_joint_state(data, with_frame=True)
    nan = [math.nan]
    return joint_state(stamp, names, nan * len(pos), nan * len(vel), nan * len(eff), frame_id=frame)
