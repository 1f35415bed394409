"""LuGre model with Stribeck curve: schema, kernels, model class.

Bristle deflection ``z``: ``dz/dx = 1 - sigma0 sgn(v) z / g(v)``, force
``sigma0 z + sigma1 dz/dt + sigma2 v`` with ``g(v) = F_C + (F_S - F_C) exp(-|v/v_s|^exponent)``.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import FrictionVariation, Model, variation_entries

NAME = "lugre"
IMPLICIT = False
FEEDFORWARD = False    # rate-dependent


class LugreFriction(FrictionVariation):
    """LuGre model with Stribeck curve g(v) = F_C + (F_S - F_C) exp(-|v/v_s|^exponent)."""
    model: Literal["lugre"]
    sigma0: Pos = Field(description="bristle stiffness [N/m]", json_schema_extra=unit("N/m", 1e2, 1e10))
    sigma1: NonNeg = Field(0.0, description="bristle damping [N·s/m]", json_schema_extra=unit("N·s/m", 1e-3, 1e6))
    viscous: NonNeg = Field(0.0, description="viscous coefficient sigma2 [N·s/m]",
                            json_schema_extra=unit("N·s/m", 1e-3, 1e5))
    f_c: Pos = Field(description="Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    f_s: Pos = Field(description="static (break-away) force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    v_s: Pos = Field(description="Stribeck velocity [m/s]", json_schema_extra=unit("m/s", 1e-8, 1.0))
    exponent: Pos = Field(2.0, description="Stribeck exponent [-]")


Schema = LugreFriction


def element(sigma0: float, f_c: float, f_s: float, v_s: float, sigma1: float = 0.0, viscous: float = 0.0,
            exponent: float = 2.0, **variation) -> dict:
    """A LuGre element as a preset mapping (``model: lugre``; the values as given, validated with
    the preset). ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element(2.19e6, 5.31, 8.5, 1e-3)["f_s"]
    8.5
    """
    return {"model": NAME, "sigma0": sigma0, "sigma1": sigma1, "viscous": viscous, "f_c": f_c, "f_s": f_s,
            "v_s": v_s, "exponent": exponent, **variation_entries(variation)}


# --------------------------------------------------------------------------- scalar kernels
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


# --------------------------------------------------------------------------- the law's interface
def params(cfg: LugreFriction) -> np.ndarray:
    """Parameter row: ``sigma0, sigma1, f_c, f_s, v_s, exponent``."""
    return np.array([cfg.sigma0, cfg.sigma1, cfg.f_c, cfg.f_s, cfg.v_s, cfg.exponent], float)


def n_state(cfg: LugreFriction) -> int:
    """State slots per trial: the bristle deflection [m]."""
    return 1


def stiffness_at_rest(cfg: LugreFriction) -> float:
    """Tangent stiffness of the relaxed element [N/m]: ``sigma0``."""
    return float(cfg.sigma0)


def explicit_damping(cfg: LugreFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m]: the bristle damping ``sigma1``."""
    return float(cfg.sigma1)


def sliding_force(cfg: LugreFriction) -> float:
    """Force after a long fast motion [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: LugreFriction, x) -> np.ndarray:
    """Force [N] along the virgin curve at ``x >= 0`` [m] at speeds well above ``v_s``:
    ``F_C (1 - exp(-sigma0 x / F_C))``."""
    x = np.asarray(x, float)
    return cfg.f_c * (1 - np.exp(-cfg.sigma0 * x / cfg.f_c))


@njit(cache=True, inline="always")
def update(p, s, b, dx, h):
    """Bristle deflection of trial ``b`` after ``dx`` [m] at constant velocity over ``h`` [s]."""
    zb, _ = lugre_update(s[0, b], dx, h, p[0], p[1], p[2], p[3], p[4], p[5])
    s[0, b] = zb


@njit(cache=True, inline="always")
def held(p, s, b, v):
    """``(sigma0 z + sigma1 dz/dt [N], tangent stiffness [N/m])`` of trial ``b`` at ``v`` [m/s]."""
    s0, s1 = p[0], p[1]
    d = 1.0 if v > 0.0 else -1.0
    g = stribeck(v, p[2], p[3], p[4], p[5])
    zb = s[0, b]
    zdot = v - s0 * abs(v) * zb / g
    kt = s0 * max(0.0, 1.0 - s0 * d * zb / g)
    return s0 * zb + s1 * zdot, kt


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Elastic bristle force of trial ``b`` [N]: ``sigma0 z``."""
    return p[0] * s[0, b]


class LuGre(Model):
    """LuGre model with Stribeck curve over a batch of trials; ``force`` includes ``sigma2 v``."""

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
