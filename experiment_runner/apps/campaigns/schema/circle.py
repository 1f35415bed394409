"""The schema of the ``circle`` campaign kind (its behaviour: :data:`~experiment_runner.apps.campaigns.trial_kinds.CIRCLE`).

A condition is a radius and a tangential speed; each is an experiment profile
(:class:`experiment_runner.core.experiment.Circle`), and its reference is that profile's.

Examples
--------
>>> t = CircleTest(kind="circle", circles=[{"radius": 5e-3, "speeds": [1e-3]}, {"radius": 5e-6, "speeds": [1e-6]}])
>>> [c.label for c in t.conditions()]
['R 5 mm, 1 mm/s', 'R 5 µm, 1 µm/s']
"""
from __future__ import annotations

from typing import ClassVar, Literal, Optional

from pydantic import Field, model_validator

from experiment_runner.apps.campaigns.schema.common import Condition, fmt_length, slug
from experiment_runner.core import experiment, profiles
from stage_sim.config import Pos, StrictModel

__all__ = ["CircleTest", "CircleSpeeds"]


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
        return [Condition(slug(f"r{fmt_length(r)}_v{fmt_length(v)}s"), f"R {fmt_length(r)}, {fmt_length(v)}/s",
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
