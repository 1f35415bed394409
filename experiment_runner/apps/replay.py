"""``nanostage replay``: republish a recording on its topics, and recompute a run's
metrics from the file alone.

* :func:`experiment_runner.ros.player.replay` (the ROS layer) republishes every message
  of a recording (the raw CDR bytes, so exactly what was recorded) with the contract
  QoS, and ``/clock`` at each new stage time, paced at ``rate`` x real time.
* :func:`check_metrics` recomputes, per trial, the settling time into the window given
  in the events, the RMS in-position error and the peak / RMS tracking error
  (:func:`trial_metrics`, built on :mod:`experiment_runner.core.metrics`) and compares them
  with what the run published on ``/experiment/results``.
* :func:`add_replay_arguments` / :func:`main_replay` are the CLI pieces
  (``nanostage replay``).
"""
from __future__ import annotations

import argparse
import json
import math
import sys

import numpy as np

from experiment_runner.core.metrics import METRICS, trial_metrics
from experiment_runner.core.recording import Recording, read_recording
from msg_defs import convert
from stage_sim.config import ConfigError

__all__ = ["check_metrics", "add_replay_arguments", "main_replay"]



# =========================================================================== metrics
def _num(v) -> float | None:
    """A recorded metric as a float (null: nan); None if it is not a number (text, a list)."""
    if v is None:
        return math.nan
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        return float(v)
    return None


def _close(a: float, b: float, rtol: float, atol: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= atol + rtol * abs(b)


def check_metrics(recording: Recording | str, *, rtol: float = 1e-9, atol: float = 1e-15) -> dict:
    """Recompute each trial's metrics from the recording and compare with ``/experiment/results``.

    Trials come from the ``trial_start`` / ``trial_end`` events (window, and target and
    settle start where the events give them); a recording without trial events is one
    trial over all its samples. A recorded value and its recomputation agree within
    ``atol + rtol * |recorded|``; null (not settled) only agrees with nan; a recorded value
    that is not a number never agrees. A trial the reader found incomplete or damaged
    (``Trial.problems``: aborted, cut short, samples missing, non-finite or absurd values,
    stamps going backwards) never agrees: its problems are listed.

    Returns
    -------
    dict
        ``trials``: one dict per trial (``trial``, ``case``, ``complete``, ``problems``, the
        recomputed metrics, ``recorded`` (the /experiment/results object or None) and
        ``mismatches`` ``{metric: [recomputed, recorded]}``); ``compared`` (trials with recorded
        results), ``mismatched``, ``ok`` (None when nothing was recorded to compare; False when a
        compared trial differs or has problems), ``complete`` (every trial complete, the file
        intact), ``warnings`` (the reader's, and results that could not be used), ``salvaged``.
    """
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    warnings = list(rec.warnings)
    recorded = {}
    for r in rec.results:
        trial = r.get("trial")
        if trial is None:
            continue
        if isinstance(trial, int) and not isinstance(trial, bool):
            recorded[trial] = r
        else:
            warnings.append(f"/experiment/results: message at {r['log_time_ns']} ns has trial {trial!r}, not an "
                            "integer; not compared")
    trials = rec.trials()
    rows = []
    whole = [d.text for d in rec.damage] + ([f"salvaged: {rec.salvaged}"] if rec.salvaged else [])
    spans = ([(tr.trial, tr.case, tr.problems, tr.slice, tr.window_m, tr.target_m,
               None if tr.settle_start_ns is None else tr.settle_start_ns * 1e-9) for tr in trials]
             or [(None, None, whole, slice(0, len(rec)), None, None, None)])
    compared = mismatched = 0
    for trial, case, problems, sl, window, target, start in spans:
        with np.errstate(over="ignore", invalid="ignore"):     # damaged values: listed in the trial's problems
            met = trial_metrics(rec.t[sl], rec.x_ref[sl], rec.v_ref[sl], rec.y[sl], window=window, target=target,
                                settle_start=start)
        got = recorded.get(trial) if trial is not None else None
        diffs = {}
        if got is not None:
            compared += 1
            for key in METRICS:
                if key in got:
                    value = _num(got[key])
                    if value is None or not _close(met[key], value, rtol, atol):
                        diffs[key] = [met[key], got[key] if value is None else value]
            mismatched += bool(diffs or problems)
        rows.append({"trial": trial, "case": case, "complete": not problems, "problems": list(problems), **met,
                     "recorded": got, "mismatches": diffs})
    return {"path": str(rec.path), "trials": rows, "compared": compared, "mismatched": mismatched,
            "ok": (mismatched == 0) if compared else None,
            "complete": rec.salvaged is None and all(r["complete"] for r in rows),
            "warnings": warnings, "salvaged": rec.salvaged}


# =========================================================================== CLI pieces
def _non_negative(kind):
    """argparse type: a ``kind`` (int or float) >= 0 (else a usage error, exit 2)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not value >= 0:
            raise argparse.ArgumentTypeError(f"got {text!r}; expected a number >= 0"
                                             + (" (an integer)" if kind is int else ""))
        return value
    parse.__name__ = kind.__name__
    return parse


def add_replay_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``nanostage replay`` (wire with ``set_defaults(func=main_replay)``)."""
    parser.add_argument("path", help="recording: the MCAP file or its bag directory")
    parser.add_argument("--rate", type=_non_negative(float), default=1.0,
                        help="speed relative to stage time; 0 = as fast as possible (default 1)")
    parser.add_argument("--check", action="store_true",
                        help="recompute the metrics from the file and compare with /experiment/results")
    parser.add_argument("--no-publish", action="store_true", help="do not publish (with --check: only check)")
    parser.add_argument("--domain-id", type=int, default=None,
                        help="ROS domain, 0 to 232 (default: ROS_DOMAIN_ID, else 42)")
    parser.add_argument("--topics", nargs="*", default=None, help="replay only these topics")
    parser.add_argument("--wait-for", type=_non_negative(int), default=0, metavar="N",
                        help="wait until N subscriptions match a contract topic before publishing")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    return parser


def _fmt(v, unit: str, scale: float) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v * scale:.4g} {unit}"


def main_replay(args) -> int:
    """Run ``nanostage replay`` from parsed arguments; 1 if the check finds a mismatch or an
    incomplete or damaged trial (listed, with the reader's warnings on stderr)."""
    out = {}
    if not getattr(args, "no_publish", False):
        from experiment_runner.ros.player import replay
        from experiment_runner.ros.run import check_domain_id
        try:
            check_domain_id(args.domain_id)
        except ValueError as err:
            raise ConfigError(str(err)) from None
        out = replay(args.path, rate=args.rate, domain_id=args.domain_id, topics=args.topics,
                     wait_for=args.wait_for, log=None if args.json else print)
    if args.check:
        out["check"] = check_metrics(args.path)
    if args.json:
        print(json.dumps(convert.strict_json(out)))
    else:
        if "published" in out:
            total = sum(out["published"].values())
            print(f"published {total} messages on {len(out['published'])} topics, "
                  f"{out['stage_time_s']:.4f} s of stage time in {out['wall_time_s']:.3f} s")
            for topic, why in out["skipped"].items():
                print(f"  skipped {topic}: {why}")
        if out.get("salvaged"):
            print(f"note: {out['salvaged']}")
        chk = out.get("check")
        if chk:
            if chk["salvaged"] and not out.get("salvaged"):
                print(f"note: {chk['salvaged']}")
            print("trial | case | settling | rms in-position | peak tracking | rms tracking | recorded")
            for r in chk["trials"]:
                print(f"{r['trial']} | {r['case'] or '-'} | {_fmt(r['settling_time_s'], 'ms', 1e3)} | "
                      f"{_fmt(r['rms_in_position_m'], 'nm', 1e9)} | {_fmt(r['peak_tracking_error_m'], 'nm', 1e9)} | "
                      f"{_fmt(r['rms_tracking_error_m'], 'nm', 1e9)} | {_state(r)}")
            if not chk["complete"]:
                print("INCOMPLETE: the recording has incomplete or damaged trials (their problems above; "
                      "the reader's warnings on stderr)")
    chk = out.get("check")
    if chk:
        for w in chk["warnings"]:
            print(f"warning: {w}", file=sys.stderr)
    return 1 if chk and (chk["ok"] is False or not chk["complete"]) else 0


def _state(row: dict) -> str:
    """The ``recorded`` column of a trial: agrees, DIFFERS (which metrics), and its problems."""
    parts = []
    if row["mismatches"]:
        parts.append("DIFFERS: " + ", ".join(row["mismatches"]))
    elif row["recorded"] is not None and not row["problems"]:
        parts.append("agrees")
    if row["problems"]:
        parts.append("INCOMPLETE: " + "; ".join(row["problems"]))
    return " ".join(parts) or "-"
