"""Chapter 6 FI design analysis (Sec. 6.3.2, 6.4.2) and Appendix D rotary FI claims.

Module-scoped fixtures run ``experiment_runner.apps.paper.fi_design`` and ``...rotary`` once.
Claims that reproduce assert ``agrees``; for the one that does not (Fig. 6.3(b) stiffness
trend) the test pins the honest property we find instead and its first-order explanation.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from experiment_runner.apps.paper import fi_design, rotary
from stage_control import isolator


@pytest.fixture(scope="module")
def fi_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("fi_design")
    return out, {c.id: c for c in fi_design.claims(out)}


@pytest.fixture(scope="module")
def rot_out(tmp_path_factory):
    out = tmp_path_factory.mktemp("rotary")
    return out, {c.id: c for c in rotary.claims(out)}


# ----------------------------------------------------------------------------- plant model
def test_plant_matches_equations_of_motion():
    """G(s) of Fig. 6.2 equals the direct solution of the 2-DOF equations at a few s."""
    m_t, m_b, k, c, kf, cf = 0.8, 0.6, 3.3e4, 240.0, 2.19e6, 175.0
    G = isolator.plant_fi(m_t, m_b, k, c, kf, cf)
    for w in (3.0, 300.0, 3000.0):
        s = 1j * w
        z, f = c * s + k, cf * s + kf
        A = np.array([[m_t * s**2 + z, -z], [-z, m_b * s**2 + z + f]])
        xt = np.linalg.solve(A, np.array([1.0, 0.0]))[0]
        assert abs(G(s) / xt - 1) < 1e-9
    # rigid limit -> No FI
    G_rigid = isolator.plant_fi(m_t, m_b, 1e12, 0.0, kf, cf)
    G0 = isolator.plant_nofi(m_t, m_b, kf, cf)
    assert abs(G_rigid(100j) / G0(100j) - 1) < 1e-4


def test_series_solver_linear_and_gms_limits():
    # linear spring: k_c = Eq. 4.1
    for eta in (1e-3, 0.1, 1.0, 10.0):
        kc = isolator.combined_stiffness(eta * 2.19e6, 2.19e6)
        assert math.isclose(kc, eta * 2.19e6 / (1 + eta), rel_tol=1e-9)
    # very stiff FI: series GMS -> plain GMS driven by the table
    from stage_sim.friction import GMS
    _, xt = isolator.circle_x_path(n=2000)
    f_series, _ = isolator.series_gms(xt, 1e14, isolator.GMS_K, isolator.GMS_ALPHA, 5.31)
    f_plain = GMS(isolator.GMS_K, isolator.GMS_ALPHA, 5.31).drive(xt)
    assert np.max(np.abs(f_series - f_plain)) < 1e-6
    # equilibrium: spring force = friction force at every sample
    k_fi = 0.05 * 2.19e6
    f, xb = isolator.series_gms(xt, k_fi, isolator.GMS_K, isolator.GMS_ALPHA, 5.31)
    assert np.max(np.abs(k_fi * (xt - xb) - f)) < 1e-9


def test_series_construction_reproduces_table_4_5():
    """The seed's FI-case GMS (Table 4.5) is the virgin curve of Table 4.4 in series with k_fi."""
    dev_series, dev_per_block = isolator.table_4_5_check()
    assert dev_series < 0.01            # 0.5 % of F_C over 0..400 um
    assert dev_per_block > 0.2          # each block with its own k_fi: not the seed's table
    # Table 4.5's initial stiffness = k_sigma,FI of Table 4.3 (8.08e4 N/m), within rounding
    assert math.isclose(isolator.GMS45_K.sum(), 8.08e4, rel_tol=0.01)
    assert math.isclose(isolator.GMS4_K.sum(), 2.19e6, rel_tol=0.005)   # Table 4.4 = Table 4.3's k_sigma


def test_gamma_optimum_scale_invariant_and_consistency_matters():
    """Fig. 6.8 on a coarse grid: same optimum for any common k_sigma = sum k_i, not for the printed pair."""
    etas = np.logspace(-2, 0, 9)
    g1, _, _ = isolator.gamma_curve(etas, gms_k=isolator.gms_consistent())
    g2, _, _ = isolator.gamma_curve(etas, k_f=float(isolator.GMS_K.sum()), gms_k=isolator.GMS_K)
    g3, _, _ = isolator.gamma_curve(etas)                                  # Tables 6.4/6.5 as printed
    assert np.argmin(g1) == np.argmin(g2)
    assert 0.05 <= etas[np.argmin(g1)] <= 0.2
    assert etas[np.argmin(g3)] <= 0.04


def test_rotary_eq_d1_d2_from_equations_of_motion():
    """D.1/D.2 re-derived: roller + two bearings, same T_f on both."""
    k, c, cf = 300.0, 0.01, 2.0
    Gp, D, *_ = rotary.blocks(k, c, cf)
    for w in (2.0, 150.0, 3000.0):
        s = 1j * w
        z = c * s + k
        A = np.array([[rotary.I_P * s**2 + 2 * z, -2 * z], [-z, rotary.I_A * s**2 + z + cf * s]])
        x_ta = np.linalg.solve(A, np.array([1.0, 0.0]))[0]     # motor torque
        x_tf = np.linalg.solve(A, np.array([0.0, 1.0]))[0]     # T_f on each bearing
        assert abs(Gp(s) / x_ta - 1) < 1e-9
        assert abs(D(s) / x_tf - 1) < 1e-9


# ----------------------------------------------------------------------------- fi_design claims
@pytest.mark.slow
def test_fi_design_plots(fi_out):
    out, _ = fi_out
    for name in ("fig_6_3_Ge.png", "fig_6_4_Gd.png", "fig_6_7_forces.png", "fig_6_8_gamma.png",
                 "fig_6_9_kappa.png"):
        assert (out / name).stat().st_size > 10_000, name


@pytest.mark.slow
def test_ge_claim_honest_property(fi_out):
    """Fig. 6.3(b) in the seed's model: ||G_e|| has an optimum in k_fi, not a plateau (whether that
    agrees with the seed's "thresholds" is the claim's verdict in claims.md, not this test's)."""
    c = fi_out[1]["6.3.2/Ge-threshold"]
    n = c.numbers
    # reproduced parts
    for lab in ("LS-LD", "LS-HD", "HS-HD"):
        assert n[f"Ge_ratio_{lab}"] <= 0.5
    assert n["Ge_LS-LD"] < n["Ge_LS-HD"] < n["Ge_HS-HD"] < n["Ge_nofi"]
    assert n["Ge_monotone_in_c"] and n["Ge_c_threshold_min"] >= 10.0
    assert n["Ge_monotone_above_kopt"]
    # the disagreement: softer than k* is clearly worse, for every c_f and structural variant
    assert n["Ge_rise_below_kopt_max_c_le_1000"] > 0.5
    assert 2e4 < n["Ge_k_opt_vs_c"]["1"] < 8e4
    for v in list(n["sensitivity_c_f"].values()) + list(n["variants"].values()):
        assert v["ge_table_ok"] and v["ge_mono_c"]
    assert n["max_closed_loop_pole_real"] < 0
    # first-order explanation: |G_e| ~ |k_fi - m_t w^2| / |C| gives the optimum and the rise
    k_opt = n["Ge_k_opt_vs_c"]["1"]
    assert abs(n["Ge_k_opt_estimate"] / k_opt - 1) < 0.25
    assert n["Ge_rise_estimate"] > 0.5
    # python-control feedback() gives the same norms as the vectorised map
    assert n["Ge_python_control_max_rel_dev"] < 1e-9


@pytest.mark.slow
def test_gd_claim_agrees(fi_out):
    c = fi_out[1]["6.3.2/Gd-monotone"]
    assert c.agrees, c.note
    n = c.numbers
    assert n["Gd_nofi"] < n["Gd_grid_min"]
    assert n["Gd_HS-HD"] < n["Gd_LS-HD"] < n["Gd_LS-LD"]
    assert all(v["agrees"] for v in n["sensitivity_c_f"].values())


@pytest.mark.slow
def test_gamma_claim_agrees_with_consistent_friction_models(fi_out):
    """Fig. 6.8: with Dahl and GMS sharing the initial stiffness (the seed's identification) the
    optimum lies in 0.05-0.1 (±1/10 decade); the printed Tables 6.4/6.5, which disagree on it, put
    it at ~0.02."""
    c = fi_out[1]["6.4.2/gamma-optimum"]
    n = c.numbers
    assert c.agrees, c.note
    assert n["u_shaped"] and n["underestimates_small"] and n["overcompensates_large"]
    assert 0.0397 <= n["eta_min"] <= 0.126
    assert 0.0397 <= n["eta_min_second_cycle"] <= 0.126
    assert math.isclose(n["gms_initial_stiffness"], 2.19e6, rel_tol=1e-9)
    # the optimum depends on the two models sharing k_sigma, not on which value is shared
    assert n["eta_min_common_scale_table_6_5"] == n["eta_min"]
    # the tables as printed (sum k_i = 0.28 k_sigma) give the old, wrong optimum
    assert 0.01 <= n["eta_min_as_printed"] <= 0.035
    # the series construction is the seed's (Table 4.5), the per-block one is not
    assert n["table_4_5_dev_series"] < 0.01 and n["table_4_5_dev_per_block"] > 0.2


@pytest.mark.slow
def test_kappa_claim_agrees(fi_out):
    c = fi_out[1]["6.4.2/kappa-eq4.2"]
    assert c.agrees, c.note
    assert c.numbers["kappa_at_0_1"] < 0.01
    assert "η → ∞" in c.note


# ----------------------------------------------------------------------------- rotary claims
@pytest.mark.slow
def test_rotary_plots(rot_out):
    out, _ = rot_out
    for name in ("fig_D5_Gd.png", "fig_D12_tracking_error.png"):
        assert (out / name).stat().st_size > 10_000, name


@pytest.mark.slow
def test_d5_claim_agrees(rot_out):
    c = rot_out[1]["D.2/Gd-lowpass"]
    assert c.agrees, c.note
    assert all(v < 0 for v in c.numbers["max_pole_real"].values())


@pytest.mark.slow
def test_d4_rms_claim(rot_out):
    c = rot_out[1]["D.4/rms-10rpm"]
    n = c.numbers
    rms = {k: n[f"rms_true.{k}"] for k in rotary.PRESETS}
    assert rms["FI w/ damper"] < rms["No FI"] < rms["FI w/o damper"]
    # simulation agrees with the linear Eq. D.3 prediction for the same disturbance spectrum
    for k in rotary.PRESETS:
        assert abs(rms[k] / n[f"rms_predicted_EqD3.{k}"] - 1) < 0.15, k
    assert c.agrees, c.note
