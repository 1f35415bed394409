"""The schema of the ``point_to_point`` campaign kind (its behaviour: :data:`~experiment_runner.apps.campaigns.trial_kinds.POINT_TO_POINT`).

A condition is a step size; each is an experiment profile
(:class:`experiment_runner.core.experiment.PointToPoint`, the one description of a run), and its
reference is that profile's.

Examples
--------
>>> t = PointToPointTest(kind="point_to_point", steps=[5e-3, 5e-6])
>>> [c.label for c in t.conditions()], t.METRICS
(['5 mm', '5 µm'], ('settling_time_s', 'rms_in_position_m'))
"""
from __future__ import annotations

from typing import ClassVar, Literal

from pydantic import Field, model_validator

from experiment_runner.apps.campaigns.schema.common import Condition, fmt_length, slug
from experiment_runner.core import experiment, profiles
from experiment_runner.core.experiment import Move
from stage_sim.config import Finite, Pos

__all__ = ["PointToPointTest"]


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
        return [Condition(slug(fmt_length(s)), fmt_length(s), step=float(s)) for s in self.steps]

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
