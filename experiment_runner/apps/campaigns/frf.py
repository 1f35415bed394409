"""Frequency responses of a campaign case: amplitude-dependent FRFs, bandwidth and margins (seed Sec. 4.3, App. C.2).

The seed measures the plant FRF of the Ch. 4 stage "by applying constant-amplitude sinusoidal
motor current commands with varying frequencies to the linear motor and recording the
corresponding output displacement" (Sec. 4.3, Fig. 4.4), at force amplitudes from 0.11 N to
16.5 N (0.01 A to 1.5 A at 11 N/A). Treating each FRF as an LTI system, it then *calculates*
the closed loop with the PID (Fig. 4.5), its -3 dB bandwidth and the gain and phase margins
(Fig. 4.6), and the same with the disturbance observer through the augmented plant of
Eq. C.5 (Fig. C.8-C.10). This module does the same on the simulated stage:

1. **Plant FRF** (:func:`plant_frf`): open-loop stepped sine on the compiled plant
   (:func:`stage_sim.plant.plant_step`, the step the batch engine and the ROS plant node use),
   one batch column per amplitude x frequency, all columns advanced together by a compiled
   loop parallel over chunks of columns (:func:`_open_loop`; the batch engine's
   :func:`experiment_runner.core.batch.simulate` always closes the servo loop, so it cannot apply
   a force command in open loop). Each column starts at rest, ramps the sine in over a
   raised-cosine envelope (no net impulse, so a sliding stage does not drift), waits for the
   transients and fits ``a cos + b sin + c + d t`` to the position (encoder reading, or the
   true table position; drive noise included) over a window of whole periods
   (:func:`experiment_runner.core.metrics.sine_phasor`). Cases on the same stage share the plant FRF.
2. **Loop** (:func:`loop_frfs`): the case's discrete controller (PID with derivative filter
   and backward-Euler integral, and the DOB of Eq. C.1-C.3 if the preset has one, exactly as
   :func:`stage_control.servo.servo_step` implements them) in the frequency domain; the loop
   broken at the plant input ``L``, the closed loop ``T`` (reference to measured position)
   and the augmented plant ``G_aug`` of Eq. C.5.
3. **Metrics**: ``bandwidth_hz`` (:func:`stage_control.tuning.closed_loop_bandwidth` of
   ``T``), ``gain_margin_db`` and ``phase_margin_deg`` (:func:`stage_control.tuning.loop_margins`: python-control
   on an FRD of ``L``).
4. Optionally (``simulate_closed_loop``) **the closed loop itself** on the batch engine
   (:func:`closed_loop_frf`, :func:`experiment_runner.core.batch.simulate` over a batch of
   amplitudes x frequencies) at the force amplitudes: a check of the LTI assumption.

Campaign files use ``test: {kind: frequency_response, ...}``
(:class:`~experiment_runner.apps.campaigns.schema.frequency_response.FrequencyResponseTest`); the campaign kind that runs
these measurements per case and writes the outputs is
:mod:`experiment_runner.apps.campaigns.frequency_response`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np
from numba import njit, prange

from experiment_runner.apps.campaigns.schema.frequency_response import FrequencyResponseTest, frequency_grid
from experiment_runner.core.batch import Models, chunked, unchunked, simulate
from experiment_runner.core.metrics import sine_phasor
from stage_control.servo import build_servo
from stage_sim.plant import OK, PlantInputs, chunk_state, init_plant_state, quantize, run_open_loop, state_chunk

__all__ = ["frequency_grid", "plant_frf", "PlantFrf", "closed_loop_frf", "controller_frf", "loop_frfs",
           "coulomb_force", "moving_mass", "nominal_fit", "NOMINAL_FIT_MAX_HZ"]

NOMINAL_FIT_MAX_HZ = 100.0
"""Upper end of the band of Table C.1's nominal-model fit ("frequencies below 100 Hz", App. C.2.1)."""


# =========================================================================== open-loop kernel
@njit(cache=True, parallel=True)
def _open_loop(pm, amp, omega, n_ramp, seeds, true_position, plant, out_y, status):
    """Open-loop sine forces on the plant (its driver :func:`stage_sim.plant.run_open_loop`);
    arrays are (chunk, ..., column), ``plant`` a chunked :class:`~stage_sim.plant.PlantState`.

    Column ``b`` gets ``u[k] = amp * env[k] * sin(omega * k * dt)`` with the raised-cosine
    envelope ``env = (1 - cos(pi k / n_ramp)) / 2`` for ``k < n_ramp`` (then 1); ``out_y[c, k, b]``
    is the encoder reading (or, with ``true_position``, the true table position) at the start of
    sample ``k`` (before ``u[k]`` acts), as the servo sees it.
    """
    n_chunks, n_steps, nb = out_y.shape
    dt = pm.dt
    for c in prange(n_chunks):
        u = np.empty((n_steps, nb))
        for k in range(n_steps):
            for b in range(nb):
                env = 1.0
                if k < n_ramp[c, b]:
                    env = 0.5 * (1.0 - math.cos(math.pi * k / n_ramp[c, b]))
                u[k, b] = amp[c, b] * env * math.sin(omega[c, b] * k * dt)
        st = state_chunk(plant, c)
        meas = np.empty((2, nb))
        for b in range(nb):
            meas[0, b] = quantize(st.z[0, b], pm.q_table)
            meas[1, b] = 0.0
        inp = PlantInputs(u, np.zeros((1, nb)), np.zeros((1, nb)), np.ones((1, nb)), np.zeros((0, 0)))
        run_open_loop(pm, st, inp, 0, seeds[c], meas, status[c], true_position, out_y[c], np.zeros((0, 0)))


def _ramp_samples(test, f, dt):
    return max(1, math.ceil(max(test.ramp_cycles / f, test.min_ramp_time) / dt))


class _Column(NamedTuple):
    """Timing of one frequency [samples]; the window is ``n_base`` times an integer per amplitude."""
    f_adj: float       # frequency with a whole number of periods in n_base samples [Hz]
    n_base: int        # base measurement window
    n_ramp: int
    n_settle: int


def _column_layout(test: FrequencyResponseTest, dt: float) -> list[_Column]:
    """Per nominal frequency: adjusted frequency [Hz], base window, ramp and settle [samples]."""
    rows = []
    for f in frequency_grid(test):
        if not f < 0.5 / dt:
            raise ValueError(f"f_max={test.f_max} Hz is not below the Nyquist frequency {0.5 / dt} Hz")
        n_periods = max(test.cycles, math.ceil(test.min_measure_time * f))
        n_base = max(1, int(round(n_periods / (f * dt))))
        f_adj = n_periods / (n_base * dt)
        n_ramp = _ramp_samples(test, f_adj, dt)
        n_settle = math.ceil(max(test.settle_cycles / f_adj, test.min_settle_time) / dt)
        rows.append(_Column(f_adj, n_base, n_ramp, n_settle))
    return rows


def _window(test: FrequencyResponseTest, col: _Column, amplitude: float, dt: float) -> int:
    """Measurement window [samples] at an amplitude: whole base windows, ``>= measure_force_time / A^2``."""
    need = (test.measure_force_time or 0.0) / amplitude ** 2
    return col.n_base * max(1, math.ceil(need / (col.n_base * dt) - 1e-9))


def _groups(cols, length, ratio=1.25, max_size=None):
    """Columns sorted by length into groups whose lengths differ by at most ``ratio`` (each group
    runs as long as its longest column), at most ``max_size`` columns each."""
    groups, cur = [], []
    for ij in sorted(cols, key=lambda ij: length[ij]):
        if cur and (length[ij] > ratio * length[cur[0]] or (max_size and len(cur) >= max_size)):
            groups.append(cur)
            cur = []
        cur.append(ij)
    return groups + ([cur] if cur else [])


def _envelope(k, n_ramp):
    """Raised-cosine ramp-in: ``(1 - cos(pi k / n_ramp)) / 2`` for ``k < n_ramp``, then 1."""
    return np.where(k < n_ramp, 0.5 * (1 - np.cos(np.pi * k / n_ramp)), 1.0)


def coulomb_force(preset) -> float:
    """Total Coulomb (gross-sliding) friction force of a linear stage [N]: bearings and table.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        A linear stage.

    Returns
    -------
    float
    """
    tot = 0.0
    items = [b.friction for b in preset.stage.bearings]
    if preset.stage.table_friction is not None:
        items.append(preset.stage.table_friction)
    for fr in items:
        tot += float(getattr(fr, "f_c", 0.0) or 0.0)
    return tot


def moving_mass(preset) -> float:
    """Table + bearings + structural-mode masses [kg] (the rigid stage in gross motion).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        A linear stage.

    Returns
    -------
    float
    """
    st = preset.stage
    m = st.table.mass * (1.0 + sum(md.mass_ratio for md in st.modes))
    return m + sum(b.mass for b in st.bearings)


@dataclass
class PlantFrf:
    """Measured plant FRFs of one preset: rows = amplitudes, columns = frequencies.

    Parameters
    ----------
    amplitudes : numpy.ndarray
        (na,) force amplitudes [N].
    freqs_hz : numpy.ndarray
        (nf,) excitation frequencies [Hz].
    G : numpy.ndarray
        (na, nf) complex, command force -> position [m/N]; NaN where not measured.
    status : numpy.ndarray
        (na, nf) plant status (0 ok, -1 skipped: the stage would slide beyond ``max_displacement``).
    samples : int
        Column-samples simulated.
    wall_s : float
        Wall time [s].
    """
    amplitudes: np.ndarray     # (na,) force amplitudes [N]
    freqs_hz: np.ndarray       # (nf,) excitation frequencies [Hz]
    G: np.ndarray              # (na, nf) complex, command force -> position [m/N]; nan = not measured
    status: np.ndarray         # (na, nf) plant status (0 ok, -1 skipped: would slide beyond max_displacement)
    samples: int               # column-samples simulated
    wall_s: float


def plant_frf(preset, test: FrequencyResponseTest, amplitudes=None, models=None) -> PlantFrf:
    """Open-loop stepped-sine plant FRFs of ``preset`` at every amplitude x frequency.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage (the controller is not used).
    test : FrequencyResponseTest
        Frequencies and timing.
    amplitudes : array_like, optional
        Force amplitudes [N] (default ``test.amplitudes``).
    models : experiment_runner.core.batch.Models, optional
        Compiled models of ``preset`` (only ``plant`` is used).

    Returns
    -------
    PlantFrf
        ``G[i, j]`` from the force command [N] to the position [m] at sample ``k`` (encoder
        reading, or the true table position with ``test.sensor == "true"``; the command of
        sample ``k`` acts over ``[k, k+1)``): the plant the discrete servo sees.
    """
    t0 = time.monotonic()
    pm = (models or Models.from_preset(preset)).plant
    dt = pm.dt
    amps = np.asarray(test.amplitudes if amplitudes is None else amplitudes, float)
    layout = _column_layout(test, dt)
    nf = len(layout)
    f_adj = np.array([c.f_adj for c in layout])
    fc_tot = coulomb_force(preset)
    m_tot = moving_mass(preset)
    G = np.full((amps.size, nf), np.nan + 0j)
    status = np.zeros((amps.size, nf), np.int64)
    cols = []                                   # (amplitude index, frequency index)
    n_meas, length = {}, {}
    for i, a in enumerate(amps):
        for j, c in enumerate(layout):
            if a > fc_tot and a / (m_tot * (2 * np.pi * c.f_adj) ** 2) > test.max_displacement:
                status[i, j] = -1
            else:
                cols.append((i, j))
                n_meas[i, j] = _window(test, c, a, dt)
                length[i, j] = c.n_ramp + c.n_settle + n_meas[i, j]
    samples = 0
    seed0 = preset.simulation.seed
    for grp in _groups(cols, length):
        B = len(grp)
        T = max(length[ij] for ij in grp)
        n_chunks = max(1, min(numba.get_num_threads(), B))
        size = -(-B // n_chunks)
        amp = np.array([amps[i] for i, _ in grp])
        om = np.array([2 * np.pi * f_adj[j] for _, j in grp])
        nr = np.array([layout[j].n_ramp for _, j in grp], np.int64)
        seeds = np.array([seed0 + i * nf + j for i, j in grp], np.int64)
        plant = chunk_state(init_plant_state(pm, n_chunks * size, 0.0, sai_mode=1.0), n_chunks)
        out_y = np.zeros((n_chunks, T, size))
        stat = np.zeros((n_chunks, size), np.int64)
        _open_loop(pm, chunked(amp, n_chunks, size), chunked(om, n_chunks, size), chunked(nr, n_chunks, size),
                   chunked(seeds, n_chunks, size), test.sensor == "true", plant, out_y, stat)
        y = unchunked(out_y, B)
        stat = unchunked(stat, B)
        samples += B * T
        for col, (i, j) in enumerate(grp):
            if stat[col] != OK:
                status[i, j] = stat[col]
                continue
            k = np.arange(T - n_meas[i, j], T)
            t = k * dt
            u = amps[i] * _envelope(k, layout[j].n_ramp) * np.sin(2 * np.pi * f_adj[j] * k * dt)
            G[i, j] = sine_phasor(t, y[col, T - n_meas[i, j]:], f_adj[j]) / sine_phasor(t, u, f_adj[j])
    return PlantFrf(amplitudes=amps, freqs_hz=f_adj, G=G, status=status, samples=samples,
                    wall_s=time.monotonic() - t0)


def closed_loop_frf(preset, test: FrequencyResponseTest, plant: PlantFrf, models=None, max_batch: int = 32):
    """Closed-loop FRFs simulated on the batch engine at the plant FRF's force amplitudes.

    A check of the seed's LTI assumption (Sec. 4.3: "each measured FRF ... represents an LTI
    system"): column ``(i, j)`` runs the case's closed loop (:func:`experiment_runner.core.batch.simulate`)
    on a sine reference of amplitude ``R = A_i |G_ij / T_ij|`` (``T`` calculated by
    :func:`loop_frfs` from the plant FRF ``G_ij`` measured at force amplitude ``A_i``), i.e. the
    reference that asks the plant input for the force amplitude ``A_i`` if the stage behaved as
    that LTI system; same ramp, settle and window as the plant FRF.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The case (stage and servo).
    test : FrequencyResponseTest
        Timing (as for the plant FRF).
    plant : PlantFrf
        The plant FRF of ``preset``'s stage at the test's amplitudes.
    models : experiment_runner.core.batch.Models, optional
        Compiled models of ``preset``.
    max_batch : int
        Columns per :func:`~experiment_runner.core.batch.simulate` call (bounds the memory of its
        recorded signals).

    Returns
    -------
    T_sim : numpy.ndarray, shape like ``plant.G``
        Simulated reference -> measured position FRF (nan where the plant FRF has none).
    u_amp : numpy.ndarray, shape like ``plant.G``
        Force-command amplitude reached at the plant input [N].
    samples : int
        Column-samples simulated.
    """
    models = models or Models.from_preset(preset)
    dt = 1.0 / preset.controller.rate
    layout = _column_layout(test, dt)
    T_sim = np.full(plant.G.shape, np.nan + 0j)
    u_amp = np.full(plant.G.shape, np.nan)
    r_amp, n_meas, length, cols, samples = {}, {}, {}, [], 0
    for i, a in enumerate(plant.amplitudes):
        ok = np.flatnonzero(np.isfinite(plant.G[i]))
        if not ok.size:
            continue
        T = loop_frfs(preset, plant.freqs_hz[ok], plant.G[i, ok])["T"]
        for j, g, t in zip(ok, plant.G[i, ok], T):
            cols.append((i, j))
            r_amp[i, j] = a * abs(g / t)
            n_meas[i, j] = _window(test, layout[j], a, dt)
            length[i, j] = layout[j].n_ramp + layout[j].n_settle + n_meas[i, j]
    for grp in _groups(cols, length, max_size=max_batch):
        n = max(length[ij] for ij in grp)
        k = np.arange(n)
        x_ref = np.array([r_amp[i, j] * _envelope(k, layout[j].n_ramp)
                          * np.sin(2 * np.pi * layout[j].f_adj * k * dt) for i, j in grp])
        seeds = preset.simulation.seed + np.array([i * len(layout) + j for i, j in grp])
        res = simulate(preset, x_ref, np.gradient(x_ref, dt, axis=1), n_trials=len(grp), seeds=seeds,
                       models=models, check=False)
        samples += x_ref.size
        for b, (i, j) in enumerate(grp):
            if res.status[b] != OK:
                continue
            w = slice(n - n_meas[i, j], n)
            t, f = k[w] * dt, layout[j].f_adj
            R = sine_phasor(t, x_ref[b, w], f)
            T_sim[i, j] = sine_phasor(t, res.y[b, w], f) / R
            u_amp[i, j] = abs(sine_phasor(t, res.u[b, w], f))
    return T_sim, u_amp, samples


# =========================================================================== nominal model (Table C.1)
def nominal_fit(freqs_hz, G, f_max: float = NOMINAL_FIT_MAX_HZ) -> tuple[float, float]:
    """Table C.1's nominal plant ``G_n(s) = Z / (s (s + P))`` (Eq. C.1) fitted to a plant FRF.

    App. C.2.1: "P and Z ... are obtained through least-squares-fitting of the low frequency
    portion of the measured plant dynamics in the gross motion regime", the 1.5 A FRF below
    100 Hz. The fit here is the linear (equation-error) least squares of
    ``s^2 G + P s G = Z`` over the measured points below ``f_max``: for a rigid mass ``m`` with
    viscous damping ``c`` it returns ``P = c / m`` and ``Z = 1 / m`` exactly. ``P`` is the
    damping per unit mass the FRF shows in that band: with Coulomb sliding alone it comes only
    from the friction's describing function (``~4 F_C w / (pi A)``, growing with frequency).

    Parameters
    ----------
    freqs_hz : array_like
        Frequencies [Hz] (points with a non-finite ``G`` are skipped).
    G : array_like of complex
        Plant FRF, force command [N] -> position [m].
    f_max : float
        Upper end of the fitted band [Hz].

    Returns
    -------
    P : float
        Pole [1/s].
    Z : float
        Gain [1/kg] per newton (Table C.1's ``Z`` [N/(A kg)] is this times the force constant);
        nan, nan with fewer than 2 points in the band.

    Examples
    --------
    >>> f = np.linspace(10.0, 100.0, 10)
    >>> s = 2j * np.pi * f
    >>> P, Z = nominal_fit(f, 0.5 / (s * (s + 120.0)))       # 2 kg, c = 240 N s/m
    >>> round(P, 6), round(Z, 6)
    (120.0, 0.5)
    """
    f = np.asarray(freqs_hz, float)
    G = np.asarray(G, complex)
    ok = np.isfinite(G) & (f <= f_max) & (f > 0)
    if ok.sum() < 2:
        return math.nan, math.nan
    s, g = 2j * np.pi * f[ok], G[ok]
    A = np.column_stack([s * g, -np.ones_like(g)])
    b = -s ** 2 * g
    P, Z = np.linalg.lstsq(np.vstack([A.real, A.imag]), np.concatenate([b.real, b.imag]), rcond=None)[0]
    return float(P), float(Z)


# =========================================================================== controller and loop
def _ss1(a, b, c, d, z):
    return d + c * b / (z - a)


def _ss2(m, p, z):
    a00, a01, a10, a11 = (getattr(m, f"{p}_a{ij}") for ij in ("00", "01", "10", "11"))
    b0, b1, c0, c1, d = (getattr(m, f"{p}_{n}") for n in ("b0", "b1", "c0", "c1", "d"))
    det = (z - a00) * (z - a11) - a01 * a10
    x0 = ((z - a11) * b0 + a01 * b1) / det
    x1 = (a10 * b0 + (z - a00) * b1) / det
    return d + c0 * x0 + c1 * x1


def controller_frf(preset, freqs_hz) -> dict:
    """Discrete-time FRFs of the case's servo (as :func:`stage_control.servo.servo_step`).

    The servo computes ``u = C (r - y) - Q G_n^-1 y + Q z^-1 u`` (no DOB: the last two are 0).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The case's stage and controller (its control rate).
    freqs_hz : array_like
        Frequencies [Hz].

    Returns
    -------
    dict
        ``C`` (PID: ``kp + ki dt / (1 - z^-1) + D(z)`` [N/m]), ``QGinv`` (``Q G_n^-1`` [N/m]) and
        ``Qd`` (``Q z^-1``), complex arrays over ``freqs_hz``; ``dob`` (bool).
    """
    m = build_servo(preset.controller, preset.stage)
    if preset.controller.feedforward is not None or preset.controller.niasa is not None:
        raise ValueError("frequency_response: the loop is calculated for a linear servo (PID [+ DOB]); "
                         "feedforward and NIASA are not linear")
    w = 2 * np.pi * np.asarray(freqs_hz, float)
    z = np.exp(1j * w * m.dt)
    C = m.kp + m.ki * m.dt / (1 - 1 / z) + _ss1(m.d_a, m.d_b, m.d_c, m.d_d, z)
    if m.dob:
        qg, qd = _ss2(m, "qg", z), _ss2(m, "q", z) / z
    else:
        qg, qd = np.zeros_like(z), np.zeros_like(z)
    return {"C": C, "QGinv": qg, "Qd": qd, "dob": bool(m.dob)}


def loop_frfs(preset, freqs_hz, G) -> dict:
    """Loop, closed loop and augmented plant of the case's servo on a measured plant FRF.

    With ``u = C (r - y) - Q G_n^-1 y + Q z^-1 u`` and ``y = G u``:

    * ``L = G (C + Q G_n^-1) / (1 - Q z^-1)``: the loop broken at the plant input (the
      margins' loop; without DOB ``L = C G``);
    * ``T = C G_aug / (1 + C G_aug)``: reference to measured position;
    * ``G_aug = G / (1 - Q z^-1 + Q G_n^-1 G)``: Eq. C.5 with the servo's one-sample ``Q`` path
      (without DOB ``G_aug = G``).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The case's stage and controller.
    freqs_hz : array_like
        (nf,) frequencies [Hz].
    G : numpy.ndarray
        (..., nf) complex plant FRF [m/N].

    Returns
    -------
    dict
        ``L``, ``T``, ``G_aug`` (complex arrays like ``G``) and the controller FRFs.
    """
    c = controller_frf(preset, freqs_hz)
    G = np.asarray(G, complex)
    den = 1.0 - c["Qd"] + c["QGinv"] * G
    G_aug = G / den
    L = G * (c["C"] + c["QGinv"]) / (1.0 - c["Qd"])
    CG = c["C"] * G_aug
    return {"L": L, "T": CG / (1.0 + CG), "G_aug": G_aug, **c}
