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
  any ``wd``) or, with ``pid.derivative_discretization: matched``, its pole matched
  (``exp(-wd dt)``, :func:`derivative_filter`); without ``derivative_cutoff`` the plain
  difference ``kd (e_k - e_{k-1})/dt``.
* DOB filters ``Q G_n^-1`` and ``Q`` (Eq. C.1, C.2): Tustin. ``Q`` is fed the command
  *applied at the previous sample*: ``x_meas[k]`` only reflects commands up to ``k-1``
  (zero-order hold), so this aligns both paths and avoids an algebraic loop.
* Feedforward (Fig. 4.15): the rate-independent law (Dahl, GMS: ``FEEDFORWARD`` in
  :mod:`stage_sim.friction`) of ``Feedforward.friction`` (stiffnesses
  scaled by ``1 + stiffness_error``) is driven by the increments of ``x_ref``; its force
  ``F`` plus ``viscous * v_ref`` is *added* to the command (the stage feels ``-F``).
* NIASA (Eq. A.1): ``K_I = (k_sigma (1 - F_hat/F_c sgn(xdot)) + kp)/tau_d`` replaces
  ``ki``; ``F_hat`` is a nominal Dahl model (shape 1) driven by ``x_meas`` and
  ``sgn(xdot)`` is the sign of the last nonzero measured increment.
* The first call latches the reference and measurement (bumpless start): the models
  see increments only, and the derivative and DOB filters start at rest, so a trial may
  start anywhere in the travel.

Batch layout: :func:`servo_step` advances a whole batch of trials at once; the state is
``(n_state, n_batch)`` with the trial axis last, so each state variable is a contiguous row
and the loops over the batch vectorize (a single trial is ``n_batch = 1``).

State rows (``SERVO_*`` index constants); ``n_state = 12 + n_ff``: started flag,
integral [N], derivative filter, DOB ``Q G_n^-1`` (2), DOB ``Q`` (2), previous command [N],
previous ``x_ref`` [m], previous ``x_meas`` [m], NIASA direction, NIASA ``F_hat`` [N],
feedforward friction (1 for Dahl, ``len(k)`` for GMS, 0 without feedforward).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from stage_control.filters import dc_state, discretize, realize, ss_coefficients
from stage_sim import friction
from stage_sim.config import Controller, Stage
from stage_sim.friction import dahl_update

__all__ = ["ServoModel", "build_servo", "check_reference", "derivative_filter", "init_servo_state", "servo_step"]

SERVO_STARTED, SERVO_INT, SERVO_DER = 0, 1, 2
SERVO_DOB_X, SERVO_DOB_U = 3, 5          # two slots each
SERVO_U_PREV, SERVO_XREF_PREV, SERVO_XMEAS_PREV = 7, 8, 9
SERVO_NIASA_DIR, SERVO_NIASA_F = 10, 11
SERVO_FF = 12

FF_NONE = 0
"""``ServoModel.ff_kind`` without feedforward; else the law's id (:func:`stage_sim.friction.kind`)."""


class ServoModel(NamedTuple):
    """Compiled-loop parameters of the servo (build with :func:`build_servo`)."""
    dt: float                 # sample time [s]
    kp: float                 # [N/m]
    ki: float                 # [N/(m s)] (unused with NIASA)
    limit: float              # command saturation [N]
    # derivative filter, e -> N (first order, ss_coefficients "d")
    d_a: float
    d_b: float
    d_c: float
    d_d: float
    d_x0: float               # its state per unit constant error
    dob: int                  # 1 = DOB on
    # DOB Q G_n^-1, m -> N (second order, ss_coefficients "qg")
    qg_a00: float
    qg_a01: float
    qg_a10: float
    qg_a11: float
    qg_b0: float
    qg_b1: float
    qg_c0: float
    qg_c1: float
    qg_d: float
    qg_x0: float              # its state per unit constant position (2)
    qg_x1: float
    # DOB Q, N -> N (second order, ss_coefficients "q")
    q_a00: float
    q_a01: float
    q_a10: float
    q_a11: float
    q_b0: float
    q_b1: float
    q_c0: float
    q_c1: float
    q_d: float
    ff_kind: int              # FF_NONE or the feedforward law's id (stage_sim.friction.kind)
    ff_par: np.ndarray        # the law's parameter row (law.params), stiffness error applied
    ff_viscous: float         # [N s/m]
    n_ff: int                 # feedforward state slots
    niasa: int                # 1 = NIASA integral gain
    ni_tau: float             # tau_d [s]
    ni_ksigma: float          # nominal k_sigma [N/m]
    ni_fc: float              # nominal F_c [N]
    n_state: int


def derivative_filter(kd: float, cutoff: float | None, dt: float, method: str = "backward_euler"):
    """Discrete realization ``(A, B, C, D)`` of the PID's filtered derivative ``kd s/(s/wd + 1)``.

    Every form is the recurrence ``D_k = a D_{k-1} + kd (1 - a)/dt (e_k - e_{k-1})``
    (:class:`stage_sim.config.Pid`), with ``wd = 2 pi cutoff`` and the pole

    * ``a = 1/(1 + wd dt)`` for ``method="backward_euler"`` (``s = (1 - z^-1)/dt``),
    * ``a = exp(-wd dt)`` for ``method="matched"`` (pole matched, zero at ``z = 1``),
    * ``a = 0`` without a ``cutoff`` (the plain difference ``kd (e_k - e_{k-1})/dt``).

    Parameters
    ----------
    kd : float
        Derivative gain [N·s/m].
    cutoff : float or None
        Filter corner [Hz].
    dt : float
        Control period [s].
    method : {"backward_euler", "matched"}
        ``Pid.derivative_discretization``.

    Examples
    --------
    The matched form follows the recurrence with ``a = exp(-wd dt)``:

    >>> import math
    >>> A, B, C, D = derivative_filter(2.0, 1000.0, 1e-4, "matched")
    >>> a = math.exp(-2 * math.pi * 1000.0 * 1e-4)
    >>> x, d_rec, e_prev, out = 0.0, 0.0, 0.0, []
    >>> for e in (1.0, 1.0, 0.5, 0.0):
    ...     y = D[0, 0] * e + C[0, 0] * x
    ...     x = A[0, 0] * x + B[0, 0] * e
    ...     d_rec = a * d_rec + 2.0 * (1 - a) / 1e-4 * (e - e_prev)
    ...     e_prev = e
    ...     out.append(bool(abs(y - d_rec) < 1e-9 * abs(d_rec) + 1e-12))
    >>> out
    [True, True, True, True]
    >>> float(A[0, 0]) == a, round(float(derivative_filter(2.0, 1000.0, 1e-4)[0][0, 0]), 6)  # backward Euler pole
    (True, 0.61413)
    """
    if kd == 0.0:
        return tuple(np.zeros((1, 1)) for _ in range(4))
    if cutoff is None:      # kd (1 - z^-1)/dt
        return realize([kd / dt, -kd / dt], [1.0, 0.0])
    wd = 2.0 * np.pi * cutoff
    if method == "matched":
        a = math.exp(-wd * dt)
        g = kd * (1.0 - a) / dt
        return realize([g, -g], [1.0, -a])
    if method != "backward_euler":
        raise ValueError(f"derivative discretization must be 'backward_euler' or 'matched', got {method!r}")
    return discretize([kd * wd, 0.0], [1.0, wd], dt, "backward")


def build_servo(controller: Controller, stage: Stage) -> ServoModel:
    """Build the servo model from the controller config and the stage's drive limit.

    Parameters
    ----------
    controller : Controller
        PID gains, optional DOB, feedforward and NIASA, control ``rate`` [Hz].
    stage : Stage
        Its ``drive.peak_force`` [N] bounds the command saturation: the limit is
        ``min(pid.output_limit, drive.peak_force)`` (the peak force alone when
        ``output_limit`` is not set), so the servo never asks for more than the drive gives.

    Returns
    -------
    ServoModel
    """
    dt = 1.0 / controller.rate
    pid = controller.pid
    d_A, d_B, d_C, d_D = derivative_filter(pid.kd, pid.derivative_cutoff, dt, pid.derivative_discretization)

    dob = controller.dob
    if dob is not None:
        wq = 2.0 * np.pi * dob.q_cutoff
        qden = [1.0, 2.0 * wq, wq * wq]
        qg = discretize(np.array([1.0, dob.pole, 0.0]) * wq * wq / dob.gain, qden, dt, "tustin")
        q = discretize([wq * wq], qden, dt, "tustin")
    else:
        qg = q = tuple(np.zeros(s) for s in ((2, 2), (2, 1), (1, 2), (1, 1)))

    ff = controller.feedforward
    if ff is None:
        kind, ff_par, ff_visc, n_ff = FF_NONE, np.zeros(1), 0.0, 0
    else:
        law = friction.law(ff.friction)
        if not law.FEEDFORWARD:
            ok = ", ".join(repr(m.NAME) for m in friction.LAWS if m.FEEDFORWARD)
            raise ValueError(f"feedforward friction must be one of {ok}, got {ff.friction.model!r}")
        fr = law.with_stiffness(ff.friction, 1.0 + ff.stiffness_error)
        kind, ff_par, ff_visc, n_ff = friction.kind(fr), law.params(fr), fr.viscous, law.n_state(fr)

    ni = controller.niasa
    qg_x = dc_state(qg[0], qg[1])
    peak = stage.drive.peak_force
    limit = peak if pid.output_limit is None else min(pid.output_limit, peak)
    return ServoModel(
        dt=dt, kp=float(pid.kp), ki=float(pid.ki), limit=float(limit),
        **ss_coefficients("d", d_A, d_B, d_C, d_D), d_x0=float(dc_state(d_A, d_B)[0]),
        dob=int(dob is not None),
        **ss_coefficients("qg", *qg), qg_x0=float(qg_x[0]), qg_x1=float(qg_x[1]),
        **ss_coefficients("q", *q),
        ff_kind=kind, ff_par=np.ascontiguousarray(ff_par, float), ff_viscous=float(ff_visc), n_ff=n_ff,
        niasa=int(ni is not None),
        ni_tau=float(ni.tau_d) if ni else 1.0, ni_ksigma=float(ni.k_sigma) if ni else 0.0,
        ni_fc=float(ni.f_c) if ni else 1.0,
        n_state=SERVO_FF + n_ff)


def check_reference(x_ref, travel) -> str | None:
    """Why a reference is refused (a position outside the stage's travel), or None.

    Parameters
    ----------
    x_ref : array_like
        Reference positions [m] (rad on a rotary stage).
    travel : stage_sim.config.Travel
        The stage's travel ``min``/``max`` [m].

    Examples
    --------
    >>> from stage_sim.config import Travel
    >>> check_reference([0.0, 0.01], Travel(min=-0.02, max=0.02)) is None
    True
    >>> check_reference([0.0, 0.03], Travel(min=-0.02, max=0.02))
    'reference x_ref[1] = 0.03 m is outside the travel [-0.02, 0.02] m'
    """
    x = np.asarray(x_ref, float)
    bad = np.flatnonzero(~((x >= travel.min) & (x <= travel.max)))     # NaN is outside too
    if bad.size == 0:
        return None
    i = int(bad[0])
    return f"reference x_ref[{i}] = {x[i]:.6g} m is outside the travel [{travel.min:g}, {travel.max:g}] m"


def init_servo_state(model: ServoModel, n_trials: int) -> np.ndarray:
    """Relaxed servo state of a batch, shape ``(model.n_state, n_trials)`` (all zeros)."""
    return np.zeros((model.n_state, int(n_trials)))


@njit(cache=True, error_model="numpy", inline="always")
def servo_step(model, state, x_ref, v_ref, x_meas, u_out):
    """One control sample of the servo for every trial of a batch.

    Parameters
    ----------
    model : ServoModel
    state : ndarray, shape (n_state, n_batch)
        Servo state, trial axis last (see :func:`init_servo_state`); updated in place.
    x_ref, v_ref : ndarray, shape (n_batch,)
        Reference position [m] and velocity [m/s].
    x_meas : ndarray, shape (n_batch,)
        Measured position [m].
    u_out : ndarray, shape (n_batch,)
        Written: saturated force command [N]. Must not alias the inputs (it is used as
        scratch for the feedforward force before the final pass).

    Notes
    -----
    Every loop runs over the batch, innermost, over contiguous rows of ``state``; nothing
    is allocated. The friction models (feedforward, NIASA: ``exp`` and branches) run in
    their own loops first; the main loop (start latch, PID, DOB, anti-windup, saturation)
    is compiled in four copies, one per DOB/NIASA configuration, each branch-free
    (selects only) so that LLVM vectorizes it. The floating-point operations and their
    order are those of the per-trial formulation: results are bit-identical to stepping
    each trial alone.
    """
    s = state
    nb = s.shape[1]
    ff_kind = model.ff_kind

    # ---- feedforward friction driven by the reference, force -> u_out (scratch) --------
    # A trial's first call latches the reference (dx = 0), as the main loop does below.
    if ff_kind != FF_NONE:
        p, visc = model.ff_par, model.ff_viscous
        ff = s[SERVO_FF:SERVO_FF + model.n_ff]
        for b in range(nb):
            xr = x_ref[b]
            prev = xr if s[SERVO_STARTED, b] == 0.0 else s[SERVO_XREF_PREV, b]
            friction.update(ff_kind, p, ff, b, xr - prev, model.dt)
            u_out[b] = friction.level(ff_kind, p, ff, b, 0.0) + visc * v_ref[b]

    # ---- NIASA nominal Dahl model driven by the measurement ----------------------------
    if model.niasa == 1:
        n_ks, n_fc = model.ni_ksigma, model.ni_fc
        for b in range(nb):
            xm = x_meas[b]
            prev = xm if s[SERVO_STARTED, b] == 0.0 else s[SERVO_XMEAS_PREV, b]
            dxm = xm - prev
            if dxm != 0.0:
                s[SERVO_NIASA_DIR, b] = 1.0 if dxm > 0.0 else -1.0
                s[SERVO_NIASA_F, b] = dahl_update(s[SERVO_NIASA_F, b], dxm, n_ks, n_fc, 1.0)

    # ---- main loop, specialized on the DOB and NIASA switches ----------------------------
    if model.dob == 1:
        if model.niasa == 1:
            _servo_main(model, s, x_ref, x_meas, u_out, 1, 1)
        else:
            _servo_main(model, s, x_ref, x_meas, u_out, 1, 0)
    elif model.niasa == 1:
        _servo_main(model, s, x_ref, x_meas, u_out, 0, 1)
    else:
        _servo_main(model, s, x_ref, x_meas, u_out, 0, 0)


@njit(inline="always", error_model="numpy")
def _servo_main(model, s, x_ref, x_meas, u_out, dob, niasa):
    """Start latch, PID, DOB, integral with clamping anti-windup, saturation; batch loop.

    ``dob`` and ``niasa`` are literal constants at every call site: inlined, they fold,
    and each of the four copies of the loop is straight-line (selects only) and vectorizes.
    ``u_out`` holds the feedforward force on entry when ``model.ff_kind != FF_NONE``.
    """
    nb = s.shape[1]
    m = model
    d_a, d_b, d_c, d_d, d_x0 = m.d_a, m.d_b, m.d_c, m.d_d, m.d_x0
    g00, g01, g10, g11, gb0, gb1 = m.qg_a00, m.qg_a01, m.qg_a10, m.qg_a11, m.qg_b0, m.qg_b1
    gc0, gc1, gd, gx0, gx1 = m.qg_c0, m.qg_c1, m.qg_d, m.qg_x0, m.qg_x1
    q00, q01, q10, q11, qb0, qb1 = m.q_a00, m.q_a01, m.q_a10, m.q_a11, m.q_b0, m.q_b1
    qc0, qc1, qd = m.q_c0, m.q_c1, m.q_d
    kp, dt, lim = model.kp, model.dt, model.limit
    has_ff = model.ff_kind != FF_NONE
    ki0, n_tau, n_ks, n_fc = model.ki, model.ni_tau, model.ni_ksigma, model.ni_fc
    for b in range(nb):
        xr = x_ref[b]
        xm = x_meas[b]
        e = xr - xm
        # bumpless start: the first call sets the filters at rest on this sample
        first = s[SERVO_STARTED, b] == 0.0
        s[SERVO_STARTED, b] = 1.0
        xd = s[SERVO_DER, b]
        xd = d_x0 * e if first else xd
        # derivative (first order)
        u_d = d_d * e + d_c * xd
        s[SERVO_DER, b] = d_a * xd + d_b * e
        u_ff = u_out[b]       # loaded unconditionally: a conditional load blocks vectorization
        u_ff = u_ff if has_ff else 0.0
        rest = kp * e + u_d + u_ff
        # disturbance observer: Q G_n^-1 [x_meas] - Q [u_{k-1}]
        if dob == 1:
            x0 = s[SERVO_DOB_X, b]
            x1 = s[SERVO_DOB_X + 1, b]
            x0 = gx0 * xm if first else x0
            x1 = gx1 * xm if first else x1
            y_qg = gd * xm + gc0 * x0 + gc1 * x1
            s[SERVO_DOB_X, b] = g00 * x0 + g01 * x1 + gb0 * xm
            s[SERVO_DOB_X + 1, b] = g10 * x0 + g11 * x1 + gb1 * xm
            up = s[SERVO_U_PREV, b]
            z0 = s[SERVO_DOB_U, b]
            z1 = s[SERVO_DOB_U + 1, b]
            y_q = qd * up + qc0 * z0 + qc1 * z1
            s[SERVO_DOB_U, b] = q00 * z0 + q01 * z1 + qb0 * up
            s[SERVO_DOB_U + 1, b] = q10 * z0 + q11 * z1 + qb1 * up
            rest = rest - (y_qg - y_q)
        # integral gain: ki, or NIASA (Eq. A.1) from the nominal friction state
        ki = ki0
        if niasa == 1:
            kf = n_ks * (1.0 - s[SERVO_NIASA_F, b] / n_fc * s[SERVO_NIASA_DIR, b])
            ki = (kf + kp) / n_tau
        i_old = s[SERVO_INT, b]
        integ = i_old + ki * dt * e
        u = rest + integ
        wind = ((u > lim) | (u < -lim)) & (e * u > 0.0)
        integ = i_old if wind else integ
        u = rest + integ
        s[SERVO_INT, b] = integ
        u = lim if u > lim else (-lim if u < -lim else u)
        s[SERVO_U_PREV, b] = u
        s[SERVO_XREF_PREV, b] = xr
        s[SERVO_XMEAS_PREV, b] = xm
        u_out[b] = u
