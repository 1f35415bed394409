"""The drive: its force constant and its delay (whole control periods and a fraction of one)."""
from __future__ import annotations

import math

from .base import Case, Effect, Param, Parameter

__all__ = ["ForceConstant", "Delay", "FractionalDelay"]


class ForceConstant(Effect):
    """``force_constant``: the motor force per command differs from nominal (see the class attributes)."""
    key = "force_constant"
    title = "force-constant error"
    physics = "The motor force per command differs from nominal (stage.drive.force_constant_ratio)."
    signature = "residual proportional to the command itself (residual vs command is a straight line)"
    parameters = (Parameter("ratio", "-", "true/nominal force constant", (0.3, 3.0)),)
    known_quantity = True
    in_drive = True
    deal = 4

    def params(self, spec, ctx):
        r = spec.preset.stage.drive.force_constant_ratio
        return [Param("ratio", "-", 0.3 * r, 3 * r, r, doc="true / nominal motor force constant")]

    def nominal(self, spec):
        return {"ratio": spec.preset.stage.drive.force_constant_ratio}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.force_constant_ratio": float(theta[0])})

    def conceal(self, d, draw):
        r = 1 + draw.sign * draw.size(0.003, 0.5)
        d["stage"]["drive"]["force_constant_ratio"] = r
        return {"ratio": r}

    def selftest_cases(self):
        return [Case("force_constant_0.8", "force_constant", {"stage.drive.force_constant_ratio": 0.8},
                     expect={"ratio": 0.8})]


class Delay(Effect):
    """``delay``: a whole number of control periods between command and force (see the class attributes)."""
    key = "delay"
    title = "actuator delay"
    kind = "integer"
    MAX = 12
    physics = "The drive applies the command some samples late (stage.drive.delay_samples)."
    signature = ("residual correlated with the rate of change of the command (largest where the command changes "
                 "fast: reversals, starts of moves); phase lag growing with frequency")
    parameters = (Parameter("delay_samples", "samples", "delay", (0, MAX)),)
    never_paired_with = ("fractional_delay",)
    in_drive = True
    resolution = 0.5
    deal = 5

    def params(self, spec, ctx):
        d = spec.preset.stage.drive.delay_samples
        return [Param("delay_samples", "samples", 0, self.MAX, d, doc="drive delay in control samples")]

    def nominal(self, spec):
        return {"delay_samples": spec.preset.stage.drive.delay_samples}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.delay_samples": int(round(theta[0]))})

    def conceal(self, d, draw):
        n = int(min(6, math.floor(draw.size(1.0, 7.0))))
        d["stage"]["drive"]["delay_samples"] = n
        return {"delay_samples": n}

    def selftest_cases(self):
        return [Case("delay_3", "delay", {"stage.drive.delay_samples": 3}, expect={"delay_samples": 3})]


class FractionalDelay(Effect):
    """A fraction of a control period more or less drive delay than the model has: the total
    ``delay_samples + delay_fraction`` shifted by ``shift`` in (-1, 1) (the plant's exact delayed
    zero-order hold). The whole samples are the integer :class:`Delay`'s: a delay of 1.4 samples
    is named as ``delay`` 1 and then ``fractional_delay`` +0.4 on top (a whole-sample delay the
    data show stays that, a fraction adopted only if it adds beyond the floor)."""
    key = "fractional_delay"
    title = "fractional actuator delay"
    physics = ("The drive delay is not a whole number of control periods: the model's delay shifted by "
               "a fraction of a period (stage.drive.delay_samples + stage.drive.delay_fraction; exact "
               "delayed zero-order hold: the command of sample k acts from k + delay). On top of the "
               "whole-sample actuator delay.")
    signature = ("as the actuator delay; the phase lag of the command -> measurement transfer grows "
                 "linearly with frequency, by 360 deg x delay x f / rate")
    parameters = (Parameter("shift", "samples", "delay added to the model's (-1 ... 1)", (-1.0, 1.0)),)
    never_paired_with = ("delay",)
    continues = ("delay",)
    in_drive = True
    deal = 21

    @staticmethod
    def total(spec):
        """The model's drive delay [control periods].

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        float
        """
        d = spec.preset.stage.drive
        return d.delay_samples + d.delay_fraction

    def params(self, spec, ctx):
        # a total delay below zero is no delay: the shift ends there (flat beyond, where the
        # observer's fit would wander)
        lo = -min(0.999, self.total(spec))
        return [Param("shift", "samples", lo, 0.999, 0.3, doc="delay added to the model's, in control periods",
                      physical_lo=lo > -0.999)]

    def starts(self, spec, ctx):
        return [[0.3], [-0.3]] if self.total(spec) > 0 else [[0.3], [0.7]]

    def nominal(self, spec):
        return {"shift": 0.0}

    def apply(self, spec, theta):
        tau = max(self.total(spec) + float(theta[0]), 0.0)
        whole = int(math.floor(tau))
        return spec.with_changes({"stage.drive.delay_samples": whole,
                                  "stage.drive.delay_fraction": min(tau - whole, 1.0 - 1e-12)})

    def conceal(self, d, draw):
        f = draw.size(0.05, 0.9)
        d["stage"]["drive"]["delay_fraction"] = f
        return {"shift": f}

    def selftest_cases(self):
        # a whole-sample and a fractional drive delay (2.4 samples): both named
        return [Case("delay_2.4", ("delay", "fractional_delay"),
                     {"stage.drive.delay_samples": 2, "stage.drive.delay_fraction": 0.4},
                     expect={"delay": {"delay_samples": 2}, "fractional_delay": {"shift": 0.4}}, seed=151)]
