"""The diagnosis pipeline: predict -> locate -> name -> fit and choose -> show.

:func:`diagnose` takes a contract recording and the nominal model that was supposed to
predict it and returns the report (a JSON-able dict, fields documented in
:mod:`.report`); with ``out`` it also writes ``report.json``, ``report.md``, plots and the
improved model (``improved_preset.yaml``).

The candidate fits of each forward-selection step are independent: by default they run on
``Options.n_jobs`` threads of this process (the compiled kernels release the GIL); with
``Options.workers`` or ``Options.cluster`` they are tasks (:func:`_candidate_task`) on an
:class:`experiment_runner.executor.Executor` -- local processes or a Dask cluster. Each
worker process rebuilds the observer from the recording once per diagnosis (cached by a
token), and the fits come back in the order the candidates were submitted, so every path
gives the same report (same effects, bit-identical parameters).
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import pickle
import threading
import time
import uuid
from dataclasses import dataclass, field

import numpy as np

from .data import DiagData, load_data
from .frf import locate_modes
from .fit import (Evaluator, FitResult, bad_point, estimate_lattice, fit_effect, fit_noise_level, fit_with,
                  joint_fit, n_eff, noise_components, sparse_regression)
from .context import Context
from .effects import LIBRARY
from .effects.body import Mode
from .effects.stochastic import NoiseLevel, Quantization
from .judge import ReplayJudge, controller_check, equivalent_reference
from .locate import locate, lowpass
from .model import ModelSpec, load_model
from .openloop import MISSING_LP, OpenLoopJudge
from .units import axis_units, convert_units
from .predict import (NoiseFloor, Observer, band_rms, compare_replay, force_resolution, open_loop_windows, replay,
                      sim_batch, sim_data, smoothing_hz)

__all__ = ["Options", "diagnose"]

# the model's servo on the recorded reference and measurement must reproduce the recorded command
# to this relative RMS, else the replay follows the equivalent reference (judge.equivalent_reference)
CONTROLLER_TOL = 0.02
# candidates are refined by the replay (output error on the fit samples) before they are compared: the
# stable ones with at most REFINE_MAX_PARAMS parameters among the REFINE_PROPOSALS best replays and the
# REFINE_PROPOSALS best force-observer fits, and every one-parameter one; larger ones among the REFINE_TOP
# best replays;
# from the second step on together with the adopted effects if REFINE_JOINT_MAX parameters are not exceeded
REFINE_MAX_PARAMS = 3
# block lengths [s] of the replay refinement's robust standard errors (time windows of each trial)
REFINE_BLOCKS_S = (0.02, 0.05, 0.1, 0.2)
REFINE_PROPOSALS = 4
REFINE_TOP = 2
REFINE_JOINT_MAX = 8


@dataclass
class Options:
    bandwidth: float | None = None        # force-observer bandwidth [Hz] (default rate/25)
    max_fit_seconds: float = 3.0          # fit set cap (whole trials) [s]
    effects: list | None = None           # restrict the candidates (keys of the library)
    library: object = None                # the effects (an effects.Library; default effects.LIBRARY)
    floor_seeds: tuple = (90001, 90002)   # noise seeds of the simulated recordings (floor)
    window_s: float = 0.01                # open-loop window length [s]
    max_steps: int = 6                    # forward-selection steps (each must pass the replay judge)
    plots: bool = True
    sparse: bool = True
    complexity: float = 0.02              # held-out J penalty per parameter
    n_jobs: int = 2                       # threads for the candidate fits (neither workers nor cluster)
    workers: int | None = None            # candidate fits as tasks on this many local processes (1: in turn here)
    cluster: object = None                # ... on this Dask cluster (scheduler address or cluster object)
    own_floor: bool = True                # judge each candidate against its own noise floor
    min_share: float = 0.25               # after the first effect: share of the remaining replay excess over
                                          # the floor a candidate must remove (the remnant of an imperfect fit
                                          # is not "explained" by extras)
    verbose: bool = False
    extra: dict = field(default_factory=dict)


class _Floor:
    """Noise floor of a model on the recorded reference: two simulated recordings."""

    def __init__(self, spec: ModelSpec, data: DiagData, f_o: float, seeds, fs: float):
        self.simA, self.simB = sim_batch(spec, data, seeds[:2])
        oa = Observer(self.simA, bandwidth=f_o, smooth_hz=fs)
        ob = Observer(self.simB, bandwidth=f_o, smooth_hz=fs)
        self.resA = oa.run(spec)
        self.resB = ob.run(spec)
        mA = self.simA.fit | self.simA.held
        self.floor = NoiseFloor(data.rate, [self.resA.r], [mA], f_max=f_o, rms_min=force_resolution(spec, f_o))
        mB = self.simB.held if self.simB.held.any() else self.simB.fit
        self.msB = self.floor.ms(self.resB.r, mB)
        self.n_eff = n_eff(self.floor.whiten(self.resB.r, mB), mB)
        self.band_rms_held = None


def _light_floor(spec: ModelSpec, data: DiagData, f_o: float, seed: int, fs: float) -> NoiseFloor:
    """Noise floor of ``spec`` from one simulated recording."""
    sim = sim_data(spec, data, seed)
    r = Observer(sim, bandwidth=f_o, smooth_hz=fs).run(spec).r
    return NoiseFloor(data.rate, [r], [sim.fit | sim.held], f_max=f_o, rms_min=force_resolution(spec, f_o))


def _fit_candidate(e, current: ModelSpec, selected: list, J_fit_cur: float, ev: Evaluator, ctx: dict,
                   base: ModelSpec, own_floor: bool, floor_seed: int) -> FitResult | None:
    """Fit candidate effect ``e`` on ``current`` (with the ``selected`` effects re-fitted, from
    step 2 on) and judge it on held-out data; None if it does not apply."""
    ctx = ctx_for(ctx, selected)
    f = fit_with(e, selected, base, ev, ctx) if selected and e.kind == "deterministic" else None
    f = f or fit_effect(e, current, ev, ctx)
    if f is not None and own_floor:
        # judge the candidate against its own noise floor: a change of the drive or the
        # dynamics also changes what noise leaves in the residual (e.g. a force-constant
        # ratio scales the drive noise). A candidate that does not even fit the fit set
        # better than the current model (against the current floor) may only look good
        # by making its own floor noisier (e.g. a stiff, undamped joint): then the larger
        # of the two counts. One that does fit better is not held back by a quieter own
        # floor (e.g. viscous damping over a quantization-only floor): the smaller counts
        f.J_held_base = f.J_held
        try:
            J_own = ev.J(f.spec, "held", floor=_light_floor(f.spec, ev.data, ev.obs.f_o, floor_seed, ev.data.smooth_hz))
        except ValueError:        # its simulated recording diverged: no floor of its own, no credit
            J_own = math.inf
        f.J_held = min(J_own, f.J_held_base) if f.J_fit < J_fit_cur else max(J_own, f.J_held_base)
    return f


_STATE: dict = {}                # token -> per-process state of the candidate-fit tasks
_STATE_LOCK = threading.Lock()


def _task_state(token: str, blob: bytes) -> dict:
    """This process's observer and context of diagnosis ``token`` (built from ``blob`` once;
    the last two diagnoses are kept)."""
    with _STATE_LOCK:
        st = _STATE.get(token)
        if st is None:
            st = pickle.loads(blob)
            # the recording was smoothed and masked by the caller's observer: not redone here
            data = st.pop("data")
            st["obs"] = Observer(data, bandwidth=st.pop("f_o"), smooth_hz=data.smooth_hz)
            while len(_STATE) >= 2:
                _STATE.pop(next(iter(_STATE)))
            _STATE[token] = st
        return st


def _candidate_task(token: str, blob: bytes, e, current: ModelSpec, selected: list, J_fit_cur: float,
                    floor: NoiseFloor, ctx: dict):
    """Executor task: :func:`_fit_candidate` of effect ``e`` (bound) against noise ``floor``.

    ``blob`` is the pickled recording (smoothed, masked), observer bandwidth, fit-set cap
    and base model of diagnosis ``token``; ``ctx`` the locate context of this step. BLAS runs single-threaded, as in
    :func:`diagnose`. Returns ``(FitResult or None, error repr or None, evaluations,
    evaluation seconds)``.
    """
    from threadpoolctl import threadpool_limits
    st = _task_state(token, blob)
    ev = Evaluator(st["obs"], floor, st["max_fit_seconds"])
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            f, err = _fit_candidate(e, current, selected, J_fit_cur, ev, ctx, st["base"], st["own_floor"],
                                    st["floor_seed"]), None
        except Exception as exc:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
            f, err = None, repr(exc)
    return f, err, ev.evals, ev.seconds


def _spec_without(selected: list, base: ModelSpec) -> ModelSpec:
    """``base`` with the ``selected`` effects at their current values (stochastic/integer ones
    first, as :func:`.fit.fit_with` builds them)."""
    spec = base
    for f in selected:
        if f.effect.kind != "deterministic":
            spec = f.effect.apply(spec, f.theta)
    for f in selected:
        if f.effect.kind == "deterministic":
            spec = f.effect.apply(spec, f.theta)
    return spec


def _block_covariance(J: np.ndarray, r: np.ndarray, block: np.ndarray, min_blocks: int = 10) -> np.ndarray:
    """Covariance of least-squares parameters from the Jacobian ``J`` (n, p) and residual ``r``
    (n,) at the optimum, with residuals correlated within blocks (``block`` (n,) ids) and
    independent between them: the cluster-robust sandwich ``B M B``, ``B = (J'J)^-1``,
    ``M = G/(G-1) sum_g (J_g' r_g)(J_g' r_g)'`` over the ``G`` blocks. With fewer than
    ``min_blocks`` blocks, the classical ``s^2 (J'J)^-1``.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> n, L = 4000, 20                          # a mean fitted to noise correlated over blocks of 20
    >>> r = np.repeat(rng.normal(size=n // L), L) + 0.1 * rng.normal(size=n)
    >>> J = np.ones((n, 1))
    >>> classical = np.sqrt(_block_covariance(J, r - r.mean(), np.zeros(n, int))[0, 0])
    >>> robust = np.sqrt(_block_covariance(J, r - r.mean(), np.arange(n) // L)[0, 0])
    >>> bool(3.5 < robust / classical < 5.5)    # ~sqrt(20): 20 samples carry one sample's information
    True
    """
    p = J.shape[1]
    bread = np.linalg.pinv(J.T @ J)
    ids, g = np.unique(block, return_inverse=True)
    G = len(ids)
    if G < min_blocks:
        return bread * (r @ r) / max(len(r) - p, 1)
    score = np.stack([np.bincount(g, weights=J[:, j] * r, minlength=G) for j in range(p)], axis=1)
    return bread @ (score.T @ score * (G / (G - 1))) @ bread


def spread_over_recordings(J: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Standard errors of least-squares parameters from the residuals ``R`` (K, n) of ``K``
    simulated recordings of the fitted model against its noise-free replay, and the Jacobian
    ``J`` (n, p) of the residual: the linearised parametric bootstrap, the spread of the
    Gauss-Newton step ``pinv(J) r_k`` each recording would give. The recordings carry the
    noise's real correlation in time (a closed loop integrates drive noise), which a sandwich
    over a dozen blocks of a short record underestimated (a mass error 10 of its sigmas off).

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> n, L = 3000, 30                                   # a slope fitted to noise correlated over 30 samples
    >>> J = np.linspace(-1.0, 1.0, n)[:, None]
    >>> R = np.repeat(rng.normal(size=(400, n // L)), L, axis=1)
    >>> exact = np.sqrt(L / (J[:, 0] @ J[:, 0]))          # ~sqrt(L) x the white-noise value
    >>> bool(abs(spread_over_recordings(J, R)[0] / exact - 1) < 0.15)
    True
    """
    step = R @ np.linalg.pinv(J).T
    return np.sqrt(np.mean(step ** 2, axis=0))


def _moved(theta: dict, key: str, i: int, v: float) -> dict:
    """A copy of the effects' parameter vectors ``theta`` with parameter ``i`` of ``key`` at ``v``."""
    th = {k: a.copy() for k, a in theta.items()}
    th[key][i] = v
    return th


def _refine_by_replay(bf: FitResult, selected: list, base: ModelSpec, ctx: dict, fj: ReplayJudge, jfl,
                      max_nfev: int = 8, with_selected: bool = False, start=None,
                      diff_step: float = 2e-2, grid: bool = False) -> dict | None:
    """Output-error refinement of candidate ``bf``: least squares of the closed-loop replay error on
    the *fit* samples (``fj``), command and position in units of the current run-to-run floor
    ``jfl``, started at the force-observer fit. The force observer's fit is off where the replay
    is sensitive when the observer's residual weighs the data differently (a ripple phase, a
    Coulomb level against a friction slope): candidates are compared at their replay optimum.

    With ``with_selected`` the adopted deterministic effects (``selected``) are refined with it
    (joint output error: a second effect is credited with what it adds once the first is
    re-fitted in its presence), else they are held at their values. ``start``: the candidate's
    own start values instead of the observer's fit; ``grid``: start from a coarse grid around it,
    coordinate by coordinate, as a one-parameter candidate always does (:data:`GRID_1D`).

    Returns None (no gain, or a failure) or a dict: ``spec``, ``theta``/``sigma``/``at_bound``
    of the candidate's own parameters, and ``joint`` (a :class:`FitResult` over the selected
    effects' and the candidate's parameters, or None). ``sigma``: from the replay Jacobian and
    residual, block-robust (:func:`_block_covariance`, the largest over blocks of
    :data:`REFINE_BLOCKS_S` with at least 10 blocks per parameter: the replay error is correlated
    over tens of milliseconds, not independent per sample). ``diff_step``: the optimiser's relative
    finite-difference step (of the log for log parameters)."""
    from scipy.optimize import least_squares

    from .fit import _Joint, _Transform
    try:
        e = bf.effect
        cont = [f for f in selected if f.effect.kind == "deterministic"] if with_selected else []
        prev = base
        for f in selected:
            if f.effect.kind != "deterministic":
                prev = f.effect.apply(prev, f.theta)
        if not with_selected:
            for f in selected:
                if f.effect.kind == "deterministic":
                    prev = f.effect.apply(prev, f.theta)
        parts = [(f.effect, len(f.theta)) for f in cont] + [(e, len(bf.theta))]
        th = [np.asarray(f.theta, float) for f in cont]
        own0 = np.asarray(bf.theta if start is None else start, float)
        starts = [np.concatenate(th + [own0])]
        if cont and bf.joint is not None and len(bf.joint.theta) == sum(map(len, th)) + len(bf.theta):
            # or where the observer's joint fit with this candidate left the adopted effects, if
            # their replay is better there (where the observer sees little its joint fit is noise)
            starts.insert(0, np.concatenate([np.asarray(bf.joint.theta, float)[:sum(map(len, th))], own0]))
        model = _Joint(parts, th + [own0])
        ps = model.params(prev, ctx)
        if len(ps) != len(starts[0]):
            return None
        tr = _Transform(ps)
        lo, hi = tr.bounds()
        eps = 1e-6 * (hi - lo)
        m = fj.mask
        bad = None

        def res(z):
            th = tr.to_theta(z)
            if not np.all(np.isfinite(th)):
                return bad
            try:
                rp = fj.replay(model.apply(prev, th))
            except ValueError:     # a model the simulator refuses (a joint too stiff for its sub-steps)
                return bad
            if not rp.ok:
                return bad
            r = fj.residual(rp, jfl)
            return r if np.all(np.isfinite(r)) else bad

        z0, r0 = None, None
        for theta0 in starts:
            z = np.clip(tr.to_z(theta0), lo + eps, hi - eps)
            r = res(z)
            if r is not None and (r0 is None or float(r @ r) < float(r0 @ r0)):
                z0, r0 = z, r
        if r0 is None:
            return None
        bad = np.full(len(r0), bad_point(float(np.mean(r0 ** 2))))     # a model that diverges or is refused
        c_obs = float(r0 @ r0)
        if len(own0) == 1 or grid:
            # one parameter (or a start the observer did not give): the replay's error is rough in it
            # (a stick-slip event or an encoder step moves with it) and may be flat at the start (a
            # stage held by friction): start from the best of a coarse grid around it, one of the
            # candidate's own coordinates after the other (the adopted effects' stay at their start)
            z1, c1 = z0, c_obs
            for i in range(len(z0) - len(own0), len(z0)):
                zi = z1
                for d in GRID_1D:
                    z = zi.copy()
                    z[i] += d * max(1.0, abs(float(zi[i])) if not ps[i].log else 1.0)
                    z = np.clip(z, lo + eps, hi - eps)
                    r = res(z)
                    if r is not bad and float(r @ r) < c1:
                        z1, c1 = z, float(r @ r)
            z0 = z1
        out = least_squares(res, z0, bounds=(lo, hi), max_nfev=max_nfev, x_scale="jac",
                            diff_step=diff_step)
        out = _back_to_no_change(out, res, bad, e.nominal(prev), ps, len(out.x) - len(own0), tr, (lo, hi), eps,
                                 dict(max_nfev=max_nfev, x_scale="jac", diff_step=diff_step))
        if not out.success and out.status < 0 or out.cost >= 0.5 * c_obs:
            return None
        tol = 1e-3 * (hi - lo)
        at = [p.name for p, z, a, b, t in zip(ps, out.x, lo, hi, tol)
              if abs(b - z) <= t or (abs(z - a) <= t and not p.physical_lo)]
        theta = tr.to_theta(out.x)
        J = out.jac
        if not (np.all(np.isfinite(J)) and np.all(np.isfinite(theta))):
            return None
        T_, B_ = m.shape
        t_of = np.broadcast_to(np.arange(T_)[:, None], m.shape)[m]
        b_of = np.broadcast_to(np.arange(B_)[None, :], m.shape)[m]
        var = np.zeros(len(theta))
        for span in REFINE_BLOCKS_S:          # the largest over block lengths: the error's correlation time is unknown
            L = max(1, int(round(span * fj.rate)))
            ids = b_of * (T_ // L + 1) + t_of // L
            if len(np.unique(ids)) >= 10 * len(theta) or span == REFINE_BLOCKS_S[0]:
                var = np.maximum(var, np.diag(_block_covariance(J, out.fun, np.tile(ids, len(out.fun) // len(ids)))))
        cov_z = np.diag(var)
        sigma = np.sqrt(np.maximum(np.diag(cov_z), 0.0)) * np.abs(tr.dtheta_dz(theta))
        spec = model.apply(prev, theta)
        k = len(theta) - len(bf.theta)
        own = bf.key + "."
        joint = None
        if cont:
            joint = dataclasses.replace(bf, key=model.key, title=model.title, names=[p.name for p in ps],
                                        units=[p.unit for p in ps], theta=np.asarray(theta, float),
                                        sigma=np.asarray(sigma, float), corr=None, spec=spec, on_bound=at,
                                        nominal={}, derived={}, joint=None)
        return {"spec": spec, "theta": np.asarray(theta[k:], float), "sigma": np.asarray(sigma[k:], float),
                "at_bound": [n[len(own):] for n in at[:] if n.startswith(own)], "joint": joint}
    except Exception:   # noqa: BLE001 - the refinement is an improvement, never a failure of the diagnosis
        return None


def _back_to_no_change(out, res, bad, nominal: dict, ps: list, k0: int, tr, bounds, eps, ls_kw: dict):
    """The output-error solution ``out`` (of ``res`` over the parameters ``ps``, in ``tr``'s
    variable), or a better one found from it with one of the candidate's own parameters (those from
    index ``k0``) back at its value of no change (``nominal``) and refined again.

    The replay's error has narrow valleys: a level the replay pins to 1 % lies inside the
    finite-difference step, and the solver stops where a second parameter stands in for the
    level's last step (a viscous asymmetry of 20.6 N s/m on a one-direction record whose truth
    has none, the force asymmetry 1.3 % off: replay D 4.1 against 1.7 at the truth). A parameter
    the data need (its error at no change more than 1.5 times the solution's): not tried."""
    from scipy.optimize import least_squares
    lo, hi = bounds
    for j, p in enumerate(ps[k0:]):
        v0 = nominal.get(p.name.split(".", 1)[-1])
        if v0 is None or not (p.lo <= v0 <= p.hi):
            continue
        th = tr.to_theta(out.x)
        if abs(th[k0 + j] - v0) <= 1e-9 * max(abs(p.hi - p.lo), 1e-300):
            continue
        th[k0 + j] = v0
        z1 = np.clip(tr.to_z(th), lo + eps, hi - eps)
        r1 = res(z1)
        if r1 is bad or float(r1 @ r1) > 3.0 * out.cost:      # out.cost: half the sum of squares
            continue
        alt = least_squares(res, z1, bounds=bounds, **ls_kw)
        if alt.cost < out.cost:
            out = alt
    return out


GRID_1D = (-0.6, -0.3, -0.15, -0.05, 0.05, 0.15, 0.3, 0.6)
"""Start grid of a one-parameter replay refinement, in the optimiser's variable (log, or scaled)."""

REFINE_MODE_PASSES = 3
"""Passes of the located-mode refinement, each weighted by the floor of the previous pass' model."""

PROPOSAL_KEYS = ("ripple_period", "peak_hz", "line_hz")


def _proposals(data: DiagData, res, floor: "_Floor", f_o: float, f_band: float, ctx: dict) -> dict:
    """The locate context's proposal entries (:data:`PROPOSAL_KEYS`) from the force residual ``res``
    of the current model (its floor ``floor``): new findings first, then the earlier ones not within
    15 % of them (at most three periods; peaks and lines as located)."""
    try:
        _, _, c = locate(data, res, floor.resA, floor.simA, f_o, f_band)
    except Exception:     # noqa: BLE001 - the earlier proposals stay
        return {}
    out = {}
    for k in PROPOSAL_KEYS:
        new = list(getattr(c, k))
        old = [v for v in getattr(ctx, k) if all(abs(math.log(v / w)) > 0.15 for w in new if v > 0 and w > 0)]
        out[k] = tuple((new + old)[:3] if k == "ripple_period" else new + old)
    return out


def ctx_for(ctx: Context, selected: list) -> Context:
    """The located context for fits on top of ``selected``: with the Coulomb level adopted, the
    position-dependent friction has no level parameter of its own (``level_fitted``)."""
    return dataclasses.replace(ctx, level_fitted=any(f.effect.sets_friction_level for f in selected))


def _unidentified(f: FitResult) -> bool:
    """Every parameter of ``f`` has a standard error above its magnitude (nothing determined)."""
    sig, th = np.asarray(f.sigma, float), np.asarray(f.theta, float)
    ok = np.isfinite(sig)
    return bool(ok.all() and np.all(sig > np.abs(th)))


NOMINAL_Z = 2.0
"""An effect whose every parameter is within this many standard errors of the current model's value
(a stated mass, force constant, delay) is not adopted: the data do not demand the change."""


def _spec_moved(selected: list, theta, base: ModelSpec) -> ModelSpec:
    """:func:`_spec_without` with the deterministic ``selected`` effects at the joint values
    ``theta`` (theirs, in order, first)."""
    k, moved = 0, []
    for f in selected:
        if f.effect.kind == "deterministic":
            n = len(f.theta)
            f = dataclasses.replace(f, theta=np.asarray(theta[k:k + n], float))
            k += n
        moved.append(f)
    return _spec_without(moved, base)


def _at_nominal(f: FitResult, spans=None) -> bool:
    """Every parameter of ``f`` has a current-model value and is within :data:`NOMINAL_Z` standard
    errors of it, or within 1e-4 of its range ``spans`` (hi - lo per parameter, if given) of it: a
    value of no change whose standard error is as small (a fractional delay of 1e-6 samples at its
    lower end, credited with what the refinement of the adopted effects did)."""
    if not f.names:
        return False
    nom = [f.nominal.get(n) for n in f.names]
    sig = np.asarray(f.sigma, float)
    if any(v is None for v in nom) or not np.all(np.isfinite(sig)) or len(sig) != len(nom):
        return False
    tol = NOMINAL_Z * sig
    if spans is not None and len(spans) == len(sig):
        tol = np.maximum(tol, 1e-4 * np.asarray(spans, float))
    return bool(np.all(np.abs(np.asarray(f.theta, float) - np.asarray(nom, float)) <= tol))


def roughness(D, v: float, sigma: float, target: float = 0.3, points: int = 7) -> float | None:
    """Spread of a parameter from the roughness of the replay around its value ``v``.

    A closed-loop replay with friction is not a smooth function of a parameter: a small change
    moves a stick-slip event or an encoder step, and the replay error ``D`` jumps (by about 1 %
    of ``D`` between values 0.5 % apart on a fractional delay), so the optimiser stops anywhere
    in a valley the local Jacobian does not see. ``D`` (a function of the parameter) is profiled
    over a step ``h`` at which it rises by about ``target`` x its value, on ``points`` values in
    ``[v - h, v + h]``; with the parabola fitted to them (curvature ``c``, residual SD ``s``,
    minimum at ``v + d``) the spread is ``sqrt(s / c + d^2)``: the values whose smooth part is
    within one roughness SD of the minimum, and the distance of ``v`` from that minimum. None if
    the profile has no positive curvature.

    >>> import numpy as np
    >>> rough = lambda x: 2.0 + 1e4 * (x - 0.4) ** 2 + 0.01 * np.sin(3e3 * x)
    >>> r = roughness(rough, 0.4, 1e-4)
    >>> 0.0002 < r < 0.003
    True
    >>> roughness(lambda x: 2.0 + 1e4 * (x - 0.4) ** 2, 0.4, 1e-4) < 1e-4
    True
    """
    D0 = D(v)
    if not np.isfinite(D0) or D0 <= 0:
        return None
    h = max(abs(v), 10.0 * sigma, 1e-12) * 0.01
    for _ in range(8):
        up = max(D(v + h), D(v - h))
        if not np.isfinite(up) or up - D0 > 3.0 * target * D0:
            h /= 3.0
        elif up - D0 < target * D0 / 3.0:
            h *= 3.0
        else:
            break
    x = np.linspace(-h, h, points)
    y = np.array([D0 if abs(d) < 1e-300 else D(v + d) for d in x])
    if not np.all(np.isfinite(y)):
        return None
    A = np.stack([np.ones_like(x), x, x * x], axis=1)
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    c = coef[2]
    if c <= 0:
        return None
    s = float(np.sqrt(np.sum((y - A @ coef) ** 2) / (points - 3)))
    d = -coef[1] / (2 * c)
    return float(math.sqrt(s / c + d * d))


def _log(opt, *a):
    if opt.verbose:
        print("[diagnose]", *a, flush=True)


def _fit_row(f: FitResult, J_cur: float, thr: float, penalty: float) -> dict:
    return {"effect": f.key, "title": f.title, "J_fit": f.J_fit, "J_held": f.J_held,
            "score": f.J_held * (1 + penalty * len(f.theta)), "improvement": J_cur - f.J_held,
            "significant": bool(J_cur - f.J_held > thr), "params": f.params(), "derived": f.derived,
            "on_bound": f.on_bound, "evals": f.evals, "seconds": round(f.seconds, 3)}


def diagnose(recording, nominal, out=None, options: Options | None = None, data: DiagData | None = None) -> dict:
    """Diagnose ``recording`` (path / Recording) against ``nominal`` (preset name/path/model file).

    BLAS runs single-threaded meanwhile (``threadpoolctl``): the diagnosis works on small
    matrices, many at a time on its own threads, where BLAS threads only contend (3x slower
    on a shared 2-core machine).

    Raises
    ------
    stage_sim.config.ConfigError
        ``options.workers`` below 1, or the Dask scheduler ``options.cluster`` cannot be
        reached (before any work is done).
    """
    from threadpoolctl import threadpool_limits
    opt = options or Options()
    with threadpool_limits(limits=1, user_api="blas"), contextlib.ExitStack() as stack:
        ex = None
        if opt.workers is not None or opt.cluster is not None:
            from experiment_runner.executor import make_executor
            ex = stack.enter_context(make_executor(opt.workers, opt.cluster))
            if ex.kind != "inline":
                # start the worker processes (their imports) while this one predicts and locates
                warm = threading.Thread(target=_warm_up, args=(ex,), daemon=True, name="nanostage-diagnose-warm-up")
                warm.start()
                stack.callback(warm.join)          # before the executor closes
        return _diagnose(recording, nominal, out, opt, data, ex)


def _started() -> int:
    """Executor task that does nothing: its worker process has imported this module by now."""
    return os.getpid()


def _warm_up(ex) -> None:
    """Run one :func:`_started` per worker of ``ex`` (a background thread of :func:`diagnose`)."""
    try:
        for _ in ex.map(_started, [(i, ()) for i in range(ex.workers)]):
            pass
    except Exception:    # noqa: BLE001 - a broken pool or a lost scheduler fails the candidate fits themselves
        return


def _fill_plant_inputs(spec: ModelSpec, data, rp: dict) -> list[str]:
    """Give ``data`` the dither forces and SAI command it lacks but the model's plant takes,
    from the nominal closed-loop replay ``rp`` (the model's own dither generator and SAI
    manager on the recorded reference: the switching rule and the dither's open-loop part
    depend on the reference only). Returns the notes for the report."""
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


def _diagnose(recording, nominal, out, opt, data, ex) -> dict:
    return _Run(recording, nominal, out, opt, data, ex).run()


class _Run:
    """One diagnosis of a recording against a nominal, stage by stage (:func:`diagnose` runs it).

    The stages, in order (:meth:`run`), each reading what the earlier ones left on the instance:
    :meth:`read` (recording, nominal, observer), :meth:`quantization` (the encoder lattice),
    :meth:`predict` (the nominal's force-observer residual, open-loop windows, noise floors and
    the replay judge), :meth:`locate` (where and what the residual holds), :meth:`prepare` (the
    evaluator and the candidate effects), :meth:`select` (forward selection: :meth:`candidates`
    proposes, :meth:`fit_all` fits, :meth:`judge_rows` / :meth:`refine_rows` judge by the
    replay, :meth:`backward` withdraws what later effects made redundant, :meth:`second_start`
    walks again from step 1's runner-up when the path ends beyond its floor), :meth:`refit_jointly`,
    :meth:`drive_noise`, :meth:`validate` (held-out data) and :meth:`report`. The forward
    selection's state is :attr:`path` (current model, floors, selected effects, steps).
    """

    def __init__(self, recording, nominal, out, opt, data, ex):
        self.recording, self.nominal, self.out, self.opt, self.data, self.ex = recording, nominal, out, opt, data, ex
        self.path = None

    def run(self) -> dict:
        """Every stage in order; returns the report (with ``_improved_spec``)."""
        for stage in (self.read, self.quantization, self.predict, self.locate, self.prepare, self.select,
                      self.refit_jointly, self.drive_noise, self.uncertainty, self.validate):
            stage()
        return self.report()

    def read(self):
        """Load the recording and the nominal (checked against each other), replay the nominal, build the force observer."""
        recording, nominal, opt, data = self.recording, self.nominal, self.opt, self.data
        T0 = time.perf_counter()
        timing = {}
        t = time.perf_counter()
        data = data if data is not None else load_data(recording)
        timing["read_s"] = time.perf_counter() - t
        spec0 = load_model(nominal)
        if not data.open_loop and "controller" not in spec0.preset.model_fields_set:
            from stage_sim.config import ConfigError
            raise ConfigError(f"{nominal}: controller: the nominal states no controller, but the recording has a "
                              "reference (/stage/reference): a closed-loop record is replayed through the model's "
                              "controller; give the controller (controller.pid ...), or record open loop")
        kind = spec0.preset.stage.kind
        if data.axis != kind:
            from stage_sim.config import ConfigError
            raise ConfigError(f"{nominal}: stage.kind: the nominal is {kind} but the recording is {data.axis} "
                              "(/experiment/config run.axis): give a nominal of the recording's axis")
        notes = list(data.notes)
        rate_p = spec0.preset.controller.rate
        if abs(rate_p - data.rate) > 1e-3 * data.rate:
            notes.append(f"recording rate {data.rate:.6g} Hz differs from the model's controller.rate {rate_p:.6g} Hz; "
                         "the model is run at the recording's rate")
            spec0 = spec0.with_changes({"controller.rate": float(data.rate)})
        t = time.perf_counter()
        rp_nom = replay(spec0, data, seed=opt.floor_seeds[0] + 7)
        notes += _fill_plant_inputs(spec0, data, rp_nom)
        f_o = opt.bandwidth or data.rate / 25.0
        obs = Observer(data, bandwidth=f_o, smooth_hz=smoothing_hz(spec0, data.rate, f_o))
        f_band = obs.f_o / 2
        W = max(8, int(round(opt.window_s * data.rate)))
        self.data, self.T0, self.timing, self.t, self.spec0, self.kind = data, T0, timing, t, spec0, kind
        self.notes, self.rp_nom, self.obs, self.f_band, self.W = notes, rp_nom, obs, f_band, W

    def quantization(self):
        """The encoder's lattice from the measured positions (a stochastic effect, decided by its own estimate)."""
        opt, data, spec0 = self.opt, self.data, self.spec0
        # ---------------------------------------------------------------- stochastic: quantization
        found = []           # effects in the order they were named
        stochastic = {}
        base = spec0
        q_nom = spec0.preset.stage.encoder.resolution
        yv = data.y[data.valid]
        q_hat = estimate_lattice(yv)
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
        stochastic["quantization"] = qinfo
        _log(opt, "quantization", qinfo)
        self.found, self.stochastic, self.base = found, stochastic, base

    def predict(self):
        """The nominal's force-observer residual and open-loop windows, the noise floors and the replay judge."""
        opt, data, timing, t, spec0, notes = self.opt, self.data, self.timing, self.t, self.spec0, self.notes
        obs, W, base = self.obs, self.W, self.base
        # ---------------------------------------------------------------- predict (nominal)
        res_nom = obs.run(spec0, snap_every=W)
        olw_nom = open_loop_windows(spec0, obs, res_nom, W)
        timing["predict_s"] = time.perf_counter() - t
        t = time.perf_counter()
        fl = _Floor(base, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
        # the judge: closed-loop replay of the held-out trials against the run-to-run floor
        ctl_err = controller_check(spec0, data) if not data.open_loop else 0.0
        x_eq = None
        if ctl_err > CONTROLLER_TOL:
            x_eq = equivalent_reference(spec0, data)
            notes.append(f"the model's controller reproduces the recorded command only to {100 * ctl_err:.1f} % RMS "
                         "(run on the recorded reference and measurement): the closed-loop replay follows the "
                         "equivalent reference, for which it reproduces the recorded command exactly")
        if data.open_loop:
            # no reference: the same statistics on the open-loop windows re-initialised from the measurement
            judge = OpenLoopJudge(data, obs)
            fit_judge = OpenLoopJudge(dataclasses.replace(data, held=data.fit), obs) if data.fit.any() else None
        else:
            judge = ReplayJudge(data, x_ref=x_eq)
            fit_judge = ReplayJudge(dataclasses.replace(data, held=data.fit), x_ref=x_eq) if data.fit.any() else None
        # output-error refinement by the replay of the fit samples; on an open-loop record by its
        # prewhitened windows (before they were whitened, a refined isolator "explained" a located
        # mode's remainder below the floor there, and open-loop records kept the observer's values)
        refine = fit_judge is not None
        jfl0 = judge.floor(base)
        timing["floor_s"] = time.perf_counter() - t
        _log(opt, f"floor: sim B ms {fl.msB:.3f}, n_eff {fl.n_eff:.0f}; replay floor {jfl0.sigma_u:.3g} N, "
                  f"{jfl0.sigma_y:.3g} m (controller check {ctl_err:.3g})")
        self.t, self.res_nom, self.olw_nom, self.fl, self.ctl_err, self.x_eq = t, res_nom, olw_nom, fl, ctl_err, x_eq
        self.judge, self.fit_judge, self.refine, self.jfl0 = judge, fit_judge, refine, jfl0

    def locate(self):
        """Where and what the nominal's residual holds (regimes, spectra, bins, modes on the transfer); binds the library."""
        opt, data, timing, t, spec0, obs = self.opt, self.data, self.timing, self.t, self.spec0, self.obs
        f_band, base, res_nom, fl = self.f_band, self.base, self.res_nom, self.fl
        # ---------------------------------------------------------------- locate
        t = time.perf_counter()
        loc, loc_arrays, ctx = locate(data, res_nom, fl.resA, fl.simA, obs.f_o, f_band)
        # modes anywhere up to Nyquist: the command -> measurement transfer against the nominal's
        try:
            frf_modes = locate_modes(spec0, data)
        except (ValueError, np.linalg.LinAlgError) as err:
            frf_modes = []
            _log(opt, f"frf mode location failed: {err!r}")
        loc["frf_modes"] = frf_modes
        ctx = dataclasses.replace(ctx, frf_modes=tuple(frf_modes), smoothing_hz=data.smooth_hz,
                                  resolution=base.preset.stage.encoder.resolution)
        timing["locate_s"] = time.perf_counter() - t
        self.t, self.loc, self.loc_arrays, self.ctx = t, loc, loc_arrays, ctx
        # the effects bound to this recording (the options' library is never changed)
        self.library = (opt.library or LIBRARY).bound(ctx)

    def prepare(self):
        """The evaluator, the nominal's and base model's costs and the candidate effects."""
        opt, t, spec0, obs, base, fl = self.opt, self.t, self.spec0, self.obs, self.base, self.fl
        # ---------------------------------------------------------------- fit and choose
        t = time.perf_counter()
        ev = Evaluator(obs, fl.floor, opt.max_fit_seconds)
        Jf0, Jh0, _ = ev.both(spec0)
        Jfb, Jhb, _ = ev.both(base) if base is not spec0 else (Jf0, Jh0, 0)
        neff = max(fl.n_eff, 10.0)
        tol_ad = max(0.1, 3 * math.sqrt(2 / neff), 2 * abs(fl.msB - 1))
        keys = opt.effects or self.library.candidates()
        self.t, self.ev, self.Jf0, self.Jh0, self.Jfb, self.Jhb = t, ev, Jf0, Jh0, Jfb, Jhb
        self.neff, self.tol_ad, self.keys = neff, tol_ad, keys

    def select(self):
        """Forward selection (:meth:`forward`), the candidate-fit tasks' shared state set first."""
        opt, data, ex, obs, found, base = self.opt, self.data, self.ex, self.obs, self.found, self.base
        # candidate fits as executor tasks (local processes / Dask): what every task needs, once
        token, blob = None, None
        if ex is not None:
            token = uuid.uuid4().hex
            blob = pickle.dumps({"data": data, "f_o": obs.f_o, "max_fit_seconds": opt.max_fit_seconds,
                                 "base": base, "own_floor": opt.own_floor, "floor_seed": opt.floor_seeds[0]},
                                protocol=pickle.HIGHEST_PROTOCOL)
        self.token, self.blob = token, blob       # the executor tasks' shared state (fit_all)
        path = self.forward()
        with _STATE_LOCK:
            _STATE.pop(token, None)     # this process's copy (executor running the tasks here, workers=1)
        current, J_cur, floor_cur, jfl = path["current"], path["J_cur"], path["floor"], path["jfl"]
        steps, selected = path["steps"], path["selected"]
        found += path["found"]
        self.found, self.token, self.blob, self.path, self.current, self.J_cur = found, token, blob, path, current, J_cur
        self.floor_cur, self.jfl, self.steps, self.selected = floor_cur, jfl, steps, selected

    def refit_jointly(self):
        """The selected deterministic effects fitted together; used if the replay is not worse and nothing is at a bound."""
        opt, timing, t, found, base, judge = self.opt, self.timing, self.t, self.found, self.base, self.judge
        ctx, ev, current, J_cur, jfl, selected = self.ctx, self.ev, self.current, self.J_cur, self.jfl, self.selected
        # joint fit of the selected deterministic effects: used only if the replay is not worse and no
        # parameter sits at its bound; then the found effects carry the joint values (as the YAML does)
        joint = None
        if len([f for f in selected if f.effect.kind == "deterministic"]) >= 2:
            try:
                jf = joint_fit(selected, base, ev, ctx_for(ctx, selected))
            except Exception as err:   # noqa: BLE001
                jf = None
                _log(opt, f"joint fit failed: {err!r}")
            if jf is not None:
                D_cur = judge.D(jfl.replay, jfl)
                rpj = judge.replay(jf.spec)
                D_j = judge.D(rpj, jfl) if rpj.ok else float("inf")
                joint = {"effects": jf.key, "J_fit": jf.J_fit, "J_held": jf.J_held, "params": jf.params(),
                         "correlation": jf.corr.tolist() if jf.corr is not None else None,
                         "replay_D": D_j, "replay_D_stepwise": D_cur, "on_bound": jf.on_bound,
                         "used": False}
                conf_pairs = []
                if jf.corr is not None:
                    for i in range(len(jf.names)):
                        for j in range(i + 1, len(jf.names)):
                            if jf.names[i].split(".")[0] != jf.names[j].split(".")[0] and abs(jf.corr[i, j]) > 0.95:
                                conf_pairs.append([jf.names[i], jf.names[j], float(jf.corr[i, j])])
                joint["confounded_parameters"] = conf_pairs
                joint["used"] = bool(D_j <= D_cur and not jf.on_bound and not conf_pairs)
                if joint["used"]:
                    current = jf.spec
                    for fe in found:
                        if fe["kind"] != "deterministic":
                            continue
                        fe["params_step"] = fe["params"]
                        fe["params"] = [dict(p, name=p["name"].split(".", 1)[1]) for p in jf.params()
                                        if p["name"].split(".")[0] == fe["effect"]]
                        fe["derived"] = next(f for f in selected if f.key == fe["effect"]).effect.derived(
                        base, [p["value"] for p in fe["params"]])
                    J_cur = ev.J(current, "held")
                    jfl = judge.floor(current)
        timing["fit_s"] = time.perf_counter() - t
        self.current, self.J_cur, self.jfl, self.joint = current, J_cur, jfl, joint

    def drive_noise(self):
        """The drive-noise level proposed from the residual spectrum, decided by the replay's run-to-run consistency."""
        opt, data, timing, t, spec0, obs = self.opt, self.data, self.timing, self.t, self.spec0, self.obs
        found, stochastic, judge, ev, current, J_cur = self.found, self.stochastic, self.judge, self.ev, self.current, self.J_cur
        floor_cur, jfl, steps = self.floor_cur, self.jfl, self.steps
        # ---------------------------------------------------------------- stochastic: drive noise
        t = time.perf_counter()
        ninfo = {"nominal_A": spec0.preset.stage.drive.noise_current_rms, "found": False}
        try:
            comps = noise_components(current, data, lambda d: Observer(d, bandwidth=obs.f_o, smooth_hz=data.smooth_hz),
                                     seeds=tuple(opt.floor_seeds[0] + 11 + i for i in range(4)))
            r_cur = obs.run(current).r
            # an open-loop record's simulated recordings carry the data's own residual below
            # MISSING_LP x f_o as a known force (openloop.sim_batch): there their residual is not the
            # data's, and the level is read above it only
            f_min = 2.0 * MISSING_LP * obs.f_o if data.open_loop else 0.0
            est = fit_noise_level(r_cur, data.fit, data.rate, comps, f_max=0.75 * obs.f_o, f_min=f_min)
            ninfo.update({k: v for k, v in est.items() if k != "ok"})
            s0 = current.preset.stage.drive.noise_current_rms
            if est.get("ok"):
                sig = est["sigma"]
                consistent = est.get("spread", 1.0) < 0.35
                if not consistent and data.open_loop and s0 > 0 and self.fit_judge is not None:
                    # the bands disagree (few of them above the open-loop records' known-force band):
                    # the level at which the fit samples' prewhitened windows are at the model's own
                    # floor, adopted in their place only if it lies inside the bands' range
                    sig_w, unc_w = self.level_at_floor(current, s0)
                    lo, hi = (s0 * math.sqrt(max(min(est["group_ratios"]), 0.0)),
                              s0 * math.sqrt(max(est["group_ratios"])))
                    ninfo["windows_sigma"] = sig_w
                    if sig_w is not None and lo <= sig_w <= hi:
                        sig, consistent = sig_w, True
                        ninfo.update(sigma=sig, sigma_unc=unc_w)
                        est["sigma_unc"] = unc_w
                        ninfo["how"] = ("open-loop windows at their floor (the residual spectrum's bands "
                                        f"disagree: {lo:.3g}-{hi:.3g} A)")
                ratio = sig / s0 if s0 > 0 else float("inf")
                ninfo["ratio"] = ratio if s0 > 0 else None
                ninfo["consistent"] = consistent
                if not (0.8 <= ratio <= 1.25) and consistent:
                    # proposed by the force residual's spectrum; decided by the replay: the data's replay
                    # error must be inconsistent with the current model's run-to-run floor (a calibrated
                    # z-score over its simulated recordings) and consistent with the candidate's
                    cand = NoiseLevel().apply(current, [sig])
                    jfl2 = judge.floor(cand)
                    z_old = judge.consistency(jfl.replay, jfl)
                    z_new = judge.consistency(jfl.replay, jfl2, norm=jfl)
                    ninfo.update({"replay_z_before": z_old, "replay_z_after": z_new, "z_critical": judge.t_q})
                    # (a deterministic remnant the effects left also makes the replay inconsistent: a noise level
                    # is adopted only if it makes the data consistent with the model's own recordings)
                    if abs(z_old) > judge.t_q and abs(z_new) < abs(z_old) - judge.t_q and abs(z_new) <= judge.t_q:
                        ninfo["found"] = True
                        found.append({"effect": "noise_level", "title": NoiseLevel.title, "kind": "stochastic",
                                      "step": len(steps) + 1,
                                      "params": [{"name": "noise_current_rms", "unit": "A", "value": sig,
                                                  "sigma": est.get("sigma_unc"), "nominal": s0}],
                                      "derived": {}, "expressible": True, "confounded_with": [],
                                      "held_out": {"metric": "|z| of the replay error among the model's simulated "
                                                             "recordings (run-to-run consistency)",
                                                   "nominal": abs(z_old), "improved": abs(z_new)}})
                        current = cand
                        floor_cur = _Floor(cand, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
                        ev.floor = floor_cur.floor
                        J_cur = ev.J(current, "held")
                        jfl = jfl2
        except Exception as err:   # noqa: BLE001
            ninfo["error"] = repr(err)
        stochastic["noise_level"] = ninfo
        timing["noise_s"] = time.perf_counter() - t
        self.t, self.current, self.J_cur, self.floor_cur, self.jfl = t, current, J_cur, floor_cur, jfl

    def uncertainty(self):
        """Standard errors from the final model's own recordings, widened by the replay's roughness
        at the final values: for every parameter of the adopted deterministic effects, on the fit
        samples against the final model's floor, its spread over that floor's simulated recordings
        (``sigma_boot``, :meth:`spread`) and the roughness of its profile, the others held
        (``sigma_rough``, :func:`roughness`); ``sigma`` becomes
        ``sqrt(max(sigma_fit, sigma_boot)^2 + sigma_rough^2)`` (``sigma_fit``: the fit's own, kept
        in the report)."""
        fj, found, selected, base = self.fit_judge, self.found, self.selected, self.base
        t = time.perf_counter()
        det = [f for f in selected if f.effect.kind == "deterministic"]
        if fj is None or not det:
            return
        rows = {fe["effect"]: fe for fe in found if fe.get("kind") == "deterministic"}
        if any(f.key not in rows for f in det):
            return
        theta = {f.key: np.array([p["value"] for p in rows[f.key]["params"]], float) for f in det}

        def spec_of(th):
            return _spec_without([dataclasses.replace(f, theta=th[f.key]) if f.key in th else f for f in selected],
                                 base)

        try:
            fl = fj.floor(self.current)
            rp0 = fj.replay(spec_of(theta))
            # the rebuilt model must be the final one (else the profile would not be about it)
            if not rp0.ok or abs(fj.D(rp0, fl) - fj.D(fj.replay(self.current), fl)) > 1e-9 * max(fj.D(rp0, fl), 1.0):
                return

            def D_at(key, i, v):
                try:
                    rp = fj.replay(spec_of(_moved(theta, key, i, v)))
                except Exception:     # noqa: BLE001 - not a valid model there (a damping below 0)
                    return float("inf")
                return fj.D(rp, fl) if rp.ok else float("inf")

            boot = self.spread(det, rows, theta, spec_of, fl, rp0)
            for f in det:
                for i, p in enumerate(rows[f.key]["params"]):
                    s_fit = p.get("sigma") or 0.0
                    r = roughness(lambda v: D_at(f.key, i, v), p["value"], s_fit)
                    s_boot = boot.get((f.key, i))
                    if r is None and s_boot is None:
                        continue
                    p["sigma_fit"] = s_fit
                    if s_boot is not None:
                        p["sigma_boot"] = s_boot
                    if r is not None:
                        p["sigma_rough"] = r
                    p["sigma"] = float(math.hypot(max(s_fit, s_boot or 0.0), r or 0.0))
        except Exception as err:   # noqa: BLE001 - the fit's standard errors stand
            _log(self.opt, f"roughness profile failed: {err!r}")
        self.timing["uncertainty_s"] = time.perf_counter() - t

    def spread(self, det: list, rows: dict, theta: dict, spec_of, fl, rp0) -> dict:
        """``{(effect, i): sigma}``: each adopted parameter's spread over the final model's
        simulated recordings of the fit samples (:func:`spread_over_recordings`; the Jacobian by
        central differences of one fit standard error, at least 1e-4 of the value); empty when a
        difference cannot be replayed."""
        fj = self.fit_judge
        idx = [(f.key, i) for f in det for i in range(len(theta[f.key]))]
        r0 = fj.residual(rp0, fl)
        J = np.zeros((len(r0), len(idx)))
        for c, (k, i) in enumerate(idx):
            v = theta[k][i]
            h = max(rows[k]["params"][i].get("sigma") or 0.0, 1e-4 * abs(v), 1e-12)
            side = []
            for d in (h, -h):
                try:
                    rp = fj.replay(spec_of(_moved(theta, k, i, v + d)))
                except ValueError:     # not a valid model there
                    return {}
                if not rp.ok:
                    return {}
                side.append(fj.residual(rp, fl))
            J[:, c] = (side[0] - side[1]) / (2 * h)
        if not np.all(np.isfinite(J)):
            return {}
        s = spread_over_recordings(J, fj.sim_residuals(rp0, fl))
        return {key: float(v) for key, v in zip(idx, s) if np.isfinite(v)}

    def level_at_floor(self, current, s0: float):
        """Open-loop records: the drive-noise level at which the fit samples' prewhitened window errors
        are at the model's own run-to-run floor (floor ratio 1; Brent's method on the log level,
        1 % tolerance) and its standard error (the data's D is one draw: its relative spread over the
        floor's simulated recordings, halved, D falling as the level squared); (None, None) when 1/10
        to 1000x the current level ``s0`` does not bracket it."""
        from scipy.optimize import brentq
        fj = self.fit_judge
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

    def validate(self):
        """The improved model against the nominal on the held-out data (replay, force residual, open-loop windows)."""
        opt, data, timing, t, obs, f_band = self.opt, self.data, self.timing, self.t, self.obs, self.f_band
        W, res_nom, olw_nom, fl, ctl_err, x_eq = self.W, self.res_nom, self.olw_nom, self.fl, self.ctl_err, self.x_eq
        judge, jfl0, ev, current, floor_cur, jfl = self.judge, self.jfl0, self.ev, self.current, self.floor_cur, self.jfl
        # ---------------------------------------------------------------- validation on held-out data
        t = time.perf_counter()
        held = data.held if data.held.any() else data.fit
        res_new = obs.run(current, snap_every=W)
        r_nom_band = band_rms(res_nom.r, held, data.rate, f_band)
        r_new_band = band_rms(res_new.r, held, data.rate, f_band)
        floor_band = band_rms(floor_cur.resB.r, floor_cur.simB.held if floor_cur.simB.held.any() else floor_cur.simB.fit,
                              data.rate, f_band)
        J_nom_held = fl.floor.ms(res_nom.r, held)         # each model against its own floor
        J_new_held = ev.floor.ms(res_new.r, held)
        hcols = [b for b in range(data.shape[1]) if held[:, b].any()]
        rp_new = replay(current, data, seed=opt.floor_seeds[0] + 7)
        hm = np.zeros_like(held)
        hm[:, hcols] = data.valid[:, hcols]
        # the judge's replay (noise-free, held-out trials) and the run-to-run floor of each model
        jrp_nom, jrp_new = jfl0.replay, jfl.replay
        cu_nom, cy_nom = judge.rms(jrp_nom)
        cu_new, cy_new = judge.rms(jrp_new)
        cu_rr, cy_rr = jfl.sigma_u, jfl.sigma_y
        z_nom = judge.consistency(jrp_nom, jfl0)
        z_new = judge.consistency(jrp_new, jfl)
        headline = {
            "command_rms_N": {"nominal": cu_nom, "improved": cu_new, "floor_nominal": jfl0.sigma_u, "floor": cu_rr},
            "position_rms_m": {"nominal": cy_nom, "improved": cy_new, "floor_nominal": jfl0.sigma_y, "floor": cy_rr},
            "floor_ratio": {"nominal": judge.floor_ratio(jrp_nom, jfl0), "improved": judge.floor_ratio(jrp_new, jfl)},
            "consistency_z": {"nominal": z_nom, "improved": z_new, "critical": judge.t_q},
            "stable": {"nominal": jrp_nom.ok, "improved": jrp_new.ok},
            "held_out_trials": [int(data.trial_ids[c]) for c in judge.cols], "held_out_samples": judge.n,
            "floor_recordings": judge.K, "replays": judge.sims,
            "reference": "none (open-loop record)" if data.open_loop else (
                "recorded" if x_eq is None else "equivalent (controller mismatch)"),
            "controller_check_rel": ctl_err,
            "how": ("noise-free closed-loop replay of the held-out samples (recorded reference, the model's controller) "
                    "against the recorded command and measurement; floor: RMS difference of simulated recordings of "
                    "the same model from its replay (run to run)") if not data.open_loop else (
                f"noise-free open-loop prediction of the held-out samples over {judge.L / data.rate:.3g} s windows, each "
                "re-initialised from the measurement (the recorded command and known force drive the model), against "
                "the measurement; floor: RMS difference of the same windows simulated with the model's noise (run to "
                "run); the command is the input (its error is 0)")}
        olw_new = open_loop_windows(current, obs, res_new, W)

        def _olw_rms(o):
            if o is None:
                return None
            sel = np.array([held[o["start"][i], o["trial"][i]] for i in range(len(o["start"]))])
            return float(np.sqrt(np.mean(o["drift_m"][sel] ** 2))) if sel.any() else None

        def _fall(a, b):
            return float(1 - b / a) if a and a > 0 else None

        validation = {
            "held_out_samples": int(held.sum()),
            "force_residual_rms_N": {"nominal": r_nom_band, "improved": r_new_band, "floor": floor_band,
                                     "fall": _fall(r_nom_band, r_new_band)},
            "J_held": {"nominal": J_nom_held, "improved": J_new_held, "fall": _fall(J_nom_held, J_new_held)},
            "replay_command_rms_N": {"nominal": cu_nom, "improved": cu_new, "run_to_run": cu_rr,
                                     "fall": _fall(cu_nom, cu_new)},
            "replay_position_rms_m": {"nominal": cy_nom, "improved": cy_new, "run_to_run": cy_rr,
                                      "fall": _fall(cy_nom, cy_new)},
            "open_loop_drift_rms_m": {"nominal": _olw_rms(olw_nom), "improved": _olw_rms(olw_new),
                                      "window_s": W / data.rate},
        }
        timing["validate_s"] = time.perf_counter() - t
        self.t, self.held, self.res_new, self.rp_new, self.jrp_nom, self.jrp_new = t, held, res_new, rp_new, jrp_nom, jrp_new
        self.z_nom, self.z_new, self.headline, self.validation = z_nom, z_new, headline, validation

    def report(self):
        """The report dict (and, with ``out``, the files); ``_improved_spec`` is the improved model."""
        nominal, out, opt, data, T0, timing = self.nominal, self.out, self.opt, self.data, self.T0, self.timing
        t, spec0, kind, notes, rp_nom, obs = self.t, self.spec0, self.kind, self.notes, self.rp_nom, self.obs
        f_band, W, found, stochastic, res_nom, olw_nom = self.f_band, self.W, self.found, self.stochastic, self.res_nom, self.olw_nom
        fl, judge, loc, loc_arrays, ctx, ev = self.fl, self.judge, self.loc, self.loc_arrays, self.ctx, self.ev
        Jf0, Jh0, Jhb, neff, tol_ad, current = self.Jf0, self.Jh0, self.Jhb, self.neff, self.tol_ad, self.current
        J_cur, floor_cur, steps, joint, held, res_new = self.J_cur, self.floor_cur, self.steps, self.joint, self.held, self.res_new
        rp_new, jrp_nom, jrp_new, z_nom, z_new, headline = self.rp_new, self.jrp_nom, self.jrp_new, self.z_nom, self.z_new, self.headline
        validation = self.validation
        # ---------------------------------------------------------------- sparse regression (unexplained)
        sparse = None
        adequate_final = bool(jrp_new.ok and z_new <= judge.t_q)
        if opt.sparse and not adequate_final:
            t = time.perf_counter()
            sparse = _sparse(data, res_new, ctx, f_band)
            timing["sparse_s"] = time.perf_counter() - t

        # the verdict is the replay's: consistent with the run-to-run floor (calibrated z) or not
        adequate_final = bool(jrp_new.ok and z_new <= judge.t_q)
        if not found:
            verdict = "model adequate" if (jrp_nom.ok and z_nom <= judge.t_q) else "unexplained residual"
        else:
            verdict = "effects found" if adequate_final else "effects found, residual remains"
        timing["total_s"] = time.perf_counter() - T0
        report = {
            "nanostage_diagnosis": 1,
            "verdict": verdict,
            "units": axis_units(kind),
            "replay": headline,
            "found": found,
            "recording": {"source": data.source, "rate_hz": data.rate, "trials": int(data.shape[1]),
                          "open_loop": data.open_loop, "axis": data.axis,
                          "samples": int(data.valid.sum()), "duration_s": float(data.valid.sum() / data.rate),
                          "split": data.split, "fit_trials": [int(data.trial_ids[c]) for c in ev.fit_cols],
                          "held_out_trials": [int(data.trial_ids[c]) for c in ev.held_cols], "notes": notes},
            "nominal": {"name": spec0.preset.name, "source": str(nominal) if not isinstance(nominal, (dict,)) else "<mapping>"},
            "observer": {"bandwidth_hz": obs.f_o, "smoothing_hz": data.smooth_hz, "band_hz": f_band,
                         "evaluations": ev.evals, "evaluation_s": ev.seconds},
            "noise": {"floor_check_J": fl.msB, "n_eff_held": neff, "adequacy_tolerance": tol_ad},
            "predict": {
                "closed_loop_replay": compare_replay(data, rp_nom),
                "force_residual": {"rms_N": band_rms(res_nom.r, data.fit | data.held, data.rate, f_band),
                                   "floor_rms_N": loc["floor_rms_N"], "J_fit": Jf0, "J_held": Jh0,
                                   "observer_failures": res_nom.bad},
                "open_loop_windows": None if olw_nom is None else {
                    "window_s": W / data.rate, "windows": int(len(olw_nom["start"])),
                    "rms_drift_m": float(np.sqrt(np.mean(olw_nom["drift_m"] ** 2))),
                    "rms_force_N": float(np.sqrt(np.mean(olw_nom["force_N"] ** 2)))},
            },
            "locate": loc,
            "selection": {"steps": steps, "J_held_start": Jhb, "J_held_final": J_cur, "adequate_final": adequate_final,
                          "second_start": self.path.get("second_start")},
            "joint_fit": joint,
            "stochastic": stochastic,
            "sparse_regression": sparse,
            "validation": validation,
            "improved_model": {"name": current.preset.name},
            "timing_s": timing,
        }
        convert_units(report, kind)       # every parameter unit on the axis of the stage (rotary: rad, N·m, kg·m²)
        if out is not None:
            from .report import write_report
            write_report(out, report, current, spec0, data,
                         {"res_nom": res_nom, "res_new": res_new, "loc": loc_arrays, "rp_nom": rp_nom, "rp_new": rp_new,
                          "held": held, "f_band": f_band, "floor": floor_cur}, plots=opt.plots)
            report["timing_s"]["total_s"] = time.perf_counter() - T0
        report["_improved_spec"] = current
        return report

    def thr(self, J):
        neff = self.neff
        return max(6 * math.sqrt(max(J, 1.0) / neff), 0.05 * max(J - 1, 0.0), 0.02)

    def candidates(self, current, selected, banned):
        """(effect, key of the adopted effect it replaces or None) for every candidate of this step. A
        member of an exclusive group (alternative friction models) whose one adopted member is the only
        conflict is a *replacement*: fitted on the model without that member (the more flexible member
        the data preferred first may not be the physics: Dahl for a GMS, Dahl for a Stribeck curve)."""
        base, ctx, keys = self.base, self.ctx, self.keys
        taken = {f.key for f in selected}
        todo = []
        for k in keys:
            e = self.library[k]      # bound to this recording: its applicability may depend on it
            if k in taken or k in banned or e.kind not in ("deterministic", "integer"):
                continue
            clash = self.library.exclusive_of(k) & taken
            if taken & set(e.not_after):
                continue                 # e.g. the Coulomb level after position-dependent friction (its level dF_0)
            if len(clash) > 1:
                continue
            rep = next(iter(clash)) if clash else None
            try:
                cur = current if rep is None else _spec_without([f for f in selected if f.key != rep], base)
            except Exception:     # noqa: BLE001 - e.g. an asymmetry larger than the friction left without rep
                continue
            if e.applicable(cur) is not None:
                continue
            todo.append((e, rep))
        return todo

    def fit_all(self, todo, current, selected, J_fit_cur):
        """Fit every candidate (with the selected effects re-fitted, from step 2 on); the ones whose
        fit failed in :attr:`failed` (effect key -> error), for the step's report."""
        opt, ex, base, ctx, ev, token = self.opt, self.ex, self.base, self.ctx, self.ev, self.token
        self.failed = {}
        blob = self.blob
        # slow (multi-parameter, stiff) candidates first for a better balance; the fits are
        # collected in this order on every path (ties of the score below keep it)
        todo.sort(key=lambda er: -len(er[0].params(current, ctx)))

        def on(rep):
            """(model, selected effects) a candidate replacing ``rep`` (or none) is fitted on."""
            if rep is None:
                return current, selected
            sel = [f for f in selected if f.key != rep]
            return _spec_without(sel, base), sel

        if ex is not None:
            out = [None] * len(todo)
            for i, (f, err, n, sec) in ex.map(_candidate_task, ((i, (token, blob, e) + on(rep)
                                                                  + (J_fit_cur, ev.floor, ctx))
                                                                 for i, (e, rep) in enumerate(todo))):
                ev.evals += n
                ev.seconds += sec
                if err is not None:
                    _log(opt, f"fit {todo[i][0].key} failed: {err}")
                    self.failed[todo[i][0].key] = err
                out[i] = f
                if f is not None:
                    f.replaces = todo[i][1]
            fits = [f for f in out if f is not None]
        else:
            def _one(er):
                e, rep = er
                try:
                    f = _fit_candidate(e, *on(rep), J_fit_cur, ev, ctx, base, opt.own_floor, opt.floor_seeds[0])
                except Exception as err:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
                    _log(opt, f"fit {e.key} failed: {err!r}")
                    self.failed[e.key] = repr(err)
                    return None
                if f is not None:
                    f.replaces = rep
                return f
            # the compiled kernels release the GIL: candidates are fitted on parallel threads
            current.compiled()
            if opt.n_jobs > 1 and len(todo) > 1:
                from concurrent.futures import ThreadPoolExecutor
                with ThreadPoolExecutor(opt.n_jobs) as pool:
                    fits = [f for f in pool.map(_one, todo) if f is not None]
            else:
                fits = [f for f in map(_one, todo) if f is not None]
        fits.sort(key=lambda f: f.J_held * (1 + opt.complexity * len(f.theta)))
        return fits

    def judge_rows(self, fits, jfl, s0, first):
        """Replay of every candidate against the current model's run-to-run floor ``jfl``."""
        opt, judge = self.opt, self.judge
        out = []
        D_floor = float(np.mean(s0.sum(axis=1))) / max(judge.n, 1)
        for f in fits:
            rp = judge.replay(f.spec)
            c = judge.compare(jfl, rp, fl_blocks=s0)
            share = c.T / max(c.D_before - D_floor, 1e-300)
            if c.accepted and not first and share < opt.min_share:
                c.accepted = False
                c.why = (f"removes {100 * share:.0f} % of the remaining replay excess over the floor "
                         f"(< {100 * opt.min_share:.0f} %)")
            bound = list(f.on_bound) + ([n for n in f.joint.on_bound if not n.startswith(f.key + ".")]
                                        if f.joint is not None else [])
            why = c.why
            if c.accepted and bound:
                why = f"not identified: {', '.join(bound)} at its bound"
            elif c.accepted and _unidentified(f):
                why = "not identified: every parameter's standard error exceeds its value"
            elif c.accepted and _at_nominal(f, self.spans(f)):
                why = (f"the data do not move it: every parameter within {NOMINAL_Z:g} standard errors of "
                       "the current model's value")
            elif c.accepted and f.effect.kind == "integer" and all(
                    f.nominal.get(n) is not None and float(f.nominal[n]) == float(v) for n, v in zip(f.names, f.theta)):
                # the improvement is the re-fit of the others, not this effect
                why = "no change: the current model's value"
            out.append({"fit": f, "rp": rp, "cmp": c, "on_bound": bound, "ok": c.accepted and why == c.why,
                        "why": why})
        return out

    def spans(self, f: FitResult):
        """The ranges (hi - lo) of candidate ``f``'s parameters on the base model, or None."""
        try:
            return [p.hi - p.lo for p in f.effect.params(self.base, self.ctx)]
        except Exception:     # noqa: BLE001 - no ranges: the standard errors alone decide
            return None

    def refine_integer(self, j, selected, jfl, s0, reach: int = 2):
        """An integer candidate (delay) re-chosen by the replay of the fit samples among the values within
        ``reach`` of the force observer's pick (the others held); its row judged again if it moved."""
        base, fit_judge, ctx = self.base, self.fit_judge, self.ctx
        f = j["fit"]
        e = f.effect
        try:
            prev = _spec_without(selected, base)
        except Exception:     # noqa: BLE001 - the observer's pick stays
            return j
        p = e.params(prev, ctx_for(ctx, selected))[0]
        v0 = int(round(f.theta[0]))
        best = (float("inf"), v0, f.spec)
        for v in range(max(int(p.lo), v0 - reach), min(int(p.hi), v0 + reach) + 1):
            sp = f.spec if v == v0 else e.apply(prev, [v])
            rp = fit_judge.replay(sp)
            d = fit_judge.D(rp, jfl) if rp.ok else float("inf")
            if d < best[0]:
                best = (d, v, sp)
        if best[1] == v0:
            return j
        f2 = dataclasses.replace(f, spec=best[2], theta=np.array([float(best[1])]), joint=None, refined=True)
        j2 = self.judge_rows([f2], jfl, s0, first=not selected)[0]
        j2["why"] += " (chosen by the replay)"
        return j2

    def refine_located(self, j, selected, jfl, s0):
        """A mode located on the transfer (``located_mode``) refined by the replay of the fit samples:
        its frequency, damping and mass fraction as the ``structural_mode`` parameters, started at the
        transfer's fit (small finite-difference steps: a lightly damped mode's replay changes over a
        fraction of its bandwidth). The errors are weighted by the floor of the model with the mode
        (an open-loop floor's prewhitening weighs most where its model is quiet: a rigid model's floor
        would weigh the mode's band and the windows' re-initialisation of the mode), renewed after each
        of :data:`REFINE_MODE_PASSES` passes. The row keeps its key, with the refined mode and its
        standard errors."""
        base, fit_judge, ctx = self.base, self.fit_judge, self.ctx
        f = j["fit"]
        i = int(round(float(f.theta[0])))
        m = f.effect.mode(f.theta)
        sm = Mode().bound(ctx)
        bf = dataclasses.replace(f, key="structural_mode", effect=sm, names=["f", "zeta", "fraction"],
                                 theta=np.array([m["f_hz"], m["zeta"], m["fraction"]]), on_bound=[], joint=None)
        sel = [s for s in selected if s.key != f.replaces]
        ref, fl = None, fit_judge.floor(f.spec)
        for _ in range(REFINE_MODE_PASSES):
            r = _refine_by_replay(bf, sel, base, ctx_for(ctx, sel), fit_judge, fl, max_nfev=30, diff_step=4e-3)
            if r is None or r["at_bound"]:
                break
            ref, bf = r, dataclasses.replace(bf, theta=r["theta"])
            fl = fit_judge.floor(r["spec"])
        if ref is None:
            return j
        (fr, z, phi), sig = ref["theta"], ref["sigma"]
        e2 = f.effect.with_mode(i, {"f_hz": float(fr), "zeta": float(z), "fraction": float(phi)})
        derived = {"f": float(fr), "zeta": float(z), "fraction": float(phi),
                   "f_sigma": float(sig[0]), "zeta_sigma": float(sig[1]), "fraction_sigma": float(sig[2])}
        f2 = dataclasses.replace(f, spec=ref["spec"], effect=e2, derived=derived, refined=True, joint=None)
        j2 = self.judge_rows([f2], jfl, s0, first=not selected)[0]
        j2["why"] += " (refined by the replay)"
        return j2

    def replay_start(self, f, sel, jfl):
        """Start of the replay refinement of a candidate the observer left at a bound (where the replay
        may not move it: a Stribeck curve at v_s -> 0 is flat in both parameters): the best of the
        effect's own starts by the replay of the fit samples."""
        base, fit_judge, ctx = self.base, self.fit_judge, self.ctx
        e = f.effect
        c2 = ctx_for(ctx, sel)
        try:
            prev = _spec_without(sel, base)
            ps = e.params(prev, c2)
        except Exception:     # noqa: BLE001 - no start of its own: the observer's
            return None
        best = (float("inf"), None)
        for th in e.starts(prev, c2):
            th = [p.clip(v) for p, v in zip(ps, th)]
            try:
                rp = fit_judge.replay(e.apply(prev, th))
            except Exception:     # noqa: BLE001 - an invalid start is no start
                continue
            d = fit_judge.D(rp, jfl) if rp.ok else float("inf")
            if d < best[0]:
                best = (d, th)
        return best[1]

    def refine_rows(self, judged, selected, jfl, s0) -> list:
        """Every stable candidate refined by the replay (:func:`_refine_by_replay`) and judged again
        before candidates are compared: the force observer proposes and gives the start, the replay
        of the fit samples sets the values (at the observer's values a flexible wrong effect can
        beat the right one whose fit is off where the replay is sensitive). Candidates with more
        than ``REFINE_MAX_PARAMS`` parameters are refined only among the ``REFINE_TOP`` best replays.
        From the second step on, the adopted effects are refined with the candidate (at most
        ``REFINE_JOINT_MAX`` parameters in all). A refined row replaces the observer's."""
        base, fit_judge, refine, ctx = self.base, self.fit_judge, self.refine, self.ctx
        if not refine:
            return judged
        judged = [self.refine_integer(j, selected, jfl, s0) if j["fit"].effect.kind == "integer" else j
                  for j in judged]
        judged = [self.refine_located(j, selected, jfl, s0) if j["fit"].key == "located_mode" and j["cmp"].stable
                  else j for j in judged]
        stable = [j for j in judged if j["cmp"].stable and j["fit"].effect.kind == "deterministic"]
        by_replay = sorted(stable, key=lambda j: j["cmp"].D_after)
        by_observer = sorted(stable, key=lambda j: j["fit"].J_held)
        top = {id(j) for j in by_replay[:REFINE_TOP]}
        # every one-parameter candidate too (a level the observer fits off where the replay is sensitive
        # may rank low on both: a Coulomb level behind multi-parameter fits of the observer residual)
        small = [j for j in by_replay[:REFINE_PROPOSALS] + by_observer[:REFINE_PROPOSALS]
                 if len(j["fit"].theta) <= REFINE_MAX_PARAMS] + [j for j in stable if len(j["fit"].theta) == 1]
        # and every small one the observer's fit made worse than no change: where the observer sees
        # little (a noisy 1 kHz observer, J near 1) its fits are noise, yet the replay may see the
        # effect clearly (a friction slope at 150x the floor); these start from their own starts
        lost = [j for j in stable if j["cmp"].T < 0 and len(j["fit"].theta) <= REFINE_MAX_PARAMS]
        small += lost
        stable = [j for j in stable if any(j is x for x in small) or id(j) in top]
        out = []
        refits = []          # (row, the adopted effects alone at the row's joint values)
        for j in judged:
            f = j["fit"]
            if any(j is x for x in stable):
                sel = [s for s in selected if s.key != f.replaces]
                n_sel = sum(len(s.theta) for s in sel if s.effect.kind == "deterministic")
                blind = any(j is x for x in lost)
                ref = _refine_by_replay(f, sel, base, ctx_for(ctx, sel), fit_judge, jfl,
                                        start=self.replay_start(f, sel, jfl) if f.on_bound or blind else None,
                                        grid=blind,
                                        max_nfev=8 if len(f.theta) <= REFINE_MAX_PARAMS else 3,
                                        with_selected=0 < n_sel and n_sel + len(f.theta) <= REFINE_JOINT_MAX)
                if ref is not None:
                    # the observer's figures of the refined model (the table shows them; they only rank)
                    J_fit, J_held, ne = self.ev.both(ref["spec"])
                    f2 = dataclasses.replace(f, spec=ref["spec"], theta=ref["theta"], sigma=ref["sigma"],
                                             on_bound=ref["at_bound"], derived=f.effect.derived(base, ref["theta"]),
                                             joint=ref["joint"], refined=True, J_fit=J_fit, J_held=J_held,
                                             n_eff_held=ne)
                    j2 = self.judge_rows([f2], jfl, s0, first=not selected)[0]
                    if ref["joint"] is not None and f.replaces is None:
                        refits.append((j2, _spec_moved(sel, ref["joint"].theta, base), ref["joint"]))
                    j2["why"] += " (refined by the replay)"
                    out.append(j2)
                    continue
            out.append(j)
        self.own_share(refits, jfl)
        return out

    def own_share(self, refits, jfl) -> None:
        """Candidates refined together with the adopted effects are credited with what they add to
        the adopted effects' re-fit, not with the re-fit: the best re-fit of the adopted effects
        alone that their joint refinements reached (``refits``: (row, model of the adopted effects
        alone at the row's joint values, the joint fit); best by the replay of the fit samples)
        is the baseline a row must beat beyond the floor to stay adoptable, and is kept as
        :attr:`path` ``["refit"]`` (:meth:`keep_refit`). (A ripple of 6e-8 N amplitude, no change,
        was adopted for the 70 % of the replay error a re-fit of the friction slope removed; each
        candidate's joint refinement reaches a different re-fit.)"""
        self.path["refit"] = None
        best, d_best = None, self.fit_D(self.path["current"])
        for _, spec, jf in refits:
            try:
                d = self.fit_D(spec)
            except Exception:     # noqa: BLE001 - not a model: no baseline
                continue
            if d < d_best:
                best, d_best = (spec, jf), d
        if best is None:
            return
        rp0 = self.judge.replay(best[0])
        if not rp0.ok:
            return
        self.path["refit"] = best
        for j, _, _ in refits:
            if not j["ok"]:
                continue
            c = self.judge.compare(jfl, j["rp"], rp_base=rp0)
            if not c.accepted:
                j["ok"] = False
                j["why"] = (f"adds nothing beyond a re-fit of the adopted effects (replay D {c.D_before:.4g} "
                            f"without it, {c.D_after:.4g} with it: {c.why}) (refined by the replay)")

    def keep_refit(self) -> bool:
        """When no candidate is adopted: the adopted effects' best re-fit their candidates' joint
        refinements reached (:meth:`own_share`) replaces their values if the held-out replay is not
        worse; the floors are renewed. Returns whether it was kept."""
        path = self.path
        best = path.pop("refit", None)
        if best is None:
            return False
        spec, jf = best
        if self.replay_D(spec) > self.replay_D(path["current"]):
            return False
        self.adopt(jf)
        path["current"] = spec
        self.renew_floor(spec)
        return True

    def adopt(self, jf, new=None):
        """Keep the re-fitted values of the selected deterministic effects (joint fit ``jf``), and of
        ``new``, the effect being adopted, when ``jf`` was fitted with it (after the selected ones)."""
        path = self.path
        selected = path["selected"]
        base = self.base
        k = 0
        for f, fe in zip(selected, path["found"]):
            if f.effect.kind != "deterministic":
                continue
            n = len(f.theta)
            f.theta, f.sigma = jf.theta[k:k + n], jf.sigma[k:k + n]
            fe["params"] = f.params()
            fe["derived"] = f.effect.derived(base, f.theta)
            k += n
        if new is not None and new.effect.kind == "deterministic" and len(jf.theta) >= k + len(new.theta):
            n = len(new.theta)
            new.theta, new.sigma = jf.theta[k:k + n], jf.sigma[k:k + n]
            new.derived = new.effect.derived(base, new.theta)

    def keep_refined(self, f, ref) -> None:
        """Keep a replay refinement ``ref`` (:func:`_refine_by_replay`) of the adopted effect ``f``: the
        joint values of every adopted effect, or ``f``'s own."""
        if ref["joint"] is not None:
            self.adopt(ref["joint"])
            return
        path = self.path
        k = next(i for i, s in enumerate(path["selected"]) if s is f)
        f.theta, f.sigma = ref["theta"], ref["sigma"]
        path["found"][k]["params"] = f.params()
        path["found"][k]["derived"] = f.effect.derived(self.base, f.theta)

    def replay_D(self, spec):
        path = self.path
        judge = self.judge
        rp = judge.replay(spec)
        return judge.D(rp, path["jfl"]) if rp.ok else float("inf")

    def fit_D(self, spec):
        """Replay error on the fit samples (floor units of the current model)."""
        path = self.path
        fit_judge = self.fit_judge
        if fit_judge is None:
            return self.replay_D(spec)
        rp = fit_judge.replay(spec)
        return fit_judge.D(rp, path["jfl"]) if rp.ok else float("inf")

    def renew_floor(self, spec):
        """The noise floors of the current model ``spec`` re-estimated (after every change)."""
        path = self.path
        opt, data, obs, judge, ev = self.opt, self.data, self.obs, self.judge, self.ev
        path["floor"] = _Floor(spec, data, obs.f_o, opt.floor_seeds, data.smooth_hz)
        ev.floor = path["floor"].floor
        path["J_fit"], path["J_cur"], _ = ev.both(spec)
        path["jfl"] = judge.floor(spec)

    def backward(self, last) -> bool:
        """Backward elimination after the adoption of ``last``: each earlier adopted deterministic
        effect is re-tested by removing it (the others, ``last`` with them, refined by the replay
        without it when that is better): if the model with it does not replay the held-out data
        better beyond the current floor (the same test as its adoption), the later effects made it
        redundant (e.g. a mass error adopted where a structural mode replayed as well, the mode
        adopted next): it is withdrawn and not proposed again. Returns whether one was."""
        path = self.path
        selected = path["selected"]
        opt, base, judge, fit_judge, refine, ctx = self.opt, self.base, self.judge, self.fit_judge, self.refine, self.ctx
        changed = False
        for e in [s for s in selected if s is not last and s.effect.kind == "deterministic"]:
            rest = [s for s in selected if s is not e]
            try:
                spec_wo = _spec_without(rest, base)
            except Exception:     # noqa: BLE001 - not a valid model without it: it stays
                continue
            best_wo = (self.fit_D(spec_wo), spec_wo, None)
            others = [s for s in rest if s is not last]
            if refine and last.effect.kind == "deterministic":
                n_o = sum(len(s.theta) for s in others if s.effect.kind == "deterministic")
                ref = _refine_by_replay(last, others, base, ctx_for(ctx, others), fit_judge, path["jfl"],
                                        with_selected=0 < n_o and n_o + len(last.theta) <= REFINE_JOINT_MAX)
                if ref is not None and not (ref["joint"].on_bound if ref["joint"] is not None
                                            else ref["at_bound"]):
                    d = self.fit_D(ref["spec"])
                    if d < best_wo[0]:
                        best_wo = (d, ref["spec"], ref)
            # the adoption test of ``e`` on top of the model without it: the floor (simulated
            # recordings) of the model without it, the current model's replay as the candidate
            fl_wo = judge.floor(best_wo[1])
            if not fl_wo.replay.ok:
                continue
            c = judge.compare(fl_wo, path["jfl"].replay)
            if c.accepted:
                continue          # the data demand it on top of the later effects
            i = next(k for k, s in enumerate(selected) if s is e)
            selected.pop(i)
            gone = path["found"].pop(i)
            path["banned"].add(e.key)
            if best_wo[2] is not None:
                self.keep_refined(last, best_wo[2])
            path["current"] = best_wo[1]
            path["found"][-1].setdefault("withdraws", []).append(
                {"effect": gone["effect"], "step": gone["step"], "params": gone["params"],
                 "replay": c.row(), "why": f"redundant after {last.key}: {c.why}"})
            _log(opt, f"backward: {gone['effect']} withdrawn after {last.key} ({c.why})")
            changed = True
        return changed

    def forward(self):
        """Forward selection from ``base``: each step (:meth:`step`) fits every candidate (re-fitting
        the selected ones with it); the force observer proposes and ranks, the closed-loop replay
        decides (:class:`.judge.ReplayJudge`): the best candidate whose replay is stable and
        beyond the run-to-run floor of the current model is adopted, its statistically
        equivalent alternatives are reported, never adopted too. When that path ends beyond its
        own floor, a second walk starts from step 1's runner-up (:meth:`second_start`) and is kept
        only if its held-out replay is better beyond the first path's floor (the adoption test);
        the path's ``second_start`` says what both found. Returns :attr:`path`."""
        ctx0 = self.ctx
        self.first_step = None
        a = self.walk()
        second = self.second_start(a)
        if second is None:
            return a
        ctx_a = self.ctx
        self.ctx = ctx0
        _log(self.opt, f"second start: {second['fit'].key} first (the path from {a['steps'][0]['accepted']} "
                       "left a residual beyond its floor)")
        b = self.walk(first=second)
        judge = self.judge
        c = judge.compare(a["jfl"], b["jfl"].replay) if b["jfl"].replay.ok else None
        chosen = b if c is not None and c.accepted else a
        chosen["second_start"] = {
            "first": second["fit"].key, "chosen": chosen is b,
            "effects": [fe["effect"] for fe in b["found"]], "greedy_effects": [fe["effect"] for fe in a["found"]],
            "replay_D": judge.D(b["jfl"].replay, a["jfl"]) if b["jfl"].replay.ok else None,
            "replay_D_greedy": judge.D(a["jfl"].replay, a["jfl"]),
            "why": c.why if c is not None else "unstable"}
        if chosen is a:
            self.ctx = ctx_a
        self.path = chosen
        self.ev.floor = chosen["floor"].floor
        _log(self.opt, f"second start: {[fe['effect'] for fe in chosen['found']]} kept "
                       f"({chosen['second_start']['why']})")
        return chosen

    def walk(self, first=None) -> dict:
        """One forward path from ``base`` (:attr:`path`): steps until none is adopted; ``first``,
        a judged candidate of the first step, is adopted there in place of the step's choice."""
        self.path = {"current": self.base, "J_cur": self.Jhb, "J_fit": self.Jfb, "floor": self.fl, "steps": [],
                     "selected": [], "found": [], "jfl": self.jfl0, "banned": set()}
        self.ev.floor = self.fl.floor
        for step in range(1, self.opt.max_steps + 1):
            if not self.step(step, first if step == 1 else None):
                break
        return self.path

    def second_start(self, a: dict):
        """The first step's runner-up, when the greedy path ``a`` ends with a replay beyond its own
        run-to-run floor: the best adoptable candidate of step 1 other than the adopted one and the
        ones confounded with it (by the selection's complexity-penalised replay). Forward selection
        commits to its first choice; where that choice is a stand-in that absorbs what two other
        effects do (12 Maxwell-slip blocks for a compliant joint plus a Stribeck curve), the path
        from the runner-up is the only way back. None when the path ends at its floor or step 1 had
        no other adoptable candidate."""
        if self.first_step is None or not a["found"] or a["steps"][0].get("accepted") is None:
            return None
        judge = self.judge
        if judge.consistency(a["jfl"].replay, a["jfl"]) <= judge.t_q or not a["jfl"].replay.ok:
            return None
        st = a["steps"][0]
        skip = {st["accepted"], *st["confounded_with"]}
        ok = sorted([j for j in self.first_step["judged"] if j["ok"] and j["fit"].key not in skip], key=self.rank)
        return ok[0] if ok else None

    def step(self, step: int, first=None) -> bool:
        """Forward step ``step``: propose, fit, judge and refine every candidate, choose one
        (:meth:`choose`), record the step and adopt the choice (:meth:`adopt_best`). Returns
        whether the selection goes on. ``first``: a judged candidate of an earlier walk's first
        step, adopted at step 1 from that step's record (:meth:`second_start`)."""
        if first is not None:
            rec = dict(self.first_step["record"], accepted=first["fit"].key, confounded_with=[],
                       second_start=True)
            self.path["steps"].append(rec)
            self.adopt_best(step, first, [], [])
            return True
        opt, judge = self.opt, self.judge
        path = self.path
        selected = path["selected"]
        self.refit_selected(step)
        current, J_cur, jfl = path["current"], path["J_cur"], path["jfl"]
        z_cur = judge.consistency(jfl.replay, jfl)
        if z_cur <= judge.t_q:
            # the current model's replay is within its run-to-run floor (calibrated z): nothing to explain
            path["steps"].append({"step": step, "J_held_before": J_cur, "replay_D_before": judge.D(jfl.replay, jfl),
                                  "replay_z_before": z_cur, "z_critical": judge.t_q,
                                  "floor_rms": {"command_N": jfl.sigma_u, "position_m": jfl.sigma_y},
                                  "threshold": None, "accepted": None, "confounded_with": [], "candidates": [],
                                  "stopped": "replay within the run-to-run floor"})
            _log(opt, f"step {step}: replay z {z_cur:.3g} <= {judge.t_q:.3g}: within the floor, stop")
            return False
        todo = self.candidates(current, selected, path["banned"])
        fits = self.fit_all(todo, current, selected, path["J_fit"])
        if not fits:
            return False
        s0 = judge.sim_blocks(jfl.replay, jfl)
        judged = self.judge_rows(fits, jfl, s0, first=not selected)
        D_cur = judge.D(jfl.replay, jfl)
        judged = self.refine_rows(judged, selected, jfl, s0)
        best, conf, alts = self.choose(judged, jfl)
        rows = self.step_rows(judged, J_cur)
        kept = best is None and self.keep_refit()
        path["steps"].append({"step": step, "J_held_before": J_cur, "replay_D_before": D_cur,
                              "replay_z_before": z_cur, "z_critical": judge.t_q,
                              "floor_rms": {"command_N": jfl.sigma_u, "position_m": jfl.sigma_y},
                              "threshold": min((r["threshold"] for r in rows), default=None),
                              "accepted": best["fit"].key if best else None,
                              "confounded_with": [j["fit"].key for j in conf or []], "candidates": rows,
                              "refit_kept": kept, "failed": dict(self.failed)})
        if step == 1:
            self.first_step = {"judged": judged, "record": path["steps"][-1]}
        _log(opt, f"step {step}: replay D {D_cur:.4g} -> " + ", ".join(
            f"{r['effect']} {r['replay']['D_after']:.4g} ({r['why']})" for r in rows[:5])
             + f"; accepted {best['fit'].key if best else None}")
        if best is None:
            return False
        self.adopt_best(step, best, conf, alts)
        return True

    def refit_selected(self, step: int) -> None:
        """From the second step on: continue the fit of the selected effects alone first (a candidate
        is credited only with what it adds to them), kept if the replay of the fit samples is better
        and the held-out replay not worse; the floors renewed if it was."""
        base, ctx, ev = self.base, self.ctx, self.ev
        path = self.path
        selected = path["selected"]
        refitted = False
        for _ in range(3 if step > 1 else 0):
            # continue the fit of the selected effects alone first: a candidate is credited only
            # with what it adds to them (kept if the replay of the fit samples is better and the
            # held-out replay not worse)
            rf = joint_fit(selected, base, ev, ctx_for(ctx, selected), min_effects=1, max_iter=8)
            if rf is None or rf.on_bound or not self.fit_D(rf.spec) < self.fit_D(path["current"]) \
                    or self.replay_D(rf.spec) > self.replay_D(path["current"]):
                break
            self.adopt(rf)
            path.update(current=rf.spec, J_cur=rf.J_held, J_fit=rf.J_fit)
            refitted = True
        if refitted:
            self.renew_floor(path["current"])
        if step > 1 and self.refine:
            self.rerefine()

    def rerefine(self) -> None:
        """The selected deterministic effects refined by the replay again, weighted by the current
        model's own floor, kept on the same terms as :meth:`refit_selected`'s; the floors renewed
        if they were. A candidate refined together with them is then credited with what it adds,
        not with a refinement of theirs its own would have continued (a fractional delay of 1e-6
        samples, no change, was adopted for 29 % of the replay error a Stribeck curve had left
        after 8 evaluations). On open-loop records also because the floor's prewhitening depends
        on the model: the effect was refined under the floor of the model without it."""
        path = self.path
        selected = path["selected"]
        det = [s for s in selected if s.effect.kind == "deterministic"]
        if not det:
            return
        last = det[-1]
        others = [s for s in selected if s is not last]
        n_o = sum(len(s.theta) for s in others if s.effect.kind == "deterministic")
        ref = _refine_by_replay(last, others, self.base, ctx_for(self.ctx, others), self.fit_judge, path["jfl"],
                                with_selected=0 < n_o and n_o + len(last.theta) <= REFINE_JOINT_MAX, max_nfev=20)
        if ref is None or (ref["joint"].on_bound if ref["joint"] is not None else ref["at_bound"]):
            return
        if not self.fit_D(ref["spec"]) < self.fit_D(path["current"]) \
                or self.replay_D(ref["spec"]) > self.replay_D(path["current"]):
            return
        self.keep_refined(last, ref)
        path["current"] = ref["spec"]
        self.renew_floor(ref["spec"])

    def rank(self, j: dict) -> float:
        """A judged candidate's rank: its replay with the selection's complexity penalty per
        parameter (a 12-block GMS must do clearly better than the one Coulomb level it contains)."""
        return j["cmp"].D_after * (1 + self.opt.complexity * len(j["fit"].theta))

    def choose(self, judged: list, jfl) -> tuple:
        """``(best, confounded, alternatives)`` among the judged candidates of a step (best None:
        none adoptable)."""
        judge = self.judge
        ok = sorted([j for j in judged if j["ok"]], key=self.rank)
        best = conf = None
        alts = []
        if ok:
            top = ok[0]
            # candidates the held-out replay cannot tell from the best: confounded
            tfl = judge.floor(top["fit"].spec) if len(ok) > 1 else None     # recordings of the best's model
            equiv = [top] + [j for j in ok[1:] if judge.equivalent(jfl, j["rp"], top["rp"], of_b=tfl)[0]]
            # adopt one of them: not a quantity the nominal states as known (a data-sheet force
            # constant) unless the data demand it, then the simplest, then the best replay
            best = min(equiv, key=lambda j: (j["fit"].key in self.library.known, len(j["fit"].theta), j["cmp"].D_after))
            # a simpler adoptable candidate wins unless the more complex one improves on it beyond the
            # floor (e.g. position-dependent friction over a plain Coulomb level it contains)
            for j in sorted(ok, key=lambda j: (len(j["fit"].theta), j["cmp"].D_after)):
                if len(j["fit"].theta) >= len(best["fit"].theta) or j["fit"].key in self.library.known:
                    continue
                # the threshold from recordings of the simpler model (the current model's scatter with
                # the distance from it: a candidate at the floor was "within the floor" of one 28x above)
                if not judge.compare(jfl, best["rp"], rp_base=j["rp"], of_base=judge.floor(j["fit"].spec)).accepted:
                    conf = [best] + [x for x in equiv if x is not best]
                    best = j
                    break
            conf = [j for j in (conf or equiv) if j is not best]
            alts = [{"effect": j["fit"].key, "title": j["fit"].title, "params": j["fit"].params(),
                     "derived": j["fit"].derived, "replay_D": j["cmp"].D_after} for j in conf]
        return best, conf, alts

    def step_rows(self, judged: list, J_cur: float) -> list:
        """The report's rows of a step's candidates, best replay first."""
        opt, judge = self.opt, self.judge
        rows = []
        for j in judged:
            f, c = j["fit"], j["cmp"]
            r = _fit_row(f, J_cur, self.thr(J_cur), opt.complexity)
            r.update({"J_improvement": r.pop("improvement"), "J_significant": r.pop("significant"),
                      "replay": c.row(), "improvement": c.T, "threshold": c.threshold_sim,
                      "block_se": c.se_block, "stable": c.stable, "on_bound": j["on_bound"],
                      "significant": j["ok"], "why": j["why"],
                      "replay_rms": dict(zip(("command_N", "position_m"), judge.rms(j["rp"])))})
            rows.append(r)
        rows.sort(key=lambda r: r["replay"]["D_after"])
        return rows

    def adopt_best(self, step: int, best: dict, conf: list, alts: list) -> None:
        """Adopt the chosen candidate ``best`` at ``step``: the member of its exclusive group it
        replaces leaves, the selected effects keep their re-fit, the adopted effects are refined
        together by the replay, the floors are renewed, redundant earlier effects withdrawn
        (:meth:`backward`) and the next proposals located in what the new model leaves."""
        data, obs, f_band, base, fit_judge, refine = self.data, self.obs, self.f_band, self.base, self.fit_judge, self.refine
        ctx, ev = self.ctx, self.ev
        path = self.path
        selected = path["selected"]
        bf = best["fit"]
        gone = None
        if bf.replaces is not None:
            # a replacement: the member of its exclusive group adopted earlier leaves the model (and
            # does not come back)
            i = next(i for i, f in enumerate(selected) if f.key == bf.replaces)
            selected.pop(i)
            gone = path["found"].pop(i)
            path["banned"].add(bf.replaces)
        new_spec = bf.spec
        if bf.joint is not None:
            self.adopt(bf.joint)             # the selected effects were re-fitted with this one
        elif step > 1:
            # an integer effect (delay) was fitted with the others held: re-fit them now, kept if the
            # replay is not worse
            refit = joint_fit(selected + [bf], base, ev, ctx_for(ctx, selected + [bf]), min_effects=1)
            if refit is not None and not refit.on_bound and self.replay_D(refit.spec) <= best["cmp"].D_after:
                self.adopt(refit, new=bf)
                new_spec = refit.spec
        if refine and bf.effect.kind == "deterministic":
            # the adopted effects refined together by the replay of the fit samples (output error),
            # kept off their bounds and if the held-out replay is not worse
            n_sel = sum(len(f.theta) for f in selected if f.effect.kind == "deterministic")
            ref = _refine_by_replay(bf, selected, base, ctx_for(ctx, selected), fit_judge, path["jfl"],
                                    with_selected=0 < n_sel and n_sel + len(bf.theta) <= REFINE_JOINT_MAX)
            if ref is not None and not (ref["joint"].on_bound if ref["joint"] is not None else ref["at_bound"]) \
                    and self.replay_D(ref["spec"]) <= self.replay_D(new_spec):
                if ref["joint"] is not None:
                    self.adopt(ref["joint"])
                new_spec, bf.theta, bf.sigma = ref["spec"], ref["theta"], ref["sigma"]
                bf.derived = bf.effect.derived(base, bf.theta)
                bf.refined = True
        selected.append(bf)
        # a confounded alternative that states a known quantity (force constant) is not adopted later;
        # the others may be, if they add beyond the floor on top of this one (then they were not
        # confounded: the data demand both, and the earlier "confounded" mark is withdrawn)
        path["banned"] |= {j["fit"].key for j in conf if j["fit"].key in self.library.known}
        for fe in path["found"]:
            if bf.key in fe["confounded_with"]:
                fe["confounded_with"] = [k for k in fe["confounded_with"] if k != bf.key]
                fe["alternatives"] = [a for a in fe["alternatives"] if a["effect"] != bf.key]
                fe.setdefault("also_adopted", []).append(bf.key)
        path["found"].append({"effect": bf.key, "title": bf.title, "kind": bf.effect.kind, "step": step,
                              "params": bf.params(), "derived": bf.derived, "expressible": bf.expressible,
                              "confounded_with": [j["fit"].key for j in conf], "alternatives": alts,
                              "J_held": bf.J_held, "replay": best["cmp"].row(),
                              "refined_by_replay": bool(bf.refined),
                              "replaces": None if gone is None else {"effect": gone["effect"], "step": gone["step"],
                                                                     "params": gone["params"]}})
        path["current"] = new_spec
        self.renew_floor(new_spec)         # the run-to-run floor re-estimated after every adoption
        if self.backward(bf):
            self.renew_floor(path["current"])
        # the next proposals come from what the adopted model leaves: ripple periods, spectral peaks and
        # lines located again in its force residual (the nominal's was dominated by the adopted effect)
        self.ctx = dataclasses.replace(ctx, **_proposals(data, obs.run(new_spec), path["floor"], obs.f_o, f_band, ctx))


def _sparse(data, res, ctx, f_band):
    """SINDy-style regression of the remaining (band-limited) residual on state functions."""
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
