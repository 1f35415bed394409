"""What every effect of the diagnosis library is and declares.

An :class:`Effect` is one hypothesis: a model change with parameters, bounds and a signature.
:meth:`Effect.apply` turns a parameter vector into a modified :class:`~..model.ModelSpec`, relative
to the model it is added to. ``kind`` says how it is fitted:

``deterministic``  fitted to the force residual on the fit set, refined by the replay (:mod:`..fit`);
``integer``        a grid over integers (actuator delay, a located mode's index);
``stochastic``     decided by its own stage: the measurement lattice (quantization) or the
                   replay's run-to-run consistency (drive noise).

Each effect class declares, besides its model change: its ``key``, ``title``, ``physics`` and
``signature`` (``nanostage diagnose --list-effects``), its documented :class:`Parameter` s with
units and plausible ranges on a linear and a rotary axis, its exclusive groups (at most one
adopted effect per group), whether it states a quantity a nominal gives as known
(``known_quantity``), its concealed truth for the power study (:meth:`Effect.conceal`, on the
settings :meth:`Effect.conceal_on`) and its self-test cases (:meth:`Effect.selftest_cases`).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, ClassVar

import numpy as np

from stage_sim.config import load_preset, preset_from_dict, with_overrides

from ..context import Context
from ..model import ModelSpec
from ..units import unit_for

__all__ = ["Param", "Parameter", "Effect", "Case", "Draw", "log_uniform", "both_bearings", "for_bearings",
           "bearing_f_c", "NOMINAL"]

NOMINAL = "fi_stage_nofi"
"""The self-test's default nominal preset (the Ch. 4 stage without FI, Dahl bearings)."""


@dataclass
class Param:
    """A fitted parameter on a given model: its bounds and start (:meth:`Effect.params`).

    Parameters
    ----------
    name : str
        As the effect's documented :class:`Parameter`.
    unit : str
        Its unit (linear axis; :func:`..units.unit_for` on a rotary one).
    lo, hi : float
        Bounds of the fit; a value at a bound is "not identified" (but see ``physical_lo``).
    x0 : float
        Start value.
    log : bool
        Fitted in log space (a positive scale parameter).
    doc : str
        What it is, in words.
    physical_lo : bool
        The lower bound is a physical limit.
    """
    name: str
    unit: str
    lo: float
    hi: float
    x0: float
    log: bool = False
    doc: str = ""
    physical_lo: bool = False
    """The lower bound is a physical limit (a capacity >= 0): reaching it is a result (the element
    is absent), not "not identified"."""

    def clip(self, v):
        """``v`` within ``[lo, hi]``.

        Parameters
        ----------
        v : float
            A value.

        Returns
        -------
        float

        Examples
        --------
        >>> Param("m", "kg", 0.1, 10.0, 1.0).clip(20.0)
        10.0
        """
        return float(min(max(v, self.lo), self.hi))


@dataclass(frozen=True)
class Parameter:
    """A parameter as the library documents it (``--list-effects``).

    ``plausible`` is the range of physically plausible values on a linear axis, in ``unit``;
    ``plausible_rotary`` the range on a rotary axis, in ``unit_for(unit, "rotary")`` (None where the
    unit is the same on both axes: ``plausible`` holds for both). ``signed``: a difference, offset or
    slope of either sign, whose *magnitude* the range bounds.

    Parameters
    ----------
    name : str
        As in the effect's :meth:`Effect.params`.
    unit : str
        Unit on a linear axis.
    meaning : str
        What it is, in words.
    plausible : tuple of float, optional
        Physically plausible range on a linear axis.
    plausible_rotary : tuple of float, optional
        The range on a rotary axis.
    signed : bool
        A quantity of either sign.
    """
    name: str
    unit: str
    meaning: str
    plausible: tuple | None = None
    plausible_rotary: tuple | None = None
    signed: bool = False

    def plausible_on(self, axis: str = "linear") -> tuple | None:
        """The plausible range on an axis of ``axis`` (``linear`` or ``rotary``), in that axis' unit.

        Parameters
        ----------
        axis : {"linear", "rotary"}
            The axis.

        Returns
        -------
        tuple of float or None

        Examples
        --------
        >>> p = Parameter("c", "N·s/m", "viscous coefficient", (1e-3, 1e5), (1e-7, 1e2))
        >>> p.plausible_on("rotary")
        (1e-07, 100.0)
        >>> Parameter("f", "Hz", "frequency", (1.0, 1e5)).plausible_on("rotary")
        (1.0, 100000.0)
        """
        if axis == "rotary" and unit_for(self.unit, "rotary") != self.unit:
            return self.plausible_rotary
        return self.plausible

    def row(self) -> dict:
        """The parameter as ``--list-effects --json`` gives it.

        Returns
        -------
        dict
        """
        return {"name": self.name, "unit": self.unit, "unit_rotary": unit_for(self.unit, "rotary"),
                "meaning": self.meaning, "plausible": self.plausible_on("linear"),
                "plausible_rotary": self.plausible_on("rotary")}


def log_uniform(q: float, lo: float, hi: float) -> float:
    """The value at quantile ``q`` (0...1) of a log-uniform range ``[lo, hi]``.

    Parameters
    ----------
    q : float
        Quantile, 0...1.
    lo, hi : float
        The range (both > 0).

    Returns
    -------
    float

    Examples
    --------
    >>> log_uniform(0.5, 1e-3, 1e-1)
    0.01
    """
    return float(lo * (hi / lo) ** q)


@dataclass
class Draw:
    """What a power-study case gives an effect's truth writer (:meth:`Effect.conceal`): the size
    quantile ``q`` (0...1: well below to well above what the record shows), the sign, the case's
    random generator (drawn in a fixed order: same study, same cases), the setting (stage
    ``rigid``/``isolated``/``sai``, the nominal's friction law ``dahl``/``gms``/``coulomb``, the
    control rate) and the record's scales.

    Parameters
    ----------
    q : float
        Size quantile, 0...1.
    sign : float
        +1 or -1, for signed effects.
    rng : numpy.random.Generator
        The case's generator.
    stage : {"rigid", "isolated", "sai"}
        The nominal stage.
    friction : {"dahl", "gms", "coulomb"}
        The nominal's bearing friction law.
    rate : float
        Control rate [Hz].
    x_center : float
        Centre of the references' position range [m].
    half_span : float
        Half that range [m] (at least 0.1 mm).
    stroke : float
        Median range of one trial's reference [m] (at least 2 um).
    v_max : float
        Largest reference speed [m/s] (at least 10 um/s).
    """
    q: float
    sign: float
    rng: np.random.Generator
    stage: str
    friction: str
    rate: float
    x_center: float
    half_span: float
    stroke: float
    v_max: float

    def size(self, lo: float, hi: float) -> float:
        """The effect's size at this case's quantile of the log-uniform range ``[lo, hi]``.

        Parameters
        ----------
        lo, hi : float
            The range, from well below to well above what the record shows.

        Returns
        -------
        float
        """
        return log_uniform(self.q, lo, hi)

    def random_log(self, lo: float, hi: float) -> float:
        """A log-uniform draw from ``[lo, hi]`` (one number of the case's generator).

        Parameters
        ----------
        lo, hi : float
            The range.

        Returns
        -------
        float
        """
        return log_uniform(self.rng.random(), lo, hi)


def for_bearings(d: dict, fn) -> None:
    """``fn(friction mapping, bearing mapping)`` for every bearing of preset mapping ``d``.

    Parameters
    ----------
    d : dict
        A preset mapping (changed in place by ``fn``).
    fn : callable
        ``fn(friction, bearing)``.
    """
    for b in d["stage"]["bearings"]:
        fn(b["friction"], b)


def bearing_f_c(d: dict) -> float:
    """Sum of the bearings' Coulomb forces of preset mapping ``d`` [N].

    Parameters
    ----------
    d : dict
        A preset mapping.

    Returns
    -------
    float
    """
    return sum(b["friction"]["f_c"] for b in d["stage"]["bearings"])


def both_bearings(path_tail: str, value) -> dict:
    """Dotted overrides setting ``path_tail`` of both bearings of a two-bearing stage to ``value``.

    Parameters
    ----------
    path_tail : str
        Dotted path below a bearing.
    value : object
        The value.

    Returns
    -------
    dict

    Examples
    --------
    >>> both_bearings("friction.viscous", 10.0)
    {'stage.bearings.0.friction.viscous': 10.0, 'stage.bearings.1.friction.viscous': 10.0}
    """
    return {f"stage.bearings.0.{path_tail}": value, f"stage.bearings.1.{path_tail}": value}


@dataclass
class Case:
    """A self-test case: a concealed truth (the nominal with the dotted ``changes`` and then the
    ``edit``, or nothing for a negative control; drive noise and quantization on), the recording
    kind (``experiment``: a key of :data:`..selftest.EXPERIMENTS`) and what the diagnosis must find
    (``effect``: a key, a pair of keys, or None; ``expect``: parameter or derived name -> truth value,
    for a pair effect -> {name: value}).

    Parameters
    ----------
    name : str
        Case name (``--only`` selects by prefix).
    effect : str, tuple of str or None
        The effect(s) to find; None: a negative control.
    changes : dict
        Dotted overrides of the nominal making the truth.
    edit : callable, optional
        ``edit(mapping)`` on the truth's preset mapping, after ``changes``.
    expect : dict
        Truth values the diagnosis's estimates are checked against.
    experiment : str
        Recording kind.
    seed : int
        Noise seed of the truth's recording.
    nominal : str
        Nominal preset name.
    nominal_edit : callable, optional
        Makes the nominal from the preset's mapping.
    """
    name: str
    effect: str | tuple | None
    changes: dict = field(default_factory=dict)
    edit: Callable | None = None
    expect: dict = field(default_factory=dict)
    experiment: str = "circle"
    seed: int = 101
    nominal: str = NOMINAL
    nominal_edit: Callable | None = None
    """Makes the nominal (and the truth's base) from the ``nominal`` preset's mapping."""

    @property
    def effects(self) -> tuple:
        """The expected effects (``()`` for a negative control)."""
        return () if self.effect is None else ((self.effect,) if isinstance(self.effect, str) else tuple(self.effect))

    def expects(self) -> dict:
        """effect -> {parameter: truth value}.

        Returns
        -------
        dict
        """
        return {self.effect: self.expect} if isinstance(self.effect, str) else dict(self.expect)

    def nominal_doc(self) -> dict:
        """The nominal preset mapping.

        Returns
        -------
        dict
        """
        data = load_preset(self.nominal).model_dump(mode="json")
        if self.nominal_edit is not None:
            self.nominal_edit(data)
            data["name"] = f"{data['name']}_{self.name}_nominal"
        return data

    def truth_doc(self) -> dict:
        """The concealed truth's preset mapping (noise seed ``seed``).

        Returns
        -------
        dict
        """
        nom = preset_from_dict(self.nominal_doc())
        p = with_overrides(nom, self.changes) if self.changes else nom
        data = p.model_dump(mode="json")
        if self.edit is not None:
            self.edit(data)
        data["name"] = f"truth_{self.name}"
        data["simulation"]["seed"] = self.seed
        return data

    @staticmethod
    def pair(name: str, first: "Case", second: "Case", seed: int, experiment: str | None = None) -> "Case":
        """The case of two effects: the truths of ``first`` and ``second`` (their changes, then their
        edits in that order) on ``first``'s nominal and recording kind (or ``experiment``).

        Parameters
        ----------
        name : str
            The pair case's name.
        first, second : Case
            The single-effect cases.
        seed : int
            Noise seed.
        experiment : str, optional
            Recording kind (default ``first``'s).

        Returns
        -------
        Case
        """
        edits = [e for e in (first.edit, second.edit) if e is not None]

        def edit(d):
            for e in edits:
                e(d)
        return Case(name, (first.effect, second.effect), {**first.changes, **second.changes},
                    edit=edit if edits else None, expect={first.effect: first.expect, second.effect: second.expect},
                    experiment=experiment or first.experiment, seed=seed, nominal=first.nominal,
                    nominal_edit=first.nominal_edit)


class Effect:
    """One hypothesis of the library (module docstring). Subclasses declare the class attributes
    and implement :meth:`params` and :meth:`apply`; :meth:`conceal` and :meth:`selftest_cases` unless
    ``truth_of`` names the effect whose truths stand for theirs."""

    key: ClassVar[str] = ""
    title: ClassVar[str] = ""
    kind: ClassVar[str] = "deterministic"
    physics: ClassVar[str] = ""
    signature: ClassVar[str] = ""
    parameters: ClassVar[tuple] = ()
    """The documented parameters (:class:`Parameter`)."""
    expressible: ClassVar[bool] = True
    """The fitted model is a preset the simulator runs as is."""
    needs: ClassVar[str] = ""
    """What a model must have for the effect to apply (said by ``--list-effects``)."""
    exclusive: ClassVar[tuple] = ()
    """Names of the groups of which at most one effect is adopted (alternative friction laws)."""
    known_quantity: ClassVar[bool] = False
    """States a quantity a nominal gives as known (a data-sheet force constant): among candidates the
    replay cannot tell apart it is adopted last, and it moves only when the data demand it."""
    not_after: ClassVar[tuple] = ()
    """Keys of adopted effects after which this one is not proposed (it is part of them)."""
    sets_friction_level: ClassVar[bool] = False
    """Adopted, it is the Coulomb level (:attr:`..context.Context.level_fitted`)."""
    resolution: ClassVar[float | None] = None
    """Half the grid step of an integer effect's values (a whole-sample delay: 0.5 sample): what the
    effect itself cannot resolve; reported beside its value (``resolution``), its σ being None."""
    continues: ClassVar[tuple] = ()
    """Keys of integer effects whose value this one continues below their grid step (a fraction of a
    sample after a whole-sample delay): once one of them is adopted, this one is tried before the
    forward selection stops (a whole sample away from the truth can be within the floor)."""
    in_drive: ClassVar[bool] = False
    """A property of the drive between a recorded command and the force it applies (force constant,
    drive delay): no candidate where the recorded command is the force applied, measured
    (``command.kind: measured``)."""
    deal: ClassVar[int | None] = None
    """Place in the power study's deal of single-effect cases (the study is fixed by it; a new
    effect takes the next number); None: not dealt (``truth_of``)."""
    paired: ClassVar[bool] = True
    """Dealt in the power study's pairs."""
    never_paired_with: ClassVar[tuple] = ()
    """Keys it is never dealt with as a pair (besides its exclusive groups)."""
    truth_of: ClassVar[str | None] = None
    """The key of the effect whose concealed truths and self-test cases stand for this one's (a mode
    fitted on the transfer is concealed as a structural mode)."""

    def bound(self, ctx: Context) -> "Effect":
        """This effect for a recording whose located context is ``ctx``: a copy that carries what
        its model change needs from the recording (block slip distances, located modes, the
        position centre). Library instances are never changed, so fits on threads and concurrent
        diagnoses share them safely; a context-free effect is its own bound form.

        Parameters
        ----------
        ctx : Context
            What was located on the recording (slip distances, modes, position centre, levels).

        Returns
        -------
        Effect
        """
        return self

    def applicable(self, spec: ModelSpec) -> str | None:
        """``None`` if the effect can be added to ``spec``, else the reason it cannot.

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.

        Returns
        -------
        str or None
        """
        return None

    def params(self, spec: ModelSpec, ctx: Context) -> list[Param]:
        """The fitted parameters on ``spec``, bounds and starts from ``ctx``.

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.
        ctx : Context
            What was located on the recording (slip distances, modes, position centre, levels).

        Returns
        -------
        list of Param
        """
        return []

    def apply(self, spec: ModelSpec, theta) -> ModelSpec:
        """``spec`` with the effect of parameters ``theta``.

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.
        theta : sequence of float
            Parameter values, in the order of :meth:`params` (units of each :class:`Param`).

        Returns
        -------
        ModelSpec
        """
        raise NotImplementedError

    def nominal(self, spec: ModelSpec) -> dict:
        """The model's values of the parameters (None where it has no such term).

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.

        Returns
        -------
        dict
            Parameter name -> value.
        """
        return {}

    def derived(self, spec: ModelSpec, theta) -> dict:
        """Physical quantities derived from the fit (compared with a truth in the self-test).

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.
        theta : sequence of float
            Parameter values, in the order of :meth:`params` (units of each :class:`Param`).

        Returns
        -------
        dict
            Name -> value.
        """
        return {}

    def probe(self, spec: ModelSpec, ctx: Context):
        """A small instance of the effect on ``spec`` for its detection limit: ``(theta, i)``, the
        parameters and the index of the one whose change from the model's value is the effect's size;
        None where the effect has no size alone (a period or frequency first to be located). Default:
        a one-parameter deterministic effect moved from its model value by 5 % of it (2 % of its range
        where it is 0).

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.
        ctx : Context
            What was located on the recording (slip distances, modes, position centre, levels).

        Returns
        -------
        tuple or None
            ``(theta, i)``.
        """
        if self.kind != "deterministic":
            return None
        ps = self.params(spec, ctx)
        if len(ps) != 1:
            return None
        p, v0 = ps[0], self.nominal(spec).get(ps[0].name)
        if v0 is None:
            return None
        h = 0.05 * abs(v0) if v0 != 0 else 0.02 * (p.hi - p.lo)
        return ([v0 + h] if v0 + h <= p.hi else [v0 - h]), 0

    def starts(self, spec: ModelSpec, ctx: Context) -> list:
        """Initial parameter vectors (multi-start); default: the x0 of :meth:`params`.

        Parameters
        ----------
        spec : ModelSpec
            The model the effect is added to.
        ctx : Context
            What was located on the recording (slip distances, modes, position centre, levels).

        Returns
        -------
        list of list of float
        """
        return [[p.x0 for p in self.params(spec, ctx)]]

    # ------------------------------------------------------------------ concealed truths
    def conceal_on(self, stage: str, friction: str) -> bool:
        """Whether a power-study truth of this effect can be written on a nominal of ``stage``
        (``rigid``/``isolated``/``sai``) with bearings of law ``friction`` (``dahl``/``gms``/``coulomb``).

        Parameters
        ----------
        stage : str
            The nominal stage.
        friction : str
            The nominal's bearing friction law.

        Returns
        -------
        bool
        """
        return True

    def conceal(self, d: dict, draw: Draw) -> dict:
        """Write the effect of size ``draw`` into the preset mapping ``d`` (in place); returns the
        truth values of its parameters (this effect's parametrisation) for the power study.

        Parameters
        ----------
        d : dict
            The nominal's preset mapping, changed in place into the truth.
        draw : Draw
            The case's size quantile, generator, setting and record scales.

        Returns
        -------
        dict
            Parameter name -> truth value.
        """
        raise NotImplementedError(f"{self.key}: no concealed truth of its own (truth_of {self.truth_of!r})")

    def selftest_cases(self) -> list[Case]:
        """The self-test cases whose truth this effect is (a pair case lists both effects).

        Returns
        -------
        list of Case
        """
        return []

    # ------------------------------------------------------------------ listing
    def row(self) -> dict:
        """The effect as ``--list-effects --json`` gives it.

        Returns
        -------
        dict
        """
        return {"key": self.key, "title": self.title, "kind": self.kind, "physics": self.physics,
                "signature": self.signature, "parameters": [p.row() for p in self.parameters],
                "in_preset": self.expressible, "needs": self.needs, "exclusive": list(self.exclusive),
                "known_quantity": self.known_quantity, "in_drive": self.in_drive}
