"""Design advisor (experiment_runner.apps.design, ``nanostage design``): FI recommendation rule, VAN checks, CLI.

One coarse, short sweep of ``fi_stage`` (module fixture) serves the rule tests; requirements are
chosen from the sweep's own range so every branch (feasible, edge, infeasible) is exercised.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from experiment_runner.apps.design.advice import advise_isolator, recommend
from experiment_runner.apps.design.cli import main_design
from experiment_runner.apps.design.sweep import GRIDS, isolator_preset, lumped_stage, sweep_isolator
from experiment_runner.apps.design.van import Flexure, check_van
from experiment_runner.core.errors import DesignError

K_GRID = np.logspace(4, 6.5, 6)        # stage totals [N/m]
C_GRID = np.array([1.0, 30.0, 1000.0])  # [N·s/m]


@pytest.fixture(scope="module")
def sweep():
    return sweep_isolator("fi_stage", K_GRID, C_GRID, n_trials=3, dwell=0.25)


def _requirements(sw):
    r = np.sort(sw.rms_mean[np.isfinite(sw.rms_mean)])
    return np.unique(np.concatenate([r, (r[1:] + r[:-1]) / 2, [r[0] * 0.9, r[-1] * 1.1]]))


@pytest.mark.slow
def test_recommendation_meets_requirement_and_next_softer_does_not(sweep):
    reqs = _requirements(sweep)
    seen_inner = False
    for req in reqs:
        a = recommend(sweep, float(req))
        if a.recommended is None:
            assert not a.feasible.any()
            continue
        p = a.recommended
        i, j = p.index
        assert sweep.settled[i, j] and p.rms_in_position_m <= req
        assert p.k_fi == sweep.k_grid[i] and p.c_fi == sweep.c_grid[j]
        # least damped at that stiffness, and no softer stiffness meets it at any damping
        assert not a.feasible[i, :j].any()
        if i > 0:
            seen_inner = True
            rms_softer = sweep.rms_mean[i - 1]
            assert np.all(~sweep.settled[i - 1] | (rms_softer > req))
    # the requirement range covers both "grid edge" and an interior recommendation
    assert recommend(sweep, float(reqs[-1])).recommended.index[0] == 0
    assert seen_inner
    # below the best point nothing is feasible: clear message, no recommendation
    a = recommend(sweep, float(reqs[0]))
    assert a.recommended is None and not a.ok and "no FI" in a.message


@pytest.mark.slow
def test_tighter_requirement_never_gives_softer_isolator(sweep):
    ks = []
    for req in _requirements(sweep)[::-1]:          # loosest first
        a = recommend(sweep, float(req))
        ks.append(math.inf if a.recommended is None else a.recommended.k_fi)
    assert all(k2 >= k1 for k1, k2 in zip(ks, ks[1:]))
    assert ks[0] < ks[-1]                           # and it does change over the range


@pytest.mark.slow
def test_sweep_contents(sweep):
    """Norms follow Sec. 6.3.2 on the grid; No FI lower G_d than any FI; Dahl-vs-GMS γ reported."""
    assert sweep.ts.shape == (K_GRID.size, C_GRID.size, 3)
    assert np.all(np.diff(sweep.gd, axis=0) < 0)      # stiffer FI: smaller ||G_d|| (Fig. 6.4(b))
    assert sweep.gd_nofi < sweep.gd.min()
    lp = sweep.lumped
    assert lp.n_joints == 2 and math.isclose(lp.k_fi, 8.27e4) and math.isclose(lp.k_f, 2.19e6)
    a = recommend(sweep, float(np.nanmax(sweep.rms_mean)))
    p = a.recommended
    assert math.isclose(p.eta, p.k_fi / 2.19e6) and p.gamma_n > 0 and math.isclose(p.kappa, (p.eta / (1 + p.eta)) ** 2)
    # the sweep reuses the servo/dither/SAI models and rebuilds only the plant: same trials as a full build
    i, j = 2, 1
    ts, rms = sweep.moves.run(isolator_preset("fi_stage", K_GRID[i], C_GRID[j]))
    assert np.array_equal(ts, sweep.ts[i, j]) and np.array_equal(rms, sweep.rms[i, j])
    # the seed's own FI settles a 5 um step much faster than the grid's stiffest FI (Table 4.2 trend)
    assert a.preset_design.settling_time_s < np.nanmin(sweep.ts_mean[-1])


@pytest.mark.slow
def test_sweep_on_two_worker_processes_is_identical(sweep):
    """The k_fi rows run as executor tasks: a local 2-process pool gives the same trials."""
    sw2 = sweep_isolator("fi_stage", K_GRID[:2], C_GRID, n_trials=3, dwell=0.25, workers=2)
    assert np.array_equal(sw2.ts, sweep.ts[:2], equal_nan=True)
    assert np.array_equal(sw2.rms, sweep.rms[:2], equal_nan=True)


def test_advise_isolator_bad_input():
    with pytest.raises(DesignError, match="rms_required_m"):
        advise_isolator("fi_stage", 0.0, grid="coarse")
    with pytest.raises(DesignError, match="rms_required_m"):
        advise_isolator("fi_stage", -1e-9, grid="coarse")
    with pytest.raises(DesignError, match="no bearing on a compliant joint"):
        advise_isolator("fi_stage_nofi", 3e-9, grid="coarse")
    with pytest.raises(DesignError, match="grid"):
        advise_isolator("fi_stage", 3e-9, grid="huge")


# ----------------------------------------------------------------------------- VAN
def test_piezo_power_matches_eq_3_7_by_hand():
    v = check_van("van_stage")
    # hand: P-842.10 k_p = 300 N / 15 um = 2e7 N/m in series with the 6.9e6 N/m flexure;
    # flexure force per volt = 6.9e6 * 0.15e-6 * 2e7 / 2.69e7; 15 N p-p (A = 7.5 N)
    fpv = 6.9e6 * 0.15e-6 * 2e7 / 2.69e7
    vpp = 15.0 / fpv
    assert math.isclose(v.v_pp, vpp, rel_tol=1e-12)
    assert math.isclose(v.power_per_piezo_w, 500.0 * 1.5e-6 * vpp ** 2, rel_tol=1e-12)
    assert math.isclose(v.power_total_w, 2 * 500.0 * 1.5e-6 * vpp ** 2, rel_tol=1e-12)
    # the seed's operating point: 20 V p-p, 500 Hz -> 0.3 W per actuator, 0.6 W total (Sec. 3.4.3)
    s = check_van("van_stage", v_pp=20.0)
    assert math.isclose(s.power_per_piezo_w, 0.3, rel_tol=1e-12) and math.isclose(s.power_total_w, 0.6)
    assert math.isclose(s.heat_per_move_j, 0.015, rel_tol=1e-12)


def test_fatigue_passes_for_seed_design_and_fails_when_overstressed():
    v = check_van("van_stage")
    assert v.passed
    # Table 3.2: d_e 3.52 mm, p_a 0.86, p_b 1.08, S_e 195.4 MPa (rounded factors; unrounded 196.4)
    assert math.isclose(v.d_e, 3.52e-3, rel_tol=2e-3)
    assert round(v.p_a, 2) == 0.86 and round(v.p_b, 2) == 1.08
    assert abs(v.s_e - 195.4e6) < 1.5e6
    assert math.isclose(v.max_load_n, 77.0, rel_tol=2e-3)        # Sec. 3.3: 77 N at 100 V
    assert 4.0 < v.fatigue_safety < 4.4
    # a flexure 5x more stressed per newton (e.g. thinner hinge) exceeds S_e: finite life
    bad = check_van("van_stage", flexure=Flexure(stress_ref=5 * 47e6))
    assert not bad.passed and bad.fatigue_safety < 1 and "FAIL" in bad.message
    # a weaker material at the seed's stress: yield and fatigue both fail
    weak = check_van("van_stage", flexure=Flexure(s_ut=80e6, s_y=40e6))
    assert not weak.passed and weak.yield_safety < 1


def test_van_bad_input():
    with pytest.raises(DesignError, match="no dither"):
        check_van("fi_stage")


# ----------------------------------------------------------------------------- CLI
def _cli(argv):
    """``nanostage design argv``: bad input is the CLI's message (or argparse's, for a bad
    option value) and exit 2."""
    from experiment_runner.apps.cli import main
    try:
        return main(["design", *argv])
    except SystemExit as exc:
        return exc.code


def test_cli_exit_codes(tmp_path, capsys):
    assert _cli(["nosuch_preset", "--rms", "3"]) == 2
    assert "nosuch_preset" in capsys.readouterr().err
    assert _cli(["fi_stage", "--rms", "0"]) == 2
    assert _cli(["fi_stage", "--rms", "-2"]) == 2
    assert _cli(["fi_stage"]) == 2                                   # requirement missing
    assert _cli(["fi_stage_nofi", "--rms", "3"]) == 2
    assert "no bearing on a compliant joint" in capsys.readouterr().err
    assert _cli(["fi_stage_nofi", "--van"]) == 2
    assert _cli(["fi_stage", "--rms", "3", "--set", "stage.table.mass=-1"]) == 2
    assert "stage.table.mass" in capsys.readouterr().err
    assert _cli(["fi_stage", "--rms", "3", "--set", "nonsense"]) == 2
    # VAN preset: automatic VAN check, passes
    assert _cli(["van_stage", "--out", str(tmp_path / "van"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["van"]["passed"] is True and (tmp_path / "van" / "design.md").is_file()


@pytest.mark.slow
def test_cli_fi_run_writes_report(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(GRIDS, "coarse", (np.array([2e4, 2e5]), np.array([1.0, 300.0])))
    out = tmp_path / "fi"
    # a loose requirement is met (0), an impossible one is not (1)
    assert _cli(["fi_stage", "--rms", "50", "--grid", "coarse", "--trials", "2", "--dwell", "0.2",
                 "--out", str(out)]) == 0
    txt = capsys.readouterr().out
    assert "recommended" in txt and "No FI" in txt
    assert {p.name for p in out.iterdir()} >= {"design.md", "design.json", "design_maps.png", "design_norms.png",
                                                "design_gamma.png"}
    doc = json.loads((out / "design.json").read_text())["isolator"]
    assert doc["ok"] and doc["recommended"]["k_fi"] == 2e4 and doc["recommended"]["c_fi"] == 1.0
    assert _cli(["fi_stage", "--rms", "0.01", "--grid", "coarse", "--trials", "2", "--dwell", "0.2",
                 "--out", str(out), "--no-plots"]) == 1


@pytest.mark.slow
def test_wired_in_nanostage_cli():
    from experiment_runner.apps.cli import build_parser
    args = build_parser().parse_args(["design", "van_stage", "--vpp", "20"])
    assert args.func is main_design and args.vpp == 20.0


def test_gamma_gms_shares_the_dahl_initial_stiffness():
    """Without GMS bearings in the preset, γ's GMS is Table 6.5's block distribution with the
    preset's initial stiffness k_f (the seed identifies both from the same FRFs), not Table 6.5's
    printed Σk_i = 6.17e5 N/m."""
    from stage_control import isolator
    lp = lumped_stage("fi_stage")                           # Dahl bearings (Table 4.3)
    assert math.isclose(sum(lp.gms_k), lp.k_f, rel_tol=1e-12)
    np.testing.assert_allclose(np.array(lp.gms_k) / lp.k_f, np.array(isolator.GMS_K) / sum(isolator.GMS_K),
                               rtol=1e-12)
    assert lp.gms_alpha == list(isolator.GMS_ALPHA)
