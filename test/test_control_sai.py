"""SAI switch manager and ILC of the switching error (Ch. 5.3)."""
import numpy as np
from scipy import signal

from stage_control.sai import build_sai, ilc_update, init_sai_state, sai_step
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import Controller, Drive, Ilc, Pid, SaiManager, Sensor, Stage, Table, Travel

RATE = 10_000.0


def run(manager, v_ref, correction=np.zeros(0)):
    """Single trial (batch of 1); returns mode and correction per sample."""
    model = build_sai(manager, RATE)
    s = init_sai_state(model, 1)
    n = len(v_ref)
    mode, xc, m1, x1 = np.zeros(n), np.zeros(n), np.zeros(1), np.zeros(1)
    for k in range(n):
        ka = min(k + model.lead, n - 1)
        sai_step(model, s, correction, k, v_ref[k:k + 1], v_ref[ka:ka + 1], m1, x1)
        mode[k], xc[k] = m1[0], x1[0]
    return mode, xc


def test_point_to_point_sequence_and_correction():
    v = np.zeros(1000)
    v[200:400] = 1e-3                                    # move, target reached at k = 400
    corr = np.linspace(1e-9, 1e-8, 10)
    mode, xc = run(SaiManager(rule="point_to_point", release_lead=0.005), v, corr)
    expected = np.zeros(1000)
    expected[150:400] = 1.0                              # released 50 samples before the move
    np.testing.assert_array_equal(mode, expected)
    ref = np.zeros(1000)
    ref[400:410] = corr                                  # Step II right after the switch to stiff
    np.testing.assert_array_equal(xc, ref)


def test_correction_restarts_at_every_switch():
    v = np.zeros(1000)
    v[100:200] = 1e-3
    v[500:600] = -1e-3
    _, xc = run(SaiManager(rule="point_to_point", release_lead=0.0), v, np.ones(5))
    assert np.flatnonzero(xc).tolist() == [200, 201, 202, 203, 204, 600, 601, 602, 603, 604]


def test_tracking_compliant_only_near_reversals():
    k = np.arange(2000)
    v = 1e-3 * np.cos(2 * np.pi * k / 1000)              # reversals at k = 250, 750, ...
    mode, xc = run(SaiManager(rule="tracking", release_lead=0.001, reversal_window=1e-4), v)
    compliant = np.flatnonzero(mode)
    assert set(compliant) == set(np.flatnonzero((np.abs(v) < 1e-4)
                                                | (np.abs(v[np.minimum(k + 10, 1999)]) < 1e-4)))
    assert 250 in compliant and 0 not in compliant and 500 not in compliant
    assert np.all(xc == 0.0)


def test_always_rules():
    v = np.r_[np.zeros(10), np.ones(10)]
    assert np.all(run(SaiManager(rule="always_compliant"), v)[0] == 1.0)
    assert np.all(run(SaiManager(rule="always_stiff"), v)[0] == 0.0)


def test_batch_trials_are_independent():
    """A batch (trial axis last) gives, per trial, exactly the single-trial outputs."""
    v = np.zeros((1000, 3))
    v[100:200, 0], v[300:650, 1], v[50:60, 2] = 1e-3, -1e-3, 2e-3
    v[700:800, 2] = 1e-3
    corr = np.linspace(1e-9, 1e-8, 25)
    for manager in (SaiManager(rule="point_to_point", release_lead=0.002),
                    SaiManager(rule="tracking", release_lead=0.001, reversal_window=1e-4)):
        model = build_sai(manager, RATE)
        s, mode, xc = init_sai_state(model, 3), np.zeros((1000, 3)), np.zeros((1000, 3))
        for k in range(1000):
            sai_step(model, s, corr, k, v[k], v[min(k + model.lead, 999)], mode[k], xc[k])
        assert np.any(xc != 0.0)
        for j in range(3):
            m1, x1 = run(manager, v[:, j], corr)
            np.testing.assert_array_equal(mode[:, j], m1)
            np.testing.assert_array_equal(xc[:, j], x1)


def test_ilc_converges_on_repeatable_switching_error():
    """Eq. 5.2 on a PID mass (100 Hz) hit by the same low-frequency force at each switch."""
    m, dt, q = 2.0, 1.0 / RATE, 1000
    wn = 2 * np.pi * 100
    stage = Stage(table=Table(mass=m), drive=Drive(force_constant=1.0, peak_force=100.0, continuous_force=50.0),
                  encoder=Sensor(resolution=0.0), travel=Travel(min=-1.0, max=1.0))
    servo = build_servo(Controller(pid=Pid(kp=m * wn**2, kd=1.4 * m * wn, ki=m * wn**3 / 10,
                                           derivative_cutoff=2000.0)), stage)
    A, B, *_ = signal.cont2discrete((np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0 / m]]),
                                     np.eye(2), np.zeros((2, 1))), dt)
    t = np.arange(q) * dt
    dist = 2.0 * np.exp(-t / 5e-3) * np.sin(2 * np.pi * 40 * t)     # repeatable switching force

    def repetition(u):
        s = init_servo_state(servo, 1)
        z, e, f, zero = np.zeros(2), np.empty(q), np.zeros(1), np.zeros(1)
        for k in range(q):
            e[k] = 0.0 - z[0]                                      # at rest at the target
            servo_step(servo, s, 0.0 + u[k:k + 1], zero, z[:1], f)  # corrected reference
            z = A @ z + B[:, 0] * (f[0] + dist[k])
        return e

    ilc = Ilc()
    u = np.zeros(q)
    rms = []
    for _ in range(ilc.iterations + 1):
        e = repetition(u)
        rms.append(np.sqrt(np.mean(e**2)))
        u = ilc_update(u, e, ilc, RATE)
    assert rms[0] > 1e-7
    assert rms[10] < 0.2 * rms[0]
    assert all(b < a for a, b in zip(rms[:4], rms[1:5]))           # monotone early on
