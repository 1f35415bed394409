"""Campaigns: the seed's comparison tables as YAML files, calibrated, run and reported.

A campaign (``experiment_runner/campaigns/<name>.yaml``, or any path) is one of the
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
  case only (:mod:`experiment_runner.calibration`); every other case is a prediction. Or
  ``calibration: {from: NAME}``: a campaign on the same stage and PID (e.g. the circle tests
  of table_4_2's stage) reuses NAME's baseline fit instead of refitting (loaded from a
  matching ``calibration.json``, else fitted once and cached there, :func:`source_calibration`).

Circle tests give each radius its own speeds (``circles``); a case's ``per_speed`` sets a
path to a factor times the condition's speed (the SAI's reversal window). A sweep may have
per-case targets (``apply``) and ``mode: series_scale`` (a model stiffness with an error, in
series with an FI's, Sec. 4.4.3). A finding may carry the seed's percentage (``change``) when
the seed gives no absolute numbers (Table 6.3), compare the spread over the sweep values
(``over: sweep_spread``, the ±1σ bands of Fig. 4.18) and, for 'similar', the reductions vs a
third case (``relative_to``, as the seed's reduction plots do).

:func:`run_campaign` calibrates, runs every case and condition on the batch engine
(:func:`experiment_runner.batch.simulate`, the same trials and metrics as the ROS graph:
:func:`experiment_runner.experiment.trial_metrics`), optionally runs the representative
trial of every case and condition through the ROS 2 graph, and writes ``results.csv``,
``results.json``, ``calibration.json``, ``report.md`` (:mod:`experiment_runner.report`),
plots and MCAP recordings to the output folder.

Trial ``i`` of a case starts at ``random_starts(1, travel, margin, starts.seed + i)`` with
noise seed ``simulation.seed + i``: every trial is reproducible on its own, and the
same in every case (common random numbers make the case comparisons paired). The
one-trial experiment file written for the graph (:func:`graph_experiment`) therefore
reproduces exactly that trial.

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
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import numpy as np
import yaml
from pydantic import ConfigDict, Discriminator, Field, Tag, ValidationError, model_validator

from experiment_runner import profiles
from experiment_runner.experiment import Trial, trial_metrics
from experiment_runner.metrics import finite_or_none
from experiment_runner.frf_campaign import FRF_METRICS, FrequencyResponseTest
from stage_sim.config import (ConfigError, Finite, Fraction, NonNeg, Pos, Preset, _format, _Strict,
                              load_preset, read_yaml_file, with_overrides)

__all__ = ["Campaign", "load_campaign", "list_campaigns", "conditions", "run_campaign", "main_job",
           "add_campaign_arguments", "main_campaign", "graph_experiment", "CAMPAIGN_DIR", "MAIN_JOB"]

CAMPAIGN_DIR = Path(__file__).with_name("campaigns")
MAIN_JOB = ("table_4_2", "table_5_2")
"""Campaigns of :func:`main_job` (``nanostage campaign --main``)."""

Metric = Literal["settling_time_s", "rms_in_position_m", "peak_tracking_error_m", "rms_tracking_error_m",
                 "bandwidth_hz", "gain_margin_db", "phase_margin_deg"]   # the last three: frequency_response
METRIC_INFO = {  # label, display unit, scale from SI
    "settling_time_s": ("mean settling time", "ms", 1e3),
    "rms_in_position_m": ("RMS in-position error", "nm", 1e9),
    "peak_tracking_error_m": ("peak tracking error", "µm", 1e6),
    "rms_tracking_error_m": ("RMS tracking error", "µm", 1e6),
}
P2P_METRICS = ("settling_time_s", "rms_in_position_m")
TRACK_METRICS = ("peak_tracking_error_m", "rms_tracking_error_m")
Name = Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=40)]


# =========================================================================== schema
class PointToPointTest(_Strict):
    """Point-to-point moves (seed Sec. 3.4.1, Fig. 3.13): one condition per step size."""
    kind: Literal["point_to_point"]
    steps: list[Finite] = Field(min_length=1, description="step sizes [m] (signed), one condition each")
    dwell: Pos = Field(1.0, description="settling portion after the reference stops [s]")
    pre: NonNeg = Field(0.005, description="rest before the move [s]")
    duration: Optional[Pos] = Field(None, description="move duration [s]; default from the seed's anchors")
    shape: Literal["cycloidal", "step"] = "cycloidal"
    window: Pos = Field(25e-9, description="settling window half-width [m]")

    @model_validator(mode="after")
    def _nonzero(self):
        if any(s == 0 for s in self.steps):
            raise ValueError("steps must be nonzero")
        if len(set(self.steps)) != len(self.steps):
            raise ValueError("steps must be distinct")
        return self


class Circle(_Strict):
    """One radius and the tangential speeds run at it."""
    radius: Pos = Field(description="circle radius [m]")
    speeds: list[Pos] = Field(min_length=1, description="tangential speeds [m/s]")


class CircleTest(_Strict):
    """x-axis reference of circles (seed Sec. 3.4.2 / 4.4.2): one condition per radius and speed.

    Either ``radii`` x ``speeds`` (every speed at every radius) or ``circles`` (each radius
    with its own speeds, e.g. mm/s at 5 mm and µm/s at 5 µm).
    """
    kind: Literal["circle"]
    radii: Optional[list[Pos]] = Field(None, min_length=1, description="circle radii [m] (x speeds)")
    speeds: Optional[list[Pos]] = Field(None, min_length=1, description="tangential speeds [m/s] (x radii)")
    circles: Optional[list[Circle]] = Field(None, min_length=1, description="radii with their own speeds")
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
        """Every (radius, speed) condition, in order."""
        if self.circles is not None:
            return [(float(c.radius), float(v)) for c in self.circles for v in c.speeds]
        return [(float(r), float(v)) for r in self.radii for v in self.speeds]


Test = Annotated[Union[PointToPointTest, CircleTest, FrequencyResponseTest], Field(discriminator="kind")]


class Starts(_Strict):
    """Trial ``i`` starts uniformly at random inside the travel minus ``margin`` (rng seed ``seed + i``)."""
    margin: NonNeg = Field(0.003, description="distance kept from the travel ends [m]")
    seed: int = Field(1, ge=0, description="rng seed of trial 0")


class StepII(_Strict):
    """SAI Step II (Sec. 5.3): learn the reference correction with the ILC of Eq. 5.2 at rest.

    The stage holds position; the SAI goes compliant for ``compliant_time`` (the p2p rule
    is triggered by a negligible reference velocity, which nothing else uses) and is
    switched back to stiff; the error after the switch, averaged over ``trials`` start
    positions, updates the correction (:func:`stage_control.sai.ilc_update`) for the
    preset's ``sai_manager.ilc.iterations`` iterations (seed: u_10).
    """
    learn: Literal["at_rest"] = "at_rest"
    compliant_time: Pos = Field(0.03, description="compliant period before the switch [s]")
    settle_before: Pos = Field(0.02, description="rest before the compliant period [s]")
    trials: int = Field(4, ge=1, le=64, description="start positions averaged per iteration")
    iterations: Optional[int] = Field(None, ge=0, le=100, description="default: preset sai_manager.ilc.iterations")


class Case(_Strict):
    name: Name
    label: str = Field(description="as in the seed's table, e.g. 'No FI'")
    description: str = ""
    preset: str = Field(description="preset name or path")
    overrides: dict = Field(default_factory=dict, description="dotted-path preset overrides of this case")
    per_speed: dict[str, Finite] = Field(
        default_factory=dict, description="circle tests: dotted path -> factor; the path is set to factor x the "
        "condition's speed [m/s] (e.g. the SAI reversal window as a fraction of the tangential speed)")
    step_ii: Optional[StepII] = None


SweepMode = Literal["value", "scale", "series_scale"]


class SweepTarget(_Strict):
    """Where the sweep value goes in some of the cases (see :class:`Sweep`)."""
    cases: list[str] = Field(min_length=1, description="cases this target applies to")
    paths: list[str] = Field(min_length=1, description="dotted paths ('*' matches every list item)")
    mode: SweepMode = "value"
    series: Optional[Pos] = Field(None, description="series_scale: stiffness in series with the scaled one [N/m]")

    @model_validator(mode="after")
    def _series(self):
        if (self.mode == "series_scale") != (self.series is not None):
            raise ValueError("mode series_scale needs 'series' (and 'series' needs mode series_scale)")
        return self


class Sweep(_Strict):
    """One more axis: a parameter set to each of ``values``.

    ``mode: value`` sets the paths to the value, ``scale`` multiplies the preset's value by
    it, ``series_scale`` scales a stiffness ``k`` and puts it in series with ``series``:
    ``1 / (1/series + 1/(value k))`` (e.g. a feedforward model's frictional stiffness with an
    error, re-combined with the FI stiffness as in Sec. 4.4.3). Either ``paths`` (with
    ``mode``, ``series`` and optionally ``cases``) for one target, or ``apply``: a list of
    targets, each for its own cases (cases in no target run unchanged at every value).
    """
    name: Name
    label: str
    paths: Optional[list[str]] = Field(None, min_length=1, description="dotted paths ('*' matches every list item)")
    mode: SweepMode = "value"
    series: Optional[Pos] = Field(None, description="series_scale: stiffness in series [N/m]")
    values: list[Finite] = Field(min_length=1)
    unit: str = ""
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
        """The target applying to ``case`` (None: the case does not depend on the sweep)."""
        if self.apply is not None:
            return next((t for t in self.apply if case in t.cases), None)
        if self.cases and case not in self.cases:
            return None
        return SweepTarget(cases=[case], paths=self.paths, mode=self.mode, series=self.series)


class _At(_Strict):
    """Condition selector: the step (point-to-point) or radius and speed (circle), and sweep value."""
    step: Optional[Finite] = None
    radius: Optional[Pos] = None
    speed: Optional[Pos] = None
    sweep: Optional[Finite] = None
    amplitude: Optional[Pos] = Field(None, description="frequency_response: force amplitude [N]")

    def at(self) -> dict:
        return {k: getattr(self, k) for k in ("step", "radius", "speed", "sweep", "amplitude")
                if getattr(self, k) is not None}


class SeedValue(_At):
    case: str
    metric: Metric
    value: Finite = Field(description="the seed's number, SI (s, m)")
    source: str = ""
    bound: Literal["value", "upper", "lower"] = Field(
        "value", description="frequency_response: the seed states a limit ('less than 10 Hz': upper)")


class Finding(_At):
    """A direction the seed reports: ``metric`` of ``case`` is lower / higher / similar vs ``versus``."""
    id: Name
    claim: str = Field(description="the seed's statement")
    case: str
    versus: str
    versus_amplitude: Optional[Pos] = Field(
        None, description="frequency_response: versus at this amplitude [N] (default: the same; case may equal versus)")
    metric: Metric
    direction: Literal["lower", "higher", "similar"]
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


class SeedData(_Strict):
    source: str
    notes: str = ""
    values: list[SeedValue] = Field(default_factory=list)
    findings: list[Finding] = Field(default_factory=list)


class CalTarget(_At):
    metric: Metric
    form: Literal["absolute", "quadrature_excess"] = "absolute"
    seed_floor: NonNeg = Field(0.0, description="quadrature_excess: deterministic floor of the seed value [SI]")


class CalParameter(_Strict):
    name: Name
    description: str = Field(description="what it is physically and why it is not known from the seed")
    paths: list[str] = Field(min_length=1, description="dotted paths ('*' matches every list item)")
    mode: Literal["value", "scale"] = "value"
    bounds: tuple[Finite, Finite]
    log: bool = False
    neutral: Optional[Finite] = Field(None, description="value that removes the effect (quadrature_excess)")
    unit: str = ""
    target: CalTarget

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


class Calibration(_Strict):
    """Fit ``parameters`` on this campaign's baseline (:mod:`experiment_runner.calibration`)."""
    trials: int = Field(16, ge=1, le=1000, description="baseline trials per evaluation (the first of the campaign's)")
    rounds: int = Field(3, ge=1, le=10, description="Gauss-Seidel rounds at most")
    rtol: Annotated[float, Field(gt=0, lt=1)] = 0.01
    parameters: list[CalParameter] = Field(min_length=1, max_length=3)


class CalibrationFrom(_Strict):
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


class Campaign(_Strict):
    name: Name
    title: str
    description: str = ""
    test: Test
    trials: int = Field(ge=1, le=10_000, description="trials per case and condition")
    starts: Starts = Starts()
    overrides: dict = Field(default_factory=dict, description="dotted-path overrides for every case")
    cases: list[Case] = Field(min_length=1)
    baseline: str
    sweep: Optional[Sweep] = None
    calibration: Optional[CalibrationSpec] = None
    seed: SeedData

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
            if c.per_speed and self.test.kind != "circle":
                raise ValueError(f"cases.{i} ({c.name}).per_speed: only for circle tests (a speed per condition)")
        conds = conditions(self)
        metrics = _metric_names(self)

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
        return next(c for c in self.cases if c.name == name)

    def seed_value(self, case: str, metric: str, **at) -> Optional[float]:
        cond = [c for c in conditions(self) if c.matches(**at)]
        for v in self.seed.values:
            if v.case == case and v.metric == metric and cond and cond[0].matches(**v.at()) \
                    and len([c for c in conditions(self) if c.matches(**v.at())]) == 1:
                return v.value
        return None


# =========================================================================== conditions
def fmt_length(x: float) -> str:
    """``5e-3 -> '5 mm'``, ``5e-6 -> '5 µm'``, ``5e-8 -> '50 nm'``.

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
    """One test condition (a step size, or a radius and speed) and sweep value."""
    key: str
    label: str
    step: Optional[float] = None
    radius: Optional[float] = None
    speed: Optional[float] = None
    sweep: Optional[float] = None
    amplitude: Optional[float] = None          # frequency_response: force amplitude [N]

    def matches(self, step=None, radius=None, speed=None, sweep=None, amplitude=None) -> bool:
        for mine, want in ((self.step, step), (self.radius, radius), (self.speed, speed), (self.sweep, sweep),
                           (self.amplitude, amplitude)):
            if want is not None and (mine is None or not math.isclose(mine, want, rel_tol=1e-9, abs_tol=0.0)):
                return False
        return True

    def at(self) -> dict:
        return {k: getattr(self, k) for k in ("step", "radius", "speed", "sweep", "amplitude")
                if getattr(self, k) is not None}


def conditions(c: Campaign) -> list[Condition]:
    """Every condition of the campaign: test conditions x sweep values."""
    t = c.test
    base = []
    if t.kind == "point_to_point":
        for s in t.steps:
            base.append(Condition(_slug(fmt_length(s)), fmt_length(s), step=float(s)))
    elif t.kind == "frequency_response":
        for a in t.amplitudes:
            base.append(Condition(f"{a:g}N".replace(".", "p").replace("+", ""), f"{a:g} N", amplitude=float(a)))
    else:
        for r, v in t.pairs():
            lab = f"R {fmt_length(r)}, {fmt_length(v)}/s"
            base.append(Condition(_slug(f"r{fmt_length(r)}_v{fmt_length(v)}s"), lab, radius=r, speed=v))
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
    """Names of the campaigns shipped with the package."""
    return sorted(p.stem for p in CAMPAIGN_DIR.glob("*.yaml"))


def load_campaign(name_or_path, check_presets: bool = True) -> Campaign:
    """Load and validate a campaign by name (shipped) or path; no code is executed.

    With ``check_presets`` every case's preset is loaded with the campaign's and the
    case's overrides, and every calibrated or swept path is resolved, so a campaign
    that loads also runs.
    """
    data, path = read_yaml_file(name_or_path, CAMPAIGN_DIR, "campaign")
    try:
        camp = Campaign.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format(err, str(path), "campaign")) from None
    if check_presets:
        check_campaign(camp, str(path))
    return camp


def check_campaign(camp: Campaign, source: str = "<campaign>") -> None:
    """Resolve every case's preset, overrides, calibrated and swept paths; ConfigError naming the field."""
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
def _expand(data, path: str) -> list[tuple[str, object]]:
    """Dotted path with '*' wildcards -> [(concrete path, value)] in ``data`` (a model_dump)."""
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
        for concrete, old in _expand(data, path):
            out[concrete] = (_scaled(old, value, concrete, series if mode == "series_scale" else None)
                             if mode in ("scale", "series_scale") else _py(value))
    return out


def _py(v):
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [_py(x) for x in v]
    if isinstance(v, dict):
        return {k: _py(x) for k, x in v.items()}
    return v


def case_overrides(camp: Campaign, case: Case, cal_values: Optional[dict] = None,
                   cond: Optional[Condition] = None) -> dict:
    """Every override of a case as absolute dotted paths, in application order: campaign,
    case, calibrated parameters, sweep value. ``with_overrides(load_preset(case.preset), o)``
    gives the case's preset (this is also what the graph experiment file holds)."""
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
    return _py(flat)


def calibration_source(camp: Campaign, source: str = "<campaign>") -> Optional[Campaign]:
    """The campaign whose calibration ``calibration: {from: NAME}`` reuses (None otherwise)."""
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
    """The calibrated parameters applied to the cases (own, or those of ``calibration.from``)."""
    if camp.calibration is None:
        return []
    src = calibration_source(camp)
    return list((src if src is not None else camp).calibration.parameters)


def case_preset(camp: Campaign, case: Case, cal_values: Optional[dict] = None,
                cond: Optional[Condition] = None) -> Preset:
    flat = case_overrides(camp, case, cal_values, cond)
    base = load_preset(case.preset)
    return with_overrides(base, flat) if flat else base


# =========================================================================== trials
def reference(camp: Campaign, cond: Condition, rate: float) -> profiles.Reference:
    """The shared (start-at-0) reference of a condition at the control rate."""
    t = camp.test
    dt = 1.0 / rate
    if t.kind == "point_to_point":
        return profiles.point_to_point(cond.step, duration=t.duration, dwell=t.dwell, dt=dt, pre=t.pre, shape=t.shape)
    return profiles.circle_x(cond.radius, cond.speed, cycles=t.cycles, dt=dt)


def start_position(camp: Campaign, preset: Preset, ref: profiles.Reference, i: int) -> float:
    """Start of trial ``i``: as :func:`experiment_runner.experiment.build_trials` for a one-trial
    experiment with ``starts.seed = campaign starts.seed + i``."""
    travel = preset.stage.travel
    lo = travel.min - min(0.0, float(ref.x.min()))
    hi = travel.max - max(0.0, float(ref.x.max()))
    return float(profiles.random_starts(1, (lo, hi), camp.starts.margin, camp.starts.seed + i)[0])


def make_trials(camp: Campaign, case: Case, preset: Preset, ref, n: int) -> list[Trial]:
    base = preset.simulation.seed
    out = []
    for i in range(n):
        x0 = start_position(camp, preset, ref, i)
        out.append(Trial(case=case.name, index=i, x_ref=ref.x + x0, v_ref=np.asarray(ref.v), seed=base + i,
                         window=camp.test.window, segments=tuple(ref.segments)))
    return out


def graph_experiment(camp: Campaign, case: Case, cond: Condition, trial: int, cal_values=None) -> dict:
    """A one-trial experiment file (:mod:`experiment_runner.experiment`) reproducing trial
    ``trial`` of ``case`` at ``cond`` through the ROS graph."""
    preset = case_preset(camp, case, cal_values, cond)
    ov = case_overrides(camp, case, cal_values, cond)
    ov["simulation.seed"] = int(preset.simulation.seed + trial)
    t = camp.test
    if t.kind == "point_to_point":
        prof = {"kind": "point_to_point", "distance": cond.step, "dwell": t.dwell, "pre": t.pre, "shape": t.shape}
        if t.duration is not None:
            prof["duration"] = t.duration
    else:
        prof = {"kind": "circle", "radius": cond.radius, "speed": cond.speed, "cycles": t.cycles}
    return {"name": f"{camp.name}_{case.name}_{cond.key}_t{trial}",
            "description": f"{camp.title}: {case.label}, {cond.label}, trial {trial} (written by nanostage campaign)",
            "preset": case.preset, "overrides": ov, "profile": prof, "trials": 1,
            "starts": {"margin": camp.starts.margin, "seed": camp.starts.seed + trial}, "window": t.window}


# =========================================================================== running
@dataclass
class Stat:
    mean: float
    std: float
    n: int
    n_valid: int
    values: list

    @classmethod
    def of(cls, values) -> "Stat":
        v = np.array([np.nan if x is None else float(x) for x in values], float)
        ok = v[np.isfinite(v)]
        return cls(mean=float(ok.mean()) if ok.size else math.nan,
                   std=float(ok.std(ddof=1)) if ok.size > 1 else (0.0 if ok.size else math.nan),
                   n=int(v.size), n_valid=int(ok.size), values=[None if not np.isfinite(x) else float(x) for x in v])


@dataclass
class Trace:
    """What the plots need of a representative trial."""
    trial: int
    t: np.ndarray              # [s] from the start of the trial
    e: np.ndarray              # measured position - target (p2p) or x_ref - y (tracking) [m]
    settle_start: Optional[float]
    settling_time: Optional[float]
    window: float
    y: np.ndarray              # measured position [m]
    x_ref: np.ndarray          # reference used by the servo [m]


@dataclass
class RunResult:
    """One case at one condition."""
    case: str
    cond: Condition
    preset: Preset
    overrides: dict
    metrics: list               # per trial dicts (trial_metrics)
    stats: dict                 # metric -> Stat
    rep: int                    # representative trial index
    trace: Trace
    wall_s: float
    recording: Optional[str] = None
    graph: Optional[dict] = None
    x0: list = field(default_factory=list)


@dataclass
class CampaignRun:
    campaign: Campaign
    out_dir: Path
    conditions: list
    runs: dict                  # (case, cond.key) -> RunResult
    findings: list
    calibration: Optional[dict]
    step_ii: dict               # case -> {"correction": ..., "history": ...}
    settings: dict
    timing: dict
    files: dict = field(default_factory=dict)

    def stat(self, case, cond_key, metric) -> Stat:
        return self.runs[(case, cond_key)].stats[metric]


def _metric_names(camp):
    return {"point_to_point": P2P_METRICS, "frequency_response": FRF_METRICS}.get(camp.test.kind, TRACK_METRICS)


def simulate_case(camp, case, cond, preset, n, correction=None, models=None, keep=False):
    """Run ``n`` trials of a case at a condition on the batch engine; metrics per trial."""
    from experiment_runner.batch import simulate
    rate = preset.controller.rate
    ref = reference(camp, cond, rate)
    trials = make_trials(camp, case, preset, ref, n)
    x0 = np.array([tr.x_ref[0] - ref.x[0] for tr in trials])
    res = simulate(preset, ref.x, ref.v, n_trials=n, x0=x0, seeds=[tr.seed for tr in trials],
                   correction=correction, models=models, check=False)
    mets = []
    for i, tr in enumerate(trials):
        if res.status[i] != 0:
            from stage_sim.plant import STATUS_TEXT
            m = {"trial": i, "case": case.name, **{k: None for k in METRIC_INFO},
                 "failed": STATUS_TEXT[int(res.status[i])]}
        else:
            m = trial_metrics(tr, res.y[i], res.x_ref[i], rate)
        mets.append(m)
    return ref, trials, res, mets


def _representative(camp, mets) -> int:
    key = "settling_time_s" if camp.test.kind == "point_to_point" else "rms_tracking_error_m"
    vals = np.array([np.nan if m.get(key) is None else m[key] for m in mets], float)
    ok = np.flatnonzero(np.isfinite(vals))
    if not ok.size:
        return 0
    med = np.median(vals[ok])
    return int(ok[np.argmin(np.abs(vals[ok] - med))])


def learn_step_ii(camp: Campaign, case: Case, preset: Preset, progress=None) -> dict:
    """Step II of Sec. 5.3 at rest: ILC (Eq. 5.2) of the reference correction after a switch."""
    from experiment_runner.batch import Models, simulate
    from stage_control.sai import ilc_update
    spec = case.step_ii
    ilc = preset.sai_manager.ilc
    rate = preset.controller.rate
    q = int(round(ilc.length * rate))
    n_pre = int(round(spec.settle_before * rate))
    n_comp = int(round(spec.compliant_time * rate))
    n_post = q + int(round(0.01 * rate))
    x = np.zeros(n_pre + n_comp + n_post)
    v = np.zeros_like(x)
    v[n_pre:n_pre + n_comp] = 1e-12       # p2p rule: compliant while v_ref != 0 (no feedforward uses it)
    travel = preset.stage.travel
    x0 = profiles.random_starts(spec.trials, (travel.min, travel.max), camp.starts.margin,
                                camp.starts.seed + 100_000)
    seeds = preset.simulation.seed + 100_000 + np.arange(spec.trials)
    models = Models.from_preset(preset)
    iterations = ilc.iterations if spec.iterations is None else spec.iterations
    u = np.zeros(q)
    hist, peak = [], []
    for it in range(iterations + 1):
        r = simulate(preset, x, v, n_trials=spec.trials, x0=x0, seeds=seeds, correction=u, models=models)
        errs = []
        for b in range(spec.trials):
            edges = np.flatnonzero((r.mode[b, :-1] == 1.0) & (r.mode[b, 1:] == 0.0))
            k0 = int(edges[0]) + 1
            e = (x0[b] + x - r.y[b])[k0:k0 + q]
            errs.append(np.pad(e, (0, q - e.size)))
        e_mean = np.mean(errs, axis=0)
        hist.append(float(np.sqrt(np.mean(np.square(errs)))))
        peak.append(float(np.max(np.abs(errs))))
        if progress:
            progress()
        if it < iterations:
            u = ilc_update(u, e_mean, ilc, rate)
    return {"correction": u, "rms_history_m": hist, "peak_history_m": peak, "iterations": iterations,
            "length_s": ilc.length, "trials": spec.trials, "compliant_time_s": spec.compliant_time}


def _calibrate(camp: Campaign, n_trials: int, bar=None) -> dict:
    """Fit the campaign's calibration parameters on its baseline case; returns calibration.json content."""
    from experiment_runner.batch import Models
    from experiment_runner.calibration import ParamSpec, fit
    cal = camp.calibration
    base = camp.case(camp.baseline)
    preset0 = case_preset(camp, base)
    specs, start, preset_values = [], {}, {}
    for p in cal.parameters:
        seed = camp.seed_value(camp.baseline, p.target.metric, **p.target.at())
        specs.append(ParamSpec(name=p.name, bounds=tuple(p.bounds), seed_value=seed, log=p.log,
                               form=p.target.form, seed_floor=p.target.seed_floor, null=p.neutral))
        if p.mode == "scale":
            start[p.name] = 1.0
            preset_values[p.name] = 1.0
        else:
            vals = {v if not isinstance(v, list) else tuple(v) for v in
                    (old for _, old in _expand(preset0.model_dump(), p.paths[0]))}
            v0 = next(iter(vals))
            start[p.name] = float(v0) if v0 is not None else float(p.bounds[0])
            preset_values[p.name] = v0
    conds = {}
    for p in cal.parameters:
        c = next(c for c in conditions(camp) if c.matches(**p.target.at()))
        conds[c.key] = c

    def evaluate(values):
        out = {}
        per_cond = {}
        for key, c in conds.items():
            preset = case_preset(camp, base, values, c)
            _, _, _, mets = simulate_case(camp, base, c, preset, n_trials, models=Models.from_preset(preset))
            per_cond[key] = mets
        for p in cal.parameters:
            c = next(c for c in conds.values() if c.matches(**p.target.at()))
            st = Stat.of([m.get(p.target.metric) for m in per_cond[c.key]])
            # an unsettled trial makes the mean undefined: report nan (the fit treats it as too large)
            out[p.name] = st.mean if st.n_valid == st.n else math.nan
        return out

    t0 = time.monotonic()
    res = fit(specs, start, evaluate, rounds=cal.rounds, rtol=cal.rtol,
              progress=(lambda: bar.update(1)) if bar is not None else None)
    # sensitivity profile around the fit (one parameter at a time, the others at their fit)
    profile = {}
    for spec in specs:
        lo, hi = spec.bounds
        v = res.values[spec.name]
        pts = sorted({min(max(v * f if spec.log or v else v + f - 1.0, lo), hi) for f in (0.5, 0.71, 1.0, 1.41, 2.0)})
        prof = []
        for x in pts:
            m = evaluate({**res.values, spec.name: x})
            if bar is not None:
                bar.update(1)
            prof.append({"value": x, "metric": m[spec.name]})
        profile[spec.name] = prof
    params = []
    for p, pf in zip(cal.parameters, res.params):
        per_case = {c.name: resolve(case_preset(camp, c), p.paths, p.mode, pf.value) for c in camp.cases}
        params.append({
            "name": p.name, "description": p.description, "paths": p.paths, "mode": p.mode, "unit": p.unit,
            "bounds": list(p.bounds), "log": p.log, "preset_value": _py(preset_values[p.name]),
            "start": pf.start, "value": pf.value, "at_bound": pf.at_bound, "applied": per_case,
            "target": {"case": camp.baseline, **p.target.at(), "metric": p.target.metric, "form": p.target.form,
                       "seed_floor": p.target.seed_floor, "seed": pf.seed_value, "seed_effective": pf.seed_effective,
                       "sim_before": pf.sim_start, "sim_after": pf.sim_value, "sim_effective": pf.sim_effective,
                       "log_residual": pf.residual},
            "profile": profile[p.name]})
    return {"campaign": camp.name, "baseline": camp.baseline, "trials": n_trials,
            "fingerprint": calibration_fingerprint(camp, n_trials),
            "method": "paired bounded 1-D root finding (brentq on log(sim/seed)), Gauss-Seidel rounds",
            "rounds": res.rounds, "converged": res.converged, "evaluations": res.evaluations,
            "wall_s": time.monotonic() - t0, "values": res.values, "parameters": params,
            "history": [{"values": v, "metrics": m} for v, m in res.history]}


def calibration_fingerprint(camp: Campaign, n_trials: int) -> str:
    """Hash of everything a baseline calibration depends on: the test, starts, the baseline
    case and its resolved preset, the calibration spec and its seed targets, the trial count."""
    import hashlib
    base = camp.case(camp.baseline)
    doc = {"test": camp.test.model_dump(mode="json"), "starts": camp.starts.model_dump(mode="json"),
           "baseline": base.model_dump(mode="json"), "preset": case_preset(camp, base).model_dump(mode="json"),
           "calibration": camp.calibration.model_dump(mode="json", exclude={"trials"}),
           "targets": [camp.seed_value(camp.baseline, p.target.metric, **p.target.at())
                       for p in camp.calibration.parameters], "trials": int(n_trials)}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]


def source_calibration(camp: Campaign, out_dir: Path, n_trials: Optional[int] = None, bar=None) -> dict:
    """The calibration of ``calibration: {from: NAME}``: loaded from a matching ``calibration.json``
    (this output folder, then ``out_dir/../NAME/``), else fitted on NAME's baseline.

    The result's ``applied`` overrides are those of this campaign's cases; ``source`` tells
    where the values come from (``loaded_from`` is None when fitted in this run).
    """
    src = calibration_source(camp)
    n = int(n_trials or camp.calibration.trials or src.calibration.trials)
    fp = calibration_fingerprint(src, n)
    doc, loaded = None, None
    for path in (out_dir / "calibration.json", out_dir.parent / src.name / "calibration.json"):
        try:
            got = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        if got.get("fingerprint") == fp and got.get("campaign") == src.name:
            doc, loaded = got, path
            break
    if doc is None:
        doc = _calibrate(src, n, bar)
    doc = dict(doc)
    doc["reused"] = loaded is not None
    doc["source"] = {"campaign": src.name, "title": src.title, "baseline": src.baseline,
                     "baseline_label": src.case(src.baseline).label,
                     "loaded_from": str(loaded) if loaded is not None else None}
    for p in doc["parameters"]:
        spec = next(q for q in src.calibration.parameters if q.name == p["name"])
        p["applied"] = {c.name: resolve(case_preset(camp, c), spec.paths, spec.mode, p["value"]) for c in camp.cases}
    return doc


def evaluate_findings(camp: Campaign, runs: dict) -> list[dict]:
    """Direction of every seed finding in the simulation (z: difference / its standard error)."""
    out = []
    conds = conditions(camp)
    for f in camp.seed.findings:
        if f.over == "sweep_spread":
            out.append(_spread_finding(camp, f, runs, [c for c in conds if c.matches(**f.at())]))
            continue
        cond = next(c for c in conds if c.matches(**f.at()))
        a = runs[(f.case, cond.key)].stats[f.metric]
        b = runs[(f.versus, cond.key)].stats[f.metric]
        sa = camp.seed_value(f.case, f.metric, **cond.at())
        sb = camp.seed_value(f.versus, f.metric, **cond.at())
        seed_rel = (sa - sb) / sb if sa is not None and sb not in (None, 0) else f.change
        rel = (a.mean - b.mean) / b.mean if b.mean and math.isfinite(a.mean) and math.isfinite(b.mean) else math.nan
        se = math.sqrt((a.std ** 2 / a.n_valid if a.n_valid > 1 else 0.0)
                       + (b.std ** 2 / b.n_valid if b.n_valid > 1 else 0.0))
        diff = a.mean - b.mean
        z = diff / se if se > 0 else (math.copysign(math.inf, diff) if diff else 0.0)
        reasons = []
        if f.relative_to is not None:       # difference of the reductions vs relative_to
            ref = runs[(f.relative_to, cond.key)].stats[f.metric].mean
            rel = (b.mean - a.mean) / ref if ref and math.isfinite(ref) and math.isfinite(rel) else math.nan
            z = math.nan
        if not math.isfinite(rel):
            agrees, status = False, "undefined (no settled trials)"
        elif f.direction == "similar":
            agrees, status = _similar(rel, f.tolerance, f"reductions vs {f.relative_to} " if f.relative_to else "")
        else:
            want = -1 if f.direction == "lower" else 1
            same_sign = np.sign(diff) == want
            significant = abs(z) >= 2.0
            agrees = bool(same_sign and significant)
            status = ("agrees" if agrees else ("same sign but within the trial scatter (|z| < 2)" if same_sign
                                                else "opposite direction"))
        for who, s in ((f.case, a), (f.versus, b)):
            if s.n_valid < s.n:
                reasons.append(f"{s.n - s.n_valid} of {s.n} trials of {who} did not settle within the dwell")
        out.append({"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": cond.label,
                    "condition_key": cond.key, **cond.at(), "metric": f.metric, "direction": f.direction,
                    "tolerance": f.tolerance if f.direction == "similar" else None,
                    "seed_case": sa, "seed_versus": sb, "seed_change": seed_rel,
                    "sim_case": a.mean, "sim_versus": b.mean, "sim_change": rel if math.isfinite(rel) else None,
                    "z": z if math.isfinite(z) else (None if z != z else (1e9 if z > 0 else -1e9)),
                    "agrees": bool(agrees), "status": status, "notes": reasons, "over": "mean",
                    "relative_to": f.relative_to,
                    "explanation": f.note if not agrees else ""})
    return out


def _similar(rel: float, tolerance: float, what: str = "") -> tuple[bool, str]:
    """A 'similar' finding: agrees when ``|rel| <= tolerance``; the status text."""
    agrees = abs(rel) <= tolerance
    return agrees, (f"{what}within ±{tolerance:.0%}" if agrees
                    else f"{what}differ by {rel:+.0%} (> ±{tolerance:.0%})")


def _spread_finding(camp: Campaign, f: Finding, runs: dict, conds: list) -> dict:
    """A ``sweep_spread`` finding: the standard deviation over the sweep values of each case's
    mean metric (e.g. the ±1σ band of Fig. 4.18 over the seven stiffness errors), case vs versus.
    Agrees when the sign matches ('lower'/'higher'; there is no trial-level z) or the relative
    difference is within the tolerance ('similar')."""
    spreads = []
    for who in (f.case, f.versus):
        means = np.array([runs[(who, c.key)].stats[f.metric].mean for c in conds], float)
        spreads.append(float(np.std(means, ddof=1)) if means.size > 1 and np.all(np.isfinite(means)) else math.nan)
    a, b = spreads
    rel = (a - b) / b if math.isfinite(a) and math.isfinite(b) and b > 0 else math.nan
    if f.relative_to is not None:          # spreads of the reductions vs relative_to, in reduction points
        ref = np.mean([runs[(f.relative_to, c.key)].stats[f.metric].mean for c in conds])
        rel = (a - b) / ref if math.isfinite(a) and math.isfinite(b) and ref > 0 else math.nan
    if not math.isfinite(rel):
        agrees, status = False, "undefined (unsettled trials or no spread)"
    elif f.direction == "similar":
        agrees, status = _similar(rel, f.tolerance,
                                  f"spreads of the reductions vs {f.relative_to} " if f.relative_to else "")
    else:
        agrees = bool(np.sign(rel) == (-1 if f.direction == "lower" else 1))
        status = "agrees" if agrees else "opposite direction"
    at = {k: v for k, v in conds[0].at().items() if k != "sweep"}
    label = conds[0].label.split(f", {camp.sweep.label} =")[0] + f", spread over {camp.sweep.label}"
    return {"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": label,
            "condition_key": conds[0].key.split("__")[0] + "__spread", **at, "metric": f.metric,
            "direction": f.direction, "tolerance": f.tolerance if f.direction == "similar" else None,
            "seed_case": None, "seed_versus": None, "seed_change": f.change,
            "sim_case": a if math.isfinite(a) else None, "sim_versus": b if math.isfinite(b) else None,
            "sim_change": rel if math.isfinite(rel) else None, "z": None, "agrees": bool(agrees), "status": status,
            "notes": [], "over": "sweep_spread", "relative_to": f.relative_to,
            "explanation": f.note if not agrees else ""}


# =========================================================================== graph
def _run_graph_with_correction(experiment: str, out: Path, timeout: float, domain_id, correction) -> dict:
    """:func:`experiment_runner.graph.run_one_process` with a learned Step II correction held by the
    SAI manager node from its start (its ``initial_correction`` parameter)."""
    from experiment_runner.graph import run_one_process
    corr = [float(v) for v in np.asarray(correction, float).ravel()]
    return run_one_process(experiment, out, timeout, domain_id,
                           params={"sai_manager": {"initial_correction": corr}} if corr else None)


def _graph_worker(jobs: list, domain_id: int) -> list:
    """Run graph jobs one after the other in this (spawned) process."""
    out = []
    for job in jobs:
        t0 = time.monotonic()
        try:
            if job.get("correction") is not None:
                s = _run_graph_with_correction(job["experiment"], Path(job["bag"]), job["timeout"], domain_id,
                                               job["correction"])
            else:
                from experiment_runner.graph import run_one_process
                s = run_one_process(job["experiment"], Path(job["bag"]), job["timeout"], domain_id)
            s = {k: s[k] for k in ("results", "aborted", "done", "recording")}
        except Exception as err:       # noqa: BLE001 - reported, the batch results stand
            s = {"results": [], "aborted": {"reason": f"{type(err).__name__}: {err}"}, "done": False,
                 "recording": None}
        s["key"] = job["key"]
        s["wall_s"] = time.monotonic() - t0
        out.append(s)
    return out


def run_graph_jobs(jobs: list, workers: int = 2, bar=None) -> list:
    """Run graph jobs on ``workers`` spawned processes, each on its own ROS domain."""
    if not jobs:
        return []
    import concurrent.futures as cf
    import multiprocessing as mp
    workers = max(1, min(workers, len(jobs)))
    parts = [[] for _ in range(workers)]
    load = [0] * workers
    for job in sorted(jobs, key=lambda j: -j["samples"]):
        w = load.index(min(load))
        parts[w].append(job)
        load[w] += job["samples"]
    base = 20 + (os.getpid() % 35) * 2
    results = []
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as ex:
        futs = [ex.submit(_graph_worker, part, base + w) for w, part in enumerate(parts)]
        for fut in cf.as_completed(futs):
            got = fut.result()
            results += got
            if bar is not None:
                bar.update(len(got))
    return results


# =========================================================================== main
def run_campaign(campaign, out_dir, *, trials: Optional[int] = None, dwell: Optional[float] = None,
                 calibrate: bool = True, calibration: Optional[dict] = None,
                 calibration_trials: Optional[int] = None, graph: bool = False, graph_workers: int = 2,
                 plots: bool = True, mcap: bool = True, progress: bool = True, report: bool = True,
                 graph_timeout: float = 600.0, workers: Optional[int] = None, cluster=None,
                 resume: bool = True) -> CampaignRun:
    """Calibrate (baseline only), run every case and condition, write the outputs.

    Parameters
    ----------
    campaign : str, Path or Campaign
    out_dir : path
        Output folder (created; files in it are overwritten).
    trials : int, optional
        Override the campaign's trial count (e.g. fast tests).
    dwell : float, optional
        Override the point-to-point dwell [s].
    calibrate : bool
        Fit the calibration parameters (else the presets' values are used).
    calibration : dict, optional
        A previous ``calibration.json`` content: use its values, do not fit.
    calibration_trials : int, optional
        Override ``calibration.trials``.
    graph : bool
        Also run the representative trial of every case and condition through the ROS graph.
    workers, cluster
        Where the trials run (:func:`experiment_runner.executor.make_executor`): ``workers``
        local processes (default 1: this process) or the Dask scheduler at ``cluster``.
    resume : bool
        Keep the trials already in ``out_dir/trials.jsonl`` from an interrupted run of the same
        campaign and settings (:mod:`experiment_runner.stream`); False discards them.
    """
    from tqdm import tqdm

    t_start = time.monotonic()
    camp = campaign if isinstance(campaign, Campaign) else load_campaign(campaign)
    if trials is not None or dwell is not None:
        data = camp.model_dump()
        if trials is not None:
            data["trials"] = int(trials)
            if isinstance(camp.calibration, Calibration):
                data["calibration"]["trials"] = min(data["calibration"]["trials"], int(trials))
        if dwell is not None:
            if camp.test.kind != "point_to_point":
                raise ConfigError("--dwell applies to point-to-point campaigns only")
            data["test"]["dwell"] = float(dwell)
        camp = Campaign.model_validate(data)
    if camp.test.kind == "frequency_response":
        from experiment_runner.frf_campaign import run_frf_campaign
        return run_frf_campaign(camp, out_dir, progress=progress, report=report, plots=plots, graph=graph)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    conds = conditions(camp)
    timing = {}
    disable = not progress

    # ---- calibration (baseline case only)
    cal = None
    cal_values = None
    if calibration is not None:
        cal = dict(calibration)
        cal["reused"] = True
        cal_values = dict(cal["values"])
    elif calibrate and isinstance(camp.calibration, CalibrationFrom):
        with tqdm(desc=f"{camp.name}: calibration of {camp.calibration.from_}", unit="eval", file=sys.stderr,
                  disable=disable, leave=False, mininterval=0.5) as bar:
            cal = source_calibration(camp, out_dir, calibration_trials, bar)
        cal_values = dict(cal["values"])
    elif calibrate and camp.calibration is not None:
        n_cal = min(calibration_trials or camp.calibration.trials, camp.trials)
        with tqdm(desc=f"{camp.name}: calibrate {camp.baseline}", unit="eval", file=sys.stderr,
                  disable=disable, leave=False, mininterval=0.5) as bar:
            cal = _calibrate(camp, n_cal, bar)
        cal_values = dict(cal["values"])
        cal["reused"] = False
    timing["calibration_s"] = time.monotonic() - t_start

    # ---- Step II learning (cases with step_ii), then every case x condition
    t1 = time.monotonic()
    step_ii = {}
    runs = {}
    unswept = {}
    n_units = len(camp.cases) * len(conds) + sum(
        ((c.step_ii.iterations if c.step_ii.iterations is not None else
          case_preset(camp, c).sai_manager.ilc.iterations) + 1) for c in camp.cases if c.step_ii)
    from experiment_runner.executor import make_executor
    from experiment_runner.stream import (STREAM_NAME, TrialStream, campaign_key, code_fingerprint,
                                          representative_trial, run_trials)
    stream_key = campaign_key(camp, {(c.name, cond.key): case_preset(camp, c, cal_values, cond)
                                     for c in camp.cases for cond in conds})
    with tqdm(total=n_units, desc=f"{camp.name}: simulate", unit="run", file=sys.stderr, disable=disable,
              leave=False, mininterval=0.5) as bar, make_executor(workers, cluster) as ex, \
            TrialStream(out_dir / STREAM_NAME, camp.name, stream_key, code_fingerprint(), resume) as stream:
        for case in camp.cases:
            corr_cache = {}
            for cond in conds:
                preset = case_preset(camp, case, cal_values, cond)
                corr = None
                if case.step_ii is not None:
                    key = preset.model_dump_json()
                    if key not in corr_cache:
                        corr_cache[key] = learn_step_ii(camp, case, preset, progress=lambda: bar.update(1))
                        step_ii.setdefault(case.name, corr_cache[key])
                    corr = corr_cache[key]["correction"]
                # a case the sweep leaves unchanged is run once per test condition and reused
                same = (case.name, preset.model_dump_json(), tuple(v for k, v in cond.at().items() if k != "sweep"))
                if cond.sweep is not None and same in unswept:
                    runs[(case.name, cond.key)] = replace(unswept[same], cond=cond, wall_s=0.0)
                    bar.update(1)
                    continue
                tc = time.monotonic()
                mets, x0 = run_trials(
                    camp, case, cond, preset, corr, ex, stream,
                    on_chunk=lambda d, n: bar.set_postfix_str(f"{case.name} {cond.label}: {d}/{n} trials"))
                stats = {m: Stat.of([x.get(m) for x in mets]) for m in _metric_names(camp)}
                rep = _representative(camp, mets)
                ref, tr, res = representative_trial(camp, case, cond, preset, rep, corr, mets[rep])
                if camp.test.kind == "point_to_point":
                    s = ref.select("settle")[0]
                    e = res.y[0] - tr.x_ref[s.stop - 1]
                    trace = Trace(rep, res.t.copy(), e, float(res.t[s.start]),
                                  mets[rep].get("settling_time_s"), camp.test.window, res.y[0].copy(),
                                  res.x_ref[0].copy())
                else:
                    trace = Trace(rep, res.t.copy(), res.x_ref[0] - res.y[0], None, None, camp.test.window,
                                  res.y[0].copy(), res.x_ref[0].copy())
                rr = RunResult(case=case.name, cond=cond, preset=preset,
                               overrides=case_overrides(camp, case, cal_values, cond), metrics=mets, stats=stats,
                               rep=rep, trace=trace, wall_s=time.monotonic() - tc, x0=x0)
                if mcap:
                    bag = out_dir / "recordings" / f"{case.name}_{cond.key}_batch"
                    from experiment_runner.recording import write_run
                    p = write_run(bag, res, preset, reference=ref, window=camp.test.window,
                                  case=f"{camp.name}/{case.name}/{cond.key}/trial{rep}", overwrite=True, node="batch")
                    rr.recording = str(p)
                runs[(case.name, cond.key)] = rr
                unswept[same] = rr
                del res
                bar.update(1)
    timing["simulation_s"] = time.monotonic() - t1

    # ---- representative trials through the ROS graph
    t2 = time.monotonic()
    if graph:
        exp_dir = out_dir / "graph_experiments"
        exp_dir.mkdir(exist_ok=True)
        jobs = []
        for case in camp.cases:
            for cond in conds:
                rr = runs[(case.name, cond.key)]
                exp = graph_experiment(camp, case, cond, rr.rep, cal_values)
                path = exp_dir / f"{case.name}_{cond.key}.yaml"
                path.write_text(yaml.safe_dump(exp, sort_keys=False, allow_unicode=True))
                bag = out_dir / "recordings" / f"{case.name}_{cond.key}_graph"
                if bag.exists():
                    shutil.rmtree(bag)
                corr = step_ii[case.name]["correction"].tolist() if case.name in step_ii else None
                jobs.append({"key": (case.name, cond.key), "experiment": str(path), "bag": str(bag),
                             "timeout": graph_timeout, "correction": corr, "samples": len(rr.trace.t)})
        with tqdm(total=len(jobs), desc=f"{camp.name}: ROS graph", unit="trial", file=sys.stderr,
                  disable=disable, leave=False, mininterval=0.5) as bar:
            got = run_graph_jobs(jobs, graph_workers, bar)
        for g in got:
            rr = runs[tuple(g["key"])]
            g = _compare_graph(g, rr)
            rr.graph = g
    timing["graph_s"] = time.monotonic() - t2

    findings = evaluate_findings(camp, runs)
    settings = {"trials": camp.trials, "test": camp.test.model_dump(), "starts": camp.starts.model_dump(),
                "calibrated": cal is not None, "calibration_trials": cal.get("trials") if cal else None,
                "graph": graph}
    cr = CampaignRun(campaign=camp, out_dir=out_dir, conditions=conds, runs=runs, findings=findings,
                     calibration=cal, step_ii=step_ii, settings=settings, timing=timing)
    write_outputs(cr, write_results, report=report, plots=plots, t_start=t_start)
    return cr


def write_outputs(cr: CampaignRun, write_results_fn, *, report: bool, plots: bool, t_start: float) -> None:
    """Results files (``write_results_fn(cr)``), PNG plots and ``report.md``; the results are
    written first (kept if a plot fails) and again with the final timing."""
    from experiment_runner import report as rep_mod
    t3 = time.monotonic()
    write_results_fn(cr)
    if report:
        if plots:
            cr.files["plots"] = rep_mod.write_plots(cr)
        cr.timing["total_s"] = time.monotonic() - t_start
        cr.files["report"] = rep_mod.write_report(cr)
    cr.timing["output_s"] = time.monotonic() - t3
    cr.timing["total_s"] = time.monotonic() - t_start
    write_results_fn(cr)


def _compare_graph(g: dict, rr: RunResult) -> dict:
    """Graph trial vs the same batch trial: metrics and the largest difference of the measured position."""
    out = {"done": g["done"], "aborted": g["aborted"], "wall_s": g["wall_s"], "recording": g["recording"],
           "results": g["results"]}
    if g["results"]:
        r = g["results"][0]
        b = rr.metrics[rr.rep]
        out["metrics"] = {k: r.get(k) for k in METRIC_INFO}
        out["batch_metrics"] = {k: b.get(k) for k in METRIC_INFO}
    try:
        from experiment_runner.recording import read_recording
        rec = read_recording(g["recording"])
        n = min(len(rec.y), len(rr.trace.y))
        out["samples"] = int(len(rec.y))
        out["batch_samples"] = int(len(rr.trace.y))
        out["max_abs_diff_m"] = float(np.max(np.abs(rec.y[:n] - rr.trace.y[:n]))) if n else None
        out["max_abs_ref_diff_m"] = float(np.max(np.abs(rec.x_ref[:n] - rr.trace.x_ref[:n]))) if n else None
    except Exception as err:     # noqa: BLE001
        out["read_error"] = f"{type(err).__name__}: {err}"
    return out


# =========================================================================== outputs
def write_results(cr: CampaignRun) -> None:
    """``results.csv``, ``results.json`` and ``calibration.json`` (SI units)."""
    from experiment_runner.report import write_rows_csv
    camp = cr.campaign
    rows = []
    for case in camp.cases:
        for cond in cr.conditions:
            rr = cr.runs[(case.name, cond.key)]
            for m in _metric_names(camp):
                st = rr.stats[m]
                seed = camp.seed_value(case.name, m, **cond.at())
                rows.append({
                    "campaign": camp.name, "case": case.name, "case_label": case.label, "condition": cond.key,
                    "condition_label": cond.label, "step_m": cond.step, "radius_m": cond.radius,
                    "speed_m_s": cond.speed, "sweep_name": camp.sweep.name if camp.sweep else None,
                    "sweep_value": cond.sweep, "metric": m, "mean": finite_or_none(st.mean), "std": finite_or_none(st.std),
                    "n_trials": st.n, "n_valid": st.n_valid, "seed": seed,
                    "sim_over_seed": finite_or_none(st.mean / seed) if seed and math.isfinite(st.mean) else None,
                    "baseline": case.name == camp.baseline})
    write_rows_csv(cr.out_dir / "results.csv", rows)
    doc = {
        "campaign": camp.name, "title": camp.title, "description": camp.description, "seed_source": camp.seed.source,
        "seed_notes": camp.seed.notes, "baseline": camp.baseline, "settings": cr.settings, "timing_s": cr.timing,
        "cases": [{"name": c.name, "label": c.label, "preset": c.preset, "description": c.description,
                   "step_ii": c.step_ii.model_dump() if c.step_ii else None,
                   "overrides": {cond.key: cr.runs[(c.name, cond.key)].overrides for cond in cr.conditions}}
                  for c in camp.cases],
        "conditions": [{"key": c.key, "label": c.label, **c.at()} for c in cr.conditions],
        "results": rows,
        "findings": cr.findings,
        "calibration": {k: v for k, v in (cr.calibration or {}).items() if k != "history"} or None,
        "step_ii": {k: {kk: (vv.tolist() if isinstance(vv, np.ndarray) else vv) for kk, vv in v.items()}
                    for k, v in cr.step_ii.items()},
        "representative": [{"case": k[0], "condition": k[1], "trial": rr.rep, "x0_m": rr.x0[rr.rep],
                            "metrics": {m: rr.metrics[rr.rep].get(m) for m in _metric_names(camp)},
                            "recording": rr.recording, "graph": rr.graph} for k, rr in cr.runs.items()],
        "trials": [{"case": k[0], "condition": k[1], "trial": i, "x0_m": rr.x0[i] if i < len(rr.x0) else None,
                    **{m: met.get(m) for m in _metric_names(camp)}, **({"failed": met["failed"]} if "failed" in met else {})}
                   for k, rr in cr.runs.items() for i, met in enumerate(rr.metrics)],
        "files": {k: [str(x) for x in v] if isinstance(v, list) else str(v) for k, v in cr.files.items()},
    }
    (cr.out_dir / "results.json").write_text(json.dumps(_clean(doc), indent=1, allow_nan=False))
    if cr.calibration is not None:
        (cr.out_dir / "calibration.json").write_text(json.dumps(_clean(cr.calibration), indent=1, allow_nan=False))


def _clean(o):
    if isinstance(o, dict):
        return {str(k): _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


# =========================================================================== main job + CLI
def main_job(out_dir="out/campaigns", progress: bool = True, graph: bool = True, **run_kw) -> Path:
    """Tables 4.2 and 5.2 end to end: calibration, all trials on the batch engine, one
    representative trial per case and step size through the ROS graph; writes
    ``out_dir/<campaign>/...`` and the summary ``out_dir/report.md``; returns its path.
    ``run_kw`` (``workers``, ``cluster``, ``resume``) go to :func:`run_campaign`."""
    from experiment_runner import report as rep_mod
    t0 = time.monotonic()
    out_dir = Path(out_dir)
    runs = [run_campaign(name, out_dir / name, graph=graph, progress=progress, **run_kw) for name in MAIN_JOB]
    path = rep_mod.write_index(runs, out_dir, time.monotonic() - t0)
    print(f"report: {path}")
    return path


def add_campaign_arguments(parser):
    """Arguments of ``nanostage campaign`` (wire with ``set_defaults(func=main_campaign)``)."""
    from experiment_runner.cliargs import positive_float, positive_int
    parser.add_argument("campaign", nargs="?", help="campaign name (see --list) or YAML path")
    parser.add_argument("--list", action="store_true", help="list the shipped campaigns")
    parser.add_argument("--main", action="store_true",
                        help=f"the main job: {' and '.join(MAIN_JOB)} end to end with --graph (always starts anew)")
    parser.add_argument("--out", default=None, help="output folder (default out/campaigns[/NAME])")
    parser.add_argument("--trials", type=positive_int, default=None, help="trials per case and condition (override)")
    parser.add_argument("--dwell", type=positive_float, default=None, help="point-to-point dwell [s] (override)")
    parser.add_argument("--graph", action="store_true",
                        help="also run the representative trial of every case and condition through the ROS graph")
    parser.add_argument("--no-calibrate", action="store_true", help="use the presets' values (no fit)")
    parser.add_argument("--calibration", default=None, metavar="JSON",
                        help="reuse the values of a calibration.json instead of fitting")
    parser.add_argument("--calibration-trials", type=positive_int, default=None,
                        help="baseline trials per fit evaluation")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--no-mcap", action="store_true", help="skip the MCAP recordings of batch trials")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--json", action="store_true", help="print results.json's findings and calibration")
    from experiment_runner.executor import add_executor_arguments, cpu_count
    add_executor_arguments(parser, "trials", cpu_count(), "default: one per core; 1 = this process")
    parser.add_argument("--restart", action="store_true",
                        help="discard the trials of an interrupted run in --out (default: resume them)")
    return parser


def _read_calibration(path) -> dict:
    """A ``calibration.json`` written by an earlier campaign (``--calibration``)."""
    try:
        doc = json.loads(Path(path).read_text())
    except OSError as err:
        raise ConfigError(f"--calibration {path}: cannot read it ({err.strerror or err})") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ConfigError(f"--calibration {path}: not a calibration.json (invalid JSON: {err})") from None
    values = doc.get("values") if isinstance(doc, dict) else None
    if not isinstance(values, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values.values()):
        raise ConfigError(f"--calibration {path}: field 'values' must map each calibrated quantity to a finite "
                          f"number (a campaign's calibration.json); got {values!r:.80}")
    return doc


def main_campaign(args) -> int:
    """Run ``nanostage campaign`` from parsed arguments; 0 on success, 2 on a configuration error."""
    try:
        if args.list:
            for name in list_campaigns():
                c = load_campaign(name, check_presets=False)
                print(f"{name:18s} {c.title}")
            return 0
        if args.main:
            # the main job always starts anew: its trials are regenerated in ~2 min, and a stream
            # left by other settings or code must not stop the README's first command
            main_job(args.out or "out/campaigns", progress=not args.quiet, workers=args.workers,
                     cluster=args.cluster, resume=False)
            return 0
        if not args.campaign:
            print("nanostage campaign: give a CAMPAIGN (name or YAML path), --list or --main", file=sys.stderr)
            return 2
        camp = load_campaign(args.campaign)
        cal = _read_calibration(args.calibration) if args.calibration else None
        out = Path(args.out or f"out/campaigns/{camp.name}")
        cr = run_campaign(camp, out, trials=args.trials, dwell=args.dwell, calibrate=not args.no_calibrate,
                          calibration=cal, calibration_trials=args.calibration_trials, graph=args.graph,
                          plots=not args.no_plots, mcap=not args.no_mcap, progress=not args.quiet,
                          workers=args.workers, cluster=args.cluster, resume=not args.restart)
    except ConfigError as err:
        print(f"nanostage campaign: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("nanostage campaign: interrupted; the same command resumes from the trials done "
              "(trials.jsonl in the output folder)", file=sys.stderr)
        return 130
    if args.json:
        print(json.dumps(_clean({"findings": cr.findings, "calibration": {
            k: v for k, v in (cr.calibration or {}).items() if k != "history"}})))
    else:
        from experiment_runner.report import summary_lines
        for line in summary_lines(cr):
            print(line)
        print(f"report: {cr.files.get('report')}")
    return 0
