"""One case of the power study: its nominal, concealed truth and recording, the diagnosis, the outcome.

The recording is simulated from the truth (the batch engine, noise on) and handed to the
diagnosis in memory as a :class:`~experiment_runner.apps.diagnosis.data.DiagData` (only what a
rig gives: reference, command, measurement, and the dither/SAI commands where the stage has
them); the nominal is the preset as a user would write it.

The **size that counts** is what the effect does to the replay: how much further the
nominal's held-out closed-loop replay is from recordings of the truth than from its own
(:func:`replay_change`, in units of the nominal's run-to-run floor,
:mod:`experiment_runner.apps.diagnosis.judge`). :func:`judge_case` says whether the diagnosis
named the concealed effects, how close their parameters came, and why a true effect was
rejected or a false one adopted.
"""
from __future__ import annotations

import json
import math
import time
import traceback
import warnings
from pathlib import Path

import numpy as np

from experiment_runner.core.batch import simulate
from experiment_runner.core.experiment import Experiment, build_trials
from stage_sim.config import preset_from_dict

from ..data import from_trials
from ..judge import ReplayJudge
from ..model import ModelSpec
from ..options import Options
from ..pipeline import diagnose
from ..truth import check_params
from .cases import PowerCase, nominal_doc, truth_effect

__all__ = ["build_case", "record", "replay_change", "judge_case", "run_case"]

def _trials(case: PowerCase, nominal):
    exp = Experiment.model_validate({"name": case.name, "preset": "fi_stage_nofi", "profile": case.profile,
                                     "trials": case.trials, "starts": {"margin": 0.005, "seed": case.seed % 100000},
                                     "window": 25e-9})
    return build_trials(exp, nominal)


def build_case(case: PowerCase):
    """Build a case: its nominal, its concealed truth and the truth's recording.

    Parameters
    ----------
    case : PowerCase
        The case.

    Returns
    -------
    tuple
        ``(nominal Preset, truth Preset, truth values {effect: {param: value}}, DiagData, trials)``.
    """
    nom_doc = nominal_doc(case)
    nominal = preset_from_dict(nom_doc, f"power case {case.name} nominal")
    tr = _trials(case, nominal)
    info = _info(tr)
    truth_doc = json.loads(json.dumps(nom_doc))
    expect = {}
    for i, (e, q) in enumerate(zip(case.effects, case.quantiles)):
        expect[e] = truth_effect(e, q, np.random.default_rng([case.seed, 7, i]), truth_doc, case, info)
    truth_doc["name"] = f"power_{case.name}_truth"
    truth_doc["simulation"]["seed"] = case.seed % 1000000
    truth = preset_from_dict(truth_doc, f"power case {case.name} truth")
    data = record(truth, tr)
    return nominal, truth, expect, data, tr


def record(truth, trials):
    """What a rig records of ``trials`` run on ``truth`` (noise on).

    Parameters
    ----------
    truth : stage_sim.config.Preset
        The concealed truth.
    trials : list of experiment_runner.core.experiment.Trial
        The trials.

    Returns
    -------
    DiagData
    """

    res = simulate(truth, np.stack([t.x_ref for t in trials]), np.stack([t.v_ref for t in trials]),
                   seeds=[truth.simulation.seed + t.index for t in trials], check=False)
    B = len(trials)
    rows = lambda a: [a[b] for b in range(B)]  # noqa: E731
    dith = truth.dither is not None
    sai = truth.stage.sai is not None and truth.sai_manager is not None
    return from_trials(truth.controller.rate, np.zeros(B), rows(res.x_ref), rows(res.v_ref), rows(res.u), rows(res.y),
                       source="power study (simulated, truth concealed)",
                       d0=rows(res.dither[..., 0]) if dith else None, d1=rows(res.dither[..., 1]) if dith else None,
                       mode=rows(res.mode) if sai else None)


def replay_change(nominal, variants: dict, data) -> dict:
    """How far the nominal's held-out replay is from recordings of each variant (presets),
    beyond its own run-to-run floor: ``sqrt(|E D(variant) - E D(nominal)| / E D(nominal))``
    (:mod:`experiment_runner.apps.diagnosis.judge`; 4 simulated recordings per variant).

    Parameters
    ----------
    nominal : stage_sim.config.Preset
        The nominal.
    variants : dict
        Name -> preset.
    data : DiagData
        The recording (its held-out trials are judged).

    Returns
    -------
    dict
        Name -> the change, in floor units (3 = the study's threshold of a detectable effect).
    """
    j = ReplayJudge(data)
    nom = ModelSpec(nominal)
    fl = j.floor(nom)
    n = max(j.n, 1)
    base = float(np.mean(j.sim_blocks(fl.replay, fl).sum(axis=1) / n))
    out = {}
    for k, p in variants.items():
        u, y, _, _ = j.simulate_recordings(ModelSpec(p), j.seeds[:4])
        e2 = [((u[i] - fl.replay.u) / fl.sigma_u) ** 2 + ((y[i] - fl.replay.y) / fl.sigma_y) ** 2 for i in range(4)]
        Dv = float(np.mean([np.sum(x[j.mask]) / n for x in e2]))
        # a floor without noise (a stage that never slips at its encoder step) counts as 2 per
        # sample, as :meth:`.judge.ReplayJudge.floor_ratio` counts it
        out[k] = float(math.sqrt(abs(Dv - base) / max(base, 2.0)))
    return out


def _named(rep: dict) -> list[tuple[str, set]]:
    return [(f["effect"], {f["effect"]} | set(f.get("confounded_with") or [])) for f in rep["found"]]


def judge_case(case: PowerCase, rep: dict, expect: dict, change: dict) -> dict:
    """Outcome of one case: named first / pair / false positive, parameter errors, reasons.

    Parameters
    ----------
    case : PowerCase
        The case.
    rep : dict
        The diagnosis report.
    expect : dict
        Effect -> parameter -> true value.
    change : dict
        Effect -> :func:`replay_change` of it.

    Returns
    -------
    dict
    """
    named = _named(rep)
    keys = [k for k, _ in named]
    truth = set(case.effects)
    out = {"case": case.name, "kind": case.kind, "effects": list(case.effects), "named": keys,
           "replay_change": change, "verdict": rep.get("verdict")}
    if not truth:
        out["false_positive"] = bool(keys)
        return out
    first_ok = bool(named) and bool(named[0][1] & truth)
    covered = {e for e in truth if any(e in st for _, st in named)}
    out["named_first"] = first_ok and covered == truth if len(truth) == 1 else first_ok
    out["both_named"] = first_ok and covered == truth
    out["detected"] = {e: e in covered for e in truth}
    out["extra"] = [k for k, st in named if not (st & truth)]
    params = {}
    for e, exp_ in expect.items():
        entry = next((f for f in rep["found"] if f["effect"] == e), None)
        if entry is None:
            entry = next((a for f in rep["found"] for a in f.get("alternatives") or [] if a["effect"] == e), None)
        ok, ch = check_params(entry, exp_)
        params[e] = {"ok": ok if entry is not None else None, "checks": ch}
    out["params"] = params
    return out


def _reason(rep: dict, effect: str) -> str:
    """Why the diagnosis did not adopt ``effect`` (from its selection steps)."""
    why = []
    for st in (rep.get("selection") or {}).get("steps", []):
        for c in st.get("candidates", []):
            if c.get("effect") == effect:
                r = c.get("why") or ("significant" if c.get("significant") else "not significant")
                why.append(f"step {st['step']}: {r}")
        if effect in (st.get("failed") or {}):
            why.append(f"step {st['step']}: the fit failed ({st['failed'][effect]})")
    if not why:
        return "never proposed (no candidate row)"
    return "; ".join(why[:3])


def run_case(case: PowerCase, keep=None) -> dict:
    """Build, diagnose and judge one case (an executor task); the warnings it raised listed
    in the result (``warnings``), not printed.

    Parameters
    ----------
    case : PowerCase
        The case.
    keep : str or pathlib.Path, optional
        Folder for the case's recording and report.

    Returns
    -------
    dict
        :func:`judge_case`'s result (or ``error`` when the case failed) with ``setting``, ``seconds`` and any ``warnings``.
    """
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:     # a worker process: per case, not per thread
        warnings.simplefilter("default")
        res = _run_case(case, keep)
    if caught:
        res["warnings"] = sorted({f"{w.category.__name__}: {w.message} ({Path(w.filename).name}:{w.lineno})"
                                  for w in caught})
    res["setting"] = {"stage": case.stage, "friction": case.friction, "rate_hz": case.rate, "noise": case.noise,
                      "record": case.record, "trials": case.trials}
    res["seconds"] = round(time.perf_counter() - t0, 2)
    return res


def _run_case(case: PowerCase, keep) -> dict:
    try:
        nominal, truth, expect, data, tr = build_case(case)
        variants = {"truth": truth}
        alldata = data.subset(np.arange(data.shape[1]))
        given = {}
        if len(case.effects) == 2:
            for i, (e, q) in enumerate(zip(case.effects, case.quantiles)):
                doc = nominal.model_dump(mode="json")
                truth_effect(e, q, np.random.default_rng([case.seed, 7, i]), doc, case, _info(tr))
                variants[e] = preset_from_dict(doc, e)
            # what each effect adds to the truth once the other is in the model: the nominal plus
            # the other effect's replay against recordings of the truth, in that model's floor
            a, b = case.effects
            given = {a: replay_change(variants[b], {"truth": truth}, alldata)["truth"],
                     b: replay_change(variants[a], {"truth": truth}, alldata)["truth"]}
        change = replay_change(nominal, variants, alldata)
        truth_stable = ReplayJudge(data.subset(np.arange(data.shape[1]))).replay(ModelSpec(truth)).ok
        out_dir = None if keep is None else Path(keep) / case.name
        rep = diagnose(None, ModelSpec(nominal), out=out_dir, data=data, options=Options(plots=keep is not None,
                                                                                          n_jobs=1, progress=False,
                                                                                          max_seconds=None))
        res = judge_case(case, rep, expect, change)
        if given:
            res["replay_change_given_other"] = given
        res["expect"] = expect
        res["truth_stable"] = bool(truth_stable)
        res["diagnose_s"] = round(rep["timing_s"]["total_s"], 2)
        res["improved_worse"] = _improved_worse(rep)
        if case.effects:
            res["reasons"] = {e: _reason(rep, e) for e in case.effects if not res["detected"].get(e)}
        res["extra_reasons"] = {e: _extra_reason(rep, e) for e in res.get("extra") or (res["named"] if not case.effects else [])}
    except Exception as err:      # noqa: BLE001 - a crashing case is a failed case, reported
        res = {"case": case.name, "kind": case.kind, "effects": list(case.effects), "error": repr(err),
               "traceback": traceback.format_exc(limit=4), "named": [], "replay_change": {}}
    return res


def _info(tr):
    x = np.concatenate([t.x_ref for t in tr])
    v = np.concatenate([t.v_ref for t in tr])
    return {"x_center": float(0.5 * (x.max() + x.min())), "half_span": max(0.5 * float(np.ptp(x)), 1e-4),
            "stroke": max(float(np.median([np.ptp(t.x_ref) for t in tr])), 2e-6),
            "v_max": max(float(np.max(np.abs(v))), 1e-5)}


def _improved_worse(rep: dict):
    """The improved model's held-out replay unstable or further from the data than the nominal's."""
    r = rep.get("replay") or {}
    if not rep.get("found") or not r:
        return False
    fr = r["floor_ratio"]
    return bool(not r["stable"]["improved"] or fr["improved"] > 1.05 * fr["nominal"])


def _extra_reason(rep: dict, effect: str) -> str:
    for st in (rep.get("selection") or {}).get("steps", []):
        if st.get("accepted") == effect:
            c = next((c for c in st.get("candidates", []) if c.get("effect") == effect), {})
            if "improvement" in c and "threshold" in c:
                return (f"step {st['step']}: replay improvement {c['improvement']:.3g} vs threshold "
                        f"{c['threshold']:.3g} ({c.get('why', '')})")
            return f"step {st['step']}: J_held improvement {c.get('improvement', float('nan')):.3g} accepted"
    f = next((f for f in rep.get("found", []) if f["effect"] == effect), {})
    if f.get("kind") == "stochastic":
        return f"stochastic: {f.get('held_out')}"
    return "adopted"
