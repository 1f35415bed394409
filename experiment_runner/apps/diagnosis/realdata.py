"""Real measured data: ``nanostage realdata`` runs the diagnosis on every data set and reports (issue 5, item 7).

Two public data sets live in ``../shared/data`` (each folder's README says what is known):

``emps/DATA_EMPS.mat``
    The EMPS benchmark: a ball-screw positioning axis under a cascaded P/P controller.
    :mod:`.emps` converts it to a contract recording, diagnoses it from a plain nominal model
    and sets the findings against the published IDIM-LS model.

``microtribometer_reciprocating/test_data_2.txt``
    Friction against position of a reciprocating contact through 50 reversals. Not a
    positioning stage (no controller, no command, no moving mass to identify): see
    :mod:`.tribometer` for the open-loop, position-driven friction identification.

:func:`run_realdata` runs both and writes ``report.md``, ``report.json`` and PNG plots
(``nanostage realdata --out DIR``).
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from experiment_runner.core import outputs

from .datasets import DataMissing, data_root
from .emps import run_emps
from .tribometer import run_tribometer

__all__ = ["run_realdata", "main_realdata", "add_realdata_arguments", "to_markdown"]

def _strip(o):
    """JSON-able copy without private (``_``-prefixed) entries."""
    if isinstance(o, dict):
        return {k: _strip(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [_strip(v) for v in o]
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return o


def run_realdata(out, data=None, only=None, structure_check: bool = True, plots: bool = True,
                 verbose: bool = False, overwrite: bool = False) -> dict:
    """Run the diagnosis on every real data set; write ``out/report.{md,json}`` and plots.

    Parameters
    ----------
    out : str or pathlib.Path
        Output folder (``emps/`` holds the recording and the diagnosis report).
    data : str or pathlib.Path, optional
        The data folder (default: :func:`data_root`).
    only : list of str, optional
        ``["emps"]``, ``["tribometer"]`` (default both).
    structure_check : bool
        Also fit the published model structures through the diagnosis (EMPS; ~1 min).
    plots : bool
        Write the PNG plots.
    verbose : bool
        Print the diagnosis's steps.
    overwrite : bool
        ``out`` may be a folder nanostage did not write (:func:`experiment_runner.core.outputs.prepare_folder`).

    Returns
    -------
    dict
        The report: ``datasets`` (per data set), ``seconds``, and ``json`` (its JSON-able form).

    Raises
    ------
    DataMissing
        A data set is not where it should be.
    """
    root = data_root(data)
    out = outputs.prepare_folder(out, overwrite, files=("report.json", "report.md"), option="--out")
    T0 = time.perf_counter()
    rep = {"nanostage_realdata": 1, "data_root": str(root), "datasets": {}}
    if not only or "emps" in only:
        rep["datasets"]["emps"] = run_emps(root, out / "emps", structure_check=structure_check, plots=plots,
                                           verbose=verbose)
    if not only or "tribometer" in only:
        rep["datasets"]["tribometer"] = run_tribometer(root, out / "tribometer", plots=plots)
    rep["seconds"] = time.perf_counter() - T0
    clean = _strip(rep)
    outputs.write_text(out / "report.json", json.dumps(clean, indent=1))
    outputs.write_text(out / "report.md", to_markdown(clean))
    rep["json"] = clean
    return rep


def _pm(q: dict, nd: int = 2) -> str:
    s = f"{q['value']:.{nd}f}"
    return s + (f" ± {q['sigma']:.{nd}f}" if q.get("sigma") else "")


def _dev(v: float, ref: float) -> str:
    return f"{100 * (v / ref - 1):+.1f} %"


def to_markdown(rep: dict) -> str:
    """The realdata report (``rep`` as written to ``report.json``).

    Parameters
    ----------
    rep : dict
        :func:`run_realdata`'s report.

    Returns
    -------
    str
        Markdown.
    """
    L = ["# Diagnosis on real data", "", f"Data: `{rep['data_root']}`. Total {rep['seconds']:.0f} s.", ""]
    e = rep["datasets"].get("emps")
    if e:
        diag = e["runs"]["diagnosis"]
        q = diag["quantities"]
        P, A = e["published"], e["published_asymmetric"]
        idim = e["idim_ls_recomputed"]
        L += ["## EMPS (positioning axis, closed loop, 1 kHz, 24.8 s)", "",
              f"Converted to `{e['conversion']['recording']}` ({e['conversion']['samples']} samples; command and "
              f"position identical to the source: max diff {e['conversion']['max_abs_command_diff_N']:.2g} N, "
              f"{e['conversion']['max_abs_position_diff_m']:.2g} m). The README's control law reproduces the "
              f"recorded drive input to {100 * e['conversion']['controller_law_rel_error']:.2f} % (relative RMS).", "",
              f"Nominal: `{Path(e['nominal']['file']).name}`: rigid {e['nominal']['mass_kg']:g} kg, no friction, "
              "no offset. The diagnosis (effect library, forward selection on held-out data, joint fit) found: "
              f"**{', '.join(diag['found'])}** ({diag['verdict']}, {diag['seconds']:.0f} s). "
              f"Full report: `{e['diagnosis_report']}`.", "",
              "Options: the defaults of `nanostage diagnose` (the same path as the CLI).", "",
              "| quantity | published (IDIM-LS) | published asym. | diagnosis (± 1σ) | vs published | IDIM-LS recomputed here |",
              "|---|---|---|---|---|---|"]
        rows = [("M [kg]", "M", P["M"]["value"], A["M"]), ("Fc [N]", "Fc", P["Fc"]["value"], None),
                ("Fv [N·s/m]", "Fv", P["Fv"]["value"], None),
                ("offset [N] (equivalent)", "offset_equivalent", P["offset"]["value"], None),
                ("Fc+ [N]", "Fc+", None, A["Fc+"]), ("Fc- [N]", "Fc-", None, A["Fc-"]),
                ("Fv+ [N·s/m]", "Fv+", None, A["Fv+"]), ("Fv- [N·s/m]", "Fv-", None, A["Fv-"])]
        for lab, k, pv, av in rows:
            ref = pv if pv is not None else av
            rc = idim["symmetric"]["values"].get(k.replace("offset_equivalent", "offset"),
                                                   idim["asymmetric"]["values"].get(k))
            L.append(f"| {lab} | {'' if pv is None else f'{pv:g}'} | {'' if av is None else f'{av:g}'} | "
                     f"{_pm(q[k])} | {_dev(q[k]['value'], ref)} | {'' if rc is None else f'{rc:.2f}'} |")
        L += ["", "Fc is the Coulomb level averaged over the recorded travel (the diagnosis may find it position "
              "dependent); `offset (equivalent)` is the found offset plus the direction-independent part of the "
              "asymmetric friction while moving, i.e. what a symmetric model calls offset. While moving, a constant "
              "offset and a Coulomb asymmetry are the same force (they differ only at rest), so when both are found "
              "Fc+ and Fc- are individually less certain than their sum and the equivalent offset.", ""]
        if diag["unmapped"]:
            L += [f"Also found, outside the benchmark's rigid model (left out of the cascaded replay): "
                  f"{', '.join(diag['unmapped'])} (parameters in the diagnosis report).", ""]
        oc = diag["offset_candidates"]
        if oc:
            L.append("Constant offset as a hypothesis during the selection: " + "; ".join(
                f"step {c['step']}: {c['offset_N']:+.2f} N ({'accepted' if c['accepted'] else 'not chosen, winner ' + str(c['step_winner'])})"
                for c in oc) + f" (published {P['offset']['value']:+.2f} N).")
            L.append("")
        for key, title in (("published_structure", "published structure (mass, Coulomb, viscous, offset)"),
                           ("published_structure_asymmetric", "published asymmetric structure (mass, Coulomb, viscous, asymmetry)")):
            r = e["runs"].get(key)
            if r:
                qq = r["quantities"]
                L.append(f"Diagnosis restricted to the {title}: found {', '.join(r['found'])}; " + ", ".join(
                    f"{k} {_pm(qq[k])}" for k in ("M", "Fc", "Fv", "offset", "Fc+", "Fc-", "Fv+", "Fv-")) + ".")
                L.append("")
        L += ["Held-out validation and closed-loop replay (benchmark cascaded loop, `stage_control.cascaded`; "
              "held out: " + e["held_out"] + "):", "",
              "| model | force residual RMS held out [N] | replay force rel. error (all / held) | replay position rel. error |",
              "|---|---|---|---|"]
        val = diag["validation"]["force_residual_rms_N"]
        for k, r in e["closed_loop_replay"].items():
            fr = {"nominal": val["nominal"], "diagnosis": val["improved"]}.get(k)
            frs = f"{fr:.2f}" if fr is not None else ""
            L.append(f"| {k} | {frs} | {100 * r['force_rel_error']:.2f} % / {100 * r['force_rel_error_held']:.2f} % | "
                     f"{100 * r['position_rel_error']:.4f} % |")
        L += ["", f"README (benchmark's own simulation of the published model): position 0.014 %, force 5.8 %. "
              f"IDIM-LS recomputed here: relative error {100 * idim['symmetric']['relative_error']:.2f} % "
              f"(asymmetric {100 * idim['asymmetric']['relative_error']:.2f} %).", ""]
        for p in e.get("plots", []):
            L.append(f"![{p}](emps/{p})")
        L.append("")
    t = rep["datasets"].get("tribometer")
    if t:
        L += ["## Reciprocating micro-tribometer (friction vs position, 5 N)", "",
              "Not a positioning stage (no controller, no command, no mass): an open-loop, position-driven "
              "identification of the project's friction models (`stage_sim.friction`), each driven by the measured "
              f"displacement history, fitted on two of three strokes, judged on the held-out ones ({t['split']}; "
              f"{t['reversals']} reversals, normal load {t['normal_force_N']:.3f} N).", "",
              "| model | params | RMS fit [N] | RMS held out [N] | held out, transition part [N] | x_zero [mm] | x_80 [mm] | mu_C |",
              "|---|---|---|---|---|---|---|---|"]
        for k, m in t["models"].items():
            L.append(f"| {'**' + k + '**' if k == t['winner'] else k} | {m['n_params']} | {m['rms_fit_N']:.3f} | "
                     f"{m['rms_held_N']:.3f} | {m['rms_held_transition_N']:.3f} | "
                     f"{1e3 * (m['transition_held']['x_zero_m'] or float('nan')):.3f} | "
                     f"{1e3 * (m['transition_held']['x_80_m'] or float('nan')):.3f} | {m['mu_C']:.3f} |")
        mt = t["measured_transition_held"]
        L += ["", f"Measured on the held-out strokes: x_zero {1e3 * mt['x_zero_m']:.3f} mm, x_80 {1e3 * mt['x_80_m']:.3f} mm "
              f"(README ≈ 0.06 and ≈ 0.10 mm); sliding level (> 0.15 mm after a reversal) {t['sliding_level_N']:.3f} N "
              f"= {t['sliding_level_N'] / t['normal_force_N']:.3f} × normal load; median |F/N| while moving "
              f"{t['mu_moving_median']:.3f} (README: median |mu| while sliding ≈ 0.43).",
              "", f"Winner on held-out strokes: **{t['winner']}**. Parameters:", ""]
        for k, m in t["models"].items():
            L.append(f"* {k}: " + ", ".join(f"{p['name']} = {p['value']:.4g} {p['unit']}" for p in m["params"]
                                            if not (k == 'gms' and p['value'] == 0)))
        L.append("")
        for p in t.get("plots", []):
            L.append(f"![{p}](tribometer/{p})")
    return "\n".join(L) + "\n"


# --------------------------------------------------------------------------- command line
def add_realdata_arguments(parser):
    """Add the arguments of ``nanostage realdata`` (wire with ``set_defaults(func=main_realdata)``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.

    Returns
    -------
    argparse.ArgumentParser
        ``parser``.
    """
    parser.add_argument("--out", default="out/realdata", help="output folder (report.md, report.json, plots)")
    parser.add_argument("--data", default=None, help="data folder (default ../shared/data or $NANOSTAGE_DATA)")
    parser.add_argument("--only", nargs="*", choices=["emps", "tribometer"], default=None, help="data sets to run")
    parser.add_argument("--no-structure-check", action="store_true",
                        help="EMPS: skip the diagnosis restricted to the published model structures")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--json", action="store_true", help="print report.json")
    parser.add_argument("--verbose", action="store_true", help="progress of the diagnosis on stdout")
    outputs.add_overwrite_argument(parser)
    return parser


def main_realdata(args) -> int:
    """Run ``nanostage realdata`` from parsed arguments.

    Parameters
    ----------
    args : argparse.Namespace
        As :func:`add_realdata_arguments` defines them.

    Returns
    -------
    int
        0 when the reports were written; 2 when the data are missing (one message on stderr).
    """
    try:
        rep = run_realdata(args.out, data=args.data, only=args.only, structure_check=not args.no_structure_check,
                           plots=not args.no_plots, verbose=args.verbose, overwrite=args.overwrite)
    except DataMissing as err:                     # a user error: the message and exit 2, as every command
        print(f"nanostage realdata: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(rep["json"], indent=1))
    else:
        print(f"{Path(args.out) / 'report.md'} ({rep['seconds']:.0f} s)")
    return 0
