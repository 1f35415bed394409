"""Batch engine: many closed-loop trials of one preset as a single compiled loop.

Each control sample ``k`` runs, in this order (the ROS graph uses the same order
and the same compiled step functions, so both give identical trajectories):

1. the SAI manager reads the reference (and its look-ahead) -> isolator mode and
   reference correction;
2. the dither generator reads reference and measurement -> piezo forces;
3. the servo reads reference (+ correction) and the measurement ``y[k]`` -> command;
4. the plant applies the command over ``[k, k+1)`` and produces ``y[k+1]``.

Trials are independent (own start position, own noise seed) and run in parallel
over the available cores with ``numba.prange``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from stage_control.dither import build_dither, dither_step, init_dither_state
from stage_control.sai import build_sai, init_sai_state, sai_step
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import Dither, Preset, SaiManager
from stage_sim.plant import (OK, STATUS_TEXT, PlantModel, SimulationError, build_plant,
                             init_plant_state, plant_step)


@dataclass
class Models:
    """Compiled models of one preset: plant, servo, dither generator, SAI manager."""
    plant: PlantModel
    servo: tuple
    dither: tuple
    sai: tuple
    lead: int            # SAI look-ahead [samples]

    @classmethod
    def from_preset(cls, preset: Preset) -> "Models":
        rate = preset.controller.rate
        sim = preset.simulation
        plant = build_plant(preset.stage, rate, sim.max_omega_h, sim.max_substeps)
        dither = preset.dither or Dither(amplitude=0.0, frequency=1.0)
        sai = preset.sai_manager or SaiManager(rule="always_compliant")
        return cls(plant=plant, servo=build_servo(preset.controller, preset.stage),
                   dither=build_dither(dither, rate), sai=build_sai(sai, rate),
                   lead=int(round(sai.release_lead * rate)))


@dataclass
class BatchResult:
    """Recorded signals, each of shape (n_trials, T) unless noted; SI units."""
    t: np.ndarray            # (T,) time of each control sample [s]
    x_ref: np.ndarray        # reference actually used by the servo (incl. SAI correction) [m]
    v_ref: np.ndarray        # reference velocity [m/s]
    y: np.ndarray            # measured table position at sample k [m]
    y_bearing: np.ndarray    # measured bearing position (nan without sensor) [m]
    u: np.ndarray            # servo command [N]
    x_table: np.ndarray      # true table position [m]
    x_bearing: np.ndarray    # true position of the first jointed bearing (= table if none) [m]
    dither: np.ndarray       # (n_trials, T, 2) piezo forces [N]
    mode: np.ndarray         # SAI mode command (1 compliant, 0 stiff)
    status: np.ndarray       # (n_trials,) plant status code (0 = ok)
    fail_step: np.ndarray    # (n_trials,) sample where a trial stopped (-1 = completed)

    def check(self):
        """Raise :class:`SimulationError` naming the first failed trial, if any."""
        bad = np.flatnonzero(self.status != OK)
        if bad.size:
            b = int(bad[0])
            k = int(self.fail_step[b])
            raise SimulationError(
                f"trial {b} stopped at t = {self.t[k]:.6f} s (sample {k}): "
                f"{STATUS_TEXT[int(self.status[b])]}; {bad.size} of {len(self.status)} trials failed")
        return self


@njit(cache=True, parallel=True)
def _run(pm, sm, dm, am, lead, x_ref, v_ref, seeds, correction,
         z, fr, ps, dbuf, f, zn, ss, ds, sa,
         out_xr, out_y, out_yb, out_u, out_xt, out_xb, out_d, out_mode, status, fail):
    n_trials, n_steps = x_ref.shape
    bdof = pm.bear_dof
    for b in prange(n_trials):
        meas = np.empty(2)
        dout = np.zeros(2)
        meas[0] = z[b, 0] if pm.q_table <= 0 else pm.q_table * math.floor(z[b, 0] / pm.q_table + 0.5)
        meas[1] = math.nan
        for k in range(n_steps):
            ka = min(k + lead, n_steps - 1)
            mode, xc = sai_step(am, sa[b], correction, k, v_ref[b, k], v_ref[b, ka])
            xr = x_ref[b, k] + xc
            dither_step(dm, ds[b], k, xr, v_ref[b, k], meas[0], dout)
            u = servo_step(sm, ss[b], xr, v_ref[b, k], meas[0])
            out_xr[b, k] = xr
            out_y[b, k] = meas[0]
            out_yb[b, k] = meas[1]
            out_u[b, k] = u
            out_xt[b, k] = z[b, 0]
            out_xb[b, k] = z[b, bdof]
            out_d[b, k, 0] = dout[0]
            out_d[b, k, 1] = dout[1]
            out_mode[b, k] = mode
            st = plant_step(pm, z[b], fr[b], ps[b], dbuf[b], f[b], zn[b], u, dout[0], dout[1],
                            mode, k, seeds[b], meas)
            if st != 0:
                status[b] = st
                fail[b] = k
                break


def simulate(preset: Preset, x_ref, v_ref, n_trials: int | None = None, x0=None, seeds=None,
             correction=None, models: Models | None = None, check: bool = True) -> BatchResult:
    """Run closed-loop trials of ``preset`` following a reference.

    Parameters
    ----------
    preset : Preset
        Stage, controller and add-ons.
    x_ref, v_ref : array_like, shape (T,) or (n_trials, T)
        Reference position [m] and velocity [m/s] at the control rate; a 1-D
        reference is shared by every trial (offset by the trial's ``x0``).
    n_trials : int, optional
        Number of trials (default: rows of ``x_ref`` or 1).
    x0 : float or array_like, optional
        Start position of each trial [m] (default 0). Added to a shared 1-D reference.
    seeds : array_like of int, optional
        Noise seed per trial (default ``preset.simulation.seed + trial index``).
    correction : array_like, optional
        SAI reference correction after each compliant->stiff switch [m] (Step II).
    models : Models, optional
        Pre-compiled models (saves rebuilding in sweeps).
    check : bool
        Raise :class:`SimulationError` if any trial diverged or left the travel.

    Returns
    -------
    BatchResult
    """
    models = models or Models.from_preset(preset)
    x_ref = np.atleast_2d(np.asarray(x_ref, float))
    v_ref = np.atleast_2d(np.asarray(v_ref, float))
    if n_trials is None:
        n_trials = x_ref.shape[0]
    x0 = np.broadcast_to(np.asarray(0.0 if x0 is None else x0, float), (n_trials,))
    if x_ref.shape[0] == 1:
        x_ref = x_ref + x0[:, None]
        v_ref = np.broadcast_to(v_ref, x_ref.shape)
    if x_ref.shape != (n_trials, x_ref.shape[1]) or v_ref.shape != x_ref.shape:
        raise ValueError(f"reference shape {x_ref.shape} does not match n_trials={n_trials}")
    x_ref = np.ascontiguousarray(x_ref)
    v_ref = np.ascontiguousarray(v_ref)
    seeds = (np.arange(n_trials) + preset.simulation.seed if seeds is None
             else np.asarray(seeds)).astype(np.int64)
    corr = np.zeros(0) if correction is None else np.asarray(correction, float)

    pm = models.plant
    init_mode = 0.0 if (preset.sai_manager and preset.sai_manager.rule in ("point_to_point", "tracking",
                                                                            "always_stiff")) else 1.0
    st = init_plant_state(pm, n_trials, x_ref[:, 0], sai_mode=init_mode)
    ss = init_servo_state(models.servo, n_trials)
    ds = init_dither_state(models.dither, n_trials)
    sa = init_sai_state(models.sai, n_trials)
    T = x_ref.shape[1]
    out = {k: np.zeros((n_trials, T)) for k in ("xr", "y", "yb", "u", "xt", "xb", "mode")}
    out_d = np.zeros((n_trials, T, 2))
    status = np.zeros(n_trials, np.int64)
    fail = -np.ones(n_trials, np.int64)
    _run(pm, models.servo, models.dither, models.sai, models.lead, x_ref, v_ref, seeds, corr,
         st.z, st.fr, st.ps, st.dbuf, st.f, st.zn, ss, ds, sa,
         out["xr"], out["y"], out["yb"], out["u"], out["xt"], out["xb"], out_d, out["mode"],
         status, fail)
    res = BatchResult(t=np.arange(T) / preset.controller.rate, x_ref=out["xr"], v_ref=v_ref,
                      y=out["y"], y_bearing=out["yb"], u=out["u"], x_table=out["xt"],
                      x_bearing=out["xb"], dither=out_d, mode=out["mode"], status=status,
                      fail_step=fail)
    return res.check() if check else res
