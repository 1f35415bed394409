"""The stages after the forward selection: the adopted effects fitted jointly, then the drive-noise
level (a stochastic effect, decided by the replay's run-to-run consistency).

Both change the final model of the selection's :class:`.selection.Path` in place (its ``current``
model, force-residual J and floors) and the report's rows ``found``.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from .effects.stochastic import NoiseLevel
from .fit import FitResult
from .floors import ForceFloor
from .joint import joint_fit
from .noise import SPREAD_MAX, fit_noise_level, noise_components
from .observer import Observer
from .openloop import MISSING_LP
from .selection import Path, Problem, for_fits_on

__all__ = ["refit_jointly", "drive_noise"]


def _confounded_pairs(jf: FitResult) -> list:
    """Parameters of different effects of the joint fit ``jf`` correlated beyond 0.95."""
    pairs = []
    if jf.corr is not None:
        for i in range(len(jf.names)):
            for j in range(i + 1, len(jf.names)):
                if jf.names[i].split(".")[0] != jf.names[j].split(".")[0] and abs(jf.corr[i, j]) > 0.95:
                    pairs.append([jf.names[i], jf.names[j], float(jf.corr[i, j])])
    return pairs


def refit_jointly(problem: Problem, path: Path, found: list) -> dict | None:
    """The adopted deterministic effects fitted together by the force observer; used (the model and
    the report's rows take its values, as the YAML does) if the replay is not worse, no parameter is at
    its bound and no two effects' parameters are confounded. Returns the report's ``joint_fit`` (None
    with fewer than two adopted deterministic effects, or when the fit fails).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    found : list of dict
        The report's rows of the adopted effects (changed in place).

    Returns
    -------
    dict or None
    """
    opt, judge, base, ev = problem.options, problem.judge, problem.base, problem.evaluator
    selected = path.selected
    if len([f for f in selected if f.effect.kind == "deterministic"]) < 2:
        return None
    try:
        jf = joint_fit(selected, base, ev, for_fits_on(path.context, selected))
    except Exception as err:   # noqa: BLE001
        opt.log(f"joint fit failed: {err!r}")
        return None
    if jf is None:
        return None
    floor = path.replay_floor
    D_cur = judge.D(floor.replay, floor)
    rpj = judge.replay(jf.spec)
    D_j = judge.D(rpj, floor) if rpj.ok else float("inf")
    joint = {"effects": jf.key, "J_fit": jf.J_fit, "J_held": jf.J_held, "params": jf.params(),
             "correlation": jf.corr.tolist() if jf.corr is not None else None,
             "replay_D": D_j, "replay_D_stepwise": D_cur, "on_bound": jf.on_bound, "used": False}
    conf_pairs = _confounded_pairs(jf)
    joint["confounded_parameters"] = conf_pairs
    joint["used"] = bool(D_j <= D_cur and not jf.on_bound and not conf_pairs)
    if joint["used"]:
        path.current = jf.spec
        for fe in found:
            if fe["kind"] != "deterministic":
                continue
            fe["params_step"] = fe["params"]
            fe["params"] = [dict(p, name=p["name"].split(".", 1)[1]) for p in jf.params()
                            if p["name"].split(".")[0] == fe["effect"]]
            fe["derived"] = next(f for f in selected if f.key == fe["effect"]).effect.derived(
                base, [p["value"] for p in fe["params"]])
        path.J_held = ev.J(path.current, "held")
        path.replay_floor = judge.floor(path.current)
    return joint


def _level_at_floor(problem: Problem, current, s0: float):
    """Open-loop records: the drive-noise level at which the fit samples' prewhitened window errors
    are at the model's own run-to-run floor (floor ratio 1; Brent's method on the log level, 1 %
    tolerance) and its standard error (the data's D is one draw: its relative spread over the
    floor's simulated recordings, halved, D falling as the level squared); (None, None) when 1/10
    to 1000x the current level ``s0`` does not bracket it."""
    fj = problem.fit_judge
    e = NoiseLevel()

    def g(log_s):
        fl = fj.floor(e.apply(current, [math.exp(log_s)]))
        return math.log(fj.floor_ratio(fl.replay, fl))

    a, b = math.log(0.1 * s0), math.log(1000.0 * s0)
    try:
        ga, gb = g(a), g(b)
        if not (ga > 0 > gb):
            return None, None
        sig = math.exp(brentq(g, a, b, xtol=0.01))
        fl = fj.floor(e.apply(current, [sig]))
        Dk = fj.sim_blocks(fl.replay, fl).sum(axis=1)
        return sig, sig * 0.5 * float(np.std(Dk, ddof=1) / np.mean(Dk))
    except Exception:     # noqa: BLE001 - no estimate: the spectrum's stands
        return None, None


def _proposed_level(problem: Problem, path: Path, ninfo: dict):
    """The drive-noise level proposed from the force residual's spectrum where drive noise dominates
    (``(sigma, standard error, consistent)``; sigma None: none proposed); ``ninfo`` gets the estimate."""
    data, obs, opt = problem.data, problem.observer, problem.options
    comps = noise_components(path.current, data, lambda d: Observer(d, bandwidth=obs.f_o, smooth_hz=data.smooth_hz),
                             seeds=tuple(opt.floor_seeds[0] + 11 + i for i in range(4)))
    r_cur = obs.run(path.current).r
    # an open-loop record's simulated recordings carry the data's own residual below
    # MISSING_LP x f_o as a known force (openloop.sim_batch): there their residual is not the
    # data's, and the level is read above it only
    f_min = 2.0 * MISSING_LP * obs.f_o if data.open_loop else 0.0
    est = fit_noise_level(r_cur, data.fit, data.rate, comps, f_max=0.75 * obs.f_o, f_min=f_min)
    ninfo.update({k: v for k, v in est.items() if k != "ok"})
    if not est.get("ok"):
        return None, None, False
    s0 = path.current.preset.stage.drive.noise_current_rms
    sig = est["sigma"]
    consistent = est.get("spread", 1.0) < SPREAD_MAX
    if not consistent and data.open_loop and s0 > 0 and problem.fit_judge is not None:
        # the bands disagree (few of them above the open-loop records' known-force band): the level at
        # which the fit samples' prewhitened windows are at the model's own floor, adopted in their
        # place only if it lies inside the bands' range
        sig_w, unc_w = _level_at_floor(problem, path.current, s0)
        lo, hi = (s0 * math.sqrt(max(min(est["group_ratios"]), 0.0)), s0 * math.sqrt(max(est["group_ratios"])))
        ninfo["windows_sigma"] = sig_w
        if sig_w is not None and lo <= sig_w <= hi:
            sig, consistent = sig_w, True
            ninfo.update(sigma=sig, sigma_unc=unc_w)
            est["sigma_unc"] = unc_w
            ninfo["how"] = f"open-loop windows at their floor (the residual spectrum's bands disagree: {lo:.3g}-{hi:.3g} A)"
    return sig, est.get("sigma_unc"), consistent


def drive_noise(problem: Problem, path: Path, found: list, stochastic: dict) -> None:
    """The drive-noise level proposed from the residual spectrum and decided by the replay: adopted
    only if the data's replay error is inconsistent with the current model's run-to-run floor (a
    calibrated z-score over its simulated recordings) and consistent with the candidate's (a
    deterministic remnant the effects left also makes the replay inconsistent: a noise level is
    adopted only if it makes the data consistent with the model's own recordings).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    found : list of dict
        The report's rows of the adopted effects (changed in place).
    stochastic : dict
        The report's stochastic-effects section (changed in place).
    """
    opt, data, obs, judge, ev = problem.options, problem.data, problem.observer, problem.judge, problem.evaluator
    ninfo = {"nominal_A": problem.base.preset.stage.drive.noise_current_rms, "found": False}
    try:
        s0 = path.current.preset.stage.drive.noise_current_rms
        sig, sig_unc, consistent = _proposed_level(problem, path, ninfo)
        if sig is not None:
            ratio = sig / s0 if s0 > 0 else float("inf")
            ninfo["ratio"] = ratio if s0 > 0 else None
            ninfo["consistent"] = consistent
            if not (0.8 <= ratio <= 1.25) and consistent:
                cand = NoiseLevel().apply(path.current, [sig])
                floor2 = judge.floor(cand)
                z_old = judge.consistency(path.replay_floor.replay, path.replay_floor)
                z_new = judge.consistency(path.replay_floor.replay, floor2, norm=path.replay_floor)
                ninfo.update({"replay_z_before": z_old, "replay_z_after": z_new, "z_critical": judge.t_q})
                if abs(z_old) > judge.t_q and abs(z_new) < abs(z_old) - judge.t_q and abs(z_new) <= judge.t_q:
                    ninfo["found"] = True
                    found.append({"effect": "noise_level", "title": NoiseLevel.title, "kind": "stochastic",
                                  "step": len(path.steps) + 1,
                                  "params": [{"name": "noise_current_rms", "unit": "A", "value": sig,
                                              "sigma": sig_unc, "nominal": s0}],
                                  "derived": {}, "expressible": True, "confounded_with": [],
                                  "held_out": {"metric": "|z| of the replay error among the model's simulated "
                                                         "recordings (run-to-run consistency)",
                                               "nominal": abs(z_old), "improved": abs(z_new)}})
                    path.current = cand
                    path.floor = ForceFloor(cand, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
                    ev.floor = path.floor.noise
                    path.J_held = ev.J(path.current, "held")
                    path.replay_floor = floor2
    except Exception as err:   # noqa: BLE001
        ninfo["error"] = repr(err)
    stochastic["noise_level"] = ninfo
