"""Semi-active isolator (SAI) switch manager and ILC of the switching error (Ch. 5.3).

Mode per sample: 1.0 = compliant (solenoid powered, lock released), 0.0 = stiff.

* ``"point_to_point"``: compliant while ``v_ref != 0`` or ``v_ref_ahead != 0`` (the caller
  passes ``v_ref`` at ``t + release_lead``, so the lock releases ``release_lead`` before a
  move); stiff once the reference has reached its target (both zero).
* ``"tracking"``: compliant only near motion reversals,
  ``|v_ref| < reversal_window`` or ``|v_ref_ahead| < reversal_window``; stiff otherwise.
* ``"always_compliant"`` / ``"always_stiff"``.

Step II of the two-step scheme: at every compliant->stiff switch the learned reference
correction restarts; ``x_correction = correction[j]`` at the ``j``-th sample after the
switch (``j = 0`` at the first stiff sample), 0 after its end. The correction is learned
offline between repetitions with :func:`ilc_update` (Eq. 5.2).

State row (``n_state = 3``): previous mode, sample index of the last compliant->stiff
switch, switch-seen flag.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit
from scipy import signal

from stage_sim.config import Ilc, SaiManager

__all__ = ["SaiModel", "build_sai", "init_sai_state", "sai_step", "ilc_update"]

RULES = ("point_to_point", "tracking", "always_compliant", "always_stiff")
SAI_MODE, SAI_K_SWITCH, SAI_SWITCHED = 0, 1, 2
SAI_N_STATE = 3


class SaiModel(NamedTuple):
    """Compiled-loop parameters of the SAI manager (build with :func:`build_sai`)."""
    rule: int                 # index into RULES
    lead: int                 # release_lead in samples (look-ahead the caller uses)
    reversal_window: float    # [m/s]
    n_correction: int         # ILC correction length [samples] (0 without ILC)
    n_state: int


def build_sai(manager: SaiManager, rate: float = 10_000.0) -> SaiModel:
    """Build the SAI manager model.

    Parameters
    ----------
    manager : SaiManager
        Switching rule, release lead [s], reversal window [m/s], optional ILC.
    rate : float
        Control rate [Hz].

    Returns
    -------
    SaiModel
    """
    return SaiModel(rule=RULES.index(manager.rule), lead=int(round(manager.release_lead * rate)),
                    reversal_window=float(manager.reversal_window),
                    n_correction=int(round(manager.ilc.length * rate)) if manager.ilc else 0,
                    n_state=SAI_N_STATE)


def init_sai_state(model: SaiModel, n_trials: int) -> np.ndarray:
    """Initial SAI manager state (stiff, no switch yet), shape ``(n_trials, model.n_state)``."""
    return np.zeros((int(n_trials), model.n_state))


@njit(cache=True)
def sai_step(model, state_row, correction, k, v_ref, v_ref_ahead):
    """One sample of the SAI switch manager.

    Parameters
    ----------
    model : SaiModel
    state_row : ndarray, shape (n_state,)
        One trial's state, updated in place.
    correction : ndarray, shape (q,)
        Learned reference correction after a compliant->stiff switch [m]; may be empty.
    k : int
        Sample index.
    v_ref : float
        Reference velocity now [m/s].
    v_ref_ahead : float
        Reference velocity ``lead`` samples ahead [m/s].

    Returns
    -------
    mode : float
        1.0 compliant, 0.0 stiff.
    x_correction : float
        Correction to add to the reference [m].
    """
    s = state_row
    if model.rule == 0:
        mode = 1.0 if (v_ref != 0.0 or v_ref_ahead != 0.0) else 0.0
    elif model.rule == 1:
        w = model.reversal_window
        mode = 1.0 if (abs(v_ref) < w or abs(v_ref_ahead) < w) else 0.0
    elif model.rule == 2:
        mode = 1.0
    else:
        mode = 0.0
    if s[SAI_MODE] == 1.0 and mode == 0.0:
        s[SAI_K_SWITCH] = k
        s[SAI_SWITCHED] = 1.0
    s[SAI_MODE] = mode
    xc = 0.0
    if s[SAI_SWITCHED] == 1.0:
        j = int(k - s[SAI_K_SWITCH])
        if 0 <= j < correction.shape[0]:
            xc = correction[j]
    return mode, xc


def ilc_update(u_k, e_k, ilc: Ilc, rate: float = 10_000.0) -> np.ndarray:
    """One P-type ILC iteration, Eq. 5.2: ``u_{k+1} = LPF(e_k) + u_k``.

    The LPF is a Butterworth of ``ilc.order`` (4) at ``ilc.cutoff`` (200 Hz), applied
    forward and backward (zero phase, ``sosfiltfilt``): the update runs offline between
    repetitions, and zero phase keeps the learning free of the filter lag. The effective
    magnitude is squared (-6 dB at the cutoff).

    Parameters
    ----------
    u_k : array_like, shape (q,)
        Correction used in repetition ``k`` [m].
    e_k : array_like, shape (q,)
        Error after the switch in repetition ``k``, nominal reference minus measured
        position [m].
    ilc : Ilc
        Filter order and cutoff [Hz].
    rate : float
        Sample rate of ``u_k`` and ``e_k`` [Hz].

    Returns
    -------
    ndarray, shape (q,)
        Correction for the next repetition [m].
    """
    u_k = np.asarray(u_k, float)
    e_k = np.asarray(e_k, float)
    if u_k.shape != e_k.shape or u_k.ndim != 1:
        raise ValueError(f"u_k {u_k.shape} and e_k {e_k.shape} must be 1-D of equal length")
    if e_k.size < 2:
        return u_k + e_k
    sos = signal.butter(ilc.order, ilc.cutoff, fs=rate, output="sos")
    padlen = min(3 * (2 * len(sos) + 1), e_k.size - 1)
    return signal.sosfiltfilt(sos, e_k, padlen=padlen) + u_k
