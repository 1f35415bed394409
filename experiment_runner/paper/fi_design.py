"""Chapter 6: design analysis of the friction isolator (FI), Sec. 6.3.2 and Sec. 6.4.2.

Frequency-domain analysis (Sec. 6.3.2, Fig. 6.2-6.4, Eq. 6.1-6.3)
------------------------------------------------------------------
Fig. 6.2 model: table ``m_t`` driven by ``F_a``, FI spring-damper ``k_fi, c_fi`` to the
bearing ``m_b``, pre-motion friction spring-damper ``k_f, c_f`` from the bearing to
ground. With ``z = c_fi s + k_fi`` and ``w = c_f s + k_f`` the equations of motion
``m_t s² X_t = F_a - z (X_t - X_b)``, ``m_b s² X_b = z (X_t - X_b) - w X_b`` give
(Eq. 6.2 of the text file is garbled; this is our own derivation)::

    G(s) = X_t/F_a = (m_b s² + (c_fi + c_f) s + (k_fi + k_f)) /
           (m_t m_b s⁴ + [c_fi (m_t + m_b) + c_f m_t] s³
            + [k_fi (m_t + m_b) + c_f c_fi + k_f m_t] s² + (c_f k_fi + k_f c_fi) s + k_f k_fi)

and for No FI (table rigidly on the bearing) ``G = 1/((m_t + m_b) s² + c_f s + k_f)``.
``G_e = 1/(1 + C G)`` (Eq. 6.1), ``G_d = G/(1 + C G)`` (Eq. 6.3), ``C`` = the PID of the
``sai_stage`` preset (same gains for all FIs, Sec. 6.3.1). "2-norm of the magnitude over
f1..f2" is taken as ``sqrt(∫ |G(j2πf)|² df)`` on a uniform 0.1 Hz grid (trapezoid).

Parameters: ``m_t`` = table side of the 1.4 kg moving mass *including* the appended
10 % mode mass of the preset (0.7273·1.1 = 0.8 kg; Fig. 6.2 has no structural mode),
``m_b`` = 0.6 kg (preset estimate), ``k_f`` = 2.19e6 N/m (Table 6.4). ``c_f`` is not given
by the seed nor the preset: we estimate 5 % of critical damping of the No-FI friction
mode, ``c_f = 2·0.05·sqrt(k_f (m_t + m_b))`` = 175 N·s/m, and report the conclusions for
1 % and 20 % as well.

Quasi-static friction analysis (Sec. 6.4.2, Fig. 6.7-6.9, Eq. 4.1-4.2)
---------------------------------------------------------------------
Table displacement ``x_t`` = x-axis of the 5 mm circle, ``R (1 - cos θ)``, one cycle from
the relaxed state (rate-independent models: only the path matters). "FI + Dahl": Dahl
with ``k_σ,FI = k_fi k_σ/(k_fi + k_σ)`` and ``F_C`` = 5.31 N driven by ``x_t``. "FI + GMS":
the Table 6.5 GMS blocks of the bearing in series with the FI spring, bearing mass
neglected: for every monotone table increment the bearing increment ``y`` solves
``k_fi (x_t - x_b - y) = F_GMS(y)`` exactly (``F_GMS`` is piecewise linear in ``y``; the
breakpoints where blocks start slipping are walked in order), then the blocks are
advanced with the exact kernel :func:`stage_sim.friction.gms_update`. ``γ`` = RMS of
``F_Dahl - F_GMS`` over the cycle (uniform in time/phase). The same series solver with a
single non-slipping block ``k_f`` gives ``k_c`` and, by perturbing ``k_f``, ``κ``.

This series connection is the seed's own: Table 4.5 (the FI-case GMS, "obtained from the
re-constructed virgin curve, by combining frictional stiffness and FI stiffness in series",
Sec. 4.4.3) is reproduced by the series solver applied to Table 4.4 and ``k_fi`` = 8.27e4 N/m
to 0.5 % of F_C over the whole virgin curve (:func:`table_4_5_check`); putting each block in
series with its own ``k_fi`` instead misses it by 38 % of F_C.

Dahl and GMS must describe the same bearing. Both are identified from the same sine-sweep
FRFs (Sec. 4.4.3: ``k_σ`` from the friction resonance of the smallest-amplitude, 0.11 N FRF;
the GMS virgin curve from ten FRFs starting at that amplitude), so the GMS's initial stiffness
``Σk_i`` is ``k_σ`` by construction — Tables 4.3/4.4 agree to 0.2 %. The Ch. 6 tables do not
(Table 6.4 ``k_σ`` = 2.19e6 N/m, a copy of Table 4.3's value, vs Table 6.5 ``Σk_i`` = 6.17e5
N/m). The γ analysis therefore uses Table 6.5's block distribution (``α_i`` and the ratios
``k_i/Σk``) with ``Σk_i = k_σ`` (:func:`gms_consistent`); the location of the optimum in
``η`` does not depend on which of the two values is the common one (scale invariance, checked
in the claim's numbers), only on the two models sharing it.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
from numba import njit

import control as ct

from experiment_runner import outputs
from experiment_runner.paper import Claim
from stage_control.tuning import pid_tf
from stage_sim.config import load_preset
from stage_sim.friction import dahl_update, gms_update

# ----------------------------------------------------------------------------- seed values
K_F = 2.19e6                      # Table 6.4: k_sigma,NoFI [N/m]
F_C = 5.31                        # Table 6.4: F_C [N]
GMS_K = np.array([3.9e5, 4.6e4, 2.3e4, 1.7e4, 1.1e4, 4.9e4, 1.4e4, 2.2e4, 3.1e4, 1.4e4])   # Table 6.5
GMS_ALPHA = np.array([0.0104, 0.0605, 0.0916, 0.1333, 0.1453,
                      0.0961, 0.0448, 0.1055, 0.2025, 0.1100])                            # Table 6.5
GMS4_K = np.array([1.34e6, 4.93e5, 8.61e4, 5.55e4, 5.87e4, 2.42e4, 3.85e4, 1.75e4, 2.69e4, 4.58e4])  # Table 4.4
GMS4_ALPHA = np.array([0.0136, 0.0568, 0.037, 0.047, 0.0805,
                       0.0508, 0.1139, 0.0732, 0.1540, 0.3733])                           # Table 4.4
GMS45_K = np.array([4.44e3, 8.49e3, 3.93e3, 3.75e3, 5.88e3, 3.38e3, 7.29e3, 4.49e3, 9.30e3, 2.96e4])  # Table 4.5
GMS45_ALPHA = np.array([0.0012, 0.0123, 0.0121, 0.0181, 0.0393,
                        0.0295, 0.0797, 0.0606, 0.1520, 0.5951])                          # Table 4.5
K_FI_4 = 8.27e4                   # Table 4.3: k_fi of the Ch. 4 FI [N/m]
FI_PRESETS = {"LS-LD": "sai_fi_ls_ld", "LS-HD": "sai_fi_ls_hd", "HS-HD": "sai_fi_hs_hd"}   # Table 6.2
CIRCLE_R = 5e-3                   # Sec. 6.4: 5 mm radius circle
ZETA_F = 0.05                     # estimate: damping ratio of the No-FI friction mode -> c_f
ZETA_F_SENS = (0.01, 0.20)        # sensitivity of the conclusions to c_f

# ----------------------------------------------------------------------------- grids
F_E = np.arange(1.0, 50.0 + 1e-9, 0.1)        # Fig. 6.3(b) band [Hz]
F_D = np.arange(1.0, 500.0 + 1e-9, 0.1)       # Fig. 6.4(b) band [Hz]
K_GRID = np.logspace(3, 6, 31)                # k_fi [N/m] (Table 6.2: 2.9e4-6.8e4)
C_GRID = np.logspace(0, 4, 33)                # c_fi [N s/m] (Table 6.2: 240-990)
ETA_GRID = np.logspace(-3, 1, 81)             # k_fi/k_f for Fig. 6.8/6.9
N_CYCLE = 10_000                              # samples per circle cycle (Fig. 6.8)

FLAT = 0.05          # "little improvement": within 5 % of the optimum
MUCH_LOWER = 0.5     # "much lower": at most half (-6 dB)


# ============================================================================= Sec. 6.3.2
def stage_parameters():
    """m_t, m_b, PID gains of the Ch. 5/6 stage, and the three Table 6.2 FIs, from presets."""
    p = load_preset("sai_stage")
    mode_ratio = sum(m.mass_ratio for m in p.stage.modes)
    m_t = p.stage.table.mass * (1.0 + mode_ratio)
    m_b = p.stage.bearings[0].mass
    fis = {}
    for label, name in FI_PRESETS.items():
        j = load_preset(name).stage.bearings[0].joint
        fis[label] = (j.stiffness, j.damping)
    return m_t, m_b, p.controller.pid.model_dump(), fis


def c_f_estimate(m_t, m_b, zeta=ZETA_F, k_f=K_F):
    """Pre-motion friction damping: ``zeta`` of critical on the No-FI friction mode [N s/m]."""
    return 2.0 * zeta * math.sqrt(k_f * (m_t + m_b))


def plant_coeffs(m_t, m_b, k_fi, c_fi, k_f, c_f):
    """Numerator/denominator coefficients (highest power first) of G = x_t/F_a (Fig. 6.2)."""
    num = [m_b, c_fi + c_f, k_fi + k_f]
    den = [m_t * m_b, c_fi * (m_t + m_b) + c_f * m_t,
           k_fi * (m_t + m_b) + c_f * c_fi + k_f * m_t, c_f * k_fi + k_f * c_fi, k_f * k_fi]
    return num, den


def plant_fi(m_t, m_b, k_fi, c_fi, k_f=K_F, c_f=0.0) -> ct.TransferFunction:
    """Fig. 6.2 plant with FI as a python-control transfer function."""
    return ct.tf(*plant_coeffs(m_t, m_b, k_fi, c_fi, k_f, c_f))


def plant_nofi(m_t, m_b, k_f=K_F, c_f=0.0) -> ct.TransferFunction:
    """Fig. 6.2 plant, No FI (rigid table-bearing connection)."""
    return ct.tf([1.0], [m_t + m_b, c_f, k_f])


def _grid_response(m_t, m_b, k, c, k_f, c_f, f):
    """G(j2πf) for arrays k, c (broadcast) -> shape broadcast(k, c) + (len(f),)."""
    s = 2j * np.pi * np.asarray(f)
    k = np.asarray(k, float)[..., None]
    c = np.asarray(c, float)[..., None]
    num = m_b * s**2 + (c + c_f) * s + (k + k_f)
    den = (m_t * m_b * s**4 + (c * (m_t + m_b) + c_f * m_t) * s**3
           + (k * (m_t + m_b) + c_f * c + k_f * m_t) * s**2 + (c_f * k + k_f * c) * s + k_f * k)
    return num / den


def _band_norm(h, f):
    """sqrt(∫ |h|² df) over the last axis."""
    return np.sqrt(np.trapezoid(np.abs(h) ** 2, f, axis=-1))


def norm_maps(m_t, m_b, pid, k_f, c_f, k_grid=K_GRID, c_grid=C_GRID):
    """||G_e||_[1,50 Hz] and ||G_d||_[1,500 Hz] over the (k_fi, c_fi) grid, and No FI."""
    C = pid_tf(pid)
    Ce, Cd = C(2j * np.pi * F_E), C(2j * np.pi * F_D)
    K, Cg = np.meshgrid(k_grid, c_grid, indexing="ij")
    Ge = _grid_response(m_t, m_b, K, Cg, k_f, c_f, F_E)
    Gd = _grid_response(m_t, m_b, K, Cg, k_f, c_f, F_D)
    E = _band_norm(1.0 / (1.0 + Ce * Ge), F_E)
    D = _band_norm(Gd / (1.0 + Cd * Gd), F_D)
    G0e, G0d = plant_nofi(m_t, m_b, k_f, c_f)(2j * np.pi * F_E), plant_nofi(m_t, m_b, k_f, c_f)(2j * np.pi * F_D)
    e0 = float(_band_norm(1.0 / (1.0 + Ce * G0e), F_E))
    d0 = float(_band_norm(G0d / (1.0 + Cd * G0d), F_D))
    return E, D, e0, d0


def point_norms(m_t, m_b, pid, k_fi, c_fi, k_f, c_f):
    E, D, _, _ = norm_maps(m_t, m_b, pid, k_f, c_f, np.array([k_fi]), np.array([c_fi]))
    return float(E[0, 0]), float(D[0, 0])


def ge_optimum_estimate(m_t, pid, f=F_E):
    """First-order estimate of the k_fi that minimises ||G_e|| at c_fi -> 0, and the rise at k_fi -> 0.

    In the band the bearing is held by ``k_f`` (>> ``m_b ω²``, ``k_fi``) and ``|C| >> |1/G|``, so
    ``|G_e(jω)| ≈ |k_c - m_t ω² + j c_fi ω| / |C(jω)|`` (``k_c`` ≈ ``k_fi``): G_e's numerator is
    the FI branch's own dynamic stiffness. With ``X = m_t ω²`` and the weight ``w = |C|⁻²`` over
    the band, ``||G_e||²`` ∝ ``E_w[(k_c - X)²]`` (c_fi → 0), minimal at ``k* = E_w[X]``; at
    ``k_c → 0`` it is ``E_w[X²]``, so the rise is ``sqrt(1 + E_w[X]²/Var_w[X]) - 1`` > 0 for any
    band, plant mass and controller: a softer FI than ``k*`` is always worse in this model.

    Returns
    -------
    (k_star, rise) : (float, float)
        [N/m], [-].
    """
    w = 2.0 * np.pi * np.asarray(f, float)
    wt = 1.0 / np.abs(pid_tf(pid)(1j * w)) ** 2
    x = m_t * w ** 2
    mean = np.trapezoid(x * wt, f) / np.trapezoid(wt, f)
    var = np.trapezoid((x - mean) ** 2 * wt, f) / np.trapezoid(wt, f)
    return float(mean), float(math.sqrt(1.0 + mean ** 2 / var) - 1.0)


def ge_norm_control(m_t, m_b, pid, k_fi, c_fi, k_f, c_f, f=F_E):
    """||G_e|| over the band from python-control's ``feedback`` (independent of :func:`norm_maps`)."""
    ge = ct.feedback(1, pid_tf(pid) * plant_fi(m_t, m_b, k_fi, c_fi, k_f, c_f))
    return float(np.sqrt(np.trapezoid(np.abs(ge(2j * np.pi * np.asarray(f))) ** 2, f)))


def max_closed_loop_real_part(m_t, m_b, pid, k_f, c_f, k_grid=K_GRID, c_grid=C_GRID):
    """Largest real part of the closed-loop poles (1 + C G = 0) over the grid and No FI [1/s]."""
    nc, dc = (np.asarray(v, float).ravel() for v in ct.tfdata(pid_tf(pid)))
    worst = -np.inf
    for k in k_grid:
        for c in c_grid:
            ng, dg = plant_coeffs(m_t, m_b, k, c, k_f, c_f)
            char = np.polyadd(np.polymul(dc, dg), np.polymul(nc, ng))
            worst = max(worst, np.roots(char).real.max())
    char = np.polyadd(np.polymul(dc, [m_t + m_b, c_f, k_f]), nc)
    return float(max(worst, np.roots(char).real.max()))


def _ge_analysis(E, e0, fis_norms):
    """Checks of the Fig. 6.3(b) statement on a ||G_e|| map (axis 0: k_fi, axis 1: c_fi)."""
    tol = 1e-3
    mono_c = bool(np.all(np.diff(E, axis=1) >= -tol * E[:, :-1]))
    # damping threshold: largest c_fi whose ||G_e|| is within FLAT of the smallest-c value
    c_thr = np.array([C_GRID[np.flatnonzero(row <= (1 + FLAT) * row[0])[-1]] for row in E])
    c_threshold = bool(np.all(c_thr >= 10 * C_GRID[0]))          # a flat region >= 1 decade
    # stiffness: optimum k*(c_fi); above it ||G_e|| must grow with k_fi, below it stay flat
    i_opt = np.argmin(E, axis=0)
    k_opt = K_GRID[i_opt]
    above_ok = all(np.all(np.diff(E[i:, j]) >= -tol * E[i:-1, j]) for j, i in enumerate(i_opt))
    rise_below = np.array([E[: i + 1, j].max() / E[i, j] - 1.0 for j, i in enumerate(i_opt)])
    below_flat = bool(np.all(rise_below <= FLAT))
    ratios = {lab: v / e0 for lab, v in fis_norms.items()}
    table_ok = all(r <= MUCH_LOWER for r in ratios.values())
    return dict(mono_c=mono_c, c_thr=c_thr, c_threshold=c_threshold, k_opt=k_opt,
                above_ok=above_ok, rise_below=rise_below, below_flat=below_flat,
                ratios=ratios, table_ok=table_ok,
                agrees=bool(table_ok and mono_c and c_threshold and above_ok and below_flat))


def _gd_analysis(D, d0):
    """Checks of the Fig. 6.4(b) statement on a ||G_d|| map."""
    dec_k = bool(np.all(np.diff(D, axis=0) < 0))
    dec_c = bool(np.all(np.diff(D, axis=1) < 0))
    # "no threshold" = no diminishing returns when increasing k_fi or c_fi: along every grid
    # line, once the reduction per decade exceeds FLAT it stays above FLAT to the grid's end
    nk = int(round((len(K_GRID) - 1) / math.log10(K_GRID[-1] / K_GRID[0])))   # steps/decade
    nc = int(round((len(C_GRID) - 1) / math.log10(C_GRID[-1] / C_GRID[0])))
    red_k = 1.0 - D[nk:, :] / D[:-nk, :]          # per-decade reduction, start index along k
    red_c = 1.0 - D[:, nc:] / D[:, :-nc]

    def plateau(red):                            # red: (line, position) -> any plateau reached?
        return any(np.any(r[np.argmax(r >= FLAT):] < FLAT) for r in red if np.any(r >= FLAT))

    no_thr = not plateau(red_k.T) and not plateau(red_c)
    top_k, top_c = red_k[-1, :], red_c[:, -1]
    nofi_min = bool(d0 < D.min())
    return dict(dec_k=dec_k, dec_c=dec_c, top_k=top_k, top_c=top_c, red_k=red_k, red_c=red_c,
                no_thr=bool(no_thr), nofi_min=nofi_min,
                agrees=bool(dec_k and dec_c and no_thr and nofi_min))


# ============================================================================= Sec. 6.4.2
@njit(cache=True)
def _series_gms(xt, k_fi, k, alpha, f_c):
    """Force of GMS blocks (k, alpha) in series with a spring k_fi, table path xt (quasi-static).

    Exact in the displacement domain for monotone table increments: the bearing increment
    ``y`` solves ``k_fi (x_t - x_b - y) = sum_i clip(f_i + k_i y, ±alpha_i F_C)``.
    Returns (force history, bearing position history).
    """
    n = k.size
    f = np.zeros(n)
    lim = alpha * f_c
    out = np.zeros(xt.size)
    xb_hist = np.zeros(xt.size)
    xb = 0.0
    for t in range(1, xt.size):
        d = xt[t] - xt[t - 1]
        if d == 0.0:
            out[t] = f.sum()
            xb_hist[t] = xb
            continue
        s = 1.0 if d > 0.0 else -1.0
        r = xt[t] - xb
        ystar = (s * lim - f) / k           # bearing increment at which block i starts slipping
        order = np.argsort(s * ystar)
        kact = 0.0
        for i in range(n):
            if s * ystar[i] > 0.0:
                kact += k[i]
        fcur = f.sum()
        ycur = 0.0
        y = (k_fi * r - fcur + kact * ycur) / (k_fi + kact)
        for m in range(n):
            i = order[m]
            if s * ystar[i] <= 0.0:
                continue
            y = (k_fi * r - fcur + kact * ycur) / (k_fi + kact)
            if s * (y - ystar[i]) <= 0.0:
                break
            fcur += kact * (ystar[i] - ycur)
            ycur = ystar[i]
            kact -= k[i]
            y = (k_fi * r - fcur + kact * ycur) / (k_fi + kact)
        out[t] = gms_update(f, y, k, alpha, f_c, n)
        xb += y
        xb_hist[t] = xb
    return out, xb_hist


@njit(cache=True)
def _dahl_path(xt, k_sigma, f_c):
    out = np.zeros(xt.size)
    f = 0.0
    for t in range(1, xt.size):
        f = dahl_update(f, xt[t] - xt[t - 1], k_sigma, f_c, 1.0)
        out[t] = f
    return out


def circle_x_path(radius=CIRCLE_R, n=N_CYCLE, cycles=1.0):
    """x-axis of the circle, R(1 - cos θ), uniform in θ (= in time), from a reversal."""
    th = np.linspace(0.0, 2.0 * np.pi * cycles, int(n * cycles) + 1)
    return th, radius * (1.0 - np.cos(th))


def force_pair(eta, xt, k_f=K_F, f_c=F_C, gms_k=GMS_K, gms_alpha=GMS_ALPHA):
    """(F_Dahl, F_GMS) [N] of the FI case for stiffness ratio eta = k_fi/k_f along path xt [m].

    Dahl: ``k_σ,FI`` = series of ``k_fi`` and ``k_f`` [N/m], Coulomb force ``f_c`` [N]; GMS:
    blocks ``gms_k`` [N/m], ``gms_alpha`` [-] (default Table 6.5) in series with ``k_fi``.
    """
    k_fi = eta * k_f
    k_sig = k_fi * k_f / (k_fi + k_f)
    return (_dahl_path(xt, k_sig, f_c),
            _series_gms(xt, k_fi, np.asarray(gms_k, float), np.asarray(gms_alpha, float), f_c)[0])


def gamma_curve(etas=ETA_GRID, k_f=K_F, f_c=F_C, gms_k=GMS_K, gms_alpha=GMS_ALPHA):
    """γ(η) over the first cycle from rest, its signed bias (+ = Dahl over-compensates),
    and γ over the second (steady) cycle [N]; friction data default to Tables 6.4/6.5."""
    _, xt = circle_x_path(cycles=2.0)
    n = N_CYCLE
    v = np.sign(np.gradient(xt))
    gam, bias, gam2 = np.empty(len(etas)), np.empty(len(etas)), np.empty(len(etas))
    for i, eta in enumerate(etas):
        fd, fg = force_pair(eta, xt, k_f, f_c, gms_k, gms_alpha)
        d = fd - fg
        gam[i] = math.sqrt(np.mean(d[: n + 1] ** 2))
        bias[i] = np.mean(d[: n + 1] * v[: n + 1])
        gam2[i] = math.sqrt(np.mean(d[n:] ** 2))
    return gam, bias, gam2


def gms_consistent(k_f=K_F, gms_k=GMS_K):
    """GMS block stiffnesses with the distribution of ``gms_k`` and initial stiffness ``Σk_i = k_f``.

    The seed identifies Dahl's ``k_σ`` and the GMS virgin curve from the same FRFs, so they share
    the initial stiffness (see the module docstring); Tables 6.4/6.5 do not, and this restores it.
    """
    gms_k = np.asarray(gms_k, float)
    return gms_k * (k_f / gms_k.sum())


def virgin_curve(x, k, alpha, f_c, k_fi=None):
    """Virgin force curve [N] of GMS blocks (k, alpha) along table displacement ``x`` >= 0 [m].

    With ``k_fi`` the blocks sit in series with that spring (exact series solver)."""
    x = np.asarray(x, float)
    if k_fi is None:
        return np.minimum(np.asarray(k)[None, :] * x[:, None], np.asarray(alpha) * f_c).sum(axis=1)
    return _series_gms(x, k_fi, np.asarray(k, float), np.asarray(alpha, float), f_c)[0]


def table_4_5_check(x_max=400e-6, n=4001):
    """Max |F| deviation / F_C of two series constructions from the seed's Table 4.5 virgin curve.

    Returns (exact series of Table 4.4 with k_fi, each Table 4.4 block in series with k_fi)."""
    x = np.linspace(0.0, x_max, n)
    ref = virgin_curve(x, GMS45_K, GMS45_ALPHA, F_C)
    series = virgin_curve(x, GMS4_K, GMS4_ALPHA, F_C, k_fi=K_FI_4)
    per_block = virgin_curve(x, GMS4_K * K_FI_4 / (GMS4_K + K_FI_4), GMS4_ALPHA, F_C)
    return float(np.abs(series - ref).max() / F_C), float(np.abs(per_block - ref).max() / F_C)


def combined_stiffness(k_fi, k_f, x=1e-6):
    """k_c by quasi-static simulation: table displaced by x through k_fi against a linear spring k_f."""
    xt = np.array([0.0, x])
    force, _ = _series_gms(xt, k_fi, np.array([k_f]), np.array([1e30]), 1.0)
    return force[-1] / x


def kappa_simulated(eta, k_f=K_F, rel=1e-3):
    """κ = ∂k_c/∂k_f by central difference of the quasi-static series simulation."""
    k_fi = eta * k_f
    hi = combined_stiffness(k_fi, k_f * (1 + rel))
    lo = combined_stiffness(k_fi, k_f * (1 - rel))
    return (hi - lo) / (2 * rel * k_f)


def kappa_eq42(eta):
    eta = np.asarray(eta, float)
    return (eta / (1.0 + eta)) ** 2


# ============================================================================= plots
def _plots(out, m_t, m_b, pid, k_f, c_f, fis, E, D, e0, d0, ge, etas, gam, bias, gam_printed,
           kap_sim):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    C = pid_tf(pid)
    f = np.logspace(0, 3, 600)
    s = 2j * np.pi * f
    Cs = C(s)
    cases = [("No FI", plant_nofi(m_t, m_b, k_f, c_f)(s))]
    for lab, (k, c) in fis.items():
        cases.append((f"{lab} ({k:.1e} N/m, {c:.0f} N·s/m)", plant_fi(m_t, m_b, k, c, k_f, c_f)(s)))
    for name, band, fn in (("G_e", 50.0, "fig_6_3_Ge.png"), ("G_d", 500.0, "fig_6_4_Gd.png")):
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        for lab, G in cases:
            h = 1 / (1 + Cs * G) if name == "G_e" else G / (1 + Cs * G)
            axes[0].loglog(f, np.abs(h), label=lab)
        axes[0].axvspan(1, band, color="0.9")
        axes[0].set_xlabel("frequency [Hz]")
        axes[0].set_ylabel(f"|{name}|" + (" [-]" if name == "G_e" else " [m/N]"))
        axes[0].set_title(f"(a) closed-loop {name} (Eq. {'6.1' if name == 'G_e' else '6.3'}), c_f = {c_f:.0f} N·s/m")
        axes[0].legend(fontsize=7)
        M = E if name == "G_e" else D
        ref = e0 if name == "G_e" else d0
        cs = axes[1].contourf(K_GRID, C_GRID, (M / ref).T, levels=30, cmap="viridis")
        axes[1].contour(K_GRID, C_GRID, (M / ref).T, levels=10, colors="w", linewidths=0.4)
        fig.colorbar(cs, ax=axes[1], label=f"||{name}|| / ||{name}, No FI||")
        for lab, (k, c) in fis.items():
            axes[1].plot(k, c, "r*", ms=9)
            axes[1].annotate(lab, (k, c), color="r", fontsize=8, xytext=(4, 4), textcoords="offset points")
        if name == "G_e":
            axes[1].plot(ge["k_opt"], C_GRID, "w--", lw=1, label="k*(c_fi): min over k_fi")
            axes[1].legend(fontsize=7, loc="lower left")
        axes[1].set_xscale("log")
        axes[1].set_yscale("log")
        axes[1].set_xlabel("k_fi [N/m]")
        axes[1].set_ylabel("c_fi [N·s/m]")
        axes[1].set_title(f"(b) 2-norm of |{name}| over 1-{band:.0f} Hz")
        fig.tight_layout()
        outputs.savefig(fig, out / fn, dpi=110)
        plt.close(fig)

    # Fig. 6.7
    th, xt = circle_x_path()
    fig, axes = plt.subplots(1, 3, figsize=(14, 4), sharey=True)
    for ax, eta in zip(axes, (0.01, 0.1, 1.0)):
        fd, fg = force_pair(eta, xt, gms_k=gms_consistent(k_f))
        ax.plot(th / (2 * np.pi), fg, label="FI + GMS (series, exact)")
        ax.plot(th / (2 * np.pi), fd, "--", label="FI + Dahl (k_σ,FI)")
        ax.set_title(f"k_fi/k_f = {eta:g}")
        ax.set_xlabel("cycle of the 5 mm circle (x axis)")
    axes[0].set_ylabel("friction force [N]")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_6_7_forces.png", dpi=110)
    plt.close(fig)

    # Fig. 6.8
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    ax.semilogx(etas, gam, "b", label="γ: Dahl vs GMS in series with k_fi (exact), Σk_i = k_σ")
    ax.semilogx(etas, gam_printed, "g:", label="Tables 6.4/6.5 as printed (Σk_i = 0.28 k_σ)")
    ax.semilogx(etas, bias, "r--", lw=0.8, label="mean (F_Dahl − F_GMS)·sgn(v)  (+ = over-comp.)")
    ax.axvspan(0.05, 0.1, color="orange", alpha=0.2, label="seed optimum 0.05-0.1")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("k_fi / k_f")
    ax.set_ylabel("force [N]")
    ax.set_title("Fig. 6.8: RMS force difference, 5 mm circle")
    ax.legend(fontsize=7)
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_6_8_gamma.png", dpi=110)
    plt.close(fig)

    # Fig. 6.9
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.loglog(etas, kappa_eq42(etas), "k", label="Eq. 4.2")
    ax.loglog(etas, kap_sim, "r.", ms=3, label="quasi-static series simulation")
    ax.axvline(0.1, color="0.6", ls="--")
    ax.axhline(0.01, color="0.6", ls="--")
    ax.set_xlabel("η = k_fi / k_f")
    ax.set_ylabel("κ = ∂k_c/∂k_f")
    ax.set_title("Fig. 6.9: sensitivity of k_c to k_f")
    ax.legend()
    fig.tight_layout()
    outputs.savefig(fig, out / "fig_6_9_kappa.png", dpi=110)
    plt.close(fig)


# ============================================================================= claims
def claims(out: Path) -> list[Claim]:
    out = outputs.prepare_folder(out)
    t0 = time.perf_counter()
    m_t, m_b, pid, fis = stage_parameters()
    c_f = c_f_estimate(m_t, m_b)

    # ---- Sec. 6.3.2
    E, D, e0, d0 = norm_maps(m_t, m_b, pid, K_F, c_f)
    fis_e, fis_d = {}, {}
    for lab, (k, c) in fis.items():
        fis_e[lab], fis_d[lab] = point_norms(m_t, m_b, pid, k, c, K_F, c_f)
    ge = _ge_analysis(E, e0, fis_e)
    gd = _gd_analysis(D, d0)
    max_re = max_closed_loop_real_part(m_t, m_b, pid, K_F, c_f)
    sens = {}
    for z in ZETA_F_SENS:
        cfz = c_f_estimate(m_t, m_b, z)
        Ez, Dz, e0z, d0z = norm_maps(m_t, m_b, pid, K_F, cfz)
        fe = {lab: point_norms(m_t, m_b, pid, k, c, K_F, cfz)[0] for lab, (k, c) in fis.items()}
        gez, gdz = _ge_analysis(Ez, e0z, fe), _gd_analysis(Dz, d0z)
        sens[z] = dict(c_f=cfz, ge_agrees=gez["agrees"], ge_table_ok=gez["table_ok"],
                       ge_mono_c=gez["mono_c"], ge_below_flat=gez["below_flat"],
                       ge_k_opt_lowc=float(gez["k_opt"][0]), ge_rise_max=float(gez["rise_below"].max()),
                       gd_agrees=gdz["agrees"])
    # structural variants (the m_t/m_b split is an estimate; the seed's C has no derivative filter)
    variants = {}
    for lab, (mt_v, mb_v, pid_v) in {
            "m_b=0.3": (m_t + m_b - 0.3, 0.3, pid), "m_b=0.9": (m_t + m_b - 0.9, 0.9, pid),
            "unfiltered_D": (m_t, m_b, dict(pid, derivative_cutoff=None))}.items():
        Ev, Dv, e0v, d0v = norm_maps(mt_v, mb_v, pid_v, K_F, c_f)
        fe = {l: point_norms(mt_v, mb_v, pid_v, k, c, K_F, c_f)[0] for l, (k, c) in fis.items()}
        gev, gdv = _ge_analysis(Ev, e0v, fe), _gd_analysis(Dv, d0v)
        variants[lab] = dict(ge_agrees=gev["agrees"], ge_k_opt_lowc=float(gev["k_opt"][0]),
                             ge_rise_max_c_le_1000=float(gev["rise_below"][C_GRID <= 1000.0].max()),
                             ge_table_ok=gev["table_ok"], ge_mono_c=gev["mono_c"],
                             gd_agrees=gdv["agrees"])
    k_star_est, rise_est = ge_optimum_estimate(m_t, pid)
    ge_ctrl = {lab: ge_norm_control(m_t, m_b, pid, k, c, K_F, c_f) for lab, (k, c) in fis.items()}
    ge_ctrl_dev = max(abs(ge_ctrl[lab] / fis_e[lab] - 1.0) for lab in fis)
    k_near = int(np.argmin(np.abs(np.log(K_GRID / 3.3e4))))
    c_lo = C_GRID <= 1000.0
    j240 = int(np.argmin(np.abs(np.log(C_GRID / 240.0))))

    # ---- Sec. 6.4.2
    gk = gms_consistent()                                   # Table 6.5 distribution, Σk_i = k_σ
    gam, bias, gam2 = gamma_curve(gms_k=gk)
    eta_min2 = float(ETA_GRID[int(np.argmin(gam2))])
    i_min = int(np.argmin(gam))
    eta_min = float(ETA_GRID[i_min])
    # sensitivity: the tables as printed (Σk_i = 6.17e5 N/m vs Dahl k_σ = 2.19e6 N/m), the Ch. 4
    # bearing (Tables 4.3/4.4, consistent), and the common scale taken from Table 6.5 instead
    gam_pr, _, gam2_pr = gamma_curve(gms_k=GMS_K)
    gam_ch4, _, gam2_ch4 = gamma_curve(gms_k=GMS4_K, gms_alpha=GMS4_ALPHA)
    gam_s65, _, gam2_s65 = gamma_curve(k_f=float(GMS_K.sum()), gms_k=GMS_K)
    eta_of = lambda g: float(ETA_GRID[int(np.argmin(g))])          # noqa: E731
    t45_series, t45_per_block = table_4_5_check()
    lo_tol, hi_tol = 0.05 / 10 ** 0.1, 0.1 * 10 ** 0.1        # seed range +- 1/10 decade
    under_small = bool(bias[0] < 0)                                 # eta = 1e-3
    over_large = bool(np.all(bias[ETA_GRID >= 1.0] > 0))
    gamma_ok = bool(lo_tol <= eta_min <= hi_tol and under_small and over_large)
    u_shape = bool(gam[0] > gam[i_min] and gam[-1] > gam[i_min])
    g_at = {e: float(np.interp(np.log(e), np.log(ETA_GRID), gam)) for e in (0.01, 0.05, 0.1, 1.0)}
    flips = np.flatnonzero(np.diff(np.sign(bias)))
    cross = float(ETA_GRID[flips[0] + 1]) if flips.size else math.nan

    kap_sim = np.array([kappa_simulated(e) for e in ETA_GRID])
    kap_eq = kappa_eq42(ETA_GRID)
    kap_err = float(np.max(np.abs(kap_sim / kap_eq - 1.0)))
    kap_small = bool(np.all(kap_sim[ETA_GRID < 0.1] < 0.01))
    kap_lim0, kap_liminf = float(kappa_simulated(1e-4)), float(kappa_simulated(1e4))
    kappa_ok = bool(kap_err < 1e-4 and kap_small and kap_lim0 < 1e-6 and kap_liminf > 0.999)

    _plots(out, m_t, m_b, pid, K_F, c_f, fis, E, D, e0, d0, ge, ETA_GRID, gam, bias, gam_pr, kap_sim)
    runtime_total = time.perf_counter() - t0

    common = dict(m_t=m_t, m_b=m_b, k_f=K_F, c_f=c_f, zeta_f=ZETA_F, kp=pid["kp"], ki=pid["ki"],
                  kd=pid["kd"], derivative_cutoff=pid["derivative_cutoff"],
                  k_fi_grid=[float(K_GRID[0]), float(K_GRID[-1]), len(K_GRID)],
                  c_fi_grid=[float(C_GRID[0]), float(C_GRID[-1]), len(C_GRID)],
                  max_closed_loop_pole_real=max_re)
    fis_txt = ", ".join(f"{lab} {fis_e[lab]:.2f}" for lab in fis)
    sens_txt = "; ".join(f"ζ_f = {z}: k* = {v['ge_k_opt_lowc']:.1e} N/m, rise +{100 * v['ge_rise_max']:.0f} %"
                         for z, v in sens.items())
    var_txt = "; ".join(f"{lab}: k* = {v['ge_k_opt_lowc']:.1e} N/m, rise +{100 * v['ge_rise_max_c_le_1000']:.0f} %"
                        for lab, v in variants.items())
    j1000 = int(np.argmin(np.abs(np.log(C_GRID / 1000.0))))
    gd_sens_txt = ", ".join(f"ζ_f = {z}: agrees = {v['gd_agrees']}" for z, v in sens.items())
    c_thr_at = float(ge["c_thr"][k_near])
    claims_ = [
        Claim(
            id="6.3.2/Ge-threshold",
            source="Sec. 6.3.2, Fig. 6.3(b), Eq. 6.1-6.2",
            claim=("||G_e|| over 1-50 Hz decreases with lower k_fi and c_fi, with little gain below "
                   "thresholds; the three Table 6.2 FIs have much lower ||G_e|| than No FI"),
            seed="lower k_fi, c_fi -> smaller ||G_e|| (thresholds below which little improvement); FIs << No FI",
            ours=(f"No FI {e0:.2f}, {fis_txt} √Hz; monotone in c_fi (flat below ≈{c_thr_at:.0f} N·s/m "
                  f"at k_fi≈3e4); NOT monotone in k_fi: min at k*≈{ge['k_opt'][0]:.1e} N/m (c_fi→0), "
                  f"rises up to +{100 * ge['rise_below'][c_lo].max():.0f} % below k*"),
            agrees=ge["agrees"],
            numbers=dict(common, Ge_nofi=e0, **{f"Ge_{k}": v for k, v in fis_e.items()},
                         **{f"Ge_ratio_{k}": v for k, v in ge["ratios"].items()},
                         Ge_monotone_in_c=ge["mono_c"], Ge_c_threshold_at_kfi_3e4=c_thr_at,
                         Ge_c_threshold_min=float(ge["c_thr"].min()),
                         Ge_c_threshold_max=float(ge["c_thr"].max()),
                         Ge_k_opt_vs_c={f"{c:.3g}": float(k) for c, k in zip(C_GRID[::4], ge["k_opt"][::4])},
                         Ge_rise_below_kopt_max_c_le_1000=float(ge["rise_below"][c_lo].max()),
                         Ge_rise_below_kopt_at_c240=float(ge["rise_below"][j240]),
                         Ge_monotone_above_kopt=ge["above_ok"], Ge_flat_below_kopt=ge["below_flat"],
                         sensitivity_c_f={str(z): v for z, v in sens.items()},
                         variants=variants, Ge_k_opt_estimate=k_star_est,
                         Ge_rise_estimate=rise_est, Ge_python_control_max_rel_dev=ge_ctrl_dev,
                         runtime_s=runtime_total),
            note=(f"criterion: every Table 6.2 FI ≤ {MUCH_LOWER:g}× No FI; ||G_e|| non-decreasing in c_fi "
                  f"at every k_fi with ≥ 1 decade of c_fi within {100 * FLAT:.0f} % of the smallest value; "
                  f"non-decreasing in k_fi above its optimum k*(c_fi) and within {100 * FLAT:.0f} % of the "
                  f"optimum below it. Grid k_fi 1e3-1e6 N/m × c_fi 1-1e4 N·s/m. Reproduced: FIs "
                  f"{min(ge['ratios'].values()):.2f}-{max(ge['ratios'].values()):.2f}× No FI, ordering LS-LD < "
                  f"LS-HD < HS-HD as the 5 µm settling-time gains of Table 6.3, lower c_fi always "
                  f"helps and is flat below a damping threshold (≈{c_thr_at:.0f} N·s/m at k_fi ≈ 3e4 N/m). "
                  f"Not reproduced: ||G_e|| has an optimum k*(c_fi) in k_fi — {ge['k_opt'][0]:.1e} N/m at low "
                  f"damping, {float(ge['k_opt'][j1000]):.1e} N/m at c_fi = 1e3, i.e. right at the Table 6.2 "
                  f"designs — and a softer FI than k* makes ||G_e|| WORSE, not flat "
                  f"(+{100 * ge['rise_below'][j240]:.0f} % at c_fi = 240 N·s/m down to 1e3 N/m, up to "
                  f"+{100 * ge['rise_below'][c_lo].max():.0f} % for c_fi ≤ 1e3). Reason: the FI mode "
                  f"sqrt(k_fi/m_t)/2π ({math.sqrt(ge['k_opt'][0] / m_t) / (2 * math.pi):.0f} Hz at k*) "
                  f"sits inside the 1-50 Hz band and raises the loop gain "
                  f"there; for k_fi → 0 the table becomes a free {m_t:.1f} kg mass whose |G_e| is larger in "
                  f"30-50 Hz. Not an artefact of the estimated c_f ({sens_txt}), of the mass split or of the "
                  f"derivative filter ({var_txt}). It is structural, not a parameter: in the band the bearing "
                  f"is held by k_f and |C| ≫ |1/G|, so |G_e| ≈ |k_fi − m_t ω² + j c_fi ω| / |C| — G_e's numerator "
                  f"is the FI branch's own dynamic stiffness, which a soft FI cannot make smaller than the "
                  f"table's m_t ω². Weighting by |C|⁻² over 1-50 Hz this first-order estimate puts the optimum at "
                  f"k* = E[m_t ω²] = {k_star_est:.2e} N/m and the k_fi → 0 rise at "
                  f"sqrt(1 + E²/Var) − 1 = +{100 * rise_est:.0f} % (exact: {ge['k_opt'][0]:.1e} N/m, "
                  f"+{100 * ge['rise_below'][0]:.0f} %), > 0 for any band, mass and controller; FI damping "
                  f"adds a k_fi-independent c_fi²ω² term that flattens it (+{100 * ge['rise_below'][j240]:.0f} % "
                  f"at 240 N·s/m). So the seed's 'thresholds' can only be this optimum seen from above, if "
                  f"Fig. 6.3(b)'s k_fi axis (not stated) starts near k*. G_e cross-checked with "
                  f"python-control's feedback(): max deviation {ge_ctrl_dev:.1e} (rel.) at the Table 6.2 FIs."),
        ),
        Claim(
            id="6.3.2/Gd-monotone",
            source="Sec. 6.3.2, Fig. 6.4(b), Eq. 6.3",
            claim=("||G_d|| over 1-500 Hz decreases monotonically with higher k_fi and c_fi (no "
                   "threshold); No FI has the smallest ||G_d||"),
            seed="higher k_fi, c_fi -> continuously smaller ||G_d||; No FI smallest",
            ours=(f"strictly decreasing in k_fi: {gd['dec_k']}, in c_fi: {gd['dec_c']}; per-decade gain grows "
                  f"with k_fi, c_fi (no plateau: {gd['no_thr']}); No FI {d0 * 1e6:.1f} < grid min "
                  f"{D.min() * 1e6:.1f} µm/(N·√Hz)"),
            agrees=gd["agrees"],
            numbers=dict(common, Gd_nofi=d0, Gd_grid_min=float(D.min()), Gd_grid_max=float(D.max()),
                         **{f"Gd_{k}": v for k, v in fis_d.items()},
                         Gd_decreasing_in_k=gd["dec_k"], Gd_decreasing_in_c=gd["dec_c"],
                         Gd_top_decade_k_reduction_min=float(gd["top_k"].min()),
                         Gd_top_decade_c_reduction_min=float(gd["top_c"].min()),
                         Gd_low_decade_k_reduction_at_c1=float(1 - D[10, 0] / D[0, 0]),
                         sensitivity_c_f={str(z): {"c_f": v["c_f"], "agrees": v["gd_agrees"]}
                                          for z, v in sens.items()}),
            note=(f"criterion: strictly decreasing along both axes of the grid; no threshold = no "
                  f"diminishing returns when increasing k_fi or c_fi (along every grid line, once the "
                  f"reduction per decade exceeds {100 * FLAT:.0f} % it stays above it to the grid's end); No FI "
                  f"below the whole grid. (A first, stricter version — ≥ {100 * FLAT:.0f} % over the top decade "
                  f"everywhere — fails only on the c_fi = 1e4 N·s/m line, ζ ≈ 15, where the damper locks the FI "
                  f"and k_fi 1e5→1e6 gains {100 * gd['top_k'].min():.0f} %.) "
                  f"Table 6.2: HS-HD {fis_d['HS-HD'] * 1e6:.1f} < "
                  f"LS-HD {fis_d['LS-HD'] * 1e6:.1f} < LS-LD {fis_d['LS-LD'] * 1e6:.1f} µm/(N·√Hz), the order of "
                  f"the in-position RMS errors of Table 6.3. The gain is slow at low k_fi/c_fi (only "
                  f"{100 * (1 - D[10, 0] / D[0, 0]):.1f} % from k_fi 1e3 to 1e4 at c_fi = 1) and accelerates "
                  f"towards k_fi ~ k_f; the soft, lightly damped corner is flat (free-table limit) — "
                  f"increasing returns, not a threshold. c_f sensitivity: "
                  f"{gd_sens_txt}. All closed loops stable "
                  f"(max pole real part {max_re:.1f} 1/s)."),
        ),
        Claim(
            id="6.4.2/gamma-optimum",
            source="Sec. 6.4.2, Fig. 6.7-6.8",
            claim=("RMS force difference γ between FI+Dahl and FI+GMS over a 5 mm circle cycle is "
                   "minimal at k_fi/k_f ≈ 0.05-0.1; Dahl underestimates at very small k_fi and "
                   "over-compensates at large k_fi"),
            seed="γ minimum at k_fi/k_f ≈ 0.05-0.1; under- (small k_fi) / over-compensation (large)",
            ours=(f"γ min {gam[i_min]:.3f} N at k_fi/k_f = {eta_min:.3f} (γ = {g_at[0.05]:.2f} N at 0.05, "
                  f"{g_at[0.1]:.2f} N at 0.1); under-est. for η < {cross:.3g}, over-comp. above"),
            agrees=gamma_ok,
            numbers=dict(k_f=K_F, F_C=F_C, radius=CIRCLE_R, samples_per_cycle=N_CYCLE,
                         eta_min=eta_min, gamma_min=float(gam[i_min]),
                         **{f"gamma_at_{k:g}": v for k, v in g_at.items()},
                         gamma_eta_1em3=float(gam[0]), gamma_eta_10=float(gam[-1]),
                         bias_eta_1em3=float(bias[0]), bias_eta_1=float(np.interp(0.0, np.log(ETA_GRID), bias)),
                         bias_sign_change_eta=float(cross), u_shaped=u_shape,
                         underestimates_small=under_small, overcompensates_large=over_large,
                         eta_min_second_cycle=eta_min2, gamma_min_second_cycle=float(gam2.min()),
                         gms_initial_stiffness=float(gk.sum()), gms_alpha_sum=float(GMS_ALPHA.sum()),
                         gms_scale_vs_table_6_5=float(gk.sum() / GMS_K.sum()),
                         eta_min_as_printed=eta_of(gam_pr), eta_min_second_cycle_as_printed=eta_of(gam2_pr),
                         eta_min_common_scale_table_6_5=eta_of(gam_s65),
                         eta_min_second_cycle_common_scale_table_6_5=eta_of(gam2_s65),
                         eta_min_ch4_tables=eta_of(gam_ch4), eta_min_second_cycle_ch4_tables=eta_of(gam2_ch4),
                         table_4_5_dev_series=t45_series, table_4_5_dev_per_block=t45_per_block,
                         acceptance_range=[lo_tol, hi_tol]),
            note=(f"criterion: argmin of γ within 0.05-0.1 widened by 1/10 decade "
                  f"({lo_tol:.3f}-{hi_tol:.3f}), mean (F_Dahl−F_GMS)·sgn(v) < 0 at η = 1e-3 and > 0 for η ≥ 1. "
                  f"Model: FI + GMS = the GMS blocks in exact series with k_fi — the seed's construction: "
                  f"applied to Table 4.4 with k_fi = 8.27e4 N/m it reproduces the seed's Table 4.5 virgin "
                  f"curve to {100 * t45_series:.1f} % of F_C (each block in series with its own k_fi: "
                  f"{100 * t45_per_block:.0f} %). Dahl and GMS share the initial stiffness (both from the same "
                  f"FRFs, Sec. 4.4.3; Tables 4.3/4.4 agree to 0.2 %), so Table 6.5's block distribution is "
                  f"used with Σk_i = k_σ = {K_F:.3g} N/m (Table 6.4; ×{gk.sum() / GMS_K.sum():.2f} on the "
                  f"printed k_i, whose Σ = {GMS_K.sum():.3g} N/m contradicts Table 6.4). The optimum does "
                  f"not depend on which value is the common one: with Σk_i = k_σ = {GMS_K.sum():.3g} N/m "
                  f"(Table 6.5's scale) it is at η = {eta_of(gam_s65):.3f} as well. With the tables as "
                  f"printed (Dahl 3.5× stiffer than the GMS it is compared with) Dahl over-compensates as "
                  f"soon as k_fi stops dominating and the optimum falls to η = {eta_of(gam_pr):.3f}, outside "
                  f"the seed's range. The block distribution matters: the Ch. 4 bearing (Tables 4.3/4.4, "
                  f"consistent) puts it at η = {eta_of(gam_ch4):.3f}. One cycle from the relaxed state; the "
                  f"steady second cycle gives η = {eta_min2:.3f}."),
        ),
        Claim(
            id="6.4.2/kappa-eq4.2",
            source="Sec. 4.1 Eq. 4.1-4.2, Sec. 6.4.2 Fig. 6.9",
            claim=("κ = ∂k_c/∂k_f = (η/(1+η))² for the quasi-static series model, and κ < 0.01 for "
                   "η = k_fi/k_f < 0.1 (robust FF compensation)"),
            seed="κ = (η/(1+η))²; κ small (robust) for η < 0.1",
            ours=(f"simulated κ matches Eq. 4.2 to {kap_err:.1e} (rel.) over η 1e-3..10; "
                  f"κ(0.1) = {float(kappa_simulated(0.1)):.5f} < 0.01; κ→0 as η→0, κ→1 as η→∞"),
            agrees=kappa_ok,
            numbers=dict(k_f=K_F, kappa_max_rel_error=kap_err, kappa_at_0_1=float(kappa_simulated(0.1)),
                         kappa_eq42_at_0_1=float(kappa_eq42(0.1)), kappa_eta_1em4=kap_lim0,
                         kappa_eta_1e4=kap_liminf, kappa_below_0_01_for_eta_lt_0_1=kap_small,
                         k_c_check_eta_0_01=float(combined_stiffness(0.01 * K_F, K_F)),
                         k_c_eq41_eta_0_01=float(0.01 * K_F * K_F / (1.01 * K_F))),
            note=("criterion: |κ_sim/κ_Eq4.2 − 1| < 1e-4 on the η grid, κ < 0.01 for all η < 0.1, "
                  "κ(1e-4) < 1e-6 and κ(1e4) > 0.999. κ_sim: table displaced 1 µm through k_fi against a "
                  "linear k_f with the same exact series solver as Fig. 6.8, k_f perturbed ±0.1 %. The "
                  "text contradicts itself: Eq. 4.2's 'k_fi ≪ k_f, η → 0' is right (η = k_fi/k_f → 0 "
                  "gives κ → 0); Sec. 6.4.2's 'η → ∞ and κ → 0' is wrong — η → ∞ (rigid FI) gives "
                  "κ → 1, the No FI sensitivity."),
        ),
    ]
    return claims_
