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
def test_rate_dependent_slip_makes_same_direction_steps_slower():
    """a = 0.02: the No FI 5 um settling time grows with the same-direction steps (seed: 47.8 ms
    first, 85 ms eighth), while the FI stage's stays flat (seed: 10.5 / 10.2 ms)."""
    nofi = micro.standalone_sequence(5e-6, 0.02, n_forward=4, n_backward=0)
    fi = micro.standalone_sequence(5e-6, 0.02, n_forward=4, n_backward=0, preset=micro.PRESET_FI)
    assert nofi[-1] > 2.0 * nofi[0]
    assert np.all(np.diff(nofi) > 0)
    assert abs(fi[-1] / fi[0] - 1) < 0.2
