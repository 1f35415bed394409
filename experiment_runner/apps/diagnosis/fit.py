"""Fit and choose: each hypothesis added to the model, fitted, and judged on held-out data.

Cost
    The whitened force residual (:class:`.predict.NoiseFloor`): its mean square ``J`` is 1
    when the model leaves only what a perfect model leaves (noise and quantization seen
    through the observer). Parameters are fitted by a bounded Gauss-Newton /
    Levenberg-Marquardt (:func:`gauss_newton`, forward-difference Jacobians) on the
    whitened residual of the *fit* samples (when every damped step is rejected although the
    linear model predicts a large gain -- many correlated parameters -- the trust-region solver
    :func:`scipy.optimize.least_squares` continues); every residual evaluation is one run of the
    compiled force observer (a few ms per second of data), so fits are fast, and the
    problem is nearly linear in most parameters (the observer follows the measurement,
    so friction and joint states are those of the measured trajectory): linear ones
    converge in one or two iterations.
Uncertainty
    From the Jacobian at the optimum: ``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual
    mean square, inflated by the residual's correlation time (effective sample count).
Use (:mod:`.tasks`, :mod:`.selection`)
    Every candidate is fitted on top of the current model -- from the second step on together
    with the adopted effects, all their parameters free again (:func:`fit_with`; integer ones
    held) -- and its held-out ``J`` is taken against its *own* noise floor (a candidate that
    changes the drive or the dynamics changes what noise leaves; if it does not fit the fit set
    better than the current model, the larger of its own-floor and current-floor ``J`` counts).
    The force residual proposes, ranks and gives start values; the closed-loop replay decides
    (:mod:`.judge`, :mod:`.selection`). After the selection the adopted effects are fitted jointly
    (:func:`joint_fit`); parameters correlating above 0.95 across effects are reported as
    confounded. Quantization is estimated from the lattice of the measured positions
    (:func:`estimate_lattice`); drive noise from the residual spectrum where drive noise dominates
    the floor (:func:`fit_noise_level`).
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, signal

from .budget import checkpoint
from .data import DiagData
from .effects.base import Effect, Param
from .model import ModelSpec
from .observer import Observer
from .predict import NoiseFloor, sim_batch

__all__ = ["Evaluator", "FitResult", "fit_effect", "fit_with", "joint_fit", "estimate_lattice", "fit_noise_level",
           "sparse_regression", "JointEffect", "Transform", "bad_point", "n_eff", "spec_with", "spec_moved"]


# --------------------------------------------------------------------------- evaluation
class Evaluator:
    """Whitened residuals of a model on the fit and held-out samples.

    Parameters
    ----------
    obs : Observer
        The force observer on the data.
    floor : NoiseFloor
        The base model's force-residual floor (whitening).
    max_fit_seconds : float, optional
        Cap of the fit set [s of data] (whole trials, in order).
    """

    def __init__(self, obs: Observer, floor: NoiseFloor, max_fit_seconds: float = 3.0):
        self.obs = obs
        self.floor = floor
        d = obs.data
        self.data = d
        B = d.shape[1]
        fit_cols = [b for b in range(B) if d.fit[:, b].any()]
        held_cols = [b for b in range(B) if d.held[:, b].any()]
        # cap the fit set (speed): whole trials, in order, up to max_fit_seconds
        if len(fit_cols) > 1:
            keep, tot = [], 0.0
            for b in fit_cols:
                if keep and tot >= max_fit_seconds:
                    break
                keep.append(b)
                tot += d.fit[:, b].sum() / d.rate
            fit_cols = keep
        self.fit_cols = np.array(fit_cols, int)
        self.held_cols = np.array(held_cols, int)
        self.same = set(fit_cols) == set(held_cols)
        self.evals = 0
        self.seconds = 0.0
        self._lock = threading.Lock()

    def _run(self, spec, cols):
        checkpoint()          # a search whose budget is spent stops here (:mod:`.budget`)
        t = time.perf_counter()
        res = self.obs.run(spec, cols=cols)
        with self._lock:
            self.evals += 1
            self.seconds += time.perf_counter() - t
        return res

    def fit_vector(self, spec: ModelSpec, bad: float = 1e3) -> np.ndarray:
        """Whitened residual on the fit samples (the least-squares vector); ``bad`` in every
        sample where the observer diverged.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        bad : float, optional
            The value of every sample when the observer diverges.

        Returns
        -------
        numpy.ndarray
        """
        res = self._run(spec, self.fit_cols)
        m = self.data.fit[:, self.fit_cols]
        if res.bad:           # not whitened: a diverged residual is no spectrum
            return np.full(int(m.sum()), bad)
        return self.floor.whiten(res.r, m)[m]

    def J(self, spec: ModelSpec, which: str = "held", floor: NoiseFloor | None = None) -> float:
        """Whitened mean square of ``spec``'s force residual on the held-out (or fit) samples; inf when the observer diverges.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        which : {'held', 'fit'}, optional
            The samples.
        floor : NoiseFloor, optional
            The floor whose units are used (default the evaluator's).

        Returns
        -------
        float
        """
        cols = self.held_cols if which == "held" else self.fit_cols
        mask = (self.data.held if which == "held" else self.data.fit)[:, cols]
        res = self._run(spec, cols)
        if res.bad:
            return float("inf")
        return (floor or self.floor).ms(res.r, mask)

    def both(self, spec: ModelSpec, floor: NoiseFloor | None = None) -> tuple[float, float, float]:
        """(J_fit, J_held, n_eff_held) in one or two observer runs.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        floor : NoiseFloor, optional
            The floor whose units are used (default the evaluator's).

        Returns
        -------
        tuple of float
        """
        fl = floor or self.floor
        cols = np.union1d(self.fit_cols, self.held_cols)
        res = self._run(spec, cols)
        if res.bad:
            return float("inf"), float("inf"), 1.0
        idx = {c: i for i, c in enumerate(cols)}
        mf = np.zeros(res.r.shape, bool)
        mh = np.zeros(res.r.shape, bool)
        for c in self.fit_cols:
            mf[:, idx[c]] = self.data.fit[:, c]
        for c in self.held_cols:
            mh[:, idx[c]] = self.data.held[:, c]
        wh = fl.whiten(res.r, mh)
        return fl.ms(res.r, mf), float(np.sum(wh[mh] ** 2) / max(1, mh.sum())), n_eff(wh, mh)


def n_eff(w: np.ndarray, mask: np.ndarray, max_lag: int = 200) -> float:
    """Effective number of independent samples of a (whitened) residual over ``mask``.

    Parameters
    ----------
    w : numpy.ndarray
        (T, B) whitened residual.
    mask : numpy.ndarray
        (T, B) bool.
    max_lag : int, optional
        Largest lag of the autocorrelation summed.

    Returns
    -------
    float
    """
    n = int(mask.sum())
    if n < 10:
        return float(max(n, 1))
    rho_sum = 0.0
    x = np.where(mask, w, 0.0)
    c0 = np.sum(x * x)
    if c0 <= 0:
        return float(n)
    for lag in range(1, min(max_lag, x.shape[0] - 1)):
        c = np.sum(x[lag:] * x[:-lag]) / c0
        if c < 0.02:
            break
        rho_sum += c
    return float(n / (1.0 + 2.0 * rho_sum))


# --------------------------------------------------------------------------- one effect
@dataclass
class FitResult:
    """One fitted effect: its values, uncertainties, model and scores (a report row is made of it).

    Parameters
    ----------
    key, title : str
        The effect's key and title.
    names, units : list of str
        Its parameters.
    theta : numpy.ndarray
        Fitted values.
    sigma : numpy.ndarray
        Their standard errors (NaN: none).
    corr : numpy.ndarray, optional
        Their correlation matrix.
    spec : ModelSpec
        The model with the effect.
    J_fit, J_held : float
        Whitened force-residual mean square on the fit and held-out samples.
    n_eff_held : float
        Effective held-out sample count.
    evals : int
        Model evaluations.
    seconds : float
        Wall time [s].
    nominal : dict
        The base model's values of the parameters.
    derived : dict
        Derived physical quantities.
    expressible : bool
        The fitted model is a preset the simulator runs.
    note : str
        What the fit noted.
    on_bound : list of str
        Parameters at a bound.
    joint : FitResult, optional
        Fitted together with the adopted effects (:func:`fit_with`).
    replaces : str, optional
        The adopted effect of its exclusive group it replaces.
    refined : bool
        Values from the closed-loop replay (output error), not the observer.
    effect : Effect, optional
        The (bound) effect fitted.
    """
    key: str
    title: str
    names: list
    units: list
    theta: np.ndarray
    sigma: np.ndarray
    corr: np.ndarray | None
    spec: ModelSpec
    J_fit: float
    J_held: float
    n_eff_held: float
    evals: int
    seconds: float
    nominal: dict
    derived: dict = field(default_factory=dict)
    expressible: bool = True
    note: str = ""
    on_bound: list = field(default_factory=list)
    joint: "FitResult | None" = None    # fitted together with the selected effects (fit_with)
    replaces: str | None = None          # an adopted effect of its exclusive group this one replaces
    refined: bool = False                # values from the closed-loop replay (output error), not the observer
    effect: "Effect | None" = None       # the (bound) effect fitted: what applies theta to a model

    def params(self) -> list[dict]:
        """The parameters as report rows: ``name``, ``unit``, ``value``, ``sigma`` (None: no standard error).

        Returns
        -------
        list of dict
        """
        return [{"name": n, "unit": u, "value": float(v), "sigma": float(s) if np.isfinite(s) else None,
                 "nominal": self.nominal.get(n)} for n, u, v, s in zip(self.names, self.units, self.theta, self.sigma)]


class Transform:
    """Parameter <-> optimiser variable: log for log params, linear scaled otherwise.

    Parameters
    ----------
    params : list of Param
        The fitted parameters.
    """

    def __init__(self, params: list[Param]):
        self.p = params
        self.scale = np.array([1.0 if p.log else max(abs(p.hi - p.lo) / 10.0, abs(p.x0), 1e-12) for p in params])

    def to_z(self, theta):
        """Optimiser variables of parameter values ``theta``.

        Parameters
        ----------
        theta : sequence of float
            Parameter values.

        Returns
        -------
        numpy.ndarray
        """
        return np.array([math.log(max(t, 1e-300)) if p.log else t / s for t, p, s in zip(theta, self.p, self.scale)])

    def to_theta(self, z):
        """Parameter values of optimiser variables ``z``.

        Parameters
        ----------
        z : sequence of float
            Optimiser variables.

        Returns
        -------
        numpy.ndarray
        """
        return np.array([math.exp(v) if p.log else v * s for v, p, s in zip(z, self.p, self.scale)])

    def bounds(self):
        """The parameters' bounds in optimiser variables.

        Returns
        -------
        tuple of numpy.ndarray
            ``(lo, hi)``.
        """
        lo = [math.log(max(p.lo, 1e-300)) if p.log else p.lo / s for p, s in zip(self.p, self.scale)]
        hi = [math.log(p.hi) if p.log else p.hi / s for p, s in zip(self.p, self.scale)]
        return np.array(lo), np.array(hi)

    def dtheta_dz(self, theta):
        """Derivative of each parameter with respect to its optimiser variable at ``theta``.

        Parameters
        ----------
        theta : sequence of float
            Parameter values.

        Returns
        -------
        numpy.ndarray
        """
        return np.array([t if p.log else s for t, p, s in zip(theta, self.p, self.scale)])


def bad_point(ms: float) -> float:
    """The residual per sample of a bad point (no model, or one the observer or the simulator
    cannot run) of a least-squares fit whose start has mean square ``ms``: a million times the
    start's cost, never below 1e3 (nor above 1e100) -- worse than any model that runs, however bad
    that one is (a flat 1e3 would be better than a nominal at J 4e8).

    Parameters
    ----------
    ms : float
        Mean square of the fit's start.

    Returns
    -------
    float

    Examples
    --------
    >>> bad_point(4e8), bad_point(0.5), bad_point(float("inf"))
    (20000000.0, 1000.0, 1000.0)
    """
    return min(max(1e3, 1e3 * math.sqrt(ms)), 1e100) if math.isfinite(ms) else 1e3


def fit_effect(effect: Effect, base: ModelSpec, ev: Evaluator, ctx: dict, max_nfev: int | None = None,
               starts: list | None = None) -> FitResult | None:
    """Fit ``effect`` added to ``base`` on the fit samples; judge it on the held-out ones.

    Parameters
    ----------
    effect : Effect
        The candidate.
    base : ModelSpec
        The model the effects are added to.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        What was located on the recording.
    max_nfev : int, optional
        Most residual evaluations.
    starts : list, optional
        Start vectors (default the effect's :meth:`.effects.base.Effect.starts`).

    Returns
    -------
    FitResult or None
        None when the effect does not apply to ``base`` or is not fitted here.
    """
    if effect.applicable(base) is not None or effect.kind not in ("deterministic", "integer"):
        return None
    effect = effect.bound(ctx)
    t0 = time.perf_counter()
    count = [0]
    params = effect.params(base, ctx)
    names = [p.name for p in params]
    units = [p.unit for p in params]
    if effect.kind == "integer":
        p = params[0]
        best = None
        for v in range(int(p.lo), int(p.hi) + 1):
            spec = effect.apply(base, [v])
            vec = ev.fit_vector(spec)
            count[0] += 1
            c = float(np.mean(vec ** 2))
            if best is None or c < best[0]:
                best = (c, v, spec)
        c, v, spec = best
        theta = np.array([float(v)])
        sigma = np.array([np.nan])        # an integer found by search: no standard error (not "± 0")
        corr = None
    else:
        tr = Transform(params)
        lo, hi = tr.bounds()
        best = None

        def fun(z):
            count[0] += 1
            th = tr.to_theta(z)
            try:
                spec = effect.apply(base, th)
            except Exception:          # noqa: BLE001 - an invalid parameter set is a bad fit
                return np.full(n_res, bad)
            try:
                return ev.fit_vector(spec, bad)
            except ValueError:         # a model the simulator refuses (a joint too stiff for its sub-steps)
                return np.full(n_res, bad)

        n_res = int(ev.data.fit[:, ev.fit_cols].sum())
        bad = bad_point(ev.J(base, "fit"))
        cand = starts or effect.starts(base, ctx)
        iters = max_nfev or 8
        # rank the starts by their cost, run Gauss-Newton from the best two
        scored = []
        for th0 in cand:
            th0 = [p.clip(v) for p, v in zip(params, th0)]
            z0 = np.clip(tr.to_z(th0), lo, hi)
            r0 = fun(z0)
            scored.append((float(r0 @ r0), z0, r0))
        scored.sort(key=lambda s: s[0])
        n_run = 2 if len(params) <= 4 else 1
        # starts the cost cannot rank (e.g. a ripple at zero amplitude: every period costs the same) are all
        # run, up to four
        ties = sum(1 for s in scored if s[0] <= scored[0][0] * (1 + 1e-9))
        for c0, z0, r0 in scored[:max(n_run, min(ties, 4))]:
            sol = gauss_newton(fun, z0, lo, hi, r0=r0, max_iter=iters)
            if best is None or sol["cost"] < best["cost"]:
                best = sol
        if best is None:
            return None
        theta = tr.to_theta(best["x"])
        spec = effect.apply(base, theta)
        Jm = best["jac"]
        npts = max(1, len(best["fun"]))
        s2 = best["cost"] / max(1, npts - len(theta))
        # correlation of the whitened residual inflates the variance
        infl = npts / max(1.0, n_eff(best["fun"][:, None], np.ones((npts, 1), bool)))
        try:
            if not np.all(np.isfinite(Jm)):
                raise np.linalg.LinAlgError("non-finite Jacobian")     # LAPACK would print to stdout
            cov_z = np.linalg.pinv(Jm.T @ Jm) * s2 * infl
            dz = tr.dtheta_dz(theta)
            cov = cov_z * np.outer(dz, dz)
            sigma = np.sqrt(np.maximum(np.diag(cov), 0.0))
            dd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
            corr = cov / np.outer(dd, dd)
        except np.linalg.LinAlgError:
            sigma = np.full(len(theta), np.nan)
            corr = None
    # at a bound (within 0.1 % of the range in the optimiser's variable, log or linear): "not identified"
    on_bound = []
    if effect.kind != "integer":
        zlo, zhi = tr.bounds()
        tol = 1e-3 * np.maximum(np.abs(zhi - zlo), 1e-300)
        on_bound = [p.name for p, z, a, b, t in zip(params, tr.to_z(theta), zlo, zhi, tol)
                    if abs(b - z) <= t or (abs(z - a) <= t and not getattr(p, "physical_lo", False))]
    J_fit, J_held, ne = ev.both(spec)
    return FitResult(key=effect.key, title=effect.title, names=names, units=units, theta=np.asarray(theta, float),
                     sigma=np.asarray(sigma, float), corr=corr, spec=spec, J_fit=J_fit, J_held=J_held, n_eff_held=ne,
                     evals=count[0] + 1, seconds=time.perf_counter() - t0, nominal=effect.nominal(base),
                     derived=effect.derived(base, theta), expressible=effect.expressible, on_bound=on_bound,
                     effect=effect)


def gauss_newton(fun, z0, lo, hi, r0=None, max_iter: int = 8, h: float = 1e-3, rtol: float = 1e-4) -> dict:
    """Bounded Levenberg-Marquardt on ``||fun(z)||^2`` with forward-difference Jacobians.

    Each iteration costs ``len(z) + 1`` residual evaluations (plus one per rejected step);
    a problem linear in ``z`` converges in one or two iterations. Returns dict with ``x``,
    ``fun``, ``cost`` (sum of squares), ``jac``, ``nfev``.

    Parameters
    ----------
    fun : callable
        ``fun(z)`` -> residual vector.
    z0 : numpy.ndarray
        Start.
    lo, hi : numpy.ndarray
        Bounds.
    r0 : numpy.ndarray, optional
        ``fun(z0)``, when known.
    max_iter : int, optional
        Most iterations.
    h : float, optional
        Relative finite-difference step.
    rtol : float, optional
        Stop when the cost falls by less than this fraction.

    Returns
    -------
    dict
    """
    z = np.array(z0, float)
    p = len(z)
    r = fun(z) if r0 is None else r0
    c = float(r @ r)
    nfev = 0 if r0 is not None else 1
    lam = 1e-4
    J = np.zeros((len(r), p))
    for _ in range(max_iter):
        for i in range(p):
            step = h if z[i] + h <= hi[i] else -h
            zi = z.copy()
            zi[i] += step
            J[:, i] = (fun(zi) - r) / step
            nfev += 1
        Q, R = np.linalg.qr(J)
        g = Q.T @ r
        D = np.sqrt(np.maximum(np.sum(J * J, axis=0), 1e-300))
        improved = False
        for _try in range(6):
            A = np.vstack([R, np.sqrt(lam) * np.diag(D)])
            b = np.concatenate([-g, np.zeros(p)])
            lb, ub = lo - z, hi - z
            sol = optimize.lsq_linear(A, b, bounds=(np.minimum(lb, 0.0), np.maximum(ub, 0.0)), method="bvls")
            dz = sol.x
            zn = np.clip(z + dz, lo, hi)
            rn = fun(zn)
            nfev += 1
            cn = float(rn @ rn)
            if cn < c:
                improved = True
                lam = max(lam * 0.1, 1e-9)
                break
            lam *= 10.0
        if not improved:
            # every damped step rejected: at a minimum the linear model predicts no gain either; a
            # large predicted gain means the Marquardt damping, stepped tenfold, did not reach a
            # step the curvature allows (many correlated parameters: a Maxwell-slip fit) -- the
            # trust-region solver (scaled by the Jacobian's columns) takes over from here
            dz0 = np.linalg.lstsq(R, -g, rcond=None)[0]
            pred = c - float(np.sum((r + J @ dz0) ** 2))
            if pred > 1e-2 * c:
                sol = optimize.least_squares(fun, z, bounds=(lo, hi), method="trf", x_scale="jac", diff_step=h,
                                             ftol=rtol, max_nfev=max_iter * (p + 1) * 2)
                nfev += sol.nfev
                if 2 * sol.cost < c:
                    z, r, c, J = sol.x, sol.fun, float(sol.fun @ sol.fun), sol.jac
            break
        gain = (c - cn) / max(c, 1e-300)
        z, r, c = zn, rn, cn
        if gain < rtol or np.max(np.abs(dz)) < 1e-9:
            break
    return {"x": z, "fun": r, "cost": c, "jac": J, "nfev": nfev}


# --------------------------------------------------------------------------- joint fit
class JointEffect(Effect):
    """Several fitted effects applied in sequence, all parameters free.

    Parameters
    ----------
    parts : list of tuple
        ``(effect, number of its parameters)``, in the order applied.
    thetas : list, optional
        The parts' fitted values (each part's bounds are relative to its predecessors').
    """

    def __init__(self, parts: list[tuple[Effect, int]], thetas: list | None = None):
        self.key = "+".join(e.key for e, _ in parts)
        self.title = " + ".join(e.title for e, _ in parts)
        self.parts = parts
        self.thetas = thetas      # fitted values of the parts: bounds of each relative to its predecessors

    def params(self, spec, ctx):
        out = []
        s = spec
        for k, (e, _) in enumerate(self.parts):
            ps = e.params(s, ctx)
            out += [Param(f"{e.key}.{p.name}", p.unit, p.lo, p.hi, p.x0, p.log, physical_lo=p.physical_lo) for p in ps]
            if self.thetas is not None:
                # e.g. the asymmetry's bounds scale with the Coulomb force an earlier part added
                s = e.apply(s, self.thetas[k])
        return out

    def apply(self, spec, theta):
        i = 0
        s = spec
        for e, n in self.parts:
            s = e.apply(s, theta[i:i + n])
            i += n
        return s


def spec_with(selected: list[FitResult], base: ModelSpec) -> ModelSpec:
    """``base`` with the ``selected`` effects at their current values (stochastic and integer ones
    first, as :func:`fit_with` builds them).

    Parameters
    ----------
    selected : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.

    Returns
    -------
    ModelSpec
    """
    spec = base
    for f in selected:
        if f.effect.kind != "deterministic":
            spec = f.effect.apply(spec, f.theta)
    for f in selected:
        if f.effect.kind == "deterministic":
            spec = f.effect.apply(spec, f.theta)
    return spec


def spec_moved(selected: list[FitResult], theta, base: ModelSpec) -> ModelSpec:
    """:func:`spec_with` with the deterministic ``selected`` effects at the joint values ``theta``
    (theirs, in order, first).

    Parameters
    ----------
    selected : list of FitResult
        The adopted effects.
    theta : sequence of float
        Joint values of the deterministic effects' parameters.
    base : ModelSpec
        The model the effects are added to.

    Returns
    -------
    ModelSpec
    """
    k, moved = 0, []
    for f in selected:
        if f.effect.kind == "deterministic":
            n = len(f.theta)
            f = dataclasses.replace(f, theta=np.asarray(theta[k:k + n], float))
            k += n
        moved.append(f)
    return spec_with(moved, base)


def joint_fit(fits: list[FitResult], base: ModelSpec, ev: Evaluator, ctx: dict,
              min_effects: int = 2, max_iter: int = 4) -> FitResult | None:
    """Re-fit all selected deterministic effects together (integer ones held at their value;
    at most ``max_iter`` Gauss-Newton iterations); None if there are fewer than
    ``min_effects`` of them.

    Parameters
    ----------
    fits : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        What was located on the recording.
    min_effects : int, optional
        Fewest deterministic effects to fit jointly.
    max_iter : int, optional
        Most Gauss-Newton iterations.

    Returns
    -------
    FitResult or None
    """
    cont = [f for f in fits if f.effect.kind == "deterministic"]
    fixed = [f for f in fits if f.effect.kind != "deterministic"]
    if len(cont) < max(1, min_effects):
        return None
    spec0 = base
    for f in fixed:
        spec0 = f.effect.apply(spec0, f.theta)
    joint = JointEffect([(f.effect, len(f.theta)) for f in cont], [f.theta for f in cont])
    x0 = np.concatenate([f.theta for f in cont])
    # bounds of each part relative to the model it is applied to
    r = fit_effect(joint, spec0, ev, ctx, starts=[list(x0)], max_nfev=max_iter)
    return r


def fit_with(effect: Effect, selected: list[FitResult], base: ModelSpec, ev: Evaluator, ctx: dict) -> FitResult | None:
    """Fit ``effect`` together with the already ``selected`` deterministic effects (all their
    parameters free again, started at their values; integer ones held), on top of ``base``.

    Forward selection with re-fitting: a second effect is judged with the first one re-fitted
    in its presence, so an error the first fit made while the second was missing does not
    stay in the residual. Returns the candidate's :class:`FitResult` (its own parameters;
    ``spec`` and ``J`` are the joint model's) with ``joint`` = the joint :class:`FitResult`.

    Parameters
    ----------
    effect : Effect
        The candidate.
    selected : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        What was located on the recording.

    Returns
    -------
    FitResult or None
    """
    cont = [f for f in selected if f.effect.kind == "deterministic"]
    if effect.kind != "deterministic" or not cont:
        return None
    spec0 = base
    for f in selected:
        if f.effect.kind != "deterministic":
            spec0 = f.effect.apply(spec0, f.theta)
    effect = effect.bound(ctx)
    n_e = len(effect.params(spec0, ctx))
    x_sel = list(np.concatenate([f.theta for f in cont]))
    cur = spec0
    for f in cont:
        cur = f.effect.apply(cur, f.theta)
    starts = effect.starts(cur, ctx)
    joint = JointEffect([(f.effect, len(f.theta)) for f in cont] + [(effect, n_e)],
                   [f.theta for f in cont] + [starts[0]])
    jf = fit_effect(joint, spec0, ev, ctx, starts=[x_sel + list(st) for st in starts])
    if jf is None:
        return None
    k = len(x_sel)
    th = jf.theta[k:]
    return FitResult(key=effect.key, title=effect.title, names=[p.name for p in effect.params(spec0, ctx)],
                     units=jf.units[k:], theta=th, sigma=jf.sigma[k:],
                     corr=None if jf.corr is None else jf.corr[k:, k:], spec=jf.spec, J_fit=jf.J_fit,
                     J_held=jf.J_held, n_eff_held=jf.n_eff_held, evals=jf.evals, seconds=jf.seconds,
                     nominal=effect.nominal(spec0), derived=effect.derived(cur, th), expressible=effect.expressible,
                     on_bound=[n.split(".", 1)[1] for n in jf.on_bound if n.startswith(effect.key + ".")],
                     joint=jf, effect=effect)


# --------------------------------------------------------------------------- stochastic
def estimate_lattice(y: np.ndarray, min_frac: float = 0.995):
    """Quantization step of measured positions, or None if they are not on a lattice.

    The smallest spacing between distinct values is the candidate; it is accepted if
    (nearly) every value is an integer multiple of it from the first value, then refined
    by least squares.

    Parameters
    ----------
    y : numpy.ndarray
        Measured positions [m].
    min_frac : float, optional
        Share of values that must lie on the lattice.

    Returns
    -------
    float or None
        The step [m].
    """
    y = np.asarray(y, float).ravel()
    y = y[np.isfinite(y)]
    if len(y) < 50:
        return None
    u = np.unique(y)
    if len(u) < 3:
        return None
    scale = max(np.max(np.abs(u)), 1e-300)
    du = np.diff(u)
    du = du[du > 1e-12 * scale]
    if not len(du):
        return None
    q1 = float(np.min(du))
    # the minimum could be an outlier: use the smallest spacing that many pairs share
    small = du[du < 1.5 * q1]
    q1 = float(np.median(small))
    n = np.round((u - u[0]) / q1)
    frac = np.abs((u - u[0]) / q1 - n)
    ok = frac < 0.02
    if ok.mean() < min_frac:
        return None
    q = float(np.sum((u - u[0])[ok] * n[ok]) / max(np.sum(n[ok] ** 2), 1e-300))
    return q


def noise_components(spec: ModelSpec, data: DiagData, obs_factory, seeds=(7001,), sigma_ref=None):
    """Force-residual spectra of simulated recordings: quantization-only and drive-noise parts.

    Returns (f, S_q, S_n, sigma_ref): with drive noise sigma, S(f) ~ S_q + (sigma/sigma_ref)^2 S_n.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    obs_factory : callable
        Builds the force observer of a simulated recording.
    seeds : tuple of int, optional
        Noise seeds.
    sigma_ref : float, optional
        Reference drive-noise RMS current [A].

    Returns
    -------
    tuple
    """
    s0 = spec.preset.stage.drive.noise_current_rms
    sigma_ref = sigma_ref or (s0 if s0 > 0 else 1e-3)
    out = []
    for sig in (0.0, sigma_ref):
        sp = spec.with_changes({"stage.drive.noise_current_rms": sig})
        psd = []
        for dd in sim_batch(sp, data, seeds):      # all seeds in one batch call
            ob = obs_factory(dd)
            r = ob.run(sp).r
            for b in range(r.shape[1]):
                m = dd.held[:, b] | dd.fit[:, b]
                if m.sum() < 256:
                    continue
                f, p = signal.welch(r[m, b], data.rate, nperseg=min(1024, int(m.sum())))
                psd.append(np.interp(np.linspace(0, data.rate / 2, 513), f, p))
        if not psd:
            raise ValueError("every trial is shorter than 256 samples: no residual spectrum to read a "
                             "drive-noise level from")
        out.append(np.mean(psd, axis=0))
    f = np.linspace(0, data.rate / 2, 513)
    return f, out[0], np.maximum(out[1] - out[0], 0.0), sigma_ref


def fit_noise_level(r_meas: np.ndarray, mask: np.ndarray, rate: float, comps, f_max: float | None = None,
                    f_min: float = 0.0) -> dict:
    """Drive-noise RMS current implied by the measured residual spectrum (robust median over
    the bands between ``f_min`` and ``f_max`` where drive noise dominates the floor).

    Parameters
    ----------
    r_meas : numpy.ndarray
        (T, B) measured force residual [N].
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    comps : tuple
        :func:`noise_components`' result.
    f_max : float, optional
        Upper end of the bands [Hz].
    f_min : float, optional
        Lower end [Hz].

    Returns
    -------
    dict
        ``ok`` and, when ok, ``sigma`` [A] with its uncertainty and the bands' ratios; else ``why``.
    """
    f, S_q, S_n, sigma_ref = comps
    psd = []
    for b in range(r_meas.shape[1]):
        m = mask[:, b]
        if m.sum() < 256:
            continue
        ff, p = signal.welch(r_meas[m, b], rate, nperseg=min(1024, int(m.sum())))
        psd.append(np.interp(f, ff, p))
    if not psd:
        return {"ok": False, "why": "not enough samples"}
    S_m = np.mean(psd, axis=0)
    inband = (np.arange(len(f)) >= 4) & (f >= f_min) & (f <= (f_max or f[-1]))
    dom = (S_n > 1.0 * S_q) & inband
    if dom.sum() < 6:
        dom = (S_n > 0.3 * S_q) & inband
    if dom.sum() < 3:
        return {"ok": False, "why": "drive noise is nowhere above the quantization part of the floor"}
    # ratio of summed power in groups of bins (unbiased, unlike a median of per-bin ratios),
    # median over the groups (robust to a group holding a deterministic remnant)
    idx = np.flatnonzero(dom)
    groups = np.array_split(idx, min(8, max(1, len(idx) // 4)))
    k2s = np.array([(S_m[g] - S_q[g]).sum() / max(S_n[g].sum(), 1e-300) for g in groups])
    k2 = float(np.median(k2s))
    sigma = sigma_ref * math.sqrt(max(k2, 0.0))
    sig_k2 = float(np.std(k2s) / math.sqrt(len(k2s))) if len(k2s) > 1 else abs(k2)
    # a deterministic remnant makes the low groups stand out: the group ratios disagree
    spread = float(np.std(k2s) / max(abs(np.mean(k2s)), 1e-300)) if len(k2s) > 1 else 1.0
    return {"ok": True, "group_ratios": [float(v) for v in k2s], "spread": spread, "sigma": sigma, "sigma_unc": sigma_ref * 0.5 * sig_k2 / max(math.sqrt(max(k2, 1e-12)), 1e-12),
            "bands": int(dom.sum()), "groups": len(groups), "f_lo": float(f[dom].min()), "f_hi": float(f[dom].max())}


# --------------------------------------------------------------------------- sparse regression
def sparse_regression(features: dict, target: np.ndarray, threshold: float = 0.05, n_iter: int = 10) -> dict:
    """Sequentially thresholded least squares (SINDy, Brunton et al. 2016) of ``target`` on
    ``features`` (name -> vector). Coefficients whose contribution (|c| * RMS(feature)) is
    below ``threshold`` times the target RMS are dropped, then the rest refitted.
    Returns {name: coef} of the surviving terms and the explained fraction.

    Parameters
    ----------
    features : dict
        Name -> feature vector.
    target : numpy.ndarray
        The target vector.
    threshold : float, optional
        Relative contribution below which a term is dropped.
    n_iter : int, optional
        Thresholding rounds.

    Returns
    -------
    dict
    """
    names = list(features)
    if not names or not len(target):
        return {"terms": {}, "explained": 0.0}
    X = np.column_stack([features[n] for n in names])
    if not (np.all(np.isfinite(X)) and np.all(np.isfinite(target))):
        # a non-finite feature (e.g. an observer that diverged): no regression (LAPACK would print to stdout)
        return {"terms": {}, "explained": 0.0, "note": "non-finite features or residual"}
    sc = np.sqrt(np.mean(X ** 2, axis=0))
    sc[sc == 0] = 1.0
    Xs = X / sc
    ty = float(np.sqrt(np.mean(target ** 2))) or 1.0
    active = np.ones(len(names), bool)
    coef = np.zeros(len(names))
    for _ in range(n_iter):
        if not active.any():
            break
        c, *_ = np.linalg.lstsq(Xs[:, active], target, rcond=None)
        coef[:] = 0.0
        coef[active] = c
        small = np.abs(coef) < threshold * ty
        new = active & ~small
        if np.array_equal(new, active):
            break
        active = new
    fitted = Xs @ coef
    expl = 1.0 - float(np.mean((target - fitted) ** 2) / max(np.mean(target ** 2), 1e-300))
    return {"terms": {n: float(c / s) for n, c, s, a in zip(names, coef, sc, active) if a}, "explained": expl}
