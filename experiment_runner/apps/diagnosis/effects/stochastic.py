"""Stochastic effects: the drive-noise level and the encoder's quantization step. Each is decided by
its own stage of the diagnosis (:mod:`..pipeline`), not by the forward selection: the quantization
from the lattice of the measured positions, the drive noise from the residual spectrum and the
replay's run-to-run consistency."""
from __future__ import annotations

import math

from .base import Case, Effect, Param, Parameter

__all__ = ["NoiseLevel", "Quantization", "NOISE"]

NOISE = 7.1e-4
"""The Ch. 4 presets' drive noise [A RMS]."""


class NoiseLevel(Effect):
    """``noise_level``: the drive's current-noise level, decided by the replay's run-to-run consistency (see the class attributes)."""
    key = "noise_level"
    title = "drive-noise level"
    kind = "stochastic"
    physics = "The drive current noise differs (stage.drive.noise_current_rms)."
    signature = ("the residual floor (spectrum where the model leaves only noise) is above / below the "
                 "floor of recordings simulated from the model")
    parameters = (Parameter("noise_current_rms", "A", "RMS current noise", (1e-7, 10.0)),)
    deal = 17

    def params(self, spec, ctx):
        s = spec.preset.stage.drive.noise_current_rms
        return [Param("noise_current_rms", "A", 0.0, 1.0, s, doc="drive current noise RMS")]

    def nominal(self, spec):
        return {"noise_current_rms": spec.preset.stage.drive.noise_current_rms}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.noise_current_rms": max(0.0, float(theta[0]))})

    def conceal(self, d, draw):
        d["stage"]["drive"]["noise_current_rms"] *= math.exp(draw.sign * draw.size(0.05, 1.6))
        return {"noise_current_rms": d["stage"]["drive"]["noise_current_rms"]}

    def selftest_cases(self):
        return [Case("noise_x3", "noise_level", {"stage.drive.noise_current_rms": NOISE * 3},
                     expect={"noise_current_rms": 2.13e-3})]


class Quantization(Effect):
    """``quantization``: the encoder's step, decided by the measurement lattice (see the class attributes)."""
    key = "quantization"
    title = "encoder quantization"
    kind = "stochastic"
    physics = "The encoder resolution differs (stage.encoder.resolution)."
    signature = "the measured positions sit on a lattice of a different step than the model's"
    parameters = (Parameter("resolution", "m", "quantization step", (1e-12, 1e-3), (1e-9, 1e-1)),)
    deal = 18

    def params(self, spec, ctx):
        q = spec.preset.stage.encoder.resolution
        return [Param("resolution", "m", 0.0, 1e-3, q, doc="encoder quantization step")]

    def nominal(self, spec):
        return {"resolution": spec.preset.stage.encoder.resolution}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.encoder.resolution": max(0.0, float(theta[0]))})

    def conceal(self, d, draw):
        d["stage"]["encoder"]["resolution"] *= math.exp(draw.sign * draw.size(0.1, 3.0))
        return {"resolution": d["stage"]["encoder"]["resolution"]}

    def selftest_cases(self):
        return [Case("quantization_20nm", "quantization", {"stage.encoder.resolution": 2.0e-8},
                     expect={"resolution": 2.0e-8})]
