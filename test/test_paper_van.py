"""Seed Sec. 3.2 (VAN simulations, Fig. 3.4/3.5/3.8) and Appendix B (averaged dynamics).

Runs the claim modules once (module-scoped) and checks each reproduced claim, its
numeric evidence and the plots.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from experiment_runner.apps.paper import Claim, appendix_b, van


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    return tmp_path_factory.mktemp("paper_van")


@pytest.fixture(scope="module")
def van_claims(out):
    return {c.id: c for c in van.claims(out)}


@pytest.fixture(scope="module")
def b_claims(out):
    return {c.id: c for c in appendix_b.claims(out)}


@pytest.mark.slow
def test_claims_are_well_formed(van_claims, b_claims):
    claims = list(van_claims.values()) + list(b_claims.values())
    assert len(claims) == 4
    for c in claims:
        assert isinstance(c, Claim)
        assert c.seed and c.ours and c.source
        assert isinstance(c.agrees, bool)


@pytest.mark.slow
def test_fig_3_4_cliff_canyon_plain(van_claims):
    c = van_claims["3.2/fig3.4-cliff-canyon-plain"]
    assert c.agrees, c.note
    stats = c.numbers["stats"]
    assert len(stats) == 8                                   # 4 deltas x 2 steps
    for s in stats.values():
        # cliff: at the lowest A*f the dither gains < 2x (the 50 nm cliff is erratic: 0.7x to
        # not settled), while the canyon gains > 100x
        assert s["corner"] >= 0.5 * s["no_dither"]
        assert s["corner"] >= 50 * s["opt"]
        assert s["opt"] < 0.01 * s["no_dither"]
        assert s["opt"] <= 0.7 * s["plain_med"]              # canyon below the plain
        assert s["canyon_cuts_ok"] == s["canyon_cuts"]       # A-cuts: down into canyon, up to plain
        assert s["plain_spread"] <= 0.3                      # flat plain
    meds = [s["plain_med"] for s in stats.values()]
    assert max(meds) <= 1.15 * min(meds)                     # plain alike for every delta/step


@pytest.mark.slow
def test_fig_3_5_near_benchmark(van_claims):
    c = van_claims["3.2/fig3.5-near-benchmark"]
    assert c.agrees, c.note
    bench = np.array(c.numbers["ts_benchmark_rigid"])
    for ts in c.numbers["ts_van"].values():
        assert np.all(np.abs(np.array(ts) - bench) <= 0.2 * bench)
    for ts in c.numbers["ts_no_dither"].values():             # without dither: >20x slower
        assert np.all(np.array(ts) > 20 * bench)


@pytest.mark.slow
def test_fig_3_8_harmonic_cancelling(van_claims):
    c = van_claims["3.2/fig3.8-harmonic-cancelling"]
    hc = c.numbers["hc"]
    assert not math.isfinite(hc["0"]["settling"])            # K_HC = 0: never settles
    assert 28e-9 <= hc["0"]["pp_tail"] <= 52e-9              # ~40 nm p-p parasitic vibration
    assert math.isfinite(hc["4e+09"]["settling"])
    t = [hc[k]["settling"] for k in ("1e+09", "2e+09", "4e+09")]
    assert t[0] > t[1] > t[2]                                # faster with higher K_HC
    os_ = c.numbers["overshoot_steps"]
    assert os_[1] < 0.5 * os_[0]                             # overshoot shrinks over the steps
    assert c.agrees, c.note


@pytest.mark.slow
def test_appendix_b_averaged_dynamics(b_claims):
    c = b_claims["B/averaged-vs-full"]
    assert c.agrees, c.note
    n = c.numbers
    # dimensional Eq. B.16: c_eq = K_D + pi m F_C / (2 a w)
    assert n["c_eq"] == pytest.approx(n["K_D"] + math.pi * n["m"] * n["F_C"] / (2 * n["a"] * n["omega"]))
    assert n["zeta_eq"] == pytest.approx(n["c_eq"] / (2 * n["m"] * n["omega_n"]))
    for key in ("50nm", "500nm"):
        step = n[f"{key}.step"]
        assert n[f"{key}.rms_slow_minus_averaged"] <= 0.05 * step
        # the averaged model explains the slow motion far better than the frictionless one
        assert n[f"{key}.rms_slow_minus_averaged"] < 0.5 * n[f"{key}.rms_slow_minus_frictionless"]
        assert n[f"{key}.final_no_dither"] < 0.5 * step        # without dither the stage sticks
        assert abs(n[f"{key}.final_slow"] - step) < 0.02 * step
    assert not math.isfinite(n["50nm.settling_full_raw"])     # raw 28 nm p-p vibration > +-10 nm


@pytest.mark.parametrize("name", ["fig_3_4_van_settling_maps.png", "fig_3_5_van_responses.png",
                                  "fig_3_8_van_hc.png", "fig_B1_averaged_vs_full.png"])
@pytest.mark.slow
def test_plots_exist(out, van_claims, b_claims, name):
    p = out / name
    assert p.is_file() and p.stat().st_size > 10_000
