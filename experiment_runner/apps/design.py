"""Design advisor (``nanostage design``): the seed's Chapter 6 and Sec. 3.3-3.4 guidelines as a tool.

Friction isolator (Sec. 6.3.2, 6.4.2)
-------------------------------------
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
  Fig. 6.2 model (:func:`stage_control.isolator.norm_maps`) lumped from the preset:
  ``m_t`` = table incl. mode masses (+ rigid bearings), ``m_b`` = jointed bearings, ``k_f`` = their
  pre-motion tangent stiffness, ``c_f`` = 5 % of critical (:func:`stage_control.isolator.c_f_estimate`).

:func:`recommend` applies Sec. 6.3.2 ("designed to meet the RMS in-position error requirements
with the smallest stiffness and damping coefficient"). **Rule:** a grid point is feasible when
every trial settles within the dwell and the mean RMS in-position error is ``<= rms_required``;
the recommendation is the feasible point with the smallest ``k_fi`` and, at that ``k_fi``, the
smallest ``c_fi``. It reports the settling time this buys against the same stage with the
bearings bolted rigidly (No FI) and the FF accuracy at that stiffness (Sec. 6.4.2): ``γ`` = RMS
difference of the Dahl and GMS friction forces over one 5 mm circle cycle with ``η = k_fi/k_f``
(:func:`stage_control.isolator.gamma_curve`; GMS blocks of the preset when its
bearings use GMS, else Table 6.5's block distribution scaled to the preset's initial stiffness, as
:func:`stage_control.isolator.gms_consistent` does for Fig. 6.8) and ``κ`` of Eq. 4.2.

Caveat: with Dahl bearings (``fi_stage``) a stiff FI or No FI drifts out of the window after
settling (the single-state Dahl ratchet under drive noise, see the ``table_4_2`` campaign), so the
stiff corner of the maps and the No FI comparison are artefacts there; the GMS variants
(``fi_stage_gms``) settle normally.

VAN (Sec. 3.3, 3.4.3)
---------------------
:func:`check_van` computes the piezo drive voltage for the preset's dither force, the piezo
power of Eq. 3.7 and the flexure fatigue check of Eq. 3.4-3.6 with Table 3.2's data.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Optional

import numpy as np

from experiment_runner.core import outputs, profiles
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.cliargs import nonnegative_float, nonzero_float, positive_float, positive_int
from experiment_runner.core.errors import DesignError
from experiment_runner.core.executor import add_executor_arguments, default_workers, make_executor
from experiment_runner.core.experiment import Starts
from experiment_runner.core.metrics import rms_in_position, settling_time
from stage_control import isolator
from stage_sim.config import GmsFriction, Preset, load_preset, with_overrides
from stage_sim.friction import initial_stiffness
from stage_sim.plant_model import build_plant
from stage_sim.validation import load_yaml

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


def _preset(preset) -> Preset:
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
    p = _preset(preset)
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
    p = _preset(preset)
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
    p = _preset(preset)
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


# ============================================================================= recommendation
RULE = ("feasible: every trial settles within the dwell and mean RMS in-position error <= requirement; "
        "recommend the feasible grid point with the smallest k_fi, then the smallest c_fi at that k_fi "
        "(Sec. 6.3.2: 'meet the RMS in-position error requirements with the smallest stiffness and damping')")


@dataclass
class Point:
    """One FI design (stage totals) with its simulated and analysed performance (SI)."""
    k_fi: float
    c_fi: float
    k_fi_per_bearing: float
    c_fi_per_bearing: float
    settling_time_s: float
    rms_in_position_m: float
    zeta_fi: float        # FI mode damping ratio c_fi / (2 sqrt(k_fi m_t m_b/(m_t + m_b))) [-]
    ge_norm: float
    gd_norm: float
    eta: float            # k_fi / k_f
    gamma_n: float        # Sec. 6.4.2 RMS F_Dahl - F_GMS over one 5 mm circle cycle [N]
    gamma_bias_n: float   # mean (F_Dahl - F_GMS) sgn(v) [N]: + = Dahl over-compensates
    kappa: float          # Eq. 4.2 sensitivity of k_c to k_f [-]
    settling_reduction_vs_nofi: float   # 1 - ts / ts_NoFI (nan if No FI did not settle)
    index: tuple = ()     # (i, j) in the sweep grid, () if off-grid


@dataclass
class Advice:
    """Result of :func:`recommend` (SI units)."""
    preset: str
    rms_required_m: float
    rule: str
    feasible: np.ndarray                  # (n_k, n_c) bool
    recommended: Optional[Point]
    fastest_feasible: Optional[Point]     # feasible point with the shortest mean settling time
    preset_design: Point                  # the preset's own FI
    nofi: dict
    message: str
    sweep: Sweep = field(repr=False)

    @property
    def ok(self) -> bool:
        return self.recommended is not None


def _point(sw: Sweep, k, c, ts, rms, index=()) -> Point:
    lp = sw.lumped
    ge, gd = isolator.point_norms(lp.m_t, lp.m_b, lp.pid, k, c, lp.k_f, lp.c_f) if not index else (
        float(sw.ge[index]), float(sw.gd[index]))
    eta = k / lp.k_f if lp.k_f else math.inf
    gam, bias, _ = isolator.gamma_curve(np.array([eta]), lp.k_f, lp.f_c, lp.gms_k, lp.gms_alpha)
    ts0 = sw.nofi["settling_time_s"]
    zeta = float(c) / (2.0 * math.sqrt(k * lp.m_t * lp.m_b / (lp.m_t + lp.m_b)))
    return Point(k_fi=float(k), c_fi=float(c), k_fi_per_bearing=float(k) / lp.n_joints,
                 c_fi_per_bearing=float(c) / lp.n_joints, settling_time_s=float(ts),
                 rms_in_position_m=float(rms), zeta_fi=zeta, ge_norm=ge, gd_norm=gd, eta=float(eta),
                 gamma_n=float(gam[0]), gamma_bias_n=float(bias[0]), kappa=float(isolator.kappa_eq42(eta)),
                 settling_reduction_vs_nofi=float(1.0 - ts / ts0) if math.isfinite(ts0) else math.nan,
                 index=tuple(int(v) for v in index))


def _required(rms_required_m) -> float:
    """The requirement as a float [m]; :class:`DesignError` unless finite and > 0."""
    try:
        v = float(rms_required_m)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise DesignError(f"rms_required_m = {rms_required_m!r}: must be a finite value > 0 [m]")
    return v


def recommend(sw: Sweep, rms_required_m: float) -> Advice:
    """Apply :data:`RULE` to a sweep for a required RMS in-position error [m]."""
    rms_required_m = _required(rms_required_m)
    ts, rms = sw.ts_mean, sw.rms_mean
    with np.errstate(invalid="ignore"):
        feas = sw.settled & (rms <= rms_required_m)
    lp = sw.lumped
    design = _point(sw, lp.k_fi, lp.c_fi, sw.design["settling_time_s"], sw.design["rms_in_position_m"])
    rec = fast = None
    if feas.any():
        i = int(np.flatnonzero(feas.any(axis=1))[0])
        j = int(np.flatnonzero(feas[i])[0])
        rec = _point(sw, sw.k_grid[i], sw.c_grid[j], ts[i, j], rms[i, j], (i, j))
        fi, fj = np.unravel_index(np.nanargmin(np.where(feas, ts, np.nan)), ts.shape)
        fast = _point(sw, sw.k_grid[fi], sw.c_grid[fj], ts[fi, fj], rms[fi, fj], (fi, fj))
        edge = " (softest grid k_fi: extend the grid down)" if i == 0 else ""
        n = sw.nofi
        vs = (f"{100 * rec.settling_reduction_vs_nofi:.0f} % faster than No FI ({n['settling_time_s'] * 1e3:.1f} ms)"
              if n["settled"] == n["trials"] else
              f"No FI settled in only {n['settled']}/{n['trials']} trials within the {sw.moves.dwell:g} s dwell")
        msg = (f"recommended k_fi = {rec.k_fi:.3g} N/m, c_fi = {rec.c_fi:.3g} N·s/m{edge}: "
               f"{rec.rms_in_position_m * 1e9:.2f} nm RMS in position, settles in "
               f"{rec.settling_time_s * 1e3:.1f} ms; {vs}")
    else:
        best = np.nanmin(rms) if np.isfinite(rms).any() else math.nan
        msg = (f"no FI on the grid meets {rms_required_m * 1e9:.3g} nm RMS in position (best "
               f"{best * 1e9:.3g} nm): relax the requirement, use a stiffer/more damped FI than the grid, "
               f"or the semi-active isolator (Sec. 6.3.2, Ch. 5)")
    return Advice(preset=sw.preset, rms_required_m=rms_required_m, rule=RULE, feasible=feas,
                  recommended=rec, fastest_feasible=fast, preset_design=design, nofi=sw.nofi, message=msg,
                  sweep=sw)


def advise_isolator(preset, rms_required_m: float, step=STEP, grid="default", **kw) -> Advice:
    """Sweep a preset's FI and recommend the softest, least damped design meeting a requirement.

    Parameters
    ----------
    preset : str or Preset
        Preset with bearings on compliant joints (e.g. ``fi_stage``).
    rms_required_m : float
        Required RMS in-position error [m] (> 0).
    step : float
        Point-to-point step [m].
    grid : str or (array_like, array_like)
        ``"default"``, ``"coarse"``, ``"fine"`` or explicit (k_fi [N/m], c_fi [N·s/m]) stage totals.
    **kw
        Passed to :func:`sweep_isolator` (``window``, ``dwell``, ``n_trials``, ``progress``,
        ``workers``, ``cluster``).

    Returns
    -------
    Advice

    Examples
    --------
    >>> a = advise_isolator("fi_stage", 4e-9, grid=([3e4, 3e5], [1.0, 100.0]), n_trials=2, dwell=0.2)
    >>> a.recommended.rms_in_position_m <= 4e-9
    True
    """
    rms_required_m = _required(rms_required_m)
    if isinstance(grid, str):
        if grid not in GRIDS:
            raise DesignError(f"grid = {grid!r}: choose one of {', '.join(GRIDS)}")
        grid = GRIDS[grid]
    return recommend(sweep_isolator(preset, grid[0], grid[1], step=step, **kw), rms_required_m)


# ============================================================================= VAN check
@dataclass(frozen=True)
class Piezo:
    """Piezo stack of the VAN stage (Sec. 3.3: PI P-842.10; datasheet values, SI)."""
    free_stroke: float = 15e-6      # stroke at v_max without load [m] (P-842.10; van_stage preset note)
    blocking_force: float = 300.0   # force at v_max against a rigid wall [N] (P-842.10)
    v_max: float = 100.0            # max operating voltage [V] (Sec. 3.3)
    # derived: Sec. 3.4.3 gives 0.3 W per actuator at V_pp = 20 V, f = 500 Hz; Eq. 3.7 then needs
    # C = 0.3/(500*20^2) = 1.5 uF, which is the P-842.10 datasheet capacitance
    capacitance: float = 1.5e-6     # [F]

    @property
    def stiffness(self) -> float:
        """Piezo stiffness = blocking force / free stroke [N/m]."""
        return self.blocking_force / self.free_stroke


@dataclass(frozen=True)
class Flexure:
    """VAN flexure strength data (Sec. 3.3, Table 3.2: 304 stainless steel; SI)."""
    s_ut: float = 517e6             # Table 3.2: ultimate tensile strength [Pa]
    s_y: float = 207e6              # Table 3.2: yield strength [Pa]
    h: float = 19e-3                # Sec. 3.3: hinge height [m]
    d: float = 1e-3                 # Sec. 3.3: hinge thickness [m]
    # Table 3.2: S_max = 47 MPa "with the maximum applied load of 77 N" (the text of Sec. 3.3 says
    # 43 MPa for the same load; the larger, conservative value is used). Stress is linear in load.
    stress_ref: float = 47e6        # [Pa] at load_ref
    load_ref: float = 77.0          # [N]
    p_c: float = 1.0                # loading factor (Sec. 3.3: 1)
    p_d: float = 1.0                # temperature factor (Sec. 3.3: 1)
    p_e: float = 0.814              # reliability factor, 99 % (Sec. 3.3)
    p_f: float = 1.0                # miscellaneous (Sec. 3.3: 1)


@dataclass
class VanCheck:
    """Result of :func:`check_van` (SI; stresses in Pa)."""
    preset: str
    dither_amplitude_n: float
    dither_frequency_hz: float
    n_piezos: int
    flexure_stiffness: float        # [N/m]
    force_per_volt: float           # flexure force per piezo volt [N/V]
    v_pp: float                     # piezo peak-to-peak voltage for the dither [V]
    power_per_piezo_w: float        # Eq. 3.7
    power_total_w: float
    heat_w: float                   # 10 % of the electrical power (Sec. 3.4.3)
    heat_per_move_j: float          # over one move of move_time
    max_load_n: float               # piezo at v_max against the flexure (worst case)
    d_e: float                      # Eq. 3.6 equivalent diameter [m]
    p_a: float
    p_b: float
    s_e_nominal: float              # S'_e = S_ut/2
    s_e: float                      # Eq. 3.4
    s_max: float                    # stress at max_load
    s_dither: float                 # stress at the dither's peak load (unipolar 0..2A)
    fatigue_safety: float           # S_e / S_max (worst case)
    yield_safety: float             # S_y / S_max
    fatigue_safety_dither: float    # S_e / S_dither
    passed: bool
    message: str


def check_van(preset, piezo: Piezo = Piezo(), flexure: Flexure = Flexure(), v_pp: Optional[float] = None,
              move_time: float = 0.25, heat_fraction: float = 0.1, min_safety: float = 1.0) -> VanCheck:
    """Piezo power (Eq. 3.7) and flexure fatigue (Eq. 3.4-3.6, Table 3.2) of a VAN preset.

    The piezo (stiffness ``k_p``) drives the flexure (stiffness ``k_j`` = the preset's joint) in
    series, so the flexure force per volt is ``k_j (x_free/v_max) k_p/(k_p + k_j)`` and the dither's
    ``2A`` peak-to-peak force needs ``V_pp = 2A / that``. ``P = f C V_pp²`` per piezo (Eq. 3.7).
    Fatigue: ``S_e = p_a p_b p_c p_d p_e p_f S'_e``, ``S'_e = S_ut/2``, ``p_a = 4.51 S_ut^-0.265``
    (S_ut in MPa), ``p_b = 1.24 d_e^-0.107``, ``d_e = 0.808 sqrt(h d)`` (mm); infinite life when
    the worst-case stress (piezo at ``v_max``) is below ``S_e`` (Sec. 3.3).

    Parameters
    ----------
    preset : str or Preset
        A preset with ``dither`` and dithered bearings on joints (e.g. ``van_stage``).
    piezo, flexure : Piezo, Flexure
        Actuator and flexure data (defaults: the seed's P-842.10 and Table 3.2).
    v_pp : float, optional
        Piezo peak-to-peak voltage [V]; default derived from the dither amplitude.
    move_time : float
        Duration of one point-to-point move for the heat estimate [s] (Sec. 3.4.3: 250 ms).
    heat_fraction : float
        Fraction of the electrical power turned into heat (Sec. 3.4.3: up to 10 %).
    min_safety : float
        Required fatigue and yield safety factors [-].

    Returns
    -------
    VanCheck

    Examples
    --------
    >>> v = check_van("van_stage", v_pp=20.0)
    >>> round(v.power_per_piezo_w, 3), round(v.s_e / 1e6, 1), v.passed
    (0.3, 196.4, True)
    """
    p = _preset(preset)
    if p.dither is None:
        raise DesignError(f"preset {p.name}: no dither section, so there is no VAN design to check")
    dith = [b for b in p.stage.bearings if b.dither_channel is not None]
    if not dith or any(b.joint is None for b in dith):
        raise DesignError(f"preset {p.name}: the dithered bearings need compliant joints (the VAN flexures)")
    if not (min_safety > 0 and move_time > 0 and 0 <= heat_fraction <= 1):
        raise DesignError("min_safety and move_time must be > 0, heat_fraction in [0, 1]")
    k_j = dith[0].joint.stiffness
    kp = piezo.stiffness
    fpv = k_j * (piezo.free_stroke / piezo.v_max) * kp / (kp + k_j)
    A, f = p.dither.amplitude, p.dither.frequency
    vpp = 2.0 * A / fpv if v_pp is None else float(v_pp)
    if not (vpp >= 0 and math.isfinite(vpp)):
        raise DesignError(f"v_pp = {v_pp!r}: must be a finite voltage >= 0")
    pw = f * piezo.capacitance * vpp ** 2
    total = pw * len(dith)
    d_e = 0.808 * math.sqrt(flexure.h * 1e3 * flexure.d * 1e3) * 1e-3
    p_a = 4.51 * (flexure.s_ut / 1e6) ** -0.265
    p_b = 1.24 * (d_e * 1e3) ** -0.107
    s_e0 = 0.5 * flexure.s_ut
    s_e = p_a * p_b * flexure.p_c * flexure.p_d * flexure.p_e * flexure.p_f * s_e0
    f_max = piezo.v_max * fpv
    per_n = flexure.stress_ref / flexure.load_ref
    s_max, s_dith = per_n * f_max, per_n * fpv * vpp
    nf, ny = s_e / s_max, flexure.s_y / s_max
    passed = nf >= min_safety and ny >= min_safety
    msg = (f"{'PASS' if passed else 'FAIL'}: worst-case flexure stress {s_max / 1e6:.1f} MPa at {f_max:.0f} N "
           f"(piezo at {piezo.v_max:.0f} V); endurance limit S_e = {s_e / 1e6:.1f} MPa -> fatigue safety "
           f"{nf:.2f}, yield safety {ny:.2f} (required {min_safety:g})"
           + ("" if passed else ": finite fatigue life or yielding, redesign the flexure"))
    return VanCheck(preset=p.name, dither_amplitude_n=A, dither_frequency_hz=f, n_piezos=len(dith),
                    flexure_stiffness=k_j, force_per_volt=fpv, v_pp=vpp, power_per_piezo_w=pw, power_total_w=total,
                    heat_w=heat_fraction * total, heat_per_move_j=heat_fraction * total * move_time,
                    max_load_n=f_max, d_e=d_e, p_a=p_a, p_b=p_b, s_e_nominal=s_e0, s_e=s_e, s_max=s_max,
                    s_dither=s_dith, fatigue_safety=nf, yield_safety=ny, fatigue_safety_dither=s_e / s_dith
                    if s_dith > 0 else math.inf, passed=passed, message=msg)


# ============================================================================= report
def _jsonable(o):
    """numpy/dataclass tree -> JSON types; non-finite floats -> None."""
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (o.tolist() if isinstance(o, np.ndarray) else o)]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    return o


def advice_dict(a: Advice) -> dict:
    """JSON-ready summary of an :class:`Advice` with its sweep maps (SI units)."""
    sw = a.sweep
    pts = {name: None if p is None else asdict(p) for name, p in (
        ("recommended", a.recommended), ("fastest_feasible", a.fastest_feasible),
        ("preset_design", a.preset_design))}
    return _jsonable(dict(
        preset=a.preset, ok=a.ok, rms_required_m=a.rms_required_m, rule=a.rule, message=a.message, **pts,
        nofi=a.nofi, lumped=asdict(sw.lumped),
        test=dict(step_m=sw.moves.step, window_m=sw.moves.window, dwell_s=sw.moves.dwell,
                  n_trials=sw.moves.n_trials, start_positions_m=sw.moves.x0, seeds=sw.moves.seeds),
        grid=dict(k_fi=sw.k_grid, c_fi=sw.c_grid, feasible=a.feasible, settled=sw.settled,
                  settling_time_s=sw.ts_mean, rms_in_position_m=sw.rms_mean, ge_norm=sw.ge, gd_norm=sw.gd,
                  ge_norm_nofi=sw.ge_nofi, gd_norm_nofi=sw.gd_nofi),
        runtime_s=sw.runtime_s))


def _fmt(v, scale=1.0, spec=".3g"):
    return "—" if v is None or not math.isfinite(v) else format(v * scale, spec)


def advice_table(a: Advice) -> list[list[str]]:
    """Rows (header first) comparing the recommendation, the fastest feasible point, the preset's own
    FI and No FI."""
    head = ["design", "k_fi [N/m]", "k_fi/bearing [N/m]", "c_fi [N·s/m]", "settling [ms]", "RMS in-pos [nm]",
            "ζ_fi", "‖G_e‖ [√Hz]", "‖G_d‖ [µm/(N·√Hz)]", "η = k_fi/k_f", "γ Dahl-GMS [N]", "κ Eq. 4.2",
            "settling vs No FI"]
    rows = [head]
    for lab, p in (("recommended", a.recommended), ("fastest feasible", a.fastest_feasible),
                   (f"{a.preset} as is", a.preset_design)):
        if p is None:
            rows.append([lab, "none meets the requirement"] + [""] * (len(head) - 2))
            continue
        red = p.settling_reduction_vs_nofi
        rows.append([lab, _fmt(p.k_fi), _fmt(p.k_fi_per_bearing), _fmt(p.c_fi), _fmt(p.settling_time_s, 1e3, ".1f"),
                     _fmt(p.rms_in_position_m, 1e9, ".2f"), _fmt(p.zeta_fi, 1, ".2g"), _fmt(p.ge_norm),
                     _fmt(p.gd_norm, 1e6),
                     _fmt(p.eta), _fmt(p.gamma_n), _fmt(p.kappa, 1, ".2g"),
                     "—" if not math.isfinite(red) else f"{-100 * red:+.0f} %"])
    n = a.nofi
    rows.append(["No FI (rigid)", "∞", "∞", "—", _fmt(n["settling_time_s"], 1e3, ".1f"),
                 _fmt(n["rms_in_position_m"], 1e9, ".2f"), "—", _fmt(a.sweep.ge_nofi), _fmt(a.sweep.gd_nofi, 1e6),
                 "∞", "—", "1", f"{n['settled']}/{n['trials']} settled"])
    return rows


def _text_table(rows) -> str:
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows)


def _md_table(rows) -> str:
    return "\n".join(["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
                     + ["| " + " | ".join(r) + " |" for r in rows[1:]])


def van_rows(v: VanCheck) -> list[list[str]]:
    """(quantity, value, seed) rows of a :class:`VanCheck`; seed values from Sec. 3.3/3.4.3, Table 3.2."""
    return [["quantity", "ours", "seed prototype (Sec. 3.3, 3.4.3)"],
            ["dither amplitude / frequency", f"{v.dither_amplitude_n:g} N / {v.dither_frequency_hz:g} Hz",
             "15 N p-p at 500 Hz (Sec. 3.4.1)"],
            ["piezo voltage V_pp", f"{v.v_pp:.1f} V", "20 V"],
            ["power per piezo (Eq. 3.7)", f"{v.power_per_piezo_w:.3f} W", "0.3 W"],
            [f"total power ({v.n_piezos} piezos)", f"{v.power_total_w:.3f} W", "0.6 W"],
            ["heat (10 %) / per 250 ms move", f"{v.heat_w:.3f} W / {v.heat_per_move_j:.4f} J", "< 0.06 W / 0.015 J"],
            ["worst-case load (piezo at V_max)", f"{v.max_load_n:.1f} N", "77 N"],
            ["d_e (Eq. 3.6)", f"{v.d_e * 1e3:.2f} mm", "3.52 mm"],
            ["p_a (Eq. 3.5) / p_b (Eq. 3.6)", f"{v.p_a:.3f} / {v.p_b:.3f}", "0.86 / 1.08"],
            ["S_e (Eq. 3.4)", f"{v.s_e / 1e6:.1f} MPa", "195.4 MPa"],
            ["S_max worst case / at dither peak", f"{v.s_max / 1e6:.1f} / {v.s_dither / 1e6:.1f} MPa", "47 MPa (43 in text)"],
            ["fatigue safety S_e/S_max", f"{v.fatigue_safety:.2f}", "195.4/47 = 4.16"],
            ["yield safety S_y/S_max", f"{v.yield_safety:.2f}", "4.8 (207/43)"],
            ["verdict", "PASS" if v.passed else "FAIL", "infinite life"]]


def _edges(g):
    lg = np.log10(g)
    mid = (lg[1:] + lg[:-1]) / 2
    d0 = (lg[1] - lg[0]) / 2 if g.size > 1 else 0.5
    d1 = (lg[-1] - lg[-2]) / 2 if g.size > 1 else 0.5
    return 10 ** np.concatenate([[lg[0] - d0], mid, [lg[-1] + d1]])


def _c_plot(g):
    """c_fi grid for log axes (c = 0 drawn at a tenth of the next value)."""
    g = np.asarray(g, float).copy()
    if g[0] <= 0:
        g[0] = g[1] / 10 if g.size > 1 else 1.0
    return g


def _markers(ax, a: Advice):
    for p, style, lab in ((a.recommended, "r*", "recommended"), (a.fastest_feasible, "wD", "fastest feasible"),
                          (a.preset_design, "kX", f"{a.preset} as is")):
        if p is not None:
            ax.plot(p.k_fi, max(p.c_fi, _c_plot(a.sweep.c_grid)[0]), style, ms=11 if style == "r*" else 7,
                    mec="k", label=lab)


def _map_axes(ax, a: Advice, k_grid, c_grid) -> None:
    """Requirement contour, markers, log axes and labels of one k_fi x c_fi map."""
    if a.feasible.any() and not a.feasible.all():
        ax.contour(k_grid, c_grid, a.feasible.T.astype(float), levels=[0.5], colors="r", linewidths=1.5)
    _markers(ax, a)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("k_fi, stage total [N/m]"), ax.set_ylabel("c_fi, stage total [N·s/m]")


def _save_maps(fig, axes, path: Path) -> Path:
    """Legend on the right map, save, close; returns ``path``."""
    import matplotlib.pyplot as plt
    axes[1].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def write_plots(a: Advice, out: Path) -> list[Path]:
    """PNG maps of the sweep (RMS in-position, settling, ||G_e||, ||G_d||) and γ(η)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    sw, files = a.sweep, []
    cg = _c_plot(sw.c_grid)
    ke, ce = _edges(sw.k_grid), _edges(cg)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, M, lab in ((axes[0], sw.rms_mean * 1e9, "mean RMS in-position error [nm]"),
                       (axes[1], sw.ts_mean * 1e3, f"mean settling time into ±{sw.moves.window * 1e9:g} nm [ms]")):
        ax.set_facecolor("0.75")
        Mm = np.ma.masked_invalid(M)
        norm = LogNorm(Mm.min(), Mm.max()) if Mm.count() and Mm.min() > 0 else None
        pc = ax.pcolormesh(ke, ce, Mm.T, cmap="viridis", shading="flat", norm=norm)
        fig.colorbar(pc, ax=ax, label=lab + " (grey: not settled)")
        _map_axes(ax, a, sw.k_grid, cg)
    axes[0].set_title(f"{a.preset}: {sw.moves.step * 1e6:g} µm steps, {sw.moves.n_trials} trials/point; "
                      f"red: requirement {a.rms_required_m * 1e9:g} nm", fontsize=9)
    files.append(_save_maps(fig, axes, out / "design_maps.png"))

    lp = sw.lumped
    kf = np.logspace(np.log10(sw.k_grid[0]), np.log10(sw.k_grid[-1]), 61)
    cf = np.logspace(np.log10(cg[0]), np.log10(cg[-1]), 41)
    E, D, e0, d0 = isolator.norm_maps(lp.m_t, lp.m_b, lp.pid, lp.k_f, lp.c_f, kf, cf)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, M, ref, lab in ((axes[0], E, e0, "||G_e||_[1,50 Hz] / No FI (Eq. 6.1: settling)"),
                            (axes[1], D, d0, "||G_d||_[1,500 Hz] / No FI (Eq. 6.3: in-position)")):
        cs = ax.contourf(kf, cf, (M / ref).T, levels=30, cmap="viridis")
        ax.contour(kf, cf, (M / ref).T, levels=10, colors="w", linewidths=0.4)
        fig.colorbar(cs, ax=ax, label=lab)
        _map_axes(ax, a, sw.k_grid, cg)
    axes[0].set_title(f"Fig. 6.2 model: m_t = {lp.m_t:.2f} kg, m_b = {lp.m_b:.2f} kg, k_f = {lp.k_f:.3g} N/m, "
                      f"c_f = {lp.c_f:.0f} N·s/m", fontsize=9)
    files.append(_save_maps(fig, axes, out / "design_norms.png"))

    etas = np.logspace(-3, 1, 41)
    gam, bias, _ = isolator.gamma_curve(etas, lp.k_f, lp.f_c, lp.gms_k, lp.gms_alpha)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(etas, gam, "k-", label="γ: RMS(F_Dahl − F_GMS), one 5 mm circle cycle")
    for p, style, lab in ((a.recommended, "r*", "recommended"), (a.preset_design, "kX", f"{a.preset} as is")):
        if p is not None:
            ax.semilogx(p.eta, p.gamma_n, style, ms=11, mec="k", label=f"{lab}: η = {p.eta:.3g}, γ = {p.gamma_n:.3g} N")
    ax2 = ax.twinx()
    ax2.loglog(etas, isolator.kappa_eq42(etas), "b:")
    ax2.set_ylabel("κ = (η/(1+η))², Eq. 4.2 (dotted)", color="b")
    ax.axvspan(0.05, 0.1, color="0.9", label="seed optimum 0.05-0.1 (Sec. 6.4.2)")
    ax.set_xlabel("η = k_fi / k_f"), ax.set_ylabel("γ [N]")
    ax.set_title(f"FF accuracy, Dahl vs GMS ({lp.gms_source}), k_f = {lp.k_f:.3g} N/m", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    files.append(outputs.savefig(fig, out / "design_gamma.png", dpi=110))
    plt.close(fig)
    return files


def write_report(out, advice: Optional[Advice] = None, van: Optional[VanCheck] = None,
                 plots: bool = True, overrides=()) -> dict:
    """Write ``design.md``, ``design.json`` and (FI) the PNG plots to ``out``; returns the paths.
    ``overrides``: the ``PATH=VALUE`` preset overrides used, recorded in both files."""
    out = outputs.prepare_folder(out)
    doc, md, files = {"overrides": list(overrides)}, ["# Design advisor (`nanostage design`)", ""], {}
    if overrides:
        md += ["Preset overrides: " + ", ".join(f"`{o}`" for o in overrides), ""]
    if advice is not None:
        sw = advice.sweep
        doc["isolator"] = advice_dict(advice)
        md += [f"## Friction isolator: {advice.preset}, required RMS in-position error "
               f"{advice.rms_required_m * 1e9:g} nm", "",
               f"**{'OK' if advice.ok else 'NO DESIGN'}**: {advice.message}", "",
               f"Rule: {advice.rule}.", "",
               f"Test: {sw.moves.step * 1e6:g} µm point-to-point moves, {sw.moves.n_trials} trials per grid point "
               f"(random starts, own noise seeds), settling into ±{sw.moves.window * 1e9:g} nm within a "
               f"{sw.moves.dwell:g} s dwell; grid {sw.k_grid.size} k_fi × {sw.c_grid.size} c_fi (stage totals, split "
               f"over {sw.lumped.n_joints} bearings); {sw.runtime_s:.1f} s.", "",
               _md_table(advice_table(advice)), "",
               f"γ: Sec. 6.4.2 RMS difference of FI+Dahl and FI+GMS friction over one 5 mm circle cycle "
               f"({sw.lumped.gms_source}); κ: Eq. 4.2 sensitivity of k_c to k_f (robust FF for η < 0.1).", ""]
        if plots:
            paths = write_plots(advice, out)
            files["plots"] = [str(p) for p in paths]
            md += [f"![{p.stem}]({p.name})" for p in paths] + [""]
    if van is not None:
        doc["van"] = _jsonable(asdict(van))
        md += [f"## VAN: {van.preset}", "", f"**{van.message}**", "", _md_table(van_rows(van)), "",
               "Piezo: P-842.10 (15 µm at 100 V, 300 N blocking, 1.5 µF: the capacitance Eq. 3.7 needs for the "
               "seed's 0.3 W at 20 V, 500 Hz). Stress linear in load from Table 3.2's 47 MPa at 77 N. Our S_e "
               "uses the unrounded Marin factors (Table 3.2's 195.4 MPa uses p_a = 0.86, p_b = 1.08).", ""]
    files["markdown"] = str(out / "design.md")
    files["json"] = str(out / "design.json")
    outputs.write_text(out / "design.md", "\n".join(md))
    outputs.write_text(out / "design.json", json.dumps(doc, indent=1, allow_nan=False))
    return files


# ============================================================================= CLI
def add_design_arguments(parser):
    """Arguments of ``nanostage design`` (wire with ``set_defaults(func=main_design)``)."""
    parser.add_argument("preset", help="preset name or YAML path (FI: bearings on joints; VAN: with dither)")
    parser.add_argument("--rms", type=positive_float, default=None, metavar="NM",
                        help="required RMS in-position error [nm] (FI sweep)")
    parser.add_argument("--van", action="store_true",
                        help="VAN check (piezo power, flexure fatigue); default: automatic when the preset dithers")
    parser.add_argument("--out", default=None, help="output folder (default out/design/PRESET)")
    parser.add_argument("--json", action="store_true", help="print design.json instead of the table")
    parser.add_argument("--grid", choices=sorted(GRIDS), default="default", help="k_fi x c_fi grid")
    parser.add_argument("--step-um", type=nonzero_float, default=STEP * 1e6, help="point-to-point step [µm]")
    parser.add_argument("--trials", type=positive_int, default=N_TRIALS, help="trials per grid point")
    parser.add_argument("--dwell", type=positive_float, default=DWELL, help="settling portion after each move [s]")
    parser.add_argument("--vpp", type=nonnegative_float, default=None,
                        help="VAN piezo voltage p-p [V] (default: from the dither force)")
    parser.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                        help="preset override, e.g. stage.drive.noise_current_rms=7e-4 (YAML value; repeatable)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    outputs.add_overwrite_argument(parser)
    add_executor_arguments(parser, "sweep", default_workers(), "default: one per core; 1 = this process")
    return parser


def _overridden(p: Preset, sets) -> Preset:
    """Apply ``PATH=VALUE`` overrides (VALUE parsed as YAML) to a preset."""
    over = {}
    for item in sets:
        path, eq, value = item.partition("=")
        if not eq or not path:
            raise DesignError(f"--set {item!r}: expected PATH=VALUE")
        over[path.strip()] = load_yaml(value, f"--set {item!r}: value")     # ConfigError if not YAML
    return with_overrides(p, over, "nanostage design --set") if over else p   # ConfigError names a bad path or value


def main_design(args) -> int:
    """Run ``nanostage design``: 0 = a design meets the requirement / VAN passes, 1 = none does /
    VAN fails; bad input raises :class:`DesignError` / ``ConfigError`` (the CLI's message, exit 2)."""
    import sys
    p = _overridden(_preset(args.preset), args.set)
    van_mode = args.van or p.dither is not None
    if not van_mode:
        if args.rms is None:
            raise DesignError("give the required RMS in-position error: --rms NM")
        lumped_stage(p)
    out = outputs.prepare_folder(args.out or f"out/design/{p.name}", args.overwrite,
                                 files=("design.md", "design.json"), option="--out")          # refused before the sweep
    progress = None if args.json else (lambda s: print(s, file=sys.stderr))
    advice = van = None
    if van_mode:
        if args.rms is not None:
            print("nanostage design: --rms is not used by the VAN check", file=sys.stderr)
        van = check_van(p, v_pp=args.vpp)
    else:
        advice = advise_isolator(p, args.rms * 1e-9, step=args.step_um * 1e-6, grid=args.grid,
                                 n_trials=args.trials, dwell=args.dwell, progress=progress,
                                 workers=args.workers, cluster=args.cluster)
    files = write_report(out, advice, van, plots=not args.no_plots, overrides=args.set)
    if args.json:
        print(Path(files["json"]).read_text())
    else:
        if advice is not None:
            print(_text_table(advice_table(advice)))
            print(advice.message)
        if van is not None:
            print(_text_table(van_rows(van)))
            print(van.message)
        print(f"report: {files['markdown']}")
    ok = (advice is None or advice.ok) and (van is None or van.passed)
    return 0 if ok else 1
