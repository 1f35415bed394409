"""The library of hypotheses: each a model change with parameters, bounds and a signature.

Every :class:`Effect` turns a parameter vector into a modified :class:`~.model.ModelSpec`
(:meth:`Effect.apply`), relative to the model it is added to. ``kind`` says how it is
fitted:

``deterministic``  fitted to the force residual on the fit set (:mod:`.fit`);
``integer``        a grid over integers (actuator delay);
``stochastic``     compared through the noise floor (drive noise) or the measurement
                   lattice (quantization), see :mod:`.fit`.

An effect that needs a stage feature the model lacks says why (:meth:`Effect.applicable`:
the isolator transient needs an SAI) and is not tried.

``expressible`` says whether the fitted model is a preset the simulator runs as is; every
effect of this library is (position-dependent and asymmetric friction, ripple, offset and
periodic force are plant features: ``stage_sim.config``), so the improved preset carries
all of them.

``nanostage diagnose --list-effects`` prints this library (:func:`describe`).
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np

from .model import ModelSpec, coulomb_total, friction_elements
from .units import unit_for
from stage_sim import friction
from stage_sim.config import set_dotted

__all__ = ["Param", "Effect", "LIBRARY", "get_effect", "describe", "virgin_x50", "split_mode", "rigid_mass"]


@dataclass
class Param:
    name: str
    unit: str
    lo: float
    hi: float
    x0: float
    log: bool = False
    doc: str = ""
    physical_lo: bool = False     # the lower bound is a physical limit (a capacity >= 0): reaching it is a
                                  # result (the element is absent), not "not identified"

    def clip(self, v):
        return float(min(max(v, self.lo), self.hi))


@dataclass
class Effect:
    key: str
    title: str
    kind: str                      # deterministic | integer | stochastic
    physics: str
    signature: str
    expressible: bool = True
    needs: str = ""
    param_doc: list = field(default_factory=list)   # (name, unit, meaning) for the listing

    def bound(self, ctx: dict) -> "Effect":
        """This effect for a recording whose locate context is ``ctx``: a copy that carries what
        its model change needs from the recording (block slip distances, located modes, the
        position centre). The library's instances are never changed, so fits on threads and
        concurrent diagnoses share them safely; a context-free effect is its own bound form."""
        return self

    def applicable(self, spec: ModelSpec) -> str | None:
        """``None`` if the effect can be added to ``spec``, else the reason it cannot."""
        return None

    def params(self, spec: ModelSpec, ctx: dict) -> list[Param]:
        return []

    def apply(self, spec: ModelSpec, theta) -> ModelSpec:
        raise NotImplementedError

    def nominal(self, spec: ModelSpec) -> dict:
        """The nominal model's values of the parameters (None where it has no such term)."""
        return {}

    def derived(self, spec: ModelSpec, theta) -> dict:
        """Physical quantities derived from the fit (compared with a truth in the self-test)."""
        return {}

    def starts(self, spec: ModelSpec, ctx: dict) -> list:
        """Initial parameter vectors (multi-start); default: the x0 of :meth:`params`."""
        return [[p.x0 for p in self.params(spec, ctx)]]


# --------------------------------------------------------------------------- helpers
def _fric_weights(spec: ModelSpec):
    els = friction_elements(spec.preset)
    fcs = np.array([max(getattr(fr, "f_c", 0.0), 0.0) for _, fr in els])
    if len(els) == 0:
        return els, fcs
    w = fcs / fcs.sum() if fcs.sum() > 0 else np.full(len(els), 1.0 / len(els))
    return els, w


def _variation(fr, f_c_new: float) -> dict:
    """The friction variation fields of ``fr`` for an element of Coulomb force ``f_c_new``
    (force-like fields scaled with it, so the relative variation is kept)."""
    s = f_c_new / fr.f_c if fr.f_c > 0 else 1.0
    return {"f_c_difference": fr.f_c_difference * s, "viscous_difference": fr.viscous_difference,
            "f_c_gradient": fr.f_c_gradient * s, "f_c_curvature": fr.f_c_curvature * s,
            "position_center": fr.position_center}


def virgin_x50(fr_dump: list) -> float:
    """Displacement [m] at which the summed virgin curve of friction elements (configs or their
    dicts) reaches half their total sliding force (pre-motion length scale; Dahl: ln2 F_C/k_sigma).
    Each law's virgin curve and sliding force come from its module (:mod:`stage_sim.friction`)."""
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


# --------------------------------------------------------------------------- friction level
class Coulomb(Effect):
    def params(self, spec, ctx):
        f0 = coulomb_total(spec.preset)
        umax = ctx.get("u_max", 10.0)
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
                    d["stage"]["table_friction"] = {"model": "coulomb", "f_c": fc, "f_s": None, "viscous": 0.0}
                else:
                    tf["f_c"] = fc
            return spec.with_changes(edit=edit)
        s = fc / f0

        def edit(d):
            for path, fr in friction_elements(spec.preset):
                node = d
                for k in path.split("."):
                    node = node[int(k)] if isinstance(node, list) else node[k]
                node["f_c"] = fr.f_c * s
                node.update(_variation(fr, fr.f_c * s))
                if fr.model == "lugre":
                    node["f_s"] = fr.f_s * s
                if fr.model == "coulomb" and fr.f_s is not None:
                    node["f_s"] = fr.f_s * s
        return spec.with_changes(edit=edit)


class Viscous(Effect):
    """Viscous friction where the stage's friction is: its bearings (shared equally; behind their
    joint on an isolated stage, where a bearing's lubricant shears), else the table's friction.
    ``c`` is the total over the friction elements (table and bearings)."""

    def _c0(self, spec):
        st = spec.preset.stage
        c = st.table_friction.viscous if st.table_friction is not None else 0.0
        return c + sum(b.friction.viscous for b in st.bearings)

    def params(self, spec, ctx):
        c0 = self._c0(spec)
        cmax = max(10 * c0, ctx.get("u_max", 10.0) / max(ctx.get("v_max", 1e-3), 1e-9))
        return [Param("c", "N·s/m", 0.0, cmax, c0 if c0 > 0 else 0.01 * cmax,
                      doc="total viscous coefficient of the friction elements")]

    def nominal(self, spec):
        return {"c": self._c0(spec)}

    def apply(self, spec, theta):
        c = max(0.0, float(theta[0]))
        c0 = self._c0(spec)
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
                d["stage"]["table_friction"] = {"model": "coulomb", "f_c": 0.0, "f_s": None, "viscous": c}
            else:
                tf["viscous"] = c
        return spec.with_changes(edit=edit)


# --------------------------------------------------------------------------- pre-motion friction
def _contact_stiffness(spec: ModelSpec) -> float:
    """The model's total pre-motion stiffness at rest [N/m] (:func:`stage_sim.friction.initial_stiffness`
    summed), or -- friction without pre-motion -- that of a 1 um pre-motion length at F_C."""
    k0 = float(sum(friction.initial_stiffness(fr) for _, fr in friction_elements(spec.preset)))
    return k0 if k0 > 0 else max(coulomb_total(spec.preset), 1e-3) / 1e-6


class Dahl(Effect):
    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element to give pre-motion"

    def params(self, spec, ctx):
        k0 = _contact_stiffness(spec)
        return [Param("k_sigma", "N/m", k0 * 1e-3, k0 * 1e3, k0, log=True,
                      doc="total pre-motion (contact) stiffness of the Dahl model")]

    def starts(self, spec, ctx):
        k0 = self.params(spec, ctx)[0].x0
        return [[k0 * s] for s in (1.0, 0.3, 3.0)] if any(
            fr.model == "dahl" for _, fr in friction_elements(spec.preset)) else [[k0 * s] for s in (0.1, 1.0, 10.0)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        return {"k_sigma": _contact_stiffness(spec) if all(fr.model == "dahl" for _, fr in els) and els else None}

    def derived(self, spec, theta):
        sp = self.apply(spec, theta)
        return {"x_50": virgin_x50([fr.model_dump() for _, fr in friction_elements(sp.preset)])}

    def apply(self, spec, theta):
        k = float(theta[0])
        els, w = _fric_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                new = {"model": "dahl", "k_sigma": k * we, "f_c": max(fr.f_c, 1e-9),
                       "shape": getattr(fr, "shape", 1.0), "viscous": fr.viscous, **_variation(fr, max(fr.f_c, 1e-9))}
                set_dotted(d, path, new)
        return spec.with_changes(edit=edit)


class Gms(Effect):
    """Maxwell-slip / Prandtl-Ishlinskii: parallel elasto-slip blocks with fitted capacities.

    The slip displacements: a model whose friction is already Maxwell-slip keeps its own (scaled by
    one common factor ``x_scale``, i.e. all its stiffnesses by ``1/x_scale``: a pre-motion length
    that differs, the GMS form of the Dahl ``k_sigma``), so the nominal is one point of the family
    and a small change of it a small step; any other model gets :attr:`N` log-spaced ones."""
    N = 12

    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element"

    @staticmethod
    def own_slips(spec) -> np.ndarray | None:
        """The slip displacements ``alpha F_C / k`` the model's Maxwell-slip elements share (None
        when any friction element is of another law or the elements' blocks differ)."""
        els = friction_elements(spec.preset)
        if not els or any(fr.model != "gms" for _, fr in els):
            return None
        ds = [np.asarray(fr.alpha) * fr.f_c / np.maximum(np.asarray(fr.k), 1e-300) for _, fr in els]
        if any(len(d) != len(ds[0]) or not np.allclose(d, ds[0], rtol=1e-6) for d in ds):
            return None
        return ds[0]

    def deltas(self, ctx):
        lo = ctx.get("delta_lo", 1e-7)
        hi = ctx.get("delta_hi", 5e-5)
        return np.logspace(np.log10(lo), np.log10(hi), self.N)

    def _caps(self, spec):
        """The model's own block capacities (totals over the elements), when it has its own slips."""
        els = friction_elements(spec.preset)
        return np.sum([np.asarray(fr.alpha) * fr.f_c for _, fr in els], axis=0)

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-3)
        own = self.own_slips(spec)
        if own is not None:
            caps = self._caps(spec)
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
            return {"x_scale": 1.0, **{f"F_{i + 1}": float(c) for i, c in enumerate(self._caps(spec))}}
        return {f"F_{i + 1}": None for i in range(self.N)}

    def _split(self, spec, theta):
        """(slip displacements, capacities) of the parameter vector ``theta`` on ``spec``."""
        own = self.own_slips(spec)
        theta = np.asarray(theta, float)
        if own is not None:
            return own * float(theta[0]), theta[1:]
        d = self._d if getattr(self, "_d", None) is not None else self.deltas({})
        return d, theta

    def derived(self, spec, theta):
        sp = self.apply(spec, theta)
        els = [fr.model_dump() for _, fr in friction_elements(sp.preset)]
        return {"F_C": float(np.sum(self._split(spec, theta)[1])), "x_50": virgin_x50(els),
                "k_0": float(sum(sum(fr["k"]) for fr in els if fr["model"] == "gms"))}

    def apply(self, spec, theta, ctx=None):
        d, F = self._split(spec, theta)
        F = np.maximum(F, 1e-9)
        fc = F.sum()
        els, w = _fric_weights(spec)

        def edit(dd):
            for (path, fr), we in zip(els, w):
                set_dotted(dd, path, {"model": "gms", "k": list(F * we / d), "alpha": list(F / fc), "f_c": fc * we,
                                     "viscous": fr.viscous, **_variation(fr, fc * we)})
        return spec.with_changes(edit=edit)

    def bound(self, ctx):
        e = copy.copy(self)
        e._d = self.deltas(ctx)
        return e


class Stribeck(Effect):
    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element"

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-6)
        vmax = max(ctx.get("v_max", 1e-3), 1e-9)
        return [Param("F_S", "N", 1.0 * fc, 6 * fc, 1.3 * fc, doc="total static (break-away) force"),
                Param("v_s", "m/s", vmax * 1e-4, vmax, 0.05 * vmax, log=True, doc="Stribeck velocity")]

    def starts(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), 1e-6)
        vmax = max(ctx.get("v_max", 1e-3), 1e-9)
        return [[1.5 * fc, vmax * s] for s in (0.01, 0.05, 0.2)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        if els and all(fr.model == "lugre" for _, fr in els):
            return {"F_S": float(sum(fr.f_s for _, fr in els)), "v_s": els[0][1].v_s}
        return {"F_S": None, "v_s": None}

    def apply(self, spec, theta):
        fs, vs = float(theta[0]), float(theta[1])
        els, w = _fric_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                k = friction.initial_stiffness(fr) or max(fr.f_c, 1e-9) / 1e-6
                set_dotted(d, path, {"model": "lugre", "sigma0": k, "sigma1": getattr(fr, "sigma1", 0.0),
                                    "viscous": fr.viscous, "f_c": max(fr.f_c, 1e-9), "f_s": max(fs * we, fr.f_c * 1.0001, 1e-9),
                                    "v_s": vs, "exponent": getattr(fr, "exponent", 2.0), **_variation(fr, max(fr.f_c, 1e-9))})
        return spec.with_changes(edit=edit)


class LugreDamping(Effect):
    """Pre-motion friction with bristle damping (LuGre, Canudas de Wit et al. 1995): each friction
    element becomes ``sigma0 z + sigma1 dz/dt`` with ``dz/dx = 1 - sigma0 sgn(v) z / g(v)``;
    ``sigma0`` and ``sigma1`` are fitted as totals shared in proportion to F_C, F_C and viscous
    kept, the Stribeck curve kept from a LuGre element (else none: F_S = F_C, where sigma1 = 0
    is Dahl with shape 1). At rest the contact is a Kelvin-Voigt solid: a force change below
    F_C is followed by creep over ``tau = sigma1 / sigma0`` instead of an instant deflection,
    and the pre-motion resonance is damped."""

    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element to give pre-motion"

    def params(self, spec, ctx):
        k0 = _contact_stiffness(spec)
        return [Param("sigma0", "N/m", k0 * 1e-2, k0 * 1e2, k0, log=True,
                      doc="total bristle (pre-motion) stiffness"),
                Param("sigma1", "N·s/m", k0 * 1e-7, k0 * 1e-2, k0 * 1e-4, log=True,
                      doc="total bristle damping (creep time sigma1 / sigma0: 0.1 us ... 10 ms)")]

    def starts(self, spec, ctx):
        k0 = _contact_stiffness(spec)
        return [[k0, k0 * t] for t in (1e-5, 1e-4, 1e-3, 5e-3)]

    def nominal(self, spec):
        els = friction_elements(spec.preset)
        if els and all(fr.model == "lugre" for _, fr in els):
            return {"sigma0": _contact_stiffness(spec), "sigma1": float(sum(fr.sigma1 for _, fr in els))}
        return {"sigma0": None, "sigma1": None}

    def derived(self, spec, theta):
        return {"tau": float(theta[1]) / float(theta[0])}

    def apply(self, spec, theta):
        s0, s1 = float(theta[0]), float(theta[1])
        els, w = _fric_weights(spec)

        def edit(d):
            for (path, fr), we in zip(els, w):
                fc = max(fr.f_c, 1e-9)
                lugre = fr.model == "lugre"
                set_dotted(d, path, {"model": "lugre", "sigma0": s0 * we, "sigma1": s1 * we, "viscous": fr.viscous,
                                     "f_c": fc, "f_s": fr.f_s if lugre else fc, "v_s": fr.v_s if lugre else 1e-3,
                                     "exponent": fr.exponent if lugre else 2.0, **_variation(fr, fc)})
        return spec.with_changes(edit=edit)


class RegularizedCoulomb(Effect):
    """Friction with a smooth zero-velocity transition: each friction element becomes
    ``F_C tanh(v / v_reg) + viscous v`` (:mod:`stage_sim.friction.regularized`, F_C and viscous
    kept). Below ``v_reg`` the friction is a steep damper ``F_C / v_reg`` instead of a stick: a
    force below F_C at rest makes the stage creep at ``v_reg atanh(F / F_C)``."""

    def applicable(self, spec):
        return None if friction_elements(spec.preset) else "the model has no friction element"

    def params(self, spec, ctx):
        vmax = max(ctx.get("v_max", 1e-3), 1e-9)
        return [Param("v_reg", "m/s", vmax * 1e-6, vmax * 0.3, vmax * 1e-2, log=True,
                      doc="regularisation velocity (F = 76 % of F_C at v_reg)")]

    def starts(self, spec, ctx):
        vmax = max(ctx.get("v_max", 1e-3), 1e-9)
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
                set_dotted(d, path, {"model": "regularized_coulomb", "f_c": fr.f_c, "v_reg": v_reg,
                                     "viscous": fr.viscous, **_variation(fr, fr.f_c)})
        return spec.with_changes(edit=edit)


# --------------------------------------------------------------------------- rigid body, drive
class Mass(Effect):
    def params(self, spec, ctx):
        m = spec.preset.stage.table.mass
        return [Param("m_table", "kg", 0.2 * m, 5 * m, m, doc="table mass (stage.table.mass)")]

    def nominal(self, spec):
        return {"m_table": spec.preset.stage.table.mass}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.table.mass": float(theta[0])})


class ForceConstant(Effect):
    def params(self, spec, ctx):
        r = spec.preset.stage.drive.force_constant_ratio
        return [Param("ratio", "-", 0.3 * r, 3 * r, r, doc="true / nominal motor force constant")]

    def nominal(self, spec):
        return {"ratio": spec.preset.stage.drive.force_constant_ratio}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.force_constant_ratio": float(theta[0])})


class Delay(Effect):
    MAX = 12

    def params(self, spec, ctx):
        d = spec.preset.stage.drive.delay_samples
        return [Param("delay_samples", "samples", 0, self.MAX, d, doc="drive delay in control samples")]

    def nominal(self, spec):
        return {"delay_samples": spec.preset.stage.drive.delay_samples}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.delay_samples": int(round(theta[0]))})


class FractionalDelay(Effect):
    """A fraction of a control period more or less drive delay than the model has: the total
    ``delay_samples + delay_fraction`` shifted by ``shift`` in (-1, 1) (the plant's exact delayed
    zero-order hold). The whole samples are the integer ``delay`` effect's: a delay of 1.4 samples
    is named as ``delay`` 1 and then ``fractional_delay`` +0.4 on top (a whole-sample delay the
    data show stays that, a fraction adopted only if it adds beyond the floor)."""

    @staticmethod
    def total(spec):
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


# --------------------------------------------------------------------------- structure
def rigid_mass(stage: dict) -> float:
    """Mass of the table's DOF in a preset mapping's ``stage``: table + rigidly bolted bearings +
    the structural modes on it [kg]."""
    mt = stage["table"]["mass"]
    return (mt * (1.0 + sum(m["mass_ratio"] for m in stage["modes"]))
            + sum(b["mass"] for b in stage["bearings"] if b.get("joint") is None))


def split_mode(d: dict, f: float, zeta: float, fraction: float) -> None:
    """Add to preset mapping ``d`` a structural mode (blocked frequency ``f`` [Hz], damping ratio
    ``zeta``) whose mass is ``fraction`` of the table DOF's mass (:func:`rigid_mass`), taken out of
    the table: the total mass stays. The other modes keep their masses. Raises ``ValueError`` if
    the table is lighter than the mode mass."""
    st = d["stage"]
    ms = fraction * rigid_mass(st)
    m_old = st["table"]["mass"]
    m_new = m_old - ms
    if not m_new > 0:
        raise ValueError(f"mode mass {ms:.4g} kg exceeds the table mass {m_old:.4g} kg")
    for m in st["modes"]:
        m["mass_ratio"] = m["mass_ratio"] * m_old / m_new
    st["table"]["mass"] = m_new
    st["modes"] = list(st["modes"]) + [{"frequency": float(f), "damping_ratio": min(float(zeta), 0.99),
                                        "mass_ratio": ms / m_new}]


class Mode(Effect):
    """A lightly damped mode anywhere between DC and Nyquist, its mass a fraction of the table's
    (:func:`split_mode`: the total mass stays the nominal's); started from the command ->
    measurement transfer (:mod:`.frf`, context ``frf_modes``) and the force residual's peaks."""

    def _max_fraction(self, spec):
        st = spec.preset.stage
        d = {"table": {"mass": st.table.mass}, "modes": [m.model_dump() for m in st.modes],
             "bearings": [b.model_dump() for b in st.bearings]}
        return 0.95 * st.table.mass / rigid_mass(d)

    def params(self, spec, ctx):
        rate = spec.preset.controller.rate
        frf = list(ctx.get("frf_modes") or [])
        f0 = frf[0]["f_hz"] if frf else (ctx["peak_hz"][0] if ctx.get("peak_hz") else 0.1 * rate)
        hi = self._max_fraction(spec)
        return [Param("f", "Hz", 2.0, 0.49 * rate, min(max(f0, 2.5), 0.48 * rate), log=True,
                      doc="blocked natural frequency"),
                Param("zeta", "-", 0.001, 0.5, 0.03, log=True, doc="damping ratio"),
                Param("fraction", "-", 1e-3, hi, min(0.1, 0.5 * hi), log=True,
                      doc="modal mass / mass of the table's DOF (taken out of the table)")]

    def starts(self, spec, ctx):
        rate = spec.preset.controller.rate
        hi = self._max_fraction(spec)
        frf = [[min(max(m["f_hz"], 2.5), 0.48 * rate), min(max(m["zeta"], 0.0015), 0.45),
                min(max(m["fraction"], 0.0015), 0.9 * hi)] for m in (ctx.get("frf_modes") or [])[:2]]
        peaks = list(ctx.get("peak_hz") or [])[:3]
        # the located peaks, then a grid of 4 per decade up to Nyquist (the starts are ranked by their cost,
        # the best two fitted): a mode far from the excitation's lines starts near its frequency too
        grid = np.geomspace(0.005 * rate, 0.4 * rate, 8)
        grid = peaks + [float(f) for f in grid if all(abs(np.log(f / p)) > 0.3 for p in peaks)]
        return (frf + [[f, 0.03, min(0.1, 0.5 * hi)] for f in grid])[:12]

    def nominal(self, spec):
        return {"f": None, "zeta": None, "fraction": None}

    def apply(self, spec, theta):
        f, z, phi = (float(v) for v in theta)
        return spec.with_changes(edit=lambda d: split_mode(d, f, z, phi))


class LocatedMode(Effect):
    """A mode located and fitted on the command -> measurement transfer (:mod:`.frf`) above the
    cutoff of the measurement's smoothing, where the force observer cannot fit it (the smoothed
    measurement it follows has no motion there): the transfer's fit (frequency, damping, mass
    fraction; :func:`split_mode`) is the candidate as it is, one per located mode, and the judge
    decides on the held-out data."""
    _modes = None

    def bound(self, ctx):
        fs = float(ctx.get("smoothing_hz") or 0.0)
        e = copy.copy(self)
        e._modes = tuple(m for m in ctx.get("frf_modes") or () if m["f_hz"] > fs)
        return e

    def applicable(self, spec):
        if self._modes is not None and not self._modes:
            return "no mode located on the command -> measurement transfer above the smoothing cutoff"
        return None

    def params(self, spec, ctx):
        n = len(self._modes or ())
        return [Param("mode", "-", 0, max(n - 1, 0), 0, doc="index of the located mode")]

    def nominal(self, spec):
        return {"mode": None}

    def _mode(self, theta):
        return self._modes[int(round(float(theta[0])))]

    def with_mode(self, i: int, mode: dict) -> "LocatedMode":
        """A copy whose located mode ``i`` has the values of ``mode`` (a refinement of the transfer's fit)."""
        e = copy.copy(self)
        e._modes = tuple(dict(m, **mode) if k == i else m for k, m in enumerate(self._modes))
        return e

    def derived(self, spec, theta):
        m = self._mode(theta)
        return {"f": m["f_hz"], "zeta": m["zeta"], "fraction": m["fraction"]}

    def apply(self, spec, theta):
        m = self._mode(theta)
        return spec.with_changes(edit=lambda d: split_mode(d, m["f_hz"], m["zeta"], m["fraction"]))


class FiCompliance(Effect):
    """The bearings behind a spring-damper (friction isolator, Ch. 4), in any nominal with friction:
    its bolted bearings, or -- a nominal written as "table with friction" -- a bearing made of the
    table friction. The bearing mass ``m_b`` is fitted; the rigid mass (table + bearings) is kept,
    so the two ways of writing the same rigid body give the same candidates and the same fit."""

    def applicable(self, spec):
        st = spec.preset.stage
        if not st.bearings and st.table_friction is None:
            return "the stage has no friction to put behind a joint (no bearing, no table friction)"
        return None

    @staticmethod
    def _rigid(st):
        """Mass of the rigid body: table + bearings [kg]."""
        return st.table.mass + sum(b.mass for b in st.bearings)

    @staticmethod
    def _mode_mass(st):
        return st.table.mass * sum(m.mass_ratio for m in st.modes)

    def _m_red(self, st, mb):
        """Reduced mass of one of the ``nb`` joints for total bearing mass ``mb`` [kg]."""
        nb = max(len(st.bearings), 1)
        mt = self._rigid(st) - mb + self._mode_mass(st)
        return (mb / nb) * mt / (mb / nb + mt)

    def _mb0(self, st):
        return sum(b.mass for b in st.bearings) if st.bearings else 0.1 * self._rigid(st)

    def params(self, spec, ctx):
        st = spec.preset.stage
        nb = max(len(st.bearings), 1)
        mb0 = self._mb0(st)
        jointed = bool(st.bearings) and st.bearings[0].joint is not None
        k0 = st.bearings[0].joint.stiffness * nb if jointed else None
        kg = k0 or self._m_red(st, mb0) * (2 * np.pi * 50.0) ** 2 * nb
        M = self._rigid(st)
        return [Param("k_fi", "N/m", 1e-3 * kg, 1e3 * kg, kg, log=True, doc="total joint stiffness (all bearings)"),
                Param("zeta_fi", "-", 1e-3, 1.0, 0.02, log=True, doc="joint damping ratio on the reduced mass"),
                Param("m_b", "kg", 0.005 * M, 0.8 * M, min(max(mb0, 0.01 * M), 0.7 * M), log=True,
                      doc="total bearing mass behind the joints (table + bearings kept)")]

    def starts(self, spec, ctx):
        st = spec.preset.stage
        nb = max(len(st.bearings), 1)
        mb = self.params(spec, ctx)[2].x0
        if st.bearings and st.bearings[0].joint is not None:
            k0 = st.bearings[0].joint.stiffness * nb
            return [[k0, 0.02, mb], [0.3 * k0, 0.02, mb], [3 * k0, 0.02, mb]]
        mr = self._m_red(st, mb)
        fr = list(ctx.get("frf_hz") or [])[:1] + list(ctx.get("peak_hz") or [])[:2] + [20.0, 60.0, 200.0]
        return [[mr * (2 * np.pi * f) ** 2 * nb, 0.02, mb] for f in fr[:4]]

    def nominal(self, spec):
        st = spec.preset.stage
        if st.bearings and st.bearings[0].joint is not None:
            j = st.bearings[0].joint
            mb = sum(b.mass for b in st.bearings)
            return {"k_fi": j.stiffness * len(st.bearings),
                    "zeta_fi": j.damping / (2 * math.sqrt(j.stiffness * self._m_red(st, mb))), "m_b": mb}
        return {"k_fi": None, "zeta_fi": None, "m_b": sum(b.mass for b in st.bearings) if st.bearings else None}

    def derived(self, spec, theta):
        st = spec.preset.stage
        k, _, mb = (float(v) for v in theta)
        nb = max(len(st.bearings), 1)
        return {"f_joint_hz": math.sqrt(k / nb / self._m_red(st, mb)) / (2 * math.pi)}

    def apply(self, spec, theta):
        k, z, mb = (float(v) for v in theta)
        st = spec.preset.stage
        M = self._rigid(st)
        m_old = st.table.mass
        m_new = M - mb
        nb = max(len(st.bearings), 1)
        kb = k / nb
        mr = self._m_red(st, mb)
        joint = {"stiffness": kb, "damping": 2 * z * math.sqrt(kb * mr)}

        def edit(d):
            sd = d["stage"]
            if sd["bearings"]:
                for b in sd["bearings"]:
                    b["mass"] = mb / nb
                    b["joint"] = dict(joint)
            else:       # "table with friction": the friction is the bearing's, behind the joint
                sd["bearings"] = [{"mass": mb, "joint": dict(joint), "friction": sd["table_friction"]}]
                sd["table_friction"] = None
            sd["table"]["mass"] = m_new
            for md in sd["modes"]:        # the modes keep their masses
                md["mass_ratio"] = md["mass_ratio"] * m_old / m_new
        return spec.with_changes(edit=edit)


# --------------------------------------------------------------------------- table forces, friction variations
def _edit_elements(spec: ModelSpec, fn):
    """``edit`` callable applying ``fn(node, fr, weight)`` to every friction element's mapping."""
    els, w = _fric_weights(spec)

    def edit(d):
        for (path, fr), we in zip(els, w):
            node = d
            for k in path.split("."):
                node = node[int(k)] if isinstance(node, list) else node[k]
            fn(node, fr, float(we))
    return edit


class Ripple(Effect):
    def params(self, spec, ctx):
        per = (ctx.get("ripple_period") or [ctx.get("x_span", 1e-3) / 4])[0]
        amp = ctx.get("r_rms", 0.1)
        return [Param("a_sin", "N", -10 * amp - 1, 10 * amp + 1, 0.0, doc="sine amplitude"),
                Param("a_cos", "N", -10 * amp - 1, 10 * amp + 1, 0.0, doc="cosine amplitude"),
                Param("period", "m", per / 3, per * 3, per, log=True, doc="spatial period")]

    def starts(self, spec, ctx):
        pers = list(ctx.get("ripple_period") or [])[:3] or [ctx.get("x_span", 1e-3) / 4]
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


class PositionFriction(Effect):
    """F_C(x) = F_C + dF_0 + g_1 (x - x_c) + g_2 (x - x_c)^2, x_c = centre of the recorded positions."""

    def applicable(self, spec):
        return None if coulomb_total(spec.preset) > 0 else "the model has no friction element with F_C > 0"

    def params(self, spec, ctx):
        fc = max(coulomb_total(spec.preset), ctx.get("r_rms", 0.1))
        hs = max(ctx.get("x_half_span", 1e-3), 1e-9)
        slope = [Param("g_1", "N/m", -3 * fc / hs, 3 * fc / hs, 0.0, doc="friction slope along the travel"),
                 Param("g_2", "N/m^2", -3 * fc / hs ** 2, 3 * fc / hs ** 2, 0.0, doc="friction curvature")]
        if ctx.get("level_fitted"):
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
        return spec.with_changes(edit=_edit_elements(spec, fn))

    def bound(self, ctx):
        e = copy.copy(self)
        e._c = float(ctx.get("x_center", 0.0))
        return e


class Asymmetry(Effect):
    """Friction different in the two directions: F_C+- = F_C +- dF_C/2, c+- = c +- dc/2."""

    def applicable(self, spec):
        return None if coulomb_total(spec.preset) > 0 else "the model has no friction element with F_C > 0"

    def params(self, spec, ctx):
        fc = coulomb_total(spec.preset)
        vmax = max(ctx.get("v_max", 1e-3), 1e-9)
        return [Param("dF_C", "N", -1.9 * fc, 1.9 * fc, 0.0, doc="Coulomb force in + minus in - direction"),
                Param("dc", "N·s/m", -4 * fc / vmax, 4 * fc / vmax, 0.0, doc="viscous coefficient + minus -")]

    def nominal(self, spec):
        return {"dF_C": 0.0, "dc": 0.0}

    def apply(self, spec, theta):
        dfc, dc = float(theta[0]), float(theta[1])

        def fn(node, fr, w):
            node["f_c_difference"] = fr.f_c_difference + dfc * w
            node["viscous_difference"] = fr.viscous_difference + dc * w
        return spec.with_changes(edit=_edit_elements(spec, fn))


class Offset(Effect):
    def params(self, spec, ctx):
        um = ctx.get("u_max", 10.0)
        return [Param("F_0", "N", -um, um, 0.0, doc="constant force on the table (+x)")]

    def nominal(self, spec):
        return {"F_0": spec.preset.stage.force_offset}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.force_offset": spec.preset.stage.force_offset + float(theta[0])})


class PeriodicForce(Effect):
    def params(self, spec, ctx):
        f0 = (ctx.get("line_hz") or [50.0])[0]
        amp = ctx.get("r_rms", 0.1)
        return [Param("a_sin", "N", -10 * amp - 1, 10 * amp + 1, 0.0), Param("a_cos", "N", -10 * amp - 1, 10 * amp + 1, 0.0),
                Param("f", "Hz", f0 * 0.98, f0 * 1.02, f0, doc="frequency of the line")]

    def starts(self, spec, ctx):
        return [[0.0, 0.0, f] for f in (ctx.get("line_hz") or [50.0])[:2]]

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


# --------------------------------------------------------------------------- stochastic
class NoiseLevel(Effect):
    def params(self, spec, ctx):
        s = spec.preset.stage.drive.noise_current_rms
        return [Param("noise_current_rms", "A", 0.0, 1.0, s, doc="drive current noise RMS")]

    def nominal(self, spec):
        return {"noise_current_rms": spec.preset.stage.drive.noise_current_rms}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.drive.noise_current_rms": max(0.0, float(theta[0]))})


class Quantization(Effect):
    def params(self, spec, ctx):
        q = spec.preset.stage.encoder.resolution
        return [Param("resolution", "m", 0.0, 1e-3, q, doc="encoder quantization step")]

    def nominal(self, spec):
        return {"resolution": spec.preset.stage.encoder.resolution}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.encoder.resolution": max(0.0, float(theta[0]))})


class IsolatorTransient(Effect):
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


# --------------------------------------------------------------------------- the library
def _lib():
    return [
        Dahl("dahl", "pre-motion friction (Dahl)", "deterministic",
             "Friction builds up over a contact stiffness k_sigma after each reversal before gross sliding "
             "(Dahl, Eq. 1.1/4.3); replaces the model's friction elements by Dahl elements (F_C kept).",
             "residual concentrated just after motion reversals and in settling / in-position; vs displacement "
             "since the last reversal it rises or falls over ~F_C/k_sigma and then vanishes",
             param_doc=[("k_sigma", "N/m", "total pre-motion stiffness")]),
        Gms("gms", "pre-motion friction (GMS / Maxwell-slip)", "deterministic",
            "Generalized Maxwell-slip (Eq. 4.4): parallel elasto-slip blocks with fitted capacities (a "
            "Prandtl-Ishlinskii operator, linear in the capacities); replaces the friction elements. A Maxwell-slip "
            "model keeps its own blocks, their slip displacements scaled by one factor x_scale; any other gets 12 "
            "blocks with log-spaced slip displacements.",
            "like Dahl, but the pre-motion transition has a different shape (long tail: blocks slipping after "
            "tens of um); vs displacement since reversal it is piecewise linear",
            param_doc=[("x_scale", "-", "a Maxwell-slip model's own slip displacements scaled (its stiffnesses by 1/x_scale)"),
                       ("F_1..F_N", "N", "block capacities (sum = F_C); without a Maxwell-slip model 12 blocks, "
                        "slip displacements log-spaced 3e-8 (or 3 encoder steps) ... 1e-4 m")]),
        Coulomb("coulomb", "Coulomb friction level", "deterministic",
                "The sliding friction force F_C differs (all friction elements scaled; added at the table if the "
                "model has none).",
                "a step of the residual with the sign of the velocity: constant while sliding, flips at reversals",
                param_doc=[("F_C", "N", "total Coulomb force")]),
        Viscous(
            "viscous", "viscous friction", "deterministic",
            "A force proportional to velocity, where the friction is: the bearings' friction.viscous "
            "(behind their joint on an isolated stage), else table_friction.viscous.",
            "residual proportional to velocity; largest at constant velocity, zero at rest",
            param_doc=[("c", "N·s/m", "total viscous coefficient")]),
        Stribeck("stribeck", "Stribeck effect (LuGre)", "deterministic",
                 "Friction higher at low sliding speed: LuGre with g(v) = F_C + (F_S - F_C) exp(-(v/v_s)^2), "
                 "sigma0 = the model's pre-motion stiffness.",
                 "residual with the sign of velocity, largest at low speed (just after reversals, before "
                 "constant velocity), vanishing above a few v_s",
                 param_doc=[("F_S", "N", "static force"), ("v_s", "m/s", "Stribeck velocity")]),
        LugreDamping("lugre", "pre-motion friction with bristle damping (LuGre)", "deterministic",
                     "LuGre bristles (Canudas de Wit et al. 1995): F = sigma0 z + sigma1 dz/dt, dz/dx = 1 - sigma0 "
                     "sgn(v) z / g(v), in every friction element (F_C, viscous and a LuGre Stribeck curve kept; "
                     "else F_S = F_C). At rest the contact is a spring and damper: after a force change below "
                     "F_C the stage creeps over tau = sigma1 / sigma0 instead of deflecting at once, and the "
                     "pre-motion resonance is damped.",
                     "like Dahl, plus a creep of ~tau after each force change during holds and settling, and a "
                     "damped (shorter) ringing of the pre-motion mode; residual correlated with the velocity "
                     "in the first micrometres after reversals",
                     param_doc=[("sigma0", "N/m", "total bristle stiffness"),
                                ("sigma1", "N·s/m", "total bristle damping")]),
        RegularizedCoulomb("regularized_coulomb", "smooth zero-velocity friction (regularised Coulomb)",
                           "deterministic",
                           "Friction without stiction: F = F_C tanh(v / v_reg) + c v in every friction element "
                           "(F_C, c kept). Near rest it acts as a steep damper F_C / v_reg, so a force below F_C "
                           "makes the stage creep instead of sticking.",
                           "residual during holds and dwell where the model sticks: the stage creeps under "
                           "forces below F_C; residual vs velocity is a step of width ~v_reg rounding the "
                           "Coulomb step at v = 0",
                           param_doc=[("v_reg", "m/s", "regularisation velocity")]),
        FiCompliance("fi_compliance", "FI compliance (bearing behind a spring-damper)", "deterministic",
                     "The bearing carriages are not rigid with the table but behind a joint of stiffness k_fi "
                     "and damping (friction isolator, Ch. 4), in any nominal with friction: adds (or re-fits) "
                     "stage.bearings[*].joint, or -- a nominal written as a table with friction -- makes that "
                     "friction a bearing's behind the joint; the bearing mass m_b is fitted, table + bearings "
                     "kept (a table with friction and a table with bolted bearings give the same fit).",
                     "an oscillatory residual at the joint mode after reversals and moves, frequency "
                     "sqrt(k_fi/m_red)/(2 pi); residual vs acceleration and in the band of that mode",
                     param_doc=[("k_fi", "N/m", "total joint stiffness"), ("zeta_fi", "-", "damping ratio"),
                                ("m_b", "kg", "total bearing mass")]),
        PositionFriction("position_friction", "position-dependent friction", "deterministic",
                         "Friction level varies along the travel: F_C(x) = F_C + dF_0 + g_1 (x - x_c) + g_2 (x - x_c)^2 "
                         "(x_c: centre of the recorded positions), shared over the friction elements in proportion "
                         "to their F_C (friction fields f_c, f_c_gradient, f_c_curvature, position_center); the element's "
                         "whole force scales with F_C(x), pre-motion stiffness included.",
                         "residual with the sign of velocity whose size depends on position (residual vs "
                         "position, split by direction of motion)",
                         param_doc=[("dF_0", "N", "level change"), ("g_1", "N/m", "slope"), ("g_2", "N/m^2", "curvature")]),
        Ripple("ripple", "position-periodic force ripple", "deterministic",
               "Motor cogging / commutation ripple: F = A sin(2 pi x / period + phase) on the table "
               "(stage.force_ripple).",
               "residual periodic in position (peak in the periodogram of residual vs position), independent "
               "of velocity sign",
               param_doc=[("a_sin, a_cos", "N", "amplitudes"), ("period", "m", "spatial period")]),
        Mode("structural_mode", "structural resonance", "deterministic",
             "An (additional) lightly damped mode anywhere between DC and Nyquist: a part of the table's mass "
             "on a spring-damper to the rest (stage.modes; the table mass is reduced by the modal mass, so the "
             "total mass stays the nominal's).",
             "a narrow resonance / anti-resonance of the command -> measurement transfer against the model's "
             "(csd/welch, located and fitted there, any frequency up to Nyquist), a narrow band of the force "
             "residual spectrum, ringing after transients",
             param_doc=[("f", "Hz", "blocked frequency"), ("zeta", "-", "damping ratio"),
                        ("fraction", "-", "modal mass / table DOF mass")]),
        LocatedMode("located_mode", "structural resonance located on the transfer", "integer",
                    "A lightly damped mode above the force observer's reach (the measurement's smoothing "
                    "cutoff) up to Nyquist, as located and fitted on the command -> measurement transfer: "
                    "blocked frequency, damping and mass fraction split off the table (stage.modes; total "
                    "mass kept).",
                    "a narrow resonance / anti-resonance of the measured transfer against the model's, where the "
                    "force residual shows nothing",
                    param_doc=[("mode", "-", "index of the located mode (derived: f [Hz], zeta, fraction)")]),
        Delay("delay", "actuator delay", "integer",
              "The drive applies the command some samples late (stage.drive.delay_samples).",
              "residual correlated with the rate of change of the command (largest where the command changes "
              "fast: reversals, starts of moves); phase lag growing with frequency",
              param_doc=[("delay_samples", "samples", "delay")]),
        FractionalDelay("fractional_delay", "fractional actuator delay", "deterministic",
                        "The drive delay is not a whole number of control periods: the model's delay shifted by "
                        "a fraction of a period (stage.drive.delay_samples + stage.drive.delay_fraction; exact "
                        "delayed zero-order hold: the command of sample k acts from k + delay). On top of the "
                        "whole-sample actuator delay.",
                        "as the actuator delay; the phase lag of the command -> measurement transfer grows "
                        "linearly with frequency, by 360 deg x delay x f / rate",
                        param_doc=[("shift", "samples", "delay added to the model's (-1 ... 1)")]),
        ForceConstant("force_constant", "force-constant error", "deterministic",
                      "The motor force per command differs from nominal (stage.drive.force_constant_ratio).",
                      "residual proportional to the command itself (residual vs command is a straight line)",
                      param_doc=[("ratio", "-", "true/nominal force constant")]),
        Mass("mass", "mass error", "deterministic",
             "The moving mass differs (stage.table.mass).",
             "residual proportional to acceleration (residual vs acceleration is a straight line); "
             "zero at constant velocity and at rest",
             param_doc=[("m_table", "kg", "table mass")]),
        Asymmetry("friction_asymmetry", "direction-asymmetric friction", "deterministic",
                  "Coulomb and viscous friction differ between the two directions of motion (EMPS: "
                  "Fc+ != Fc-, Fv+ != Fv-): friction fields f_c_difference, viscous_difference.",
                  "a residual of the same sign in both directions while moving (not flipping at reversals), "
                  "zero at rest; residual vs velocity is V-shaped / offset between the branches",
                  param_doc=[("dF_C", "N", "F_C+ - F_C-"), ("dc", "N·s/m", "c+ - c-")]),
        Offset("offset", "constant force offset", "deterministic",
               "A constant force on the table (cable drag, gravity on a tilted axis, amplifier offset): "
               "stage.force_offset.",
               "a constant residual, independent of state",
               param_doc=[("F_0", "N", "force")]),
        NoiseLevel("noise_level", "drive-noise level", "stochastic",
                   "The drive current noise differs (stage.drive.noise_current_rms).",
                   "the residual floor (spectrum where the model leaves only noise) is above / below the "
                   "floor of recordings simulated from the model",
                   param_doc=[("noise_current_rms", "A", "RMS current noise")]),
        Quantization("quantization", "encoder quantization", "stochastic",
                     "The encoder resolution differs (stage.encoder.resolution).",
                     "the measured positions sit on a lattice of a different step than the model's",
                     param_doc=[("resolution", "m", "quantization step")]),
        PeriodicForce("dither_imbalance", "dither imbalance / periodic force", "deterministic",
                      "A force at a fixed frequency on the table: the net force of imbalanced dither piezos "
                      "(VAN, Ch. 3) or a periodic disturbance: stage.periodic_force, A sin(2 pi f t + phase).",
                      "a spectral line of the residual far above the floor at one frequency (the dither "
                      "frequency), present in every regime",
                      param_doc=[("a_sin, a_cos", "N", "amplitudes"), ("f", "Hz", "frequency")]),
        IsolatorTransient("isolator_transient", "isolator switching transient", "deterministic",
                          "SAI locking (Ch. 5, Sec. 5.3): the solenoid armature strikes the lock face and a "
                          "force pulse of impulse impact_impulse x (1 - cushioning) reaches the bearing "
                          "(stage.sai.impact_impulse; the switching instants are the recorded /stage/isolator "
                          "or the model's SAI manager on the recorded reference).",
                          "residual bursts a few ms long right after each compliant -> stiff switch, in the "
                          "settling regime, ringing at the lock mode",
                          needs="a model with stage.sai and a sai_manager",
                          param_doc=[("impact_impulse", "N·s", "impulse before cushioning")]),
    ]


LIBRARY: dict[str, Effect] = {e.key: e for e in _lib()}


def library(ctx: dict) -> dict:
    """Every effect of :data:`LIBRARY` bound to a recording's locate context ``ctx``
    (:meth:`Effect.bound`): one diagnosis' library."""
    return {k: e.bound(ctx) for k, e in LIBRARY.items()}


def get_effect(key: str) -> Effect:
    if key not in LIBRARY:
        raise KeyError(f"unknown effect {key!r} (known: {', '.join(LIBRARY)})")
    return LIBRARY[key]


def describe(as_json: bool = False):
    """The library as text (``--list-effects``) or a list of dicts."""
    rows = []
    for e in LIBRARY.values():
        rows.append({"key": e.key, "title": e.title, "kind": e.kind, "physics": e.physics, "signature": e.signature,
                     "parameters": [{"name": n, "unit": u, "unit_rotary": unit_for(u, "rotary"), "meaning": m}
                                    for n, u, m in e.param_doc],
                     "in_preset": e.expressible, "needs": e.needs})
    rows.append({"key": "sparse_regression", "title": "sparse regression (SINDy-style)", "kind": "fallback",
                 "physics": "When no effect explains a residual: sequentially thresholded least squares of the "
                            "residual on a library of state functions (1, v, sign v, v|v|, |v|, x, x^2, a, u, "
                            "friction state phi_f, |phi_f|, phi_f x, phi_f x^2, sin/cos of x at the periodogram "
                            "peak).",
                 "signature": "any residual left above the noise floor after the effects",
                 "parameters": [], "in_preset": False, "needs": "reported as terms; not simulated"})
    if as_json:
        return rows
    out = []
    for r in rows:
        out.append(f"{r['key']}  -  {r['title']}  [{r['kind']}{'' if r['in_preset'] else ', not in preset'}]")
        out.append(f"    physics:   {r['physics']}")
        out.append(f"    signature: {r['signature']}")
        if r["parameters"]:
            out.append("    params:    " + "; ".join(
                f"{p['name']} [{p['unit']}" + (f"; rotary {p['unit_rotary']}" if p["unit_rotary"] != p["unit"] else "")
                + f"] {p['meaning']}".rstrip() for p in r["parameters"]))
        if r["needs"]:
            out.append(f"    needs:     {r['needs']}")
    return "\n".join(out)
