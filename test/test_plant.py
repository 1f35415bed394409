"""Defining properties of the plant integrator (stage_sim.plant)."""
import numpy as np
import pytest

from experiment_runner.batch import simulate
from experiment_runner.profiles import point_to_point
from stage_sim.config import Stage, load_preset, with_overrides
from stage_sim.plant import PlantSim, SimulationError, build_plant

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
