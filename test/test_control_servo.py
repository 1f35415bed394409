"""Servo controller: PID, anti-windup, DOB, feedforward friction compensation, NIASA.

Plants are simulated here: a rigid mass, ZOH-exact at 10 kHz, with optional Dahl
friction (stage feels ``-F``) updated from each sample's displacement increment.
"""
import numpy as np
import pytest
from scipy import signal

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


def mass_zoh(m):
    A, B, *_ = signal.cont2discrete((np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0 / m]]),
                                     np.eye(2), np.zeros((2, 1))), DT, method="zoh")
    return A, B[:, 0]


def simulate(ctrl, x_ref, v_ref=None, m=M, dist=None, dahl=None, st=None):
    """Closed loop; returns measured positions (before each command) and commands."""
    model = build_servo(ctrl, st or stage(m))
    s = init_servo_state(model, 1)[0]
    A, B = mass_zoh(m)
    n = len(x_ref)
    v_ref = np.zeros(n) if v_ref is None else v_ref
    dist = np.zeros(n) if dist is None else dist
    z = np.zeros(2)
    f = 0.0
    x, u = np.empty(n), np.empty(n)
    for k in range(n):
        x[k] = z[0]
        u[k] = servo_step(model, s, x_ref[k], v_ref[k], z[0])
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
    s = init_servo_state(model, 1)[0]
    assert [servo_step(model, s, 5e-3, 0.0, 5e-3) for _ in range(3)] == pytest.approx([0.0] * 3, abs=1e-9)


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
    s = init_servo_state(model, 1)[0]
    for _ in range(2000):                        # stage blocked, 1 mm error for 0.2 s
        assert servo_step(model, s, 1e-3, 0.0, 0.0) == 1.0
    assert abs(s[SERVO_INT]) < 1.0               # naive: ki * 1 mm * 0.2 s = 1e4 N


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
    s = init_servo_state(model, 1)[0]
    assert s.shape == (12 + 3,)
    servo_step(model, s, 0.0, 0.0, 0.0)
    assert servo_step(model, s, 1e-7, 0.0, 1e-7) == pytest.approx(1.5 * 6e6 * 1e-7)
    assert servo_step(model, s, 1e-3, 0.0, 1e-3) == pytest.approx(2.0)


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
