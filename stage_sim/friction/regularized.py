"""Regularised Coulomb friction: ``F = F_C tanh(v / v_reg) + viscous v``.

A smooth zero-velocity transition (no stiction, no pre-motion state): below ``v_reg`` the
friction acts as a steep viscous damper ``F_C / v_reg``, above it as Coulomb friction. The
plant solves it linearly implicitly per sub-step (:func:`implicit`), so the steep slope at
rest needs no extra sub-steps.
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import FrictionVariation

NAME = "regularized_coulomb"
IMPLICIT = True
FEEDFORWARD = False


class RegularizedCoulombFriction(FrictionVariation):
    """Regularised Coulomb + viscous friction, ``F = f_c tanh(v / v_reg) + viscous v``."""
    model: Literal["regularized_coulomb"]
    f_c: NonNeg = Field(description="Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    v_reg: Pos = Field(description="regularisation velocity: F reaches tanh(1) = 76 % of f_c at v_reg [m/s]",
                       json_schema_extra=unit("m/s", 1e-9, 1.0))
    viscous: NonNeg = Field(0.0, description="viscous coefficient [N·s/m]",
                            json_schema_extra=unit("N·s/m", 1e-3, 1e5))


Schema = RegularizedCoulombFriction


def params(cfg: RegularizedCoulombFriction) -> np.ndarray:
    """Parameter row: ``f_c, v_reg``."""
    return np.array([cfg.f_c, cfg.v_reg], float)


def n_state(cfg: RegularizedCoulombFriction) -> int:
    """No state."""
    return 0


def stiffness_at_rest(cfg: RegularizedCoulombFriction) -> float:
    """No pre-motion stiffness (a damper at rest)."""
    return 0.0


def explicit_damping(cfg: RegularizedCoulombFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m]: none (the slope is implicit)."""
    return 0.0


def sliding_force(cfg: RegularizedCoulombFriction) -> float:
    """Sliding force [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: RegularizedCoulombFriction, x) -> np.ndarray:
    """Force [N] at displacements ``x`` [m] of a motion from rest (faster than ``v_reg``): ``F_C``."""
    return np.full(np.shape(x), float(cfg.f_c))


@njit(cache=True, inline="always")
def implicit(p, a, g, v_prev, sc):
    """The element's force over a sub-step, linearly implicit in the end velocity.

    With ``F(v) = sc F_C tanh(v / v_reg)`` and its slope ``c_t = F'(v_prev)``, the force
    ``F(v_prev) + c_t (v - v_prev)`` at the end velocity ``v = a - g F`` (backward Euler on
    the friction's damping: stable for any slope, no oscillation at rest). Parameters as
    :func:`stage_sim.friction.coulomb.implicit`; never sticks.

    Examples
    --------
    >>> p = np.array([2.0, 1e-6])
    >>> f, stick = implicit(p, 1.0, 1e-3, 1.0, 1.0)     # sliding fast: F_C
    >>> round(f, 12), stick
    (2.0, False)
    >>> f, _ = implicit(p, 0.0, 1e-3, 0.0, 1.0)          # at rest, no push: no force
    >>> f
    0.0
    """
    fc = p[0] * sc
    th = math.tanh(v_prev / p[1])
    f0 = fc * th
    ct = fc / p[1] * (1.0 - th * th)
    v = (a - g * (f0 - ct * v_prev)) / (1.0 + g * ct)
    return f0 + ct * (v - v_prev), False


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force at velocity ``v`` [N]: ``F_C tanh(v / v_reg)``."""
    return p[0] * math.tanh(v / p[1])
