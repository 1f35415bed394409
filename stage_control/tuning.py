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
``-3 dB`` bandwidth of ``T = CG / (1 + CG)`` computed by python-control
(:func:`control.bandwidth`) equals the requested bandwidth (to 1e-6 relative).
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
from typing import Mapping, Optional

import control as ct
import numpy as np
from scipy.optimize import brentq

__all__ = [
    "DEFAULT_RATE", "HALF_SAMPLE_DELAY",
    "plant_tf", "pid_tf", "delay_tf",
    "loop_shape_pid", "closed_loop_bandwidth_hz", "margins",
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


# --------------------------------------------------------------------------- analysis
def _loop(mass, gains, delay=0.0, pade_order=2):
    L = pid_tf(gains) * plant_tf(mass)
    if delay:
        L = L * delay_tf(delay, pade_order)
    return L


def closed_loop_bandwidth_hz(mass: float, gains: Mapping[str, Optional[float]],
                             delay: float = 0.0, pade_order: int = 2) -> float:
    """Closed-loop ``-3 dB`` bandwidth of the PID on the rigid plant.

    Computed by :func:`control.bandwidth` on ``T = CG/(1 + CG)`` (first frequency where
    ``|T|`` drops 3 dB below its DC value of 1).

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
    T = ct.feedback(_loop(mass, gains, delay, pade_order), 1)
    return float(ct.bandwidth(T)) / _TWO_PI


def margins(mass: float, gains: Mapping[str, Optional[float]],
            delay: float = HALF_SAMPLE_DELAY, pade_order: int = 2) -> dict:
    """Stability margins of the PID on the rigid plant, with the sampling delay.

    Uses :func:`control.stability_margins` on ``L = C G D`` where ``D`` is a Padé
    approximation of ``delay`` (default: half a sample at 10 kHz, the ZOH delay of
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
    L = _loop(mass, gains, delay, pade_order)
    gm, pm, sm, wpc, wgc, wms = (np.atleast_1d(np.asarray(v, dtype=float))
                                 for v in ct.stability_margins(L, returnall=True))
    # With an integrator on a double integrator the phase is below -180 deg at low
    # frequency: that crossing gives a *lower* gain margin (< 1, how much the gain may
    # drop); the usual (upper) gain margin is the smallest one above 1.
    up = gm > 1
    lo = (gm > 0) & (gm < 1)
    gain_margin = float(gm[up].min()) if up.any() else math.inf
    lower = float(gm[lo].max()) if lo.any() else 0.0
    i_pm = int(np.argmin(pm)) if pm.size else None
    return {
        "gain_margin": gain_margin,
        "gain_margin_db": 20.0 * math.log10(gain_margin) if math.isfinite(gain_margin) else math.inf,
        "phase_crossover_hz": (float(wpc[up][np.argmin(gm[up])]) / _TWO_PI) if up.any() else math.nan,
        "lower_gain_margin": lower,
        "phase_margin_deg": float(pm[i_pm]) if i_pm is not None else math.inf,
        "crossover_hz": float(wgc[i_pm]) / _TWO_PI if i_pm is not None else math.nan,
        "stability_margin": float(np.min(sm)) if sm.size else math.inf,
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
