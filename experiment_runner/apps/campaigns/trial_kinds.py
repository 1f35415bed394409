"""The trial campaign kinds: point-to-point moves and circles.

Both run many closed-loop trials per case and condition on the batch engine
(:func:`experiment_runner.apps.campaigns.trial_run.run_trial_campaign`) and share their results,
report and closing plots; they differ in their metrics, representative trial, trace,
settling analysis and plots:

* :data:`POINT_TO_POINT` -- settling time and RMS in-position error (seed Sec. 3.4.1); plots of
  the settling portion (Fig. 4.7), in-position error spectra (Fig. 3.15), metrics vs step size
  (Fig. C.1, C.12); the settling mechanism of each representative trial
  (:mod:`experiment_runner.apps.campaigns.mechanism`);
* :data:`CIRCLE` -- peak and RMS tracking error (Sec. 3.4.2, 4.4.2); tracking-error plots and the
  reduction vs the baseline over the speed (Fig. 3.21/3.22, 4.13/4.14).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np
from matplotlib.ticker import NullFormatter

from experiment_runner.apps.campaigns import mechanism
from experiment_runner.apps.campaigns.base import CampaignRun, RunSettings, Trace
from experiment_runner.apps.campaigns.registry import METRICS
from experiment_runner.apps.campaigns.report import (colors, save_figure, trial_how, trial_plots, trial_section,
                                                trial_settings)
from experiment_runner.apps.campaigns.schema.circle import CircleTest
from experiment_runner.apps.campaigns.schema.common import Condition, fmt_length
from experiment_runner.apps.campaigns.schema.point_to_point import PointToPointTest
from experiment_runner.apps.campaigns.spec import Campaign
from experiment_runner.apps.campaigns.trial_run import run_trial_campaign, write_results
from experiment_runner.core import profiles
from experiment_runner.core.metrics import error_spectrum

__all__ = ["TrialKind", "PointToPoint", "Circle", "POINT_TO_POINT", "CIRCLE"]


class TrialKind:
    """What the trial kinds share (a :class:`~experiment_runner.apps.campaigns.base.CampaignKind`)."""
    name: str
    test: type                     # the schema class, in campaigns/schema/<name>.py

    @property
    def metrics(self) -> tuple:
        """Metric names the kind reports (its schema's ``METRICS``)."""
        return self.test.METRICS

    @property
    def representative_metric(self) -> str:
        """The representative trial has the median of this metric."""
        return self.test.REPRESENTATIVE

    def reference(self, camp: Campaign, cond: Condition, rate: float) -> profiles.Reference:
        """The shared (start-at-0) reference of a condition (its schema's ``reference``).

        Parameters
        ----------
        camp : Campaign
            The campaign as run.
        cond : Condition
            A condition.
        rate : float
            Control rate [Hz].

        Returns
        -------
        experiment_runner.core.profiles.Reference
        """
        return camp.test.reference(cond, rate)

    def run(self, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
        """Run the campaign (:func:`~experiment_runner.apps.campaigns.trial_run.run_trial_campaign`).

        Parameters
        ----------
        camp : Campaign
            The campaign as run.
        out_dir : pathlib.Path
            The campaign's output folder.
        settings : RunSettings
            How it runs.

        Returns
        -------
        CampaignRun
        """
        return run_trial_campaign(self, camp, out_dir, settings)

    def write_results(self, cr: CampaignRun) -> None:
        """Write the results files (:func:`~experiment_runner.apps.campaigns.trial_run.write_results`).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.
        """
        write_results(cr)

    def report_how(self, cr: CampaignRun) -> str:
        """How it was run (:func:`~experiment_runner.apps.campaigns.report.trial_how`).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.

        Returns
        -------
        str
        """
        return trial_how(cr)

    def report_section(self, cr: CampaignRun) -> list[str]:
        """The report's body (:func:`~experiment_runner.apps.campaigns.report.trial_section`).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.

        Returns
        -------
        list of str
            Lines of Markdown.
        """
        return trial_section(cr)

    def report_settings(self, cr: CampaignRun) -> list[str]:
        """The report's settings (:func:`~experiment_runner.apps.campaigns.report.trial_settings`).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.

        Returns
        -------
        list of str
            Lines of Markdown.
        """
        return trial_settings(cr)

    def plots(self, cr: CampaignRun, plt, out: Path) -> list:
        """The kind's own plots, then the shared ones (:func:`~experiment_runner.apps.campaigns.report.trial_plots`).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.
        plt : module
            ``matplotlib.pyplot``.
        out : pathlib.Path
            Plots folder.

        Returns
        -------
        list of pathlib.Path
        """
        return self.own_plots(cr, plt, out) + trial_plots(cr, plt, out)

    # ---------------------------------------------------------------- per kind
    def own_plots(self, cr: CampaignRun, plt, out: Path) -> list:
        """The kind's plots (before the shared ones).

        Parameters
        ----------
        cr : CampaignRun
            A trial campaign as run.
        plt : module
            ``matplotlib.pyplot``.
        out : pathlib.Path
            Plots folder.

        Returns
        -------
        list of pathlib.Path
        """
        raise NotImplementedError

    def trace(self, camp: Campaign, ref, trial, res, metrics: dict, rep: int) -> Trace:
        """What the plots need of the representative trial ``rep`` (``res``: its one-row batch result).

        Parameters
        ----------
        camp : Campaign
            The campaign as run.
        ref : experiment_runner.core.profiles.Reference
            The shared reference.
        trial : experiment_runner.core.experiment.Trial
            The trial.
        res : experiment_runner.core.batch.BatchResult
            Its one-row batch result.
        metrics : dict
            Its metrics.
        rep : int
            Its index.

        Returns
        -------
        Trace
        """
        raise NotImplementedError

    def analyse(self, camp, case, cond, preset, rep: int, correction) -> Optional[dict]:
        """The settling mechanism of the representative trial (None: not analysed).

        Parameters
        ----------
        camp : Campaign
            The campaign as run.
        case : Case
            The case.
        cond : Condition
            A condition.
        preset : stage_sim.config.Preset
            The case's stage.
        rep : int
            The representative trial.
        correction : numpy.ndarray or None
            SAI Step II correction.

        Returns
        -------
        dict or None
        """
        return None


class PointToPoint(TrialKind):
    """Point-to-point moves: settling time and RMS in-position error (seed Sec. 3.4.1)."""
    name = "point_to_point"
    test = PointToPointTest

    def trace(self, camp, ref, trial, res, metrics, rep):
        s = ref.select("settle")[0]
        e = res.y[0] - trial.x_ref[s.stop - 1]
        return Trace(rep, res.t.copy(), e, float(res.t[s.start]), metrics.get("settling_time_s"), camp.test.window,
                     res.y[0].copy(), res.x_ref[0].copy())

    def analyse(self, camp, case, cond, preset, rep, correction):
        if camp.sweep is not None:
            return None
        return mechanism.analyse(camp, case, cond, preset, rep, correction)

    def own_plots(self, cr, plt, out):
        camp = cr.campaign
        cols = colors(len(camp.cases))
        files = []
        for cond in cr.conditions:
            files.append(_plot_settling(plt, cr, cond, camp.cases, cols, out))
            files.append(_plot_spectrum(plt, cr, cond, camp.cases, cols, out))
        if len(camp.test.steps) > 2 and camp.sweep is None:
            files.append(_plot_vs_step(plt, cr, camp.cases, cols, out))
        return files


class Circle(TrialKind):
    """Circles: peak and RMS tracking error (seed Sec. 3.4.2, 4.4.2)."""
    name = "circle"
    test = CircleTest

    def trace(self, camp, ref, trial, res, metrics, rep):
        return Trace(rep, res.t.copy(), res.x_ref[0] - res.y[0], None, None, camp.test.window, res.y[0].copy(),
                     res.x_ref[0].copy())

    def own_plots(self, cr, plt, out):
        camp = cr.campaign
        cols = colors(len(camp.cases))
        files = [_plot_tracking(plt, cr, cond, camp.cases, cols, out) for cond in cr.conditions]
        files.append(_plot_reduction(plt, cr, camp.cases, cols, out))
        return files


POINT_TO_POINT = PointToPoint()
CIRCLE = Circle()


# =========================================================================== plots
def _plot_settling(plt, cr, cond, cases, cols, out):
    w = cr.campaign.test.window
    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(9, 7.5), gridspec_kw={"height_ratios": [1, 1.6]})
    t_end = 0.0
    tr0 = cr.runs[(cases[0].name, cond.key)].trace
    span = float(np.max(np.abs(tr0.x_ref - tr0.x_ref[0]))) or 1e-9
    punit, pscale = next((u, 1 / s) for u, s in (("mm", 1e-3), ("µm", 1e-6), ("nm", 1e-9)) if span >= s * 0.999)
    ax0.plot(tr0.t, (tr0.x_ref - tr0.x_ref[0]) * pscale, color="k", lw=0.8, ls=":", label="reference")
    for case, c in zip(cases, cols):
        rr = cr.runs[(case.name, cond.key)]
        tr = rr.trace
        ts = tr.settling_time
        lab = f"{case.label} (trial {tr.trial}: " + (f"{ts * 1e3:.1f} ms" if ts is not None else "not settled") + ")"
        ax0.plot(tr.t, (tr.y - tr.y[0]) * pscale, color=c, lw=1, label=lab)
        tau = tr.t - tr.settle_start
        ax1.plot(tau * 1e3, tr.e * 1e9, color=c, lw=1, label=lab)
        if ts is not None:
            ax1.axvline(ts * 1e3, color=c, ls="--", lw=0.8)
        t_end = max(t_end, (ts or 0.1))
    ss = tr0.settle_start
    x1 = min(max(0.1, 1.6 * t_end + 0.02), tr0.t[-1] - ss)
    ax0.axvspan(ss, ss + x1, color="k", alpha=0.08, lw=0)
    ax0.set_xlim(0, min(tr0.t[-1], ss + 1.3 * x1))
    ax0.set_xlabel("time [s]")
    ax0.set_ylabel(f"position from start [{punit}]")
    ax0.set_title(f"{cr.campaign.title}\n{cond.label}: representative trials (median settling time)", fontsize=10)
    ax0.legend(fontsize=8, loc="best")
    ax0.grid(alpha=0.3)
    ax1.axhspan(-w * 1e9, w * 1e9, color="g", alpha=0.12, lw=0, label=f"±{w * 1e9:g} nm")
    ax1.axhline(w * 1e9, color="g", lw=0.8)
    ax1.axhline(-w * 1e9, color="g", lw=0.8)
    ax1.set_xlim(-0.05 * x1 * 1e3, x1 * 1e3)
    ax1.set_ylim(-5 * w * 1e9, 5 * w * 1e9)
    ax1.set_xlabel("time after the reference reaches the target [ms] (settling portion)")
    ax1.set_ylabel("position error [nm]")
    ax1.grid(alpha=0.3)
    ax1.legend(fontsize=8, loc="upper right")
    return save_figure(plt, fig, out / f"settling_{cond.key}.png")


def _plot_spectrum(plt, cr, cond, cases, cols, out):
    fig, ax = plt.subplots(figsize=(8, 4.5))
    any_ = False
    for case, c in zip(cases, cols):
        tr = cr.runs[(case.name, cond.key)].trace
        if tr.settling_time is None:
            continue
        k0 = int(np.searchsorted(tr.t, tr.settle_start + tr.settling_time - 1e-12))
        e = tr.e[k0:]
        if e.size < 64:
            continue
        fs = 1.0 / (tr.t[1] - tr.t[0])
        f, a = error_spectrum(e - e.mean(), fs)
        rms = float(np.sqrt(np.mean(e ** 2)))
        ax.loglog(f[1:], a[1:] * 1e9, color=c, lw=0.8, label=f"{case.label} (RMS {rms * 1e9:.2f} nm)")
        any_ = True
    if not any_:
        plt.close(fig)
        return None
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("amplitude [nm]")
    ax.set_title(f"In-position error spectrum after settling, {cond.label} (representative trials)", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=8)
    return save_figure(plt, fig, out / f"spectrum_{cond.key}.png")


def _plot_vs_step(plt, cr, cases, cols, out):
    """Mean settling time and RMS in-position error vs step size with ±1σ bands (Fig. C.1, C.12)."""
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.2))
    conds = sorted(cr.conditions, key=lambda c: abs(c.step))
    x = np.array([abs(c.step) for c in conds])
    for ax, metric in zip(axs, ("settling_time_s", "rms_in_position_m")):
        label, unit, scale = METRICS[metric][:3]
        for case, col in zip(cases, cols):
            st = [cr.runs[(case.name, c.key)].stats[metric] for c in conds]
            m = np.array([s.mean for s in st]) * scale
            sd = np.array([s.std for s in st]) * scale
            unsettled = sum(s.n - s.n_valid for s in st)
            ax.plot(x, m, "o-", color=col, label=case.label + (f" ({unsettled} unsettled trials)" if unsettled else ""))
            ax.fill_between(x, m - sd, m + sd, color=col, alpha=0.15, lw=0)
        ax.set_xscale("log")
        ax.set_xlabel("step size [m]")
        ax.set_ylabel(f"{label} [{unit}]")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=8)
    fig.suptitle(f"{cr.campaign.title}: mean and ±1σ over {cr.campaign.trials} trials", fontsize=10)
    return save_figure(plt, fig, out / "vs_step.png")


def _plot_tracking(plt, cr, cond, cases, cols, out):
    fig, ax = plt.subplots(figsize=(9, 4.5))
    for case, c in zip(cases, cols):
        tr = cr.runs[(case.name, cond.key)].trace
        ax.plot(tr.t, tr.e * 1e6, color=c, lw=0.8, label=f"{case.label} (trial {tr.trial})")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("tracking error x_ref - y [µm]")
    ax.set_title(f"{cr.campaign.title}\n{cond.label}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(plt, fig, out / f"tracking_{cond.key}.png")


def _plot_reduction(plt, cr, cases, cols, out):
    """Reduction of the peak and RMS tracking errors vs the baseline over the speed, one row per
    radius (Fig. 3.21/3.22, 4.13/4.14); with a sweep, the mean over its values and a ±1σ band
    (Fig. 4.18/4.19)."""
    camp = cr.campaign
    others = [(c, col) for c, col in zip(cases, cols) if c.name != camp.baseline]
    radii = sorted({c.radius for c in cr.conditions}, reverse=True)
    if not others or not radii:
        return None
    fig, axs = plt.subplots(len(radii), 2, figsize=(11, 3.6 * len(radii)), squeeze=False)
    for row, r in zip(axs, radii):
        speeds = sorted({c.speed for c in cr.conditions if c.radius == r})
        for ax, metric in zip(row, ("peak_tracking_error_m", "rms_tracking_error_m")):
            for case, col in others:
                mean, lo, hi = [], [], []
                for v in speeds:
                    red = []
                    for cond in (c for c in cr.conditions if c.radius == r and c.speed == v):
                        a = cr.runs[(case.name, cond.key)].stats[metric].mean
                        b = cr.runs[(camp.baseline, cond.key)].stats[metric].mean
                        if b and math.isfinite(a) and math.isfinite(b):
                            red.append(100.0 * (1.0 - a / b))
                    m = float(np.mean(red)) if red else math.nan
                    sd = float(np.std(red)) if len(red) > 1 else 0.0
                    mean.append(m)
                    lo.append(m - sd)
                    hi.append(m + sd)
                x = np.array(speeds) * (1e3 if r >= 1e-4 else 1e6)
                ax.plot(x, mean, "o-", color=col, label=case.label)
                if camp.sweep is not None:
                    ax.fill_between(x, lo, hi, color=col, alpha=0.15, lw=0)
            ax.axhline(0.0, color="k", lw=0.8)
            ax.set_xscale("log")
            ax.set_xticks(x)
            ax.set_xticklabels([f"{v:g}" for v in x])
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel(f"tangential speed [{'mm/s' if r >= 1e-4 else 'µm/s'}]")
            ax.set_ylabel(f"{METRICS[metric].label} reduction vs {camp.case(camp.baseline).label} [%]")
            ax.set_title(f"R {fmt_length(r)}" + (f" (mean and ±1σ over {camp.sweep.label})" if camp.sweep else ""),
                         fontsize=9)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    fig.suptitle(camp.title, fontsize=10)
    return save_figure(plt, fig, out / "reduction_vs_speed.png")


