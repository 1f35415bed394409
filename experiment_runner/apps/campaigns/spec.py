"""Campaign files: the seed's comparison tables as YAML files, calibrated, run and reported.

A campaign (``experiment_runner/apps/campaigns/<name>.yaml``, or any path) is one of the
seed's experimental comparisons, e.g. Table 4.2 (No FI vs FI, 5 mm and 5 µm
point-to-point, 50 trials at random positions). It is validated into a
:class:`Campaign` (pydantic, unknown keys refused, errors name the field) holding

* ``cases`` -- what is compared (a preset plus dotted-path overrides each; optional SAI
  Step II learning), one of them the ``baseline``;
* ``test`` -- the reference family and its *conditions* (point-to-point step sizes,
  or circle radius x speed), the window, the dwell;
* ``sweep`` -- optionally one more axis: a parameter and its values (cases x
  conditions x values);
* ``trials`` and ``starts`` -- how many trials per case and condition, where they start;
* ``seed`` -- the seed's numbers the simulation is compared with, and every finding the
  seed reports as a direction (lower / higher / similar) between two cases;
* ``calibration`` -- the few physically meaningful parameters fitted on the *baseline*
  case only (:mod:`experiment_runner.apps.campaigns.calibration`); every other case is a prediction. Or
  ``calibration: {from: NAME}``: a campaign on the same stage and PID (e.g. the circle tests
  of table_4_2's stage) reuses NAME's baseline fit instead of refitting (loaded from a
  matching ``calibration.json``, else fitted once and cached there,
  :func:`experiment_runner.apps.campaigns.calibration.source_calibration`).

Circle tests give each radius its own speeds (``circles``); a case's ``per_speed`` sets a
path to a factor times the condition's speed (the SAI's reversal window). A sweep may have
per-case targets (``apply``) and ``mode: series_scale`` (a model stiffness with an error, in
series with an FI's, Sec. 4.4.3). A finding may carry the seed's percentage (``change``) when
the seed gives no absolute numbers (Table 6.3), compare the spread over the sweep values
(``over: sweep_spread``, the ±1σ bands of Fig. 4.18) and, for 'similar', the reductions vs a
third case (``relative_to``, as the seed's reduction plots do).

This module is the schema (pydantic, no code executed), :func:`load_campaign` /
:func:`list_campaigns`, the conditions and the presets of every case (:func:`case_preset`:
campaign, case, calibrated and swept overrides). Each test kind (``point_to_point``,
``circle``, ``frequency_response``) is one schema class here that knows its conditions, its
metrics and its reference; what a kind *does* (run, report section, plots) is its
:class:`~experiment_runner.apps.campaigns.base.CampaignKind` in :mod:`experiment_runner.apps.campaigns.kinds`.

Examples
--------
>>> {"table_4_2", "table_5_2"} <= set(list_campaigns())
True
>>> c = load_campaign("table_4_2")
>>> c.baseline, [k.name for k in c.cases], [cond.label for cond in conditions(c)]
('nofi', ['nofi', 'fi'], ['5 mm', '5 µm'])
"""
from __future__ import annotations

import copy
import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Annotated, ClassVar, Literal, Optional, Union

import numpy as np
from pydantic import ConfigDict, Discriminator, Field, Tag, ValidationError, model_validator

from experiment_runner.apps.campaigns.registry import Metric
from experiment_runner.core import experiment, profiles
from experiment_runner.core.experiment import Move, Starts
from stage_sim.config import (ConfigError, Finite, Fraction, NonNeg, Pos, Preset, schema_error_message, StrictModel,
                              load_preset, read_yaml_file, with_overrides)

__all__ = ["Campaign", "Case", "Condition", "PointToPointTest", "CircleTest", "FrequencyResponseTest",
           "load_campaign", "list_campaigns", "check_campaign", "conditions", "frequency_grid", "fmt_length",
           "case_overrides", "case_preset", "resolve", "cal_parameters", "calibration_source", "CAMPAIGN_DIR"]

CAMPAIGN_DIR = Path(__file__).parent
"""The shipped campaign files (``*.yaml`` next to this module, installed as package data)."""
Name = Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=40)]


# =========================================================================== conditions
def fmt_length(x: float) -> str:
    """``5e-3 -> '5 mm'``, ``5e-6 -> '5 µm'``, ``5e-8 -> '50 nm'``.

    Parameters
    ----------
    x : float
        A length [m].

    Returns
    -------
    str

    Examples
    --------
    >>> fmt_length(5e-3), fmt_length(-5e-6), fmt_length(2e-5)
    ('5 mm', '-5 µm', '20 µm')
    """
    a = abs(x)
    for unit, s in (("m", 1.0), ("mm", 1e-3), ("µm", 1e-6), ("nm", 1e-9)):
        if a >= s * 0.9999:
            return f"{x / s:.4g} {unit}"
    return f"{x * 1e12:.4g} pm"


def _slug(s: str) -> str:
    return "".join(ch if ch.isalnum() else "_" for ch in s.replace("µ", "u").replace(" ", "")).strip("_")


@dataclass(frozen=True)
class Condition:
    """One test condition (a step size, a radius and speed, or a force amplitude) and sweep value.

    The coordinates a kind does not use are None.

    Parameters
    ----------
    key : str
        Identifier of the condition, letters, digits and ``_`` only (``'5mm'``), unique in the
        campaign: used in file names and result keys.
    label : str
        The condition as the reports show it (``'5 mm'``).
    step : float, optional
        Point-to-point step size [m] (signed).
    radius : float, optional
        Circle radius [m].
    speed : float, optional
        Circle tangential speed [m/s].
    sweep : float, optional
        The campaign sweep's value (in the sweep's ``unit``).
    amplitude : float, optional
        Frequency response: force amplitude at the plant input [N].

    Examples
    --------
    >>> c = Condition("5mm__k_2", "5 mm, k = 2", step=5e-3, sweep=2.0)
    >>> c.matches(step=5e-3), c.matches(step=5e-3, sweep=1.0), c.matches(radius=1e-3)
    (True, False, False)
    >>> c.at()
    {'step': 0.005, 'sweep': 2.0}
    """
    key: str
    label: str
    step: Optional[float] = None
    radius: Optional[float] = None
    speed: Optional[float] = None
    sweep: Optional[float] = None
    amplitude: Optional[float] = None          # frequency_response: force amplitude [N]

    def matches(self, step=None, radius=None, speed=None, sweep=None, amplitude=None) -> bool:
        """Whether this condition has every coordinate given (equal to a relative 1e-9; None: any).

        Parameters
        ----------
        step : float, optional
            Step size [m].
        radius : float, optional
            Circle radius [m].
        speed : float, optional
            Tangential speed [m/s].
        sweep : float, optional
            Sweep value.
        amplitude : float, optional
            Force amplitude [N].

        Returns
        -------
        bool
            False when a given coordinate differs or this condition does not have it.
        """
        for mine, want in ((self.step, step), (self.radius, radius), (self.speed, speed), (self.sweep, sweep),
                           (self.amplitude, amplitude)):
            if want is not None and (mine is None or not math.isclose(mine, want, rel_tol=1e-9, abs_tol=0.0)):
                return False
        return True

    def at(self) -> dict:
        """The coordinates this condition has, as :meth:`matches` takes them.

        Returns
        -------
        dict
            ``step``, ``radius``, ``speed``, ``sweep``, ``amplitude`` -> value, the ones not None.
        """
        return {k: getattr(self, k) for k in ("step", "radius", "speed", "sweep", "amplitude")
                if getattr(self, k) is not None}



# =========================================================================== tests (one schema per campaign kind)
# A trial kind's condition is an experiment profile (:mod:`experiment_runner.core.experiment`, the one
# description of a run): ``profile(cond)``; its reference is that profile's.
class PointToPointTest(Move):
    """Point-to-point moves (seed Sec. 3.4.1, Fig. 3.13): one condition per step size, each an
    experiment's :class:`~experiment_runner.core.experiment.PointToPoint` of this :class:`~experiment_runner.core.experiment.Move`."""
    kind: Literal["point_to_point"] = Field(description="the test kind: point_to_point")
    steps: list[Finite] = Field(min_length=1, description="step sizes [m] (signed), one condition each")
    dwell: Pos = Field(1.0, description="settling portion recorded after the reference stops [s] (the seed's "
                                        "tables: 1 s)")
    window: Pos = Field(25e-9, description="settling window half-width [m]")

    METRICS: ClassVar[tuple] = ("settling_time_s", "rms_in_position_m")
    REPRESENTATIVE: ClassVar[str] = "settling_time_s"      # the representative trial has the median of it

    @model_validator(mode="after")
    def _nonzero(self):
        if any(s == 0 for s in self.steps):
            raise ValueError("steps must be nonzero")
        if len(set(self.steps)) != len(self.steps):
            raise ValueError("steps must be distinct")
        return self

    def conditions(self) -> list[Condition]:
        """One condition per step size.

        Returns
        -------
        list of Condition
            In the order of ``steps``; each with ``step`` [m] and a label such as ``'5 µm'``.
        """
        return [Condition(_slug(fmt_length(s)), fmt_length(s), step=float(s)) for s in self.steps]

    def profile(self, cond: Condition) -> experiment.PointToPoint:
        """The experiment profile of a condition: its step, moved as this test moves.

        Parameters
        ----------
        cond : Condition
            One of :meth:`conditions`.

        Returns
        -------
        experiment_runner.core.experiment.PointToPoint
            The step ``cond.step`` with this test's move (dwell, profile, limits).
        """
        return experiment.PointToPoint(kind="point_to_point", distance=cond.step,
                                       **self.model_dump(include=set(Move.model_fields)))

    def reference(self, cond: Condition, rate: float) -> profiles.Reference:
        """The shared (start-at-0) reference of a condition at the control rate.

        Every trial of the condition follows it, offset by its start position.

        Parameters
        ----------
        cond : Condition
            One of :meth:`conditions`.
        rate : float
            The control rate [Hz]: the reference is sampled every ``1 / rate`` s.

        Returns
        -------
        experiment_runner.core.profiles.Reference
            :func:`experiment_runner.core.experiment.reference` of :meth:`profile`.
        """
        return experiment.reference(self.profile(cond), 1.0 / rate)


class CircleSpeeds(StrictModel):
    """One radius and the tangential speeds run at it."""
    radius: Pos = Field(description="circle radius [m]")
    speeds: list[Pos] = Field(min_length=1, description="tangential speeds [m/s]")


class CircleTest(StrictModel):
    """x-axis reference of circles (seed Sec. 3.4.2 / 4.4.2): one condition per radius and speed.

    Either ``radii`` x ``speeds`` (every speed at every radius) or ``circles`` (each radius
    with its own speeds, e.g. mm/s at 5 mm and µm/s at 5 µm).
    """
    kind: Literal["circle"] = Field(description="the test kind: circle")
    radii: Optional[list[Pos]] = Field(None, min_length=1, description="circle radii [m] (x speeds)")
    speeds: Optional[list[Pos]] = Field(None, min_length=1, description="tangential speeds [m/s] (x radii)")
    circles: Optional[list[CircleSpeeds]] = Field(None, min_length=1, description="radii with their own speeds")
    cycles: Pos = Field(1.0, description="revolutions")
    window: Pos = Field(25e-9, description="(recorded only) [m]")

    @model_validator(mode="after")
    def _one_form(self):
        if self.circles is None and (self.radii is None or self.speeds is None):
            raise ValueError("give radii and speeds, or circles")
        if self.circles is not None and (self.radii is not None or self.speeds is not None):
            raise ValueError("give either radii and speeds, or circles (not both)")
        pairs = self.pairs()
        if len(set(pairs)) != len(pairs):
            raise ValueError("radius/speed pairs must be distinct")
        return self

    def pairs(self) -> list[tuple[float, float]]:
        """Every (radius, speed) condition, in order.

        Returns
        -------
        list of tuple of float
            ``(radius [m], speed [m/s])``: each radius with each of its speeds (``circles``), or
            every speed at every radius (``radii`` x ``speeds``), radius-major.
        """
        if self.circles is not None:
            return [(float(c.radius), float(v)) for c in self.circles for v in c.speeds]
        return [(float(r), float(v)) for r in self.radii for v in self.speeds]

    METRICS: ClassVar[tuple] = ("peak_tracking_error_m", "rms_tracking_error_m")
    REPRESENTATIVE: ClassVar[str] = "rms_tracking_error_m"

    def conditions(self) -> list[Condition]:
        """One condition per radius and speed.

        Returns
        -------
        list of Condition
            In the order of :meth:`pairs`; each with ``radius`` [m] and ``speed`` [m/s].
        """
        return [Condition(_slug(f"r{fmt_length(r)}_v{fmt_length(v)}s"), f"R {fmt_length(r)}, {fmt_length(v)}/s",
                          radius=r, speed=v) for r, v in self.pairs()]

    def profile(self, cond: Condition) -> experiment.Circle:
        """The experiment profile of a condition: its radius and speed.

        Parameters
        ----------
        cond : Condition
            One of :meth:`conditions`.

        Returns
        -------
        experiment_runner.core.experiment.Circle
            The circle of radius ``cond.radius`` at ``cond.speed``, this test's cycles.
        """
        return experiment.Circle(kind="circle", radius=cond.radius, speed=cond.speed, cycles=self.cycles)

    def reference(self, cond: Condition, rate: float) -> profiles.Reference:
        """The shared (start-at-0) reference of a condition at the control rate.

        Every trial of the condition follows it, offset by its start position.

        Parameters
        ----------
        cond : Condition
            One of :meth:`conditions`.
        rate : float
            The control rate [Hz]: the reference is sampled every ``1 / rate`` s.

        Returns
        -------
        experiment_runner.core.profiles.Reference
            :func:`experiment_runner.core.experiment.reference` of :meth:`profile`.
        """
        return experiment.reference(self.profile(cond), 1.0 / rate)


class FrequencyResponseTest(StrictModel):
    """Stepped-sine FRFs at several force amplitudes (seed Sec. 4.3): one condition per amplitude.

    Every amplitude x frequency is an independent column starting at rest: a sine force of
    the amplitude, ramped in over ``max(ramp_cycles / f, min_ramp_time)``, then
    ``max(settle_cycles / f, min_settle_time)`` for the transients, then the measurement
    window: the base window of ``max(cycles, ceil(min_measure_time f))`` whole periods (the
    frequency is adjusted by less than half a sample per window so that it holds whole
    samples), repeated until it lasts ``measure_force_time / amplitude^2``.
    """
    kind: Literal["frequency_response"] = Field(description="the test kind: frequency_response")
    amplitudes: list[Pos] = Field(min_length=1,
                                  description="force amplitudes at the plant input [N], one condition each")
    f_min: Pos = Field(description="lowest frequency [Hz]")
    f_max: Pos = Field(description="highest frequency [Hz] (below the Nyquist frequency)")
    points_per_decade: int = Field(30, ge=2, le=200, description="log-spaced frequencies per decade")
    cycles: int = Field(8, ge=1, le=1000, description="measured periods per frequency (at least)")
    min_measure_time: NonNeg = Field(0.1, description="measurement window at least [s]")
    measure_force_time: Optional[NonNeg] = Field(
        None, description="window at least this / amplitude^2 [N^2 s] (whole multiples of the base window): the "
                          "drive noise is the same force at every amplitude, so a given FRF scatter needs a window "
                          "growing as 1/amplitude^2")
    ramp_cycles: NonNeg = Field(3.0, description="raised-cosine ramp-in [periods]")
    min_ramp_time: NonNeg = Field(0.1, description="ramp-in at least [s]")
    settle_cycles: NonNeg = Field(3.0, description="wait after the ramp [periods]")
    min_settle_time: NonNeg = Field(1.0, description="wait after the ramp at least [s] (light damping rings long)")
    sensor: Literal["encoder", "true"] = Field(
        "encoder", description="position measured: the encoder reading (quantised) or the true table position")
    simulate_closed_loop: bool = Field(
        False, description="also simulate each case's closed loop at the force amplitudes on the batch engine "
                           "(a check of the LTI assumption; see campaigns.frf.closed_loop_frf)")
    max_displacement: Pos = Field(
        2e-3, description="skip frequencies at which an amplitude above the stage's total Coulomb force would "
                          "slide the rigid stage by more than this [m] (A / (m w^2)); the travel limits the seed too")

    METRICS: ClassVar[tuple] = ("bandwidth_hz", "gain_margin_db", "phase_margin_deg", "nominal_pole_per_s",
                                "nominal_gain")

    @model_validator(mode="after")
    def _check(self):
        if not self.f_min < self.f_max:
            raise ValueError(f"f_min={self.f_min} must be below f_max={self.f_max}")
        if len(set(self.amplitudes)) != len(self.amplitudes):
            raise ValueError("amplitudes must be distinct")
        return self

    def conditions(self) -> list[Condition]:
        """One condition per force amplitude.

        Returns
        -------
        list of Condition
            In the order of ``amplitudes``; each with ``amplitude`` [N].
        """
        return [Condition(f"{a:g}N".replace(".", "p").replace("+", ""), f"{a:g} N", amplitude=float(a))
                for a in self.amplitudes]


def frequency_grid(test: FrequencyResponseTest) -> np.ndarray:
    """Nominal log-spaced frequencies [Hz] from ``f_min`` to ``f_max`` (both included).

    ``round(log10(f_max / f_min) * points_per_decade) + 1`` frequencies, at least 2. Nominal: a
    run adjusts each so that its measurement window holds whole samples.

    Parameters
    ----------
    test : FrequencyResponseTest
        The test (its ``f_min``, ``f_max`` [Hz] and ``points_per_decade``).

    Returns
    -------
    numpy.ndarray
        The frequencies [Hz], ascending.

    Examples
    --------
    >>> t = FrequencyResponseTest(kind="frequency_response", amplitudes=[1.0], f_min=1.0, f_max=100.0,
    ...                           points_per_decade=2)
    >>> frequency_grid(t).round(3).tolist()
    [1.0, 3.162, 10.0, 31.623, 100.0]
    """
    n = max(2, int(round(math.log10(test.f_max / test.f_min) * test.points_per_decade)) + 1)
    return np.logspace(math.log10(test.f_min), math.log10(test.f_max), n)




Test = Annotated[Union[PointToPointTest, CircleTest, FrequencyResponseTest], Field(discriminator="kind")]


class StepII(StrictModel):
    """SAI Step II (Sec. 5.3): learn the reference correction with the ILC of Eq. 5.2 at rest.

    The stage holds position; the SAI goes compliant for ``compliant_time`` (the p2p rule
    is triggered by a negligible reference velocity, which nothing else uses) and is
    switched back to stiff; the error after the switch, averaged over ``trials`` start
    positions, updates the correction (:func:`stage_control.sai.ilc_update`) for the
    preset's ``sai_manager.ilc.iterations`` iterations (seed: u_10).
    """
    learn: Literal["at_rest", "on_move"] = Field(
        "at_rest", description="at_rest: the seed's procedure; on_move: NOT the seed's -- the error after the switch "
                               "of each condition's own move (the counterfactual of docs/headline.md)")
    compliant_time: Pos = Field(0.03, description="compliant period before the switch [s]")
    settle_before: Pos = Field(0.02, description="rest before the compliant period [s]")
    trials: int = Field(4, ge=1, le=64, description="start positions averaged per iteration")
    iterations: Optional[int] = Field(None, ge=0, le=100, description="default: preset sai_manager.ilc.iterations")


class Case(StrictModel):
    """One of the compared configurations: a preset, its overrides, optionally SAI Step II learning."""
    name: Name = Field(description="identifier (a letter, then letters, digits, _; at most 40), unique in the "
                                   "campaign; referred to by baseline, seed values, findings, sweeps")
    label: str = Field(description="as in the seed's table, e.g. 'No FI'")
    description: str = Field("", description="what the case is physically (free text)")
    preset: str = Field(description="preset name or path")
    overrides: dict = Field(default_factory=dict, description="dotted-path preset overrides of this case")
    per_speed: dict[str, Finite] = Field(
        default_factory=dict, description="circle tests: dotted path -> factor; the path is set to factor x the "
        "condition's speed [m/s] (e.g. the SAI reversal window as a fraction of the tangential speed)")
    step_ii: Optional[StepII] = Field(None, description="learn the SAI's reference correction (seed Sec. 5.3) "
                                                        "before the trials; None: no learning")
    seed_mechanism: str = Field("", description="the seed's own account of how this case settles (quoted in the "
                                                "report beside the simulated mechanism)")


SweepMode = Literal["value", "scale", "series_scale"]


class SweepTarget(StrictModel):
    """Where the sweep value goes in some of the cases (see :class:`Sweep`)."""
    cases: list[str] = Field(min_length=1, description="cases this target applies to")
    paths: list[str] = Field(min_length=1, description="dotted paths ('*' matches every list item)")
    mode: SweepMode = Field("value", description="value: set the paths to the sweep value; scale: multiply the "
                                                 "preset's values by it; series_scale: scale, then in series with "
                                                 "'series'")
    series: Optional[Pos] = Field(None, description="series_scale: stiffness in series with the scaled one [N/m]")

    @model_validator(mode="after")
    def _series(self):
        if (self.mode == "series_scale") != (self.series is not None):
            raise ValueError("mode series_scale needs 'series' (and 'series' needs mode series_scale)")
        return self


class Sweep(StrictModel):
    """One more axis: a parameter set to each of ``values``.

    ``mode: value`` sets the paths to the value, ``scale`` multiplies the preset's value by
    it, ``series_scale`` scales a stiffness ``k`` and puts it in series with ``series``:
    ``1 / (1/series + 1/(value k))`` (e.g. a feedforward model's frictional stiffness with an
    error, re-combined with the FI stiffness as in Sec. 4.4.3). Either ``paths`` (with
    ``mode``, ``series`` and optionally ``cases``) for one target, or ``apply``: a list of
    targets, each for its own cases (cases in no target run unchanged at every value).
    """
    name: Name = Field(description="identifier of the swept parameter (in condition keys)")
    label: str = Field(description="the swept parameter as the reports name it")
    paths: Optional[list[str]] = Field(None, min_length=1, description="dotted paths ('*' matches every list item)")
    mode: SweepMode = Field("value", description="value, scale or series_scale (see the class)")
    series: Optional[Pos] = Field(None, description="series_scale: stiffness in series [N/m]")
    values: list[Finite] = Field(min_length=1, description="the swept values, distinct (a value or a factor, "
                                                           "per mode); one condition each per test condition")
    unit: str = Field("", description="unit of the values, for labels (empty: none)")
    cases: Optional[list[str]] = Field(None, description="cases it applies to (default all)")
    apply: Optional[list[SweepTarget]] = Field(None, min_length=1, description="per-case targets (instead of paths)")

    @model_validator(mode="after")
    def _form(self):
        if (self.paths is None) == (self.apply is None):
            raise ValueError("give either paths (one target) or apply (per-case targets)")
        if self.apply is not None and (self.cases is not None or self.series is not None or self.mode != "value"):
            raise ValueError("with apply, give cases/mode/series inside each target")
        if self.paths is not None and (self.mode == "series_scale") != (self.series is not None):
            raise ValueError("mode series_scale needs 'series' (and 'series' needs mode series_scale)")
        if len(set(self.values)) != len(self.values):
            raise ValueError("values must be distinct")
        return self

    def target(self, case: str) -> Optional[SweepTarget]:
        """The target applying to ``case`` (None: the case does not depend on the sweep).

        Parameters
        ----------
        case : str
            A case name.

        Returns
        -------
        SweepTarget or None
            The ``apply`` entry listing ``case``, or the one-target form (``paths``, ``mode``,
            ``series``) when ``cases`` is unset or lists it; None: the case runs unchanged at
            every value.
        """
        if self.apply is not None:
            return next((t for t in self.apply if case in t.cases), None)
        if self.cases and case not in self.cases:
            return None
        return SweepTarget(cases=[case], paths=self.paths, mode=self.mode, series=self.series)


class _At(StrictModel):
    """Condition selector: the step (point-to-point) or radius and speed (circle), and sweep value."""
    step: Optional[Finite] = Field(None, description="point_to_point: step size [m]")
    radius: Optional[Pos] = Field(None, description="circle: radius [m]")
    speed: Optional[Pos] = Field(None, description="circle: tangential speed [m/s]")
    sweep: Optional[Finite] = Field(None, description="the sweep value (required when the campaign sweeps)")
    amplitude: Optional[Pos] = Field(None, description="frequency_response: force amplitude [N]")

    def at(self) -> dict:
        """The coordinates given, as :meth:`Condition.matches` takes them.

        Returns
        -------
        dict
            ``step``, ``radius``, ``speed``, ``sweep``, ``amplitude`` -> value, the ones not None.
        """
        return {k: getattr(self, k) for k in ("step", "radius", "speed", "sweep", "amplitude")
                if getattr(self, k) is not None}


class SeedValue(_At):
    """A number the seed reports: ``metric`` of ``case`` at the one condition selected."""
    case: str = Field(description="case name")
    metric: Metric = Field(description="metric name (campaigns.registry.METRICS), measured by the test kind")
    value: Finite = Field(description="the seed's number in the metric's SI unit (s, m; Hz, dB, deg, 1/s, "
                                      "N/(A kg) for the frequency-response metrics)")
    source: str = Field("", description="where in the seed (table, figure, section)")
    bound: Literal["value", "upper", "lower"] = Field(
        "value", description="frequency_response: the seed states a limit ('less than 10 Hz': upper)")


class Finding(_At):
    """A direction the seed reports: ``metric`` of ``case`` is lower / higher / similar vs ``versus``."""
    id: Name = Field(description="identifier, unique in the campaign")
    claim: str = Field(description="the seed's statement")
    case: str = Field(description="the case the statement is about")
    versus: str = Field(description="the case it is compared with")
    versus_amplitude: Optional[Pos] = Field(
        None, description="frequency_response: versus at this amplitude [N] (default: the same; case may equal versus)")
    metric: Metric = Field(description="metric name (campaigns.registry.METRICS), measured by the test kind")
    direction: Literal["lower", "higher", "similar"] = Field(description="the metric of case vs versus")
    tolerance: Fraction = Field(0.2, description="'similar': largest relative difference")
    change: Optional[Finite] = Field(None, description="the seed's relative change (case - versus) / versus, "
                                     "when it gives a percentage only (e.g. Table 6.3); else from seed.values")
    relative_to: Optional[str] = Field(
        None, description="'similar' only: compare the reductions vs this case, 1 - metric/metric(relative_to), "
        "as the seed's reduction plots do (Fig. 6.5, 6.6); tolerance is then in reduction points (0.1 = 10%)")
    over: Literal["mean", "sweep_spread"] = Field(
        "mean", description="mean: the metric's means at one condition; sweep_spread: the spread (standard "
        "deviation) of the means over the sweep values at the condition (robustness, Fig. 4.18)")
    note: str = Field("", description="why the model is expected to differ; shown when it disagrees")

    @model_validator(mode="after")
    def _change_direction(self):
        if self.change is not None:
            if self.direction == "lower" and self.change >= 0 or self.direction == "higher" and self.change <= 0:
                raise ValueError(f"change {self.change:+g} contradicts direction {self.direction!r}")
            if self.direction == "similar" and abs(self.change) > self.tolerance:
                raise ValueError(f"change {self.change:+g} is outside the 'similar' tolerance {self.tolerance}")
        if self.over == "sweep_spread" and self.sweep is not None:
            raise ValueError("over: sweep_spread compares every sweep value; do not give 'sweep'")
        if self.relative_to is not None and self.direction != "similar":
            raise ValueError("relative_to is for direction 'similar' (a lower/higher reduction is a lower/higher metric)")
        return self


class SeedData(StrictModel):
    """What the seed reports for the campaign: its numbers and its findings."""
    source: str = Field(description="where in the seed (shown at the top of the report)")
    notes: str = Field("", description="remarks on the seed's data (shown in the report)")
    values: list[SeedValue] = Field(default_factory=list, description="the seed's numbers")
    findings: list[Finding] = Field(default_factory=list, description="the directions the seed reports")


class CalTarget(_At):
    """The one baseline number a calibrated parameter is fitted to: ``metric`` at the condition selected."""
    metric: Metric = Field(description="metric name; its seed value for the baseline case is the target")
    form: Literal["absolute", "quadrature_excess"] = Field(
        "absolute", description="absolute: match the metric; quadrature_excess: match its part above a "
                                "deterministic floor, sqrt(metric^2 - floor^2)")
    seed_floor: NonNeg = Field(0.0, description="quadrature_excess: deterministic floor of the seed value [SI]")


class CalParameter(StrictModel):
    """One physically meaningful parameter the seed leaves open, fitted on the baseline to one seed number."""
    name: Name = Field(description="identifier (calibration.json values)")
    description: str = Field(description="what it is physically and why it is not known from the seed")
    paths: list[str] = Field(min_length=1, description="dotted paths ('*' matches every list item)")
    mode: Literal["value", "scale"] = Field("value", description="value: the parameter is the paths' value; "
                                                                 "scale: a factor on the preset's values")
    bounds: tuple[Finite, Finite] = Field(description="(lower, upper), lower below upper: the fit stays inside "
                                                      "and reports a parameter at a bound")
    log: bool = Field(False, description="fit in the logarithm of the parameter (positive bounds)")
    neutral: Optional[Finite] = Field(None, description="value that removes the effect (quadrature_excess)")
    unit: str = Field("", description="unit of the parameter, for the report")
    target: CalTarget = Field(description="the baseline number it is fitted to")

    @model_validator(mode="after")
    def _bounds(self):
        lo, hi = self.bounds
        if not lo < hi:
            raise ValueError(f"bounds {self.bounds}: lower must be below upper")
        if self.log and lo <= 0:
            raise ValueError("log: true needs positive bounds")
        if self.target.form == "quadrature_excess" and self.neutral is None:
            raise ValueError("target.form quadrature_excess needs 'neutral' (the value without the effect)")
        return self


class Calibration(StrictModel):
    """Fit ``parameters`` on this campaign's baseline (:mod:`experiment_runner.apps.campaigns.calibration`)."""
    trials: int = Field(16, ge=1, le=1000, description="baseline trials per evaluation (the first of the campaign's)")
    rounds: int = Field(3, ge=1, le=10, description="Gauss-Seidel rounds at most")
    rtol: Annotated[float, Field(gt=0, lt=1)] = Field(
        0.01, description="converged when no parameter moved by more than this, relative, in a round")
    parameters: list[CalParameter] = Field(min_length=1, max_length=3, description="the parameters fitted (1 to 3)")


class CalibrationFrom(StrictModel):
    """Reuse the baseline calibration of another campaign on the same stage and PID.

    ``from: table_4_2`` applies that campaign's calibrated parameters (its paths and modes)
    to every case here instead of refitting. :func:`run_campaign` loads the values from
    ``calibration.json`` in the output folder or in ``<output folder>/../<from>/`` when it
    was fitted with the same campaign, baseline preset and trial count (a fingerprint),
    else fits that campaign's baseline and caches the result as ``calibration.json``.
    """
    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)
    from_: Name = Field(alias="from", description="campaign whose baseline calibration is reused")
    trials: Optional[int] = Field(None, ge=1, le=1000, description="its fit's trials (default: its calibration.trials)")


def _calibration_kind(v) -> str:
    if isinstance(v, dict):
        return "from" if ("from" in v or "from_" in v) else "fit"
    return "from" if isinstance(v, CalibrationFrom) else "fit"


CalibrationSpec = Annotated[Union[Annotated[Calibration, Tag("fit")], Annotated[CalibrationFrom, Tag("from")]],
                            Discriminator(_calibration_kind)]


class Campaign(StrictModel):
    """One of the seed's experimental comparisons: cases x conditions (x sweep values), trials, seed data.

    Validation also checks the whole: case names unique, ``baseline`` a case (without
    ``step_ii``), every seed value and finding naming cases and selecting exactly one condition
    of a metric the test measures, sweep and calibration targets consistent.
    """
    name: Name = Field(description="identifier (a letter, then letters, digits, _; at most 40)")
    title: str = Field(description="one line, shown on top of the report and the plots")
    description: str = Field("", description="what is run and why (free text)")
    test: Test = Field(description="the test: point_to_point, circle or frequency_response (by 'kind')")
    trials: int = Field(ge=1, le=10_000, description="trials per case and condition")
    starts: Starts = Field(Starts(), description="where trials start (trial i: starts.trial(i), on its own)")
    overrides: dict = Field(default_factory=dict, description="dotted-path overrides for every case")
    cases: list[Case] = Field(min_length=1, description="the compared cases")
    baseline: str = Field(description="the case the calibration is fitted on (the conventional stage)")
    sweep: Optional[Sweep] = Field(None, description="one more axis of conditions: a parameter's values")
    calibration: Optional[CalibrationSpec] = Field(
        None, description="parameters fitted on the baseline, or {from: NAME}: another campaign's fit; None: "
                          "every case runs on its preset as is")
    seed: SeedData = Field(description="the seed's numbers and findings compared with the simulation")

    @model_validator(mode="after")
    def _consistent(self):
        names = [c.name for c in self.cases]
        if len(set(names)) != len(names):
            raise ValueError(f"case names must be unique: {names}")
        if self.baseline not in names:
            raise ValueError(f"baseline {self.baseline!r} is not a case ({names})")
        if self.case(self.baseline).step_ii is not None:
            raise ValueError("the baseline case cannot use step_ii (it is the conventional stage)")
        for i, c in enumerate(self.cases):
            if c.per_speed and not isinstance(self.test, CircleTest):
                raise ValueError(f"cases.{i} ({c.name}).per_speed: only for circle tests (a speed per condition)")
        conds = conditions(self)
        metrics = self.test.METRICS

        def check_at(where, sel: _At, metric=None, spread=False):
            if metric is not None and metric not in metrics:
                raise ValueError(f"{where}: metric {metric} is not measured by a {self.test.kind} test "
                                 f"({', '.join(metrics)})")
            if spread and self.sweep is None:
                raise ValueError(f"{where}: over: sweep_spread needs a campaign sweep")
            if self.sweep is not None and sel.sweep is None and not spread:
                raise ValueError(f"{where}: give 'sweep' (the campaign sweeps {self.sweep.name})")
            if not [c for c in conds if c.matches(**sel.at())]:
                raise ValueError(f"{where}: no condition matches {sel.at()} "
                                 f"(conditions: {', '.join(c.label for c in conds)})")
            n = len([c for c in conds if c.matches(**sel.at())])
            if n > (len(self.sweep.values) if spread else 1):
                raise ValueError(f"{where}: {sel.at()} matches {n} conditions; give all of step/radius/speed"
                                 + ("" if spread else "/sweep"))

        for i, v in enumerate(self.seed.values):
            if v.case not in names:
                raise ValueError(f"seed.values.{i}: case {v.case!r} is not a case ({names})")
            check_at(f"seed.values.{i}", v, v.metric)
        ids = [f.id for f in self.seed.findings]
        if len(set(ids)) != len(ids):
            raise ValueError("seed.findings: ids must be unique")
        for i, f in enumerate(self.seed.findings):
            for who in (f.case, f.versus) + ((f.relative_to,) if f.relative_to else ()):
                if who not in names:
                    raise ValueError(f"seed.findings.{i} ({f.id}): case {who!r} is not a case ({names})")
            if f.case == f.versus and f.versus_amplitude is None:
                raise ValueError(f"seed.findings.{i} ({f.id}): case and versus are the same")
            if f.versus_amplitude is not None and not [c for c in conds if c.matches(amplitude=f.versus_amplitude)]:
                raise ValueError(f"seed.findings.{i} ({f.id}): versus_amplitude {f.versus_amplitude} matches no "
                                 f"condition ({', '.join(c.label for c in conds)})")
            check_at(f"seed.findings.{i} ({f.id})", f, f.metric, spread=f.over == "sweep_spread")
        if self.sweep is not None:
            groups = [("sweep.cases", self.sweep.cases or [])] + [
                (f"sweep.apply.{j}.cases", t.cases) for j, t in enumerate(self.sweep.apply or [])]
            seen = set()
            for where, cs in groups:
                for c in cs:
                    if c not in names:
                        raise ValueError(f"{where}: {c!r} is not a case ({names})")
                    if c in seen:
                        raise ValueError(f"{where}: case {c!r} is in more than one sweep target")
                    seen.add(c)
        if isinstance(self.calibration, Calibration):
            pnames = [p.name for p in self.calibration.parameters]
            if len(set(pnames)) != len(pnames):
                raise ValueError("calibration.parameters: names must be unique")
            for i, p in enumerate(self.calibration.parameters):
                where = f"calibration.parameters.{i} ({p.name}).target"
                check_at(where, p.target, p.target.metric)
                if self.seed_value(self.baseline, p.target.metric, **p.target.at()) is None:
                    raise ValueError(f"{where}: seed.values has no {p.target.metric} of the baseline "
                                     f"{self.baseline!r} at {p.target.at()}")
                for c in self.cases:
                    clash = [q for q in p.paths if q in c.overrides]
                    if clash:
                        raise ValueError(f"{where}: case {c.name!r} overrides {clash}, which is calibrated")
        return self

    # ----------------------------------------------------------------- helpers
    def case(self, name: str) -> Case:
        """The case named ``name``.

        Parameters
        ----------
        name : str
            A case name.

        Returns
        -------
        Case
        """
        return next(c for c in self.cases if c.name == name)

    def seed_value(self, case: str, metric: str, **at) -> Optional[float]:
        """The seed's number of ``metric`` for ``case`` at the one condition ``at`` selects (None: the seed gives none).

        Parameters
        ----------
        case : str
            Case name.
        metric : str
            Metric name.
        **at
            The condition (``step``, ``radius``, ``speed``, ``sweep``, ``amplitude``).

        Returns
        -------
        float or None
        """
        cond = [c for c in conditions(self) if c.matches(**at)]
        for v in self.seed.values:
            if v.case == case and v.metric == metric and cond and cond[0].matches(**v.at()) \
                    and len([c for c in conditions(self) if c.matches(**v.at())]) == 1:
                return v.value
        return None



def conditions(c: Campaign) -> list[Condition]:
    """Every condition of the campaign: test conditions x sweep values.

    Parameters
    ----------
    c : Campaign
        The campaign.

    Returns
    -------
    list of Condition
    """
    base = c.test.conditions()
    if c.sweep is None:
        return base
    out = []
    for b in base:
        for v in c.sweep.values:
            out.append(replace(b, key=f"{b.key}__{_slug(c.sweep.name)}_{v:g}".replace("-", "m").replace(".", "p"),
                               label=f"{b.label}, {c.sweep.label} = {v:g}{(' ' + c.sweep.unit) if c.sweep.unit else ''}",
                               sweep=float(v)))
    return out


# =========================================================================== loading
def list_campaigns() -> list[str]:
    """Names of the campaigns shipped with the package.

    Returns
    -------
    list of str
    """
    return sorted(p.stem for p in CAMPAIGN_DIR.glob("*.yaml"))


def load_campaign(name_or_path, check_presets: bool = True) -> Campaign:
    """Load and validate a campaign by name (shipped) or path; no code is executed.

    With ``check_presets`` every case's preset is loaded with the campaign's and the
    case's overrides, and every calibrated or swept path is resolved, so a campaign
    that loads also runs.

    Parameters
    ----------
    name_or_path : str or pathlib.Path
        A shipped campaign's name or a YAML file.
    check_presets : bool, optional
        Also resolve every preset and path (:func:`check_campaign`).

    Returns
    -------
    Campaign
    """
    data, path = read_yaml_file(name_or_path, CAMPAIGN_DIR, "campaign")
    try:
        camp = Campaign.model_validate(data)
    except ValidationError as err:
        raise ConfigError(schema_error_message(err, str(path), "campaign")) from None
    if check_presets:
        check_campaign(camp, str(path))
    return camp


def check_campaign(camp: Campaign, source: str = "<campaign>") -> None:
    """Resolve every case's preset, overrides, calibrated and swept paths; ConfigError naming the field.

    Parameters
    ----------
    camp : Campaign
        The campaign.
    source : str, optional
        Where it came from, for messages.
    """
    for i, case in enumerate(camp.cases):
        where = f"{source}: cases.{i} ({case.name})"
        try:
            preset = case_preset(camp, case)
            if case.per_speed:
                case_preset(camp, case, None, conditions(camp)[0])
        except (ConfigError, KeyError, IndexError, ValueError, TypeError) as err:
            raise ConfigError(f"{where}: preset {case.preset!r} with overrides: {err}") from None
        src = calibration_source(camp, source)
        where_cal = f"calibration (from {src.name})" if src is not None else "calibration"
        for j, p in enumerate(cal_parameters(camp)):
            try:
                resolve(preset, p.paths, p.mode, p.bounds[0])
            except (ConfigError, KeyError, IndexError, ValueError, TypeError) as err:
                raise ConfigError(f"{source}: {where_cal}.parameters.{j} ({p.name}).paths in case "
                                  f"{case.name!r}: {err}") from None
            clash = [q for q in p.paths if q in case.overrides]
            if src is not None and clash:
                raise ConfigError(f"{source}: {where_cal}: case {case.name!r} overrides {clash}, which is "
                                  f"calibrated in {src.name}")
        target = camp.sweep.target(case.name) if camp.sweep is not None else None
        if target is not None:
            for v in camp.sweep.values:
                try:
                    resolve(preset, target.paths, target.mode, v, target.series)
                except (ConfigError, KeyError, IndexError, ValueError, TypeError) as err:
                    raise ConfigError(f"{source}: sweep paths in case {case.name!r} (value {v}): {err}") from None
        if case.step_ii is not None and (preset.sai_manager is None or preset.sai_manager.ilc is None
                                         or preset.sai_manager.rule != "point_to_point"):
            raise ConfigError(f"{where}: step_ii needs a preset with sai_manager.rule point_to_point and an ilc")


# =========================================================================== overrides
def expand_path(data, path: str) -> list[tuple[str, object]]:
    """Dotted path with '*' wildcards -> [(concrete path, value)] in ``data`` (a model_dump).

    Parameters
    ----------
    data : dict
        A nested mapping (a preset's ``model_dump()``).
    path : str
        Dotted path; a part is a mapping key, a list index (negative counts from the end) or
        ``*`` (every item of a list or mapping).

    Returns
    -------
    list of tuple
        ``(concrete dotted path, value)`` of every match, in order; list indices non-negative.

    Raises
    ------
    stage_sim.config.ConfigError
        A part that is not there (the message names the fields or item count there).

    Examples
    --------
    >>> expand_path({"a": [{"b": 1}, {"b": 2}]}, "a.*.b")
    [('a.0.b', 1), ('a.1.b', 2)]
    >>> expand_path({"a": [{"b": 1}, {"b": 2}]}, "a.-1.b")
    [('a.1.b', 2)]
    """
    nodes = [(data, [])]
    for part in path.split("."):
        nxt = []
        for node, pre in nodes:
            if part == "*":
                if isinstance(node, list):
                    nxt += [(v, pre + [str(i)]) for i, v in enumerate(node)]
                elif isinstance(node, dict):
                    nxt += [(v, pre + [k]) for k, v in node.items()]
                else:
                    raise ConfigError(f"{path}: '*' at {'.'.join(pre) or 'top'} which is not a list or mapping")
            elif isinstance(node, list):
                if not part.lstrip("-").isdigit() or not -len(node) <= int(part) < len(node):
                    raise ConfigError(f"{path}: {'.'.join(pre)} has {len(node)} items, no {part!r}")
                nxt.append((node[int(part)], pre + [str(int(part) % len(node))]))
            elif isinstance(node, dict):
                if part not in node:
                    raise ConfigError(f"{path}: {'.'.join(pre) or 'preset'} has no field {part!r} "
                                      f"(fields: {', '.join(node)})")
                nxt.append((node[part], pre + [part]))
            else:
                raise ConfigError(f"{path}: {'.'.join(pre)} is {node!r}, not a mapping")
        nodes = nxt
    if not nodes:
        raise ConfigError(f"{path}: matches nothing")
    return [(".".join(pre), v) for v, pre in nodes]


def _scaled(v, factor, path, series=None):
    if isinstance(v, list):
        return [_scaled(x, factor, path, series) for x in v]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        k = float(v) * float(factor)
        if series is None:
            return k
        if k <= 0:
            raise ConfigError(f"{path}: series_scale needs a positive stiffness, got {k!r}")
        return 1.0 / (1.0 / float(series) + 1.0 / k)
    raise ConfigError(f"{path}: cannot scale {v!r}")


def resolve(preset: Preset, paths, mode: str, value, series: Optional[float] = None) -> dict:
    """Absolute dotted-path overrides setting (``mode: value``), scaling (``scale``) or
    scaling and combining in series with ``series`` (``series_scale``) ``paths``.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The case's preset.
    paths : list of str
        Dotted paths (with ``*`` over list items).
    mode : {'value', 'scale', 'series_scale'}
        How ``value`` applies.
    value : float
        The value or factor.
    series : float, optional
        The element combined in series (``series_scale``).

    Returns
    -------
    dict
        Absolute dotted-path overrides.

    Examples
    --------
    >>> p = load_preset("fi_stage_gms")
    >>> o = resolve(p, ["stage.bearings.*.friction.f_c"], "scale", 2.0)
    >>> o
    {'stage.bearings.0.friction.f_c': 5.31, 'stage.bearings.1.friction.f_c': 5.31}
    >>> k = resolve(p, ["stage.bearings.0.friction.k"], "series_scale", 1.0, series=8.27e4)
    >>> round(k["stage.bearings.0.friction.k"][0])      # 1 / (1/8.27e4 + 1/6.7e5)
    73614
    """
    if mode == "series_scale" and series is None:
        raise ConfigError(f"{paths}: mode series_scale needs a series stiffness")
    data = preset.model_dump()
    out = {}
    for path in paths:
        for concrete, old in expand_path(data, path):
            out[concrete] = (_scaled(old, value, concrete, series if mode == "series_scale" else None)
                             if mode in ("scale", "series_scale") else to_python(value))
    return out


def to_python(v):
    """``v`` with numpy scalars as Python numbers, also inside lists, tuples and dicts (for YAML/JSON).

    Parameters
    ----------
    v : object
        A value, list, tuple or dict.

    Returns
    -------
    object
        The same with every ``numpy.generic`` replaced by its ``item()``; tuples become lists.

    Examples
    --------
    >>> to_python({"k": (np.float64(1.5), np.int64(2))})
    {'k': [1.5, 2]}
    """
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [to_python(x) for x in v]
    if isinstance(v, dict):
        return {k: to_python(x) for k, x in v.items()}
    return v


def case_overrides(camp: Campaign, case: Case, cal_values: Optional[dict] = None,
                   cond: Optional[Condition] = None) -> dict:
    """Every override of a case as absolute dotted paths, in application order: campaign,
    case, calibrated parameters, sweep value. ``with_overrides(load_preset(case.preset), o)``
    gives the case's preset (this is also what the graph experiment file holds).

    Parameters
    ----------
    camp : Campaign
        The campaign.
    case : Case
        One of its cases.
    cal_values : dict, optional
        Calibrated values (``calibration.json`` ``values``).
    cond : Condition, optional
        A condition (its speed and sweep value).

    Returns
    -------
    dict
    """
    flat = {**copy.deepcopy(camp.overrides), **copy.deepcopy(case.overrides)}
    if cond is not None and cond.speed is not None:
        flat.update({k: float(f) * cond.speed for k, f in case.per_speed.items()})
    preset = (with_overrides(load_preset(case.preset), flat, f"campaign {camp.name}: case {case.name} overrides")
              if flat else load_preset(case.preset))
    if cal_values and camp.calibration is not None:
        for p in cal_parameters(camp):
            if p.name in cal_values:
                o = resolve(preset, p.paths, p.mode, cal_values[p.name])
                flat.update(o)
        preset = with_overrides(load_preset(case.preset), flat)
    target = camp.sweep.target(case.name) if camp.sweep is not None else None
    if cond is not None and cond.sweep is not None and target is not None:
        flat.update(resolve(preset, target.paths, target.mode, cond.sweep, target.series))
    return to_python(flat)


def calibration_source(camp: Campaign, source: str = "<campaign>") -> Optional[Campaign]:
    """The campaign whose calibration ``calibration: {from: NAME}`` reuses (None otherwise).

    Parameters
    ----------
    camp : Campaign
        The campaign.
    source : str, optional
        Where it came from, for messages.

    Returns
    -------
    Campaign or None
    """
    if not isinstance(camp.calibration, CalibrationFrom):
        return None
    name = camp.calibration.from_
    if name == camp.name:
        raise ConfigError(f"{source}: calibration.from: {name!r} is this campaign")
    try:
        src = _load_source(name)
    except ConfigError as err:
        raise ConfigError(f"{source}: calibration.from: {name!r}: {err}") from None
    if not isinstance(src.calibration, Calibration):
        raise ConfigError(f"{source}: calibration.from: campaign {name!r} fits no calibration of its own")
    return src


def _load_source(name: str) -> Campaign:
    key = (name, (CAMPAIGN_DIR / f"{name}.yaml").stat().st_mtime_ns if (CAMPAIGN_DIR / f"{name}.yaml").exists() else 0)
    if key not in _SOURCES:
        _SOURCES[key] = load_campaign(name, check_presets=False)
    return _SOURCES[key]


_SOURCES: dict = {}


def cal_parameters(camp: Campaign) -> list:
    """The calibrated parameters applied to the cases (own, or those of ``calibration.from``).

    Parameters
    ----------
    camp : Campaign
        The campaign.

    Returns
    -------
    list of CalParameter
    """
    if camp.calibration is None:
        return []
    src = calibration_source(camp)
    return list((src if src is not None else camp).calibration.parameters)


def case_preset(camp: Campaign, case: Case, cal_values: Optional[dict] = None,
                cond: Optional[Condition] = None) -> Preset:
    """The preset a case runs on: its preset with :func:`case_overrides` applied.

    Parameters
    ----------
    camp : Campaign
        The campaign.
    case : Case
        One of its cases.
    cal_values : dict, optional
        Calibrated values (``calibration.json`` ``values``).
    cond : Condition, optional
        A condition (its speed and sweep value).

    Returns
    -------
    stage_sim.config.Preset
    """
    flat = case_overrides(camp, case, cal_values, cond)
    base = load_preset(case.preset)
    return with_overrides(base, flat) if flat else base

