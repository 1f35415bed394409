"""Dither generator, on-off regulation and HC controller (Sec. 3.2.2)."""
import numpy as np
import pytest
from scipy import signal

from stage_control.dither import build_dither, dither_step, init_dither_state, piezo_power
from stage_control.servo import build_servo, init_servo_state, servo_step
from stage_sim.config import Controller, Dither, Drive, Pid, Sensor, Stage, Table, Travel

RATE = 10_000.0
DT = 1.0 / RATE


def run(dither, v_ref, x_ref=None, x_meas=None):
    model = build_dither(dither, RATE)
    s = init_dither_state(model, 1)[0]
    n = len(v_ref)
    x_ref = np.zeros(n) if x_ref is None else x_ref
    x_meas = np.zeros(n) if x_meas is None else x_meas
    out = np.zeros((n, 2))
    for k in range(n):
        dither_step(model, s, k, x_ref[k], v_ref[k], x_meas[k], out[k])
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
        ds, ss = init_dither_state(dm, 1)[0], init_servo_state(servo, 1)[0]
        z, out, x = np.zeros(2), np.zeros(2), np.empty(n)
        for i in range(n):
            x[i] = z[0]
            dither_step(dm, ds, i, 0.0, 0.0, z[0], out)
            u = servo_step(servo, ss, 0.0, 0.0, z[0])
            # rigid body: bearing forces +out[0] and -out[1] both reach the table
            z = A @ z + B[:, 0] * (u + out[0] - out[1] + dist[i])
        tail = slice(n - 400, n)              # last 40 ms = 20 periods
        ph = np.exp(-2j * np.pi * f * k[tail] * DT)
        return 2 * abs(np.mean(x[tail] * ph))

    a0, a1 = amplitude_at_f(0.0), amplitude_at_f(4e9)
    assert a0 > 10e-9
    assert a1 < 0.05 * a0


def test_piezo_power_eq_3_7():
    # 0.3 W per actuator at 20 V_pp and 500 Hz (Sec. 3.4.3) -> C = 1.5 uF
    assert piezo_power(500.0, 1.5e-6, 20.0) == pytest.approx(0.3)
