"""Discretization helpers and the compiled state-space step."""
import numpy as np
from scipy import signal

from stage_control.filters import dc_state, discretize, realize, ss_step


def run(ss, u):
    A, B, C, D = ss
    x = np.zeros(A.shape[0])
    return np.array([ss_step(A, B, C, D, x, v) for v in u])


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
    x = dc_state(A, B) * 2.0
    assert np.allclose([ss_step(A, B, C, D, x, 2.0) for _ in range(5)], 2.0 * 5.0 / 200.0)
    np.testing.assert_allclose(run(realize([1.0, -1.0], [1.0, 0.0]), [1.0, 3.0, 3.0, 0.0]), [1.0, 2.0, 0.0, -3.0])
