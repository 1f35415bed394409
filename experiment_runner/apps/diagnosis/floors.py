"""Noise floors of the force residual: what a model's own simulated recordings leave.

The replay's run-to-run floor (what decides) is :meth:`.judge.ReplayJudge.floor`; the floors here
weigh the force observer's fits (:class:`.predict.NoiseFloor`, whitening) and its figures.
"""
from __future__ import annotations

from .data import DiagData
from .evaluator import n_eff
from .model import ModelSpec
from .observer import Observer
from .predict import NoiseFloor, force_resolution, sim_batch, sim_data

__all__ = ["ForceFloor", "light_floor"]


class ForceFloor:
    """Noise floor of a model's force residual on the recorded reference, from two simulated
    recordings: ``a`` defines the whitening (:attr:`noise`), ``b`` checks it (:attr:`check_ms`, ~1)
    and gives the effective sample count of a whitened residual (:attr:`n_eff`).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording (reference, masks, split).
    f_o : float
        Force-observer bandwidth [Hz].
    seeds : sequence of int
        Noise seeds of the two recordings.
    smooth_hz : float
        Cutoff of the measurement's smoothing the observer follows [Hz].
    """

    def __init__(self, spec: ModelSpec, data: DiagData, f_o: float, seeds, smooth_hz: float):
        self.sim_a, self.sim_b = sim_batch(spec, data, seeds[:2])
        self.res_a = Observer(self.sim_a, bandwidth=f_o, smooth_hz=smooth_hz).run(spec)
        self.res_b = Observer(self.sim_b, bandwidth=f_o, smooth_hz=smooth_hz).run(spec)
        mask_a = self.sim_a.fit | self.sim_a.held
        self.noise = NoiseFloor(data.rate, [self.res_a.r], [mask_a], f_max=f_o, rms_min=force_resolution(spec, f_o))
        mask_b = self.sim_b.held if self.sim_b.held.any() else self.sim_b.fit
        self.check_ms = self.noise.ms(self.res_b.r, mask_b)
        self.n_eff = n_eff(self.noise.whiten(self.res_b.r, mask_b), mask_b)


def light_floor(spec: ModelSpec, data: DiagData, f_o: float, seed: int, smooth_hz: float) -> NoiseFloor:
    """Noise floor of ``spec``'s force residual from one simulated recording.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    f_o : float
        Observer bandwidth [Hz].
    seed : int
        Noise seed of the simulated recording.
    smooth_hz : float
        Position smoothing cutoff [Hz].

    Returns
    -------
    NoiseFloor
    """
    sim = sim_data(spec, data, seed)
    r = Observer(sim, bandwidth=f_o, smooth_hz=smooth_hz).run(spec).r
    return NoiseFloor(data.rate, [r], [sim.fit | sim.held], f_max=f_o, rms_min=force_resolution(spec, f_o))
