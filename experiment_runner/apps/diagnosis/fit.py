"""Fit one effect: bounded Gauss-Newton / Levenberg-Marquardt on the whitened force residual.

Fit
    :func:`fit_effect` fits an effect added to a model on the whitened residual of the *fit*
    samples (:class:`.evaluator.Evaluator`) by a bounded Gauss-Newton / Levenberg-Marquardt
    (:func:`gauss_newton`, forward-difference Jacobians; when every damped step is rejected
    although the linear model predicts a large gain -- many correlated parameters -- the
    trust-region solver :func:`scipy.optimize.least_squares` continues), in optimiser variables
    (:class:`Transform`: log for log parameters, scaled linear otherwise), and scores it on the
    held-out samples; an integer effect is searched over its range. Every residual evaluation is
    one run of the compiled force observer (a few ms per second of data), so fits are fast, and
    the problem is nearly linear in most parameters (the observer follows the measurement, so
    friction and joint states are those of the measured trajectory): linear ones converge in one
    or two iterations. A point the observer or the simulator cannot run costs
    :func:`bad_point` per sample.
Uncertainty
    From the Jacobian at the optimum: ``cov = s^2 (J^T J)^-1`` with ``s^2`` the residual
    mean square, inflated by the residual's correlation time (effective sample count,
    :func:`.evaluator.n_eff`). A parameter within 0.1 % of the range of a bound (in the
    optimiser's variable) is reported on it; an integer found by search has no standard error.
Result
    :class:`FitResult`: one fitted effect's values, uncertainties, model and scores (a report
    row is made of it). Fits of several effects together are in :mod:`.joint`.
Sparse regression
    :func:`sparse_regression`: sequentially thresholded least squares (SINDy) of a residual on
    named features, for what remains after the adopted effects (:mod:`.verdict`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize

from .effects.base import Effect, Param
from .evaluator import Evaluator, n_eff
from .model import ModelSpec

__all__ = ["FitResult", "fit_effect", "gauss_newton", "sparse_regression", "Transform", "bad_point"]


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
        """The parameters as report rows: ``name``, ``unit``, ``value``, ``sigma`` (None: no standard
        error), ``nominal``, and for an integer effect with a grid (a whole-sample delay) its
        ``resolution`` (:attr:`.effects.base.Effect.resolution`: ± half a grid step).

        Returns
        -------
        list of dict
        """
        res = getattr(self.effect, "resolution", None)
        return [{"name": n, "unit": u, "value": float(v), "sigma": float(s) if np.isfinite(s) else None,
                 "nominal": self.nominal.get(n), **({"resolution": res} if res is not None else {})}
                for n, u, v, s in zip(self.names, self.units, self.theta, self.sigma)]


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
