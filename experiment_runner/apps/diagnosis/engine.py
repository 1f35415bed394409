"""Compiled kernels of the diagnosis: force observer and open-loop windows.

Both drive the project's own compiled plant step (:func:`stage_sim.plant.plant_step`,
the step the batch engine and the ROS plant node use; :func:`open_loop` is the plant's open-loop
driver :func:`stage_sim.plant.run_open_loop`) with the model's full plant -- drive
delay, limits and force constant included -- minus its random parts (:func:`observer_model`).
Every effect a hypothesis adds is a plant feature (preset field), so nothing is simulated here
that the plant does not simulate itself; closed-loop runs are :func:`experiment_runner.core.batch.simulate`.

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

from stage_sim import friction
from stage_sim.plant import OK, PlantInputs, PlantState, init_plant_state, plant_step, quantize, run_open_loop
from stage_sim.plant_model import PlantModel

__all__ = ["observer_model", "observe", "open_loop", "new_state", "friction_norm"]


def observer_model(pm: PlantModel) -> PlantModel:
    """The plant model without its random parts (drive noise, random bearing friction) and
    with an ideal sensor: what the observer and the open-loop windows run.

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The plant model.

    Returns
    -------
    stage_sim.plant_model.PlantModel
    """
    return pm._replace(noise_std=0.0, fr_noise=np.zeros_like(pm.fr_noise), q_table=0.0, q_bearing=0.0)


@njit(cache=True, inline="always")
def friction_norm(pm, z, fr, b, fc_tot):
    """Normalised friction force on the table DOF (-1 ... 1) of trial ``b``: pre-motion state aware.

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The plant model.
    z : numpy.ndarray
        The plant's continuous states.
    fr : numpy.ndarray
        The friction states.
    b : int
        Trial column.
    fc_tot : float
        Coulomb force of the friction elements on the table [N].

    Returns
    -------
    float
    """
    n = pm.n
    tot = 0.0
    for e in range(pm.fr_kind.shape[0]):
        if pm.fr_dof[e] == 0:
            tot += friction.level(pm.fr_kind[e], pm.fr_par[e], fr[e], b, z[n, b])
    if fc_tot > 0.0:
        return tot / fc_tot
    v = z[n, b]
    return math.tanh(v / 1e-6)


@njit(cache=True, inline="always")
def _copy2(dst, src):
    """``dst[:] = src`` for 2-D arrays, element by element (no temporary: no runtime needed)."""
    for i in range(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


@njit(cache=True, nogil=True)
def observe(pm, fc_tot, inp, ys, vs, st, omega, m_eff, snap_every,
            out_d, out_x, out_v, out_phi, snap_z, snap_fr, snap_ps, snap_dbuf):
    """Force observer over a batch of trials (see module docstring).

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The observer's plant model (:func:`observer_model`).
    fc_tot : float
        Coulomb force of the friction elements on the table [N].
    inp : stage_sim.plant.PlantInputs
        Over the record, (T, B) each: the recorded command [N], piezo dither forces [N] and SAI
        solenoid command (1 compliant, 0 stiff); its ``f_ext`` (T, B) is the known external table
        force [N] (``/stage/external_force``), applied with the tracking force, or empty (0, 0) for none.
    ys, vs : numpy.ndarray
        (T, B) smoothed measured position [m] and velocity [m/s].
    st : stage_sim.plant.PlantState
        Plant state, at rest at ``ys[0]``.
    omega : float
        Observer bandwidth [rad/s].
    m_eff : float
        Table mass at high frequency [kg].
    snap_every : int
        Keep the plant state every this many samples (0: never).
    out_d, out_x, out_v, out_phi : numpy.ndarray
        (T, B) outputs: force residual [N], observer position [m] and velocity [m/s], normalised
        table friction state.
    snap_z, snap_fr, snap_ps, snap_dbuf : numpy.ndarray
        Plant-state snapshots (for :func:`open_loop`).

    Returns
    -------
    int
        Sample-and-trial steps at which the plant reported a non-OK status.
    """
    B = ys.shape[1]
    return _observe(pm, fc_tot, inp, ys, vs, st, omega, m_eff, snap_every, out_d, out_x, out_v, out_phi,
                    snap_z, snap_fr, snap_ps, snap_dbuf, np.zeros((5, B)), np.zeros((2, B), np.int64))


@njit(cache=True, nogil=True, _nrt=False)
def _observe(pm, fc_tot, inp, ys, vs, st, omega, m_eff, snap_every, out_d, out_x, out_v, out_phi,
             snap_z, snap_fr, snap_ps, snap_dbuf, work, iwork):
    """:func:`observe`'s loop, compiled without the runtime (no reference counting in the
    per-sample loop; ``work`` (5, B), ``iwork`` (2, B) zeroed scratch)."""
    T, B = ys.shape
    n = pm.n
    z, fr, ps, dbuf = st.z, st.fr, st.ps, st.dbuf
    dt = pm.dt
    kp = 3.0 * m_eff * omega * omega
    kd = 3.0 * m_eff * omega
    ki = m_eff * omega * omega * omega
    integ, d, dk, meas = work[0], work[1], work[2], work[3:5]
    known = inp.f_ext.shape[0] > 0
    seeds, status = iwork[0], iwork[1]
    bad = 0
    for k in range(T):
        if snap_every > 0 and k % snap_every == 0:
            s = k // snap_every
            _copy2(snap_z[s], z)
            for e in range(fr.shape[0]):
                _copy2(snap_fr[s, e], fr[e])
            _copy2(snap_ps[s], ps)
            _copy2(snap_dbuf[s], dbuf)
        for b in range(B):
            e = ys[k, b] - z[0, b]
            ev = vs[k, b] - z[n, b]
            integ[b] += ki * dt * e
            d[b] = kp * e + kd * ev + integ[b]
            dk[b] = d[b] + inp.f_ext[k, b] if known else d[b]
            out_d[k, b] = d[b]
            out_x[k, b] = z[0, b]
            out_v[k, b] = z[n, b]
            out_phi[k, b] = friction_norm(pm, z, fr, b, fc_tot)
        plant_step(pm, st, PlantInputs(inp.u[k], inp.d0[k], inp.d1[k], inp.mode[k], dk), k, seeds, meas, status)
        for b in range(B):
            if status[b] != OK:
                bad += 1
                status[b] = OK
    return bad


def open_loop(pm, inp, k0, st, out_x, seeds=None, out_y=None) -> int:
    """Open loop from sample ``k0``: column ``w`` is driven by the inputs ``inp`` (a
    :class:`stage_sim.plant.PlantInputs` of (length, W) arrays; ``f_ext`` the known external
    table force (length, W), or empty (0, 0) for none) from the state ``st`` (column ``w``);
    writes the true table position into ``out_x`` (length, W) and, if given, the measurement
    (the sensor's, quantized) into ``out_y``. ``seeds`` (W,): the noise seeds of a plant model
    with noise (a simulated recording; zeros by default). The plant's open-loop driver
    :func:`stage_sim.plant.run_open_loop`.

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The plant model.
    inp : stage_sim.plant.PlantInputs
        (length, W) inputs.
    k0 : int
        First sample.
    st : stage_sim.plant.PlantState
        Start state, one column per window.
    out_x : numpy.ndarray
        (length, W) true table position [m], written.
    seeds : numpy.ndarray, optional
        (W,) noise seeds.
    out_y : numpy.ndarray, optional
        (length, W) measurement [m], written.

    Returns
    -------
    int
        Columns that diverged or left the travel.
    """
    W = out_x.shape[1]
    seeds = np.zeros(W, np.int64) if seeds is None else np.asarray(seeds, np.int64)
    meas = np.zeros((2, W))
    meas[0] = [quantize(x, pm.q_table) for x in st.z[0]]
    status = np.zeros(W, np.int64)
    run_open_loop(pm, st, inp, k0, seeds, meas, status, True, out_x,
                  np.zeros((0, 0)) if out_y is None else out_y)
    return int(np.count_nonzero(status != OK))


def new_state(pm: PlantModel, x0, sai_mode: float = 1.0) -> PlantState:
    """Plant state at rest at ``x0`` (B,), the isolator in ``sai_mode`` (1 compliant, 0 stiff and locked).

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The plant model.
    x0 : numpy.ndarray
        (B,) positions [m].
    sai_mode : float, optional
        1 compliant, 0 stiff and locked.

    Returns
    -------
    stage_sim.plant.PlantState
    """
    x0 = np.atleast_1d(np.asarray(x0, float))
    return init_plant_state(pm, len(x0), x0, sai_mode=sai_mode)
