"""Defining properties of the plant integrator (stage_sim.plant)."""
import numpy as np
import pytest

from experiment_runner.core.batch import simulate
from experiment_runner.core.profiles import point_to_point
from stage_sim.config import Stage, load_preset, with_overrides
from stage_sim.plant import PlantSim, SimulationError
from stage_sim.plant_model import build_plant

DRIVE = dict(force_constant=1.0, peak_force=100.0, continuous_force=100.0)
TRAVEL = dict(min=-0.05, max=0.05)


def _stage(**kw):
    base = dict(table=dict(mass=1.0), drive=DRIVE, encoder=dict(resolution=0.0), travel=TRAVEL)
    base.update(kw)
    return Stage.model_validate(base)


def _settle(sim, force, steps, mode=1.0):
    for _ in range(steps):
        sim.step(force, mode=mode)


def _fi_stage(k_fi, k_f):
    """Table on an FI joint to a bearing held by a linear friction spring (one GMS block)."""
    return _stage(bearings=[dict(mass=0.2, joint=dict(stiffness=k_fi, damping=50.0),
                                 friction=dict(model="gms", k=[k_f], alpha=[1.0], f_c=1e6,
                                               viscous=300.0))])


def _static_stiffness(k_fi, k_f, force=0.1):
    sim = PlantSim(build_plant(_fi_stage(k_fi, k_f)))
    _settle(sim, force, 6000)
    return force / sim.positions[0, 0]


def test_fi_series_stiffness_eq_4_1():
    k_fi, k_f = 4e4, 1e6
    k_c = _static_stiffness(k_fi, k_f)
    assert k_c == pytest.approx(k_fi * k_f / (k_fi + k_f), rel=1e-3)


def test_fi_sensitivity_eq_4_2():
    k_fi, k_f = 4e4, 1e6
    kappa = (_static_stiffness(k_fi, 1.01 * k_f) - _static_stiffness(k_fi, 0.99 * k_f)) / (0.02 * k_f)
    eta = k_fi / k_f
    assert kappa == pytest.approx((eta / (1 + eta)) ** 2, rel=0.02)


def _sai_stage():
    return _stage(table=dict(mass=1.4),
                  bearings=[dict(mass=0.3, joint=dict(stiffness=5e4, damping=50.0),
                                 friction=dict(model="dahl", k_sigma=2.19e6, f_c=5.31))],
                  sai=dict(lock_stiffness=1e8, lock_damping=200.0, lock_capacity=50.0,
                           impact_impulse=0.0, impact_duration=1e-3))


@pytest.mark.slow
def test_sai_lock_stores_deflection_and_unlock_releases_it():
    sim = PlantSim(build_plant(_sai_stage()))
    _settle(sim, 1.0, 5000, mode=1.0)                       # compliant: flexure deflects
    defl = lambda: sim.positions[0, 0] - sim.positions[1, 0]
    d0 = defl()
    assert d0 == pytest.approx(1.0 / 5e4, rel=0.05)
    _settle(sim, 1.0, 500, mode=0.0)                        # switch stiff: lock engages
    _settle(sim, 0.0, 5000, mode=0.0)                       # remove the force: lock holds
    assert defl() == pytest.approx(d0, rel=0.01)
    _settle(sim, 0.0, 8000, mode=1.0)                       # unlock: stored deflection released
    assert abs(defl()) < 0.05 * d0


def test_sai_impact_excites_motion_and_cushioning_reduces_it():
    def peak(cushioning):
        st = _sai_stage().model_copy(update={"sai": _sai_stage().sai.model_copy(
            update={"impact_impulse": 2e-3, "cushioning": cushioning})})
        sim = PlantSim(build_plant(st))
        _settle(sim, 0.0, 100, mode=1.0)
        x = []
        for _ in range(200):
            sim.step(0.0, mode=0.0)
            x.append(sim.positions[0, 0])
        return np.ptp(x)
    assert peak(0.0) > 1e-8
    assert peak(0.9) == pytest.approx(0.1 * peak(0.0), rel=0.15)


def test_seeded_noise_is_deterministic():
    preset = load_preset("fi_stage")
    ref = point_to_point(5e-6, dwell=0.05)
    a = simulate(preset, ref.x, ref.v, n_trials=3, seeds=[1, 2, 3])
    b = simulate(preset, ref.x, ref.v, n_trials=3, seeds=[1, 2, 3])
    c = simulate(preset, ref.x, ref.v, n_trials=3, seeds=[4, 5, 6])
    np.testing.assert_array_equal(a.y, b.y)
    assert not np.array_equal(a.y, c.y)
    # a trial's result does not depend on the batch it runs in
    d = simulate(preset, ref.x, ref.v, n_trials=1, seeds=[2])
    np.testing.assert_array_equal(d.y[0], a.y[1])


def test_encoder_quantization():
    preset = load_preset("fi_stage")
    ref = point_to_point(5e-6, dwell=0.02)
    y = simulate(preset, ref.x, ref.v).y
    q = preset.stage.encoder.resolution
    assert q == pytest.approx(4.88e-9)
    np.testing.assert_allclose(y / q, np.round(y / q), atol=1e-6)


def test_divergence_stops_with_reason():
    preset = with_overrides(load_preset("als130h"), {
        "controller.pid.kd": 1e5, "stage.drive.peak_force": 1e9, "stage.drive.continuous_force": 1e9})
    ref = point_to_point(50e-9, shape="step", dwell=0.05)
    with pytest.raises(SimulationError, match="diverged|travel"):
        simulate(preset, ref.x, ref.v)


def test_leaving_travel_stops_with_reason():
    sim = PlantSim(build_plant(_stage()))
    with pytest.raises(SimulationError, match="left the travel"):
        _settle(sim, 50.0, 2000)


def test_force_saturation():
    sim = PlantSim(build_plant(_stage()))
    sim.step(1e4)                                           # peak force 100 N on 1 kg
    assert sim.velocities[0, 0] == pytest.approx(100.0 * 1e-4, rel=1e-9)


def test_coulomb_stiction_and_sliding():
    st = _stage(table_friction=dict(model="coulomb", f_c=1.0, f_s=1.5))
    sim = PlantSim(build_plant(st))
    _settle(sim, 1.2, 100)                                  # below static force: sticks
    assert sim.positions[0, 0] == 0.0
    _settle(sim, 1.6, 100)                                  # breaks away, slides at F_C
    v1 = sim.velocities[0, 0]
    assert v1 == pytest.approx((1.6 - 1.0) * 100 * 1e-4, rel=1e-6)


def test_structural_mode_frequency():
    st = _stage(modes=[dict(frequency=400.0, damping_ratio=0.01, mass_ratio=0.1)])
    sim = PlantSim(build_plant(st))
    x = []
    sim.step(1.0)
    for _ in range(4000):
        sim.step(0.0)
        x.append(sim.positions[0, 0] - sim.positions[1, 0])
    spec = np.abs(np.fft.rfft(np.asarray(x) - np.mean(x)))
    f = np.fft.rfftfreq(len(x), 1e-4)
    assert f[np.argmax(spec)] == pytest.approx(400.0 * np.sqrt(1.1), abs=3.0)


def test_substeps_converge():
    preset = load_preset("fi_stage_nofi")
    fine = with_overrides(preset, {"simulation.max_omega_h": 0.02})
    ref = point_to_point(5e-6, dwell=0.05)
    a = simulate(preset, ref.x, ref.v, seeds=[0])
    b = simulate(fine, ref.x, ref.v, seeds=[0])
    err = np.max(np.abs(a.x_table - b.x_table))
    assert err < 0.02 * 5e-6


# --------------------------------------------------------------------------- table forces, friction variations
def test_variations_off_by_default():
    pm = build_plant(load_preset("fi_stage_nofi").stage)
    assert not pm.table_force and not pm.fr_var.any()
    assert pm.ripple.shape == (0, 3) and pm.periodic.shape == (0, 3)


def test_force_offset_equals_external_force_and_bypasses_the_drive():
    """``stage.force_offset`` and the external input of plant_step (PlantInputs.f_ext) are the same table
    force; neither passes through the drive (here: 3 samples of delay)."""
    drive = dict(DRIVE, delay_samples=3)
    a = PlantSim(build_plant(_stage(force_offset=0.5, drive=drive)))
    b = PlantSim(build_plant(_stage(drive=drive)))
    for _ in range(20):
        a.step(0.0)
        b.step(0.0, f_ext=0.5)
    np.testing.assert_array_equal(a.state.z, b.state.z)
    t = 20 * 1e-4
    assert a.positions[0, 0] == pytest.approx(0.5 * 0.5 * t * t, rel=1e-9)   # no delay: F/m from t = 0


def test_force_ripple_and_periodic_force():
    """Frictionless table: a ripple pushes with A sin(2 pi x0/p + phase) at rest at x0; a
    fixed-frequency force gives v(t) = A/(m w) (cos phase - cos(w t + phase))."""
    x0, per, amp = 1.3e-4, 4e-4, 0.2
    sim = PlantSim(build_plant(_stage(force_ripple=[dict(amplitude=amp, period=per, phase=0.3)])), x0=x0)
    sim.step(0.0)
    assert sim.velocities[0, 0] == pytest.approx(amp * np.sin(2 * np.pi * x0 / per + 0.3) * 1e-4, rel=1e-6)
    f, ph = 37.0, 0.4
    sim = PlantSim(build_plant(_stage(periodic_force=[dict(amplitude=amp, frequency=f, phase=ph)])))
    w = 2 * np.pi * f
    for k in range(1, 301):
        sim.step(0.0)
        t = k * 1e-4
        assert sim.velocities[0, 0] == pytest.approx(amp / w * (np.cos(ph) - np.cos(w * t + ph)), abs=1e-3 * amp / w)


def test_direction_dependent_coulomb_and_viscous_friction():
    """Sliding at steady state: F = F_C+- + c+- |v| with F_C+- = f_c +- dF/2, c+- = c +- dc/2."""
    fr = dict(model="coulomb", f_c=1.0, viscous=200.0, f_c_difference=0.4, viscous_difference=100.0)
    for sign, fc, c in ((1, 1.2, 250.0), (-1, 0.8, 150.0)):
        sim = PlantSim(build_plant(_stage(table_friction=fr)))
        _settle(sim, sign * 3.0, 3000)
        assert abs(sim.velocities[0, 0]) == pytest.approx((3.0 - fc) / c, rel=1e-6)


def test_position_dependent_friction_level():
    """F_C(x) = f_c + g (x - x_c): at x0 the stage sticks below F_C(x0) and slides above it;
    a Dahl element's force scales the same way."""
    fr = dict(model="coulomb", f_c=1.0, f_c_gradient=100.0, position_center=0.002)
    x0 = 0.012                                               # F_C(x0) = 2 N
    for force, moves in ((1.9, False), (2.1, True)):
        sim = PlantSim(build_plant(_stage(table_friction=fr)), x0=x0)
        _settle(sim, force, 50)
        assert (sim.positions[0, 0] != x0) == moves
    # Dahl: near x0 the element is a Dahl element of twice the force (F_C and k_sigma doubled)
    x = []
    for fr in (dict(model="dahl", k_sigma=1e6, f_c=1.0, f_c_gradient=100.0, position_center=0.002, viscous=50.0),
               dict(model="dahl", k_sigma=2e6, f_c=2.0, viscous=50.0)):
        sim = PlantSim(build_plant(_stage(table_friction=fr)), x0=x0)
        _settle(sim, 1.5, 2000)                              # below 2 N: pre-motion only
        x.append(sim.positions[0, 0] - x0)
    assert 0 < x[0] < 1e-5 and x[0] == pytest.approx(x[1], rel=2e-3)


def test_friction_variation_is_validated():
    from stage_sim.config import ConfigError, preset_from_dict
    data = load_preset("fi_stage_nofi").model_dump()
    data["stage"]["bearings"][0]["friction"]["f_c_difference"] = 6.0     # f_c = 2.655
    with pytest.raises(ConfigError, match=r"bearings\.0\.friction.*f_c_difference"):
        preset_from_dict(data, "p.yaml")
    data = load_preset("fi_stage_nofi").model_dump()
    data["stage"]["force_ripple"] = [dict(amplitude=0.1, period=0.0)]
    with pytest.raises(ConfigError, match=r"force_ripple\.0\.period"):
        preset_from_dict(data, "p.yaml")
    data = load_preset("fi_stage_nofi").model_dump()
    data["controller"]["feedforward"] = {"friction": dict(data["stage"]["bearings"][0]["friction"],
                                                          f_c_gradient=1.0)}
    with pytest.raises(ConfigError, match="feedforward.*no friction variation"):
        preset_from_dict(data, "p.yaml")
