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

State (``n_state = 3`` rows, one column per trial): previous mode, sample index of the
last compliant->stiff switch, switch-seen flag. :func:`sai_step` advances a whole batch
(trial axis last and innermost).
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
    """Initial SAI manager state of a batch (stiff, no switch yet), shape
    ``(model.n_state, n_trials)`` (zeros)."""
    return np.zeros((model.n_state, int(n_trials)))


@njit(cache=True, error_model="numpy", inline="always")
def sai_step(model, state, correction, k, v_ref, v_ref_ahead, mode_out, xc_out):
    """One sample of the SAI switch manager for every trial of a batch.

    Parameters
    ----------
    model : SaiModel
    state : ndarray, shape (n_state, n_batch)
        Manager state, trial axis last (see :func:`init_sai_state`); updated in place.
    correction : ndarray, shape (q,)
        Learned reference correction after a compliant->stiff switch [m] (shared by the
        batch); may be empty.
    k : int
        Sample index shared by the batch.
    v_ref : ndarray, shape (n_batch,)
        Reference velocity now [m/s].
    v_ref_ahead : ndarray, shape (n_batch,)
        Reference velocity ``lead`` samples ahead [m/s].
    mode_out : ndarray, shape (n_batch,)
        Written: 1.0 compliant, 0.0 stiff.
    xc_out : ndarray, shape (n_batch,)
        Written: correction to add to the reference [m].
    """
    s = state
    rule = model.rule
    w = model.reversal_window
    p2p = rule == 0
    tracking = rule == 1
    always = rule == 2
    kf = float(k)
    nc = correction.shape[0]
    for b in range(s.shape[1]):
        # mode of every rule, then a select (one branch-free loop, vectorizes)
        v = v_ref[b]
        va = v_ref_ahead[b]
        moving = (v != 0.0) | (va != 0.0)
        reversal = (abs(v) < w) | (abs(va) < w)
        compliant = moving if p2p else (reversal if tracking else always)
        mode = 1.0 if compliant else 0.0
        # Step II: restart the correction at every compliant -> stiff switch
        switch = (s[SAI_MODE, b] == 1.0) & (mode == 0.0)
        k_sw = s[SAI_K_SWITCH, b]
        k_sw = kf if switch else k_sw
        switched = s[SAI_SWITCHED, b]
        switched = 1.0 if switch else switched
        s[SAI_K_SWITCH, b] = k_sw
        s[SAI_SWITCHED, b] = switched
        s[SAI_MODE, b] = mode
        mode_out[b] = mode
        xc = 0.0
        if switched == 1.0:
            j = int(kf - k_sw)
            if 0 <= j < nc:
                xc = correction[j]
        xc_out[b] = xc


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
