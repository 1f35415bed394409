"""The batch engine and sample-by-sample stepping (as the ROS nodes do) give the
same trajectories, bit for bit: one implementation of each algorithm, two drivers."""
import numpy as np
import pytest

from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.profiles import point_to_point
from stage_control.dither import dither_step
from stage_control.sai import sai_step
from stage_control.servo import servo_step
from stage_sim.config import load_preset
from stage_sim.plant import PlantInputs, plant_step


def _step_by_step(preset, x_ref, v_ref, seed):
    """One trial, one component call per sample, B = 1 arrays (the node adapters' way), from
    the models and initial state the nodes use."""
    m = Models.from_preset(preset)
    one = lambda v: np.array([v], float)
    init = m.initial_state([x_ref[0]])
    plant, meas, ss, ds, sa = init.plant, init.meas, init.servo, init.dither, init.sai
    seeds, status = np.array([seed], np.int64), np.zeros(1, np.int64)
    y = meas[0].copy()
    mode, xc, u, dout = one(0), one(0), one(0), np.zeros((2, 1))
    ys = np.empty(len(x_ref))
    for k in range(len(x_ref)):
        ka = min(k + m.lead, len(x_ref) - 1)
        sai_step(m.sai, sa, np.zeros(0), k, one(v_ref[k]), one(v_ref[ka]), mode, xc)
        xr = one(x_ref[k] + xc[0])
        dither_step(m.dither, ds, k, xr, one(v_ref[k]), y, dout)
        servo_step(m.servo, ss, xr, one(v_ref[k]), y, u)
        ys[k] = y[0]
        plant_step(m.plant, plant, PlantInputs(u, dout[0].copy(), dout[1].copy(), mode, np.zeros(0)), k, seeds,
                   meas, status)
        assert status[0] == 0
        y = meas[0].copy()
    return ys


@pytest.mark.parametrize("name", ["fi_stage", "fi_stage_nofi_dob", "van_sim_asym", "sai_stage"])
def test_stepping_equals_batch(name):
    preset = load_preset(name)
    ref = point_to_point(5e-6, dwell=0.03, dt=1.0 / preset.controller.rate)
    x0 = 1.3e-3
    batch = simulate(preset, ref.x, ref.v, n_trials=3, x0=[0.0, x0, -x0], seeds=[7, 8, 9])
    single = _step_by_step(preset, ref.x + x0, ref.v, seed=8)
    np.testing.assert_array_equal(single, batch.y[1])
    assert np.ptp(single) > 4e-6          # the trial really moved


def test_batch_external_force_is_a_table_force():
    """The batch engine's known external force (``f_ext``, the closed-loop replay's
    ``/stage/external_force``): a constant 0.2 N is bit for bit the preset's
    ``stage.force_offset`` of 0.2 N, and zeros are bit for bit no input."""
    p = load_preset("fi_stage_nofi")
    ref = point_to_point(5e-6, dt=1.0 / p.controller.rate, dwell=0.05)
    none = simulate(p, ref.x, ref.v, n_trials=2)
    zeros = simulate(p, ref.x, ref.v, n_trials=2, f_ext=np.zeros(len(ref.x)))
    assert np.array_equal(none.y, zeros.y) and np.array_equal(none.u, zeros.u)
    offset = simulate(p.model_copy(update={"stage": p.stage.model_copy(update={"force_offset": 0.2})}),
                      ref.x, ref.v, n_trials=2)
    ext = simulate(p, ref.x, ref.v, n_trials=2, f_ext=0.2)
    assert np.array_equal(offset.y, ext.y) and np.array_equal(offset.u, ext.u)
    assert np.abs(ext.y - none.y).max() > 1e-8                       # the force moved the stage
