"""Frequency-response campaigns (Fig. 4.4-4.6, C.8-C.10): estimator, loop, margins, campaign files and runs."""
from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
import scipy.signal
import yaml
from scipy.optimize import brentq

from experiment_runner.apps.campaigns.findings import seed_bound_check
from experiment_runner.apps.campaigns.frf import loop_frfs, nominal_fit, plant_frf
from experiment_runner.apps.campaigns.kinds import kind_of
from experiment_runner.apps.campaigns.runner import run_campaign
from experiment_runner.apps.campaigns.schema.frequency_response import FrequencyResponseTest, frequency_grid
from experiment_runner.apps.campaigns.spec import Campaign, case_preset, conditions, load_campaign
from experiment_runner.core.batch import simulate
from experiment_runner.core.metrics import sine_phasor
from stage_control.tuning import loop_margins
from stage_sim.config import ConfigError, load_preset, with_overrides

# A linear stage: the table (modes removed) on the two FI flexures to bearings held by a
# Coulomb stiction far above any force used (they never slip), no drive noise, no quantisation:
# G(s) = 1 / (m s^2 + c s + k) with m = table mass, k = c = the two joints in parallel.
K_JOINT, C_JOINT = 4.0e4, 20.0


def _linear_preset(dob=None):
    p = load_preset("fi_stage_gms")
    ov = {"stage.modes": [], "stage.drive.noise_current_rms": 0.0, "stage.encoder.resolution": 1e-12}
    for i in range(len(p.stage.bearings)):
        ov[f"stage.bearings.{i}.friction"] = {"model": "coulomb", "f_c": 1000.0}
        ov[f"stage.bearings.{i}.joint"] = {"stiffness": K_JOINT, "damping": C_JOINT}
    if dob is not None:
        ov["controller.dob"] = dob
    return with_overrides(p, ov)


def _exact_plant(preset, f):
    """ZOH discretisation of 1/(m s^2 + c s + k): the encoder sample k after the command of sample k-1."""
    n = len(preset.stage.bearings)
    m, c, k = preset.stage.table.mass, n * C_JOINT, n * K_JOINT
    dt = 1.0 / preset.controller.rate
    num, den, _ = scipy.signal.cont2discrete(([1.0], [m, c, k]), dt, method="zoh")
    z = np.exp(2j * np.pi * np.asarray(f) * dt)
    return np.polyval(np.ravel(num), z) / np.polyval(den, z)


def _test(**kw):
    base = dict(kind="frequency_response", amplitudes=[0.5], f_min=5.0, f_max=2000.0, points_per_decade=3,
                cycles=3, min_measure_time=0.05, min_settle_time=0.6, sensor="true")
    return FrequencyResponseTest(**{**base, **kw})


# --------------------------------------------------------------------------- estimator and loop
def test_sine_phasor_rejects_offset_and_drift():
    t = np.arange(2000) * 1e-4                       # 10 periods of 50 Hz
    s = 3e-6 * np.sin(2 * np.pi * 50 * t - 0.7) + 1e-3 + 0.02 * t
    S = sine_phasor(t, s, 50.0)
    assert abs(S) == pytest.approx(3e-6, rel=1e-9)
    assert np.angle(S) == pytest.approx(-0.7 - np.pi / 2, abs=1e-9)   # sin = cos(. - pi/2)


def test_plant_frf_recovers_a_linear_stage():
    preset = _linear_preset()
    pf = plant_frf(preset, _test(amplitudes=[0.2, 2.0]))
    assert (pf.status == 0).all() and np.isfinite(pf.G).all()
    exact = _exact_plant(preset, pf.freqs_hz)
    for row in pf.G:                                  # linear: the same FRF at every amplitude
        err = np.abs(row / exact - 1.0)
        assert err.max() < 2e-3, (pf.freqs_hz, err)   # transients and the fit: below 0.2 %
    # the encoder reading (4.88 nm counts) gives the same FRF where the motion spans many counts
    enc = with_overrides(preset, {"stage.encoder.resolution": 4.88e-9})
    pe = plant_frf(enc, _test(amplitudes=[2.0], sensor="encoder"))
    many = np.abs(pe.G[0]) * 2.0 > 200 * 4.88e-9
    assert many.sum() >= 3 and np.abs(pe.G[0, many] / exact[many] - 1).max() < 5e-3
    # ... and is visibly quantised at 2 kHz (2 counts peak to peak), where the true position is exact
    assert abs(pe.G[0, -1] / exact[-1] - 1) > 0.05
    # and the continuous-time value at 5 Hz (the ZOH changes the magnitude by < 1e-5 there)
    w = 2 * np.pi * pf.freqs_hz[0]
    g = 1 / abs(2 * K_JOINT - preset.stage.table.mass * w ** 2 + 2j * C_JOINT * w)
    assert abs(pf.G[0, 0]) == pytest.approx(g, rel=1e-3)


@pytest.mark.parametrize("dob", [None, {"pole": 244.0, "gain": 13.8 / 11, "q_cutoff": 200.0}])
def test_calculated_closed_loop_matches_the_batch_engine(dob):
    """T calculated from the plant FRF and the servo's discrete PID (+ DOB) = the simulated closed loop."""
    preset = _linear_preset(dob)
    freqs = np.array([20.0, 150.0, 400.0])
    dt = 1.0 / preset.controller.rate
    n_ramp, n_settle, n_meas = 1000, 6000, 2000          # 0.1 s ramp, 0.6 s wait, 0.2 s window
    k = np.arange(n_ramp + n_settle + n_meas)
    f_adj = np.round(freqs * n_meas * dt) / (n_meas * dt)     # whole periods in the window
    env = np.where(k < n_ramp, 0.5 * (1 - np.cos(np.pi * k / n_ramp)), 1.0)
    x_ref = 1e-6 * env * np.sin(2 * np.pi * f_adj[:, None] * k * dt)
    res = simulate(preset, x_ref, np.zeros_like(x_ref))
    w = slice(k.size - n_meas, k.size)
    t = k[w] * dt
    T_sim = np.array([sine_phasor(t, res.y[i, w], f) / sine_phasor(t, x_ref[i, w], f)
                      for i, f in enumerate(f_adj)])
    T_calc = loop_frfs(preset, f_adj, _exact_plant(preset, f_adj))["T"]
    assert np.abs(T_sim - T_calc).max() < 1e-3 * np.abs(T_calc).max(), (T_sim, T_calc)
    # the loop is not trivially 1: a real test of the controller FRF
    assert np.abs(T_calc - 1).max() > 0.1


def test_loop_margins_reference_values():
    """L = K / (s (s+1) (s+10)): phase crossover at sqrt(10) rad/s where |L| = K / 110."""
    f = np.logspace(-2.5, 1.5, 1500)
    s = 2j * np.pi * f
    for K in (11.0, 220.0):
        wc = brentq(lambda w: w * math.hypot(w, 1) * math.hypot(w, 10) - K, 1e-3, 1e3)
        pm_ref = 90.0 - math.degrees(math.atan(wc) + math.atan(wc / 10))
        m = loop_margins(f, K / (s * (s + 1) * (s + 10)))
        assert m.gain_margin_db == pytest.approx(20 * math.log10(110 / K), abs=0.02)
        assert m.phase_margin_deg == pytest.approx(pm_ref, abs=0.05)
        assert m.phase_crossover_hz == pytest.approx(math.sqrt(10) / (2 * math.pi), rel=1e-3)
        assert m.gain_crossover_hz == pytest.approx(wc / (2 * math.pi), rel=1e-3)
    # K = 220 is unstable: both margins negative (GM -6.02 dB)
    assert m.gain_margin_db < 0 and m.phase_margin_deg < 0


# --------------------------------------------------------------------------- campaign files
@pytest.mark.slow
def test_frf_campaign_files_validate():
    for name in ("frf_fi", "frf_dob"):
        c = load_campaign(name)
        conds = conditions(c)
        assert [x.amplitude for x in conds] == [0.11, 0.22, 0.55, 1.1, 2.2, 4.95, 11.0, 16.5]
        assert conds[0].label == "0.11 N" and c.test.f_min <= 1.0
        assert kind_of(c).metrics == FrequencyResponseTest.METRICS
    fi = load_campaign("frf_fi")
    assert fi.seed_value("nofi", "bandwidth_hz", amplitude=16.5) == 200.0
    dob = load_campaign("frf_dob")
    assert dob.case("nofi_dob").overrides["controller.dob"]["q_cutoff"] == 100.0
    assert dob.case("fi_dob").overrides["controller.dob"]["q_cutoff"] == 200.0


def _frf_yaml(**seed_extra):
    return {"name": "t", "title": "t", "trials": 1, "baseline": "nofi",
            "test": {"kind": "frequency_response", "amplitudes": [0.11, 16.5], "f_min": 1.0, "f_max": 100.0},
            "cases": [{"name": "nofi", "label": "No FI", "preset": "fi_stage_nofi_gms"}],
            "seed": {"source": "t", "findings": [{"id": "f", "claim": "c", "case": "nofi", "versus": "nofi",
                                                  "amplitude": 0.11, "versus_amplitude": 16.5,
                                                  "metric": "bandwidth_hz", "direction": "lower",
                                                  **seed_extra}]}}


@pytest.mark.parametrize("mutate, where", [
    (lambda d: d["seed"]["findings"][0].update(versus_amplitude=3.0), "versus_amplitude 3.0"),
    (lambda d: d["seed"]["findings"][0].pop("versus_amplitude"), "case and versus are the same"),
    (lambda d: d["seed"]["findings"][0].update(metric="settling_time_s"), "not measured by a frequency_response"),
    (lambda d: d["test"].update(f_min=200.0), "f_min=200.0 must be below f_max"),
    (lambda d: d["seed"]["findings"][0].update(amplitude=0.2), "no condition matches"),
])
def test_frf_schema_errors_name_the_field(tmp_path, mutate, where):
    d = _frf_yaml()
    load_campaign(_write(tmp_path, d))          # the unmutated file is valid
    mutate(d)
    with pytest.raises(ConfigError, match=where):
        load_campaign(_write(tmp_path, d))


def _write(tmp_path, data):
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


# --------------------------------------------------------------------------- reduced runs
# the amplitudes the findings and seed numbers refer to, a coarser grid from 2 Hz
REDUCED = {"frf_fi": {"amplitudes": [0.11, 0.55, 1.1, 16.5], "f_min": 2.0, "points_per_decade": 10},
           "frf_dob": {"amplitudes": [0.11, 0.22, 0.55, 1.1, 16.5], "f_min": 2.0, "points_per_decade": 10}}


def _reduced(name):
    d = load_campaign(name).model_dump()
    d["test"].update(REDUCED[name])
    return Campaign.model_validate(d)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = {}
    for name in ("frf_fi", "frf_dob"):
        path = tmp_path_factory.mktemp(name)
        # through the campaign hook; plots of one campaign only (they take seconds)
        out[name] = run_campaign(_reduced(name), path, progress=False, plots=name == "frf_fi")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", ["frf_fi", "frf_dob"])
def test_seed_findings_directions(runs, name):
    """Findings without a note reproduce the seed; one with a note that disagrees carries its reason
    (a known disagreement is a report finding, not pinned here)."""
    cr = runs[name]
    assert len(cr.findings) == len(cr.campaign.seed.findings)
    for f in cr.findings:
        assert f["sim_case"] is not None and f["sim_versus"] is not None, f["id"]
        if f["note"]:
            assert f["agrees"] or f["explanation"], f["id"]
        else:
            assert f["agrees"], (f["id"], f["status"], f["sim_case"], f["sim_versus"])


@pytest.mark.slow
def test_frf_fi_physics(runs):
    cr = runs["frf_fi"]
    r = {(c, a): cr.runs[(c, k.key)] for c in ("nofi", "fi") for k in cr.conditions for a in [k.amplitude]}
    # the FI stage at 0.11 N: table on the flexures in series with the stuck bearings' GMS stiffness
    k_series = 1 / (1 / 8.27e4 + 1 / 2.186e6)
    assert abs(r[("fi", 0.11)].G[0]) == pytest.approx(1 / k_series, rel=0.03)
    # No FI: the bandwidth rises monotonically with the amplitude up to gross motion (Fig. 4.6(a))
    bw = [r[("nofi", a)].values["bandwidth_hz"] for a in REDUCED["frf_fi"]["amplitudes"]]
    assert bw == sorted(bw) and bw[0] < 10.0 < 150.0 < bw[-1]
    # margins of both stages positive at every amplitude (Sec. 4.3)
    assert all(x.values[m] > 0 for x in r.values() for m in ("gain_margin_db", "phase_margin_deg"))


@pytest.mark.slow
def test_simulated_closed_loop_agrees_with_the_calculated_one(runs):
    """frf_fi also runs each closed loop on the batch engine at the force amplitudes (the LTI check)."""
    cr = runs["frf_fi"]
    assert cr.campaign.test.simulate_closed_loop
    for (case, _), r in cr.runs.items():
        a = r.cond.amplitude
        ok = np.isfinite(r.T_sim)
        assert ok.sum() >= np.isfinite(r.G).sum() - 1          # every measured frequency simulated
        mid = ok & (r.freqs_hz < 500)                          # where |T| is not buried in noise
        assert np.abs(r.u_amp[mid] / a - 1).max() < 0.3, (case, a)   # the force amplitude asked for
        if a == 16.5:                                          # gross sliding: linear, same bandwidth
            assert r.bandwidth_sim_hz == pytest.approx(r.values["bandwidth_hz"], rel=0.02)
    assert cr.runs[("nofi", "0p11N")].bandwidth_sim_hz < 10.0  # the seed's '< 10 Hz' in closed loop too
    rows = list(csv.DictReader(open(cr.out_dir / "frf.csv")))
    assert all(x["T_sim_re"] != "" for x in rows if x["status"] == "0")


@pytest.mark.slow
def test_frf_dob_seed_bounds(runs):
    checks = seed_bound_check(runs["frf_dob"].campaign, runs["frf_dob"].runs)
    # the 200 Hz DOB's negative No FI margins at 0.11 N are not reproduced (see the finding's note)
    failed = {(c["case"], c["metric"]) for c in checks if c["within_bound"] is False}
    assert failed == {("nofi_dob200", "gain_margin_db"), ("nofi_dob200", "phase_margin_deg")}
    assert all(c["within_bound"] for c in checks if c["case"] != "nofi_dob200" and c["bound"] != "value")


@pytest.mark.slow
def test_outputs_are_written(runs):
    cr = runs["frf_dob"]
    d = json.loads((cr.out_dir / "results.json").read_text())
    assert d["kind"] == "frequency_response" and d["units"]["G"] == "m/N"
    n_f = len(frequency_grid(cr.campaign.test))
    n_a = len(REDUCED["frf_dob"]["amplitudes"])
    assert len(d["frf"]) == 5 * n_a
    assert all(len(x["freqs_hz"]) == n_f and len(x["T_real"]) == n_f for x in d["frf"])
    assert {r["metric"] for r in d["results"]} == set(FrequencyResponseTest.METRICS)
    with open(cr.out_dir / "frf.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 5 * n_a * n_f
    # 16.5 N slides the stage: the lowest frequencies are skipped (status -1, no data)
    skipped = [x for x in rows if x["amplitude_n"] == "16.5" and x["status"] == "-1"]
    assert skipped and all(x["G_re_m_per_n"] == "" for x in skipped)
    report = (cr.out_dir / "report.md").read_text()
    assert "| 0.11 N |" in report and "seed findings reproduced" in report
    fi = runs["frf_fi"]
    assert sorted(p.name for p in (fi.out_dir / "plots").glob("*.png")) == sorted(
        [f"bode_{c.name}.png" for c in fi.campaign.cases] + ["bandwidth_margins.png"])
    assert "![bode_nofi](plots/bode_nofi.png)" in (fi.out_dir / "report.md").read_text()


@pytest.mark.slow
def test_table_c1_identifies_the_gross_motion_damping():
    """Table C.1 (App. C.2.1): Z / (s (s + P)) fitted below 100 Hz to the 1.5 A (16.5 N) plant FRFs gives
    P = 120 1/s (No FI) and 244 1/s, Z = 7.9 and 13.8 N/(A kg) (FI). On frf_fi's stage: Coulomb sliding
    alone gives far too little damping; the campaign's viscous term (derived from the No FI P) gives
    the No FI P, and then predicts the FI column with the presets' light (1 %) flexure damping, while
    a heavily damped flexure (30 %) misses the Z ratio."""
    camp = load_campaign("frf_fi")
    test = camp.test.model_copy(update={"f_min": 11.0, "f_max": 100.0, "points_per_decade": 10,
                                        "amplitudes": [16.5]})

    def fit(case, **ov):
        p = case_preset(camp, camp.case(case))
        p = with_overrides(p, {"stage.drive.noise_current_rms": 0.0, **ov})
        pf = plant_frf(p, test)
        P, Z = nominal_fit(pf.freqs_hz, pf.G[0])
        return P, Z * p.stage.drive.force_constant

    p_nofi, z_nofi = fit("nofi")
    p_coulomb, _ = fit("nofi", **{f"stage.bearings.{i}.friction.viscous": 0.0 for i in (0, 1)})
    assert p_nofi == pytest.approx(120.0, rel=0.10)
    assert p_coulomb < 0.6 * 120.0                       # the seed's P needs more than Coulomb sliding
    p_fi, z_fi = fit("fi")
    assert z_fi / z_nofi == pytest.approx(13.8 / 7.9, rel=0.05)
    assert p_fi == pytest.approx(244.0, rel=0.15)
    c30 = 2 * 0.30 * math.sqrt(4.135e4 * 0.3113)          # 30 % of critical on the FI's reduced mass
    _, z_fi30 = fit("fi", **{f"stage.bearings.{i}.joint.damping": c30 for i in (0, 1)})
    assert abs(z_fi30 / z_nofi / (13.8 / 7.9) - 1) > 0.10
