"""Reference profiles for nanopositioning experiments (SI units).

Every generator returns a :class:`Reference`: position ``x`` [m], velocity
``v`` [m/s] and acceleration ``a`` [m/s^2] sampled every ``dt`` seconds
(default 1e-4 s, the 10 kHz control rate of the seed's dSPACE controller),
plus a list of :class:`Segment` objects (half-open sample-index ranges) that
metrics use to cut a record into trials, e.g. the "move" and "settle" part of
each point-to-point step (seed Sec. 3.4.1, Fig. 3.13).

All durations are rounded to a whole number of samples. A reference is at most
:data:`MAX_SAMPLES` long: a longer one is refused (:class:`~stage_sim.validation.ConfigError`
naming the duration, its sample count and the limit) before anything is allocated.
"""

from dataclasses import dataclass, field
import math

import numpy as np

from stage_sim.validation import ConfigError

DT = 1e-4
"""Default sample time [s] (10 kHz control rate)."""

_T_5MM = 0.125
"""Duration [s] of the 5 mm point-to-point move (seed Sec. 3.4.1)."""
_T_5UM = 0.0177
"""Duration [s] of the 5 um point-to-point move (seed App. C.1)."""
_DURATION_EXPONENT = math.log(_T_5MM / _T_5UM) / math.log(1000.0)


@dataclass(frozen=True)
class Segment:
    """A labelled half-open range ``[start, stop)`` of sample indices.

    Attributes
    ----------
    kind : str
        Label, e.g. ``"move"``, ``"settle"``, ``"track"``, ``"reversal"``
        or ``"sine"``.
    start, stop : int
        Sample indices; the segment covers ``slice(start, stop)``.
    target : float
        Position [m] (or signal value) the reference holds or heads for in
        this segment, e.g. the end position of a step.
    index : int
        Ordinal of the segment among those of its kind (0-based step number,
        reversal number or frequency number).
    frequency : float
        Excitation frequency [Hz] of a ``"sine"`` segment, nan otherwise.

    Examples
    --------
    >>> seg = Segment("settle", 10, 20, 5e-3, 0)
    >>> seg.slice
    slice(10, 20, None)
    """

    kind: str
    start: int
    stop: int
    target: float
    index: int
    frequency: float = math.nan

    @property
    def slice(self):
        """``slice(start, stop)`` for indexing sampled arrays."""
        return slice(self.start, self.stop)


@dataclass(frozen=True, eq=False)
class Reference:
    """A sampled reference trajectory (arrays are read-only).

    Attributes
    ----------
    t : numpy.ndarray
        Time [s], ``t[k] = k * dt``.
    x : numpy.ndarray
        Position [m] (or excitation signal, see :func:`sine_sweep`).
    v : numpy.ndarray
        Time derivative of ``x`` [m/s].
    a : numpy.ndarray
        Second time derivative of ``x`` [m/s^2].
    dt : float
        Sample time [s].
    segments : list of Segment
        Labelled index ranges.

    Examples
    --------
    >>> ref = point_to_point(5e-6)
    >>> [s.kind for s in ref.select("settle")]
    ['settle']
    """

    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    dt: float
    segments: list[Segment] = field(default_factory=list)

    def __post_init__(self):
        for name in ("t", "x", "v", "a"):
            arr = np.array(getattr(self, name), dtype=float)
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    def select(self, kind: str) -> list[Segment]:
        """Segments of the given ``kind``, in order."""
        return [s for s in self.segments if s.kind == kind]


def default_move_duration(distance: float) -> float:
    """Duration [s] of a point-to-point move of the given size.

    The seed gives two anchor points: a 5 mm move lasts 125 ms (Sec. 3.4.1,
    total duration of the reference of Fig. 3.13) and a 5 um move lasts
    17.7 ms (App. C.1). They are joined by the power law
    ``T = 0.125 s * (|D| / 5 mm)**p`` with
    ``p = log(0.125 / 0.0177) / log(1000) ~= 0.283``, which passes through
    both anchors (the distance ratio between them is 1000).

    Parameters
    ----------
    distance : float
        Step size D [m]; the sign is ignored and it must be nonzero.

    Returns
    -------
    float
        Move duration T [s].

    Examples
    --------
    >>> round(default_move_duration(5e-3), 6)
    0.125
    >>> round(default_move_duration(-5e-6), 6)
    0.0177
    """
    if distance == 0:
        raise ValueError("distance must be nonzero")
    return _T_5MM * (abs(distance) / 5e-3) ** _DURATION_EXPONENT


MAX_SAMPLES = 50_000_000
"""Longest reference [samples]: 5000 s at 10 kHz, 400 MB per signal; a trial's batch run holds
about a dozen such signals."""


def _samples(duration: float, dt: float, what: str | None = None) -> int:
    """``duration`` [s] in whole samples of ``dt``; with ``what`` (its name in errors) checked
    against :data:`MAX_SAMPLES` before anything of that length is allocated."""
    n = duration / dt
    if what is not None:
        _check_length(n, dt, f"{what} {duration:g} s")
    return int(round(n))


def _check_length(n: float, dt: float, what: str) -> None:
    """Refuse a reference of ``n`` samples beyond :data:`MAX_SAMPLES` (a memory estimate)."""
    if not n <= MAX_SAMPLES:
        raise ConfigError(f"{what} at {1 / dt:g} Hz is {n:.3g} samples ({8 * n / 2**30:.3g} GiB per signal); "
                          f"a reference holds at most {MAX_SAMPLES:.3g} samples ({MAX_SAMPLES * dt:g} s, "
                          f"{8 * MAX_SAMPLES / 2**30:.2g} GiB per signal)")


def _cycloid(distance: float, n: int, dt: float):
    """Cycloidal rest-to-rest move sampled at k = 0..n-1 (s = k/n < 1)."""
    T = n * dt
    s = np.arange(n) / n
    w = 2.0 * np.pi * s
    x = distance * (s - np.sin(w) / (2.0 * np.pi))
    v = distance / T * (1.0 - np.cos(w))
    a = 2.0 * np.pi * distance / T**2 * np.sin(w)
    return x, v, a


def _triangular(distance: float, n: int, dt: float):
    """Triangular-velocity (bang-bang acceleration) rest-to-rest move sampled at k = 0..n-1.

    The trapezoidal-velocity profile with no constant-velocity phase: ``a = +4D/T**2`` for
    ``t < T/2`` and ``-4D/T**2`` after, the least peak acceleration of any trapezoid of
    duration ``T``; the acceleration steps at the start, middle and end (unbounded jerk).
    """
    T = n * dt
    t = np.arange(n) * dt
    A = 4.0 * distance / T**2
    first = t < 0.5 * T
    tau = T - t
    x = np.where(first, 0.5 * A * t**2, distance - 0.5 * A * tau**2)
    v = np.where(first, A * t, A * tau)
    a = np.where(first, A, -A)
    return x, v, a


_MOVES = {"cycloidal": _cycloid, "triangular": _triangular}
SHAPES = ("cycloidal", "triangular", "step")
"""Point-to-point move shapes (see :func:`point_to_point`)."""


def steps_reference(distances, start, pre, dwell, dt, duration, shape) -> Reference:
    """Concatenate rest, then per step a move and a dwell at rest."""
    if shape not in SHAPES:
        raise ValueError(f"unknown shape {shape!r}")
    n_pre, n_dwell = _samples(pre, dt, "pre"), _samples(dwell, dt, "dwell")
    n_moves = [0 if shape == "step" else
               _samples(default_move_duration(d) if duration is None else duration, dt, "move duration")
               for d in distances]
    if shape != "step" and min(n_moves, default=1) < 1:
        raise ValueError("move duration is shorter than one sample")
    _check_length(n_pre + sum(n_moves) + len(n_moves) * n_dwell, dt,
                  f"{len(n_moves)} move(s) with dwell {dwell:g} s")
    xs = [np.full(n_pre, float(start))]
    vs, as_ = [np.zeros(n_pre)], [np.zeros(n_pre)]
    segments, k, pos = [], n_pre, float(start)
    for i, (d, n_move) in enumerate(zip(distances, n_moves)):
        if shape == "step":
            x, v, a = (np.empty(0),) * 3
        else:
            x, v, a = _MOVES[shape](d, n_move, dt)
        xs += [pos + x, np.full(n_dwell, pos + d)]
        pos += d
        vs += [v, np.zeros(n_dwell)]
        as_ += [a, np.zeros(n_dwell)]
        segments.append(Segment("move", k, k + n_move, pos, i))
        segments.append(Segment("settle", k + n_move, k + n_move + n_dwell,
                                pos, i))
        k += n_move + n_dwell
    x = np.concatenate(xs)
    return Reference(np.arange(x.size) * dt, x, np.concatenate(vs),
                     np.concatenate(as_), dt, segments)


def point_to_point(distance: float, duration: float | None = None,
                   dwell: float = 0.25, dt: float = DT, start: float = 0.0,
                   pre: float = 0.005, shape: str = "cycloidal") -> Reference:
    """One rest-to-rest move (seed Fig. 3.13).

    The record is ``pre`` seconds at ``start``, the move, then ``dwell``
    seconds at ``start + distance`` (the settling portion). The cycloidal
    move is ``x = D (s - sin(2 pi s) / (2 pi))`` with ``s = t / T``, which
    has zero velocity and acceleration at both ends; peak velocity is
    ``2 D / T`` and peak acceleration ``2 pi D / T**2``.

    Parameters
    ----------
    distance : float
        Step size D [m] (signed).
    duration : float, optional
        Move duration T [s]; default :func:`default_move_duration`. Ignored
        for ``shape="step"``.
    dwell : float
        Time at rest after the move [s].
    dt : float
        Sample time [s].
    start : float
        Initial position [m].
    pre : float
        Time at rest before the move [s].
    shape : {"cycloidal", "triangular", "step"}
        ``"triangular"`` is the trapezoidal-velocity move without a cruise
        phase: constant acceleration ``4 D / T**2`` for the first half of the
        move and its negative for the second (peak velocity ``2 D / T``, as
        the cycloid's, but the acceleration steps at both ends: the reference
        stops with a sudden end of deceleration). ``"step"`` jumps to the target at ``t = pre`` (ideal step of the
        Appendix A simulations); its ``v`` and ``a`` are zero everywhere
        (the impulses at the jump are not representable) and its "move"
        segment is empty.

    Returns
    -------
    Reference
        With segments ``Segment("move", ..., index=0)`` and
        ``Segment("settle", ..., index=0)``; the settle segment starts at
        the first sample where the reference equals the target.

    Examples
    --------
    >>> ref = point_to_point(5e-3)
    >>> move, settle = ref.segments
    >>> (move.stop - move.start) * ref.dt, float(ref.x[settle.start])
    (0.125, 0.005)
    """
    return steps_reference([distance], start, pre, dwell, dt, duration, shape)


def step_sequence(distance: float, n_forward: int = 8, n_backward: int = 8,
                  start: float = 0.0, dwell: float = 0.25, dt: float = DT,
                  duration: float | None = None, pre: float = 0.005,
                  shape: str = "cycloidal") -> Reference:
    """``n_forward`` steps of ``distance``, then ``n_backward`` back.

    The stepping test of seed App. C.1 (8 forward then 8 backward steps of
    the same size). Each step is a :func:`point_to_point` move followed by
    ``dwell`` seconds at rest.

    Parameters
    ----------
    distance : float
        Step size [m] (signed: the first steps go in this direction).
    n_forward, n_backward : int
        Number of forward and backward steps.
    start : float
        Initial position [m].
    dwell : float
        Time at rest after each move [s].
    dt : float
        Sample time [s].
    duration : float, optional
        Duration of each move [s]; default :func:`default_move_duration`.
    pre : float
        Time at rest before the first move [s].
    shape : {"cycloidal", "triangular", "step"}
        Move shape, see :func:`point_to_point`.

    Returns
    -------
    Reference
        With one "move" and one "settle" segment per step; ``index`` is the
        0-based step number.

    Examples
    --------
    >>> ref = step_sequence(5e-6)
    >>> [round(s.target * 1e6) for s in ref.select("settle")][6:10]
    [35, 40, 35, 30]
    """
    _check_length(n_forward + n_backward, dt, f"{n_forward} + {n_backward} steps (one sample each at least)")
    distances = [distance] * n_forward + [-distance] * n_backward
    return steps_reference(distances, start, pre, dwell, dt, duration, shape)


def random_starts(n: int, travel: tuple[float, float], margin: float = 0.0,
                  rng_seed: int | None = 0, extent: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Random start positions [m], uniform in ``travel`` shrunk by ``margin`` and by the
    reference's ``extent``, so that the whole reference stays inside the travel.

    Used for repeated trials "at random positions of the table" (seed
    Sec. 4.4.1, 50 trials).

    Parameters
    ----------
    n : int
        Number of positions.
    travel : (float, float)
        Travel range ``(min, max)`` [m].
    margin : float
        Distance [m] kept free at both ends, e.g. the step size.
    rng_seed : int or None
        Seed of :func:`numpy.random.default_rng`; the same seed gives the
        same positions.
    extent : (float, float)
        Lowest and highest position of the reference relative to its start
        [m] (``(ref.x.min(), ref.x.max())`` of a reference starting at 0).

    Returns
    -------
    numpy.ndarray
        Shape ``(n,)``, values in ``[min + margin - min(0, extent[0]), max - margin - max(0, extent[1]))``.

    Raises
    ------
    stage_sim.validation.ConfigError
        The reference alone spans more than the travel (naming both), or the
        margin leaves no room for a start.

    Examples
    --------
    >>> x0 = random_starts(50, (-10e-3, 10e-3), margin=5e-3, rng_seed=1)
    >>> bool(x0.min() >= -5e-3 and x0.max() < 5e-3)
    True
    >>> random_starts(1, (-10e-3, 10e-3), extent=(0.0, 1000.0))
    Traceback (most recent call last):
    stage_sim.validation.ConfigError: the reference moves over 1000 m (0 to 1000 m from its start): more than the travel -0.01 to 0.01 m (0.02 m)
    """
    down, up = min(0.0, float(extent[0])), max(0.0, float(extent[1]))
    width, span = travel[1] - travel[0], up - down
    if not span < width:
        raise ConfigError(f"the reference moves over {span:g} m ({down:g} to {up:g} m from its start): more than "
                          f"the travel {travel[0]:g} to {travel[1]:g} m ({width:g} m)")
    lo, hi = travel[0] - down + margin, travel[1] - up - margin
    if not lo < hi:
        raise ConfigError(f"the margin {margin:g} m kept at both travel ends leaves no room for a start: the travel "
                          f"{travel[0]:g} to {travel[1]:g} m less the reference's {span:g} m leaves {width - span:g} m")
    return np.random.default_rng(rng_seed).uniform(lo, hi, n)


def circle_x(radius: float, speed: float, cycles: float = 1.0,
             dt: float = DT, pre: float = 0.0) -> Reference:
    """x-axis reference of a circle (seed Sec. 3.4.2).

    ``x = R (1 - cos(w t))`` with ``w = speed / R`` after ``pre`` seconds at
    rest at 0, so the motion starts at a reversal (``v = 0``) and
    ``v = speed sin(w t)``, ``a = R w**2 cos(w t)`` (``a`` jumps from 0 to
    ``speed**2 / R`` at the start, as for a circle entered at full speed).

    Parameters
    ----------
    radius : float
        Circle radius R [m].
    speed : float
        Tangential speed [m/s].
    cycles : float
        Number of revolutions.
    dt : float
        Sample time [s].
    pre : float
        Time at rest before the motion [s].

    Returns
    -------
    Reference
        Segments: ``"track"`` for the whole motion (end point included) and
        one ``"reversal"`` per interior velocity zero crossing (at
        ``t = pre + m pi / w``), spanning +-5 % of the period around it and
        with ``target`` the reversal position (0 or 2R).

    Examples
    --------
    >>> ref = circle_x(5e-3, 5e-3)
    >>> round(float(ref.v.max()), 9), [s.kind for s in ref.segments]
    (0.005, ['track', 'reversal'])
    """
    w = speed / radius
    period = 2.0 * np.pi / w
    n_pre = _samples(pre, dt, "pre")
    n = _samples(cycles * period, dt, f"{cycles:g} cycle(s) of {period:g} s")
    _check_length(n_pre + n + 1, dt, "the circle")
    tau = np.arange(n + 1) * dt
    rest = np.zeros(n_pre)
    x = np.concatenate([rest, radius * (1.0 - np.cos(w * tau))])
    v = np.concatenate([rest, speed * np.sin(w * tau)])
    a = np.concatenate([rest, radius * w**2 * np.cos(w * tau)])
    segments = [Segment("track", n_pre, x.size, math.nan, 0)]
    half = 0.05 * period
    for m in range(1, math.ceil(2 * cycles)):
        tc = m * period / 2
        segments.append(Segment(
            "reversal", n_pre + max(0, _samples(tc - half, dt)),
            n_pre + min(n + 1, _samples(tc + half, dt) + 1),
            0.0 if m % 2 == 0 else 2.0 * radius, m - 1))
    return Reference(np.arange(x.size) * dt, x, v, a, dt, segments)


def sine_sweep(frequencies, amplitude: float, periods: int = 10,
               settle_periods: int = 5, dt: float = DT,
               min_steady: float = 0.02,
               min_settle: float = 0.05) -> Reference:
    """Stepped-sine excitation for FRF measurement (seed Sec. 4.3).

    One constant-amplitude sine per frequency, in the given order. Each block
    starts with ``max(settle_periods / f, min_settle)`` seconds for
    transients to decay (a lightly damped resonance rings for many periods
    of a higher excitation frequency), followed by a steady-state window of
    ``max(periods, ceil(min_steady * f))`` whole periods. The frequency is
    adjusted (by less than half a sample per window, <= 0.25 % for the
    defaults) so that the window holds an exact integer number of samples;
    the adjusted value is stored in ``Segment.frequency``. The phase is
    continuous across blocks, so ``x`` has no jumps.

    Parameters
    ----------
    frequencies : array_like
        Excitation frequencies [Hz], below the Nyquist frequency ``0.5/dt``.
    amplitude : float
        Sine amplitude, in the unit of the excitation (force [N] for
        open-loop plant FRFs, position [m] for closed-loop FRFs).
    periods : int
        Minimum number of steady-state periods per frequency.
    settle_periods : int
        Minimum number of periods before the steady-state window.
    dt : float
        Sample time [s].
    min_steady : float
        Minimum steady-state window length [s].
    min_settle : float
        Minimum time before the steady-state window [s].

    Returns
    -------
    Reference
        ``x`` is the excitation, ``v`` and ``a`` its analytic first and
        second time derivatives. One ``Segment("sine", ...)`` per frequency
        marks its steady-state window (``index`` = position in
        ``frequencies``, ``target`` = 0, the centre of the oscillation).

    Examples
    --------
    >>> ref = sine_sweep([10.0, 100.0], amplitude=0.11)
    >>> [(s.frequency, (s.stop - s.start) * ref.dt) for s in ref.segments]
    [(10.0, 1.0), (100.0, 0.1)]
    """
    xs, vs, as_, segments = [], [], [], []
    k, phase0 = 0, 0.0
    for i, f in enumerate(np.asarray(frequencies, dtype=float)):
        if not 0 < f < 0.5 / dt:
            raise ValueError(f"frequency {f} Hz outside (0, Nyquist)")
        n_periods = max(periods, math.ceil(min_steady * f))
        n_steady = _samples(n_periods / f, dt, f"{n_periods} periods at {f:g} Hz")
        f_adj = n_periods / (n_steady * dt)
        _check_length(k + n_steady + max(settle_periods / f_adj, min_settle) / dt, dt, "the sine sweep")
        n_settle = math.ceil(max(settle_periods / f_adj, min_settle) / dt)
        w = 2.0 * np.pi * f_adj
        phase = phase0 + w * dt * np.arange(n_settle + n_steady)
        xs.append(amplitude * np.sin(phase))
        vs.append(amplitude * w * np.cos(phase))
        as_.append(-amplitude * w**2 * np.sin(phase))
        segments.append(Segment("sine", k + n_settle, k + n_settle + n_steady,
                                0.0, i, f_adj))
        k += n_settle + n_steady
        phase0 = phase[-1] + w * dt
    x = np.concatenate(xs)
    return Reference(np.arange(x.size) * dt, x, np.concatenate(vs),
                     np.concatenate(as_), dt, segments)
