"""Plant simulator: lumped-mass stage with friction, isolators, drive, sensors.

:func:`build_plant` compiles a validated :class:`stage_sim.config.Stage` into a
:class:`PlantModel` (plain arrays), and :func:`plant_step` advances one trial by
one control period. The same compiled step is called by the batch engine
(``experiment_runner.batch``) and by the ROS plant node, so both produce the same
trajectories.

Integration scheme (per control period ``dt``, ``n_sub`` sub-steps of ``h``):

* the linear part (masses, joints, structural modes, viscous friction) is advanced
  with its exact zero-order-hold discretisation ``z+ = Phi z + Gam f``;
* friction, lock and impact forces are held over a sub-step and then updated
  exactly in the displacement domain (Dahl, GMS) or at constant velocity (LuGre);
* Coulomb elements are solved implicitly per sub-step (stick if the force needed
  to stop is within the static limit), so there is no chattering at rest;
* optional force variations of each friction element (position-dependent and
  direction-dependent level, direction-dependent viscous part: ``config._FrictionVariation``)
  scale its held force; optional table forces (``stage.force_offset``, ``force_ripple``,
  ``periodic_force``) and an external force input (:func:`plant_step_ext`) act on the table,
  held over a sub-step; all are skipped when off, so results are bit-identical without them;
* ``n_sub`` is chosen so the stiffest mode of the configuration -- including the
  tangent stiffness of pre-motion friction and the SAI lock -- satisfies
  ``omega_max * h <= max_omega_h``.

Coordinates: DOF 0 is the table (plus any rigidly attached bearing), then each
bearing on a joint, then structural-mode masses. Rotary stages use the same
equations with rad, N·m and kg·m².
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.linalg
from numba import njit

from .config import CoulombFriction, DahlFriction, GmsFriction, LugreFriction, Stage
from .friction import dahl_tangent, dahl_update, gms_block, gms_block_tangent, initial_stiffness, lugre_update, stribeck

# friction element kinds
DAHL, GMS, LUGRE, COULOMB = 1, 2, 3, 4
# per-trial scalar state slots
P_THERMAL, P_NOISE, P_RC, P_LOCKED, P_ANCHOR, P_PULSE, P_ARM_TIMER, P_DELAY_IDX, P_FPREV = range(9)
N_PSTATE = 9
# status codes returned by plant_step
OK, DIVERGED, OUT_OF_TRAVEL = 0, 1, 2
STATUS_TEXT = {OK: "ok", DIVERGED: "state diverged (non-finite or beyond 1e3 x travel)",
               OUT_OF_TRAVEL: "table left the travel range"}


class SimulationError(RuntimeError):
    """A simulation stopped: the message names the trial, the time and the reason."""


class PlantModel(NamedTuple):
    """Compiled plant (SI units). Built by :func:`build_plant`; read-only."""
    n: int                 # number of DOFs
    n_sub: int             # sub-steps per control period
    h: float               # sub-step [s]
    dt: float              # control period [s]
    phi: np.ndarray        # (2n, 2n) exact state transition over h
    gam: np.ndarray        # (2n, n) exact ZOH force input over h
    fr_kind: np.ndarray    # (nf,) friction element kind
    fr_dof: np.ndarray     # (nf,) DOF the element acts on
    fr_par: np.ndarray     # (nf, 6) kind-specific parameters
    fr_k: np.ndarray       # (nf, nmax) GMS block stiffnesses
    fr_alpha: np.ndarray   # (nf, nmax) GMS block fractions
    fr_n: np.ndarray       # (nf,) GMS block count
    fr_noise: np.ndarray   # (nf,) random force per control sample, RMS [N]
    dither_dof: np.ndarray  # (2,) DOF driven by piezo 0 / 1, -1 if none
    kf_ratio: float        # true / nominal force constant
    peak: float            # peak force [N]
    cont: float            # continuous force [N]
    th_alpha: float        # dt / thermal time constant
    noise_std: float       # drive noise force RMS [N]
    noise_a: float         # noise low-pass coefficient (1 = white)
    noise_gain: float      # keeps the filtered noise RMS equal to noise_std
    delay: int             # drive delay [samples]
    q_table: float         # encoder resolution [m]
    bear_dof: int          # first bearing on a joint (0 = table if none)
    bsens_dof: int         # DOF seen by the bearing sensor, -1 if none
    q_bearing: float       # bearing sensor resolution [m]
    travel_min: float
    travel_max: float
    x_limit: float         # divergence bound on any position [m]
    sai_dof: int           # bearing DOF locked by the SAI, -1 if none
    k_lock: float
    c_lock: float
    cap_lock: float
    rc_a: float            # RC filter coefficient per sub-step (1 = no filter)
    arm_steps: int         # armature travel time [sub-steps]
    pulse_force: float     # impact force during the pulse [N]
    pulse_steps: int       # impact duration [sub-steps]
    fr_var: np.ndarray     # (nf, 6) force variation: on, f_c_difference/(2 f_c), viscous_difference/2,
                           #   position_center [m], f_c_gradient/f_c [1/m], f_c_curvature/f_c [1/m²]
    f_offset: float        # constant table force [N]
    ripple: np.ndarray     # (nr, 3) position-periodic table force: amplitude [N], 2 pi/period [rad/m], phase
    periodic: np.ndarray   # (np, 3) fixed-frequency table force: amplitude [N], 2 pi f [rad/s], phase
    table_force: bool      # any of f_offset, ripple, periodic
    delay_frac: float      # fractional drive delay [control periods] (0 = whole samples only)
    g_prev: np.ndarray     # (n_sub, 2n) exact response of each sub-step to (previous - present) drive force


def _friction_params(fr):
    """(kind, par[6], k_blocks, alpha_blocks, tangent stiffness) of a friction config."""
    par = np.zeros(6)
    k = alpha = np.zeros(0)
    if isinstance(fr, DahlFriction):
        par[:3] = fr.k_sigma, fr.f_c, fr.shape
        return DAHL, par, k, alpha, initial_stiffness(fr)
    if isinstance(fr, GmsFriction):
        par[0] = fr.f_c
        k, alpha = np.array(fr.k), np.array(fr.alpha)
        return GMS, par, k, alpha, initial_stiffness(fr)
    if isinstance(fr, LugreFriction):
        par[:6] = fr.sigma0, fr.sigma1, fr.f_c, fr.f_s, fr.v_s, fr.exponent
        return LUGRE, par, k, alpha, initial_stiffness(fr)
    if isinstance(fr, CoulombFriction):
        par[:2] = fr.f_c, fr.f_c if fr.f_s is None else fr.f_s
        return COULOMB, par, k, alpha, initial_stiffness(fr)
    raise TypeError(f"unknown friction config {fr!r}")


def _variation(fr) -> np.ndarray:
    """Row of :attr:`PlantModel.fr_var` for a friction config (all zero = no variation)."""
    var = np.zeros(6)
    if fr.f_c_difference or fr.viscous_difference or fr.f_c_gradient or fr.f_c_curvature:
        fc = fr.f_c if fr.f_c > 0 else 1.0    # f_c = 0 only without gradient/curvature (validated)
        var[:] = (1.0, fr.f_c_difference / (2.0 * fc), 0.5 * fr.viscous_difference, fr.position_center,
                  fr.f_c_gradient / fc, fr.f_c_curvature / fc)
    return var


def _exact_zoh(a, b, h):
    """Van Loan: exact ZOH discretisation of z' = a z + b f over h (memoised: model fits
    rebuild plants whose linear part did not change)."""
    phi, gam = _exact_zoh_cached(a.tobytes(), b.tobytes(), b.shape, float(h))
    return phi.copy(), gam.copy()


@lru_cache(maxsize=512)
def _exact_zoh_cached(a_bytes, b_bytes, shape, h):
    nz, nu = shape
    a = np.frombuffer(a_bytes).reshape(nz, nz)
    b = np.frombuffer(b_bytes).reshape(nz, nu)
    big = np.zeros((nz + nu, nz + nu))
    big[:nz, :nz] = a * h
    big[:nz, nz:] = b * h
    e = scipy.linalg.expm(big)
    return e[:nz, :nz].copy(), e[:nz, nz:].copy()


def _delayed_zoh(a, b, h, n_sub, frac):
    """(n_sub, 2n): exact delayed zero-order hold of the drive force. Over a control period the
    force is the previous sample's until ``frac`` of the period, then the present one's; sub-step
    ``i`` propagates with the present force (``phi z + gam f``) plus row ``i`` times (previous -
    present): ``gam[:, 0]`` for a sub-step wholly before the switch, ``phi(h - t_s) gam(t_s)[:, 0]``
    for the one the switch splits at ``t_s``, zero after it."""
    out = np.zeros((n_sub, a.shape[0]))
    if frac <= 0.0:
        return out
    ts = frac * n_sub
    whole = int(math.floor(ts))
    phi_h, gam_h = _exact_zoh(a, b, h)
    out[:whole] = gam_h[:, 0]
    rest = (ts - whole) * h
    if whole < n_sub and rest > 0.0:
        gam_a = _exact_zoh(a, b, rest)[1]
        phi_b = _exact_zoh(a, b, h - rest)[0]
        out[whole] = phi_b @ gam_a[:, 0]
    return out


def build_plant(stage: Stage, rate: float = 10_000.0, max_omega_h: float = 0.25,
                max_substeps: int = 200) -> PlantModel:
    """Compile a stage configuration into a :class:`PlantModel`.

    Parameters
    ----------
    stage : Stage
        Validated stage configuration.
    rate : float
        Control rate [Hz]; the plant advances ``1/rate`` per :func:`plant_step`.
    max_omega_h : float
        Largest allowed ``omega_max * h`` [-], which sets the number of sub-steps.
    max_substeps : int
        Refuse configurations needing more sub-steps than this.

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> pm = build_plant(load_preset("fi_stage").stage)
    >>> pm.n_sub >= 1
    True
    """
    dt = 1.0 / rate
    m_table = stage.table.mass + sum(b.mass for b in stage.bearings if b.joint is None)
    masses = [m_table]
    springs = []                     # (i, j, k, c); j = -1 for ground
    fr_list = []                     # (config, dof, noise)
    dither_dof = [-1, -1]
    bearing_dofs = []
    if stage.table_friction is not None:
        fr_list.append((stage.table_friction, 0, 0.0))
    for b in stage.bearings:
        if b.joint is None:
            dof = 0
        else:
            dof = len(masses)
            masses.append(b.mass)
            springs.append((0, dof, b.joint.stiffness, b.joint.damping))
            bearing_dofs.append(dof)
        fr_list.append((b.friction, dof, b.force_noise_rms))
        if b.dither_channel is not None:
            dither_dof[b.dither_channel] = dof
    for mode in stage.modes:
        dof = len(masses)
        ms = mode.mass_ratio * stage.table.mass
        w = 2 * math.pi * mode.frequency
        masses.append(ms)
        springs.append((0, dof, ms * w * w, 2 * mode.damping_ratio * ms * w))

    n = len(masses)
    kmat, cmat = np.zeros((n, n)), np.zeros((n, n))
    for i, j, k, c in springs:
        for mat, val in ((kmat, k), (cmat, c)):
            mat[i, i] += val
            mat[j, j] += val
            mat[i, j] -= val
            mat[j, i] -= val

    nf = len(fr_list)
    nmax = max([1] + [len(f.k) for f, _, _ in fr_list if isinstance(f, GmsFriction)])
    fr_kind = np.zeros(nf, np.int64)
    fr_dof = np.zeros(nf, np.int64)
    fr_par = np.zeros((nf, 6))
    fr_k = np.zeros((nf, nmax))
    fr_alpha = np.zeros((nf, nmax))
    fr_n = np.zeros(nf, np.int64)
    fr_noise = np.zeros(nf)
    fr_var = np.zeros((nf, 6))
    k_tangent = np.zeros((n, n))
    c_explicit = np.zeros(n)
    for e, (fr, dof, noise) in enumerate(fr_list):
        kind, par, kb, ab, kt = _friction_params(fr)
        fr_kind[e], fr_dof[e], fr_par[e], fr_noise[e] = kind, dof, par, noise
        fr_k[e, :len(kb)], fr_alpha[e, :len(ab)], fr_n[e] = kb, ab, len(kb)
        fr_var[e] = _variation(fr)
        cmat[dof, dof] += fr.viscous
        k_tangent[dof, dof] += kt * (1.0 + abs(fr_var[e, 1]))
        if kind == LUGRE:
            c_explicit[dof] += fr.sigma1

    sai_dof, k_lock, c_lock, cap, rc_a, arm_steps, pulse_force, pulse_steps = -1, 0.0, 0.0, 1.0, 1.0, 0, 0.0, 0
    sai = stage.sai
    if sai is not None:
        sai_dof = bearing_dofs[0]
        k_lock, c_lock, cap = sai.lock_stiffness, sai.lock_damping, sai.lock_capacity
        for mat, val in ((k_tangent, k_lock),):
            mat[0, 0] += val
            mat[sai_dof, sai_dof] += val
            mat[0, sai_dof] -= val
            mat[sai_dof, 0] -= val
        c_explicit[0] += c_lock
        c_explicit[sai_dof] += c_lock

    minv = np.diag(1.0 / np.array(masses))
    eig = np.linalg.eigvals(minv @ (kmat + k_tangent))
    omega_max = float(np.sqrt(np.max(np.abs(eig))))
    rate_max = float(np.max(c_explicit / np.array(masses)))  # explicit damping rate [1/s]
    n_sub = max(1, math.ceil(max(omega_max, rate_max) * dt / max_omega_h))
    if n_sub > max_substeps:
        raise ValueError(
            f"stage needs {n_sub} sub-steps per control period (stiffest mode "
            f"{omega_max / (2 * math.pi):.0f} Hz); limit is simulation.max_substeps={max_substeps}")
    h = dt / n_sub

    a = np.zeros((2 * n, 2 * n))
    a[:n, n:] = np.eye(n)
    a[n:, :n] = -minv @ kmat
    a[n:, n:] = -minv @ cmat
    b = np.zeros((2 * n, n))
    b[n:, :] = minv
    phi, gam = _exact_zoh(a, b, h)

    if sai is not None:
        rc_a = 1.0 if sai.rc_cutoff is None else 1.0 - math.exp(-2 * math.pi * sai.rc_cutoff * h)
        arm_steps = int(round(sai.switch_delay / h))
        pulse_steps = max(1, int(round(sai.impact_duration / h)))
        pulse_force = sai.impact_impulse * (1.0 - sai.cushioning) / (pulse_steps * h)

    d = stage.drive
    noise_a, noise_gain = 1.0, 1.0
    if d.noise_cutoff is not None:
        noise_a = 1.0 - math.exp(-2 * math.pi * d.noise_cutoff * dt)
        noise_gain = math.sqrt((2.0 - noise_a) / noise_a)   # unit-variance AR(1) output
    span = stage.travel.max - stage.travel.min
    bsens = -1
    if stage.bearing_sensor is not None:
        bsens = bearing_dofs[0]
    return PlantModel(
        n=n, n_sub=n_sub, h=h, dt=dt, phi=phi, gam=gam,
        fr_kind=fr_kind, fr_dof=fr_dof, fr_par=fr_par, fr_k=fr_k, fr_alpha=fr_alpha,
        fr_n=fr_n, fr_noise=fr_noise, dither_dof=np.array(dither_dof, np.int64),
        kf_ratio=d.force_constant_ratio, peak=d.peak_force, cont=d.continuous_force,
        th_alpha=dt / d.thermal_time_constant,
        noise_std=d.noise_current_rms * d.force_constant * d.force_constant_ratio,
        noise_a=noise_a, noise_gain=noise_gain, delay=d.delay_samples,
        q_table=stage.encoder.resolution, bsens_dof=bsens,
        bear_dof=bearing_dofs[0] if bearing_dofs else 0,
        q_bearing=0.0 if stage.bearing_sensor is None else stage.bearing_sensor.resolution,
        travel_min=stage.travel.min, travel_max=stage.travel.max,
        x_limit=1e3 * span + abs(stage.travel.min) + abs(stage.travel.max),
        sai_dof=sai_dof, k_lock=k_lock, c_lock=c_lock, cap_lock=cap, rc_a=rc_a,
        arm_steps=arm_steps, pulse_force=pulse_force, pulse_steps=pulse_steps,
        fr_var=fr_var, f_offset=float(stage.force_offset),
        ripple=np.array([[r.amplitude, 2 * math.pi / r.period, r.phase] for r in stage.force_ripple],
                        float).reshape(-1, 3),
        periodic=np.array([[p.amplitude, 2 * math.pi * p.frequency, p.phase] for p in stage.periodic_force],
                          float).reshape(-1, 3),
        table_force=bool(stage.force_offset != 0.0 or stage.force_ripple or stage.periodic_force),
        delay_frac=float(d.delay_fraction), g_prev=_delayed_zoh(a, b, h, n_sub, d.delay_fraction),
    )


class PlantState(NamedTuple):
    """State of a batch of trials; the trial axis is LAST (batch-inner layout)."""
    z: np.ndarray        # (2n, B) positions then velocities
    fr: np.ndarray       # (nf, nmax, B) friction states
    ps: np.ndarray       # (N_PSTATE, B) scalar states (see P_* slots)
    dbuf: np.ndarray     # (delay+1, B) drive delay line
    f: np.ndarray        # (n, B) scratch: forces
    zn: np.ndarray       # (2n, B) scratch: next state
    force: np.ndarray    # (B,) scratch: motor force


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
    return PlantState(z=z, fr=np.zeros(pm.fr_k.shape + (n_trials,)), ps=ps,
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
    motion in ``direction`` (+1: moving +, -1: moving -); see ``config._FrictionVariation``."""
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
    Coulomb elements are solved implicitly in :func:`plant_step` instead.
    """
    n = pm.n
    hh = 0.5 * pm.h
    nb = z.shape[1]
    par = pm.fr_par
    for e in range(pm.fr_kind.shape[0]):
        kind = pm.fr_kind[e]
        dof = pm.fr_dof[e]
        if kind == DAHL:
            k0, fc, shape = par[e, 0], par[e, 1], par[e, 2]
            for b in range(nb):
                v = z[n + dof, b]
                fe = fr[e, 0, b]
                kt = dahl_tangent(fe, 1.0 if v > 0.0 else -1.0, k0, fc, shape)
                if pm.fr_var[e, 0] != 0.0:
                    f[dof, b] -= _varied(pm, e, z[dof, b], v, fe + kt * v * hh)
                else:
                    f[dof, b] -= fe + kt * v * hh
        elif kind == GMS:
            fc = par[e, 0]
            for b in range(nb):
                v = z[n + dof, b]
                s = 1.0 if v > 0.0 else -1.0
                fe = 0.0
                kt = 0.0
                for i in range(pm.fr_n[e]):
                    fi = fr[e, i, b]
                    fe += fi
                    kt += gms_block_tangent(fi, s, pm.fr_k[e, i], pm.fr_alpha[e, i] * fc)
                if pm.fr_var[e, 0] != 0.0:
                    f[dof, b] -= _varied(pm, e, z[dof, b], v, fe + kt * v * hh)
                else:
                    f[dof, b] -= fe + kt * v * hh
        elif kind == LUGRE:
            s0, s1 = par[e, 0], par[e, 1]
            for b in range(nb):
                v = z[n + dof, b]
                s = 1.0 if v > 0.0 else -1.0
                g = stribeck(v, par[e, 2], par[e, 3], par[e, 4], par[e, 5])
                zb = fr[e, 0, b]
                zdot = v - s0 * abs(v) * zb / g
                kt = s0 * max(0.0, 1.0 - s0 * s * zb / g)
                if pm.fr_var[e, 0] != 0.0:
                    f[dof, b] -= _varied(pm, e, z[dof, b], v, s0 * zb + s1 * zdot + kt * v * hh)
                else:
                    f[dof, b] -= s0 * zb + s1 * zdot + kt * v * hh
        elif kind == COULOMB and pm.fr_var[e, 2] != 0.0:
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


_NO_FORCE = np.zeros(0)


@njit(cache=True)
def plant_step(pm, z, fr, ps, dbuf, f, zn, force, u_cmd, d0, d1, mode, k, seeds, meas, status):
    """Advance a batch of trials by one control period.

    :func:`plant_step_ext` without an external force (see there for the parameters).
    """
    plant_step_ext(pm, z, fr, ps, dbuf, f, zn, force, u_cmd, _NO_FORCE, d0, d1, mode, k, seeds, meas, status)


@njit(cache=True)
def plant_step_ext(pm, z, fr, ps, dbuf, f, zn, force, u_cmd, f_ext, d0, d1, mode, k, seeds, meas, status):
    """Advance a batch of trials by one control period, with an external table force.

    Parameters
    ----------
    pm : PlantModel
    z, fr, ps, dbuf, f, zn, force : ndarray
        The fields of a :class:`PlantState` (trial axis last), updated in place.
    u_cmd : ndarray, shape (B,)
        Servo force command [N] (drive input, scaled by the nominal force constant).
    f_ext : ndarray, shape (B,) or (0,)
        External force on the table [N], held over the period, not through the drive
        (delay, limits, force constant, noise); empty = none. Used by the model
        diagnosis (force observer); the closed loop passes none.
    d0, d1 : ndarray, shape (B,)
        Piezo dither forces [N]: ``+d0`` on the channel-0 bearing, ``-d1`` on the
        channel-1 bearing (Eq. 3.2).
    mode : ndarray, shape (B,)
        SAI solenoid command: 1 compliant (lock released), 0 stiff.
    k : int
        Control sample index (selects the noise samples).
    seeds : ndarray of int64, shape (B,)
        Trial seeds.
    meas : ndarray, shape (2, B)
        Out: quantized table position and bearing-sensor position [m].
    status : ndarray of int64, shape (B,)
        Out: ``OK``, ``DIVERGED`` or ``OUT_OF_TRAVEL`` (a nonzero status is kept).
    """
    n = pm.n
    nz = 2 * n
    nb = u_cmd.shape[0]
    # ---- drive: delay, peak and thermal (I²t) limits, force-constant error, noise
    for b in range(nb):
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
    nf = pm.fr_kind.shape[0]
    j0, j1 = pm.dither_dof[0], pm.dither_dof[1]
    ext = f_ext.shape[0] > 0

    for sub in range(pm.n_sub):
        t_sub = k * pm.dt + (sub + 0.5) * pm.h
        for b in range(nb):
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
        _friction_forces(pm, z, fr, f, k, seeds)
        if pm.sai_dof >= 0:
            _sai_forces(pm, z, ps, f, mode)
        # ---- exact linear propagation  zn = phi z + gam f  (same summation order in
        # both branches, so a trial's result is bit-identical for any batch size)
        if nb < 8:
            for b in range(nb):
                for r in range(nz):
                    acc = 0.0
                    for c in range(nz):
                        a = pm.phi[r, c]
                        if a != 0.0:
                            acc += a * z[c, b]
                    for c in range(n):
                        a = pm.gam[r, c]
                        if a != 0.0:
                            acc += a * f[c, b]
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
        # ---- fractional drive delay: the previous sample's force over the first part of the period
        if pm.delay_frac > 0.0:
            for b in range(nb):
                df = ps[P_FPREV, b] - force[b]
                for r in range(nz):
                    zn[r, b] += pm.g_prev[sub, r] * df
        # ---- Coulomb elements: implicit stick/slip
        for e in range(nf):
            if pm.fr_kind[e] == COULOMB:
                dof = pm.fr_dof[e]
                g = pm.gam[n + dof, dof]
                for b in range(nb):
                    a = zn[n + dof, b]
                    f_stop = a / g
                    lim = pm.fr_par[e, 1] if z[n + dof, b] == 0.0 else pm.fr_par[e, 0]
                    sc = 1.0
                    if pm.fr_var[e, 0] != 0.0:
                        sc = _var_scale(pm, e, z[dof, b], 1.0 if a > 0.0 else -1.0)
                        lim *= sc
                    stick = abs(f_stop) <= lim
                    fc = f_stop if stick else pm.fr_par[e, 0] * sc * (1.0 if a > 0.0 else -1.0)
                    for r in range(nz):
                        zn[r, b] -= pm.gam[r, dof] * fc
                    if stick:
                        zn[n + dof, b] = 0.0
        # ---- friction states, exactly in the displacement domain
        for e in range(nf):
            kind = pm.fr_kind[e]
            dof = pm.fr_dof[e]
            if kind == DAHL:
                k0, fc, shape = pm.fr_par[e, 0], pm.fr_par[e, 1], pm.fr_par[e, 2]
                for b in range(nb):
                    fr[e, 0, b] = dahl_update(fr[e, 0, b], zn[dof, b] - z[dof, b], k0, fc, shape)
            elif kind == GMS:
                fc = pm.fr_par[e, 0]
                for b in range(nb):
                    dx = zn[dof, b] - z[dof, b]
                    for i in range(pm.fr_n[e]):
                        fr[e, i, b] = gms_block(fr[e, i, b], dx, pm.fr_k[e, i], pm.fr_alpha[e, i] * fc)
            elif kind == LUGRE:
                p = pm.fr_par
                for b in range(nb):
                    zb, _ = lugre_update(fr[e, 0, b], zn[dof, b] - z[dof, b], pm.h, p[e, 0],
                                         p[e, 1], p[e, 2], p[e, 3], p[e, 4], p[e, 5])
                    fr[e, 0, b] = zb
        for b in range(nb):
            for r in range(nz):
                z[r, b] = zn[r, b]

    if pm.delay_frac > 0.0:
        for b in range(nb):
            ps[P_FPREV, b] = force[b]
    for b in range(nb):
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


class PlantSim:
    """Python-side stepper over :func:`plant_step` (used by the ROS plant node and tests).

    Examples
    --------
    >>> from stage_sim.config import load_preset
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
        self.meas[0] = [quantize(x, pm.q_table) for x in self.state.z[0]]
        self.meas[1] = ([quantize(x, pm.q_bearing) for x in self.state.z[pm.bsens_dof]]
                        if pm.bsens_dof >= 0 else np.nan)

    def step(self, u, d0=0.0, d1=0.0, mode=1.0, f_ext=None):
        """Apply command ``u`` [N], dither ``d0, d1`` [N] and SAI ``mode`` for one period,
        and optionally an external table force ``f_ext`` [N] (:func:`plant_step_ext`).

        Returns the measurement (2, n_trials): table and bearing-sensor positions [m].
        Raises :class:`SimulationError` if a trial diverged or left the travel.
        """
        b = self._zeros.shape[0]
        u, d0, d1, mode = [np.broadcast_to(np.asarray(v, float), (b,)).copy() for v in (u, d0, d1, mode)]
        if f_ext is None:
            plant_step(self.pm, *self.state, u, d0, d1, mode, self.k, self.seeds, self.meas, self.status)
        else:
            fe = np.broadcast_to(np.asarray(f_ext, float), (b,)).copy()
            plant_step_ext(self.pm, *self.state, u, fe, d0, d1, mode, self.k, self.seeds, self.meas, self.status)
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
