"""Coulomb + viscous friction with stiction: schema, kernels, model class.

No state: the plant solves the element implicitly per sub-step (:func:`implicit`): it
sticks while the force needed to stop the body is within the static limit, so there is no
chattering at rest.
"""
from __future__ import annotations

from typing import Literal, Optional

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg
from stage_sim.validation import unit

from .base import FrictionVariation, Model, variation_entries

NAME = "coulomb"
IMPLICIT = True        # solved per sub-step from the velocity the other forces give
FEEDFORWARD = False


class CoulombFriction(FrictionVariation):
    """Coulomb + viscous friction with stiction (stick while |force| <= f_s)."""
    model: Literal["coulomb"]
    f_c: NonNeg = Field(description="Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    f_s: Optional[NonNeg] = Field(None, description="static force [N]; default f_c",
                                  json_schema_extra=unit("N", 1e-3, 1e3))
    viscous: NonNeg = Field(0.0, description="viscous coefficient [N·s/m]",
                            json_schema_extra=unit("N·s/m", 1e-3, 1e5))


Schema = CoulombFriction


def element(f_c: float, f_s: float | None = None, viscous: float = 0.0, **variation) -> dict:
    """A Coulomb element as a preset mapping (``model: coulomb``; ``f_s`` None = ``f_c``; the
    values as given, validated with the preset). ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element(5.31, viscous=10.0)
    {'model': 'coulomb', 'f_c': 5.31, 'f_s': None, 'viscous': 10.0}
    """
    return {"model": NAME, "f_c": f_c, "f_s": f_s, "viscous": viscous, **variation_entries(variation)}


def params(cfg: CoulombFriction) -> np.ndarray:
    """Parameter row: ``f_c, f_s`` (``f_s`` defaults to ``f_c``)."""
    return np.array([cfg.f_c, cfg.f_c if cfg.f_s is None else cfg.f_s], float)


def n_state(cfg: CoulombFriction) -> int:
    """No state."""
    return 0


def stiffness_at_rest(cfg: CoulombFriction) -> float:
    """No pre-motion stiffness (rigid stiction)."""
    return 0.0


def explicit_damping(cfg: CoulombFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m] (none)."""
    return 0.0


def sliding_force(cfg: CoulombFriction) -> float:
    """Sliding force [N]: ``F_C``."""
    return float(cfg.f_c)


def virgin(cfg: CoulombFriction, x) -> np.ndarray:
    """Force [N] at displacements ``x`` [m] from rest: ``F_C`` at once."""
    return np.full(np.shape(x), float(cfg.f_c))


@njit(cache=True, inline="always")
def implicit(p, a, g, v_prev, sc):
    """The element's force over a sub-step, solved implicitly.

    Parameters
    ----------
    p : ndarray
        Parameter row (:func:`params`).
    a : float
        Velocity of the body at the end of the sub-step without this element [m/s].
    g : float
        Velocity change per unit force held over the sub-step [m/(N s)].
    v_prev : float
        Velocity at the start of the sub-step [m/s] (0 = at rest: the static limit applies).
    sc : float
        Force scale of the element's variation (1 without).

    Returns
    -------
    (float, bool)
        Force [N] resisting the motion, and whether the body sticks (its velocity is then 0).
    """
    f_stop = a / g
    lim = (p[1] if v_prev == 0.0 else p[0]) * sc
    stick = abs(f_stop) <= lim
    return (f_stop if stick else p[0] * sc * (1.0 if a > 0.0 else -1.0)), stick


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force at velocity ``v`` [N]: ``F_C sgn(v)`` (0 at rest)."""
    return p[0] * (1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0))


class CoulombViscous(Model):
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
