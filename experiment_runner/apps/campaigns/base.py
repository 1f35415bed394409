"""What every campaign kind shares: the settings of a run, its results, the kind protocol.

A *campaign kind* is what a ``test: {kind: ...}`` does. Its schema (conditions, metrics,
reference) is a class in the module of its name in :mod:`experiment_runner.apps.campaigns.schema`; its behaviour is a
:class:`CampaignKind` (point-to-point, circle: :mod:`~experiment_runner.apps.campaigns.trial_kinds`;
frequency response: :mod:`~experiment_runner.apps.campaigns.frequency_response`), listed once in
:data:`experiment_runner.apps.campaigns.kinds.KINDS`. Nothing outside a kind asks ``test.kind``.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional, Protocol

import numpy as np

from experiment_runner.apps.campaigns.schema.common import Condition
from experiment_runner.apps.campaigns.spec import Campaign
from experiment_runner.core import outputs, profiles
from stage_sim.config import Preset

__all__ = ["RunSettings", "Stat", "Trace", "RunResult", "CampaignRun", "CampaignKind", "clean",
           "write_json", "write_rows_csv"]


@dataclass(frozen=True)
class RunSettings:
    """How a campaign is run (every field has the default of ``nanostage campaign NAME``).

    Parameters
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
        Also run the representative trial of every case and condition through the ROS graph.
    graph_workers : int
        Processes running those graph trials.
    graph_timeout : float
        Seconds after which one graph trial is given up.
    plots, mcap, report, progress : bool
        PNG plots, MCAP recordings of the representative batch trials, ``report.md``, progress bars.
    workers : int, optional
    cluster : str or object, optional
        Where the trials run (:func:`experiment_runner.core.executor.make_executor`): ``workers``
        local processes (default 1: this process) or the Dask scheduler at ``cluster``.
    executor : experiment_runner.core.executor.Executor, optional
        An executor to run the trials on instead (kept open: several campaigns share its warm
        workers, as :func:`~experiment_runner.apps.campaigns.runner.main_job` does).
    resume : bool
        Keep the trials already in ``out_dir/trials.jsonl`` from an interrupted run of the same
        campaign and settings (:mod:`experiment_runner.apps.campaigns.stream`); False discards them.
    overwrite : bool
        ``out_dir`` may be a non-empty folder nanostage did not write (its other files are kept:
        :func:`experiment_runner.core.outputs.prepare_folder`).
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
    """Mean, standard deviation and count of a metric over trials (undefined values left out).

    Parameters
    ----------
    mean, std : float
        Mean and sample standard deviation (``ddof=1``) of the finite values, in the metric's
        unit; NaN when there is none (``std`` 0 for one value).
    n : int
        Trials.
    n_valid : int
        Trials whose value is finite.
    values : list of float or None
        The values per trial, None where undefined.
    """
    mean: float
    std: float
    n: int
    n_valid: int
    values: list

    @classmethod
    def of(cls, values) -> "Stat":
        """The statistics of ``values``.

        Parameters
        ----------
        values : iterable of float or None
            One value per trial; None and non-finite values count as undefined.

        Returns
        -------
        Stat

        Examples
        --------
        >>> s = Stat.of([1.0, None, 3.0])
        >>> (s.mean, s.n, s.n_valid, s.values)
        (2.0, 3, 2, [1.0, None, 3.0])
        """
        v = np.array([np.nan if x is None else float(x) for x in values], float)
        ok = v[np.isfinite(v)]
        return cls(mean=float(ok.mean()) if ok.size else math.nan,
                   std=float(ok.std(ddof=1)) if ok.size > 1 else (0.0 if ok.size else math.nan),
                   n=int(v.size), n_valid=int(ok.size), values=[None if not np.isfinite(x) else float(x) for x in v])


@dataclass
class Trace:
    """What the plots need of a representative trial.

    Parameters
    ----------
    trial : int
        The trial's index.
    t : numpy.ndarray
        Time from the start of the trial [s].
    e : numpy.ndarray
        Error [m]: measured position - target (point-to-point) or x_ref - y (tracking).
    settle_start : float or None
        Time the settling window opens [s] (None: no settling metric).
    settling_time : float or None
        Settling time [s] (None: did not settle).
    window : float
        Half-width of the settling window [m].
    y : numpy.ndarray
        Measured position [m].
    x_ref : numpy.ndarray
        Reference used by the servo [m].
    """
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
    """One case at one condition.

    Parameters
    ----------
    case : str
        The case's name.
    cond : Condition
        The condition.
    preset : stage_sim.config.Preset
        The stage as simulated (calibration and overrides applied).
    overrides : dict
        The case's overrides of its preset.
    metrics : list of dict
        Per trial, metric name -> value (SI units; :mod:`~experiment_runner.apps.campaigns.registry`).
    stats : dict
        Metric name -> :class:`Stat` over the trials.
    rep : int
        Index of the representative trial (plotted, recorded, run through the graph).
    trace : Trace
        What the plots need of the representative trial.
    wall_s : float
        Wall time of the case at this condition [s].
    recording : str, optional
        MCAP recording of the representative trial.
    graph : dict, optional
        The representative trial through the ROS graph against the batch engine.
    x0 : list of float
        Start position of each trial [m].
    mechanism : dict, optional
        Point-to-point: :func:`experiment_runner.apps.campaigns.mechanism.analyse` of the trial.
    """
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
    """A campaign as run: its kind, conditions, results per (case, condition key), findings, files.

    Parameters
    ----------
    campaign : Campaign
        The campaign's description.
    kind : CampaignKind
        Its kind.
    out_dir : pathlib.Path
        Its output folder.
    conditions : list of Condition
        The conditions run.
    runs : dict
        ``(case, cond.key)`` -> :class:`RunResult` (frequency response:
        :class:`~experiment_runner.apps.campaigns.frequency_response.FrfRun`).
    findings : list of dict
        The seed's directions checked (:mod:`~experiment_runner.apps.campaigns.findings`).
    calibration : dict or None
        What was calibrated (``calibration.json``), None when nothing was.
    step_ii : dict
        SAI cases: case -> ``{"correction": ..., "history": ...}`` of the Step II learning.
    settings : dict
        The run settings as written to ``results.json``.
    timing : dict
        Wall times [s] of the run's parts.
    files : dict
        Name -> path of the files written.
    """
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

    def stat(self, case: str, cond_key: str, metric: str) -> Stat:
        """The statistics of ``metric`` for ``case`` at the condition ``cond_key``.

        Parameters
        ----------
        case : str
            Case name.
        cond_key : str
            The condition's key (:attr:`Condition.key`).
        metric : str
            Metric name (:data:`experiment_runner.apps.campaigns.registry.METRICS`).

        Returns
        -------
        Stat
        """
        return self.runs[(case, cond_key)].stats[metric]


class CampaignKind(Protocol):
    """What a campaign kind does. One object per ``test.kind`` (:data:`~experiment_runner.apps.campaigns.kinds.KINDS`).

    Parameters
    ----------
    *args, **kwargs
        A protocol: not instantiated.

    Attributes
    ----------
    name : str
        The schema's ``kind``.
    test : type
        The schema class (``campaigns/schema/<name>.py``).
    metrics : tuple of str
        Metric names (keys of :data:`experiment_runner.apps.campaigns.registry.METRICS`) it reports.

    Notes
    -----
    To add a kind: its test schema in ``campaigns/schema/<name>.py`` (``kind`` literal,
    ``METRICS``, ``conditions()``, ``reference()``) added to the ``Test`` union of
    :mod:`~experiment_runner.apps.campaigns.spec`, a module with an object implementing this
    protocol, and its entry in ``KINDS``.
    """
    name: str                   # the schema's ``kind``
    test: type                  # the schema class, in campaigns/schema/<name>.py
    metrics: tuple              # metric names (keys of campaigns.registry.METRICS) it reports

    def reference(self, camp: Campaign, cond: Condition, rate: float) -> Optional[profiles.Reference]:
        """The reference of a condition (None: the kind has no closed-loop reference).

        Parameters
        ----------
        camp : Campaign
            The campaign.
        cond : Condition
            One of its conditions.
        rate : float
            Control rate [Hz] of the stage it runs on.

        Returns
        -------
        experiment_runner.core.profiles.Reference or None
        """

    def run(self, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
        """Run the campaign (calibrated, overrides applied) into ``out_dir``, write its outputs.

        Parameters
        ----------
        camp : Campaign
            The campaign.
        out_dir : pathlib.Path
            Its output folder (:func:`experiment_runner.core.outputs.prepare_folder`).
        settings : RunSettings
            How it runs.

        Returns
        -------
        CampaignRun
        """

    def write_results(self, cr: CampaignRun) -> None:
        """Write ``results.json`` and ``results.csv`` (and any kind-specific data file).

        Parameters
        ----------
        cr : CampaignRun
            The campaign as run; the files go to ``cr.out_dir``.
        """

    def report_section(self, cr: CampaignRun) -> list[str]:
        """Markdown of ``report.md`` between its head and its plots.

        Parameters
        ----------
        cr : CampaignRun
            The campaign as run.

        Returns
        -------
        list of str
            Lines of Markdown.
        """

    def plots(self, cr: CampaignRun, plt, out: Path) -> list:
        """Write the kind's PNG plots into ``out``.

        Parameters
        ----------
        cr : CampaignRun
            The campaign as run.
        plt : module
            ``matplotlib.pyplot`` (imported by the caller, Agg backend).
        out : pathlib.Path
            Folder of the plots.

        Returns
        -------
        list of pathlib.Path or None
            The plots' paths (None entries are dropped by the caller).
        """


def clean(o: Any) -> Any:
    """``o`` with numpy values as Python ones and non-finite floats as None (strict JSON).

    Parameters
    ----------
    o : object
        Nested dicts, lists, tuples, numpy arrays and scalars; dict keys become strings.

    Returns
    -------
    object
        The same structure with only JSON types.

    Examples
    --------
    >>> clean({"a": np.array([1.0, np.nan]), 2: np.int64(3), "ok": np.bool_(True)})
    {'a': [1.0, None], '2': 3, 'ok': True}
    """
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
"""Files every campaign writes in its output folder (checked before it runs: :func:`experiment_runner.core.outputs.prepare_folder`)."""


def write_json(path: Path, doc: Any) -> None:
    """Write ``doc`` as strict JSON (:func:`clean`), one space of indentation.

    Parameters
    ----------
    path : pathlib.Path
        The file, written atomically (:mod:`experiment_runner.core.outputs`: absent, or a file nanostage wrote).
    doc : object
        What :func:`clean` accepts.
    """
    outputs.write_text(path, json.dumps(clean(doc), indent=1, allow_nan=False))


def write_rows_csv(path: Path, rows: list[dict]) -> None:
    """Write ``rows`` as CSV, None as an empty cell.

    Parameters
    ----------
    path : pathlib.Path
        The file, written atomically (:mod:`experiment_runner.core.outputs`).
    rows : list of dict
        One dict per row, all with the first row's keys (the header).
    """
    with outputs.replacing(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})
