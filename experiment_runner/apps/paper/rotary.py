"""Appendix D: friction-isolated rotary roll-to-roll roller (Eq. D.1-D.4, Fig. D.5, Sec. D.4).

Frequency domain (Fig. D.5)
---------------------------
Eq. D.1-D.4 with Table D.1 (``I_p`` = 0.15, ``I_a`` = 0.015 kg·m², PID ``K_p, K_d, K_i, T_f``,
``f_Q`` = 80 Hz) and ``c_f`` = 2 N·m·s/rad (Fig. D.5 caption). Eq. D.1/D.2 were re-derived
(roller ``I_p``, two bearings ``I_a`` each tied to the roller by ``c_fi s + k_fi`` and to
ground by ``c_f s``, the same friction torque ``T_f`` on both bearings) and agree with the
text. The FI damping is "a modal damping of 0.1 %": ``c_fi = 2 ζ k_fi / ω_n`` with
``ζ`` = 0.001 and ``ω_n² = k_fi (I_p + 2 I_a)/(I_a I_p)`` the FI mode (bearings against the
roller). ``G_d`` (Eq. D.3) is evaluated from the frequency responses of ``D, G_p, G_n, C,
Q`` (python-control transfer functions); closed-loop stability is checked on the
characteristic polynomial ``N_Q D_C (N_p D_n - N_n D_p) + D_Q N_n (D_C D_p + N_C N_p)``.

Time domain (Sec. D.4, Fig. D.12)
---------------------------------
Presets ``rotary_nofi`` (c_f = 0.2), ``rotary_fi_nodamper`` (c_f = 0.2) and ``rotary_fi``
(c_f = 1.4 N·m·s/rad), Table D.2 plant, Table D.1 PID + 80 Hz DOB, 1.33 µrad encoder,
10 kHz control. Reference ``θ_r = ω t``, ``ω`` = 10 rpm, from rest; the first 2 s are
discarded (the undamped-FI transient decays with ~0.18 s: < 0.01 µrad left at 2 s, 0.1 µrad
RMS at 1 s), RMS of ``θ_r − θ_roller`` (true angle) over the next 5 s, 8 seeds. Disturbance
(the seed's bandwidth is not stated): independent Gaussian torque per bearing, white at
the 10 kHz control rate (zero-order held, flat to ~5 kHz), 0.15·√2 N·m each — the same
roller-side spectrum as the fully correlated 0.15 N·m per bearing of Eq. D.1 (preset
comment). A continuous-time prediction from Eq. D.3 with the same disturbance spectrum
(``2 σ² T_s sinc²(f T_s)``, Table D.2 values) is reported as a cross-check.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import control as ct
import numpy as np
from scipy import signal

from experiment_runner.apps.paper import Claim
from experiment_runner.core import outputs
from experiment_runner.core.batch import simulate
from stage_sim.config import load_preset, with_overrides

# ----------------------------------------------------------------------------- Table D.1
I_P, I_A = 0.15, 0.015                         # [kg m^2]
KP, KD, KI, TF = 1.54e4, 81.62, 6.16e5, 0.0005884
F_Q = 80.0                                     # [Hz]
C_F_D5 = 2.0                                   # Fig. D.5 caption [N m s/rad]
ZETA_FI = 0.001                                # "modal damping of 0.1 %"
K_FI_D5 = (30.0, 100.0, 300.0, 1000.0, 3000.0)  # [N m/rad]; Table D.2 has 324.85, Fig. D.6 300
F_AXIS = np.logspace(-1, np.log10(2000.0), 3000)

# ----------------------------------------------------------------------------- Sec. D.4
SEED_RMS = {"No FI": 1.41e-6, "FI w/o damper": 2.62e-6, "FI w/ damper": 0.91e-6}   # [rad]
PRESETS = {"No FI": "rotary_nofi", "FI w/o damper": "rotary_fi_nodamper", "FI w/ damper": "rotary_fi"}
RPM = 10.0
T_SIM, T_SKIP, N_SEEDS = 7.0, 2.0, 8
RATIO_TOL = 0.20                               # ratios within +-20 % of the seed's
SIGMA = 0.15                                   # [N m] per bearing, correlated (seed)


# ============================================================================= Eq. D.1-D.4
def fi_damping(k_fi, i_p=I_P, i_a=I_A, zeta=ZETA_FI):
    """c_fi giving modal damping ``zeta`` to the FI mode [N m s/rad]."""
    wn = math.sqrt(k_fi * (i_p + 2 * i_a) / (i_a * i_p))
    return 2.0 * zeta * k_fi / wn, wn


def blocks(k_fi=None, c_fi=0.0, c_f=C_F_D5, i_p=I_P, i_a=I_A, kp=KP, kd=KD, ki=KI, tf=TF,
           f_q=F_Q, c_f_nominal=None):
    """Transfer functions (G_p, D, G_n, C, Q) of Eq. D.1, D.2, D.4; k_fi None = No FI."""
    s = ct.tf("s")
    C = kp + kd * s / (tf * s + 1) + ki / s
    wq = 2 * math.pi * f_q
    Q = ct.tf([wq**2], [1.0, 2 * wq, wq**2])
    cfn = c_f if c_f_nominal is None else c_f_nominal
    Gn = ct.tf([1.0], [i_p + 2 * i_a, 2 * cfn, 0.0])
    if k_fi is None:
        Gp = ct.tf([1.0], [i_p + 2 * i_a, 2 * c_f, 0.0])
        D = 2 * Gp
    else:
        B = [i_a, c_fi + c_f, k_fi]
        den = [i_p * i_a, c_fi * (i_p + 2 * i_a) + c_f * i_p,
               k_fi * (i_p + 2 * i_a) + 2 * c_fi * c_f, 2 * k_fi * c_f, 0.0]
        Gp = ct.tf(B, den)
        D = ct.tf(np.polymul([2 * c_fi, 2 * k_fi], [1.0]), den)   # G_p * 2(c_fi s + k_fi)/B
    return Gp, D, Gn, C, Q


def gd_response(bl, f):
    """Eq. D.3 at frequencies f [Hz] from the block responses."""
    Gp, D, Gn, C, Q = (np.asarray(b(2j * np.pi * np.asarray(f))) for b in bl)
    return D * Gn * (1 - Q) / (Q * (Gp - Gn) + Gn * (1 + C * Gp))


def max_pole_real(bl):
    """Largest real part of the DOB + PID closed-loop poles [1/s]."""
    (np_, dp), (_, _), (nn, dn), (nc, dc), (nq, dq) = (
        tuple(np.asarray(v, float).ravel() for v in ct.tfdata(b)) for b in bl)
    pm = np.polymul
    char = np.polyadd(pm(pm(nq, dc), np.polysub(pm(np_, dn), pm(nn, dp))),
                      pm(pm(dq, nn), np.polyadd(pm(dc, dp), pm(nc, np_))))
    char = np.trim_zeros(char, "f")
    return float(np.roots(char).real.max())


def _slope_db_per_dec(g, f, f1, f2):
    i1, i2 = np.argmin(abs(f - f1)), np.argmin(abs(f - f2))
    return 20 * math.log10(abs(g[i2]) / abs(g[i1])) / math.log10(f[i2] / f[i1])


def _band_norm(g, f, lo, hi):
    m = (f >= lo) & (f <= hi)
    return float(np.sqrt(np.trapezoid(np.abs(g[m]) ** 2, f[m])))


# ============================================================================= Sec. D.4
def predicted_rms(preset_name, rate):
    """Continuous Eq. D.3 prediction of the RMS error for ZOH-white torque (Table D.2 values)."""
    p = load_preset(preset_name)
    b = p.stage.bearings[0]
    pid, dob = p.controller.pid, p.controller.dob
    c_f = b.friction.viscous
    c_nom = dob.pole / dob.gain / 2.0                 # G_n = gain/(s(s + pole)) -> c_f of Eq. D.4
    i_p, i_a = p.stage.table.mass, b.mass
    tf = 1.0 / (2 * math.pi * pid.derivative_cutoff)
    kfi = None if b.joint is None else b.joint.stiffness
    cfi = 0.0 if b.joint is None else b.joint.damping
    bl = blocks(kfi, cfi, c_f, i_p, i_a, pid.kp, pid.kd, pid.ki, tf, dob.q_cutoff, c_nom)
    ts = 1.0 / rate
    f = np.linspace(0.01, 20 * rate, 400_000)
    g = gd_response(bl, f)
    psd = 2 * SIGMA**2 * ts * np.sinc(f * ts) ** 2        # one-sided, correlated 0.15 N m per bearing
    return float(np.sqrt(np.trapezoid(np.abs(g) ** 2 * psd, f))), max_pole_real(bl)


def run_case(preset, n_seeds=N_SEEDS, t_sim=T_SIM):
    rate = preset.controller.rate
    w = RPM * 2 * math.pi / 60.0
    n = int(round(t_sim * rate)) + 1
    t = np.arange(n) / rate
    res = simulate(preset, w * t, np.full(n, w), n_trials=n_seeds)
    keep = t >= T_SKIP
    e_true = (res.x_ref - res.x_table)[:, keep]
    e_meas = (res.x_ref - res.y)[:, keep]
    return t[keep], e_true, e_meas


def _rms(e):
    per = np.sqrt(np.mean(e**2, axis=1))
    return float(np.sqrt(np.mean(per**2))), float(per.std(ddof=1) / math.sqrt(len(per)))


# ============================================================================= claims
def _fig_d5(out, plt):
    """Fig. D.5: |G_d| without FI and for each k_fi of the figure, their analysis and plot."""
    f = F_AXIS
    bl0 = blocks(None)
    g0 = gd_response(bl0, f)
    poles = {"No FI": max_pole_real(bl0)}
    rows = {}
    for k in K_FI_D5:
        cfi, wn = fi_damping(k)
        bl = blocks(k, cfi)
        g = gd_response(bl, f)
        fn = wn / (2 * math.pi)
        hi = f >= 3 * fn
        rows[k] = dict(c_fi=cfi, f_n=fn, g=g, below_nofi_above_3fn=bool(np.all(np.abs(g[hi]) < np.abs(g0[hi]))),
                       slope_300_1000=_slope_db_per_dec(g, f, 300, 1000),
                       peak=float(np.abs(g).max()), f_peak=float(f[np.argmax(np.abs(g))]),
                       norm_1_1000=_band_norm(g, f, 1, 1000),
                       at_100=float(abs(g[np.argmin(abs(f - 100))])),
                       at_1000=float(abs(g[np.argmin(abs(f - 1000))])))
        poles[f"k_fi={k:g}"] = max_pole_real(bl)
    slope0 = _slope_db_per_dec(g0, f, 300, 1000)
    ks = list(K_FI_D5)
    f_lo = 3 * rows[ks[-1]]["f_n"]
    hf = f >= f_lo
    mags = np.array([np.abs(rows[k]["g"][hf]) for k in ks])
    hf_order = bool(np.all(np.diff(mags, axis=0) > 0))          # lower k_fi -> lower |G_d| at every f
    norm_order = bool(np.all(np.diff([rows[k]["norm_1_1000"] for k in ks]) > 0))
    below = all(r["below_nofi_above_3fn"] for r in rows.values())
    rolloff = all(r["slope_300_1000"] <= slope0 - 30.0 for r in rows.values())
    stable = all(v < 0 for v in poles.values())
    d5_ok = bool(below and rolloff and hf_order and norm_order and stable)
    norm0 = _band_norm(g0, f, 1, 1000)

    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.loglog(f, np.abs(g0), "k", lw=2, label="No FI")
    for k in ks:
        ax.loglog(f, np.abs(rows[k]["g"]), label=f"FI, k_fi = {k:g} N·m/rad")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("|G_d| [rad/(N·m)]")
    ax.set_title("Fig. D.5: |G_d| (Eq. D.3), Table D.1, c_f = 2 N·m·s/rad, ζ_FI = 0.1 %")
    ax.set_ylim(1e-14, 1e-3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_D5_Gd.png", dpi=110)
    plt.close(fig)
    return dict(g0=g0, rows=rows, poles=poles, slope0=slope0, ks=ks, f_lo=f_lo, hf_order=hf_order, norm_order=norm_order, below=below, d5_ok=d5_ok, norm0=norm0)


def _sec_d4(out, plt, poles):
    """Sec. D.4: RMS tracking error of the three presets at 10 rpm, sensitivities and plot.

    Adds each preset's predicted closed-loop pole margin to `poles` (reported with Fig. D.5).
    """
    rms, sem, rms_meas, pred, traces, peak_f = {}, {}, {}, {}, {}, {}
    for lab, name in PRESETS.items():
        p = load_preset(name)
        t, e, em = run_case(p)
        rms[lab], sem[lab] = _rms(e)
        rms_meas[lab] = _rms(em)[0]
        pred[lab], poles[f"D4 {lab}"] = predicted_rms(name, p.controller.rate)
        traces[lab] = (t, e[0])
        fw, pxx = signal.welch(e, fs=p.controller.rate, nperseg=8192, axis=-1)
        pm_ = pxx.mean(axis=0)
        band = (fw >= 2) & (fw <= 500)
        peak_f[lab] = float(fw[band][np.argmax(pm_[band])])
    # sensitivities: ideal encoder, and a No FI roller that also gets the eddy-current damper
    rms_ideal = {}
    for lab, name in PRESETS.items():
        p = with_overrides(load_preset(name), {"stage.encoder.resolution": 0.0})
        rms_ideal[lab] = _rms(run_case(p)[1])[0]
    pd = with_overrides(load_preset("rotary_nofi"), {
        "stage.bearings.0.friction.viscous": 1.4, "stage.bearings.1.friction.viscous": 1.4,
        "controller.dob.pole": 2 * 1.4 / (0.1401 + 2 * 0.01491)})
    rms_nofi_damped = _rms(run_case(pd)[1])[0]

    r_wo = rms["FI w/o damper"] / rms["No FI"]
    r_w = rms["FI w/ damper"] / rms["No FI"]
    s_wo = SEED_RMS["FI w/o damper"] / SEED_RMS["No FI"]
    s_w = SEED_RMS["FI w/ damper"] / SEED_RMS["No FI"]
    order_ok = rms["FI w/ damper"] < rms["No FI"] < rms["FI w/o damper"]
    ratio_ok = abs(r_wo / s_wo - 1) <= RATIO_TOL and abs(r_w / s_w - 1) <= RATIO_TOL
    d4_ok = bool(order_ok and ratio_ok)
    p_fi = load_preset("rotary_fi")
    k_d2, ip2, ia2 = p_fi.stage.bearings[0].joint.stiffness, p_fi.stage.table.mass, p_fi.stage.bearings[0].mass
    fn_d2 = math.sqrt(k_d2 * (ip2 + 2 * ia2) / (ia2 * ip2)) / (2 * math.pi)

    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True, sharey=True)
    for ax, (lab, (t, e)) in zip(axes, traces.items()):
        sel = t <= T_SKIP + 2.0
        ax.plot(t[sel], 1e6 * e[sel], lw=0.5)
        ax.set_title(f"{lab}: RMS {1e6 * rms[lab]:.2f} µrad (seed {1e6 * SEED_RMS[lab]:.2f})", fontsize=9)
        ax.set_ylabel("error [µrad]")
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("Fig. D.12: tracking error at 10 rpm, 0.15 N·m random bearing torque", fontsize=10)
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_D12_tracking_error.png", dpi=110)
    plt.close(fig)
    return dict(rms=rms, sem=sem, rms_meas=rms_meas, pred=pred, peak_f=peak_f, rms_ideal=rms_ideal, rms_nofi_damped=rms_nofi_damped, r_wo=r_wo, r_w=r_w, s_wo=s_wo, s_w=s_w, d4_ok=d4_ok, fn_d2=fn_d2)


def _claims_d5(g0, rows, poles, slope0, ks, f_lo, hf_order, norm_order, below, d5_ok, norm0):
    """The Fig. D.5 claim (G_d low-pass above the FI mode)."""
    d5_numbers = dict(I_p=I_P, I_a=I_A, K_p=KP, K_d=KD, K_i=KI, T_f=TF, f_Q=F_Q, c_f=C_F_D5,
                      zeta_fi=ZETA_FI, nofi_peak=float(np.abs(g0).max()), nofi_norm_1_1000=norm0,
                      nofi_slope_300_1000=slope0, hf_band_start_hz=f_lo,
                      lower_k_lower_Gd_every_f_above=hf_order, lower_k_lower_norm=norm_order,
                      max_pole_real=poles, **{
                          f"k{k:g}.{q}": v for k, r in rows.items() for q, v in r.items() if q != "g"})
    txt_rows = ", ".join(f"{k:g}: {rows[k]['f_n']:.0f} Hz, {rows[k]['slope_300_1000']:.0f}" for k in ks)
    return [Claim(
        id="D.2/Gd-lowpass",
        source="App. D, Eq. D.1-D.4, Fig. D.5",
        claim=("|G_d| of the FI rotary system rolls off after the FI resonance and lies below No FI "
               "at high frequency; a lower k_fi suppresses the frictional disturbance better"),
        seed="FI low-pass filters friction; lower k_fi -> faster roll-off, better suppression",
        ours=(f"FI below No FI above 3 f_n: {below}; slope 300-1000 Hz FI ≈ "
              f"{rows[300.0]['slope_300_1000']:.0f} vs No FI {slope0:.0f} dB/dec; lower k_fi -> lower "
              f"|G_d| above {f_lo:.0f} Hz and lower 1-1000 Hz norm: {hf_order and norm_order}"),
        agrees=d5_ok,
        numbers=d5_numbers,
        note=(f"criterion, for k_fi ∈ {{{', '.join(f'{k:g}' for k in ks)}}} N·m/rad: |G_d,FI| < |G_d,NoFI| "
              f"for all f ∈ [3 f_n, 2 kHz]; slope over 300-1000 Hz ≥ 30 dB/dec steeper than No FI; "
              f"|G_d,FI| increasing with k_fi at every f ≥ 3 f_n(k_max) = {f_lo:.0f} Hz and in the "
              f"1-1000 Hz 2-norm; all closed loops stable. FI mode f_n and slope [dB/dec] per k_fi: "
              f"{txt_rows} (No FI {slope0:.0f}). Caveats: the resonance peak of k_fi = 1000-3000 "
              f"N·m/rad ({rows[1000.0]['peak']:.1e}, {rows[3000.0]['peak']:.1e} rad/(N·m)) exceeds the No "
              f"FI peak ({np.abs(g0).max():.1e}) and their 1-1000 Hz norms "
              f"({rows[1000.0]['norm_1_1000']:.1e}, {rows[3000.0]['norm_1_1000']:.1e}) exceed No FI "
              f"({norm0:.1e}); the FI pays off broadband only for k_fi ≲ 300 N·m/rad "
              f"({rows[300.0]['norm_1_1000']:.1e}). c_fi from ζ = 0.1 % of the FI mode "
              f"(c_fi = 2ζ k_fi/ω_n)."),
    )]


def _claims_d4(rms, sem, rms_meas, pred, peak_f, rms_ideal, rms_nofi_damped, r_wo, r_w, s_wo, s_w, d4_ok, fn_d2, runtime):
    """The Sec. D.4 claim (RMS tracking error at 10 rpm)."""
    return [Claim(
        id="D.4/rms-10rpm",
        source="App. D, Sec. D.4, Fig. D.12, Table D.2",
        claim=("10 rpm constant velocity with 0.15 N·m normally distributed bearing torque: RMS error "
               "No FI 1.41, FI w/o damper 2.62, FI with damper 0.91 µrad"),
        seed="1.41 / 2.62 / 0.91 µrad (ratios 1.86, 0.65)",
        ours=(f"{1e6 * rms['No FI']:.2f} / {1e6 * rms['FI w/o damper']:.2f} / {1e6 * rms['FI w/ damper']:.2f} "
              f"µrad (ratios {r_wo:.2f}, {r_w:.2f})"),
        agrees=d4_ok,
        numbers=dict(rpm=RPM, t_sim=T_SIM, t_skip=T_SKIP, n_seeds=N_SEEDS, sigma_per_bearing_correlated=SIGMA,
                     disturbance="white per 1e-4 s control sample, ZOH, independent 0.2121 N·m per bearing",
                     **{f"rms_true.{k}": v for k, v in rms.items()},
                     **{f"rms_sem.{k}": v for k, v in sem.items()},
                     **{f"rms_measured.{k}": v for k, v in rms_meas.items()},
                     **{f"rms_ideal_encoder.{k}": v for k, v in rms_ideal.items()},
                     **{f"rms_predicted_EqD3.{k}": v for k, v in pred.items()},
                     **{f"error_psd_peak_hz.{k}": v for k, v in peak_f.items()},
                     rms_nofi_with_damper=rms_nofi_damped, ratio_fi_wo=r_wo, ratio_fi_w=r_w,
                     seed_ratio_fi_wo=s_wo, seed_ratio_fi_w=s_w, fi_mode_hz_table_D2=fn_d2,
                     runtime_s=runtime),
        note=(f"criterion: ordering FI w/ < No FI < FI w/o and both ratios within ±{100 * RATIO_TOL:.0f} % of "
              f"the seed's ({s_wo:.2f}, {s_w:.2f}); absolute values are not judged because the seed "
              f"does not state the disturbance bandwidth. Assumed: per-bearing torque white at the "
              f"10 kHz control rate (zero-order held), 0.15 N·m std per bearing fully correlated "
              f"(equivalently 0.212 N·m independent). With that assumption the absolute values are also "
              f"within {100 * max(abs(rms[k] / SEED_RMS[k] - 1) for k in rms):.0f} % of the seed. The FI w/o "
              f"damper ratio is {100 * (r_wo / s_wo - 1):+.0f} % off (Eq. D.3 expectation "
              f"{pred['FI w/o damper'] / pred['No FI']:.2f}): its error is a lightly damped FI resonance, "
              f"so a single run scatters by ~{100 * sem['FI w/o damper'] * math.sqrt(N_SEEDS) / rms['FI w/o damper']:.0f} % "
              f"(per-seed std over 5 s); the seed's 2.62 µrad, probably one short run, is within ~2σ. "
              f"True-angle error, {N_SEEDS} seeds × {T_SIM - T_SKIP:.0f} s after a {T_SKIP:.0f} s transient "
              f"(seed-to-seed SEM ≤ {1e6 * max(sem.values()):.2f} µrad). Cross-checks: Eq. D.3 with the "
              f"same spectrum predicts {', '.join(f'{1e6 * v:.2f}' for v in pred.values())} µrad; an ideal "
              f"encoder gives {', '.join(f'{1e6 * v:.2f}' for v in rms_ideal.values())} µrad (the 1.33 µrad "
              f"quantisation barely matters); the measured-angle RMS is "
              f"{', '.join(f'{1e6 * v:.2f}' for v in rms_meas.values())} µrad. FI w/o damper error peaks "
              f"at {peak_f['FI w/o damper']:.1f} Hz (FI mode of Table D.2: {fn_d2:.1f} Hz), the "
              f"'vibrations around the resonance' of the seed. Choice in the No FI preset: no eddy-current "
              f"damper (c_f = 0.2); with it (c_f = 1.4) No FI gives {1e6 * rms_nofi_damped:.2f} µrad."),
    )]


def claims(out: Path) -> list[Claim]:
    out = outputs.prepare_folder(out)
    t0 = time.perf_counter()
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    d5 = _fig_d5(out, plt)
    d4 = _sec_d4(out, plt, d5["poles"])
    runtime = time.perf_counter() - t0
    return _claims_d5(**d5) + _claims_d4(**d4, runtime=runtime)
