"""Campaign trials on executors (in process, local processes, Dask), streamed and resumable.

A tiny campaign (Table 4.2's two cases at the 5 µm step, 6 trials, 50 ms dwell) must give
exactly the per-trial metrics of one in-memory batch run of all trials, whatever runs it.
"""
import json
import math
import os
import subprocess
import sys

import pytest

from experiment_runner.apps.campaigns import stream as stream_mod
from experiment_runner.apps.campaigns.runner import run_campaign
from experiment_runner.apps.campaigns.spec import Campaign, case_preset, conditions, load_campaign
from experiment_runner.apps.campaigns.stream import STREAM_NAME
from experiment_runner.apps.campaigns.trials import metric_record, simulate_trials
from experiment_runner.core import executor as executor_mod
from experiment_runner.core.executor import Executor, cgroup_cpu_limit, default_workers, make_executor
from stage_sim.config import ConfigError

STEP = 5e-6
TRIALS = 6


@pytest.fixture(scope="module")
def camp() -> Campaign:
    data = load_campaign("table_4_2").model_dump()
    data["test"]["steps"] = [STEP]
    data["test"]["dwell"] = 0.05
    data["trials"] = TRIALS
    data["calibration"] = None
    for k in ("values", "findings"):
        data["seed"][k] = [v for v in data["seed"][k] if v.get("step") == STEP]
    return Campaign.model_validate(data)


@pytest.fixture(scope="module")
def reference_metrics(camp) -> dict:
    """Per-trial metrics of one batch run of all trials of each case (no chunks, no stream)."""
    (cond,) = conditions(camp)
    out = {}
    for case in camp.cases:
        preset = case_preset(camp, case, None, cond)
        ref, trials, res = simulate_trials(camp, case, cond, preset, range(TRIALS))
        mets = [metric_record(tr, res, j, preset.controller.rate) for j, tr in enumerate(trials)]
        out[case.name] = (_canon(mets), [float(t.x_ref[0] - ref.x[0]) for t in trials])
    return out


def _canon(mets) -> str:
    """Exact, NaN-safe comparison form of a metrics list."""
    return json.dumps(mets, sort_keys=True)


def _run(camp, out, **kw):
    return run_campaign(camp, out, calibrate=False, plots=False, mcap=False, report=False, progress=False, **kw)


def _check_same(cr, reference_metrics, camp):
    (cond,) = conditions(camp)
    for case in camp.cases:
        rr = cr.runs[(case.name, cond.key)]
        assert _canon(rr.metrics) == reference_metrics[case.name][0], case.name
        assert rr.x0 == reference_metrics[case.name][1], case.name
        assert rr.metrics[rr.rep]["trial"] == rr.rep
        assert rr.trace.settling_time == rr.metrics[rr.rep]["settling_time_s"]


@pytest.mark.slow
def test_in_process_matches_one_batch_and_streams_every_trial(camp, reference_metrics, tmp_path):
    cr = _run(camp, tmp_path, workers=1)
    _check_same(cr, reference_metrics, camp)
    lines = (tmp_path / STREAM_NAME).read_text().splitlines()
    head = json.loads(lines[0])
    assert head["format"] == "nanostage-trials" and head["campaign"] == camp.name
    recs = [json.loads(x) for x in lines[1:]]
    assert sorted((r["case"], r["trial"]) for r in recs) == sorted(
        (c.name, i) for c in camp.cases for i in range(TRIALS))
    x0 = {(r["case"], r["trial"]): r["x0_m"] for r in recs}
    (cond,) = conditions(camp)
    for case in camp.cases:
        assert cr.runs[(case.name, cond.key)].x0 == [x0[(case.name, i)] for i in range(TRIALS)]


@pytest.mark.slow
def test_local_process_pool_gives_identical_metrics(camp, reference_metrics, tmp_path):
    _check_same(_run(camp, tmp_path, workers=2), reference_metrics, camp)


@pytest.mark.dask
def test_dask_local_cluster_gives_identical_metrics(camp, reference_metrics, tmp_path, dask_cluster):
    _check_same(_run(camp, tmp_path, cluster=dask_cluster.scheduler_address), reference_metrics, camp)


@pytest.mark.slow
def test_resume_runs_only_the_missing_trials(camp, reference_metrics, tmp_path, monkeypatch):
    _run(camp, tmp_path)
    path = tmp_path / STREAM_NAME
    lines = path.read_text().splitlines(keepends=True)
    kept = lines[:6]                                      # header + 5 trials
    cut = lines[6][: len(lines[6]) // 2]                  # interrupted in the middle of a line
    path.write_text("".join(kept) + cut)
    done = {(r["case"], r["trial"]) for r in map(json.loads, kept[1:])}

    ran = []
    task = stream_mod.chunk_task

    def spy(camp_json, case_name, cond_key, preset_json, correction, indices, code):
        ran.extend((case_name, i) for i in indices)
        return task(camp_json, case_name, cond_key, preset_json, correction, indices, code)

    monkeypatch.setattr(stream_mod, "chunk_task", spy)
    cr = _run(camp, tmp_path)
    _check_same(cr, reference_metrics, camp)
    assert sorted(ran) == sorted({(c.name, i) for c in camp.cases for i in range(TRIALS)} - done)
    recs = [json.loads(x) for x in path.read_text().splitlines()[1:]]
    assert len(recs) == len(camp.cases) * TRIALS           # no duplicate, no partial line


@pytest.mark.slow
def test_stream_of_other_settings_is_refused(camp, tmp_path):
    _run(camp, tmp_path)
    other = Campaign.model_validate({**camp.model_dump(), "trials": TRIALS - 1})
    with pytest.raises(ConfigError, match=r"trials\.jsonl: cannot resume.*other settings.*--restart"):
        _run(other, tmp_path)
    cr = _run(other, tmp_path, resume=False)               # --restart: starts anew
    assert all(len(rr.metrics) == TRIALS - 1 for rr in cr.runs.values())
    (tmp_path / STREAM_NAME).write_text('{"format": "nanostage-trials", "version": 1, "campaign": "x", '
                                        '"key": "k", "code": "c"}\n')
    with pytest.raises(ConfigError, match="campaign 'x'"):
        _run(other, tmp_path)
    (tmp_path / STREAM_NAME).write_text("trial,metric\n")
    with pytest.raises(ConfigError, match="not a nanostage trial stream"):
        _run(other, tmp_path)


def test_worker_with_other_model_code_refuses_to_run(camp):
    (cond,) = conditions(camp)
    case = camp.cases[0]
    args = (camp.model_dump_json(), case.name, cond.key, case_preset(camp, case, None, cond).model_dump_json(),
            None, [0])
    assert stream_mod.chunk_task(*args, stream_mod.code_fingerprint())[0]["trial"] == 0
    with pytest.raises(RuntimeError, match="runs other model code"):
        stream_mod.chunk_task(*args, "0123456789abcdef")


@pytest.mark.dask
def test_executor_map_results_and_errors(dask_cluster):
    tasks = [(("t", i), (float(i),)) for i in range(5)]
    for ex in (make_executor(1), make_executor(2), make_executor(cluster=dask_cluster.scheduler_address)):
        with ex:
            got = dict(ex.map(math.sqrt, tasks, window=2))
            assert got == {("t", i): math.sqrt(i) for i in range(5)}, ex
            with pytest.raises(ValueError, match="math domain error") as err:
                list(ex.map(math.sqrt, [("ok", (1.0,)), ("bad", (-1.0,))]))
            assert "in task 'bad'" in "".join(getattr(err.value, "__notes__", [])), ex
    with pytest.raises(ConfigError, match="--workers: must be >= 1"):
        make_executor(0)


# --------------------------------------------------------------------------- every core by default
def test_cgroup_cpu_quota_is_read_along_the_process_cgroup(tmp_path):
    root, me = tmp_path / "cg", tmp_path / "self"
    (root / "job" / "step").mkdir(parents=True)
    (root / "cpu.max").write_text("max 100000\n")                      # v2, no quota at the top
    (root / "job" / "cpu.max").write_text("300000 100000\n")           # 3 CPUs for the job
    (root / "job" / "step" / "cpu.max").write_text("max 100000\n")
    me.write_text("0::/job/step\n")
    assert cgroup_cpu_limit(str(root), str(me)) == 3.0
    (root / "job" / "step" / "cpu.max").write_text("150000 100000\n")
    assert cgroup_cpu_limit(str(root), str(me)) == 1.5
    v1 = tmp_path / "v1"                                                # v1: cpu,cpuacct controller
    (v1 / "cpu,cpuacct" / "docker" / "c1").mkdir(parents=True)
    (v1 / "cpu,cpuacct" / "docker" / "c1" / "cpu.cfs_quota_us").write_text("200000\n")
    (v1 / "cpu,cpuacct" / "docker" / "c1" / "cpu.cfs_period_us").write_text("100000\n")
    me.write_text("4:memory:/docker/c1\n3:cpu,cpuacct:/docker/c1\n")
    assert cgroup_cpu_limit(str(v1), str(me)) == 2.0
    (v1 / "cpu,cpuacct" / "docker" / "c1" / "cpu.cfs_quota_us").write_text("-1\n")
    assert cgroup_cpu_limit(str(v1), str(me)) is None


def test_default_workers_is_the_affinity_capped_by_the_quota(monkeypatch):
    monkeypatch.setattr(executor_mod.os, "sched_getaffinity", lambda pid: set(range(16)), raising=False)
    monkeypatch.setattr(executor_mod, "cgroup_cpu_limit", lambda: None)
    assert default_workers() == 16
    monkeypatch.setattr(executor_mod, "cgroup_cpu_limit", lambda: 2.5)
    assert default_workers() == 3
    monkeypatch.setattr(executor_mod, "cgroup_cpu_limit", lambda: 0.2)
    assert default_workers() == 1


def test_the_commands_default_to_every_core(monkeypatch):
    """campaign and design sweeps: one worker process per core; the diagnosis: one thread per core."""
    import argparse
    from experiment_runner.apps.campaigns.cli import add_campaign_arguments
    from experiment_runner.apps.design.cli import add_design_arguments
    from experiment_runner.apps.diagnosis.pipeline import Options
    monkeypatch.setattr(executor_mod.os, "sched_getaffinity", lambda pid: set(range(7)), raising=False)
    monkeypatch.setattr(executor_mod, "cgroup_cpu_limit", lambda: None)
    for add, argv in ((add_campaign_arguments, ["table_4_2"]), (add_design_arguments, ["fi_stage"])):
        assert add(argparse.ArgumentParser()).parse_args(argv).workers == 7, add.__name__
    assert Options().n_jobs == 7


# --------------------------------------------------------------------------- chunks and the stream
def test_chunks_shrink_as_the_work_left_does(camp, monkeypatch, tmp_path):
    """Guided scheduling: on 4 workers the first chunks are large, the last ones small, and every trial runs once."""
    data = camp.model_dump()
    data["trials"] = 120
    big = Campaign.model_validate(data)
    (cond,) = conditions(big)
    jobs = [(c, cond, case_preset(big, c, None, cond), None) for c in big.cases]
    sizes, ran = [], []
    monkeypatch.setattr(stream_mod, "chunk_task",
                        lambda *a: (sizes.append(len(a[5])), ran.extend((a[1], i) for i in a[5]), [])[-1])
    with stream_mod.TrialStream(tmp_path / STREAM_NAME, big.name, "k", "c", resume=False) as stream:
        stream_mod.run_trial_jobs(big, jobs, Executor("inline", 4, threads=1), stream)
    assert sorted(ran) == sorted((c.name, i) for c in big.cases for i in range(120))
    assert sizes[0] == 30 and max(sizes[-3:]) <= stream_mod.MIN_CHUNK, sizes     # not 8 chunks of 30


def test_stream_hands_records_to_the_os_at_once_and_syncs_once_a_second(camp, tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(stream_mod.os, "fsync", lambda fd: synced.append(fd))
    path = tmp_path / STREAM_NAME
    rec = lambda i: {"case": "a", "condition": "c", "trial": i, "x0_m": 0.0, "metrics": {}}  # noqa: E731
    with stream_mod.TrialStream(path, "x", "k", "c", resume=False) as stream:
        for i in range(20):
            stream.append([rec(i)])
            assert len(path.read_text().splitlines()) == i + 2          # readable by another process at once
        assert synced == []                                              # not one fsync per chunk
        stream._synced -= stream_mod.SYNC_SECONDS
        stream.append([rec(20)])
        assert len(synced) == 1
    assert len(synced) == 2                                              # and at close


@pytest.mark.slow
def test_a_killed_run_keeps_its_streamed_trials(tmp_path):
    """SIGKILL right after an append (no close, no fsync): a resume finds every appended trial."""
    code = f"""
import os, signal
from experiment_runner.apps.campaigns.stream import TrialStream
s = TrialStream({str(tmp_path / STREAM_NAME)!r}, "x", "k", "c", resume=False)
for i in range(5):
    s.append([{{"case": "a", "condition": "c", "trial": i, "x0_m": 0.0, "metrics": {{}}}}])
os.kill(os.getpid(), signal.SIGKILL)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60)
    assert out.returncode == -9, out.stderr
    with stream_mod.TrialStream(tmp_path / STREAM_NAME, "x", "k", "c") as stream:
        assert stream.done("a", "c") == set(range(5))


@pytest.mark.slow
def test_warm_all_runs_on_every_worker_process():
    with make_executor(2) as ex:
        assert ex.warm_all(os.getpid, ()) == 2
        assert ex.threads == max(1, default_workers() // 2)
