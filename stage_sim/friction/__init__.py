"""Friction laws of the seed and their registry: Dahl, GMS, LuGre, Coulomb, regularised Coulomb,
GMS with rate-and-state sliders.

One module per law (:mod:`.dahl`, :mod:`.gms`, :mod:`.lugre`, :mod:`.coulomb`,
:mod:`.regularized`, :mod:`.gms_rate_state`) owns all of it: its schema (the ``model: NAME`` entry of a preset's
friction), its compiled kernels (state update, held force and tangent stiffness, or an
implicit per-sub-step solve), its stiffness at rest and its virgin curve. This registry is
what the rest of the code iterates: the preset schema (:data:`FRICTION`), the plant
(:func:`update`, :func:`held`, :func:`implicit` dispatched on the law's integer id
:func:`kind`), the servo's feedforward (:attr:`FEEDFORWARD` laws), the diagnosis and the
design advisor (:func:`law`, :func:`initial_stiffness`).

**Adding a law**: write ``stage_sim/friction/NAME.py`` with the attributes and functions of
the others (``NAME``, ``Schema``, ``IMPLICIT``, ``FEEDFORWARD``, ``params``, ``n_state``,
``stiffness_at_rest``, ``explicit_damping``, ``sliding_force``, ``virgin``, ``element`` (the
law's preset mapping: every module that writes an element of the law calls it), and the kernels
``update``/``held``/``level`` for a stateful law or ``implicit``/``level`` for an implicit
one), then append it to :data:`LAWS` here and add its branch to each dispatcher below.

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
>>> [law.NAME for law in LAWS]
['dahl', 'gms', 'lugre', 'coulomb', 'regularized_coulomb', 'gms_rate_state']
"""
from __future__ import annotations

from typing import Annotated, Union

from numba import njit
from pydantic import Field

from . import coulomb, dahl, gms, gms_rate_state, lugre, regularized
from .base import FrictionVariation, Model, virgin_curve
from .coulomb import CoulombFriction, CoulombViscous
from .dahl import Dahl, DahlFriction, dahl_tangent, dahl_update
from .gms import GMS, GmsFriction, gms_block, gms_block_tangent, gms_update
from .lugre import LuGre, LugreFriction, lugre_update, stribeck
from .gms_rate_state import GmsRateStateFriction
from .regularized import RegularizedCoulombFriction

__all__ = [
    "LAWS", "FRICTION", "law", "kind", "initial_stiffness", "update", "held", "implicit", "level",
    "DAHL", "GMS_KIND", "LUGRE", "COULOMB", "REGULARIZED", "GMS_RATE_STATE",
    "FrictionVariation", "DahlFriction", "GmsFriction", "LugreFriction", "CoulombFriction",
    "RegularizedCoulombFriction", "GmsRateStateFriction",
    "dahl_update", "dahl_tangent", "gms_block", "gms_block_tangent", "gms_update", "lugre_update", "stribeck",
    "Dahl", "GMS", "LuGre", "CoulombViscous", "Model", "virgin_curve",
]

LAWS = (dahl, gms, lugre, coulomb, regularized, gms_rate_state)
"""Every law, in the order of their integer ids (1, 2, ...): the compiled plant dispatches on them."""

DAHL, GMS_KIND, LUGRE, COULOMB, REGULARIZED, GMS_RATE_STATE = range(1, len(LAWS) + 1)
_BY_NAME = {m.NAME: m for m in LAWS}
assert [m.NAME for m in LAWS] == ["dahl", "gms", "lugre", "coulomb", "regularized_coulomb", "gms_rate_state"]

FRICTION = Annotated[Union[tuple(m.Schema for m in LAWS)], Field(discriminator="model")]
"""Schema of a friction element: any law's, told apart by its ``model`` field."""


def law(cfg):
    """The module of the law of a friction config (or of a ``model`` name)."""
    return _BY_NAME[cfg if isinstance(cfg, str) else cfg.model]


def kind(cfg) -> int:
    """Integer id of the law of a friction config (1-based position in :data:`LAWS`)."""
    return LAWS.index(law(cfg)) + 1


def initial_stiffness(cfg) -> float:
    """Tangent stiffness [N/m] of a relaxed friction element at rest (Dahl ``k_sigma``, GMS
    ``sum(k_i)``, LuGre ``sigma0``, Coulomb 0): the pre-motion stiffness the plant's sub-steps
    and the FI design advisor work with.

    >>> initial_stiffness(GmsFriction(model="gms", k=[1e5, 2e5], alpha=[0.4, 0.6], f_c=5.0))
    300000.0
    """
    return law(cfg).stiffness_at_rest(cfg)


# --------------------------------------------------------------------------- compiled dispatch
# One branch per law; ``kind`` is the law's id, ``p`` its parameter row (``law.params``),
# ``s`` its state (slots, trials), ``b`` the trial.
@njit(cache=True, inline="always")
def update(kind, p, s, b, dx, h):
    """Advance the state of a stateful law by the displacement ``dx`` [m] over ``h`` [s]."""
    if kind == DAHL:
        dahl.update(p, s, b, dx, h)
    elif kind == GMS_KIND:
        gms.update(p, s, b, dx, h)
    elif kind == LUGRE:
        lugre.update(p, s, b, dx, h)
    elif kind == GMS_RATE_STATE:
        gms_rate_state.update(p, s, b, dx, h)


@njit(cache=True, inline="always")
def held(kind, p, s, b, v):
    """``(force [N], tangent stiffness [N/m])`` of a stateful law at velocity ``v`` [m/s]."""
    if kind == DAHL:
        return dahl.held(p, s, b, v)
    if kind == GMS_KIND:
        return gms.held(p, s, b, v)
    if kind == LUGRE:
        return lugre.held(p, s, b, v)
    if kind == GMS_RATE_STATE:
        return gms_rate_state.held(p, s, b, v)
    return 0.0, 0.0


@njit(cache=True, inline="always")
def implicit(kind, p, a, g, v_prev, sc):
    """``(mean force [N], sticks, slope [N])`` of an implicit law over a sub-step: the force held is
    ``mean + slope (s - 1/2)`` at the fraction ``s`` of the sub-step (see :func:`.coulomb.implicit`,
    :func:`.regularized.implicit`; Coulomb's is held flat)."""
    if kind == COULOMB:
        f, stick = coulomb.implicit(p, a, g, v_prev, sc)
        return f, stick, 0.0
    if kind == REGULARIZED:
        return regularized.implicit(p, a, g, v_prev, sc)
    return 0.0, False, 0.0


@njit(cache=True, inline="always")
def level(kind, p, s, b, v):
    """Friction force of any law from its state and velocity [N] (no viscous part)."""
    if kind == DAHL:
        return dahl.level(p, s, b, v)
    if kind == GMS_KIND:
        return gms.level(p, s, b, v)
    if kind == LUGRE:
        return lugre.level(p, s, b, v)
    if kind == COULOMB:
        return coulomb.level(p, s, b, v)
    if kind == REGULARIZED:
        return regularized.level(p, s, b, v)
    if kind == GMS_RATE_STATE:
        return gms_rate_state.level(p, s, b, v)
    return 0.0
