"""The last stages: the improved model against the nominal on the held-out data, and the report.

:func:`validate` measures both models on the held-out samples (closed-loop replay against the
run-to-run floor -- the headline stdout and ``report.md`` lead with -- force residual, open-loop
windows); :func:`assemble` writes the report dict (fields documented in :mod:`.report`), with a
SINDy-style regression of what an inadequate final model leaves (:func:`sparse_terms`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .context import Context
from .fit import sparse_regression
from .locate import lowpass
from .observer import ObsResult
from .predict import band_rms, compare_replay, open_loop_windows, replay
from .selection import Path, Problem
from .stages import Prediction, Setup
from .units import axis_units, convert_units

__all__ = ["Validation", "Run", "validate", "assemble", "sparse_terms", "plot_arrays"]


@dataclass
class Validation:
    """What :func:`validate` leaves."""
    held: np.ndarray
    """The held-out samples (the fit samples when none are held out)."""
    residual: ObsResult
    """The improved model's force residual."""
    improved_replay: dict
    """The improved model's closed-loop replay (for the plots)."""
    adequate_nominal: bool
    adequate: bool
    """The improved model's replay is stable and consistent with its run-to-run floor."""
    headline: dict
    """The report's ``replay``."""
    figures: dict
    """The report's ``validation``."""


def _how(data, judge) -> str:
    if not data.open_loop:
        return ("noise-free closed-loop replay of the held-out samples (recorded reference, the model's controller) "
                "against the recorded command and measurement; floor: RMS difference of simulated recordings of "
                "the same model from its replay (run to run)")
    return (f"noise-free open-loop prediction of the held-out samples over {judge.L / data.rate:.3g} s windows, each "
            "re-initialised from the measurement (the recorded command and known force drive the model), against "
            "the measurement; floor: RMS difference of the same windows simulated with the model's noise (run to "
            "run); the command is the input (its error is 0)")


def _fall(a, b):
    return float(1 - b / a) if a and a > 0 else None


def validate(setup: Setup, pred: Prediction, problem: Problem, path: Path, opt) -> Validation:
    """The improved model (``path.current``) against the nominal on the held-out data: replay (each
    model against its own run-to-run floor), force residual (each against its own floor), open-loop
    windows."""
    data, obs, judge = setup.data, setup.observer, pred.judge
    current, force_floor, floor_new, floor_nom = path.current, path.floor, path.replay_floor, pred.replay_floor
    held = data.held if data.held.any() else data.fit
    res_new = obs.run(current, snap_every=setup.window)
    r_nom_band = band_rms(pred.residual.r, held, data.rate, setup.band_hz)
    r_new_band = band_rms(res_new.r, held, data.rate, setup.band_hz)
    sim_b = force_floor.sim_b
    floor_band = band_rms(force_floor.res_b.r, sim_b.held if sim_b.held.any() else sim_b.fit, data.rate, setup.band_hz)
    J_nom_held = pred.floor.noise.ms(pred.residual.r, held)         # each model against its own floor
    J_new_held = problem.evaluator.floor.ms(res_new.r, held)
    rp_improved = replay(current, data, seed=opt.floor_seeds[0] + 7)
    # the judge's replay (noise-free, held-out trials) and the run-to-run floor of each model
    replay_nom, replay_new = floor_nom.replay, floor_new.replay
    u_nom, y_nom = judge.rms(replay_nom)
    u_new, y_new = judge.rms(replay_new)
    u_floor, y_floor = floor_new.sigma_u, floor_new.sigma_y
    z_nom = judge.consistency(replay_nom, floor_nom)
    z_new = judge.consistency(replay_new, floor_new)
    headline = {
        "command_rms_N": {"nominal": u_nom, "improved": u_new, "floor_nominal": floor_nom.sigma_u, "floor": u_floor},
        "position_rms_m": {"nominal": y_nom, "improved": y_new, "floor_nominal": floor_nom.sigma_y, "floor": y_floor},
        "floor_ratio": {"nominal": judge.floor_ratio(replay_nom, floor_nom), "improved": judge.floor_ratio(replay_new, floor_new)},
        "consistency_z": {"nominal": z_nom, "improved": z_new, "critical": judge.t_q},
        "stable": {"nominal": replay_nom.ok, "improved": replay_new.ok},
        "held_out_trials": [int(data.trial_ids[c]) for c in judge.cols], "held_out_samples": judge.n,
        "floor_recordings": judge.K, "replays": judge.sims,
        "reference": "none (open-loop record)" if data.open_loop else (
            "recorded" if pred.reference is None else "equivalent (controller mismatch)"),
        "controller_check_rel": pred.controller_error,
        "how": _how(data, judge)}
    windows_new = open_loop_windows(current, obs, res_new, setup.window)

    def drift_rms(o):
        if o is None:
            return None
        sel = np.array([held[o["start"][i], o["trial"][i]] for i in range(len(o["start"]))])
        return float(np.sqrt(np.mean(o["drift_m"][sel] ** 2))) if sel.any() else None

    figures = {
        "held_out_samples": int(held.sum()),
        "force_residual_rms_N": {"nominal": r_nom_band, "improved": r_new_band, "floor": floor_band,
                                 "fall": _fall(r_nom_band, r_new_band)},
        "J_held": {"nominal": J_nom_held, "improved": J_new_held, "fall": _fall(J_nom_held, J_new_held)},
        "replay_command_rms_N": {"nominal": u_nom, "improved": u_new, "run_to_run": u_floor,
                                 "fall": _fall(u_nom, u_new)},
        "replay_position_rms_m": {"nominal": y_nom, "improved": y_new, "run_to_run": y_floor,
                                  "fall": _fall(y_nom, y_new)},
        "open_loop_drift_rms_m": {"nominal": drift_rms(pred.windows), "improved": drift_rms(windows_new),
                                  "window_s": setup.window / data.rate},
    }
    return Validation(held=held, residual=res_new, improved_replay=rp_improved,
                      adequate_nominal=bool(replay_nom.ok and z_nom <= judge.t_q),
                      adequate=bool(replay_new.ok and z_new <= judge.t_q), headline=headline, figures=figures)


def sparse_terms(data, res: ObsResult, ctx: Context, f_band: float) -> dict:
    """SINDy-style regression of the remaining (band-limited) force residual ``res`` on state functions
    (:func:`.fit.sparse_regression`)."""
    mask = data.fit | data.held
    rl = lowpass(res.r, mask, data.rate, f_band)
    x, v = res.x, data.vs
    acc = lowpass(np.gradient(data.vs, axis=0) * data.rate, data.valid, data.rate, f_band)
    xc, xs = ctx.x_center, max(ctx.x_half_span, 1e-12)
    vmax = max(ctx.v_max, 1e-12)
    xi = (x - xc) / xs
    feats = {"1": np.ones_like(x), "v": v, "sign(v)": np.tanh(v / (0.01 * vmax)), "v|v|": v * np.abs(v),
             "|v|": np.abs(v), "|phi_f|": np.abs(res.phi),
             "x": xi, "x^2": xi ** 2, "a": acc, "u": data.u, "phi_f": res.phi, "phi_f*x": res.phi * xi,
             "phi_f*x^2": res.phi * xi ** 2}
    per = (ctx.ripple_period or [None])[0]
    if per:
        feats[f"sin(2pi x/{per:.3g})"] = np.sin(2 * np.pi * x / per)
        feats[f"cos(2pi x/{per:.3g})"] = np.cos(2 * np.pi * x / per)
    target = rl[mask]
    out = sparse_regression({k: lowpass(f_, mask, data.rate, f_band)[mask] for k, f_ in feats.items()}, target)
    out["units"] = "missing table force [N] = sum coef * term; x normalised: (x - x_center)/x_half_span"
    out["x_center_m"], out["x_half_span_m"] = xc, xs
    return out


@dataclass
class Run:
    """Everything the report is written from (one diagnosis' stages)."""
    nominal_source: object
    setup: Setup
    stochastic: dict
    prediction: Prediction
    locate_summary: dict
    problem: Problem
    path: Path
    found: list
    joint: dict | None
    J_fit_nominal: float
    J_held_nominal: float
    adequacy_tolerance: float
    validation: Validation


def assemble(run: Run, timing: dict, sparse: dict | None) -> dict:
    """The report dict (fields documented in :mod:`.report`); units on the stage's axis."""
    setup, pred, problem, path, val = run.setup, run.prediction, run.problem, run.path, run.validation
    data, spec0, obs, ev = setup.data, setup.nominal, setup.observer, problem.evaluator
    if not run.found:
        verdict = "model adequate" if val.adequate_nominal else "unexplained residual"
    else:
        verdict = "effects found" if val.adequate else "effects found, residual remains"
    olw = pred.windows
    kind = spec0.preset.stage.kind
    report = {
        "nanostage_diagnosis": 1,
        "verdict": verdict,
        "units": axis_units(kind),
        "replay": val.headline,
        "found": run.found,
        "recording": {"source": data.source, "rate_hz": data.rate, "trials": int(data.shape[1]),
                      "open_loop": data.open_loop, "axis": data.axis,
                      "samples": int(data.valid.sum()), "duration_s": float(data.valid.sum() / data.rate),
                      "split": data.split, "fit_trials": [int(data.trial_ids[c]) for c in ev.fit_cols],
                      "held_out_trials": [int(data.trial_ids[c]) for c in ev.held_cols], "notes": setup.notes},
        "nominal": {"name": spec0.preset.name,
                    "source": str(run.nominal_source) if not isinstance(run.nominal_source, (dict,)) else "<mapping>"},
        "observer": {"bandwidth_hz": obs.f_o, "smoothing_hz": data.smooth_hz, "band_hz": setup.band_hz,
                     "evaluations": ev.evals, "evaluation_s": ev.seconds},
        "noise": {"floor_check_J": pred.floor.check_ms, "n_eff_held": problem.n_eff,
                  "adequacy_tolerance": run.adequacy_tolerance},
        "predict": {
            "closed_loop_replay": compare_replay(data, setup.nominal_replay),
            "force_residual": {"rms_N": band_rms(pred.residual.r, data.fit | data.held, data.rate, setup.band_hz),
                               "floor_rms_N": run.locate_summary["floor_rms_N"], "J_fit": run.J_fit_nominal,
                               "J_held": run.J_held_nominal, "observer_failures": pred.residual.bad},
            "open_loop_windows": None if olw is None else {
                "window_s": setup.window / data.rate, "windows": int(len(olw["start"])),
                "rms_drift_m": float(np.sqrt(np.mean(olw["drift_m"] ** 2))),
                "rms_force_N": float(np.sqrt(np.mean(olw["force_N"] ** 2)))},
        },
        "locate": run.locate_summary,
        "selection": {"steps": path.steps, "J_held_start": problem.J_held_base, "J_held_final": path.J_held,
                      "adequate_final": val.adequate, "second_start": path.second_start},
        "joint_fit": run.joint,
        "stochastic": run.stochastic,
        "sparse_regression": sparse,
        "validation": val.figures,
        "improved_model": {"name": path.current.preset.name},
        "timing_s": timing,
    }
    convert_units(report, kind)       # every parameter unit on the axis of the stage (rotary: rad, N·m, kg·m²)
    return report


def plot_arrays(run: Run, loc_arrays: dict) -> dict:
    """The arrays :func:`.report.write_report` plots."""
    setup, val = run.setup, run.validation
    return {"res_nom": run.prediction.residual, "res_new": val.residual, "loc": loc_arrays,
            "rp_nom": setup.nominal_replay, "rp_new": val.improved_replay, "held": val.held, "f_band": setup.band_hz,
            "floor": run.path.floor}

