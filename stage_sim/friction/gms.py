"""Generalized Maxwell-slip model with Coulomb slip (Eq. 4.4): schema, kernels, model class.

``n`` blocks of stiffness ``k_i`` in parallel, each sticking until its force reaches
``alpha_i F_C`` and slipping there; exact for any monotone displacement increment.
"""
from __future__ import annotations

from typing import Literal

import numpy as np
from numba import njit
from pydantic import Field, model_validator

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import FrictionVariation, Model, variation_entries

NAME = "gms"
IMPLICIT = False
FEEDFORWARD = True


class GmsFriction(FrictionVariation):
    """Generalized Maxwell-slip model with Coulomb slip, Eq. 4.4."""
    model: Literal["gms"]
    k: list[Pos] = Field(min_length=1, description="block stiffnesses k_i [N/m]",
                         json_schema_extra=unit("N/m", 1.0, 1e10))
    alpha: list[Pos] = Field(min_length=1, description="block saturation fractions alpha_i [-]")
    f_c: Pos = Field(description="Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))
    viscous: NonNeg = Field(0.0, description="viscous coefficient to ground [N·s/m]",
                            json_schema_extra=unit("N·s/m", 1e-3, 1e5))

    @model_validator(mode="after")
    def _same_length(self):
        if len(self.k) != len(self.alpha):
            raise ValueError(f"k has {len(self.k)} blocks but alpha has {len(self.alpha)}")
        return self


Schema = GmsFriction


def element(k: list, alpha: list, f_c: float, viscous: float = 0.0, **variation) -> dict:
    """A generalized Maxwell-slip element as a preset mapping (``model: gms``; block stiffnesses
    ``k`` [N/m] and capacity fractions ``alpha``, the values as given, validated with the preset).
    ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element([1e5, 2e5], [0.4, 0.6], 5.0)
    {'model': 'gms', 'k': [100000.0, 200000.0], 'alpha': [0.4, 0.6], 'f_c': 5.0, 'viscous': 0.0}
    """
    return {"model": NAME, "k": list(k), "alpha": list(alpha), "f_c": f_c, "viscous": viscous,
            **variation_entries(variation)}


# --------------------------------------------------------------------------- scalar kernels
@njit(cache=True, inline="always")
def gms_block(f_i, dx, k_i, limit):
    """One Maxwell-slip block (Eq. 4.4) after a displacement ``dx`` [m]: it sticks
    (``f_i + k_i dx``) up to ``±limit`` (= ``alpha_i F_C``) and slips there. Exact for any
    monotone ``dx``; the one place the GMS block law is written.

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


# --------------------------------------------------------------------------- the law's interface
def params(cfg: GmsFriction) -> np.ndarray:
    """Parameter row: ``f_c, n, k_0 ... k_{n-1}, alpha_0 f_c ... alpha_{n-1} f_c`` (block limits)."""
    n = len(cfg.k)
    return np.array([cfg.f_c, n] + list(cfg.k) + [a * cfg.f_c for a in cfg.alpha], float)


def n_state(cfg: GmsFriction) -> int:
    """State slots per trial: the block forces [N]."""
    return len(cfg.k)


def stiffness_at_rest(cfg: GmsFriction) -> float:
    """Tangent stiffness of the relaxed element [N/m]: ``sum(k_i)``.

    >>> stiffness_at_rest(GmsFriction(model="gms", k=[1e5, 2e5], alpha=[0.4, 0.6], f_c=5.0))
    300000.0
    """
    return float(sum(cfg.k))


def explicit_damping(cfg: GmsFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m] (none)."""
    return 0.0


def sliding_force(cfg: GmsFriction) -> float:
    """Force after a long motion [N]: ``F_C sum(alpha_i)``."""
    return float(cfg.f_c * sum(cfg.alpha))


def virgin(cfg: GmsFriction, x) -> np.ndarray:
    """Force [N] along the virgin curve at displacements ``x >= 0`` [m]: ``sum min(k_i x, alpha_i F_C)``."""
    x = np.asarray(x, float)
    tot = np.zeros_like(x)
    for k, a in zip(cfg.k, cfg.alpha):
        tot += np.minimum(k * x, a * cfg.f_c)
    return tot


def with_stiffness(cfg: GmsFriction, factor: float) -> GmsFriction:
    """The law with every block stiffness scaled by ``factor`` (feedforward stiffness errors)."""
    return cfg.model_copy(update={"k": [k * factor for k in cfg.k]})


@njit(cache=True, inline="always")
def update(p, s, b, dx, h):
    """Block forces of trial ``b`` after a monotone displacement ``dx`` [m], in place."""
    n = int(p[1])
    for i in range(n):
        s[i, b] = gms_block(s[i, b], dx, p[2 + i], p[2 + n + i])


@njit(cache=True, inline="always")
def held(p, s, b, v):
    """``(force [N], tangent stiffness [N/m])`` of trial ``b`` moving at ``v`` [m/s]."""
    n = int(p[1])
    d = 1.0 if v > 0.0 else -1.0
    fe = 0.0
    kt = 0.0
    for i in range(n):
        fi = s[i, b]
        fe += fi
        kt += gms_block_tangent(fi, d, p[2 + i], p[2 + n + i])
    return fe, kt


@njit(cache=True, inline="always")
def level(p, s, b, v):
    """Friction force of trial ``b`` from its state [N]: the sum of the block forces."""
    fe = 0.0
    for i in range(int(p[1])):
        fe += s[i, b]
    return fe


class GMS(Model):
    """Generalized Maxwell-slip model with Coulomb slip (Eq. 4.4) over a batch of trials.

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
