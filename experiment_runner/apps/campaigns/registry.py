"""The one table of campaign metrics: name -> label, display unit, scale from SI, formatter.

Every metric a campaign measures (per trial: :func:`experiment_runner.core.experiment.trial_metrics`;
per frequency response: :mod:`experiment_runner.apps.campaigns.frf`) is listed here once; the
report, ``results.csv`` / ``results.json`` and the findings name and format metrics through it,
and the campaign schema's metric type (:data:`Metric`) and :data:`TRIAL_METRICS` are derived from it.

Examples
--------
>>> fmt_metric(0.0441, "settling_time_s"), fmt_metric(1.6e-9, "rms_in_position_m"), fmt_metric(None, "x")
('44.1 ms', '1.6 nm', '–')
>>> METRICS["phase_margin_deg"].compact(45.25)
'45.2°'

The schema's metric type and the per-trial metrics are derived from the table:

>>> import typing
>>> typing.get_args(Metric) == tuple(METRICS)
True
>>> TRIAL_METRICS
('settling_time_s', 'rms_in_position_m', 'peak_tracking_error_m', 'rms_tracking_error_m')

... and are the metrics the core measures of a trial:

>>> from experiment_runner.core import metrics
>>> TRIAL_METRICS == metrics.METRICS
True
"""
from __future__ import annotations

import math
from typing import Literal, NamedTuple, Optional

__all__ = ["MetricInfo", "METRICS", "Metric", "TRIAL_METRICS", "fmt_metric", "fmt_change"]


class MetricInfo(NamedTuple):
    """How a metric is named and shown, and what it is measured on.

    Parameters
    ----------
    label : str
        Its name in reports, e.g. "settling time".
    unit : str
        Display unit, e.g. "ms".
    scale : float
        Display value = SI value x ``scale``.
    short : str, optional
        Format of a compact table cell (``"{:.1f}°"``); default: :func:`fmt_metric`'s.
    per : {"trial", "frequency_response"}, optional
        Measured on every simulated trial, or on a case's FRF at an amplitude.
    """
    label: str                       # e.g. "settling time"
    unit: str                        # display unit, e.g. "ms"
    scale: float                     # display value = SI value x scale
    short: Optional[str] = None      # compact format of a table cell ("{:.1f}°"); default: fmt_metric
    per: Literal["trial", "frequency_response"] = "trial"   # every simulated trial, or a case's FRF at an amplitude

    def compact(self, v: Optional[float]) -> str:
        """A table cell: ``short`` (or :func:`fmt_metric`'s ``3 significant digits unit``), ``–`` if undefined.

        Parameters
        ----------
        v : float or None
            The value in SI units.

        Returns
        -------
        str
        """
        if v is None or not math.isfinite(v):
            return "–"
        return self.short.format(v * self.scale) if self.short else f"{v * self.scale:.3g} {self.unit}"


METRICS: dict[str, MetricInfo] = {
    # per trial (time domain)
    "settling_time_s": MetricInfo("settling time", "ms", 1e3),
    "rms_in_position_m": MetricInfo("RMS in-position error", "nm", 1e9),
    "peak_tracking_error_m": MetricInfo("peak tracking error", "µm", 1e6),
    "rms_tracking_error_m": MetricInfo("RMS tracking error", "µm", 1e6),
    # per case and amplitude (frequency response)
    "bandwidth_hz": MetricInfo("-3 dB closed-loop bandwidth", "Hz", 1.0, "{:.3g} Hz", "frequency_response"),
    "gain_margin_db": MetricInfo("gain margin", "dB", 1.0, "{:.1f} dB", "frequency_response"),
    "phase_margin_deg": MetricInfo("phase margin", "°", 1.0, "{:.1f}°", "frequency_response"),
    # Table C.1: Z / (s (s + P)) fitted to the plant FRF below 100 Hz (campaigns.frf.nominal_fit)
    "nominal_pole_per_s": MetricInfo("nominal-model pole P (Table C.1)", "1/s", 1.0, "{:.0f} 1/s",
                                     "frequency_response"),
    "nominal_gain": MetricInfo("nominal-model gain Z (Table C.1)", "N/(A·kg)", 1.0, "{:.2f} N/(A·kg)",
                               "frequency_response"),
}

Metric = Literal[tuple(METRICS)]
"""A metric name (the schema's type): a key of :data:`METRICS`."""

TRIAL_METRICS = tuple(name for name, info in METRICS.items() if info.per == "trial")
"""The metrics of one simulated trial (a failed trial has them all None)."""


def fmt_metric(v: Optional[float], metric: str, digits: int = 3) -> str:
    """``0.044, 'settling_time_s' -> '44 ms'``: ``digits`` significant digits in the display unit.

    Parameters
    ----------
    v : float or None
        The value in SI units; None or non-finite gives ``–``.
    metric : str
        A key of :data:`METRICS`.
    digits : int, optional
        Significant digits.

    Returns
    -------
    str
    """
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    info = METRICS[metric]
    return f"{v * info.scale:.{digits}g} {info.unit}"


def fmt_change(r: Optional[float]) -> str:
    """Relative change as a signed percentage.

    Parameters
    ----------
    r : float or None
        The change as a fraction (-0.634: 63 % less); None or non-finite gives ``–``.

    Returns
    -------
    str

    Examples
    --------

    >>> fmt_change(-0.634), fmt_change(None)
    ('-63%', '–')
    """
    if r is None or (isinstance(r, float) and not math.isfinite(r)):
        return "–"
    return f"{r * 100:+.0f}%".replace("+-", "-")
