"""Friction laws: pre-motion (Dahl, generalised Maxwell-slip), the Stribeck curve, bristle damping
(LuGre) and friction without stiction (regularised Coulomb). Each replaces the law of every friction
element, F_C and viscous kept; at most one of them is adopted (exclusive group ``friction_law``)."""
from __future__ import annotations

import copy
import math

import numpy as np

from stage_sim import friction
from stage_sim.config import load_preset, set_dotted

from ..context import Context
from ..model import ModelSpec, coulomb_total, friction_elements
from .base import Case, Effect, Param, Parameter, bearing_f_c, both_bearings, for_bearings, log_uniform
from .friction import FORCE, TORQUE, friction_weights, scaled_variation, virgin_x50

__all__ = ["Dahl", "Gms", "Stribeck", "LugreDamping", "RegularizedCoulomb", "contact_stiffness", "K_SIGMA_NOMINAL",
           "LUGRE_SIGMA1", "PRE_MOTION_LENGTH", "pre_motion_length"]

K_SIGMA_NOMINAL = 1.095e6
"""Dahl stiffness of one bearing of the self-test's nominal (Table 4.3) [N/m]."""

LUGRE_SIGMA1 = 500.0
"""Bristle damping per bearing [N·s/m] of the self-test case ``lugre``: damping ratio ~0.37 of a
bearing's pre-motion mode (0.43 kg on 1.095e6 N/m, 254 Hz), creep time sigma1 / sigma0 = 0.46 ms."""

STIFFNESS = ((1e2, 1e10), (1e-2, 1e6))
"""Plausible pre-motion stiffnesses: linear [N/m], rotary [N·m/rad]."""

PRE_MOTION_LENGTH = {"linear": 1e-6, "rotary": 1e-4}
"""The pre-motion length [m] or [rad] a model without pre-motion is given when a law needs a
contact stiffness (``F_C / length``; the start of ``dahl``'s search, which spans three decades
either side): the seed's bearings reach half their friction within about 1 um (Table 4.3:
x_50 ~ 0.6 um); a rotary axis's pre-rolling angle is of the order of 10-1000 urad."""


def pre_motion_length(kind: str) -> float:
    """The default pre-motion length of an axis of ``kind`` (:data:`PRE_MOTION_LENGTH`).

    Parameters
    ----------
    kind : {"linear", "rotary"}
        The axis.

    Returns
    -------
    float
        [m] or [rad].

    Examples
    --------
    >>> pre_motion_length("linear"), pre_motion_length("rotary")
    (1e-06, 0.0001)
    """
    return PRE_MOTION_LENGTH["rotary" if kind == "rotary" else "linear"]


def contact_stiffness(spec: ModelSpec) -> float:
    """The model's total pre-motion stiffness at rest [N/m] (:func:`stage_sim.friction.initial_stiffness`
    summed), or -- friction without pre-motion -- that of the axis' default pre-motion length at F_C
    (:data:`PRE_MOTION_LENGTH`).

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    float
    """
    k0 = float(sum(friction.initial_stiffness(fr) for _, fr in friction_elements(spec.preset)))
    return k0 if k0 > 0 else max(coulomb_total(spec.preset), 1e-3) / pre_motion_length(spec.preset.stage.kind)


def _short(x: float) -> str:
    """``x`` as ``3e-8`` (one significant digit, no exponent padding)."""
    return f"{x:.0e}".replace("e-0", "e-").replace("e+0", "e")


def _no_friction(spec) -> str | None:
    return None if friction_elements(spec.preset) else "the model has no friction element"


class Dahl(Effect):
    """``dahl``: pre-motion friction as a Dahl contact (see the class attributes)."""
    key = "dahl"
    title = "pre-motion friction (Dahl)"
    physics = ("Friction builds up over a contact stiffness k_sigma after each reversal before gross sliding "
               "(Dahl, Eq. 1.1/4.3); replaces the model's friction elements by Dahl elements (F_C kept).")
    signature = ("residual concentrated just after motion reversals and in settling / in-position; vs displacement "
                 "since the last reversal it rises or falls over ~F_C/k_sigma and then vanishes")
    parameters = (Parameter("k_sigma", "N/m", "total pre-motion stiffness", *STIFFNESS),)
    exclusive = ("friction_law",)
    deal = 6

    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element to give pre-motion"

    def params(self, spec, ctx):
        k0 = contact_stiffness(spec)
        return [Param("k_sigma", "N/m", k0 * 1e-3, k0 * 1e3, k0, log=True,
                      doc="total pre-motion (contact) stiffness of the Dahl model")]

    def starts(self, spec, ctx):
        k0 = self.params(spec, ctx)[0].x0
        return [[k0 * s] for s in (1.0, 0.3, 3.0)] if any(
            fr.model == "dahl" for _, fr in friction_elements(spec.preset)) else [[k0 * s] for s in (0.1, 1.0, 10.0)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        return {"k_sigma": contact_stiffness(spec) if all(fr.model == "dahl" for _, fr in els) and els else None}

    def derived(self, spec, theta):
        sp = self.apply(spec, theta)
        return {"x_50": virgin_x50([fr.model_dump() for _, fr in friction_elements(sp.preset)])}

    def apply(self, spec, theta):
        k = float(theta[0])
        els, w = friction_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                f_c = max(fr.f_c, 1e-9)
                set_dotted(d, path, friction.dahl.element(k * we, f_c, getattr(fr, "shape", 1.0), fr.viscous,
                                                          **scaled_variation(fr, f_c)))
        return spec.with_changes(edit=edit)

    def conceal_on(self, stage, law):
        return law in ("dahl", "coulomb")

    def conceal(self, d, draw):
        if draw.friction == "dahl":
            f = math.exp(draw.sign * draw.size(0.03, 2.5))
            for_bearings(d, lambda fr, b: fr.update(k_sigma=fr["k_sigma"] * f))
            return {"k_sigma": sum(b["friction"]["k_sigma"] for b in d["stage"]["bearings"])}
        # Coulomb nominal: the truth has pre-motion over x_pre = F_C / k_sigma
        fc = bearing_f_c(d)
        x_pre = log_uniform(1 - draw.q, 3e-8, 3e-5)
        for_bearings(d, lambda fr, b: b.update(friction=friction.dahl.element(
            fr["f_c"] / x_pre, fr["f_c"], 1.0, fr.get("viscous", 0.0))))
        return {"k_sigma": fc / x_pre}

    def selftest_cases(self):
        return [Case("dahl_k_x0.4", "dahl", both_bearings("friction.k_sigma", K_SIGMA_NOMINAL * 0.4),
                     expect={"k_sigma": 2.19e6 * 0.4}, experiment="steps")]


class Gms(Effect):
    """Maxwell-slip / Prandtl-Ishlinskii: parallel elasto-slip blocks with fitted capacities.

    The slip displacements: a model whose friction is already Maxwell-slip keeps its own (scaled by
    one common factor ``x_scale``, i.e. all its stiffnesses by ``1/x_scale``: a pre-motion length
    that differs, the GMS form of the Dahl ``k_sigma``), so the nominal is one point of the family
    and a small change of it a small step; any other model gets :attr:`N` log-spaced ones over
    :meth:`slip_range`."""
    key = "gms"
    title = "pre-motion friction (GMS / Maxwell-slip)"
    N = 12
    SLIP_MIN = 0.03
    """Shortest slip displacement of the log-spaced blocks, in the axis' pre-motion lengths
    (:data:`PRE_MOTION_LENGTH`: 30 nm, 3 urad; at least 3 encoder steps)."""
    SLIP_MAX = 100.0
    """Longest slip displacement, in the axis' pre-motion lengths (100 um, 10 mrad; at least 30
    times the shortest)."""
    physics = ("Generalized Maxwell-slip (Eq. 4.4): parallel elasto-slip blocks with fitted capacities (a "
               "Prandtl-Ishlinskii operator, linear in the capacities); replaces the friction elements. A Maxwell-slip "
               "model keeps its own blocks, their slip displacements scaled by one factor x_scale; any other gets 12 "
               "blocks with log-spaced slip displacements.")
    signature = ("like Dahl, but the pre-motion transition has a different shape (long tail: blocks slipping after "
                 "tens of um); vs displacement since reversal it is piecewise linear")
    parameters = (Parameter("x_scale", "-", "a Maxwell-slip model's own slip displacements scaled (its stiffnesses "
                            "by 1/x_scale)", (0.1, 10.0)),
                  Parameter("F_1..F_N", "N", f"block capacities (sum = F_C); without a Maxwell-slip model {N} "
                            f"blocks, slip displacements log-spaced {_short(SLIP_MIN * PRE_MOTION_LENGTH['linear'])} "
                            f"(or 3 encoder steps) ... {_short(SLIP_MAX * PRE_MOTION_LENGTH['linear'])} m "
                            f"({_short(SLIP_MIN * PRE_MOTION_LENGTH['rotary'])} ... "
                            f"{_short(SLIP_MAX * PRE_MOTION_LENGTH['rotary'])} rad)", (1e-6, 1e4), (1e-8, 1e3)))
    exclusive = ("friction_law", "coulomb_level")
    deal = 7
    _d = None

    applicable = staticmethod(_no_friction)

    @classmethod
    def slip_range(cls, resolution: float, axis: str = "linear") -> tuple[float, float]:
        """(shortest, longest) slip displacement [m] or [rad] of the log-spaced blocks for an
        encoder step ``resolution`` on an ``axis``.

        Parameters
        ----------
        resolution : float
            Encoder step [m] or [rad] (0: ideal).
        axis : {"linear", "rotary"}
            The axis (its pre-motion length scales the range).

        Returns
        -------
        tuple of float

        Examples
        --------
        >>> Gms.slip_range(0.0), Gms.slip_range(1e-7)
        ((3e-08, 0.0001), (3e-07, 0.0001))
        >>> [float(f"{x:.3g}") for x in Gms.slip_range(1e-7, "rotary")]
        [3e-06, 0.01]
        """
        length = pre_motion_length(axis)
        # rounded: 0.03 * 1e-6 is 3.0000000000000004e-08 in binary; the linear range stays 3e-8 exactly
        lo = max(3 * resolution, round(cls.SLIP_MIN * length, 15))
        return lo, max(round(cls.SLIP_MAX * length, 15), 30 * lo)

    @staticmethod
    def own_slips(spec) -> np.ndarray | None:
        """The slip displacements ``alpha F_C / k`` the model's Maxwell-slip elements share (None
        when any friction element is of another law or the elements' blocks differ).

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        numpy.ndarray or None
        """
        els = friction_elements(spec.preset)
        if not els or any(fr.model != "gms" for _, fr in els):
            return None
        ds = [np.asarray(fr.alpha) * fr.f_c / np.maximum(np.asarray(fr.k), 1e-300) for _, fr in els]
        if any(len(d) != len(ds[0]) or not np.allclose(d, ds[0], rtol=1e-6) for d in ds):
            return None
        return ds[0]

    def deltas(self, ctx: Context) -> np.ndarray:
        """The :attr:`N` log-spaced slip displacements [m] for a recording of context ``ctx``.

        Parameters
        ----------
        ctx : Context
            What was located on the recording.

        Returns
        -------
        numpy.ndarray
        """
        lo, hi = self.slip_range(ctx.resolution, ctx.axis)
        return np.logspace(np.log10(lo), np.log10(hi), self.N)

    @staticmethod
    def capacities(spec) -> np.ndarray:
        """The model's own block capacities (totals over the elements), when it has its own slips.

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        numpy.ndarray
            Per block [N].
        """
        els = friction_elements(spec.preset)
        return np.sum([np.asarray(fr.alpha) * fr.f_c for _, fr in els], axis=0)

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-3)
        own = self.own_slips(spec)
        if own is not None:
            caps = self.capacities(spec)
            return [Param("x_scale", "-", 0.1, 10.0, 1.0, log=True,
                          doc="the model's slip displacements scaled (its block stiffnesses by 1/x_scale)")] + [
                Param(f"F_{i + 1}", "N", 1e-4 * fc, 3 * fc, max(float(c), 1e-4 * fc), physical_lo=True,
                      doc=f"capacity of the block slipping after {d * 1e6:.3g} um (times x_scale)")
                for i, (d, c) in enumerate(zip(own, caps))]
        d = self.deltas(ctx)
        return [Param(f"F_{i + 1}", "N", 1e-4 * fc, 3 * fc, fc / self.N, physical_lo=True,
                      doc=f"capacity of the block slipping after {d[i] * 1e6:.3g} um") for i in range(self.N)]

    def starts(self, spec, ctx):
        if self.own_slips(spec) is not None:
            return [[p.x0 for p in self.params(spec, ctx)]]
        fc = max(coulomb_total(spec.preset), 1e-3)
        d = self.deltas(ctx)
        out = [[fc / self.N] * self.N]
        # the nominal model's own virgin curve sampled at the grid (if it has pre-motion)
        els = friction_elements(spec.preset)
        x50 = virgin_x50([fr.model_dump() for _, fr in els])
        if np.isfinite(x50):
            w = np.exp(-0.5 * (np.log(d / x50) / 1.0) ** 2)
            out.append(list(fc * w / w.sum()))
        return out

    def nominal(self, spec):
        if self.own_slips(spec) is not None:
            return {"x_scale": 1.0, **{f"F_{i + 1}": float(c) for i, c in enumerate(self.capacities(spec))}}
        return {f"F_{i + 1}": None for i in range(self.N)}

    def _split(self, spec, theta):
        """(slip displacements, capacities) of the parameter vector ``theta`` on ``spec``."""
        own = self.own_slips(spec)
        theta = np.asarray(theta, float)
        if own is not None:
            return own * float(theta[0]), theta[1:]
        d = self._d if self._d is not None else self.deltas(Context())
        return d, theta

    def derived(self, spec, theta):
        sp = self.apply(spec, theta)
        els = [fr.model_dump() for _, fr in friction_elements(sp.preset)]
        return {"F_C": float(np.sum(self._split(spec, theta)[1])), "x_50": virgin_x50(els),
                "k_0": float(sum(sum(fr["k"]) for fr in els if fr["model"] == "gms"))}

    def apply(self, spec, theta):
        d, F = self._split(spec, theta)
        F = np.maximum(F, 1e-9)
        fc = F.sum()
        els, w = friction_weights(spec)

        def edit(dd):
            for (path, fr), we in zip(els, w):
                set_dotted(dd, path, friction.gms.element(list(F * we / d), list(F / fc), fc * we, fr.viscous,
                                                          **scaled_variation(fr, fc * we)))
        return spec.with_changes(edit=edit)

    def bound(self, ctx: Context):
        e = copy.copy(self)
        e._d = self.deltas(ctx)
        return e

    @staticmethod
    def table_4_4() -> dict:
        """The Maxwell-slip bearing friction of Table 4.4 (preset ``fi_stage_nofi_gms``) as a mapping.

        Returns
        -------
        dict
        """
        return load_preset("fi_stage_nofi_gms").stage.bearings[0].friction.model_dump(mode="json")

    def conceal_on(self, stage, law):
        return law in ("dahl", "gms")

    def conceal(self, d, draw):
        g = self.table_4_4()
        if draw.friction == "gms":
            f = math.exp(draw.sign * draw.size(0.03, 2.5))
        else:          # Dahl nominal: the GMS of Table 4.4, its pre-motion length scaled
            f = math.exp(draw.sign * draw.size(0.02, 2.0))
        g["k"] = [k * f for k in g["k"]]
        for_bearings(d, lambda fr, b: b.update(friction=dict(g)))
        return self.truth(b["friction"] for b in d["stage"]["bearings"])

    @staticmethod
    def truth(elements) -> dict:
        """The truth values (total F_C, virgin x_50) of Maxwell-slip element mappings.

        Parameters
        ----------
        elements : iterable of dict
            Maxwell-slip element mappings.

        Returns
        -------
        dict
        """
        els = list(elements)
        return {"F_C": float(sum(x["f_c"] * sum(x["alpha"]) for x in els)), "x_50": virgin_x50(els)}

    def selftest_cases(self):
        g = load_preset("fi_stage_nofi_gms")

        def edit(d):
            table = g.model_dump(mode="json")
            for i in (0, 1):
                d["stage"]["bearings"][i]["friction"] = table["stage"]["bearings"][i]["friction"]
        return [Case("gms_table_4.4", "gms", edit=edit, expect=self.truth(b.friction.model_dump() for b in g.stage.bearings))]


class Stribeck(Effect):
    """``stribeck``: the Stribeck effect, as LuGre with the model's bristle stiffness and damping (see the class attributes)."""
    key = "stribeck"
    title = "Stribeck effect (LuGre)"
    physics = ("Friction higher at low sliding speed: LuGre with g(v) = F_C + (F_S - F_C) exp(-(v/v_s)^2), "
               "sigma0 = the model's pre-motion stiffness.")
    signature = ("residual with the sign of velocity, largest at low speed (just after reversals, before "
                 "constant velocity), vanishing above a few v_s")
    parameters = (Parameter("F_S", "N", "static force", FORCE, TORQUE),
                  Parameter("v_s", "m/s", "Stribeck velocity", (1e-8, 1.0), (1e-6, 1e2)))
    exclusive = ("friction_law",)
    deal = 8

    applicable = staticmethod(_no_friction)

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-6)
        vmax = max(ctx.v_max, 1e-9)
        return [Param("F_S", "N", 1.0 * fc, 6 * fc, 1.3 * fc, doc="total static (break-away) force"),
                Param("v_s", "m/s", vmax * 1e-4, vmax, 0.05 * vmax, log=True, doc="Stribeck velocity")]

    def starts(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-6)
        vmax = max(ctx.v_max, 1e-9)
        return [[1.5 * fc, vmax * s] for s in (0.01, 0.05, 0.2)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        if els and all(fr.model == "lugre" for _, fr in els):
            return {"F_S": float(sum(fr.f_s for _, fr in els)), "v_s": els[0][1].v_s}
        return {"F_S": None, "v_s": None}

    def apply(self, spec, theta):
        fs, vs = float(theta[0]), float(theta[1])
        els, w = friction_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                k = friction.initial_stiffness(fr) or max(fr.f_c, 1e-9) / pre_motion_length(spec.preset.stage.kind)
                f_c = max(fr.f_c, 1e-9)
                set_dotted(d, path, friction.lugre.element(
                    k, f_c, max(fs * we, fr.f_c * 1.0001, 1e-9), vs, sigma1=getattr(fr, "sigma1", 0.0),
                    viscous=fr.viscous, exponent=getattr(fr, "exponent", 2.0), **scaled_variation(fr, f_c)))
        return spec.with_changes(edit=edit)

    def conceal(self, d, draw):
        fc = bearing_f_c(d)
        m = draw.size(0.02, 2.0)
        vs = draw.random_log(0.02, 0.3) * draw.v_max

        def lug(fr, b):
            k = fr.get("k_sigma") or (sum(fr["k"]) if fr["model"] == "gms" else
                                      fr["f_c"] / pre_motion_length(d["stage"].get("kind", "linear")))
            b["friction"] = friction.lugre.element(k, fr["f_c"], fr["f_c"] * (1 + m), vs, sigma1=0.0,
                                                   viscous=fr.get("viscous", 0.0))
        for_bearings(d, lug)
        return {"F_S": fc * (1 + m), "v_s": vs}

    def selftest_cases(self):
        def edit(d):
            for b in d["stage"]["bearings"]:
                f = b["friction"]
                b["friction"] = friction.lugre.element(f["k_sigma"], f["f_c"], 1.6 * f["f_c"], 1.0e-3, sigma1=0.0,
                                                       viscous=0.0)
        return [Case("stribeck", "stribeck", edit=edit, expect={"F_S": 1.6 * 5.31, "v_s": 1.0e-3})]


class LugreDamping(Effect):
    """Pre-motion friction with bristle damping (LuGre, Canudas de Wit et al. 1995): each friction
    element becomes ``sigma0 z + sigma1 dz/dt`` with ``dz/dx = 1 - sigma0 sgn(v) z / g(v)``;
    ``sigma0`` and ``sigma1`` are fitted as totals shared in proportion to F_C, F_C and viscous
    kept, the Stribeck curve kept from a LuGre element (else none: F_S = F_C, where sigma1 = 0
    is Dahl with shape 1). At rest the contact is a Kelvin-Voigt solid: a force change below
    F_C is followed by creep over ``tau = sigma1 / sigma0`` instead of an instant deflection,
    and the pre-motion resonance is damped."""
    key = "lugre"
    title = "pre-motion friction with bristle damping (LuGre)"
    physics = ("LuGre bristles (Canudas de Wit et al. 1995): F = sigma0 z + sigma1 dz/dt, dz/dx = 1 - sigma0 "
               "sgn(v) z / g(v), in every friction element (F_C, viscous and a LuGre Stribeck curve kept; "
               "else F_S = F_C). At rest the contact is a spring and damper: after a force change below "
               "F_C the stage creeps over tau = sigma1 / sigma0 instead of deflecting at once, and the "
               "pre-motion resonance is damped.")
    signature = ("like Dahl, plus a creep of ~tau after each force change during holds and settling, and a "
                 "damped (shorter) ringing of the pre-motion mode; residual correlated with the velocity "
                 "in the first micrometres after reversals")
    parameters = (Parameter("sigma0", "N/m", "total bristle stiffness", *STIFFNESS),
                  Parameter("sigma1", "N·s/m", "total bristle damping", (1e-3, 1e6), (1e-7, 1e2)))
    exclusive = ("friction_law",)
    deal = 19

    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element to give pre-motion"

    def params(self, spec, ctx):
        k0 = contact_stiffness(spec)
        return [Param("sigma0", "N/m", k0 * 1e-2, k0 * 1e2, k0, log=True,
                      doc="total bristle (pre-motion) stiffness"),
                Param("sigma1", "N·s/m", k0 * 1e-7, k0 * 1e-2, k0 * 1e-4, log=True,
                      doc="total bristle damping (creep time sigma1 / sigma0: 0.1 us ... 10 ms)")]

    def starts(self, spec, ctx):
        k0 = contact_stiffness(spec)
        return [[k0, k0 * t] for t in (1e-5, 1e-4, 1e-3, 5e-3)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        if els and all(fr.model == "lugre" for _, fr in els):
            return {"sigma0": contact_stiffness(spec), "sigma1": float(sum(fr.sigma1 for _, fr in els))}
        return {"sigma0": None, "sigma1": None}

    def derived(self, spec, theta):
        return {"tau": float(theta[1]) / float(theta[0])}

    def apply(self, spec, theta):
        s0, s1 = float(theta[0]), float(theta[1])
        els, w = friction_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                fc = max(fr.f_c, 1e-9)
                lugre = fr.model == "lugre"
                set_dotted(d, path, friction.lugre.element(
                    s0 * we, fc, fr.f_s if lugre else fc, fr.v_s if lugre else 1e-3, sigma1=s1 * we,
                    viscous=fr.viscous, exponent=fr.exponent if lugre else 2.0, **scaled_variation(fr, fc)))
        return spec.with_changes(edit=edit)

    def conceal_on(self, stage, law):
        return law in ("dahl", "coulomb")       # one element per bearing to rewrite

    def conceal(self, d, draw):
        tau = draw.size(2e-5, 1e-3)            # creep time sigma1 / sigma0 [s]

        def lug(fr, b):
            k = fr.get("k_sigma") or fr["f_c"] / pre_motion_length(d["stage"].get("kind", "linear"))
            b["friction"] = friction.lugre.element(k, fr["f_c"], fr["f_c"], 1e-3, sigma1=tau * k,
                                                   viscous=fr.get("viscous", 0.0))
        for_bearings(d, lug)
        els = [b["friction"] for b in d["stage"]["bearings"]]
        return {"sigma0": sum(x["sigma0"] for x in els), "sigma1": sum(x["sigma1"] for x in els)}

    def selftest_cases(self):
        def edit(d):
            for b in d["stage"]["bearings"]:
                f = b["friction"]
                b["friction"] = friction.lugre.element(f["k_sigma"], f["f_c"], f["f_c"], 1.0e-3, sigma1=LUGRE_SIGMA1,
                                                       viscous=f["viscous"])
        # bristle damping: the Dahl bearings' pre-motion becomes a Kelvin-Voigt contact
        return [Case("lugre", "lugre", edit=edit, expect={"sigma0": 2.19e6, "sigma1": 2 * LUGRE_SIGMA1},
                     experiment="steps")]


class RegularizedCoulomb(Effect):
    """Friction with a smooth zero-velocity transition: each friction element becomes
    ``F_C tanh(v / v_reg) + viscous v`` (:mod:`stage_sim.friction.regularized`, F_C and viscous
    kept). Below ``v_reg`` the friction is a steep damper ``F_C / v_reg`` instead of a stick: a
    force below F_C at rest makes the stage creep at ``v_reg atanh(F / F_C)``."""
    key = "regularized_coulomb"
    title = "smooth zero-velocity friction (regularised Coulomb)"
    physics = ("Friction without stiction: F = F_C tanh(v / v_reg) + c v in every friction element "
               "(F_C, c kept). Near rest it acts as a steep damper F_C / v_reg, so a force below F_C "
               "makes the stage creep instead of sticking.")
    signature = ("residual during holds and dwell where the model sticks: the stage creeps under "
                 "forces below F_C; residual vs velocity is a step of width ~v_reg rounding the "
                 "Coulomb step at v = 0")
    parameters = (Parameter("v_reg", "m/s", "regularisation velocity", (1e-9, 1.0), (1e-7, 1e2)),)
    exclusive = ("friction_law",)
    deal = 20

    applicable = staticmethod(_no_friction)

    def params(self, spec, ctx):
        vmax = max(ctx.v_max, 1e-9)
        return [Param("v_reg", "m/s", vmax * 1e-6, vmax * 0.3, vmax * 1e-2, log=True,
                      doc="regularisation velocity (F = 76 % of F_C at v_reg)")]

    def starts(self, spec, ctx):
        vmax = max(ctx.v_max, 1e-9)
        return [[vmax * s] for s in (1e-4, 1e-3, 1e-2, 0.1)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        if els and all(fr.model == "regularized_coulomb" for _, fr in els):
            return {"v_reg": els[0][1].v_reg}
        return {"v_reg": None}

    def derived(self, spec, theta):
        fc = coulomb_total(spec.preset)
        return {"c_rest": fc / float(theta[0]) if fc > 0 else float("nan")}

    def apply(self, spec, theta):
        v_reg = float(theta[0])
        els = friction_elements(spec.preset)

        def edit(d):
            for path, fr in els:
                set_dotted(d, path, friction.regularized.element(fr.f_c, v_reg, fr.viscous,
                                                                 **scaled_variation(fr, fr.f_c)))
        return spec.with_changes(edit=edit)

    def conceal_on(self, stage, law):
        return law in ("dahl", "coulomb")       # one element per bearing to rewrite

    def conceal(self, d, draw):
        v = draw.size(1e-4, 3e-2) * draw.v_max
        for_bearings(d, lambda fr, b: b.update(friction=friction.regularized.element(fr["f_c"], v,
                                                                                     fr.get("viscous", 0.0))))
        return {"v_reg": v}

    def selftest_cases(self):
        def edit(d):
            for b in d["stage"]["bearings"]:
                f = b["friction"]
                b["friction"] = friction.regularized.element(f["f_c"], 1.0e-4, f["viscous"])
        # friction without stiction: the bearings creep at v_reg atanh(F/F_C) under the servo's holding
        # force instead of holding elastically (Dahl)
        return [Case("regularized_coulomb", "regularized_coulomb", edit=edit, expect={"v_reg": 1.0e-4},
                     experiment="steps")]
