"""MCAP recordings: writer (McapRecorder, write_run), reader (read_recording), salvage,
errors, metrics check and replay.

ROS nodes only run in a subprocess with its own ROS_DOMAIN_ID and localhost discovery.
"""
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from experiment_runner.apps.replay import check_metrics, main_replay, add_replay_arguments
from experiment_runner.core.batch import BatchResult
from experiment_runner.core.metrics import trial_metrics
from experiment_runner.core.outputs import OutputError
from experiment_runner.core.recording import (McapRecorder, RecordingError, TrialSignals, bag_layout, mcap_file,
                                         read_recording, write_run, write_trials)
from msg_defs import convert
from msg_defs.topics import CONTRACT_TOPICS, TOPICS, offered_qos_yaml
from stage_sim.config import load_preset

TS = get_typestore(Stores.ROS2_JAZZY)
ROOT = Path(__file__).resolve().parents[1]
DT_NS = 100_000                      # 10 kHz
N = 1200                             # samples in the synthetic recordings


def _signals(n=N, seed=0):
    """Awkward floats: tiny, huge, negative zero, subnormal, random."""
    rng = np.random.default_rng(seed)
    x = rng.standard_normal(n) * 1e-3
    x[:4] = [0.0, -0.0, 5e-324, 1e-300]
    return {"x_ref": x, "v_ref": rng.standard_normal(n) * 1e-2, "u": rng.standard_normal(n) * 1e2,
            "y": x + rng.standard_normal(n) * 1e-9, "yb": rng.standard_normal(n) * 1e-6}


def _write_synthetic(path, sig, *, chunk_ns=20_000_000, family=None, raw_measured=False):
    """A contract recording written with McapRecorder; reference via rclpy (or ``family``),
    command via rosbags, measured via rclpy (or raw Fast-CDR bytes)."""
    from rclpy.serialization import serialize_message
    with McapRecorder(path, "run: {case: synthetic}\n", chunk_ns=chunk_ns) as rec:
        rec.write("/experiment/events", 0, convert.event_msg(TS, "trial_start", trial=0, case="syn", stamp_ns=0,
                                                            window_m=1e-3, node="test"))
        for k in range(len(sig["x_ref"])):
            s = k * DT_NS
            rec.write("/clock", s, convert.clock_msg(family, s))
            rec.write("/stage/reference", s, convert.joint_state(family, s, ["table"], position=[sig["x_ref"][k]],
                                                                 velocity=[sig["v_ref"][k]]))
            rec.write("/stage/command", s, convert.joint_state(TS, s, ["motor"], effort=[sig["u"][k]]))
            meas = convert.joint_state(None, s, ["table", "bearing"], position=[sig["y"][k], sig["yb"][k]])
            rec.write("/stage/measured", s, serialize_message(meas) if raw_measured else meas)
        end = (len(sig["x_ref"]) - 1) * DT_NS
        rec.write("/experiment/events", end, convert.event_msg(TS, "trial_end", trial=0, case="syn", stamp_ns=end,
                                                              node="test"))
    return rec


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    sig = _signals()
    rec = _write_synthetic(tmp_path_factory.mktemp("syn") / "run.mcap", sig)
    return rec, sig


def _same_bits(a, b):
    return np.array_equal(np.asarray(a, np.float64).view(np.int64), np.asarray(b, np.float64).view(np.int64))


# --------------------------------------------------------------------------- file format
def test_layout_is_a_rosbag2_bag_with_one_mcap_file(synthetic):
    rec, _ = synthetic
    assert rec.path == rec.bag_dir / "run.mcap" and bag_layout("x/run") == bag_layout("x/run.mcap")
    # + nanostage's manifest of what it wrote there (experiment_runner.core.outputs)
    assert sorted(p.name for p in rec.bag_dir.iterdir()) == [".nanostage-output.json", "metadata.yaml", "run.mcap"]
    meta = yaml.safe_load((rec.bag_dir / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 9 and meta["storage_identifier"] == "mcap" and meta["relative_file_paths"] == ["run.mcap"]
    # readers accept the file, the directory, or the name the recorder was given
    assert mcap_file(rec.path) == mcap_file(rec.bag_dir) == mcap_file(rec.bag_dir.with_suffix(".mcap")) == rec.path


def test_mcap_profile_schemas_statistics_and_qos(synthetic):
    rec, _ = synthetic
    with open(rec.path, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == "ros2"
        stats = summary.statistics
        assert stats is not None and stats.message_count == 4 * N + 3 and stats.chunk_count > 3
        assert len(summary.chunk_indexes) == stats.chunk_count          # indexed
        assert sum(stats.channel_message_counts.values()) == stats.message_count
        for ch in summary.channels.values():
            schema = summary.schemas[ch.schema_id]
            assert ch.message_encoding == "cdr" and schema.encoding == "ros2msg"
            assert schema.name == TOPICS[ch.topic].msg_type
            assert ch.metadata["offered_qos_profiles"] == offered_qos_yaml(ch.topic)
        js = next(s for s in summary.schemas.values() if s.name == "sensor_msgs/msg/JointState").data.decode()
        assert "MSG: std_msgs/Header" in js and "MSG: builtin_interfaces/Time" in js    # dependencies included
        assert [m.name for m in reader.iter_metadata()] == ["rosbag2"]
        first = next(reader.iter_messages(log_time_order=True))
        assert first[1].topic == "/experiment/config"                                  # config first
    # chunks are closed every chunk_ns of stage time: a killed writer loses little
    spans = [c.message_end_time - c.message_start_time for c in summary.chunk_indexes]
    assert max(spans) <= 20_000_000


def test_opens_with_rosbags_anyreader(synthetic):
    rec, sig = synthetic
    got = {}
    with AnyReader([rec.bag_dir]) as reader:
        assert reader.message_count == 4 * N + 3
        for conn in reader.connections:
            (q,) = conn.ext.offered_qos_profiles
            assert q.depth == TOPICS[conn.topic].qos.depth
        for conn, t, raw in reader.messages(connections=[c for c in reader.connections
                                                         if c.topic in CONTRACT_TOPICS]):
            msg = reader.deserialize(raw, conn.msgtype)                 # rclpy-written messages too
            assert convert.stamp_ns(msg) == t
            got.setdefault(conn.topic, []).append(msg)
    assert _same_bits([m.position[0] for m in got["/stage/reference"]], sig["x_ref"])
    assert _same_bits([m.effort[0] for m in got["/stage/command"]], sig["u"])
    assert _same_bits([m.position[1] for m in got["/stage/measured"]], sig["yb"])


def test_opens_with_mcap_ros2_decoder(synthetic):
    rec, sig = synthetic
    with open(rec.path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        vel = [m.velocity[0] for _, _, _, m in reader.iter_decoded_messages(topics=["/stage/reference"])]
    assert _same_bits(vel, sig["v_ref"])


# --------------------------------------------------------------------------- reading
def test_round_trip_is_exact(synthetic):
    rec, sig = synthetic
    r = read_recording(rec.path)
    assert r.salvaged is None and r.warnings == [] and r.profile == "ros2"
    assert np.array_equal(r.stamp_ns, np.arange(N) * DT_NS) and np.array_equal(r.t, r.stamp_ns * 1e-9)
    for key, got in (("x_ref", r.x_ref), ("v_ref", r.v_ref), ("u", r.u), ("y", r.y), ("yb", r.y_bearing)):
        assert _same_bits(got, sig[key]), key
    assert r.config == "run: {case: synthetic}\n"
    assert [e["event"] for e in r.events] == ["trial_start", "trial_end"]
    (tr,) = r.trials()
    assert (tr.trial, tr.case, tr.start, tr.stop, tr.window_m, tr.complete) == (0, "syn", 0, N, 1e-3, True)
    assert r.counts["/clock"] == N and r.topics["/clock"] == "rosgraph_msgs/msg/Clock"


def test_raw_fast_cdr_bytes_read_back(tmp_path):
    """Fast CDR (rclpy) bytes written as given, trailing padding and all."""
    sig = _signals(200, seed=3)
    rec = _write_synthetic(tmp_path / "raw", sig, raw_measured=True, family=TS)
    r = read_recording(rec.bag_dir)
    assert _same_bits(r.y, sig["y"]) and _same_bits(r.y_bearing, sig["yb"]) and _same_bits(r.x_ref, sig["x_ref"])


def test_write_trials_is_the_one_writer_of_signals(tmp_path):
    """Two trials in stage time (the second failed), a series written on some samples only, the
    clock first: what is read back is what was given, events and results in order."""
    n, dt = 50, 1_000_000
    x = np.linspace(0.0, 1e-6, 2 * n)
    trials = [TrialSignals(np.arange(k * n, (k + 1) * n, dtype=np.int64) * dt,
                           [("/stage/isolator", ("isolator",), {"position": np.full(n, float(k))}, [0, 7]),
                            ("/stage/reference", ("table",), {"position": x[k * n:(k + 1) * n],
                                                              "velocity": np.zeros(n)}, None),
                            ("/stage/command", ("motor",), {"effort": -x[k * n:(k + 1) * n]}, None),
                            ("/stage/measured", ("table",), {"position": x[k * n:(k + 1) * n] + 1e-9}, None)],
                           {"window_m": 2e-8}, fault="diverged" if k else None, results={"score": float(k)},
                           clock=True)
              for k in range(2)]
    path = write_trials(tmp_path / "rec", "recording_contract: 1\n", trials, case="c", node="n")
    r = read_recording(path)
    np.testing.assert_array_equal(r.x_ref, x)
    np.testing.assert_array_equal(r.u, -x)
    np.testing.assert_array_equal(r.y, x + 1e-9)
    assert r.counts["/stage/isolator"] == 4 and r.counts["/clock"] == 2 * n
    assert [e["event"] for e in r.events] == ["run_start", "trial_start", "trial_end", "trial_start", "fault",
                                              "trial_end", "run_end"]
    assert r.events[1]["window_m"] == 2e-8 and r.events[4]["reason"] == "diverged"
    assert [(q["trial"], q["score"], q["node"]) for q in r.results] == [(0, 0.0, "n"), (1, 1.0, "n")]


def test_recording_written_by_rosbags_directly(tmp_path):
    """Another tool's contract recording (rosbags' own writer, default chunking, bearing
    listed first, an unknown topic): read_recording reads it."""
    bag = tmp_path / "rig_bag"
    n = 300
    x = np.linspace(0, 1e-6, n)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, TOPICS[t].msg_type, typestore=TS) for t in CONTRACT_TOPICS}
        extra = w.add_connection("/rig/temperature", "std_msgs/msg/Float64", typestore=TS)
        for k in range(n):
            s = 5_000_000_000 + k * DT_NS
            msgs = {"/stage/reference": convert.joint_state(TS, s, ["table"], position=[x[k]], velocity=[1e-5]),
                    "/stage/command": convert.joint_state(TS, s, ["motor"], effort=[-k * 0.5]),
                    "/stage/measured": convert.joint_state(TS, s, ["bearing", "table"], position=[-x[k], x[k] + 1e-9])}
            for t, m in msgs.items():
                w.write(conns[t], s, TS.serialize_cdr(m, TOPICS[t].msg_type))
            w.write(extra, s, TS.serialize_cdr(TS.types["std_msgs/msg/Float64"](data=21.5), "std_msgs/msg/Float64"))
    r = read_recording(bag)                       # the bag directory
    assert len(r) == n and r.stamp_ns[0] == 5_000_000_000
    assert np.array_equal(r.x_ref, x) and np.array_equal(r.y, x + 1e-9) and np.array_equal(r.y_bearing, -x)
    assert np.array_equal(r.u, -np.arange(n) * 0.5) and np.all(r.v_ref == 1e-5)
    assert r.events == [] and r.config is None and r.counts["/rig/temperature"] == n
    assert check_metrics(r)["ok"] is None                             # nothing recorded to compare with


def test_recording_written_by_mcap_ros2_writer(tmp_path):
    """A zstd-compressed file from mcap_ros2's writer, no QoS metadata, no bearing sensor."""
    from mcap_ros2.writer import Writer as Ros2Writer
    msgdef, _ = TS.generate_msgdef("sensor_msgs/msg/JointState", ros_version=2)
    path = tmp_path / "foreign.mcap"
    with open(path, "wb") as f:
        w = Ros2Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/JointState", msgdef)
        for k in range(100):
            s = k * DT_NS
            stamp = {"sec": 0, "nanosec": s}
            hdr = {"stamp": stamp, "frame_id": ""}
            w.write_message("/stage/reference", schema, {"header": hdr, "name": ["table"], "position": [k * 1e-9],
                                                          "velocity": [1e-5], "effort": []}, log_time=s)
            w.write_message("/stage/command", schema, {"header": hdr, "name": ["motor"], "position": [],
                                                        "velocity": [], "effort": [k * 1.0]}, log_time=s)
            w.write_message("/stage/measured", schema, {"header": hdr, "name": ["table"], "position": [k * 1e-9],
                                                         "velocity": [], "effort": []}, log_time=s)
        w.finish()
    r = read_recording(path)
    assert len(r) == 100 and r.u[-1] == 99.0 and np.all(np.isnan(r.y_bearing))


def test_indexed_fast_path_gives_the_mcap_librarys_messages(synthetic, tmp_path):
    """The reader's own chunk loop (:func:`indexed_messages`) against ``mcap``'s
    ``SeekingReader.iter_messages``: same messages, same order, same bytes, on our recorder's
    file (uncompressed, CRCs) and on another writer's zstd chunks; a flipped byte inside a
    chunk fails the CRC check as in the library."""
    from mcap_ros2.writer import Writer as Ros2Writer

    from experiment_runner.core.recording.mcap import indexed_messages
    msgdef, _ = TS.generate_msgdef("sensor_msgs/msg/JointState", ros_version=2)
    foreign = tmp_path / "zstd.mcap"
    with open(foreign, "wb") as f:
        w = Ros2Writer(f, chunk_size=4096)
        schema = w.register_msgdef("sensor_msgs/msg/JointState", msgdef)
        for k in range(500):
            hdr = {"stamp": {"sec": 0, "nanosec": k}, "frame_id": ""}
            w.write_message("/stage/command", schema, {"header": hdr, "name": ["motor"], "position": [],
                                                        "velocity": [], "effort": [k * 1.0]}, log_time=(k * 7919) % 500)
        w.finish()
    for path in (mcap_file(synthetic[0].path), foreign):
        with open(path, "rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert len(summary.chunk_indexes) > 1
            lib = [m for _, _, m in reader.iter_messages(log_time_order=False)]
            ours = indexed_messages(f, summary)
        assert len(ours) == len(lib) > 100 and ours == lib
    data = bytearray(mcap_file(synthetic[0].path).read_bytes())
    with open(mcap_file(synthetic[0].path), "rb") as f:
        ci = make_reader(f).get_summary().chunk_indexes[1]
    data[ci.chunk_start_offset + ci.chunk_length - 20] ^= 0xFF            # inside the chunk's records
    import io as _io

    from mcap.stream_reader import CRCValidationError
    with pytest.raises(CRCValidationError):
        indexed_messages(_io.BytesIO(bytes(data)), make_reader(_io.BytesIO(bytes(data))).get_summary())


# --------------------------------------------------------------------------- salvage
def _chunks(data: bytes):
    """(end offset, message count) of every chunk of a complete file."""
    from io import BytesIO

    from mcap.records import Chunk, Message
    from mcap.stream_reader import breakup_chunk
    summary = make_reader(BytesIO(data)).get_summary()
    counts = [sum(isinstance(x, Message) for x in breakup_chunk(rec))
              for rec in StreamReader(BytesIO(data), emit_chunks=True).records if isinstance(rec, Chunk)]
    ends = [c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes]
    assert len(ends) == len(counts)
    return list(zip(ends, counts)), summary


@pytest.mark.slow
def test_truncated_file_is_salvaged_up_to_its_last_complete_chunk(synthetic, tmp_path):
    rec, sig = synthetic
    data = rec.path.read_bytes()
    chunks, summary = _chunks(data)
    full = read_recording(rec.path)
    cuts = [len(data) - 1,                       # inside the closing magic: all data intact
            chunks[-1][0] + 5,                   # after the data, inside the summary
            chunks[len(chunks) // 2][0] + 3,     # just after a chunk, inside its message index
            chunks[len(chunks) // 2][0] - 3,     # inside a chunk
            chunks[1][0] - 100]                  # inside the second chunk
    for cut in cuts:
        path = tmp_path / f"cut_{cut}.mcap"
        path.write_bytes(data[:cut])
        r = read_recording(path)
        complete = [c for c in chunks if c[0] <= cut]
        n_msgs = sum(c[1] for c in complete)
        assert r.salvaged is not None, cut
        if cut >= chunks[-1][0]:
            assert len(r) == N and _same_bits(r.x_ref, full.x_ref)
        else:
            assert "cut short" in r.salvaged and f"from {len(complete)} complete chunk(s)" in r.salvaged
        assert f"{n_msgs} messages" in r.salvaged, (cut, r.salvaged)
        # what was salvaged is exactly the start of the recording
        assert 0 < len(r) <= N and np.array_equal(r.stamp_ns, full.stamp_ns[:len(r)])
        for a, b in ((r.x_ref, full.x_ref), (r.u, full.u), (r.y, full.y)):
            assert _same_bits(a, b[:len(r)])
        # every sample whose messages all lie in complete chunks is there (a sample may straddle)
        assert len(r) >= (n_msgs - 2) // 4 - 1
    # cut before the first chunk is complete: nothing to read, and the error says so
    path = tmp_path / "early.mcap"
    path.write_bytes(data[:chunks[0][0] - 1])
    with pytest.raises(RecordingError, match="cut short.*missing contract topic"):
        read_recording(path)


@pytest.mark.slow
def test_killed_recorder_leaves_a_readable_file(tmp_path):
    """A recorder process killed with SIGKILL: every flushed chunk is read back."""
    script = textwrap.dedent(f"""
        import sys
        from rosbags.typesys import Stores, get_typestore
        from experiment_runner.core.recording import McapRecorder
        from msg_defs import convert
        ts = get_typestore(Stores.ROS2_JAZZY)
        rec = McapRecorder(sys.argv[1], "a: 1\\n", chunk_ns=10_000_000)
        k = 0
        while True:
            s = k * {DT_NS}
            rec.write("/stage/reference", s, convert.joint_state(ts, s, ["table"], position=[k * 1e-9], velocity=[0.0]))
            rec.write("/stage/command", s, convert.joint_state(ts, s, ["motor"], effort=[k * 1.0]))
            rec.write("/stage/measured", s, convert.joint_state(ts, s, ["table"], position=[k * 2e-9]))
            if k == 2000:
                print("ready", flush=True)
            k += 1
    """)
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path / "killed")], stdout=subprocess.PIPE,
                            cwd=ROOT, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    r = read_recording(tmp_path / "killed")
    assert r.salvaged and "cut short" in r.salvaged
    assert len(r) >= 1900                                   # all but the last < 10 ms chunk
    k = np.arange(len(r))
    assert np.array_equal(r.stamp_ns, k * DT_NS) and np.array_equal(r.u, k * 1.0)
    assert np.array_equal(r.x_ref, k * 1e-9) and np.array_equal(r.y, k * 2e-9)
    assert r.config == "a: 1\n"


# --------------------------------------------------------------------------- errors
def _mcap_with_profile(path, profile):
    from mcap.writer import Writer as RawWriter
    with open(path, "wb") as f:
        w = RawWriter(f)
        w.start(profile=profile, library="test")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data")
        cid = w.register_channel("/stage/reference", "cdr", sid)
        w.add_message(cid, log_time=0, data=b"\x00\x01\x00\x00\x01\x00\x00\x00\x00\x00\x00\x00", publish_time=0)
        w.finish()


def test_errors_name_the_problem(tmp_path):
    txt = tmp_path / "notes.mcap"
    txt.write_text("these are not the bytes you are looking for\n")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_recording(txt)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="not an MCAP file"):
        read_recording(empty)
    _mcap_with_profile(tmp_path / "ros1.mcap", "ros1")
    with pytest.raises(RecordingError, match="profile 'ros1'.*needs 'ros2'"):
        read_recording(tmp_path / "ros1.mcap")
    _mcap_with_profile(tmp_path / "noprofile.mcap", "")
    with pytest.raises(RecordingError, match="profile ''"):
        read_recording(tmp_path / "noprofile.mcap")
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "nothing.mcap")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(RecordingError, match="no .mcap file"):
        read_recording(tmp_path / "emptydir")
    # a contract topic missing
    with McapRecorder(tmp_path / "partial") as rec:
        for k in range(10):
            s = k * DT_NS
            rec.write("/stage/reference", s, convert.joint_state(TS, s, ["table"], position=[0.0], velocity=[0.0]))
            rec.write("/stage/measured", s, convert.joint_state(TS, s, ["table"], position=[0.0]))
    with pytest.raises(RecordingError, match=r"missing contract topic\(s\) /stage/command"):
        read_recording(rec.path)
    # a contract topic of the wrong type (written raw by another tool)
    with Writer(tmp_path / "wrongtype", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        for t in CONTRACT_TOPICS:
            typ = "std_msgs/msg/String" if t == "/stage/command" else TOPICS[t].msg_type
            c = w.add_connection(t, typ, typestore=TS)
            w.write(c, 0, TS.serialize_cdr(TS.types[typ](data="x") if typ.endswith("String")
                                           else convert.joint_state(TS, 0, ["table"], position=[0.0]), typ))
    with pytest.raises(RecordingError, match="/stage/command has type std_msgs/msg/String"):
        read_recording(tmp_path / "wrongtype")
    # a contract topic without the joint it must carry
    with McapRecorder(tmp_path / "nojoint") as rec:
        rec.write("/stage/reference", 0, convert.joint_state(TS, 0, ["table"], position=[0.0]))
        rec.write("/stage/command", 0, convert.joint_state(TS, 0, ["drive"], effort=[0.0]))
        rec.write("/stage/measured", 0, convert.joint_state(TS, 0, ["table"], position=[0.0]))
    with pytest.raises(RecordingError, match="/stage/command has no joint 'motor'"):
        read_recording(rec.path)


def test_recorder_enforces_the_contract(tmp_path):
    rec = McapRecorder(tmp_path / "r")
    with pytest.raises(OutputError, match="exists; pass --overwrite"):
        McapRecorder(tmp_path / "r")
    rec.write("/stage/command", 0, convert.joint_state(TS, 0, ["motor"], effort=[1.0]))
    with pytest.raises(ValueError, match="once, first"):
        rec.write("/experiment/config", 0, convert.string_msg(TS, "a: 1"))
    with pytest.raises(ValueError, match="stamp 5 ns != log time 6 ns"):
        rec.write("/stage/command", 6, convert.joint_state(None, 5, ["motor"], effort=[1.0]))
    with pytest.raises(TypeError, match="carries sensor_msgs/msg/JointState"):
        rec.write("/stage/measured", 0, convert.string_msg(None, "x"))
    with pytest.raises(KeyError, match="give its msg_type"):
        rec.write("/my/raw", 0, b"\x00\x01\x00\x00")
    rec.add_topic("/my/raw", "std_msgs/msg/Float64")
    rec.write("/my/raw", 0, TS.serialize_cdr(TS.types["std_msgs/msg/Float64"](data=1.0), "std_msgs/msg/Float64"))
    rec.write("/my/string", 0, convert.string_msg(None, "non-contract topic: type from the message"))
    rec.close()
    rec.close()                                            # idempotent
    assert rec.counts == {"/stage/command": 1, "/my/raw": 1, "/my/string": 1}
    McapRecorder(tmp_path / "r", overwrite=True).close()


# --------------------------------------------------------------------------- batch runs
def _batch(preset, n, rng, failed=False):
    """A synthetic BatchResult of one trial (no simulation)."""
    t = np.arange(n) * 1e-4
    x_ref = np.minimum(t / 0.01, 1.0)[None] * 5e-6
    v_ref = np.where(t < 0.01, 5e-6 / 0.01, 0.0)[None]
    y = x_ref + rng.standard_normal((1, n)) * 1e-9
    mode = (t > 0.02).astype(float)[None]
    fields = dict(t=t, x_ref=x_ref, x_correction=np.zeros_like(x_ref), v_ref=v_ref, y=y, y_bearing=y * 0.5,
                  u=rng.standard_normal((1, n)), x_table=y + 1e-12, x_bearing=y * 0.5 + 1e-12,
                  dither=rng.standard_normal((1, n, 2)), mode=mode, status=np.array([2 if failed else 0]),
                  fail_step=np.array([n // 2 if failed else -1]))
    return BatchResult(**{k: v for k, v in fields.items() if k in BatchResult.__dataclass_fields__})


def test_write_run_with_dither_sai_and_a_failed_trial(tmp_path):
    rng = np.random.default_rng(5)
    preset = load_preset("van_stage")
    assert preset.dither is not None
    ok, bad = _batch(preset, 400, rng), _batch(preset, 400, rng, failed=True)
    both = BatchResult(**{k: (np.concatenate([getattr(ok, k), getattr(bad, k)]) if k != "t" else ok.t)
                          for k in ok.__dataclass_fields__})
    sai = load_preset("sai_stage")
    f = write_run(tmp_path / "van", both, preset, window=20e-9, case="van", clock=True)
    r = read_recording(f)
    assert len(r) == 400 + 201 and r.counts["/clock"] == 601
    assert r.dither is not None and r.dither.names == ["piezo_1", "piezo_2"]
    assert np.array_equal(r.dither.effort, np.concatenate([ok.dither[0], bad.dither[0, :201]]))
    t0, t1 = r.trials()
    assert t0.complete and not t1.complete and t1.stop - t1.start == 201
    assert [e["event"] for e in t1.events] == ["trial_start", "fault", "trial_end"]
    assert "travel" in t1.events[1]["reason"]
    g = write_run(tmp_path / "sai", ok, sai, window=20e-9)
    r = read_recording(g)
    iso = r.isolator
    assert list(iso.joint("isolator")) == [0.0, 1.0] and iso.stamp_ns[1] == np.argmax(ok.mode[0]) * DT_NS
    assert r.truth.names == (["table", "bearing"] if sai.stage.bearings else ["table"])


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    from experiment_runner.core.batch import simulate
    from experiment_runner.core.profiles import point_to_point
    preset = load_preset("fi_stage")
    ref = point_to_point(5e-6)
    res = simulate(preset, ref.x, ref.v, n_trials=2, x0=[0.0, 1e-3])
    path = write_run(tmp_path_factory.mktemp("sim") / "p2p.mcap", res, preset, reference=ref, window=25e-9,
                     case="p2p_5um")
    return preset, ref, res, path


@pytest.mark.slow
def test_write_run_round_trip_of_a_simulation(simulated):
    preset, ref, res, path = simulated
    r = read_recording(path)
    T = len(ref.x)
    assert len(r) == 2 * T and r.salvaged is None and r.warnings == []
    for got, want in ((r.x_ref, res.x_ref), (r.v_ref, res.v_ref), (r.u, res.u), (r.y, res.y),
                      (r.y_bearing, res.y_bearing)):
        assert _same_bits(got, want.reshape(-1))
    assert np.array_equal(r.truth.joint("table"), res.x_table.reshape(-1))
    cfg = yaml.safe_load(r.config)
    assert cfg["preset"]["name"] == "fi_stage" and cfg["run"]["window_m"] == 25e-9
    trials = r.trials()
    assert [(t.trial, t.start, t.stop, t.complete) for t in trials] == [(0, 0, T, True), (1, T, 2 * T, True)]
    settle = ref.select("settle")[-1]
    assert trials[1].target_m == pytest.approx(settle.target + 1e-3, abs=1e-18)
    assert trials[1].settle_start_ns == (T + settle.start) * DT_NS
    # the metrics recorded equal those recomputed from the file and those of the batch arrays
    chk = check_metrics(r)
    assert chk["ok"] is True and chk["compared"] == 2
    for i, row in enumerate(chk["trials"]):
        direct = trial_metrics(res.t, res.x_ref[i], res.v_ref[i], res.y[i], window=25e-9,
                               target=settle.target + res.x_ref[i, 0] - ref.x[0], settle_start=res.t[settle.start])
        for key in ("settling_time_s", "rms_in_position_m", "peak_tracking_error_m", "rms_tracking_error_m"):
            assert row[key] == pytest.approx(direct[key], rel=1e-9, abs=1e-12, nan_ok=True), key
        assert np.isfinite(row["settling_time_s"])


@pytest.mark.slow
def test_check_metrics_catches_a_wrong_result(simulated, tmp_path, capsys):
    preset, ref, res, _ = simulated
    path = write_run(tmp_path / "tampered", res, preset, trials=[0], reference=ref, window=25e-9, results=False)
    # append a wrong result by rewriting the bag with an extra message
    r = read_recording(path)
    with McapRecorder(tmp_path / "tampered2", r.config) as rec:
        for k, s in enumerate(r.stamp_ns):
            rec.write("/stage/reference", s, convert.joint_state(TS, s, ["table"], position=[r.x_ref[k]],
                                                                 velocity=[r.v_ref[k]]))
            rec.write("/stage/command", s, convert.joint_state(TS, s, ["motor"], effort=[r.u[k]]))
            rec.write("/stage/measured", s, convert.joint_state(TS, s, ["table", "bearing"],
                                                                position=[r.y[k], r.y_bearing[k]]))
        for ev in r.events:
            ev = {k: v for k, v in ev.items() if k != "log_time_ns"}
            rec.write("/experiment/events", ev["stamp_ns"], convert.event_msg(TS, ev.pop("event"), **ev))
        rec.write("/experiment/results", int(r.stamp_ns[-1]), convert.string_msg(
            TS, convert.to_json({"trial": 0, "settling_time_s": 0.5, "rms_in_position_m": None})))
    chk = check_metrics(rec.path)
    assert chk["ok"] is False and set(chk["trials"][0]["mismatches"]) == {"settling_time_s", "rms_in_position_m"}
    import argparse
    args = add_replay_arguments(argparse.ArgumentParser()).parse_args([str(rec.path), "--check", "--no-publish"])
    assert main_replay(args) == 1
    assert "DIFFERS: settling_time_s, rms_in_position_m" in capsys.readouterr().out
    args = add_replay_arguments(argparse.ArgumentParser()).parse_args([str(path), "--check", "--no-publish", "--json"])
    assert main_replay(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["check"]["ok"] is None and out["check"]["trials"][0]["settling_time_s"] > 0


# --------------------------------------------------------------------------- replay (ROS)
PROBE = textwrap.dedent("""
    import json, sys, threading, time
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from msg_defs import convert
    from msg_defs.topics import CLOCK, MEASURED
    from experiment_runner.apps.replay import check_metrics
    from experiment_runner.ros.player import replay
    from experiment_runner.ros.qos import qos_profile

    ctx = Context()
    rclpy.init(context=ctx)
    node = Node("replay_probe", context=ctx)
    got = {"measured": [], "clock": []}
    node.create_subscription(convert.message_class(None, MEASURED.msg_type), MEASURED.name,
                             lambda m: got["measured"].append([convert.stamp_ns(m), convert.joint(m, "table")]),
                             qos_profile(MEASURED))
    node.create_subscription(convert.message_class(None, CLOCK.msg_type), CLOCK.name,
                             lambda m: got["clock"].append(convert.stamp_ns(m)), qos_profile(CLOCK))
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    out = replay(sys.argv[1], rate=float(sys.argv[2]), wait_for=1)
    out["check"] = check_metrics(sys.argv[1])
    deadline = time.monotonic() + 10
    while len(got["measured"]) < out["published"]["/stage/measured"] and time.monotonic() < deadline:
        time.sleep(0.05)
    ex.shutdown()
    rclpy.shutdown(context=ctx)
    th.join()
    print(json.dumps({"out": out["published"], "ok": out["check"]["ok"], "wall": out["wall_time_s"], **got}))
""")


@pytest.mark.ros
def test_replay_republishes_with_clock(tmp_path, ros_domain):
    sig = _signals(300, seed=9)
    rec = _write_synthetic(tmp_path / "small", sig, family=TS)
    from experiment_runner.ros.run import domain_env
    env = domain_env(ros_domain)                        # a graph's settings, before the probe's participant
    proc = subprocess.run([sys.executable, "-c", PROBE, str(rec.bag_dir), "0"], env=env, cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["out"]["/stage/measured"] == 300 and "/clock" not in res["out"]   # /clock made from log times
    stamps = [s for s, _ in res["measured"]]
    assert stamps == [k * DT_NS for k in range(300)]
    assert _same_bits([y for _, y in res["measured"]], sig["y"])
    assert res["clock"] == stamps
    assert res["ok"] is None


def test_trials_without_end_events(tmp_path):
    """An aborted trial ends where the next starts; the last runs to the end of the file."""
    with McapRecorder(tmp_path / "aborted") as rec:
        for k in range(30):
            s = k * DT_NS
            if k in (0, 10):
                rec.write("/experiment/events", s, convert.event_msg(TS, "trial_start", trial=k // 10, stamp_ns=s))
            if k == 5:
                rec.write("/experiment/events", s, convert.event_msg(TS, "abort", trial=0, stamp_ns=s,
                                                                    reason="operator stop", node="sequencer"))
            rec.write("/stage/reference", s, convert.joint_state(TS, s, ["table"], position=[0.0], velocity=[0.0]))
            rec.write("/stage/command", s, convert.joint_state(TS, s, ["motor"], effort=[0.0]))
            rec.write("/stage/measured", s, convert.joint_state(TS, s, ["table"], position=[1e-9 * k]))
    t0, t1 = read_recording(rec.path).trials()
    assert (t0.start, t0.stop, t0.complete, t0.end_ns) == (0, 10, False, None)
    assert [e["event"] for e in t0.events] == ["trial_start", "abort"] and t0.events[1]["reason"] == "operator stop"
    assert (t1.start, t1.stop, t1.complete) == (10, 30, False)
    chk = check_metrics(rec.path)
    assert [r["complete"] for r in chk["trials"]] == [False, False] and chk["ok"] is None


# --------------------------------------------------------------------------- damage
def test_recorder_writes_chunk_crcs_and_a_bad_crc_is_refused(synthetic, tmp_path):
    """Every chunk we write carries the CRC-32 of its records; one flipped bit inside a
    chunk of a complete file is a RecordingError naming the chunk, not silently wrong data."""
    import zlib
    from io import BytesIO

    from mcap.records import Chunk
    rec, _ = synthetic
    data = rec.path.read_bytes()
    chunks = [r for r in StreamReader(BytesIO(data), emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) > 3 and all(c.uncompressed_crc == zlib.crc32(c.data) != 0 for c in chunks)
    second_chunk_end = _chunks(data)[0][1][0]
    bad = bytearray(data)
    bad[second_chunk_end - 50] ^= 0x10          # inside the records of the second chunk
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(bad))
    with pytest.raises(RecordingError, match=r"damaged: a chunk \(stage time 0\.0[0-9]+ s to 0\.0[0-9]+ s\) "
                                             r"fails its CRC check at byte \d+ .*1 chunk\(s\) before it"):
        read_recording(path)


def test_corrupt_length_in_a_complete_file_is_damage_not_a_cut(synthetic, tmp_path):
    import struct
    rec, _ = synthetic
    data = bytearray(rec.path.read_bytes())
    start = _chunks(bytes(data))[1].chunk_indexes[1].chunk_start_offset
    struct.pack_into("<Q", data, start + 1, 2**40)      # the length of the second chunk record
    assert len(read_recording(_put(tmp_path / "index.mcap", data))) == 1200   # the index has the true length
    footer = len(data) - 8 - (1 + 8 + 8 + 8 + 4)
    struct.pack_into("<Q", data, footer + 9, 0)         # footer: no summary -> read record by record
    with pytest.raises(RecordingError, match="damaged: .* runs past the end of the data .*the length is wrong"):
        read_recording(_put(tmp_path / "badlength.mcap", data))


def _put(path, data):
    path.write_bytes(bytes(data))
    return path


def test_truncated_bag_says_how_much_of_the_recording_was_salvaged(synthetic, tmp_path):
    """Cut inside a bag directory: the note gives salvaged / recorded messages (metadata.yaml)."""
    import shutil
    rec, _ = synthetic
    bag = tmp_path / "cut"
    shutil.copytree(rec.bag_dir, bag)
    mcap = bag / rec.path.name
    data = mcap.read_bytes()
    chunks, summary = _chunks(data)
    total = summary.statistics.message_count
    cut = chunks[2][0] + 7
    mcap.write_bytes(data[:cut])
    r = read_recording(bag)
    n = sum(c[1] for c in chunks[:3])
    assert f"salvaged {n} messages of {total} recorded, stage time 0.000000 s to " in r.salvaged
    assert "from 3 complete chunk(s)" in r.salvaged and f"at byte {cut - 7} of {cut}" in r.salvaged


def test_undeclared_channel_and_unreadable_events(tmp_path):
    from mcap.writer import Writer as RawWriter
    msgdef, _ = TS.generate_msgdef("sensor_msgs/msg/JointState", ros_version=2)
    path = tmp_path / "undeclared.mcap"
    with open(path, "wb") as f:
        w = RawWriter(f)
        w.start(profile="ros2", library="test")
        sid = w.register_schema("sensor_msgs/msg/JointState", "ros2msg", msgdef.encode())
        for t in CONTRACT_TOPICS:
            cid = w.register_channel(t, "cdr", sid)
            w.add_message(cid, log_time=0, publish_time=0, data=TS.serialize_cdr(
                convert.joint_state(TS, 0, ["table", "motor"], position=[0.0, 0.0], effort=[0.0, 0.0]),
                "sensor_msgs/msg/JointState"))
        w.add_message(77, log_time=0, publish_time=0, data=b"")
        w.finish()
    with pytest.raises(RecordingError, match="on channel 77, which the file does not declare"):
        read_recording(path)
    # events of the wrong shape are skipped with a warning, never break trials()
    with McapRecorder(tmp_path / "events") as rec:
        rec.write("/experiment/events", 0, convert.string_msg(TS, '{"event": "trial_start", "stamp_ns": "0"}'))
        rec.write("/experiment/events", 0, convert.string_msg(TS, '{"event": "trial_start", "stamp_ns": 0, '
                                                                  '"trial": true}'))
        rec.write("/experiment/events", 0, convert.string_msg(TS, "[1, 2]"))
        rec.write("/stage/reference", 0, convert.joint_state(TS, 0, ["table"], position=[0.0]))
        rec.write("/stage/command", 0, convert.joint_state(TS, 0, ["motor"], effort=[0.0]))
        rec.write("/stage/measured", 0, convert.joint_state(TS, 0, ["table"], position=[0.0]))
    r = read_recording(rec.path)
    assert r.events == [] and r.trials() == [] and len(r.warnings) == 3
    assert "stamp_ns '0' is not an integer" in r.warnings[0] and "trial True is not an integer" in r.warnings[1]


def test_a_pipe_or_device_is_refused_without_blocking(tmp_path):
    fifo = tmp_path / "run.mcap"
    os.mkfifo(fifo)                                   # opening it for reading would wait for a writer
    for p in (fifo, Path("/dev/zero")):
        with pytest.raises(RecordingError, match=f"^{p}: not a regular file"):
            read_recording(p)
