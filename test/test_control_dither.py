"""Dither generator, on-off regulation and HC controller (Sec. 3.2.2)."""
import math

import numpy as np
import pytest
from scipy import signal

from stage_control.dither import build_dither, dither_step, init_dither_state, piezo_power
from stage_control.filters import discretize
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import Controller, Dither, Drive, Pid, Sensor, Stage, Table, Travel

RATE = 10_000.0
DT = 1.0 / RATE


def run(dither, v_ref, x_ref=None, x_meas=None, ks=None):
    """Single trial (batch of 1); returns ``out`` per sample, shape (n, 2)."""
    model = build_dither(dither, RATE)
    s = init_dither_state(model, 1)
    n = len(v_ref)
    x_ref = np.zeros(n) if x_ref is None else x_ref
    x_meas = np.zeros(n) if x_meas is None else x_meas
    ks = range(n) if ks is None else ks
    out, o = np.zeros((n, 2)), np.zeros((2, 1))
    for i, k in enumerate(ks):
        dither_step(model, s, k, x_ref[i:i + 1], v_ref[i:i + 1], x_meas[i:i + 1], o)
        out[i] = o[:, 0]
    return out


def test_preemptive_dither_is_a_sine_at_f():
    n = 2000
    out = run(Dither(amplitude=3.0, frequency=500.0, preemptive=0.1), np.zeros(n))
    k = np.arange(n)
    np.testing.assert_allclose(out[:, 0], 3.0 * np.sin(2 * np.pi * 500.0 * k / RATE), atol=1e-12)
    np.testing.assert_array_equal(out[:, 0], out[:, 1])
    spectrum = np.abs(np.fft.rfft(out[:, 0]))
    assert np.fft.rfftfreq(n, DT)[np.argmax(spectrum)] == 500.0


def test_continuous_starts_with_the_move():
    v = np.zeros(1000)
    v[300:500] = 1e-3
    out = run(Dither(amplitude=1.0, frequency=700.0), v)
    assert np.all(out[:300] == 0.0)
    assert np.abs(out[300:320, 0]).max() > 0.9 and np.abs(out[-20:, 0]).max() > 0.9


def test_on_off_switches_off_after_off_after():
    v = np.zeros(1000)
    v[100:300] = 1e-3
    v[700:800] = -1e-3
    out = run(Dither(amplitude=1.0, frequency=1000.0, regulation="on_off", off_after=0.01), v)
    on = np.abs(out[:, 1]) > 0
    ref = np.zeros(1000, bool)
    ref[100:400] = True                  # reference stops at k=300, off 100 samples later
    ref[700:900] = True                  # back on at the next move
    sine_zero = np.isclose(np.sin(2 * np.pi * 1000.0 * np.arange(1000) / RATE), 0.0, atol=1e-9)
    np.testing.assert_array_equal(on[~sine_zero], ref[~sine_zero])


def test_zero_amplitude_and_gain_gives_zeros():
    v = np.zeros(500)
    v[100:200] = 1e-3
    out = run(Dither(amplitude=0.0, frequency=500.0, hc_gain=0.0),
              v, x_ref=np.full(500, 1e-6), x_meas=np.random.default_rng(0).normal(0, 1e-6, 500))
    assert np.all(out == 0.0)


def test_hc_rejects_harmonic_disturbance():
    """PID mass (100 Hz) with an unbalanced 1 N force at the dither frequency."""
    m, f = 2.0, 500.0
    wn = 2 * np.pi * 100
    stage = Stage(table=Table(mass=m), drive=Drive(force_constant=1.0, peak_force=100.0, continuous_force=50.0),
                  encoder=Sensor(resolution=0.0), travel=Travel(min=-1.0, max=1.0))
    servo = build_servo(Controller(pid=Pid(kp=m * wn**2, kd=1.4 * m * wn, ki=m * wn**3 / 10,
                                           derivative_cutoff=2000.0)), stage)
    A, B, *_ = signal.cont2discrete((np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [1.0 / m]]),
                                     np.eye(2), np.zeros((2, 1))), DT)
    n = 4000
    k = np.arange(n)
    dist = np.sin(2 * np.pi * f * k * DT + 0.3)

    def amplitude_at_f(hc_gain):
        dm = build_dither(Dither(amplitude=3.0, frequency=f, hc_gain=hc_gain, preemptive=0.1), RATE)
        ds, ss = init_dither_state(dm, 1), init_servo_state(servo, 1)
        z, out, x = np.zeros(2), np.zeros((2, 1)), np.empty(n)
        zero, meas, u = np.zeros(1), np.zeros(1), np.zeros(1)
        for i in range(n):
            x[i] = meas[0] = z[0]
            dither_step(dm, ds, i, zero, zero, meas, out)
            servo_step(servo, ss, zero, zero, meas, u)
            # rigid body: bearing forces +out[0] and -out[1] both reach the table
            z = A @ z + B[:, 0] * (u[0] + out[0, 0] - out[1, 0] + dist[i])
        tail = slice(n - 400, n)              # last 40 ms = 20 periods
        ph = np.exp(-2j * np.pi * f * k[tail] * DT)
        return 2 * abs(np.mean(x[tail] * ph))

    a0, a1 = amplitude_at_f(0.0), amplitude_at_f(4e9)
    assert a0 > 10e-9
    assert a1 < 0.05 * a0


def test_sine_phasor_stays_exact_over_long_runs_and_jumps():
    """The recurrence for sin(w k dt) does not drift (resync) and follows jumps in k."""
    f, n = 1234.5, 30_000
    ks = np.r_[np.arange(7, n // 2), np.arange(n // 2 + 999, n + 999 + 7)][:n]
    out = run(Dither(amplitude=1.0, frequency=f, preemptive=0.1), np.zeros(n), ks=ks)
    np.testing.assert_allclose(out[:, 1], np.sin(2 * np.pi * f * ks / RATE), rtol=0, atol=1e-11)


def test_batch_trials_are_independent():
    """A batch (trial axis last) gives, per trial, exactly the single-trial outputs."""
    d = Dither(amplitude=2.0, frequency=700.0, hc_gain=1e9, regulation="on_off", off_after=0.002)
    model = build_dither(d, RATE)
    rng = np.random.default_rng(4)
    n, nb = 600, 3
    v_ref = np.zeros((n, nb))
    v_ref[50:150, 0], v_ref[100:120, 1], v_ref[300:500, 2] = 1e-3, -1e-3, 2e-3
    x_ref, x_meas = np.full((n, nb), 1e-6), rng.normal(0, 1e-6, (n, nb))
    s, out = init_dither_state(model, nb), np.zeros((n, 2, nb))
    for k in range(n):
        dither_step(model, s, k, x_ref[k], v_ref[k], x_meas[k], out[k])
    assert np.any(out != 0.0) and np.any(out[:, 1] == 0.0)
    for j in range(nb):
        np.testing.assert_array_equal(out[:, :, j], run(d, v_ref[:, j], x_ref[:, j], x_meas[:, j]))


def test_piezo_power_eq_3_7():
    # 0.3 W per actuator at 20 V_pp and 500 Hz (Sec. 3.4.3) -> C = 1.5 uF
    assert piezo_power(500.0, 1.5e-6, 20.0) == pytest.approx(0.3)


def test_matches_per_trial_reference():
    """Regulation and HC as the per-trial law (HC runs free while off); sine to rounding."""
    d = Dither(amplitude=2.0, frequency=811.0, hc_gain=2e9, regulation="on_off", off_after=0.003)
    model = build_dither(d, RATE)
    rng = np.random.default_rng(6)
    n = 3000
    v = np.zeros(n)
    v[200:500], v[1400:1450] = 1e-3, -1e-3
    x_ref, x_meas = np.full(n, 1e-6), rng.normal(0, 1e-6, n)
    x_ref[2000:] = 2e-6                      # an ideal step (v = 0) also starts the dither
    out = run(d, v, x_ref, x_meas)
    A, B, C, D = discretize([1.0, 0.0], [1.0, 0.0, model.omega ** 2], DT, "tustin", prewarp=model.omega)
    x, on, moved, k_stop, ref = np.zeros(2), 0.0, 0.0, 0.0, np.zeros((n, 2))
    for k in range(n):
        if v[k] != 0.0 or (k > 0 and x_ref[k] != x_ref[k - 1]):
            on, moved, k_stop = 1.0, 1.0, k + 1.0
        elif moved == 1.0 and k - k_stop >= model.n_off:
            on, moved = 0.0, 0.0
        uh = (x_meas[k] - x_ref[k]) * d.hc_gain if on else 0.0
        f_comp = D[0, 0] * uh + C[0, 0] * x[0] + C[0, 1] * x[1]
        x = A @ x + B[:, 0] * uh
        f_d = d.amplitude * math.sin(model.omega * (k / RATE))
        ref[k] = (f_d + f_comp, f_d) if on else (0.0, 0.0)
    assert np.any(ref[:, 0] - ref[:, 1] != 0.0) and np.any(ref == 0.0)
    np.testing.assert_array_equal(out == 0.0, ref == 0.0)
    np.testing.assert_allclose(out, ref, rtol=1e-9, atol=3e-12 * d.amplitude)
