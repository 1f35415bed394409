"""Every shipped campaign file validates and runs at a reduced scale, and the simulation takes
the direction of every seed finding it does not explain away: findings without a ``note``
must have the seed's direction; a finding with a ``note`` that disagrees shows the note in
report.md (a known disagreement is a finding of the report, not an assertion of this test). Also: ``calibration: {from: ...}`` (fit, cache, reuse), per-case sweep targets
with ``series_scale``, seed percentages (``change``) and ``sweep_spread`` findings.

Reduced scale: 2 trials (5 for table_6_3, whose weakest reproduced effects are 1.5-2.3% at 20 trials;
1 for the feedforward sweeps, whose effects are tens of percent and whose runs are many),
circle campaigns cut to the conditions the seed's numbers and findings name, sweeps to the values
they name (plus the smallest, -50%, for spread findings), cases to those they name. The point-to-point dwell is kept: the RMS
in-position error is measured over it, and a 0.4 s dwell already flips table_4_2's 5 um RMS
finding (+9% at 1 s, -1% at 0.4 s, 2 trials). Calibrated values are those
of the full runs (as in test_campaign.py), so nothing is fitted except in the ``from`` test.
"""
from __future__ import annotations

import importlib
import math
import pkgutil

import pytest
import yaml

from experiment_runner.apps.campaigns.calibration import calibration_fingerprint
from experiment_runner.apps.campaigns import schema
from experiment_runner.apps.campaigns.kinds import KINDS, kind_of, schemas
from experiment_runner.apps.campaigns.registry import METRICS
from experiment_runner.apps.campaigns.runner import run_campaign
from experiment_runner.apps.campaigns.spec import (CAMPAIGN_DIR, Calibration, CalibrationFrom, Campaign, cal_parameters,
                                              calibration_source, case_preset, conditions, list_campaigns,
                                              load_campaign)
from stage_sim.config import ConfigError

# Calibrated values of the full runs (see test_campaign.py), by the campaign that fits them.
CAL = {"table_4_2": {"drive_noise_current_rms": 9.78e-4},
       "table_4_2_dahl": {"drive_noise_current_rms": 9.78e-4},
       "table_4_2_aging": {"drive_noise_current_rms": 9.78e-4},
       "table_5_2": {"drive_noise_current_rms": 1.55e-3},
       "table_3_3": {"drive_noise_current_rms": 9.562e-4}}
TRIALS = {"table_6_3": 5, "ff_4_16": 1, "ff_6_5": 1}
RUN_KINDS = ("point_to_point", "circle")      # frequency_response campaigns: test_frf_campaign.py


def _cal(camp):
    """Calibration values for a campaign: its own fit or that of ``calibration.from``."""
    if camp.calibration is None:
        return None
    src = camp.calibration.from_ if isinstance(camp.calibration, CalibrationFrom) else camp.name
    return {"values": CAL[src], "parameters": [], "trials": 0}


def _reduced(camp: Campaign) -> Campaign:
    """The campaign at test scale: fewer trials, only the named conditions and cases."""
    d = camp.model_dump(by_alias=True)
    d["trials"] = TRIALS.get(camp.name, 2)
    if isinstance(camp.calibration, Calibration):
        d["calibration"]["trials"] = min(d["calibration"]["trials"], d["trials"])
    named = list(camp.seed.values) + list(camp.seed.findings)
    if camp.test.kind == "circle":
        pairs = sorted({(x.radius, x.speed) for x in named})
        d["test"].update(radii=None, speeds=None,
                         circles=[{"radius": r, "speeds": [v for rr, v in pairs if rr == r]}
                                  for r in sorted({r for r, _ in pairs})])
    used = {camp.baseline} | {w for x in named for w in (x.case, getattr(x, "versus", None),
                                                         getattr(x, "relative_to", None)) if w}
    d["cases"] = [c for c in d["cases"] if c["name"] in used]
    if camp.sweep is not None:
        if d["sweep"]["apply"]:
            d["sweep"]["apply"] = [t for t in d["sweep"]["apply"] if set(t["cases"]) & used] or None
            for t in d["sweep"]["apply"] or []:
                t["cases"] = [c for c in t["cases"] if c in used]
        keep = {x.sweep for x in named if x.sweep is not None}
        if any(getattr(x, "over", "mean") == "sweep_spread" for x in named):
            keep.add(min(camp.sweep.values))     # a spread needs two values: the largest error (-50%)
        d["sweep"]["values"] = [v for v in camp.sweep.values if v in keep]
    return Campaign.model_validate(d)


def _same_direction(f) -> bool:
    if f["direction"] == "similar":
        return f["agrees"]
    return f["sim_change"] is not None and (f["sim_change"] < 0) == (f["direction"] == "lower")


# --------------------------------------------------------------------------- every file
@pytest.mark.parametrize("name", list_campaigns())
def test_file_validates_with_sourced_seed_numbers(name):
    c = load_campaign(name)
    assert c.seed.source and c.seed.findings
    for f in c.seed.findings:                    # a stated direction, and a reason where it fails
        assert f.claim and (f.note == "" or len(f.note) > 80), f.id
    if isinstance(c.calibration, CalibrationFrom):
        src = calibration_source(c)
        assert isinstance(src.calibration, Calibration)
        assert {p.name for p in cal_parameters(c)} == set(CAL[src.name])


@pytest.mark.parametrize("name", [n for n in list_campaigns()
                                  if load_campaign(n, check_presets=False).test.kind in RUN_KINDS])
@pytest.mark.slow
def test_file_runs_and_takes_the_seed_directions(name, tmp_path):
    camp = _reduced(load_campaign(name))
    cr = run_campaign(camp, tmp_path, calibration=_cal(camp), progress=False, plots=False, mcap=False)
    assert len(cr.findings) == len(camp.seed.findings)
    md = (tmp_path / "report.md").read_text()
    notes = {f.id: f.note for f in camp.seed.findings}
    for f in cr.findings:
        if notes[f["id"]]:
            # a known disagreement is a finding of the report, not of this test: where the run
            # disagrees, the report names it with the campaign's reason
            if not f["agrees"]:
                assert f"**{f['id']}**" in md and notes[f["id"]].strip()[:60] in md, f["id"]
        else:
            assert _same_direction(f), (f["id"], f["sim_change"], f["status"])


# --------------------------------------------------------------------------- calibration: {from: ...}
@pytest.mark.slow
def test_calibration_from_fits_caches_and_reuses(tmp_path):
    """A circle campaign on the table_4_2 stage runs table_4_2's baseline fit once (2 trials),
    caches it as calibration.json, and the next run into the folder, or into a sibling of the
    source campaign's folder, loads it instead of refitting."""
    camp = load_campaign("circle_4_11")
    d = camp.model_dump(by_alias=True)
    d.update(trials=1)
    d["test"]["circles"] = [{"radius": 5e-6, "speeds": [20e-6]}]
    d["seed"]["values"] = []
    d["seed"]["findings"] = [f for f in d["seed"]["findings"] if f["id"] == "fi_rms_lower_5um"]
    tiny = Campaign.model_validate(d)
    out = tmp_path / "circle"
    first = run_campaign(tiny, out, calibration_trials=1, progress=False, mcap=False)
    cal = first.calibration
    assert not cal["reused"] and cal["source"]["campaign"] == "table_4_2" and cal["trials"] == 1
    fit = {p["name"]: p for p in cal["parameters"]}     # fitted to table_4_2's No FI 5 mm numbers
    rms = fit["drive_noise_current_rms"]["target"]
    assert rms["sim_effective"] == pytest.approx(rms["seed_effective"], rel=0.1), cal
    for case in ("nofi", "fi"):                 # applied to every case here; the PID is the designed one
        ov = first.runs[(case, "r5um_v20ums")].overrides
        assert "controller.pid.ki" not in ov
        assert ov["stage.drive.noise_current_rms"] == pytest.approx(cal["values"]["drive_noise_current_rms"])
    assert "calibration: {from: table_4_2}" in (out / "report.md").read_text()
    assert (out / "plots" / "reduction_vs_speed.png").is_file()        # Fig. 4.13/4.14 style
    again = run_campaign(tiny, out, calibration_trials=1, progress=False, plots=False, mcap=False)
    assert again.calibration["reused"] and again.calibration["values"] == cal["values"]
    assert again.calibration["source"]["loaded_from"] == str(out / "calibration.json")
    # a table_4_2 run's own calibration.json, next to the output folder, is found too
    (tmp_path / "table_4_2").mkdir()
    (tmp_path / "table_4_2" / "calibration.json").write_text((out / "calibration.json").read_text())
    third = run_campaign(tiny, tmp_path / "other", calibration_trials=1, progress=False, plots=False,
                            mcap=False, report=False)
    assert third.calibration["source"]["loaded_from"] == str(tmp_path / "table_4_2" / "calibration.json")
    # another trial count is another fit: the cache is not used
    assert calibration_fingerprint(load_campaign("table_4_2"), 3) != cal["fingerprint"]


# --------------------------------------------------------------------------- schema
def _write(tmp_path, data):
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False, allow_unicode=True))
    return p


def _circle(**extra):
    d = yaml.safe_load((CAMPAIGN_DIR / "circle_4_11.yaml").read_text())
    d.update(extra)
    return d


@pytest.mark.parametrize("mutate, where", [
    (lambda d: d.update(calibration={"from": "no_such_campaign"}), "calibration.from: 'no_such_campaign'"),
    (lambda d: d.update(calibration={"from": "circle_3_19"}), "fits no calibration of its own"),
    (lambda d: d.update(calibration={"from": "table_4_2", "bogus": 1}), "calibration.from.bogus"),
    (lambda d: d["test"].update(radii=[5e-3]), "either radii and speeds, or circles"),
    (lambda d: d["seed"]["findings"][1].update(change=0.16), "change +0.16 contradicts direction 'lower'"),
    (lambda d: d["cases"][1].update(per_speed={"bogus.path": 0.3}), "cases.1 (fi)"),
    (lambda d: d["cases"][1].update(overrides={"stage.drive.noise_current_rms": 1e-3}),
     "overrides ['stage.drive.noise_current_rms']"),
])
def test_schema_errors_name_the_field(tmp_path, mutate, where):
    d = _circle()
    mutate(d)
    with pytest.raises(ConfigError) as err:
        load_campaign(_write(tmp_path, d))
    assert where in str(err.value)


def test_sweep_schema_errors(tmp_path):
    d = yaml.safe_load((CAMPAIGN_DIR / "ff_4_16.yaml").read_text())
    d["sweep"]["apply"][2].pop("series")
    with pytest.raises(ConfigError, match="series_scale needs 'series'"):
        load_campaign(_write(tmp_path, d))
    d = yaml.safe_load((CAMPAIGN_DIR / "ff_4_16.yaml").read_text())
    d["sweep"]["apply"][1]["cases"] = ["nofi_dahl"]
    with pytest.raises(ConfigError, match="in more than one sweep target"):
        load_campaign(_write(tmp_path, d))
    d = yaml.safe_load((CAMPAIGN_DIR / "ff_4_16.yaml").read_text())
    d["seed"]["findings"][-1]["sweep"] = 1.0
    with pytest.raises(ConfigError, match="sweep_spread compares every sweep value"):
        load_campaign(_write(tmp_path, d))
    d = yaml.safe_load((CAMPAIGN_DIR / "ff_6_5.yaml").read_text())
    d["seed"]["findings"][3]["direction"] = "lower"
    with pytest.raises(ConfigError, match="relative_to is for direction 'similar'"):
        load_campaign(_write(tmp_path, d))
    d = yaml.safe_load((CAMPAIGN_DIR / "ff_6_5.yaml").read_text())
    d["seed"]["findings"][3]["relative_to"] = "nobody"
    with pytest.raises(ConfigError, match="case 'nobody' is not a case"):
        load_campaign(_write(tmp_path, d))


@pytest.mark.slow
def test_feedforward_stiffness_errors_follow_the_seed():
    """Sec. 4.4.3: the No FI models' stiffnesses scale with the error; FI + Dahl re-combines the
    erroneous k_sigma,NoFI in series with k_fi (8.08e4 N/m of Table 4.3 without error); Baseline and
    FI + GMS do not depend on the sweep."""
    c = load_campaign("ff_4_16")
    conds = {cond.sweep: cond for cond in conditions(c) if cond.radius == 5e-3 and cond.speed == 5e-3}
    ff = {s: {k.name: case_preset(c, k, CAL["table_4_2"], cond).controller.feedforward for k in c.cases}
          for s, cond in conds.items()}
    assert ff[1.0]["baseline"] is None
    k_fi = 1 / (1 / 8.27e4 + 1 / 2.19e6)      # Table 4.3 lists 8.08e4; its own k_fi, k_sigma,NoFI give 7.97e4
    assert ff[1.0]["fi_dahl"].friction.k_sigma == pytest.approx(k_fi)
    assert ff[1.0]["fi_dahl"].friction.k_sigma == pytest.approx(8.08e4, rel=0.015)
    k_half = 1 / (1 / 8.27e4 + 1 / (0.5 * 2.19e6))
    assert ff[0.5]["fi_dahl"].friction.k_sigma == pytest.approx(k_half)
    assert ff[0.5]["fi_dahl"].friction.k_sigma / ff[1.0]["fi_dahl"].friction.k_sigma > 0.95   # Eq. 4.2
    assert ff[1.5]["nofi_dahl"].friction.k_sigma == pytest.approx(1.5 * 2.19e6)
    assert ff[0.5]["nofi_gms"].friction.k[0] == pytest.approx(0.5 * 1.34e6)
    assert ff[0.5]["fi_gms"] == ff[1.5]["fi_gms"]


@pytest.mark.slow
def test_sai_reversal_window_follows_the_speed():
    c = load_campaign("circle_5_14")
    for cond in conditions(c):
        p = case_preset(c, c.case("sai"), None, cond)
        assert p.sai_manager.reversal_window == pytest.approx(0.309 * cond.speed)
        assert p.sai_manager.rule == "tracking" and p.sai_manager.ilc is None
        assert math.isclose(case_preset(c, c.case("fi"), None, cond).sai_manager.reversal_window, 0.0)


def test_new_campaigns_are_listed():
    assert {"table_6_3", "circle_3_19", "circle_4_11", "circle_5_14", "ff_4_16", "ff_6_5", "steps_c1",
            "steps_c12"} <= set(list_campaigns())


def test_every_campaign_kind_has_its_schema_beside_it():
    """Each kind's schema is in ``campaigns/schema/<kind>.py`` and nowhere else: the schema package holds
    one module per kind in :data:`KINDS` (plus ``common``), and that module defines the kind's schema class."""
    modules = {m.name for m in pkgutil.iter_modules(schema.__path__)}
    assert modules - {"common"} == set(KINDS), "a schema module without a kind, or a kind without a schema module"
    for name, kind in KINDS.items():
        assert kind.test.__module__ == f"{schema.__name__}.{name}", f"{name}'s schema is in {kind.test.__module__}"
        assert getattr(importlib.import_module(kind.test.__module__), kind.test.__name__) is kind.test
    assert set(schemas()) == {kind.test for kind in KINDS.values()}


def test_every_test_schema_has_its_kind_and_metrics():
    """The ``test`` union and :data:`KINDS` list the same kinds; each kind reports its schema's metrics,
    every one of them in the metric registry; each shipped campaign's conditions come from its schema."""
    assert {s.model_fields["kind"].annotation.__args__[0] for s in schemas()} == set(KINDS)
    for name, kind in KINDS.items():
        assert kind.name == name and kind.test in schemas()
        assert kind.metrics == kind.test.METRICS and set(kind.metrics) <= set(METRICS)
    for n in list_campaigns():
        camp = load_campaign(n, check_presets=False)
        assert kind_of(camp).test is type(camp.test)
        base = camp.test.conditions()
        assert len(conditions(camp)) == len(base) * (len(camp.sweep.values) if camp.sweep else 1)


@pytest.mark.parametrize("fi, nofi, agrees, bound", [
    ([0.018, 0.019], [None, None], True, (0.0185 - 1.0) / 1.0),     # No FI never settles: FI faster, change <= -98 %
    ([None, None], [0.06, 0.07], False, (1.0 - 0.065) / 0.065),     # FI never settles: the opposite direction
])
def test_a_settling_time_never_reached_is_right_censored(fi, nofi, agrees, bound):
    """A settling-time finding where one case never settles within the dwell and the other does
    (table_4_2_dahl's No FI table ratchets out of the +-25 nm window): the direction is known -- the
    unsettled case takes longer than the dwell -- and the change is a bound against the dwell;
    before, the finding was "undefined (no settled trials)" and, where it has no note, this file's
    run test failed on a machine whose two reduced-scale No FI trials both ratcheted. Neither side
    settled stays undefined."""
    from experiment_runner.apps.campaigns.base import Stat
    from experiment_runner.apps.campaigns.findings import evaluate_findings

    class Run:
        def __init__(self, v):
            self.stats = {"settling_time_s": Stat.of(v), "rms_in_position_m": Stat.of([None, None])}

    camp = load_campaign("table_4_2_dahl")
    conds = {c.label: c for c in conditions(camp)}
    key = next(c.key for c in conds.values() if abs(c.at()["step"] - 5e-6) < 1e-12)
    runs = {(case, c.key): Run([0.05, 0.05]) for c in conds.values() for case in ("fi", "nofi")}
    runs[("fi", key)], runs[("nofi", key)] = Run(fi), Run(nofi)
    f = next(r for r in evaluate_findings(camp, runs) if r["id"] == "fi_settles_faster_5um")
    assert f["agrees"] is agrees and f["sim_change"] == pytest.approx(bound)
    assert "never settled within the 1 s dwell" in f["status"]
    runs[("fi", key)] = Run([None, None])
    runs[("nofi", key)] = Run([None, None])
    f = next(r for r in evaluate_findings(camp, runs) if r["id"] == "fi_settles_faster_5um")
    assert f["status"] == "undefined (no settled trials)" and f["sim_change"] is None
