"""The plant's compiled model: a validated stage configuration as the arrays of a :class:`PlantModel`.

:func:`build_plant` turns the stage into lumped bodies, discretises their linear part exactly over
the sub-step (Van Loan) and chooses the sub-steps; one small builder per physics block writes that
block's fields (friction elements, SAI, drive, sensors and travel, table forces). The compiled step
that advances the model (:func:`stage_sim.plant.plant_step`) and the integration scheme are in
:mod:`stage_sim.plant`, which also exports :func:`build_plant` and :class:`PlantModel`.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import scipy.linalg

from . import friction
from .config import Stage


BRISTLE_H = 0.01
"""Sub-step x (explicitly held law damping / mass) at most this: LuGre's bristle damping
``sigma1 dz/dt`` is held over a sub-step, a first-order error in the sub-step (against RK4:
4.3 um over 0.45 mm of travel at 1 kHz with 4 sub-steps, 0.17 um at 0.01)."""


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
