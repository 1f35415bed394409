"""Compiled kernels of the diagnosis: force observer and open-loop windows.

Both drive the project's own compiled plant step (:func:`stage_sim.plant.plant_step_ext`,
the step the batch engine and the ROS plant node use) with the model's full plant -- drive
delay, limits and force constant included -- minus its random parts (:func:`observer_model`).
Every effect a hypothesis adds is a plant feature (preset field), so nothing is simulated here
that the plant does not simulate itself; closed-loop runs are :func:`experiment_runner.batch.simulate`.

Kernels
-------
:func:`observe`
    The *force observer*: the model plant, driven by the recorded command, is made to follow
    the (zero-phase smoothed) measured position by a high-bandwidth tracking force applied
    through the plant's external-force input (PID, triple pole at ``omega``); the tracking
    force ``d[k]`` is the force the model is missing at sample ``k`` (below the observer
    bandwidth; ``d = 0`` when the model is right, up to noise). Its state follows the
    measurement, so every friction and joint state is "re-initialised from the measurement"
    at every sample.
:func:`open_loop`
    The recorded command through the plant in open loop over one window per column, every
    column started at the same sample from the observer's state there.

Trial axis last everywhere (the plant's batch-inner layout). SI units.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from stage_sim.plant import COULOMB, DAHL, GMS, LUGRE, OK, PlantModel, init_plant_state, plant_step_ext, quantize

__all__ = ["observer_model", "observe", "open_loop", "new_state", "friction_norm"]


def observer_model(pm: PlantModel) -> PlantModel:
    """The plant model without its random parts (drive noise, random bearing friction) and
    with an ideal sensor: what the observer and the open-loop windows run."""
    return pm._replace(noise_std=0.0, fr_noise=np.zeros_like(pm.fr_noise), q_table=0.0, q_bearing=0.0)


@njit(cache=True)
def friction_norm(pm, z, fr, b, fc_tot):
    """Normalised friction force on the table DOF (-1 ... 1) of trial ``b``: pre-motion state aware."""
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


@njit(cache=True, nogil=True)
def observe(pm, fc_tot, u, fe, d0, d1, mode, ys, vs, z, fr, ps, dbuf, f, zn, force, omega, m_eff, snap_every,
            out_d, out_x, out_v, out_phi, snap_z, snap_fr, snap_ps, snap_dbuf):
    """Force observer over a batch of trials (see module docstring).

    ``u, ys, vs``: (T, B) recorded command [N], smoothed measured position [m] and velocity
    [m/s]; ``fe``: (T, B) known external table force [N] (applied with the tracking force);
    ``d0, d1, mode``: (T, B) the plant's other inputs, piezo dither forces [N] and SAI
    solenoid command (1 compliant, 0 stiff). ``z ... force``: plant state
    (:class:`stage_sim.plant.PlantState` fields, at rest at ``ys[0]``). Writes ``out_d`` (force residual [N]), ``out_x``, ``out_v`` (observer position
    and velocity), ``out_phi`` (normalised table friction state), and every ``snap_every``
    samples the plant state into ``snap_*`` (for :func:`open_loop`). Returns the number of
    samples at which the plant reported a non-OK status.
    """
    T, B = u.shape
    n = pm.n
    dt = pm.dt
    kp = 3.0 * m_eff * omega * omega
    kd = 3.0 * m_eff * omega
    ki = m_eff * omega * omega * omega
    integ = np.zeros(B)
    d = np.zeros(B)
    dk = np.zeros(B)
    uk = np.zeros(B)
    d0k = np.zeros(B)
    d1k = np.zeros(B)
    mk = np.zeros(B)
    seeds = np.zeros(B, np.int64)
    meas = np.zeros((2, B))
    status = np.zeros(B, np.int64)
    bad = 0
    for k in range(T):
        if snap_every > 0 and k % snap_every == 0:
            s = k // snap_every
            snap_z[s] = z
            snap_fr[s] = fr
            snap_ps[s] = ps
            snap_dbuf[s] = dbuf
        for b in range(B):
            e = ys[k, b] - z[0, b]
            ev = vs[k, b] - z[n, b]
            integ[b] += ki * dt * e
            d[b] = kp * e + kd * ev + integ[b]
            dk[b] = d[b] + fe[k, b]
            uk[b] = u[k, b]
            d0k[b] = d0[k, b]
            d1k[b] = d1[k, b]
            mk[b] = mode[k, b]
            out_d[k, b] = d[b]
            out_x[k, b] = z[0, b]
            out_v[k, b] = z[n, b]
            out_phi[k, b] = friction_norm(pm, z, fr, b, fc_tot)
        plant_step_ext(pm, z, fr, ps, dbuf, f, zn, force, uk, dk, d0k, d1k, mk, k, seeds, meas, status)
        for b in range(B):
            if status[b] != OK:
                bad += 1
                status[b] = OK
    return bad


@njit(cache=True, nogil=True)
def open_loop(pm, u, fe, d0, d1, mode, k0, z, fr, ps, dbuf, f, zn, force, out_x, seeds, out_y):
    """Open loop from sample ``k0``: column ``w`` is driven by the command ``u[:, w]``
    (length, W), the known external force ``fe`` and the inputs ``d0, d1, mode`` (length, W)
    (see :func:`observe`) from the state ``z ... force`` (column ``w``); writes the table
    position into ``out_x`` (length, W) and the measurement (the sensor's, quantized) into
    ``out_y``. ``seeds`` (W,): the noise seeds of a plant model with noise (a simulated
    recording); returns the number of columns that diverged or left the travel."""
    length, W = u.shape
    fk = np.zeros(W)
    uk = np.zeros(W)
    d0k = np.zeros(W)
    d1k = np.zeros(W)
    mk = np.zeros(W)
    meas = np.zeros((2, W))
    status = np.zeros(W, np.int64)
    for w in range(W):
        meas[0, w] = quantize(z[0, w], pm.q_table)
    for j in range(length):
        for w in range(W):
            out_x[j, w] = z[0, w]
            out_y[j, w] = meas[0, w]
            uk[w] = u[j, w]
            fk[w] = fe[j, w]
            d0k[w] = d0[j, w]
            d1k[w] = d1[j, w]
            mk[w] = mode[j, w]
        plant_step_ext(pm, z, fr, ps, dbuf, f, zn, force, uk, fk, d0k, d1k, mk, k0 + j, seeds, meas, status)
    bad = 0
    for w in range(W):
        if status[w] != OK:
            bad += 1
    return bad


def new_state(pm: PlantModel, x0, sai_mode: float = 1.0) -> tuple:
    """Plant state arrays (z, fr, ps, dbuf, f, zn, force) at rest at ``x0`` (B,), the isolator
    in ``sai_mode`` (1 compliant, 0 stiff and locked)."""
    x0 = np.atleast_1d(np.asarray(x0, float))
    return tuple(init_plant_state(pm, len(x0), x0, sai_mode=sai_mode))
