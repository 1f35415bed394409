"""Frequency-response campaigns: amplitude-dependent FRFs, bandwidth and margins (seed Sec. 4.3, App. C.2).

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
   :func:`experiment_runner.batch.simulate` always closes the servo loop, so it cannot apply
   a force command in open loop). Each column starts at rest, ramps the sine in over a
   raised-cosine envelope (no net impulse, so a sliding stage does not drift), waits for the
   transients and fits ``a cos + b sin + c + d t`` to the position (encoder reading, or the
   true table position; drive noise included) over a window of whole periods
   (:func:`experiment_runner.metrics.sine_phasor`). Cases on the same stage share the plant FRF.
2. **Loop** (:func:`loop_frfs`): the case's discrete controller (PID with derivative filter
   and backward-Euler integral, and the DOB of Eq. C.1-C.3 if the preset has one, exactly as
   :func:`stage_control.servo.servo_step` implements them) in the frequency domain; the loop
   broken at the plant input ``L``, the closed loop ``T`` (reference to measured position)
   and the augmented plant ``G_aug`` of Eq. C.5.
3. **Metrics**: ``bandwidth_hz`` (:func:`stage_control.tuning.closed_loop_bandwidth` of
   ``T``), ``gain_margin_db`` and ``phase_margin_deg`` (:func:`stage_control.tuning.loop_margins`: python-control
   on an FRD of ``L``).
4. Optionally (``simulate_closed_loop``) **the closed loop itself** on the batch engine
   (:func:`closed_loop_frf`, :func:`experiment_runner.batch.simulate` over a batch of
   amplitudes x frequencies) at the force amplitudes: a check of the LTI assumption.

Campaign files use ``test: {kind: frequency_response, ...}`` (:class:`FrequencyResponseTest`);
conditions are the force amplitudes. :func:`run_frf_campaign` (called by
:func:`experiment_runner.campaign.run_campaign`) writes ``results.json``, ``results.csv``,
``frf.csv`` (every FRF point, SI units, Hz), ``report.md`` and Bode plots.
"""
from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple, Optional

import numba
import numpy as np
from numba import njit, prange
from pydantic import Field, model_validator

from experiment_runner.metrics import finite_or_none, sine_phasor
from stage_sim.config import NonNeg, Pos, _Strict
from stage_control.tuning import LoopMargins, closed_loop_bandwidth, loop_margins
from stage_sim.plant import OK, init_plant_state, plant_step, quantize

__all__ = ["FrequencyResponseTest", "FRF_METRICS", "FRF_METRIC_INFO", "frequency_grid",
           "plant_frf", "PlantFrf", "closed_loop_frf", "controller_frf", "loop_frfs",
           "run_frf_campaign", "write_frf_plots", "write_frf_report"]

FRF_METRICS = ("bandwidth_hz", "gain_margin_db", "phase_margin_deg")
FRF_METRIC_INFO = {  # label, display unit, scale from SI
    "bandwidth_hz": ("-3 dB closed-loop bandwidth", "Hz", 1.0),
    "gain_margin_db": ("gain margin", "dB", 1.0),
    "phase_margin_deg": ("phase margin", "°", 1.0),
}


# =========================================================================== schema
class FrequencyResponseTest(_Strict):
    """Stepped-sine FRFs at several force amplitudes (seed Sec. 4.3): one condition per amplitude.

    Every amplitude x frequency is an independent column starting at rest: a sine force of
    the amplitude, ramped in over ``max(ramp_cycles / f, min_ramp_time)``, then
    ``max(settle_cycles / f, min_settle_time)`` for the transients, then the measurement
    window: the base window of ``max(cycles, ceil(min_measure_time f))`` whole periods (the
    frequency is adjusted by less than half a sample per window so that it holds whole
    samples), repeated until it lasts ``measure_force_time / amplitude^2``.
    """
    kind: Literal["frequency_response"]
    amplitudes: list[Pos] = Field(min_length=1,
                                  description="force amplitudes at the plant input [N], one condition each")
    f_min: Pos = Field(description="lowest frequency [Hz]")
    f_max: Pos = Field(description="highest frequency [Hz] (below the Nyquist frequency)")
    points_per_decade: int = Field(30, ge=2, le=200, description="log-spaced frequencies per decade")
    cycles: int = Field(8, ge=1, le=1000, description="measured periods per frequency (at least)")
    min_measure_time: NonNeg = Field(0.1, description="measurement window at least [s]")
    measure_force_time: Optional[NonNeg] = Field(
        None, description="window at least this / amplitude^2 [N^2 s] (whole multiples of the base window): the "
                          "drive noise is the same force at every amplitude, so a given FRF scatter needs a window "
                          "growing as 1/amplitude^2")
    ramp_cycles: NonNeg = Field(3.0, description="raised-cosine ramp-in [periods]")
    min_ramp_time: NonNeg = Field(0.1, description="ramp-in at least [s]")
    settle_cycles: NonNeg = Field(3.0, description="wait after the ramp [periods]")
    min_settle_time: NonNeg = Field(1.0, description="wait after the ramp at least [s] (light damping rings long)")
    sensor: Literal["encoder", "true"] = Field(
        "encoder", description="position measured: the encoder reading (quantised) or the true table position")
    simulate_closed_loop: bool = Field(
        False, description="also simulate each case's closed loop at the force amplitudes on the batch engine "
                           "(a check of the LTI assumption; see frf_campaign.closed_loop_frf)")
    max_displacement: Pos = Field(
        2e-3, description="skip frequencies at which an amplitude above the stage's total Coulomb force would "
                          "slide the rigid stage by more than this [m] (A / (m w^2)); the travel limits the seed too")

    @model_validator(mode="after")
    def _check(self):
        if not self.f_min < self.f_max:
            raise ValueError(f"f_min={self.f_min} must be below f_max={self.f_max}")
        if len(set(self.amplitudes)) != len(self.amplitudes):
            raise ValueError("amplitudes must be distinct")
        return self


def frequency_grid(test: FrequencyResponseTest) -> np.ndarray:
    """Nominal log-spaced frequencies [Hz] from ``f_min`` to ``f_max`` (both included).

    >>> t = FrequencyResponseTest(kind="frequency_response", amplitudes=[1.0], f_min=1.0, f_max=100.0,
    ...                           points_per_decade=2)
    >>> frequency_grid(t).round(3).tolist()
    [1.0, 3.162, 10.0, 31.623, 100.0]
    """
    n = max(2, int(round(math.log10(test.f_max / test.f_min) * test.points_per_decade)) + 1)
    return np.logspace(math.log10(test.f_min), math.log10(test.f_max), n)



# =========================================================================== open-loop kernel
@njit(cache=True, parallel=True)
def _open_loop(pm, amp, omega, n_ramp, seeds, true_position, z, fr, ps, dbuf, f, zn, force, out_y, status):
    """Open-loop sine forces on the plant; arrays are (chunk, ..., column).

    Column ``b`` gets ``u[k] = amp * env[k] * sin(omega * k * dt)`` with the raised-cosine
    envelope ``env = (1 - cos(pi k / n_ramp)) / 2`` for ``k < n_ramp`` (then 1); ``out_y[c, k, b]``
    is the encoder reading (or, with ``true_position``, the true table position) at the start of
    sample ``k`` (before ``u[k]`` acts), as the servo sees it.
    """
    n_chunks, n_steps, nb = out_y.shape
    dt = pm.dt
    for c in prange(n_chunks):
        zc, frc, psc, dbc, fc, znc, forc = z[c], fr[c], ps[c], dbuf[c], f[c], zn[c], force[c]
        st, seed = status[c], seeds[c]
        meas = np.empty((2, nb))
        u = np.zeros(nb)
        zero = np.zeros(nb)
        one = np.ones(nb)
        for b in range(nb):
            meas[0, b] = quantize(zc[0, b], pm.q_table)
            meas[1, b] = 0.0
        for k in range(n_steps):
            for b in range(nb):
                env = 1.0
                if k < n_ramp[c, b]:
                    env = 0.5 * (1.0 - math.cos(math.pi * k / n_ramp[c, b]))
                u[b] = amp[c, b] * env * math.sin(omega[c, b] * k * dt)
                out_y[c, k, b] = zc[0, b] if true_position else meas[0, b]
            plant_step(pm, zc, frc, psc, dbc, fc, znc, forc, u, zero, zero, one, k, seed, meas, st)


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
    """Total Coulomb (gross-sliding) friction force of a linear stage [N]: bearings and table."""
    tot = 0.0
    items = [b.friction for b in preset.stage.bearings]
    if preset.stage.table_friction is not None:
        items.append(preset.stage.table_friction)
    for fr in items:
        tot += float(getattr(fr, "f_c", 0.0) or 0.0)
    return tot


def moving_mass(preset) -> float:
    """Table + bearings + structural-mode masses [kg] (the rigid stage in gross motion)."""
    st = preset.stage
    m = st.table.mass * (1.0 + sum(md.mass_ratio for md in st.modes))
    return m + sum(b.mass for b in st.bearings)


@dataclass
class PlantFrf:
    """Measured plant FRFs of one preset: rows = amplitudes, columns = frequencies."""
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
    models : experiment_runner.batch.Models, optional
        Compiled models of ``preset`` (only ``plant`` is used).

    Returns
    -------
    PlantFrf
        ``G[i, j]`` from the force command [N] to the position [m] at sample ``k`` (encoder
        reading, or the true table position with ``test.sensor == "true"``; the command of
        sample ``k`` acts over ``[k, k+1)``): the plant the discrete servo sees.
    """
    from experiment_runner.batch import Models, _chunked, _unchunked
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
        st = init_plant_state(pm, n_chunks * size, 0.0, sai_mode=1.0)
        plant = [np.ascontiguousarray(np.moveaxis(a.reshape(a.shape[:-1] + (n_chunks, size)), -2, 0)) for a in st]
        out_y = np.zeros((n_chunks, T, size))
        stat = np.zeros((n_chunks, size), np.int64)
        _open_loop(pm, _chunked(amp, n_chunks, size), _chunked(om, n_chunks, size), _chunked(nr, n_chunks, size),
                   _chunked(seeds, n_chunks, size), test.sensor == "true", *plant, out_y, stat)
        y = _unchunked(out_y, B)
        stat = _unchunked(stat, B)
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
    system"): column ``(i, j)`` runs the case's closed loop (:func:`experiment_runner.batch.simulate`)
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
    models : experiment_runner.batch.Models, optional
        Compiled models of ``preset``.
    max_batch : int
        Columns per :func:`~experiment_runner.batch.simulate` call (bounds the memory of its
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
    from experiment_runner.batch import Models, simulate
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

    Returns
    -------
    dict
        ``C`` (PID: ``kp + ki dt / (1 - z^-1) + D(z)`` [N/m]), ``QGinv`` (``Q G_n^-1`` [N/m]) and
        ``Qd`` (``Q z^-1``), complex arrays over ``freqs_hz``; ``dob`` (bool).
    """
    from stage_control.servo import build_servo
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




# =========================================================================== campaign
@dataclass
class FrfRun:
    """One case at one amplitude (a campaign condition)."""
    case: str
    cond: object                # campaign.Condition
    preset: object
    overrides: dict
    freqs_hz: np.ndarray
    G: np.ndarray               # plant, force -> position [m/N]
    G_aug: np.ndarray           # augmented plant (Eq. C.5; = G without DOB)
    L: np.ndarray               # loop at the plant input
    T: np.ndarray               # closed loop, reference -> position
    values: dict                # metric -> float
    margins: LoopMargins
    status: np.ndarray
    stats: dict = field(default_factory=dict)   # metric -> campaign.Stat (one value)
    wall_s: float = 0.0
    T_sim: Optional[np.ndarray] = None          # closed loop simulated at the force amplitude (batch engine)
    u_amp: Optional[np.ndarray] = None          # force amplitude it reached [N]
    bandwidth_sim_hz: float = math.nan          # -3 dB bandwidth of T_sim


def _seed_number(camp, case: str, metric: str, cond) -> float | None:
    """The seed's value of ``metric`` of ``case`` at ``cond``; None if none or only a limit ('< 10 Hz')."""
    for v in camp.seed.values:
        if v.case == case and v.metric == metric and cond.matches(**v.at()):
            return v.value if v.bound == "value" else None
    return None


def evaluate_frf_findings(camp, runs: dict) -> list[dict]:
    """Direction of every seed finding: one deterministic value per case and amplitude.

    A finding compares ``metric`` of ``case`` at its amplitude with ``versus`` at
    ``versus_amplitude`` (default: the same amplitude). 'lower' / 'higher' agree when the
    sign matches, 'similar' when the relative change ``(case - versus) / |versus|`` is within
    the tolerance.
    """
    from experiment_runner.campaign import conditions
    conds = conditions(camp)
    out = []
    for f in camp.seed.findings:
        ca = next(c for c in conds if c.matches(**f.at()))
        cb = ca if f.versus_amplitude is None else next(c for c in conds if c.matches(amplitude=f.versus_amplitude))
        a = runs[(f.case, ca.key)].values[f.metric]
        b = runs[(f.versus, cb.key)].values[f.metric]
        sa, sb = _seed_number(camp, f.case, f.metric, ca), _seed_number(camp, f.versus, f.metric, cb)
        seed_rel = (sa - sb) / abs(sb) if sa is not None and sb not in (None, 0) else None
        ok = math.isfinite(a) and math.isfinite(b)
        rel = (a - b) / abs(b) if ok and b != 0 else (math.nan if not ok else math.copysign(math.inf, a - b))
        if not ok:
            agrees, status = False, "undefined (" + ", ".join(
                f"{who} has no {f.metric} in the measured range" for who, v in ((f.case, a), (f.versus, b))
                if not math.isfinite(v)) + ")"
        elif f.direction == "similar":
            agrees = abs(rel) <= f.tolerance
            status = f"within ±{f.tolerance:.0%}" if agrees else f"differs by {rel:+.0%} (> ±{f.tolerance:.0%})"
        else:
            agrees = (a < b) if f.direction == "lower" else (a > b)
            status = "agrees" if agrees else "opposite direction"
        label = ca.label if cb is ca else f"{ca.label} vs {cb.label}"
        out.append({"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": label,
                    "condition_key": ca.key, "versus_condition_key": cb.key, **ca.at(),
                    "versus_amplitude": cb.amplitude, "metric": f.metric, "direction": f.direction,
                    "tolerance": f.tolerance if f.direction == "similar" else None,
                    "seed_case": sa, "seed_versus": sb, "seed_change": seed_rel,
                    "sim_case": a if math.isfinite(a) else None, "sim_versus": b if math.isfinite(b) else None,
                    "sim_change": rel if math.isfinite(rel) else None,
                    "z": None, "agrees": bool(agrees), "status": status, "notes": [],
                    "explanation": f.note if not agrees else "", "note": f.note})
    return out


def seed_bound_check(camp, runs: dict) -> list[dict]:
    """Every seed value vs the simulation (``bound: upper/lower`` values are limits the seed states)."""
    from experiment_runner.campaign import conditions
    rows = []
    conds = conditions(camp)
    for v in camp.seed.values:
        cond = next(c for c in conds if c.matches(**v.at()))
        sim = runs[(v.case, cond.key)].values[v.metric]
        bound = v.bound
        ok = None
        if math.isfinite(sim):
            ok = sim <= v.value if bound == "upper" else (sim >= v.value if bound == "lower" else None)
        rows.append({"case": v.case, "condition": cond.label, "amplitude_n": cond.amplitude, "metric": v.metric,
                     "seed": v.value, "bound": bound, "source": v.source, "sim": sim if math.isfinite(sim) else None,
                     "sim_over_seed": sim / v.value if math.isfinite(sim) and v.value else None,
                     "within_bound": ok})
    return rows


def run_frf_campaign(camp, out_dir, *, progress: bool = True, report: bool = True, plots: bool = True,
                     graph: bool = False):
    """Run a ``frequency_response`` campaign: plant FRFs of every case (all amplitudes and
    frequencies in one batch per case), loops, metrics, findings; write the outputs.

    ``graph`` must be False: the FRFs are open-loop runs of the compiled plant, there is no
    closed-loop trial to re-run through the ROS graph.

    Returns
    -------
    experiment_runner.campaign.CampaignRun
        ``runs[(case, condition key)]`` are :class:`FrfRun`.
    """
    from tqdm import tqdm

    from experiment_runner.batch import Models
    from experiment_runner.campaign import CampaignRun, Stat, case_overrides, case_preset, conditions, write_outputs
    from stage_sim.config import ConfigError
    if graph:
        raise ConfigError(f"{camp.name}: --graph does not apply to a frequency_response campaign "
                          "(open-loop FRFs on the compiled plant)")
    t_start = time.monotonic()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    conds = conditions(camp)
    test = camp.test
    runs, samples, plants = {}, 0, {}
    with tqdm(total=len(camp.cases), desc=f"{camp.name}: FRFs", unit="case", file=sys.stderr,
              disable=not progress, leave=False) as bar:
        for case in camp.cases:
            preset = case_preset(camp, case)
            models = Models.from_preset(preset)
            # the plant FRF does not depend on the controller: cases on the same stage share it
            key = (preset.stage.model_dump_json(), preset.simulation.model_dump_json(), preset.controller.rate)
            if key not in plants:
                plants[key] = plant_frf(preset, test, models=models)
                samples += plants[key].samples
            pf = plants[key]
            if test.simulate_closed_loop:
                T_sim, u_amp, n = closed_loop_frf(preset, test, pf, models=models)
                samples += n
            for i, cond in enumerate(conds):
                ok = np.isfinite(pf.G[i])
                f, G = pf.freqs_hz[ok], pf.G[i, ok]
                lf = loop_frfs(preset, f, G)
                bw = closed_loop_bandwidth(f, lf["T"]) if f.size > 1 else math.nan
                mg = loop_margins(f, lf["L"]) if f.size > 2 else LoopMargins(math.nan, math.nan, math.nan,
                                                                             math.nan, 0)
                vals = {"bandwidth_hz": bw, "gain_margin_db": mg.gain_margin_db,
                        "phase_margin_deg": mg.phase_margin_deg}

                def full(x):
                    a = np.full(pf.freqs_hz.shape, np.nan + 0j)
                    a[ok] = x
                    return a
                runs[(case.name, cond.key)] = FrfRun(
                    case=case.name, cond=cond, preset=preset, overrides=case_overrides(camp, case),
                    freqs_hz=pf.freqs_hz, G=pf.G[i].copy(), G_aug=full(lf["G_aug"]), L=full(lf["L"]),
                    T=full(lf["T"]), values=vals, margins=mg, status=pf.status[i].copy(),
                    stats={m: Stat.of([v if math.isfinite(v) else None]) for m, v in vals.items()},
                    wall_s=pf.wall_s / len(conds))
                if test.simulate_closed_loop:
                    r = runs[(case.name, cond.key)]
                    r.T_sim, r.u_amp = T_sim[i], u_amp[i]
                    okc = np.isfinite(T_sim[i])
                    r.bandwidth_sim_hz = closed_loop_bandwidth(pf.freqs_hz[okc], T_sim[i, okc]) \
                        if okc.sum() > 1 else math.nan
            bar.update(1)
    timing = {"simulation_s": time.monotonic() - t_start, "column_samples": samples}
    findings = evaluate_frf_findings(camp, runs)
    settings = {"trials": 1, "test": test.model_dump(), "calibrated": False, "graph": False,
                "frequencies_hz": frequency_grid(test).tolist()}
    cr = CampaignRun(campaign=camp, out_dir=out_dir, conditions=conds, runs=runs, findings=findings,
                     calibration=None, step_ii={}, settings=settings, timing=timing)
    write_outputs(cr, write_frf_results, report=report, plots=plots, t_start=t_start)
    return cr


# =========================================================================== outputs
def write_frf_results(cr) -> None:
    """``results.json`` (metrics, findings, seed checks, every FRF), ``results.csv`` (metrics)
    and ``frf.csv`` (one row per case x amplitude x frequency); SI units, Hz, dB, degrees."""
    from experiment_runner.report import write_rows_csv
    from experiment_runner.campaign import _clean
    camp = cr.campaign
    rows = []
    for case in camp.cases:
        for cond in cr.conditions:
            r = cr.runs[(case.name, cond.key)]
            for m in FRF_METRICS:
                seed = camp.seed_value(case.name, m, **cond.at())
                rows.append({"campaign": camp.name, "case": case.name, "case_label": case.label,
                             "condition": cond.key, "condition_label": cond.label, "amplitude_n": cond.amplitude,
                             "metric": m, "value": finite_or_none(r.values[m]), "seed": seed,
                             "baseline": case.name == camp.baseline})
    write_rows_csv(cr.out_dir / "results.csv", rows)
    with open(cr.out_dir / "frf.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["case", "amplitude_n", "frequency_hz", "status", "G_re_m_per_n", "G_im_m_per_n",
                    "G_aug_re_m_per_n", "G_aug_im_m_per_n", "L_re", "L_im", "T_re", "T_im",
                    "T_sim_re", "T_sim_im", "u_amp_sim_n"])
        for (case, _), r in cr.runs.items():
            nan = np.full(r.freqs_hz.shape, np.nan)
            t_sim = r.T_sim if r.T_sim is not None else nan + 0j
            u_amp = r.u_amp if r.u_amp is not None else nan
            for j, fr in enumerate(r.freqs_hz):
                vals = [r.G[j], r.G_aug[j], r.L[j], r.T[j], t_sim[j]]
                w.writerow([case, r.cond.amplitude, f"{fr:.8g}", int(r.status[j])]
                           + [("" if not np.isfinite(x) else f"{x:.10g}") for v in vals for x in (v.real, v.imag)]
                           + ["" if not np.isfinite(u_amp[j]) else f"{u_amp[j]:.10g}"])
    frfs = [{"case": case, "condition": key, "amplitude_n": r.cond.amplitude, "freqs_hz": r.freqs_hz,
             "status": r.status, **{f"{n}_{part}": getattr(getattr(r, n), part) for n in ("G", "G_aug", "L", "T")
                                    for part in ("real", "imag")},
             "margins": r.margins._asdict(),
             **({"T_sim_real": r.T_sim.real, "T_sim_imag": r.T_sim.imag, "u_amp_sim_n": r.u_amp,
                 "bandwidth_sim_hz": r.bandwidth_sim_hz} if r.T_sim is not None else {})}
            for (case, key), r in cr.runs.items()]
    doc = {"campaign": camp.name, "title": camp.title, "description": camp.description,
           "seed_source": camp.seed.source, "seed_notes": camp.seed.notes, "baseline": camp.baseline,
           "kind": "frequency_response", "settings": cr.settings, "timing_s": cr.timing,
           "units": {"G": "m/N", "frequency": "Hz", "bandwidth_hz": "Hz", "gain_margin_db": "dB",
                     "phase_margin_deg": "deg", "amplitude_n": "N"},
           "cases": [{"name": c.name, "label": c.label, "preset": c.preset, "description": c.description,
                      "overrides": cr.runs[(c.name, cr.conditions[0].key)].overrides} for c in camp.cases],
           "conditions": [{"key": c.key, "label": c.label, **c.at()} for c in cr.conditions],
           "results": rows, "findings": cr.findings, "seed_checks": seed_bound_check(camp, cr.runs), "frf": frfs,
           "files": {k: [str(x) for x in v] if isinstance(v, list) else str(v) for k, v in cr.files.items()}}
    (cr.out_dir / "results.json").write_text(json.dumps(_clean(doc), indent=1, allow_nan=False))


def _fmt(v, metric) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    if metric == "bandwidth_hz":
        return f"{v:.3g} Hz"
    if metric == "gain_margin_db":
        return f"{v:.1f} dB"
    return f"{v:.1f}°"


def write_frf_plots(cr) -> list:
    """Bode plots (plant, augmented plant with DOB, closed loop) per case, every amplitude,
    and bandwidth / margins vs amplitude (Fig. 4.6 / C.10 style); returns the PNG paths."""
    from experiment_runner.report import _plt
    plt = _plt()
    out = cr.out_dir / "plots"
    out.mkdir(exist_ok=True)
    camp = cr.campaign
    files = []
    cmap = plt.get_cmap("viridis")
    na = len(cr.conditions)
    for case in camp.cases:
        r0 = cr.runs[(case.name, cr.conditions[0].key)]
        kinds = [("G", "plant G (force → position)", "m/N")]
        if np.any(np.isfinite(r0.G_aug) & (np.abs(r0.G_aug - r0.G) > 1e-12 * np.abs(r0.G))):
            kinds.append(("G_aug", "augmented plant G_aug (Eq. C.5)", "m/N"))
        kinds.append(("T", "closed loop T (reference → position)", "-"))
        fig, axes = plt.subplots(2, len(kinds), figsize=(5.2 * len(kinds), 7), sharex=True, squeeze=False)
        for col, (attr, title, unit) in enumerate(kinds):
            for i, cond in enumerate(cr.conditions):
                r = cr.runs[(case.name, cond.key)]
                h = getattr(r, attr)
                ok = np.isfinite(h)
                c = cmap(i / max(na - 1, 1))
                axes[0, col].semilogx(r.freqs_hz[ok], 20 * np.log10(np.abs(h[ok])), color=c, lw=1.2,
                                      label=cond.label)
                ph = np.degrees(np.unwrap(np.angle(h[ok])))      # starts in (-180, 180]
                axes[1, col].semilogx(r.freqs_hz[ok], ph, color=c, lw=1.2)
                if attr == "T" and r.T_sim is not None:        # closed loop simulated at this amplitude
                    oks = np.isfinite(r.T_sim)
                    axes[0, col].semilogx(r.freqs_hz[oks], 20 * np.log10(np.abs(r.T_sim[oks])), "o", ms=2.5,
                                          color=c, mfc="none")
            axes[0, col].set_title(title + (" (o: simulated)" if attr == "T" and r0.T_sim is not None
                                            else ""))
            axes[0, col].set_ylabel(f"magnitude [dB re 1 {unit}]")
            axes[1, col].set_ylabel("phase [°]")
            axes[1, col].set_xlabel("frequency [Hz]")
            if attr == "T":
                axes[0, col].axhline(-3.0, color="k", ls=":", lw=0.8)
            for ax in axes[:, col]:
                ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].legend(fontsize=7, title="force amplitude", title_fontsize=7)
        fig.suptitle(f"{camp.title}: {case.label}")
        fig.tight_layout()
        path = out / f"bode_{case.name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        files.append(path)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for k, case in enumerate(camp.cases):
        a = [c.amplitude for c in cr.conditions]
        for ax, m in zip(axes, FRF_METRICS):
            v = [cr.runs[(case.name, c.key)].values[m] for c in cr.conditions]
            ax.semilogx(a, v, "o-", color=f"C{k % 10}", label=case.label)
    for ax, m in zip(axes, FRF_METRICS):
        ax.set_xlabel("force amplitude [N]")
        ax.set_ylabel(f"{FRF_METRIC_INFO[m][0]} [{FRF_METRIC_INFO[m][1]}]")
        ax.grid(True, which="both", alpha=0.3)
        if m != "bandwidth_hz":
            ax.axhline(0.0, color="k", lw=0.8)
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{camp.title}: bandwidth and margins vs amplitude")
    fig.tight_layout()
    path = out / "bandwidth_margins.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    files.append(path)
    return files


def frf_table(cr, metric) -> list[str]:
    """Markdown rows of one metric: amplitude x case (the seed's number or limit where it states one)."""
    camp = cr.campaign
    lines = ["| amplitude | " + " | ".join(c.label for c in camp.cases) + " |", "|---|" + "---|" * len(camp.cases)]
    bounds = {(s["case"], s["condition"]): s for s in seed_bound_check(camp, cr.runs) if s["metric"] == metric}
    for cond in cr.conditions:
        cells = []
        for case in camp.cases:
            s = _fmt(cr.runs[(case.name, cond.key)].values[metric], metric)
            b = bounds.get((case.name, cond.label))
            if b is not None:
                sym = {"upper": "≤ ", "lower": "≥ "}.get(b["bound"], "")
                s += f" (seed {sym}{_fmt(b['seed'], metric)})"
            cells.append(s)
        lines.append(f"| {cond.label} | " + " | ".join(cells) + " |")
    return lines


def write_frf_report(cr) -> Path:
    """``out_dir/report.md`` of a frequency-response campaign."""
    from experiment_runner.report import cases_md, findings_table, plots_md, report_head
    camp = cr.campaign
    t = camp.test
    L = report_head(camp, f"open-loop stepped-sine plant FRFs on the compiled plant ({len(t.amplitudes)} force "
                    f"amplitudes x {len(frequency_grid(t))} frequencies {t.f_min:g}–{t.f_max:g} Hz per case, "
                    f"{cr.timing.get('column_samples', 0) / 1e6:.1f} M column-samples), loops calculated with each "
                    f"case's discrete servo; wall time {cr.timing.get('total_s', math.nan):.1f} s.")
    L += ["## Bandwidth and margins per amplitude", "",
          "BW: -3 dB bandwidth of the closed loop T (reference → measured position); GM / PM: margins of the loop "
          "broken at the plant input, at its last gain crossover (negative = the LTI loop at that amplitude is "
          "unstable); – = not in the measured range. In brackets: the seed's number or limit where its text "
          "states one.", ""]
    for m in FRF_METRICS:
        label = FRF_METRIC_INFO[m][0]
        L += [f"### {label[0].upper() + label[1:]}", ""] + frf_table(cr, m) + [""]
    if any(r.T_sim is not None for r in cr.runs.values()):
        L += ["### Closed loop simulated at each force amplitude (batch engine)", "",
              "A check of the LTI assumption (Sec. 4.3): each case's closed loop run on the batch engine with a "
              "sine reference of amplitude A·|G/T| (the reference that asks the plant input for the force "
              "amplitude A of the plant FRF if the stage were that LTI system); -3 dB bandwidth of the simulated "
              "T (calculated in brackets) and the range of force amplitudes reached over the frequencies.", "",
              "| amplitude | " + " | ".join(c.label for c in camp.cases) + " |", "|---|" + "---|" * len(camp.cases)]
        for cond in cr.conditions:
            cells = []
            for case in camp.cases:
                r = cr.runs[(case.name, cond.key)]
                ua = r.u_amp[np.isfinite(r.u_amp)] / cond.amplitude if r.u_amp is not None else np.zeros(0)
                cells.append(f"{_fmt(r.bandwidth_sim_hz, 'bandwidth_hz')} "
                             f"({_fmt(r.values['bandwidth_hz'], 'bandwidth_hz')})"
                             + (f", force {ua.min():.2f}–{ua.max():.2f} × A" if ua.size else ""))
            L.append(f"| {cond.label} | " + " | ".join(cells) + " |")
        L.append("")
    checks = seed_bound_check(camp, cr.runs)
    if checks:
        L += ["Seed numbers:", ""]
        for s in checks:
            sym = {"upper": "at most ", "lower": "at least "}.get(s["bound"], "")
            verdict = "" if s["within_bound"] is None else \
                (" — satisfied" if s["within_bound"] else " — NOT satisfied")
            L.append(f"* {camp.case(s['case']).label}, {s['condition']}: {FRF_METRIC_INFO[s['metric']][0]} seed "
                     f"{sym}{_fmt(s['seed'], s['metric'])} ({s['source']}); simulation "
                     f"{_fmt(s['sim'] if s['sim'] is not None else math.nan, s['metric'])}{verdict}.")
    L += ["", "## Findings: direction in the simulation", "",
          "One deterministic value per case and amplitude (no trial scatter): 'lower'/'higher' agree when the sign "
          "matches, 'similar' when the change is within the tolerance.", ""]
    L += findings_table(cr)
    bad = [f for f in cr.findings if not f["agrees"]]
    L += ["", f"**{len(cr.findings) - len(bad)} of {len(cr.findings)} seed findings reproduced.**", ""]
    if bad:
        L += ["Where the simulation disagrees:", ""]
        for f in bad:
            L.append(f"* **{f['id']}** ({f['claim']}): {f['status']}."
                     + (f" {f['explanation'].strip()}" if f["explanation"] else ""))
        L.append("")
    L += plots_md(cr)
    L += ["## Settings", "", f"* Test: `{t.model_dump()}`", "* Cases:"]
    L += cases_md(cr)
    L += ["", "Files: `results.json` (metrics, findings, every FRF), `results.csv` (metrics), `frf.csv` "
          "(G, G_aug, L, T per case, amplitude and frequency; SI, Hz), `plots/`.", ""]
    path = cr.out_dir / "report.md"
    path.write_text("\n".join(L))
    return path
