"""The design advisor's report: ``design.md``, ``design.json``, the PNG maps and the tables of stdout."""
from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path
from typing import Optional

import numpy as np

from experiment_runner.core import outputs
from stage_control import isolator

from .advice import Advice
from .van import VanCheck


def _jsonable(o):
    """numpy/dataclass tree -> JSON types; non-finite floats -> None."""
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, (list, tuple, np.ndarray)):
        return [_jsonable(v) for v in (o.tolist() if isinstance(o, np.ndarray) else o)]
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (int, np.integer)):
        return int(o)
    if isinstance(o, (float, np.floating)):
        return float(o) if math.isfinite(o) else None
    return o


def advice_dict(a: Advice) -> dict:
    """JSON-ready summary of an :class:`Advice` with its sweep maps (SI units)."""
    sw = a.sweep
    pts = {name: None if p is None else asdict(p) for name, p in (
        ("recommended", a.recommended), ("fastest_feasible", a.fastest_feasible),
        ("preset_design", a.preset_design))}
    return _jsonable(dict(
        preset=a.preset, ok=a.ok, rms_required_m=a.rms_required_m, rule=a.rule, message=a.message, **pts,
        nofi=a.nofi, lumped=asdict(sw.lumped),
        test=dict(step_m=sw.moves.step, window_m=sw.moves.window, dwell_s=sw.moves.dwell,
                  n_trials=sw.moves.n_trials, start_positions_m=sw.moves.x0, seeds=sw.moves.seeds),
        grid=dict(k_fi=sw.k_grid, c_fi=sw.c_grid, feasible=a.feasible, settled=sw.settled,
                  settling_time_s=sw.ts_mean, rms_in_position_m=sw.rms_mean, ge_norm=sw.ge, gd_norm=sw.gd,
                  ge_norm_nofi=sw.ge_nofi, gd_norm_nofi=sw.gd_nofi),
        runtime_s=sw.runtime_s))


def _fmt(v, scale=1.0, spec=".3g"):
    return "—" if v is None or not math.isfinite(v) else format(v * scale, spec)


def advice_table(a: Advice) -> list[list[str]]:
    """Rows (header first) comparing the recommendation, the fastest feasible point, the preset's own
    FI and No FI."""
    head = ["design", "k_fi [N/m]", "k_fi/bearing [N/m]", "c_fi [N·s/m]", "settling [ms]", "RMS in-pos [nm]",
            "ζ_fi", "‖G_e‖ [√Hz]", "‖G_d‖ [µm/(N·√Hz)]", "η = k_fi/k_f", "γ Dahl-GMS [N]", "κ Eq. 4.2",
            "settling vs No FI"]
    rows = [head]
    for lab, p in (("recommended", a.recommended), ("fastest feasible", a.fastest_feasible),
                   (f"{a.preset} as is", a.preset_design)):
        if p is None:
            rows.append([lab, "none meets the requirement"] + [""] * (len(head) - 2))
            continue
        red = p.settling_reduction_vs_nofi
        rows.append([lab, _fmt(p.k_fi), _fmt(p.k_fi_per_bearing), _fmt(p.c_fi), _fmt(p.settling_time_s, 1e3, ".1f"),
                     _fmt(p.rms_in_position_m, 1e9, ".2f"), _fmt(p.zeta_fi, 1, ".2g"), _fmt(p.ge_norm),
                     _fmt(p.gd_norm, 1e6),
                     _fmt(p.eta), _fmt(p.gamma_n), _fmt(p.kappa, 1, ".2g"),
                     "—" if not math.isfinite(red) else f"{-100 * red:+.0f} %"])
    n = a.nofi
    rows.append(["No FI (rigid)", "∞", "∞", "—", _fmt(n["settling_time_s"], 1e3, ".1f"),
                 _fmt(n["rms_in_position_m"], 1e9, ".2f"), "—", _fmt(a.sweep.ge_nofi), _fmt(a.sweep.gd_nofi, 1e6),
                 "∞", "—", "1", f"{n['settled']}/{n['trials']} settled"])
    return rows


def text_table(rows) -> str:
    """Rows (header first) as plain text in aligned columns."""
    w = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    return "\n".join("  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows)


def _md_table(rows) -> str:
    return "\n".join(["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
                     + ["| " + " | ".join(r) + " |" for r in rows[1:]])


def van_rows(v: VanCheck) -> list[list[str]]:
    """(quantity, value, seed) rows of a :class:`VanCheck`; seed values from Sec. 3.3/3.4.3, Table 3.2."""
    return [["quantity", "ours", "seed prototype (Sec. 3.3, 3.4.3)"],
            ["dither amplitude / frequency", f"{v.dither_amplitude_n:g} N / {v.dither_frequency_hz:g} Hz",
             "15 N p-p at 500 Hz (Sec. 3.4.1)"],
            ["piezo voltage V_pp", f"{v.v_pp:.1f} V", "20 V"],
            ["power per piezo (Eq. 3.7)", f"{v.power_per_piezo_w:.3f} W", "0.3 W"],
            [f"total power ({v.n_piezos} piezos)", f"{v.power_total_w:.3f} W", "0.6 W"],
            ["heat (10 %) / per 250 ms move", f"{v.heat_w:.3f} W / {v.heat_per_move_j:.4f} J", "< 0.06 W / 0.015 J"],
            ["worst-case load (piezo at V_max)", f"{v.max_load_n:.1f} N", "77 N"],
            ["d_e (Eq. 3.6)", f"{v.d_e * 1e3:.2f} mm", "3.52 mm"],
            ["p_a (Eq. 3.5) / p_b (Eq. 3.6)", f"{v.p_a:.3f} / {v.p_b:.3f}", "0.86 / 1.08"],
            ["S_e (Eq. 3.4)", f"{v.s_e / 1e6:.1f} MPa", "195.4 MPa"],
            ["S_max worst case / at dither peak", f"{v.s_max / 1e6:.1f} / {v.s_dither / 1e6:.1f} MPa", "47 MPa (43 in text)"],
            ["fatigue safety S_e/S_max", f"{v.fatigue_safety:.2f}", "195.4/47 = 4.16"],
            ["yield safety S_y/S_max", f"{v.yield_safety:.2f}", "4.8 (207/43)"],
            ["verdict", "PASS" if v.passed else "FAIL", "infinite life"]]


def _edges(g):
    lg = np.log10(g)
    mid = (lg[1:] + lg[:-1]) / 2
    d0 = (lg[1] - lg[0]) / 2 if g.size > 1 else 0.5
    d1 = (lg[-1] - lg[-2]) / 2 if g.size > 1 else 0.5
    return 10 ** np.concatenate([[lg[0] - d0], mid, [lg[-1] + d1]])


def _c_plot(g):
    """c_fi grid for log axes (c = 0 drawn at a tenth of the next value)."""
    g = np.asarray(g, float).copy()
    if g[0] <= 0:
        g[0] = g[1] / 10 if g.size > 1 else 1.0
    return g


def _markers(ax, a: Advice):
    for p, style, lab in ((a.recommended, "r*", "recommended"), (a.fastest_feasible, "wD", "fastest feasible"),
                          (a.preset_design, "kX", f"{a.preset} as is")):
        if p is not None:
            ax.plot(p.k_fi, max(p.c_fi, _c_plot(a.sweep.c_grid)[0]), style, ms=11 if style == "r*" else 7,
                    mec="k", label=lab)


def _map_axes(ax, a: Advice, k_grid, c_grid) -> None:
    """Requirement contour, markers, log axes and labels of one k_fi x c_fi map."""
    if a.feasible.any() and not a.feasible.all():
        ax.contour(k_grid, c_grid, a.feasible.T.astype(float), levels=[0.5], colors="r", linewidths=1.5)
    _markers(ax, a)
    ax.set_xscale("log"), ax.set_yscale("log")
    ax.set_xlabel("k_fi, stage total [N/m]"), ax.set_ylabel("c_fi, stage total [N·s/m]")


def _save_maps(fig, axes, path: Path) -> Path:
    """Legend on the right map, save, close; returns ``path``."""
    import matplotlib.pyplot as plt
    axes[1].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    outputs.savefig(fig, path, dpi=110)
    plt.close(fig)
    return path


def write_plots(a: Advice, out: Path) -> list[Path]:
    """PNG maps of the sweep (RMS in-position, settling, ||G_e||, ||G_d||) and γ(η)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    sw, files = a.sweep, []
    cg = _c_plot(sw.c_grid)
    ke, ce = _edges(sw.k_grid), _edges(cg)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, M, lab in ((axes[0], sw.rms_mean * 1e9, "mean RMS in-position error [nm]"),
                       (axes[1], sw.ts_mean * 1e3, f"mean settling time into ±{sw.moves.window * 1e9:g} nm [ms]")):
        ax.set_facecolor("0.75")
        Mm = np.ma.masked_invalid(M)
        norm = LogNorm(Mm.min(), Mm.max()) if Mm.count() and Mm.min() > 0 else None
        pc = ax.pcolormesh(ke, ce, Mm.T, cmap="viridis", shading="flat", norm=norm)
        fig.colorbar(pc, ax=ax, label=lab + " (grey: not settled)")
        _map_axes(ax, a, sw.k_grid, cg)
    axes[0].set_title(f"{a.preset}: {sw.moves.step * 1e6:g} µm steps, {sw.moves.n_trials} trials/point; "
                      f"red: requirement {a.rms_required_m * 1e9:g} nm", fontsize=9)
    files.append(_save_maps(fig, axes, out / "design_maps.png"))

    lp = sw.lumped
    kf = np.logspace(np.log10(sw.k_grid[0]), np.log10(sw.k_grid[-1]), 61)
    cf = np.logspace(np.log10(cg[0]), np.log10(cg[-1]), 41)
    E, D, e0, d0 = isolator.norm_maps(lp.m_t, lp.m_b, lp.pid, lp.k_f, lp.c_f, kf, cf)
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, M, ref, lab in ((axes[0], E, e0, "||G_e||_[1,50 Hz] / No FI (Eq. 6.1: settling)"),
                            (axes[1], D, d0, "||G_d||_[1,500 Hz] / No FI (Eq. 6.3: in-position)")):
        cs = ax.contourf(kf, cf, (M / ref).T, levels=30, cmap="viridis")
        ax.contour(kf, cf, (M / ref).T, levels=10, colors="w", linewidths=0.4)
        fig.colorbar(cs, ax=ax, label=lab)
        _map_axes(ax, a, sw.k_grid, cg)
    axes[0].set_title(f"Fig. 6.2 model: m_t = {lp.m_t:.2f} kg, m_b = {lp.m_b:.2f} kg, k_f = {lp.k_f:.3g} N/m, "
                      f"c_f = {lp.c_f:.0f} N·s/m", fontsize=9)
    files.append(_save_maps(fig, axes, out / "design_norms.png"))

    etas = np.logspace(-3, 1, 41)
    gam, bias, _ = isolator.gamma_curve(etas, lp.k_f, lp.f_c, lp.gms_k, lp.gms_alpha)
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.semilogx(etas, gam, "k-", label="γ: RMS(F_Dahl − F_GMS), one 5 mm circle cycle")
    for p, style, lab in ((a.recommended, "r*", "recommended"), (a.preset_design, "kX", f"{a.preset} as is")):
        if p is not None:
            ax.semilogx(p.eta, p.gamma_n, style, ms=11, mec="k", label=f"{lab}: η = {p.eta:.3g}, γ = {p.gamma_n:.3g} N")
    ax2 = ax.twinx()
    ax2.loglog(etas, isolator.kappa_eq42(etas), "b:")
    ax2.set_ylabel("κ = (η/(1+η))², Eq. 4.2 (dotted)", color="b")
    ax.axvspan(0.05, 0.1, color="0.9", label="seed optimum 0.05-0.1 (Sec. 6.4.2)")
    ax.set_xlabel("η = k_fi / k_f"), ax.set_ylabel("γ [N]")
    ax.set_title(f"FF accuracy, Dahl vs GMS ({lp.gms_source}), k_f = {lp.k_f:.3g} N/m", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    files.append(outputs.savefig(fig, out / "design_gamma.png", dpi=110))
    plt.close(fig)
    return files


def write_report(out, advice: Optional[Advice] = None, van: Optional[VanCheck] = None,
                 plots: bool = True, overrides=()) -> dict:
    """Write ``design.md``, ``design.json`` and (FI) the PNG plots to ``out``; returns the paths.
    ``overrides``: the ``PATH=VALUE`` preset overrides used, recorded in both files."""
    out = outputs.prepare_folder(out)
    doc, md, files = {"overrides": list(overrides)}, ["# Design advisor (`nanostage design`)", ""], {}
    if overrides:
        md += ["Preset overrides: " + ", ".join(f"`{o}`" for o in overrides), ""]
    if advice is not None:
        sw = advice.sweep
        doc["isolator"] = advice_dict(advice)
        md += [f"## Friction isolator: {advice.preset}, required RMS in-position error "
               f"{advice.rms_required_m * 1e9:g} nm", "",
               f"**{'OK' if advice.ok else 'NO DESIGN'}**: {advice.message}", "",
               f"Rule: {advice.rule}.", "",
               f"Test: {sw.moves.step * 1e6:g} µm point-to-point moves, {sw.moves.n_trials} trials per grid point "
               f"(random starts, own noise seeds), settling into ±{sw.moves.window * 1e9:g} nm within a "
               f"{sw.moves.dwell:g} s dwell; grid {sw.k_grid.size} k_fi × {sw.c_grid.size} c_fi (stage totals, split "
               f"over {sw.lumped.n_joints} bearings); {sw.runtime_s:.1f} s.", "",
               _md_table(advice_table(advice)), "",
               f"γ: Sec. 6.4.2 RMS difference of FI+Dahl and FI+GMS friction over one 5 mm circle cycle "
               f"({sw.lumped.gms_source}); κ: Eq. 4.2 sensitivity of k_c to k_f (robust FF for η < 0.1).", ""]
        if plots:
            paths = write_plots(advice, out)
            files["plots"] = [str(p) for p in paths]
            md += [f"![{p.stem}]({p.name})" for p in paths] + [""]
    if van is not None:
        doc["van"] = _jsonable(asdict(van))
        md += [f"## VAN: {van.preset}", "", f"**{van.message}**", "", _md_table(van_rows(van)), "",
               "Piezo: P-842.10 (15 µm at 100 V, 300 N blocking, 1.5 µF: the capacitance Eq. 3.7 needs for the "
               "seed's 0.3 W at 20 V, 500 Hz). Stress linear in load from Table 3.2's 47 MPa at 77 N. Our S_e "
               "uses the unrounded Marin factors (Table 3.2's 195.4 MPa uses p_a = 0.86, p_b = 1.08).", ""]
    files["markdown"] = str(out / "design.md")
    files["json"] = str(out / "design.json")
    outputs.write_text(out / "design.md", "\n".join(md))
    outputs.write_text(out / "design.json", json.dumps(doc, indent=1, allow_nan=False))
    return files
