"""Loop-shaping PID design for a rigid-body stage, the way the seed tunes its servos.

The seed tunes every servo controller "to ~200 Hz closed loop bandwidth using loop
shaping, based on the FRF in the gross motion regime" (Sec. 4.3; also Sec. 3.4 with
180 Hz and Sec. 5.3 with 200 Hz). In the gross-motion regime the frictional stiffness
is zero and the plant from motor force to table position is the rigid body

    G(s) = 1 / (m s^2)            [m/N]

The controller has the form used throughout the project (:class:`stage_sim.config.Pid`)

    C(s) = kp + ki/s + kd s / (s/wd + 1)       [N/m],  wd = 2 pi derivative_cutoff

i.e. a lead (derivative zero below the crossover, derivative filter pole above it)
plus an integrator whose corner sits well below the crossover.

Design procedure (:func:`loop_shape_pid`)
------------------------------------------
For a trial open-loop crossover ``wc`` [rad/s]:

1. the derivative filter pole is put at ``wd = derivative_filter_ratio * wc``;
2. the integrator corner is put at ``wi = ki/kp = wc / integral_ratio``;
3. ``kp`` and ``kd`` are the unique solution of the two real equations
   ``|C(j wc) G(j wc)| = 1`` and ``arg C(j wc) = phase_margin + wc * delay``
   (the last term pre-compensates the phase lag of the sampling delay, so that the
   margins computed *with* the delay by :func:`margins` equal ``phase_margin_deg``).
   The resulting derivative zero ``wz = 1 / (1/wd + kd/kp)`` lies below ``wc``.

The crossover ``wc`` is then found with Brent's method so that the closed-loop
``-3 dB`` bandwidth of ``T = CG / (1 + CG)`` (:func:`closed_loop_bandwidth`, where
``|T|`` first drops below -3 dB) equals the requested bandwidth (to 1e-6
relative).

Analysis
--------
One implementation serves measured FRFs (the campaigns' stepped-sine tests) and the
models here alike: :func:`closed_loop_bandwidth` and :func:`loop_margins` take an FRF on
a frequency grid (python-control's :func:`control.stability_margins` on
:func:`control.frd` finds the crossovers); :func:`closed_loop_bandwidth_hz` and
:func:`margins` evaluate the model's loop on :data:`FREQUENCY_GRID_HZ` and call them.
With the defaults (PM 40°, ``wd = 3 wc``, ``wi = wc/5``) the crossover lands at
``wc = 0.572 x bandwidth`` (114.5 Hz for 200 Hz): the -3 dB point of a 40° loop lies
well above its crossover because of the closed-loop peaking.

Sampling delay
--------------
The seed's controllers run on a dSPACE board at 10 kHz (Sec. 3.4, 4.3, 5.3). A
zero-order hold behaves, below Nyquist, like a pure delay of half a sample,
``Ts/2 = 50 us``. :func:`margins` includes that delay as a 2nd-order Padé
approximation (:func:`control.pade`); pass ``delay=1/rate`` for the more
conservative one-sample (computation + ZOH-ish) delay, or ``delay=0`` for the
continuous-time margins. :func:`closed_loop_bandwidth_hz` defaults to no delay, i.e.
the bandwidth of C*G as the loop-shaping target is defined; including the half-sample
delay raises the -3 dB point by ~3 % (200 -> 205.7 Hz for the default shape) because
the extra phase lag increases the closed-loop peaking.

Examples
--------
>>> from stage_control.tuning import loop_shape_pid, closed_loop_bandwidth_hz, margins
>>> g = loop_shape_pid(2.0, 200.0)          # Ch. 4 stage, 2 kg, 200 Hz
>>> sorted(g)
['derivative_cutoff', 'kd', 'ki', 'kp']
>>> round(closed_loop_bandwidth_hz(2.0, g), 3)
200.0
>>> round(margins(2.0, g)["phase_margin_deg"], 3)
40.0
"""
from __future__ import annotations

import math
from typing import Mapping, NamedTuple, Optional

import control as ct
import numpy as np
from scipy.optimize import brentq

__all__ = [
    "DEFAULT_RATE", "HALF_SAMPLE_DELAY",
    "plant_tf", "pid_tf", "delay_tf",
    "loop_shape_pid", "closed_loop_bandwidth_hz", "margins",
    "closed_loop_bandwidth", "LoopMargins", "loop_margins", "FREQUENCY_GRID_HZ",
]

#: Control rate of the seed's dSPACE DS1007 boards [Hz] (Sec. 3.4, 4.3, 5.3).
DEFAULT_RATE = 10_000.0
#: Half a sample at 10 kHz [s]: the ZOH delay used for the margins by default.
HALF_SAMPLE_DELAY = 0.5 / DEFAULT_RATE

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- building blocks
def plant_tf(mass: float) -> ct.TransferFunction:
    """Rigid-body plant in the gross-motion regime, ``G(s) = 1/(m s^2)``.

    Parameters
    ----------
    mass : float
        Moving mass [kg] (rotary stages: inertia [kg·m²]).

    Returns
    -------
    control.TransferFunction
        Force [N] to position [m] (rotary: torque [N·m] to angle [rad]).

    Examples
    --------
    >>> float(abs(plant_tf(2.0)(1j)))
    0.5
    """
    if not (mass > 0 and math.isfinite(mass)):
        raise ValueError(f"mass must be a positive finite number [kg], got {mass!r}")
    return ct.tf([1.0], [float(mass), 0.0, 0.0])


def pid_tf(gains: Mapping[str, Optional[float]]) -> ct.TransferFunction:
    """PID ``C(s) = kp + ki/s + kd s/(s/wd + 1)`` as a transfer function.

    Parameters
    ----------
    gains : mapping
        ``kp`` [N/m], ``ki`` [N/(m·s)] (default 0), ``kd`` [N·s/m] (default 0) and
        ``derivative_cutoff`` [Hz] (``wd = 2 pi derivative_cutoff``; ``None`` or
        missing = unfiltered derivative). A :class:`stage_sim.config.Pid` dumped with
        ``model_dump()`` works as is; extra keys are ignored.

    Returns
    -------
    control.TransferFunction
        Position error [m] to force [N]. An unfiltered derivative gives an improper
        transfer function (numerator degree 2 over ``s``), which python-control
        handles for frequency responses and feedback with a strictly proper plant.

    Examples
    --------
    >>> C = pid_tf({"kp": 1.0, "ki": 0.0, "kd": 0.0})
    >>> float(abs(C(10j)))
    1.0
    """
    kp = float(gains.get("kp", 0.0) or 0.0)
    ki = float(gains.get("ki", 0.0) or 0.0)
    kd = float(gains.get("kd", 0.0) or 0.0)
    fd = gains.get("derivative_cutoff")
    s = ct.tf("s")
    C = ct.tf([kp], [1.0])
    if ki:
        C = C + ki / s
    if kd:
        if fd is None:
            C = C + kd * s
        else:
            wd = _TWO_PI * float(fd)
            C = C + ct.tf([kd, 0.0], [1.0 / wd, 1.0])
    return ct.minreal(C, verbose=False) if ki or kd else C


def delay_tf(delay: float, order: int = 2) -> ct.TransferFunction:
    """Padé approximation of a pure delay ``exp(-s delay)``.

    Parameters
    ----------
    delay : float
        Delay [s]; 0 returns a unit gain.
    order : int, optional
        Padé order (numerator = denominator degree). Order 2 is exact to better than
        0.01° of phase below 1 kHz for a 50 us delay.

    Returns
    -------
    control.TransferFunction

    Examples
    --------
    >>> D = delay_tf(50e-6)
    >>> round(float(abs(D(1000j))), 12)
    1.0
    """
    if delay < 0 or not math.isfinite(delay):
        raise ValueError(f"delay must be >= 0 [s], got {delay!r}")
    if delay == 0:
        return ct.tf([1.0], [1.0])
    num, den = ct.pade(delay, order)
    return ct.tf(num, den)


# --------------------------------------------------------------------------- FRF analysis
# One implementation of the closed-loop bandwidth and the stability margins, for measured
# FRFs (campaigns) and for the models below alike.
def closed_loop_bandwidth(freqs_hz, T) -> float:
    """-3 dB closed-loop bandwidth [Hz] (seed Fig. 4.6(a)).

    The lowest frequency at which ``|T|`` drops below -3 dB relative to the
    ideal DC gain 1 (``10**(-3/20)``, as :func:`control.bandwidth` defines it;
    ``1/sqrt(2)`` = -3.01 dB would read 0.08 % higher on the seed's loops),
    interpolated linearly in (log frequency, dB) between the two samples around
    the crossing.

    Parameters
    ----------
    freqs_hz : array_like, shape (n,)
        Increasing frequencies [Hz].
    T : array_like, shape (n,)
        Complex closed-loop FRF (reference to position).

    Returns
    -------
    float
        Bandwidth [Hz]; nan if ``|T|`` never drops below the threshold or is
        already below it at the lowest frequency (the crossing lies outside
        the measured range).

    Examples
    --------
    >>> f = np.logspace(0, 4, 200)  # 50 points per decade
    >>> round(closed_loop_bandwidth(f, 1 / (1j * f / 200.0 + 1)), 1)  # exact: 200 sqrt(10**0.3 - 1)
    199.5
    """
    f = np.asarray(freqs_hz, dtype=float)
    mag_db = 20.0 * np.log10(np.abs(np.asarray(T)))
    threshold = -3.0
    below = np.flatnonzero(mag_db < threshold)
    if below.size == 0 or below[0] == 0:
        return float("nan")
    k = below[0]
    frac = (threshold - mag_db[k - 1]) / (mag_db[k] - mag_db[k - 1])
    return float(np.exp(np.log(f[k - 1]) + frac * np.log(f[k] / f[k - 1])))



def _crossovers(freqs_hz, L):
    """Gain and phase crossovers [rad/s] of a loop FRF (python-control, inside the range),
    and ``|L|`` / unwrapped ``arg L`` interpolated in log frequency."""
    f = np.asarray(freqs_hz, float)
    L = np.asarray(L, complex)
    w = _TWO_PI * f
    _, _, _, w180, wgc, _ = ct.stability_margins(ct.frd(L, w), returnall=True)
    wgc = np.sort(np.asarray(wgc, float).ravel())
    w180 = np.sort(np.asarray(w180, float).ravel())
    wgc = wgc[np.isfinite(wgc) & (wgc >= w[0]) & (wgc <= w[-1])]
    w180 = w180[np.isfinite(w180) & (w180 >= w[0]) & (w180 <= w[-1])]
    lw, lmag, ph = np.log(w), np.log(np.abs(L)), np.unwrap(np.angle(L))

    def mag(x):
        return float(np.exp(np.interp(math.log(x), lw, lmag)))

    def phase(x):
        return float(np.interp(math.log(x), lw, ph))
    return wgc, w180, mag, phase

class LoopMargins(NamedTuple):
    """Margins of a measured loop at its last gain crossover (see :func:`loop_margins`)."""
    gain_margin_db: float
    phase_margin_deg: float
    phase_crossover_hz: float
    gain_crossover_hz: float
    n_gain_crossovers: int


def loop_margins(freqs_hz, L) -> LoopMargins:
    """Gain and phase margins of a measured loop FRF, signed (negative = unstable).

    python-control (:func:`control.stability_margins` with ``returnall=True`` on
    ``control.frd(L, w)``) finds every gain crossover ``|L| = 1`` and phase crossover
    ``arg L = -180° (mod 360°)``. The loops here have an integrator (type 1 on a stuck stage,
    type 3 on a sliding one), so low-frequency phase crossovers with ``|L| > 1`` are
    conditional-stability crossings, not margins; the margins are taken where the loop finally
    rolls off:

    * ``phase_margin_deg = 180° + arg L`` at the *last* (highest) gain crossover, wrapped into
      (-180°, 180°] (negative: the phase there is below -180°);
    * if it is positive, ``gain_margin_db = -20 log10 |L|`` at the first phase crossover above
      it (inf if none in the measured range); if not, at the last phase crossover below it
      (|L| > 1 there: the gain margin is negative too).

    Parameters
    ----------
    freqs_hz : array_like, shape (n,)
        Increasing frequencies [Hz] (finite data only).
    L : array_like, shape (n,)
        Complex loop FRF.

    Returns
    -------
    LoopMargins
        nan margins if ``|L|`` never crosses 1 in the range.

    Examples
    --------
    ``K / (s (s+1) (s+10))`` has its phase crossover at sqrt(10) rad/s where ``|L| = K/110``:

    >>> f = np.logspace(-2.5, 1.5, 1500)
    >>> s = 2j * np.pi * f
    >>> [tuple(round(v, 1) for v in loop_margins(f, K / (s * (s + 1) * (s + 10)))[:2]) for K in (11, 220)]
    [(20.0, 45.2), (-6.0, -11.2)]
    """
    return _margins_at(*_crossovers(freqs_hz, L))


def _margins_at(wgc, w180, mag, phase) -> LoopMargins:
    """:func:`loop_margins` from the crossovers :func:`_crossovers` found."""
    if wgc.size == 0:
        return LoopMargins(math.nan, math.nan, math.nan, math.nan, 0)
    wc = float(wgc[-1])
    pm = (math.degrees(phase(wc)) + 360.0) % 360.0 - 180.0
    pm = 180.0 if pm == -180.0 else pm

    if pm > 0:
        above = w180[w180 > wc]
        wp = float(above[0]) if above.size else math.nan
    else:
        below = w180[w180 < wc]
        wp = float(below[-1]) if below.size else math.nan
    gm = -20.0 * math.log10(mag(wp)) if math.isfinite(wp) else (math.inf if pm > 0 else math.nan)
    return LoopMargins(float(gm), float(pm), wp / (2 * np.pi), wc / (2 * np.pi), int(wgc.size))


# --------------------------------------------------------------------------- analysis
#: Frequencies [Hz] on which the models' loops are evaluated: 0.01 Hz to 100 kHz,
#: 500 per decade (linear interpolation between them is exact to ~1e-5 in dB and degrees).
FREQUENCY_GRID_HZ = np.logspace(-2.0, 5.0, 3501)


def _loop(mass, gains, delay=0.0, pade_order=2):
    L = pid_tf(gains) * plant_tf(mass)
    if delay:
        L = L * delay_tf(delay, pade_order)
    return L


def _loop_frf(mass, gains, delay=0.0, pade_order=2) -> np.ndarray:
    """``L(j w)`` of the PID on the rigid plant on :data:`FREQUENCY_GRID_HZ`."""
    return np.asarray(_loop(mass, gains, delay, pade_order)(2j * np.pi * FREQUENCY_GRID_HZ), complex)


def closed_loop_bandwidth_hz(mass: float, gains: Mapping[str, Optional[float]],
                             delay: float = 0.0, pade_order: int = 2) -> float:
    """Closed-loop ``-3 dB`` bandwidth of the PID on the rigid plant.

    :func:`closed_loop_bandwidth` of ``T = CG/(1 + CG)`` evaluated on
    :data:`FREQUENCY_GRID_HZ` (first frequency where ``|T|`` drops below -3 dB; its DC
    value is 1 with the integrator or the double-integrator plant), the definition of
    :func:`control.bandwidth`.

    Parameters
    ----------
    mass : float
        Moving mass [kg] (rotary: inertia [kg·m²]).
    gains : mapping
        PID gains, see :func:`pid_tf`.
    delay : float, optional
        Loop delay [s] included as a Padé approximation; default 0 (the seed's
        loop-shaping bandwidth of C*G).
    pade_order : int, optional
        Padé order for ``delay``.

    Returns
    -------
    float
        Bandwidth [Hz].

    Examples
    --------
    >>> g = {"kp": 8e5, "ki": 0.0, "kd": 850.0, "derivative_cutoff": None}
    >>> round(closed_loop_bandwidth_hz(1.5, g), 1)   # Table A.1 PD on the ALS-130H
    199.2
    """
    loop = _loop(mass, gains, delay, pade_order)
    L = np.asarray(loop(2j * np.pi * FREQUENCY_GRID_HZ), complex)
    f_bw = closed_loop_bandwidth(FREQUENCY_GRID_HZ, L / (1.0 + L))
    if not math.isfinite(f_bw):
        return f_bw
    # the model is known between the grid points: polish the crossing to machine precision

    def excess_db(f):
        Lf = complex(loop(2j * np.pi * f))
        return 20.0 * math.log10(abs(Lf / (1.0 + Lf))) + 3.0
    k = int(np.searchsorted(FREQUENCY_GRID_HZ, f_bw))
    lo, hi = FREQUENCY_GRID_HZ[max(k - 1, 0)], FREQUENCY_GRID_HZ[min(k, FREQUENCY_GRID_HZ.size - 1)]
    if excess_db(lo) > 0 > excess_db(hi):
        f_bw = brentq(excess_db, lo, hi, xtol=1e-12 * hi, rtol=1e-14)
    return float(f_bw)


def margins(mass: float, gains: Mapping[str, Optional[float]],
            delay: float = HALF_SAMPLE_DELAY, pade_order: int = 2) -> dict:
    """Stability margins of the PID on the rigid plant, with the sampling delay.

    :func:`loop_margins` of ``L = C G D`` evaluated on :data:`FREQUENCY_GRID_HZ`, where
    ``D`` is a Padé approximation of ``delay`` (default: half a sample at 10 kHz, the ZOH delay of
    the seed's dSPACE loop; pass ``1/rate`` for a one-sample delay, 0 for none).

    Parameters
    ----------
    mass : float
        Moving mass [kg] (rotary: inertia [kg·m²]).
    gains : mapping
        PID gains, see :func:`pid_tf`.
    delay : float, optional
        Loop delay [s].
    pade_order : int, optional
        Padé order for ``delay``.

    Returns
    -------
    dict
        ``gain_margin`` [-]: upper gain margin, the factor by which the loop gain
        may grow (``inf`` if the phase never crosses -180° above the crossover; the
        delay makes it finite), ``gain_margin_db`` [dB], ``phase_crossover_hz`` [Hz]
        where it is measured (``nan`` if none); ``lower_gain_margin`` [-]: the factor
        (< 1) down to which the gain may drop before the low-frequency -180°
        crossing caused by the integrator destabilises the loop (0 if none);
        ``phase_margin_deg`` [deg] and ``crossover_hz`` [Hz] at the gain crossover;
        ``stability_margin`` [-] (minimum distance of the Nyquist curve to -1, i.e.
        ``1/max|S|``); ``delay`` [s].

    Examples
    --------
    >>> m = margins(2.0, loop_shape_pid(2.0, 200.0))
    >>> round(m["phase_margin_deg"], 2), round(m["crossover_hz"], 1)
    (40.0, 114.5)
    >>> m["gain_margin_db"] > 20, m["lower_gain_margin"] < 0.5
    (True, True)
    """
    L = _loop_frf(mass, gains, delay, pade_order)
    wgc, w180, mag, phase = _crossovers(FREQUENCY_GRID_HZ, L)            # searched once
    m = _margins_at(wgc, w180, mag, phase)
    # With an integrator on a double integrator the phase is below -180 deg at low
    # frequency, where |L| > 1: that crossing gives a *lower* gain margin (< 1, how far the
    # gain may drop), the largest 1/|L| there.
    below = [1.0 / mag(w) for w in w180 if wgc.size and w < wgc[-1] and mag(w) > 1.0]
    gm_db = m.gain_margin_db
    return {
        "gain_margin": 10.0 ** (gm_db / 20.0) if math.isfinite(gm_db) else math.inf,
        "gain_margin_db": gm_db if math.isfinite(gm_db) else math.inf,
        "phase_crossover_hz": m.phase_crossover_hz,
        "lower_gain_margin": max(below) if below else 0.0,
        "phase_margin_deg": m.phase_margin_deg,
        "crossover_hz": m.gain_crossover_hz,
        "stability_margin": float(np.min(np.abs(1.0 + L))),
        "delay": float(delay),
    }


# --------------------------------------------------------------------------- design
def _gains_at_crossover(mass, wc, phase_margin_deg, integral_ratio, derivative_filter_ratio, delay):
    """kp, ki, kd, wd placing |CG| = 1 and arg C = PM + wc*delay at wc."""
    wd = derivative_filter_ratio * wc
    wi = wc / integral_ratio
    # C(j wc) = kp * A + kd * D with A = 1 - j wi/wc and D = j wc / (j wc/wd + 1)
    A = 1.0 - 1j * wi / wc
    D = 1j * wc / (1j * wc / wd + 1.0)
    target = mass * wc**2 * np.exp(1j * (math.radians(phase_margin_deg) + wc * delay))
    M = np.array([[A.real, D.real], [A.imag, D.imag]])
    kp, kd = np.linalg.solve(M, np.array([target.real, target.imag]))
    return float(kp), float(kp * wi), float(kd), float(wd)


def loop_shape_pid(mass: float, bandwidth_hz: float, phase_margin_deg: float = 40.0,
                   integral_ratio: float = 5.0, derivative_filter_ratio: float = 3.0,
                   delay: float = HALF_SAMPLE_DELAY) -> dict:
    """Loop-shape a PID on the rigid plant ``1/(m s^2)`` to a closed-loop bandwidth.

    Parameters
    ----------
    mass : float
        Moving mass in the gross-motion regime [kg] (rotary: inertia [kg·m²]).
    bandwidth_hz : float
        Requested closed-loop ``-3 dB`` bandwidth [Hz] (seed: 200 Hz in Ch. 4-6,
        180 Hz in Ch. 3).
    phase_margin_deg : float, optional
        Phase margin [deg] at the open-loop crossover, *including* ``delay``
        (default 40°, a common precision-motion target; with the default ratios it
        is the phase of the classic lead-at-3x / integrator-at-1/5 shape).
    integral_ratio : float, optional
        Crossover over integrator corner, ``wc / (ki/kp)`` [-] (default 5).
    derivative_filter_ratio : float, optional
        Derivative filter pole over crossover, ``wd / wc`` [-] (default 3).
    delay : float, optional
        Loop delay [s] whose phase lag ``wc*delay`` is pre-compensated (default half
        a sample at 10 kHz). Use 0 for a purely continuous design.

    Returns
    -------
    dict
        ``kp`` [N/m], ``ki`` [N/(m·s)], ``kd`` [N·s/m] and ``derivative_cutoff`` [Hz],
        ready for ``controller.pid`` of a preset.

    Raises
    ------
    ValueError
        If the inputs are not positive/finite, or the phase margin cannot be reached
        with the given ratios (needs ``-atan(1/integral_ratio) < PM + wc*delay <
        atan(derivative_filter_ratio)``).

    Examples
    --------
    >>> g = loop_shape_pid(1.4, 200.0)          # Ch. 5 SAI stage
    >>> round(closed_loop_bandwidth_hz(1.4, g), 6)
    200.0
    >>> g["derivative_cutoff"] > 200.0 > g["ki"] / g["kp"] / 6.283
    True
    """
    for name, v in (("mass", mass), ("bandwidth_hz", bandwidth_hz),
                    ("integral_ratio", integral_ratio),
                    ("derivative_filter_ratio", derivative_filter_ratio)):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise ValueError(f"{name} must be a positive finite number, got {v!r}")
    if not (0 < phase_margin_deg < 90):
        raise ValueError(f"phase_margin_deg must be in (0, 90), got {phase_margin_deg!r}")
    if delay < 0 or not math.isfinite(delay):
        raise ValueError(f"delay must be >= 0 [s], got {delay!r}")

    wb = _TWO_PI * bandwidth_hz

    def design(wc):
        kp, ki, kd, wd = _gains_at_crossover(mass, wc, phase_margin_deg, integral_ratio,
                                             derivative_filter_ratio, delay)
        if kp <= 0 or kd <= 0:
            raise ValueError(
                f"phase margin {phase_margin_deg} deg (+{math.degrees(wc * delay):.2f} deg delay "
                f"compensation) is not reachable with integral_ratio={integral_ratio} and "
                f"derivative_filter_ratio={derivative_filter_ratio}")
        return {"kp": kp, "ki": ki, "kd": kd, "derivative_cutoff": wd / _TWO_PI}

    def err(wc):
        return math.log(closed_loop_bandwidth_hz(mass, design(wc)) / bandwidth_hz)

    lo, hi = 0.2 * wb, 1.5 * wb
    if err(lo) > 0 or err(hi) < 0:
        raise ValueError("could not bracket the crossover for the requested bandwidth")
    wc = brentq(err, lo, hi, xtol=1e-12 * wb, rtol=1e-12, maxiter=200)
    gains = design(wc)
    bw = closed_loop_bandwidth_hz(mass, gains)
    if abs(bw / bandwidth_hz - 1.0) > 1e-6:  # pragma: no cover - brentq guarantees this
        raise RuntimeError(f"bandwidth solve did not converge: {bw} Hz vs {bandwidth_hz} Hz")
    return gains
