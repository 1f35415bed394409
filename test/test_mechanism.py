"""Settling mechanism analysis (experiment_runner.apps.campaigns.mechanism): turning points, the friction-free twin,
and the seed's mechanism on a small campaign."""
from __future__ import annotations

import numpy as np
import pytest

from experiment_runner.apps.campaigns import mechanism as mech
from experiment_runner.apps.campaigns.frequency_response import frf_lines
from experiment_runner.apps.campaigns.runner import run_campaign
from experiment_runner.apps.campaigns.spec import Campaign, case_preset, conditions, load_campaign
from stage_sim.config import load_preset


def test_turning_points_ignore_excursions_below_the_hysteresis():
    t = np.linspace(0, 1, 2001)
    x = np.sin(2 * np.pi * 2 * t) + 0.01 * np.sin(2 * np.pi * 200 * t)     # 2 Hz swing + small ripple
    k = mech.turning_points(x, 0.1)
    assert len(k) == 4                                                  # maxima and minima of the swing
    np.testing.assert_allclose(t[k], [0.125, 0.375, 0.625, 0.875], atol=0.01)
    assert mech.turning_points(x, 3.0) == []                            # swing smaller than the hysteresis
    assert mech.turning_points(np.arange(10.0), 0.5) == []               # monotonic


def test_frictionless_twin_is_the_rigid_stage_without_friction():
    for name in ("fi_stage_gms", "sai_stage", "van_stage"):
        p = load_preset(name)
        tw = mech.frictionless_twin(p)
        assert all(b.joint is None and b.friction.model == "coulomb" and b.friction.f_c == 0
                   for b in tw.stage.bearings)
        assert tw.stage.sai is None and tw.sai_manager is None and tw.dither is None
        assert tw.controller == p.controller                            # the same PID
        assert sum(b.mass for b in tw.stage.bearings) == sum(b.mass for b in p.stage.bearings)


def test_premotion_range_of_the_table_4_4_bearing():
    # largest Table 4.4 block per bearing: alpha_10 F_C / k_10 = 0.3733 * 2.655 / 22900; x2 after a reversal
    assert mech.premotion_range(load_preset("fi_stage_nofi_gms")) == pytest.approx(2 * 0.3733 * 2.655 / 22900)
    assert mech.premotion_range(load_preset("fi_stage_nofi")) == pytest.approx(6 * 2.655 / 1.095e6)


def test_no_fi_5mm_is_friction_limited_and_fi_is_not():
    """Table 4.2 stage, designed PID, one trial: the No FI table reverses after the reference stops and
    settles in the pre-motion regime at least twice as slowly as its friction-free twin; the FI case
    with the same PID is within 35% of the same twin."""
    camp = load_campaign("table_4_2")
    cond = next(c for c in conditions(camp) if c.step == 5e-3)
    out = {}
    for case in camp.cases:
        out[case.name] = mech.analyse(camp, case, cond, case_preset(camp, case, None, cond), 0)
    nofi, fi = out["nofi"], out["fi"]
    assert nofi["friction_limited"] and nofi["settled_in_premotion"]
    assert nofi["settling_time_s"] > 2.0 * nofi["twin_settling_time_s"]
    assert any(r["t_s"] >= 0 for r in nofi["reversals"])
    assert abs(nofi["excursion_m"]) > 1e-6                              # pushed back micrometres
    assert not fi["friction_limited"] and fi["settling_time_s"] < 1.35 * fi["twin_settling_time_s"]
    assert "friction-limited" in mech.summary(nofi)
    tr = nofi["trace"]
    assert tr["t"].shape == tr["e"].shape == tr["e_twin"].shape and tr["t"][0] < 0 < tr["t"][-1]


@pytest.mark.slow
def test_frf_lines_put_bandwidth_and_margins_next_to_the_settling(tmp_path):
    """The main job's Fig. 4.6 table: one row per amplitude, the No FI pre-motion bandwidth collapse, and
    the FI's gain-margin loss explained by the 2 kg -> 1.14 kg rigid-body loop gain (4.8 dB)."""
    d = load_campaign("frf_fi").model_dump(by_alias=True)
    d["test"].update(amplitudes=[0.11, 16.5], f_min=2.0, points_per_decade=8, simulate_closed_loop=False)
    keep = lambda x: all(a in (None, 0.11, 16.5) for a in (x.get("amplitude"), x.get("versus_amplitude")))
    d["seed"]["findings"] = [f for f in d["seed"]["findings"] if keep(f)]
    d["seed"]["values"] = [v for v in d["seed"]["values"] if keep(v)]
    frf = run_campaign(Campaign.model_validate(d), tmp_path, progress=False, plots=False)
    lines = frf_lines(frf)
    rows = [x for x in lines if x.startswith("| 0.11 N") or x.startswith("| 16.5 N")]
    assert len(rows) == 2
    bw_pre = frf.runs[("nofi", frf.conditions[0].key)].values["bandwidth_hz"]
    bw_gross = frf.runs[("nofi", frf.conditions[1].key)].values["bandwidth_hz"]
    assert bw_pre < 10.0 < 150.0 < bw_gross                              # Sec. 4.3: 200 Hz -> below 10 Hz
    text = "\n".join(lines)
    assert "4.8 dB more loop gain" in text and "Table C.1" in text
