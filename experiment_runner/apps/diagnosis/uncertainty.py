"""Standard errors of the adopted parameters: their spread over the final model's own recordings and
the roughness of the replay around their values.

A closed-loop replay with friction is not a smooth function of a parameter (a small change moves a
stick-slip event or an encoder step), so the optimiser stops anywhere in a valley its local
Jacobian does not see (:func:`roughness`); and the fit's own standard errors miss the noise's
correlation in time that the model's simulated recordings carry (:func:`spread_over_recordings`).
:func:`widen` sets each adopted parameter's ``sigma`` to
``sqrt(max(sigma_fit, sigma_boot)^2 + sigma_rough^2)``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .joint import spec_with
from .options import Options

__all__ = ["roughness", "spread_over_recordings", "widen"]


def roughness(D, v: float, sigma: float, target: float = 0.3, points: int = 7) -> float | None:
    """Spread of a parameter from the roughness of the replay around its value ``v``.

    ``D`` (a function of the parameter) is profiled over a step ``h`` at which it rises by about
    ``target`` x its value, on ``points`` values in ``[v - h, v + h]``; with the parabola fitted to
    them (curvature ``c``, residual SD ``s``, minimum at ``v + d``) the spread is
    ``sqrt(s / c + d^2)``: the values whose smooth part is within one roughness SD of the minimum,
    and the distance of ``v`` from that minimum. None if the profile has no positive curvature.

    >>> rough = lambda x: 2.0 + 1e4 * (x - 0.4) ** 2 + 0.01 * np.sin(3e3 * x)
    >>> r = roughness(rough, 0.4, 1e-4)
    >>> 0.0002 < r < 0.003
    True
    >>> roughness(lambda x: 2.0 + 1e4 * (x - 0.4) ** 2, 0.4, 1e-4) < 1e-4
    True

    Parameters
    ----------
    D : callable
        The replay error as a function of the parameter.
    v : float
        The parameter's value.
    sigma : float
        Its standard error so far (the first step's scale).
    target : float, optional
        Relative rise of ``D`` over the step.
    points : int, optional
        Profile points.

    Returns
    -------
    float or None
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


def spread_over_recordings(J: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Standard errors of least-squares parameters from the residuals ``R`` (K, n) of ``K``
    simulated recordings of the fitted model against its noise-free replay, and the Jacobian
    ``J`` (n, p) of the residual: the linearised parametric bootstrap, the spread of the
    Gauss-Newton step ``pinv(J) r_k`` each recording would give. The recordings carry the
    noise's real correlation in time (a closed loop integrates drive noise).

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> n, L = 3000, 30                                   # a slope fitted to noise correlated over 30 samples
    >>> J = np.linspace(-1.0, 1.0, n)[:, None]
    >>> R = np.repeat(rng.normal(size=(400, n // L)), L, axis=1)
    >>> exact = np.sqrt(L / (J[:, 0] @ J[:, 0]))          # ~sqrt(L) x the white-noise value
    >>> bool(abs(spread_over_recordings(J, R)[0] / exact - 1) < 0.15)
    True

    Parameters
    ----------
    J : numpy.ndarray
        (n, p) Jacobian of the residual.
    R : numpy.ndarray
        (K, n) residuals of the simulated recordings.

    Returns
    -------
    numpy.ndarray
        (p,) standard errors.
    """
    step = R @ np.linalg.pinv(J).T
    return np.sqrt(np.mean(step ** 2, axis=0))


def _moved(theta: dict, key: str, i: int, v: float) -> dict:
    """A copy of the effects' parameter vectors ``theta`` with parameter ``i`` of ``key`` at ``v``."""
    th = {k: a.copy() for k, a in theta.items()}
    th[key][i] = v
    return th


class _Profile:
    """The adopted deterministic effects of the final model on the fit samples: their values
    (``theta``: key -> vector, as reported), the model at moved values, its replay error."""

    def __init__(self, fit_judge, selected: list, base, floor, theta: dict):
        self.fj, self.selected, self.base, self.floor, self.theta = fit_judge, selected, base, floor, theta

    def spec(self, th: dict):
        """The final model with the adopted effects at the values ``th``."""
        return spec_with([dataclasses.replace(f, theta=th[f.key]) if f.key in th else f for f in self.selected],
                         self.base)

    def D_at(self, key: str, i: int, v: float) -> float:
        """Replay error of the fit samples with parameter ``i`` of ``key`` at ``v``, the others held."""
        try:
            rp = self.fj.replay(self.spec(_moved(self.theta, key, i, v)))
        except Exception:     # noqa: BLE001 - not a valid model there (a damping below 0)
            return float("inf")
        return self.fj.D(rp, self.floor) if rp.ok else float("inf")

    def spread(self, det: list, rows: dict, rp0) -> dict:
        """``{(effect, i): sigma}``: each adopted parameter's spread over the final model's simulated
        recordings of the fit samples (:func:`spread_over_recordings`; the Jacobian by central
        differences of one fit standard error, at least 1e-4 of the value); empty when a difference
        cannot be replayed."""
        fj, fl = self.fj, self.floor
        idx = [(f.key, i) for f in det for i in range(len(self.theta[f.key]))]
        r0 = fj.residual(rp0, fl)
        J = np.zeros((len(r0), len(idx)))
        for c, (k, i) in enumerate(idx):
            v = self.theta[k][i]
            h = max(rows[k]["params"][i].get("sigma") or 0.0, 1e-4 * abs(v), 1e-12)
            side = []
            for d in (h, -h):
                try:
                    rp = fj.replay(self.spec(_moved(self.theta, k, i, v + d)))
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


def widen(fit_judge, found: list, selected: list, base, current, opt: Options) -> bool:
    """Widen the reported standard errors of the adopted deterministic effects (rows of ``found``, in
    place): each parameter's spread over the final model's recordings (``sigma_boot``) and the
    roughness of its profile, the others held (``sigma_rough``), on the fit samples against the
    final model ``current``'s floor; ``sigma`` becomes ``sqrt(max(sigma_fit, sigma_boot)^2 +
    sigma_rough^2)`` (``sigma_fit``: the fit's own, kept). Returns whether it ran (not without a
    judge of the fit samples, adopted deterministic effects, or when the rebuilt model is not the
    final one).

    Parameters
    ----------
    fit_judge : ReplayJudge or None
        The judge of the fit samples.
    found : list of dict
        The report's rows of the adopted effects (changed in place).
    selected : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model they were added to.
    current : ModelSpec
        The final model.
    opt : Options
        The diagnosis's options.

    Returns
    -------
    bool
    """
    det = [f for f in selected if f.effect.kind == "deterministic"]
    if fit_judge is None or not det:
        return False
    rows = {fe["effect"]: fe for fe in found if fe.get("kind") == "deterministic"}
    if any(f.key not in rows for f in det):
        return False
    theta = {f.key: np.array([p["value"] for p in rows[f.key]["params"]], float) for f in det}
    try:
        fl = fit_judge.floor(current)
        prof = _Profile(fit_judge, selected, base, fl, theta)
        rp0 = fit_judge.replay(prof.spec(theta))
        # the rebuilt model must be the final one (else the profile would not be about it)
        if not rp0.ok or abs(fit_judge.D(rp0, fl) - fit_judge.D(fit_judge.replay(current), fl)) \
                > 1e-9 * max(fit_judge.D(rp0, fl), 1.0):
            return False
        boot = prof.spread(det, rows, rp0)
        for f in det:
            for i, p in enumerate(rows[f.key]["params"]):
                s_fit = p.get("sigma") or 0.0
                r = roughness(lambda v: prof.D_at(f.key, i, v), p["value"], s_fit)
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
        opt.log(f"roughness profile failed: {err!r}")
    return True
