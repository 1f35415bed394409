"""Plant simulator: lumped-mass stage with friction, isolators, drive, sensors.

:func:`stage_sim.plant_model.build_plant` compiles a validated
:class:`stage_sim.config.Stage` into a :class:`PlantModel` (plain arrays), and :func:`plant_step` advances a batch of trials
(:class:`PlantState`, trial axis last) under :class:`PlantInputs` by one control period. The
same compiled step is called by the batch engine (``experiment_runner.core.batch``), the ROS plant
node (a batch of one) and :func:`run_open_loop` (the open-loop driver of the diagnosis, the FRF
campaign and the paper's Appendix B), so all produce the same trajectories.

Integration scheme (per control period ``dt``, ``n_sub`` sub-steps of ``h``):

* the linear part (masses, joints, structural modes, viscous friction) is advanced
  with its exact zero-order-hold discretisation ``z+ = Phi z + Gam f``;
* friction, lock and impact forces are held over a sub-step and then updated
  exactly in the displacement domain (Dahl, GMS) or at constant velocity (LuGre);
* Coulomb elements are solved implicitly per sub-step (stick if the force needed
  to stop is within the static limit), so there is no chattering at rest; a regularised
  Coulomb element (``F_C tanh(v / v_reg)``) is solved in parts of the sub-step, each exact for the
  law linearised at its start (or along its chord to the balance it settles at), and its force
  acts as its mean plus the slope of its straight-line fit over the sub-step (``gam_ramp``,
  exact): its stiffness ``F_C / v_reg`` sets no sub-step;
* optional force variations of each friction element (position-dependent and
  direction-dependent level, direction-dependent viscous part: ``stage_sim.friction.FrictionVariation``)
  scale its held force; optional table forces (``stage.force_offset``, ``force_ripple``,
  ``periodic_force``) and an external force input (``PlantInputs.f_ext``) act on the table,
  held over a sub-step; all are skipped when off, so results are bit-identical without them;
* ``n_sub`` is chosen so the stiffest mode of the configuration -- including the
  tangent stiffness of pre-motion friction and the SAI lock -- satisfies
  ``omega_max * h <= max_omega_h``.

The per-sample kernels (:func:`plant_step`, :func:`run_open_loop`) allocate nothing and are
compiled without numba's runtime (``_nrt=False``), as are the loops that inline them (the batch
engine's chunk loop, the diagnosis' observer): with the runtime, each inlined call that takes
the model tuple increfs and decrefs its ~25 arrays (~70 ns per call, atomic operations the
threads contend on). Results are identical either way.

Coordinates: DOF 0 is the table (plus any rigidly attached bearing), then each
bearing on a joint, then structural-mode masses. Rotary stages use the same
equations with rad, N·m and kg·m².
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from . import friction
from .plant_model import PlantModel

# per-trial scalar state slots
P_THERMAL, P_NOISE, P_RC, P_LOCKED, P_ANCHOR, P_PULSE, P_ARM_TIMER, P_DELAY_IDX, P_FPREV = range(9)
N_PSTATE = 9
# status codes returned by plant_step
OK, DIVERGED, OUT_OF_TRAVEL = 0, 1, 2
STATUS_TEXT = {OK: "ok", DIVERGED: "state diverged (non-finite or beyond 1e3 x travel)",
               OUT_OF_TRAVEL: "table left the travel range"}


class SimulationError(RuntimeError):
    """A simulation stopped: the message names the trial, the time and the reason."""


class PlantState(NamedTuple):
    """State of a batch of trials; the trial axis is LAST (batch-inner layout).

    Passed whole to the compiled code (numba types a NamedTuple of arrays); a chunk of a
    chunked state (leading chunk axis on every field) is :func:`state_chunk`.
    """
    z: np.ndarray        # (2n, B) positions then velocities
    fr: np.ndarray       # (nf, n_frs, B) friction states
    ps: np.ndarray       # (N_PSTATE, B) scalar states (see P_* slots)
    dbuf: np.ndarray     # (delay+1, B) drive delay line
    f: np.ndarray        # (n, B) scratch: forces
    zn: np.ndarray       # (2n, B) scratch: next state
    force: np.ndarray    # (B,) scratch: motor force


class PlantInputs(NamedTuple):
    """What drives the plant over one control period, each (B,) (trial axis last); or, for
    :func:`run_open_loop`, each (T, B) over T periods."""
    u: np.ndarray        # servo force command [N] (drive input, scaled by the nominal force constant)
    d0: np.ndarray       # piezo dither force, +d0 on the channel-0 bearing [N] (Eq. 3.2)
    d1: np.ndarray       # piezo dither force, -d1 on the channel-1 bearing [N]
    mode: np.ndarray     # SAI solenoid command: 1 compliant (lock released), 0 stiff
    f_ext: np.ndarray    # external force on the table [N], not through the drive (delay, limits,
                         #   force constant, noise); EMPTY (0,) = none (the closed loop passes none)


def plant_inputs(n_trials: int, f_ext: bool = False, T: int | None = None) -> PlantInputs:
    """Zero inputs (isolator compliant) for ``n_trials``, per period or (``T``) over ``T`` periods;
    ``f_ext=False``: no external force (an empty ``f_ext``)."""
    shape = (n_trials,) if T is None else (T, n_trials)
    return PlantInputs(u=np.zeros(shape), d0=np.zeros(shape), d1=np.zeros(shape), mode=np.ones(shape),
                       f_ext=np.zeros(shape if f_ext else (0,) * len(shape)))


@njit(cache=True, inline="always")
def state_chunk(st, c):
    """Chunk ``c`` of a chunked :class:`PlantState` (every field with a leading chunk axis)."""
    return PlantState(st.z[c], st.fr[c], st.ps[c], st.dbuf[c], st.f[c], st.zn[c], st.force[c])


def chunk_state(st: PlantState, n_chunks: int) -> PlantState:
    """A state over ``n_chunks * size`` trials as ``n_chunks`` chunks of ``size`` (trial axis
    last, chunk axis first), contiguous, for :func:`state_chunk`."""
    size = st.z.shape[-1] // n_chunks
    return PlantState(*[np.ascontiguousarray(np.moveaxis(a.reshape(a.shape[:-1] + (n_chunks, size)), -2, 0))
                        for a in st])


def init_plant_state(pm: PlantModel, n_trials: int, x0=0.0, sai_mode: float = 1.0) -> PlantState:
    """Relaxed state: every body at rest at ``x0`` [m] (scalar or per trial), friction zero.

    ``sai_mode`` is the initial isolator mode (1 compliant, 0 stiff and locked).
    """
    n = pm.n
    z = np.zeros((2 * n, n_trials))
    z[:n, :] = np.broadcast_to(np.asarray(x0, float), (n_trials,))[None, :]
    ps = np.zeros((N_PSTATE, n_trials))
    ps[P_RC] = sai_mode
    if pm.sai_dof >= 0 and sai_mode < 0.5:
        ps[P_LOCKED] = 1.0
    return PlantState(z=z, fr=np.zeros((pm.fr_kind.shape[0], pm.n_frs, n_trials)), ps=ps,
                      dbuf=np.zeros((pm.delay + 1, n_trials)), f=np.zeros((n, n_trials)),
                      zn=np.zeros((2 * n, n_trials)), force=np.zeros(n_trials))


@njit(cache=True, inline="always")
def _splitmix(x):
    x = x + np.uint64(0x9E3779B97F4A7C15)
    x = (x ^ (x >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    x = (x ^ (x >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


@njit(cache=True, inline="always")
def gauss(seed, k, channel):
    """Standard normal sample, a pure function of (seed, sample index, channel).

    Counter-based, so a trial's noise does not depend on batch size or execution
    order: the ROS graph and the batch engine draw identical sequences.
    """
    x = _splitmix(np.uint64(seed) * np.uint64(0x100000001B3) + np.uint64(k) * np.uint64(64)
                  + np.uint64(channel))
    y = _splitmix(x)
    u1 = ((x >> np.uint64(11)) + np.uint64(1)) * (1.0 / 9007199254740993.0)
    u2 = (y >> np.uint64(11)) * (1.0 / 9007199254740992.0)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@njit(cache=True, inline="always")
def quantize(x, q):
    """Round ``x`` to the sensor resolution ``q`` (``q = 0``: ideal sensor)."""
    if q > 0.0:
        return q * math.floor(x / q + 0.5)
    return x


@njit(cache=True, inline="always")
def _var_scale(pm, e, x, direction):
    """Force scale of friction element ``e`` at position ``x`` [m] for a force resisting
    motion in ``direction`` (+1: moving +, -1: moving -); see ``stage_sim.friction.FrictionVariation``."""
    var = pm.fr_var
    d = x - var[e, 3]
    s = 1.0 + var[e, 4] * d + var[e, 5] * d * d
    if s < 0.0:
        s = 0.0
    return s * (1.0 + var[e, 1] * direction)


@njit(cache=True, inline="always")
def _varied(pm, e, x, v, fh):
    """Held friction force ``fh`` of element ``e`` with its variation (position, direction)."""
    return fh * _var_scale(pm, e, x, 1.0 if fh > 0.0 else -1.0) + pm.fr_var[e, 2] * abs(v)


@njit(cache=True, inline="always")
def _table_force(pm, x, t):
    """Offset, position-periodic ripple and fixed-frequency forces on the table [N]."""
    out = pm.f_offset
    for i in range(pm.ripple.shape[0]):
        out += pm.ripple[i, 0] * math.sin(pm.ripple[i, 1] * x + pm.ripple[i, 2])
    for i in range(pm.periodic.shape[0]):
        out += pm.periodic[i, 0] * math.sin(pm.periodic[i, 1] * t + pm.periodic[i, 2])
    return out


@njit(cache=True, inline="always")
def _friction_forces(pm, z, fr, f, k, seeds):
    """Subtract every friction element's held force from ``f`` (all trials).

    The held value is the model's force plus its tangent stiffness times half the
    predicted sub-step displacement ``v h / 2`` (a mid-point force): a plainly held
    spring force lags by half a sub-step and pumps energy into lightly damped
    pre-motion resonances; the mid-point force keeps the scheme area-preserving.
    Implicit laws (Coulomb) are solved in :func:`plant_step` instead.
    """
    n = pm.n
    hh = 0.5 * pm.h
    nb = z.shape[1]
    for e in range(pm.fr_kind.shape[0]):
        kind = pm.fr_kind[e]
        dof = pm.fr_dof[e]
        p = pm.fr_par[e]
        s = fr[e]
        varied = pm.fr_var[e, 0] != 0.0
        if not pm.fr_implicit[e]:
            for b in range(nb):
                v = z[n + dof, b]
                fe, kt = friction.held(kind, p, s, b, v)
                if varied:
                    f[dof, b] -= _varied(pm, e, z[dof, b], v, fe + kt * v * hh)
                else:
                    f[dof, b] -= fe + kt * v * hh
        elif pm.fr_var[e, 2] != 0.0:
            for b in range(nb):            # direction-dependent viscous part (the rest is implicit)
                f[dof, b] -= pm.fr_var[e, 2] * abs(z[n + dof, b])
        if pm.fr_noise[e] > 0.0:
            for b in range(nb):
                f[dof, b] -= pm.fr_noise[e] * gauss(seeds[b], k, 1 + e)


@njit(cache=True, inline="always")
def _sai_forces(pm, z, ps, f, mode):
    """SAI: RC-filtered solenoid, armature travel, friction lock and impact pulse."""
    n = pm.n
    j = pm.sai_dof
    for b in range(z.shape[1]):
        ps[P_RC, b] += pm.rc_a * (mode[b] - ps[P_RC, b])
        if ps[P_LOCKED, b] > 0.5 and ps[P_RC, b] > 0.5:
            ps[P_LOCKED, b] = 0.0                     # release: the stored deflection acts
            ps[P_ARM_TIMER, b] = 0.0
        elif ps[P_LOCKED, b] < 0.5 and ps[P_RC, b] < 0.5:
            ps[P_ARM_TIMER, b] += 1.0
            if ps[P_ARM_TIMER, b] > pm.arm_steps:
                ps[P_LOCKED, b] = 1.0                 # lock: keep the present deflection
                ps[P_ANCHOR, b] = z[0, b] - z[j, b]
                ps[P_PULSE, b] = pm.pulse_steps
        if ps[P_LOCKED, b] > 0.5:
            spring = pm.k_lock * (z[0, b] - z[j, b] - ps[P_ANCHOR, b])
            dv = z[n, b] - z[n + j, b]
            if abs(spring) > pm.cap_lock:             # the lock slips
                sgn = 1.0 if spring > 0.0 else -1.0
                ps[P_ANCHOR, b] = z[0, b] - z[j, b] - sgn * pm.cap_lock / pm.k_lock
                fl = sgn * pm.cap_lock + pm.c_lock * dv
            else:
                fl = spring + pm.c_lock * dv + pm.k_lock * dv * (0.5 * pm.h)
            f[0, b] -= fl
            f[j, b] += fl
        if ps[P_PULSE, b] > 0.0:
            f[0, b] += pm.pulse_force
            f[j, b] -= pm.pulse_force
            ps[P_PULSE, b] -= 1.0


@njit(cache=True, inline="always")
def _drive_force(pm, ps, dbuf, u_cmd, k, seeds, force):
    """Drive force of each trial over the control period into ``force`` [N]: the command after the
    whole-sample delay, the peak and thermal (I²t) limits, the force-constant error and the noise."""
    for b in range(u_cmd.shape[0]):
        if pm.delay > 0:
            i = int(ps[P_DELAY_IDX, b])
            u_in = dbuf[i, b]
            dbuf[i, b] = u_cmd[b]
            ps[P_DELAY_IDX, b] = (i + 1) % pm.delay
        else:
            u_in = u_cmd[b]
        u = min(max(u_in, -pm.peak), pm.peak)
        if ps[P_THERMAL, b] > pm.cont * pm.cont:
            u = min(max(u, -pm.cont), pm.cont)
        ps[P_THERMAL, b] += pm.th_alpha * (u * u - ps[P_THERMAL, b])
        force[b] = pm.kf_ratio * u
        if pm.noise_std > 0.0:
            w = gauss(seeds[b], k, 0)
            if pm.noise_a < 1.0:
                ps[P_NOISE, b] += pm.noise_a * (w * pm.noise_gain - ps[P_NOISE, b])
                w = ps[P_NOISE, b]
            force[b] += pm.noise_std * w


@njit(cache=True, inline="always")
def _applied_forces(pm, z, force, d0, d1, f_ext, t_sub, f):
    """Forces on every DOF other than friction and the SAI, held over the sub-step centred at
    ``t_sub`` [s], written to ``f``: drive, table and external forces on the table, piezo dither
    forces on their bearings (``f_ext`` empty: none)."""
    n = pm.n
    j0, j1 = pm.dither_dof[0], pm.dither_dof[1]
    ext = f_ext.shape[0] > 0
    for b in range(force.shape[0]):
        f[0, b] = force[b]
        if pm.table_force:
            f[0, b] += _table_force(pm, z[0, b], t_sub)
        if ext:
            f[0, b] += f_ext[b]
        for i in range(1, n):
            f[i, b] = 0.0
        if j0 >= 0:
            f[j0, b] += d0[b]
        if j1 >= 0:
            f[j1, b] -= d1[b]


@njit(cache=True, inline="always")
def _propagate(pm, z, f, zn):
    """Exact linear propagation over a sub-step, ``zn = phi z + gam f``.

    Both branches sum in the same order, so a trial's result is bit-identical for any batch size:
    the few-trial branch also adds the zero entries' products, +-0, which change no finite sum.
    """
    n = pm.n
    nz = 2 * n
    nb = z.shape[1]
    if nb < 8:
        for b in range(nb):
            for r in range(nz):
                acc = 0.0
                for c in range(nz):
                    acc += pm.phi[r, c] * z[c, b]
                for c in range(n):
                    acc += pm.gam[r, c] * f[c, b]
                zn[r, b] = acc
    else:
        for r in range(nz):
            for b in range(nb):
                zn[r, b] = 0.0
            for c in range(nz):
                a = pm.phi[r, c]
                if a != 0.0:
                    for b in range(nb):
                        zn[r, b] += a * z[c, b]
            for c in range(n):
                a = pm.gam[r, c]
                if a != 0.0:
                    for b in range(nb):
                        zn[r, b] += a * f[c, b]


@njit(cache=True, inline="always")
def _delayed_drive(pm, ps, force, sub, zn):
    """Fractional drive delay: add to ``zn`` the response of sub-step ``sub`` to the previous
    sample's force acting over the first part of the period (``pm.g_prev``)."""
    for b in range(force.shape[0]):
        df = ps[P_FPREV, b] - force[b]
        for r in range(2 * pm.n):
            zn[r, b] += pm.g_prev[sub, r] * df


@njit(cache=True, inline="always")
def _implicit_friction(pm, z, zn):
    """Implicit laws (Coulomb: stick or slip), solved from the velocity the other forces give
    ``zn``; their force (mean and slope over the sub-step) is taken off ``zn``, a stuck element's
    velocity set to zero."""
    n = pm.n
    nz = 2 * n
    for e in range(pm.fr_kind.shape[0]):
        if pm.fr_implicit[e]:
            kind = pm.fr_kind[e]
            dof = pm.fr_dof[e]
            p = pm.fr_par[e]
            g = pm.gam[n + dof, dof]
            for b in range(z.shape[1]):
                a = zn[n + dof, b]
                sc = 1.0
                if pm.fr_var[e, 0] != 0.0:
                    sc = _var_scale(pm, e, z[dof, b], 1.0 if a > 0.0 else -1.0)
                fc, stick, slope = friction.implicit(kind, p, a, g, z[n + dof, b], sc)
                for r in range(nz):
                    zn[r, b] -= pm.gam[r, dof] * fc + pm.gam_ramp[r, dof] * slope
                if stick:
                    zn[n + dof, b] = 0.0


@njit(cache=True, inline="always")
def _friction_states(pm, z, zn, fr):
    """Advance the explicit laws' states ``fr`` over the sub-step from ``z`` to ``zn``, exactly in
    the displacement domain."""
    for e in range(pm.fr_kind.shape[0]):
        if not pm.fr_implicit[e]:
            kind = pm.fr_kind[e]
            dof = pm.fr_dof[e]
            p = pm.fr_par[e]
            s = fr[e]
            for b in range(z.shape[1]):
                friction.update(kind, p, s, b, zn[dof, b] - z[dof, b], pm.h)


@njit(cache=True, inline="always")
def _measure(pm, z, meas, status):
    """Quantized table and bearing-sensor positions into ``meas``; a trial's ``status`` set to
    ``DIVERGED`` or ``OUT_OF_TRAVEL`` (a nonzero status is kept)."""
    n = pm.n
    for b in range(z.shape[1]):
        meas[0, b] = quantize(z[0, b], pm.q_table)
        meas[1, b] = quantize(z[pm.bsens_dof, b], pm.q_bearing) if pm.bsens_dof >= 0 else math.nan
        if status[b] != OK:
            continue
        # every DOF is coupled to the table through phi, so a non-finite or runaway
        # state reaches the table's position or velocity within one sub-step
        x, v = z[0, b], z[n, b]
        if not (abs(x) <= pm.x_limit and abs(v) <= 1e4 * pm.x_limit):
            status[b] = DIVERGED
        elif x < pm.travel_min or x > pm.travel_max:
            status[b] = OUT_OF_TRAVEL


@njit(cache=True, inline="always", _nrt=False)
def plant_step(pm, st, inp, k, seeds, meas, status):
    """Advance a batch of trials by one control period.

    The drive force is held over the period; each of the ``n_sub`` sub-steps holds the applied,
    explicit friction and SAI forces, propagates the linear part exactly, then solves the implicit
    laws and advances the friction states (the steps are inlined functions, so the kernel compiles
    as one loop nest).

    Parameters
    ----------
    pm : PlantModel
    st : PlantState
        The batch's state (trial axis last), updated in place.
    inp : PlantInputs
        The inputs held over the period (:class:`PlantInputs`, each (B,); ``f_ext`` may be empty).
    k : int
        Control sample index (selects the noise samples and the time of periodic forces).
    seeds : ndarray of int64, shape (B,)
        Trial seeds.
    meas : ndarray, shape (2, B)
        Out: quantized table position and bearing-sensor position [m].
    status : ndarray of int64, shape (B,)
        Out: ``OK``, ``DIVERGED`` or ``OUT_OF_TRAVEL`` (a nonzero status is kept).
    """
    z, fr, ps, dbuf, f, zn, force = st
    u_cmd, d0, d1, mode, f_ext = inp
    _drive_force(pm, ps, dbuf, u_cmd, k, seeds, force)
    for sub in range(pm.n_sub):
        _applied_forces(pm, z, force, d0, d1, f_ext, k * pm.dt + (sub + 0.5) * pm.h, f)
        _friction_forces(pm, z, fr, f, k, seeds)
        if pm.sai_dof >= 0:
            _sai_forces(pm, z, ps, f, mode)
        _propagate(pm, z, f, zn)
        if pm.delay_frac > 0.0:
            _delayed_drive(pm, ps, force, sub, zn)
        _implicit_friction(pm, z, zn)
        _friction_states(pm, z, zn, fr)
        for b in range(z.shape[1]):
            for r in range(z.shape[0]):
                z[r, b] = zn[r, b]
    if pm.delay_frac > 0.0:
        for b in range(force.shape[0]):
            ps[P_FPREV, b] = force[b]
    _measure(pm, z, meas, status)


@njit(cache=True, nogil=True, _nrt=False)
def run_open_loop(pm, st, inp, k0, seeds, meas, status, true_position, out, out_meas):
    """The one open-loop driver: the plant under given inputs for ``T`` control periods.

    Parameters
    ----------
    pm : PlantModel
    st : PlantState
        State of the batch (B trials) at sample ``k0``; advanced in place.
    inp : PlantInputs
        Inputs over the run, each (T, B), or (1, B) for an input held over the whole run;
        ``f_ext`` also empty (0, 0) for none.
    k0 : int
        Control sample index of the first period (noise, periodic forces).
    seeds : ndarray of int64, shape (B,)
    meas : ndarray, shape (2, B)
        The measurement at ``k0`` on entry, the last one on return.
    status : ndarray of int64, shape (B,)
        Plant status, kept once nonzero (see :func:`plant_step`).
    true_position : bool
        Record the true table position (else the measured one, as a servo would see it).
    out : ndarray, shape (T, B)
        Written: the table position at the start of each period, before its inputs act.
    out_meas : ndarray, shape (T, B) or (0, 0)
        Also written, unless empty: the measured position at the start of each period.
    """
    T = out.shape[0]
    if T == 0:
        return
    none = out[0, :0]           # an empty row (compiled without the runtime: nothing allocated)
    ext = inp.f_ext.shape[0] > 0
    both = out_meas.shape[0] > 0
    z = st.z
    for j in range(T):
        for b in range(out.shape[1]):
            out[j, b] = z[0, b] if true_position else meas[0, b]
            if both:
                out_meas[j, b] = meas[0, b]
        plant_step(pm, st, PlantInputs(_row(inp.u, j), _row(inp.d0, j), _row(inp.d1, j), _row(inp.mode, j),
                                       _row(inp.f_ext, j) if ext else none), k0 + j, seeds, meas, status)


@njit(cache=True, inline="always")
def _row(a, j):
    """Row ``j`` of a (T, B) input, or its only row when it is held (1, B)."""
    return a[j] if a.shape[0] > 1 else a[0]


class PlantSim:
    """Python-side stepper over :func:`plant_step` (used by the ROS plant node and tests).

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> from stage_sim.plant_model import build_plant
    >>> sim = PlantSim(build_plant(load_preset("als130h").stage))
    >>> y = sim.step(0.5)          # 0.5 N for one control period
    >>> float(y[0, 0]) > 0.0
    True
    """

    def __init__(self, pm: PlantModel, n_trials: int = 1, x0=0.0, sai_mode: float = 1.0,
                 seeds=None):
        self.pm = pm
        self.state = init_plant_state(pm, n_trials, x0, sai_mode)
        self.seeds = np.arange(n_trials, dtype=np.int64) if seeds is None else np.asarray(seeds, np.int64)
        self.k = 0
        self.meas = np.zeros((2, n_trials))
        self.status = np.zeros(n_trials, np.int64)
        self._zeros = np.zeros(n_trials)
        self._none = np.zeros(0)
        self.meas[0] = [quantize(x, pm.q_table) for x in self.state.z[0]]
        self.meas[1] = ([quantize(x, pm.q_bearing) for x in self.state.z[pm.bsens_dof]]
                        if pm.bsens_dof >= 0 else np.nan)

    def step(self, u, d0=0.0, d1=0.0, mode=1.0, f_ext=None):
        """Apply command ``u`` [N], dither ``d0, d1`` [N] and SAI ``mode`` for one period,
        and optionally an external table force ``f_ext`` [N] (:class:`PlantInputs`).

        Returns the measurement (2, n_trials): table and bearing-sensor positions [m].
        Raises :class:`SimulationError` if a trial diverged or left the travel.
        """
        b = self._zeros.shape[0]
        u, d0, d1, mode = [np.broadcast_to(np.asarray(v, float), (b,)).copy() for v in (u, d0, d1, mode)]
        fe = self._none if f_ext is None else np.broadcast_to(np.asarray(f_ext, float), (b,)).copy()
        plant_step(self.pm, self.state, PlantInputs(u, d0, d1, mode, fe), self.k, self.seeds, self.meas,
                   self.status)
        self.k += 1
        if self.status.any():
            i = int(np.flatnonzero(self.status)[0])
            raise SimulationError(f"trial {i} stopped at t = {self.k * self.pm.dt:.6f} s: "
                                  f"{STATUS_TEXT[int(self.status[i])]}")
        return self.meas

    @property
    def positions(self):
        """True positions of every DOF, shape (n, n_trials) [m]."""
        return self.state.z[:self.pm.n]

    @property
    def velocities(self):
        """True velocities of every DOF, shape (n, n_trials) [m/s]."""
        return self.state.z[self.pm.n:]
