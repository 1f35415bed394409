"""Friction models of the seed: Dahl, generalized Maxwell-slip (GMS), LuGre, Coulomb.

The one home of each law's mathematics: its compiled kernels -- the update
(:func:`dahl_update`, :func:`gms_block` / :func:`gms_update`, :func:`lugre_update`),
the tangent stiffness (:func:`dahl_tangent`, :func:`gms_block_tangent`) and the
stiffness at rest (:func:`initial_stiffness`) -- used by the plant integrator, the
servo's feedforward, the FI design advisor and the diagnosis, plus a small batch class
per law that drives the kernels with a displacement history, e.g. to draw hysteresis
loops and virgin curves (:func:`virgin_curve`). The schema of each law's parameters is
in :mod:`stage_sim.config`.

Sign convention: the returned friction force ``F`` *resists* the motion, i.e. the
body feels ``-F``; ``F -> +F_C`` after a long motion in the positive direction.

Rate-independent models (Dahl, GMS) are advanced *exactly* in the displacement
domain: for a monotone displacement increment ``dx`` the update is the closed-form
solution of the model's ODE in ``x``, so the result does not depend on how the
increment is split and is unconditionally stable.

Examples
--------
>>> import numpy as np
>>> from stage_sim.friction import Dahl
>>> d = Dahl(k_sigma=2.19e6, f_c=5.31)
>>> float(d.drive(np.array([0.0, 1e-3]))[-1]) == 5.31   # saturates at F_C
True
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "dahl_update", "dahl_tangent", "gms_block", "gms_block_tangent", "gms_update", "lugre_update", "stribeck",
    "initial_stiffness",
    "Dahl", "GMS", "LuGre", "CoulombViscous", "virgin_curve",
]


@njit(cache=True, inline="always")
def dahl_update(f, dx, k_sigma, f_c, shape):
    """Exact Dahl update (Eq. 1.1) for a monotone displacement increment.

    Parameters
    ----------
    f : float
        Friction force before the increment [N].
    dx : float
        Displacement increment of the bearing surfaces [m].
    k_sigma, f_c, shape : float
        Initial contact stiffness [N/m], Coulomb force [N], shape factor ``nu`` [-].

    Returns
    -------
    float
        Friction force after the increment [N], ``|f| <= f_c``.
    """
    if dx == 0.0:
        return f
    s = 1.0 if dx > 0.0 else -1.0
    u0 = 1.0 - s * f / f_c          # distance to saturation, in [0, 2]
    if u0 < 0.0:
        u0 = 0.0
    a = k_sigma * abs(dx) / f_c
    if shape == 1.0:
        u = u0 * np.exp(-a)
    else:
        # d u / d|x| = -(k/F_C) u**nu  ->  u**(1-nu) = u0**(1-nu) - (1-nu) a
        p = 1.0 - shape
        w = u0 ** p - p * a
        u = w ** (1.0 / p) if w > 0.0 else 0.0
    return s * f_c * (1.0 - u)


@njit(cache=True, inline="always")
def dahl_tangent(f, direction, k_sigma, f_c, shape):
    """Tangent stiffness ``dF/dx`` of the Dahl model (Eq. 1.1) at force ``f`` [N/m].

    ``k_sigma (1 - direction f / F_C)**shape`` for motion in ``direction`` (+1 or -1);
    0 once saturated.

    Examples
    --------
    >>> dahl_tangent(0.0, 1.0, 2e6, 5.0, 1.0), dahl_tangent(5.0, 1.0, 2e6, 5.0, 1.0)
    (2000000.0, 0.0)
    """
    u = 1.0 - direction * f / f_c
    if u <= 0.0:
        return 0.0
    if shape == 1.0:
        return k_sigma * u
    return k_sigma * u ** shape


@njit(cache=True, inline="always")
def gms_block(f_i, dx, k_i, limit):
    """One Maxwell-slip block (Eq. 4.4) after a displacement ``dx`` [m]: it sticks
    (``f_i + k_i dx``) up to ``±limit`` (= ``alpha_i F_C``) and slips there. Exact for any
    monotone ``dx``; the one place the GMS block law is written (plant, feedforward,
    :func:`gms_update`).

    Examples
    --------
    >>> gms_block(0.0, 1e-6, 1e5, 0.5), gms_block(0.0, 1e-4, 1e5, 0.5)   # sticks (0.1 N), slips
    (0.09999999999999999, 0.5)
    """
    fi = f_i + k_i * dx
    if fi > limit:
        return limit
    if fi < -limit:
        return -limit
    return fi


@njit(cache=True, inline="always")
def gms_block_tangent(f_i, direction, k_i, limit):
    """Tangent stiffness of one Maxwell-slip block moving in ``direction``: ``k_i`` while it
    sticks, 0 once it slips at ``direction * f_i = limit``."""
    return k_i if direction * f_i < limit else 0.0


@njit(cache=True, fastmath=False)
def gms_update(f, dx, k, alpha, f_c, n):
    """Exact update of ``n`` Maxwell-slip blocks (Eq. 4.4, Coulomb slip), in place.

    Each block sticks (``df_i = k_i dx``) until ``|f_i| = alpha_i F_C`` and then slips
    (:func:`gms_block`). Returns the total friction force ``sum(f_i)`` [N].
    """
    total = 0.0
    for i in range(n):
        fi = gms_block(f[i], dx, k[i], alpha[i] * f_c)
        f[i] = fi
        total += fi
    return total


def initial_stiffness(friction) -> float:
    """Tangent stiffness [N/m] of a relaxed friction element at rest (a
    :mod:`stage_sim.config` friction: Dahl ``k_sigma``, GMS ``sum(k_i)``, LuGre
    ``sigma0``, Coulomb 0): the pre-motion stiffness the plant's sub-steps and the FI
    design advisor work with.

    Examples
    --------
    >>> from stage_sim.config import GmsFriction
    >>> initial_stiffness(GmsFriction(model="gms", k=[1e5, 2e5], alpha=[0.4, 0.6], f_c=5.0))
    300000.0
    """
    from stage_sim.config import CoulombFriction, DahlFriction, GmsFriction, LugreFriction
    if isinstance(friction, DahlFriction):
        return float(friction.k_sigma)
    if isinstance(friction, GmsFriction):
        return float(sum(friction.k))
    if isinstance(friction, LugreFriction):
        return float(friction.sigma0)
    if isinstance(friction, CoulombFriction):
        return 0.0
    raise TypeError(f"unknown friction config {friction!r}")


@njit(cache=True, fastmath=False)
def stribeck(v, f_c, f_s, v_s, exponent):
    """Stribeck curve ``g(v) = F_C + (F_S - F_C) exp(-|v/v_s|^exponent)`` [N]."""
    return f_c + (f_s - f_c) * np.exp(-abs(v / v_s) ** exponent)


@njit(cache=True, fastmath=False)
def lugre_update(z, dx, dt, sigma0, sigma1, f_c, f_s, v_s, exponent):
    """LuGre bristle update over one step at constant velocity ``dx/dt``.

    Exact for constant velocity: ``dz/dx = 1 - sigma0 sgn(v) z / g(v)``.

    Returns
    -------
    z_new : float
        Bristle deflection [m].
    force : float
        ``sigma0 z + sigma1 dz/dt`` averaged over the step [N] (viscous part excluded;
        the plant integrates the viscous term exactly with the linear dynamics).
    """
    if dx == 0.0 or dt <= 0.0:
        return z, sigma0 * z
    v = dx / dt
    g = stribeck(v, f_c, f_s, v_s, exponent)
    s = 1.0 if dx > 0.0 else -1.0
    zss = s * g / sigma0
    z_new = zss + (z - zss) * np.exp(-sigma0 * abs(dx) / g)
    return z_new, sigma0 * z_new + sigma1 * (z_new - z) / dt


class _Model:
    """Batch driver shared by the model classes: state per trial, driven by ``x``."""

    n_state = 1

    def __init__(self, n_trials: int = 1):
        self.n_trials = int(n_trials)
        self.reset()

    def reset(self):
        """Relax the model (zero internal state) for every trial."""
        self.state = np.zeros((self.n_trials, self.n_state))
        self._x = None

    def drive(self, x, dt: float = 1e-4):
        """Drive the model with a displacement history.

        Parameters
        ----------
        x : array_like, shape (T,) or (T, n_trials)
            Bearing displacement history [m]; the first sample is the start point.
        dt : float
            Sample time [s] (only rate-dependent models use it).

        Returns
        -------
        ndarray, same shape as ``x``
            Friction force at each sample [N].
        """
        x = np.asarray(x, dtype=float)
        squeeze = x.ndim == 1
        xs = x[:, None] * np.ones(self.n_trials) if squeeze else x
        out = np.empty_like(xs)
        self._x = xs[0].copy()
        out[0] = self.force()
        for t in range(1, xs.shape[0]):
            out[t] = self.step(xs[t] - self._x, dt)
            self._x = xs[t].copy()
        return out[:, 0] if squeeze and self.n_trials == 1 else out


class Dahl(_Model):
    """Dahl model (Eq. 1.1; Eq. 4.3 with ``shape=1``)."""

    def __init__(self, k_sigma: float, f_c: float, shape: float = 1.0, n_trials: int = 1):
        self.k_sigma, self.f_c, self.shape = float(k_sigma), float(f_c), float(shape)
        super().__init__(n_trials)

    def force(self):
        return self.state[:, 0].copy()

    def step(self, dx, dt=None):
        dx = np.broadcast_to(np.asarray(dx, float), (self.n_trials,))
        for b in range(self.n_trials):
            self.state[b, 0] = dahl_update(self.state[b, 0], dx[b], self.k_sigma, self.f_c, self.shape)
        return self.force()


class GMS(_Model):
    """Generalized Maxwell-slip model with Coulomb slip (Eq. 4.4).

    Parameters
    ----------
    k : array_like
        Block stiffnesses ``k_i`` [N/m].
    alpha : array_like
        Block saturation fractions ``alpha_i`` [-] (each block slips at ``alpha_i F_C``).
    f_c : float
        Coulomb force [N].
    """

    def __init__(self, k, alpha, f_c: float, n_trials: int = 1):
        self.k = np.asarray(k, float)
        self.alpha = np.asarray(alpha, float)
        if self.k.shape != self.alpha.shape:
            raise ValueError("GMS: k and alpha must have the same length")
        self.f_c = float(f_c)
        self.n_state = len(self.k)
        super().__init__(n_trials)

    def force(self):
        return self.state.sum(axis=1)

    def step(self, dx, dt=None):
        dx = np.broadcast_to(np.asarray(dx, float), (self.n_trials,))
        for b in range(self.n_trials):
            gms_update(self.state[b], dx[b], self.k, self.alpha, self.f_c, self.n_state)
        return self.force()


class LuGre(_Model):
    """LuGre model with Stribeck curve; ``force`` includes the viscous term ``sigma2 v``."""

    def __init__(self, sigma0, sigma1, sigma2, f_c, f_s, v_s, exponent=2.0, n_trials: int = 1):
        self.p = tuple(float(v) for v in (sigma0, sigma1, sigma2, f_c, f_s, v_s, exponent))
        self._last = np.zeros(n_trials)
        super().__init__(n_trials)

    def force(self):
        return self._last.copy()

    def step(self, dx, dt=1e-4):
        s0, s1, s2, fc, fs, vs, ex = self.p
        dx = np.broadcast_to(np.asarray(dx, float), (self.n_trials,))
        for b in range(self.n_trials):
            z, f = lugre_update(self.state[b, 0], dx[b], dt, s0, s1, fc, fs, vs, ex)
            self.state[b, 0] = z
            self._last[b] = f + s2 * dx[b] / dt
        return self.force()


class CoulombViscous(_Model):
    """Plain Coulomb + viscous friction ``F = F_C sgn(v) + c v`` (zero at rest)."""

    def __init__(self, f_c: float, viscous: float = 0.0, n_trials: int = 1):
        self.f_c, self.viscous = float(f_c), float(viscous)
        self._last = np.zeros(n_trials)
        super().__init__(n_trials)

    def force(self):
        return self._last.copy()

    def step(self, dx, dt=1e-4):
        v = np.broadcast_to(np.asarray(dx, float), (self.n_trials,)) / dt
        self._last = self.f_c * np.sign(v) + self.viscous * v
        return self.force()


def virgin_curve(model: _Model, x_max: float, n: int = 200):
    """Force-displacement curve from the relaxed state up to ``x_max`` [m].

    Returns ``(x, F)`` with ``x`` from 0 to ``x_max`` in ``n`` samples.
    """
    model.reset()
    x = np.linspace(0.0, x_max, n)
    f = model.drive(x)
    return x, np.asarray(f).reshape(n, -1)[:, 0]
