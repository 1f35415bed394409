"""Micrometre settling study (experiment_runner.apps.paper.micro): the standalone loop and the App. C.1
evidence it was built to test. The slider kernels are the law's: test/test_friction_rate_state.py."""
from __future__ import annotations


import numpy as np
import pytest

from experiment_runner.apps.paper import micro


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


@pytest.mark.slow
def test_history_dependence_of_a_5um_step():
    """Rate-and-state: a 5 um step after a same-direction 5 mm move is much slower than after an
    opposite one (the slipped blocks relax while the PID holds); the seed's GMS barely cares."""
    gms = micro.history(5e-6, 0.0)
    rs = micro.history(5e-6, 0.02)
    assert abs(gms[0] / gms[1] - 1) < 0.15
    assert rs[0] > 2.0 * rs[1]
    assert 0.062 * 0.85 <= rs.mean() <= 0.062 * 1.3          # Table 4.2 No FI 5 um: 62 ms
