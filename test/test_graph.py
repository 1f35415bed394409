"""Topic-level integration tests of the ROS 2 node graph.

Every node runs as its own process (the console scripts ``plant_sim``,
``servo_controller``, ``dither_generator``, ``sai_manager``, ``recorder``,
``experiment_sequencer``: :class:`experiment_runner.ros.launch.NodeProcesses`, the
``node_graph`` fixture) on a ROS domain leased to the test (``conftest.lease_domain``: never
the default, never another running test's), localhost-only on 127.0.0.1 (``domain_env``).
What a test checks is what went over the topics: the MCAP recording read back with
``read_recording``, the ``/experiment/events`` heard by a listener in this process
(``conftest.Listener``), parameter services. Every wait is bounded; no timing is asserted
(speed is ``nanostage bench``'s job).
"""
from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import GRAPH_TIMEOUT as RUN_TIMEOUT
from conftest import lease_domain, ros_environment
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from experiment_runner.core.experiment import build_trials, experiment_preset, load_experiment, run_batch, trial_metrics
from experiment_runner.core.recording import read_recording
from experiment_runner.ros.launch import run_processes
from experiment_runner.ros.nodes import NODE_NAMES
from experiment_runner.ros.run import domain_env

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
WITH_LISTENER = {"wait_for_nodes": 6}  # the five trajectory subscribers of the graph + the Listener



def _graph_run(tmp_path_factory, experiment: str) -> dict:
    """A whole experiment, one process per node, through ``run_processes``."""
    out = tmp_path_factory.mktemp(experiment)
    with lease_domain() as domain, ros_environment(domain):     # run_processes sets the domain in os.environ
        code = run_processes(experiment, out / "run", timeout=RUN_TIMEOUT, domain_id=domain)
    return {"code": code, "rec": read_recording(out / "run"), "out": out}


def _batch(name):
    exp = load_experiment(name)
    trials, res = run_batch(exp)
    return exp, trials, res


# =========================================================================== 1. FI point-to-point
@pytest.fixture(scope="module")
def fi_run(tmp_path_factory):
    return _graph_run(tmp_path_factory, "fi_p2p_5um")


@pytest.mark.slow
def test_fi_point_to_point_settles_and_publishes_its_settling_time(fi_run):
    rec = fi_run["rec"]
    assert fi_run["code"] == 0
    assert rec.salvaged is None and not rec.warnings
    exp = load_experiment("fi_p2p_5um")
    trials = rec.trials()
    assert [t.trial for t in trials] == list(range(exp.trials)) and all(t.complete for t in trials)
    assert [r["trial"] for r in rec.results] == list(range(exp.trials))
    for r in rec.results:
        assert r["node"] == "experiment_sequencer" and r["case"] == "fi_p2p_5um"
        ts = r["settling_time_s"]
        assert isinstance(ts, float) and 0.0 < ts < exp.profile.dwell, r
        assert r["rms_in_position_m"] is not None and r["rms_in_position_m"] < exp.window
    ev = [e["event"] for e in rec.events]
    assert ev[0] == "run_start" and ev[-1] == "run_end" and "abort" not in ev and "fault" not in ev


@pytest.mark.slow
def test_fi_trajectories_equal_the_batch_engine_bit_for_bit(fi_run):
    rec = fi_run["rec"]
    exp, trials, res = _batch("fi_p2p_5um")
    rate = experiment_preset(exp).controller.rate
    got = rec.trials()
    assert len(got) == len(trials)
    for t, tr in zip(got, trials):
        n = len(tr.x_ref)
        assert t.stop - t.start == n
        assert np.array_equal(rec.x_ref[t.slice], tr.x_ref)
        assert np.array_equal(rec.y[t.slice], res.y[tr.index]), f"trial {tr.index}: y differs from the batch"
        assert np.array_equal(rec.u[t.slice], res.u[tr.index])
        # the published settling time is the batch trajectory's
        want = trial_metrics(tr, res.y[tr.index], tr.x_ref, rate)["settling_time_s"]
        assert rec.results[tr.index]["settling_time_s"] == want


# =========================================================================== 2. SAI switching
@pytest.fixture(scope="module")
def sai_run(tmp_path_factory):
    return _graph_run(tmp_path_factory, "sai_p2p_5um")


@pytest.mark.slow
def test_sai_goes_compliant_before_the_move_and_stiff_at_the_target(sai_run):
    rec = sai_run["rec"]
    assert sai_run["code"] == 0
    exp = load_experiment("sai_p2p_5um")
    trials = build_trials(exp)
    dt_ns = int(round(1e9 / experiment_preset(exp).controller.rate))
    iso = rec.isolator
    assert iso is not None and iso.names == ["isolator"]
    stamps, mode = iso.stamp_ns, iso.joint("isolator")
    assert set(np.unique(mode)) <= {0.0, 1.0}
    got = rec.trials()
    assert [t.trial for t in got] == list(range(exp.trials)) and all(t.complete for t in got)
    for t, tr in zip(got, trials):
        move = next(s for s in tr.segments if s.kind == "move")
        move_ns = t.start_ns + move.start * dt_ns                   # the reference starts moving
        assert t.settle_start_ns is not None and t.settle_start_ns > move_ns
        x = rec.x_ref[t.slice]
        k_settle = (t.settle_start_ns - t.start_ns) // dt_ns
        assert np.all(x[:move.start] == x[0]) and x[move.start + 1] != x[0]   # at rest until move_ns
        assert x[k_settle] == t.target_m and np.all(x[k_settle:] == t.target_m)
        mine = (stamps >= t.start_ns) & (stamps <= t.end_ns)
        s, m = stamps[mine], mode[mine]
        compliant = s[m == 1.0]
        assert compliant.size, f"trial {t.trial}: the SAI never went compliant"
        assert compliant[0] < move_ns, f"trial {t.trial}: compliant at {compliant[0]} ns, move at {move_ns} ns"
        stiff_after = s[(m == 0.0) & (s > compliant[0])]
        assert stiff_after.size, f"trial {t.trial}: the SAI never went stiff again"
        assert stiff_after[0] >= t.settle_start_ns, (
            f"trial {t.trial}: stiff at {stiff_after[0]} ns before the reference reached its target "
            f"({t.settle_start_ns} ns)")
        assert m[-1] == 0.0                                          # and stays stiff
    # the graph's trajectories are the batch engine's here too
    _, _, res = _batch("sai_p2p_5um")
    for t, tr in zip(got, trials):
        assert np.array_equal(rec.y[t.slice], res.y[tr.index])
    assert all(r["settling_time_s"] is not None for r in rec.results)


# =========================================================================== 3. VAN harmonic cancelling
@pytest.fixture(scope="module")
def van_runs(tmp_path_factory):
    return {name: _graph_run(tmp_path_factory, name) for name in ("van_asym_no_hc", "van_asym_hc")}


def _tail_pp(rec, seconds=0.05):
    """Peak-to-peak of the true table position over the last ``seconds`` [m]."""
    n = int(round(seconds / (rec.t[1] - rec.t[0])))
    table = rec.truth.joint("table")
    assert len(table) == len(rec) and not np.isnan(table[-n:]).any()
    return float(np.ptp(table[-n:])), float(np.ptp(rec.y[-n:]))


@pytest.mark.slow
def test_dither_hc_removes_the_parasitic_vibration_of_an_asymmetric_van_stage(van_runs):
    no_hc, hc = van_runs["van_asym_no_hc"], van_runs["van_asym_hc"]
    assert no_hc["code"] == 0 and hc["code"] == 0
    for run in (no_hc, hc):
        assert run["rec"].dither is not None and len(run["rec"].dither) == len(run["rec"])
        assert np.abs(run["rec"].dither.effort).max() > 0.0           # the dither is on in both
    pp_no, pp_no_meas = _tail_pp(no_hc["rec"])
    pp_hc, pp_hc_meas = _tail_pp(hc["rec"])
    assert pp_no > 10.0 * pp_hc, f"p-p last 50 ms: without HC {pp_no:.3g} m, with HC {pp_hc:.3g} m"
    assert pp_no_meas > 10.0 * pp_hc_meas
    assert no_hc["rec"].results[0]["settling_time_s"] is None          # never settles without HC
    assert hc["rec"].results[0]["settling_time_s"] is not None


# =========================================================================== 4. killed nodes
@pytest.mark.slow
def test_servo_killed_mid_trial_aborts_the_trial_naming_it(tmp_path, ros_domain, listener, node_graph):
    lst = listener(ros_domain)
    g = node_graph("fi_p2p_5um", ros_domain, params={"plant_sim": {"input_timeout": 3.0},
                                                     "experiment_sequencer": WITH_LISTENER})
    try:
        seq = g.procs["experiment_sequencer"]
        # into the first trial: it started and the servo has sent 200 commands
        heard = lst.wait_for(lambda ev: any(e["event"] == "trial_start" for e in ev) and lst.commands >= 200,
                             RUN_TIMEOUT, alive=lambda: seq.poll() is None)
        assert heard, f"no trial_start and 200 servo commands within the timeout ({lst.commands} heard)"
        g.kill("servo_controller")
        code = g.wait(timeout=RUN_TIMEOUT)                         # the run stops by itself (None: it did not)
        lst.wait_for(lambda ev: any(e["event"] == "run_end" for e in ev), 5.0)
    finally:
        codes = g.stop()
    assert code == 1, "an aborted run exits non-zero"
    assert all(c != "hung" for c in codes.values()), codes
    assert codes["servo_controller"] == -signal.SIGKILL
    # what the test heard live
    aborts = [e for e in lst.events if e["event"] == "abort"]
    faults = [e for e in lst.events if e["event"] == "fault"]
    assert len(aborts) == 1 and "servo_controller" in aborts[0]["reason"]
    assert faults and faults[0]["node"] == "plant_sim" and faults[0]["silent"] == ["servo_controller"]
    assert "servo_controller" in faults[0]["reason"]
    killed = aborts[0]["trial"]
    assert killed is not None and faults[0]["trial"] == killed
    assert not any(e["event"] == "trial_end" and e["trial"] == killed for e in lst.events)
    # what the recorder wrote reads back, with the abort in it
    rec = read_recording(tmp_path / "run")
    assert any(e["event"] == "abort" and e["trial"] == killed and "servo_controller" in e["reason"]
               for e in rec.events)
    tr = next(t for t in rec.trials() if t.trial == killed)
    assert not tr.complete and tr.end_ns is None
    assert tr.stop > tr.start                                      # killed mid-trial: samples were taken
    assert len(rec.results) == killed                              # no result for the aborted trial
    _, trials, res = _batch("fi_p2p_5um")
    assert np.array_equal(rec.y[tr.slice], res.y[killed][:tr.stop - tr.start])


@pytest.mark.slow
def test_recorder_killed_mid_run_leaves_a_salvageable_file_and_a_restarted_one_the_rest(
        tmp_path, ros_domain, listener, node_graph):
    lst = listener(ros_domain)
    params = {"experiment_sequencer": {**WITH_LISTENER, "sample_timeout": 120.0},
              "plant_sim": {"input_timeout": 120.0}}
    g = node_graph("fi_p2p_5um", ros_domain, params=params)
    try:
        seq = g.procs["experiment_sequencer"]
        # trial 2 starts after 2454 samples: two 0.1 s chunks are closed by then
        heard = lst.wait_for(lambda ev: any(e["event"] == "trial_start" and e["trial"] == 2 for e in ev),
                             RUN_TIMEOUT, alive=lambda: seq.poll() is None)
        assert heard, "trial 2 did not start within the timeout"
        g.pause("servo_controller")                                # hold the loop while the recorder restarts
        g.restart("recorder")
        deadline = time.monotonic() + RUN_TIMEOUT                  # until the new one has the run's config
        while "recording to" not in g.stderr("recorder") and time.monotonic() < deadline:   # the new one's line
            time.sleep(0.2)
        time.sleep(2.0)     # the loop is held: let discovery match the plant's publishers with it too
        g.resume("servo_controller")
        code = g.wait(timeout=RUN_TIMEOUT)                         # the recorder is not in the loop
    finally:
        codes = g.stop()
    assert code == 0 and all(c != "hung" for c in codes.values()), codes
    # the restarted recorder did not replace the first part: it wrote the next free bag, the rest of the run
    second = read_recording(tmp_path / "run_2")
    assert second.salvaged is None and "run_end" in [e["event"] for e in second.events]
    # after run_end at most the recorder's own note that it fell behind catching up (load)
    tail = second.events[[e["event"] for e in second.events].index("run_end") + 1:]
    assert all(e.get("cause") == "recording_incomplete" for e in tail), tail
    assert [r["trial"] for r in second.results] == [2] and not any(e["event"] == "abort" for e in second.events)
    _, trials, res = _batch("fi_p2p_5um")
    everything = np.concatenate([res.y[t.index] for t in trials])
    k = second.stamp_ns // 100_000                                 # run sample index (10 kHz)
    assert 0 < len(second) and np.array_equal(second.y, everything[k])
    rec = read_recording(tmp_path / "run")
    assert isinstance(rec.salvaged, str) and rec.salvaged, "a cut file says what was salvaged"
    _, trials, res = _batch("fi_p2p_5um")
    n0 = len(trials[0].x_ref)
    # samples indexed by their stage time (the run starts at 0): a recorder matched late with a
    # publisher (a loaded machine) may lack the run's first samples of a topic, which the reading
    # then leaves out (with a warning); what it has must be right
    k = rec.stamp_ns // 100_000
    assert k[-1] >= n0 - 1 and len(rec) < sum(len(t.x_ref) for t in trials)   # trial 0 at least, not the whole run
    assert np.array_equal(rec.y, np.concatenate([res.y[t.index] for t in trials])[k])   # what was salvaged is right
    assert rec.config is not None and rec.results[0]["trial"] == 0


@pytest.mark.slow
def test_a_controller_that_joins_late_gets_the_sample_again_and_nothing_is_lost(tmp_path, ros_domain, listener,
                                                                                node_graph):
    """A sample published before its subscriber was matched is lost even on a reliable
    topic (what a slow start-up does at random): here the servo starts only after the
    trial did. The plant sends the waiting sample again, the servo answers, and the run
    is the batch engine's, sample for sample (nothing computed twice, nothing recorded twice)."""
    import yaml
    from experiment_runner.core.experiment import EXPERIMENT_DIR
    doc = yaml.safe_load((EXPERIMENT_DIR / "fi_p2p_5um.yaml").read_text())
    doc.update(name="late_servo", trials=1)
    exp_file = tmp_path / "late_servo.yaml"
    exp_file.write_text(yaml.safe_dump(doc))
    lst = listener(ros_domain)
    params = {"plant_sim": {"input_timeout": 60.0},
              "experiment_sequencer": {"wait_for_nodes": 3, "sample_timeout": 60.0}}   # plant, recorder, listener
    g = node_graph(exp_file, ros_domain, params=params, nodes=("plant_sim", "recorder", "experiment_sequencer"))
    try:
        seq = g.procs["experiment_sequencer"]
        assert lst.wait_for(lambda ev: any(e["event"] == "trial_start" for e in ev), RUN_TIMEOUT,
                            alive=lambda: seq.poll() is None), "the trial did not start"
        g.start("servo_controller")
        code = g.wait(timeout=RUN_TIMEOUT)
    finally:
        codes = g.stop()
    assert code == 0 and all(c != "hung" for c in codes.values()), codes     # 1 = aborted
    # The plant's measurements (the recorder matched the plant from the start) are the batch
    # engine's, sample for sample, each recorded once. The late servo's first commands went
    # out before discovery matched it with the recorder; the recorder still gets the last
    # 0.1 s of them (msg_defs.topics.subscription_qos), but a slower discovery (a loaded CI
    # machine) loses more, possibly all of this short trial: whatever it has is right.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from experiment_runner.core.recording import bag_layout
    with open(bag_layout(tmp_path / "run")[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        msgs = [(ch.topic, raw.log_time, m) for _, ch, raw, m in
                reader.iter_decoded_messages(topics=["/stage/measured", "/stage/command"])]
    y = [m.position[0] for t, _, m in msgs if t == "/stage/measured"]
    cmd = [(lt, m.effort[0]) for t, lt, m in msgs if t == "/stage/command"]
    _, trials, res = _batch("fi_p2p_5um")
    assert len(y) == len(trials[0].x_ref) and np.array_equal(np.asarray(y), res.y[0])
    stamps = np.array([lt for lt, _ in cmd], dtype=np.int64)
    k = stamps // 100_000                                         # sample index (the run starts at 0)
    assert len(np.unique(stamps)) == len(stamps)                  # nothing recorded twice
    assert np.array_equal(np.array([u for _, u in cmd]), res.u[0][k])


# =========================================================================== 5. parameters
def _params_file(path: Path, node: str, **values) -> Path:
    import yaml
    path.write_text(yaml.safe_dump({node: {"ros__parameters": values}}))
    return path


def _run_refused(args, domain, timeout=60.0):
    proc = subprocess.run(args, env=domain_env(domain), capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stderr


@pytest.mark.slow
def test_params_file_sets_a_node_parameter_and_bad_values_are_refused_at_run_time(tmp_path, ros_domain, listener,
                                                                                  node_graph):
    lst = listener(ros_domain)
    pfile = _params_file(tmp_path / "plant.yaml", "plant_sim", input_timeout=0.75)
    g = node_graph("fi_p2p_5um", ros_domain, nodes=("plant_sim",), ros_args={"plant_sim": ["--params-file", str(pfile)]})
    try:
        client = AsyncParameterClient(lst.node, "plant_sim")
        assert client.wait_for_services(timeout_sec=RUN_TIMEOUT), "plant_sim parameter services"
        got = lst.call(lambda: client.get_parameters(["input_timeout"]))
        assert got.values[0].double_value == 0.75
        bad = lst.call(lambda: client.set_parameters([Parameter("input_timeout", value=-1.0)])).results[0]
        assert not bad.successful and "input_timeout" in bad.reason
        bad = lst.call(lambda: client.set_parameters([Parameter("preset", value="no_such_preset")])).results[0]
        assert not bad.successful and "preset" in bad.reason and "no_such_preset" in bad.reason
        good = lst.call(lambda: client.set_parameters([Parameter("input_timeout", value=2.5)])).results[0]
        assert good.successful
        got = lst.call(lambda: client.get_parameters(["input_timeout", "preset"]))
        assert got.values[0].double_value == 2.5 and got.values[1].string_value == ""
        assert g.procs["plant_sim"].poll() is None                     # refusing did not end the node
    finally:
        codes = g.stop()
    assert codes["plant_sim"] == 0, g.stderr("plant_sim")


@pytest.mark.parametrize("node,values,name", [
    ("plant_sim", {"input_timeout": -1.0}, "input_timeout"),
    ("plant_sim", {"input_timeout": -1}, "input_timeout"),
    ("experiment_sequencer", {"experiment": "does_not_exist"}, "experiment"),
])
def test_bad_parameter_in_a_params_file_is_refused_naming_it(tmp_path, ros_domain, node, values, name):
    pfile = _params_file(tmp_path / "bad.yaml", node, **values)
    code, err = _run_refused([str(BIN / node), "--ros-args", "--params-file", str(pfile)], ros_domain)
    assert code != 0
    assert name in err and str(values[name]) in err, err
    assert "Traceback" not in err, err


@pytest.mark.slow
@pytest.mark.parametrize("text,says", [
    ("plant_sim:\n  ros__parameters:\n    input_timeout: [1.0\n",            # not YAML
     "not valid YAML at line 4, column 1: expected ',' or ']'"),
    ("plant_sim:\n  ros__parameters:\n    input_timeout: 1.0\n    input_timeout: 2.0\n",
     "not valid YAML at line 4, column 5: found duplicate key 'input_timeout' (first at line 3)"),
    ("- plant_sim\n", "top level must be a mapping of node names, got list"),
])
def test_a_params_file_that_is_not_valid_yaml_is_refused_in_one_line_naming_file_and_line(tmp_path, ros_domain, text,
                                                                                          says):
    pfile = tmp_path / "plant.yaml"
    pfile.write_text(text)
    code, err = _run_refused([str(BIN / "plant_sim"), "--ros-args", "--params-file", str(pfile)], ros_domain)
    assert code == 2 and "Traceback" not in err, err
    assert err == f"error: plant_sim (params file {pfile}): {err.split('): ', 1)[1]}" and says in err, err
    assert err.count("\n") == 1, err                                  # one line


@pytest.mark.slow
def test_ros_arguments_rcl_refuses_are_one_error_line_and_exit_2(tmp_path, ros_domain):
    """What YAML accepts but ROS does not (a value outside ``ros__parameters``, a list of mixed
    types, a ``-p`` value that is not YAML): rcl's reason with the file's line, no traceback."""
    pfile = tmp_path / "plant.yaml"
    pfile.write_text("plant_sim:\n  input_timeout: 1.0\n")
    code, err = _run_refused([str(BIN / "plant_sim"), "--ros-args", "--params-file", str(pfile)], ros_domain)
    assert code == 2 and "Traceback" not in err, err
    assert (f"error: plant_sim: Couldn't parse params file: '--params-file {pfile}'. Error: Cannot have a value "
            "before ros__parameters at line 2\n") in err and "/project/" not in err
    code, err = _run_refused([str(BIN / "plant_sim"), "--ros-args", "-p", "input_timeout:=[1.0"], ros_domain)
    assert code == 2 and "Traceback" not in err, err
    assert "error: plant_sim: Couldn't parse parameter override rule: '-p input_timeout:=[1.0'" in err


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["--processes", "one process"])
def test_a_graph_that_times_out_says_what_did_not_finish_in_one_line(tmp_path, ros_domain, mode):
    """``nanostage graph --timeout`` shorter than the nodes' start-up: exit 124, one line naming
    what did not finish, no traceback from a node stopped in the middle of its imports."""
    args = [str(BIN / "nanostage"), "graph", "fi_p2p_5um", "--out", str(tmp_path), "--timeout", "0.5",
            "--domain-id", str(ros_domain)] + ([mode] if mode == "--processes" else [])
    run = subprocess.run(args, capture_output=True, text=True, timeout=RUN_TIMEOUT)
    assert run.returncode == 124 and "Traceback" not in run.stderr, run.stderr
    lines = run.stderr.splitlines()
    if mode == "--processes":
        assert lines[0].startswith("run timed out after 0.5 s (--timeout): the experiment did not finish; ")
        assert lines[0].endswith("; every node is stopped"), lines
        if "still starting: " in lines[0]:                       # (they are, 0.5 s after they were started)
            assert set(lines[0].split("still starting: ")[1].split("; ")[0].split(", ")) <= set(NODE_NAMES)
    else:
        assert lines[0] == "run timed out after 0.5 s (--timeout): 0 of 3 trials done; every node is stopped"
    # what a run leaves is handled as before: here nothing was recorded, and it says so
    assert lines[1:] == [f"no recording: the run ended before the recorder heard /experiment/config "
                         f"({tmp_path / 'run.mcap'})"], lines


# =========================================================================== 6. start-up: compiled kernels
_WARM_UP_CHECK = r"""
import json, sys
import numpy as np
import numba
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from experiment_runner.ros.nodes import NODES
from msg_defs import convert
from stage_sim.config import PRESET_DIR, load_preset
import importlib

def loaded():
    '''Every compiled kernel of the project loaded in this process, with its argument types.'''
    found = {}
    for name, mod in list(sys.modules.items()):
        if name.split(".")[0] in ("stage_sim", "stage_control", "experiment_runner"):
            for attr, obj in vars(mod).items():
                if isinstance(obj, numba.core.dispatcher.Dispatcher):
                    found[f"{obj.py_func.__module__}.{attr}"] = {str(s) for s in obj.signatures}
    return found

classes = {n.name: getattr(importlib.import_module(n.module), n.cls) for n in NODES}
for cls in classes.values():
    cls.warm_up()
warm = loaded()
ctx = Context()
rclpy.init(context=ctx)
for preset in sorted(p.stem for p in PRESET_DIR.glob("*.yaml")):
    rate = load_preset(preset).controller.rate
    traj = convert.trajectory_to_msg(None, np.zeros(4), np.zeros(4), trial=0, case="warm", start=0, rate=rate)
    dt_ns = int(round(1e9 / rate))
    for name in ("plant_sim", "servo_controller", "dither_generator", "sai_manager"):
        node = classes[name](context=ctx, parameter_overrides=[Parameter("preset", value=preset)])
        node._trajectory(traj)                        # a trial, and its first samples
        for k in range(2):
            for need in node.lock.needed:
                value = (0.0, 0.0) if need == "dither" else 0.0
                if name == "plant_sim":
                    node._input(k * dt_ns, need, value)
                else:
                    node._put(k * dt_ns, need, value)
        assert (node.k if name == "plant_sim" else node.last_k) >= 1, (preset, name)
        node.destroy_node()
rclpy.shutdown(context=ctx)
new = {k: sorted(v - warm.get(k, set())) for k, v in loaded().items() if v - warm.get(k, set())}
print(json.dumps(new))
"""


@pytest.mark.slow
def test_a_node_that_warmed_up_loads_no_kernel_in_a_trial_of_any_preset(tmp_path, ros_domain):
    """What each node steps per sample is loaded by its ``warm_up`` (from one preset's models),
    before it joins a run: trials of every shipped preset, run through the nodes' own
    code, load or compile no further kernel and no further argument types. Run in a fresh
    interpreter: what this one has loaded already would hide a kernel that ``warm_up`` misses."""
    run = subprocess.run([sys.executable, "-c", _WARM_UP_CHECK], env=domain_env(ros_domain), capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.splitlines()[-1]) == {}, run.stdout


def _kernel_cache_without(tmp_path: Path, *kernels: str) -> Path:
    """A copy of the compiled-kernel cache without the files of ``kernels`` (glob patterns of
    ``<module>.<function>-*``), to be used as ``NUMBA_CACHE_DIR``: these are compiled again."""
    import numba
    if not numba.config.CACHE_DIR:
        pytest.skip("the compiled kernels are cached beside the sources (read-only install): not copied")
    cache = tmp_path / "kernels"
    shutil.copytree(numba.config.CACHE_DIR, cache)
    for kernel in kernels:
        for f in cache.rglob(kernel):
            f.unlink()
    return cache


@pytest.mark.slow
def test_a_node_stopped_while_it_compiles_its_kernels_ends_at_once_as_still_starting(tmp_path, ros_domain, listener):
    """SIGTERM while the plant compiles its step (before it spins): it ends by the signal, as a node
    still importing does (``launch.STARTING``: ``nanostage graph`` says "still starting"), with
    its ROS node torn down, no traceback, and without waiting out ``EXIT_GRACE_S``."""
    cache = _kernel_cache_without(tmp_path, "plant.plant_step-*")
    lst = listener(ros_domain, defer_trajectory=True)
    err_path = tmp_path / "plant_sim.stderr"
    with open(err_path, "w") as err:
        proc = subprocess.Popen([str(BIN / "plant_sim")], stdout=subprocess.DEVNULL, stderr=err,
                                env=dict(domain_env(ros_domain), NUMBA_CACHE_DIR=str(cache)))
    try:
        deadline = time.monotonic() + RUN_TIMEOUT     # the node is made (in the graph): it compiles now
        while "plant_sim" not in lst.node.get_node_names() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert proc.poll() is None, err_path.read_text()
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = err_path.read_text()
    assert code == -signal.SIGTERM, err
    assert "Traceback" not in err and "did not finish" not in err, err
    assert not list(cache.rglob("plant.plant_step-*")), "the plant was stopped after it had compiled its step"


@pytest.mark.slow
def test_a_graph_whose_nodes_compile_their_kernels_first_runs(tmp_path, monkeypatch, ros_domain):
    """The compiled-kernel cache without the plant's and the servo's step functions (as a fresh
    clone, or any change to compiled code, leaves it: the first run compiles them). Each node
    compiles its kernels before it joins the run, never inside the lockstep: the run is the
    batch engine's, with a ``sample_timeout`` of 2 s, less than compiling the plant's step takes.
    (Compiled at the plant's first sample, the plant sent nothing for seconds, not even its
    waiting sample again, and the sequencer aborted: "no measured sample after sample 0 within
    5.0 s (node: plant_sim)"; the plant was stopped before it saved its kernel, so the next
    runs did the same.)"""
    import yaml
    from experiment_runner.core.experiment import EXPERIMENT_DIR
    cache = _kernel_cache_without(tmp_path, "plant.plant_step-*", "servo.servo_step-*")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(cache))
    doc = yaml.safe_load((EXPERIMENT_DIR / "fi_p2p_5um.yaml").read_text())
    doc.update(name="cold_kernels", trials=1)
    exp_file = tmp_path / "cold_kernels.yaml"
    exp_file.write_text(yaml.safe_dump(doc))
    with ros_environment(ros_domain):
        code = run_processes(str(exp_file), tmp_path / "run", timeout=RUN_TIMEOUT, domain_id=ros_domain,
                             params={"experiment_sequencer": {"sample_timeout": 2.0}})
    assert code == 0
    assert list(cache.rglob("plant.plant_step-*.nbi")) and list(cache.rglob("servo.servo_step-*.nbi"))  # compiled
    rec = read_recording(tmp_path / "run")
    _, trials, res = _batch("fi_p2p_5um")
    assert rec.trials()[0].complete and np.array_equal(rec.y, res.y[0])


@pytest.mark.slow
def test_a_node_that_is_there_but_has_not_joined_when_the_start_times_out_is_named_still_starting(tmp_path, ros_domain,
                                                                                                    listener,
                                                                                                    node_graph):
    """The sequencer's start-up abort tells a node that is not in the graph ("missing") from one
    that is but has not joined the run yet ("still starting": e.g. still compiling its kernels).
    Here only the sequencer runs, and a node named plant_sim that never subscribes to
    /experiment/trajectory."""
    lst = listener(ros_domain, defer_trajectory=True)
    stand_in = Node("plant_sim", context=lst.ctx)
    g = node_graph("fi_p2p_5um", ros_domain, nodes=("experiment_sequencer",),
                   params={"experiment_sequencer": {"start_timeout": 5.0}})
    try:
        code = g.wait(timeout=RUN_TIMEOUT)
    finally:
        codes = g.stop()
        stand_in.destroy_node()
    assert code == 1 and all(c != "hung" for c in codes.values()), codes
    assert ("run aborted (trial None): only 0 of 5 nodes after 5.0 s; missing: servo_controller, dither_generator, "
            "sai_manager, recorder; still starting: plant_sim (node: plant_sim, servo_controller, dither_generator, "
            "sai_manager, recorder)") in g.stderr("experiment_sequencer"), g.stderr("experiment_sequencer")
