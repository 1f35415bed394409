"""Command-line entry of ``nanostage diagnose`` (wired in :mod:`experiment_runner.apps.cli`).

:mod:`experiment_runner.apps.cli` imports this module only for the ``diagnose`` command (or the
full ``nanostage --help``), so its imports are at the top like any other module's.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from experiment_runner.core.cliargs import positive_float, positive_int
from experiment_runner.core.executor import add_executor_arguments
from experiment_runner.core.nominal_model import nominal_preset_from_doc
from experiment_runner.core.outputs import add_overwrite_argument, prepare_folder
from experiment_runner.core.recording import read_recording
from msg_defs.topics import CONFIG
from stage_sim.config import ConfigError, preset_from_dict

from .budget import DEFAULT_MAX_SECONDS
from .data import load_data
from .effects import LIBRARY
from .options import Options
from .pipeline import diagnose
from .power.cases import DEFAULT_CASES
from .power.study import run_power
from .report import REPORT_FILES, jsonable
from .selftest import run_selftest

__all__ = ["add_diagnose_arguments", "main_diagnose", "effect_keys"]


def effect_keys(text: str) -> list[str]:
    """argparse type of ``--effects``: comma-separated keys of the library of hypotheses (those
    ``--list-effects`` prints), each checked; a usage error naming the unknown ones and the keys.

    Parameters
    ----------
    text : str
        The option's value.

    Returns
    -------
    list of str
        The keys, stripped.

    Raises
    ------
    argparse.ArgumentTypeError
        An unknown key, or none.

    Examples
    --------
    >>> effect_keys("viscous, stribeck")
    ['viscous', 'stribeck']
    """
    keys = [k.strip() for k in text.split(",") if k.strip()]
    unknown = [k for k in keys if k not in LIBRARY]
    if unknown or not keys:
        raise argparse.ArgumentTypeError(f"got {text!r}; unknown effect key(s) {', '.join(map(repr, unknown))}; "
                                         f"expected comma-separated keys of: {', '.join(LIBRARY)}"
                                         if keys else f"got {text!r}; expected comma-separated effect keys")
    return keys


def add_diagnose_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the arguments of ``nanostage diagnose`` (wire with ``set_defaults(func=main_diagnose)``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.

    Returns
    -------
    argparse.ArgumentParser
        ``parser``.
    """
    parser.add_argument("recording", nargs="?", help="contract recording (MCAP file or bag directory)")
    parser.add_argument("nominal", nargs="?", help="nominal model: preset name or YAML, or model file "
                                                   "{preset}; default: the preset in the "
                                                   "recording's /experiment/config, or its nominal_model "
                                                   "block translated (experiment_runner.core.nominal_model)")
    parser.add_argument("--out", default=None, help="output folder for report.json/.md, plots, improved model "
                                                    "(default out/diagnose/<recording name>)")
    parser.add_argument("--json", action="store_true", help="print the report (or the self-test summary) as JSON")
    parser.add_argument("--list-effects", action="store_true", help="print the library of hypotheses and exit")
    parser.add_argument("--selftest", action="store_true",
                        help="concealed-data self-test: synthesise recordings with known effects and diagnose them")
    parser.add_argument("--power", action="store_true",
                        help="with --selftest: the power study (randomized concealed-effect cases and negative "
                             "controls; detection rate vs effect size, false-positive rate)")
    parser.add_argument("--cases", type=positive_int, default=None,
                        help="power study: number of cases (default 150: 45 negative controls, 15 pairs, 90 single effects)")
    parser.add_argument("--only", nargs="*", default=None, help="self-test: run only cases whose name starts so "
                                                                "(power study: whose name contains it)")
    parser.add_argument("--keep", default=None, help="self-test: keep recordings and reports in this folder")
    parser.add_argument("--effects", type=effect_keys, default=None,
                        help="comma-separated effect keys to consider (those of --list-effects; default all)")
    parser.add_argument("--bandwidth", type=positive_float, default=None,
                        help="force-observer bandwidth [Hz] (default rate/25)")
    parser.add_argument("--max-fit-seconds", type=positive_float, default=3.0, help="cap of the fit set [s of data]")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--verbose", action="store_true", help="details of every stage on stdout")
    parser.add_argument("--max-seconds", type=positive_float, default=DEFAULT_MAX_SECONDS,
                        help="wall-clock budget [s] (default %(default)g): the search stops there and keeps the "
                             "model of its last completed step; the report says what was not examined")
    parser.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_overwrite_argument(parser)
    add_executor_arguments(parser, "candidate fits", workers_help="default: threads of this process")
    return parser


def nominal_from_config(rec):
    """The nominal of the recording's ``/experiment/config`` (read by the project's YAML loader
    and validated: errors name the recording, the topic and the field): its ``preset``, or its
    ``nominal_model`` block (a rig's model in its own terms) translated
    (:mod:`experiment_runner.core.nominal_model`); None if it carries neither.

    Parameters
    ----------
    rec : experiment_runner.core.recording.Recording
        The opened recording.

    Returns
    -------
    stage_sim.config.Preset or dict or None
        The ``preset`` validated as a :class:`stage_sim.config.Preset`; else the translated
        ``nominal_model`` as a validated preset mapping (a line on stderr says so); else None.

    Raises
    ------
    stage_sim.config.ConfigError
        A ``preset`` that is not a valid preset mapping, or an invalid ``nominal_model``.
    """
    doc = rec.config_doc()
    preset = doc.get("preset")
    source = f"{rec.path}: {CONFIG.name} preset"
    if preset is not None:
        if not isinstance(preset, dict):
            raise ConfigError(f"{source}: got {type(preset).__name__}; expected a mapping (a preset)")
        return preset_from_dict(preset, source)
    preset = nominal_preset_from_doc(doc, source=str(rec.path))
    if preset is not None:
        print(f"nominal: the recording's nominal_model block, translated as preset {preset['name']!r} "
              f"(nanostage convert nominal {rec.path} --out FILE writes it)", file=sys.stderr)
    return preset


def diagnose_options(args):
    """The :class:`.options.Options` of parsed ``nanostage diagnose`` arguments.

    Parameters
    ----------
    args : argparse.Namespace
        As :func:`add_diagnose_arguments` defines them.

    Returns
    -------
    Options
    """
    return Options(bandwidth=args.bandwidth, max_fit_seconds=args.max_fit_seconds,
                   effects=args.effects,
                   plots=not args.no_plots, verbose=args.verbose, workers=args.workers, cluster=args.cluster,
                   max_seconds=args.max_seconds, progress=not args.quiet)


def main_diagnose(args) -> int:
    """Run ``nanostage diagnose`` from parsed arguments.

    A diagnosis of ``args.recording`` against its nominal, the self-test (``--selftest``), the
    power study (``--selftest --power``) or the library listing (``--list-effects``).

    Parameters
    ----------
    args : argparse.Namespace
        As :func:`add_diagnose_arguments` defines them.

    Returns
    -------
    int
        0 when a report was written (a partial one included); the self-test: 0 when every case
        passed, else 1. Bad input exits 2 with one message.
    """
    if args.list_effects:
        print(json.dumps(LIBRARY.describe(as_json=True), indent=1) if args.json else LIBRARY.describe())
        return 0
    if args.selftest and args.power:
        return _main_power(args)
    if args.selftest:
        s = run_selftest(only=args.only, as_json=args.json, keep=args.keep, verbose=args.verbose,
                         workers=args.workers, cluster=args.cluster, overwrite=args.overwrite,
                         progress=not args.quiet)
        if args.json:
            print(json.dumps(_clean(s), indent=1))
        else:
            print(f"self-test: {s['passed']}/{s['cases']} passed, {s['false_positives']} false positive(s), "
                  f"{s['negative_controls']} negative controls")
            for kind, row in s["by_profile"].items():
                print(f"  {kind:18s} {row['passed']}/{row['cases']} passed, {row['false_positives']} false positive(s)")
        return 0 if s["passed"] == s["cases"] else 1
    if not args.recording:
        raise SystemExit("nanostage diagnose: give RECORDING [NOMINAL], or --list-effects, or --selftest")
    rec = read_recording(args.recording, require_reference=False)   # not there / unreadable: no output folder made
    for w in ([f"recording {rec.salvaged}"] if rec.salvaged else []) + rec.warnings:
        print(f"warning: {w}", file=sys.stderr)         # what the reader found, before the long work
    out = Path(args.out) if args.out else Path("out/diagnose") / Path(args.recording).with_suffix("").name
    nominal = args.nominal
    if nominal is None:
        nominal = nominal_from_config(rec)
        if nominal is None:
            raise SystemExit("nanostage diagnose: the recording carries no preset (nor a nominal_model block) "
                             "in /experiment/config; give the NOMINAL model")
    data = load_data(rec)
    for e in data.incomplete:
        print(f"warning: incomplete {e} (its samples are used)", file=sys.stderr)
    for e in data.excluded:
        print(f"warning: excluded {e}", file=sys.stderr)
    prepare_folder(out, args.overwrite, files=REPORT_FILES, option="--out")     # bad input above: no folder made
    started = time.time()
    try:
        rep = diagnose(args.recording, nominal, out=out, options=diagnose_options(args), data=data)
    except KeyboardInterrupt:       # SIGINT / SIGTERM: a search it stopped left its partial report
        if _interrupted_report(out / "report.json", started):
            print(f"partial report (interrupted): {out / 'report.md'}", file=sys.stderr)
        raise
    if args.json:
        print(json.dumps(jsonable(rep), indent=1))
        return 0
    if rep["budget"]["reached"]:
        print(f"partial: {rep['budget']['statement']}")
    for line in replay_lines(rep):
        print(line)
    print(f"verdict: {rep['verdict']}")
    if data.excluded:
        print(f"excluded as damaged ({len(data.excluded)} trial(s), neither fitted nor judged):")
        for e in data.excluded:
            print(f"  {e}")
    if data.incomplete:
        print(f"incomplete trials used ({len(data.incomplete)}; their samples are data):")
        for e in data.incomplete:
            print(f"  {e}")
    for i, f in enumerate(rep["found"], 1):
        print(f"  {i}. {finding_line(f)}")
    for w in rep.get("withdrawn") or []:
        print(f"  not identified, withdrawn: {w['title']} ({w['why']})")
    for fnd in rep.get("findings") or []:
        if fnd["status"] == "located, not explained":
            w = fnd.get("where") or {}
            print(f"  {fnd['finding']}: located, not explained"
                  + (f" (most in {w['regime']['regime']})" if w.get("regime") else ""))
    dl = rep.get("detection_limits")
    if dl and not rep["found"]:
        print("  the record would have shown (smallest change, half the recordings): " + ", ".join(
            f"{d['parameter']} {d['smallest_change']:.3g} {d['unit']}" for d in dl[:6])
            + (f" ... ({len(dl)} effects: report.md)" if len(dl) > 6 else ""))
    cmd = rep["recording"].get("command")
    if cmd and cmd["kind"] != "drive":
        print(f"  command: {cmd['kind']} ({cmd['meaning']})")
    v = rep["validation"]["force_residual_rms_N"]
    fu = (rep.get("units") or {}).get("force", "N")
    if v["fall"] is not None:
        print(f"held-out force residual RMS: {v['nominal']:.4g} {fu} -> {v['improved']:.4g} {fu} "
              f"({100 * abs(v['fall']):.1f} % {'lower' if v['fall'] >= 0 else 'higher'}; floor {v['floor']:.3g} {fu})")
    dis = rep["validation"].get("disagreements") or []
    if dis:
        print(f"  {dis[0]} (why: report.md, Findings)")
    if remaining_line(rep):
        print(remaining_line(rep))
    print(f"report: {out / 'report.md'}   improved preset: {out / 'improved_preset.yaml'}   "
          f"({rep['timing_s']['total_s']:.1f} s)")
    return 0


def finding_line(f: dict) -> str:
    """One adopted effect's line on stdout: its title, each parameter with its standard error,
    unit and nominal (a parameter whose σ exceeds its value marked not determined: the effect is
    identified by its others), and its status with the rule that chose where it is confounded.

    Parameters
    ----------
    f : dict
        A row of the report's ``found``.

    Returns
    -------
    str

    Examples
    --------
    >>> finding_line({"title": "direction asymmetry", "status": "identified", "params": [
    ...     {"name": "dF_C", "value": -0.5, "sigma": 0.53, "unit": "N", "identified": False},
    ...     {"name": "dc", "value": -78.0, "sigma": 5.9, "unit": "N·s/m", "identified": True}]})
    'direction asymmetry: dF_C = -0.5 ± 0.53 N (not determined: σ above its value), dc = -78 ± 5.9 N·s/m  [identified]'
    """
    def param(p):
        err = (f" ± {p['sigma']:.2g}" if p.get("sigma") else
               f" ± {p['resolution']:g} (whole steps)" if p.get("resolution") else "")
        nominal = f" (nominal {p['nominal']:.4g})" if isinstance(p.get("nominal"), (int, float)) else ""
        weak = " (not determined: σ above its value)" if p.get("identified") is False else ""
        return f"{p['name']} = {p['value']:.4g}{err} {p['unit']}{nominal}{weak}"
    st = f.get("status", "identified")
    rule = f"; chosen by {f['chosen_by']}" if st != "identified" and f.get("chosen_by") else ""
    return f"{f['title']}: {', '.join(param(p) for p in f['params'])}  [{st}{rule}]"


def _interrupted_report(path, since: float) -> bool:
    """Whether ``path`` is a report.json written since ``since`` (epoch s) by an interrupted run."""
    try:
        if path.stat().st_mtime < since:
            return False
        b = json.loads(path.read_text()).get("budget") or {}
    except (OSError, ValueError):
        return False
    return str(b.get("stopped") or "").startswith("interrupted")


def remaining_line(rep: dict) -> str | None:
    """The stdout line of what the improved model leaves (the report's ``remaining``, its three
    largest signatures), or None when it left nothing beyond its floor.

    Parameters
    ----------
    rep : dict
        A diagnosis report (``report.json`` content).

    Returns
    -------
    str or None

    Examples
    --------
    >>> remaining_line({"remaining": {"signatures": [{"text": "line at 50 Hz", "share": 0.4}]}})
    'left, located but not explained: line at 50 Hz (40 %)'
    >>> remaining_line({}) is None
    True
    """
    left = rep.get("remaining")
    if not left:
        return None
    sigs = left.get("signatures") or []
    return "left, located but not explained: " + ("; ".join(
        f"{sg['text']} ({100 * sg['share']:.0f} %)" for sg in sigs[:3]) or "spread, no line, position signature "
        "or regime concentration (remaining.png)")


def _main_power(args) -> int:
    out = prepare_folder(Path(args.out) if args.out else Path("out/diagnose/power"), args.overwrite,
                         files=("power.json", "report.md"), option="--out")
    if args.keep:
        prepare_folder(args.keep, args.overwrite, option="--keep")
    s = run_power(args.cases or DEFAULT_CASES, workers=args.workers,
                  cluster=args.cluster, out=out, keep=args.keep, progress=not args.quiet,
                  only=args.only)
    if args.json:
        print(json.dumps(_clean(s), indent=1))
        return 0
    p = s["power"]

    def pct(x):
        return "-" if x is None else f"{100 * x:.1f} %"
    print(f"power study: {s['cases']} cases ({s['negatives']} negative controls), {s['wall_s']:.0f} s")
    print(f"  named first  {pct(p['named_first_rate'])} of {p['named_first_cases']} single effects >= 3x the floor "
          f"(goal >= 95 %)")
    print(f"  pairs        {pct(p['pair_rate'])} of {p['pair_cases']} pairs (goal >= 90 %)")
    print(f"  parameters   {pct(p['params_rate'])} within +-20 % of {p['params_cases']}")
    print(f"  false pos.   {pct(s['false_positive_rate'])} of {s['negatives']} negative controls (goal <= 5 %)")
    print(f"report: {out / 'report.md'}")
    return 0


def replay_lines(rep: dict) -> list[str]:
    """The headline: held-out closed-loop replay error, nominal -> improved, against the run-to-run
    floor (what stdout and report.md lead with).

    Parameters
    ----------
    rep : dict
        A diagnosis report (``report.json`` content).

    Returns
    -------
    list of str
        Lines, in the recording's units (``rep["units"]``).
    """
    r = rep["replay"]
    c, p = r["command_rms_N"], r["position_rms_m"]
    st = r["stable"]
    U = rep.get("units") or {}
    fu, pu = U.get("force", "N"), U.get("position", "m")
    if rep.get("recording", {}).get("open_loop"):
        how = r.get("predictor", "windows re-initialised from the measurement")
        head = [f"held-out open-loop prediction ({len(r['held_out_trials'])} trial(s), {r['held_out_samples']} samples, "
                f"{how}; the recorded command is the input):"]
    else:
        head = [f"held-out closed-loop replay ({len(r['held_out_trials'])} trial(s), {r['held_out_samples']} samples, "
                f"{r['reference']} reference):",
                f"  command error RMS  {c['nominal']:.4g} {fu} -> {c['improved']:.4g} {fu}   "
                f"(run-to-run floor {c['floor']:.3g} {fu})"]
    return head + [
            f"  position error RMS {p['nominal']:.4g} {pu} -> {p['improved']:.4g} {pu}   "
            f"(run-to-run floor {p['floor']:.3g} {pu})",
            f"  error / floor      {r['floor_ratio']['nominal']:.3g}x -> {r['floor_ratio']['improved']:.3g}x"
            + ("" if st["improved"] else "   IMPROVED MODEL UNSTABLE") + ("" if st["nominal"] else "   (nominal unstable)")]


def _clean(o):
    return jsonable(o)
