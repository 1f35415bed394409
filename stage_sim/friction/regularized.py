"""Regularised Coulomb friction: ``F = F_C tanh(v / v_reg) + viscous v``.

A smooth zero-velocity transition (no stiction, no pre-motion state): below ``v_reg`` the
friction acts as a steep viscous damper ``F_C / v_reg``, above it as Coulomb friction. The
plant holds per sub-step the mean force of the law linearised at its start (:func:`implicit`):
stable for any slope; the sub-steps resolve the slope at rest for accuracy
(:func:`explicit_damping`).
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import FrictionVariation, variation_entries

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


def element(f_c: float, v_reg: float, viscous: float = 0.0, **variation) -> dict:
    """A regularised Coulomb element as a preset mapping (``model: regularized_coulomb``; the values
    as given, validated with the preset). ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element(5.31, 1e-4)
    {'model': 'regularized_coulomb', 'f_c': 5.31, 'v_reg': 0.0001, 'viscous': 0.0}
    """
    return {"model": NAME, "f_c": f_c, "v_reg": v_reg, "viscous": viscous, **variation_entries(variation)}


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
    """Damping the sub-steps must resolve [N·s/m]: the slope at rest ``F_C / v_reg``.

    The implicit solve is stable at any sub-step, but a creep transient lasts only
    ``m v_reg / F_C`` (0.4 ms for 2 kg, 5 N, 1 mm/s): held over a 1 ms control period the
    table's position misses ~half the velocity change of every force step (a micrometre over a
    record against an independent integrator). The plant keeps ``h F_C / (m v_reg)`` within
    ``simulation.max_omega_h`` as for explicit damping, but -- the solve being stable at any
    step -- never beyond ``simulation.max_substeps`` and without refusing the stage."""
    return float(cfg.f_c / cfg.v_reg)


def sliding_force(cfg: RegularizedCoulombFriction) -> float:
    """Sliding force [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: RegularizedCoulombFriction, x) -> np.ndarray:
    """Force [N] at displacements ``x`` [m] of a motion from rest (faster than ``v_reg``): ``F_C``."""
    return np.full(np.shape(x), float(cfg.f_c))


@njit(cache=True, inline="always")
def implicit(p, a, g, v_prev, sc):
    """The element's force held over a sub-step: the mean of the linearised law over the sub-step.

    With ``F(v) = sc F_C tanh(v / v_reg)`` linearised at the start, ``F_0 + c_t (v - v_prev)``,
    and the end velocity ``v = a - g F`` of the held force ``F``, the velocity relaxes
    exponentially towards its balance with rate ``z = g c_t`` per sub-step; the force held is
    that relaxation's mean, ``F_0 + (a - g F_0 - v_prev) phi(z) / g`` with
    ``phi(z) = 1 - (1 - exp(-z)) / z``, so the end velocity is the linearised law's exact one
    (``v_prev + (1 - exp(-z)) (v_balance - v_prev)``): stable for any slope, never past the
    balance (no oscillation at rest), and second-order accurate for small ``z`` (backward Euler,
    ``phi = z / (1 + z)``, is first order). Parameters as
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
    z = g * fc / p[1] * (1.0 - th * th)
    phi = 1.0 + math.expm1(-z) / z if z > 1e-6 else 0.5 * z * (1.0 - z / 3.0)
    return f0 + (a - g * f0 - v_prev) * phi / g, False


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force at velocity ``v`` [N]: ``F_C tanh(v / v_reg)``."""
    return p[0] * math.tanh(v / p[1])
