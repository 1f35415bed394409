"""What every campaign kind shares: the settings of a run, its results, the kind protocol.

A *campaign kind* is what a ``test: {kind: ...}`` does. Its schema (conditions, metrics,
reference) is a class in :mod:`experiment_runner.campaigns.spec`; its behaviour is a
:class:`CampaignKind` (point-to-point, circle: :mod:`~experiment_runner.campaigns.trial_kinds`;
frequency response: :mod:`~experiment_runner.campaigns.frequency_response`), listed once in
:data:`experiment_runner.campaigns.kinds.KINDS`. Nothing outside a kind asks ``test.kind``.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Protocol

import numpy as np

from experiment_runner import outputs, profiles
from experiment_runner.campaigns.spec import Campaign, Condition
from stage_sim.config import Preset

__all__ = ["RunSettings", "Stat", "Trace", "RunResult", "CampaignRun", "CampaignKind", "clean",
           "write_json", "write_rows_csv"]


@dataclass(frozen=True)
class RunSettings:
    """How a campaign is run (every field has the default of ``nanostage campaign NAME``).

    Attributes
    ----------
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
        Also run the representative trial of every case and condition through the ROS graph,
        on ``graph_workers`` processes, each given up after ``graph_timeout`` seconds.
    plots, mcap, report, progress : bool
        PNG plots, MCAP recordings of the representative batch trials, ``report.md``, progress bars.
    workers, cluster
        Where the trials run (:func:`experiment_runner.executor.make_executor`): ``workers``
        local processes (default 1: this process) or the Dask scheduler at ``cluster``.
    executor : experiment_runner.executor.Executor, optional
        An executor to run the trials on instead (kept open: several campaigns share its warm
        workers, as :func:`~experiment_runner.campaigns.runner.main_job` does).
    resume : bool
        Keep the trials already in ``out_dir/trials.jsonl`` from an interrupted run of the same
        campaign and settings (:mod:`experiment_runner.campaigns.stream`); False discards them.
    overwrite : bool
        ``out_dir`` may be a non-empty folder nanostage did not write (its other files are kept:
        :func:`experiment_runner.outputs.prepare_folder`).
    """
    trials: Optional[int] = None
    dwell: Optional[float] = None
    calibrate: bool = True
    calibration: Optional[dict] = None
    calibration_trials: Optional[int] = None
    graph: bool = False
    graph_workers: int = 2
    graph_timeout: float = 600.0
    plots: bool = True
    mcap: bool = True
    report: bool = True
    progress: bool = True
    workers: Optional[int] = None
    cluster: Any = None
    executor: Any = None
    resume: bool = True
    overwrite: bool = False


@dataclass
class Stat:
    """Mean, standard deviation and count of a metric over trials (undefined values left out)."""
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
    mechanism: Optional[dict] = None   # point-to-point: campaigns.mechanism.analyse of the trial


@dataclass
class CampaignRun:
    """A campaign as run: its kind, conditions, results per (case, condition key), findings, files."""
    campaign: Campaign
    kind: "CampaignKind"
    out_dir: Path
    conditions: list
    runs: dict                  # (case, cond.key) -> RunResult (frequency response: FrfRun)
    findings: list
    calibration: Optional[dict]
    step_ii: dict               # case -> {"correction": ..., "history": ...}
    settings: dict
    timing: dict
    files: dict = field(default_factory=dict)

    def stat(self, case, cond_key, metric) -> Stat:
        return self.runs[(case, cond_key)].stats[metric]


class CampaignKind(Protocol):
    """What a campaign kind does. One object per ``test.kind`` (:data:`~experiment_runner.campaigns.kinds.KINDS`).

    To add a kind: a test schema in :mod:`~experiment_runner.campaigns.spec` (``kind`` literal,
    ``METRICS``, ``conditions()``, ``reference()``) added to its ``Test`` union, a module with
    an object implementing this protocol, and its entry in ``KINDS``.
    """
    name: str                   # the schema's ``kind``
    metrics: tuple              # metric names (keys of campaigns.registry.METRICS) it reports

    def reference(self, camp: Campaign, cond: Condition, rate: float) -> Optional[profiles.Reference]:
        """The reference of a condition (None: the kind has no closed-loop reference)."""

    def run(self, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
        """Run the campaign (calibrated, overrides applied) into ``out_dir``, write its outputs."""

    def write_results(self, cr: CampaignRun) -> None:
        """``results.json`` and ``results.csv`` (and any kind-specific data file)."""

    def report_section(self, cr: CampaignRun) -> list[str]:
        """Markdown of ``report.md`` between its head and its plots."""

    def plots(self, cr: CampaignRun, plt, out: Path) -> list:
        """The kind's PNG plots in ``out``; returns their paths (None entries are dropped)."""


def clean(o):
    """``o`` with numpy values as Python ones and non-finite floats as None (strict JSON)."""
    if isinstance(o, dict):
        return {str(k): clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return clean(o.tolist())
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


OUTPUT_FILES = ("results.csv", "results.json", "report.md")
"""Files every campaign writes in its output folder (checked before it runs: :func:`experiment_runner.outputs.prepare_folder`)."""


def write_json(path: Path, doc) -> None:
    """``doc`` as strict JSON (:func:`clean`), one space of indentation (atomically: :mod:`experiment_runner.outputs`)."""
    outputs.write_text(path, json.dumps(clean(doc), indent=1, allow_nan=False))


def write_rows_csv(path: Path, rows: list[dict]) -> None:
    """``rows`` (dicts with the same keys) as CSV, None as an empty cell (atomically)."""
    with outputs.replacing(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})
