"""The force observer: the model, driven by the recorded command, follows the measured position.

:class:`Observer` smooths a recording's measurement once (zero phase, cutoff :func:`smoothing_hz`)
and runs any model's compiled observer on it (:func:`.engine.observe`): the tracking force
``r[k]`` (:attr:`ObsResult.r`) is the force the model is missing at each sample (zero up to noise
when the model is right); the model's state is snapshot for the open-loop windows.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stage_sim.plant import PlantInputs

from . import engine as E
from .data import DiagData, smooth
from .model import ModelSpec

__all__ = ["Observer", "ObsResult", "smoothing_hz", "SMOOTH_FACTOR"]


@dataclass
class ObsResult:
    """What one run of the force observer gives.

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) force residual [N]: what the model does not explain.
    x, v : numpy.ndarray
        (T, B) observer table position [m] and velocity [m/s].
    phi : numpy.ndarray
        (T, B) normalised table friction state [-].
    snaps : tuple, optional
        ``(every, z, fr, ps, dbuf)`` plant-state snapshots every ``every`` samples (open-loop windows).
    bad : int
        Sample-and-trial steps the plant's step flagged (not OK; reset and continued; 0: none).
    """
    r: np.ndarray        # (T, B) force residual [N]
    x: np.ndarray        # observer table position [m]
    v: np.ndarray        # observer table velocity [m/s]
    phi: np.ndarray      # normalised table friction state [-]
    snaps: tuple | None = None   # (every, z, fr, ps, dbuf) plant-state snapshots for open-loop windows
    bad: int = 0


SMOOTH_FACTOR = 2.5
"""Default cutoff of the zero-phase smoothing of the measured position, in observer bandwidths."""


def smoothing_hz(spec: ModelSpec, rate: float, f_o: float) -> float:
    """Cutoff [Hz] of the smoothing of the measured position the observer follows:
    ``SMOOTH_FACTOR * f_o``, or (nearly raw) ``0.45 * rate`` for a model with a semi-active
    isolator: its lock mode (~2 kHz) rings after every lock, and with the ring smoothed out of
    the measurement the observer would fight the model's own ring (the isolator transient
    could not be fitted).

    Parameters
    ----------
    spec : ModelSpec
        The model (its stage's ``sai``).
    rate : float
        Control rate [Hz].
    f_o : float
        Observer bandwidth [Hz].

    Returns
    -------
    float
    """
    if spec.preset.stage.sai is not None:
        return 0.45 * rate
    return min(SMOOTH_FACTOR * f_o, 0.45 * rate)


class Observer:
    """Force observer on one :class:`DiagData` (smoothing done once, runs per model).

    Parameters
    ----------
    data : DiagData
        The data; its smoothed position is set here, and the last ``burn_out`` seconds of each
        trial are taken out of its fit and held-out sets.
    bandwidth : float, optional
        Observer bandwidth [Hz] (default rate/25; above ~rate/25 the 3rd-order observer is unstable).
    smooth_hz : float, optional
        Cutoff of the position smoothing [Hz] (:func:`smoothing_hz`; default ``SMOOTH_FACTOR`` x
        the bandwidth, at most 0.45 x rate).
    burn_out : float, optional
        Seconds at each trial's end where the smoothed signal is unreliable.
    """

    def __init__(self, data: DiagData, bandwidth: float | None = None, smooth_hz: float | None = None,
                 burn_out: float = 0.004):
        self.data = data
        self.f_o = float(bandwidth or data.rate / 25.0)
        self.omega = 2.0 * np.pi * self.f_o
        fs = min(smooth_hz or SMOOTH_FACTOR * self.f_o, 0.45 * data.rate)
        if data.ys is None or data.smooth_hz != fs:
            data.ys, data.vs = smooth(data.y, data.rate, fs, data.lengths)
            data.smooth_hz = fs
        # the smoothed signal is unreliable near each trial's end: leave it out of the sets
        n_out = int(round(burn_out * data.rate))
        k = np.arange(data.shape[0])[:, None]
        tail = k >= (data.lengths[None, :] - n_out)
        data.fit &= ~tail
        data.held &= ~tail
        self.u = np.ascontiguousarray(data.u)
        self.ys = np.ascontiguousarray(data.ys)
        self.vs = np.ascontiguousarray(data.vs)
        self.inputs = tuple(np.ascontiguousarray(a) for a in data.plant_inputs())    # d0, d1, mode
        self.fe = np.ascontiguousarray(data.known_force())                        # known external force
        self.calls = 0

    def run(self, spec: ModelSpec, cols=None, snap_every: int = 0, stop: int | None = None) -> ObsResult:
        """Run the observer of model ``spec`` over the data.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        cols : array_like of int, optional
            Trial columns (default all).
        snap_every : int, optional
            Keep the plant state every this many samples (0: none).
        stop : int, optional
            Run the first ``stop`` samples only (the observer is causal: they are what a run over
            every sample gives there); the outputs are zero after them and ``bad`` counts the
            steps before. Default: every sample.

        Returns
        -------
        ObsResult
        """
        c = spec.compiled()
        u, ys, vs, fe, inputs = self.u, self.ys, self.vs, self.fe, self.inputs
        if cols is not None:
            u, ys, vs, fe = (np.ascontiguousarray(a[:, cols]) for a in (u, ys, vs, fe))
            inputs = tuple(np.ascontiguousarray(a[:, cols]) for a in inputs)
        T, B = u.shape
        n = T if stop is None else max(1, min(int(stop), T))
        st = E.new_state(c.pm, ys[0], sai_mode=float(inputs[2][0, 0]))
        outs = [np.empty((T, B)) if n == T else np.zeros((T, B)) for _ in range(4)]
        ns = (n + snap_every - 1) // snap_every if snap_every > 0 else 1
        snaps = [np.zeros((ns,) + a.shape) for a in st[:4]]
        inp = PlantInputs(u[:n], *(a[:n] for a in inputs), fe[:n] if fe is not None and np.any(fe) else np.zeros((0, 0)))
        bad = E.observe(c.pm, c.fc_tot, inp, ys[:n], vs[:n], st, self.omega, c.m_eff, int(snap_every),
                        *(o[:n] for o in outs), *snaps)
        self.calls += 1
        return ObsResult(*outs, snaps=(snap_every, *snaps) if snap_every > 0 else None, bad=int(bad))
