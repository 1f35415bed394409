"""Tests of experiment_runner.core.profiles."""

import math

import numpy as np
import pytest

from experiment_runner.core.profiles import (
    Segment, circle_x, default_move_duration, point_to_point, random_starts,
    sine_sweep, step_sequence)

DT = 1e-4


def test_default_durations_hit_seed_anchor_points():
    assert default_move_duration(5e-3) == pytest.approx(0.125, rel=1e-12)
    assert default_move_duration(5e-6) == pytest.approx(0.0177, rel=1e-12)
    assert default_move_duration(-5e-6) == default_move_duration(5e-6)
    # monotonic power law in between
    assert 0.0177 < default_move_duration(50e-6) < default_move_duration(
        500e-6) < 0.125
    with pytest.raises(ValueError):
        default_move_duration(0.0)


@pytest.mark.parametrize("distance, n_move", [(5e-3, 1250), (-5e-6, 177)])
def test_point_to_point_layout(distance, n_move):
    ref = point_to_point(distance, start=1e-3, pre=0.005, dwell=0.1)
    move, settle = ref.segments
    assert (move.kind, settle.kind) == ("move", "settle")
    assert (move.start, move.stop) == (50, 50 + n_move)
    assert (settle.start, settle.stop) == (move.stop, ref.x.size)
    assert settle.stop - settle.start == 1000
    assert move.target == settle.target == pytest.approx(1e-3 + distance)
    # at rest before, exactly at the target (zero v, a) during settling
    np.testing.assert_array_equal(ref.x[:move.start], 1e-3)
    np.testing.assert_array_equal(ref.x[settle.slice], settle.target)
    for arr in (ref.v, ref.a):
        assert not arr[:move.start].any() and not arr[settle.slice].any()
    # the move actually moves, in the right direction
    assert np.all(np.sign(ref.v[move.start + 1:move.stop]) == np.sign(distance))
    np.testing.assert_allclose(ref.t, np.arange(ref.x.size) * DT)


def test_cycloid_derivatives_match_finite_differences():
    ref = point_to_point(5e-6, dwell=0.01)
    D, T = 5e-6, 0.0177
    v_fd = np.gradient(ref.x, DT)
    a_fd = np.gradient(ref.v, DT)
    inner = slice(1, -1)  # np.gradient is one-sided at the ends
    assert np.max(np.abs(v_fd - ref.v)[inner]) < 1e-3 * 2 * D / T
    # the jerk jumps at the move ends, where the central difference of v
    # is off by half a sample of jerk (~0.9 % of the peak acceleration)
    assert np.max(np.abs(a_fd - ref.a)[inner]) < 1e-2 * 2 * np.pi * D / T**2
    assert ref.v.max() == pytest.approx(2 * D / T, rel=1e-3)
    # smooth at both ends: velocity and acceleration vanish continuously
    move = ref.select("move")[0]
    assert ref.v[move.start] == 0 and ref.a[move.start] == 0
    assert abs(ref.v[move.stop - 1]) < 1e-3 * 2 * D / T


def test_explicit_duration_and_step_shape():
    ref = point_to_point(1e-6, duration=0.01)
    assert ref.segments[0].stop - ref.segments[0].start == 100

    step = point_to_point(1e-6, shape="step", pre=0.002)
    move, settle = step.segments
    assert move.start == move.stop == settle.start == 20
    assert step.x[19] == 0.0 and step.x[20] == 1e-6
    assert not step.v.any() and not step.a.any()
    with pytest.raises(ValueError):
        point_to_point(1e-6, shape="trapezoid")


def test_step_sequence_returns_to_start():
    ref = step_sequence(5e-6, start=2e-3, dwell=0.05)
    settles = ref.select("settle")
    assert [s.index for s in settles] == list(range(16))
    targets = np.array([s.target for s in settles])
    np.testing.assert_allclose(
        targets - 2e-3, 5e-6 * np.r_[np.arange(1, 9), np.arange(7, -1, -1)],
        atol=1e-15)
    assert ref.x[-1] == pytest.approx(2e-3, abs=1e-15)
    for s in settles:
        np.testing.assert_allclose(ref.x[s.slice], s.target, atol=1e-15)
    # each move lasts the default 17.7 ms
    assert {s.stop - s.start for s in ref.select("move")} == {177}


def test_random_starts_reproducible_and_inside_margin():
    a = random_starts(50, (-0.01, 0.01), margin=5e-3, rng_seed=3)
    b = random_starts(50, (-0.01, 0.01), margin=5e-3, rng_seed=3)
    c = random_starts(50, (-0.01, 0.01), margin=5e-3, rng_seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.shape == (50,) and a.min() >= -5e-3 and a.max() < 5e-3
    assert np.ptp(a) > 5e-3  # spread over the allowed range
    with pytest.raises(ValueError):
        random_starts(1, (0.0, 1e-3), margin=6e-4)


def test_circle_x():
    R, speed = 5e-6, 20e-6
    ref = circle_x(R, speed, cycles=2.0, pre=0.01)
    period = 2 * np.pi * R / speed
    track = ref.select("track")[0]
    assert track.start == 100 and track.stop == ref.x.size
    assert (track.stop - track.start - 1) * DT == pytest.approx(2 * period,
                                                                abs=DT)
    assert ref.v.max() == pytest.approx(speed, rel=1e-6)
    assert ref.x.min() == 0.0 and ref.x.max() == pytest.approx(2 * R)
    np.testing.assert_allclose(np.gradient(ref.x, DT)[track.start + 1:-1],
                               ref.v[track.start + 1:-1], atol=1e-3 * speed)
    reversals = ref.select("reversal")
    assert [s.index for s in reversals] == [0, 1, 2]
    for s in reversals:
        v = ref.v[s.slice]
        assert v[0] * v[-1] < 0  # velocity changes sign inside
        assert (s.stop - s.start) * DT == pytest.approx(0.1 * period, abs=2 * DT)
        assert ref.x[s.slice].flat[np.argmin(np.abs(v))] == pytest.approx(
            s.target, abs=1e-3 * R)
    assert [s.target for s in reversals] == [2 * R, 0.0, 2 * R]


def test_sine_sweep_segments_hold_whole_periods():
    freqs = [3.0, 47.0, 333.0, 1234.5]
    ref = sine_sweep(freqs, amplitude=0.11, periods=10, settle_periods=5)
    sines = ref.select("sine")
    assert [s.index for s in sines] == [0, 1, 2, 3]
    for s, f in zip(sines, freqs):
        n = s.stop - s.start
        assert s.frequency == pytest.approx(f, rel=2.5e-3)
        assert n * DT >= 0.02 - DT
        cycles = s.frequency * n * DT
        assert cycles == pytest.approx(round(cycles), abs=1e-9)
        assert round(cycles) >= 10
        x = ref.x[s.slice]
        assert np.max(np.abs(x)) == pytest.approx(0.11, rel=1e-2)
        assert abs(np.mean(x)) < 1e-12  # whole periods
        w = 2 * np.pi * s.frequency  # v, a are the analytic derivatives
        np.testing.assert_allclose(x**2 + (ref.v[s.slice] / w) ** 2, 0.11**2)
        assert np.corrcoef(np.gradient(x), ref.v[s.slice])[0, 1] > 0.99
        np.testing.assert_allclose(ref.a[s.slice], -w**2 * x, atol=1e-9)
    # settle time before each window: 5 periods, at least 50 ms
    assert sines[0].start * DT >= 5 / 3.0
    assert (sines[3].start - sines[2].stop) * DT == pytest.approx(0.05)
    # phase continuity: across each block boundary x moves no more than one
    # sample of the previous sine allows
    for prev, s in zip(sines, sines[1:]):
        jump = abs(ref.x[prev.stop] - ref.x[prev.stop - 1])
        assert jump <= 0.11 * 2 * np.pi * prev.frequency * DT * (1 + 1e-9)
    with pytest.raises(ValueError):
        sine_sweep([6000.0], amplitude=1.0)


def test_reference_is_read_only_and_segment_defaults():
    ref = point_to_point(1e-6)
    with pytest.raises(ValueError):
        ref.x[0] = 1.0
    seg = Segment("move", 0, 3, 1.0, 0)
    assert math.isnan(seg.frequency)
    assert np.arange(5)[seg.slice].tolist() == [0, 1, 2]


def test_triangular_move_is_bang_bang_and_ends_at_rest():
    """Triangular velocity (trapezoid without cruise): +-4D/T^2 acceleration, peak velocity 2D/T at
    mid-move, position, velocity and acceleration consistent, at the target with zero velocity."""
    D, T = 5e-3, 0.125
    ref = point_to_point(D, dwell=0.01, shape="triangular")
    move, settle = ref.segments
    assert (move.stop - move.start) * DT == pytest.approx(T)
    a = ref.a[move.slice]
    np.testing.assert_allclose(np.unique(np.round(a, 9)), [-4 * D / T**2, 4 * D / T**2])
    assert np.all(a[: a.size // 2] > 0) and np.all(a[a.size // 2:] < 0)
    assert ref.v.max() == pytest.approx(2 * D / T, rel=1e-3)
    inner = slice(move.start + 1, move.stop - 1)
    assert np.max(np.abs(np.gradient(ref.x, DT) - ref.v)[inner]) < 2e-3 * 2 * D / T
    assert ref.x[settle.start] == pytest.approx(D) and ref.v[settle.start] == 0
    assert ref.v[move.stop - 1] == pytest.approx(4 * D / T**2 * DT, rel=1e-6)   # one sample before rest
    with pytest.raises(ValueError, match="unknown shape"):
        point_to_point(D, shape="trapezium")
