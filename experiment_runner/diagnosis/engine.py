"""Compiled kernels of the diagnosis: force observer, open-loop windows, closed loop.

All three drive the project's own compiled plant step (:func:`stage_sim.plant.plant_step`)
with a *mechanical* copy of the plant model (no drive delay, force-constant error, noise or
limits: see :func:`mechanical`), and apply the drive themselves (:func:`_drive`), so that

* an extra force can act on the table without passing through the drive (the plant step has
  no such input: ``u_cmd`` goes through delay, force constant and noise);
* additive force models that the preset cannot express (position-periodic ripple,
  position-dependent friction, offset, a force at a fixed frequency, sparse-regression
  terms) act on the table, evaluated on the simulated state (:func:`_additive`).

Kernels
-------
:func:`observe`
    The *force observer*: the nominal plant, driven by the recorded command, is made to
    follow the (zero-phase smoothed) measured position by a high-bandwidth tracking loop
    (PID, triple pole at ``omega``); the tracking force ``d[k]`` is the force the nominal
    plant is missing at sample ``k`` (below the observer bandwidth; ``d = 0`` when the
    model is right, up to noise). Its state follows the measurement, so every friction and
    joint state is "re-initialised from the measurement" at every sample.
:func:`open_loop`
    The recorded command through the plant in open loop over short windows, each started
    from the observer's state at the window start (windows are batch columns).
:func:`closed_loop`
    The closed loop (servo + drive + plant + additive forces) on a batch of references;
    identical to :func:`experiment_runner.batch.simulate` when there are no additive forces
    (same compiled steps, same counter-based noise), plus additive forces when there are.

Trial axis last everywhere (the plant's batch-inner layout). SI units.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from stage_control.servo import servo_step
from stage_sim.plant import (COULOMB, DAHL, GMS, LUGRE, N_PSTATE, OK, PlantModel, gauss,
                             plant_step, quantize)

# additive force kinds: f_table = sum_j coef_j * phi_j(x, v, t, friction state)
ADD_OFFSET, ADD_SIGN, ADD_VEL, ADD_SIN_X, ADD_FRIC_POS, ADD_SIN_T, ADD_POLY_X, ADD_VABSV, ADD_ABS_FRIC, ADD_ABS_V = range(10)
ADD_KINDS = {"offset": ADD_OFFSET, "sign_v": ADD_SIGN, "velocity": ADD_VEL, "sin_x": ADD_SIN_X,
             "friction_x": ADD_FRIC_POS, "sin_t": ADD_SIN_T, "poly_x": ADD_POLY_X, "v_abs_v": ADD_VABSV,
             "abs_friction": ADD_ABS_FRIC, "abs_v": ADD_ABS_V}
N_ADD_PAR = 4


def mechanical(pm: PlantModel, keep_noise: bool = False, keep_quantization: bool = True) -> PlantModel:
    """The plant model with the drive stripped (the kernels apply the drive themselves).

    ``keep_noise`` keeps the random bearing friction (``fr_noise``); the drive noise is
    always applied by the kernels. Peak/continuous limits are applied by :func:`_drive`.
    """
    return pm._replace(kf_ratio=1.0, peak=1e300, cont=1e300, th_alpha=0.0, noise_std=0.0, delay=0,
                       fr_noise=pm.fr_noise if keep_noise else np.zeros_like(pm.fr_noise),
                       q_table=pm.q_table if keep_quantization else 0.0)


@njit(cache=True)
def _friction_norm(pm, z, fr, b, fc_tot):
    """Normalised friction force on the table DOF (-1 ... 1): pre-motion state aware."""
    n = pm.n
    tot = 0.0
    for e in range(pm.fr_kind.shape[0]):
        if pm.fr_dof[e] != 0:
            continue
        kind = pm.fr_kind[e]
        if kind == DAHL:
            tot += fr[e, 0, b]
        elif kind == GMS:
            for i in range(pm.fr_n[e]):
                tot += fr[e, i, b]
        elif kind == LUGRE:
            tot += pm.fr_par[e, 0] * fr[e, 0, b]
        elif kind == COULOMB:
            v = z[n, b]
            tot += pm.fr_par[e, 0] * (1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0))
    if fc_tot > 0.0:
        return tot / fc_tot
    v = z[n, b]
    return math.tanh(v / 1e-6)


@njit(cache=True)
def _additive(pm, z, fr, b, t, kinds, par, coef, fc_tot):
    """Sum of the additive table forces [N] for trial ``b`` at time ``t``."""
    if kinds.shape[0] == 0:
        return 0.0
    n = pm.n
    x = z[0, b]
    v = z[n, b]
    out = 0.0
    phi_f = 0.0
    have_f = False
    for j in range(kinds.shape[0]):
        k = kinds[j]
        c = coef[j]
        if k == ADD_OFFSET:
            out += c
        elif k == ADD_SIGN:
            out += c * math.tanh(v / par[j, 0])
        elif k == ADD_VEL:
            out += c * v
        elif k == ADD_SIN_X:
            out += c * math.sin(2.0 * math.pi * x / par[j, 0] + par[j, 1])
        elif k == ADD_FRIC_POS:
            if not have_f:
                phi_f = _friction_norm(pm, z, fr, b, fc_tot)
                have_f = True
            xi = (x - par[j, 0]) / par[j, 1]
            out += c * phi_f * xi ** par[j, 2]
        elif k == ADD_SIN_T:
            out += c * math.sin(2.0 * math.pi * par[j, 0] * t + par[j, 1])
        elif k == ADD_POLY_X:
            xi = (x - par[j, 0]) / par[j, 1]
            out += c * xi ** par[j, 2]
        elif k == ADD_VABSV:
            out += c * v * abs(v)
        elif k == ADD_ABS_FRIC:
            if not have_f:
                phi_f = _friction_norm(pm, z, fr, b, fc_tot)
                have_f = True
            out += c * abs(phi_f)
        elif k == ADD_ABS_V:
            out += c * abs(v)
    return out


@njit(cache=True, inline="always")
def _drive(u_hist, k, b, delay, kf, peak, cont, th_alpha, th):
    """Drive: delay, peak and thermal (I²t) limits, force-constant ratio (as plant_step)."""
    u_in = u_hist[k - delay, b] if k >= delay else 0.0
    u = min(max(u_in, -peak), peak)
    if th[b] > cont * cont:
        u = min(max(u, -cont), cont)
    th[b] += th_alpha * (u * u - th[b])
    return kf * u


@njit(cache=True, nogil=True)
def observe(pm, kf, delay, peak, cont, th_alpha, kinds, par, coef, fc_tot,
            u, ys, vs, t0, z, fr, ps, dbuf, f, zn, force, omega, m_eff, snap_every,
            out_d, out_x, out_v, out_phi, snap_z, snap_fr, snap_th):
    """Force observer over a batch of trials (see module docstring).

    ``u, ys, vs``: (T, B) recorded command [N], smoothed measured position [m] and
    velocity [m/s]. ``z, fr, ps, dbuf, f, zn, force``: plant state (init at rest at ``ys[0]``).
    Writes ``out_d`` (force residual [N]), ``out_x``, ``out_v`` (observer position and
    velocity), ``out_phi`` (normalised friction state), and every ``snap_every`` samples
    the plant and thermal state into ``snap_*`` (for :func:`open_loop`). Returns the
    number of samples at which the plant reported a non-OK status.
    """
    T, B = u.shape
    n = pm.n
    dt = pm.dt
    kp = 3.0 * m_eff * omega * omega
    kd = 3.0 * m_eff * omega
    ki = m_eff * omega * omega * omega
    th = np.zeros(B)
    integ = np.zeros(B)
    uin = np.zeros(B)
    zero = np.zeros(B)
    one = np.ones(B)
    seeds = np.zeros(B, np.int64)
    meas = np.zeros((2, B))
    status = np.zeros(B, np.int64)
    bad = 0
    for k in range(T):
        t = t0 + k * dt
        if snap_every > 0 and k % snap_every == 0:
            s = k // snap_every
            for b in range(B):
                for r in range(2 * n):
                    snap_z[s, r, b] = z[r, b]
                for e in range(fr.shape[0]):
                    for i in range(fr.shape[1]):
                        snap_fr[s, e, i, b] = fr[e, i, b]
                snap_th[s, b] = th[b]
        for b in range(B):
            e = ys[k, b] - z[0, b]
            ev = vs[k, b] - z[n, b]
            integ[b] += ki * dt * e
            d = kp * e + kd * ev + integ[b]
            fa = _additive(pm, z, fr, b, t, kinds, par, coef, fc_tot)
            out_d[k, b] = d
            out_x[k, b] = z[0, b]
            out_v[k, b] = z[n, b]
            out_phi[k, b] = _friction_norm(pm, z, fr, b, fc_tot)
            uin[b] = _drive(u, k, b, delay, kf, peak, cont, th_alpha, th) + fa + d
        plant_step(pm, z, fr, ps, dbuf, f, zn, force, uin, zero, zero, one, k, seeds, meas, status)
        for b in range(B):
            if status[b] == 1:
                bad += 1
                status[b] = OK
    return bad


@njit(cache=True, nogil=True)
def open_loop(pm, kf, delay, peak, cont, th_alpha, kinds, par, coef, fc_tot,
              u, trial, start, length, t0, z, fr, ps, dbuf, f, zn, force, th, out_x):
    """Open-loop windows: column ``w`` starts at sample ``start[w]`` of trial ``trial[w]``
    from the state in ``z, fr, th`` (column ``w``) and is driven by the recorded command
    ``u`` (T, B) for ``length`` samples; writes the table position into ``out_x`` (length, W)."""
    W = trial.shape[0]
    uw = np.zeros((length + delay + 1, W))
    T = u.shape[0]
    for w in range(W):
        for j in range(length + delay + 1):
            kk = start[w] - delay + j
            if 0 <= kk < T:
                uw[j, w] = u[kk, trial[w]]
    uin = np.zeros(W)
    zero = np.zeros(W)
    one = np.ones(W)
    seeds = np.zeros(W, np.int64)
    meas = np.zeros((2, W))
    status = np.zeros(W, np.int64)
    for j in range(length):
        for w in range(W):
            out_x[j, w] = z[0, w]
            t = t0[w] + (start[w] + j) * pm.dt
            fa = _additive(pm, z, fr, w, t, kinds, par, coef, fc_tot)
            uin[w] = _drive(uw, j + delay, w, delay, kf, peak, cont, th_alpha, th) + fa
        plant_step(pm, z, fr, ps, dbuf, f, zn, force, uin, zero, zero, one, j, seeds, meas, status)


@njit(cache=True, nogil=True)
def closed_loop(pm, kf, delay, peak, cont, th_alpha, noise_std, noise_a, noise_gain,
                kinds, par, coef, fc_tot, sm, ss, x_ref, v_ref, seeds, t0,
                z, fr, ps, dbuf, f, zn, force, out_y, out_u, out_x):
    """Closed loop of the servo on the plant with drive noise and additive forces.

    ``x_ref, v_ref``: (T, B). Writes measured position, command and true table position
    (T, B). Returns the first sample at which a trial stopped (-1 = none).
    """
    T, B = x_ref.shape
    th = np.zeros(B)
    nz = np.zeros(B)
    uin = np.zeros(B)
    u = np.zeros(B)
    y = np.zeros(B)
    xr = np.zeros(B)
    vr = np.zeros(B)
    zero = np.zeros(B)
    one = np.ones(B)
    meas = np.zeros((2, B))
    status = np.zeros(B, np.int64)
    uh = np.zeros((T, B))
    for b in range(B):
        meas[0, b] = quantize(z[0, b], pm.q_table)
    fail = -1
    for k in range(T):
        for b in range(B):
            xr[b] = x_ref[k, b]
            vr[b] = v_ref[k, b]
            y[b] = meas[0, b]
        servo_step(sm, ss, xr, vr, y, u)
        for b in range(B):
            uh[k, b] = u[b]
            out_y[k, b] = y[b]
            out_u[k, b] = u[b]
            out_x[k, b] = z[0, b]
            t = t0 + k * pm.dt
            fa = _additive(pm, z, fr, b, t, kinds, par, coef, fc_tot)
            force_b = _drive(uh, k, b, delay, kf, peak, cont, th_alpha, th)
            if noise_std > 0.0:
                w = gauss(seeds[b], k, 0)
                if noise_a < 1.0:
                    nz[b] += noise_a * (w * noise_gain - nz[b])
                    w = nz[b]
                force_b += noise_std * w
            uin[b] = force_b + fa
        plant_step(pm, z, fr, ps, dbuf, f, zn, force, uin, zero, zero, one, k, seeds, meas, status)
        for b in range(B):
            if status[b] != OK and fail < 0:
                fail = k
    return fail


def new_state(pm: PlantModel, x0) -> tuple:
    """Plant state arrays (z, fr, ps, dbuf, f, zn, force) at rest at ``x0`` (B,)."""
    from stage_sim.plant import init_plant_state
    x0 = np.atleast_1d(np.asarray(x0, float))
    return tuple(init_plant_state(pm, len(x0), x0))


__all__ = ["mechanical", "observe", "open_loop", "closed_loop", "new_state", "ADD_KINDS", "N_ADD_PAR",
           "N_PSTATE"]
