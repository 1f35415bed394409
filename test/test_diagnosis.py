"""Model diagnosis (experiment_runner.apps.diagnosis): kernels, predict, locate, fit, report, synth.

The end-to-end concealed-data cases (synth -> MCAP -> diagnose) are in
test_diagnosis_selftest.py; here the pieces, on short in-memory batches.
"""
import dataclasses
import math

import numpy as np
import pytest
import yaml

from experiment_runner.apps.diagnosis.power.case_run import build_case
from experiment_runner.apps.diagnosis.power.cases import DEFAULT_CASES, make_cases
from experiment_runner.apps.diagnosis.context import Context
from experiment_runner.apps.diagnosis.data import DiagData
from experiment_runner.apps.diagnosis.effects import LIBRARY
from experiment_runner.apps.diagnosis.effects.friction import virgin_x50
from experiment_runner.apps.diagnosis.evaluator import Evaluator
from experiment_runner.apps.diagnosis.fit import fit_effect, gauss_newton, sparse_regression
from experiment_runner.apps.diagnosis.locate import REGIMES, by_regime, regimes
from experiment_runner.apps.diagnosis.model import ModelSpec, load_model
from experiment_runner.apps.diagnosis.noise import estimate_lattice
from experiment_runner.apps.diagnosis.predict import NoiseFloor, Observer, closed_loop, force_resolution, sim_batch, sim_data
from experiment_runner.core import profiles
from experiment_runner.core.batch import simulate
from stage_sim.config import ConfigError, load_preset, preset_from_dict, with_overrides

NOM = load_preset("fi_stage_nofi")


def _data(preset_or_spec, n=4, seed0=100):
    """Circle trials simulated from a truth, as DiagData (trial 3 held out)."""
    ref = profiles.circle_x(1e-3, 20e-3, cycles=1)
    x0 = np.linspace(-4e-3, 4e-3, n)
    spec = preset_or_spec if isinstance(preset_or_spec, ModelSpec) else ModelSpec(preset_or_spec)
    xr = (ref.x[:, None] + x0[None, :])
    vr = np.repeat(ref.v[:, None], n, axis=1)
    y, u, _, _ = closed_loop(spec, xr, vr, seed0 + np.arange(n))
    T = len(ref.x)
    valid = np.ones((T, n), bool)
    use = np.arange(T)[:, None] >= 50
    fit = valid & use
    held = np.zeros_like(fit)
    held[:, -1] = fit[:, -1]
    fit[:, -1] = False
    return DiagData(rate=1e4, t0=np.zeros(n), x_ref=xr, v_ref=vr, u=u, y=y, valid=valid, fit=fit, held=held,
                    lengths=np.full(n, T), trial_ids=list(range(n)))


# --------------------------------------------------------------------------- kernels
def test_simulated_recordings_of_several_seeds_are_one_batch_call():
    """sim_batch runs (trials x seeds) as one batch call; each seed's recording is the
    batch engine's own trials with those seeds (batching changes nothing)."""
    d = _data(NOM, n=2)
    a, b = sim_batch(ModelSpec(NOM), d, [7, 50])
    res = simulate(NOM, d.x_ref.T, d.v_ref.T, seeds=[50, 51])
    assert np.array_equal(b.y, res.y.T) and np.array_equal(b.u, res.u.T)
    assert not np.array_equal(a.y, b.y)


def test_observer_residual_is_the_missing_force():
    """A nominal model lacking a constant 0.3 N table force: the force residual is 0.3 N
    (up to noise); the exact model leaves only the noise floor."""
    truth = ModelSpec(with_overrides(NOM, {"stage.force_offset": 0.3}))
    d = _data(truth)
    ob = Observer(d)
    r = ob.run(ModelSpec(NOM)).r
    m = d.fit | d.held
    assert np.mean(r[m]) == pytest.approx(0.3, abs=0.01)
    r_exact = ob.run(truth).r
    assert abs(np.mean(r_exact[m])) < 0.003 and np.std(r_exact[m]) < 0.05


def test_open_loop_windows_drift_small_for_exact_model():
    from experiment_runner.apps.diagnosis.predict import open_loop_windows
    d = _data(NOM)
    ob = Observer(d)
    spec = ModelSpec(NOM)
    res = ob.run(spec, snap_every=100)
    w_ok = open_loop_windows(spec, ob, res, 100)
    wrong = LIBRARY["coulomb"].apply(spec, [4.0])
    res_w = ob.run(wrong, snap_every=100)
    w_bad = open_loop_windows(wrong, ob, res_w, 100)
    assert len(w_ok["start"]) > 50
    assert np.sqrt(np.mean(w_bad["drift_m"] ** 2)) > 20 * np.sqrt(np.mean(w_ok["drift_m"] ** 2))


# --------------------------------------------------------------------------- fitting
def test_gauss_newton_solves_a_linear_problem_in_one_step():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((200, 3))
    x_true = np.array([0.5, -1.0, 2.0])
    b = A @ x_true
    sol = gauss_newton(lambda z: A @ z - b, np.zeros(3), -10 * np.ones(3), 10 * np.ones(3), max_iter=3)
    assert np.allclose(sol["x"], x_true, atol=1e-6)
    assert sol["nfev"] <= 3 * 4 + 4


def test_lattice_estimate():
    rng = np.random.default_rng(1)
    q = 4.88e-9
    y = q * np.floor(rng.uniform(-1e-3, 1e-3, 5000) / q + 0.5)
    assert estimate_lattice(y) == pytest.approx(q, rel=1e-9)
    assert estimate_lattice(rng.uniform(-1e-3, 1e-3, 5000)) is None


def test_sparse_regression_keeps_the_true_terms():
    rng = np.random.default_rng(2)
    v = rng.standard_normal(3000)
    x = rng.standard_normal(3000)
    target = 2.0 * np.sign(v) - 0.5 * x + 0.01 * rng.standard_normal(3000)
    out = sparse_regression({"1": np.ones(3000), "v": v, "sign(v)": np.sign(v), "x": x, "x^2": x ** 2}, target)
    assert set(out["terms"]) == {"sign(v)", "x"}
    assert out["terms"]["sign(v)"] == pytest.approx(2.0, rel=0.01)
    assert out["explained"] > 0.99


@pytest.fixture(scope="module")
def coulomb_case():
    truth = with_overrides(NOM, {"stage.bearings.0.friction.f_c": 2.655 * 1.3,
                                 "stage.bearings.1.friction.f_c": 2.655 * 1.3})
    d = _data(truth)
    ob = Observer(d)
    spec = ModelSpec(NOM)
    sim = sim_data(spec, d, 999)
    osim = Observer(sim, bandwidth=ob.f_o)
    fl = NoiseFloor(d.rate, [osim.run(spec).r], [sim.fit | sim.held], f_max=ob.f_o)
    return d, ob, fl, spec


def test_fit_recovers_coulomb_and_rejects_others(coulomb_case):
    d, ob, fl, spec = coulomb_case
    ev = Evaluator(ob, fl)
    J0 = ev.J(spec)
    ctx = Context(u_max=float(np.abs(d.u).max()), v_max=0.02, x_center=0.0, x_half_span=5e-3)
    f = fit_effect(LIBRARY["coulomb"], spec, ev, ctx)
    assert f.theta[0] == pytest.approx(5.31 * 1.3, rel=1e-3)
    assert f.J_held < 2 and J0 > 1e4
    assert 0 < f.sigma[0] < 0.01
    fm = fit_effect(LIBRARY["mass"], spec, ev, ctx)
    assert fm.J_held > 100 * f.J_held


def test_evaluator_runs_the_observer_once_per_model_and_columns(coulomb_case):
    """The candidates of a step score their start against the same current model, and a fit's
    held-out J under its own floor repeats the run of its figures: the observer runs once per
    model and trial columns; each call still counts as an evaluation, and a cached run gives the
    same J as a fresh evaluator's (under another floor too)."""
    d, ob, fl, spec = coulomb_case
    ev = Evaluator(ob, fl)
    n0 = ob.calls
    J_fit = ev.J(spec, "fit")
    assert ev.J(spec, "fit") == J_fit and ob.calls == n0 + 1 and ev.evals == 2
    J_held = ev.J(spec, "held")
    other = NoiseFloor(d.rate, [ob.run(spec).r], [d.fit | d.held], f_max=ob.f_o)
    n1 = ob.calls
    J_other = ev.J(spec, "held", floor=other)            # the held-out run again, another floor
    assert ob.calls == n1
    fresh = Evaluator(ob, fl)
    assert fresh.J(ModelSpec(NOM), "held") == J_held and fresh.J(ModelSpec(NOM), "held", floor=other) == J_other
    assert ob.calls == n1 + 2                              # a new spec object: run again


def test_fit_runs_of_the_observer_stop_at_the_last_fit_sample(coulomb_case):
    """The observer is causal: a run stopped at sample ``n`` is the full run there (zero after);
    the evaluator's fit runs stop at the last fit sample and give the full run's fit vector."""
    d, ob, fl, spec = coulomb_case
    full = ob.run(spec, cols=[0])
    part = ob.run(spec, cols=[0], stop=300)
    assert np.array_equal(part.r[:300], full.r[:300]) and np.array_equal(part.v[:300], full.v[:300])
    assert not part.r[300:].any() and part.bad == 0
    half = dataclasses.replace(d, fit=d.fit & (np.arange(d.shape[0])[:, None] < d.shape[0] // 2))
    ob2 = Observer(half, bandwidth=ob.f_o)
    ev = Evaluator(ob2, fl)
    assert ev.fit_stop == d.shape[0] // 2
    m = half.fit[:, ev.fit_cols]
    ref = fl.whiten(ob2.run(spec, cols=ev.fit_cols).r, m)[m]
    assert np.array_equal(ev.fit_vector(spec), ref)


def test_whitening_gain_is_computed_once_per_length(coulomb_case):
    """Every residual a fit evaluates is whitened by the same gain: computed once per FFT length
    (read-only, shared), equal to a floor's built afresh."""
    d, ob, fl, spec = coulomb_case
    g = fl.gain(4096)
    assert fl.gain(4096) is g and not g.flags.writeable and fl.gain(8192) is not g
    again = NoiseFloor(d.rate, [Observer(sim_data(spec, d, 999), bandwidth=ob.f_o).run(spec).r],
                       [d.fit | d.held], f_max=ob.f_o)
    assert np.array_equal(again.gain(4096), g)


def test_replay_refinement_replays_a_point_once(coulomb_case):
    """The least-squares solver of a replay refinement starts where the start search scored: a
    point evaluated before is not replayed again, and its residual comes back unchanged (a
    copy: the caller may not spoil it)."""
    from experiment_runner.apps.diagnosis.judge import ReplayJudge
    from experiment_runner.apps.diagnosis.refinement import _OutputError
    d, ob, fl, spec = coulomb_case
    ctx = Context(u_max=float(np.abs(d.u).max()), v_max=0.02, x_center=0.0, x_half_span=5e-3)
    f = fit_effect(LIBRARY["coulomb"], spec, Evaluator(ob, fl), ctx)
    judge = ReplayJudge(d)
    floor = judge.floor(spec)
    oe = _OutputError(f, [], np.asarray(f.theta, float), spec, ctx, judge, floor)
    z = oe.clip(oe.tr.to_z(f.theta))
    n0 = judge.sims
    r1 = oe.residual(z)
    r1[:] = 0.0
    r2 = oe.residual(z.copy())
    assert judge.sims == n0 + 1
    assert np.array_equal(r2, judge.residual(judge.replay(f.effect.apply(spec, oe.tr.to_theta(z))), floor))
    oe.residual(z + 0.01)
    assert judge.sims == n0 + 3                            # the check's replay, and a new point


def _fit_on(d, nominal, key, ctx=None, starts=None):
    """``key`` fitted on ``nominal`` to the data ``d`` (from ``starts``, else its own); (fit, the
    nominal's held-out J)."""
    ob = Observer(d)
    spec = ModelSpec(nominal)
    sim = sim_data(spec, d, 999)
    fl = NoiseFloor(d.rate, [Observer(sim, bandwidth=ob.f_o).run(spec).r], [sim.fit | sim.held], f_max=ob.f_o,
                    rms_min=force_resolution(spec, ob.f_o))     # as the diagnosis bounds it
    ev = Evaluator(ob, fl)
    ctx = Context(**{"u_max": float(np.abs(d.u).max()), "v_max": 0.02, **(ctx or {})})
    return fit_effect(LIBRARY[key], spec, ev, ctx, starts=starts), ev.J(spec)


@pytest.mark.slow
def test_gms_effect_on_a_maxwell_slip_model_scales_its_own_blocks():
    """A Maxwell-slip nominal is one point of the GMS effect (x_scale 1, its own capacities): a
    stiffer contact (all block stiffnesses x1.25) is found as x_scale 0.8 with the capacities kept."""
    gms = load_preset("fi_stage_nofi_gms")
    e = LIBRARY["gms"]
    spec = ModelSpec(gms)
    ps = e.params(spec, Context())
    assert ps[0].name == "x_scale" and len(ps) == 1 + len(gms.stage.bearings[0].friction.k)
    same = e.apply(spec, [p.x0 for p in ps]).preset.stage.bearings[0].friction
    assert np.allclose(same.k, gms.stage.bearings[0].friction.k, rtol=1e-9)
    assert np.allclose(same.alpha, gms.stage.bearings[0].friction.alpha, rtol=1e-3)   # Table 4.4 sums to 1.0001
    truth = with_overrides(gms, {f"stage.bearings.{i}.friction.k": [k * 1.25 for k in b.friction.k]
                                 for i, b in enumerate(gms.stage.bearings)})
    f, J0 = _fit_on(_data(truth), gms, "gms")
    assert f.theta[0] == pytest.approx(0.8, rel=0.02)
    fc = sum(b.friction.f_c for b in gms.stage.bearings)
    assert f.derived["F_C"] == pytest.approx(fc, rel=0.02)
    assert f.J_held < 2 and J0 > 20


@pytest.mark.slow
def test_gms_fit_gets_past_rejected_damped_steps():
    """Twelve correlated capacities on an isolated stage (power-study case 006: a Maxwell-slip truth
    with a 13 um pre-motion length behind the isolator joints, Dahl nominal): from the start,
    Marquardt's damping stepped tenfold six times rejects every step (the fit stayed at its start);
    the trust-region solver takes over and reaches the data's level."""
    case = next(c for c in make_cases(DEFAULT_CASES) if c.name.startswith("006_gms_"))
    nominal, truth, expect, data, _ = build_case(case)
    f, J0 = _fit_on(data, nominal, "gms", {"v_max": 7e-4})
    assert J0 > 1000
    assert f.J_held < 10, f.J_held


@pytest.mark.slow
def test_a_start_the_simulator_refuses_is_a_bad_point_not_a_lost_candidate():
    """Power-study case 029: an isolator joint behind the bearings of a 1 kHz Coulomb stage. One
    of the joint's starts (the stiffest joint) is too stiff for the simulator's sub-step limit (the
    nominal's ``simulation.max_substeps`` lowered to 30: the stiffest start needs 46 at 1 kHz, the
    truth 22); that start counts as a bad fit and the others find the joint (the candidate was
    dropped before, and the diagnosis named GMS). The nominal states its bearings' mass: held."""
    case = next(c for c in make_cases(DEFAULT_CASES) if c.name.startswith("029_fi_compliance_"))
    nominal, truth, expect, data, _ = build_case(case)
    nominal = with_overrides(nominal, {"simulation.max_substeps": 30})
    spec = ModelSpec(nominal)
    e = LIBRARY["fi_compliance"]
    p = e.params(spec, Context())
    assert [q.name for q in p] == ["k_fi", "zeta_fi"]
    stiff = [p[0].hi, 0.02]
    with pytest.raises(ValueError, match="sub-steps"):
        e.apply(spec, stiff).compiled()
    f, J0 = _fit_on(data, nominal, "fi_compliance", starts=[stiff] + e.starts(spec, Context()))
    assert f.theta[0] == pytest.approx(expect["fi_compliance"]["k_fi"], rel=0.05)
    assert f.J_held < 1e-3 * J0


def test_noise_floor_whitening_is_unit_for_the_model_itself(coulomb_case):
    d, ob, fl, spec = coulomb_case
    sim2 = sim_data(spec, d, 4242)
    r2 = Observer(sim2, bandwidth=ob.f_o).run(spec).r
    assert fl.ms(r2, sim2.fit | sim2.held) == pytest.approx(1.0, abs=0.25)


# --------------------------------------------------------------------------- library, model files
@pytest.mark.parametrize("key", list(LIBRARY))
def test_every_effect_applies_to_the_nominal(key):
    e = LIBRARY[key].bound(Context(x_center=0.0, x_half_span=5e-3, observer_hz=400.0,
                                   frf_modes=({"f_hz": 1500.0, "zeta": 0.02, "fraction": 0.05},)))
    spec = ModelSpec(NOM)
    if e.applicable(spec) is not None:            # needs what the nominal lacks (isolator_transient: an SAI)
        assert key == "isolator_transient", e.applicable(spec)
        spec = ModelSpec(load_preset("sai_stage"))
        assert e.applicable(spec) is None
    ctx = Context(u_max=8.0, v_max=0.02, x_span=1e-2, peak_hz=(150.0,), ripple_period=(4e-4,), line_hz=(120.0,),
                  r_rms=0.5)
    ps = e.params(spec, ctx)
    assert all(p.lo <= p.x0 <= p.hi for p in ps), key
    new = e.apply(spec, [p.x0 for p in ps])
    preset_from_dict(new.preset.model_dump())            # still a valid preset
    assert e.expressible, key
    new.compiled()


def test_viscous_lands_where_the_friction_is():
    """The viscous hypothesis changes the friction elements' total: on the isolated stage (bearings
    behind the FI joint) the bearings' viscous, behind the joint, as the power study's truths and a
    bearing's lubricant put it -- not a damper on the table, which a joint would not filter; a
    decrease scales the bearings down; a table-only nominal keeps it on the table."""
    from stage_sim.config import load_preset
    e = LIBRARY["viscous"]
    iso = ModelSpec(load_preset("fi_stage"))
    st0 = iso.preset.stage
    c0 = e.nominal(iso)["c"]
    assert c0 == pytest.approx(sum(b.friction.viscous for b in st0.bearings)
                               + (st0.table_friction.viscous if st0.table_friction else 0.0))
    up = e.apply(iso, [c0 + 8.0]).preset.stage
    assert all(b.joint is not None for b in up.bearings)
    assert [b.friction.viscous for b in up.bearings] == pytest.approx([b.friction.viscous + 8.0 / len(st0.bearings)
                                                                      for b in st0.bearings])
    assert (up.table_friction.viscous if up.table_friction else 0.0) == (st0.table_friction.viscous if st0.table_friction else 0.0)
    assert e.nominal(e.apply(iso, [c0 + 8.0]))["c"] == pytest.approx(c0 + 8.0)
    down = e.apply(iso, [0.5 * c0])
    assert e.nominal(down)["c"] == pytest.approx(0.5 * c0) and all(b.friction.viscous >= 0 for b in down.preset.stage.bearings)
    table_only = ModelSpec(NOM).with_changes(edit=lambda d: d["stage"].update(
        bearings=[], table_friction={"model": "coulomb", "f_c": 1.0, "f_s": None, "viscous": 2.0}))
    t = e.apply(table_only, [12.0]).preset.stage
    assert t.table_friction.viscous == pytest.approx(12.0) and not t.bearings


def test_list_effects_covers_the_issue():
    keys = {r["key"] for r in LIBRARY.describe(as_json=True)}
    for k in ("dahl", "gms", "coulomb", "viscous", "stribeck", "fi_compliance", "position_friction", "ripple",
              "structural_mode", "delay", "force_constant", "mass", "noise_level", "quantization",
              "dither_imbalance", "isolator_transient", "sparse_regression", "fractional_delay", "located_mode",
              "regularized_coulomb", "lugre"):
        assert k in keys
    text = LIBRARY.describe()
    assert "signature" in text and "needs" in text


def test_model_file_round_trip(tmp_path):
    """Every effect is a preset field: the improved preset YAML (here with ripple, offset and
    asymmetric friction) loads back as the same preset; the old additive-force files are refused."""
    spec = ModelSpec(NOM)
    spec = LIBRARY["ripple"].apply(spec, [0.1, 0.05, 4e-4])
    spec = LIBRARY["offset"].apply(spec, [0.2])
    spec = LIBRARY["friction_asymmetry"].apply(spec, [0.5, 3.0])
    pre = tmp_path / "p.yaml"
    pre.write_text(spec.preset_yaml())
    back = load_preset(pre)
    assert back == spec.preset and back.stage.force_offset == 0.2
    assert back.stage.force_ripple[0].amplitude == pytest.approx(np.hypot(0.1, 0.05))
    assert sum(b.friction.f_c_difference for b in back.stage.bearings) == pytest.approx(0.5)
    assert load_model({"preset": back.model_dump(mode="json")}).preset == back
    bad = tmp_path / "m.yaml"
    bad.write_text(yaml.safe_dump({"preset": "fi_stage_nofi", "additive_forces": [{"kind": "offset", "coef": 1}]}))
    with pytest.raises(ConfigError, match="force_offset"):
        load_model(bad)


def test_virgin_x50_of_dahl():
    x50 = virgin_x50([{"model": "dahl", "k_sigma": 2e6, "f_c": 5.0, "shape": 1.0}])
    assert x50 == pytest.approx(math.log(2) * 5.0 / 2e6, rel=0.01)


# --------------------------------------------------------------------------- locate
def test_regimes_of_steps_and_circle():
    ref = profiles.step_sequence(5e-6, 1, 1, dwell=0.05)
    v = ref.v[:, None]
    lab = regimes(ref.x[:, None], v, np.ones_like(v, bool), 1e4)
    names = {REGIMES[i] for i in np.unique(lab)}
    assert {"in_position", "settling", "acceleration"} <= names
    settle = ref.select("settle")[0]
    assert REGIMES[lab[settle.start + 5, 0]] == "settling"
    assert REGIMES[lab[settle.stop - 5, 0]] == "in_position"
    c = profiles.circle_x(1e-3, 2e-2)
    lab = regimes(c.x[:, None], c.v[:, None], np.ones((len(c.x), 1), bool), 1e4)
    half = len(c.x) // 2
    assert REGIMES[lab[half, 0]] == "reversal"
    assert REGIMES[lab[half // 2, 0]] == "constant_velocity"


def test_by_regime_shares_and_floor():
    """The one per-regime breakdown (locate, signatures, verdict): shares of the examined samples and
    of the residual's energy, the floor scaled to each regime's samples, regimes below
    ``min_samples`` left out."""
    lab = np.array([0] * 10 + [1] * 30 + [4] * 60)[:, None]
    r = np.concatenate([np.full(10, 2.0), np.full(30, 1.0), np.full(60, 0.5)])[:, None]
    mask = np.ones_like(r, bool)
    floor = np.full_like(r, 0.5)
    floor_mask = np.arange(100)[:, None] < 50          # the floor's 50 samples: 10 of constant_velocity
    rows = by_regime(r, mask, lab, floor=floor, floor_mask=floor_mask)
    assert [g["regime"] for g in rows] == ["in_position", "settling", "constant_velocity"]
    assert math.isclose(sum(g["time_share"] for g in rows), 1.0)
    assert math.isclose(sum(g["energy_share"] for g in rows), 1.0)
    total = 10 * 4.0 + 30 * 1.0 + 60 * 0.25
    assert math.isclose(rows[0]["energy_share"], 40.0 / total) and rows[0]["rms_N"] == 2.0
    # the floor's energy in a regime is scaled to the regime's samples: constant_velocity's 10 floor
    # samples stand for its 60
    assert rows[0]["floor_rms_N"] == 0.5 and rows[2]["floor_rms_N"] == 0.5
    excess = [max(0.0, g["samples"] * (g["rms_N"] ** 2 - g["floor_rms_N"] ** 2)) for g in rows]
    assert excess[2] == 0.0 and math.isclose(rows[0]["excess_share"], excess[0] / sum(excess))
    assert [g["regime"] for g in by_regime(r, mask, lab, min_samples=20)] == ["settling", "constant_velocity"]


def test_experiment_sine_sweep_profile():
    """The experiment schema's stepped sine is profiles.sine_sweep; its trials start inside the travel."""
    from experiment_runner.core.experiment import Experiment, build_trials, reference
    exp = Experiment.model_validate({"name": "s", "preset": "fi_stage_nofi", "trials": 2,
                                     "starts": {"margin": 0.005, "seed": 1},
                                     "profile": {"kind": "sine_sweep", "frequencies": [8.0, 25.0],
                                                 "amplitude": 1.5e-4, "periods": 4, "settle_periods": 1}})
    ref = reference(exp.profile, 1e-4)
    want = profiles.sine_sweep([8.0, 25.0], 1.5e-4, periods=4, settle_periods=1, dt=1e-4)
    assert np.array_equal(ref.x, want.x) and [s.frequency for s in ref.segments] == [8.0, 25.0]
    tr = build_trials(exp)
    assert len(tr) == 2 and all(np.allclose(t.x_ref - t.x_ref[0], ref.x, rtol=0, atol=1e-15) for t in tr)
    with pytest.raises(Exception, match="frequencies"):
        Experiment.model_validate({**exp.model_dump(), "profile": {"kind": "sine_sweep", "frequencies": [],
                                                                   "amplitude": 1e-4}})


def test_noise_floor_of_a_model_that_leaves_no_residual():
    """Simulated recordings with no force residual at all (a stage held by Coulomb friction whose
    measurement never changes) still give a floor: the white lower bound of one encoder step's force
    at the observer bandwidth. Whitening is finite; a 1 N residual is far above it, a residual at
    that bound is at it (without the bound the scale was 1/0 and every observer fit undefined)."""
    from experiment_runner.apps.diagnosis.predict import force_resolution
    rate, T = 1000.0, 4000
    mask = np.ones((T, 1), bool)
    f_min = force_resolution(ModelSpec(NOM), 40.0)
    fl = NoiseFloor(rate, [np.zeros((T, 1))], [mask], f_max=40.0, rms_min=f_min)
    assert np.isfinite(fl.scale) and np.all(np.isfinite(fl.psd))
    r = np.random.default_rng(0).normal(0, 1.0, (T, 1))
    assert fl.ms(r, mask) > 1e6
    assert 0.1 < fl.ms(r * f_min, mask) < 10


def test_noise_floor_refuses_a_diverged_recording():
    """A candidate whose simulated recording diverged has no floor (the candidate gets no credit from
    it): a clear ValueError, not overflow warnings from the spectrum and a NaN floor."""
    T = 2000
    mask = np.ones((T, 1), bool)
    r = np.zeros((T, 1))
    r[1500:] = 1e200
    with pytest.raises(ValueError, match="diverged"):
        NoiseFloor(1000.0, [r], [mask], f_max=40.0)
