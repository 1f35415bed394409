"""The friction isolator (FI) of Ch. 6 as a model: the Fig. 6.2 plant, its closed-loop error and
disturbance norms over ``k_fi, c_fi`` (Sec. 6.3.2) and the quasi-static series solver of the FI with
the bearing's GMS / Dahl friction (Sec. 6.4.2), with the seed's table values. Used by the design
advisor (:mod:`experiment_runner.apps.design`) and by the reproduction of the chapter's claims
(:mod:`experiment_runner.apps.paper.fi_design`).
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

import numpy as np
from numba import njit

import control as ct

from stage_control.tuning import pid_tf
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
CIRCLE_R = 5e-3                   # Sec. 6.4: 5 mm radius circle
ZETA_F = 0.05                     # estimate: damping ratio of the No-FI friction mode -> c_f

# ----------------------------------------------------------------------------- grids
F_E = np.arange(1.0, 50.0 + 1e-9, 0.1)        # Fig. 6.3(b) band [Hz]
F_D = np.arange(1.0, 500.0 + 1e-9, 0.1)       # Fig. 6.4(b) band [Hz]
K_GRID = np.logspace(3, 6, 31)                # k_fi [N/m] (Table 6.2: 2.9e4-6.8e4)
C_GRID = np.logspace(0, 4, 33)                # c_fi [N s/m] (Table 6.2: 240-990)
ETA_GRID = np.logspace(-3, 1, 81)             # k_fi/k_f for Fig. 6.8/6.9
N_CYCLE = 10_000                              # samples per circle cycle (Fig. 6.8)


# ============================================================================= Sec. 6.3.2


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


# ============================================================================= Sec. 6.4.2
@njit(cache=True)
def series_gms(xt, k_fi, k, alpha, f_c):
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
def dahl_path(xt, k_sigma, f_c):
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
    return (dahl_path(xt, k_sig, f_c),
            series_gms(xt, k_fi, np.asarray(gms_k, float), np.asarray(gms_alpha, float), f_c)[0])


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
    return series_gms(x, k_fi, np.asarray(k, float), np.asarray(alpha, float), f_c)[0]


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
    force, _ = series_gms(xt, k_fi, np.array([k_f]), np.array([1e30]), 1.0)
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
