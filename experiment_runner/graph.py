"""``nanostage graph``: run an experiment through the ROS 2 node graph and record it.

One process (all nodes under one executor) or, with ``processes=True``, one process
per node (the console scripts ``plant_sim``, ``servo_controller``, ...), always on
an explicit ROS domain with localhost-only discovery.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

NODES = ("plant_sim", "servo_controller", "dither_generator", "sai_manager", "recorder",
         "experiment_sequencer")


def _isolate(domain_id):
    from msg_defs.node_io import domain_env
    os.environ.update(domain_env(domain_id))


def run_one_process(experiment: str, out: Path, timeout: float = 600.0, domain_id=None) -> dict:
    """All nodes in this process under one single-threaded executor."""
    _isolate(domain_id)
    import rclpy

    from msg_defs.node_io import make_executor
    from experiment_runner.recorder_node import RecorderNode
    from experiment_runner.sequencer import SequencerNode
    from stage_control.nodes import DitherNode, SaiNode, ServoNode
    from stage_sim.node import PlantNode

    rclpy.init()
    try:
        nodes = [PlantNode(), ServoNode(), DitherNode(), SaiNode(), RecorderNode(out=str(out))]
        seq = SequencerNode(experiment=experiment)
        ex = make_executor()
        for n in nodes + [seq]:
            ex.add_node(n)
        t0 = time.monotonic()
        while not seq.done and time.monotonic() - t0 < timeout:
            ex.spin_once(timeout_sec=0.1)
        t_end = time.monotonic() + 0.5
        while time.monotonic() < t_end:          # deliver the last events to the recorder
            ex.spin_once(timeout_sec=0.05)
        nodes[-1].close()
        summary = {"results": seq.results, "aborted": seq.aborted, "done": seq.done,
                   "wall_s": time.monotonic() - t0, "recording": str(nodes[-1].rec.path if nodes[-1].rec else None)}
        for n in nodes + [seq]:
            n.destroy_node()
    finally:
        rclpy.shutdown()
    return summary


def run_processes(experiment: str, out: Path, timeout: float = 600.0, domain_id=None) -> int:
    """One process per node; returns the sequencer's exit code."""
    _isolate(domain_id)
    bindir = Path(sys.executable).parent
    procs = {}
    for name in NODES:
        args = [str(bindir / name), "--ros-args"]
        if name == "experiment_sequencer":
            args += ["-p", f"experiment:={experiment}"]
        if name == "recorder":
            args += ["-p", f"out:={out}"]
        procs[name] = subprocess.Popen(args, env=os.environ.copy())
    try:
        code = procs["experiment_sequencer"].wait(timeout=timeout)
    finally:
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
    return code


def run_graph(experiment: str, out_dir: Path, processes: bool = False, domain_id=None,
              timeout: float = 3600.0) -> int:
    """``nanostage graph``: run, record ``out_dir/run.mcap``, print the trial results."""
    import json
    out_dir.mkdir(parents=True, exist_ok=True)
    bag = out_dir / "run"
    t0 = time.monotonic()
    if processes:
        code = run_processes(experiment, bag, timeout, domain_id)
    else:
        summary = run_one_process(experiment, bag, timeout, domain_id)
        code = 0 if summary["done"] and not summary["aborted"] else 1
        if summary["aborted"]:
            print(f"run aborted: {summary['aborted']}", file=sys.stderr)
    from experiment_runner.recording import bag_layout, read_recording
    bag_dir, mcap = bag_layout(bag)
    final = out_dir / "run.mcap"
    if mcap.exists():                      # make out_dir itself the rosbag2 bag: run.mcap + metadata.yaml
        for f in bag_dir.iterdir():
            f.replace(out_dir / f.name)
        bag_dir.rmdir()
    rec = read_recording(final)
    for r in rec.results:
        print(json.dumps({k: r[k] for k in ("trial", "case", "settling_time_s", "rms_in_position_m",
                                            "peak_tracking_error_m", "rms_tracking_error_m")}))
    print(f"{len(rec)} samples in {time.monotonic() - t0:.1f} s; recording: {final}"
          + (f" (salvaged: {rec.salvaged})" if rec.salvaged else ""))
    return code
