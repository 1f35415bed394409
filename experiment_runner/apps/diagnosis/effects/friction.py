"""Friction level and its variations: Coulomb level, viscous friction, position-dependent and
direction-asymmetric friction; and what every friction effect shares (the friction elements'
weights, their variation fields)."""
from __future__ import annotations

import copy

import numpy as np

from stage_sim import friction

from ..context import Context
from ..model import ModelSpec, coulomb_total, friction_elements, viscous_total
from .base import Case, Effect, Param, Parameter, bearing_f_c, both_bearings, for_bearings

__all__ = ["Coulomb", "Viscous", "PositionFriction", "Asymmetry", "friction_weights", "scaled_variation",
           "edit_elements", "virgin_x50", "F_C_NOMINAL"]

F_C_NOMINAL = 2.655
"""Coulomb force of one bearing of the self-test's nominal (Table 4.3) [N]."""

FORCE = (1e-3, 1e4)
"""Plausible force magnitudes on a linear axis [N]."""
TORQUE = (1e-5, 1e3)
"""Plausible torque magnitudes on a rotary axis [N·m]."""


def friction_weights(spec: ModelSpec):
    """``(elements, weights)``: the friction elements of ``spec`` (:func:`..model.friction_elements`)
    and each one's share of their total Coulomb force (equal shares when none has one).

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    tuple
        ``(elements, weights)``; the weights sum to 1.
    """
    els = friction_elements(spec.preset)
    fcs = np.array([max(getattr(fr, "f_c", 0.0), 0.0) for _, fr in els])
    if len(els) == 0:
        return els, fcs
    w = fcs / fcs.sum() if fcs.sum() > 0 else np.full(len(els), 1.0 / len(els))
    return els, w


def scaled_variation(fr, f_c_new: float) -> dict:
    """The friction variation fields of element ``fr`` for an element of Coulomb force ``f_c_new``
    (force-like fields scaled with it, so the relative variation is kept).

    Parameters
    ----------
    fr : stage_sim.friction.base.FrictionVariation
        A friction element.
    f_c_new : float
        The new Coulomb force [N].

    Returns
    -------
    dict
    """
    s = f_c_new / fr.f_c if fr.f_c > 0 else 1.0
    return {"f_c_difference": fr.f_c_difference * s, "viscous_difference": fr.viscous_difference,
            "f_c_gradient": fr.f_c_gradient * s, "f_c_curvature": fr.f_c_curvature * s,
            "position_center": fr.position_center}


def element_node(d: dict, path: str) -> dict:
    """The mapping at dotted ``path`` of preset mapping ``d`` (list indices as numbers).

    Parameters
    ----------
    d : dict
        A preset mapping.
    path : str
        Dotted path, e.g. ``stage.bearings.0.friction``.

    Returns
    -------
    dict
    """
    node = d
    for k in path.split("."):
        node = node[int(k)] if isinstance(node, list) else node[k]
    return node


def edit_elements(spec: ModelSpec, fn):
    """``edit`` callable applying ``fn(node, fr, weight)`` to every friction element's mapping.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    fn : callable
        ``fn(node, fr, weight)``: the element's mapping, its config and its share of the Coulomb force.

    Returns
    -------
    callable
        ``edit(d)`` for :meth:`.model.ModelSpec.with_changes`.
    """
    els, w = friction_weights(spec)

    def edit(d):
        for (path, fr), we in zip(els, w):
            fn(element_node(d, path), fr, float(we))
    return edit


def virgin_x50(fr_dump: list) -> float:
    """Displacement [m] at which the summed virgin curve of friction elements (configs or their
    dicts) reaches half their total sliding force (pre-motion length scale; Dahl: ln2 F_C/k_sigma).
    Each law's virgin curve and sliding force come from its module (:mod:`stage_sim.friction`).

    Parameters
    ----------
    fr_dump : list
        Friction element configs or their mappings.

    Returns
    -------
    float

    Examples
    --------
    >>> x50 = virgin_x50([friction.dahl.element(1e6, 1.0)])     # ln2 um on a grid of 2000 per 8 decades
    >>> bool(abs(x50 / (np.log(2) * 1e-6) - 1) < 0.01)
    True
    """
    xs = np.logspace(-10, -2, 2000)
    tot = np.zeros_like(xs)
    fc = 0.0
    for fr in fr_dump:
        law = friction.law(fr["model"] if isinstance(fr, dict) else fr)
        cfg = law.Schema.model_construct(**fr) if isinstance(fr, dict) else fr
        tot += law.virgin(cfg, xs)
        fc += law.sliding_force(cfg)
    if fc <= 0:
        return float("nan")
    i = int(np.searchsorted(tot, 0.5 * fc))
    return float(xs[min(i, len(xs) - 1)])


class Coulomb(Effect):
    """``coulomb``: the bearings' Coulomb friction level (see the class attributes)."""
    key = "coulomb"
    title = "Coulomb friction level"
    physics = ("The sliding friction force F_C differs (all friction elements scaled; added at the table if the "
               "model has none).")
    signature = "a step of the residual with the sign of the velocity: constant while sliding, flips at reversals"
    parameters = (Parameter("F_C", "N", "total Coulomb force", FORCE, TORQUE),)
    exclusive = ("coulomb_level",)
    not_after = ("position_friction",)
    sets_friction_level = True
    deal = 1

    def params(self, spec, ctx):
        f0 = coulomb_total(spec.preset)
        umax = ctx.u_max
        return [Param("F_C", "N", 0.0 if f0 == 0 else 0.02 * f0, max(3 * f0, 2 * umax), f0 if f0 > 0 else 0.1 * umax,
                      doc="total Coulomb (sliding) friction force")]

    def nominal(self, spec):
        return {"F_C": coulomb_total(spec.preset)}

    def apply(self, spec, theta):
        fc = float(theta[0])
        f0 = coulomb_total(spec.preset)
        if f0 <= 0:
            def edit(d):
                tf = d["stage"]["table_friction"]
                if tf is None:
                    d["stage"]["table_friction"] = friction.coulomb.element(fc)
                else:
                    tf["f_c"] = fc
            return spec.with_changes(edit=edit)
        s = fc / f0

        def edit(d):
            for path, fr in friction_elements(spec.preset):
                node = element_node(d, path)
                node["f_c"] = fr.f_c * s
                node.update(scaled_variation(fr, fr.f_c * s))
                if fr.model == "lugre":
                    node["f_s"] = fr.f_s * s
                if fr.model == "coulomb" and fr.f_s is not None:
                    node["f_s"] = fr.f_s * s
        return spec.with_changes(edit=edit)

    def conceal(self, d, draw):
        fc = bearing_f_c(d)
        s = 1 + draw.sign * draw.size(0.003, 0.6)
        for_bearings(d, lambda fr, b: fr.update(f_c=fr["f_c"] * s, **({"f_s": fr["f_s"] * s} if fr.get("f_s") else {})))
        return {"F_C": fc * s}

    def selftest_cases(self):
        up = both_bearings("friction.f_c", F_C_NOMINAL * 1.3)
        expect = {"F_C": 2 * F_C_NOMINAL * 1.3}
        return [Case("coulomb_+30%", "coulomb", up, expect=expect),
                # VAN stage (Ch. 3, 500 Hz dither on both bearings)
                Case("coulomb_+30%_van", "coulomb", up, expect=expect, experiment="steps", nominal="van_stage",
                     seed=142),
                Case("coulomb_+30%_sine", "coulomb", up, expect=expect, experiment="sine", seed=121)]


class Viscous(Effect):
    """Viscous friction where the stage's friction is: its bearings (shared equally; behind their
    joint on an isolated stage, where a bearing's lubricant shears), else the table's friction.
    ``c`` is the total over the friction elements (table and bearings)."""
    key = "viscous"
    title = "viscous friction"
    physics = ("A force proportional to velocity, where the friction is: the bearings' friction.viscous "
               "(behind their joint on an isolated stage), else table_friction.viscous.")
    signature = "residual proportional to velocity; largest at constant velocity, zero at rest"
    parameters = (Parameter("c", "N·s/m", "total viscous coefficient", (1e-3, 1e5), (1e-7, 1e2)),)
    deal = 2

    @staticmethod
    def total(spec):
        """The model's total viscous coefficient (table and bearings) [N·s/m].

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        float
        """
        return viscous_total(spec.preset)

    def params(self, spec, ctx):
        c0 = self.total(spec)
        cmax = max(10 * c0, ctx.u_max / max(ctx.v_max, 1e-9))
        return [Param("c", "N·s/m", 0.0, cmax, c0 if c0 > 0 else 0.01 * cmax,
                      doc="total viscous coefficient of the friction elements")]

    def nominal(self, spec):
        return {"c": self.total(spec)}

    def apply(self, spec, theta):
        c = max(0.0, float(theta[0]))
        c0 = self.total(spec)
        st = spec.preset.stage
        tf0 = st.table_friction.viscous if st.table_friction is not None else 0.0
        nb = len(st.bearings)

        def edit(d):
            if nb:
                # the change on the bearings: added equally; a decrease scales them down (the table's
                # own viscous kept unless the bearings have none left to give)
                vb = [b["friction"]["viscous"] for b in d["stage"]["bearings"]]
                tot = sum(vb)
                if c >= c0:
                    for b in d["stage"]["bearings"]:
                        b["friction"]["viscous"] += (c - c0) / nb
                    return
                keep_tf = min(tf0, c)
                for b, v in zip(d["stage"]["bearings"], vb):
                    b["friction"]["viscous"] = v * (c - keep_tf) / tot if tot > 0 else (c - keep_tf) / nb
                if d["stage"]["table_friction"] is not None:
                    d["stage"]["table_friction"]["viscous"] = keep_tf
                return
            tf = d["stage"]["table_friction"]
            if tf is None:
                d["stage"]["table_friction"] = friction.coulomb.element(0.0, viscous=c)
            else:
                tf["viscous"] = c
        return spec.with_changes(edit=edit)

    def conceal(self, d, draw):
        nb = len(d["stage"]["bearings"])
        c = draw.size(0.02, 30.0)
        for_bearings(d, lambda fr, b: fr.update(viscous=fr.get("viscous", 0.0) + c / nb))
        return {"c": c}

    def selftest_cases(self):
        return [Case("viscous_20", "viscous", both_bearings("friction.viscous", 10.0), expect={"c": 20.0}),
                Case("viscous_20_sine", "viscous", both_bearings("friction.viscous", 10.0), expect={"c": 20.0},
                     experiment="sine", seed=122)]


class PositionFriction(Effect):
    """F_C(x) = F_C + dF_0 + g_1 (x - x_c) + g_2 (x - x_c)^2, x_c = centre of the recorded positions."""
    key = "position_friction"
    title = "position-dependent friction"
    physics = ("Friction level varies along the travel: F_C(x) = F_C + dF_0 + g_1 (x - x_c) + g_2 (x - x_c)^2 "
               "(x_c: centre of the recorded positions), shared over the friction elements in proportion "
               "to their F_C (friction fields f_c, f_c_gradient, f_c_curvature, position_center); the element's "
               "whole force scales with F_C(x), pre-motion stiffness included.")
    signature = ("residual with the sign of velocity whose size depends on position (residual vs "
                 "position, split by direction of motion)")
    parameters = (Parameter("dF_0", "N", "level change", FORCE, TORQUE, signed=True),
                  Parameter("g_1", "N/m", "slope", (1e-2, 1e7), (1e-4, 1e4), signed=True),
                  Parameter("g_2", "N/m^2", "curvature", (1.0, 1e10), (1e-4, 1e4), signed=True))
    deal = 10
    _c = 0.0

    def applicable(self, spec):
        return None if coulomb_total(spec.preset) > 0 else "the model has no friction element with F_C > 0"

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), ctx.r_rms)
        hs = max(ctx.x_half_span, 1e-9)
        slope = [Param("g_1", "N/m", -3 * fc / hs, 3 * fc / hs, 0.0, doc="friction slope along the travel"),
                 Param("g_2", "N/m^2", -3 * fc / hs ** 2, 3 * fc / hs ** 2, 0.0, doc="friction curvature")]
        if ctx.level_fitted:
            # the Coulomb level is already an adopted effect: dF_0 would be the same parameter twice
            return slope
        return [Param("dF_0", "N", -0.9 * fc, 3 * fc, 0.0, doc="friction change at the centre of the recorded travel")
                ] + slope

    def nominal(self, spec):
        return {"dF_0": 0.0, "g_1": 0.0, "g_2": 0.0}

    def derived(self, spec, theta):
        return {"x_center": self._c}

    def apply(self, spec, theta):
        c = self._c
        df0, g1, g2 = (float(v) for v in theta) if len(theta) == 3 else (0.0, float(theta[0]), float(theta[1]))

        def fn(node, fr, w):
            # re-centre an existing variation at c: g1' (x-c0) + g2' (x-c0)^2 about c
            dc = c - fr.position_center
            a1 = fr.f_c_gradient + 2 * fr.f_c_curvature * dc
            a0 = fr.f_c_gradient * dc + fr.f_c_curvature * dc * dc
            # the level at c scales the whole element (its force at every displacement, as the
            # plant's position scale does), so pre-motion stiffnesses scale with F_C
            s0 = max(fr.f_c + a0 + df0 * w, 1e-6) / fr.f_c
            node["f_c"] = fr.f_c * s0
            for key in ("k_sigma", "sigma0", "sigma1", "f_s"):
                if node.get(key) is not None:
                    node[key] = node[key] * s0
            if fr.model == "gms":
                node["k"] = [k * s0 for k in node["k"]]
            node["f_c_difference"] = fr.f_c_difference * s0
            node["f_c_gradient"] = a1 + g1 * w
            node["f_c_curvature"] = fr.f_c_curvature + g2 * w
            node["position_center"] = c
        return spec.with_changes(edit=edit_elements(spec, fn))

    def bound(self, ctx: Context):
        e = copy.copy(self)
        e._c = float(ctx.x_center)
        return e

    def probe(self, spec, ctx):
        """A slope of 5 % of the Coulomb force over the recorded half span.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        ctx : Context
            What was located on the recording.

        Returns
        -------
        tuple
            ``(theta, i)`` as :meth:`.base.Effect.probe`.
        """
        ps = self.params(spec, ctx)
        th = [0.0] * len(ps)
        i = len(ps) - 2
        th[i] = 0.05 * max(coulomb_total(spec.preset), 1e-12) / max(ctx.x_half_span, 1e-9)
        return th, i

    def conceal(self, d, draw):
        nb = len(d["stage"]["bearings"])
        g1 = draw.sign * draw.size(0.01, 0.8) * bearing_f_c(d) / draw.half_span
        for_bearings(d, lambda fr, b: fr.update(f_c_gradient=g1 / nb, position_center=draw.x_center))
        return {"g_1": g1}

    def selftest_cases(self):
        return [Case("position_friction", "position_friction", both_bearings("friction.f_c_gradient", 30.0),
                     expect={"g_1": 60.0})]


class Asymmetry(Effect):
    """Friction different in the two directions: F_C+- = F_C +- dF_C/2, c+- = c +- dc/2."""
    key = "friction_asymmetry"
    title = "direction-asymmetric friction"
    physics = ("Coulomb and viscous friction differ between the two directions of motion (EMPS: "
               "Fc+ != Fc-, Fv+ != Fv-): friction fields f_c_difference, viscous_difference.")
    signature = ("a residual of the same sign in both directions while moving (not flipping at reversals), "
                 "zero at rest; residual vs velocity is V-shaped / offset between the branches")
    parameters = (Parameter("dF_C", "N", "F_C+ - F_C-", FORCE, TORQUE, signed=True),
                  Parameter("dc", "N·s/m", "c+ - c-", (1e-3, 1e5), (1e-7, 1e2), signed=True))
    deal = 13

    def applicable(self, spec):
        return None if coulomb_total(spec.preset) > 0 else "the model has no friction element with F_C > 0"

    def params(self, spec, ctx):
        fc = coulomb_total(spec.preset)
        vmax = max(ctx.v_max, 1e-9)
        return [Param("dF_C", "N", -1.9 * fc, 1.9 * fc, 0.0, doc="Coulomb force in + minus in - direction"),
                Param("dc", "N·s/m", -4 * fc / vmax, 4 * fc / vmax, 0.0, doc="viscous coefficient + minus -")]

    def nominal(self, spec):
        return {"dF_C": 0.0, "dc": 0.0}

    def probe(self, spec, ctx):
        """A Coulomb difference of 5 % of the Coulomb force.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        ctx : Context
            What was located on the recording.

        Returns
        -------
        tuple
            ``(theta, i)`` as :meth:`.base.Effect.probe`.
        """
        return [0.05 * coulomb_total(spec.preset), 0.0], 0

    def apply(self, spec, theta):
        dfc, dc = float(theta[0]), float(theta[1])

        def fn(node, fr, w):
            node["f_c_difference"] = fr.f_c_difference + dfc * w
            node["viscous_difference"] = fr.viscous_difference + dc * w
        return spec.with_changes(edit=edit_elements(spec, fn))

    def conceal(self, d, draw):
        fc = bearing_f_c(d)
        m = draw.size(0.01, 1.0)
        for_bearings(d, lambda fr, b: fr.update(f_c_difference=draw.sign * m * fr["f_c"]))
        return {"dF_C": draw.sign * m * fc, "dc": 0.0}

    def selftest_cases(self):
        return [Case("friction_asymmetry", "friction_asymmetry",
                     {**both_bearings("friction.f_c_difference", 0.4), **both_bearings("friction.viscous_difference", 5.0)},
                     expect={"dF_C": 0.8, "dc": 10.0})]
