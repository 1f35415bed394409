"""Appendix B: averaged (MDPM) dynamics of a dithered PD-controlled stage vs the full simulation.

Seed (App. B, Fig. B.1): the rigid ALS-130H stage of Table A.1 under PD control
(``K_I = 0``) with a *traditional* dither force ``a w^2 sin(w t)`` added to the servo
force (Fig. 3.1), ``a w^2 = 2 N``, ``w = 1e4 rad/s``. The method of direct partition of
motion gives the slow dynamics Eq. (B.16), a linear 2nd-order system without any
friction stiffness, ``E_s'' + 2 zeta_eq E_s' + E_s = 0`` with
``zeta_eq = zeta + pi f_c / (4 a_bar Omega)``. The seed shows that the slow part of the
full response (4th-order Butterworth low-pass, 500 Hz) agrees with Eq. (B.16).

Dimensional form (derived from Eq. B.2/B.8, the arbitrary length ``L`` cancels)::

    pi f_c / (4 a_bar Omega) = pi F_C / (4 a w w_n)      (a = (a w^2) / w^2  [N s^2])
    c_eq = 2 m w_n zeta_eq = K_D + c_f,   c_f = pi m F_C / (2 a w) = F_C / <|v_d|>

i.e. the averaged Dahl friction is a viscous damper ``c_f = F_C / <|v_d|>`` with the
mean dither speed ``<|v_d|> = (2/pi) a w / m``. For a step of the reference ``x_r`` the
averaged closed loop is ``X_s/X_r = (K_D s + K_P) / (m s^2 + (K_D + c_f) s + K_P)``
(the ``K_D`` derivative kick of the step gives the initial condition of Eq. B.16,
``e(0+) = D``, ``de/dt(0+) = -K_D D / m``).

Full simulation (Eq. B.1): our compiled plant (``stage_sim.plant.plant_step``, exact
Dahl update, preset ``als130h``) in a small Python loop with the PD of Table A.1
computed here, ``u = K_P e + K_D (e_k - e_{k-1})/dt + a w^2 sin(w t)``. The dither at
1.59 kHz would have only 6.3 samples per period at the 10 kHz control rate (zero-order
hold: fundamental 4 % low, phase lag and 8.4/11.6 kHz images), so the loop runs at
100 kHz (``controller.rate`` override) to approximate the continuous Eq. (B.1); the
10 kHz result is reported alongside. The dither is switched on (raised-cosine ramp
over 3 ms, avoiding the drift of an abrupt ``sin`` start) 30 ms before the step, so the
step starts from the dithered steady state assumed by the averaging.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from scipy import signal

from experiment_runner.apps.paper import Claim
from experiment_runner.core import outputs
from experiment_runner.core.metrics import settling_time
from stage_sim.config import load_preset, with_overrides
from stage_sim.plant import OK, SimulationError, init_plant_state, plant_inputs, plant_step
from stage_sim.plant_model import build_plant

STEPS = (50e-9, 500e-9)          # App. A test steps [m]
DITHER_FORCE = 2.0               # a w^2 [N]
OMEGA = 1e4                      # w [rad/s]
RATE = 100_000.0                 # control rate of the full simulation [Hz]
T_PRE, T_POST, RAMP = 0.03, 0.10, 0.003     # [s]
LPF_HZ, LPF_ORDER = 500.0, 4     # seed: 4th-order Butterworth, 500 Hz
RMS_TOL = 0.05                   # agreement criterion: RMS(slow - averaged) <= 5 % of the step


def _full(preset, rate, steps, force_amp, omega):
    """Eq. (B.1): PD-controlled rigid stage + Dahl friction + dither on the servo force.

    Returns ``t`` (0 at the step) and the true table position, shape ``(len(steps), T)``.
    """
    p = with_overrides(preset, {"controller.rate": rate})
    pm = build_plant(p.stage, rate, p.simulation.max_omega_h, p.simulation.max_substeps)
    kp, kd = p.controller.pid.kp, p.controller.pid.kd
    dt = 1.0 / rate
    D = np.asarray(steps, float)
    B = D.size
    st = init_plant_state(pm, B, 0.0)
    inp = plant_inputs(B)                   # u set below; no dither on the piezos, isolator compliant
    n_pre = int(round(T_PRE * rate))
    N = n_pre + int(round(T_POST * rate))
    x = np.empty((B, N))
    zero = np.zeros(B)
    seeds = np.zeros(B, np.int64)
    meas, status = np.zeros((2, B)), np.zeros(B, np.int64)
    meas[0] = st.z[0]
    e_prev = np.zeros(B)
    u = inp.u
    for k in range(N):
        xr = D if k >= n_pre else zero
        e = xr - meas[0]
        tk = k * dt
        env = 1.0 if tk >= RAMP else 0.5 * (1.0 - math.cos(math.pi * tk / RAMP))
        # dither evaluated at the sample midpoint: the zero-order hold then has no net delay
        u[:] = kp * e + kd * (e - e_prev) / dt + env * force_amp * math.sin(omega * (tk + 0.5 * dt))
        e_prev = e
        x[:, k] = st.z[0]
        plant_step(pm, st, inp, k, seeds, meas, status)
    if (status != OK).any():
        raise SimulationError(f"appendix B full simulation failed: status {status.tolist()}")
    return (np.arange(N) - n_pre) * dt, x


def _slow(x, rate):
    """Slow part: zero-phase 4th-order Butterworth low-pass at 500 Hz (seed Fig. B.1)."""
    b, a = signal.butter(LPF_ORDER, LPF_HZ, fs=rate)
    return signal.filtfilt(b, a, x, axis=-1)


def _averaged(m, kp, kd, c_f, t):
    """Unit-step response of Eq. (B.16) in dimensional form (PD derivative kick included)."""
    tt = t[t >= 0]
    _, y, _ = signal.lsim(signal.lti([kd, kp], [m, kd + c_f, kp]), np.ones_like(tt), tt)
    out = np.zeros_like(t)
    out[t >= 0] = y
    return out


def _averaged_maxwell(m, kp, kd, c_f, k_sigma, t):
    """Unit-step response when the averaged Dahl friction keeps its relaxation.

    Averaging Eq. (B.9) without assuming ``<df/dt> = 0`` gives
    ``df_s/dt = k_sigma (v_s - f_s <|v_d|> / F_C)``: a Maxwell element (spring ``k_sigma``
    in series with the damper ``c_f``, time constant ``c_f / k_sigma``). Eq. (B.16) is its
    limit ``k_sigma -> inf``. Used only as a diagnostic of the residual difference.
    """
    tau = c_f / k_sigma
    num = np.polymul([kd, kp], [tau, 1.0])
    den = np.polyadd(np.polymul([m, kd, kp], [tau, 1.0]), [c_f, 0.0])
    tt = t[t >= 0]
    _, y, _ = signal.lsim(signal.lti(num, den), np.ones_like(tt), tt)
    out = np.zeros_like(t)
    out[t >= 0] = y
    return out


def _settle(t, x, target, window, hold=0.02):
    """Settling time [s] after t = 0; nan unless the band is held for the last ``hold`` s."""
    ts = settling_time(t, x, target, 0.0, window)
    return float("nan") if not ts <= t[-1] - hold else float(ts)


def claims(out: Path) -> list[Claim]:
    out = outputs.prepare_folder(out)
    t0 = time.perf_counter()
    preset = load_preset("als130h")
    m = preset.stage.table.mass
    kp, kd, ki = preset.controller.pid.kp, preset.controller.pid.kd, preset.controller.pid.ki
    assert ki == 0.0, "Appendix B is the PD (K_I = 0) stage"
    fc = preset.stage.table_friction.f_c
    k_sigma = preset.stage.table_friction.k_sigma
    a = DITHER_FORCE / OMEGA ** 2                     # [N s^2]
    wn = math.sqrt(kp / m)
    zeta = kd / (2 * m * wn)
    # non-dimensional Eq. (B.16) with an arbitrary L (cancels) -> dimensional damping
    L = 1e-7
    a_bar, Omega, f_c_bar = a / (m * L), OMEGA / wn, fc / (m * wn ** 2 * L)
    zeta_eq = zeta + math.pi * f_c_bar / (4 * a_bar * Omega)
    c_f = math.pi * m * fc / (2 * a * OMEGA)          # = 2 m wn (zeta_eq - zeta)
    assert abs(2 * m * wn * (zeta_eq - zeta) - c_f) < 1e-6 * c_f
    relax = k_sigma * (2 / math.pi) * (a * OMEGA / m) / fc   # Dahl relaxation rate [1/s]

    t, x_full = _full(preset, RATE, STEPS, DITHER_FORCE, OMEGA)
    _, x_nod = _full(preset, RATE, STEPS, 0.0, OMEGA)
    t10, x10 = _full(preset, 10_000.0, STEPS, DITHER_FORCE, OMEGA)
    x_slow = _slow(x_full, RATE)
    x_slow10 = _slow(x10, 10_000.0)
    unit_avg = _averaged(m, kp, kd, c_f, t)
    unit_bench = _averaged(m, kp, kd, 0.0, t)          # frictionless, no dither (benchmark)
    unit_maxwell = _averaged_maxwell(m, kp, kd, c_f, k_sigma, t)
    post = t >= 0
    post10 = t10 >= 0
    unit_avg10 = _averaged(m, kp, kd, c_f, t10)

    per = {}
    for i, D in enumerate(STEPS):
        d_avg = x_slow[i, post] - D * unit_avg[post]
        d_bench = x_slow[i, post] - D * unit_bench[post]
        fast = (x_full[i] - x_slow[i])[post][-int(0.02 * RATE):]
        tail = slice(-int(0.02 * RATE), None)
        per[f"{D * 1e9:.0f}nm"] = dict(
            step=D,
            rms_slow_minus_averaged=float(np.sqrt(np.mean(d_avg ** 2))),
            max_abs_slow_minus_averaged=float(np.max(np.abs(d_avg))),
            rms_slow_minus_averaged_10kHz=float(np.sqrt(np.mean(
                (x_slow10[i, post10] - D * unit_avg10[post10]) ** 2))),
            rms_slow_minus_frictionless=float(np.sqrt(np.mean(d_bench ** 2))),
            rms_slow_minus_averaged_with_dahl_lag=float(np.sqrt(np.mean(
                (x_slow[i, post] - D * unit_maxwell[post]) ** 2))),
            settling_slow=_settle(t, x_slow[i], D, 0.2 * D),
            settling_averaged=_settle(t, D * unit_avg, D, 0.2 * D),
            settling_full_raw=_settle(t, x_full[i], D, 0.2 * D),
            settling_frictionless=_settle(t, D * unit_bench, D, 0.2 * D),
            final_slow=float(np.mean(x_slow[i, tail])),
            final_no_dither=float(x_nod[i, -1]),
            fast_vibration_pp=float(np.ptp(fast)),
        )
    ok = all(v["rms_slow_minus_averaged"] <= RMS_TOL * v["step"] for v in per.values())
    runtime = time.perf_counter() - t0

    # ---- Fig. B.1
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, (i, D) in zip(axes, enumerate(STEPS)):
        ms = 1e3 * t
        sel = t >= -0.005
        ax.plot(ms[sel], 1e9 * x_full[i, sel], color="0.75", lw=0.5, label="full dynamics (Eq. B.1)")
        ax.plot(ms[sel], 1e9 * x_slow[i, sel], "b", label="full, 500 Hz low-pass (slow part)")
        ax.plot(ms[sel], 1e9 * D * unit_avg[sel], "r--", label=f"averaged (Eq. B.16), ζ_eq={zeta_eq:.2f}")
        ax.plot(ms[sel], 1e9 * x_nod[i, sel], "k:", label="no dither")
        ax.plot(ms[sel], 1e9 * D * unit_bench[sel], "g-.", lw=0.8, label=f"frictionless, ζ={zeta:.2f}")
        ax.axhspan(0.8e9 * D, 1.2e9 * D, color="g", alpha=0.08)
        ax.set_title(f"{D * 1e9:.0f} nm step, aω² = {DITHER_FORCE} N, ω = {OMEGA:.0e} rad/s")
        ax.set_xlabel("time [ms]")
        ax.set_ylabel("position [nm]")
    axes[0].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_B1_averaged_vs_full.png", dpi=110)
    plt.close(fig)

    p50, p500 = per["50nm"], per["500nm"]
    numbers = dict(m=m, K_P=kp, K_D=kd, F_C=fc, a=a, omega=OMEGA, omega_n=wn, zeta=zeta,
                   zeta_eq=zeta_eq, c_f=c_f, dahl_relaxation_rate=relax, c_eq=kd + c_f, rate=RATE, lpf_hz=LPF_HZ,
                   rms_tolerance_fraction=RMS_TOL, runtime_s=runtime, **{
                       f"{k}.{q}": v for k, d in per.items() for q, v in d.items()})
    return [Claim(
        id="B/averaged-vs-full",
        source="App. B, Eq. B.16, Fig. B.1",
        claim=("with traditional dither (aω² = 2 N, ω = 1e4 rad/s on the servo force) the slow "
               "part of the PD stage's response follows the linear averaged dynamics Eq. B.16"),
        seed="averaged response in good agreement with the 500 Hz low-passed full response",
        ours=(f"ζ_eq = {zeta_eq:.2f} (ζ = {zeta:.3f}); RMS(slow − averaged) = "
              f"{100 * p50['rms_slow_minus_averaged'] / p50['step']:.1f} % (50 nm), "
              f"{100 * p500['rms_slow_minus_averaged'] / p500['step']:.1f} % (500 nm) of the step"),
        agrees=bool(ok),
        numbers=numbers,
        note=(f"criterion: RMS difference over 100 ms after the step ≤ {100 * RMS_TOL:.0f} % of the "
              f"step for both 50 and 500 nm. Dimensional Eq. B.16: c_eq = K_D + πmF_C/(2aω) = "
              f"{kd:.0f} + {c_f:.0f} N·s/m (a = 2 N/ω² = {a:.1e} N·s²). The largest deviations "
              f"({100 * p50['max_abs_slow_minus_averaged'] / p50['step']:.0f} % / "
              f"{100 * p500['max_abs_slow_minus_averaged'] / p500['step']:.0f} % of the step) sit ~1 ms "
              f"after the step: Eq. B.16 assumes the slow friction follows the slow speed at once, but "
              f"the averaged Dahl state relaxes at k_σ<|v_d|>/F_C ≈ {relax:.0f} 1/s (a Maxwell element "
              f"k_σ in series with c_f); keeping that lag lowers the RMS to "
              f"{100 * p50['rms_slow_minus_averaged_with_dahl_lag'] / p50['step']:.1f} % / "
              f"{100 * p500['rms_slow_minus_averaged_with_dahl_lag'] / p500['step']:.1f} %; the rest is "
              f"the 500 nm derivative-kick speed K_D·D/m = {kd * STEPS[1] / m:.1e} m/s exceeding the dither "
              f"speed aω/m = {a * OMEGA / m:.1e} m/s, against "
              f"the averaging assumption. Full sim at 100 kHz; at the 10 kHz control rate the RMS is "
              f"{100 * p50['rms_slow_minus_averaged_10kHz'] / p50['step']:.1f} % / "
              f"{100 * p500['rms_slow_minus_averaged_10kHz'] / p500['step']:.1f} %. Without dither the "
              f"stage sticks at {100 * p50['final_no_dither'] / p50['step']:.0f} % / "
              f"{100 * p500['final_no_dither'] / p500['step']:.0f} % of the step; with it the raw "
              f"response carries a {1e9 * p50['fast_vibration_pp']:.1f} nm p-p vibration, so the raw "
              f"50 nm response never holds ±10 nm (as the seed warns), while the slow part settles in {1e3 * p50['settling_slow']:.1f} ms (50 nm; "
              f"averaged model {1e3 * p50['settling_averaged']:.1f} ms)."),
    )]
