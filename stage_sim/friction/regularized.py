"""Regularised Coulomb friction: ``F = F_C tanh(v / v_reg) + viscous v``.

A smooth zero-velocity transition (no stiction, no pre-motion state): below ``v_reg`` the
friction acts as a steep viscous damper ``F_C / v_reg``, above it as Coulomb friction. The
plant takes per sub-step the mean force and slope of the law solved in parts, each exact for
the law linearised at its start, or along its chord to the balance where the rest of the sub-step
settles there (:func:`implicit`): stable for any slope, and accurate without resolving the slope
with sub-steps (:func:`explicit_damping` asks for none).
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
    """Damping the plant integrates explicitly [N·s/m]: none. The slope at rest ``F_C / v_reg``
    (a creep transient of ``m v_reg / F_C``: 0.4 us for 2 kg, 5.31 N, 1 um/s) is resolved inside
    the sub-step by :func:`implicit`, so it asks the plant for no sub-steps."""
    return 0.0


def sliding_force(cfg: RegularizedCoulombFriction) -> float:
    """Sliding force [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: RegularizedCoulombFriction, x) -> np.ndarray:
    """Force [N] at displacements ``x`` [m] of a motion from rest (faster than ``v_reg``): ``F_C``."""
    return np.full(np.shape(x), float(cfg.f_c))


SPLIT_TOL = 1e-4
"""Largest error of the linearised law at the end of a part of a sub-step, as a fraction of ``F_C``:
:func:`implicit` splits a sub-step until every part meets it."""
MAX_PARTS = 4096
"""Most tries (parts and halvings) in one sub-step; beyond, the rest in one part."""
Z_BALANCE = 30.0
"""Least relaxation (rate x duration) for :func:`implicit` to take the rest of a sub-step as one
part that ends at the law's balance velocity (its transient decays by ``exp(-30)`` = 1e-13)."""


@njit(cache=True, inline="always")
def _relax(f0, ct, v, dw, g):
    """A force linear in the velocity over (part of) a sub-step, solved exactly.

    The force is ``f0 + ct (u - v)`` at velocity ``u``, ``v`` the start velocity; ``dw`` is the
    velocity change the other forces give over the part, ``g`` the velocity change per unit
    force. The velocity relaxes as ``u_b + (v - u_b) exp(-z s)`` (``z = g ct``, ``s`` the fraction
    0..1 of the part), so the force is ``(dw + z (v - u_b) exp(-z s)) / g``: a transient at the
    start where ``z`` is large, which the first moment keeps. Stable for any ``ct >= 0``, never past
    the balance. One part of :func:`implicit`.

    Returns
    -------
    f : float
        Mean force over the part [N].
    m1 : float
        Its first moment over the part's fraction 0..1 [N].
    v1 : float
        End velocity [m/s].

    Examples
    --------
    >>> f, m1, v1 = _relax(0.0, 0.0, 0.0, 1.0, 0.5)    # no force: the free change
    >>> f, m1, v1
    (0.0, 0.0, 1.0)
    >>> f, m1, v1 = _relax(0.0, 1e9, 0.0, 1.0, 0.5)    # stiff: held at the balance u_b ~ 0
    >>> round(f, 6), round(v1, 9)
    (2.0, 2e-09)
    """
    z = g * ct
    if z > 1e-3:
        em = math.expm1(-z)
        phi = 1.0 + em / z
        psi = (-em - z * (1.0 + em)) / (-z * em)
    else:
        phi = 0.5 * z * (1.0 - z / 3.0)
        psi = 0.5 - z / 12.0
    f = f0 + (dw - g * f0) * phi / g
    v1 = v + dw - g * f
    m1 = (0.5 * dw + (v - v1) * psi) / g
    return f, m1, v1


@njit(cache=True, inline="always")
def implicit(p, a, g, v_prev, sc):
    """The element's force over a sub-step: its mean and slope, the law solved in parts.

    Each part holds the mean force of the law linearised at the part's start velocity: with
    ``F(v) = sc F_C tanh(v / v_reg)`` linearised, ``F_0 + c_t (v - v_0)``, and the end velocity
    ``v = a - g F`` of the held force ``F``, the velocity relaxes exponentially towards its balance
    with rate ``z = g c_t`` per part; the force held is that relaxation's mean,
    ``F_0 + (a - g F_0 - v_0) phi(z) / g`` with ``phi(z) = 1 - (1 - exp(-z)) / z``, so the end
    velocity is the linearised law's exact one: stable for any slope, never past the balance (no
    oscillation at rest), second-order accurate for small ``z``. Where the linearisation misses
    the law at the part's end by more than ``SPLIT_TOL F_C`` -- a breakaway, a reversal, a passage
    through the transition ``|v| < v_reg`` shorter than the sub-step -- the part is halved (the
    free velocity change ``a - v_prev`` taken as uniform over the sub-step), so the sub-step
    length is free of the law's stiffness ``F_C / v_reg``: a creep transient of 0.4 us is
    resolved inside a 100 us sub-step.

    A push below ``F_C`` has a balance: the velocity ``v_b = v_reg atanh(H / F_C)`` at which the law
    holds the force ``H = (a - v_prev) / g`` that keeps the velocity. Where the rest of the sub-step
    relaxes to it by more than :data:`Z_BALANCE` (at the slowest rate on the way: the chord from the
    part's start to the balance, or the law's slope there) and the transient's impulse is too
    small to move the first moment by ``SPLIT_TOL F_C``, the rest is one part along that chord:
    an element creeping at rest costs one part per sub-step instead of a halving down to the
    transient and a doubling back (~20 parts on average behind a stiff joint, up to 80).

    Returns the mean force over the sub-step, ``False`` (never sticks) and the slope of the
    force's straight-line fit over the sub-step (its first moment: the plant propagates it
    exactly, so the position feels when in the sub-step the force switched). Parameters as
    :func:`stage_sim.friction.coulomb.implicit`.

    Examples
    --------
    >>> p = np.array([2.0, 1e-6])
    >>> f, stick, slope = implicit(p, 1.0, 1e-3, 1.0, 1.0)     # sliding fast: F_C, flat
    >>> round(f, 12), stick, round(slope, 12)
    (2.0, False, 0.0)
    >>> implicit(p, 0.0, 1e-3, 0.0, 1.0)[0]                    # at rest, no push: no force
    0.0
    >>> f, _, slope = implicit(p, -3e-3, 1e-3, 1e-3, 1.0)      # reversal at 1/6: +F_C, then -F_C
    >>> round(f, 2), round(slope, 2)                           # (2/6 - 10/6) F_C / 2; 12 (M_1 - f / 2)
    (-1.33, -3.33)
    >>> f, _, slope = implicit(p, 1e-3, 1e-3, 0.0, 1.0)        # F_C / 2 from rest: creeps, one part
    >>> round(f, 6), round(slope, 4)        # F_C / 2 less the impulse to v_reg atanh(1/2); its transient
    (0.999451, 0.0033)
    """
    fc = p[0] * sc
    ve = p[1]
    dw = a - v_prev
    tol = SPLIT_TOL * fc
    hold = dw / g if g > 0.0 else 0.0
    bal = abs(hold) < fc * (1.0 - 1e-12)
    vb, sb = 0.0, 0.0
    if bal:
        tb = hold / fc
        vb = ve * math.atanh(tb)
        sb = fc / ve * (1.0 - tb * tb)
    v, left, imp, mom, ds = v_prev, 1.0, 0.0, 0.0, 1.0
    for _ in range(MAX_PARTS):
        th = math.tanh(v / ve)
        f0 = fc * th
        if bal:
            cs = (f0 - hold) / (v - vb) if v != vb else sb
            zr = g * left * min(cs, sb)
            if zr >= Z_BALANCE and 12.0 * abs(v - vb) * left <= tol * g * zr:
                f, m1, v1 = _relax(f0, cs, v, dw * left, g * left)
                imp += f * left
                mom += f * left * (1.0 - left) + m1 * left * left
                return imp, False, 12.0 * (mom - 0.5 * imp)
        ct = fc / ve * (1.0 - th * th)
        f, m1, v1 = _relax(f0, ct, v, dw * ds, g * ds)
        if abs(fc * math.tanh(v1 / ve) - f0 - ct * (v1 - v)) > tol and ds > 1e-9:
            ds *= 0.5
            continue
        imp += f * ds
        mom += f * ds * (1.0 - left) + m1 * ds * ds
        v = v1
        if ds >= left:
            return imp, False, 12.0 * (mom - 0.5 * imp)
        left -= ds
        ds = min(2.0 * ds, left)
    th = math.tanh(v / ve)
    f, m1, v1 = _relax(fc * th, fc / ve * (1.0 - th * th), v, dw * left, g * left)
    imp += f * left
    mom += f * left * (1.0 - left) + m1 * left * left
    return imp, False, 12.0 * (mom - 0.5 * imp)


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force at velocity ``v`` [N]: ``F_C tanh(v / v_reg)``."""
    return p[0] * math.tanh(v / p[1])
