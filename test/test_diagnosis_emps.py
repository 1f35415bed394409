"""EMPS with the CLI defaults (issue 11, item 4): ``nanostage diagnose REC emps_nominal.yaml``
on the EMPS identification record, no options, comes out near the published rigid model.

Tolerances (the issue's, not tuned): mass within 10 %, Coulomb and viscous within 30 % of the
published IDIM-LS values (M 95.1 kg, Fc 20.4 N, Fv 203.5 N·s/m), the published viscous
asymmetry (Fv+ - Fv- = -73.7 N·s/m) within 30 %; the data-sheet force constant (gtau) left at
its stated value; the improved model's held-out closed-loop replay stable and at least 5x
better than the nominal's; printed values are the improved YAML's values.

Skipped (with the reason) when the EMPS data are not under the shared data folder. One
diagnosis of a 24.8 s record (~1 min): slow.
"""
from __future__ import annotations

import argparse
import json

import pytest

from experiment_runner.diagnosis import add_diagnose_arguments, main_diagnose
from experiment_runner.diagnosis import realdata as R
from experiment_runner.diagnosis.datasets import DataMissing, data_root
from experiment_runner.tabular import convert_emps
from stage_sim.config import load_preset

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def emps_cli(tmp_path_factory):
    try:
        mat = data_root() / "emps" / "DATA_EMPS.mat"
    except DataMissing as err:
        pytest.skip(f"EMPS data missing: {err}")
    if not mat.is_file():
        pytest.skip(f"EMPS data missing: {mat} is not a file")
    d = tmp_path_factory.mktemp("emps_cli")
    rec = convert_emps(mat, d / "rec")
    p = argparse.ArgumentParser()
    add_diagnose_arguments(p)
    out = d / "diagnosis"
    # the CLI's defaults except the wall-clock budget: the answer must not depend on the machine's load
    # (a loaded CI machine); how long it takes is the bench's figure (diagnose_seconds_emps)
    args = p.parse_args([str(rec), str(R.EMPS_NOMINAL), "--out", str(out), "--json", "--no-plots",
                         "--max-seconds", "3600"])
    import contextlib
    import io
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main_diagnose(args) == 0
    return json.loads(buf.getvalue()), load_preset(out / "improved_preset.yaml")


def _param(rep, effect, name):
    f = next((f for f in rep["found"] if f["effect"] == effect), None)
    assert f is not None, f"{effect} not found: {[f['effect'] for f in rep['found']]}"
    return next(p["value"] for p in f["params"] if p["name"] == name)


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


def test_emps_printed_values_are_the_yaml_values(emps_cli):
    rep, p = emps_cli
    assert _param(rep, "mass", "m_table") == p.stage.table.mass
    assert _param(rep, "viscous", "c") == p.stage.table_friction.viscous
    if "coulomb" in [f["effect"] for f in rep["found"]]:
        assert _param(rep, "coulomb", "F_C") == pytest.approx(p.stage.table_friction.f_c, rel=1e-12)


def test_emps_replay_leads_and_improves(emps_cli):
    rep, _ = emps_cli
    r = rep["replay"]
    assert r["stable"]["improved"]
    assert r["command_rms_N"]["improved"] < 0.2 * r["command_rms_N"]["nominal"]
    assert r["position_rms_m"]["improved"] < 0.2 * r["position_rms_m"]["nominal"]
    # the mass/force-constant pair is confounded on a rigid axis: reported, the stated constant kept
    mass = next(f for f in rep["found"] if f["effect"] == "mass")
    assert "force_constant" in mass["confounded_with"]
