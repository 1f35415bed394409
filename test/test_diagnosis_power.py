"""The power study, reduced (issue 11, item 5): ``nanostage diagnose --selftest --power
--cases 4 --json``: the JSON keys, the report and plot, no case failing to run, no effect
named on the negative control, rates computed from the cases. Named-first is not asserted
per case in the reduced study (four cases are no estimate of a rate); the full study's figures
are in the diagnosis README.

Cases of the full study that changes to the diagnosis fixed, each at its cause (54: the Coulomb
level named, not position-dependent friction; 50: an FI joint not taken for an asymmetry 28x
above the floor; 101: a friction slope the force observer cannot see; 12: a narrow valley; 123
and 10: no warnings; 93: the second start; 65: a parameter's sigma), the construction of a
pair's truth and the pair rate's count, and the estimator facade (fit / predict / score) on one
concealed force-gain case.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json

import numpy as np
import pytest

from experiment_runner.apps.diagnosis import add_diagnose_arguments, main_diagnose
from experiment_runner.apps.diagnosis.power.case_run import build_case
from experiment_runner.apps.diagnosis.power.cases import DEFAULT_CASES, PowerCase, make_cases

pytestmark = pytest.mark.slow


def test_cases_are_fixed_by_their_seed():
    a, b = make_cases(30), make_cases(30)
    assert [c.name for c in a] == [c.name for c in b] and [c.quantiles for c in a] == [c.quantiles for c in b]
    kinds = [c.kind for c in a]
    assert kinds.count("negative") == 9 and kinds.count("pair") == 3 and kinds.count("single") == 18


def test_reduced_power_study_json(tmp_path):
    p = argparse.ArgumentParser()
    add_diagnose_arguments(p)
    args = p.parse_args(["--selftest", "--power", "--cases", "4", "--workers", "1", "--json", "--out", str(tmp_path)])
    buf, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(err):
        assert main_diagnose(args) == 0
    s = json.loads(buf.getvalue())
    # progress on stderr by default: a line per case as it ends, counted
    lines = [ln for ln in err.getvalue().splitlines() if ln.startswith("[power")]
    assert [ln.split("] ")[1].split(" ")[1] for ln in lines] == ["1/4", "2/4", "3/4", "4/4"], err.getvalue()
    assert {"named_first_rate", "pair_rate"} <= set(s["power"])
    assert {"false_positive_rate", "cases", "negatives"} <= set(s)
    assert s["cases"] == 4 and s["negatives"] == 1 and s["errors"] == 0
    assert s["false_positive_rate"] == 0.0
    # every case carries what the rates are computed from, and the rates are those of the cases
    singles = [r for r in s["results"] if r["kind"] == "single"]
    assert len(singles) == 3 and all("replay_change" in r and "named_first" in r for r in singles)
    big = [r for r in singles if r["replay_change"]["truth"] >= 3]
    assert s["power"]["named_first_cases"] == len(big)
    if big:
        assert s["power"]["named_first_rate"] == sum(r["named_first"] for r in big) / len(big)
    assert (tmp_path / "report.md").read_text().startswith("# Diagnosis power study")
    assert (tmp_path / "power_detection.png").is_file()


def test_replay_refined_candidates_name_the_simpler_true_effect():
    """Power-study case 54: a +0.3 % Coulomb change (F_C 5.311 -> 5.327 N) concealed in one
    point-to-point trial of the rigid GMS stage at 1 kHz, 6x the run-to-run floor in the replay.
    At the force observer's values position-dependent friction (3 parameters) replayed better
    than the Coulomb level (whose observer fit is off where the replay is sensitive) and was
    adopted instead. With every candidate refined by the replay before candidates are compared,
    the Coulomb level reaches the floor, the friction slope adds nothing beyond it, and the
    simpler true effect is named first, its value within 2 % (the issue asks 20 %)."""
    from experiment_runner.apps.diagnosis.power.case_run import run_case
    # the case as dealt before lugre / regularised Coulomb / fractional delay joined the deal
    case = PowerCase(index=54, effects=("coulomb",), stage="rigid", friction="gms", rate=1000.0, noise=0.5,
                     record="p2p1", quantiles=(0.008776320631489587,), seed=176666255, trials=1,
                     profile={"kind": "point_to_point", "distance": -0.0017649611270172064, "dwell": 0.25})
    r = run_case(case)
    assert "error" not in r, r.get("traceback")
    assert r["replay_change"]["truth"] >= 3
    assert r["named"][0] == "coulomb" and r["named_first"], r["named"]
    chk = r["params"]["coulomb"]["checks"]["F_C"]
    assert chk["estimate"] == pytest.approx(chk["truth"], rel=0.02)


def test_estimator_fit_predict_score():
    from experiment_runner.apps.diagnosis.estimator import Diagnosis
    from experiment_runner.apps.diagnosis.model import ModelSpec
    case = PowerCase(index=0, effects=("force_constant",), stage="rigid", friction="dahl", rate=1e4, noise=1.0,
                     record="p2p", quantiles=(0.9,), seed=4242,
                     profile={"kind": "point_to_point", "distance": 1e-4, "dwell": 0.06}, trials=4)
    nominal, truth, expect, data, _ = build_case(case)
    est = Diagnosis(plots=False).fit(None, ModelSpec(nominal), data=data)
    assert est.effects_[0] == "force_constant"
    assert est.model_.preset.stage.drive.force_constant_ratio == pytest.approx(expect["force_constant"]["ratio"],
                                                                             rel=0.02)
    rp = est.predict(data)
    assert rp.ok and rp.u.shape[0] == data.shape[0] and np.all(np.isfinite(rp.y))
    assert est.score(data) > 0.9


def test_pair_truth_keeps_the_first_effects_friction_variation():
    """A pair's second effect may write a new friction law over the bearings (Stribeck: LuGre); the
    variation the first gave them (an asymmetry) stays in the truth. It was dropped: the
    asymmetry of case 94 changed the truth's replay by 0.0x its floor, yet counted as a missed
    effect of 30.7x."""
    case = PowerCase(index=94, effects=("friction_asymmetry", "stribeck"), stage="rigid", friction="dahl",
                     rate=10000.0, noise=0.5, record="sine", quantiles=(0.45226191396749166, 0.7486007398833707),
                     seed=633604648, trials=3,
                     profile={"kind": "sine_sweep", "frequencies": [8.379879891775918, 25.139639675327754],
                              "amplitude": 0.00010573973354992971, "periods": 3, "settle_periods": 1})
    _, truth, expect, _, _ = build_case(case)
    frs = [b.friction for b in truth.stage.bearings]
    assert all(fr.model == "lugre" for fr in frs)
    assert sum(fr.f_c_difference for fr in frs) == pytest.approx(expect["friction_asymmetry"]["dF_C"], rel=1e-12)
    assert expect["friction_asymmetry"]["dF_C"] != 0.0


def test_pair_rate_counts_what_each_effect_adds_given_the_other():
    """``pair_rate`` is over pairs in which each effect changes the replay by >= 3 floors once the
    other is in the model; an effect large alone but hidden by the other does not count there
    (it does in ``pair_rate_alone``)."""
    from experiment_runner.apps.diagnosis.power.study import summarize

    def pair(name, alone, given, both):
        return {"case": name, "kind": "pair", "effects": ["a", "b"], "named": [], "both_named": both,
                "replay_change": {"truth": 50.0, **alone}, "replay_change_given_other": given,
                "detected": {}, "params": {}, "truth_stable": True}
    res = [pair("p1", {"a": 30.0, "b": 40.0}, {"a": 0.5, "b": 40.0}, False),    # a hidden by b
           pair("p2", {"a": 30.0, "b": 40.0}, {"a": 25.0, "b": 35.0}, True),
           pair("p3", {"a": 2.0, "b": 40.0}, {"a": 4.0, "b": 35.0}, False)]      # a larger given b
    p = summarize(res)["power"]
    assert (p["pair_cases"], p["pair_rate"]) == (2, 0.5)
    assert (p["pair_cases_alone"], p["pair_rate_alone"]) == (2, 0.5)
    res[2]["both_named"] = True
    assert summarize(res)["power"]["pair_rate"] == 1.0


def _named_alone(case: PowerCase, param: str, min_change: float) -> dict:
    """Run single-effect ``case``: its effect changes the replay by >= ``min_change`` floors and is
    the one effect named; returns the check of its parameter ``param`` (truth, estimate)."""
    from experiment_runner.apps.diagnosis.power.case_run import run_case
    r = run_case(case)
    assert "error" not in r, r.get("traceback")
    assert r["replay_change"]["truth"] >= min_change
    assert r["named"] == list(case.effects), r["named"]
    return r["params"][case.effects[0]]["checks"][param]


def test_candidate_at_the_floor_is_not_confounded_with_one_far_above_it():
    """Power-study case 50: an isolator joint of 6e4 N/m concealed in four point-to-point trials of
    the rigid Dahl stage at 10 kHz (732x the floor). The joint model reaches the floor (D 2.04)
    while a friction asymmetry stays 28x above it (D 1574); both were judged against recordings
    of the *nominal*, whose scatter grows with the distance of both replays from it, so the two
    looked equivalent and the simpler asymmetry was adopted. Judged against recordings of the
    better model, the joint is named alone, its stiffness within 2 %."""
    case = PowerCase(index=50, effects=("fi_compliance",), stage="rigid", friction="dahl", rate=10000.0, noise=0.5,
                     record="p2p", quantiles=(0.8412552697291148,), seed=150244432, trials=4,
                     profile={"kind": "point_to_point", "distance": -8.575679166411267e-06, "dwell": 0.06})
    chk = _named_alone(case, "k_fi", min_change=3)
    assert chk["estimate"] == pytest.approx(chk["truth"], rel=0.02)


def test_effect_the_observer_cannot_see_is_found_by_the_replay_alone():
    """A friction slope along the travel (g_1 -57.5 N/m) concealed in three 0.25 s circle trials
    of the rigid Dahl stage at 1 kHz: 153x the floor in the replay, while the 40 Hz force
    observer is at its own noise (J 1.2) and fits it as noise (g_1 +1669 N/m, worse than no
    change). Such a candidate is refined by the replay from its own start (a coarse grid per
    coordinate), and a later candidate is credited only with what it adds to the re-fit of the
    adopted slope (at 6e-8 N, a "ripple" had been adopted for what that re-fit did). Named
    alone, the slope within 5 % (the issue asks 20 %)."""
    case = PowerCase(index=101, effects=("position_friction",), stage="rigid", friction="dahl", rate=1000.0,
                     noise=1.0, record="circle", quantiles=(0.4900249910266407,), seed=1382235942, trials=3,
                     profile={"kind": "circle", "radius": 0.000734506268586675, "speed": 0.018460155979260397,
                              "cycles": 1.0})
    chk = _named_alone(case, "g_1", min_change=100)
    assert chk["estimate"] == pytest.approx(chk["truth"], rel=0.05)


def test_a_parameter_standing_in_for_a_narrow_valley_goes_back_to_no_change():
    """Power-study case 12: a friction asymmetry (F+ - F- = -0.431 N) in four point-to-point
    trials that all move the same way. The replay pins the asymmetry to 1 %, inside the
    refinement's finite-difference step: the solver stopped 1.3 % off with a viscous asymmetry of
    20.6 N s/m standing in (replay D 4.9, Coulomb 2.7), and the simpler Coulomb level was named
    alone. From the solution with the viscous part back at zero the refinement reaches the
    truth; on a record that only slides one way the asymmetry, a Coulomb level and an offset are
    the same physics, reported as one confounded set."""
    from experiment_runner.apps.diagnosis.power.case_run import run_case
    case = PowerCase(index=12, effects=("friction_asymmetry",), stage="rigid", friction="coulomb", rate=10000.0,
                     noise=0.5, record="p2p", quantiles=(0.4546660325742645,), seed=2016181085, trials=4,
                     profile={"kind": "point_to_point", "distance": -3.327984788133078e-06, "dwell": 0.06})
    r = run_case(case)
    assert "error" not in r, r.get("traceback")
    assert r["named_first"], r["named"]
    chk = r["params"]["friction_asymmetry"]["checks"]
    assert chk["dF_C"]["estimate"] == pytest.approx(chk["dF_C"]["truth"], rel=0.02)
    assert abs(chk["dc"]["estimate"]) < 1.0


def test_a_stage_held_by_friction_gets_its_plots_and_no_warnings(tmp_path):
    """Power-study case 123, a negative control: a 2.5 um move of the 1 kHz Coulomb stage, which
    friction holds (every residual exactly zero). Its residual spectrum cannot be drawn on log
    axes: the plot says so instead of a Matplotlib warning, and nothing else warns."""
    from experiment_runner.apps.diagnosis.power.case_run import run_case
    case = PowerCase(index=123, effects=(), stage="rigid", friction="coulomb", rate=1000.0, noise=0.5,
                     record="p2p1", quantiles=(), seed=678996794, trials=1,
                     profile={"kind": "point_to_point", "distance": -2.4751129462579884e-06, "dwell": 0.25})
    r = run_case(case, tmp_path)
    assert "error" not in r, r.get("traceback")
    assert not r.get("warnings"), r["warnings"]
    assert r["named"] == []
    assert (tmp_path / case.name / "residual_spectrum.png").stat().st_size > 1000
    assert "plots failed" not in (tmp_path / case.name / "report.md").read_text()


def test_a_diverged_candidate_costs_its_bad_point_without_a_numpy_warning():
    """Power-study case 10 (a ripple on the isolated 1 kHz Dahl stage): some parameter sets of a
    candidate fitted beside it make the force observer diverge. Their cost is the bad-point
    value; the NaN residual is not whitened first (NumPy warned about NaN in its FFT). The case
    names the ripple or nothing: its score test merges the held-out blocks until their noise is
    independent (3 blocks of 13 here), and with so few the ripple (2.7x its floor) may stay within
    the data's own noise -- reported as a residual located, not explained; never a wrong name."""
    from experiment_runner.apps.diagnosis.power.case_run import run_case
    case = PowerCase(index=10, effects=("ripple",), stage="isolated", friction="dahl", rate=1000.0, noise=2.0,
                     record="p2p", quantiles=(0.5169795335958682,), seed=1345403502, trials=4,
                     profile={"kind": "point_to_point", "distance": 2.106864430632203e-06, "dwell": 0.25})
    r = run_case(case)
    assert "error" not in r, r.get("traceback")
    assert not r.get("warnings"), r["warnings"]
    assert r["named"] in (["ripple"], []), r["named"]


def test_second_start_finds_the_pair_a_stand_in_had_absorbed(tmp_path):
    """Power-study pair 93: an FI joint (k_fi 1.24e5 N/m) behind the Coulomb bearings of the
    1 kHz rigid stage, and a Stribeck curve. Twelve Maxwell-slip blocks (a spring and a slider
    each) replay the joint and the curve together better than the joint alone, so forward
    selection took the GMS first and a mass change next, and ended 3.7x above its floor
    (replay D 27.8). The path from step 1's runner-up, the joint, adds the Stribeck curve and
    reaches the floor (D 2.03): it is kept, and the report says why. What is asserted is the
    right answer and, where a second start gave it, the report's reason for it; not which stand-in
    the forward selection took (a known weakness, not a behaviour to keep)."""
    from experiment_runner.apps.diagnosis.model import ModelSpec
    from experiment_runner.apps.diagnosis.options import Options
    from experiment_runner.apps.diagnosis.pipeline import diagnose
    from experiment_runner.apps.diagnosis.power.case_run import judge_case
    case = PowerCase(index=93, effects=("fi_compliance", "stribeck"), stage="rigid", friction="coulomb",
                     rate=1000.0, noise=2.0, record="sine", quantiles=(0.7361101347540763, 0.6788227103221747),
                     seed=444203855, trials=3,
                     profile={"kind": "sine_sweep", "frequencies": [3.6392302889418167, 10.917690866825449],
                              "amplitude": 0.00017801475431217456, "periods": 3, "settle_periods": 1})
    nominal, _, expect, data, _ = build_case(case)
    diagnose(None, ModelSpec(nominal), out=tmp_path, data=data, options=Options(plots=False, n_jobs=1,
                                                                               max_seconds=None))
    rep = json.loads((tmp_path / "report.json").read_text())
    r = judge_case(case, rep, expect, {})
    assert r["named"] == ["fi_compliance", "stribeck"] and r["both_named"]
    chk = r["params"]["fi_compliance"]["checks"]
    assert chk["k_fi"]["estimate"] == pytest.approx(chk["k_fi"]["truth"], rel=0.05)
    assert rep["selection"]["steps"][0]["accepted"] == "fi_compliance"
    ss = rep["selection"].get("second_start") or {}
    if ss.get("chosen"):          # the forward path ended above its floor: the report says which path, and why
        assert ss["first"] == "fi_compliance" and ss["greedy_effects"] != r["named"]
        assert ss["replay_D"] < 0.2 * ss["replay_D_greedy"]
        assert "Second start" in (tmp_path / "report.md").read_text()


def test_a_joint_behind_stated_bearings_is_named_with_their_mass_held(tmp_path):
    """Power-study case 029: an FI joint (k_fi 1.28e7 N/m) behind the Coulomb bearings of the 1 kHz
    rigid stage, whose nominal states the bearings' mass. With the mass fitted too, the joint's
    frequency fixed only k_fi / m_red, the observer's fit ran the mass to its bound and the
    refinement, started elsewhere, ended at 2.3e6 N/m: nothing named. The stated mass is held: the
    joint is named first with k_fi within 5 %. Its replay is then within its run-to-run floor in
    size (RMS ratio <= 1) though not in distribution, and no second walk is taken (it cost 2.4x the
    greedy walk and ended at D 35 against 1.5); the report says why."""
    from experiment_runner.apps.diagnosis.model import ModelSpec
    from experiment_runner.apps.diagnosis.options import Options
    from experiment_runner.apps.diagnosis.pipeline import diagnose
    from experiment_runner.apps.diagnosis.power.case_run import judge_case
    case = make_cases(DEFAULT_CASES)[29]
    assert case.effects == ("fi_compliance",) and case.rate == 1000.0
    nominal, _, expect, data, _ = build_case(case)
    diagnose(None, ModelSpec(nominal), out=tmp_path, data=data, options=Options(plots=False, n_jobs=1,
                                                                               max_seconds=None))
    rep = json.loads((tmp_path / "report.json").read_text())
    r = judge_case(case, rep, expect, {})
    assert r["named"] == ["fi_compliance"], r["named"]
    chk = r["params"]["fi_compliance"]["checks"]
    assert chk["k_fi"]["estimate"] == pytest.approx(chk["k_fi"]["truth"], rel=0.05)
    assert [p["name"] for p in rep["found"][0]["params"]] == ["k_fi", "zeta_fi"]
    ss = rep["selection"]["second_start"]
    assert rep["replay"]["floor_ratio"]["improved"] <= 1.0 and ss["chosen"] is False and "skipped" in ss
    assert "No second start" in (tmp_path / "report.md").read_text()


def test_a_parameters_sigma_is_its_spread_over_the_models_own_recordings():
    """Power-study case 65: a +0.4 % table mass on the isolated 1 kHz GMS stage, one 0.34 s
    point-to-point trial. The block sandwich of the refinement's Jacobian gave sigma 1.2e-4 kg,
    and the estimate was 1.5e-3 kg off (z -10). The reported sigma now holds the linearised
    spread over the final model's simulated recordings (``sigma_boot``). That spread must be the
    spread of the estimate itself: the mass refitted, by the same replay error, to each of those
    recordings."""
    import dataclasses

    from scipy.optimize import minimize_scalar

    from experiment_runner.apps.diagnosis.joint import spec_with
    from experiment_runner.apps.diagnosis.model import ModelSpec
    from experiment_runner.apps.diagnosis.options import Options
    from experiment_runner.apps.diagnosis.pipeline import diagnose_stages
    case = PowerCase(index=65, effects=("mass",), stage="isolated", friction="gms", rate=1000.0, noise=1.0,
                     record="p2p1", quantiles=(0.017266704834976786,), seed=1650044624, trials=1,
                     profile={"kind": "point_to_point", "distance": 0.0011869291091236476, "dwell": 0.25})
    nominal, _, expect, data, _ = build_case(case)
    rep, run = diagnose_stages(None, ModelSpec(nominal), options=Options(plots=False, n_jobs=1), data=data)
    assert [f["effect"] for f in rep["found"]] == ["mass"]
    p = rep["found"][0]["params"][0]
    assert p["name"] == "m_table" and p["sigma"] >= p["sigma_boot"] > 0
    fj, f = run.prediction.fit_judge, run.path.selected[0]
    fl = fj.floor(run.path.current)

    def cost(m, k):
        rp = fj.replay(spec_with([dataclasses.replace(f, theta=np.array([m]))], run.problem.base))
        e = np.concatenate([e[fj.mask] for e in fj._errors(fl.u[k], fl.y[k], rp, fl)])
        return float(e @ e)

    s, m0 = p["sigma_boot"], p["value"]
    refits = [minimize_scalar(cost, args=(k,), bounds=(m0 - 15 * s, m0 + 15 * s), method="bounded",
                              options={"xatol": 0.02 * s}).x for k in range(fj.K)]
    assert np.sqrt(np.mean((np.array(refits) - m0) ** 2)) == pytest.approx(s, rel=0.3)
