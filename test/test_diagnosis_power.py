"""The power study, reduced (issue 11, item 5): ``nanostage diagnose --selftest --power
--cases 4 --json``: the JSON keys, the report and plot, no case failing to run, no effect
named on the negative control, rates computed from the cases. Named-first is not asserted
per case in the reduced study: the study's goal (>= 95 %) is not met (85.4 % in the full
study, see the diagnosis README).

One case of the full study that the replay refinement of the candidates fixed (case 54: the
Coulomb level named, not position-dependent friction), and the estimator facade (fit /
predict / score) on one concealed force-gain case.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json

import numpy as np
import pytest

from experiment_runner.diagnosis import add_diagnose_arguments, main_diagnose
from experiment_runner.diagnosis.power import PowerCase, build_case, make_cases

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
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main_diagnose(args) == 0
    s = json.loads(buf.getvalue())
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
    from experiment_runner.diagnosis.power import run_case
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
    from experiment_runner.diagnosis.estimator import Diagnosis
    from experiment_runner.diagnosis.model import ModelSpec
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
