"""Calibration of a campaign's *baseline* case, before any prediction.

A campaign file (:mod:`experiment_runner.apps.campaigns.spec`) names a few physically meaningful
parameters of the simulated stage that the seed does not give (e.g. the drive's current
noise, the PID integral corner), each with bounds and the *one* baseline number it is
fitted to (e.g. the No FI mean settling time of the 5 mm step, Table 4.2). This module
fits them, and nothing else: the other cases of the campaign then run with the same
values and are predictions. No non-baseline number is ever used.

Method
------
Each parameter ``p_i`` is paired with its target ``T_i`` (a mean over the calibration
trials of the baseline case). The residual is the log ratio

    r_i(p) = log(sim_i(p) / seed_i)

(``form: quadrature_excess``: the part of the metric above a deterministic floor,
``sqrt(sim_i(p)^2 - sim_i(p_i = null)^2)`` against ``sqrt(seed_i^2 - floor^2)``, so that
a noise level is fitted to the noise-attributable part of an in-position error only).
The pairs are solved by bounded 1-D root finding (:func:`scipy.optimize.brentq` in the
parameter, or in its logarithm for ``log: true``), one parameter at a time with the
others held (Gauss-Seidel), for a few rounds until no parameter moves by more than
``rtol``. If ``r_i`` does not change sign inside the bounds, the bound with the smaller
``|r_i|`` is taken and reported as ``at_bound`` (the target is then out of the model's
reach, and the report says so). Evaluations use the same trials (start positions and
noise seeds) every time, so the objective is deterministic; they are cached.

:func:`calibrate` sets up and runs that fit for a campaign's baseline (and a sensitivity profile
around it), :func:`source_calibration` reuses another campaign's (``calibration: {from: NAME}``).

Examples
--------
A toy "simulation" whose metric is ``2 p``, fitted to a seed value of 3:

>>> from experiment_runner.apps.campaigns.calibration import ParamSpec, fit
>>> spec = ParamSpec(name="p", bounds=(0.1, 10.0), log=True, seed_value=3.0)
>>> res = fit([spec], {"p": 1.0}, lambda v: {"p": 2.0 * v["p"]})
>>> round(res.values["p"], 4), res.params[0].at_bound
(1.5, None)
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

from scipy.optimize import brentq

from experiment_runner.apps.campaigns.base import Stat
from experiment_runner.apps.campaigns.overrides import expand_path, resolve, to_python
from experiment_runner.apps.campaigns.spec import Campaign, calibration_source, case_preset, conditions
from experiment_runner.apps.campaigns.trials import metric_record, simulate_trials
from experiment_runner.core.batch import Models
from experiment_runner.core.metrics import finite_or_none

__all__ = ["ParamSpec", "ParamFit", "CalibrationResult", "fit", "calibrate", "calibration_fingerprint",
           "source_calibration"]

_CLIP = 20.0      # |log ratio| used for a metric that is 0, nan or not reached


@dataclass(frozen=True)
class ParamSpec:
    """One parameter and the target it is fitted to (see module docstring).

    Parameters
    ----------
    name : str
        The parameter's name.
    bounds : tuple of float
        Its search range (SI units, or the scale factor of a ``scale`` parameter).
    seed_value : float
        The seed's baseline number of the target metric (SI).
    log : bool
        Search in log(p).
    form : {"absolute", "quadrature_excess"}
        What is matched: the metric itself, or its excess over ``seed_floor`` in quadrature.
    seed_floor : float
        ``quadrature_excess``: the deterministic floor of the seed value.
    null : float, optional
        ``quadrature_excess``: the parameter value that removes the effect.
    """
    name: str
    bounds: tuple[float, float]
    seed_value: float                 # the seed's baseline number (SI)
    log: bool = False                 # search in log(p)
    form: str = "absolute"            # "absolute" | "quadrature_excess"
    seed_floor: float = 0.0           # quadrature_excess: deterministic floor of the seed value
    null: Optional[float] = None      # quadrature_excess: parameter value that removes the effect


@dataclass
class ParamFit:
    """Result for one parameter.

    Parameters
    ----------
    name : str
        The parameter.
    value, start : float
        Fitted and start value.
    bounds : tuple of float
        Search range.
    at_bound : {None, "lower", "upper"}
        The bound the fit ended at, if any (then the target is not reached).
    seed_value : float
        The seed's number of the target metric (SI).
    seed_effective : float
        What the residual compares with (after the floor).
    sim_start, sim_value, sim_effective : float or None
        The metric at the start values, at the fitted values, and its effective part.
    residual : float
        log(sim_effective / seed_effective) at the fit.
    """
    name: str
    value: float
    start: float
    bounds: tuple[float, float]
    at_bound: Optional[str]           # None, "lower" or "upper"
    seed_value: float
    seed_effective: float             # what the residual compares with (after the floor)
    sim_start: Optional[float]        # metric at the start values
    sim_value: Optional[float]        # metric at the fitted values
    sim_effective: Optional[float]
    residual: float                   # log(sim_effective / seed_effective) at the fit


@dataclass
class CalibrationResult:
    """What :func:`fit` returns.

    Parameters
    ----------
    values : dict
        Parameter name -> fitted value.
    params : list of ParamFit
        Per parameter.
    evaluations : int
        Simulations of the baseline run.
    rounds : int
        Gauss-Seidel rounds run.
    converged : bool
        No parameter changed by more than ``rtol`` in the last round.
    history : list
        ``(values, metrics)`` of every evaluation.
    """
    values: dict
    params: list
    evaluations: int
    rounds: int
    converged: bool
    history: list = field(default_factory=list)   # (values, metrics) of every evaluation


def _seed_effective(spec: ParamSpec) -> float:
    if spec.form == "quadrature_excess":
        return math.sqrt(max(spec.seed_value ** 2 - spec.seed_floor ** 2, 0.0))
    return spec.seed_value


def fit(specs: list[ParamSpec], start: dict, evaluate: Callable[[dict], dict], *, rounds: int = 3,
        rtol: float = 0.01, progress: Optional[Callable[[], None]] = None) -> CalibrationResult:
    """Fit ``specs`` (paired parameter/target) by bounded 1-D root finding, Gauss-Seidel.

    Parameters
    ----------
    specs : list of ParamSpec
        The parameters, each with its target.
    start : dict
        Start value of every parameter (usually the preset's value); also the values
        held for parameters not being fitted.
    evaluate : callable
        ``evaluate(values) -> {param name: metric}``: simulates the baseline with the
        given parameter values and returns, for every parameter, the mean of its target
        metric (nan if not defined, e.g. the trials never settled).
    rounds : int
        Maximum number of Gauss-Seidel rounds.
    rtol : float
        Stop when no parameter changes by more than this (relative) in a round.
    progress : callable, optional
        Called after every new evaluation (progress bars).

    Returns
    -------
    CalibrationResult
    """
    cache: dict = {}
    history: list = []

    def run(values: dict) -> dict:
        key = tuple(round(float(values[s.name]), 15) for s in specs)
        if key not in cache:
            cache[key] = evaluate(dict(values))
            history.append((dict(values), dict(cache[key])))
            if progress:
                progress()
        return cache[key]

    def effective(spec: ParamSpec, values: dict) -> float:
        sim = run(values)[spec.name]
        if sim is None or not math.isfinite(sim):
            return math.nan
        if spec.form == "quadrature_excess":
            null = spec.null if spec.null is not None else spec.bounds[0]
            base = run({**values, spec.name: null})[spec.name]
            if base is None or not math.isfinite(base):
                return math.nan
            return math.sqrt(max(sim ** 2 - base ** 2, 0.0))
        return sim

    def residual(spec: ParamSpec, values: dict) -> float:
        sim = effective(spec, values)
        target = _seed_effective(spec)
        if not math.isfinite(sim):
            return _CLIP          # e.g. never settled: treat as far too large
        if sim <= 0.0 or target <= 0.0:
            return -_CLIP if sim <= 0.0 else _CLIP
        return max(-_CLIP, min(_CLIP, math.log(sim / target)))

    def to_s(spec, p):
        return math.log(p) if spec.log else p

    def to_p(spec, s):
        return math.exp(s) if spec.log else s

    for s in specs:
        lo, hi = s.bounds
        if not lo < hi or (s.log and lo <= 0):
            raise ValueError(f"calibration parameter {s.name}: bad bounds {s.bounds}")
    values = {s.name: float(start[s.name]) for s in specs}
    for s in specs:          # start inside the bounds
        values[s.name] = min(max(values[s.name], s.bounds[0]), s.bounds[1])
    start_values = dict(values)
    start_metrics = run(values)
    at_bound: dict = {s.name: None for s in specs}
    converged = False
    n_rounds = 0
    for n_rounds in range(1, rounds + 1):
        moved = 0.0
        for spec in specs:
            lo, hi = (to_s(spec, b) for b in spec.bounds)

            def f(sv, spec=spec):
                return residual(spec, {**values, spec.name: to_p(spec, sv)})

            s0 = to_s(spec, values[spec.name])
            # try a bracket around the present value first (cheap in later rounds)
            a, b = (lo, hi) if n_rounds == 1 else (max(lo, s0 - 0.1 * (hi - lo)), min(hi, s0 + 0.1 * (hi - lo)))
            fa, fb = f(a), f(b)
            if fa * fb > 0 and (a, b) != (lo, hi):
                a, b = lo, hi
                fa, fb = f(a), f(b)
            if fa == 0.0:
                new, where = a, None
            elif fb == 0.0:
                new, where = b, None
            elif fa * fb < 0:
                new = brentq(f, a, b, xtol=1e-4 * max(1.0, abs(hi - lo)), rtol=1e-4, maxiter=40)
                where = None
            else:           # no sign change inside the bounds: the closer bound
                new, where = (a, "lower" if a == lo else None) if abs(fa) <= abs(fb) else (b, "upper" if b == hi else None)
            p_new = to_p(spec, new)
            old = values[spec.name]
            moved = max(moved, abs(p_new - old) / max(abs(old), 1e-300))
            values[spec.name] = p_new
            at_bound[spec.name] = where
        if moved <= rtol:
            converged = True
            break
    fits = []
    final = run(values)
    for spec in specs:
        sim_eff = effective(spec, values)
        fits.append(ParamFit(
            name=spec.name, value=values[spec.name], start=start_values[spec.name], bounds=tuple(spec.bounds),
            at_bound=at_bound[spec.name], seed_value=spec.seed_value, seed_effective=_seed_effective(spec),
            sim_start=finite_or_none(start_metrics.get(spec.name)), sim_value=finite_or_none(final.get(spec.name)),
            sim_effective=finite_or_none(sim_eff), residual=residual(spec, values)))
    return CalibrationResult(values=values, params=fits, evaluations=len(cache), rounds=n_rounds,
                             converged=converged, history=history)


def calibrate(camp: Campaign, n_trials: int, bar=None) -> dict:
    """Fit the campaign's calibration parameters on its baseline case.

    Parameters
    ----------
    camp : Campaign
        The campaign (its ``calibration`` block and seed targets).
    n_trials : int
        Trials per evaluation.
    bar : tqdm.tqdm, optional
        Progress bar, updated per evaluation.

    Returns
    -------
    dict
        The ``calibration.json`` content: values, per-parameter fits, fingerprint.
    """
    cal = camp.calibration
    base = camp.case(camp.baseline)
    preset0 = case_preset(camp, base)
    specs, start, preset_values = [], {}, {}
    for p in cal.parameters:
        seed = camp.seed_value(camp.baseline, p.target.metric, **p.target.at())
        specs.append(ParamSpec(name=p.name, bounds=tuple(p.bounds), seed_value=seed, log=p.log,
                               form=p.target.form, seed_floor=p.target.seed_floor, null=p.neutral))
        if p.mode == "scale":
            start[p.name] = 1.0
            preset_values[p.name] = 1.0
        else:
            vals = {v if not isinstance(v, list) else tuple(v) for v in
                    (old for _, old in expand_path(preset0.model_dump(), p.paths[0]))}
            v0 = next(iter(vals))
            start[p.name] = float(v0) if v0 is not None else float(p.bounds[0])
            preset_values[p.name] = v0
    conds = {}
    for p in cal.parameters:
        c = next(c for c in conditions(camp) if c.matches(**p.target.at()))
        conds[c.key] = c

    def evaluate(values):
        out = {}
        per_cond = {}
        for key, c in conds.items():
            preset = case_preset(camp, base, values, c)
            _, trials, res = simulate_trials(camp, base, c, preset, range(n_trials), models=Models.from_preset(preset))
            mets = [metric_record(tr, res, j, preset.controller.rate) for j, tr in enumerate(trials)]
            per_cond[key] = mets
        for p in cal.parameters:
            c = next(c for c in conds.values() if c.matches(**p.target.at()))
            st = Stat.of([m.get(p.target.metric) for m in per_cond[c.key]])
            # an unsettled trial makes the mean undefined: report nan (the fit treats it as too large)
            out[p.name] = st.mean if st.n_valid == st.n else math.nan
        return out

    t0 = time.monotonic()
    res = fit(specs, start, evaluate, rounds=cal.rounds, rtol=cal.rtol,
              progress=(lambda: bar.update(1)) if bar is not None else None)
    # sensitivity profile around the fit (one parameter at a time, the others at their fit)
    profile = {}
    for spec in specs:
        lo, hi = spec.bounds
        v = res.values[spec.name]
        pts = sorted({min(max(v * f if spec.log or v else v + f - 1.0, lo), hi) for f in (0.5, 0.71, 1.0, 1.41, 2.0)})
        prof = []
        for x in pts:
            m = evaluate({**res.values, spec.name: x})
            if bar is not None:
                bar.update(1)
            prof.append({"value": x, "metric": m[spec.name]})
        profile[spec.name] = prof
    params = []
    for p, pf in zip(cal.parameters, res.params):
        per_case = {c.name: resolve(case_preset(camp, c), p.paths, p.mode, pf.value) for c in camp.cases}
        params.append({
            "name": p.name, "description": p.description, "paths": p.paths, "mode": p.mode, "unit": p.unit,
            "bounds": list(p.bounds), "log": p.log, "preset_value": to_python(preset_values[p.name]),
            "start": pf.start, "value": pf.value, "at_bound": pf.at_bound, "applied": per_case,
            "target": {"case": camp.baseline, **p.target.at(), "metric": p.target.metric, "form": p.target.form,
                       "seed_floor": p.target.seed_floor, "seed": pf.seed_value, "seed_effective": pf.seed_effective,
                       "sim_before": pf.sim_start, "sim_after": pf.sim_value, "sim_effective": pf.sim_effective,
                       "log_residual": pf.residual},
            "profile": profile[p.name]})
    return {"campaign": camp.name, "baseline": camp.baseline, "trials": n_trials,
            "fingerprint": calibration_fingerprint(camp, n_trials),
            "method": "paired bounded 1-D root finding (brentq on log(sim/seed)), Gauss-Seidel rounds",
            "rounds": res.rounds, "converged": res.converged, "evaluations": res.evaluations,
            "wall_s": time.monotonic() - t0, "values": res.values, "parameters": params,
            "history": [{"values": v, "metrics": m} for v, m in res.history]}


def calibration_fingerprint(camp: Campaign, n_trials: int) -> str:
    """Hash of everything a baseline calibration depends on: the test, starts, the baseline
    case and its resolved preset, the calibration spec and its seed targets, the trial count.

    Parameters
    ----------
    camp : Campaign
        The campaign whose baseline is calibrated.
    n_trials : int
        Trials per evaluation.

    Returns
    -------
    str
        16 hex digits; a ``calibration.json`` is reused only under the same fingerprint.
    """
    base = camp.case(camp.baseline)
    doc = {"test": camp.test.model_dump(mode="json"), "starts": camp.starts.model_dump(mode="json"),
           "baseline": base.model_dump(mode="json"), "preset": case_preset(camp, base).model_dump(mode="json"),
           "calibration": camp.calibration.model_dump(mode="json", exclude={"trials"}),
           "targets": [camp.seed_value(camp.baseline, p.target.metric, **p.target.at())
                       for p in camp.calibration.parameters], "trials": int(n_trials)}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def source_calibration(camp: Campaign, out_dir: Path, n_trials: Optional[int] = None, bar=None) -> dict:
    """The calibration of ``calibration: {from: NAME}``: loaded from a matching ``calibration.json``
    (this output folder, then ``out_dir/../NAME/``), else fitted on NAME's baseline.

    The result's ``applied`` overrides are those of this campaign's cases; ``source`` tells
    where the values come from (``loaded_from`` is None when fitted in this run).

    Parameters
    ----------
    camp : Campaign
        The campaign whose calibration comes from another.
    out_dir : pathlib.Path
        This campaign's output folder.
    n_trials : int, optional
        Trials per evaluation (default: the campaign's, else the source's).
    bar : tqdm.tqdm, optional
        Progress bar of a fit.

    Returns
    -------
    dict
        The ``calibration.json`` content with ``reused``, ``source`` and per parameter ``applied``.
    """
    src = calibration_source(camp)
    n = int(n_trials or camp.calibration.trials or src.calibration.trials)
    fp = calibration_fingerprint(src, n)
    doc, loaded = None, None
    for path in (out_dir / "calibration.json", out_dir.parent / src.name / "calibration.json"):
        try:
            got = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if got.get("fingerprint") == fp and got.get("campaign") == src.name:
            doc, loaded = got, path
            break
    if doc is None:
        doc = calibrate(src, n, bar)
    doc = dict(doc)
    doc["reused"] = loaded is not None
    doc["source"] = {"campaign": src.name, "title": src.title, "baseline": src.baseline,
                     "baseline_label": src.case(src.baseline).label,
                     "loaded_from": str(loaded) if loaded is not None else None}
    for p in doc["parameters"]:
        spec = next(q for q in src.calibration.parameters if q.name == p["name"])
        p["applied"] = {c.name: resolve(case_preset(camp, c), spec.paths, spec.mode, p["value"]) for c in camp.cases}
    return doc

