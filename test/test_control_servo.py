"""Servo controller: PID, anti-windup, DOB, feedforward friction compensation, NIASA.

Plants are simulated here: a rigid mass, ZOH-exact at 10 kHz, with optional Dahl
friction (stage feels ``-F``) updated from each sample's displacement increment.
"""
import numpy as np
import pytest
from scipy import signal

from stage_control.filters import SS2_FIELDS
from stage_control.servo import SERVO_INT, build_servo, init_servo_state, servo_step
from stage_sim.config import (Controller, DahlFriction, Dob, Drive, Feedforward, GmsFriction,
                              Niasa, Pid, Sensor, Stage, Table, Travel)
from stage_sim.friction import dahl_update

RATE = 10_000.0
DT = 1.0 / RATE
M = 2.0
WN = 2 * np.pi * 100          # PD design: natural frequency 100 Hz, damping 0.7
PID = Pid(kp=M * WN**2, kd=2 * 0.7 * M * WN, ki=M * WN**3 / 10, derivative_cutoff=2000.0)


def stage(mass=M, peak=100.0):
    return Stage(table=Table(mass=mass),
                 drive=Drive(force_constant=1.0, peak_force=peak, continuous_force=peak / 2),
                 encoder=Sensor(resolution=0.0), travel=Travel(min=-1.0, max=1.0))


def step1(model, s, x_ref, v_ref, x_meas):
    """One servo sample of a single trial (batch of 1); returns the command [N]."""
    u = np.zeros(1)
    servo_step(model, s, np.array([x_ref]), np.array([v_ref]), np.array([x_meas]), u)
    return u[0]


def mass_zoh(m):
    A, B, *_ = signal.cont2discrete((np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0 / m]]),
                                     np.eye(2), np.zeros((2, 1))), DT, method="zoh")
    return A, B[:, 0]


def simulate(ctrl, x_ref, v_ref=None, m=M, dist=None, dahl=None, st=None):
    """Closed loop; returns measured positions (before each command) and commands."""
    model = build_servo(ctrl, st or stage(m))
    s = init_servo_state(model, 1)
    A, B = mass_zoh(m)
    n = len(x_ref)
    v_ref = np.zeros(n) if v_ref is None else v_ref
    dist = np.zeros(n) if dist is None else dist
    z = np.zeros(2)
    f = 0.0
    x, u = np.empty(n), np.empty(n)
    for k in range(n):
        x[k] = z[0]
        u[k] = step1(model, s, x_ref[k], v_ref[k], z[0])
        z_new = A @ z + B * (u[k] + dist[k] - f)
        if dahl is not None:
            f = dahl_update(f, z_new[0] - z[0], dahl[0], dahl[1], 1.0)
        z = z_new
    return x, u


def step(n, k0, size):
    r = np.zeros(n)
    r[k0:] = size
    return r


def test_pid_step_zero_steady_state_error():
    x, _ = simulate(Controller(pid=PID), step(3000, 100, 1e-6))
    assert abs(x[-1] - 1e-6) < 1e-12
    assert x[600] > 0.9e-6                      # reaches the target within 50 ms


def test_first_call_latches_a_nonzero_start():
    """A trial starting at rest away from 0 sees no kick (FF, DOB, derivative)."""
    ctrl = Controller(pid=PID, dob=Dob(pole=0.0, gain=1 / M, q_cutoff=200.0),
                      feedforward=Feedforward(friction=DahlFriction(model="dahl", k_sigma=1e6, f_c=1.0)))
    model = build_servo(ctrl, stage())
    s = init_servo_state(model, 1)
    assert [step1(model, s, 5e-3, 0.0, 5e-3) for _ in range(3)] == pytest.approx([0.0] * 3, abs=1e-9)


def test_anti_windup_limits_overshoot_after_saturation():
    limit = 1.0
    ctrl = Controller(pid=PID.model_copy(update={"output_limit": limit}))
    r = step(4000, 10, 100e-6)                  # needs ~30 ms at full force
    x, u = simulate(ctrl, r)
    assert np.all(np.abs(u) <= limit) and np.sum(np.abs(u) == limit) > 200
    overshoot = x.max() - 100e-6

    # same loop with a naive (always integrating) PID for comparison
    A, B = mass_zoh(M)
    wd = 2 * np.pi * PID.derivative_cutoff
    z, integ, dstate, e_prev, xs = np.zeros(2), 0.0, 0.0, 0.0, []
    for k in range(len(r)):
        e = r[k] - z[0]
        integ += PID.ki * DT * e
        dstate = (dstate / wd + PID.kd * (e - e_prev)) / (1 / wd + DT)
        e_prev = e
        uk = np.clip(PID.kp * e + integ + dstate, -limit, limit)
        z = A @ z + B * uk
        xs.append(z[0])
    naive = max(xs) - 100e-6
    assert naive > 20e-6
    assert overshoot < 0.2 * naive


def test_integrator_bounded_while_saturated():
    ctrl = Controller(pid=PID.model_copy(update={"output_limit": 1.0}))
    model = build_servo(ctrl, stage())
    s = init_servo_state(model, 1)
    for _ in range(2000):                        # stage blocked, 1 mm error for 0.2 s
        assert step1(model, s, 1e-3, 0.0, 0.0) == 1.0
    assert abs(s[SERVO_INT, 0]) < 1.0               # naive: ki * 1 mm * 0.2 s = 1e4 N


def test_dob_rejects_step_disturbance():
    pd = PID.model_copy(update={"ki": 0.0})
    n = 3000
    d = step(n, 500, 5.0)
    x0, _ = simulate(Controller(pid=pd), np.zeros(n), dist=d)
    x1, _ = simulate(Controller(pid=pd, dob=Dob(pole=0.0, gain=1 / M, q_cutoff=500.0)), np.zeros(n), dist=d)
    assert abs(x0[-1]) > 5e-6                    # PD alone: d/kp
    assert abs(x1[-1]) < 0.01 * abs(x0[-1])
    assert np.abs(x1).max() < 0.3 * np.abs(x0).max()


def test_feedforward_dahl_reduces_tracking_error():
    k_sigma, f_c = 2.19e6, 5.31                  # Table 4.3, No FI
    n = 10_000
    t = np.arange(n) * DT
    amp, f = 10e-6, 2.0
    r = amp * (1 - np.cos(2 * np.pi * f * t))
    v = amp * 2 * np.pi * f * np.sin(2 * np.pi * f * t)
    ff = Feedforward(friction=DahlFriction(model="dahl", k_sigma=k_sigma, f_c=f_c))
    e0 = r - simulate(Controller(pid=PID), r, v, dahl=(k_sigma, f_c))[0]
    e1 = r - simulate(Controller(pid=PID, feedforward=ff), r, v, dahl=(k_sigma, f_c))[0]
    rms0, rms1 = np.sqrt(np.mean(e0[5000:] ** 2)), np.sqrt(np.mean(e1[5000:] ** 2))
    assert rms1 < 0.1 * rms0


def test_feedforward_gms_state_and_output():
    """GMS feedforward: one slot per block; force saturates at sum(alpha) F_c."""
    ff = Feedforward(friction=GmsFriction(model="gms", k=[1e6, 2e6, 3e6], alpha=[0.2, 0.3, 0.5], f_c=2.0),
                     stiffness_error=0.5)
    model = build_servo(Controller(pid=Pid(kp=0.0), feedforward=ff), stage())
    s = init_servo_state(model, 1)
    assert s.shape == (12 + 3, 1)
    step1(model, s, 0.0, 0.0, 0.0)
    assert step1(model, s, 1e-7, 0.0, 1e-7) == pytest.approx(1.5 * 6e6 * 1e-7)
    assert step1(model, s, 1e-3, 0.0, 1e-3) == pytest.approx(2.0)


def test_niasa_settles_where_pd_does_not():
    """Appendix A.2, Table A.1: 50 nm step into a +-10 nm window."""
    m, kp, kd = 1.5, 8e5, 850.0
    k_sigma, f_c = 8e6, 1.0
    pd = Pid(kp=kp, kd=kd)
    n = 2000
    r = step(n, 10, 50e-9)
    x_pd, _ = simulate(Controller(pid=pd), r, m=m, dahl=(k_sigma, f_c))
    x_ni, _ = simulate(Controller(pid=pd, niasa=Niasa(tau_d=4e-3, k_sigma=k_sigma, f_c=f_c)), r, m=m,
                       dahl=(k_sigma, f_c))
    tail = slice(1500, None)                     # last 50 ms
    assert np.all(np.abs(r[tail] - x_ni[tail]) < 10e-9)
    assert np.all(np.abs(r[tail] - x_pd[tail]) > 10e-9)


@pytest.mark.parametrize("extras", [{}, {"dob": Dob(pole=3.0, gain=1 / M, q_cutoff=300.0)},
                                    {"feedforward": Feedforward(friction=GmsFriction(
                                        model="gms", k=[1e6, 2e6], alpha=[0.4, 0.6], f_c=2.0, viscous=1.0)),
                                     "niasa": Niasa(tau_d=4e-3, k_sigma=8e6, f_c=1.0)}])
def test_batch_trials_are_independent(extras):
    """A batch (trial axis last) gives, per trial, exactly the single-trial commands."""
    model = build_servo(Controller(pid=PID.model_copy(update={"output_limit": 1.0}), **extras), stage())
    rng = np.random.default_rng(3)
    n, nb = 300, 4
    x_ref = np.cumsum(rng.normal(0, 1e-7, (n, nb)), axis=0) + rng.normal(0, 1e-3, nb)
    v_ref = rng.normal(0, 1e-3, (n, nb))
    x_meas = np.round((x_ref + rng.normal(0, 1e-7, (n, nb))) / 1e-9) * 1e-9
    s, u = init_servo_state(model, nb), np.zeros((n, nb))
    for k in range(n):
        servo_step(model, s, x_ref[k], v_ref[k], x_meas[k], u[k])
    assert np.any(np.abs(u) == 1.0) and np.any(np.abs(u) < 1.0)
    for j in range(nb):
        s1 = init_servo_state(model, 1)
        u1 = [step1(model, s1, x_ref[k, j], v_ref[k, j], x_meas[k, j]) for k in range(n)]
        np.testing.assert_array_equal(u[:, j], u1)
        np.testing.assert_array_equal(s[:, j], s1[:, 0])


def reference_step(model, s, x_ref, v_ref, x_meas):
    """Plain per-trial transcription of the control law (module docstring), state row ``s``.

    Same operations in the same order as the compiled batch kernel, so results must be
    bit-identical.
    """
    d_a, d_b, d_c, d_d, d_x0 = model.d_a, model.d_b, model.d_c, model.d_d, model.d_x0
    g = [getattr(model, "qg_" + f) for f in SS2_FIELDS] + [model.qg_x0, model.qg_x1]
    q = [getattr(model, "q_" + f) for f in SS2_FIELDS]
    e = x_ref - x_meas
    if s[0] == 0.0:                                   # bumpless start
        s[0] = 1.0
        s[2] = d_x0 * e
        s[8], s[9] = x_ref, x_meas
        s[3], s[4] = g[9] * x_meas, g[10] * x_meas
    u_d = d_d * e + d_c * s[2]
    s[2] = d_a * s[2] + d_b * e
    dxm = x_meas - s[9]
    s[9] = x_meas
    ki = model.ki
    if model.niasa:
        if dxm != 0.0:
            s[10] = 1.0 if dxm > 0.0 else -1.0
            s[11] = dahl_update(s[11], dxm, model.ni_ksigma, model.ni_fc, 1.0)
        ki = (model.ni_ksigma * (1.0 - s[11] / model.ni_fc * s[10]) + model.kp) / model.ni_tau
    dxr = x_ref - s[8]
    s[8] = x_ref
    u_ff = 0.0
    p = model.ff_par                                  # Dahl: k_sigma, f_c, shape; GMS: f_c, n, k_i..., alpha_i f_c...
    if model.ff_kind == 1:
        s[12] = dahl_update(s[12], dxr, p[0], p[1], p[2])
        u_ff = s[12] + model.ff_viscous * v_ref
    elif model.ff_kind == 2:
        total = 0.0
        for i in range(model.n_ff):
            lim = p[2 + model.n_ff + i]
            s[12 + i] = min(max(s[12 + i] + p[2 + i] * dxr, -lim), lim)
            total += s[12 + i]
        u_ff = total + model.ff_viscous * v_ref
    d_hat = 0.0
    if model.dob:
        x0, x1, z0, z1, up = s[3], s[4], s[5], s[6], s[7]
        d_hat = (g[8] * x_meas + g[6] * x0 + g[7] * x1) - (q[8] * up + q[6] * z0 + q[7] * z1)
        s[3], s[4] = g[0] * x0 + g[1] * x1 + g[4] * x_meas, g[2] * x0 + g[3] * x1 + g[5] * x_meas
        s[5], s[6] = q[0] * z0 + q[1] * z1 + q[4] * up, q[2] * z0 + q[3] * z1 + q[5] * up
    rest = model.kp * e + u_d + u_ff - d_hat
    integ = s[1] + ki * model.dt * e
    u = rest + integ
    if (u > model.limit or u < -model.limit) and e * u > 0.0:
        integ = s[1]
        u = rest + integ
    s[1] = integ
    u = min(max(u, -model.limit), model.limit)
    s[7] = u
    return u


@pytest.mark.parametrize("ctrl", [
    Controller(pid=PID.model_copy(update={"derivative_cutoff": None, "output_limit": 1.0})),
    Controller(pid=PID.model_copy(update={"output_limit": 3.0}), dob=Dob(pole=3.0, gain=1 / M, q_cutoff=300.0),
               feedforward=Feedforward(friction=DahlFriction(model="dahl", k_sigma=2e6, f_c=5.0, shape=2.0,
                                                             viscous=2.0), stiffness_error=0.1),
               niasa=Niasa(tau_d=4e-3, k_sigma=8e6, f_c=1.0)),
    Controller(pid=PID, dob=Dob(pole=0.0, gain=1 / M, q_cutoff=500.0),
               feedforward=Feedforward(friction=GmsFriction(model="gms", k=[1e6, 2e6, 3e6], alpha=[0.2, 0.3, 0.5],
                                                            f_c=2.0, viscous=1.0)),
               niasa=Niasa(tau_d=2e-3, k_sigma=5e6, f_c=2.0)),
])
def test_batch_kernel_matches_per_trial_reference(ctrl):
    """Bit-identical to the plain per-trial law, incl. a start away from 0 with e != 0."""
    model = build_servo(ctrl, stage())
    rng = np.random.default_rng(5)
    n, nb = 400, 3
    x_ref = 1e-3 * np.arange(1, nb + 1) + np.cumsum(rng.normal(0, 2e-7, (n, nb)), axis=0)
    v_ref = rng.normal(0, 1e-3, (n, nb))
    x_meas = np.round((x_ref + rng.normal(0, 3e-7, (n, nb))) / 1e-9) * 1e-9
    x_meas[100:120] = x_meas[100]                     # repeated measurements (dx = 0)
    s, u = init_servo_state(model, nb), np.zeros((n, nb))
    for k in range(n):
        servo_step(model, s, x_ref[k], v_ref[k], x_meas[k], u[k])
    for j in range(nb):
        row = np.zeros(model.n_state)
        ref = [reference_step(model, row, x_ref[k, j], v_ref[k, j], x_meas[k, j]) for k in range(n)]
        np.testing.assert_array_equal(u[:, j], ref)
        np.testing.assert_array_equal(s[:, j], row)


@pytest.mark.slow
def test_models_work_inside_a_prange_region():
    """The batch engine calls the kernels from ``prange``: models must be flat NamedTuples
    (Numba cannot pass tuples of tuples into a parallel region, numba#9098)."""
    from numba import njit, prange

    from stage_control.dither import build_dither, dither_step, init_dither_state
    from stage_control.sai import build_sai, init_sai_state, sai_step
    from stage_sim.config import Dither, SaiManager

    @njit(parallel=True)
    def run(sm, dm, am, ss, ds, sa, x, v, y, u, out, mo, xc):
        for c in prange(ss.shape[0]):
            for k in range(3):
                sai_step(am, sa[c], x[c], k, v[c], v[c], mo[c], xc[c])
                dither_step(dm, ds[c], k, x[c], v[c], y[c], out[c])
                servo_step(sm, ss[c], x[c], v[c], y[c], u[c])

    sm = build_servo(Controller(pid=PID, dob=Dob(pole=0.0, gain=1 / M, q_cutoff=200.0)), stage())
    dm = build_dither(Dither(amplitude=1.0, frequency=500.0, hc_gain=1e9), RATE)
    am = build_sai(SaiManager(rule="point_to_point"), RATE)
    nc, nb = 2, 3
    ss, ds, sa = (np.stack([init(m, nb)] * nc) for init, m in
                  ((init_servo_state, sm), (init_dither_state, dm), (init_sai_state, am)))
    x, v, y, u, mo, xc = (np.full((nc, nb), 1e-6) for _ in range(6))
    out = np.zeros((nc, 2, nb))
    run(sm, dm, am, ss, ds, sa, x, v, y, u, out, mo, xc)
    ref = init_servo_state(sm, nb)
    u1 = np.zeros(nb)
    for _ in range(3):
        servo_step(sm, ref, x[0], v[0], y[0], u1)
    np.testing.assert_array_equal(u, [u1, u1])
