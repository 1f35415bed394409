"""Forces on the table: position-periodic ripple, a constant offset, a force at a fixed frequency
(dither imbalance) and the semi-active isolator's switching impulse."""
from __future__ import annotations

import math

from .base import Case, Effect, Param, Parameter
from .friction import FORCE, TORQUE

__all__ = ["Ripple", "Offset", "PeriodicForce", "IsolatorTransient", "no_ilc"]


def no_ilc(d: dict) -> None:
    """The SAI stage of preset mapping ``d`` without its iterative learning (Step II): every trial
    alike, as recorded.

    Parameters
    ----------
    d : dict
        A preset mapping (changed in place).
    """
    d["sai_manager"]["ilc"] = None


class Ripple(Effect):
    """``ripple``: a force periodic in the table's position (see the class attributes)."""
    key = "ripple"
    title = "position-periodic force ripple"
    physics = ("Motor cogging / commutation ripple: F = A sin(2 pi x / period + phase) on the table "
               "(stage.force_ripple).")
    signature = ("residual periodic in position (peak in the periodogram of residual vs position), independent "
                 "of velocity sign")
    parameters = (Parameter("a_sin, a_cos", "N", "amplitudes", FORCE, TORQUE, signed=True),
                  Parameter("period", "m", "spatial period", (1e-7, 1.0), (1e-4, 2 * math.pi)))
    deal = 11

    def params(self, spec, ctx):
        per = (ctx.ripple_period or [ctx.x_span / 4])[0]
        amp = ctx.r_rms
        return [Param("a_sin", "N", -10 * amp - 1, 10 * amp + 1, 0.0, doc="sine amplitude"),
                Param("a_cos", "N", -10 * amp - 1, 10 * amp + 1, 0.0, doc="cosine amplitude"),
                Param("period", "m", per / 3, per * 3, per, log=True, doc="spatial period")]

    def starts(self, spec, ctx):
        pers = list(ctx.ripple_period or [])[:3] or [ctx.x_span / 4]
        return [[0.0, 0.0, p] for p in pers]

    def nominal(self, spec):
        return {"a_sin": 0.0, "a_cos": 0.0, "period": None}

    def derived(self, spec, theta):
        return {"amplitude": float(math.hypot(theta[0], theta[1])), "period": float(theta[2]),
                "phase": float(math.atan2(theta[1], theta[0]))}

    def apply(self, spec, theta):
        a, b, per = (float(v) for v in theta)

        def edit(d):
            d["stage"]["force_ripple"] = list(d["stage"]["force_ripple"]) + [
                {"amplitude": math.hypot(a, b), "period": per, "phase": math.atan2(b, a)}]
        return spec.with_changes(edit=edit)

    def conceal(self, d, draw):
        a = draw.size(0.003, 0.6)
        per = draw.random_log(max(draw.stroke / 30, 2e-6), max(draw.stroke / 3, 4e-6))
        d["stage"]["force_ripple"] = [{"amplitude": a, "period": per, "phase": float(draw.rng.uniform(-3, 3))}]
        return {"amplitude": a, "period": per}

    def selftest_cases(self):
        return [Case("ripple", "ripple", {"stage.force_ripple": [{"amplitude": 0.2, "period": 4.0e-4, "phase": 0.3}]},
                     expect={"amplitude": 0.2, "period": 4.0e-4})]


class Offset(Effect):
    """``offset``: a constant force on the table (see the class attributes)."""
    key = "offset"
    title = "constant force offset"
    physics = ("A constant force on the table (cable drag, gravity on a tilted axis, amplifier offset): "
               "stage.force_offset.")
    signature = "a constant residual, independent of state"
    parameters = (Parameter("F_0", "N", "force", FORCE, TORQUE, signed=True),)
    deal = 14

    def params(self, spec, ctx):
        um = ctx.u_max
        return [Param("F_0", "N", -um, um, 0.0, doc="constant force on the table (+x)")]

    def nominal(self, spec):
        return {"F_0": spec.preset.stage.force_offset}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.force_offset": spec.preset.stage.force_offset + float(theta[0])})

    def conceal(self, d, draw):
        f0 = draw.sign * draw.size(0.003, 1.0)
        d["stage"]["force_offset"] = f0
        return {"F_0": f0}

    def selftest_cases(self):
        return [Case("offset", "offset", {"stage.force_offset": 0.3}, expect={"F_0": 0.3}),
                Case("offset_sine", "offset", {"stage.force_offset": 0.3}, expect={"F_0": 0.3}, experiment="sine",
                     seed=124)]


class PeriodicForce(Effect):
    """``dither_imbalance``: a force at a fixed frequency on the table (see the class attributes)."""
    key = "dither_imbalance"
    title = "dither imbalance / periodic force"
    physics = ("A force at a fixed frequency on the table: the net force of imbalanced dither piezos "
               "(VAN, Ch. 3) or a periodic disturbance: stage.periodic_force, A sin(2 pi f t + phase).")
    signature = ("a spectral line of the residual far above the floor at one frequency (the dither "
                 "frequency), present in every regime")
    parameters = (Parameter("a_sin, a_cos", "N", "amplitudes", FORCE, TORQUE, signed=True),
                  Parameter("f", "Hz", "frequency", (0.1, 1e6)))
    deal = 15

    def params(self, spec, ctx):
        f0 = (ctx.line_hz or [50.0])[0]
        amp = ctx.r_rms
        return [Param("a_sin", "N", -10 * amp - 1, 10 * amp + 1, 0.0), Param("a_cos", "N", -10 * amp - 1, 10 * amp + 1, 0.0),
                Param("f", "Hz", f0 * 0.98, f0 * 1.02, f0, doc="frequency of the line")]

    def starts(self, spec, ctx):
        return [[0.0, 0.0, f] for f in (ctx.line_hz or [50.0])[:2]]

    def nominal(self, spec):
        return {"a_sin": 0.0, "a_cos": 0.0, "f": None}

    def derived(self, spec, theta):
        return {"amplitude": float(math.hypot(theta[0], theta[1])), "f": float(theta[2])}

    def apply(self, spec, theta):
        a, b, f = (float(v) for v in theta)

        def edit(d):
            d["stage"]["periodic_force"] = list(d["stage"]["periodic_force"]) + [
                {"amplitude": math.hypot(a, b), "frequency": f, "phase": math.atan2(b, a)}]
        return spec.with_changes(edit=edit)

    def conceal(self, d, draw):
        a = draw.size(0.005, 0.5)
        f = draw.random_log(20.0, 0.4 * draw.rate)
        d["stage"]["periodic_force"] = [{"amplitude": a, "frequency": f, "phase": float(draw.rng.uniform(-3, 3))}]
        return {"amplitude": a, "f": f}

    def selftest_cases(self):
        # net force of two dither piezos whose amplitudes differ by ~7 % (Ch. 3: 3 N dither at 500 Hz each;
        # 0.2 N moves the ~1 kg table ~40 nm p-p, the parasitic vibration of Fig. 3.8 without HC); above the
        # observer bandwidth: a line search case
        return [Case("dither_imbalance_500Hz", "dither_imbalance",
                     {"stage.periodic_force": [{"amplitude": 0.2, "frequency": 500.0, "phase": 0.4}]},
                     expect={"amplitude": 0.2, "f": 500.0})]


class IsolatorTransient(Effect):
    """``isolator_transient``: the impulse of the semi-active isolator's switching (see the class attributes)."""
    key = "isolator_transient"
    title = "isolator switching transient"
    physics = ("SAI locking (Ch. 5, Sec. 5.3): the solenoid armature strikes the lock face and a "
               "force pulse of impulse impact_impulse x (1 - cushioning) reaches the bearing "
               "(stage.sai.impact_impulse; the switching instants are the recorded /stage/isolator "
               "or the model's SAI manager on the recorded reference).")
    signature = ("residual bursts a few ms long right after each compliant -> stiff switch, in the "
                 "settling regime, ringing at the lock mode")
    needs = "a model with stage.sai and a sai_manager"
    parameters = (Parameter("impact_impulse", "N·s", "impulse before cushioning", (1e-9, 10.0), (1e-11, 1.0)),)
    deal = 16
    paired = False

    def applicable(self, spec):
        if spec.preset.stage.sai is None or spec.preset.sai_manager is None:
            return "the model has no semi-active isolator (stage.sai and sai_manager)"
        return None

    def params(self, spec, ctx):
        j = spec.preset.stage.sai.impact_impulse
        return [Param("impact_impulse", "N·s", 0.0, max(30 * j, 1e-2), j,
                      doc="impulse of the armature impact on locking, before cushioning")]

    def nominal(self, spec):
        return {"impact_impulse": spec.preset.stage.sai.impact_impulse}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.sai.impact_impulse": max(0.0, float(theta[0]))})

    def conceal_on(self, stage, law):
        return stage == "sai"

    def conceal(self, d, draw):
        j = d["stage"]["sai"]["impact_impulse"]
        f = math.exp(draw.sign * draw.size(0.1, 2.5))
        d["stage"]["sai"]["impact_impulse"] = j * f
        return {"impact_impulse": j * f}

    def selftest_cases(self):
        # the SAI's armature impact on locking 3x the nominal (less cushioning than assumed)
        return [Case("isolator_transient_x3", "isolator_transient", {"stage.sai.impact_impulse": 3.6e-3},
                     expect={"impact_impulse": 3.6e-3}, experiment="sai_steps", nominal="sai_stage",
                     nominal_edit=no_ilc, seed=141)]
