"""Appendix A claims (Fig. A.2 PID vs K_I, Fig. A.3 NIASA robustness) on our simulator."""
import json
import math
from dataclasses import asdict

import pytest

from experiment_runner.apps.paper import Claim
from experiment_runner.apps.paper.appendix_a import claims

pytestmark = pytest.mark.slow              # the claims' simulations: ~8 s, shared by every test here


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("appendix_a")
    return out, {c.id: c for c in claims(out)}


def test_claims_are_well_formed(result):
    _, cs = result
    assert set(cs) == {"A.2/ki0-no-settle", "A.2/best-ki-50nm", "A.2/ki3e3-500nm-slower",
                       "A.2/ki6e3-unstable", "A.3/niasa-robustness", "A.3/niasa-500nm"}
    for c in cs.values():
        assert isinstance(c, Claim) and c.seed and c.ours and c.note
        json.dumps(asdict(c), allow_nan=False)      # numbers are plain, finite JSON


def test_plots_written(result):
    out, _ = result
    for name in ("appendix_a_fig_a2.png", "appendix_a_fig_a2_sweep.png", "appendix_a_fig_a3.png"):
        f = out / name
        assert f.is_file() and f.stat().st_size > 10_000
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_ki0_does_not_settle(result):
    c = result[1]["A.2/ki0-no-settle"]
    assert c.agrees
    assert c.numbers["kind"] == ["stuck", "stuck"]
    # stopped well short of the target by the pre-motion spring
    assert all(x < 0.5 * d for x, d in zip(c.numbers["final_position"], c.numbers["step"]))


def test_best_ki_50nm_near_3e3_and_about_33_percent_faster(result):
    c = result[1]["A.2/best-ki-50nm"]
    assert c.agrees
    assert 2e9 <= c.numbers["ki_best"] <= 4e9
    assert abs(c.numbers["reduction_best"] - 0.33) <= 0.10
    assert abs(c.numbers["reduction_ki_3e3"] - 0.33) <= 0.10


def test_ki3e3_500nm_large_overshoot_but_not_slower(result):
    # The large overshoot is reproduced; the response re-enters the +-100 nm window on its first
    # return (whether that agrees with the seed's "+31 % slower" is the claim's verdict, claims.md).
    c = result[1]["A.2/ki3e3-500nm-slower"]
    assert c.numbers["overshoot"] > 0.5
    assert c.numbers["relative_change"] < 0
    # independent continuous-time model (derivative on the error) agrees with the engine
    assert math.isclose(c.numbers["cont_ki3e3"], c.numbers["settling_ki_3e3_500nm"], abs_tol=1e-3)
    assert math.isclose(c.numbers["cont_bench"], c.numbers["benchmark_500nm"], abs_tol=5e-4)


def test_ki3e3_500nm_sign_not_determined_by_the_seeds_rounding(result):
    """Over K_I = 2.5e3..3.5e3 (what rounds to the seed's 3e3) the 500 nm settling time relative
    to the benchmark changes sign (lobe jumps), and stays below the seed's +31 % with the
    derivative on the error; the derivative on the measurement reaches +31 % +- 10 points there."""
    n = result[1]["A.2/ki3e3-500nm-slower"].numbers
    eng = [v for v in n["rounding_rel_change_engine"] if v is not None]
    assert len(eng) == len(n["rounding_ki"])                      # all settle
    assert min(eng) < -0.1 and max(eng) > 0.05                     # both signs, well beyond resolution
    assert max(eng) < 0.31 - 0.10                                  # never the seed's +31 %
    dm = n["rounding_rel_change_cont_dmeas"]
    assert any(v is not None and abs(v - 0.31) <= 0.10 for v in dm)
    assert 0.23 <= n["cont_dmeas_reduction_50nm_ki3e3"] <= 0.43   # 50 nm claim holds in that form too


def test_ki6e3_limit_cycle_and_instability(result):
    c = result[1]["A.2/ki6e3-unstable"]
    assert c.agrees
    assert c.numbers["kind"] == ["limit cycle", "unstable"]
    assert c.numbers["pp_last_50nm"] > 2 * 10e-9          # cannot fit the +-10 nm window


def test_niasa_robustness(result):
    c = result[1]["A.3/niasa-robustness"]
    assert c.agrees
    n = c.numbers
    assert n["kind_50nm"] == ["limit cycle", "settled", "settled", "settled", "settled"]
    assert n["kind_500nm"][1:] == ["settled"] * 4
    assert n["pp_last_50nm_delta_m065"] > 2 * 10e-9
    assert n["spread_50nm"] >= 0.25


def test_niasa_500nm_affected_by_delta(result):
    c = result[1]["A.3/niasa-500nm"]
    assert c.agrees
