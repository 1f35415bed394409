"""Servo controller: PID + optional DOB, feedforward friction compensation and NIASA.

The command at sample ``k`` is (all forces in N, positions in m)::

    e     = x_ref - x_meas
    u_pid = kp e + I + D[e]                              PID, Appendix A
    u_ff  = F_model(x_ref) + c_v v_ref                   feedforward, Fig. 4.15
    d_hat = Q G_n^-1 [x_meas] - Q [u_{k-1}]              DOB, Eq. C.1-C.5
    u_k   = sat(u_pid + u_ff - d_hat)

Design choices
--------------
* Integral: backward Euler, ``I += K_I dt e`` with ``K_I = ki`` or the NIASA gain of
  Eq. A.1. Clamping anti-windup: the increment is discarded when the unsaturated
  command exceeds the limit and ``e`` has the sign of the command.
* Derivative ``kd s/(s/wd + 1)`` on the error, backward Euler (stable, no ringing for
  any ``wd``); without ``derivative_cutoff`` the plain difference ``kd (e_k - e_{k-1})/dt``.
* DOB filters ``Q G_n^-1`` and ``Q`` (Eq. C.1, C.2): Tustin. ``Q`` is fed the command
  *applied at the previous sample*: ``x_meas[k]`` only reflects commands up to ``k-1``
  (zero-order hold), so this aligns both paths and avoids an algebraic loop.
* Feedforward (Fig. 4.15): the Dahl or GMS model of ``Feedforward.friction`` (stiffnesses
  scaled by ``1 + stiffness_error``) is driven by the increments of ``x_ref``; its force
  ``F`` plus ``viscous * v_ref`` is *added* to the command (the stage feels ``-F``).
* NIASA (Eq. A.1): ``K_I = (k_sigma (1 - F_hat/F_c sgn(xdot)) + kp)/tau_d`` replaces
  ``ki``; ``F_hat`` is a nominal Dahl model (shape 1) driven by ``x_meas`` and
  ``sgn(xdot)`` is the sign of the last nonzero measured increment.
* The first call latches the reference and measurement (bumpless start): the models
  see increments only, and the derivative and DOB filters start at rest, so a trial may
  start anywhere in the travel.

State row layout (``SERVO_*`` index constants); ``n_state = 12 + n_ff``: started flag,
integral [N], derivative filter, DOB ``Q G_n^-1`` (2), DOB ``Q`` (2), previous command [N],
previous ``x_ref`` [m], previous ``x_meas`` [m], NIASA direction, NIASA ``F_hat`` [N],
feedforward friction (1 for Dahl, ``len(k)`` for GMS, 0 without feedforward).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from stage_control.filters import dc_state, discretize, realize, ss_step
from stage_sim.config import Controller, DahlFriction, GmsFriction, Stage
from stage_sim.friction import dahl_update, gms_update

__all__ = ["ServoModel", "build_servo", "init_servo_state", "servo_step"]

SERVO_STARTED, SERVO_INT, SERVO_DER = 0, 1, 2
SERVO_DOB_X, SERVO_DOB_U = 3, 5          # two slots each
SERVO_U_PREV, SERVO_XREF_PREV, SERVO_XMEAS_PREV = 7, 8, 9
SERVO_NIASA_DIR, SERVO_NIASA_F = 10, 11
SERVO_FF = 12

FF_NONE, FF_DAHL, FF_GMS = 0, 1, 2


class ServoModel(NamedTuple):
    """Compiled-loop parameters of the servo (build with :func:`build_servo`)."""
    dt: float                 # sample time [s]
    kp: float                 # [N/m]
    ki: float                 # [N/(m s)] (unused with NIASA)
    limit: float              # command saturation [N]
    d_A: np.ndarray           # derivative filter, e -> N
    d_B: np.ndarray
    d_C: np.ndarray
    d_D: np.ndarray
    d_x0: np.ndarray          # its state per unit constant error
    dob: int                  # 1 = DOB on
    qg_A: np.ndarray          # Q G_n^-1, m -> N
    qg_B: np.ndarray
    qg_C: np.ndarray
    qg_D: np.ndarray
    qg_x0: np.ndarray         # its state per unit constant position
    q_A: np.ndarray           # Q, N -> N
    q_B: np.ndarray
    q_C: np.ndarray
    q_D: np.ndarray
    ff_kind: int              # FF_NONE / FF_DAHL / FF_GMS
    ff_k: np.ndarray          # Dahl k_sigma (1,) or GMS k_i [N/m]
    ff_alpha: np.ndarray      # GMS alpha_i [-]
    ff_fc: float              # Coulomb force [N]
    ff_shape: float           # Dahl shape factor [-]
    ff_viscous: float         # [N s/m]
    n_ff: int                 # feedforward state slots
    niasa: int                # 1 = NIASA integral gain
    ni_tau: float             # tau_d [s]
    ni_ksigma: float          # nominal k_sigma [N/m]
    ni_fc: float              # nominal F_c [N]
    n_state: int


def _derivative(kd: float, cutoff: float | None, dt: float):
    if kd == 0.0:
        return tuple(np.zeros((1, 1)) for _ in range(4))
    if cutoff is None:      # kd (1 - z^-1)/dt
        return realize([kd / dt, -kd / dt], [1.0, 0.0])
    wd = 2.0 * np.pi * cutoff
    return discretize([kd * wd, 0.0], [1.0, wd], dt, "backward")


def build_servo(controller: Controller, stage: Stage) -> ServoModel:
    """Build the servo model from the controller config and the stage's drive limit.

    Parameters
    ----------
    controller : Controller
        PID gains, optional DOB, feedforward and NIASA, control ``rate`` [Hz].
    stage : Stage
        Used for ``drive.peak_force`` [N] when ``pid.output_limit`` is not set.

    Returns
    -------
    ServoModel
    """
    dt = 1.0 / controller.rate
    pid = controller.pid
    d_A, d_B, d_C, d_D = _derivative(pid.kd, pid.derivative_cutoff, dt)

    dob = controller.dob
    if dob is not None:
        wq = 2.0 * np.pi * dob.q_cutoff
        qden = [1.0, 2.0 * wq, wq * wq]
        qg = discretize(np.array([1.0, dob.pole, 0.0]) * wq * wq / dob.gain, qden, dt, "tustin")
        q = discretize([wq * wq], qden, dt, "tustin")
    else:
        qg = q = tuple(np.zeros(s) for s in ((2, 2), (2, 1), (1, 2), (1, 1)))

    ff = controller.feedforward
    ff_alpha = np.ones(1)
    ff_shape = 1.0
    if ff is None:
        kind, ff_k, ff_fc, ff_visc = FF_NONE, np.zeros(1), 1.0, 0.0
    elif isinstance(ff.friction, DahlFriction):
        fr = ff.friction
        kind, ff_k, ff_fc, ff_visc, ff_shape = (FF_DAHL, np.array([fr.k_sigma]), fr.f_c,
                                                fr.viscous, fr.shape)
    elif isinstance(ff.friction, GmsFriction):
        fr = ff.friction
        kind, ff_k, ff_fc, ff_visc = FF_GMS, np.array(fr.k, float), fr.f_c, fr.viscous
        ff_alpha = np.array(fr.alpha, float)
    else:
        raise ValueError(f"feedforward friction must be 'dahl' or 'gms', got {ff.friction.model!r}")
    if ff is not None:
        ff_k = ff_k * (1.0 + ff.stiffness_error)
    n_ff = {FF_NONE: 0, FF_DAHL: 1, FF_GMS: len(ff_k)}[kind]

    ni = controller.niasa
    limit = pid.output_limit if pid.output_limit is not None else stage.drive.peak_force
    return ServoModel(
        dt=dt, kp=float(pid.kp), ki=float(pid.ki), limit=float(limit),
        d_A=d_A, d_B=d_B, d_C=d_C, d_D=d_D, d_x0=dc_state(d_A, d_B),
        dob=int(dob is not None),
        qg_A=qg[0], qg_B=qg[1], qg_C=qg[2], qg_D=qg[3], qg_x0=dc_state(qg[0], qg[1]),
        q_A=q[0], q_B=q[1], q_C=q[2], q_D=q[3],
        ff_kind=kind, ff_k=np.ascontiguousarray(ff_k, float), ff_alpha=ff_alpha,
        ff_fc=float(ff_fc), ff_shape=float(ff_shape), ff_viscous=float(ff_visc), n_ff=n_ff,
        niasa=int(ni is not None),
        ni_tau=float(ni.tau_d) if ni else 1.0, ni_ksigma=float(ni.k_sigma) if ni else 0.0,
        ni_fc=float(ni.f_c) if ni else 1.0,
        n_state=SERVO_FF + n_ff)


def init_servo_state(model: ServoModel, n_trials: int) -> np.ndarray:
    """Relaxed servo state, shape ``(n_trials, model.n_state)``."""
    return np.zeros((int(n_trials), model.n_state))


@njit(cache=True)
def servo_step(model, state_row, x_ref, v_ref, x_meas):
    """One control sample of the servo.

    Parameters
    ----------
    model : ServoModel
    state_row : ndarray, shape (n_state,)
        One trial's state, updated in place.
    x_ref, v_ref : float
        Reference position [m] and velocity [m/s].
    x_meas : float
        Measured position [m].

    Returns
    -------
    float
        Saturated force command [N].
    """
    s = state_row
    e = x_ref - x_meas
    if s[SERVO_STARTED] == 0.0:
        s[SERVO_STARTED] = 1.0
        s[SERVO_DER] = model.d_x0[0] * e
        s[SERVO_XREF_PREV] = x_ref
        s[SERVO_XMEAS_PREV] = x_meas
        for i in range(2):
            s[SERVO_DOB_X + i] = model.qg_x0[i] * x_meas
    # derivative
    u_d = ss_step(model.d_A, model.d_B, model.d_C, model.d_D, s[SERVO_DER:SERVO_DER + 1], e)

    # NIASA nominal Dahl model driven by the measurement
    dxm = x_meas - s[SERVO_XMEAS_PREV]
    s[SERVO_XMEAS_PREV] = x_meas
    ki = model.ki
    if model.niasa == 1:
        if dxm != 0.0:
            s[SERVO_NIASA_DIR] = 1.0 if dxm > 0.0 else -1.0
            s[SERVO_NIASA_F] = dahl_update(s[SERVO_NIASA_F], dxm, model.ni_ksigma, model.ni_fc, 1.0)
        kf = model.ni_ksigma * (1.0 - s[SERVO_NIASA_F] / model.ni_fc * s[SERVO_NIASA_DIR])
        ki = (kf + model.kp) / model.ni_tau

    # feedforward friction driven by the reference
    dxr = x_ref - s[SERVO_XREF_PREV]
    s[SERVO_XREF_PREV] = x_ref
    u_ff = 0.0
    if model.ff_kind == FF_DAHL:
        s[SERVO_FF] = dahl_update(s[SERVO_FF], dxr, model.ff_k[0], model.ff_fc, model.ff_shape)
        u_ff = s[SERVO_FF] + model.ff_viscous * v_ref
    elif model.ff_kind == FF_GMS:
        u_ff = gms_update(s[SERVO_FF:SERVO_FF + model.n_ff], dxr, model.ff_k, model.ff_alpha,
                          model.ff_fc, model.n_ff) + model.ff_viscous * v_ref

    # disturbance observer
    d_hat = 0.0
    if model.dob == 1:
        d_hat = (ss_step(model.qg_A, model.qg_B, model.qg_C, model.qg_D,
                         s[SERVO_DOB_X:SERVO_DOB_X + 2], x_meas)
                 - ss_step(model.q_A, model.q_B, model.q_C, model.q_D,
                           s[SERVO_DOB_U:SERVO_DOB_U + 2], s[SERVO_U_PREV]))

    # integral with clamping anti-windup
    rest = model.kp * e + u_d + u_ff - d_hat
    integ = s[SERVO_INT] + ki * model.dt * e
    u = rest + integ
    if (u > model.limit or u < -model.limit) and e * u > 0.0:
        integ = s[SERVO_INT]
        u = rest + integ
    s[SERVO_INT] = integ
    if u > model.limit:
        u = model.limit
    elif u < -model.limit:
        u = -model.limit
    s[SERVO_U_PREV] = u
    return u
