"""Dither generator and harmonic-cancelling (HC) controller of the VAN stage (Ch. 3).

Outputs per sample ``k`` (``t = k/rate``), following Eq. 3.2 and Fig. 3.7::

    out[0] = F_d1 + F_comp      the plant applies +out[0] to the bearing on channel 0
    out[1] = F_d2               the plant applies -out[1] to the bearing on channel 1

with ``F_d1 = F_d2 = A sin(2 pi f t)`` (180 deg apart through the sign of Eq. 3.2), so the
two dither forces cancel on the table of a symmetric stage and ``F_comp`` is the only
net force.

Design choices
--------------
* HC (Eq. 3.3), ``G_HC(s) = K_HC s/(s^2 + w^2)``, ``w = 2 pi f``: Tustin prewarped at
  ``w``, so the discrete poles lie exactly at ``exp(+-j w dt)`` on the unit circle and the
  internal model rejects the harmonic at ``f`` with zero steady-state error.
* Sign: ``F_comp = G_HC[x_meas - x_ref] = -G_HC[e]``. The path from ``F_comp`` to the
  table is mass-like at ``f`` (joint modes above ``f``, servo bandwidth below it), where
  ``Re{P S(jw)} < 0``; with ``+G_HC[e]`` the resonator poles move into the right half
  plane for every ``K_HC > 0``, with ``-G_HC[e]`` they move left (``K_HC = 4e9 N/m`` of
  Fig. 3.8 is stable on the 3-mass model of Fig. 3.3).
* Regulation: the generator starts at the first sample with ``v_ref != 0`` (or at the
  first call if ``preemptive > 0``). ``"continuous"`` then stays on. ``"on_off"`` switches
  off ``round(off_after*rate)`` samples after ``v_ref`` returns to 0 (the first sample
  with ``v_ref == 0`` counts as 0) and on again at the next move; ``preemptive`` only
  covers the first move (the generator does not see future moves).
* While off, both outputs are 0 and the HC resonator runs free with zero input: it keeps
  its learned amplitude and phase, coherent with the dither phase, so the compensation
  resumes at once at the next move.

State row (``n_state = 6``): started flag, on flag, move-seen flag (a move has occurred
since switching on), sample at which the reference stopped, HC resonator (2).
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from stage_control.filters import discretize, ss_step
from stage_sim.config import Dither

__all__ = ["DitherModel", "build_dither", "init_dither_state", "dither_step", "piezo_power"]

DITHER_STARTED, DITHER_ON, DITHER_MOVED, DITHER_K_STOP, DITHER_HC = 0, 1, 2, 3, 4
DITHER_N_STATE = 6


class DitherModel(NamedTuple):
    """Compiled-loop parameters of the dither generator (build with :func:`build_dither`)."""
    rate: float           # control rate [Hz]
    amplitude: float      # A [N]
    omega: float          # 2 pi f [rad/s]
    on_off: int           # 1 = on-off regulation, 0 = continuous
    n_off: int            # on-off: samples after the reference stops
    preemptive: int       # 1 = on from the first call
    hc_A: np.ndarray      # HC resonator, m -> N
    hc_B: np.ndarray
    hc_C: np.ndarray
    hc_D: np.ndarray
    n_state: int


def build_dither(dither: Dither, rate: float = 10_000.0) -> DitherModel:
    """Build the dither model.

    Parameters
    ----------
    dither : Dither
        Amplitude [N], frequency [Hz], HC gain [N/m], regulation.
    rate : float
        Control rate [Hz].

    Returns
    -------
    DitherModel
    """
    w = 2.0 * np.pi * dither.frequency
    if w / rate >= np.pi:
        raise ValueError(f"dither frequency {dither.frequency} Hz is not below Nyquist ({rate / 2} Hz)")
    A, B, C, D = discretize([1.0, 0.0], [1.0, 0.0, w * w], 1.0 / rate, "tustin", prewarp=w)
    hc = (A, B * dither.hc_gain, C, D * dither.hc_gain)     # K_HC = 0: state stays 0
    return DitherModel(rate=float(rate), amplitude=float(dither.amplitude), omega=float(w),
                       on_off=int(dither.regulation == "on_off"),
                       n_off=int(round(dither.off_after * rate)),
                       preemptive=int(dither.preemptive > 0.0),
                       hc_A=hc[0], hc_B=hc[1], hc_C=hc[2], hc_D=hc[3], n_state=DITHER_N_STATE)


def init_dither_state(model: DitherModel, n_trials: int) -> np.ndarray:
    """Initial (off) dither state, shape ``(n_trials, model.n_state)``."""
    return np.zeros((int(n_trials), model.n_state))


@njit(cache=True)
def dither_step(model, state_row, k, x_ref, v_ref, x_meas, out):
    """One sample of the dither generator and HC controller.

    Parameters
    ----------
    model : DitherModel
    state_row : ndarray, shape (n_state,)
        One trial's state, updated in place.
    k : int
        Sample index (``t = k/rate``).
    x_ref, v_ref : float
        Reference position [m] and velocity [m/s].
    x_meas : float
        Measured table position [m].
    out : ndarray, shape (2,)
        Written: ``out[0] = F_d1 + F_comp``, ``out[1] = F_d2`` [N].
    """
    s = state_row
    if s[DITHER_STARTED] == 0.0:
        s[DITHER_STARTED] = 1.0
        s[DITHER_ON] = float(model.preemptive)
    if v_ref != 0.0:
        s[DITHER_ON] = 1.0
        s[DITHER_MOVED] = 1.0
        s[DITHER_K_STOP] = k + 1.0
    elif model.on_off == 1 and s[DITHER_MOVED] == 1.0 and k - s[DITHER_K_STOP] >= model.n_off:
        s[DITHER_ON] = 0.0
        s[DITHER_MOVED] = 0.0
    hc = s[DITHER_HC:DITHER_HC + 2]
    if s[DITHER_ON] == 1.0:
        f_d = model.amplitude * math.sin(model.omega * (k / model.rate))
        f_comp = ss_step(model.hc_A, model.hc_B, model.hc_C, model.hc_D, hc, x_meas - x_ref)
        out[0] = f_d + f_comp
        out[1] = f_d
    else:
        ss_step(model.hc_A, model.hc_B, model.hc_C, model.hc_D, hc, 0.0)
        out[0] = 0.0
        out[1] = 0.0


def piezo_power(frequency: float, capacitance: float, v_pp: float) -> float:
    """Power drawn by a piezo stack in sinusoidal operation, Eq. 3.7 [W].

    Parameters
    ----------
    frequency : float
        Operating frequency f [Hz].
    capacitance : float
        Piezo capacitance C_PZT [F].
    v_pp : float
        Peak-to-peak voltage [V].
    """
    return frequency * capacitance * v_pp ** 2
