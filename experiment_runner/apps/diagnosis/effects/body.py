"""Body and modes: the table's mass, structural modes (fitted by the force observer, or as located on
the command -> measurement transfer) and the bearings behind a compliant joint (friction isolator)."""
from __future__ import annotations

import copy
import math

import numpy as np

from stage_sim.config import load_preset

from ..context import Context
from .base import NOMINAL, Case, Effect, Param, Parameter, log_uniform

__all__ = ["Mass", "Mode", "LocatedMode", "FiCompliance", "rigid_mass", "split_mode", "TABLE_MASS", "BEARING_MASS",
           "MODE_FRACTION"]

TABLE_MASS = 1.040843214756258
"""Table mass of the self-test's nominal ``fi_stage_nofi`` [kg]."""
BEARING_MASS = 0.427536231884058
"""Mass of one of its two bearings [kg]."""
MODE_FRACTION = 0.15 * TABLE_MASS / (TABLE_MASS * 1.1 + 2 * BEARING_MASS)
"""A 150 Hz mode of 0.15 x the fi_stage_nofi table mass, split off the table's DOF (table with its 381 Hz
mode of mass ratio 0.1, and the two bolted bearings): the total mass kept."""

MASS = ((1e-4, 1e4), (1e-8, 1e2))
"""Plausible masses: linear [kg], rotary inertias [kg·m²]."""


def rigid_mass(stage: dict) -> float:
    """Mass of the table's DOF in a preset mapping's ``stage``: table + rigidly bolted bearings +
    the structural modes on it [kg].

    Parameters
    ----------
    stage : dict
        A preset mapping's ``stage``.

    Returns
    -------
    float
    """
    mt = stage["table"]["mass"]
    return (mt * (1.0 + sum(m["mass_ratio"] for m in stage["modes"]))
            + sum(b["mass"] for b in stage["bearings"] if b.get("joint") is None))


def split_mode(d: dict, f: float, zeta: float, fraction: float) -> None:
    """Add to preset mapping ``d`` a structural mode (blocked frequency ``f`` [Hz], damping ratio
    ``zeta``) whose mass is ``fraction`` of the table DOF's mass (:func:`rigid_mass`), taken out of
    the table: the total mass stays. The other modes keep their masses. Raises ``ValueError`` if
    the table is lighter than the mode mass.

    Parameters
    ----------
    d : dict
        A preset mapping (changed in place).
    f : float
        Blocked frequency [Hz].
    zeta : float
        Damping ratio.
    fraction : float
        Mass fraction of the table's degree of freedom.
    """
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


def _mode_150(d):
    split_mode(d, 150.0, 0.03, MODE_FRACTION)


def frictionless(d: dict) -> None:
    """The nominal stage of preset mapping ``d`` without friction: bearings folded into the table mass.

    Parameters
    ----------
    d : dict
        A preset mapping (changed in place).
    """
    st = d["stage"]
    st["table"]["mass"] = st["table"]["mass"] + sum(b["mass"] for b in st["bearings"])
    st["bearings"] = []
    st["bearing_sensor"] = None


class Mass(Effect):
    """``mass``: an error of the table's mass (see the class attributes and ``--list-effects``)."""
    key = "mass"
    title = "mass error"
    physics = "The moving mass differs (stage.table.mass)."
    signature = ("residual proportional to acceleration (residual vs acceleration is a straight line); "
                 "zero at constant velocity and at rest")
    parameters = (Parameter("m_table", "kg", "table mass", *MASS),)
    deal = 3

    def params(self, spec, ctx):
        m = spec.preset.stage.table.mass
        return [Param("m_table", "kg", 0.2 * m, 5 * m, m, doc="table mass (stage.table.mass)")]

    def nominal(self, spec):
        return {"m_table": spec.preset.stage.table.mass}

    def apply(self, spec, theta):
        return spec.with_changes({"stage.table.mass": float(theta[0])})

    def conceal(self, d, draw):
        d["stage"]["table"]["mass"] *= 1 + draw.sign * draw.size(0.003, 0.6)
        return {"m_table": d["stage"]["table"]["mass"]}

    def selftest_cases(self):
        up = TABLE_MASS * 1.25
        rigid = 1.895915678524374          # table + bearings of fi_stage_nofi [kg]
        return [Case("mass_+25%", "mass", {"stage.table.mass": up}, expect={"m_table": up}),
                # without friction, a mass error and a force-constant error are indistinguishable (F = m a):
                # the diagnosis must report them as a confounded set
                Case("mass_frictionless_confounded", "mass", {"stage.table.mass": rigid * 1.25},
                     expect={"m_table": rigid * 1.25}, nominal_edit=frictionless),
                Case("mass_+25%_sine", "mass", {"stage.table.mass": up}, expect={"m_table": up}, experiment="sine",
                     seed=123)]


class Mode(Effect):
    """A lightly damped mode anywhere between DC and Nyquist, its mass a fraction of the table's
    (:func:`split_mode`: the total mass stays the nominal's); started from the command ->
    measurement transfer (:mod:`..frf`, context ``frf_modes``) and the force residual's peaks."""
    key = "structural_mode"
    title = "structural resonance"
    physics = ("An (additional) lightly damped mode anywhere between DC and Nyquist: a part of the table's mass "
               "on a spring-damper to the rest (stage.modes; the table mass is reduced by the modal mass, so the "
               "total mass stays the nominal's).")
    signature = ("a narrow resonance / anti-resonance of the command -> measurement transfer against the model's "
                 "(csd/welch, located and fitted there, any frequency up to Nyquist), a narrow band of the force "
                 "residual spectrum, ringing after transients")
    parameters = (Parameter("f", "Hz", "blocked frequency", (1.0, 1e5)),
                  Parameter("zeta", "-", "damping ratio", (1e-3, 0.5)),
                  Parameter("fraction", "-", "modal mass / table DOF mass", (1e-3, 0.95)))
    deal = 12

    @staticmethod
    def max_fraction(spec) -> float:
        """The largest mass fraction a mode can take off the table of ``spec``.

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        float
        """
        st = spec.preset.stage
        d = {"table": {"mass": st.table.mass}, "modes": [m.model_dump() for m in st.modes],
             "bearings": [b.model_dump() for b in st.bearings]}
        return 0.95 * st.table.mass / rigid_mass(d)

    def params(self, spec, ctx):
        rate = spec.preset.controller.rate
        frf = list(ctx.frf_modes or [])
        f0 = frf[0]["f_hz"] if frf else (ctx.peak_hz[0] if ctx.peak_hz else 0.1 * rate)
        hi = self.max_fraction(spec)
        return [Param("f", "Hz", 2.0, 0.49 * rate, min(max(f0, 2.5), 0.48 * rate), log=True,
                      doc="blocked natural frequency"),
                Param("zeta", "-", 0.001, 0.5, 0.03, log=True, doc="damping ratio"),
                Param("fraction", "-", 1e-3, hi, min(0.1, 0.5 * hi), log=True,
                      doc="modal mass / mass of the table's DOF (taken out of the table)")]

    def starts(self, spec, ctx):
        rate = spec.preset.controller.rate
        hi = self.max_fraction(spec)
        frf = [[min(max(m["f_hz"], 2.5), 0.48 * rate), min(max(m["zeta"], 0.0015), 0.45),
                min(max(m["fraction"], 0.0015), 0.9 * hi)] for m in (ctx.frf_modes or [])[:2]]
        peaks = list(ctx.peak_hz or [])[:3]
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

    def conceal(self, d, draw):
        mu = draw.size(0.01, 0.5)
        f = draw.random_log(30.0, 0.3 * draw.rate)
        frac = mu * d["stage"]["table"]["mass"] / rigid_mass(d["stage"])    # a mode of mu x the table mass, split off it
        split_mode(d, f, 0.03, frac)
        return {"f": f, "fraction": frac}

    def selftest_cases(self):
        return [Case("structural_mode_150Hz", "structural_mode", edit=_mode_150,
                     expect={"f": 150.0, "fraction": MODE_FRACTION})]


class LocatedMode(Effect):
    """A mode located and fitted on the command -> measurement transfer or the closed loop's noise
    response (:mod:`..frf`) above the force observer's bandwidth, where the observer cannot fit it
    (it follows forces up to its bandwidth; beyond the measurement's smoothing cutoff it sees no
    motion at all): the located fit (frequency, damping, mass fraction; :func:`split_mode`) is the
    candidate as it is, one per located mode, and the judge decides on the held-out data. Refined
    by the replay as a :class:`Mode`.

    Between the observer's bandwidth and the smoothing cutoff a mode is visible to neither fit of
    :class:`Mode` (its observer fit wanders off to where the observer sees something) nor, were
    the cutoff the limit, to this one: a 500 Hz mode under a 400 Hz observer was located within
    5 % and never proposed, and a drive delay stood in for it.

    Examples
    --------
    >>> ctx = Context(observer_hz=400.0, frf_modes=({"f_hz": 520.0, "zeta": 0.03, "fraction": 0.2},
    ...                                              {"f_hz": 150.0, "zeta": 0.03, "fraction": 0.1}))
    >>> [m["f_hz"] for m in LocatedMode().bound(ctx)._modes]
    [520.0]
    """
    key = "located_mode"
    title = "structural resonance located on the transfer or in the noise response"
    kind = "integer"
    physics = ("A lightly damped mode above the force observer's reach (its bandwidth) up to Nyquist, as "
               "located and fitted on the command -> measurement transfer or the closed loop's noise response: "
               "blocked frequency, damping and mass fraction split off the table (stage.modes; total "
               "mass kept).")
    signature = ("a narrow resonance / anti-resonance of the measured transfer against the model's, where the "
                 "force residual shows nothing")
    parameters = (Parameter("mode", "-", "index of the located mode (derived: f [Hz], zeta, fraction)"),)
    truth_of = "structural_mode"
    _modes = None

    def bound(self, ctx: Context):
        f_o = float(ctx.observer_hz or 0.0)
        e = copy.copy(self)
        e._modes = tuple(m for m in ctx.frf_modes or () if m["f_hz"] > f_o)
        return e

    def applicable(self, spec):
        if self._modes is not None and not self._modes:
            return "no mode located above the force observer's bandwidth"
        return None

    def params(self, spec, ctx):
        n = len(self._modes or ())
        return [Param("mode", "-", 0, max(n - 1, 0), 0, doc="index of the located mode")]

    def nominal(self, spec):
        return {"mode": None}

    def mode(self, theta) -> dict:
        """The located mode of parameter ``theta`` (its index): ``f_hz``, ``zeta``, ``fraction``.

        Parameters
        ----------
        theta : sequence of float
            ``[index]`` of the located mode.

        Returns
        -------
        dict
        """
        return self._modes[int(round(float(theta[0])))]

    def with_mode(self, i: int, mode: dict) -> "LocatedMode":
        """A copy whose located mode ``i`` has the values of ``mode`` (a refinement of the transfer's fit).

        Parameters
        ----------
        i : int
            Index of the located mode.
        mode : dict
            Values replacing its own (``f_hz``, ``zeta``, ``fraction``).

        Returns
        -------
        LocatedMode
        """
        e = copy.copy(self)
        e._modes = tuple(dict(m, **mode) if k == i else m for k, m in enumerate(self._modes))
        return e

    def derived(self, spec, theta):
        m = self.mode(theta)
        return {"f": m["f_hz"], "zeta": m["zeta"], "fraction": m["fraction"]}

    def apply(self, spec, theta):
        m = self.mode(theta)
        return spec.with_changes(edit=lambda d: split_mode(d, m["f_hz"], m["zeta"], m["fraction"]))


def _fi_joints(d):
    for b in d["stage"]["bearings"]:
        b["joint"] = {"stiffness": 4.135e4, "damping": 2.2691}


def _fi_stage(d):
    """The FI compliance's truth: the nominal's stage with its bearings behind the FI joints."""
    nom = load_preset(NOMINAL).model_dump(mode="json")
    _fi_joints(nom)
    d["stage"] = nom["stage"]


def table_friction(d: dict) -> None:
    """The nominal's rigid body of preset mapping ``d`` written as a table with friction: its ``n``
    identical bolted bearings (a Dahl or Coulomb law) folded into the table mass and one
    table element of ``n`` times their forces and stiffness (``n`` identical elements in parallel
    are exactly that).

    Parameters
    ----------
    d : dict
        A preset mapping (changed in place).
    """
    st = d["stage"]
    n = len(st["bearings"])
    fr = dict(st["bearings"][0]["friction"])
    if not all(b["friction"] == fr for b in st["bearings"]) or fr["model"] not in ("dahl", "coulomb"):
        raise ValueError(f"table_friction: needs identical Dahl or Coulomb bearings, got {st['bearings']}")
    fr.update({k: n * fr[k] for k in ("f_c", "f_s", "k_sigma", "viscous", "f_c_difference", "viscous_difference",
                                      "f_c_gradient", "f_c_curvature") if fr.get(k) is not None})
    m_old = st["table"]["mass"]
    st["table"]["mass"] = m_old + sum(b["mass"] for b in st["bearings"])
    for md in st["modes"]:                  # the table's structural mode keeps its mass
        md["mass_ratio"] *= m_old / st["table"]["mass"]
    st["bearings"] = []
    st["bearing_sensor"] = None
    st["table_friction"] = fr


class FiCompliance(Effect):
    """The bearings behind a spring-damper (friction isolator, Ch. 4), in any nominal with friction:
    its bolted bearings, or -- a nominal written as "table with friction" -- a bearing made of the
    table friction. The rigid mass (table + bearings) is kept. A nominal with bolted bearings states
    their mass: it is held (a stated quantity), and only ``k_fi`` and ``zeta_fi`` are fitted -- with
    the mass free as well, the joint's frequency fixes only k_fi/m_red and the three slide along one
    valley to a bound (power case 029). A nominal written as a table with friction states no
    bearing mass: ``m_b`` is fitted as a third parameter."""
    key = "fi_compliance"
    title = "FI compliance (bearing behind a spring-damper)"
    physics = ("The bearing carriages are not rigid with the table but behind a joint of stiffness k_fi "
               "and damping (friction isolator, Ch. 4), in any nominal with friction: adds (or re-fits) "
               "stage.bearings[*].joint, or -- a nominal written as a table with friction -- makes that "
               "friction a bearing's behind the joint; table + bearings kept; the bearing mass m_b is "
               "the nominal's where it states bolted bearings, fitted where it states a table with friction).")
    signature = ("an oscillatory residual at the joint mode after reversals and moves, frequency "
                 "sqrt(k_fi/m_red)/(2 pi); residual vs acceleration and in the band of that mode")
    parameters = (Parameter("k_fi", "N/m", "total joint stiffness", (1.0, 1e10), (1e-4, 1e6)),
                  Parameter("zeta_fi", "-", "damping ratio", (1e-3, 1.0)),
                  Parameter("m_b", "kg", "total bearing mass", *MASS))
    deal = 9

    def applicable(self, spec):
        st = spec.preset.stage
        if not st.bearings and st.table_friction is None:
            return "the stage has no friction to put behind a joint (no bearing, no table friction)"
        return None

    @staticmethod
    def rigid(st):
        """Mass of the rigid body: table + bearings [kg].

        Parameters
        ----------
        st : stage_sim.config.Stage
            The model's stage.

        Returns
        -------
        float
        """
        return st.table.mass + sum(b.mass for b in st.bearings)

    @staticmethod
    def mode_mass(st):
        """Mass of the table's structural modes [kg].

        Parameters
        ----------
        st : stage_sim.config.Stage
            The model's stage.

        Returns
        -------
        float
        """
        return st.table.mass * sum(m.mass_ratio for m in st.modes)

    def reduced_mass(self, st, mb):
        """Reduced mass of one of the ``nb`` joints for total bearing mass ``mb`` [kg].

        Parameters
        ----------
        st : stage_sim.config.Stage
            The model's stage.
        mb : float
            Total bearing mass [kg].

        Returns
        -------
        float
        """
        nb = max(len(st.bearings), 1)
        mt = self.rigid(st) - mb + self.mode_mass(st)
        return (mb / nb) * mt / (mb / nb + mt)

    def bearing_mass(self, st):
        """The model's bearing mass, or a tenth of the rigid mass without bearings [kg].

        Parameters
        ----------
        st : stage_sim.config.Stage
            The model's stage.

        Returns
        -------
        float
        """
        held = self._held_mass(st)
        return held if held is not None else 0.1 * self.rigid(st)

    @staticmethod
    def _held_mass(st):
        """The bearing mass the nominal states (bolted bearings), held in the fit, else None [kg]."""
        return sum(b.mass for b in st.bearings) if st.bearings else None

    def _mass(self, st, theta):
        """The total bearing mass for parameters ``theta`` (k_fi, zeta_fi[, m_b]) on stage ``st`` [kg]."""
        return float(theta[2]) if len(theta) > 2 else self._held_mass(st)

    def params(self, spec, ctx):
        st = spec.preset.stage
        nb = max(len(st.bearings), 1)
        mb0 = self.bearing_mass(st)
        jointed = bool(st.bearings) and st.bearings[0].joint is not None
        k0 = st.bearings[0].joint.stiffness * nb if jointed else None
        kg = k0 or self.reduced_mass(st, mb0) * (2 * np.pi * 50.0) ** 2 * nb
        M = self.rigid(st)
        ps = [Param("k_fi", "N/m", 1e-3 * kg, 1e3 * kg, kg, log=True, doc="total joint stiffness (all bearings)"),
              Param("zeta_fi", "-", 1e-3, 1.0, 0.02, log=True, doc="joint damping ratio on the reduced mass")]
        if self._held_mass(st) is None:
            ps.append(Param("m_b", "kg", 0.005 * M, 0.8 * M, min(max(mb0, 0.01 * M), 0.7 * M), log=True,
                            doc="total bearing mass behind the joints (table + bearings kept)"))
        return ps

    def starts(self, spec, ctx):
        st = spec.preset.stage
        nb = max(len(st.bearings), 1)
        ps = self.params(spec, ctx)
        mb = ps[2].x0 if len(ps) > 2 else self._held_mass(st)
        tail = [mb] if len(ps) > 2 else []
        if st.bearings and st.bearings[0].joint is not None:
            k0 = st.bearings[0].joint.stiffness * nb
            return [[k0, 0.02] + tail, [0.3 * k0, 0.02] + tail, [3 * k0, 0.02] + tail]
        mr = self.reduced_mass(st, mb)
        fr = list(ctx.peak_hz or [])[:2] + [20.0, 60.0, 200.0]
        return [[mr * (2 * np.pi * f) ** 2 * nb, 0.02] + tail for f in fr[:4]]

    def nominal(self, spec):
        st = spec.preset.stage
        if st.bearings and st.bearings[0].joint is not None:
            j = st.bearings[0].joint
            mb = self._held_mass(st)
            return {"k_fi": j.stiffness * len(st.bearings),
                    "zeta_fi": j.damping / (2 * math.sqrt(j.stiffness * self.reduced_mass(st, mb)))}
        return {"k_fi": None, "zeta_fi": None} if st.bearings else {"k_fi": None, "zeta_fi": None, "m_b": None}

    def derived(self, spec, theta):
        st = spec.preset.stage
        k, mb = float(theta[0]), self._mass(st, theta)
        nb = max(len(st.bearings), 1)
        return {"f_joint_hz": math.sqrt(k / nb / self.reduced_mass(st, mb)) / (2 * math.pi)}

    def apply(self, spec, theta):
        st = spec.preset.stage
        k, z, mb = float(theta[0]), float(theta[1]), self._mass(st, theta)
        M = self.rigid(st)
        m_old = st.table.mass
        m_new = M - mb
        nb = max(len(st.bearings), 1)
        kb = k / nb
        mr = self.reduced_mass(st, mb)
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

    def conceal_on(self, stage, law):
        return stage != "sai"

    def conceal(self, d, draw):
        nb = len(d["stage"]["bearings"])
        if draw.stage == "isolated":
            f = math.exp(draw.sign * draw.size(0.05, 2.0))
            for b in d["stage"]["bearings"]:
                b["joint"]["stiffness"] *= f
                b["joint"]["damping"] *= math.sqrt(f)
            return {"k_fi": sum(b["joint"]["stiffness"] for b in d["stage"]["bearings"])}
        k = log_uniform(1 - draw.q, 2e4, 2e7)
        mt = d["stage"]["table"]["mass"] * (1 + sum(m_["mass_ratio"] for m_ in d["stage"]["modes"]))
        for b in d["stage"]["bearings"]:
            mr = b["mass"] * mt / (b["mass"] + mt)
            b["joint"] = {"stiffness": k / nb, "damping": 2 * 0.02 * math.sqrt(k / nb * mr)}
        return {"k_fi": k}

    def selftest_cases(self):
        return [Case("fi_compliance", "fi_compliance", edit=_fi_joints, expect={"k_fi": 8.27e4}, experiment="steps"),
                # found from a nominal written as a table with friction (the bearing mass fitted)
                Case("fi_compliance_table_friction", "fi_compliance", edit=_fi_stage, nominal_edit=table_friction,
                     expect={"k_fi": 8.27e4, "m_b": 2 * BEARING_MASS}, experiment="steps", seed=152)]
