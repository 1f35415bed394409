"""Tests of experiment_runner.core.metrics."""

import math

import control
import numpy as np
import pytest
from scipy import optimize, signal

from experiment_runner.core.metrics import (
    cross_spectra, error_spectrum, sine_phasor, rms_in_position, settling_time, tracking_errors, welch_csd)
from experiment_runner.core.profiles import sine_sweep
from stage_control.tuning import closed_loop_bandwidth, loop_margins

DT = 1e-4
WINDOW = 25e-9


def _decaying_oscillation(t, t0, amp, tau, freq):
    """``amp exp(-(t-t0)/tau) cos(2 pi freq (t-t0))`` after t0, ``amp`` before."""
    s = np.clip(t - t0, 0.0, None)
    return np.where(t >= t0, amp * np.exp(-s / tau) * np.cos(2 * np.pi * freq * s),
                    amp)


def _last_exit_time(t0, amp, tau, freq):
    """Time after t0 at which |e| last crosses the band edge (root-found)."""
    fine = np.arange(t0, t0 + 0.2, 1e-6)
    i = np.flatnonzero(np.abs(_decaying_oscillation(fine, t0, amp, tau, freq))
                       > WINDOW)[-1]
    return optimize.brentq(
        lambda t: abs(_decaying_oscillation(t, t0, amp, tau, freq)) - WINDOW,
        fine[i], fine[i + 1], xtol=1e-12) - t0


def test_settling_time_of_decaying_oscillation_within_one_sample():
    t = np.arange(0, 0.3, DT)
    target, t0 = 5e-3, 0.0123
    for amp, tau, freq in [(1e-6, 0.01, 120.0), (-3e-7, 0.02, 37.0)]:
        x = target + _decaying_oscillation(t, t0, amp, tau, freq)
        ts = settling_time(t, x, target, t0, WINDOW)
        exact = _last_exit_time(t0, amp, tau, freq)
        assert exact < ts <= exact + DT


def test_settling_time_edge_cases_and_t_end():
    t = np.arange(0, 0.1, DT)
    x = np.zeros_like(t)
    assert settling_time(t, x, 0.0, 0.02, WINDOW) == 0.0
    x[-1] = 1e-6  # outside at the end of the record
    assert math.isnan(settling_time(t, x, 0.0, 0.02, WINDOW))
    # excursions after t_end are ignored; before t_start too
    x[100] = 1e-6
    x[300] = 1e-6
    assert settling_time(t, x, 0.0, 0.02, WINDOW, t_end=0.09) == pytest.approx(
        0.0301 - 0.02)
    assert math.isnan(settling_time(t, x, 0.0, 0.2, WINDOW))  # empty interval


def test_settling_time_batch_matches_single_trials():
    t = np.arange(0, 0.3, DT)
    params = [(1e-6, 0.01, 120.0), (2e-6, 0.03, 80.0), (5e-7, 0.005, 300.0)]
    targets = np.array([0.0, 1e-3, -2e-3])
    t0s = np.array([0.01, 0.02, 0.03])
    x = np.stack([tg + _decaying_oscillation(t, t0, *p)
                  for tg, t0, p in zip(targets, t0s, params)])
    x[2, -1] += 1e-6  # trial 2 is outside at the end: never settles
    batch = settling_time(t, x, targets, t0s, WINDOW)
    single = [settling_time(t, xi, tg, t0, WINDOW)
              for xi, tg, t0 in zip(x, targets, t0s)]
    assert batch.shape == (3,)
    np.testing.assert_array_equal(batch, single)
    assert np.isnan(batch[2]) and np.all(batch[:2] > 0.01)


def test_rms_in_position_of_known_sine():
    t = np.arange(0, 0.5, DT)
    x = 1e-3 + np.where(t >= 0.1, 2e-9 * np.sin(2 * np.pi * 50 * t), 1e-6)
    rms = rms_in_position(t, x, 1e-3, 0.1, t_end=0.3 - DT / 2)  # 10 periods
    assert rms == pytest.approx(2e-9 / np.sqrt(2), rel=1e-9)
    assert math.isnan(rms_in_position(t, x, 1e-3, np.nan))
    batch = rms_in_position(t, np.stack([x, 2 * x - 1e-3]), 1e-3,
                            np.array([0.1, np.nan]))
    assert batch[0] == pytest.approx(2e-9 / np.sqrt(2), rel=1e-3)
    assert np.isnan(batch[1])


def test_tracking_errors():
    t = np.arange(0, 1, DT)
    x_ref = 5e-3 * (1 - np.cos(2 * np.pi * t))
    e = 1.5e-6 * np.sin(2 * np.pi * 3 * t)
    peak, rms = tracking_errors(x_ref, x_ref - e)
    assert peak == pytest.approx(1.5e-6, rel=1e-6)
    assert rms == pytest.approx(1.5e-6 / np.sqrt(2), rel=1e-6)
    peaks, rmss = tracking_errors(x_ref, np.stack([x_ref - e, x_ref - 2 * e]))
    np.testing.assert_allclose(peaks, [1.5e-6, 3e-6], rtol=1e-6)
    np.testing.assert_allclose(rmss, np.array([1, 2]) * 1.5e-6 / np.sqrt(2),
                               rtol=1e-6)


def test_sine_phasors_give_the_frf_of_a_mass_spring_damper():
    """The stepped-sine FRF the FRF campaign computes: Y/U of the phasors per sine segment."""
    m, fn, zeta = 2.0, 80.0, 0.2  # [kg], [Hz], [-]
    wn = 2 * np.pi * fn
    plant = signal.lti([1 / m], [1, 2 * zeta * wn, wn**2])  # force -> position
    freqs = [5.0, 30.0, 70.0, 80.0, 95.0, 200.0, 300.0]
    ref = sine_sweep(freqs, amplitude=1.0)
    # lsim interpolates the input linearly between samples, which scales a
    # sine by sinc(f dt)**2 (0.3 % at 300 Hz): stay well below Nyquist
    _, y, _ = signal.lsim(plant, ref.x, ref.t)
    sines = [s for s in ref.segments if s.kind == "sine"]
    f = np.array([s.frequency for s in sines])
    H = np.array([sine_phasor(ref.t[s.start:s.stop], y[s.start:s.stop], s.frequency)
                  / sine_phasor(ref.t[s.start:s.stop], ref.x[s.start:s.stop], s.frequency) for s in sines])
    _, H_true = signal.freqresp(plant, 2 * np.pi * f)
    np.testing.assert_allclose(f, freqs, rtol=2.5e-3)
    np.testing.assert_allclose(H, H_true, rtol=0.01)
    # a batch of two outputs at once
    s = sines[2]
    Y2 = sine_phasor(ref.t[s.start:s.stop], np.stack([y, 2 * y])[:, s.start:s.stop], s.frequency)
    np.testing.assert_allclose(Y2 / sine_phasor(ref.t[s.start:s.stop], ref.x[s.start:s.stop], s.frequency),
                               [H[2], 2 * H[2]], rtol=1e-12)


def test_cross_spectra_give_the_h1_frf_of_a_discrete_filter():
    fs = 1e4
    b, a = signal.butter(2, 500.0, fs=fs)
    u = np.random.default_rng(0).standard_normal(100_000)
    y = 1e-6 * signal.lfilter(b, a, u)
    f, suu, syy, suy = cross_spectra(u, y, fs, nperseg=2048)
    H, coh = suy / suu, np.abs(suy) ** 2 / (suu * syy)
    _, H_true = signal.freqz(1e-6 * b, a, worN=f, fs=fs)
    band = (f > 10) & (f < 1000)
    np.testing.assert_allclose(H[band], H_true[band], rtol=0.02)
    assert np.all(coh[band] > 0.99)
    # uncorrelated output: coherence collapses
    _, suu, syy, suy = cross_spectra(u, np.roll(u, 5000), fs, nperseg=2048)
    coh_noise = np.abs(suy) ** 2 / (suu * syy)
    assert np.median(coh_noise) < 0.05


@pytest.mark.parametrize("n, nperseg, detrend", [(3000, 256, "linear"), (3001, 255, "linear"), (5000, 1024, "constant"),
                                                 (4096, 4096, "linear"), (999, 100, False)])
def test_welch_csd_is_scipys_csd_and_welch(n, nperseg, detrend):
    """The vectorised Welch estimate is scipy's (csd and welch with their defaults: periodic Hann,
    50 % overlap, density, one-sided; odd and even segments, both detrends, one segment) to
    rounding, on signals with a trend 1000x their noise (where a linear detrend's rounding shows)."""
    rng = np.random.default_rng(n)
    x, y = 1e-6 * rng.standard_normal((2, n)) + np.linspace(0.0, 1e-3, n)
    f0, p0 = signal.csd(x, y, fs=1e4, nperseg=nperseg, detrend=detrend)
    f1, p1 = welch_csd(x, y, fs=1e4, nperseg=nperseg, detrend=detrend)
    np.testing.assert_array_equal(f0, f1)
    np.testing.assert_allclose(p1, p0, rtol=0, atol=1e-10 * np.max(np.abs(p0)))
    _, w0 = signal.welch(x, fs=1e4, nperseg=nperseg, detrend=detrend)
    _, w1 = welch_csd(x, fs=1e4, nperseg=nperseg, detrend=detrend)
    assert w1.dtype == np.float64
    np.testing.assert_allclose(w1, w0, rtol=0, atol=1e-10 * np.max(w0))


def test_closed_loop_bandwidth_first_order():
    fc = 180.0
    f = np.logspace(0, 4, 81)  # 20 points per decade
    T = 1 / (1j * f / fc + 1)
    assert closed_loop_bandwidth(f, T) == pytest.approx(fc, rel=0.02)
    # second-order T with resonance peak: first downward crossing counts
    wn, zeta = 2 * np.pi * 200.0, 0.3
    s = 2j * np.pi * f
    T2 = wn**2 / (s**2 + 2 * zeta * wn * s + wn**2)
    wb = wn * np.sqrt(1 - 2 * zeta**2 + np.sqrt((1 - 2 * zeta**2) ** 2 + 1))
    assert closed_loop_bandwidth(f, T2) == pytest.approx(wb / (2 * np.pi),
                                                         rel=0.02)
    assert math.isnan(closed_loop_bandwidth(f, np.ones_like(T)))
    assert math.isnan(closed_loop_bandwidth(f, 0.5 * T))  # below from the start


def test_margins_match_control_margin():
    # filtered PID on a 1 kg mass held by a 1 N/um frictional spring
    # (pre-motion regime), with a 2 kHz actuator lag
    s = control.tf("s")
    pid = 1e6 * (1 + 2 * np.pi * 20 / s + s / (2 * np.pi * 60)) / (
        s / (2 * np.pi * 1000) + 1)
    plant = 1 / (1.0 * s**2 + 50 * s + 1e6)
    loop = pid * plant / (s / (2 * np.pi * 2000) + 1)
    gm, pm, w_pc, w_gc = control.margin(loop)
    f = np.logspace(0, 4, 2000)
    m = loop_margins(f, loop(2j * np.pi * f))
    assert m.gain_margin_db == pytest.approx(20 * np.log10(gm), abs=0.05)
    assert m.phase_margin_deg == pytest.approx(pm, abs=0.1)
    assert m.phase_crossover_hz == pytest.approx(w_pc / (2 * np.pi), rel=1e-3)
    assert m.gain_crossover_hz == pytest.approx(w_gc / (2 * np.pi), rel=1e-3)
    assert m.gain_margin_db == pytest.approx(16.2, abs=0.1)
    assert m.phase_margin_deg == pytest.approx(47.4, abs=0.1)


def test_margins_without_phase_crossover():
    f = np.logspace(0, 3, 300)
    m = loop_margins(f, 100 / (2j * np.pi * f))  # integrator: PM = 90, GM = inf
    assert m.phase_margin_deg == pytest.approx(90.0, abs=1e-6)
    assert m.gain_crossover_hz == pytest.approx(100 / (2 * np.pi), rel=1e-6)
    assert m.gain_margin_db == math.inf and math.isnan(m.phase_crossover_hz)


def test_error_spectrum_amplitudes():
    fs, n = 1e4, 2000
    t = np.arange(n) / fs
    e = 3e-9 + 607e-9 * np.sin(2 * np.pi * 500 * t) + 10e-9 * np.cos(
        2 * np.pi * 120 * t)
    f, amp = error_spectrum(e, fs)
    assert f[1] == pytest.approx(fs / n) and f[-1] == fs / 2
    assert amp[f == 500][0] == pytest.approx(607e-9, rel=1e-9)
    assert amp[f == 120][0] == pytest.approx(10e-9, rel=1e-9)
    assert amp[0] == pytest.approx(3e-9, rel=1e-9)
    # a tone between bins: flat-top window keeps the amplitude
    _, amp_ft = error_spectrum(607e-9 * np.sin(2 * np.pi * 502.5 * t), fs,
                               window="flattop")
    assert amp_ft.max() == pytest.approx(607e-9, rel=2e-3)
    _, amp2 = error_spectrum(np.stack([e, 2 * e]), fs)
    np.testing.assert_allclose(amp2, [amp, 2 * amp])
