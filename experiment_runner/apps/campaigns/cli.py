"""``nanostage campaign``: arguments and entry point (wired by :mod:`experiment_runner.apps.cli`)."""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from experiment_runner.apps.campaigns.base import RunSettings, clean
from experiment_runner.apps.campaigns.report import summary_lines
from experiment_runner.apps.campaigns.runner import MAIN_JOB, main_job, run_campaign
from experiment_runner.apps.campaigns.spec import list_campaigns, load_campaign
from experiment_runner.core.cliargs import positive_float, positive_int
from experiment_runner.core.executor import add_executor_arguments, default_workers
from experiment_runner.core.outputs import add_overwrite_argument
from stage_sim.config import ConfigError
from stage_sim.validation import read_text_file

__all__ = ["add_campaign_arguments", "main_campaign"]


def add_campaign_arguments(parser):
    """Add the arguments of ``nanostage campaign`` (wire with ``set_defaults(func=main_campaign)``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.

    Returns
    -------
    argparse.ArgumentParser
        ``parser``.
    """
    parser.add_argument("campaign", nargs="?", help="campaign name (see --list) or YAML path")
    parser.add_argument("--list", action="store_true", help="list the shipped campaigns")
    parser.add_argument("--main", action="store_true",
                        help=f"the main job: {' and '.join(MAIN_JOB)} end to end with --graph (always starts anew)")
    parser.add_argument("--out", default=None, help="output folder (default out/campaigns[/NAME])")
    parser.add_argument("--trials", type=positive_int, default=None, help="trials per case and condition (override)")
    parser.add_argument("--dwell", type=positive_float, default=None, help="point-to-point dwell [s] (override)")
    parser.add_argument("--graph", action="store_true",
                        help="also run the representative trial of every case and condition through the ROS graph")
    parser.add_argument("--no-calibrate", action="store_true", help="use the presets' values (no fit)")
    parser.add_argument("--calibration", default=None, metavar="JSON",
                        help="reuse the values of a calibration.json instead of fitting")
    parser.add_argument("--calibration-trials", type=positive_int, default=None,
                        help="baseline trials per fit evaluation")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    parser.add_argument("--no-mcap", action="store_true", help="skip the MCAP recordings of batch trials")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument("--json", action="store_true", help="print results.json's findings and calibration")
    add_executor_arguments(parser, "trials", default_workers(), "default: one per core; 1 = this process")
    parser.add_argument("--restart", action="store_true",
                        help="discard the trials of an interrupted run in --out (default: resume them)")
    add_overwrite_argument(parser)
    return parser


def read_calibration(path) -> dict:
    """A ``calibration.json`` written by an earlier campaign (``--calibration``).

    Parameters
    ----------
    path : str or pathlib.Path
        The file (read bounded, at most 64 MB).

    Returns
    -------
    dict
        Its content; ``values`` maps each calibrated quantity to a finite number (SI units).

    Raises
    ------
    stage_sim.config.ConfigError
        The file is missing, not JSON, or its ``values`` are not finite numbers.
    """
    try:
        doc = json.loads(read_text_file(path, "calibration", max_bytes=64 << 20))
    except ConfigError as err:
        raise ConfigError(f"--calibration {err}") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"--calibration {path}: not a calibration.json (invalid JSON: {err})") from None
    values = doc.get("values") if isinstance(doc, dict) else None
    if not isinstance(values, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in values.values()):
        raise ConfigError(f"--calibration {path}: field 'values' must map each calibrated quantity to a finite "
                          f"number (a campaign's calibration.json); got {values!r:.80}")
    return doc


def main_campaign(args) -> int:
    """Run ``nanostage campaign`` from parsed arguments.

    Parameters
    ----------
    args : argparse.Namespace
        As :func:`add_campaign_arguments` defines them.

    Returns
    -------
    int
        0 on success. Bad input raises :class:`~stage_sim.config.ConfigError` (the CLI prints it
        and exits 2).
    """
    if args.list:
        for name in list_campaigns():
            c = load_campaign(name, check_presets=False)
            print(f"{name:18s} {c.title}")
        return 0
    try:
        if args.main:
            # the main job always starts anew: its trials are regenerated in ~2 min, and a stream
            # left by other settings or code must not stop the README's first command
            path = main_job(args.out or "out/campaigns", progress=not args.quiet, workers=args.workers,
                            cluster=args.cluster, resume=False, overwrite=args.overwrite)
            print(f"report: {path}")
            return 0
        if not args.campaign:
            raise ConfigError("give a CAMPAIGN (name or YAML path), --list or --main")
        camp = load_campaign(args.campaign)
        settings = RunSettings(
            trials=args.trials, dwell=args.dwell, calibrate=not args.no_calibrate,
            calibration=read_calibration(args.calibration) if args.calibration else None,
            calibration_trials=args.calibration_trials, graph=args.graph, plots=not args.no_plots,
            mcap=not args.no_mcap, progress=not args.quiet, workers=args.workers, cluster=args.cluster,
            resume=not args.restart, overwrite=args.overwrite)
        cr = run_campaign(camp, Path(args.out or f"out/campaigns/{camp.name}"), settings)
    except KeyboardInterrupt as err:               # SIGINT, or SIGTERM (experiment_runner.core.outputs.Interrupted)
        print("nanostage campaign: interrupted; the same command resumes from the trials done "
              "(trials.jsonl in the output folder)", file=sys.stderr)
        return 128 + getattr(err, "signum", 2)
    if args.json:
        print(json.dumps(clean({"findings": cr.findings, "calibration": {
            k: v for k, v in (cr.calibration or {}).items() if k != "history"}})))
    else:
        for line in summary_lines(cr):
            print(line)
        print(f"report: {cr.files.get('report')}")
    return 0
