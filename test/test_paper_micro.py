"""Micrometre settling study (experiment_runner.paper.micro): the standalone loop, the
rate-dependent GMS slider, and the App. C.1 evidence it was built to test."""
from __future__ import annotations

import math

import numpy as np
import pytest

from experiment_runner.paper import micro


def test_block_update_coulomb_limit():
    """a = 0 is the seed's GMS block: elastic below the limit, clipped at it."""
    assert micro._block_update(0.0, 1e-7, 1e6, 0.2, 0.0, 0.08, 1e-5) == pytest.approx(0.1)
    assert micro._block_update(0.15, 1e-7, 1e6, 0.2, 0.0, 0.08, 1e-5) == 0.2
    assert micro._block_update(-0.15, -1e-7, 1e6, 0.2, 0.0, 0.08, 1e-5) == -0.2


def test_block_relaxation_is_logarithmic():
    """A block held at its Coulomb share relaxes as f = lim (1 - a ln(1 + t/t_c)), t_c = a lim/(k v_r)."""
    k, lim, a, v_r, h = 4.58e4, 1.98, 0.02, 0.08, 1e-5
    t_c = a * lim / (k * v_r)
    f = lim
    checks = {}
    for n in range(1, 20_001):                   # 0.2 s at rest
        f = micro._block_update(f, 0.0, k, lim, a, v_r, h)
        if n in (100, 1_000, 20_000):            # from 1 ms = 90 t_c (backward Euler, h ~ t_c)
            checks[n * h] = f
    for tt, ff in checks.items():
        exact = lim * (1.0 - a * math.log(1.0 + tt / t_c))
        assert abs(ff - exact) < 0.01 * (lim - exact), (tt, ff, exact)
    # after 0.2 s the share has lost a ln(1 + t/t_c) ~ 19 % (a = 0.02): 2.3 a per decade of time
    assert 1 - ff / lim == pytest.approx(a * math.log(1 + 0.2 / t_c), rel=0.01)


def test_saturated_force_grows_with_same_direction_travel():
    f = [micro.saturated_force(n * 5e-6) for n in (1, 4, 8)]
    assert f[0] < f[1] < f[2] <= 5.31 + 1e-9
    assert f[0] == pytest.approx(0.82, abs=0.01)            # blocks 1-4 of Table 4.4


@pytest.mark.slow
def test_standalone_matches_engine_and_rate_independent_steps_get_faster():
    """a = 0: the standalone loop is the engine (No FI, 5 um steps); rate-independent friction
    makes later same-direction steps faster, the opposite of the seed's App. C.1 sequence."""
    eng = micro.engine_sequence(5e-6, n_forward=4, n_backward=0)
    sa = micro.standalone_sequence(5e-6, 0.0, n_forward=4, n_backward=0)
    assert np.all(np.abs(sa - eng) <= 0.5e-3)
    assert sa[-1] < sa[0]


@pytest.mark.slow
def test_rate_and_state_reproduces_the_growth_and_the_5mm_settling():
    """a = b = 0.02: the No FI 5 um settling time grows with the same-direction steps (seed Fig.
    C.2: 47.8 ms first, 85 ms eighth) while the 5 mm move still settles near Table 4.2's 44 ms;
    the FI stage's 5 um steps stay flat (seed 10.5 / 10.2 ms). Creep without aging (b = 0)
    grows too but wrecks the 5 mm move."""
    nofi = micro.standalone_sequence(5e-6, 0.02, n_forward=8, n_backward=0, b=0.02)
    assert nofi[-1] > 2.0 * nofi[0]
    assert nofi[-1] == pytest.approx(0.085, rel=0.2)
    assert micro.standalone_single(5e-3, 0.02, b=0.02) == pytest.approx(0.044, rel=0.15)
    assert micro.standalone_single(5e-3, 0.0) > 0.044 * 1.15                 # GMS alone: 56 ms
    assert micro.standalone_single(5e-3, 0.02, b=0.0) > 0.1                  # creep alone: 122 ms
    fi = micro.standalone_sequence(5e-6, 0.02, n_forward=4, n_backward=0, b=0.02, preset=micro.PRESET_FI)
    assert abs(fi[-1] / fi[0] - 1) < 0.2


def _slide(v, a, b, v_r, n=20_000, h=None, k=4.58e4, lim=1.98):
    """Slide a block at speed v over 20 pre-sliding distances (implicit steps: any h)."""
    h = 20 * lim / k / (v * n) if h is None else h
    f, th = 0.0, 1.0
    for _ in range(n):
        f, th = micro.slider_step(f, th, v * h, k, lim, lim / k, a, b, v_r, h)
    return f, th


def test_rate_and_state_slider_steady_slip_is_coulomb_when_b_equals_a():
    """b = a: steady sliding carries exactly the Coulomb share at any speed (the seed's gross
    motion friction) and v_r drops out; b = 0 (creep only) is rate-dependent."""
    lim = 1.98
    for v in (1e-4, 1e-2):
        f, th = _slide(v, 0.02, 0.02, 0.08)
        assert f == pytest.approx(lim, rel=1e-3)
        assert th == pytest.approx(lim / 4.58e4 / v, rel=1e-2)          # θ_ss = L/v
        assert _slide(v, 0.02, 0.02, 0.8)[0] == pytest.approx(f, rel=1e-9)
    slow, fast = _slide(1e-4, 0.02, 0.0, 0.08)[0], _slide(1e-2, 0.02, 0.0, 0.08)[0]
    assert fast - slow == pytest.approx(0.02 * lim * math.log(100), rel=0.02)   # a ln(v2/v1)


def test_aging_strengthens_a_held_block():
    """After sliding, a block held at rest relaxes less with aging (b = a) than without (b = 0)."""
    k, lim, a, h = 4.58e4, 1.98, 0.02, 1e-5
    f0, th0 = _slide(1e-3, a, a, 0.08)
    f_age, th = f0, th0
    f_creep = f0
    for _ in range(20_000):                                   # 0.2 s held
        f_age, th = micro.slider_step(f_age, th, 0.0, k, lim, lim / k, a, a, 0.08, h)
        f_creep, _ = micro.slider_step(f_creep, 1.0, 0.0, k, lim, lim / k, a, 0.0, 0.08, h)
    assert th > 0.19                                          # θ grows ~ t at rest
    assert lim - f_age < 0.5 * (lim - f_creep)


@pytest.mark.slow
def test_history_dependence_of_a_5um_step():
    """Rate-and-state: a 5 um step after a same-direction 5 mm move is much slower than after an
    opposite one (the slipped blocks relax while the PID holds); the seed's GMS barely cares."""
    gms = micro.history(5e-6, 0.0)
    rs = micro.history(5e-6, 0.02)
    assert abs(gms[0] / gms[1] - 1) < 0.15
    assert rs[0] > 2.0 * rs[1]
    assert 0.062 * 0.85 <= rs.mean() <= 0.062 * 1.3          # Table 4.2 No FI 5 um: 62 ms
