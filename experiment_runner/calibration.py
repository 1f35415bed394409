"""Calibration of a campaign's *baseline* case, before any prediction.

A campaign file (:mod:`experiment_runner.campaign`) names a few physically meaningful
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

Examples
--------
A toy "simulation" whose metric is ``2 p``, fitted to a seed value of 3:

>>> from experiment_runner.calibration import ParamSpec, fit
>>> spec = ParamSpec(name="p", bounds=(0.1, 10.0), log=True, seed_value=3.0)
>>> res = fit([spec], {"p": 1.0}, lambda v: {"p": 2.0 * v["p"]})
>>> round(res.values["p"], 4), res.params[0].at_bound
(1.5, None)
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Optional

from scipy.optimize import brentq

from experiment_runner.metrics import finite_or_none

__all__ = ["ParamSpec", "ParamFit", "CalibrationResult", "fit"]

_CLIP = 20.0      # |log ratio| used for a metric that is 0, nan or not reached


@dataclass(frozen=True)
class ParamSpec:
    """One parameter and the target it is fitted to (see module docstring)."""
    name: str
    bounds: tuple[float, float]
    seed_value: float                 # the seed's baseline number (SI)
    log: bool = False                 # search in log(p)
    form: str = "absolute"            # "absolute" | "quadrature_excess"
    seed_floor: float = 0.0           # quadrature_excess: deterministic floor of the seed value
    null: Optional[float] = None      # quadrature_excess: parameter value that removes the effect


@dataclass
class ParamFit:
    """Result for one parameter."""
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
    values: dict
    params: list
    evaluations: int
    rounds: int
    converged: bool
    history: list = field(default_factory=list)   # (values, metrics) of every evaluation

    def to_dict(self) -> dict:
        return {"values": dict(self.values), "params": [asdict(p) for p in self.params],
                "evaluations": self.evaluations, "rounds": self.rounds, "converged": self.converged}


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
