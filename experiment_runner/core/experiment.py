"""Experiment files: which preset, which reference, how many trials, which metrics.

An experiment (``experiment_runner/core/experiments/<name>.yaml``, or any path) is
validated into an :class:`Experiment`, and :func:`build_trials` turns it into the
list of :class:`Trial` references that both the ROS graph (the sequencer node) and
the batch engine (:func:`run_batch`) execute, so both run exactly the same trials.

This module is also the one description of a run that campaigns share: a campaign's test
condition *is* an experiment profile (``PointToPointTest.profile(cond)`` is a
:class:`PointToPoint`, whose move is a :class:`Move`; ``CircleTest.profile(cond)`` a
:class:`Circle`), its reference is :func:`reference`'s, and its trials start by
:class:`Starts` (trial ``i`` of a campaign as the one trial of an experiment with
``Starts.trial(i)``).

Examples
--------
>>> exp = load_experiment("fi_p2p_5um")
>>> trials = build_trials(exp)
>>> len(trials), trials[0].case
(3, 'fi_p2p_5um')
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
from pydantic import Field, ValidationError

from experiment_runner.core import metrics, profiles
from experiment_runner.core.batch import simulate
from stage_sim.config import (ConfigError, Finite, NonNeg, Pos, Preset, schema_error_message, StrictModel,
                              load_preset, read_yaml_file, with_overrides)

EXPERIMENT_DIR = Path(__file__).with_name("experiments")


class Move(StrictModel):
    """How a point-to-point move goes, whatever its size: an experiment's :class:`PointToPoint`
    (one ``distance``) and a campaign's point-to-point test (its ``steps``) both are one."""
    duration: Optional[Pos] = Field(None, description="move duration [s]; default from the seed's anchors "
                                                      "(profiles.default_move_duration)")
    dwell: Pos = Field(0.25, description="settling portion recorded after the reference stops [s]")
    pre: NonNeg = Field(0.005, description="rest before the move [s]")
    shape: Literal["cycloidal", "triangular", "step"] = Field("cycloidal", description="move profile")


class PointToPoint(Move):
    """One point-to-point move (:func:`experiment_runner.core.profiles.point_to_point`)."""
    kind: Literal["point_to_point"]
    distance: Finite = Field(description="move size [m] (sign = direction)")


class StepSequence(StrictModel):
    kind: Literal["step_sequence"]
    distance: Finite
    n_forward: int = Field(8, ge=0)
    n_backward: int = Field(8, ge=0)
    duration: Optional[Pos] = None
    dwell: Pos = 0.25


class Circle(StrictModel):
    """The x-axis reference of a circle (:func:`experiment_runner.core.profiles.circle_x`)."""
    kind: Literal["circle"]
    radius: Pos = Field(description="circle radius [m]")
    speed: Pos = Field(description="tangential speed [m/s]")
    cycles: Pos = Field(1.0, description="revolutions")


class SineSweep(StrictModel):
    """Stepped sine (:func:`experiment_runner.core.profiles.sine_sweep`): one constant-amplitude
    position sine per frequency, phase continuous."""
    kind: Literal["sine_sweep"]
    frequencies: list[Pos] = Field(min_length=1, description="excitation frequencies [Hz], in order")
    amplitude: Pos = Field(description="position amplitude [m]")
    periods: int = Field(10, ge=1, description="steady-state periods per frequency")
    settle_periods: int = Field(5, ge=0, description="periods before the steady-state window")


Profile = Union[PointToPoint, StepSequence, Circle, SineSweep]


class Starts(StrictModel):
    """Where trials start: uniformly at random inside the travel less ``margin`` at both ends and
    less the reference's own extent, so that the whole reference stays inside; reproducible.

    The one rule of start positions (:meth:`positions`): ``n`` trials draw theirs in order from one
    generator seeded with ``seed``. A trial run on its own (each trial of a campaign, in any chunk,
    process or machine) is the one trial of :meth:`trial`'s starts.

    Examples
    --------
    >>> s = Starts(margin=5e-3, seed=1)
    >>> x0 = s.positions(3, (-10e-3, 10e-3))
    >>> bool(x0.min() >= -5e-3 and x0.max() < 5e-3), bool(s.positions(1, (-10e-3, 10e-3))[0] == x0[0])
    (True, True)
    >>> s.trial(2)
    Starts(margin=0.005, seed=3)
    """
    margin: NonNeg = Field(0.003, description="distance kept from the travel ends [m]")
    seed: int = Field(1, ge=0, description="seed of the generator the starts are drawn from")

    def positions(self, n: int, travel, extent=(0.0, 0.0), where: str = "") -> np.ndarray:
        """The starts [m] of ``n`` trials in ``travel`` (``(min, max)`` [m], or a preset's
        ``stage.travel``) of a reference moving over ``extent`` (its lowest and highest position
        relative to its start [m]): :func:`experiment_runner.core.profiles.random_starts`. A
        :class:`~stage_sim.validation.ConfigError` (``where``: what it is about) when there is no room."""
        lo, hi = (travel.min, travel.max) if hasattr(travel, "min") else travel
        try:
            return profiles.random_starts(n, (lo, hi), self.margin, self.seed, extent=extent)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}" if where else str(err)) from None

    def trial(self, i: int) -> "Starts":
        """The starts of trial ``i`` run on its own: the one trial of ``seed + i``."""
        return Starts(margin=self.margin, seed=self.seed + i)


class Experiment(StrictModel):
    name: str
    description: str = ""
    preset: str = Field(description="preset name or path")
    overrides: dict = Field(default_factory=dict, description="dotted-path preset overrides")
    profile: Profile = Field(discriminator="kind")
    trials: int = Field(1, ge=1, le=100_000)
    starts: Optional[Starts] = Field(None, description="random start positions; None = all start at 0")
    window: Pos = Field(25e-9, description="settling window half-width [m]")


@dataclass(frozen=True)
class Trial:
    """One trial: its reference at the control rate and everything needed to judge it."""
    case: str
    index: int
    x_ref: np.ndarray        # [m]
    v_ref: np.ndarray        # [m/s]
    seed: int
    window: float            # [m]
    segments: tuple          # profiles.Segment of the reference (settle / track ...)


def load_experiment(name_or_path) -> Experiment:
    """Load and validate an experiment file by name (shipped) or path; no code is executed."""
    data, path = read_yaml_file(name_or_path, EXPERIMENT_DIR, "experiment")
    try:
        return Experiment.model_validate(data)
    except ValidationError as err:
        raise ConfigError(schema_error_message(err, str(path))) from None


def list_experiments() -> list[str]:
    """Names of the experiments shipped with the package."""
    return sorted(p.stem for p in EXPERIMENT_DIR.glob("*.yaml"))


def experiment_preset(exp: Experiment) -> Preset:
    """The experiment's preset with its overrides applied (re-validated)."""
    preset = load_preset(exp.preset)
    return with_overrides(preset, exp.overrides) if exp.overrides else preset


def reference(profile: Profile, dt: float) -> profiles.Reference:
    """The reference of an experiment profile at sample time ``dt`` [s] (starting at 0)."""
    if profile.kind == "point_to_point":
        return profiles.point_to_point(profile.distance, duration=profile.duration, dwell=profile.dwell,
                                       dt=dt, pre=profile.pre, shape=profile.shape)
    if profile.kind == "step_sequence":
        return profiles.step_sequence(profile.distance, profile.n_forward, profile.n_backward,
                                      dwell=profile.dwell, dt=dt, duration=profile.duration)
    if profile.kind == "sine_sweep":
        return profiles.sine_sweep(profile.frequencies, profile.amplitude, periods=profile.periods,
                                   settle_periods=profile.settle_periods, dt=dt)
    return profiles.circle_x(profile.radius, profile.speed, cycles=profile.cycles, dt=dt)


def build_trials(exp: Experiment, preset: Preset | None = None) -> list[Trial]:
    """The trials of an experiment (seed of trial i = ``simulation.seed + i``, as the batch engine)."""
    preset = preset or experiment_preset(exp)
    ref = reference(exp.profile, 1.0 / preset.controller.rate)
    if exp.starts is None:
        x0 = np.zeros(exp.trials)
    else:
        x0 = exp.starts.positions(exp.trials, preset.stage.travel, extent=(float(ref.x.min()), float(ref.x.max())),
                                  where=f"experiment {exp.name} (profile {exp.profile.kind}, preset {preset.name})")
    return [Trial(case=exp.name, index=i, x_ref=ref.x + x0[i], v_ref=np.asarray(ref.v), seed=preset.simulation.seed + i,
                  window=exp.window, segments=tuple(ref.segments)) for i in range(exp.trials)]


def run_batch(exp: Experiment):
    """Run every trial of the experiment on the batch engine; returns (trials, BatchResult)."""
    preset = experiment_preset(exp)
    trials = build_trials(exp, preset)
    res = simulate(preset, np.stack([t.x_ref for t in trials]), np.stack([t.v_ref for t in trials]),
                   seeds=[t.seed for t in trials])
    return trials, res


def trial_metrics(trial: Trial, y: np.ndarray, x_ref: np.ndarray, rate: float) -> dict:
    """:func:`experiment_runner.core.metrics.trial_metrics` of one trial, judged at the target
    and settling start of its first settle segment (SI units, nan = not defined)."""
    t = np.arange(len(y)) / rate
    settle = [s for s in trial.segments if s.kind == "settle"]
    kw = {}
    if settle:
        kw = {"target": float(trial.x_ref[settle[0].stop - 1]), "settle_start": float(t[settle[0].start]),
              "window": trial.window}
    res = metrics.trial_metrics(t, x_ref, trial.v_ref, y, **kw)
    return {"trial": trial.index, "case": trial.case, **res}
