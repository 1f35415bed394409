"""Running a trial campaign (point-to-point, circle): calibrate, learn, simulate, judge, write.

:func:`run_trial_campaign` is the ``run`` of the trial kinds
(:mod:`experiment_runner.apps.campaigns.trial_kinds`), in steps that are functions here:

1. :func:`calibration_of` -- fit the campaign's calibration on its baseline case only
   (:mod:`~experiment_runner.apps.campaigns.calibration`), reuse another campaign's, or take a given
   ``calibration.json``;
2. :func:`simulate_all` -- every case x condition: SAI Step II learning where a case has it
   (:func:`~experiment_runner.apps.campaigns.trials.learn_step_ii`), all trials of all of them in
   chunks on one executor, streamed to ``trials.jsonl`` (:mod:`~experiment_runner.apps.campaigns.stream`), the
   statistics, the representative trial (median of the kind's representative metric) run again
   for its trace, its settling mechanism (the kind's ``analyse``) and MCAP recording;
3. :func:`run_graph` -- optionally the representative trials through the ROS 2 graph;
4. the findings (:func:`~experiment_runner.apps.campaigns.findings.evaluate_findings`) and the
   outputs (:func:`write_results`, :func:`experiment_runner.apps.campaigns.report.write_outputs`).
"""
from __future__ import annotations

import math
import sys
import time
from contextlib import nullcontext
from dataclasses import replace
from pathlib import Path
from typing import Optional

import numpy as np
import yaml
from tqdm import tqdm

from experiment_runner.apps.campaigns.base import (OUTPUT_FILES, CampaignKind, CampaignRun, RunResult, RunSettings, Stat,
                                              write_json, write_rows_csv)
from experiment_runner.apps.campaigns.calibration import calibrate, source_calibration
from experiment_runner.apps.campaigns.findings import evaluate_findings
from experiment_runner.apps.campaigns.graph_runs import compare_graph, run_graph_jobs
from experiment_runner.apps.campaigns.report import write_outputs
from experiment_runner.apps.campaigns.spec import CalibrationFrom, Campaign, case_overrides, case_preset, conditions
from experiment_runner.apps.campaigns.stream import (STREAM_NAME, TrialStream, campaign_key, code_fingerprint,
                                                representative_trial, run_trial_jobs, warm_up)
from experiment_runner.apps.campaigns.trials import graph_experiment, learn_step_ii
from experiment_runner.core import outputs
from experiment_runner.core.executor import make_executor
from experiment_runner.core.metrics import finite_or_none
from experiment_runner.core.recording import write_run

__all__ = ["run_trial_campaign", "calibration_of", "simulate_all", "run_graph", "write_results"]


def _bar(settings: RunSettings, desc: str, **kw) -> tqdm:
    return tqdm(desc=desc, file=sys.stderr, disable=not settings.progress, leave=False, mininterval=0.5, **kw)


def run_trial_campaign(kind: CampaignKind, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
    """Calibrate (baseline only), run every case and condition, write the outputs (see the module docstring).

    Parameters
    ----------
    kind : CampaignKind
        The campaign's kind (point-to-point or circle).
    camp : Campaign
        The campaign as run.
    out_dir : pathlib.Path
        The campaign's output folder.
    settings : RunSettings
        How it runs.

    Returns
    -------
    CampaignRun
    """
    t_start = time.monotonic()
    out_dir = outputs.prepare_folder(out_dir, settings.overwrite, files=OUTPUT_FILES, option="--out")
    conds = conditions(camp)
    timing = {}
    with _executor(settings) as ex:
        base = camp.case(camp.baseline)
        warm_up(camp, base, conds[0], case_preset(camp, base, None, conds[0]), ex)   # while calibrating
        cal = calibration_of(camp, out_dir, settings)
        cal_values = dict(cal["values"]) if cal is not None else None
        timing["calibration_s"] = time.monotonic() - t_start
        t1 = time.monotonic()
        runs, step_ii = simulate_all(kind, camp, conds, cal_values, out_dir, settings, ex)
        timing["simulation_s"] = time.monotonic() - t1
    t2 = time.monotonic()
    if settings.graph:
        run_graph(camp, conds, runs, step_ii, cal_values, out_dir, settings)
    timing["graph_s"] = time.monotonic() - t2
    findings = evaluate_findings(camp, runs)
    summary = {"trials": camp.trials, "test": camp.test.model_dump(), "starts": camp.starts.model_dump(),
               "calibrated": cal is not None, "calibration_trials": cal.get("trials") if cal else None,
               "graph": settings.graph}
    cr = CampaignRun(campaign=camp, kind=kind, out_dir=out_dir, conditions=conds, runs=runs, findings=findings,
                     calibration=cal, step_ii=step_ii, settings=summary, timing=timing)
    write_outputs(cr, report=settings.report, plots=settings.plots, t_start=t_start)
    return cr


def calibration_of(camp: Campaign, out_dir: Path, settings: RunSettings) -> Optional[dict]:
    """The calibration the cases run with (``calibration.json`` content), or None (the presets' values).

    A fit runs in this process (numba threads over the trials): on a process pool its many short
    evaluations were no faster (table_4_2, 16 trials, 2 workers: calibration + simulation the same).

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    out_dir : pathlib.Path
        The campaign's output folder.
    settings : RunSettings
        How it runs.

    Returns
    -------
    dict or None
        ``settings.calibration`` marked ``reused``, a new fit, or None when nothing is calibrated.
    """
    if settings.calibration is not None:
        cal = dict(settings.calibration)
        cal["reused"] = True
        return cal
    if not settings.calibrate or camp.calibration is None:
        return None
    if isinstance(camp.calibration, CalibrationFrom):
        with _bar(settings, f"{camp.name}: calibration of {camp.calibration.from_}", unit="eval") as bar:
            return source_calibration(camp, out_dir, settings.calibration_trials, bar)
    n_cal = min(settings.calibration_trials or camp.calibration.trials, camp.trials)
    with _bar(settings, f"{camp.name}: calibrate {camp.baseline}", unit="eval") as bar:
        cal = calibrate(camp, n_cal, bar)
    cal["reused"] = False
    return cal


def simulate_all(kind: CampaignKind, camp: Campaign, conds: list, cal_values: Optional[dict], out_dir: Path,
                 settings: RunSettings, executor) -> tuple[dict, dict]:
    """Every case at every condition: ``runs[(case, condition key)]`` (:class:`RunResult`) and the
    learned Step II corrections ``{case: {...}}``.

    First the presets and Step II corrections of every case and condition, then all their trials
    as one task list on the executor (:func:`~experiment_runner.apps.campaigns.stream.run_trial_jobs`),
    then each one's statistics and representative trial.

    Parameters
    ----------
    kind : CampaignKind
        The campaign's kind (point-to-point or circle).
    camp : Campaign
        The campaign as run.
    conds : list of Condition
        The conditions.
    cal_values : dict or None
        Calibrated values (SI units).
    out_dir : pathlib.Path
        The campaign's output folder.
    settings : RunSettings
        How it runs.
    executor : experiment_runner.core.executor.Executor
        Where the trials run.

    Returns
    -------
    runs : dict
        ``(case, condition key)`` -> :class:`RunResult`.
    step_ii : dict
        Case -> its learned Step II correction (:func:`~experiment_runner.apps.campaigns.trials.learn_step_ii`).
    """
    step_ii, runs, first = {}, {}, {}
    n_units = len(camp.cases) * len(conds) + sum(
        ((c.step_ii.iterations if c.step_ii.iterations is not None else
          case_preset(camp, c).sai_manager.ilc.iterations) + 1) * (len(conds) if c.step_ii.learn == "on_move" else 1)
        for c in camp.cases if c.step_ii)
    stream_key = campaign_key(camp, {(c.name, cond.key): case_preset(camp, c, cal_values, cond)
                                     for c in camp.cases for cond in conds})
    with _bar(settings, f"{camp.name}: simulate", total=n_units, unit="run") as bar, \
            TrialStream(out_dir / STREAM_NAME, camp.name, stream_key, code_fingerprint(), settings.resume) as stream:
        plan = []                      # (case, cond, preset, correction, the first run of the same trials)
        for case in camp.cases:
            corr_cache = {}
            for cond in conds:
                preset = case_preset(camp, case, cal_values, cond)
                corr = None
                if case.step_ii is not None:
                    key = (preset.model_dump_json(), cond.key if case.step_ii.learn == "on_move" else None)
                    if key not in corr_cache:
                        corr_cache[key] = learn_step_ii(camp, case, preset, progress=lambda: bar.update(1), cond=cond)
                        step_ii.setdefault(case.name, corr_cache[key])
                    corr = corr_cache[key]["correction"]
                # a case the sweep leaves unchanged is run once per test condition and reused
                same = (case.name, preset.model_dump_json(), tuple(v for k, v in cond.at().items() if k != "sweep"))
                if cond.sweep is None or same not in first:
                    first[same] = (case.name, cond.key)
                plan.append((case, cond, preset, corr, first[same]))
        jobs = [(case, cond, preset, corr) for case, cond, preset, corr, ref in plan if ref == (case.name, cond.key)]
        run_trial_jobs(camp, jobs, executor, stream, on_chunk=lambda case, cond, d, n: bar.set_postfix_str(
            f"{case.name} {cond.label}: {d}/{n} trials"))
        for case, cond, preset, corr, ref in plan:
            if ref != (case.name, cond.key):
                runs[(case.name, cond.key)] = replace(runs[ref], cond=cond, wall_s=0.0)
            else:
                runs[(case.name, cond.key)] = _case_at(kind, camp, case, cond, preset, corr, cal_values, stream,
                                                       out_dir, settings)
            bar.update(1)
    return runs, step_ii


def _executor(settings: RunSettings):
    """The executor of the trials: ``settings.executor`` (kept open) or a new one (closed after the campaign)."""
    return nullcontext(settings.executor) if settings.executor is not None else \
        make_executor(settings.workers, settings.cluster)


def _case_at(kind, camp, case, cond, preset, corr, cal_values, stream, out_dir, settings) -> RunResult:
    """One case at one condition: its trials (from the stream), statistics and representative trial."""
    tc = time.monotonic()
    mets, x0 = stream.read(case.name, cond.key, camp.trials)
    stats = {m: Stat.of([x.get(m) for x in mets]) for m in kind.metrics}
    rep = representative(kind, mets)
    ref, tr, res = representative_trial(camp, case, cond, preset, rep, corr, mets[rep])
    rr = RunResult(case=case.name, cond=cond, preset=preset, overrides=case_overrides(camp, case, cal_values, cond),
                   metrics=mets, stats=stats, rep=rep, trace=kind.trace(camp, ref, tr, res, mets[rep], rep),
                   wall_s=time.monotonic() - tc, x0=x0)
    rr.mechanism = kind.analyse(camp, case, cond, preset, rep, corr)
    if settings.mcap:
        bag = out_dir / "recordings" / f"{case.name}_{cond.key}_batch"
        p = write_run(bag, res, preset, reference=ref, window=camp.test.window,
                      case=f"{camp.name}/{case.name}/{cond.key}/trial{rep}", overwrite=True, node="batch")
        rr.recording = str(p)
    return rr


def representative(kind: CampaignKind, mets: list) -> int:
    """The trial whose representative metric is nearest the median of the settled ones (0 if none).

    Parameters
    ----------
    kind : CampaignKind
        The campaign's kind (point-to-point or circle).
    mets : list of dict
        Metrics per trial.

    Returns
    -------
    int
        Trial index.
    """
    key = kind.representative_metric
    vals = np.array([np.nan if m.get(key) is None else m[key] for m in mets], float)
    ok = np.flatnonzero(np.isfinite(vals))
    if not ok.size:
        return 0
    med = np.median(vals[ok])
    return int(ok[np.argmin(np.abs(vals[ok] - med))])


def run_graph(camp: Campaign, conds: list, runs: dict, step_ii: dict, cal_values: Optional[dict], out_dir: Path,
              settings: RunSettings) -> None:
    """The representative trial of every case and condition through the ROS graph; sets ``runs[...].graph``.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    conds : list of Condition
        The conditions.
    runs : dict
        ``(case, condition key)`` -> :class:`RunResult`; each gets its ``graph`` comparison.
    step_ii : dict
        Learned Step II corrections per case.
    cal_values : dict or None
        Calibrated values.
    out_dir : pathlib.Path
        The campaign's output folder.
    settings : RunSettings
        How it runs.
    """
    exp_dir = out_dir / "graph_experiments"
    jobs = []
    for case in camp.cases:
        for cond in conds:
            rr = runs[(case.name, cond.key)]
            exp = graph_experiment(camp, case, cond, rr.rep, cal_values)
            path = exp_dir / f"{case.name}_{cond.key}.yaml"
            outputs.write_text(path, yaml.safe_dump(exp, sort_keys=False, allow_unicode=True))
            bag = out_dir / "recordings" / f"{case.name}_{cond.key}_graph"
            outputs.prepare_recording(bag, overwrite=True)       # the recorder writes it anew
            corr = step_ii[case.name]["correction"].tolist() if case.name in step_ii else None
            jobs.append({"key": (case.name, cond.key), "experiment": str(path), "bag": str(bag),
                         "timeout": settings.graph_timeout, "correction": corr, "samples": len(rr.trace.t)})
    with _bar(settings, f"{camp.name}: ROS graph", total=len(jobs), unit="trial") as bar:
        got = run_graph_jobs(jobs, settings.graph_workers, bar)
    for g in got:
        rr = runs[tuple(g["key"])]
        rr.graph = compare_graph(g, rr)


def write_results(cr: CampaignRun) -> None:
    """Write ``results.csv``, ``results.json`` and ``calibration.json`` (SI units).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run; the files go to ``cr.out_dir``.
    """
    camp = cr.campaign
    metrics = cr.kind.metrics
    rows = []
    for case in camp.cases:
        for cond in cr.conditions:
            rr = cr.runs[(case.name, cond.key)]
            for m in metrics:
                st = rr.stats[m]
                seed = camp.seed_value(case.name, m, **cond.at())
                rows.append({
                    "campaign": camp.name, "case": case.name, "case_label": case.label, "condition": cond.key,
                    "condition_label": cond.label, "step_m": cond.step, "radius_m": cond.radius,
                    "speed_m_s": cond.speed, "sweep_name": camp.sweep.name if camp.sweep else None,
                    "sweep_value": cond.sweep, "metric": m, "mean": finite_or_none(st.mean), "std": finite_or_none(st.std),
                    "n_trials": st.n, "n_valid": st.n_valid, "seed": seed,
                    "sim_over_seed": finite_or_none(st.mean / seed) if seed and math.isfinite(st.mean) else None,
                    "baseline": case.name == camp.baseline})
    write_rows_csv(cr.out_dir / "results.csv", rows)
    doc = {
        "campaign": camp.name, "title": camp.title, "description": camp.description, "seed_source": camp.seed.source,
        "seed_notes": camp.seed.notes, "baseline": camp.baseline, "settings": cr.settings, "timing_s": cr.timing,
        "cases": [{"name": c.name, "label": c.label, "preset": c.preset, "description": c.description,
                   "step_ii": c.step_ii.model_dump() if c.step_ii else None,
                   "overrides": {cond.key: cr.runs[(c.name, cond.key)].overrides for cond in cr.conditions}}
                  for c in camp.cases],
        "conditions": [{"key": c.key, "label": c.label, **c.at()} for c in cr.conditions],
        "results": rows,
        "findings": cr.findings,
        "calibration": {k: v for k, v in (cr.calibration or {}).items() if k != "history"} or None,
        "step_ii": {k: {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv) for kk, vv in v.items()}
                    for k, v in cr.step_ii.items()},
        "representative": [{"case": k[0], "condition": k[1], "trial": rr.rep, "x0_m": rr.x0[rr.rep],
                            "metrics": {m: rr.metrics[rr.rep].get(m) for m in metrics},
                            "recording": rr.recording, "graph": rr.graph,
                            "mechanism": ({k2: v for k2, v in rr.mechanism.items() if k2 != "trace"}
                                          if rr.mechanism else None)} for k, rr in cr.runs.items()],
        "trials": [{"case": k[0], "condition": k[1], "trial": i, "x0_m": rr.x0[i] if i < len(rr.x0) else None,
                    **{m: met.get(m) for m in metrics}, **({"failed": met["failed"]} if "failed" in met else {})}
                   for k, rr in cr.runs.items() for i, met in enumerate(rr.metrics)],
        "files": {k: [str(x) for x in v] if isinstance(v, list) else str(v) for k, v in cr.files.items()},
    }
    write_json(cr.out_dir / "results.json", doc)
    if cr.calibration is not None:
        write_json(cr.out_dir / "calibration.json", cr.calibration)
