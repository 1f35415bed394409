"""Defining properties of the friction models (stage_sim.friction)."""
import numpy as np
import pytest

from stage_sim.friction import GMS, CoulombViscous, Dahl, LuGre, dahl_update, virgin_curve

F_C = 5.31          # Table 4.3
K_SIGMA = 2.19e6    # Table 4.3


def _cycle(amplitude, n=2000):
    """0 -> +A -> -A -> +A displacement history [m]."""
    return np.concatenate([np.linspace(0, amplitude, n), np.linspace(amplitude, -amplitude, 2 * n),
                           np.linspace(-amplitude, amplitude, 2 * n)])


def test_dahl_saturates_at_coulomb_force():
    f = Dahl(K_SIGMA, F_C).drive(_cycle(50e-6))
    assert f.max() == pytest.approx(F_C, rel=1e-9)
    assert f.min() == pytest.approx(-F_C, rel=1e-9)
    assert np.all(np.abs(f) <= F_C)


def test_dahl_hysteresis_loop_closes():
    """Cycling converges to a closed loop (each cycle contracts the difference by
    exp(-4 k_sigma A / F_C)) that encloses area (hysteresis)."""
    amp, n = 5e-6, 2000
    down, up = np.linspace(amp, -amp, 2 * n), np.linspace(-amp, amp, 2 * n)
    x = np.concatenate([np.linspace(0, amp, n)] + [down, up] * 4)
    f = Dahl(K_SIGMA, F_C).drive(x)
    third, fourth = f[9 * n:13 * n], f[13 * n:17 * n]
    np.testing.assert_allclose(fourth, third, atol=1e-6 * F_C)
    assert abs(f[9 * n - 1] - f[5 * n - 1]) < np.exp(-4 * K_SIGMA * amp / F_C) * abs(f[5 * n - 1] - f[n - 1]) * 1.05
    on_down, on_up = f[10 * n], f[12 * n]                         # both at x ~ 0
    assert on_up - on_down > 1.0 and on_up == pytest.approx(-on_down, rel=1e-3)


def test_dahl_initial_stiffness_and_exact_splitting():
    d = 1e-9
    assert dahl_update(0.0, d, K_SIGMA, F_C, 1.0) == pytest.approx(K_SIGMA * d, rel=1e-3)
    # exact in the displacement domain: one increment equals many small ones
    one = dahl_update(0.3, 2e-6, K_SIGMA, F_C, 1.0)
    many = 0.3
    for _ in range(1000):
        many = dahl_update(many, 2e-9, K_SIGMA, F_C, 1.0)
    assert one == pytest.approx(many, rel=1e-12)


@pytest.mark.parametrize("shape", [0.5, 2.0])
def test_dahl_shape_factor_matches_ode(shape):
    """Closed form for nu != 1 against a fine Euler integration of Eq. 1.1."""
    x_end, n = 3e-6, 200_000
    f = 0.0
    dx = x_end / n
    for _ in range(n):
        f += dx * K_SIGMA * max(0.0, 1 - f / F_C) ** shape
    assert dahl_update(0.0, x_end, K_SIGMA, F_C, shape) == pytest.approx(f, rel=1e-3)


def test_gms_virgin_curve_from_blocks():
    """Virgin curve = sum of elastic-perfectly-plastic blocks (Table 4.4)."""
    k = [1.34e6, 4.93e5, 8.61e4, 5.55e4, 5.87e4, 2.42e4, 3.85e4, 1.75e4, 2.69e4, 4.58e4]
    a = [0.0136, 0.0568, 0.037, 0.047, 0.0805, 0.0508, 0.1139, 0.0732, 0.1540, 0.3733]
    x, f = virgin_curve(GMS(k, a, F_C), 200e-6, 400)
    expected = np.minimum(np.multiply.outer(x, k), np.array(a) * F_C).sum(axis=1)
    np.testing.assert_allclose(f, expected, rtol=1e-12, atol=1e-12)
    assert f[-1] == pytest.approx(sum(a) * F_C)


def test_gms_reversal_has_initial_stiffness_of_all_blocks():
    k, a = [1e6, 1e5], [0.3, 0.7]
    g = GMS(k, a, F_C)
    g.drive(np.linspace(0, 1e-3, 50))                  # gross sliding: all blocks slipping
    f0 = g.force()[0]
    f1 = g.step(-1e-9)[0]
    assert (f0 - f1) / 1e-9 == pytest.approx(sum(k), rel=1e-9)


def test_lugre_steady_state_is_stribeck_plus_viscous():
    p = dict(sigma0=1e6, sigma1=50.0, sigma2=20.0, f_c=1.0, f_s=1.5, v_s=1e-3)
    for v in (2e-4, 1e-3, 1e-2):
        m = LuGre(**p)
        dt = 1e-4
        f = m.drive(np.arange(2000) * v * dt, dt=dt)
        g = p["f_c"] + (p["f_s"] - p["f_c"]) * np.exp(-(v / p["v_s"]) ** 2)
        assert f[-1] == pytest.approx(g + p["sigma2"] * v, rel=1e-6)


def test_coulomb_viscous_force():
    m = CoulombViscous(2.0, viscous=10.0, n_trials=2)
    f = m.step(np.array([1e-6, -2e-6]), dt=1e-4)
    np.testing.assert_allclose(f, [2.0 + 10 * 0.01, -2.0 - 10 * 0.02])


def test_batch_of_trials_is_independent():
    d = Dahl(K_SIGMA, F_C, n_trials=3)
    x = np.stack([np.linspace(0, s, 100) for s in (1e-7, 1e-6, -1e-5)], axis=1)
    f = d.drive(x)
    for i, s in enumerate((1e-7, 1e-6, -1e-5)):
        np.testing.assert_allclose(f[:, i], Dahl(K_SIGMA, F_C).drive(np.linspace(0, s, 100)))
