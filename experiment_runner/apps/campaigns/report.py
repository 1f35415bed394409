"""Plots and Markdown reports of campaign runs.

* :func:`write_plots` -- ``out_dir/plots/*.png``: the kind's plots (its
  :meth:`~experiment_runner.apps.campaigns.base.CampaignKind.plots`); for trial campaigns these
  end with the shared ones here: the distribution of every metric over the trials (box +
  strip, the seed's mean marked), the Step II learning curve (Fig. 5.9 style), the settling
  mechanism and the calibration evaluations.
* :func:`write_report` -- ``report.md``: a head, the kind's section (for trial campaigns
  :func:`trial_section`: seed vs simulation table, the direction of every seed finding in the
  simulation with the reason where it disagrees, the calibration, Step II, the ROS-graph runs),
  the plots and the settings.
* :func:`write_index` -- the main job's summary over several campaigns.

Metric names, units and formats come from :mod:`experiment_runner.apps.campaigns.registry`.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.ticker import NullFormatter

from experiment_runner.apps.campaigns import headline, mechanism
from experiment_runner.apps.campaigns.base import CampaignRun, write_json
from experiment_runner.apps.campaigns.registry import METRICS, fmt_change, fmt_metric
from experiment_runner.apps.campaigns.schema.common import fmt_length
from experiment_runner.core import outputs

__all__ = ["write_outputs", "write_plots", "write_report", "write_index", "summary_lines", "trial_section",
           "trial_plots", "report_head", "findings_table", "plots_md", "cases_md"]

def _plt():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (selected before pyplot is imported)."""
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt          # noqa: PLC0415 - pyplot needs the backend chosen first
    return plt


def colors(n):
    """Matplotlib's colour cycle names for ``n`` cases (``C0`` .. ``C9``, repeating).

    Parameters
    ----------
    n : int
        Number of cases.

    Returns
    -------
    list of str

    Examples
    --------
    >>> colors(3)
    ['C0', 'C1', 'C2']
    """
    return [f"C{i % 10}" for i in range(n)]


# =========================================================================== outputs
def write_outputs(cr: CampaignRun, *, report: bool, plots: bool, t_start: float) -> None:
    """Results files (the kind's ``write_results``), PNG plots and ``report.md``; the results are
    written first (kept if a plot fails) and again with the final timing.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.
    report : bool
        Write ``report.md``.
    plots : bool
        Write the PNG plots.
    t_start : float
        ``time.monotonic()`` at the campaign's start (total wall time).
    """
    t3 = time.monotonic()
    cr.kind.write_results(cr)
    if report:
        if plots:
            cr.files["plots"] = write_plots(cr)
        cr.timing["total_s"] = time.monotonic() - t_start
        cr.files["report"] = write_report(cr)
    cr.timing["output_s"] = time.monotonic() - t3
    cr.timing["total_s"] = time.monotonic() - t_start
    cr.kind.write_results(cr)


# =========================================================================== plots
def write_plots(cr: CampaignRun) -> list:
    """Write the PNG plots of a campaign run into ``out_dir/plots``; returns their paths.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of pathlib.Path
    """
    plt = _plt()
    out = outputs.prepare_folder(cr.out_dir / "plots")
    files = cr.kind.plots(cr, plt, out)
    plt.close("all")
    return [f for f in files if f is not None]


def trial_plots(cr: CampaignRun, plt, out: Path) -> list:
    """The plots every trial campaign ends with: the distribution of each metric, the Step II
    learning, the settling mechanism (point-to-point) and the calibration.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.
    plt : module
        ``matplotlib.pyplot``.
    out : pathlib.Path
        Plots folder.

    Returns
    -------
    list of pathlib.Path or None
    """
    camp = cr.campaign
    cols = colors(len(camp.cases))
    files = [_plot_distribution(plt, cr, metric, camp.cases, cols, out) for metric in cr.kind.metrics]
    if cr.step_ii:
        files.append(_plot_step_ii(plt, cr, out))
    files += mechanism.plot(cr, plt, out)
    if cr.calibration and cr.calibration.get("parameters"):
        files.append(_plot_calibration(plt, cr, out))
    return files


def save_figure(plt, fig, path: Path) -> Path:
    """Lay out, write ``path`` (PNG, 110 dpi), close the figure; returns ``path``.

    Parameters
    ----------
    plt : module
        ``matplotlib.pyplot``.
    fig : matplotlib.figure.Figure
        The figure.
    path : pathlib.Path
        The PNG file (written atomically).

    Returns
    -------
    pathlib.Path
    """
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def _plot_distribution(plt, cr, metric, cases, cols, out):
    label, unit, scale = METRICS[metric][:3]
    n = len(cr.conditions)
    fig, axs = plt.subplots(1, n, figsize=(max(4.0, 2.2 + 1.3 * len(cases)) * n, 4.5), squeeze=False)
    rng = np.random.default_rng(0)
    camp = cr.campaign
    for ax, cond in zip(axs[0], cr.conditions):
        data, seeds = [], []
        for case in cases:
            st = cr.runs[(case.name, cond.key)].stats[metric]
            data.append([v * scale for v in st.values if v is not None])
            s = camp.seed_value(case.name, metric, **cond.at())
            seeds.append(None if s is None else s * scale)
        pos = np.arange(1, len(cases) + 1)
        ax.boxplot([d if d else [np.nan] for d in data], positions=pos, widths=0.5, showfliers=False)
        for p, d, c in zip(pos, data, cols):
            if d:
                ax.plot(p + rng.uniform(-0.15, 0.15, len(d)), d, "o", ms=3, color=c, alpha=0.6)
        for p, s in zip(pos, seeds):
            if s is not None:
                ax.plot(p + 0.32, s, "D", color="crimson", ms=7)
        for p, case in zip(pos, cases):
            st = cr.runs[(case.name, cond.key)].stats[metric]
            if st.n_valid < st.n:
                ax.annotate(f"{st.n - st.n_valid} unsettled", (p, 0), xycoords=("data", "axes fraction"),
                            xytext=(0, 3), textcoords="offset points", ha="center", fontsize=7, color="crimson")
        ax.set_xticks(pos)
        ax.set_xticklabels([c.label for c in cases], fontsize=9)
        ax.set_title(cond.label, fontsize=10)
        ax.set_ylabel(f"{label} [{unit}]")
        ax.grid(alpha=0.3, axis="y")
    axs[0][0].plot([], [], "D", color="crimson", label="seed (mean)")
    axs[0][0].legend(fontsize=8, loc="best")
    fig.suptitle(f"{camp.title}: {label} over {camp.trials} trials", fontsize=10)
    return save_figure(plt, fig, out / f"distribution_{metric}.png")


def _plot_step_ii(plt, cr, out):
    fig, (ax0, ax1) = plt.subplots(1, 2, figsize=(11, 4))
    for name, d in cr.step_ii.items():
        label = cr.campaign.case(name).label
        h = np.array(d["rms_history_m"]) * 1e9
        ax0.plot(np.arange(h.size), h, "o-", label=label)
        u = np.asarray(d["correction"]) * 1e9
        ax1.plot(np.arange(u.size) * d["length_s"] / max(u.size, 1) * 1e3, u, label=f"{label}: u_{d['iterations']}")
    ax0.set_xlabel("iteration k")
    ax0.set_ylabel("RMS error after the switch [nm]")
    ax0.set_title("Step II learning at rest (Eq. 5.2, cf. Fig. 5.9)", fontsize=10)
    ax0.grid(alpha=0.3)
    ax0.legend(fontsize=8)
    ax1.set_xlabel("time after the compliant->stiff switch [ms]")
    ax1.set_ylabel("reference correction [nm]")
    ax1.set_title("learned correction", fontsize=10)
    ax1.grid(alpha=0.3)
    return save_figure(plt, fig, out / "step_ii.png")


def _plot_calibration(plt, cr, out):
    cal = cr.calibration
    params = cal["parameters"]
    fig, axs = plt.subplots(1, len(params), figsize=(5.2 * len(params), 4), squeeze=False)
    for ax, p in zip(axs[0], params):
        metric = p["target"]["metric"]
        unit, scale = METRICS[metric][1:3]
        prof = [q for q in p.get("profile", []) if q["metric"] is not None and math.isfinite(q["metric"])]
        if prof:
            ax.plot([q["value"] for q in prof], [q["metric"] * scale for q in prof], "o-", color="C0", ms=4,
                    label="baseline, others at their fit")
        t = p["target"]
        ax.axhline(t["seed"] * scale, color="crimson", ls="--", label="seed (baseline)")
        if t.get("form") == "quadrature_excess" and t.get("sim_after") is not None and t.get("sim_effective") is not None:
            floor = math.sqrt(max(t["sim_after"] ** 2 - t["sim_effective"] ** 2, 0.0))
            ax.axhline(math.hypot(floor, t["seed_effective"]) * scale, color="crimson", ls=":",
                       label="target: sim floor ⊕ seed excess")
        ax.axvline(p["value"], color="k", lw=0.8, label=f"fit {p['value']:.4g}")
        if p["log"]:
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
            if prof:
                ax.set_xticks([q["value"] for q in prof])
                ax.set_xticklabels([f"{q['value']:.3g}" for q in prof], fontsize=8)
        ax.set_xlabel(f"{p['name']}" + (f" [{p['unit']}]" if p["unit"] else ""))
        ax.set_ylabel(f"{METRICS[metric].label} [{unit}]")
        ax.set_title(f"fitted to {p['target']['case']} {_cond_label(p['target'])}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    return save_figure(plt, fig, out / "calibration.png")


def _cond_label(at: dict) -> str:
    parts = []
    if at.get("step") is not None:
        parts.append(f"{fmt_length(at['step'])} step")
    if at.get("radius") is not None:
        parts.append(f"R {fmt_length(at['radius'])}")
    if at.get("speed") is not None:
        parts.append(f"{fmt_length(at['speed'])}/s")
    if at.get("sweep") is not None:
        parts.append(f"sweep {at['sweep']:g}")
    return ", ".join(parts)


# =========================================================================== markdown
def _sim_cell(st, metric, baseline_cal=False):
    if st.n_valid == 0:
        return f"not settled (0/{st.n})"
    s = f"{fmt_metric(st.mean, metric)} ± {fmt_metric(st.std, metric, 2)}"
    if st.n_valid < st.n:
        s += f" ({st.n_valid}/{st.n} settled)"
    if baseline_cal:
        s += " †"
    return s


def comparison_table(cr) -> list[str]:
    """Markdown rows: condition x metric, per case seed | simulation (mean ± std).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = cr.campaign
    cal_targets = set()
    if cr.calibration and not cr.calibration.get("source"):
        for p in cr.calibration["parameters"]:
            t = p["target"]
            cal_targets.add((t["metric"], tuple(sorted((k, t[k]) for k in ("step", "radius", "speed", "sweep")
                                                       if t.get(k) is not None))))
    head = "| condition | metric | " + " | ".join(f"{c.label}: seed | {c.label}: sim" for c in camp.cases) + " |"
    sep = "|---|---|" + "---|---|" * len(camp.cases)
    lines = [head, sep]
    for cond in cr.conditions:
        for metric in cr.kind.metrics:
            cells = []
            for case in camp.cases:
                st = cr.runs[(case.name, cond.key)].stats[metric]
                seed = camp.seed_value(case.name, metric, **cond.at())
                is_cal = case.name == camp.baseline and (metric, tuple(sorted(cond.at().items()))) in cal_targets
                cells += [fmt_metric(seed, metric), _sim_cell(st, metric, is_cal)]
            lines.append(f"| {cond.label} | {METRICS[metric].label} | " + " | ".join(cells) + " |")
    return lines


def excess_notes(cr) -> list[str]:
    """Explain calibration targets fitted in the quadrature-excess form (the total cannot match).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    out = []
    cal = cr.calibration or {}
    for p in ([] if cal.get("source") else cal.get("parameters", [])):
        t = p.get("target", {})
        if t.get("form") != "quadrature_excess" or t.get("sim_after") is None or t.get("sim_effective") is None:
            continue
        m = t["metric"]
        floor = math.sqrt(max(t["sim_after"] ** 2 - t["sim_effective"] ** 2, 0.0))
        out.append(f"† {METRICS[m].label} of the baseline ({_cond_label(t)}): `{p['name']}` is fitted to its part above "
                   f"the seed's {fmt_metric(t['seed_floor'], m)} quantisation floor, in quadrature (seed "
                   f"{fmt_metric(t['seed_effective'], m)}, simulation {fmt_metric(t['sim_effective'], m)}); the "
                   f"simulated stage's own noise-free level is {fmt_metric(floor, m)} (encoder quantisation "
                   f"hunting and the integrator tail after entering the window), so the total cannot reach the "
                   f"seed's {fmt_metric(t['seed'], m)}.")
    return out


def findings_table(cr) -> list[str]:
    """Markdown table of the seed's findings: seed change, simulated change, z, agrees.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    lines = ["| finding (seed) | condition | seed change | simulation change | z | agrees |", "|---|---|---|---|---|---|"]
    for f in cr.findings:
        sim = fmt_change(f["sim_change"])
        if f.get("relative_to"):
            sim += f" (Δ reduction vs {cr.campaign.case(f['relative_to']).label})"
        if f["sim_case"] is not None and f["sim_versus"] is not None:
            sim += (f" ({'σ over the sweep ' if f.get('over') == 'sweep_spread' else ''}"
                    f"{fmt_metric(f['sim_versus'], f['metric'])} → {fmt_metric(f['sim_case'], f['metric'])})")
        seedc = fmt_change(f["seed_change"]) if f["seed_change"] is not None else "–"
        if f["direction"] == "similar":
            seedc += f" (similar, ±{f['tolerance']:.0%})"
        z = "–" if f["z"] is None else (f"{f['z']:+.1f}" if abs(f["z"]) < 1e8 else ("+∞" if f["z"] > 0 else "-∞"))
        lines.append(f"| {f['claim']} | {f['condition']} | {seedc} | {sim} | {z} | "
                     f"{'yes' if f['agrees'] else 'no'} |")
    return lines


def summary_lines(cr) -> list[str]:
    """Console summary: ``finding | seed | ours | agrees``.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines for stdout.
    """
    out = [f"{cr.campaign.title}"]
    for f in cr.findings:
        out.append(f"  {f['id']:28s} | seed {fmt_change(f['seed_change']):>6s} | ours {fmt_change(f['sim_change']):>6s}"
                   f" | {'agrees' if f['agrees'] else 'DISAGREES: ' + f['status']}")
    n = sum(f["agrees"] for f in cr.findings)
    out.append(f"  {n} of {len(cr.findings)} seed findings reproduced")
    return out


def calibration_lines(cr) -> list[str]:
    """Markdown: what was calibrated, to which seed target, and where it ended (or that nothing was).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    cal = cr.calibration
    camp = cr.campaign
    if cal is None:
        return ["No calibration: the presets' values were used for every case."]
    lines = []
    src = cal.get("source")
    if src:
        where = (f"loaded from `{src['loaded_from']}` (a calibration.json with the same fingerprint: campaign, "
                 f"baseline preset, trials)" if src.get("loaded_from") else "fitted in this run")
        lines += [f"`calibration: {{from: {src['campaign']}}}`: the values calibrated on the baseline "
                  f"({src['baseline_label']}) of campaign `{src['campaign']}` ({src['title']}) on the same stage and "
                  f"PID are applied to every case here, not refitted ({where}; cached as `calibration.json` in this "
                  f"folder, reused by the next run). Every number of this campaign is a prediction.", ""]
    elif cal.get("reused"):
        lines.append("Values reused from a previous calibration.json (not fitted in this run).")
        lines.append("")
    if not cal.get("parameters"):
        vals = ", ".join(f"`{k}` = {v:.4g}" for k, v in cal.get("values", {}).items())
        return lines + [f"Values: {vals}."]
    base_label = src["baseline_label"] if src else camp.case(camp.baseline).label
    lines += [f"Fitted on the **baseline case only ({base_label})**"
              + (f" of `{src['campaign']}`" if src else "") + f", {cal['trials']} trials per evaluation "
              f"(the first trials of the campaign: same start positions and noise seeds every evaluation); "
              f"{cal.get('method', '')}; {cal.get('evaluations', '?')} evaluations, {cal.get('rounds', '?')} round(s), "
              f"{'converged' if cal.get('converged') else 'NOT converged'}. Every other case runs with the same "
              f"values: its numbers are predictions.", "",
              "| parameter | preset value | calibrated | fitted to | seed | sim before | sim after | note |",
              "|---|---|---|---|---|---|---|---|"]
    for p in cal["parameters"]:
        t = p["target"]
        m = t["metric"]
        pv = p["preset_value"]
        unit = f" {p['unit']}" if p["unit"] else ""
        pvs = f"{pv:.4g}{unit}" if isinstance(pv, (int, float)) else str(pv)
        if p["mode"] == "scale":
            pvs = "×1"
            val = f"×{p['value']:.4g}"
        else:
            val = f"{p['value']:.4g}{unit}"
        fitted = f"{base_label} {_cond_label(t)}, {METRICS[m].label}"
        seed = fmt_metric(t["seed"], m)
        note = []
        if t["form"] == "quadrature_excess":
            fitted += " (part above the floor, in quadrature)"
            seed += f" (above {fmt_metric(t['seed_floor'], m)}: {fmt_metric(t['seed_effective'], m)})"
            note.append(f"sim excess {fmt_metric(t['sim_effective'], m)}")
        if p["at_bound"]:
            note.append(f"**at its {p['at_bound']} bound**: the target is out of reach within {p['bounds']}")
        lines.append(f"| `{p['name']}` | {pvs} | {val} | {fitted} | {seed} | {fmt_metric(t['sim_before'], m)} | "
                     f"{fmt_metric(t['sim_after'], m)} | {'; '.join(note)} |")
    lines.append("")
    for p in cal["parameters"]:
        lines.append(f"* `{p['name']}` ({', '.join('`' + x + '`' for x in p['paths'])}, {p['mode']}, bounds "
                     f"{p['bounds']}{', log' if p['log'] else ''}): {p['description'].strip()}")
        applied = "; ".join(f"{case}: " + ", ".join(f"`{k}` = {_short(v)}" for k, v in ov.items())
                            for case, ov in p["applied"].items())
        lines.append(f"  Applied: {applied}.")
    return lines


def _short(v):
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_short(x) for x in v) + "]"
    return str(v)


def report_head(camp, how: str) -> list[str]:
    """The first lines of a campaign's ``report.md``: title, description, seed, ``how`` it was
    run, seed notes.

    Parameters
    ----------
    camp : Campaign
        The campaign.
    how : str
        How it was run (the kind's ``report_how``).

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    L = [f"# {camp.title}", ""]
    if camp.description:
        L += [camp.description.strip(), ""]
    L += [f"Seed: {camp.seed.source}. Campaign file `{camp.name}`; {how}", ""]
    if camp.seed.notes:
        L += [f"Seed notes: {camp.seed.notes.strip()}", ""]
    return L


def write_report(cr: CampaignRun) -> Path:
    """``out_dir/report.md``: head, the kind's section, plots, settings.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    pathlib.Path
        The report.
    """
    L = report_head(cr.campaign, cr.kind.report_how(cr))
    L += cr.kind.report_section(cr)
    L += plots_md(cr)
    L += cr.kind.report_settings(cr)
    return outputs.write_text(cr.out_dir / "report.md", "\n".join(L))


def trial_how(cr: CampaignRun) -> str:
    """How a trial campaign was run (the report's head).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    str
    """
    camp = cr.campaign
    return (f"{camp.trials} trials per case and condition, run on the batch engine"
            + (" (representative trials also through the ROS 2 graph)" if cr.settings.get("graph") else "")
            + f"; wall time {cr.timing.get('total_s', float('nan')):.0f} s "
            f"(calibration {cr.timing.get('calibration_s', 0):.0f} s, simulation "
            f"{cr.timing.get('simulation_s', 0):.0f} s, graph {cr.timing.get('graph_s', 0):.0f} s).")


def trial_section(cr: CampaignRun) -> list[str]:
    """The body of a trial campaign's report: seed vs simulation, findings, mechanism,
    calibration, Step II, the ROS-graph runs.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = cr.campaign
    L = []
    L += ["## Seed vs simulation", "",
          "Simulation: mean ± standard deviation over the trials (SI values in `results.csv`). "
          "† = calibration target (baseline): fitted, not predicted.", ""]
    L += comparison_table(cr)
    notes = excess_notes(cr)
    if notes:
        L += [""] + notes
    L += ["", "## Findings: direction in the simulation", "",
          "Change = (case − versus) / versus of the means; z = difference / its standard error; a 'lower'/'higher' "
          "finding agrees when the sign matches and |z| ≥ 2, a 'similar' one when the change is within the tolerance.",
          ""]
    L += findings_table(cr)
    bad = [f for f in cr.findings if not f["agrees"]]
    n_ok = len(cr.findings) - len(bad)
    L += ["", f"**{n_ok} of {len(cr.findings)} seed findings reproduced.**", ""]
    if bad:
        L += ["Where the simulation disagrees:", ""]
        for f in bad:
            why = f["status"]
            extra = (" " + "; ".join(f["notes"]) + ".") if f["notes"] else ""
            L.append(f"* **{f['id']}** ({f['claim']}): {why}.{extra}"
                     + (f" {f['explanation'].strip()}" if f["explanation"] else ""))
        L.append("")
    L += mechanism.report_lines(cr)
    L += ["## Calibration", ""]
    L += calibration_lines(cr)
    L.append("")
    if cr.step_ii:
        L += ["## SAI Step II (reference correction, Sec. 5.3)", ""]
        for name, d in cr.step_ii.items():
            h = ", ".join(f"{x * 1e9:.2f}" for x in d["rms_history_m"])
            L.append(f"* {camp.case(name).label}: learned at rest over {d['iterations']} ILC iterations (Eq. 5.2, "
                     f"{d['trials']} start positions averaged per iteration, {d['length_s'] * 1e3:.0f} ms after "
                     f"each compliant→stiff switch); RMS error after the switch per iteration [nm]: {h}. "
                     f"u_{d['iterations']} is added after every switch in the point-to-point trials."
                     + (f" The learning did not reduce the error after the switch ({h0 * 1e9:.2f} -> {h1 * 1e9:.2f} nm): "
                        "in the simulation the cushioned switch at rest leaves a small, mostly non-repeatable error "
                        "(drive noise, quantisation, a short ring of the structural mode above the ILC's 200 Hz "
                        "filter), not the repeatable low-frequency error of the seed's Fig. 5.8, so u_"
                        f"{d['iterations']} is mostly learned noise."
                        if (h1 := d["rms_history_m"][-1]) >= 0.9 * (h0 := d["rms_history_m"][0]) else
                        f" The RMS error after the switch fell from {h0 * 1e9:.2f} to {h1 * 1e9:.2f} nm."))
        L.append("")
    graph_runs = [(k, rr) for k, rr in cr.runs.items() if rr.graph is not None]
    if graph_runs:
        L += ["## Representative trials through the ROS 2 graph", "",
              "The representative trial (median settling / tracking error) of every case and condition, re-run "
              "through the node graph (plant_sim, servo_controller, dither_generator, sai_manager, recorder, "
              "experiment_sequencer in one process) from a one-trial experiment file "
              "(`graph_experiments/`), recorded to MCAP (`recordings/*_graph/`); the batch engine's trial is in "
              "`recordings/*_batch/`.", "",
              "| case | condition | trial | metrics (graph) | metrics (batch) | max abs(y_graph - y_batch) | wall | ok |",
              "|---|---|---|---|---|---|---|---|"]
        for (case, key), rr in graph_runs:
            g = rr.graph
            ms = cr.kind.metrics
            gm = ", ".join(fmt_metric((g.get("metrics") or {}).get(m), m) for m in ms)
            bm = ", ".join(fmt_metric((g.get("batch_metrics") or {}).get(m), m) for m in ms)
            d = g.get("max_abs_diff_m")
            ok = g.get("done") and not g.get("aborted")
            L.append(f"| {camp.case(case).label} | {rr.cond.label} | {rr.rep} | {gm} | {bm} | "
                     f"{'–' if d is None else f'{d * 1e9:.3g} nm'} | {g.get('wall_s', 0):.1f} s | "
                     f"{'yes' if ok else 'no: ' + str(g.get('aborted') or g.get('read_error'))} |")
        L.append("")
    return L


def trial_settings(cr: CampaignRun) -> list[str]:
    """The settings at the end of a trial campaign's report.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    camp = cr.campaign
    L = ["## Settings", "",
         f"* Test: `{camp.test.model_dump()}`",
         f"* Starts: trial i at `random_starts(1, travel, {camp.starts.margin}, {camp.starts.seed} + i)`, noise seed "
         f"`simulation.seed + i` (the same in every case).", "* Cases:"]
    L += cases_md(cr)
    L += ["", "Files: `results.csv`, `results.json` (per-trial metrics too), `calibration.json`, `plots/`, "
          "`recordings/` (MCAP, rosbag2 layout).", ""]
    return L


def write_index(runs, out_dir, runtime_s: float, extras: dict | None = None) -> Path:
    """The main job's summary ``out_dir/report.md`` over several campaign runs, led by the seed's
    headline ratios (:mod:`~experiment_runner.apps.campaigns.headline`, also ``out_dir/headline.json``);
    ``extras`` maps a campaign name to Markdown lines added to its section.

    Parameters
    ----------
    runs : list of CampaignRun
        The campaigns as run.
    out_dir : str or pathlib.Path
        The main job's folder.
    runtime_s : float
        Its wall time [s].
    extras : dict, optional
        Campaign name -> Markdown lines added to its section.

    Returns
    -------
    pathlib.Path
        The summary ``report.md``.
    """
    out_dir = Path(out_dir)
    L = ["# Campaigns: seed vs simulation", "",
         f"Main job: {', '.join(cr.campaign.name for cr in runs)}; total wall time {runtime_s:.0f} s. "
         "Each campaign is calibrated on its baseline case only; everything else is a prediction. "
         "All trials on the batch engine, one representative trial per case and step size also through the "
         "ROS 2 graph.", ""]
    L += headline.report_lines(runs)
    write_json(out_dir / "headline.json", {"ratios": headline.evaluate(runs)})
    for cr in runs:
        rel = Path(cr.files["report"]).relative_to(out_dir)
        L += [f"## {cr.campaign.title}", "", f"Full report: [{rel.as_posix()}]({rel.as_posix()}); seed: "
              f"{cr.campaign.seed.source}.", ""]
        L += comparison_table(cr)
        L += [""] + excess_notes(cr) + [""]
        L += findings_table(cr)
        n = sum(f["agrees"] for f in cr.findings)
        L += ["", f"**{n} of {len(cr.findings)} seed findings reproduced.** Calibration: "
              + ("; ".join(f"`{p['name']}` = {p['value']:.4g}{(' ' + p['unit']) if p['unit'] else ''}"
                           f"{' (at bound)' if p['at_bound'] else ''}" for p in cr.calibration["parameters"])
                 if cr.calibration else "none") + ".", ""]
        bad = [f for f in cr.findings if not f["agrees"]]
        for f in bad:
            L.append(f"* {f['id']}: {f['status']}." + (f" {f['explanation'].strip()}" if f["explanation"] else ""))
        if bad:
            L.append("")
        L += mechanism.report_lines(cr, images=(rel.parent / "plots").as_posix() if cr.files.get("plots") else "")
        L += (extras or {}).get(cr.campaign.name, [])
        g = [rr.graph for rr in cr.runs.values() if rr.graph is not None]
        if g:
            ok = sum(1 for x in g if x.get("done") and not x.get("aborted"))
            dmax = max((x.get("max_abs_diff_m") or 0.0) for x in g)
            L += [f"ROS graph: {ok} of {len(g)} representative trials completed; largest difference of the measured "
                  f"position from the batch engine's trial: {dmax * 1e9:.3g} nm.", ""]
    return outputs.write_text(out_dir / "report.md", "\n".join(L))


def plots_md(cr) -> list[str]:
    """Markdown lines embedding the campaign's PNG plots (paths relative to the report).

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    L = []
    for p in cr.files.get("plots") or []:
        rel = Path(p).relative_to(cr.out_dir)
        L += [f"![{rel.stem}]({rel.as_posix()})", ""]
    return ["## Plots", ""] + L if L else []


def cases_md(cr) -> list[str]:
    """Markdown list items: every case with its preset, overrides and description.

    Parameters
    ----------
    cr : CampaignRun
        The campaign as run.

    Returns
    -------
    list of str
        Lines of Markdown.
    """
    L = []
    for case in cr.campaign.cases:
        ov = cr.runs[(case.name, cr.conditions[0].key)].overrides
        L.append(f"  * **{case.label}** (`{case.name}`): preset `{case.preset}`"
                 + (f", overrides {', '.join(f'`{k}` = {_short(v)}' for k, v in ov.items())}" if ov else "")
                 + (f". {case.description}" if case.description else ""))
    return L
