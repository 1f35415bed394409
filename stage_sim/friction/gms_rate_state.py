"""GMS with rate-and-state sliders (issue 13, item 3): schema, kernels, model class.

Each block of the seed's generalized Maxwell-slip model (Eq. 4.4, Table 4.4: stiffness ``k_i``,
limit ``lim_i = alpha_i F_C``) keeps its spring; its Coulomb slider becomes a rate-and-state
slider (Dieterich-Ruina, aging law)::

    df_i/dt = k_i (v - w_i)
    w_i     = v_r (L_i / (v_r theta_i))^(b/a) exp((|f_i|/lim_i - 1)/a) sgn(f_i)
    dtheta_i/dt = 1 - |w_i| theta_i / L_i,          L_i = lim_i / k_i

A slipping block carries ``lim_i [1 + a ln(w/v_r) + b ln(v_r theta/L_i)]``: the direct effect
``a`` (the force relaxes, creeps, as the slip slows) and aging ``b`` (the contact strengthens
with time at rest; ``theta`` is about the dwell time). Steady sliding carries
``lim_i [1 + (a - b) ln(w/v_r)]``, so with ``b = a`` (the default) the steady slip force is
exactly ``lim_i`` at any speed, as the seed's Coulomb gross-motion friction (Sec. 4.4.3), and
``v_r`` drops out. ``L_i`` is the block's own pre-sliding distance (no new parameter).
``a = 0`` is the seed's GMS (:mod:`.gms`), bit for bit. The study that found it and its
evidence (App. C.1 step-sequence growth, Table 4.2 No FI 5 mm) and cost (in-position RMS) are
in :mod:`experiment_runner.apps.paper.micro` and docs/headline.md, "Micrometre physics".

Discretisation (per plant sub-step ``h`` with bearing displacement ``dx``): backward Euler in
the block force, ``f = f_old + k dx - k h w(f, theta_old)``, solved to machine precision by a
safeguarded Newton iteration (the slip rate is exponential in ``f`` with scale ``a lim``:
explicit schemes would need ``h << a lim/(k v)``); then backward Euler in ``theta`` with the new
slip rate, ``theta = (theta_old + h)/(1 + h |w|/L)``. Both are unconditionally stable, and
their steady sliding state is exact (``w = dx/h``, ``theta = L/w``, hence ``|f| = lim`` for
``b = a``); the relaxation at rest is first order in ``h`` (tested against the exact solution).

State per trial: the block forces ``f_i`` [N], then ``theta_i - theta0`` [s] (so the plant's
zero state is the relaxed element, ``theta0`` seconds at rest).

``stiffness_at_rest``, ``sliding_force`` and ``virgin`` are the GMS's: at rest each block is its
spring ``k_i`` (the slip is not instantaneous); steady sliding carries ``sum alpha_i F_C`` for
``b = a`` (at ``v_r`` otherwise); the virgin curve is the quasi-static (``a -> 0``) envelope, which a
motion from an aged contact first overshoots by about ``a lim_i ln(v theta0/L_i)`` per block (the
static peak; tested).
"""
from __future__ import annotations

import math
from typing import Literal, Optional

import numpy as np
from numba import njit
from pydantic import Field

from stage_sim.schema import NonNeg, Pos
from stage_sim.validation import unit

from .base import Model, variation_entries
from .gms import GmsFriction, gms_block, gms_block_tangent
from .gms import sliding_force, stiffness_at_rest, virgin  # noqa: F401  (the same as the seed's GMS)

NAME = "gms_rate_state"
IMPLICIT = False
FEEDFORWARD = False          # rate dependent: the servo's feedforward models are rate-independent


class GmsRateStateFriction(GmsFriction):
    """GMS (Eq. 4.4, Table 4.4 blocks) whose Coulomb sliders are rate-and-state sliders (aging law).

    ``a = 0`` is the seed's GMS exactly. ``b`` defaults to ``a`` (rate-independent steady sliding,
    the seed's Coulomb gross motion, Sec. 4.4.3).
    """
    model: Literal["gms_rate_state"]
    a: NonNeg = Field(description=(
        "direct effect of the rate-and-state sliders [-]: a slipping block's force changes by "
        "a lim_i ln(w2/w1) between slip rates; not in the seed. issue 13 study "
        "(experiment_runner/apps/paper/micro.py): a = b = 0.02 is bracketed by two seed numbers (App. C.1 "
        "eighth 5 um step 85 ms, Table 4.2 No FI 5 mm 44 ms), NOT identified"),
        json_schema_extra=unit("1", 1e-3, 0.2))
    b: Optional[NonNeg] = Field(None, description=(
        "aging of the rate-and-state sliders [-] (force gain b lim_i ln(theta) with time at rest); "
        "None = a, so that steady sliding is Coulomb at any speed (Sec. 4.4.3)"),
        json_schema_extra=unit("1", 1e-3, 0.2))
    v_r: Pos = Field(0.08, description=(
        "reference slip rate [m/s] at which a steady slipping block carries alpha_i F_C; drops out "
        "for b = a. Default: the 5 mm move's peak speed (Sec. 3.4.1: 5 mm in 125 ms, triangular)"),
        json_schema_extra=unit("m/s", 1e-9, 10.0))
    theta0: Pos = Field(1.0, description=(
        "aging state of the relaxed element [s]: time at rest before the record (not in the seed; "
        "0.1-10 s moves the eighth App. C.1 5 um step by < 0.1 ms in the study)"),
        json_schema_extra=unit("s", 1e-3, 1e5))

    @property
    def b_eff(self) -> float:
        """The aging ``b`` in use (``a`` when unset)."""
        return self.a if self.b is None else self.b


Schema = GmsRateStateFriction


def element(k: list, alpha: list, f_c: float, a: float, b: float | None = None, v_r: float = 0.08,
            theta0: float = 1.0, viscous: float = 0.0, **variation) -> dict:
    """A GMS element with rate-and-state sliders as a preset mapping (``model: gms_rate_state``;
    the values as given, validated with the preset). ``variation``: :class:`.base.FrictionVariation` fields.

    >>> element([1e5], [1.0], 5.0, a=0.02)["b"] is None
    True
    """
    return {"model": NAME, "k": list(k), "alpha": list(alpha), "f_c": f_c, "a": a, "b": b, "v_r": v_r,
            "theta0": theta0, "viscous": viscous, **variation_entries(variation)}


# --------------------------------------------------------------------------- scalar kernels
@njit(cache=True)
def slip_block(f_old, dx, k, lim, a, v_r, h, c_state=1.0):
    """Backward-Euler step of one rate-dependent block: the root ``f`` of
    ``f = f_old + k dx - k h w(f)``, ``w = v_r c_state exp((|f|/lim - 1)/a) sgn(f)``.

    ``c_state`` carries the aging state (``(L/(v_r theta))^(b/a)``; 1 without it). ``a <= 0``:
    the seed's Coulomb slip at ``±lim``. The root is the Lambert W closed form
    ``|f| = |f_tr| - a lim W(X)``, ``X = c/(a lim) exp((|f_tr| - lim)/(a lim))``, ``c = k h v_r c_state``,
    ``f_tr = f_old + k dx`` (the elastic predictor); ``W`` by Newton on ``W e^W = X`` (``X <= e``) or on
    ``W + ln W = ln X`` (larger ``X``, no overflow), both monotonically convergent to machine precision.

    Examples
    --------
    >>> f = slip_block(0.0, 1e-3, 1e5, 1.0, 0.02, 0.08, 1e-5)   # slips: |f| + c exp((|f| - 1)/0.02) = 100
    >>> round(f, 9), bool(abs(f + 0.08 * np.exp((f - 1.0) / 0.02) - 100.0) < 1e-9)
    (1.142388184, True)
    >>> slip_block(0.0, 1e-7, 1e5, 1.0, 0.02, 0.08, 1e-5)       # sticks: elastic
    0.01
    """
    f_tr = f_old + k * dx
    if a <= 0.0:                                 # seed's GMS: Coulomb slip at the limit
        return min(max(f_tr, -lim), lim)
    s = 1.0 if f_tr >= 0.0 else -1.0
    y_tr = abs(f_tr)
    c = k * h * v_r * c_state                    # force relaxed per unit exp(...) in one step
    q = a * lim
    if c * math.exp((y_tr - lim) / q) < 1e-12 * lim:
        return f_tr                              # creep negligible: elastic predictor stands
    ln_x = math.log(c / q) + (y_tr - lim) / q
    if ln_x <= 1.0:                              # W e^W = X, from W = X (right of the root)
        x = math.exp(ln_x)
        w = x
        for _ in range(100):
            ew = math.exp(w)
            dw = (w * ew - x) / (ew * (1.0 + w))
            w -= dw
            if abs(dw) <= 1e-16 * (1.0 + w):
                break
    else:                                        # W + ln W = ln X, from ln X - ln ln X (left of it)
        w = ln_x - math.log(ln_x)
        for _ in range(100):
            dw = (w + math.log(w) - ln_x) * w / (w + 1.0)
            w -= dw
            if abs(dw) <= 1e-16 * (1.0 + w):
                break
    y = y_tr - q * w
    return s * y if y > 0.0 else 0.0


@njit(cache=True)
def slider_step(f, theta, dx, k, lim, ell, a, b, v_r, h):
    """One step ``h`` [s] of a block with a rate-and-state slider after ``dx`` [m]; returns ``(f, theta)``.

    ``b = 0``: rate dependence only (``theta`` unchanged); ``a = 0``: the seed's Coulomb block.
    ``ell`` is the block's pre-sliding distance ``lim/k`` [m].
    """
    if b <= 0.0 or a <= 0.0:
        return slip_block(f, dx, k, lim, a, v_r, h), theta
    cs = (ell / (v_r * theta)) ** (b / a)
    f = slip_block(f, dx, k, lim, a, v_r, h, cs)
    w = v_r * cs * math.exp((abs(f) / lim - 1.0) / a)
    return f, (theta + h) / (1.0 + h * w / ell)


@njit(cache=True)
def slip_rate(f, theta, lim, ell, a, b, v_r):
    """Slip rate ``w`` [m/s] of a block holding ``f`` [N] at aging state ``theta`` [s] (signed as ``f``)."""
    cs = (ell / (v_r * theta)) ** (b / a) if b > 0.0 else 1.0
    w = v_r * cs * math.exp((abs(f) / lim - 1.0) / a)
    return w if f >= 0.0 else -w


# --------------------------------------------------------------------------- the law's interface
def params(cfg: GmsRateStateFriction) -> np.ndarray:
    """Parameter row: ``f_c, n, k_0..k_{n-1}, lim_0..lim_{n-1}, a, b, v_r, theta0`` (``lim_i = alpha_i f_c``)."""
    n = len(cfg.k)
    return np.array([cfg.f_c, n] + list(cfg.k) + [al * cfg.f_c for al in cfg.alpha]
                    + [cfg.a, cfg.b_eff, cfg.v_r, cfg.theta0], float)


def n_state(cfg: GmsRateStateFriction) -> int:
    """State slots per trial: the block forces [N], then ``theta_i - theta0`` [s]."""
    return 2 * len(cfg.k)


def explicit_damping(cfg: GmsRateStateFriction) -> float:
    """Damping the plant integrates explicitly [N·s/m] (none: the slip is implicit)."""
    return 0.0


def with_stiffness(cfg: GmsRateStateFriction, factor: float) -> GmsRateStateFriction:
    """The law with every block stiffness scaled by ``factor``."""
    return cfg.model_copy(update={"k": [k * factor for k in cfg.k]})


@njit(cache=True)
def update(p, s, b, dx, h):
    """Block forces and aging states of trial ``b`` after ``dx`` [m] over ``h`` [s], in place.

    Not inlined into the plant (unlike the seed's laws): a called function keeps the compiled plant
    of every other law as it was (inlining it slowed the GMS presets by ~5-10 %, measured)."""
    n = int(p[1])
    a = p[2 + 2 * n]
    if a <= 0.0:                                 # the seed's GMS, the same arithmetic as gms.update
        for i in range(n):
            s[i, b] = gms_block(s[i, b], dx, p[2 + i], p[2 + n + i])
        return
    bb, v_r, th0 = p[3 + 2 * n], p[4 + 2 * n], p[5 + 2 * n]
    for i in range(n):
        k, lim = p[2 + i], p[2 + n + i]
        f, th = slider_step(s[i, b], th0 + s[n + i, b], dx, k, lim, lim / k, a, bb, v_r, h)
        s[i, b] = f
        s[n + i, b] = th - th0


@njit(cache=True)
def held(p, s, b, v):
    """``(force [N], tangent stiffness [N/m])`` of trial ``b`` moving at ``v`` [m/s].

    A block's tangent is ``df_i/dx = k_i (1 - w_i/v)`` (clipped to ``[0, k_i]``): ``k_i`` at rest,
    ~0 in steady slip (``w_i = v``), as the GMS block's stick/slip tangent for ``a = 0``."""
    n = int(p[1])
    a = p[2 + 2 * n]
    d = 1.0 if v > 0.0 else -1.0
    fe = 0.0
    kt = 0.0
    if a <= 0.0:
        for i in range(n):
            fi = s[i, b]
            fe += fi
            kt += gms_block_tangent(fi, d, p[2 + i], p[2 + n + i])
        return fe, kt
    bb, v_r, th0 = p[3 + 2 * n], p[4 + 2 * n], p[5 + 2 * n]
    av = abs(v)
    for i in range(n):
        fi = s[i, b]
        k, lim = p[2 + i], p[2 + n + i]
        fe += fi
        if av > 0.0:
            r = 1.0 - d * slip_rate(fi, th0 + s[n + i, b], lim, lim / k, a, bb, v_r) / av
            kt += k * min(max(r, 0.0), 1.0)
        else:
            kt += k
    return fe, kt


@njit(cache=True)
def level(p, s, b, v):
    """Friction force of trial ``b`` from its state [N]: the sum of the block forces."""
    fe = 0.0
    for i in range(int(p[1])):
        fe += s[i, b]
    return fe


class GmsRateState(Model):
    """GMS with rate-and-state sliders over a batch of trials (time-stepped: ``drive(x, dt)``).

    Parameters
    ----------
    k, alpha : array_like
        Block stiffnesses [N/m] and saturation fractions [-] (Table 4.4).
    f_c : float
        Coulomb force [N].
    a : float
        Direct effect [-]. ``b`` [-] (default ``a``), ``v_r`` [m/s], ``theta0`` [s] as the schema.
    """

    def __init__(self, k, alpha, f_c: float, a: float, b: float | None = None, v_r: float = 0.08,
                 theta0: float = 1.0, n_trials: int = 1):
        cfg = GmsRateStateFriction(model=NAME, k=list(k), alpha=list(alpha), f_c=f_c, a=a, b=b, v_r=v_r,
                                   theta0=theta0)
        self.p = params(cfg)
        self.n_state = n_state(cfg)
        super().__init__(n_trials)

    def force(self):
        return self.state[:, :self.n_state // 2].sum(axis=1)

    def step(self, dx, dt=1e-4):
        dx = np.broadcast_to(np.asarray(dx, float), (self.n_trials,))
        s = np.ascontiguousarray(self.state.T)          # (slots, trials), the plant's layout
        for b in range(self.n_trials):
            _update(self.p, s, b, float(dx[b]), float(dt))
        self.state = np.ascontiguousarray(s.T)
        return self.force()


@njit(cache=True)
def _update(p, s, b, dx, h):
    update(p, s, b, dx, h)
