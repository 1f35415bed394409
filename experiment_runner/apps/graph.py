"""``nanostage graph``: run an experiment through the ROS 2 node graph and record it.

One process (all nodes under one executor) or, with ``processes=True``, one process
per node (the console scripts ``plant_sim``, ``servo_controller``, ...), always on an
explicit ROS domain with localhost-only discovery; the nodes and how they are started
are the ROS layer's (:mod:`experiment_runner.ros`). The run is recorded to
``<out>/run.mcap``, its trial results are printed, and the exit code says how it went.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

from experiment_runner.core import outputs
from experiment_runner.core.experiment import load_experiment
from experiment_runner.core.recording import bag_layout, read_recording
from experiment_runner.ros.launch import EXIT_ABORTED, EXIT_RECORDING_CUT, EXIT_TIMEOUT, run_one_process, run_processes
from experiment_runner.ros.run import check_domain_id
from stage_sim.config import ConfigError

__all__ = ["run_graph", "check_run"]


def run_graph(experiment: str, out_dir: Path, processes: bool = False, domain_id=None,
              timeout: float = 3600.0, params: dict | None = None, overwrite: bool = False) -> int:
    """``nanostage graph``: run, record ``out_dir/run.mcap``, print the trial results.

    The recording of a previous run in ``out_dir`` is removed first (nanostage's files only,
    :mod:`experiment_runner.core.outputs`; ``overwrite``: ``out_dir`` may be a non-empty folder
    nanostage did not write). ``params``: ``{node: {parameter: value}}``. Returns 0 (every
    trial complete, recording intact), :data:`EXIT_ABORTED`, :data:`EXIT_TIMEOUT` or
    :data:`EXIT_RECORDING_CUT`.
    """
    import json

    check_run(experiment, out_dir, domain_id, timeout, overwrite)   # bad input: a ConfigError before any node starts
    bag = out_dir / "run"
    _clear_previous_run(out_dir)
    t0 = time.monotonic()
    if processes:
        code = run_processes(experiment, bag, timeout, domain_id, params=params)
    else:
        summary = run_one_process(experiment, bag, timeout, domain_id, params=params)
        code = 0 if summary["done"] and not summary["aborted"] else (
            EXIT_ABORTED if summary["aborted"] else EXIT_TIMEOUT)
        if summary["aborted"]:
            print(f"run aborted: {summary['aborted']}", file=sys.stderr)
        elif code:
            print(f"run timed out after {timeout:g} s (--timeout): {len(summary['results'])} of "
                  f"{summary['trials']} trials done; every node is stopped", file=sys.stderr)
    bag_dir, mcap = bag_layout(bag)
    final = out_dir / "run.mcap"
    if mcap.exists():                      # make out_dir itself the rosbag2 bag: run.mcap + metadata.yaml
        for name in sorted(outputs.listed(bag_dir) or ()):
            if (bag_dir / name).is_file():
                outputs.move_into(bag_dir / name, out_dir / name)
        outputs.remove(bag_dir)
    extra = sorted(p for p in out_dir.glob("run_*") if outputs.is_output_folder(p))
    if extra:
        print(f"the recorder restarted: later parts in {', '.join(str(p) for p in extra)}", file=sys.stderr)
    if not final.exists():
        print(f"no recording: the run ended before the recorder heard /experiment/config ({final})",
              file=sys.stderr)
        return code or EXIT_ABORTED
    rec = read_recording(final)
    for r in rec.results:
        print(json.dumps({k: r[k] for k in ("trial", "case", "settling_time_s", "rms_in_position_m",
                                            "peak_tracking_error_m", "rms_tracking_error_m")}))
    print(f"{len(rec)} samples in {time.monotonic() - t0:.1f} s; recording: {final}"
          + (f" (salvaged: {rec.salvaged})" if rec.salvaged else ""))
    incomplete = [e["reason"] for e in rec.events if e.get("cause") == "recording_incomplete"]
    for reason in incomplete:
        print(f"recording incomplete: {reason}", file=sys.stderr)
    return EXIT_RECORDING_CUT if code == 0 and (rec.salvaged or extra or incomplete) else code


def check_run(experiment: str, out_dir: Path, domain_id=None, timeout: float = 3600.0,
              overwrite: bool = False) -> None:
    """Refuse a run that cannot work, before any node starts: a :class:`ConfigError` naming the
    experiment file's problem, a ROS domain ID out of range (argument or ``ROS_DOMAIN_ID``), a
    timeout that is not positive, an output folder that cannot be made or is not nanostage's
    (:func:`experiment_runner.core.outputs.prepare_folder`). ``out_dir`` exists after."""
    load_experiment(experiment)
    try:
        check_domain_id(domain_id)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    if not (isinstance(timeout, (int, float)) and timeout > 0):
        raise ConfigError(f"--timeout: got {timeout!r}; expected a positive number of seconds")
    outputs.prepare_folder(out_dir, overwrite, option="--out")


def _clear_previous_run(out_dir: Path):
    """Remove the recording a previous run left in ``out_dir`` (``run.mcap``, ``metadata.yaml``,
    ``run/``, ``run_<i>/``), so nothing of it is read as this run's -- nanostage's files only: one of
    those names that nanostage did not write is an :class:`~experiment_runner.core.outputs.OutputError`
    (before any node starts)."""
    paths = [out_dir / "run.mcap", out_dir / "metadata.yaml", out_dir / "run",
             *sorted(p for p in out_dir.glob("run_*") if outputs.is_output_folder(p))]
    for p in paths:
        kept = outputs.remove(p)
        if kept:
            raise ConfigError(f"{p}: holds files nanostage did not write ({', '.join(k.name for k in kept)}); "
                              "move them away or choose another --out")
