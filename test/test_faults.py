"""Faults in the node graph, and the safety limits in the loop.

Each graph test runs the graph as separate processes (:class:`experiment_runner.ros.launch.NodeProcesses`,
the ``node_graph`` fixture of ``conftest.py``) on a ROS domain leased to it and injects one fault mid-trial: a node killed (SIGKILL), stopped
(SIGSTOP), restarted; messages on a topic dropped, delayed or made NaN (the test-only
``fault.*`` parameters of :class:`msg_defs.node_io.StageNode`); a reference outside the
travel; the table leaving its travel. What is checked is what a user sees: the processes'
exit codes (every one ends: none is "hung"), the ``/experiment/events`` heard live, and
the recording read back. Experiments are cut to one or two trials and the timeouts to
about a second; no timing is asserted.
"""
from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import GRAPH_TIMEOUT as RUN_TIMEOUT
from conftest import ros_environment

from experiment_runner.apps.graph import EXIT_ABORTED, run_graph
from experiment_runner.core import outputs
from experiment_runner.core.experiment import EXPERIMENT_DIR, experiment_preset, load_experiment, run_batch
from experiment_runner.core.recording import read_recording, write_run
from experiment_runner.ros.nodes import nodes_for
from stage_control.servo import build_servo, check_reference
from stage_sim.config import load_preset, with_overrides

def _nodes(experiment: str) -> tuple[str, ...]:
    """The nodes a run of ``experiment`` needs (the table of nodes: no dither generator without
    dither, no SAI manager without one)."""
    return nodes_for(experiment_preset(load_experiment(experiment)))


FI_NODES = _nodes("fi_p2p_5um")
VAN_NODES = _nodes("van_asym_hc")
SAI_NODES = _nodes("sai_p2p_5um")

FAST = {"plant_sim": {"input_timeout": 3.0},               # the watchdog
        "experiment_sequencer": {"sample_timeout": 6.0, "wait_for_nodes": 4,   # 3 nodes + the Listener
                                 "start_delay": 0.3}}
"""Short timeouts (the plant's watchdog fires before the sequencer's own), long enough for a
loaded 2-core machine."""
DT_NS = 100_000                       # control period of the FI stage (10 kHz) [ns]


MID_TRIAL = 0.3
"""Dwell [s] of a trial that a test acts on mid-way (about 3,500 samples): long enough that the
trial is still running when the listener has heard the servo's first 200 commands, however
fast the graph loop is (several kHz with one process per node)."""


def _experiment(tmp_path: Path, trials: int = 1, dwell: float = 0.03, base: str = "fi_p2p_5um", **doc) -> Path:
    """Experiment ``base`` with ``trials`` trials, starting at 0, ``dwell`` [s] (fi_p2p_5um,
    0.03: 527 samples a trial), changed by ``doc``."""
    base = yaml.safe_load((EXPERIMENT_DIR / f"{base}.yaml").read_text())
    base.pop("starts", None)
    base["profile"]["dwell"] = dwell
    base.update(name="faults", trials=trials, **doc)
    path = tmp_path / "faults.yaml"
    path.write_text(yaml.safe_dump(base))
    return path


def _params(*extra: dict) -> dict:
    out = {n: dict(v) for n, v in FAST.items()}
    for e in extra:
        for node, vals in e.items():
            out.setdefault(node, {}).update(vals)
    return out


class Run:
    """One graph run with a live listener; ``finish()`` waits for the sequencer, stops the rest."""

    def __init__(self, tmp_path: Path, graph, listener):
        self.tmp, self.graph, self.listener = tmp_path, graph, listener
        self.seq = self.graph.procs["experiment_sequencer"]
        self.listener.join_when_matched(event_publishers=len(graph.procs))

    def events(self, kind: str) -> list[dict]:
        return [e for e in self.listener.events if e["event"] == kind]

    def wait_commands(self, n: int = 200):
        """Into the first trial: it started and the servo has sent ``n`` commands."""
        ok = self.listener.wait_for(lambda ev: any(e["event"] == "trial_start" for e in ev)
                                    and self.listener.commands >= n, RUN_TIMEOUT,
                                    alive=lambda: self.seq.poll() is None)
        assert ok, f"no trial_start and {n} commands ({self.listener.commands} heard)"

    def finish(self, timeout: float = 30.0):
        """Sequencer's exit code (None if it did not end), every node's exit code."""
        code = self.graph.wait(timeout=timeout)
        self.listener.wait_for(lambda ev: any(e["event"] == "run_end" for e in ev), 15.0)   # returns when heard; a loaded machine may be slow
        codes = self.graph.stop()
        assert all(c != "hung" for c in codes.values()), codes      # nothing hangs
        return code, codes

    def recording(self, name: str = "run"):
        return read_recording(self.tmp / name)


@pytest.fixture
def make_run(ros_domain, listener, node_graph):
    """``make_run(tmp_path, exp, params, nodes=FI_NODES)``: a :class:`Run` on the test's domain (its
    nodes stopped and its listener closed after the test by the fixtures)."""
    def make(tmp_path: Path, exp: Path, params: dict, nodes=FI_NODES) -> Run:
        lst = listener(ros_domain, defer_trajectory=True)
        return Run(tmp_path, node_graph(exp, ros_domain, nodes=nodes, params=params), lst)
    return make


def _batch_y(exp: Path) -> np.ndarray:
    _, res = run_batch(load_experiment(exp))
    return res.y


def _sample(rec, event) -> int:
    """Sample index (in trial 0) of an event's stamp."""
    return (event["stamp_ns"] - rec.trials()[0].start_ns) // DT_NS


def _one_abort(run: Run, node: str) -> dict:
    aborts = run.events("abort")
    assert len(aborts) == 1, run.listener.events
    assert node in aborts[0]["responsible"] and node in aborts[0]["reason"], aborts[0]
    return aborts[0]


def _recorded_abort(rec, node: str, trial=0) -> None:
    """The recording holds the abort naming ``node``, the trial is not complete, run_end last."""
    aborts = [e for e in rec.events if e["event"] == "abort"]
    assert len(aborts) == 1 and node in aborts[0]["reason"] and aborts[0]["trial"] == trial, rec.events
    kinds = [e["event"] for e in rec.events]
    # run_end last, or after it only late `fault` notes: a node resumed (SIGCONT) after the run
    # ended whose watchdog fires before it hears the abort, the recorder's count of lost samples
    assert "run_end" in kinds and all(k == "fault" for k in kinds[kinds.index("run_end") + 1:]), rec.events
    assert not rec.trials()[trial].complete and rec.results == []


# =========================================================================== killed nodes
# (a killed servo and a killed recorder: test_graph.py)
@pytest.mark.ros
@pytest.mark.parametrize("node", ["plant_sim", "experiment_sequencer"])
def test_a_killed_node_ends_the_run_with_the_trial_aborted_naming_it(tmp_path, make_run, node):
    exp = _experiment(tmp_path, dwell=MID_TRIAL)
    run = make_run(tmp_path, exp, _params())
    run.wait_commands()
    assert run.graph.kill(node) == -signal.SIGKILL
    code, codes = run.finish()
    rec = run.recording()
    assert rec.salvaged is None                # the recorder closed the file cleanly
    if node == "experiment_sequencer":
        assert code == -signal.SIGKILL
        _recorded_abort(rec, "experiment_sequencer")               # written by the recorder
        assert rec.events[-2]["node"] == "recorder"
    else:
        assert code == EXIT_ABORTED
        assert _one_abort(run, node)["trial"] == 0
        _recorded_abort(rec, node)
    y = _batch_y(exp)[0]
    tr = rec.trials()[0]
    assert 0 < tr.stop - tr.start <= len(y)    # (with the sequencer gone the loop may finish)
    assert node == "experiment_sequencer" or tr.stop - tr.start < len(y)    # cut mid-trial
    assert np.array_equal(rec.y[tr.slice], y[:tr.stop - tr.start])         # what was recorded is right


@pytest.mark.parametrize("base, node, nodes", [("van_asym_hc", "dither_generator", VAN_NODES),
                                                ("sai_p2p_5um", "sai_manager", SAI_NODES)])
@pytest.mark.ros
def test_a_killed_dither_generator_or_sai_manager_trips_the_watchdog_naming_it(tmp_path, make_run, base, node,
                                                                               nodes):
    """The plant waits for their per-sample inputs: the watchdog names the silent node (and the
    servo too where it waits for the SAI manager's correction)."""
    exp = _experiment(tmp_path, base=base, dwell=MID_TRIAL)
    run = make_run(tmp_path, exp, _params({"experiment_sequencer": {"wait_for_nodes": len(nodes)}}), nodes=nodes)
    run.wait_commands()
    assert run.graph.kill(node) == -signal.SIGKILL
    code, codes = run.finish()
    assert code == EXIT_ABORTED and codes[node] == -signal.SIGKILL
    fault = run.events("fault")[0]
    assert fault["node"] == "plant_sim" and fault["cause"] == "watchdog" and node in fault["responsible"]
    _one_abort(run, node)
    rec = run.recording()
    assert rec.salvaged is None
    _recorded_abort(rec, node)
    y = _batch_y(exp)[0]
    tr = rec.trials()[0]
    assert 0 < tr.stop - tr.start < len(y)                                  # cut mid-trial
    assert np.array_equal(rec.y[tr.slice], y[:tr.stop - tr.start])         # what was recorded is right


@pytest.mark.ros
def test_a_stopped_servo_trips_the_watchdog_and_its_late_commands_are_not_applied(tmp_path, make_run):
    exp = _experiment(tmp_path, dwell=MID_TRIAL)
    run = make_run(tmp_path, exp, _params())
    run.wait_commands()
    run.graph.pause("servo_controller")                            # SIGSTOP: hangs, sockets open
    assert run.listener.wait_for(lambda ev: any(e["event"] == "abort" for e in ev), 30.0)
    run.graph.resume("servo_controller")                           # its pending answer goes out now
    time.sleep(1.0)
    code, codes = run.finish()
    assert code == EXIT_ABORTED and codes["servo_controller"] == 0    # it exits on SIGINT afterwards
    fault = run.events("fault")[0]
    assert fault["node"] == "plant_sim" and fault["cause"] == "watchdog"
    assert fault["responsible"] == ["servo_controller"] and "zero force" in fault["reason"]
    _one_abort(run, "servo_controller")
    rec = run.recording()
    _recorded_abort(rec, "servo_controller")
    # drive latched off: no sample after the one the watchdog stopped at was simulated
    k = _sample(rec, fault)
    assert rec.counts["/stage/measured"] == rec.counts["/stage/truth"] == k + 1 and len(rec) >= k


@pytest.mark.ros
def test_a_stopped_plant_is_named_by_the_sequencer(tmp_path, make_run):
    """Nothing comes from a SIGSTOPped plant: the sequencer's sample timeout aborts the trial."""
    exp = _experiment(tmp_path, dwell=MID_TRIAL)
    run = make_run(tmp_path, exp, _params())
    run.wait_commands()
    run.graph.pause("plant_sim")
    assert run.listener.wait_for(lambda ev: any(e["event"] == "abort" for e in ev), 30.0)
    code, codes = run.finish()                  # SIGCONT + SIGINT: it ends normally
    assert code == EXIT_ABORTED and codes["plant_sim"] == 0
    abort = _one_abort(run, "plant_sim")
    assert "no measured sample" in abort["reason"]
    rec = run.recording()
    _recorded_abort(rec, "plant_sim")
    tr = rec.trials()[0]
    assert np.array_equal(rec.y[tr.slice], _batch_y(exp)[0][:tr.stop - tr.start])


@pytest.mark.ros
def test_a_stopped_recorder_never_leaves_a_silently_incomplete_recording(tmp_path, make_run):
    """SIGSTOPped for 2 s the recorder falls behind (more than the topics' 0.1 s history, unless
    the machine is slow): the run goes on (the recorder is not in the loop); resumed, it takes
    what is still on its way. What it wrote is right, and a recording that misses anything
    says so: a ``recording_incomplete`` fault counting the gaps it saw, or trials it did not
    hear end (incomplete)."""
    exp = _experiment(tmp_path, trials=2, dwell=0.1)
    run = make_run(tmp_path, exp, _params())
    run.wait_commands()
    run.graph.pause("recorder")
    time.sleep(2.0)
    run.graph.resume("recorder")
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == 0 and codes["recorder"] == 0
    rec = run.recording()
    assert rec.salvaged is None
    y = np.concatenate([_batch_y(exp)[i] for i in range(2)])
    k = rec.stamp_ns // DT_NS          # sample index in the run (stage time starts at 0; a recorder
    # matched late by discovery may lack the first samples, so the first one recorded need not be 0)
    assert 0 < len(rec) and np.array_equal(rec.y, y[k])                  # what it has is right
    gaps = [e for e in rec.events if e.get("cause") == "recording_incomplete"]
    for topic, n in (gaps[0]["lost"].items() if gaps else ()):           # what it reports is real
        assert rec.counts[topic] <= len(y) - n and f"{n} sample(s) of {topic}" in gaps[0]["reason"]
    topics = ("/stage/reference", "/stage/command", "/stage/measured", "/stage/truth", "/clock")
    everything = all(rec.counts[t] == len(y) for t in topics)
    told = bool(gaps) or len(rec.trials()) < 2 or not all(t.complete for t in rec.trials())
    assert everything or told, rec.counts


# =========================================================================== restarts
@pytest.mark.ros
def test_a_plant_restarted_mid_trial_aborts_the_trial_naming_it(tmp_path, make_run):
    """The new plant gets the trial's trajectory (latched) and starts it again from sample 0:
    the sequencer sees the sample index go back and refuses the mixed trial."""
    exp = _experiment(tmp_path, dwell=MID_TRIAL)
    slow = {"plant_sim": {"input_timeout": 60.0}, "experiment_sequencer": {"sample_timeout": 60.0}}
    run = make_run(tmp_path, exp, _params(slow))
    run.wait_commands()
    run.graph.restart("plant_sim")
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == EXIT_ABORTED
    reason = _one_abort(run, "plant_sim")["reason"]
    assert "restarted" in reason
    rec = run.recording()
    _recorded_abort(rec, "plant_sim")
    tr = rec.trials()[0]                    # the recorder kept each sample once: the first plant's
    assert np.array_equal(rec.y[tr.slice], _batch_y(exp)[0][:tr.stop - tr.start])


@pytest.mark.ros
def test_a_servo_restarted_mid_trial_aborts_the_trial_naming_it(tmp_path, make_run):
    """The new servo gets the trial's trajectory (latched) and the plant's repeated sample k > 0:
    it refuses to start from rest in mid-motion."""
    exp = _experiment(tmp_path, dwell=MID_TRIAL)
    slow = {"plant_sim": {"input_timeout": 60.0}, "experiment_sequencer": {"sample_timeout": 60.0}}
    run = make_run(tmp_path, exp, _params(slow))                    # no watchdog: the restart is seen
    run.wait_commands()
    run.graph.restart("servo_controller")
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == EXIT_ABORTED
    reason = _one_abort(run, "servo_controller")["reason"]         # the new servo's fault, passed on
    assert reason.startswith("joined_mid_trial: ") and "restarted" in reason
    rec = run.recording()
    _recorded_abort(rec, "servo_controller")
    tr = rec.trials()[0]                    # each sample once, the batch engine's, up to the restart
    assert np.array_equal(rec.y[tr.slice], _batch_y(exp)[0][:tr.stop - tr.start])


@pytest.mark.ros
def test_a_rerun_in_the_same_out_dir_starts_clean(tmp_path, ros_domain):
    """A previous run's recording is not read as the next one's, even if the next records nothing."""
    out = outputs.prepare_folder(tmp_path / "out")
    old_exp = load_experiment(_experiment(tmp_path, trials=2))
    _, res = run_batch(old_exp)
    bag = write_run(tmp_path / "old", res, experiment_preset(old_exp))    # "the last run"
    outputs.move_into(bag, out / "run.mcap")                              # as run_graph leaves it
    outputs.move_into(bag.parent / "metadata.yaml", out / "metadata.yaml")
    outputs.prepare_folder(out / "run_2")                                 # + a restarted recorder's part
    assert sorted(p.name for p in out.iterdir()) == [outputs.MANIFEST, "metadata.yaml", "run.mcap", "run_2"]
    never = {"experiment_sequencer": {"wait_for_nodes": 99, "start_timeout": 2.0}}  # aborts before it starts
    with ros_environment(ros_domain):
        code = run_graph(str(_experiment(tmp_path)), out, processes=True, domain_id=ros_domain,
                         timeout=RUN_TIMEOUT, params=never)
    assert code == EXIT_ABORTED
    assert sorted(p.name for p in out.iterdir()) == [outputs.MANIFEST]  # nothing of the last run is left


# =========================================================================== messages
@pytest.mark.ros
def test_dropped_and_delayed_messages_are_recovered_and_change_nothing(tmp_path, make_run):
    """A lost lockstep message is sent again (the plant repeats its sample after 0.25 s, the
    servo its answer); a late one is waited for: the run is the batch engine's, bit for bit.
    Here 3 commands in a row are dropped and 20 measurements come 50 ms late."""
    exp = _experiment(tmp_path)
    faults = {"servo_controller": {"fault.topic": "/stage/command", "fault.mode": "drop", "fault.after": 300,
                                   "fault.count": 3},
              "plant_sim": {"fault.topic": "/stage/measured", "fault.mode": "delay", "fault.after": 100,
                            "fault.count": 20, "fault.delay_ms": 50.0}}
    run = make_run(tmp_path, exp, _params(faults))
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == 0 and not run.events("fault") and not run.events("abort")
    for node in faults:                                                   # the faults were on
        assert "TEST FAULT INJECTION" in (tmp_path / f"{node}.stderr").read_text()
    rec = run.recording()
    assert rec.trials()[0].complete and len(rec.results) == 1
    assert np.array_equal(rec.y, _batch_y(exp)[0]) and len(np.unique(rec.stamp_ns)) == len(rec)


@pytest.mark.parametrize("base, node, topic, nodes", [
    ("fi_p2p_5um", "plant_sim", "/stage/measured", FI_NODES),
    ("van_asym_hc", "dither_generator", "/stage/dither", VAN_NODES),
    ("sai_p2p_5um", "sai_manager", "/sai/command", SAI_NODES)])
@pytest.mark.ros
def test_dropped_lockstep_messages_of_every_node_are_recovered(tmp_path, make_run, base, node, topic, nodes):
    """3 messages in a row lost on each lockstep topic: the plant sends its sample again, the
    node answers again; the run is the batch engine's, bit for bit."""
    exp = _experiment(tmp_path, base=base, dwell=0.05)
    faults = {node: {"fault.topic": topic, "fault.mode": "drop", "fault.after": 200, "fault.count": 3},
              "experiment_sequencer": {"wait_for_nodes": len(nodes)}}
    run = make_run(tmp_path, exp, _params(faults), nodes=nodes)
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == 0 and not run.events("fault") and not run.events("abort")
    assert "TEST FAULT INJECTION" in (tmp_path / f"{node}.stderr").read_text()
    rec = run.recording()
    assert rec.trials()[0].complete and len(rec.results) == 1
    assert np.array_equal(rec.y, _batch_y(exp)[0]) and len(np.unique(rec.stamp_ns)) == len(rec)


@pytest.mark.parametrize("node, topic", [("servo_controller", "/stage/reference"), ("plant_sim", "/stage/truth"),
                                         ("plant_sim", "/clock")])
@pytest.mark.ros
def test_lost_messages_outside_the_lockstep_are_recorded_as_lost(tmp_path, make_run, node, topic):
    """Messages no node waits for (the reference record, the truth, the clock) are lost for
    good: the loop runs on bit for bit. Without its reference record the trial's metrics
    cannot be computed: the sequencer aborts it naming the servo and the lost samples; a lost
    contract sample is left out of the reading of the recording with a warning naming the
    topic, the rest is intact."""
    exp = _experiment(tmp_path)
    faults = {node: {"fault.topic": topic, "fault.mode": "drop", "fault.after": 100, "fault.count": 5}}
    run = make_run(tmp_path, exp, _params(faults))
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    aborts = run.events("abort")
    if topic == "/stage/reference":
        assert code == EXIT_ABORTED and len(aborts) == 1
        assert "servo_controller" in aborts[0]["reason"] and "5 reference sample(s)" in aborts[0]["reason"]
    else:
        assert code == 0 and not run.events("fault") and not aborts
    assert "TEST FAULT INJECTION" in (tmp_path / f"{node}.stderr").read_text()
    rec = run.recording()
    y = _batch_y(exp)[0]
    k = (rec.stamp_ns - rec.stamp_ns[0]) // DT_NS                          # sample index of each row
    assert np.array_equal(rec.y, y[k])
    if topic == "/stage/reference":
        assert len(rec) == len(y) - 5
        assert any(w.startswith("/stage/reference: no message at 5 control sample(s)") and "dropped" in w
                   for w in rec.warnings)
    else:
        assert len(rec) == len(y) and not rec.warnings
    # the recorder says what never reached it
    (gap,) = [e for e in rec.events if e.get("cause") == "recording_incomplete"]
    assert gap["lost"] == {topic: 5} and f"5 sample(s) of {topic}" in gap["reason"]


@pytest.mark.ros
def test_a_nan_command_stops_the_run_naming_the_servo(tmp_path, make_run):
    node, topic, catcher, sender = "servo_controller", "/stage/command", "plant_sim", "servo_controller"
    exp = _experiment(tmp_path)
    nan = {node: {"fault.topic": topic, "fault.mode": "nan", "fault.after": 400, "fault.count": 1}}
    run = make_run(tmp_path, exp, _params(nan))
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == EXIT_ABORTED
    faults = run.events("fault")
    assert faults[0]["node"] == catcher and faults[0]["cause"] == "non_finite_input"
    assert faults[0]["responsible"] == [sender] and "nan" in faults[0]["reason"]
    _one_abort(run, sender)
    rec = run.recording()
    _recorded_abort(rec, sender)
    k = _sample(rec, faults[0])
    assert 390 <= k <= 400
    bad = rec.u if topic == "/stage/command" else rec.y
    assert np.isnan(bad[k]) and np.isfinite(bad[:k]).all()     # the recording shows what was sent
    assert np.isfinite(rec.truth.joint("table")).all()         # the plant never applied a NaN
    assert np.array_equal(rec.y[:k], _batch_y(exp)[0][:k])     # the samples before it stand


# =========================================================================== travel and divergence
@pytest.mark.ros
def test_the_table_leaving_its_travel_stops_the_run_and_keeps_the_recording(tmp_path, make_run):
    # the table overshoots the 5 um target by ~7 nm 0.06 s into the trial
    exp = _experiment(tmp_path, dwell=0.1, overrides={"stage.travel.max": 5.001e-6})
    run = make_run(tmp_path, exp, _params())
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == EXIT_ABORTED
    fault = run.events("fault")[0]
    assert fault["node"] == "plant_sim" and fault["cause"] == "out_of_travel"
    assert "travel" in fault["reason"] and "zero force" in fault["reason"]
    _one_abort(run, "plant_sim")
    rec = run.recording()
    _recorded_abort(rec, "plant_sim")
    assert rec.salvaged is None and 0 < len(rec) < len(_batch_y(_experiment(tmp_path, dwell=0.1))[0])


@pytest.mark.ros
def test_a_reference_outside_the_travel_is_refused_before_the_trial_moves(tmp_path, make_run):
    exp = _experiment(tmp_path, overrides={"stage.travel.max": 4.0e-6})    # the 5 um target is beyond it
    # the fault comes at the trial's first sample: give discovery time to match the servo's events
    # publisher with the listener too (the sequencer only waits for the listener's trajectory subscription)
    run = make_run(tmp_path, exp, _params({"experiment_sequencer": {"start_delay": 2.0}}))
    code, codes = run.finish(timeout=RUN_TIMEOUT)
    assert code == EXIT_ABORTED
    fault = run.events("fault")[0]
    assert fault["node"] == "servo_controller" and fault["cause"] == "reference_out_of_travel"
    assert fault["responsible"] == ["experiment_sequencer"] and "x_ref[" in fault["reason"]
    _one_abort(run, "experiment_sequencer")
    assert run.listener.commands == 0                          # no command was ever sent


# =========================================================================== limits (no graph)
def test_the_servo_never_commands_more_than_the_drive_peak_force():
    p = load_preset("fi_stage")
    peak = p.stage.drive.peak_force
    assert build_servo(p.controller, p.stage).limit == peak
    more = with_overrides(p, {"controller.pid.output_limit": 10 * peak})
    assert build_servo(more.controller, more.stage).limit == peak
    less = with_overrides(p, {"controller.pid.output_limit": peak / 2})
    assert build_servo(less.controller, less.stage).limit == peak / 2


def test_check_reference_names_the_first_sample_outside_the_travel():
    travel = load_preset("fi_stage").stage.travel
    assert check_reference([0.0, travel.max], travel) is None
    msg = check_reference([0.0, 0.0, travel.max + 1e-9, np.nan], travel)
    assert "x_ref[2]" in msg and "travel" in msg
    assert "x_ref[1]" in check_reference([0.0, np.nan], travel)


# =========================================================================== a controller node alone
@pytest.fixture
def servo_node(ros_domain):
    """A ``servo_controller`` in this process (own context, no graph), on the FI preset, with
    a 5 um point-to-point trial started; ``node.faults`` collects its fault events."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from experiment_runner.ros.servo_node import ServoNode
    from msg_defs import convert
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    node = ServoNode(context=ctx, parameter_overrides=[Parameter("preset", value="fi_stage")])
    node.faults = []
    node.fault_event = lambda cause, reason, responsible, **kw: node.faults.append((cause, reason, responsible))
    x = np.linspace(0.0, 5e-6, 50)
    node._trajectory(convert.trajectory_to_msg(None, x, np.zeros_like(x), trial=0))
    yield node
    node.destroy_node()
    rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_the_servo_names_the_plant_for_a_nan_measurement(servo_node):
    for k in range(3):
        servo_node._put(k * DT_NS, "measured", 0.0)
    assert servo_node.faults == [] and servo_node.last_k == 2
    servo_node._put(3 * DT_NS, "measured", float("nan"))
    (cause, reason, who), = servo_node.faults
    assert cause == "non_finite_input" and who == "plant_sim" and "sample 3" in reason
    servo_node._put(4 * DT_NS, "measured", 0.0)                   # stopped: nothing more computed
    assert servo_node.last_k == 2


@pytest.mark.ros
def test_the_servo_reports_its_own_state_diverging(servo_node):
    servo_node._put(0, "measured", 0.0)
    servo_node.state[1, 0] = np.inf                                # the integrator blows up
    servo_node._put(DT_NS, "measured", 0.0)
    (cause, reason, who), = servo_node.faults
    assert cause == "diverged" and who == "servo_controller" and "sample 1" in reason


@pytest.mark.ros
def test_a_servo_joining_a_trial_after_its_first_sample_refuses_it(servo_node):
    servo_node._put(7 * DT_NS, "measured", 1e-6)
    (cause, reason, who), = servo_node.faults
    assert cause == "joined_mid_trial" and who == "servo_controller" and "sample 7" in reason
    assert servo_node.last_k == -1                                 # nothing was computed


@pytest.mark.ros
def test_a_second_sequencer_on_the_domain_refuses_to_start(ros_domain):
    """Its latched trajectories would mix into the other run: the one that starts later aborts."""
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor

    from experiment_runner.ros.sequencer_node import SequencerNode
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        seqs = [SequencerNode(context=ctx, experiment="fi_p2p_5um") for _ in range(2)]
        ex = SingleThreadedExecutor(context=ctx)
        for s in seqs:
            ex.add_node(s)
        deadline = time.monotonic() + 20.0
        while not all(s.done for s in seqs) and time.monotonic() < deadline:
            ex.spin_once(timeout_sec=0.05)
        for s in seqs:
            assert s.done and s.aborted["node"] == "experiment_sequencer" and s.aborted["trial"] is None
            assert "another experiment_sequencer" in s.aborted["reason"]
        ex.shutdown()
        for s in seqs:
            s.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)


@pytest.mark.ros
def test_the_recorder_counts_samples_lost_before_it_heard_the_config(tmp_path, ros_domain):
    """On a loaded machine the run's config (transient_local, matched on its own) may reach the
    recorder after the first per-sample messages: a gap among those is still counted (the
    control period comes with the config) and reported as ``recording_incomplete``."""
    import rclpy
    from rclpy.context import Context
    from std_msgs.msg import String

    from experiment_runner.ros.recorder_node import RecorderNode
    from msg_defs import cdr
    ctx = Context()
    rclpy.init(context=ctx, domain_id=ros_domain)
    try:
        node = RecorderNode(out=str(tmp_path / "run"), context=ctx)
        truth = cdr.JointStateWriter()
        for k in [0, 1, 2, 6, 7]:                                   # samples 3, 4, 5 never came
            node._write_raw("/stage/truth", truth.pack(k * DT_NS, ("table",), (1e-9 * k,)), lambda d: d)
        node._config_in(String(data=yaml.safe_dump({"preset": load_preset("fi_stage").model_dump(mode="json")})))
        for k in [8, 10]:                                          # and sample 9, after the config
            node._write_raw("/stage/truth", truth.pack(k * DT_NS, ("table",), (1e-9 * k,)), lambda d: d)
        node.close()
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from experiment_runner.core.recording import bag_layout
    from msg_defs.convert import parse_event
    with open(bag_layout(tmp_path / "run")[1], "rb") as f:
        events = [parse_event(m.data) for *_, m in make_reader(f, decoder_factories=[DecoderFactory()])
                  .iter_decoded_messages(topics=["/experiment/events"])]
    (gap,) = [e for e in events if e.get("cause") == "recording_incomplete"]
    assert gap["lost"] == {"/stage/truth": 4} and "4 sample(s) of /stage/truth" in gap["reason"]
