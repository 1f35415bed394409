"""Issue 12: the diagnosis on records as they come -- open-loop records with a known external
force, rotary axes -- each on recordings written by code other than the project's simulator
(scipy's ZOH discretisation of the continuous plant and ``scipy.signal.dlsim``), imported with
``nanostage convert table``, at 1 kHz and 10 kHz.
"""
import json

import numpy as np
import pytest
import yaml
from scipy import signal

from experiment_runner.apps.diagnosis.data import load_data
from experiment_runner.apps.diagnosis.model import load_model
from experiment_runner.apps.diagnosis.openloop import OpenLoopJudge
from experiment_runner.apps.diagnosis.options import Options
from experiment_runner.apps.diagnosis.pipeline import diagnose
from experiment_runner.apps.diagnosis.predict import Observer
from experiment_runner.core.tabular import convert_table
from independent import lugre_rk4, regularized_coulomb_rk4
from stage_sim.config import ConfigError


def _record(tmp_path, rate, T=3.0, m=2.0, c=30.0, q=1e-8, noise=0.02, shaker=3.0, seed=1, units="linear"):
    """An open-loop record of a mass-damper ``m x'' = u + f + w - c x'`` (force/torque mode):
    ``u`` a random staircase (5 ms steps) plus a square wave, ``f`` a known 7 Hz shaker force
    (``--input``), ``w`` unknown white drive noise; exact ZOH by scipy (cont2discrete + dlsim),
    measurement quantized to ``q``. Written as .npz and converted (no reference column)."""
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    t = np.arange(n) / rate
    hold = int(round(0.005 * rate))
    u = np.repeat(rng.normal(0, 4.0, n // hold + 1), hold)[:n] + 6.0 * np.sign(np.sin(2 * np.pi * 1.5 * t))
    f = shaker * np.sin(2 * np.pi * 7.0 * t)
    w = rng.normal(0, noise, n)
    plant = signal.StateSpace([[0, 1], [0, -c / m]], [[0], [1 / m]], [[1, 0]], [[0]]).to_discrete(1 / rate, method="zoh")
    _, y, _ = signal.dlsim(plant, u + f + w, x0=[0.0, 0.0])
    y = q * np.floor(y[:, 0] / q + 0.5)
    src = tmp_path / f"run{int(rate)}.npz"
    np.savez(src, t=t, u=u, x=y, f=f)
    mapping = {"time": "t", "command": "u", "measured": "x", "input": "f", "units": units}
    return convert_table(src, mapping, tmp_path / f"run{int(rate)}.mcap", overwrite=True)


def _nominal(m=2.0, c=0.0, q=1e-8, noise=0.02, kind="linear", travel=1.0):
    """A nominal without a controller (a model of open-loop data)."""
    st = {"kind": kind, "table": {"mass": m},
          "drive": {"force_constant": 1.0, "peak_force": 200.0, "continuous_force": 200.0, "noise_current_rms": noise},
          "encoder": {"resolution": q}, "travel": {"min": -travel, "max": travel}}
    if c:
        st["table_friction"] = {"model": "coulomb", "f_c": 0.0, "viscous": c}
    return {"name": "open_loop_nominal", "stage": st}


def _judge(rec, nominal, drop_input=False):
    d = load_data(rec)
    assert d.open_loop and d.f_ext is not None
    if drop_input:
        d.f_ext = None
    spec = load_model(nominal).with_changes({"controller.rate": d.rate})
    obs = Observer(d)
    j = OpenLoopJudge(d, obs)
    fl = j.floor(spec)
    return j, spec, fl, j.floor_ratio(fl.replay, fl)


@pytest.mark.slow
def test_open_loop_judge_truth_at_its_floor_nominal_far_known_force_needed(tmp_path):
    """The open-loop judge on an open-loop record (1 kHz): the truth model's held-out window
    prediction is at its run-to-run floor (error/floor RMS ratio 1 +- 0.3, consistency z below
    the critical value), the nominal lacking the 30 N·s/m damper is far above it (> 10x), and
    the truth is adopted over the nominal by the judge's test; without the known shaker force
    the truth model itself is far from its floor (the input is used)."""
    rec = _record(tmp_path, 1000.0, T=2.0)
    j, spec_t, fl_t, ratio_t = _judge(rec, _nominal(c=30.0))
    assert 0.7 < ratio_t < 1.3
    assert j.consistency(fl_t.replay, fl_t) < j.t_q
    _, spec_n, fl_n, ratio_n = _judge(rec, _nominal(c=0.0))
    assert ratio_n > 10
    cmp = j.compare(fl_n, j.replay(spec_t))
    assert cmp.accepted, cmp.why
    _, _, _, ratio_blind = _judge(rec, _nominal(c=30.0), drop_input=True)
    assert ratio_blind > 5


def test_nominal_without_controller_refused_for_a_closed_loop_record(tmp_path):
    """A nominal that states no controller models open-loop data only: on a record with a
    reference the diagnosis says so (ConfigError naming the field), before any work."""
    from experiment_runner.apps.diagnosis.synth import synth
    rec = tmp_path / "cl.mcap"
    synth("fi_stage_nofi", "fi_p2p_5um", rec, trials=1)
    nom = _nominal(m=load_model("fi_stage_nofi").preset.stage.table.mass)
    with pytest.raises(ConfigError, match="controller"):
        diagnose(rec, nom, options=Options(plots=False))


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_open_loop_record_diagnosed(tmp_path, rate):
    """End to end on the open-loop record (no reference, known shaker force), nominal without a
    controller and without the damper: exactly the viscous term is found, within 3 % of the
    30 N·s/m the scipy integrator used, and the improved model's held-out prediction is at its
    run-to-run floor (ratio < 1.3); the report says it judged open-loop windows."""
    rec = _record(tmp_path, rate, T=3.0 if rate < 5000 else 1.5)
    rep = diagnose(rec, _nominal(), out=tmp_path / "out", options=Options(plots=False))
    assert [f["effect"] for f in rep["found"]] == ["viscous"]
    c = rep["found"][0]["params"][0]["value"]
    assert abs(c / 30.0 - 1) < 0.03
    assert rep["replay"]["floor_ratio"]["improved"] < 1.3 < 10 < rep["replay"]["floor_ratio"]["nominal"]
    assert rep["replay"]["reference"] == "none (open-loop record)"
    md = (tmp_path / "out" / "report.md").read_text()
    assert "Held-out open-loop prediction" in md


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_rotary_axis_diagnosed_in_rotary_units(tmp_path, rate, capsys):
    """A rotary axis (inertia 0.05 kg·m², torque mode, angle in rad, a 0.4 N·m·s/rad damper the
    nominal lacks), converted with --units rotary: the diagnosis finds the viscous term within
    3 % and reports every unit as rotary -- the parameter [N·m·s/rad], report.json's units,
    report.md's tables and stdout ([rad], N·m)."""
    from experiment_runner.apps.cli import main
    rec = _record(tmp_path, rate, T=3.0 if rate < 5000 else 1.5, m=0.05, c=0.4, q=1e-7, noise=0.002, shaker=0.1,
                  units="rotary")
    nom = tmp_path / "rotary_nominal.yaml"
    nom.write_text(yaml.safe_dump(_nominal(m=0.05, q=1e-7, noise=0.002, kind="rotary", travel=1e3)))
    out = tmp_path / "out"
    assert main(["diagnose", str(rec), str(nom), "--out", str(out)]) == 0
    text = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    assert rep["units"]["position"] == "rad" and rep["units"]["force"] == "N·m" and rep["units"]["mass"] == "kg·m²"
    assert [f["effect"] for f in rep["found"]] == ["viscous"]
    p = rep["found"][0]["params"][0]
    assert p["unit"] == "N·m·s/rad" and abs(p["value"] / 0.4 - 1) < 0.03
    md = (out / "report.md").read_text()
    assert "position [rad]" in md and "N·m·s/rad" in md and "position [m]" not in md
    assert " rad " in text and "N·m·s/rad" in text and " m " not in text.split("report:")[0]


def test_axis_mismatch_refused(tmp_path):
    """A rotary record diagnosed against a linear nominal: one message naming stage.kind."""
    rec = _record(tmp_path, 1000.0, T=0.5, units="rotary")
    with pytest.raises(ConfigError, match="stage.kind"):
        diagnose(rec, _nominal(), options=Options(plots=False))


# --------------------------------------------------------------------------- fractional delay
def _delayed(u, rate, delay, m, c, over=50):
    """Mass-damper response to the command ``u`` applied ``delay`` control periods late (exact
    delayed ZOH), by scipy on a grid ``over`` times finer (``delay * over`` whole fine steps)."""
    shift = int(round(delay * over))
    assert abs(shift - delay * over) < 1e-9
    uf = np.concatenate([np.zeros(shift), np.repeat(u, over)])[:len(u) * over]
    plant = signal.StateSpace([[0, 1], [0, -c / m]], [[0], [1 / m]], [[1, 0]], [[0]]).to_discrete(
        1 / (rate * over), method="zoh")
    _, y, _ = signal.dlsim(plant, uf, x0=[0.0, 0.0])
    return y[::over, 0]


@pytest.mark.parametrize("rate", [1000.0, 10000.0])
@pytest.mark.parametrize("delay", [0.3, 2.74])
def test_plant_fractional_delay_is_the_exact_delayed_zoh(rate, delay):
    """stage.drive.delay_samples + delay_fraction: the plant's response of a mass-damper to a
    random command equals scipy's exact delayed zero-order hold to 1e-9 relative (the fraction's
    linear part is exact, not an average over the period)."""
    from stage_sim.config import preset_from_dict
    from stage_sim.plant import PlantSim
    from stage_sim.plant_model import build_plant
    m, c = 2.0, 30.0
    d = _nominal(m=m, c=c, q=0.0, noise=0.0)
    d["stage"]["drive"].update(delay_samples=int(delay), delay_fraction=delay - int(delay))
    d["controller"] = {"rate": rate, "pid": {"kp": 0.0}}
    sim = PlantSim(build_plant(preset_from_dict(d).stage, rate))
    u = np.random.default_rng(3).normal(0, 5.0, 400)
    y = np.array([float(sim.step(uk)[0, 0]) for uk in u])       # position after each period
    ref = _delayed(u, rate, delay, m, c)[1:]                      # dlsim: the position before each input
    assert np.max(np.abs(y[:-1] - ref)) < 1e-9 * np.max(np.abs(ref))


@pytest.mark.parametrize("delay, lo", [(0.0, 0.0), (0.25, -0.25), (2.4, -0.999)])
def test_fractional_delay_shift_ends_at_no_delay(delay, lo):
    """The fractional delay's shift cannot take the model's total delay below zero: there the
    model is flat in it (a shift of -0.31 on a model without delay was the same model as no
    shift, and the observer's fit wandered there); the end at zero delay is a physical one."""
    from experiment_runner.apps.diagnosis.context import Context
    from experiment_runner.apps.diagnosis.effects import LIBRARY
    from experiment_runner.apps.diagnosis.model import ModelSpec
    from stage_sim.config import preset_from_dict
    d = _nominal(m=2.0, c=30.0, q=1e-9, noise=0.002)
    d["stage"]["drive"].update(delay_samples=int(delay), delay_fraction=delay - int(delay))
    spec = ModelSpec(preset_from_dict(d))
    (p,) = LIBRARY["fractional_delay"].params(spec, Context())
    assert p.lo == pytest.approx(lo) and p.hi == pytest.approx(0.999)
    assert p.physical_lo == (lo > -0.999)


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_fractional_delay_diagnosed(tmp_path, rate):
    """An open-loop record whose drive acts 1.4 control periods late (scipy, exact delayed ZOH on
    a 50x finer grid): against a nominal without delay the diagnosis names the whole-sample delay
    and the fractional delay on top and nothing else, together within 0.01 sample of 1.4 (measured:
    1.40001 at 1 kHz, 1.4011 at 10 kHz, refined by the open-loop windows; 1.399 and 1.351 from the
    force observer alone; a whole-sample delay alone cannot express it)."""
    m, c = 2.0, 30.0
    n = int((4.0 if rate < 5000 else 1.0) * rate)
    rng = np.random.default_rng(5)
    hold = int(round(0.002 * rate))
    u = np.repeat(rng.normal(0, 5.0, n // hold + 1), hold)[:n] + 6.0 * np.sign(np.sin(2 * np.pi * 5.0 * np.arange(n) / rate))
    w = rng.normal(0, 0.002, n)
    y = _delayed(u + w, rate, 1.4, m, c)
    q = 1e-9
    y = q * np.floor(y / q + 0.5)
    np.savez(tmp_path / "d.npz", t=np.arange(n) / rate, u=u, x=y)
    rec = convert_table(tmp_path / "d.npz", {"time": "t", "command": "u", "measured": "x"}, tmp_path / "d.mcap")
    rep = diagnose(rec, _nominal(m=m, c=c, q=q, noise=0.002), options=Options(plots=False))
    found = {f["effect"]: f for f in rep["found"]}
    assert set(found) == {"delay", "fractional_delay"}, list(found)
    total = found["delay"]["params"][0]["value"] + found["fractional_delay"]["params"][0]["value"]
    assert abs(total - 1.4) < 0.01, total


# --------------------------------------------------------------------------- isolator in any rigid nominal
def _isolated_record(tmp_path, rate, T, m_t=1.7, m_b=0.3, f_j=60.0, zeta=0.05, c_b=40.0, seed=7):
    """Open-loop record of a table (m_t) whose friction is a bearing (m_b, viscous c_b to ground)
    behind a joint of blocked... reduced-mass frequency ``f_j`` and damping ratio ``zeta``;
    scipy's exact ZOH of the 2-DOF state space. Returns (recording, joint stiffness)."""
    m_r = m_t * m_b / (m_t + m_b)
    k = m_r * (2 * np.pi * f_j) ** 2
    c = 2 * zeta * np.sqrt(k * m_r)
    A = [[0, 0, 1, 0], [0, 0, 0, 1], [-k / m_t, k / m_t, -c / m_t, c / m_t],
         [k / m_b, -k / m_b, c / m_b, -(c + c_b) / m_b]]
    plant = signal.StateSpace(A, [[0], [0], [1 / m_t], [0]], [[1, 0, 0, 0]], [[0]]).to_discrete(1 / rate, method="zoh")
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    hold = max(1, int(round(0.002 * rate)))
    u = np.repeat(rng.normal(0, 5.0, n // hold + 1), hold)[:n] + 6.0 * np.sign(np.sin(2 * np.pi * 5.0 * np.arange(n) / rate))
    _, y, _ = signal.dlsim(plant, u + rng.normal(0, 0.002, n), x0=np.zeros(4))
    q = 1e-9
    np.savez(tmp_path / "iso.npz", t=np.arange(n) / rate, u=u, x=q * np.floor(y[:, 0] / q + 0.5))
    return convert_table(tmp_path / "iso.npz", {"time": "t", "command": "u", "measured": "x"},
                         tmp_path / "iso.mcap", overwrite=True), k


def _rigid_nominals(m_t=1.7, m_b=0.3, c_b=40.0):
    """The same rigid body written twice: a table with the bearing's friction, and a table with a
    rigidly bolted bearing carrying that friction."""
    fr = {"model": "coulomb", "f_c": 0.0, "viscous": c_b}
    a = _nominal(m=m_t + m_b, c=c_b, q=1e-9, noise=0.002)
    b = _nominal(m=m_t, q=1e-9, noise=0.002)
    b["stage"]["bearings"] = [{"mass": m_b, "friction": fr}]
    return a, b


def test_isolator_hypothesis_in_any_rigid_nominal_same_candidate():
    """fi_compliance applies to a table with friction (its friction becomes the bearing's behind the
    joint) and to a table with bolted bearings; the same parameters give the same plant in both
    writings (every DOF mass, joint, friction), the rigid mass kept."""
    from experiment_runner.apps.diagnosis.effects import LIBRARY
    from stage_sim.plant_model import build_plant
    e = LIBRARY["fi_compliance"]
    a, b = (load_model(x).with_changes({"controller.rate": 1000.0}) for x in _rigid_nominals())
    assert e.applicable(a) is None and e.applicable(b) is None
    theta = [3.0e4, 0.05, 0.25]
    pa, pb = (build_plant(e.apply(s, theta).preset.stage, 1000.0) for s in (a, b))
    for name in ("phi", "gam", "fr_par", "fr_dof"):
        assert np.allclose(getattr(pa, name), getattr(pb, name), rtol=1e-12, atol=0), name
    sa = e.apply(a, theta).preset.stage
    assert sa.table_friction is None and sa.bearings[0].mass == 0.25 and abs(sa.table.mass - 1.75) < 1e-12


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_table_with_friction_and_bolted_bearings_give_the_same_diagnosis(tmp_path, rate):
    """A record of a table whose bearing sits behind a joint (scipy, 2-DOF), diagnosed against the
    rigid body written as "table with friction" and as "table + bolted bearing with that friction":
    both name the FI compliance first, each parameter within 2 % of the truth or within 3 of its
    reported sigma (the damping's optimum is shallow: at 1 kHz 0.0496 ± 0.0008 and 0.0487 ± 0.0006
    for 0.05), and the two diagnoses agree (same effects, parameters within 2 %). The table with
    friction states no bearing mass: it is fitted; the bolted bearing states it: it is held."""
    rec, k = _isolated_record(tmp_path, rate, T=3.0 if rate < 5000 else 1.0, f_j=60.0 if rate < 5000 else 300.0)
    reps = [diagnose(rec, nom, options=Options(plots=False)) for nom in _rigid_nominals()]
    keys = [[f["effect"] for f in r["found"]] for r in reps]
    assert keys[0] == keys[1] and keys[0][0] == "fi_compliance", keys
    vals = [{p["name"]: p["value"] for p in r["found"][0]["params"]} for r in reps]
    sig = [{p["name"]: p["sigma"] for p in r["found"][0]["params"]} for r in reps]
    assert "m_b" in vals[0] and "m_b" not in vals[1], vals
    truth = {"k_fi": k, "zeta_fi": 0.05, "m_b": 0.3}
    for v, sg in zip(vals, sig):
        assert all(abs(v[n] - truth[n]) < max(0.02 * truth[n], 3 * sg[n]) for n in v), (vals, sig)
    for name in vals[1]:
        assert abs(vals[0][name] / vals[1][name] - 1) < 0.02, (name, vals)


# --------------------------------------------------------------------------- modes up to Nyquist
def _mode_record(tmp_path, rate, T, M=2.0, fraction=0.2, f_b=None, zeta=0.02, c=30.0, seed=11):
    """Open-loop record of a table of rigid mass ``M`` with a mode: ``fraction`` of it on a spring-
    damper (blocked frequency ``f_b``, damping ratio ``zeta``), viscous ``c`` on the table; a white
    random command (every sample) plus a square wave; scipy's exact ZOH of the 2-DOF state space."""
    ms, mt = fraction * M, (1 - fraction) * M
    w = 2 * np.pi * f_b
    k, cm = ms * w * w, 2 * zeta * ms * w
    A = [[0, 0, 1, 0], [0, 0, 0, 1], [-k / mt, k / mt, -(cm + c) / mt, cm / mt], [k / ms, -k / ms, cm / ms, -cm / ms]]
    plant = signal.StateSpace(A, [[0], [0], [1 / mt], [0]], [[1, 0, 0, 0]], [[0]]).to_discrete(1 / rate, method="zoh")
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    u = rng.normal(0, 5.0, n) + 6.0 * np.sign(np.sin(2 * np.pi * 5.0 * np.arange(n) / rate))
    _, y, _ = signal.dlsim(plant, u + rng.normal(0, 0.002, n), x0=np.zeros(4))
    q = 1e-10
    np.savez(tmp_path / "mode.npz", t=np.arange(n) / rate, u=u, x=q * np.floor(y[:, 0] / q + 0.5))
    return convert_table(tmp_path / "mode.npz", {"time": "t", "command": "u", "measured": "x"},
                         tmp_path / "mode.mcap", overwrite=True)


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_mode_located_from_the_transfer_up_to_nyquist(tmp_path, rate):
    """A 2 % damped mode at 0.3 x Nyquist (150 Hz at 1 kHz, 1.5 kHz at 10 kHz: far above the force
    observer's rate/25), 20 % of the table's mass: located and fitted from the command ->
    measurement transfer against the rigid nominal (csd/welch): frequency within 3 %, mass fraction
    within 20 %, damping within a factor 1.5; the rigid truth shows no mode."""
    from experiment_runner.apps.diagnosis.frf import locate_modes
    f_b = 0.15 * rate
    rec = _mode_record(tmp_path, rate, T=2.0 if rate < 5000 else 0.5, f_b=f_b)
    d = load_data(rec)
    spec = load_model(_nominal(m=2.0, c=30.0, q=1e-10, noise=0.002)).with_changes({"controller.rate": rate})
    modes = locate_modes(spec, d)
    assert modes, "no mode located"
    m = modes[0]
    assert abs(m["f_hz"] / f_b - 1) < 0.03 and abs(m["fraction"] / 0.2 - 1) < 0.2 and 1 / 1.5 < m["zeta"] / 0.02 < 1.5, m
    rigid = _record(tmp_path, rate, T=2.0 if rate < 5000 else 0.5)
    assert locate_modes(spec, load_data(rigid)) == []


@pytest.mark.slow
def test_open_loop_judge_prewhitened_sees_a_mode_the_drift_buries(tmp_path):
    """A 1.5 kHz mode of 20 % of the mass on a 10 kHz open-loop record (scipy): in RMS the rigid
    nominal's window errors are within their floor (0.93x: the re-initialised state's drift
    dominates); prewhitened by the floor's own AR filter the rigid nominal is far above it (> 10x)
    while the truth stays at its floor (1 +- 0.2), and the judge adopts the truth over the nominal."""
    from experiment_runner.apps.diagnosis.effects import LIBRARY
    rate = 10000.0
    rec = _mode_record(tmp_path, rate, T=0.5, f_b=1500.0)
    d = load_data(rec)
    nom = load_model(_nominal(m=2.0, c=30.0, q=1e-10, noise=0.002)).with_changes({"controller.rate": rate})
    truth = LIBRARY["structural_mode"].apply(nom, [1500.0, 0.02, 0.2])
    j = OpenLoopJudge(d, Observer(d))
    fl_n, fl_t = j.floor(nom), j.floor(truth)
    assert j.floor_ratio(fl_n.replay, fl_n) > 10
    assert abs(j.floor_ratio(fl_t.replay, fl_t) - 1) < 0.2
    assert j.consistency(fl_t.replay, fl_t) < j.t_q
    e_rms = j.rms(fl_n.replay)[1]
    assert e_rms < 1.2 * fl_n.sigma_y          # in metres the drift hides it
    assert j.compare(fl_n, j.replay(truth)).accepted


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_mode_diagnosed_with_its_mass_split_off_the_table(tmp_path, rate):
    """End to end: the diagnosis names exactly the structural mode (frequency within 1 %, damping
    within 10 %, fraction within 5 %), its mass taken out of the table (improved table + mode mass =
    the nominal's 2 kg), and the improved model's held-out prediction is at its run-to-run floor
    (ratio 1 +- 0.2). Above the smoothing cutoff of the force observer (2.5 x rate/25) it is the
    mode located and fitted on the transfer (``located_mode``), refined by the open-loop windows.
    (At 10 kHz it was located but not adopted before the open-loop judge was prewhitened: the
    nominal's windows were at 0.93x their floor, the mode's band buried under the drift.)"""
    f_b = 0.15 * rate
    rec = _mode_record(tmp_path, rate, T=2.0 if rate < 5000 else 0.5, f_b=f_b)
    rep = diagnose(rec, _nominal(m=2.0, c=30.0, q=1e-10, noise=0.002), options=Options(plots=False))
    assert [f["effect"] for f in rep["found"]] in (["structural_mode"], ["located_mode"]), [f["effect"] for f in rep["found"]]
    first = rep["found"][0]
    v = {p["name"]: p["value"] for p in first["params"]} if first["effect"] == "structural_mode" else first["derived"]
    assert abs(v["f"] / f_b - 1) < 0.01 and abs(v["zeta"] / 0.02 - 1) < 0.1 and abs(v["fraction"] / 0.2 - 1) < 0.05, v
    assert abs(rep["replay"]["floor_ratio"]["improved"] - 1) < 0.2, rep["replay"]["floor_ratio"]
    st = rep["_improved_spec"].preset.stage
    assert abs(st.table.mass * (1 + sum(m.mass_ratio for m in st.modes)) - 2.0) < 1e-9
    # the drive noise is the nominal's (0.002): not raised to hide what the windows cannot
    # re-initialise (the open-loop simulated recordings carry the data's own low-frequency residual
    # as a known force, so the level is read above it only; it was 0.20 A, adopted)
    assert "noise_level" not in [f["effect"] for f in rep["found"]], rep["stochastic"]["noise_level"]
    assert st.drive.noise_current_rms == 0.002


# --------------------------------------------------------------------------- regularised Coulomb
def _regularized_record(tmp_path, rate, T, m=2.0, f_c=5.0, v_reg=1e-3, c=30.0, noise=0.02, q=1e-8, seed=3):
    """An open-loop record of ``m x'' = u + w - F_C tanh(v / v_reg) - c v`` by classical RK4 on
    a 10 us grid (``independent.py``; the command held over each sample), written as .npz and converted. The forces
    stay mostly below F_C: a Coulomb model sticks there, this one creeps at v_reg atanh(F/F_C)."""
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    hold = int(round(0.02 * rate))
    u = np.repeat(rng.normal(0, 3.0, n // hold + 1), hold)[:n] + 4.0 * np.sign(np.sin(2 * np.pi * np.arange(n) / rate))
    w = rng.normal(0, noise, n)
    x = np.r_[0.0, regularized_coulomb_rk4(u + w, rate, m, f_c, v_reg, c)[:-1]]     # sample k: before u[k]
    x = q * np.floor(x / q + 0.5)
    np.savez(tmp_path / "rc.npz", t=np.arange(n) / rate, u=u, x=x)
    return convert_table(tmp_path / "rc.npz", {"time": "t", "command": "u", "measured": "x"}, tmp_path / "rc.mcap")


@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_regularized_coulomb_diagnosed(tmp_path, rate):
    """A stage whose friction has a smooth zero-velocity transition (F_C tanh(v / v_reg), v_reg =
    1 mm/s; RK4 in the test) against a nominal with the same F_C and damper as plain Coulomb
    friction (which sticks): the diagnosis names exactly the regularised-Coulomb effect, v_reg
    within 10 %, and the improved model's held-out prediction is at its run-to-run floor."""
    rec = _regularized_record(tmp_path, rate, T=3.0 if rate < 5000 else 0.8)
    nom = _nominal(m=2.0, c=30.0)
    nom["stage"]["table_friction"]["f_c"] = 5.0
    rep = diagnose(rec, nom, options=Options(plots=False))
    assert [f["effect"] for f in rep["found"]] == ["regularized_coulomb"], [f["effect"] for f in rep["found"]]
    v_reg = rep["found"][0]["params"][0]["value"]
    assert abs(v_reg / 1e-3 - 1) < 0.1, v_reg
    assert rep["replay"]["floor_ratio"]["improved"] < 1.5 < 5 < rep["replay"]["floor_ratio"]["nominal"]


# --------------------------------------------------------------------------- drive noise, open loop
@pytest.mark.slow
@pytest.mark.parametrize("rate", [1000.0, 10000.0])
def test_drive_noise_level_of_an_open_loop_record(tmp_path, rate):
    """An open-loop record (scipy) whose drive noise is 10x the nominal's (0.2 A against 0.02 A),
    the model otherwise exact: the diagnosis names the drive-noise level alone, within 5 % of the
    truth, and the improved model's held-out windows are at their floor. At 1 kHz the residual
    spectrum's bands above the known-force band disagree (0.17-0.28 A, spread 0.37: not adopted
    before); the level at which the fit samples' prewhitened windows are at their floor, inside
    that range, is adopted (measured 0.1986 +- 0.0061 A; 10 kHz from the spectrum, 0.2028 A)."""
    rec = _record(tmp_path, rate, T=2.0 if rate < 5000 else 0.8, noise=0.2)
    rep = diagnose(rec, _nominal(c=30.0, noise=0.02), options=Options(plots=False))
    assert [f["effect"] for f in rep["found"]] == ["noise_level"], [f["effect"] for f in rep["found"]]
    p = rep["found"][0]["params"][0]
    assert abs(p["value"] / 0.2 - 1) < 0.05, p
    assert abs(p["value"] - 0.2) < 3 * p["sigma"], p
    assert rep["replay"]["floor_ratio"]["improved"] < 1.3 < 2 < rep["replay"]["floor_ratio"]["nominal"]


# --------------------------------------------------------------------------- LuGre bristle damping
@pytest.mark.slow
@pytest.mark.parametrize("rate, sigma1, T", [(1000.0, 1500.0, 2.0), (1000.0, 1.0e4, 2.0), (10000.0, 1500.0, 0.8)])
def test_lugre_bristle_damping_diagnosed(tmp_path, rate, sigma1, T):
    """A stage whose contact has bristle damping (LuGre: 2 kg, sigma0 2e6 N/m, F_C 5 N, 30 N·s/m;
    RK4 in (x, v, z) in the test, ``independent.py``) against a nominal with the same contact as a
    Dahl element (sigma1 = 0): the diagnosis names exactly ``lugre``, sigma0 and sigma1 within 5 %,
    and the improved model's held-out prediction falls to 1.5x its run-to-run floor (nominal
    beyond 3x that). sigma1 = 1500 N·s/m damps the 159 Hz pre-motion mode (zeta 0.37); 1e4 is an
    overdamped contact that creeps over sigma1 / sigma0 = 5 ms after each force change. Measured
    (the open-loop windows refine the observer's fit): 1 kHz sigma1 -1.4 %, 5.3 -> 1.10x; 1 kHz
    1e4 +1.6 %, 11.3 -> 1.07x; 10 kHz +0.14 %, 13.7 -> 1.00x. (Before, at 1 kHz the mode was beyond
    the force observer's reach (40 Hz) and open-loop records were not refined: only the 1e4 case
    was found, sigma1 +17 %, 3.1x the floor.)"""
    rng = np.random.default_rng(3)
    m, s0, f_c, c, q = 2.0, 2e6, 5.0, 30.0, 1e-9
    n = int(T * rate)
    hold = int(round(0.02 * rate))
    u = np.repeat(rng.normal(0, 3.0, n // hold + 1), hold)[:n] + 4.0 * np.sign(np.sin(2 * np.pi * np.arange(n) / rate))
    w = rng.normal(0, 0.02, n)
    x = np.r_[0.0, lugre_rk4(u + w, rate, m, s0, sigma1, f_c, f_c, 1e-3, c, h=5e-6)[:-1]]   # sample k: before u[k]
    x = q * np.floor(x / q + 0.5)
    np.savez(tmp_path / "lg.npz", t=np.arange(n) / rate, u=u, x=x)
    rec = convert_table(tmp_path / "lg.npz", {"time": "t", "command": "u", "measured": "x"}, tmp_path / "lg.mcap")
    nom = _nominal(m=2.0, c=30.0, q=q)
    nom["stage"]["table_friction"] = {"model": "dahl", "f_c": f_c, "k_sigma": s0, "shape": 1.0, "viscous": c}
    rep = diagnose(rec, nom, options=Options(plots=False))
    assert [f["effect"] for f in rep["found"]] == ["lugre"], [f["effect"] for f in rep["found"]]
    got = {p["name"]: p["value"] for p in rep["found"][0]["params"]}
    assert abs(got["sigma1"] / sigma1 - 1) < 0.05 and abs(got["sigma0"] / s0 - 1) < 0.05, got
    assert rep["replay"]["floor_ratio"]["improved"] < 1.5 < 4.5 < rep["replay"]["floor_ratio"]["nominal"]


# --------------------------------------------------------------------------- known force, closed loop
def test_known_force_applied_in_the_closed_loop_replay():
    """A closed-loop record (fi_stage_nofi, 5 um point-to-point moves, 3 trials) with a known
    0.3 N, 7 Hz force on the table (``/stage/external_force``): the model's noise-free replay
    of its held-out trial applies it -- the truth is at its run-to-run floor (error/floor
    RMS ratio 0.5 ... 1.5; measured 0.79) -- and without the known force the same model is far
    off (> 5x; measured 16.1x). Before, the replay applied no external force."""
    from experiment_runner.apps.diagnosis.data import from_trials
    from experiment_runner.apps.diagnosis.judge import ReplayJudge
    from experiment_runner.core.batch import simulate
    from experiment_runner.core.profiles import point_to_point
    spec = load_model("fi_stage_nofi")
    rate = spec.preset.controller.rate
    ref = point_to_point(5e-6, dt=1.0 / rate, dwell=0.1)
    B, T = 3, len(ref.x)
    f = 0.3 * np.sin(2 * np.pi * 7.0 * np.arange(T) / rate + np.arange(B)[:, None])
    res = simulate(spec.preset, ref.x, ref.v, n_trials=B, seeds=[71, 72, 73], f_ext=f)
    trials = [a for a in (list(res.x_ref), list(res.v_ref), list(res.u), list(res.y))]
    d = from_trials(rate, np.zeros(B), *trials, f_ext=list(f))
    with_f = ReplayJudge(d)
    fl = with_f.floor(spec)
    assert 0.5 < with_f.floor_ratio(with_f.replay(spec), fl) < 1.5
    d.f_ext = None
    without = ReplayJudge(d)
    fl0 = without.floor(spec)
    assert without.floor_ratio(without.replay(spec), fl0) > 5


# --------------------------------------------------------------------------- tiny motion (pre-sliding), torque mode
_ROT = dict(J=2e-4, f_c=0.01, c=1e-4, q=2 * np.pi / 16384, noise=2e-5)     # a small servo motor, 14-bit encoder


def _presliding_record(tmp_path, k_sigma=10.0, T=3.0, rate=1000.0, seed=5):
    """A rotary torque-mode record of motion within a few encoder counts: a torque of 0.8 and 0.1
    times the breakaway torque (1 Hz and 3.3 Hz) on a Dahl contact (``k_sigma`` [N·m/rad]: a
    pre-rolling angle F_C / k_sigma of 1 mrad, 2.6 counts), J 2e-4 kg·m², white drive noise;
    RK4 of LuGre with sigma1 = 0 and F_S = F_C (Dahl, shape 1; ``independent.py``), 14-bit
    encoder. The stage yields by about +-4 counts and never slides."""
    rng = np.random.default_rng(seed)
    n = int(T * rate)
    t = np.arange(n) / rate
    fc = _ROT["f_c"]
    u = 0.8 * fc * np.sin(2 * np.pi * t) + 0.1 * fc * np.sin(2 * np.pi * 3.3 * t)
    w = rng.normal(0, _ROT["noise"], n)
    x = np.r_[0.0, lugre_rk4(u + w, rate, _ROT["J"], k_sigma, 0.0, fc, fc, 1.0, _ROT["c"], h=5e-5)[:-1]]
    q = _ROT["q"]
    x = q * np.floor(x / q + 0.5)
    assert 5 < np.ptp(x) / q < 12
    np.savez(tmp_path / "ps.npz", t=t, u=u, x=x)
    return convert_table(tmp_path / "ps.npz", {"time": "t", "command": "u", "measured": "x", "units": "rotary"},
                         tmp_path / "ps.mcap")


def _rotary_nominal(law: str, J=None, f_c=None, c=None, **friction):
    fr = {"model": law, "f_c": _ROT["f_c"] if f_c is None else f_c, "viscous": _ROT["c"] if c is None else c,
          **friction}
    return {"name": f"rotary_{law}", "stage": {
        "kind": "rotary", "table": {"mass": _ROT["J"] if J is None else J},
        "drive": {"force_constant": 1.0, "peak_force": 1.0, "continuous_force": 1.0,
                  "noise_current_rms": _ROT["noise"]},
        "encoder": {"resolution": _ROT["q"]}, "travel": {"min": -1e4, "max": 1e4}, "table_friction": fr}}


@pytest.mark.slow
def test_presliding_stiffness_found_on_a_tiny_motion_record(tmp_path):
    """A pre-rolling run (motion of +-4 encoder counts under a sub-breakaway torque; Dahl truth,
    10 N·m/rad) against a rigid Coulomb nominal: the open-loop prediction runs the trial whole,
    quantized like the sensor (over 50 ms windows, whose re-estimated start absorbs a fraction of a
    count, the nominal read 1.3x its floor and nothing was named; the prewhitening filter of the
    floor's step-like errors cancelled the missing motion, D 1.3 for 36); the diagnosis names
    exactly ``dahl``, k_sigma within 5 % of 10 N·m/rad (measured 10.0), improved prediction at its
    floor, the nominal far above (measured 6.0x -> 0.95x). Before, the rotary start of the search
    was a 1 um "pre-motion length" (1e4 N·m/rad, its lower bound 10: at the truth)."""
    rec = _presliding_record(tmp_path)
    rep = diagnose(rec, _rotary_nominal("coulomb"), options=Options(plots=False))
    assert "whole trials" in rep["replay"]["predictor"]
    assert [f["effect"] for f in rep["found"]] == ["dahl"], [f["effect"] for f in rep["found"]]
    p = rep["found"][0]["params"][0]
    assert p["unit"] == "N·m/rad" and abs(p["value"] / 10.0 - 1) < 0.05, p
    assert rep["replay"]["floor_ratio"]["improved"] < 1.3 < 3 < rep["replay"]["floor_ratio"]["nominal"]


@pytest.mark.slow
def test_presliding_truth_adequate_with_the_stiffness_it_could_have_shown(tmp_path):
    """The same record against its truth (Dahl, 10 N·m/rad): "model adequate" (prediction at its
    floor, predicted whole: measured 0.95x; over windows, on a 4 s record of the same kind, the truth
    read 1.45x and a viscous term went to its bound),
    and the absence of a further change is stated with a bound: the smallest k_sigma change the
    record would have shown, finite and below the truth's value (measured 0.48 N·m/rad)."""
    rec = _presliding_record(tmp_path)
    rep = diagnose(rec, _rotary_nominal("dahl", k_sigma=10.0, shape=1.0), options=Options(plots=False))
    assert "whole trials" in rep["replay"]["predictor"]
    assert rep["found"] == [] and rep["replay"]["floor_ratio"]["nominal"] < 1.3
    lim = {d["parameter"]: d for d in rep["detection_limits"]}
    assert "k_sigma" in lim and 0 < lim["k_sigma"]["smallest_change"] < 10.0, lim.get("k_sigma")


@pytest.mark.slow
def test_torque_mode_inertia_agrees_with_a_least_squares_check(tmp_path):
    """A rotary torque-mode record (RK4 in the test: J 2e-4 kg·m², F_C 0.01 N·m regularised over
    1 mrad/s, 3e-4 N·m·s/rad, random torque staircase and a 1 Hz square wave, 14-bit encoder)
    against a nominal 30 % heavy, with F_C +20 % and a third of the viscous term: the diagnosis
    finds the inertia within 3 % of the truth and within 10 % of the ordinary least-squares check
    of the same data, which the report carries (``least_squares_check``: every quantity agrees
    with the improved model; measured J 2.002e-4 against the check's 2.04e-4 +- 7e-7); the
    nominal itself disagrees with the check in inertia (the check can fail)."""
    from experiment_runner.apps.diagnosis.openloop import least_squares_check
    rng = np.random.default_rng(7)
    rate, T, q = 1000.0, 4.0, _ROT["q"]
    n = int(T * rate)
    t = np.arange(n) / rate
    u = np.repeat(rng.normal(0, 0.02, n // 50 + 1), 50)[:n] + 0.02 * np.sign(np.sin(2 * np.pi * t))
    w = rng.normal(0, 2e-4, n)
    x = np.r_[0.0, regularized_coulomb_rk4(u + w, rate, 2e-4, 0.01, 1e-3, 3e-4, h=2e-5)[:-1]]
    x = q * np.floor(x / q + 0.5)
    np.savez(tmp_path / "tm.npz", t=t, u=u, x=x)
    rec = convert_table(tmp_path / "tm.npz", {"time": "t", "command": "u", "measured": "x", "units": "rotary"},
                        tmp_path / "tm.mcap")
    nom = _rotary_nominal("coulomb", J=2.6e-4, f_c=0.012, c=1e-4)
    nom["stage"]["drive"]["noise_current_rms"] = 2e-4
    bad = least_squares_check(load_data(rec), load_model(nom))
    assert bad is not None and not bad["inertia"]["agree"] and not bad["agree"]
    rep = diagnose(rec, nom, options=Options(plots=False))
    got = {p["name"]: p["value"] for f in rep["found"] for p in f["params"]}
    assert "m_table" in got, [f["effect"] for f in rep["found"]]
    lsq = rep["least_squares_check"]
    assert abs(got["m_table"] / 2e-4 - 1) < 0.03
    assert abs(got["m_table"] / lsq["inertia"]["value"] - 1) < 0.10
    assert lsq["agree"], lsq
    assert rep["replay"]["floor_ratio"]["improved"] < 1.3 < 5 < rep["replay"]["floor_ratio"]["nominal"]
