"""The last stages: the improved model against the nominal on the held-out data, and the report.

:func:`validate` measures both models on the held-out samples (closed-loop replay against the
run-to-run floor -- the headline stdout and ``report.md`` lead with -- force residual, open-loop
windows); :func:`assemble` writes the report dict (fields documented in :mod:`.report`), with a
SINDy-style regression of what an inadequate final model leaves (:func:`sparse_terms`).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from msg_defs.topics import COMMAND_KINDS

from .adoption import renew_floor
from .context import Context
from .effects.stochastic import NoiseLevel
from .fit import sparse_regression
from .joint import spec_with
from .locate import by_regime, lowpass, regimes
from .observer import ObsResult
from .openloop import TINY_MOTION_STEPS, least_squares_check
from .predict import band_rms, compare_replay, open_loop_windows, replay
from .selection import Path, Problem, for_fits_on, identification
from .stages import Prediction, Setup
from .units import axis_units, convert_units

__all__ = ["Validation", "Run", "validate", "assemble", "sparse_terms", "plot_arrays", "withdraw_unidentified"]


def withdraw_unidentified(problem: Problem, path: Path, found: list) -> list:
    """The adopted deterministic effects checked with their final values and standard errors (after
    the joint fit and :func:`.uncertainty.widen`): one not identified (:func:`.selection.identification`:
    at or within its own standard error of a bound, outside its plausible range, or every standard
    error above its value) is withdrawn from the final model, which is rebuilt without it (the
    drive-noise level kept) and its floors renewed. A parameter whose standard error exceeds its
    value in an effect identified by its others is marked ``identified: false``. Returns the report's
    rows of the withdrawn effects (``why``).

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
    list of dict
    """
    gone = []
    axis = problem.data.axis
    for f in [s for s in path.selected if s.effect.kind == "deterministic"]:
        row = next((fe for fe in path.found if fe["effect"] == f.key and fe.get("kind") == "deterministic"), None)
        if row is None:
            continue
        names = [p["name"] for p in row["params"]]
        vals = [p["value"] for p in row["params"]]
        sig = [np.nan if p.get("sigma") is None else p["sigma"] for p in row["params"]]
        others = [s for s in path.selected if s is not f]
        try:
            ps = f.effect.params(spec_with(others, problem.base), for_fits_on(path.context, others))
        except Exception:     # noqa: BLE001 - no bounds: the plausible ranges and standard errors decide
            ps = None
        if ps is not None and len(ps) != len(names):
            ps = None
        why, weak = identification(names, vals, sig, ps, {p.name: p for p in f.effect.parameters}, axis)
        for p in row["params"]:
            p["identified"] = p["name"] not in weak
        if why is None:
            continue
        path.selected.remove(f)
        path.found.remove(row)
        if row in found:
            found.remove(row)
        gone.append({"effect": row["effect"], "title": row["title"], "step": row["step"], "params": row["params"],
                     "why": f"not identified with its final standard errors: {why}"})
        problem.options.log(f"withdrawn: {row['effect']} ({why})")
    if gone:
        # the others at their final values (the report's rows: the joint fit's where it was used)
        final = {fe["effect"]: [p["value"] for p in fe["params"]] for fe in path.found}
        path.selected = [dataclasses.replace(f, theta=np.asarray(final[f.key], float))
                         if f.effect.kind == "deterministic" and len(final.get(f.key, ())) == len(f.theta) else f
                         for f in path.selected]
        spec = spec_with(path.selected, problem.base)
        for fe in found:
            if fe["effect"] == "noise_level":
                spec = NoiseLevel().apply(spec, [fe["params"][0]["value"]])
        path.current = spec
        renew_floor(problem, path, spec)
    return gone


@dataclass
class Validation:
    """What :func:`validate` leaves.

    Parameters
    ----------
    held : numpy.ndarray
        The held-out samples (the fit samples when none are held out).
    residual : ObsResult
        The improved model's force residual.
    improved_replay : dict
        The improved model's closed-loop replay (for the plots).
    adequate_nominal : bool
        The nominal's replay is consistent with its own run-to-run floor.
    adequate : bool
        The improved model's replay is stable and consistent with its run-to-run floor.
    headline : dict
        The report's ``replay``.
    figures : dict
        The report's ``validation``.
    """
    held: np.ndarray
    residual: ObsResult
    improved_replay: dict
    adequate_nominal: bool
    adequate: bool
    headline: dict
    figures: dict


def _predictor(data, judge) -> str:
    """How the held-out samples were predicted, in a few words (stdout and report.md say it)."""
    if not data.open_loop:
        return "closed-loop replay"
    if getattr(judge, "whole", False):
        return ("whole trials from their start, quantized like the sensor (tiny motion: at most "
                f"{TINY_MOTION_STEPS} encoder steps)")
    return f"{judge.L / data.rate * 1e3:.3g} ms windows re-initialised from the measurement"


def _how(data, judge) -> str:
    if getattr(judge, "whole", False):
        return ("noise-free open-loop prediction of the held-out samples, each trial run whole from the "
                "observer's start state and quantized like the sensor (tiny motion), against the measurement; "
                "floor: RMS difference of the same predictions of recordings simulated with the model's noise "
                "(run to run), not prewhitened; the command is the input (its error is 0)")
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
    windows.

    Parameters
    ----------
    setup : Setup
        The read data, nominal and observer.
    pred : Prediction
        The nominal's prediction.
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    opt : Options
        The diagnosis's options.

    Returns
    -------
    Validation
    """
    data, obs, judge = setup.data, setup.observer, pred.judge
    current, force_floor, floor_new = path.current, path.floor, path.replay_floor
    floor_nom = pred.nominal_replay_floor or pred.replay_floor      # the nominal's own, before any prior
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
        "predictor": _predictor(data, judge),
        "how": _how(data, judge)}
    windows_new = open_loop_windows(current, obs, res_new, setup.window)
    figures_explained = []

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
    figures_explained += explain_figures(data, pred.residual, res_new, held, setup.band_hz, figures)
    figures["disagreements"] = figures_explained
    return Validation(held=held, residual=res_new, improved_replay=rp_improved,
                      adequate_nominal=bool(replay_nom.ok and z_nom <= judge.t_q),
                      adequate=bool(replay_new.ok and z_new <= judge.t_q), headline=headline, figures=figures)


def explain_figures(data, res_nom: ObsResult, res_new: ObsResult, held: np.ndarray, f_band: float,
                    figures: dict) -> list:
    """Sentences explaining held-out figures that disagree (one better by more than 5 %, another worse
    by more than 5 %): where the force residual rose -- by regime of the reference and below/above a
    tenth of its band -- beside the replay's change, and which figure decides.

    Parameters
    ----------
    data : DiagData
        The recording.
    res_nom, res_new : ObsResult
        Force observer of the nominal and the improved model.
    held : numpy.ndarray
        (T, B) bool: held-out samples.
    f_band : float
        Band of the residual [Hz].
    figures : dict
        Held-out figure -> (nominal, improved).

    Returns
    -------
    list of str
    """
    falls = {k: figures[k]["fall"] for k in ("force_residual_rms_N", "replay_command_rms_N", "replay_position_rms_m")
             if figures.get(k) and figures[k].get("fall") is not None}
    better = [k for k, f in falls.items() if f > 0.05]
    worse = [k for k, f in falls.items() if f < -0.05]
    if not better or not worse:
        return []
    name = {"force_residual_rms_N": "the held-out force residual", "replay_command_rms_N": "the replay's command error",
            "replay_position_rms_m": "the replay's position error"}
    lab = regimes(data.x_ref, data.v_ref, data.valid, data.rate)
    rn, ri = lowpass(res_nom.r, held, data.rate, f_band), lowpass(res_new.r, held, data.rate, f_band)
    low_n, low_i = lowpass(res_nom.r, held, data.rate, f_band / 10), lowpass(res_new.r, held, data.rate, f_band / 10)
    parts = [(gi["rms_N"] - gn["rms_N"], f"{gn['regime']} {gn['rms_N']:.3g} -> {gi['rms_N']:.3g} N")
             for gn, gi in zip(by_regime(rn, held, lab, min_samples=10), by_regime(ri, held, lab, min_samples=10))]
    parts.sort(key=lambda t: -t[0])
    lo = (float(np.sqrt(np.mean(low_n[held] ** 2))), float(np.sqrt(np.mean(low_i[held] ** 2))))
    hi = (float(np.sqrt(np.mean((rn - low_n)[held] ** 2))), float(np.sqrt(np.mean((ri - low_i)[held] ** 2))))
    out = [(", ".join(f"{name[k]} {100 * falls[k]:+.0f} % better" for k in better) + "; "
            + ", ".join(f"{name[k]} {-100 * falls[k]:.0f} % worse" for k in worse) + ".")]
    if "force_residual_rms_N" in worse:
        out.append("The force residual is the force the force observer adds for the model to follow the measured "
                   f"position (band-limited to {f_band:.4g} Hz); it rose by regime: "
                   + "; ".join(t for _, t in parts[:3])
                   + f"; below {f_band / 10:.3g} Hz {lo[0]:.3g} -> {lo[1]:.3g} N, above {hi[0]:.3g} -> {hi[1]:.3g} N. "
                   "The replay is the closed loop's answer to the recorded reference: an effect that brings the "
                   "loop's response to the data can leave or add force the loop does not pass to the command and "
                   "position (above its bandwidth, or where friction holds the stage). The replay decides what is "
                   "adopted; where the force residual rose is what the improved model still misses there.")
    else:
        out.append("The replay rose where the force residual fell: the adopted effects explain force the observer "
                   "sees but the closed loop does not reproduce it as recorded; the replay decides.")
    return out


def model_changes(nominal, improved, applied: list) -> list:
    """Every preset field the improved model changes from the nominal ``{field, nominal, improved, by}``
    (``by``: the keys of the adopted effects whose model change moves it, ``applied`` = [(effect,
    values)] applied in turn on ``nominal`` with their final values; ``[]`` for a change none makes).
    Nothing moves silently: a field an effect moves besides the parameter it names (a static force
    scaled with the Coulomb level) is listed with it.

    Parameters
    ----------
    nominal, improved : stage_sim.config.Preset
        The two models.
    applied : list of tuple
        ``(effect, values)`` applied in turn on ``nominal``.

    Returns
    -------
    list of dict
    """
    def flat(d, pre=""):
        out = {}
        if isinstance(d, dict):
            for k, v in d.items():
                out.update(flat(v, f"{pre}{k}."))
        elif isinstance(d, list) and all(isinstance(v, dict) for v in d):     # [] of a list of dicts: none
            for i, v in enumerate(d):
                out.update(flat(v, f"{pre}{i}."))
        else:
            out[pre[:-1]] = d
        return out
    a, b = flat(nominal.preset.model_dump(mode="json")), flat(improved.preset.model_dump(mode="json"))
    by: dict = {}
    spec = nominal
    for eff, values in applied:
        try:
            nxt = eff.apply(spec, values)
        except Exception:     # noqa: BLE001 - not attributable
            continue
        fa, fb = flat(spec.preset.model_dump(mode="json")), flat(nxt.preset.model_dump(mode="json"))
        for k in set(fa) | set(fb):
            if fa.get(k) != fb.get(k):
                by.setdefault(k, []).append(eff.key)
        spec = nxt
    out = []
    for k in sorted(set(a) | set(b)):
        if k == "name" or a.get(k) == b.get(k):
            continue
        if isinstance(a.get(k), float) and isinstance(b.get(k), float) and \
                abs(a[k] - b[k]) <= 1e-12 * max(abs(a[k]), abs(b[k])):
            continue
        out.append({"field": k, "nominal": a.get(k), "improved": b.get(k), "by": by.get(k, [])})
    return out


def detection_limits(problem: Problem, path: Path) -> list:
    """What the record could have revealed on top of the final model: for every candidate effect not
    adopted, the smallest change of its size parameter the adoption test would pass in half the
    recordings (a truth of that size replayed exactly, its noise as the final model's).

    From one small instance of the effect (:meth:`.effects.base.Effect.probe`; one sample more for
    the whole-sample delay): its replay change ``d`` from the final model's, in floor units over the
    held-out samples, and the final model's simulated recordings' errors ``e_k``. A truth of size
    ``delta`` moves the replay by ``(delta / h) d`` (linearised) and passes the test when its
    squared norm exceeds the Student quantile ``t`` times the spread of ``e_k . d`` over the
    recordings: ``delta_50 = |h| t sd_k(e_k . d) / |d|^2``. Rows: effect, parameter, unit, the
    model's value, ``smallest_change`` (absolute; ``relative`` to the value where it is not 0).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.

    Returns
    -------
    list of dict
    """
    judge, lib = problem.judge, problem.library
    fl = path.replay_floor
    rp0 = fl.replay
    if not rp0.ok or not judge.n:
        return []
    E = judge.sim_residuals(rp0, fl)
    spec = path.current
    taken = {f.key for f in path.selected}
    ctx = for_fits_on(path.context, path.selected)
    out = []
    for k in problem.keys:
        e = lib[k]
        if k in taken or e.kind not in ("deterministic", "integer") or e.applicable(spec) is not None or (
                e.in_drive and problem.data.command_kind == "measured"):
            continue
        try:
            ps = e.params(spec, ctx)
            if e.kind == "integer":
                v0 = e.nominal(spec).get(ps[0].name)
                pr = None if v0 is None else ([v0 + 1 if v0 + 1 <= ps[0].hi else v0 - 1], 0)
            else:
                pr = e.probe(spec, ctx)
            if pr is None:
                continue
            theta, i = pr
            v0 = e.nominal(spec).get(ps[i].name, 0.0)
            h = float(theta[i]) - float(v0)
            rp = judge.replay(e.apply(spec, theta))
        except Exception:     # noqa: BLE001 - no limit for this one
            continue
        if not rp.ok or h == 0:
            continue
        d = judge.difference(rp, rp0, fl)
        n2 = float(d @ d)
        if not n2 > 0:
            continue
        sd = float(np.std(E @ d, ddof=1))
        lim = abs(h) * judge.t_q * sd / n2
        out.append({"effect": k, "title": e.title, "parameter": ps[i].name, "unit": ps[i].unit, "model_value": v0,
                    "smallest_change": lim, "relative": lim / abs(v0) if v0 else None,
                    "probe_change": h, "probe_replay_D": n2 / judge.n})
    return out


def findings(run: Run, verdict: str) -> list:
    """Every finding with its status: ``identified``, ``confounded with X`` (the rule that chose in
    ``chosen_by``), ``not identified`` (withdrawn, why), ``located, not explained`` (what the final
    model leaves beyond its floor, where), or ``nothing found`` with what the record could have
    revealed (:func:`detection_limits`).

    Parameters
    ----------
    run : Run
        The diagnosis's stages.
    verdict : str
        The diagnosis's verdict.

    Returns
    -------
    list of dict
    """
    out = []
    for fe in run.found:
        row = {"finding": fe["title"], "effect": fe["effect"], "status": fe["status"]}
        weak = [p["name"] for p in fe["params"] if p.get("identified") is False]
        if weak:
            row["not_determined"] = weak
        if fe.get("chosen_by") and fe.get("alternatives"):
            row["chosen_by"] = fe["chosen_by"]
        out.append(row)
    for w in run.withdrawn:
        out.append({"finding": w["title"], "effect": w["effect"], "status": "not identified", "why": w["why"]})
    val = run.validation
    if not val.adequate:
        rem = run.remaining or {}
        where = {}
        regs = sorted(rem.get("regimes") or [], key=lambda r: -r["excess_share"])
        if regs:
            where["regime"] = {k: regs[0][k] for k in ("regime", "excess_share", "rms_N", "floor_rms_N")}
        bands = sorted(rem.get("bands") or [], key=lambda b: -b["excess_share"])
        if bands:
            where["band_hz"] = [bands[0]["f_lo_hz"], bands[0]["f_hi_hz"]]
            where["band_excess_share"] = bands[0]["excess_share"]
        if rem.get("peaks"):
            where["peaks_hz"] = [p["f_hz"] for p in rem["peaks"][:3]]
        out.append({"finding": "residual beyond the run-to-run floor "
                               f"({val.headline['floor_ratio']['improved']:.3g}x)",
                    "status": "located, not explained", "where": where})
    elif not run.found:
        out.append({"finding": "nothing beyond the run-to-run floor", "status": "model adequate",
                    "could_have_revealed": run.detection or []})
    return out


def improved_name(spec, nominal, found: list):
    """``spec`` named for what it is: the nominal's name ``+`` the keys of the effects found (the
    nominal's own name where none was).

    Parameters
    ----------
    spec : ModelSpec
        The improved model.
    nominal : ModelSpec
        The nominal.
    found : list of dict
        The report's rows of the adopted effects.

    Returns
    -------
    ModelSpec
    """
    if not found:
        return spec
    return spec.with_changes({"name": nominal.preset.name + "+" + "+".join(fe["effect"] for fe in found)})


def status_of(row: dict) -> str:
    """A finding's status: ``identified``, or ``confounded with X`` when candidates the held-out replay
    cannot tell from it exist (listed with the rule that chose, ``chosen_by``).

    Parameters
    ----------
    row : dict
        A finding's report row.

    Returns
    -------
    str
    """
    alts = [a["effect"] for a in row.get("alternatives") or []] or list(row.get("confounded_with") or [])
    return f"confounded with {', '.join(alts)}" if alts else "identified"


def sparse_terms(data, res: ObsResult, ctx: Context, f_band: float) -> dict:
    """SINDy-style regression of the remaining (band-limited) force residual ``res`` on state functions
    (:func:`.fit.sparse_regression`).

    Parameters
    ----------
    data : DiagData
        The recording.
    res : ObsResult
        The final model's force observer.
    ctx : Context
        What was located (position centre, scales).
    f_band : float
        Band of the residual [Hz].

    Returns
    -------
    dict
        Terms {name: coefficient} and the explained share.
    """
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
    """Everything the report is written from (one diagnosis' stages).

    Parameters
    ----------
    nominal_source : object
        The nominal as given (name, path or model).
    setup : Setup
        What :func:`.stages.read` left.
    stochastic : dict
        The report's ``stochastic`` section.
    prediction : Prediction
        What :func:`.stages.predict` left.
    locate_summary : dict
        The report's ``locate`` section.
    problem : Problem
        What the forward selection worked on.
    path : Path
        The selection's final path.
    found : list
        The report's rows of the adopted effects.
    joint : dict, optional
        The report's ``joint_fit`` (:func:`.closing.refit_jointly`).
    J_fit_nominal, J_held_nominal : float
        The nominal's force-residual J on the fit and held-out samples.
    adequacy_tolerance : float
        Tolerance of the adequacy test.
    validation : Validation
        What :func:`validate` left.
    withdrawn : list
        The report's rows of the adopted effects withdrawn as not identified
        (:func:`withdraw_unidentified`).
    detection : list, optional
        What the record could have revealed on top of the final model (:func:`detection_limits`),
        when that model is consistent with its floor.
    remaining : dict, optional
        Where the final model's force residual lies (:func:`.locate.locate`'s summary), when it is
        not.
    """
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
    withdrawn: list = field(default_factory=list)
    detection: list | None = None
    remaining: dict | None = None


def assemble(run: Run, timing: dict, sparse: dict | None) -> dict:
    """The report dict (fields documented in :mod:`.report`); units on the stage's axis.

    Parameters
    ----------
    run : Run
        The diagnosis's stages.
    timing : dict
        Wall times [s] per stage.
    sparse : dict or None
        :func:`sparse_terms`' result.

    Returns
    -------
    dict
    """
    setup, pred, problem, path, val = run.setup, run.prediction, run.problem, run.path, run.validation
    data, spec0, obs, ev = setup.data, setup.nominal, setup.observer, problem.evaluator
    if not run.found:
        verdict = "model adequate" if val.adequate_nominal else "unexplained residual"
    else:
        verdict = "effects found" if val.adequate else "effects found, residual remains"
    olw = pred.windows
    kind = spec0.preset.stage.kind
    for fe in run.found:
        fe["status"] = status_of(fe)
    lib = problem.library
    applied = []
    for fe in run.found:
        eff = next((f.effect for f in path.selected if f.key == fe["effect"]), None) or (
            lib[fe["effect"]] if fe["effect"] in lib else None)
        if eff is not None:
            applied.append((eff, [p["value"] for p in fe["params"]]))
    applied = [a for a in applied if a[0].kind != "deterministic"] + [a for a in applied if a[0].kind == "deterministic"]
    changes = model_changes(spec0, path.current, applied)
    moved = {k for c in changes for k in c["by"]}
    for fe in run.found:
        if fe["effect"] not in moved:
            fe["status"] += " (its final value is the nominal's: the model is unchanged by it)"
    lsq = least_squares_check(data, path.current) if data.open_loop else None
    report = {
        "nanostage_diagnosis": 1,
        "verdict": verdict,
        "units": axis_units(kind),
        "replay": val.headline,
        "found": run.found,
        "recording": {"source": data.source, "rate_hz": data.rate, "trials": int(data.shape[1]),
                      "open_loop": data.open_loop, "axis": data.axis,
                      "command": {"kind": data.command_kind, "meaning": COMMAND_KINDS.get(data.command_kind, ""),
                                  "not_proposed": [k for k in problem.keys if k in lib and lib[k].in_drive]
                                  if data.command_kind == "measured" else []},
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
        "improved_model": {"name": path.current.preset.name, "changes": changes},
        "withdrawn": run.withdrawn,
        "findings": findings(run, verdict),
        "detection_limits": run.detection,
        "least_squares_check": lsq,
        "timing_s": timing,
    }
    if lsq is not None and not lsq["agree"]:
        off = [k for k in ("inertia", "coulomb", "viscous") if not lsq[k]["agree"]]
        report["findings"].append({
            "finding": "the rigid-body least-squares check disagrees with the improved model in " + ", ".join(off),
            "status": "located, not explained",
            "where": {k: {"model": lsq[k]["model"], "check": lsq[k]["value"], "sigma": lsq[k]["sigma"]} for k in off}})
    convert_units(report, kind)       # every parameter unit on the axis of the stage (rotary: rad, N·m, kg·m²)
    return report


def plot_arrays(run: Run, loc_arrays: dict) -> dict:
    """The arrays :func:`.report.write_report` plots.

    Parameters
    ----------
    run : Run
        The diagnosis's stages.
    loc_arrays : dict
        The location stage's arrays.

    Returns
    -------
    dict
    """
    setup, val = run.setup, run.validation
    return {"res_nom": run.prediction.residual, "res_new": val.residual, "loc": loc_arrays,
            "rp_nom": setup.nominal_replay, "rp_new": val.improved_replay, "held": val.held, "f_band": setup.band_hz,
            "floor": run.path.floor}

