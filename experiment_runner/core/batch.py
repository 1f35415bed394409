"""Batch engine: many closed-loop trials of one preset as a single compiled loop.

Each control sample ``k`` runs, in this order (written once, in :func:`run_chunks`; the ROS graph uses the same order
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
import os
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from numba import njit, prange

from stage_control.dither import build_dither, dither_step, init_dither_state
from stage_control.sai import build_sai, init_sai_state, sai_step
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import ConfigError, Dither, Preset, SaiManager
from stage_sim.plant import OK, STATUS_TEXT, PlantInputs, PlantState, SimulationError, chunk_state, init_plant_state, plant_step, quantize, state_chunk
from stage_sim.plant_model import PlantModel, build_plant


class InitialState(NamedTuple):
    """Where every component of a trial starts (arrays over trials, last axis)."""
    plant: PlantState
    meas: np.ndarray     # (2, n) first measurement: table, bearing sensor (nan without one) [m]
    servo: np.ndarray
    dither: np.ndarray
    sai: np.ndarray


@dataclass
class Models:
    """Compiled models of one preset: plant, servo, dither generator, SAI manager.

    The one place a preset becomes models and a trial's initial state, for the batch
    engine and the graph's nodes alike (so both start every trial identically).
    """
    plant: PlantModel
    servo: tuple
    dither: tuple
    sai: tuple
    lead: int            # SAI look-ahead [samples]
    sai_mode: float = 1.0  # isolator mode at the start of a trial (1 compliant, 0 stiff)

    @classmethod
    def from_preset(cls, preset: Preset) -> "Models":
        rate = preset.controller.rate
        sim = preset.simulation
        plant = build_plant(preset.stage, rate, sim.max_omega_h, sim.max_substeps)
        dither = preset.dither or Dither(amplitude=0.0, frequency=1.0)
        sai = preset.sai_manager or SaiManager(rule="always_compliant")
        return cls(plant=plant, servo=build_servo(preset.controller, preset.stage),
                   dither=build_dither(dither, rate), sai=build_sai(sai, rate),
                   lead=int(round(sai.release_lead * rate)),
                   sai_mode=0.0 if sai.rule != "always_compliant" else 1.0)

    def initial_state(self, x0) -> InitialState:
        """Every component at rest, one trial per start position in ``x0`` [m]: relaxed
        plant (isolator in :attr:`sai_mode`), zero controller states."""
        x0 = np.atleast_1d(np.asarray(x0, float))
        n, pm = x0.shape[0], self.plant
        plant = init_plant_state(pm, n, x0, sai_mode=self.sai_mode)
        meas = np.full((2, n), np.nan)
        meas[0] = [quantize(x, pm.q_table) for x in plant.z[0]]
        if pm.bsens_dof >= 0:
            meas[1] = [quantize(x, pm.q_bearing) for x in plant.z[pm.bsens_dof]]
        return InitialState(plant=plant, meas=meas, servo=init_servo_state(self.servo, n),
                            dither=init_dither_state(self.dither, n), sai=init_sai_state(self.sai, n))


@dataclass
class BatchResult:
    """Recorded signals, each of shape (n_trials, T) unless noted; SI units."""
    t: np.ndarray            # (T,) time of each control sample [s]
    x_ref: np.ndarray        # reference actually used by the servo (incl. SAI correction) [m]
    x_correction: np.ndarray  # SAI Step II correction included in x_ref [m]
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
def run_chunks(pm, sm, dm, am, lead, x_ref, v_ref, f_ext, seeds, correction, plant, ss, ds, sa, out, o_dither,
         status, fail):
    """The trials in chunks of ``size = status.shape[1]``, one chunk per task (``prange``).

    Inputs and outputs keep the caller's layout, (trial, sample): chunk ``c`` reads and writes
    rows ``c * size + b`` (inputs: clipped to the last trial, the padding repeats it), so no
    array is transposed on the way in or out. ``plant`` is a chunked
    :class:`~stage_sim.plant.PlantState` and ``ss, ds, sa`` are (chunk, ..., trial) as
    :func:`_run_chunk` steps them; ``out`` (7, padded trials, sample); ``f_ext`` (0, 0): none.
    Each task allocates its chunk's scratch here, so that :func:`_run_chunk` needs no runtime."""
    size = status.shape[1]
    for c in prange(status.shape[0]):
        _run_chunk(pm, sm, dm, am, lead, x_ref, v_ref, f_ext, c * size, seeds, correction, state_chunk(plant, c),
                   ss[c], ds[c], sa[c], out, o_dither, status[c], fail[c], np.zeros((14, size)),
                   np.empty((2, size), np.int64))


@njit(cache=True, error_model="numpy", _nrt=False)
def _run_chunk(pm, sm, dm, am, lead, x_ref, v_ref, f_ext, off, seeds, correction, pc, ssc, dsc, sac,
               out, o_dither, st, fail, work, iwork):
    """Closed loop over time for the chunk of trials ``off .. off + size``: the step order
    SAI -> dither -> servo -> plant, written once. States are (..., trial); inputs (trial,
    sample) and outputs ``out`` (signal, trial, sample) in the caller's layout; ``f_ext`` the
    known external table force (trial, sample), or (0, 0) for none; ``work`` (14, size) and
    ``iwork`` (2, size) the chunk's scratch.

    Compiled without numba's runtime (``_nrt=False``: nothing is allocated here): with it, every
    inlined step function that takes a model tuple (``pm`` holds ~25 arrays) increfs and
    decrefs each of its arrays at every call, ~70 ns per call and an atomic operation on memory
    the threads share; without it one trajectory runs ~1.9x faster, and the threads scale."""
    n_steps = x_ref.shape[1]
    nb = st.shape[0]
    last = x_ref.shape[0] - 1
    rows, seed = iwork[0], iwork[1]
    for b in range(nb):
        rows[b] = min(off + b, last)
        seed[b] = seeds[rows[b]]
    o_xr, o_y, o_yb, o_u, o_xt, o_xb, o_mode = out[0], out[1], out[2], out[3], out[4], out[5], out[6]
    zc = pc.z
    meas, dout = work[0:2], work[2:4]
    y, d0, d1, u, mode, xc, xr, vr, va = work[4], work[5], work[6], work[7], work[8], work[9], work[10], work[11], work[12]
    ext = f_ext.shape[0] > 0
    fe = work[13] if ext else work[13, :0]
    inp = PlantInputs(u, d0, d1, mode, fe)
    for b in range(nb):
        meas[0, b] = quantize(zc[0, b], pm.q_table)
        meas[1, b] = quantize(zc[pm.bsens_dof, b], pm.q_bearing) if pm.bsens_dof >= 0 else math.nan
    for k in range(n_steps):
        ka = min(k + lead, n_steps - 1)
        for b in range(nb):
            vr[b] = v_ref[rows[b], k]
            va[b] = v_ref[rows[b], ka]
        sai_step(am, sac, correction, k, vr, va, mode, xc)
        for b in range(nb):
            xr[b] = x_ref[rows[b], k] + xc[b]
            y[b] = meas[0, b]
        dither_step(dm, dsc, k, xr, vr, y, dout)
        servo_step(sm, ssc, xr, vr, y, u)
        for b in range(nb):
            i = off + b
            d0[b] = dout[0, b]
            d1[b] = dout[1, b]
            o_xr[i, k] = xr[b]
            o_y[i, k] = y[b]
            o_yb[i, k] = meas[1, b]
            o_u[i, k] = u[b]
            o_xt[i, k] = zc[0, b]
            o_xb[i, k] = zc[pm.bear_dof, b]
            o_dither[i, k, 0] = d0[b]
            o_dither[i, k, 1] = d1[b]
            o_mode[i, k] = mode[b]
        if ext:
            for b in range(nb):
                fe[b] = f_ext[rows[b], k]
        plant_step(pm, pc, inp, k, seed, meas, st)
        for b in range(nb):
            if st[b] != OK and fail[b] < 0:
                fail[b] = k


def chunked(a, n_chunks, size):
    """(B, ...) -> (n_chunks, ..., size): pad by repeating the last trial, trial axis last."""
    a = np.asarray(a)
    pad = n_chunks * size - a.shape[0]
    if pad:
        a = np.concatenate([a, np.repeat(a[-1:], pad, axis=0)])
    a = a.reshape((n_chunks, size) + a.shape[1:])
    return np.ascontiguousarray(np.moveaxis(a, 1, -1))


def unchunked(a, n_trials):
    """(n_chunks, ..., size) -> (B, ...) without the padding."""
    a = np.moveaxis(a, -1, 1)
    return a.reshape((-1,) + a.shape[2:])[:n_trials]


BYTES_PER_SAMPLE = 13 * 8
"""Memory a batch run takes per trial and sample [bytes]: its inputs and outputs (seven
recorded signals, two dither forces, the references and their copies), float64."""


def check_memory(n_trials: int, samples: int, rate: float) -> None:
    """Refuse (:class:`ConfigError`, before anything is allocated) a batch run of ``n_trials``
    trials of ``samples`` samples whose arrays (:data:`BYTES_PER_SAMPLE` a sample) would not fit
    in this machine's memory."""
    need = BYTES_PER_SAMPLE * float(n_trials) * float(samples)
    try:
        have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError):
        return
    if need > have:
        raise ConfigError(f"{n_trials} trial(s) of {samples} samples ({samples / rate:g} s at {rate:g} Hz) need about "
                          f"{need / 2**30:.3g} GiB; this machine has {have / 2**30:.3g} GiB of memory (fewer trials or "
                          "a shorter profile)")


def _arg(a, dtype=float) -> np.ndarray:
    """``a`` as the kernel takes it: C-contiguous, aligned, writable, of ``dtype`` (copied only when
    it is not). numba compiles one specialization per argument type, read-only included: a
    reference shared by one trial is a read-only broadcast view, by two a copy, and without this
    the first chunk of one trial and the next of forty each compiled (and cached) ``run_chunks``, about a
    minute each on a fresh machine.

    >>> v = np.broadcast_to(np.zeros(3), (1, 3))
    >>> v.flags.writeable, _arg(v).flags.writeable, _arg(v).flags.c_contiguous
    (False, True, True)
    """
    return np.require(a, dtype, "CAW")


def simulate(preset: Preset, x_ref, v_ref, n_trials: int | None = None, x0=None, seeds=None,
             correction=None, models: Models | None = None, check: bool = True, f_ext=None) -> BatchResult:
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
    f_ext : array_like, shape (T,) or (n_trials, T), optional
        Known external force on the table at each sample [N] (``/stage/external_force``; not
        through the drive), held over the control period; default none.

    Returns
    -------
    BatchResult
    """
    models = models or Models.from_preset(preset)
    x_ref = np.atleast_2d(np.asarray(x_ref, float))
    v_ref = np.atleast_2d(np.asarray(v_ref, float))
    if n_trials is None:
        n_trials = x_ref.shape[0]
    check_memory(n_trials, x_ref.shape[1], preset.controller.rate)
    x0 = np.broadcast_to(np.asarray(0.0 if x0 is None else x0, float), (n_trials,))
    if x_ref.shape[0] == 1:
        x_ref = x_ref + x0[:, None]
        v_ref = np.broadcast_to(v_ref, x_ref.shape)
    if x_ref.shape != (n_trials, x_ref.shape[1]) or v_ref.shape != x_ref.shape:
        raise ValueError(f"reference shape {x_ref.shape} does not match n_trials={n_trials}")
    seeds = _arg(np.arange(n_trials) + preset.simulation.seed if seeds is None else seeds, np.int64)
    corr = _arg(np.zeros(0) if correction is None else correction)
    if f_ext is not None:
        f_ext = np.broadcast_to(np.asarray(f_ext, float), x_ref.shape)

    size = -(-n_trials // max(1, min(numba.get_num_threads(), n_trials)))     # trials per thread
    n_chunks = -(-n_trials // size)           # 40 trials on 16 threads: 14 chunks of 3, not 16 (8 padded trials)
    pm = models.plant
    # padded trials repeat the last one (as _run_chunk reads their inputs)
    init = models.initial_state(x_ref[np.minimum(np.arange(n_chunks * size), n_trials - 1), 0])
    plant = chunk_state(init.plant, n_chunks)
    T = x_ref.shape[1]
    states = [np.ascontiguousarray(np.moveaxis(a.reshape(-1, n_chunks, size), 1, 0))
              for a in (init.servo, init.dither, init.sai)]
    out = np.empty((7, n_chunks * size, T))
    o_dither = np.empty((n_chunks * size, T, 2))
    status = np.zeros((n_chunks, size), np.int64)
    fail = -np.ones((n_chunks, size), np.int64)
    fe = _arg(np.zeros((0, 0)) if f_ext is None else f_ext)
    run_chunks(pm, models.servo, models.dither, models.sai, models.lead, _arg(x_ref), _arg(v_ref), fe, seeds, corr,
         plant, *states, out, o_dither, status, fail)
    xr, y, yb, u, xt, xb, mode = (o[:n_trials] for o in out)
    res = BatchResult(t=np.arange(T) / preset.controller.rate, x_ref=xr, x_correction=xr - x_ref,
                      v_ref=np.asarray(v_ref),
                      y=y, y_bearing=yb, u=u, x_table=xt, x_bearing=xb,
                      dither=o_dither[:n_trials], mode=mode,
                      status=status.reshape(-1)[:n_trials], fail_step=fail.reshape(-1)[:n_trials])
    return res.check() if check else res
