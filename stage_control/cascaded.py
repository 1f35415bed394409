"""Cascaded P position / P velocity loop of the EMPS benchmark, and its rigid-axis closed loop.

The EMPS axis (``shared/data/emps/README.md``) is run by a dSPACE loop at 1 kHz::

    qf(k)  = (qm(k) + qm(k-1)) / 2                      FIR filter of the measured position
    qd(k)  = (qf(k) - qf(k-1)) / dt                     velocity used by the loop
    vir(k) = sat( kp kv (qg(k) - qm(k)) - kv qd(k) )    drive input [V], saturated at +-limit
    tau(k) = gtau vir(k)                                force on the load [N], held over a sample

It is not the project's PID (:mod:`stage_control.servo` differentiates the *error*; this loop
differentiates the *measurement* through a two-tap filter), so it lives here, ROS-free and
small: :func:`cascaded_command` evaluates the law on a recorded (or simulated) position,
:func:`simulate_rigid` closes it around the rigid-body inverse-dynamic model of the benchmark
(``tau = M qdd + Fv qd + Fc sign(qd) + offset``, with optional direction-asymmetric and
position-dependent friction), as the benchmark's own closed-loop simulation does.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["CascadedPP", "RigidAxis", "cascaded_command", "simulate_rigid"]


@dataclass(frozen=True)
class CascadedPP:
    """Gains of the cascaded P/P loop.

    Parameters
    ----------
    kp : float
        Outer position-loop gain [1/s].
    kv : float
        Inner velocity-loop gain [V/(m/s)].
    gain : float
        Drive gain from loop output to force ``gtau`` [N/V].
    limit : float
        Saturation of the loop output [V] (EMPS simulation: 10 V).
    rate : float
        Loop rate [Hz].
    """
    kp: float
    kv: float
    gain: float
    limit: float = 10.0
    rate: float = 1000.0

    def __post_init__(self):
        for name in ("kp", "kv", "gain", "limit", "rate"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"CascadedPP.{name} = {v!r}: expected a finite value > 0")


@dataclass(frozen=True)
class RigidAxis:
    """Rigid-body axis with friction, in the benchmark's inverse-dynamic convention.

    ``tau = M qdd + F(qd, q) + offset`` with, moving in ``+`` (``-``) direction,
    ``F = +-(fc_pos|neg + g1 (q - xc) + g2 (q - xc)^2) + fv_pos|neg qd``. Coulomb friction is
    solved implicitly (sticks at rest while ``|tau - offset| <= F_C``). Units: kg, N, N·s/m,
    N/m, N/m², m. ``resolution`` quantizes the measured position [m] (0 = ideal).
    """
    mass: float
    fc_pos: float = 0.0
    fc_neg: float = 0.0
    fv_pos: float = 0.0
    fv_neg: float = 0.0
    offset: float = 0.0
    g1: float = 0.0
    g2: float = 0.0
    xc: float = 0.0
    resolution: float = 0.0

    def __post_init__(self):
        if not (np.isfinite(self.mass) and self.mass > 0):
            raise ValueError(f"RigidAxis.mass = {self.mass!r}: expected a finite value > 0 [kg]")


def cascaded_command(ctrl: CascadedPP, qg, qm) -> np.ndarray:
    """Loop output ``vir`` [V] for reference ``qg`` and measurement ``qm`` (arrays [m]).

    The filter and difference start at rest on the first sample (``qm(-1) = qm(0)``).
    """
    qg = np.asarray(qg, float)
    qm = np.asarray(qm, float)
    qf = 0.5 * (qm + np.r_[qm[:1], qm[:-1]])
    qd = np.r_[0.0, np.diff(qf)] * ctrl.rate
    return np.clip(ctrl.kp * ctrl.kv * (qg - qm) - ctrl.kv * qd, -ctrl.limit, ctrl.limit)


@njit(cache=True)
def _rigid_loop(qg, q0, kp, kv, gain, limit, dt, n_sub, m, fcp, fcn, fvp, fvn, off, g1, g2, xc, res,
                out_q, out_qm, out_v, out_tau):
    n = qg.shape[0]
    h = dt / n_sub
    x = q0
    v = 0.0
    qm_prev = q0
    qf_prev = q0
    for k in range(n):
        qm = x if res <= 0.0 else res * np.round(x / res)
        qf = 0.5 * (qm + qm_prev)
        qd = (qf - qf_prev) / dt if k > 0 else 0.0
        vir = kp * kv * (qg[k] - qm) - kv * qd
        vir = limit if vir > limit else (-limit if vir < -limit else vir)
        tau = gain * vir
        out_q[k] = x
        out_qm[k] = qm
        out_v[k] = v
        out_tau[k] = tau
        qm_prev = qm
        qf_prev = qf
        for _ in range(n_sub):
            dx = x - xc
            dfc = g1 * dx + g2 * dx * dx
            fv = fvp if v > 0.0 else (fvn if v < 0.0 else 0.5 * (fvp + fvn))
            v_free = v + h * (tau - off - fv * v) / m
            if v_free > 0.0:
                stop = h * max(fcp + dfc, 0.0) / m
                v = v_free - stop if v_free > stop else 0.0
            else:
                stop = h * max(fcn + dfc, 0.0) / m
                v = v_free + stop if v_free < -stop else 0.0
            x += h * v
    return 0


def simulate_rigid(ctrl: CascadedPP, axis: RigidAxis, qg, q0: float | None = None, n_sub: int = 20) -> dict:
    """Closed loop of ``ctrl`` on ``axis`` following the reference ``qg`` (array [m]).

    Starts at rest at ``q0`` (default ``qg[0]``). Each loop period is split into ``n_sub``
    semi-implicit Euler sub-steps (the force ``tau`` is held over the period).

    Returns
    -------
    dict
        ``q`` true position [m], ``qm`` measured (quantized) position [m], ``v`` velocity
        [m/s], ``tau`` force command [N]; arrays like ``qg``.
    """
    qg = np.ascontiguousarray(qg, float)
    n = len(qg)
    out = {k: np.empty(n) for k in ("q", "qm", "v", "tau")}
    a = axis
    _rigid_loop(qg, float(qg[0] if q0 is None else q0), ctrl.kp, ctrl.kv, ctrl.gain, ctrl.limit, 1.0 / ctrl.rate,
                int(n_sub), a.mass, a.fc_pos, a.fc_neg, a.fv_pos, a.fv_neg, a.offset, a.g1, a.g2, a.xc,
                a.resolution, out["q"], out["qm"], out["v"], out["tau"])
    return out
