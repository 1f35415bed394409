"""EMPS with the CLI defaults (issue 11, item 4): ``nanostage diagnose REC emps_nominal.yaml``
on the EMPS identification record, no options, comes out near the published rigid model.

Tolerances (the issue's, not tuned): mass within 10 %, Coulomb and viscous within 30 % of the
published IDIM-LS values (M 95.1 kg, Fc 20.4 N, Fv 203.5 N·s/m), the published viscous
asymmetry (Fv+ - Fv- = -73.7 N·s/m) within 30 %; the data-sheet force constant (gtau) left at
its stated value; the improved model's held-out closed-loop replay stable and at least 5x
better than the nominal's; printed values are the improved YAML's values.

The diagnosis is the suite's one diagnosis of the EMPS record (``conftest.emps_diagnosis``, shared
with ``test_realdata.py``): ``nanostage realdata``'s, which runs ``nanostage diagnose``'s defaults
(:func:`test_realdata_diagnoses_with_the_cli_defaults` keeps the two the same) and writes the
report and the improved preset the CLI writes. Skipped (naming where it looked) when the EMPS data
are not under the shared data folder.
"""
from __future__ import annotations

import argparse
import json

import pytest

from experiment_runner.apps.diagnosis import add_diagnose_arguments
from experiment_runner.apps.diagnosis import emps as R
from experiment_runner.apps.diagnosis.cli import diagnose_options
from experiment_runner.apps.diagnosis.options import Options
from stage_sim.config import load_preset


@pytest.fixture(scope="module")
def emps_cli(emps_diagnosis):
    out = emps_diagnosis["diagnosis"]
    return json.loads((out / "report.json").read_text()), load_preset(out / "improved_preset.yaml")


def test_realdata_diagnoses_with_the_cli_defaults():
    """``nanostage diagnose REC emps_nominal.yaml --no-plots`` runs ``Options(plots=False)``, the
    options of :func:`~experiment_runner.apps.diagnosis.emps.run_emps`'s diagnosis; the suite's one
    (``conftest.emps_diagnosis``) lifts only the wall-clock budget (``max_seconds=None``: an answer
    that must not depend on the machine's load)."""
    p = argparse.ArgumentParser()
    add_diagnose_arguments(p)
    assert diagnose_options(p.parse_args(["rec.mcap", str(R.EMPS_NOMINAL), "--no-plots"])) == Options(plots=False)


def _param(rep, effect, name):
    f = next((f for f in rep["found"] if f["effect"] == effect), None)
    assert f is not None, f"{effect} not found: {[f['effect'] for f in rep['found']]}"
    return next(p["value"] for p in f["params"] if p["name"] == name)


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_defaults_give_the_published_rigid_model(emps_cli):
    rep, p = emps_cli
    P, A = R.EMPS_PUBLISHED, R.EMPS_PUBLISHED_ASYM
    found = [f["effect"] for f in rep["found"]]
    assert "force_constant" not in found, found
    assert p.stage.drive.force_constant_ratio == 1.0
    fr = p.stage.table_friction
    assert p.stage.table.mass == pytest.approx(P["M"][0], rel=0.10)
    assert fr.f_c == pytest.approx(P["Fc"][0], rel=0.30)
    assert fr.viscous == pytest.approx(P["Fv"][0], rel=0.30)
    assert fr.viscous_difference == pytest.approx(A["Fv+"] - A["Fv-"], rel=0.30)


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_printed_values_are_the_yaml_values(emps_cli):
    rep, p = emps_cli
    assert _param(rep, "mass", "m_table") == p.stage.table.mass
    assert _param(rep, "viscous", "c") == p.stage.table_friction.viscous
    if "coulomb" in [f["effect"] for f in rep["found"]]:
        assert _param(rep, "coulomb", "F_C") == pytest.approx(p.stage.table_friction.f_c, rel=1e-12)


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_replay_leads_and_improves(emps_cli):
    rep, _ = emps_cli
    r = rep["replay"]
    assert r["stable"]["improved"]
    assert r["command_rms_N"]["improved"] < 0.2 * r["command_rms_N"]["nominal"]
    assert r["position_rms_m"]["improved"] < 0.2 * r["position_rms_m"]["nominal"]
    # the mass/force-constant pair is confounded on a rigid axis: reported, the stated constant kept
    mass = next(f for f in rep["found"] if f["effect"] == "mass")
    assert "force_constant" in mass["confounded_with"]
