"""The topic contract (msg_defs.topics) and the message conversions (msg_defs.convert).

rclpy message classes are only imported (no rclpy.init, no node).
"""
import math
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.typesys import Stores, get_typestore

from msg_defs import cdr, convert
from experiment_runner.ros.qos import qos_profile, subscription_qos
from msg_defs.topics import CONTRACT_TOPICS, EVENT_KINDS, TOPICS, Qos, get_topic, markdown_table, offered_qos_yaml

TS = get_typestore(Stores.ROS2_JAZZY)
FAMILIES = [None, TS]
ROOT = Path(__file__).resolve().parents[1]

REQUIRED = ["/stage/reference", "/stage/command", "/stage/measured", "/stage/truth", "/stage/dither",
            "/stage/isolator", "/clock", "/experiment/config", "/experiment/events",
            "/experiment/trajectory", "/stage/correction", "/experiment/results"]


def test_every_topic_is_defined_with_a_standard_type():
    assert set(REQUIRED) <= set(TOPICS)
    assert CONTRACT_TOPICS == ("/stage/reference", "/stage/command", "/stage/measured")
    for name, t in TOPICS.items():
        assert t.name == name and t.units and t.rate and t.description
        assert t.msg_type in TS.types, t.msg_type                       # rosbags knows it
        cls = convert.message_class(None, t.msg_type)                   # rclpy class imports
        assert convert.message_type_of(cls) == t.msg_type
    # the contract's types
    for name in ("/stage/reference", "/stage/command", "/stage/measured", "/stage/truth", "/stage/dither",
                 "/stage/isolator"):
        assert TOPICS[name].msg_type == "sensor_msgs/msg/JointState"
    assert TOPICS["/clock"].msg_type == "rosgraph_msgs/msg/Clock"
    assert TOPICS["/experiment/config"].msg_type == "std_msgs/msg/String"
    with pytest.raises(KeyError, match="/nope"):
        get_topic("/nope")


def test_qos_plain_data_and_rclpy_profile():
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy
    for t in TOPICS.values():
        assert t.qos.reliability == "reliable"                          # lockstep: nothing best-effort
    assert TOPICS["/experiment/config"].qos.durability == "transient_local"
    assert TOPICS["/stage/measured"].qos.depth >= 1000
    p = qos_profile("/experiment/config")
    assert p.durability == DurabilityPolicy.TRANSIENT_LOCAL and p.reliability == ReliabilityPolicy.RELIABLE
    p = qos_profile(TOPICS["/clock"])        # offered: the last 0.1 s kept for a recorder joining late
    assert p.history == HistoryPolicy.KEEP_LAST and p.depth == 1000 and p.durability == DurabilityPolicy.TRANSIENT_LOCAL
    # requested: only a recorder asks for it; a controller joining late starts from the live sample
    assert subscription_qos("/clock").durability == DurabilityPolicy.VOLATILE
    assert subscription_qos("/clock", record=True).durability == DurabilityPolicy.TRANSIENT_LOCAL
    assert subscription_qos("/experiment/trajectory").durability == DurabilityPolicy.TRANSIENT_LOCAL  # latched
    streams = {n for n, t in TOPICS.items() if t.stream}
    assert streams == {"/stage/reference", "/stage/command", "/stage/measured", "/stage/truth", "/stage/dither",
                       "/clock", "/stage/external_force", "/source/channels"}
    assert qos_profile(Qos("best_effort", depth=3)).reliability == ReliabilityPolicy.BEST_EFFORT
    with pytest.raises(ValueError, match="reliability"):
        Qos("sometimes")


def test_offered_qos_yaml_is_rosbag2_v9():
    from rosbags.interfaces import QosDurability, QosHistory, QosReliability
    from rosbags.rosbag2.metadata import parse_qos
    text = offered_qos_yaml("/experiment/config")
    doc = yaml.safe_load(text)
    assert isinstance(doc, list) and len(doc) == 1
    assert list(doc[0]) == ["history", "depth", "reliability", "durability", "deadline", "lifespan",
                            "liveliness", "liveliness_lease_duration", "avoid_ros_namespace_conventions"]
    assert doc[0]["deadline"] == {"sec": 9223372036, "nsec": 854775807}
    assert doc[0]["avoid_ros_namespace_conventions"] is False
    (q,) = parse_qos(text)                                               # rosbags understands it
    assert (q.history, q.depth, q.reliability, q.durability) == (
        QosHistory.KEEP_LAST, 1, QosReliability.RELIABLE, QosDurability.TRANSIENT_LOCAL)


def test_readme_table_matches_the_module():
    text = (ROOT / "msg_defs" / "README.md").read_text()
    assert markdown_table() in text, "regenerate the README table from msg_defs.topics.markdown_table()"


@pytest.mark.parametrize("types", FAMILIES, ids=["rclpy", "rosbags"])
def test_joint_state_both_families(types):
    m = convert.joint_state(types, 3_000_000_123, ["table", "bearing"], position=[1e-6, -2e-9],
                            velocity=np.array([0.5, 0.0]))
    assert convert.stamp_ns(m) == 3_000_000_123
    assert (m.header.stamp.sec, m.header.stamp.nanosec) == (3, 123)
    assert convert.joint(m, "bearing") == -2e-9 and convert.joint(m, "table", "velocity") == 0.5
    assert math.isnan(convert.joint(m, "table", "effort")) and math.isnan(convert.joint(m, "motor"))
    assert convert.message_type_of(m) == "sensor_msgs/msg/JointState"
    with pytest.raises(ValueError, match="position"):
        convert.joint_state(types, 0, ["table"], position=[1.0, 2.0])


def test_families_serialize_to_the_same_cdr():
    from rclpy.serialization import deserialize_message
    from sensor_msgs.msg import JointState
    m = convert.joint_state(TS, 7, ["motor"], effort=[0.25])
    back = deserialize_message(bytes(TS.serialize_cdr(m, "sensor_msgs/msg/JointState")), JointState)
    assert convert.stamp_ns(back) == 7 and list(back.name) == ["motor"] and list(back.effort) == [0.25]
    # a class picks its family
    from sensor_msgs.msg import JointState as R
    assert isinstance(convert.joint_state(R, 0, ["a"]), R)
    assert convert.is_rosbags(convert.joint_state(TS.types["sensor_msgs/msg/JointState"], 0, ["a"]))


def test_split_ns_and_clock():
    for ns in (0, 1, 999_999_999, 1_000_000_000, 123_456_789_012, -1, -1_000_000_001):
        sec, nsec = convert.split_ns(ns)
        assert 0 <= nsec < 10**9 and sec * 10**9 + nsec == ns
        for types in FAMILIES:
            assert convert.stamp_ns(convert.clock_msg(types, ns)) == ns
            assert convert.stamp_ns(convert.time_msg(types, ns)) == ns


@pytest.mark.parametrize("types", FAMILIES, ids=["rclpy", "rosbags"])
def test_trajectory_and_correction_round_trip_exactly(types):
    rng = np.random.default_rng(1)
    x = rng.standard_normal(1001) * 1e-3
    v = np.concatenate([[0.0, -0.0, 5e-324, 1e300], rng.standard_normal(997)])
    msg = convert.trajectory_to_msg(types, x, v, trial=7, case='case "a": b|c', start=12345, rate=20_000.0)
    assert [d.label.split(":")[0] for d in msg.layout.dim] == ["signal", "sample"]
    assert [int(d.size) for d in msg.layout.dim] == [2, 1001]
    tr = convert.trajectory_from_msg(msg)
    assert np.array_equal(tr.x_ref, x) and np.array_equal(tr.v_ref.view(np.int64), v.view(np.int64))
    assert (tr.trial, tr.case, tr.start, tr.rate) == (7, 'case "a": b|c', 12345, 20_000.0)
    c = convert.correction_from_msg(convert.correction_to_msg(types, x[:50], iteration=4, rate=1e4))
    assert np.array_equal(c.values, x[:50]) and (c.iteration, c.rate) == (4, 1e4)
    with pytest.raises(ValueError, match="x_ref has"):
        convert.trajectory_to_msg(types, x, v[:3], trial=0)
    bad = convert.float64_multiarray(types, [1.0, 2.0], [("sample", 2, 2)])
    with pytest.raises(ValueError, match="layout"):
        convert.trajectory_from_msg(bad)


def test_events_are_documented_json():
    text = convert.event_json("trial_start", trial=2, case="p2p", step_index=1, stamp_ns=10**9,
                              window_m=25e-9, node="sequencer", target_m=5e-6, settle_start_ns=1_020_000_000)
    ev = convert.parse_event(text)
    assert ev == {"event": "trial_start", "trial": 2, "case": "p2p", "step_index": 1, "stamp_ns": 10**9,
                  "window_m": 25e-9, "reason": None, "node": "sequencer", "target_m": 5e-6,
                  "settle_start_ns": 1_020_000_000}
    assert set(EVENT_KINDS) == {"trial_start", "trial_end", "run_start", "run_end", "abort", "fault"}
    msg = convert.event_msg(None, "fault", stamp_ns=5, trial=0, reason="table left its travel", node="plant")
    assert convert.parse_event(msg.data)["reason"] == "table left its travel"
    with pytest.raises(ValueError, match="expected one of"):
        convert.event("begin", stamp_ns=0)
    with pytest.raises(ValueError, match="trial number"):
        convert.event("trial_end", stamp_ns=0)
    with pytest.raises(ValueError, match="window_m"):
        convert.event("trial_start", trial=0, stamp_ns=0, window_m=math.nan)
    with pytest.raises(ValueError, match="not JSON"):
        convert.parse_event("{oops")
    with pytest.raises(ValueError, match="expected an object"):
        convert.parse_event('{"event": "trial_start"}')
    assert convert.parse_event('{"event": "run_end", "stamp_ns": 3}')["trial"] is None  # optional keys -> None
    assert convert.to_json({"a": math.nan, "b": [np.float64(1.5), np.int64(2), math.inf]}) == \
        '{"a":null,"b":[1.5,2,null]}'


# --------------------------------------------------------------------------- CDR codec (msg_defs.cdr)
JS = "sensor_msgs/msg/JointState"
LAYOUTS = [(("table",), dict(position=[1e-6], velocity=[0.25])), (("motor",), dict(effort=[-3.5])),
           (("table", "bearing"), dict(position=[5e-324, -0.0])), (("piezo_1", "piezo_2"), dict(effort=[0.1, 1e300])),
           (("table", "body_1", "bearing"), dict(position=[1.0, 2.0, 3.0], velocity=[4.0, 5.0, 6.0],
                                                 effort=[math.inf, -math.inf, math.nan])),
           ((), {}), (("x" * 9,), dict(velocity=[7.0]))]


def _bits(values):
    return np.asarray(values, np.float64).view(np.int64).tolist()


@pytest.mark.parametrize("names, arrays", LAYOUTS)
@pytest.mark.parametrize("frame", ["", "base_link"])
def test_cdr_joint_state_is_rosbags_canonical_cdr_and_reads_any_cdr(names, arrays, frame):
    from rclpy.serialization import deserialize_message, serialize_message
    from sensor_msgs.msg import JointState
    stamp = 1_234_567_890_123
    ref = convert.joint_state(TS, stamp, list(names), **arrays)
    ref.header.frame_id = frame
    mine = cdr.joint_state(stamp, names, frame_id=frame, **arrays)
    assert mine == bytes(TS.serialize_cdr(ref, JS))                      # byte for byte what rosbags writes
    back = deserialize_message(mine, JointState)                         # what every rclpy subscriber gets
    assert convert.stamp_ns(back) == stamp and tuple(back.name) == names and back.header.frame_id == frame
    for key in ("position", "velocity", "effort"):
        assert _bits(getattr(back, key)) == _bits(arrays.get(key, []))
    fast = serialize_message(back)                                        # Fast CDR: padding and tail unset
    for data in (mine, fast):
        stamp_, names_, *values = cdr.read_joint_state(data)
        assert (stamp_, names_) == (stamp, names) and cdr.stamp_ns(data) == stamp
        assert [_bits(v) for v in values] == [_bits(arrays.get(k, [])) for k in ("position", "velocity", "effort")]
        assert cdr.canonical(data) == mine
    reader = cdr.JointStateReader()
    for data in (fast, mine, mine, fast):                                 # general and learned paths agree
        assert reader.canonical(data) == mine
        got, want = reader.read(data), cdr.read_joint_state(data)
        assert got[:2] == want[:2] and [_bits(v) for v in got[2:]] == [_bits(v) for v in want[2:]]


@pytest.mark.parametrize("names, arrays", [l for l in LAYOUTS if any(l[1].values())])
def test_cdr_reader_canonical_clears_unset_alignment_bytes(names, arrays):
    """Fast CDR leaves the alignment bytes before the arrays of doubles unset (they may hold
    anything): a message of the learned layout with non-zero padding is still made canonical."""
    from msg_defs.cdr import joint_state_layout
    mine = cdr.joint_state(42, names, **arrays)
    layout, static = joint_state_layout(tuple(names), tuple(len(arrays.get(k, [])) for k in ("position", "velocity", "effort")))
    packed = layout.pack(*layout.unpack_from(mine))
    assert packed == mine
    dirty = bytearray(mine)
    at, pads = 12 + len(static), []
    for n in (len(arrays.get(k, [])) for k in ("position", "velocity", "effort")):
        at += 4
        if n:
            pad = -(at - 4) % 8
            pads += range(at, at + pad)
            at += pad + 8 * n
    if not pads:
        pytest.skip("this layout has no alignment bytes before its arrays")
    for i in pads:
        dirty[i] = 0xA5
    reader = cdr.JointStateReader()
    for data in (mine, bytes(dirty), mine, bytes(dirty)):            # learned from mine, then dirty
        assert reader.canonical(data) == mine
        assert [_bits(v) for v in reader.read(data)[2:]] == [_bits(arrays.get(k, []))
                                                            for k in ("position", "velocity", "effort")]


def test_cdr_clock_nan_fill_and_bad_lengths():
    from rclpy.serialization import serialize_message
    for ns in (0, 1, 10**9, 123_456_789_012):
        assert cdr.clock(ns) == bytes(TS.serialize_cdr(convert.clock_msg(TS, ns), "rosgraph_msgs/msg/Clock"))
        assert cdr.stamp_ns(serialize_message(convert.clock_msg(None, ns))) == ns
        assert cdr.canonical(serialize_message(convert.clock_msg(None, ns)), cdr.CLOCK) == cdr.clock(ns)
    data = cdr.joint_state(5, ("table", "bearing"), position=(1.0, 2.0), effort=(3.0, 4.0))
    stamp, names, pos, vel, eff = cdr.read_joint_state(cdr.nan_filled(data))
    assert (stamp, names, vel) == (5, ("table", "bearing"), ()) and all(map(math.isnan, pos + eff))
    assert math.isnan(cdr.first(cdr.joint_state(0, ("a",)), "position"))
    with pytest.raises(ValueError, match="effort has 2 values for 1 names"):
        cdr.joint_state(0, ("motor",), effort=(1.0, 2.0))
    be = TS.serialize_cdr(convert.joint_state(TS, 9, ["m"], effort=[2.5]), JS, little_endian=False)
    assert cdr.read_joint_state(be) == (9, ("m",), (), (), (2.5,))       # big endian read too
