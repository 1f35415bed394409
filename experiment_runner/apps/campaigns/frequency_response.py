"""The frequency-response campaign kind (seed Sec. 4.3, App. C.2): FRFs, bandwidth and margins per amplitude.

:data:`FREQUENCY_RESPONSE` runs a ``test: {kind: frequency_response}`` campaign: the plant FRFs
of every case (:func:`experiment_runner.apps.campaigns.frf.plant_frf`, all amplitudes and
frequencies in one batch per stage; cases on the same stage share them), the loops with each
case's servo (:func:`~experiment_runner.apps.campaigns.frf.loop_frfs`), the metrics
(``bandwidth_hz``, ``gain_margin_db``, ``phase_margin_deg``), optionally the closed loop
simulated at each amplitude (:func:`~experiment_runner.apps.campaigns.frf.closed_loop_frf`), the
findings (:func:`~experiment_runner.apps.campaigns.findings.evaluate_frf_findings`); it writes
``results.json``, ``results.csv``, ``frf.csv`` (every FRF point, SI units, Hz), ``report.md``
and Bode plots. :func:`frf_lines` is the main job's summary of such a run.
"""
from __future__ import annotations

import csv
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
from tqdm import tqdm

from experiment_runner.apps.campaigns.base import (OUTPUT_FILES, CampaignRun, RunSettings, Stat, write_json,
                                              write_rows_csv)
from experiment_runner.apps.campaigns.calibration import source_calibration
from experiment_runner.apps.campaigns.findings import evaluate_frf_findings, seed_bound_check
from experiment_runner.apps.campaigns.frf import closed_loop_frf, loop_frfs, nominal_fit, plant_frf
from experiment_runner.apps.campaigns.registry import METRICS
from experiment_runner.apps.campaigns.report import cases_md, findings_table, write_outputs
from experiment_runner.apps.campaigns.schema.common import Condition
from experiment_runner.apps.campaigns.schema.frequency_response import FrequencyResponseTest, frequency_grid
from experiment_runner.apps.campaigns.spec import CalibrationFrom, Campaign, case_overrides, case_preset, conditions
from experiment_runner.core import outputs
from experiment_runner.core.batch import Models
from experiment_runner.core.metrics import finite_or_none
from stage_control.tuning import LoopMargins, closed_loop_bandwidth, loop_margins, margins
from stage_sim.config import ConfigError

__all__ = ["FrequencyResponse", "FREQUENCY_RESPONSE", "FrfRun", "frf_lines"]

FRF_METRICS = FrequencyResponseTest.METRICS


# =========================================================================== runs
@dataclass
class FrfRun:
    """One case at one amplitude (a campaign condition).

    Parameters
    ----------
    case : str
        The case's name.
    cond : Condition
        The condition (its force amplitude).
    preset : stage_sim.config.Preset
        The case's stage, as run.
    overrides : dict
        The case's overrides of its preset.
    freqs_hz : numpy.ndarray
        (nf,) excitation frequencies [Hz].
    G : numpy.ndarray
        (nf,) plant FRF, force -> position [m/N].
    G_aug : numpy.ndarray
        Augmented plant (Eq. C.5; ``G`` without DOB) [m/N].
    L : numpy.ndarray
        Loop broken at the plant input.
    T : numpy.ndarray
        Closed loop, reference -> position.
    values : dict
        Metric -> value (bandwidth [Hz], margins [dB, deg], Table C.1 fit).
    margins : LoopMargins
        Gain and phase margins and their frequencies.
    status : numpy.ndarray
        (nf,) plant status per frequency (0 ok, -1 skipped).
    stats : dict
        Metric -> :class:`~experiment_runner.apps.campaigns.base.Stat` (one value).
    wall_s : float
        Wall time [s].
    T_sim : numpy.ndarray, optional
        Closed loop simulated at the force amplitude (batch engine).
    u_amp : numpy.ndarray, optional
        Force amplitude it reached [N].
    bandwidth_sim_hz : float
        -3 dB bandwidth of ``T_sim`` [Hz].
    """
    case: str
    cond: object                # campaign.Condition
    preset: object
    overrides: dict
    freqs_hz: np.ndarray
    G: np.ndarray               # plant, force -> position [m/N]
    G_aug: np.ndarray           # augmented plant (Eq. C.5; = G without DOB)
    L: np.ndarray               # loop at the plant input
    T: np.ndarray               # closed loop, reference -> position
    values: dict                # metric -> float
    margins: LoopMargins
    status: np.ndarray
    stats: dict = field(default_factory=dict)   # metric -> campaign.Stat (one value)
    wall_s: float = 0.0
    T_sim: Optional[np.ndarray] = None          # closed loop simulated at the force amplitude (batch engine)
    u_amp: Optional[np.ndarray] = None          # force amplitude it reached [N]
    bandwidth_sim_hz: float = math.nan          # -3 dB bandwidth of T_sim



def run_frf_campaign(kind, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
    """Run a ``frequency_response`` campaign: plant FRFs of every case (all amplitudes and
    frequencies in one batch per case), loops, metrics, findings; write the outputs.

    ``settings.graph`` must be False: the FRFs are open-loop runs of the compiled plant, there is no
    closed-loop trial to re-run through the ROS graph.

    Parameters
    ----------
    kind : CampaignKind
        The frequency-response kind.
    camp : Campaign
        The campaign as run.
    out_dir : pathlib.Path
        The campaign's output folder.
    settings : RunSettings
        How it runs.

    Returns
    -------
    experiment_runner.apps.campaigns.base.CampaignRun
        ``runs[(case, condition key)]`` are :class:`FrfRun`.
    """
    if settings.graph:
        raise ConfigError(f"{camp.name}: --graph does not apply to a frequency_response campaign "
                          "(open-loop FRFs on the compiled plant)")
    t_start = time.monotonic()
    out_dir = outputs.prepare_folder(out_dir, settings.overwrite, files=OUTPUT_FILES, option="--out")
    conds = conditions(camp)
    test = camp.test
    # calibration: {from: NAME} reuses a point-to-point campaign's fitted stage (e.g. its bearing stiffness)
    cal = source_calibration(camp, out_dir) if isinstance(camp.calibration, CalibrationFrom) else None
    cal_values = dict(cal["values"]) if cal else None
    runs, samples, plants = {}, 0, {}
    with tqdm(total=len(camp.cases), desc=f"{camp.name}: FRFs", unit="case", file=sys.stderr,
              disable=not settings.progress, leave=False) as bar:
        for case in camp.cases:
            preset = case_preset(camp, case, cal_values)
            models = Models.from_preset(preset)
            # the plant FRF does not depend on the controller: cases on the same stage share it
            key = (preset.stage.model_dump_json(), preset.simulation.model_dump_json(), preset.controller.rate)
            if key not in plants:
                plants[key] = plant_frf(preset, test, models=models)
                samples += plants[key].samples
            pf = plants[key]
            if test.simulate_closed_loop:
                T_sim, u_amp, n = closed_loop_frf(preset, test, pf, models=models)
                samples += n
            for i, cond in enumerate(conds):
                ok = np.isfinite(pf.G[i])
                f, G = pf.freqs_hz[ok], pf.G[i, ok]
                lf = loop_frfs(preset, f, G)
                bw = closed_loop_bandwidth(f, lf["T"]) if f.size > 1 else math.nan
                mg = loop_margins(f, lf["L"]) if f.size > 2 else LoopMargins(math.nan, math.nan, math.nan,
                                                                             math.nan, 0)
                P, Z = nominal_fit(f, G)
                vals = {"bandwidth_hz": bw, "gain_margin_db": mg.gain_margin_db,
                        "phase_margin_deg": mg.phase_margin_deg, "nominal_pole_per_s": P,
                        "nominal_gain": Z * preset.stage.drive.force_constant}

                def full(x):
                    a = np.full(pf.freqs_hz.shape, np.nan + 0j)
                    a[ok] = x
                    return a
                runs[(case.name, cond.key)] = FrfRun(
                    case=case.name, cond=cond, preset=preset, overrides=case_overrides(camp, case, cal_values),
                    freqs_hz=pf.freqs_hz, G=pf.G[i].copy(), G_aug=full(lf["G_aug"]), L=full(lf["L"]),
                    T=full(lf["T"]), values=vals, margins=mg, status=pf.status[i].copy(),
                    stats={m: Stat.of([v if math.isfinite(v) else None]) for m, v in vals.items()},
                    wall_s=pf.wall_s / len(conds))
                if test.simulate_closed_loop:
                    r = runs[(case.name, cond.key)]
                    r.T_sim, r.u_amp = T_sim[i], u_amp[i]
                    okc = np.isfinite(T_sim[i])
                    r.bandwidth_sim_hz = closed_loop_bandwidth(pf.freqs_hz[okc], T_sim[i, okc]) \
                        if okc.sum() > 1 else math.nan
            bar.update(1)
    timing = {"simulation_s": time.monotonic() - t_start, "column_samples": samples}
    findings = evaluate_frf_findings(camp, runs)
    summary = {"trials": 1, "test": test.model_dump(), "calibrated": cal is not None, "graph": False,
                "frequencies_hz": frequency_grid(test).tolist()}
    cr = CampaignRun(campaign=camp, kind=kind, out_dir=out_dir, conditions=conds, runs=runs, findings=findings,
                     calibration=cal, step_ii={}, settings=summary, timing=timing)
    write_outputs(cr, report=settings.report, plots=settings.plots, t_start=t_start)
    return cr



# =========================================================================== outputs
def write_frf_results(cr) -> None:
    """``results.json`` (metrics, findings, seed checks, every FRF), ``results.csv`` (metrics)
    and ``frf.csv`` (one row per case x amplitude x frequency); SI units, Hz, dB, degrees.

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.
    """
    camp = cr.campaign
    rows = []
    for case in camp.cases:
        for cond in cr.conditions:
            r = cr.runs[(case.name, cond.key)]
            for m in FRF_METRICS:
                seed = camp.seed_value(case.name, m, **cond.at())
                rows.append({"campaign": camp.name, "case": case.name, "case_label": case.label,
                             "condition": cond.key, "condition_label": cond.label, "amplitude_n": cond.amplitude,
                             "metric": m, "value": finite_or_none(r.values[m]), "seed": seed,
                             "baseline": case.name == camp.baseline})
    write_rows_csv(cr.out_dir / "results.csv", rows)
    with outputs.replacing(cr.out_dir / "frf.csv") as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["case", "amplitude_n", "frequency_hz", "status", "G_re_m_per_n", "G_im_m_per_n",
                    "G_aug_re_m_per_n", "G_aug_im_m_per_n", "L_re", "L_im", "T_re", "T_im",
                    "T_sim_re", "T_sim_im", "u_amp_sim_n"])
        for (case, _), r in cr.runs.items():
            nan = np.full(r.freqs_hz.shape, np.nan)
            t_sim = r.T_sim if r.T_sim is not None else nan + 0j
            u_amp = r.u_amp if r.u_amp is not None else nan
            for j, fr in enumerate(r.freqs_hz):
                vals = [r.G[j], r.G_aug[j], r.L[j], r.T[j], t_sim[j]]
                w.writerow([case, r.cond.amplitude, f"{fr:.8g}", int(r.status[j])]
                           + [("" if not np.isfinite(x) else f"{x:.10g}") for v in vals for x in (v.real, v.imag)]
                           + ["" if not np.isfinite(u_amp[j]) else f"{u_amp[j]:.10g}"])
    frfs = [{"case": case, "condition": key, "amplitude_n": r.cond.amplitude, "freqs_hz": r.freqs_hz,
             "status": r.status, **{f"{n}_{part}": getattr(getattr(r, n), part) for n in ("G", "G_aug", "L", "T")
                                    for part in ("real", "imag")},
             "margins": r.margins._asdict(),
             **({"T_sim_real": r.T_sim.real, "T_sim_imag": r.T_sim.imag, "u_amp_sim_n": r.u_amp,
                 "bandwidth_sim_hz": r.bandwidth_sim_hz} if r.T_sim is not None else {})}
            for (case, key), r in cr.runs.items()]
    doc = {"campaign": camp.name, "title": camp.title, "description": camp.description,
           "seed_source": camp.seed.source, "seed_notes": camp.seed.notes, "baseline": camp.baseline,
           "kind": "frequency_response", "settings": cr.settings, "timing_s": cr.timing,
           "units": {"G": "m/N", "frequency": "Hz", "bandwidth_hz": "Hz", "gain_margin_db": "dB",
                     "phase_margin_deg": "deg", "amplitude_n": "N"},
           "cases": [{"name": c.name, "label": c.label, "preset": c.preset, "description": c.description,
                      "overrides": cr.runs[(c.name, cr.conditions[0].key)].overrides} for c in camp.cases],
           "conditions": [{"key": c.key, "label": c.label, **c.at()} for c in cr.conditions],
           "results": rows, "findings": cr.findings, "seed_checks": seed_bound_check(camp, cr.runs), "frf": frfs,
           "files": {k: [str(x) for x in v] if isinstance(v, list) else str(v) for k, v in cr.files.items()}}
    write_json(cr.out_dir / "results.json", doc)


def _fmt(v, metric) -> str:
    return METRICS[metric].compact(v)


def write_frf_plots(cr, plt, out: Path) -> list:
    """Bode plots (plant, augmented plant with DOB, closed loop) per case, every amplitude,
    and bandwidth / margins vs amplitude (Fig. 4.6 / C.10 style); returns the PNG paths.

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.
    plt : module
        ``matplotlib.pyplot``.
    out : pathlib.Path
        Plots folder.

    Returns
    -------
    list of pathlib.Path
    """
    camp = cr.campaign
    files = []
    cmap = plt.get_cmap("viridis")
    na = len(cr.conditions)
    for case in camp.cases:
        r0 = cr.runs[(case.name, cr.conditions[0].key)]
        kinds = [("G", "plant G (force → position)", "m/N")]
        if np.any(np.isfinite(r0.G_aug) & (np.abs(r0.G_aug - r0.G) > 1e-12 * np.abs(r0.G))):
            kinds.append(("G_aug", "augmented plant G_aug (Eq. C.5)", "m/N"))
        kinds.append(("T", "closed loop T (reference → position)", "-"))
        fig, axes = plt.subplots(2, len(kinds), figsize=(5.2 * len(kinds), 7), sharex=True, squeeze=False)
        for col, (attr, title, unit) in enumerate(kinds):
            for i, cond in enumerate(cr.conditions):
                r = cr.runs[(case.name, cond.key)]
                h = getattr(r, attr)
                ok = np.isfinite(h)
                c = cmap(i / max(na - 1, 1))
                axes[0, col].semilogx(r.freqs_hz[ok], 20 * np.log10(np.abs(h[ok])), color=c, lw=1.2,
                                      label=cond.label)
                ph = np.degrees(np.unwrap(np.angle(h[ok])))      # starts in (-180, 180]
                axes[1, col].semilogx(r.freqs_hz[ok], ph, color=c, lw=1.2)
                if attr == "T" and r.T_sim is not None:        # closed loop simulated at this amplitude
                    oks = np.isfinite(r.T_sim)
                    axes[0, col].semilogx(r.freqs_hz[oks], 20 * np.log10(np.abs(r.T_sim[oks])), "o", ms=2.5,
                                          color=c, mfc="none")
            axes[0, col].set_title(title + (" (o: simulated)" if attr == "T" and r0.T_sim is not None
                                            else ""))
            axes[0, col].set_ylabel(f"magnitude [dB re 1 {unit}]")
            axes[1, col].set_ylabel("phase [°]")
            axes[1, col].set_xlabel("frequency [Hz]")
            if attr == "T":
                axes[0, col].axhline(-3.0, color="k", ls=":", lw=0.8)
            for ax in axes[:, col]:
                ax.grid(True, which="both", alpha=0.3)
        axes[0, 0].legend(fontsize=7, title="force amplitude", title_fontsize=7)
        fig.suptitle(f"{camp.title}: {case.label}")
        fig.tight_layout()
        path = outputs.savefig(fig, out / f"bode_{case.name}.png", dpi=110)
        plt.close(fig)
        files.append(path)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for k, case in enumerate(camp.cases):
        a = [c.amplitude for c in cr.conditions]
        for ax, m in zip(axes, FRF_METRICS):
            v = [cr.runs[(case.name, c.key)].values[m] for c in cr.conditions]
            ax.semilogx(a, v, "o-", color=f"C{k % 10}", label=case.label)
    for ax, m in zip(axes, FRF_METRICS):
        ax.set_xlabel("force amplitude [N]")
        ax.set_ylabel(f"{METRICS[m].label} [{METRICS[m].unit}]")
        ax.grid(True, which="both", alpha=0.3)
        if m != "bandwidth_hz":
            ax.axhline(0.0, color="k", lw=0.8)
    axes[0].set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{camp.title}: bandwidth and margins vs amplitude")
    fig.tight_layout()
    path = outputs.savefig(fig, out / "bandwidth_margins.png", dpi=110)
    plt.close(fig)
    files.append(path)
    return files


def frf_table(cr, metric) -> list[str]:
    """Markdown rows of one metric: amplitude x case (the seed's number or limit where it states one).

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.
    metric : str
        Metric name (:data:`~experiment_runner.apps.campaigns.registry.METRICS`).

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = cr.campaign
    lines = ["| amplitude | " + " | ".join(c.label for c in camp.cases) + " |", "|---|" + "---|" * len(camp.cases)]
    bounds = {(s["case"], s["condition"]): s for s in seed_bound_check(camp, cr.runs) if s["metric"] == metric}
    for cond in cr.conditions:
        cells = []
        for case in camp.cases:
            s = _fmt(cr.runs[(case.name, cond.key)].values[metric], metric)
            b = bounds.get((case.name, cond.label))
            if b is not None:
                sym = {"upper": "≤ ", "lower": "≥ "}.get(b["bound"], "")
                s += f" (seed {sym}{_fmt(b['seed'], metric)})"
            cells.append(s)
        lines.append(f"| {cond.label} | " + " | ".join(cells) + " |")
    return lines


def frf_how(cr) -> str:
    """How a frequency-response campaign was run (the report's head).

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.

    Returns
    -------
    str
    """
    t = cr.campaign.test
    return (f"open-loop stepped-sine plant FRFs on the compiled plant ({len(t.amplitudes)} force "
            f"amplitudes x {len(frequency_grid(t))} frequencies {t.f_min:g}–{t.f_max:g} Hz per case, "
            f"{cr.timing.get('column_samples', 0) / 1e6:.1f} M column-samples), loops calculated with each "
            f"case's discrete servo; wall time {cr.timing.get('total_s', math.nan):.1f} s.")


def frf_section(cr) -> list[str]:
    """The body of a frequency-response campaign's report: bandwidth and margins per amplitude,
    the closed loop simulated, the seed's numbers, the findings.

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = cr.campaign
    L = ["## Bandwidth and margins per amplitude", "",
          "BW: -3 dB bandwidth of the closed loop T (reference → measured position); GM / PM: margins of the loop "
          "broken at the plant input, at its last gain crossover (negative = the LTI loop at that amplitude is "
          "unstable); – = not in the measured range. In brackets: the seed's number or limit where its text "
          "states one.", ""]
    for m in FRF_METRICS:
        label = METRICS[m].label
        L += [f"### {label[0].upper() + label[1:]}", ""] + frf_table(cr, m) + [""]
    if any(r.T_sim is not None for r in cr.runs.values()):
        L += ["### Closed loop simulated at each force amplitude (batch engine)", "",
              "A check of the LTI assumption (Sec. 4.3): each case's closed loop run on the batch engine with a "
              "sine reference of amplitude A·|G/T| (the reference that asks the plant input for the force "
              "amplitude A of the plant FRF if the stage were that LTI system); -3 dB bandwidth of the simulated "
              "T (calculated in brackets) and the range of force amplitudes reached over the frequencies.", "",
              "| amplitude | " + " | ".join(c.label for c in camp.cases) + " |", "|---|" + "---|" * len(camp.cases)]
        for cond in cr.conditions:
            cells = []
            for case in camp.cases:
                r = cr.runs[(case.name, cond.key)]
                ua = r.u_amp[np.isfinite(r.u_amp)] / cond.amplitude if r.u_amp is not None else np.zeros(0)
                cells.append(f"{_fmt(r.bandwidth_sim_hz, 'bandwidth_hz')} "
                             f"({_fmt(r.values['bandwidth_hz'], 'bandwidth_hz')})"
                             + (f", force {ua.min():.2f}–{ua.max():.2f} × A" if ua.size else ""))
            L.append(f"| {cond.label} | " + " | ".join(cells) + " |")
        L.append("")
    checks = seed_bound_check(camp, cr.runs)
    if checks:
        L += ["Seed numbers:", ""]
        for s in checks:
            sym = {"upper": "at most ", "lower": "at least "}.get(s["bound"], "")
            verdict = "" if s["within_bound"] is None else \
                (" — satisfied" if s["within_bound"] else " — NOT satisfied")
            L.append(f"* {camp.case(s['case']).label}, {s['condition']}: {METRICS[s['metric']].label} seed "
                     f"{sym}{_fmt(s['seed'], s['metric'])} ({s['source']}); simulation "
                     f"{_fmt(s['sim'] if s['sim'] is not None else math.nan, s['metric'])}{verdict}.")
    L += ["", "## Findings: direction in the simulation", "",
          "One deterministic value per case and amplitude (no trial scatter): 'lower'/'higher' agree when the sign "
          "matches, 'similar' when the change is within the tolerance.", ""]
    L += findings_table(cr)
    bad = [f for f in cr.findings if not f["agrees"]]
    L += ["", f"**{len(cr.findings) - len(bad)} of {len(cr.findings)} seed findings reproduced.**", ""]
    if bad:
        L += ["Where the simulation disagrees:", ""]
        for f in bad:
            L.append(f"* **{f['id']}** ({f['claim']}): {f['status']}."
                     + (f" {f['explanation'].strip()}" if f["explanation"] else ""))
        L.append("")
    return L


def frf_settings(cr) -> list[str]:
    """The settings at the end of a frequency-response campaign's report.

    Parameters
    ----------
    cr : CampaignRun
        A frequency-response campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    L = ["## Settings", "", f"* Test: `{cr.campaign.test.model_dump()}`", "* Cases:"]
    L += cases_md(cr)
    L += ["", "Files: `results.json` (metrics, findings, every FRF), `results.csv` (metrics), `frf.csv` "
          "(G, G_aug, L, T per case, amplitude and frequency; SI, Hz), `plots/`.", ""]
    return L


class FrequencyResponse:
    """The frequency-response campaign kind (a :class:`~experiment_runner.apps.campaigns.base.CampaignKind`)."""
    name = "frequency_response"
    test = FrequencyResponseTest
    metrics = FrequencyResponseTest.METRICS

    def reference(self, camp: Campaign, cond: Condition, rate: float) -> None:
        """No closed-loop reference: the FRFs are open-loop sine forces on the plant.

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
        None
        """
        return None          # open-loop sine forces on the plant, no closed-loop reference

    def run(self, camp: Campaign, out_dir: Path, settings: RunSettings) -> CampaignRun:
        """Run the campaign (:func:`run_frf_campaign`).

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
        return run_frf_campaign(self, camp, out_dir, settings)

    def write_results(self, cr: CampaignRun) -> None:
        """Write the results files (:func:`write_frf_results`).

        Parameters
        ----------
        cr : CampaignRun
            A frequency-response campaign as run.
        """
        write_frf_results(cr)

    def report_how(self, cr: CampaignRun) -> str:
        """How it was run (:func:`frf_how`).

        Parameters
        ----------
        cr : CampaignRun
            A frequency-response campaign as run.

        Returns
        -------
        str
        """
        return frf_how(cr)

    def report_section(self, cr: CampaignRun) -> list[str]:
        """The report's body (:func:`frf_section`).

        Parameters
        ----------
        cr : CampaignRun
            A frequency-response campaign as run.

        Returns
        -------
        list of str
            Lines of Markdown.
        """
        return frf_section(cr)

    def report_settings(self, cr: CampaignRun) -> list[str]:
        """The report's settings (:func:`frf_settings`).

        Parameters
        ----------
        cr : CampaignRun
            A frequency-response campaign as run.

        Returns
        -------
        list of str
            Lines of Markdown.
        """
        return frf_settings(cr)

    def plots(self, cr: CampaignRun, plt, out: Path) -> list:
        """The Bode and bandwidth plots (:func:`write_frf_plots`).

        Parameters
        ----------
        cr : CampaignRun
            A frequency-response campaign as run.
        plt : module
            ``matplotlib.pyplot``.
        out : pathlib.Path
            Plots folder.

        Returns
        -------
        list of pathlib.Path
        """
        return write_frf_plots(cr, plt, out)


FREQUENCY_RESPONSE = FrequencyResponse()


def frf_lines(frf_cr, settling_cr=None, images: str = "") -> list[str]:
    """Markdown: closed-loop bandwidth and margins vs force amplitude of a frequency-response
    campaign run (Fig. 4.6), next to the settling times of the point-to-point run on the same
    stage, and why the isolated stage's margins differ (rigid-body loop gain at the crossover).

    Parameters
    ----------
    frf_cr : CampaignRun
        The frequency-response campaign as run.
    settling_cr : CampaignRun, optional
        The point-to-point campaign on the same stage.
    images : str, optional
        Plots folder relative to the report ('': no images).

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = frf_cr.campaign
    cases = camp.cases
    L = [f"### Closed-loop bandwidth and margins vs force amplitude ({camp.name}, Fig. 4.6)", "",
         "The same PID on the plant FRF measured at each force amplitude (stepped sine, "
         f"[{camp.name}/report.md]({camp.name}/report.md)): the stage without isolation loses its bandwidth in "
         "the pre-motion regime (small amplitudes), which is where the point-to-point trials above settle.", "",
         "| amplitude | " + " | ".join(f"{c.label}: BW / GM / PM" for c in cases) + " |",
         "|---|" + "---|" * len(cases)]

    def cell(case, cond):
        st = frf_cr.runs[(case.name, cond.key)].stats
        v = [st[m].mean for m in ("bandwidth_hz", "gain_margin_db", "phase_margin_deg")]
        return " / ".join("–" if not math.isfinite(x) else f"{x:.3g}{u}" for x, u in zip(v, (" Hz", " dB", "°")))
    for cond in frf_cr.conditions:
        L.append(f"| {cond.label} | " + " | ".join(cell(c, cond) for c in cases) + " |")
    if settling_cr is not None:
        L += ["", "Settling times of the same cases (above): " + "; ".join(
            f"{settling_cr.campaign.case(c.name).label} {cond.label} "
            f"{settling_cr.stat(c.name, cond.key, 'settling_time_s').mean * 1e3:.1f} ms"
            for c in settling_cr.campaign.cases for cond in settling_cr.conditions
            if (c.name, cond.key) in settling_cr.runs) + "."]
    # why the isolated stage's margins are lower: above its FI mode the PID sees the table alone
    presets = {c.name: frf_cr.runs[(c.name, frf_cr.conditions[-1].key)].preset for c in cases}
    p0 = next(iter(presets.values()))
    pid = p0.controller.pid.model_dump()
    m_all = p0.stage.table.mass * (1 + sum(md.mass_ratio for md in p0.stage.modes)) + sum(
        b.mass for b in p0.stage.bearings)
    jointed = [p for p in presets.values() if any(b.joint is not None for b in p.stage.bearings)]
    if jointed:
        p = jointed[0]
        m_table = p.stage.table.mass * (1 + sum(md.mass_ratio for md in p.stage.modes)) + sum(
            b.mass for b in p.stage.bearings if b.joint is None)
        a, b = margins(m_all, pid), margins(m_table, pid)
        L += ["", f"Why the isolated stage's margins are lower: above its FI mode the bearings are decoupled and "
              f"the PID (designed on the {m_all:.3g} kg rigid stage) drives the {m_table:.3g} kg table alone, "
              f"{20 * math.log10(m_all / m_table):.1f} dB more loop gain at every frequency above the mode. "
              f"On the rigid bodies alone that moves the crossover from {a['crossover_hz']:.0f} to "
              f"{b['crossover_hz']:.0f} Hz and lowers the gain margin from {a['gain_margin_db']:.1f} to "
              f"{b['gain_margin_db']:.1f} dB (phase margin {a['phase_margin_deg']:.0f}° vs "
              f"{b['phase_margin_deg']:.0f}°): the whole gain-margin difference of the FRFs; the stiff stage's "
              "phase margin is raised instead by the friction's damping at its crossover."]
        if camp.name == "frf_fi":       # the Ch. 4 stage: the seed's Table C.1 measures the same mass ratio
            L[-1] += (" The seed's own Table C.1 has the same ratio (Z = 13.8 vs 7.9 N/(A kg), 4.8 dB), so its "
                      "'similar or slightly better' FI margins (Sec. 4.3) require No FI margins lowered by the "
                      "friction resonance's interaction with its ~400 Hz mode, which the model's appended-mass "
                      "mode (a mass on the table, independent of friction) does not have.")
    if images:
        L += [""] + [f"![{camp.name} {n}]({images}/{n}.png)" for n in ("bandwidth_margins",)]
    return L + [""]
