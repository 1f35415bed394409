"""Plant simulator: lumped-mass stage with friction, isolators, drive, sensors.

:func:`build_plant` compiles a validated :class:`stage_sim.config.Stage` into a
:class:`PlantModel` (plain arrays), and :func:`plant_step` advances a batch of trials
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
  law linearised at its start, and its force acts as its mean plus the slope of its straight-line
  fit over the sub-step (``gam_ramp``, exact): its stiffness ``F_C / v_reg`` sets no sub-step;
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
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.linalg
from numba import njit

from . import friction
from .config import Stage

# per-trial scalar state slots
P_THERMAL, P_NOISE, P_RC, P_LOCKED, P_ANCHOR, P_PULSE, P_ARM_TIMER, P_DELAY_IDX, P_FPREV = range(9)
N_PSTATE = 9
BRISTLE_H = 0.01
"""Sub-step x (explicitly held law damping / mass) at most this: LuGre's bristle damping
``sigma1 dz/dt`` is held over a sub-step, a first-order error in the sub-step (against RK4:
4.3 um over 0.45 mm of travel at 1 kHz with 4 sub-steps, 0.17 um at 0.01)."""
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
    fr_kind: np.ndarray    # (nf,) friction law id (stage_sim.friction.kind)
    fr_dof: np.ndarray     # (nf,) DOF the element acts on
    fr_par: np.ndarray     # (nf, npar) the law's parameter row (its params()), zero-padded
    fr_implicit: np.ndarray  # (nf,) bool: the law is solved implicitly per sub-step (law.IMPLICIT)
    n_frs: int             # friction state slots per element (max of the laws' n_state, >= 1)
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
    gam_ramp: np.ndarray   # (2n, n) exact response over h to a force (t/h - 1/2) (an implicit law's slope)


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


def _ramp_response(a, b, h):
    """(2n, n): exact response over ``h`` of ``z' = a z + b f`` from ``z = 0`` to the zero-mean ramp
    ``f = t / h - 1/2`` (Van Loan, the input's value and slope as states)."""
    nz, nu = b.shape
    big = np.zeros((nz + 2 * nu, nz + 2 * nu))
    big[:nz, :nz] = a * h
    big[:nz, nz:nz + nu] = b * h
    big[nz:nz + nu, nz + nu:] = np.eye(nu)
    e = scipy.linalg.expm(big)
    return e[:nz, nz + nu:] - 0.5 * e[:nz, nz:nz + nu]


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


class _Bodies(NamedTuple):
    """A stage as lumped bodies, DOF 0 the table (with its rigidly attached bearings), then each
    bearing on a joint, then each structural-mode mass (built by :func:`_bodies`)."""
    masses: list          # mass of each DOF [kg]
    springs: list         # (i, j, stiffness [N/m], damping [N·s/m]) between DOFs i and j
    elements: list        # (friction config, DOF it acts on, random force RMS [N]) per friction element
    dither_dof: list      # DOF driven by piezo 0 / 1, -1 if none
    bearing_dofs: list    # DOF of each bearing on a joint


def _bodies(stage: Stage) -> _Bodies:
    """The lumped bodies, couplings and friction elements of a stage.

    Parameters
    ----------
    stage : Stage
        Validated stage configuration.

    Returns
    -------
    _Bodies
        A bearing without a joint moves with the table (its mass added to DOF 0); the table's own
        friction, if any, is the first element, then each bearing's.

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> bodies = _bodies(load_preset("fi_stage").stage)
    >>> len(bodies.masses), bodies.bearing_dofs, [dof for _, dof, _ in bodies.elements]
    (4, [1, 2], [1, 2])
    """
    masses = [stage.table.mass + sum(b.mass for b in stage.bearings if b.joint is None)]
    springs, elements, dither_dof, bearing_dofs = [], [], [-1, -1], []
    if stage.table_friction is not None:
        elements.append((stage.table_friction, 0, 0.0))
    for b in stage.bearings:
        if b.joint is None:
            dof = 0
        else:
            dof = len(masses)
            masses.append(b.mass)
            springs.append((0, dof, b.joint.stiffness, b.joint.damping))
            bearing_dofs.append(dof)
        elements.append((b.friction, dof, b.force_noise_rms))
        if b.dither_channel is not None:
            dither_dof[b.dither_channel] = dof
    for mode in stage.modes:
        dof = len(masses)
        ms = mode.mass_ratio * stage.table.mass
        w = 2 * math.pi * mode.frequency
        masses.append(ms)
        springs.append((0, dof, ms * w * w, 2 * mode.damping_ratio * ms * w))
    return _Bodies(masses, springs, elements, dither_dof, bearing_dofs)


def _couple(mat: np.ndarray, i: int, j: int, value: float) -> None:
    """Add a coupling ``value`` (a stiffness or a damping) between DOFs ``i`` and ``j`` to the
    symmetric matrix ``mat`` in place."""
    mat[i, i] += value
    mat[j, j] += value
    mat[i, j] -= value
    mat[j, i] -= value


def _linear_matrices(bodies: _Bodies) -> tuple[np.ndarray, np.ndarray]:
    """Stiffness and damping matrices (n, n) of the joints and structural modes, the friction
    elements' viscous parts added to the damping."""
    n = len(bodies.masses)
    kmat, cmat = np.zeros((n, n)), np.zeros((n, n))
    for i, j, k, c in bodies.springs:
        _couple(kmat, i, j, k)
        _couple(cmat, i, j, c)
    for fr, dof, _ in bodies.elements:
        cmat[dof, dof] += fr.viscous
    return kmat, cmat


def _state_space(bodies: _Bodies, kmat: np.ndarray, cmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The linear part ``z' = a z + b f`` (``z``: positions then velocities, ``f``: a force on each DOF)."""
    n = len(bodies.masses)
    minv = np.diag(1.0 / np.array(bodies.masses))
    a = np.zeros((2 * n, 2 * n))
    a[:n, n:] = np.eye(n)
    a[n:, :n] = -minv @ kmat
    a[n:, n:] = -minv @ cmat
    b = np.zeros((2 * n, n))
    b[n:, :] = minv
    return a, b


def _friction_fields(elements: list) -> dict:
    """The friction elements' :class:`PlantModel` fields: law ids, DOFs, parameter rows, implicit
    flags, state slots, random force RMS and force variations (``fr_*``, ``n_frs``).

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> fields = _friction_fields(_bodies(load_preset("fi_stage").stage).elements)
    >>> fields["fr_dof"].tolist(), fields["fr_par"].shape[0], fields["n_frs"]
    ([1, 2], 2, 1)
    """
    nf = len(elements)
    laws = [friction.law(fr) for fr, _, _ in elements]
    pars = [law.params(fr) for law, (fr, _, _) in zip(laws, elements)]
    fr_par = np.zeros((nf, max([1] + [len(p) for p in pars])))
    fr_var = np.zeros((nf, 6))
    for e, (fr, _, _) in enumerate(elements):
        fr_par[e, :len(pars[e])] = pars[e]
        fr_var[e] = _variation(fr)
    return dict(
        fr_kind=np.array([friction.kind(fr) for fr, _, _ in elements], np.int64),
        fr_dof=np.array([dof for _, dof, _ in elements], np.int64),
        fr_par=fr_par,
        fr_implicit=np.array([law.IMPLICIT for law in laws], np.bool_),
        n_frs=max([1] + [law.n_state(fr) for law, (fr, _, _) in zip(laws, elements)]),
        fr_noise=np.array([noise for _, _, noise in elements], float),
        fr_var=fr_var)


def _explicit_terms(bodies: _Bodies, fr_var: np.ndarray, sai, sai_dof: int) -> tuple[np.ndarray, ...]:
    """The stiffness and damping the sub-steps hold explicitly, which set their number.

    Returns
    -------
    k_tangent : ndarray, shape (n, n)
        Tangent stiffness at rest of the friction elements (scaled by their direction variation)
        and of the SAI lock [N/m].
    c_law : ndarray, shape (n,)
        Damping an explicit law holds over a sub-step (LuGre's ``sigma1``) [N·s/m].
    c_explicit : ndarray, shape (n,)
        ``c_law`` plus the SAI lock's damping: the explicit damping the sub-steps keep stable [N·s/m].
    """
    n = len(bodies.masses)
    k_tangent = np.zeros((n, n))
    c_law = np.zeros(n)
    for e, (fr, dof, _) in enumerate(bodies.elements):
        law = friction.law(fr)
        k_tangent[dof, dof] += law.stiffness_at_rest(fr) * (1.0 + abs(fr_var[e, 1]))
        c_law[dof] += law.explicit_damping(fr) * (1.0 + abs(fr_var[e, 1]))
    c_explicit = c_law.copy()
    if sai is not None:
        _couple(k_tangent, 0, sai_dof, sai.lock_stiffness)
        c_explicit[0] += sai.lock_damping
        c_explicit[sai_dof] += sai.lock_damping
    return k_tangent, c_law, c_explicit


def _substeps(bodies: _Bodies, kmat: np.ndarray, explicit: tuple, dt: float, max_omega_h: float,
              max_substeps: int) -> int:
    """Sub-steps per control period.

    Stability: the stiffest mode (joints, structural modes and the tangent stiffness of
    ``explicit``, from :func:`_explicit_terms`) and the fastest explicit damping rate satisfy
    ``rate * h <= max_omega_h``; more than ``max_substeps`` is refused (``ValueError``). Accuracy,
    up to ``max_substeps`` (beyond: stable but coarse): a law's explicitly held damping (LuGre's
    ``sigma1 dz/dt``, first order in the sub-step) to :data:`BRISTLE_H` of its rate. An implicit law's
    slope (regularised Coulomb at rest, ``F_C / v_reg``) asks for none: the law resolves its own
    transient inside the sub-step (``stage_sim.friction.regularized.implicit``).
    """
    k_tangent, c_law, c_explicit = explicit
    masses = np.array(bodies.masses)
    minv = np.diag(1.0 / masses)
    eig = np.linalg.eigvals(minv @ (kmat + k_tangent))
    omega_max = float(np.sqrt(np.max(np.abs(eig))))
    rate_max = float(np.max(c_explicit / masses))  # explicit damping rate [1/s]
    n_sub = max(1, math.ceil(max(omega_max, rate_max) * dt / max_omega_h))
    if n_sub > max_substeps:
        raise ValueError(
            f"stage needs {n_sub} sub-steps per control period (stiffest mode "
            f"{omega_max / (2 * math.pi):.0f} Hz); limit is simulation.max_substeps={max_substeps}")
    need = math.ceil(float(np.max(c_law / masses)) * dt / BRISTLE_H)
    return max(n_sub, min(max_substeps, need))


def _sai_fields(sai, sai_dof: int, h: float) -> dict:
    """The SAI's :class:`PlantModel` fields (lock, solenoid RC filter, armature delay, impact
    pulse over sub-steps of ``h`` [s]); with no SAI (``sai`` None) a lock that never acts."""
    if sai is None:
        return dict(sai_dof=-1, k_lock=0.0, c_lock=0.0, cap_lock=1.0, rc_a=1.0, arm_steps=0, pulse_force=0.0,
                    pulse_steps=0)
    pulse_steps = max(1, int(round(sai.impact_duration / h)))
    return dict(
        sai_dof=sai_dof, k_lock=sai.lock_stiffness, c_lock=sai.lock_damping, cap_lock=sai.lock_capacity,
        rc_a=1.0 if sai.rc_cutoff is None else 1.0 - math.exp(-2 * math.pi * sai.rc_cutoff * h),
        arm_steps=int(round(sai.switch_delay / h)),
        pulse_force=sai.impact_impulse * (1.0 - sai.cushioning) / (pulse_steps * h),
        pulse_steps=pulse_steps)


def _drive_fields(d, dt: float, a: np.ndarray, b: np.ndarray, h: float, n_sub: int) -> dict:
    """The drive's :class:`PlantModel` fields: force-constant error, peak and thermal limits, noise
    (RMS force, AR(1) low-pass keeping that RMS), whole-sample delay and the exact delayed hold of
    its fractional part (over the linear part ``a``, ``b`` and ``n_sub`` sub-steps of ``h``)."""
    noise_a, noise_gain = 1.0, 1.0
    if d.noise_cutoff is not None:
        noise_a = 1.0 - math.exp(-2 * math.pi * d.noise_cutoff * dt)
        noise_gain = math.sqrt((2.0 - noise_a) / noise_a)   # unit-variance AR(1) output
    return dict(
        kf_ratio=d.force_constant_ratio, peak=d.peak_force, cont=d.continuous_force,
        th_alpha=dt / d.thermal_time_constant,
        noise_std=d.noise_current_rms * d.force_constant * d.force_constant_ratio,
        noise_a=noise_a, noise_gain=noise_gain, delay=d.delay_samples,
        delay_frac=float(d.delay_fraction), g_prev=_delayed_zoh(a, b, h, n_sub, d.delay_fraction))


def _sensor_fields(stage: Stage, bearing_dofs: list) -> dict:
    """The encoder's, the bearing sensor's (on the first jointed bearing) and the travel's
    :class:`PlantModel` fields; the divergence bound is 1000 travels beyond the range."""
    span = stage.travel.max - stage.travel.min
    return dict(
        q_table=stage.encoder.resolution,
        bsens_dof=-1 if stage.bearing_sensor is None else bearing_dofs[0],
        bear_dof=bearing_dofs[0] if bearing_dofs else 0,
        q_bearing=0.0 if stage.bearing_sensor is None else stage.bearing_sensor.resolution,
        travel_min=stage.travel.min, travel_max=stage.travel.max,
        x_limit=1e3 * span + abs(stage.travel.min) + abs(stage.travel.max))


def _table_force_fields(stage: Stage) -> dict:
    """The table forces' :class:`PlantModel` fields: constant offset, position-periodic ripple and
    fixed-frequency forces, and whether any acts."""
    return dict(
        f_offset=float(stage.force_offset),
        ripple=np.array([[r.amplitude, 2 * math.pi / r.period, r.phase] for r in stage.force_ripple],
                        float).reshape(-1, 3),
        periodic=np.array([[p.amplitude, 2 * math.pi * p.frequency, p.phase] for p in stage.periodic_force],
                          float).reshape(-1, 3),
        table_force=bool(stage.force_offset != 0.0 or stage.force_ripple or stage.periodic_force))


def build_plant(stage: Stage, rate: float = 10_000.0, max_omega_h: float = 0.25,
                max_substeps: int = 200) -> PlantModel:
    """Compile a stage configuration into a :class:`PlantModel`.

    The stage becomes lumped bodies (:func:`_bodies`) whose linear part is discretised exactly over
    the sub-step; the sub-steps are as many as the stiffest explicitly held term needs
    (:func:`_substeps`); each physics block writes its own fields (friction elements, SAI, drive,
    sensors and travel, table forces).

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

    Returns
    -------
    PlantModel

    Raises
    ------
    ValueError
        The stage needs more than ``max_substeps`` sub-steps per control period.

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> pm = build_plant(load_preset("fi_stage").stage)
    >>> pm.n_sub >= 1
    True
    """
    dt = 1.0 / rate
    bodies = _bodies(stage)
    n = len(bodies.masses)
    fr_fields = _friction_fields(bodies.elements)
    sai_dof = bodies.bearing_dofs[0] if stage.sai is not None else -1
    kmat, cmat = _linear_matrices(bodies)
    explicit = _explicit_terms(bodies, fr_fields["fr_var"], stage.sai, sai_dof)
    n_sub = _substeps(bodies, kmat, explicit, dt, max_omega_h, max_substeps)
    h = dt / n_sub
    a, b = _state_space(bodies, kmat, cmat)
    phi, gam = _exact_zoh(a, b, h)
    return PlantModel(
        n=n, n_sub=n_sub, h=h, dt=dt, phi=phi, gam=gam, dither_dof=np.array(bodies.dither_dof, np.int64),
        gam_ramp=_ramp_response(a, b, h) if fr_fields["fr_implicit"].any() else np.zeros((2 * n, n)),
        **fr_fields, **_sai_fields(stage.sai, sai_dof, h), **_drive_fields(stage.drive, dt, a, b, h, n_sub),
        **_sensor_fields(stage, bodies.bearing_dofs), **_table_force_fields(stage))


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
