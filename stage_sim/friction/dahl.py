"""Dahl model (Eq. 1.1; Eq. 4.3 with ``shape = 1``): schema, kernels, model class.

``dF/dx = k_sigma (1 - F/F_C sgn(dx))**shape``, advanced *exactly* in the displacement
domain (:func:`dahl_update`), so the result does not depend on how an increment is split.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import FrictionVariation, Model, variation_entries

NAME = "dahl"
IMPLICIT = False       # an explicit, stateful law: held force + exact state update per sub-step
FEEDFORWARD = True     # rate-independent: the servo can drive it with the reference


class DahlFriction(FrictionVariation):
    """Dahl model, Eq. 1.1 (shape factor ``shape``) / Eq. 4.3 (shape = 1)."""
    model: Literal["dahl"]
    k_sigma: Pos = Field(description="initial contact stiffness [N/m]", json_schema_extra=unit("N/m", 1e2, 1e10))
    f_c: Pos = Field(description="Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    shape: Pos = Field(1.0, description="shape factor nu [-]")
    viscous: NonNeg = Field(0.0, description="viscous coefficient to ground [N·s/m]",
                            json_schema_extra=unit("N·s/m", 1e-3, 1e5))


Schema = DahlFriction


def element(k_sigma: float, f_c: float, shape: float = 1.0, viscous: float = 0.0, **variation) -> dict:
    """A Dahl friction element as a preset mapping (``model: dahl``; the values as given,
    validated with the preset). ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element(2.19e6, 5.31)
    {'model': 'dahl', 'k_sigma': 2190000.0, 'f_c': 5.31, 'shape': 1.0, 'viscous': 0.0}
    """
    return {"model": NAME, "k_sigma": k_sigma, "f_c": f_c, "shape": shape, "viscous": viscous,
            **variation_entries(variation)}


# --------------------------------------------------------------------------- scalar kernels
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


# --------------------------------------------------------------------------- the law's interface
def params(cfg: DahlFriction) -> np.ndarray:
    """Parameter row of the kernels: ``k_sigma, f_c, shape``."""
    return np.array([cfg.k_sigma, cfg.f_c, cfg.shape], float)


def n_state(cfg: DahlFriction) -> int:
    """State slots per trial: the force [N]."""
    return 1


def stiffness_at_rest(cfg: DahlFriction) -> float:
    """Tangent stiffness of the relaxed element [N/m]: ``k_sigma``."""
    return float(cfg.k_sigma)


def explicit_damping(cfg: DahlFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m] (none)."""
    return 0.0


def sliding_force(cfg: DahlFriction) -> float:
    """Force after a long motion [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: DahlFriction, x) -> np.ndarray:
    """Force [N] along the virgin curve (from rest) at displacements ``x >= 0`` [m], exact."""
    x = np.asarray(x, float)
    if cfg.shape == 1.0:
        return cfg.f_c * (1 - np.exp(-cfg.k_sigma * x / cfg.f_c))
    return np.array([dahl_update(0.0, xi, cfg.k_sigma, cfg.f_c, cfg.shape) for xi in x.ravel()]).reshape(x.shape)


def with_stiffness(cfg: DahlFriction, factor: float) -> DahlFriction:
    """The law with its stiffness scaled by ``factor`` (feedforward stiffness errors)."""
    return cfg.model_copy(update={"k_sigma": cfg.k_sigma * factor})


@njit(cache=True, inline="always")
def update(p, s, b, dx, h):
    """State of trial ``b`` after a monotone displacement ``dx`` [m] over ``h`` [s], in place."""
    s[0, b] = dahl_update(s[0, b], dx, p[0], p[1], p[2])


@njit(cache=True, inline="always")
def held(p, s, b, v):
    """``(force [N], tangent stiffness [N/m])`` of trial ``b`` moving at ``v`` [m/s]."""
    fe = s[0, b]
    return fe, dahl_tangent(fe, 1.0 if v > 0.0 else -1.0, p[0], p[1], p[2])


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force of trial ``b`` from its state [N] (no viscous part)."""
    return s[0, b]


class Dahl(Model):
    """Dahl model (Eq. 1.1; Eq. 4.3 with ``shape=1``) over a batch of trials.

    Examples
    --------
    >>> d = Dahl(k_sigma=2.19e6, f_c=5.31)
    >>> float(d.drive(np.array([0.0, 1e-3]))[-1]) == 5.31   # saturates at F_C
    True
    """

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
