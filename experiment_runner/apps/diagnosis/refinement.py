"""Output-error refinement: a candidate's values set by the closed-loop replay of the fit samples.

The force observer proposes a candidate and gives its start; :func:`refine_by_replay` then fits it
by least squares of the replay error on the *fit* samples (command and position in units of the
current model's run-to-run floor; on an open-loop record the prewhitened window errors), so that
candidates are compared at their replay optimum: the observer's fit is off where the replay is
sensitive when its residual weighs the data differently (a ripple's phase, a Coulomb level against
a friction slope). Its standard errors are block-robust (:func:`block_covariance`): the replay error
is correlated over tens of milliseconds, not independent per sample.
"""
from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from .budget import checkpoint, parallel_map
from .context import Context
from .fit import FitResult, Transform, bad_point
from .joint import JointEffect
from .model import ModelSpec

__all__ = ["Refinement", "refine_by_replay", "block_covariance", "GRID_1D", "REFINE_MAX_PARAMS", "REFINE_PROPOSALS",
           "REFINE_TOP", "REFINE_JOINT_MAX", "REFINE_MODE_PASSES", "REFINE_BLOCKS_S"]

REFINE_MAX_PARAMS = 3
"""Candidates with at most this many parameters are refined among the :data:`REFINE_PROPOSALS` best
replays and the as many best force-observer fits (every one-parameter candidate always)."""
REFINE_PROPOSALS = 4
REFINE_TOP = 2
"""Larger candidates are refined among this many best replays."""
REFINE_JOINT_MAX = 8
"""From the second step on a candidate is refined together with the adopted effects while their
parameters number at most this many."""
REFINE_BLOCKS_S = (0.02, 0.05, 0.1, 0.2)
"""Block lengths [s] of the robust standard errors (time windows of each trial)."""
_LS_WORKERS = "workers" in inspect.signature(least_squares).parameters
"""scipy's least squares takes a map for its finite-difference columns (scipy >= 1.16; requirements.txt
pins 1.17.1); an older one computes them one after the other."""
GRID_1D = (-0.6, -0.3, -0.15, -0.05, 0.05, 0.15, 0.3, 0.6)
"""Start grid of a one-parameter replay refinement, in the optimiser's variable (log, or scaled)."""
REFINE_MODE_PASSES = 3
"""Passes of the located-mode refinement, each weighted by the floor of the previous pass' model."""


@dataclass
class Refinement:
    """A candidate refined by the replay.

    Parameters
    ----------
    spec : ModelSpec
        The refined model (the adopted effects and the candidate).
    theta : numpy.ndarray
        The candidate's own parameters.
    sigma : numpy.ndarray
        Their block-robust standard errors.
    at_bound : list
        Names of the candidate's own parameters at a bound.
    joint : FitResult, optional
        The fit over the adopted effects' and the candidate's parameters (refined together), else
        None.
    """
    spec: ModelSpec
    theta: np.ndarray
    sigma: np.ndarray
    at_bound: list
    joint: FitResult | None

    def on_bound(self) -> bool:
        """Any refined parameter at a bound (of the joint fit, when refined together).

        Returns
        -------
        bool
        """
        return bool(self.joint.on_bound if self.joint is not None else self.at_bound)


def block_covariance(J: np.ndarray, r: np.ndarray, block: np.ndarray, min_blocks: int = 10) -> np.ndarray:
    """Covariance of least-squares parameters from the Jacobian ``J`` (n, p) and residual ``r``
    (n,) at the optimum, with residuals correlated within blocks (``block`` (n,) ids) and
    independent between them: the cluster-robust sandwich ``B M B``, ``B = (J'J)^-1``,
    ``M = G/(G-1) sum_g (J_g' r_g)(J_g' r_g)'`` over the ``G`` blocks. With fewer than
    ``min_blocks`` blocks, the classical ``s^2 (J'J)^-1``.

    Parameters
    ----------
    J : numpy.ndarray
        (n, p) Jacobian.
    r : numpy.ndarray
        (n,) residual at the optimum.
    block : numpy.ndarray
        (n,) block id of each residual.
    min_blocks : int, optional
        Fewest blocks for the sandwich.

    Returns
    -------
    numpy.ndarray
        (p, p) covariance.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> n, L = 4000, 20                          # a mean fitted to noise correlated over blocks of 20
    >>> r = np.repeat(rng.normal(size=n // L), L) + 0.1 * rng.normal(size=n)
    >>> J = np.ones((n, 1))
    >>> classical = np.sqrt(block_covariance(J, r - r.mean(), np.zeros(n, int))[0, 0])
    >>> robust = np.sqrt(block_covariance(J, r - r.mean(), np.arange(n) // L)[0, 0])
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


class _OutputError:
    """The least-squares problem of one refinement: the candidate (start ``own0``; after the adopted
    effects it is refined with, ``refined``) on the model ``prev``, in the optimiser's variable
    (:class:`.fit.Transform`)."""

    def __init__(self, candidate: FitResult, refined: list, own0: np.ndarray, prev: ModelSpec, ctx: Context, judge,
                 floor):
        self.model = JointEffect([(f.effect, len(f.theta)) for f in refined] + [(candidate.effect, len(candidate.theta))],
                                 [np.asarray(f.theta, float) for f in refined] + [own0])
        self.prev, self.judge, self.floor = prev, judge, floor
        self.params = self.model.params(prev, ctx)
        self.tr = Transform(self.params)
        self.lo, self.hi = self.tr.bounds()
        self.eps = 1e-6 * (self.hi - self.lo)
        self.bad = None          # the residual of a point that does not run (None until a start runs)
        self._seen = {}          # z's bytes -> its residual (:meth:`residual`)

    def clip(self, z):
        """``z`` inside the bounds by a margin."""
        return np.clip(z, self.lo + self.eps, self.hi - self.eps)

    def residual(self, z):
        """The replay error of the fit samples at ``z`` in floor units, or :attr:`bad`; a point
        evaluated before is not replayed again (the solver's first evaluation is the start the
        grid or :meth:`best_start` chose; :meth:`back_to_no_change` starts where it scored)."""
        checkpoint()          # a search whose budget is spent stops here (:mod:`.budget`)
        z = np.asarray(z, float)
        key = z.tobytes()
        hit = self._seen.get(key)
        if hit is not None:
            return hit if hit is self.bad else hit.copy()
        r = self._residual(z)
        if r is not None:
            self._seen[key] = r
        return r if r is None or r is self.bad else r.copy()

    def _residual(self, z):
        th = self.tr.to_theta(z)
        if not np.all(np.isfinite(th)):
            return self.bad
        try:
            rp = self.judge.replay(self.model.apply(self.prev, th))
        except ValueError:     # a model the simulator refuses (a joint too stiff for its sub-steps)
            return self.bad
        if not rp.ok:
            return self.bad
        r = self.judge.residual(rp, self.floor)
        return r if np.all(np.isfinite(r)) else self.bad

    def residuals(self, fun, zs) -> list:
        """``[fun(z) for z in zs]``, the replays on the search's threads (:func:`.budget.parallel_map`):
        the least-squares solver's finite-difference columns (its ``workers``), a start grid's points."""
        return parallel_map(fun, zs)

    def best_start(self, starts):
        """``(z, residual)`` of the best of the parameter vectors ``starts`` that runs; ``(None, None)``."""
        z0, r0 = None, None
        zs = [self.clip(self.tr.to_z(theta0)) for theta0 in starts]
        for z, r in zip(zs, self.residuals(self.residual, zs)):
            if r is not None and (r0 is None or float(r @ r) < float(r0 @ r0)):
                z0, r0 = z, r
        return z0, r0

    def grid(self, z0, cost: float, n_own: int):
        """From ``z0`` (cost ``cost``): the best of :data:`GRID_1D` around it, one of the candidate's own
        ``n_own`` coordinates after the other (the adopted effects' stay at their start)."""
        z1, c1 = z0, cost
        for i in range(len(z0) - n_own, len(z0)):
            zi = z1
            zs = []
            for d in GRID_1D:
                z = zi.copy()
                z[i] += d * max(1.0, abs(float(zi[i])) if not self.params[i].log else 1.0)
                zs.append(self.clip(z))
            for z, r in zip(zs, self.residuals(self.residual, zs)):
                if r is not self.bad and float(r @ r) < c1:
                    z1, c1 = z, float(r @ r)
        return z1

    def back_to_no_change(self, out, nominal: dict, k0: int, ls_kw: dict):
        """The solution ``out``, or a better one found from it with one of the candidate's own
        parameters (those from index ``k0``) back at its value of no change (``nominal``) and
        refined again.

        The replay's error has narrow valleys: a level the replay pins to 1 % lies inside the
        finite-difference step, and the solver can stop where a second parameter stands in for the
        level's last step. A parameter the data need (its error at no change more than 1.5 times
        the solution's): not tried."""
        for j, p in enumerate(self.params[k0:]):
            v0 = nominal.get(p.name.split(".", 1)[-1])
            if v0 is None or not (p.lo <= v0 <= p.hi):
                continue
            th = self.tr.to_theta(out.x)
            if abs(th[k0 + j] - v0) <= 1e-9 * max(abs(p.hi - p.lo), 1e-300):
                continue
            th[k0 + j] = v0
            z1 = self.clip(self.tr.to_z(th))
            r1 = self.residual(z1)
            if r1 is self.bad or float(r1 @ r1) > 3.0 * out.cost:      # out.cost: half the sum of squares
                continue
            alt = least_squares(self.residual, z1, bounds=(self.lo, self.hi), **ls_kw)
            if alt.cost < out.cost:
                out = alt
        return out

    def sigma(self, out, theta) -> np.ndarray:
        """Block-robust standard errors of ``theta`` from the solution ``out``: the largest over the
        block lengths :data:`REFINE_BLOCKS_S` with at least 10 blocks per parameter (the error's
        correlation time is unknown)."""
        m = self.judge.mask
        T_, B_ = m.shape
        t_of = np.broadcast_to(np.arange(T_)[:, None], m.shape)[m]
        b_of = np.broadcast_to(np.arange(B_)[None, :], m.shape)[m]
        var = np.zeros(len(theta))
        for span in REFINE_BLOCKS_S:
            L = max(1, int(round(span * self.judge.rate)))
            ids = b_of * (T_ // L + 1) + t_of // L
            if len(np.unique(ids)) >= 10 * len(theta) or span == REFINE_BLOCKS_S[0]:
                var = np.maximum(var, np.diag(block_covariance(out.jac, out.fun,
                                                               np.tile(ids, len(out.fun) // len(ids)))))
        return np.sqrt(np.maximum(var, 0.0)) * np.abs(self.tr.dtheta_dz(theta))


def refine_by_replay(candidate: FitResult, selected: list, base: ModelSpec, ctx: Context, judge, floor,
                     max_nfev: int = 8, with_selected: bool = False, start=None,
                     diff_step: float = 2e-2, grid: bool = False) -> Refinement | None:
    """Output-error refinement of ``candidate``: least squares of the replay error of the fit samples
    (``judge``, a judge of the fit samples) in units of the run-to-run ``floor``, started at the
    force observer's fit.

    With ``with_selected`` the adopted deterministic effects (``selected``) are refined with it
    (joint output error: a second effect is credited with what it adds once the first is re-fitted
    in its presence), else they are held at their values. A one-parameter candidate, or one with
    ``grid``, starts from the best of a coarse grid around its start, coordinate by coordinate
    (:data:`GRID_1D`): the replay error is rough in such a parameter.

    Parameters
    ----------
    candidate : FitResult
        The force observer's fit of the candidate effect (its values are the start).
    selected : list of FitResult
        The adopted effects of the current model (without the one the candidate replaces).
    base : ModelSpec
        The base model the adopted effects are applied to.
    ctx : Context
        The located context for fits on top of ``selected`` (:func:`.selection.for_fits_on`).
    judge : ReplayJudge
        The judge of the fit samples: its replay error is the least-squares residual.
    floor : Floor
        The current model's run-to-run floor; its ``sigma_u`` [N] and ``sigma_y`` [m] make the
        residual dimensionless.
    max_nfev : int, optional
        Replay evaluations of the least squares at most (the caller gives fewer to candidates
        with many parameters).
    with_selected : bool, optional
        Refine the adopted deterministic effects jointly with the candidate.
    start : array_like, optional
        The candidate's own start values (its parameter units) instead of the observer's fit.
    diff_step : float, optional
        The optimiser's relative finite-difference step (of the log for log parameters).
    grid : bool, optional
        Start from the coarse grid whatever the number of parameters.

    Returns
    -------
    Refinement or None
        The refined candidate; None when the replay error did not decrease or anything failed
        (the refinement improves a candidate, it never fails a diagnosis).
    """
    try:
        refined = [f for f in selected if f.effect.kind == "deterministic"] if with_selected else []
        prev = base
        for f in selected:
            if f.effect.kind != "deterministic":
                prev = f.effect.apply(prev, f.theta)
        if not with_selected:
            for f in selected:
                if f.effect.kind == "deterministic":
                    prev = f.effect.apply(prev, f.theta)
        th = [np.asarray(f.theta, float) for f in refined]
        own0 = np.asarray(candidate.theta if start is None else start, float)
        starts = [np.concatenate(th + [own0])]
        n_sel = sum(map(len, th))
        if refined and candidate.joint is not None and len(candidate.joint.theta) == n_sel + len(candidate.theta):
            # or where the observer's joint fit with this candidate left the adopted effects, if
            # their replay is better there (where the observer sees little its joint fit is noise)
            starts.insert(0, np.concatenate([np.asarray(candidate.joint.theta, float)[:n_sel], own0]))
        oe = _OutputError(candidate, refined, own0, prev, ctx, judge, floor)
        if len(oe.params) != len(starts[0]):
            return None
        z0, r0 = oe.best_start(starts)
        if r0 is None:
            return None
        oe.bad = np.full(len(r0), bad_point(float(np.mean(r0 ** 2))))     # a model that diverges or is refused
        cost0 = float(r0 @ r0)
        if len(own0) == 1 or grid:
            # one parameter (or a start the observer did not give): the replay's error is rough in it
            # (a stick-slip event or an encoder step moves with it) and may be flat at the start (a
            # stage held by friction): start from the best of a coarse grid around it
            z0 = oe.grid(z0, cost0, len(own0))
        ls_kw = dict(max_nfev=max_nfev, x_scale="jac", diff_step=diff_step,
                     **({"workers": oe.residuals} if _LS_WORKERS else {}))
        out = least_squares(oe.residual, z0, bounds=(oe.lo, oe.hi), **ls_kw)
        out = oe.back_to_no_change(out, candidate.effect.nominal(prev), len(out.x) - len(own0), ls_kw)
        if not out.success and out.status < 0 or out.cost >= 0.5 * cost0:
            return None
        tol = 1e-3 * (oe.hi - oe.lo)
        at = [p.name for p, z, a, b, t in zip(oe.params, out.x, oe.lo, oe.hi, tol)
              if abs(b - z) <= t or (abs(z - a) <= t and not p.physical_lo)]
        theta = oe.tr.to_theta(out.x)
        if not (np.all(np.isfinite(out.jac)) and np.all(np.isfinite(theta))):
            return None
        sigma = oe.sigma(out, theta)
        spec = oe.model.apply(prev, theta)
        k = len(theta) - len(candidate.theta)
        own = candidate.key + "."
        joint = None
        if refined:
            joint = dataclasses.replace(candidate, key=oe.model.key, title=oe.model.title,
                                        names=[p.name for p in oe.params], units=[p.unit for p in oe.params],
                                        theta=np.asarray(theta, float), sigma=np.asarray(sigma, float), corr=None,
                                        spec=spec, on_bound=at, nominal={}, derived={}, joint=None)
        return Refinement(spec=spec, theta=np.asarray(theta[k:], float), sigma=np.asarray(sigma[k:], float),
                          at_bound=[n[len(own):] for n in at if n.startswith(own)], joint=joint)
    except Exception:   # noqa: BLE001 - the refinement is an improvement, never a failure of the diagnosis
        return None
