"""Plots and Markdown reports of campaigns (:mod:`experiment_runner.campaign`).

* :func:`write_plots` -- settling plots like Fig. 4.7 (position error of a representative
  trial per case, whole move and the settling portion with the ±window band), the
  distribution of every metric over the trials (box + strip, the seed's mean marked),
  in-position error spectra (Fig. 3.15 style), the Step II learning curve (Fig. 5.9 style)
  and the calibration evaluations; tracking-error plots for circle campaigns.
* :func:`write_report` -- ``report.md``: seed vs simulation table, the direction of every
  seed finding in the simulation (with the reason where it disagrees), the calibration,
  Step II, the ROS-graph runs and the settings.
* :func:`write_index` -- the main job's summary over several campaigns.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["write_plots", "write_report", "write_index", "summary_lines", "fmt_metric", "fmt_change"]

_INFO = {  # label, unit, scale
    "settling_time_s": ("settling time", "ms", 1e3),
    "rms_in_position_m": ("RMS in-position error", "nm", 1e9),
    "peak_tracking_error_m": ("peak tracking error", "µm", 1e6),
    "rms_tracking_error_m": ("RMS tracking error", "µm", 1e6),
    "bandwidth_hz": ("-3 dB closed-loop bandwidth", "Hz", 1.0),    # frequency_response (frf_campaign)
    "gain_margin_db": ("gain margin", "dB", 1.0),
    "phase_margin_deg": ("phase margin", "°", 1.0),
}


def fmt_metric(v, metric, digits=3) -> str:
    """``0.044, 'settling_time_s' -> '44 ms'``.

    >>> fmt_metric(0.0441, "settling_time_s"), fmt_metric(1.6e-9, "rms_in_position_m"), fmt_metric(None, "x")
    ('44.1 ms', '1.6 nm', '–')
    """
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    _, unit, scale = _INFO[metric]
    return f"{v * scale:.{digits}g} {unit}"


def fmt_change(r) -> str:
    """Relative change as a signed percentage.

    >>> fmt_change(-0.634), fmt_change(None)
    ('-63%', '–')
    """
    if r is None or (isinstance(r, float) and not math.isfinite(r)):
        return "–"
    return f"{r * 100:+.0f}%".replace("+-", "-")


def _metrics(cr):
    if cr.campaign.test.kind == "frequency_response":
        return ("bandwidth_hz", "gain_margin_db", "phase_margin_deg")
    return ("settling_time_s", "rms_in_position_m") if cr.campaign.test.kind == "point_to_point" \
        else ("peak_tracking_error_m", "rms_tracking_error_m")


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _colors(n):
    return [f"C{i % 10}" for i in range(n)]


# =========================================================================== plots
def write_plots(cr) -> list:
    """Write the PNG plots of a campaign run into ``out_dir/plots``; returns their paths."""
    if cr.campaign.test.kind == "frequency_response":      # Bode plots, bandwidth/margins vs amplitude
        from experiment_runner.frf_campaign import write_frf_plots
        return write_frf_plots(cr)
    plt = _plt()
    out = cr.out_dir / "plots"
    out.mkdir(exist_ok=True)
    camp = cr.campaign
    files = []
    cases = camp.cases
    cols = _colors(len(cases))
    for cond in cr.conditions:
        if camp.test.kind == "point_to_point":
            files.append(_plot_settling(plt, cr, cond, cases, cols, out))
            files.append(_plot_spectrum(plt, cr, cond, cases, cols, out))
        else:
            files.append(_plot_tracking(plt, cr, cond, cases, cols, out))
    if camp.test.kind == "circle":
        files.append(_plot_reduction(plt, cr, cases, cols, out))
    if camp.test.kind == "point_to_point" and len(camp.test.steps) > 2 and camp.sweep is None:
        files.append(_plot_vs_step(plt, cr, cases, cols, out))
    for metric in _metrics(cr):
        files.append(_plot_distribution(plt, cr, metric, cases, cols, out))
    if cr.step_ii:
        files.append(_plot_step_ii(plt, cr, out))
    from experiment_runner import mechanism
    files += mechanism.plot(cr, out)
    if cr.calibration and cr.calibration.get("parameters"):
        files.append(_plot_calibration(plt, cr, out))
    plt.close("all")
    return [f for f in files if f is not None]


def _save(plt, fig, path: Path) -> Path:
    """Lay out, write ``path`` (PNG, 110 dpi), close the figure; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


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
    return _save(plt, fig, out / f"settling_{cond.key}.png")


def _plot_spectrum(plt, cr, cond, cases, cols, out):
    from experiment_runner.metrics import error_spectrum
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
    return _save(plt, fig, out / f"spectrum_{cond.key}.png")


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
    return _save(plt, fig, out / f"tracking_{cond.key}.png")


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
    from matplotlib.ticker import NullFormatter

    from experiment_runner.campaign import fmt_length
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
            ax.set_ylabel(f"{_INFO[metric][0]} reduction vs {camp.case(camp.baseline).label} [%]")
            ax.set_title(f"R {fmt_length(r)}" + (f" (mean and ±1σ over {camp.sweep.label})" if camp.sweep else ""),
                         fontsize=9)
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7)
    fig.suptitle(camp.title, fontsize=10)
    return _save(plt, fig, out / "reduction_vs_speed.png")


def _plot_vs_step(plt, cr, cases, cols, out):
    """Mean settling time and RMS in-position error vs step size with ±1σ bands (Fig. C.1, C.12)."""
    fig, axs = plt.subplots(1, 2, figsize=(11, 4.2))
    conds = sorted(cr.conditions, key=lambda c: abs(c.step))
    x = np.array([abs(c.step) for c in conds])
    for ax, metric in zip(axs, ("settling_time_s", "rms_in_position_m")):
        label, unit, scale = _INFO[metric]
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
    return _save(plt, fig, out / "vs_step.png")


def _plot_distribution(plt, cr, metric, cases, cols, out):
    label, unit, scale = _INFO[metric]
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
    return _save(plt, fig, out / f"distribution_{metric}.png")


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
    return _save(plt, fig, out / "step_ii.png")


def _plot_calibration(plt, cr, out):
    from matplotlib.ticker import NullFormatter
    cal = cr.calibration
    params = cal["parameters"]
    fig, axs = plt.subplots(1, len(params), figsize=(5.2 * len(params), 4), squeeze=False)
    for ax, p in zip(axs[0], params):
        metric = p["target"]["metric"]
        _, unit, scale = _INFO[metric]
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
        ax.set_ylabel(f"{_INFO[metric][0]} [{unit}]")
        ax.set_title(f"fitted to {p['target']['case']} {_cond_label(p['target'])}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    return _save(plt, fig, out / "calibration.png")


def _cond_label(at: dict) -> str:
    from experiment_runner.campaign import fmt_length
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
    """Markdown rows: condition x metric, per case seed | simulation (mean ± std)."""
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
        for metric in _metrics(cr):
            cells = []
            for case in camp.cases:
                st = cr.runs[(case.name, cond.key)].stats[metric]
                seed = camp.seed_value(case.name, metric, **cond.at())
                is_cal = case.name == camp.baseline and (metric, tuple(sorted(cond.at().items()))) in cal_targets
                cells += [fmt_metric(seed, metric), _sim_cell(st, metric, is_cal)]
            lines.append(f"| {cond.label} | {_INFO[metric][0]} | " + " | ".join(cells) + " |")
    return lines


def excess_notes(cr) -> list[str]:
    """Explain calibration targets fitted in the quadrature-excess form (the total cannot match)."""
    out = []
    cal = cr.calibration or {}
    for p in ([] if cal.get("source") else cal.get("parameters", [])):
        t = p.get("target", {})
        if t.get("form") != "quadrature_excess" or t.get("sim_after") is None or t.get("sim_effective") is None:
            continue
        m = t["metric"]
        floor = math.sqrt(max(t["sim_after"] ** 2 - t["sim_effective"] ** 2, 0.0))
        out.append(f"† {_INFO[m][0]} of the baseline ({_cond_label(t)}): `{p['name']}` is fitted to its part above "
                   f"the seed's {fmt_metric(t['seed_floor'], m)} quantisation floor, in quadrature (seed "
                   f"{fmt_metric(t['seed_effective'], m)}, simulation {fmt_metric(t['sim_effective'], m)}); the "
                   f"simulated stage's own noise-free level is {fmt_metric(floor, m)} (encoder quantisation "
                   f"hunting and the integrator tail after entering the window), so the total cannot reach the "
                   f"seed's {fmt_metric(t['seed'], m)}.")
    return out


def findings_table(cr) -> list[str]:
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
    """Console summary: ``finding | seed | ours | agrees``."""
    out = [f"{cr.campaign.title}"]
    for f in cr.findings:
        out.append(f"  {f['id']:28s} | seed {fmt_change(f['seed_change']):>6s} | ours {fmt_change(f['sim_change']):>6s}"
                   f" | {'agrees' if f['agrees'] else 'DISAGREES: ' + f['status']}")
    n = sum(f["agrees"] for f in cr.findings)
    out.append(f"  {n} of {len(cr.findings)} seed findings reproduced")
    return out


def calibration_lines(cr) -> list[str]:
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
        fitted = f"{base_label} {_cond_label(t)}, {_INFO[m][0]}"
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


def write_rows_csv(path: Path, rows: list[dict]) -> None:
    """``rows`` (dicts with the same keys) as CSV, None as an empty cell."""
    import csv
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else v) for k, v in r.items()})


def report_head(camp, how: str) -> list[str]:
    """The first lines of a campaign's ``report.md``: title, description, seed, ``how`` it was
    run, seed notes."""
    L = [f"# {camp.title}", ""]
    if camp.description:
        L += [camp.description.strip(), ""]
    L += [f"Seed: {camp.seed.source}. Campaign file `{camp.name}`; {how}", ""]
    if camp.seed.notes:
        L += [f"Seed notes: {camp.seed.notes.strip()}", ""]
    return L


def write_report(cr) -> Path:
    """``out_dir/report.md``."""
    if cr.campaign.test.kind == "frequency_response":      # bandwidth/margins per amplitude table
        from experiment_runner.frf_campaign import write_frf_report
        return write_frf_report(cr)
    camp = cr.campaign
    L = report_head(camp, f"{camp.trials} trials per case and condition, run on the batch engine"
                    + (" (representative trials also through the ROS 2 graph)" if cr.settings.get("graph") else "")
                    + f"; wall time {cr.timing.get('total_s', float('nan')):.0f} s "
                    f"(calibration {cr.timing.get('calibration_s', 0):.0f} s, simulation "
                    f"{cr.timing.get('simulation_s', 0):.0f} s, graph {cr.timing.get('graph_s', 0):.0f} s).")
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
    from experiment_runner import mechanism
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
            ms = _metrics(cr)
            gm = ", ".join(fmt_metric((g.get("metrics") or {}).get(m), m) for m in ms)
            bm = ", ".join(fmt_metric((g.get("batch_metrics") or {}).get(m), m) for m in ms)
            d = g.get("max_abs_diff_m")
            ok = g.get("done") and not g.get("aborted")
            L.append(f"| {camp.case(case).label} | {rr.cond.label} | {rr.rep} | {gm} | {bm} | "
                     f"{'–' if d is None else f'{d * 1e9:.3g} nm'} | {g.get('wall_s', 0):.1f} s | "
                     f"{'yes' if ok else 'no: ' + str(g.get('aborted') or g.get('read_error'))} |")
        L.append("")
    L += plots_md(cr)
    L += ["## Settings", "",
          f"* Test: `{camp.test.model_dump()}`",
          f"* Starts: trial i at `random_starts(1, travel, {camp.starts.margin}, {camp.starts.seed} + i)`, noise seed "
          f"`simulation.seed + i` (the same in every case).", "* Cases:"]
    L += cases_md(cr)
    L += ["", "Files: `results.csv`, `results.json` (per-trial metrics too), `calibration.json`, `plots/`, "
          "`recordings/` (MCAP, rosbag2 layout).", ""]
    path = cr.out_dir / "report.md"
    path.write_text("\n".join(L))
    return path


def write_index(runs, out_dir, runtime_s: float, extras: dict | None = None) -> Path:
    """The main job's summary ``out_dir/report.md`` over several campaign runs; ``extras`` maps a
    campaign name to Markdown lines added to its section."""
    out_dir = Path(out_dir)
    L = ["# Campaigns: seed vs simulation", "",
         f"Main job: {', '.join(cr.campaign.name for cr in runs)}; total wall time {runtime_s:.0f} s. "
         "Each campaign is calibrated on its baseline case only; everything else is a prediction. "
         "All trials on the batch engine, one representative trial per case and step size also through the "
         "ROS 2 graph.", ""]
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
        from experiment_runner import mechanism
        L += mechanism.report_lines(cr, images=(rel.parent / "plots").as_posix() if cr.files.get("plots") else "")
        L += (extras or {}).get(cr.campaign.name, [])
        g = [rr.graph for rr in cr.runs.values() if rr.graph is not None]
        if g:
            ok = sum(1 for x in g if x.get("done") and not x.get("aborted"))
            dmax = max((x.get("max_abs_diff_m") or 0.0) for x in g)
            L += [f"ROS graph: {ok} of {len(g)} representative trials completed; largest difference of the measured "
                  f"position from the batch engine's trial: {dmax * 1e9:.3g} nm.", ""]
    path = out_dir / "report.md"
    path.write_text("\n".join(L))
    return path


def plots_md(cr) -> list[str]:
    """Markdown lines embedding the campaign's PNG plots (paths relative to the report)."""
    L = []
    for p in cr.files.get("plots") or []:
        rel = Path(p).relative_to(cr.out_dir)
        L += [f"![{rel.stem}]({rel.as_posix()})", ""]
    return ["## Plots", ""] + L if L else []


def cases_md(cr) -> list[str]:
    """Markdown list items: every case with its preset, overrides and description."""
    L = []
    for case in cr.campaign.cases:
        ov = cr.runs[(case.name, cr.conditions[0].key)].overrides
        L.append(f"  * **{case.label}** (`{case.name}`): preset `{case.preset}`"
                 + (f", overrides {', '.join(f'`{k}` = {_short(v)}' for k, v in ov.items())}" if ov else "")
                 + (f". {case.description}" if case.description else ""))
    return L
