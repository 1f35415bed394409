"""The friction isolator's (``k_fi``, ``c_fi``) grid of a preset, simulated and analysed (Sec. 6.3.2).

For a preset whose bearings sit on compliant joints, :func:`sweep_isolator` sweeps the stage's
total FI stiffness ``k_fi`` [N/m] and damping ``c_fi`` [N·s/m] (split equally over the jointed
bearings; an SAI lock is removed, Sec. 6.2 runs the SAI as a passive FI) and, per grid point,

* simulates ``n_trials`` point-to-point moves on the batch engine (one
  :func:`experiment_runner.core.batch.simulate` call per grid point with all its trials: the engine
  runs one plant model per call, so grid points with different joints cannot share a call; the
  servo/dither/SAI models are built once and only the plant is rebuilt per point) and
  measures settling time into ``±window`` and RMS in-position error after settling
  (:mod:`experiment_runner.core.metrics`), mean over trials;
* computes the band 2-norms ``||G_e||_[1,50 Hz]`` and ``||G_d||_[1,500 Hz]`` of Eq. 6.1/6.3 on the
  Fig. 6.2 model (:func:`stage_control.isolator.norm_maps`) lumped from the preset
  (:func:`lumped_stage`): ``m_t`` = table incl. mode masses (+ rigid bearings), ``m_b`` = jointed
  bearings, ``k_f`` = their pre-motion tangent stiffness, ``c_f`` = 5 % of critical
  (:func:`stage_control.isolator.c_f_estimate`).

The same moves run on the stage with the bearings bolted rigidly (No FI) and on the preset's own FI.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np

from experiment_runner.core import profiles
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.errors import DesignError
from experiment_runner.core.executor import make_executor
from experiment_runner.core.experiment import Starts
from experiment_runner.core.metrics import rms_in_position, settling_time
from stage_control import isolator
from stage_sim.config import GmsFriction, Preset, load_preset, with_overrides
from stage_sim.friction import initial_stiffness
from stage_sim.plant_model import build_plant

# ----------------------------------------------------------------------------- defaults
STEP = 5e-6          # Sec. 6.3.1: 5 um steps show the settling/in-position trade-off (Table 6.3)
WINDOW = 25e-9       # Sec. 6.3.1: +-25 nm settling window
DWELL = 0.5          # settling portion [s]: > 5x the slowest No FI mean settling time of Table 4.2
N_TRIALS = 8         # trials per grid point (random start positions, own noise seeds)
START_SEED = 1       # rng seed of the random start positions
GRIDS = {            # stage-total k_fi [N/m] x c_fi [N·s/m]
    "default": (np.logspace(4, 7, 19), np.logspace(0, 4, 13)),
    "coarse": (np.logspace(4, 7, 7), np.logspace(0, 4, 5)),
    "fine": (np.logspace(4, 7, 31), np.logspace(0, 4, 21)),
}
RIGID = math.inf     # k_fi of the No FI stage


def as_preset(preset) -> Preset:
    """``preset`` itself when it is a :class:`~stage_sim.config.Preset`, else the preset of that name or path."""
    return preset if isinstance(preset, Preset) else load_preset(preset)


# ============================================================================= lumped model
@dataclass
class LumpedStage:
    """Fig. 6.2 parameters of a preset (SI) and its own FI design (stage totals)."""
    m_t: float            # table incl. structural-mode masses and rigid bearings [kg]
    m_b: float            # bearings on joints [kg]
    k_f: float            # pre-motion tangent stiffness of the jointed bearings [N/m]
    c_f: float            # pre-motion damping, isolator.c_f_estimate (5 % of critical) [N·s/m]
    f_c: float            # Coulomb force of the jointed bearings [N]
    n_joints: int         # jointed bearings (k_fi, c_fi are split equally over them)
    k_fi: float           # the preset's own total FI stiffness [N/m]
    c_fi: float           # the preset's own total FI damping [N·s/m]
    pid: dict             # PID gains (stage_control.tuning.pid_tf keys)
    gms_k: list           # GMS blocks for γ [N/m] (preset's, or Table 6.5's distribution with Σk_i = k_f)
    gms_alpha: list       # GMS fractions for γ [-]
    gms_source: str


def lumped_stage(preset) -> LumpedStage:
    """Lump a preset with FI joints into the Fig. 6.2 model.

    Raises
    ------
    DesignError
        If no bearing of the preset sits on a compliant joint.
    """
    p = as_preset(preset)
    st = p.stage
    jointed = [b for b in st.bearings if b.joint is not None]
    if not jointed:
        raise DesignError(f"preset {p.name}: no bearing on a compliant joint (stage.bearings.*.joint), "
                          f"so there is no friction isolator to size")
    m_t = st.table.mass * (1.0 + sum(m.mass_ratio for m in st.modes)) + sum(
        b.mass for b in st.bearings if b.joint is None)
    m_b = sum(b.mass for b in jointed)
    k_f = sum(initial_stiffness(b.friction) for b in jointed)
    f_c = sum(b.friction.f_c for b in jointed)
    gms = [b.friction for b in jointed if isinstance(b.friction, GmsFriction)]
    if len(gms) == len(jointed):        # parallel bearings: blocks side by side, fractions of the total F_C
        gk = [k for fr in gms for k in fr.k]
        ga = [a * fr.f_c / f_c for fr in gms for a in fr.alpha]
        src = f"{p.name} GMS blocks"
    else:
        # the seed identifies Dahl and GMS from the same FRFs: they share the initial stiffness
        # (isolator.gms_consistent), so Table 6.5's block distribution is scaled to the preset's k_f
        gk = list(isolator.gms_consistent(k_f)) if k_f else list(isolator.GMS_K)
        ga, src = list(isolator.GMS_ALPHA), "Table 6.5 distribution, Σk_i = k_f"
    return LumpedStage(m_t=m_t, m_b=m_b, k_f=k_f, c_f=isolator.c_f_estimate(m_t, m_b, k_f=k_f) if k_f else 0.0,
                       f_c=f_c, n_joints=len(jointed), k_fi=sum(b.joint.stiffness for b in jointed),
                       c_fi=sum(b.joint.damping for b in jointed), pid=p.controller.pid.model_dump(),
                       gms_k=gk, gms_alpha=ga, gms_source=src)


def isolator_preset(preset, k_fi: float, c_fi: float) -> Preset:
    """The preset with every jointed bearing on ``k_fi/n`` [N/m], ``c_fi/n`` [N·s/m] (stage totals
    ``k_fi``, ``c_fi``); ``k_fi = inf`` bolts the bearings rigidly (No FI). Any SAI lock is removed."""
    p = as_preset(preset)
    idx = [i for i, b in enumerate(p.stage.bearings) if b.joint is not None]
    over = {"stage.sai": None, "sai_manager": None}
    for i in idx:
        over[f"stage.bearings.{i}.joint"] = None if math.isinf(k_fi) else {
            "stiffness": k_fi / len(idx), "damping": c_fi / len(idx)}
    if math.isinf(k_fi):
        over["stage.bearing_sensor"] = None
    return with_overrides(p, over)


# ============================================================================= simulation
@dataclass
class Moves:
    """Point-to-point test of every grid point: shared reference, starts and seeds."""
    step: float           # [m]
    window: float         # settling half-band [m]
    dwell: float          # [s]
    n_trials: int
    x0: np.ndarray        # start positions [m]
    seeds: np.ndarray

    @classmethod
    def make(cls, preset: Preset, step=STEP, window=WINDOW, dwell=DWELL, n_trials=N_TRIALS) -> "Moves":
        x0 = Starts(margin=abs(step) + 1e-3, seed=START_SEED).positions(n_trials, preset.stage.travel)
        return cls(step, window, dwell, n_trials, x0, preset.simulation.seed + np.arange(n_trials))

    def run(self, preset: Preset, models: Optional[Models] = None):
        """Settling time [s] (nan: not settled) and RMS in-position error [m] per trial; ``models``:
        pre-built models of ``preset`` (see :func:`experiment_runner.core.batch.simulate`)."""
        ref = profiles.point_to_point(self.step, dwell=self.dwell, dt=1.0 / preset.controller.rate)
        t_start = ref.t[ref.select("settle")[0].start]
        r = simulate(preset, ref.x, ref.v, n_trials=self.n_trials, x0=self.x0, seeds=self.seeds, models=models,
                     check=False)
        target = self.x0 + self.step
        ts = np.asarray(settling_time(r.t, r.y, target, t_start, self.window), float)
        ts[r.status != 0] = np.nan
        rms = np.asarray(rms_in_position(r.t, r.y, target, t_start + ts), float)
        return ts, rms


def _summary(ts, rms):
    """Trial counts and means [s], [m]; the means are nan unless every trial settled (as the grid)."""
    return dict(settled=int(np.isfinite(ts).sum()), trials=int(ts.size),
                settling_time_s=float(np.mean(ts)), rms_in_position_m=float(np.mean(rms)))


@dataclass
class Sweep:
    """Simulated and analysed (k_fi, c_fi) grid of one preset; arrays are (n_k, n_c[, n_trials])."""
    preset: str
    k_grid: np.ndarray    # stage-total k_fi [N/m]
    c_grid: np.ndarray    # stage-total c_fi [N·s/m]
    moves: Moves
    ts: np.ndarray        # settling time per trial [s]
    rms: np.ndarray       # RMS in-position error per trial [m]
    ge: np.ndarray        # ||G_e||_[1,50 Hz] [√Hz]
    gd: np.ndarray        # ||G_d||_[1,500 Hz] [m/(N·√Hz)]
    ge_nofi: float
    gd_nofi: float
    lumped: LumpedStage
    nofi: dict            # No FI (rigid) summary
    design: dict          # the preset's own FI summary
    runtime_s: float

    @property
    def settled(self):
        """(n_k, n_c): every trial settled within the dwell."""
        return np.all(np.isfinite(self.ts), axis=-1)

    @property
    def ts_mean(self):
        """(n_k, n_c) mean settling time [s], nan unless every trial settled."""
        return self.ts.mean(axis=-1)

    @property
    def rms_mean(self):
        """(n_k, n_c) mean RMS in-position error [m], nan unless every trial settled."""
        return self.rms.mean(axis=-1)


def _grid_row(p: Preset, moves: Moves, k: float, c_grid: np.ndarray):
    """Executor task: settling times [s] and RMS in-position errors [m] of one k_fi row, (n_c, n_trials) each."""
    ts = np.empty((c_grid.size, moves.n_trials))
    rms = np.empty_like(ts)
    # servo, dither and SAI models do not depend on the joints: build them once, only the plant per point
    base = Models.from_preset(isolator_preset(p, k, c_grid[0]))
    for j, c in enumerate(c_grid):
        q = isolator_preset(p, k, c)
        plant = build_plant(q.stage, q.controller.rate, q.simulation.max_omega_h, q.simulation.max_substeps)
        ts[j], rms[j] = moves.run(q, replace(base, plant=plant))
    return ts, rms


def sweep_isolator(preset, k_grid=None, c_grid=None, step=STEP, window=WINDOW, dwell=DWELL,
                   n_trials=N_TRIALS, progress=None, workers=None, cluster=None) -> Sweep:
    """Simulate and analyse the FI (k_fi, c_fi) grid of a preset.

    Parameters
    ----------
    preset : str or Preset
        Preset name/path or object; needs bearings on compliant joints.
    k_grid, c_grid : array_like, optional
        Stage-total FI stiffness [N/m] and damping [N·s/m] (default ``GRIDS["default"]``).
    step : float
        Point-to-point step [m] (default 5 um, Sec. 6.3.1).
    window : float
        Settling half-band [m] (default 25 nm).
    dwell : float
        Settling portion after the reference stops [s].
    n_trials : int
        Trials per grid point (random starts, own noise seeds; the same for every point).
    progress : callable, optional
        Called with a one-line status per k_fi row.
    workers, cluster : optional
        Where the grid runs (:func:`experiment_runner.core.executor.make_executor`): in this
        process (default), on ``workers`` local processes, or on a Dask cluster; same results.
        A task is a k_fi row, or a part of one where the rows are fewer than twice the workers.

    Returns
    -------
    Sweep
    """
    t0 = time.perf_counter()
    p = as_preset(preset)
    lump = lumped_stage(p)
    kd, cd = GRIDS["default"]
    k_grid = np.sort(np.asarray(kd if k_grid is None else k_grid, float))
    c_grid = np.sort(np.asarray(cd if c_grid is None else c_grid, float))
    if k_grid.size == 0 or c_grid.size == 0 or k_grid[0] <= 0 or c_grid[0] < 0:
        raise DesignError("grid: k_fi must be > 0 and c_fi >= 0 (non-empty)")
    moves = Moves.make(p, step, window, dwell, n_trials)
    ts = np.empty((k_grid.size, c_grid.size, n_trials))
    rms = np.empty_like(ts)
    with make_executor(workers, cluster) as ex:
        parts = min(c_grid.size, math.ceil(2 * ex.workers / k_grid.size)) if ex.workers > 1 else 1
        cuts = np.linspace(0, c_grid.size, parts + 1).round().astype(int)
        tasks = (((i, a, b), (p, moves, float(k), c_grid[a:b])) for i, k in enumerate(k_grid)
                 for a, b in zip(cuts[:-1], cuts[1:]))
        left = np.full(k_grid.size, parts)
        for (i, a, b), (ts_part, rms_part) in ex.map(_grid_row, tasks):
            ts[i, a:b], rms[i, a:b] = ts_part, rms_part
            left[i] -= 1
            if progress and not left[i]:
                progress(f"k_fi = {k_grid[i]:.3g} N/m: {np.isfinite(ts[i]).all(-1).sum()}/{c_grid.size} "
                         "points settled")
    ge, gd, ge0, gd0 = isolator.norm_maps(lump.m_t, lump.m_b, lump.pid, lump.k_f, lump.c_f, k_grid, c_grid)
    nofi = _summary(*moves.run(isolator_preset(p, RIGID, 0.0)))
    design = _summary(*moves.run(isolator_preset(p, lump.k_fi, lump.c_fi)))
    return Sweep(preset=p.name, k_grid=k_grid, c_grid=c_grid, moves=moves, ts=ts, rms=rms, ge=ge, gd=gd,
                 ge_nofi=ge0, gd_nofi=gd0, lumped=lump, nofi=nofi, design=design,
                 runtime_s=time.perf_counter() - t0)
