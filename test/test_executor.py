"""Campaign trials on executors (in process, local processes, Dask), streamed and resumable.

A tiny campaign (Table 4.2's two cases at the 5 µm step, 6 trials, 50 ms dwell) must give
exactly the per-trial metrics of one in-memory batch run of all trials, whatever runs it.
"""
import json
import logging
import math

import pytest

from experiment_runner.campaigns import stream as stream_mod
from experiment_runner.campaigns.runner import run_campaign
from experiment_runner.campaigns.spec import Campaign, case_preset, conditions, load_campaign
from experiment_runner.campaigns.stream import STREAM_NAME
from experiment_runner.campaigns.trials import metric_record, simulate_trials
from experiment_runner.executor import make_executor
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


@pytest.fixture(scope="module")
def dask_cluster():
    from distributed import LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR) as cluster:
        yield cluster


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


@pytest.mark.slow
def test_dask_local_cluster_gives_identical_metrics(camp, reference_metrics, tmp_path, dask_cluster):
    _check_same(_run(camp, tmp_path, cluster=dask_cluster.scheduler_address), reference_metrics, camp)


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
