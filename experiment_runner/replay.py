"""Replay a recording on its topics, and recompute a run's metrics from the file alone.

* :func:`replay` republishes every message of a recording (the raw CDR bytes, so
  exactly what was recorded) with the contract QoS, and ``/clock`` at each new stage
  time, paced at ``rate`` x real time (``rate=0``: as fast as the subscribers
  acknowledge). It runs an rclpy node in its own context; the domain comes from
  ``ROS_DOMAIN_ID`` (or ``domain_id``), so a test or a lab can isolate it.
* :func:`check_metrics` recomputes, per trial, the settling time into the window given
  in the events, the RMS in-position error and the peak / RMS tracking error
  (:func:`trial_metrics`, built on :mod:`experiment_runner.metrics`) and compares them
  with what the run published on ``/experiment/results``.
* :func:`add_replay_arguments` / :func:`main_replay` are the CLI pieces
  (``nanostage replay``).
"""
from __future__ import annotations

import argparse
import json
import math
import time


from experiment_runner.metrics import METRICS, trial_metrics
from experiment_runner.recording import Recording, _load, read_recording
from msg_defs import convert
from msg_defs.topics import CLOCK, CONTRACT_TOPICS, TOPICS, Qos, qos_profile

__all__ = ["check_metrics", "replay", "add_replay_arguments", "main_replay"]



# =========================================================================== metrics
def _num(v) -> float:
    return math.nan if v is None else float(v)


def _close(a: float, b: float, rtol: float, atol: float) -> bool:
    if math.isnan(a) or math.isnan(b):
        return math.isnan(a) and math.isnan(b)
    return abs(a - b) <= atol + rtol * abs(b)


def check_metrics(recording: Recording | str, *, rtol: float = 1e-9, atol: float = 1e-15) -> dict:
    """Recompute each trial's metrics from the recording and compare with ``/experiment/results``.

    Trials come from the ``trial_start`` / ``trial_end`` events (window, and target and
    settle start where the events give them); a recording without trial events is one
    trial over all its samples. A recorded value and its recomputation agree within
    ``atol + rtol * |recorded|``; null (not settled) only agrees with nan.

    Returns
    -------
    dict
        ``trials``: one dict per trial (``trial``, ``case``, ``complete``, the recomputed
        metrics, ``recorded`` (the /experiment/results object or None) and ``mismatches``
        ``{metric: [recomputed, recorded]}``); ``compared`` (trials with recorded
        results), ``mismatched``, ``ok`` (None when nothing was recorded to compare),
        ``salvaged``.
    """
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    recorded = {}
    for r in rec.results:
        if r.get("trial") is not None:
            recorded[int(r["trial"])] = r
    trials = rec.trials()
    rows = []
    spans = ([(tr.trial, tr.case, tr.complete, tr.slice, tr.window_m, tr.target_m,
               None if tr.settle_start_ns is None else tr.settle_start_ns * 1e-9) for tr in trials]
             or [(None, None, rec.salvaged is None, slice(0, len(rec)), None, None, None)])
    compared = mismatched = 0
    for trial, case, complete, sl, window, target, start in spans:
        met = trial_metrics(rec.t[sl], rec.x_ref[sl], rec.v_ref[sl], rec.y[sl], window=window, target=target,
                            settle_start=start)
        got = recorded.get(trial) if trial is not None else None
        diffs = {}
        if got is not None:
            compared += 1
            for key in METRICS:
                if key in got and not _close(met[key], _num(got[key]), rtol, atol):
                    diffs[key] = [met[key], _num(got[key])]
            mismatched += bool(diffs)
        rows.append({"trial": trial, "case": case, "complete": complete, **met, "recorded": got,
                     "mismatches": diffs})
    return {"path": str(rec.path), "trials": rows, "compared": compared, "mismatched": mismatched,
            "ok": (mismatched == 0) if compared else None, "salvaged": rec.salvaged}


# =========================================================================== replay
def _qos_from_metadata(text: str | None) -> Qos:
    """QoS of a non-contract topic from its channel's offered_qos_profiles (default: reliable, 100)."""
    import yaml
    try:
        prof = (yaml.safe_load(text) or [{}])[0]
        depth = int(prof.get("depth") or 100)
        rel = prof.get("reliability")
        dur = prof.get("durability")
        return Qos("best_effort" if rel in ("best_effort", 2) else "reliable",
                   "transient_local" if dur in ("transient_local", 1) else "volatile", max(depth, 1))
    except Exception:                     # noqa: BLE001 - absent or foreign metadata
        return Qos(depth=100)


def replay(path, rate: float = 1.0, check: bool = False, *, domain_id: int | None = None,
           topics=None, clock: bool = True, wait_for: int = 0, wait_timeout: float = 10.0,
           node_name: str = "nanostage_replay", log=None) -> dict:
    """Republish a recording on its topics.

    Parameters
    ----------
    path : str or Path
        Recording (MCAP file or bag directory); a file cut short is replayed up to its
        last complete chunk.
    rate : float
        Speed relative to stage time (1 = real time, 2 = twice as fast); 0 = as fast as
        possible (publishers wait for their subscribers' DDS acknowledgements every 200
        messages; a subscriber whose callbacks are slower than the replay still drops
        what overflows its keep-last queue, 1000 samples on the per-sample topics).
    check : bool
        Also run :func:`check_metrics` and return it under ``"check"``.
    domain_id : int, optional
        ROS domain (default: ``ROS_DOMAIN_ID`` of the environment).
    topics : iterable of str, optional
        Only these topics (default all).
    clock : bool
        Publish ``rosgraph_msgs/Clock`` at each new log time (recorded ``/clock``
        messages are then not republished, since they carry the same time).
    wait_for : int
        Wait (up to ``wait_timeout`` s) until this many subscriptions match one of the
        contract topics (any of them) before publishing.
    log : callable, optional
        Called with progress strings.

    Returns
    -------
    dict
        ``published`` (messages per topic), ``skipped`` (topics whose type is not
        importable), ``stage_time_s``, ``wall_time_s``, ``salvaged`` and, with
        ``check``, ``check``.
    """
    import rclpy
    from rclpy.context import Context
    from rclpy.duration import Duration
    from rclpy.node import Node

    raw = _load(path)
    wanted = None if topics is None else set(topics)
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    out = {"published": {}, "skipped": {}, "salvaged": raw.salvaged}
    try:
        node = Node(node_name, context=ctx)
        pubs, names = {}, {}
        for ch in raw.channels.values():
            if (wanted is not None and ch.topic not in wanted) or (clock and ch.topic == CLOCK.name):
                continue
            schema = raw.schemas.get(ch.schema_id)
            msg_type = schema.name if schema else "?"
            try:
                cls = convert.message_class(None, msg_type)
            except (ImportError, AttributeError, ValueError) as err:
                out["skipped"][ch.topic] = f"{msg_type}: {err}"
                continue
            qos = TOPICS[ch.topic].qos if ch.topic in TOPICS else _qos_from_metadata(
                ch.metadata.get("offered_qos_profiles"))
            pubs[ch.id] = node.create_publisher(cls, ch.topic, qos_profile(qos))
            names[ch.id] = ch.topic
        clock_pub = (node.create_publisher(convert.message_class(None, CLOCK.msg_type), CLOCK.name,
                                           qos_profile(CLOCK)) if clock else None)
        if wait_for:
            watched = [p for cid, p in pubs.items() if names[cid] in CONTRACT_TOPICS] or list(pubs.values())
            deadline = time.monotonic() + wait_timeout
            while (time.monotonic() < deadline
                   and max((p.get_subscription_count() for p in watched), default=wait_for) < wait_for):
                time.sleep(0.02)
        every_pub = list(pubs.values()) + ([clock_pub] if clock_pub else [])

        def settle():
            for p in every_pub:
                p.wait_for_all_acked(Duration(seconds=5))

        counts: dict[str, int] = {}
        msgs = [m for m in raw.messages if m.channel_id in pubs]
        t0 = msgs[0].log_time if msgs else 0
        wall0 = time.monotonic()
        last = None
        for n, m in enumerate(msgs):
            if rate > 0:
                delay = wall0 + (m.log_time - t0) * 1e-9 / rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            elif n and n % 200 == 0:
                settle()
            if clock_pub is not None and m.log_time != last:
                clock_pub.publish(convert.clock_msg(None, m.log_time))
                last = m.log_time
            pubs[m.channel_id].publish(bytes(m.data))
            topic = names[m.channel_id]
            counts[topic] = counts.get(topic, 0) + 1
            if log is not None and n and n % 10000 == 0:
                log(f"replayed {n} of {len(msgs)} messages (stage time {(m.log_time - t0) * 1e-9:.3f} s)")
        settle()
        out["published"] = counts
        out["stage_time_s"] = (msgs[-1].log_time - t0) * 1e-9 if msgs else 0.0
        out["wall_time_s"] = time.monotonic() - wall0
        node.destroy_node()
    finally:
        rclpy.shutdown(context=ctx)
    if check:
        out["check"] = check_metrics(path)
    return out


# =========================================================================== CLI pieces
def add_replay_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``nanostage replay`` (wire with ``set_defaults(func=main_replay)``)."""
    parser.add_argument("path", help="recording: the MCAP file or its bag directory")
    parser.add_argument("--rate", type=float, default=1.0,
                        help="speed relative to stage time; 0 = as fast as possible (default 1)")
    parser.add_argument("--check", action="store_true",
                        help="recompute the metrics from the file and compare with /experiment/results")
    parser.add_argument("--no-publish", action="store_true", help="do not publish (with --check: only check)")
    parser.add_argument("--domain-id", type=int, default=None, help="ROS domain (default: ROS_DOMAIN_ID)")
    parser.add_argument("--topics", nargs="*", default=None, help="replay only these topics")
    parser.add_argument("--wait-for", type=int, default=0, metavar="N",
                        help="wait until N subscriptions match a contract topic before publishing")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    return parser


def _fmt(v, unit: str, scale: float) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v * scale:.4g} {unit}"


def main_replay(args) -> int:
    """Run ``nanostage replay`` from parsed arguments; 1 if the check finds a mismatch."""
    out = {}
    if not getattr(args, "no_publish", False):
        out = replay(args.path, rate=args.rate, domain_id=args.domain_id, topics=args.topics,
                     wait_for=args.wait_for, log=None if args.json else print)
    if args.check:
        out["check"] = check_metrics(args.path)
    if args.json:
        print(json.dumps(convert._clean(out)))
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
                state = ("-" if r["recorded"] is None else
                         "agrees" if not r["mismatches"] else "DIFFERS: " + ", ".join(r["mismatches"]))
                print(f"{r['trial']} | {r['case'] or '-'} | {_fmt(r['settling_time_s'], 'ms', 1e3)} | "
                      f"{_fmt(r['rms_in_position_m'], 'nm', 1e9)} | {_fmt(r['peak_tracking_error_m'], 'nm', 1e9)} | "
                      f"{_fmt(r['rms_tracking_error_m'], 'nm', 1e9)} | {state}")
    chk = out.get("check")
    return 1 if chk and chk["ok"] is False else 0
