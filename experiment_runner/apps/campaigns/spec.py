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

This module is the campaign model (pydantic, no code executed), :func:`load_campaign` /
:func:`list_campaigns`, the conditions and the presets of every case (:func:`case_preset`:
campaign, case, calibrated and swept overrides, resolved by
:mod:`~experiment_runner.apps.campaigns.overrides`). Each test kind (``point_to_point``,
``circle``, ``frequency_response``) has its schema -- the class that knows its conditions, its
metrics and its reference -- in the module of its name in
:mod:`experiment_runner.apps.campaigns.schema`; the model assembles them into its ``Test``
union. What a kind *does* (run, report section, plots) is its
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
from dataclasses import replace
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

from pydantic import ConfigDict, Discriminator, Field, Tag, ValidationError, model_validator

from experiment_runner.apps.campaigns.overrides import resolve, to_python
from experiment_runner.apps.campaigns.registry import Metric
from experiment_runner.apps.campaigns.schema.circle import CircleTest
from experiment_runner.apps.campaigns.schema.common import Condition, Name, slug
from experiment_runner.apps.campaigns.schema.frequency_response import FrequencyResponseTest
from experiment_runner.apps.campaigns.schema.point_to_point import PointToPointTest
from experiment_runner.core.experiment import Starts
from stage_sim.config import (ConfigError, Finite, Fraction, NonNeg, Pos, Preset, schema_error_message, StrictModel,
                              load_preset, read_yaml_file, with_overrides)

__all__ = ["Campaign", "Case", "Test", "load_campaign", "list_campaigns", "check_campaign", "conditions",
           "case_overrides", "case_preset", "cal_parameters", "calibration_source", "CAMPAIGN_DIR"]

CAMPAIGN_DIR = Path(__file__).parent
"""The shipped campaign files (``*.yaml`` next to this module, installed as package data)."""


# =========================================================================== the campaign model
Test = Annotated[Union[PointToPointTest, CircleTest, FrequencyResponseTest], Field(discriminator="kind")]
"""The ``test`` of a campaign file: one schema per campaign kind (:mod:`experiment_runner.apps.campaigns.schema`), by ``kind``."""


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
            out.append(replace(b, key=f"{b.key}__{slug(c.sweep.name)}_{v:g}".replace("-", "m").replace(".", "p"),
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


# =========================================================================== the presets of the cases
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

