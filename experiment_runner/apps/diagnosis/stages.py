"""The stages of a diagnosis before the forward selection, each returning what the later ones read.

:func:`read` (recording and nominal, checked against each other; the nominal's replay; the force
observer) -> :func:`quantization` (the encoder lattice) -> :func:`predict` (the nominal's force
residual and open-loop windows, noise floors, the replay judges) -> :func:`locate` (where and what
the residual holds; the library bound to the recording) -> :func:`prepare` (the selection's
:class:`.selection.Problem`).
"""
from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from stage_sim.config import ConfigError

from .context import Context
from .controller import controller_check, equivalent_reference
from .data import DiagData, load_data
from .effects import Library
from .effects.stochastic import NoiseLevel, Quantization
from .evaluator import Evaluator
from .floors import ForceFloor
from .judge import ReplayJudge
from .locate import locate as locate_residual
from .locate import transfer_modes
from .model import ModelSpec, load_model
from .noise import SPREAD_MAX, estimate_lattice, fit_noise_level, noise_components
from .observer import ObsResult, Observer, smoothing_hz
from .openloop import MISSING_LP, TINY_MOTION_STEPS, OpenLoopJudge
from .options import CONTROLLER_TOL, Options
from .predict import open_loop_windows, replay
from .replay_floor import Floor
from .selection import Problem

__all__ = ["Setup", "Lattice", "Prediction", "Location", "read", "quantization", "predict", "drive_noise_prior",
           "locate", "prepare", "fill_plant_inputs", "noise_states"]


@dataclass
class Setup:
    """What :func:`read` leaves: the recording and the nominal as the diagnosis runs them.

    Parameters
    ----------
    data : DiagData
        The recording as read (plant inputs filled in from the nominal where absent).
    nominal : ModelSpec
        The nominal model (at the recording's rate).
    notes : list
        The report's notes on the recording and the model.
    nominal_replay : dict
        The nominal's closed-loop replay of the recorded reference (:func:`.predict.replay`).
    observer : Observer
        The force observer on the data.
    band_hz : float
        The force residual's band [Hz] (half the observer bandwidth).
    window : int
        Length of the report's open-loop windows [samples].
    """
    data: DiagData
    nominal: ModelSpec
    notes: list
    nominal_replay: dict
    observer: Observer
    band_hz: float
    window: int


@dataclass
class Lattice:
    """What :func:`quantization` leaves.

    Parameters
    ----------
    base : ModelSpec
        The nominal with the encoder step found from the lattice (where the selection starts).
    found : list
        The report's row of the quantization, when found.
    stochastic : dict
        The report's ``stochastic`` entries so far.
    """
    base: ModelSpec
    found: list
    stochastic: dict


@dataclass
class Prediction:
    """What :func:`predict` leaves.

    Parameters
    ----------
    residual : ObsResult
        The nominal's force residual (with window snapshots).
    windows : dict, optional
        The nominal's open-loop windows (:func:`.predict.open_loop_windows`).
    floor : ForceFloor
        The base model's force-residual floor.
    controller_error : float
        Relative RMS by which the model's controller misses the recorded command (0: open loop).
    reference : numpy.ndarray, optional
        The equivalent reference the replay follows, or None (the recorded one).
    judge : ReplayJudge
        The replay judge of the held-out trials (open loop: :class:`.openloop.OpenLoopJudge`).
    fit_judge : ReplayJudge, optional
        The same on the fit trials (None: candidates are not refined by the replay).
    replay_floor : Floor
        The base model's run-to-run replay floor.
    nominal_replay_floor : Floor, optional
        The nominal's own replay floor where the base took a drive-noise level before judging
        (:func:`drive_noise_prior`; None: ``replay_floor`` is the nominal's): the report's nominal
        column.
    """
    residual: ObsResult
    windows: dict | None
    floor: ForceFloor
    controller_error: float
    reference: np.ndarray | None
    judge: ReplayJudge
    fit_judge: ReplayJudge | None
    replay_floor: Floor
    nominal_replay_floor: Floor | None = None


@dataclass
class Location:
    """What :func:`locate` leaves.

    Parameters
    ----------
    summary : dict
        The report's ``locate`` section.
    arrays : dict
        Arrays for the plots.
    context : Context
        What was located, for the effects.
    library : Library
        The effects bound to this recording (the options' library is never changed).
    """
    summary: dict
    arrays: dict
    context: Context
    library: Library


def fill_plant_inputs(spec: ModelSpec, data, rp: dict) -> list[str]:
    """Give ``data`` the dither forces and SAI command it lacks but the model's plant takes, from the
    nominal closed-loop replay ``rp`` (the model's own dither generator and SAI manager on the
    recorded reference: the switching rule and the dither's open-loop part depend on the reference
    only). Returns the notes for the report.

    Parameters
    ----------
    spec : ModelSpec
        The nominal.
    data : DiagData
        The recording (changed in place).
    rp : dict
        The nominal's closed-loop replay (:func:`.predict.replay`).

    Returns
    -------
    list of str
        Notes on what was filled in.
    """
    p, notes = spec.preset, []
    if p.dither is not None and data.d0 is None:
        data.d0, data.d1 = rp["d0"], rp["d1"]
        notes.append("dither forces not recorded (/stage/dither): the nominal model's dither generator on the "
                     "recorded reference")
    if p.stage.sai is not None and p.sai_manager is not None and data.mode is None:
        data.mode = rp["mode"]
        notes.append("SAI mode not recorded (/stage/isolator): the nominal model's SAI manager on the recorded "
                     "reference")
    return notes


def read(recording, nominal, opt: Options, data: DiagData | None, timing: dict) -> Setup:
    """Load the recording and the nominal (checked against each other), replay the nominal, build the
    force observer.

    Raises
    ------
    stage_sim.config.ConfigError
        A closed-loop record against a nominal without a controller, or axes that differ.

    Parameters
    ----------
    recording : str, pathlib.Path or Recording
        The recording (None when ``data`` is given).
    nominal : str, pathlib.Path, dict or ModelSpec
        The nominal.
    opt : Options
        The diagnosis's options.
    data : DiagData or None
        The recording already loaded.
    timing : dict
        Wall times [s] per stage (added to).

    Returns
    -------
    Setup
    """
    t = time.perf_counter()
    data = data if data is not None else load_data(recording)
    timing["read_s"] = time.perf_counter() - t
    spec0 = load_model(nominal)
    if not data.open_loop and "controller" not in spec0.preset.model_fields_set:
        raise ConfigError(f"{nominal}: controller: the nominal states no controller, but the recording has a "
                          "reference (/stage/reference): a closed-loop record is replayed through the model's "
                          "controller; give the controller (controller.pid ...), or record open loop")
    kind = spec0.preset.stage.kind
    if data.axis != kind:
        raise ConfigError(f"{nominal}: stage.kind: the nominal is {kind} but the recording is {data.axis} "
                          "(/experiment/config run.axis): give a nominal of the recording's axis")
    notes = list(data.notes)
    rate_p = spec0.preset.controller.rate
    if abs(rate_p - data.rate) > 1e-3 * data.rate:
        notes.append(f"recording rate {data.rate:.6g} Hz differs from the model's controller.rate {rate_p:.6g} Hz; "
                     "the model is run at the recording's rate")
        spec0 = spec0.with_changes({"controller.rate": float(data.rate)})
    rp_nom = replay(spec0, data, seed=opt.floor_seeds[0] + 7)
    notes += fill_plant_inputs(spec0, data, rp_nom)
    f_o = opt.bandwidth or data.rate / 25.0
    obs = Observer(data, bandwidth=f_o, smooth_hz=smoothing_hz(spec0, data.rate, f_o))
    return Setup(data=data, nominal=spec0, notes=notes, nominal_replay=rp_nom, observer=obs, band_hz=obs.f_o / 2,
                 window=max(8, int(round(opt.window_s * data.rate))))


def quantization(setup: Setup, opt: Options) -> Lattice:
    """The encoder's lattice from the measured positions (a stochastic effect, decided by its own
    estimate: adopted when it differs from the nominal's step by more than 5 %).

    Parameters
    ----------
    setup : Setup
        What :func:`read` left.
    opt : Options
        The diagnosis's options.

    Returns
    -------
    Lattice
    """
    data, spec0 = setup.data, setup.nominal
    found = []
    base = spec0
    q_nom = spec0.preset.stage.encoder.resolution
    q_hat = estimate_lattice(data.y[data.valid])
    q_held = estimate_lattice(data.y[data.held]) if data.held.any() else None
    qinfo = {"nominal_m": q_nom, "estimate_m": q_hat, "held_out_estimate_m": q_held}
    if q_hat is not None and (q_nom == 0 or abs(q_hat / q_nom - 1) > 0.05):
        eff = Quantization()
        base = eff.apply(base, [q_hat])
        ref = q_held or q_hat
        qinfo.update(found=True, held_out_error_nominal=abs(q_nom - ref) / ref, held_out_error_improved=abs(q_hat - ref) / ref)
        found.append({"effect": "quantization", "title": eff.title, "kind": "stochastic", "step": 0,
                      "params": [{"name": "resolution", "unit": "m", "value": q_hat,
                                  "sigma": abs(q_hat - ref) if q_held else None, "nominal": q_nom}],
                      "derived": {}, "expressible": True, "confounded_with": [],
                      "held_out": {"metric": "relative lattice-step error",
                                   "nominal": qinfo["held_out_error_nominal"], "improved": qinfo["held_out_error_improved"]}})
    else:
        qinfo["found"] = False
        if q_hat is None and q_nom > 0:
            qinfo["note"] = "measured positions are not on a lattice"
    opt.log("quantization", qinfo)
    return Lattice(base=base, found=found, stochastic={"quantization": qinfo})


def predict(setup: Setup, base: ModelSpec, opt: Options, timing: dict) -> Prediction:
    """The nominal's force-observer residual and open-loop windows, the noise floors and the replay
    judges: the closed-loop replay of the held-out trials against the run-to-run floor (on an
    open-loop record the same statistics on the open-loop windows re-initialised from the
    measurement), and the same of the fit samples for the output-error refinement.

    Parameters
    ----------
    setup : Setup
        What :func:`read` left.
    base : ModelSpec
        The nominal with the encoder step found (:class:`Lattice`).
    opt : Options
        The diagnosis's options.
    timing : dict
        Wall times [s] per stage (added to).

    Returns
    -------
    Prediction
    """
    data, spec0, obs, notes = setup.data, setup.nominal, setup.observer, setup.notes
    t = time.perf_counter()
    res_nom = obs.run(spec0, snap_every=setup.window)
    windows = open_loop_windows(spec0, obs, res_nom, setup.window)
    timing["predict_s"] = time.perf_counter() - t
    t = time.perf_counter()
    fl = ForceFloor(base, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
    ctl_err = controller_check(spec0, data) if not data.open_loop else 0.0
    x_eq = None
    if ctl_err > CONTROLLER_TOL:
        x_eq = equivalent_reference(spec0, data)
        notes.append(f"the model's controller reproduces the recorded command only to {100 * ctl_err:.1f} % RMS "
                     "(run on the recorded reference and measurement): the closed-loop replay follows the "
                     "equivalent reference, for which it reproduces the recorded command exactly")
    if data.open_loop:
        q = base.preset.stage.encoder.resolution
        judge = OpenLoopJudge(data, obs, resolution=q)
        fit_judge = OpenLoopJudge(dataclasses.replace(data, held=data.fit), obs, resolution=q) if data.fit.any() else None
        if judge.whole:
            notes.append(f"tiny motion: every trial moves over at most {TINY_MOTION_STEPS} encoder steps "
                         f"({q:.3g}); the open-loop prediction runs each trial whole from its start, "
                         "quantized like the sensor (windows would absorb the motion)")
    else:
        judge = ReplayJudge(data, x_ref=x_eq)
        fit_judge = ReplayJudge(dataclasses.replace(data, held=data.fit), x_ref=x_eq) if data.fit.any() else None
    replay_floor = judge.floor(base)
    timing["floor_s"] = time.perf_counter() - t
    opt.log(f"floor: sim B ms {fl.check_ms:.3f}, n_eff {fl.n_eff:.0f}; replay floor {replay_floor.sigma_u:.3g} N, "
            f"{replay_floor.sigma_y:.3g} m (controller check {ctl_err:.3g})")
    return Prediction(residual=res_nom, windows=windows, floor=fl, controller_error=ctl_err, reference=x_eq,
                      judge=judge, fit_judge=fit_judge, replay_floor=replay_floor)


def noise_states(spec: ModelSpec) -> bool:
    """The model states a random force (drive current noise or bearing friction noise).

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    bool
    """
    st = spec.preset.stage
    return st.drive.noise_current_rms > 0 or any(b.force_noise_rms > 0 for b in st.bearings)


def drive_noise_prior(setup: Setup, lattice: Lattice, pred: Prediction, opt: Options, timing: dict) -> Prediction:
    """The data's drive-noise level read from the nominal's force residual spectrum where drive noise
    dominates (:func:`.noise.fit_noise_level`), before anything is judged. A nominal that states no
    random force (noise-free, the floor a numerical nothing) takes that level into the base model
    (a stochastic finding, said in the report; the floors are estimated again) when that level alone
    makes its replay consistent with its own simulated recordings -- the record holds noise and
    nothing else; otherwise the level is fitted after the deterministic effects. A stated level
    moves before judging only when its groups' ratios agree (:data:`.noise.SPREAD_MAX`) on a
    spectrum sharp enough to tell noise from a deterministic remnant (noise alone scatters them by
    at most half that: a short record's few segments cannot); otherwise the
    ratio of the data's level to the model's is kept (``stochastic['noise_prior']``): where the data
    are not quieter than the model, a candidate whose replay is closer to the data than its own
    recordings are replays the noise (:func:`.selection.choose`). Returns the prediction (renewed
    floors when the base changed); ``lattice`` gets the base and the finding.

    Parameters
    ----------
    setup : Setup
        What :func:`read` left.
    lattice : Lattice
        What :func:`quantization` left (gets the base and the finding).
    pred : Prediction
        What :func:`predict` left.
    opt : Options
        The diagnosis's options.
    timing : dict
        Wall times [s] per stage (added to).

    Returns
    -------
    Prediction
    """
    data, obs = setup.data, setup.observer
    t = time.perf_counter()
    base = lattice.base
    states = noise_states(base)
    info = {"nominal_A": base.preset.stage.drive.noise_current_rms, "stated": states}
    lattice.stochastic["noise_prior"] = info
    try:
        comps = noise_components(base, data, lambda d: Observer(d, bandwidth=obs.f_o, smooth_hz=data.smooth_hz),
                                 seeds=tuple(opt.floor_seeds[0] + 31 + i for i in range(2)))
        f_min = 2.0 * MISSING_LP * obs.f_o if data.open_loop else 0.0
        est = fit_noise_level(pred.residual.r, data.fit | data.held, data.rate, comps, f_max=0.75 * obs.f_o,
                              f_min=f_min)
    except (ValueError, FloatingPointError) as err:
        est = {"ok": False, "why": str(err)}
    info.update({k: v for k, v in est.items() if k != "ok"})
    timing["noise_prior_s"] = time.perf_counter() - t
    if not est.get("ok"):
        return pred
    sig = float(est["sigma"])
    s0 = base.preset.stage.drive.noise_current_rms
    eff = NoiseLevel()
    judge, fl0 = pred.judge, pred.replay_floor
    if states:
        if not s0 > 0:
            return pred
        info["ratio"] = sig / s0
        if 0.8 <= sig / s0 <= 1.25 or est.get("spread", 1.0) >= SPREAD_MAX or not fl0.replay.ok:
            return pred
        if est.get("noise_spread", 1.0) > 0.5 * SPREAD_MAX:
            # a stated level moves only when the data demand it: where noise alone would scatter the
            # groups' ratios as widely as a deterministic remnant does (a short record: few segments,
            # coarse bins), the spectrum cannot tell the one from the other (a 33 Hz mode read as 5x
            # the drive noise); the level is then fitted after the deterministic effects
            info["not_taken"] = (f"the residual spectrum cannot tell noise from a deterministic remnant: noise "
                                 f"alone scatters its groups by {est['noise_spread']:.2f} (level fitted after the "
                                 "effects)")
            return pred
    elif not (sig > 0 and fl0.replay.ok):
        return pred
    # taken before judging only if that level alone makes the nominal's replay consistent with its own
    # simulated recordings: the record holds noise and nothing else. Otherwise the residual holds
    # deterministic physics too (read in the motion's own band, the level would put the floor above it:
    # a noise-free nominal missing its friction reads amperes); the level is then fitted after the
    # deterministic effects (:func:`.closing.drive_noise`)
    fl1 = judge.floor(eff.apply(base, [sig]))
    z_old, z_new = judge.consistency(fl0.replay, fl0), judge.consistency(fl0.replay, fl1, norm=fl0)
    info.update(replay_z_before=z_old, replay_z_after=z_new)
    if not (abs(z_old) > judge.t_q and abs(z_new) <= judge.t_q):
        info["not_taken"] = ("that level alone does not make the nominal's replay consistent with its own "
                             "recordings: the residual holds more than noise (level fitted after the effects)")
        return pred
    held_out = {"metric": "|z| of the replay error among the model's simulated recordings (run-to-run "
                          "consistency); the level read from the residual spectrum before judging",
                "nominal": abs(z_old), "improved": abs(z_new)}
    lattice.base = eff.apply(base, [sig])
    info["adopted"] = sig
    lattice.found.append({"effect": "noise_level", "title": eff.title, "kind": "stochastic", "step": 0,
                          "params": [{"name": "noise_current_rms", "unit": "A", "value": sig,
                                      "sigma": est.get("sigma_unc"), "nominal": s0}],
                          "derived": {}, "expressible": True, "confounded_with": [],
                          "held_out": held_out or {
                              "metric": "the nominal states no drive noise: its level read from the force residual "
                                        "spectrum before judging (the floor is the data's)"}})
    opt.log(f"noise prior: {sig:.3g} A from the residual spectrum (the nominal's {s0:.3g} A)")
    t = time.perf_counter()
    fl = ForceFloor(lattice.base, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
    pred = dataclasses.replace(pred, floor=fl, replay_floor=pred.judge.floor(lattice.base),
                               nominal_replay_floor=pred.nominal_replay_floor or pred.replay_floor)
    timing["floor_s"] = timing.get("floor_s", 0.0) + time.perf_counter() - t
    return pred


def locate(setup: Setup, base: ModelSpec, pred: Prediction, opt: Options, timing: dict) -> Location:
    """Where and what the nominal's residual holds (regimes, spectra, bins; modes on the measured
    transfer and, on a closed-loop record, in the command's noise spectrum, anywhere up to Nyquist:
    :func:`.locate.transfer_modes`); the library bound to the recording.

    Parameters
    ----------
    setup : Setup
        What :func:`read` left.
    base : ModelSpec
        The nominal with the encoder step found (:class:`Lattice`).
    pred : Prediction
        What :func:`predict` left.
    opt : Options
        The diagnosis's options.
    timing : dict
        Wall times [s] per stage (added to).

    Returns
    -------
    Location
    """
    data, obs = setup.data, setup.observer
    t = time.perf_counter()
    summary, arrays, ctx = locate_residual(data, pred.residual, pred.floor.res_a, pred.floor.sim_a, obs.f_o,
                                           setup.band_hz)
    try:
        frf_modes, frf_info = transfer_modes(base, data)
    except (ValueError, np.linalg.LinAlgError) as err:
        frf_modes, frf_info = [], {"why": f"failed: {err!r}"}
        opt.log(f"frf mode location failed: {err!r}")
    summary["frf_modes"] = frf_modes
    summary["transfer"] = frf_info
    ctx = dataclasses.replace(ctx, frf_modes=tuple(frf_modes), observer_hz=obs.f_o,
                              resolution=base.preset.stage.encoder.resolution)
    timing["locate_s"] = time.perf_counter() - t
    return Location(summary=summary, arrays=arrays, context=ctx, library=opt.effect_library().bound(ctx))


def prepare(setup: Setup, base: ModelSpec, pred: Prediction, loc: Location, opt: Options, executor) -> tuple:
    """The evaluator and the selection's :class:`.selection.Problem`; returns ``(problem, J_fit_nominal,
    J_held_nominal, adequacy tolerance)``.

    Parameters
    ----------
    setup : Setup
        What :func:`read` left.
    base : ModelSpec
        The nominal with the encoder step found (:class:`Lattice`).
    pred : Prediction
        What :func:`predict` left.
    loc : Location
        What :func:`locate` left.
    opt : Options
        The diagnosis's options.
    executor : experiment_runner.core.executor.Executor or None
        Where candidate fits run.

    Returns
    -------
    tuple
    """
    spec0, fl = setup.nominal, pred.floor
    ev = Evaluator(setup.observer, fl.noise, opt.max_fit_seconds)
    Jf0, Jh0, _ = ev.both(spec0)
    Jfb, Jhb, _ = ev.both(base) if base is not spec0 else (Jf0, Jh0, 0)
    neff = max(fl.n_eff, 10.0)
    tol_ad = max(0.1, 3 * math.sqrt(2 / neff), 2 * abs(fl.check_ms - 1))
    problem = Problem(options=opt, data=setup.data, observer=setup.observer, base=base, library=loc.library,
                      keys=list(opt.effects) if opt.effects else loc.library.candidates(), evaluator=ev,
                      judge=pred.judge, fit_judge=pred.fit_judge, base_floor=fl, base_replay_floor=pred.replay_floor,
                      J_held_base=Jhb, J_fit_base=Jfb, band_hz=setup.band_hz, n_eff=neff, executor=executor)
    return problem, Jf0, Jh0, tol_ad
