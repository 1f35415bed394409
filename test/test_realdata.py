"""Real data (issue 5, item 7): the diagnosis recovers what the data sets' READMEs say is there.

Reads the real files of ``../shared/data`` (``conftest.shared_data`` / ``shared_file``: resolved by
:func:`experiment_runner.apps.diagnosis.datasets.data_root`); where a data set is missing its tests are
skipped naming the places looked in, and the core suite deselects them (``-m "not realdata"``).

Tolerances (stated here, not tuned): EMPS, against the published IDIM-LS model
(shared/data/emps/README.md): mass within 2 %, Coulomb and viscous within 10 %, the offset
(symmetric-model equivalent) with the published sign and within 15 %, the viscous asymmetry
``Fv- - Fv+`` within 25 %. Tribometer (README): a pre-sliding model beats plain Coulomb on
held-out strokes by more than 3x in RMS; its transition lengths within 25 % of the README's
approximate values (sign change ~0.06 mm, 80 % of the new level ~0.10 mm).

The EMPS record is diagnosed once for the whole suite (``conftest.emps_diagnosis``, shared with
``test_diagnosis_emps.py``): the whole effect library from the shipped nominal, and the
published-structure fits.
"""
from __future__ import annotations

import numpy as np
import pytest

from experiment_runner.apps.diagnosis import emps as R
from experiment_runner.apps.diagnosis.datasets import DataMissing, data_root
from experiment_runner.apps.diagnosis.tribometer import run_tribometer
from experiment_runner.core.tabular import convert_emps


@pytest.fixture(scope="module")
def emps(shared_file):
    return R.load_emps(shared_file("emps/DATA_EMPS.mat"))


@pytest.fixture(scope="module")
def emps_run(emps_diagnosis):
    return emps_diagnosis["summary"]


@pytest.mark.realdata
@pytest.mark.slow
def test_convert_emps_is_the_contract_mapping(emps, emps_diagnosis):
    """The suite's EMPS recording (``convert emps``, as the diagnosis read it)."""
    from experiment_runner.core.recording import read_recording
    from stage_control.cascaded import CascadedPP, cascaded_command
    rec = read_recording(emps_diagnosis["recording"])
    assert len(rec) == 24841
    np.testing.assert_array_equal(rec.u, emps.gtau * emps.vir)
    np.testing.assert_array_equal(rec.y, emps.qm)
    np.testing.assert_array_equal(rec.x_ref, emps.qg)
    assert np.allclose(np.diff(rec.t), 1e-3, atol=1e-9)
    # the README's control law, evaluated on the recording, reproduces the recorded drive input
    vir = cascaded_command(CascadedPP(emps.kp, emps.kv, emps.gtau), rec.x_ref, rec.y)
    assert np.linalg.norm(vir - emps.vir) / np.linalg.norm(emps.vir) < 0.01


def test_convert_refuses_a_bad_file(tmp_path):
    bad = tmp_path / "x.mat"
    bad.write_bytes(b"not a mat file")
    with pytest.raises(ValueError, match="x.mat"):
        convert_emps(bad, tmp_path / "out")
    with pytest.raises(DataMissing, match="nothing.mat"):
        R.load_emps(tmp_path / "nothing.mat")


@pytest.mark.realdata
@pytest.mark.slow
def test_cascaded_loop_on_the_published_model_reproduces_the_record(emps):
    from stage_control.cascaded import CascadedPP, RigidAxis, simulate_rigid
    ctrl = CascadedPP(emps.kp, emps.kv, emps.gtau)
    P = R.EMPS_PUBLISHED
    pub = RigidAxis(P["M"][0], P["Fc"][0], P["Fc"][0], P["Fv"][0], P["Fv"][0], P["offset"][0], resolution=5e-8)
    err = {}
    for name, ax in (("published", pub), ("mass only", RigidAxis(P["M"][0], resolution=5e-8))):
        s = simulate_rigid(ctrl, ax, emps.qg, q0=emps.qm[0])
        err[name] = np.linalg.norm(s["tau"] - emps.force) / np.linalg.norm(emps.force)
    assert err["published"] < 0.08          # README: 5.8 % with the benchmark's own simulation
    assert err["mass only"] > 5 * err["published"]


@pytest.mark.realdata
def test_idim_ls_recipe_matches_the_published_values(emps):
    v = R.idim_ls(emps)["values"]
    for k in ("M", "Fv", "Fc", "offset"):
        assert v[k] == pytest.approx(R.EMPS_PUBLISHED[k][0], rel=0.03), k


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_diagnosis_names_the_published_physics(emps_run):
    """From the whole library (frictionless 70 kg nominal): the effects the README says are there."""
    run = emps_run["runs"]["diagnosis"]
    found = set(run["found"])
    q = run["quantities"]
    P = R.EMPS_PUBLISHED
    assert {"mass", "viscous", "friction_asymmetry"} <= found, found
    assert found & {"coulomb", "position_friction"}, found      # a Coulomb level (the nominal has none)
    assert q["M"]["value"] == pytest.approx(P["M"][0], rel=0.02)
    assert q["Fv"]["value"] == pytest.approx(P["Fv"][0], rel=0.10)
    assert q["offset_equivalent"]["value"] == pytest.approx(P["offset"][0], rel=0.15)
    # the README stresses asymmetric friction: found, with the published direction and size
    A = R.EMPS_PUBLISHED_ASYM
    assert q["Fv-"]["value"] - q["Fv+"]["value"] == pytest.approx(A["Fv-"] - A["Fv+"], rel=0.25)
    assert all(q[k]["sigma"] > 0 for k in ("M", "Fc", "Fv", "Fv-"))


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_published_structure_fit_recovers_the_published_values(emps_run):
    """Like for like: restricted to the published rigid-body structures, the fitted values
    match the published IDIM-LS estimates (the whole-library model splits the friction force
    over more terms, e.g. a trajectory-synchronous periodic force, so its Coulomb level is not
    the IDIM one)."""
    P, A = R.EMPS_PUBLISHED, R.EMPS_PUBLISHED_ASYM
    q = emps_run["runs"]["published_structure"]["quantities"]
    for k in ("M", "Fc", "Fv", "offset"):
        assert q[k]["value"] == pytest.approx(P[k][0], rel=0.10), k
        assert q[k]["sigma"] > 0, k
    qa = emps_run["runs"]["published_structure_asymmetric"]["quantities"]
    for k in ("Fv+", "Fv-"):
        assert qa[k]["value"] == pytest.approx(A[k], rel=0.10), k
    assert qa["M"]["value"] == pytest.approx(A["M"], rel=0.02)


@pytest.mark.realdata
@pytest.mark.slow
def test_emps_diagnosed_model_predicts_held_out_data(emps_run):
    val = emps_run["runs"]["diagnosis"]["validation"]["force_residual_rms_N"]
    assert val["improved"] < 0.1 * val["nominal"]
    cl = emps_run["closed_loop_replay"]
    assert cl["diagnosis"]["force_rel_error_held"] < 0.08
    assert cl["diagnosis"]["force_rel_error_held"] < 0.2 * cl["nominal"]["force_rel_error_held"]
    assert emps_run["conversion"]["max_abs_command_diff_N"] == 0.0


@pytest.mark.realdata
@pytest.mark.slow
def test_tribometer_pre_sliding_beats_coulomb_on_held_out_strokes(shared_data, tmp_path):
    t = run_tribometer(shared_data, tmp_path, plots=False)
    m = t["models"]
    assert t["reversals"] >= 90
    assert t["mu_moving_median"] == pytest.approx(0.43, abs=0.02)        # README's statistic
    assert t["winner"] in ("dahl", "gms", "lugre")
    for k in ("dahl", "gms", "lugre"):
        assert m[k]["rms_held_N"] < m["coulomb"]["rms_held_N"] / 3, k
    w = m[t["winner"]]["transition_held"]
    assert w["x_zero_m"] == pytest.approx(0.06e-3, rel=0.25)
    assert w["x_80_m"] == pytest.approx(0.10e-3, rel=0.25)
    # the plain Coulomb model has no transition at all (it flips at the reversal)
    assert m["coulomb"]["transition_held"]["x_80_m"] < 0.01e-3


def test_data_root_names_where_it_looked(tmp_path):
    with pytest.raises(DataMissing, match=str(tmp_path)):
        data_root(tmp_path)


@pytest.mark.realdata
@pytest.mark.slow
def test_convert_command_line(emps, tmp_path, capsys):
    from experiment_runner.apps.cli import main
    assert main(["convert", "emps", str(emps.path), "--out", str(tmp_path / "rec")]) == 0
    assert capsys.readouterr().out.startswith(f"{tmp_path / 'rec' / 'rec.mcap'}: 24841 samples at 1000 Hz")
    # a bad input is one line on stderr and exit 2, nothing written
    assert main(["convert", "emps", str(tmp_path / "missing.mat"), "--out", str(tmp_path / "r2")]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing.mat" in err and len(err.splitlines()) == 1 and not (tmp_path / "r2").exists()
