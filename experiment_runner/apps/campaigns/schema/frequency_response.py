"""The schema of the ``frequency_response`` campaign kind (its behaviour:
:data:`~experiment_runner.apps.campaigns.frequency_response.FREQUENCY_RESPONSE`).

A condition is a force amplitude at the plant input; the frequencies are
:func:`frequency_grid`'s, the same at every amplitude. The kind has no closed-loop reference.

Examples
--------
>>> t = FrequencyResponseTest(kind="frequency_response", amplitudes=[0.5, 2.0], f_min=1.0, f_max=1e3)
>>> [c.key for c in t.conditions()], len(frequency_grid(t))
(['0p5N', '2N'], 91)
"""
from __future__ import annotations

import math
from typing import ClassVar, Literal, Optional

import numpy as np
from pydantic import Field, model_validator

from experiment_runner.apps.campaigns.schema.common import Condition
from stage_sim.config import NonNeg, Pos, StrictModel

__all__ = ["FrequencyResponseTest", "frequency_grid"]


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
