"""Discretization helpers and the compiled state-space step."""
import numpy as np
import pytest
from scipy import signal

from stage_control.filters import dc_state, discretize, realize, ss_step


def run(ss, u, x=None):
    """Single trial (batch of 1) driven by the sequence ``u``; returns the outputs."""
    A, B, C, D = ss
    x = np.zeros((A.shape[0], 1)) if x is None else x
    ub, y, out = np.zeros(1), np.zeros(1), []
    for v in u:
        ub[0] = v
        ss_step(A, B, C, D, x, ub, y)
        out.append(y[0])
    return np.array(out)


@pytest.mark.slow
def test_ss_step_matches_scipy_any_order():
    rng = np.random.default_rng(1)
    u = rng.normal(size=300)
    for order in (1, 2, 3):
        b, a = signal.butter(order, 2 * np.pi * 300.0, analog=True)
        ss = discretize(b, a, 1e-4, "zoh")
        ref = signal.dlsim((*ss, 1e-4), u)[1][:, 0]
        np.testing.assert_allclose(run(ss, u), ref, rtol=1e-10, atol=1e-12)


def test_prewarped_tustin_puts_resonator_poles_at_w():
    w, dt = 2 * np.pi * 500.0, 1e-4
    A, *_ = discretize([1.0, 0.0], [1.0, 0.0, w * w], dt, "tustin", prewarp=w)
    np.testing.assert_allclose(np.sort(np.angle(np.linalg.eigvals(A))), [-w * dt, w * dt], rtol=1e-12)
    np.testing.assert_allclose(np.abs(np.linalg.eigvals(A)), 1.0, rtol=1e-12)


def test_dc_state_starts_at_rest_and_realize_difference():
    ss = discretize([1.0, 5.0], [1.0, 30.0, 200.0], 1e-3, "backward")
    A, B, C, D = ss
    x = (dc_state(A, B) * 2.0)[:, None]
    assert np.allclose(run(ss, [2.0] * 5, x), 2.0 * 5.0 / 200.0)
    np.testing.assert_allclose(run(realize([1.0, -1.0], [1.0, 0.0]), [1.0, 3.0, 3.0, 0.0]), [1.0, 2.0, 0.0, -3.0])


def test_ss_step_batch_trials_are_independent():
    """Each trial of a batch (trial axis last) follows its own input, as if run alone."""
    rng = np.random.default_rng(2)
    u = rng.normal(size=(200, 3))
    for order in (1, 2, 3):
        b, a = signal.butter(order, 2 * np.pi * 300.0, analog=True)
        A, B, C, D = ss = discretize(b, a, 1e-4, "zoh")
        x, y, ys = np.zeros((order, 3)), np.zeros(3), []
        for uk in u:
            ss_step(A, B, C, D, x, uk, y)
            ys.append(y.copy())
        for j in range(3):
            np.testing.assert_array_equal(np.array(ys)[:, j], run(ss, u[:, j]))
