"""``nanostage graph``: run an experiment through the ROS 2 node graph and record it.

One process (all nodes under one executor) or, with ``processes=True``, one process
per node (the console scripts ``plant_sim``, ``servo_controller``, ...), always on
an explicit ROS domain with localhost-only discovery. :class:`NodeProcesses` starts,
signals (kill, stop/continue, restart) and reaps the node processes of one run; every
wait is bounded, so a run never hangs.
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

EXIT_ABORTED, EXIT_TIMEOUT, EXIT_RECORDING_CUT = 1, 124, 3
"""Exit codes of a graph run besides 0 (every trial complete, recording intact): a trial
was aborted; the run did not end within its timeout (every process killed); the run
completed but the recording was cut short (its recorder died; salvaged) or misses samples
(a ``recording_incomplete`` fault of the recorder)."""

STOP_GRACE_S = 10.0
"""Wall-clock time a node process gets to exit after SIGINT before it is killed [s]."""


class NodeProcesses:
    """The node processes of one run (console scripts), started on the current domain.

    Parameters
    ----------
    experiment : str
        Experiment name or YAML path (the sequencer's ``experiment`` parameter).
    out : Path
        Recording path (the recorder's ``out`` parameter).
    nodes : sequence of str
        Node executables to start, in order (default: all of :data:`NODES`).
    params : dict, optional
        ``{node: {parameter: value}}`` given as ``-p parameter:=value`` (e.g. the test-only
        ``fault.*`` parameters of :class:`msg_defs.node_io.StageNode`).
    stderr_dir : Path, optional
        Write each node's stderr to ``stderr_dir/<node>.stderr`` (default: inherited).
    """

    def __init__(self, experiment: str, out: Path, nodes=NODES, params: dict | None = None,
                 stderr_dir: Path | None = None):
        self.experiment, self.out = experiment, Path(out)
        self.params = params or {}
        self.stderr_dir = stderr_dir
        self.bindir = Path(sys.executable).parent
        self.env = os.environ.copy()             # the domain of the run, also for restarts
        self.procs: dict[str, subprocess.Popen] = {}
        self.codes: dict[str, object] = {}       # exit code of every process that ended ("hung": killed)
        self.stopped: set[str] = set()           # sent SIGSTOP, not continued yet
        for name in nodes:
            self.start(name)

    def start(self, name: str, params: dict | None = None):
        """Start node ``name`` (again: its previous process must have ended)."""
        if name in self.procs and self.procs[name].poll() is None:
            raise RuntimeError(f"{name} is still running (pid {self.procs[name].pid})")
        args = [str(self.bindir / name), "--ros-args"]
        if name == "experiment_sequencer":
            args += ["-p", f"experiment:={self.experiment}"]
        if name == "recorder":
            args += ["-p", f"out:={self.out}"]
        for key, val in {**self.params.get(name, {}), **(params or {})}.items():
            if isinstance(val, str):             # quoted: "nan", "true", "1" stay strings
                val = "'" + val.replace("'", "''") + "'"
            args += ["-p", f"{key}:={val}"]
        err = None
        if self.stderr_dir is not None:
            self.stderr_dir.mkdir(parents=True, exist_ok=True)
            err = open(self.stderr_dir / f"{name}.stderr", "a")
        try:
            self.procs[name] = subprocess.Popen(args, env=self.env, stderr=err,
                                                stdout=subprocess.DEVNULL if err else None)
        finally:
            if err:
                err.close()
        self.codes.pop(name, None)

    def kill(self, name: str) -> int:
        """SIGKILL node ``name`` and reap it; returns its exit code (-9)."""
        p = self.procs[name]
        p.send_signal(signal.SIGKILL)
        self.codes[name] = p.wait(timeout=STOP_GRACE_S)
        self.stopped.discard(name)
        return self.codes[name]

    def pause(self, name: str):
        """SIGSTOP node ``name`` (it hangs: no callback runs, its sockets stay open)."""
        self.procs[name].send_signal(signal.SIGSTOP)
        self.stopped.add(name)

    def resume(self, name: str):
        """SIGCONT node ``name``."""
        self.procs[name].send_signal(signal.SIGCONT)
        self.stopped.discard(name)

    def restart(self, name: str, params: dict | None = None):
        """Kill node ``name`` and start it again (a crash and a supervisor's restart)."""
        self.kill(name)
        self.start(name, params)

    def dead(self) -> dict[str, int]:
        """Nodes whose process has ended, with their exit codes."""
        return {n: p.poll() for n, p in self.procs.items() if p.poll() is not None}

    def wait(self, name: str = "experiment_sequencer", timeout: float = 600.0):
        """Exit code of node ``name`` once it ends, or None after ``timeout`` [s]."""
        try:
            self.codes[name] = self.procs[name].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        return self.codes[name]

    def stop(self) -> dict:
        """End every node still running: SIGCONT (a stopped process cannot act on SIGINT),
        SIGINT, then SIGKILL after :data:`STOP_GRACE_S` (reported as ``"hung"``). The recorder
        goes first, while the publishers still hold what it has not taken yet.
        Returns every node's exit code."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
        self.stopped.clear()
        first = [n for n in self.procs if n == "recorder"]
        for group in (first, [n for n in self.procs if n not in first]):
            live = {n: self.procs[n] for n in group if self.procs[n].poll() is None}
            for p in live.values():
                p.send_signal(signal.SIGINT)
            deadline = time.monotonic() + STOP_GRACE_S
            for name in group:
                p = self.procs[name]
                if name not in live:
                    self.codes.setdefault(name, p.poll())
                    continue
                try:
                    self.codes[name] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.send_signal(signal.SIGUSR1)      # its threads' stacks to its stderr
                    time.sleep(0.5)
                    p.kill()
                    p.wait()
                    self.codes[name] = "hung"
        return dict(self.codes)


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
        nodes = [PlantNode(), ServoNode(), DitherNode(), SaiNode(), RecorderNode(out=str(out), overwrite=True)]
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


def run_processes(experiment: str, out: Path, timeout: float = 600.0, domain_id=None,
                  params: dict | None = None) -> int:
    """One process per node; returns the sequencer's exit code (0 complete, 1 aborted), or
    :data:`EXIT_TIMEOUT` if the run did not end within ``timeout`` [s]. A node process that
    ends before the sequencer is reported on stderr; every process is gone on return."""
    _isolate(domain_id)
    graph = NodeProcesses(experiment, out, params=params)
    reported = set()
    code = None
    try:
        t_end = time.monotonic() + timeout
        while code is None and time.monotonic() < t_end:
            code = graph.wait(timeout=0.2)
            for name, c in graph.dead().items():
                if name != "experiment_sequencer" and name not in reported:
                    reported.add(name)
                    print(f"node {name} ended early ({_exit_text(c)})", file=sys.stderr)
        if code is None:
            print(f"run timed out after {timeout} s: every node is stopped", file=sys.stderr)
            code = EXIT_TIMEOUT
        elif code < 0:
            print(f"node experiment_sequencer ended early ({_exit_text(code)})", file=sys.stderr)
            code = EXIT_ABORTED
    finally:
        codes = graph.stop()
    hung = [n for n, c in codes.items() if c == "hung"]
    if hung:
        print(f"killed after {STOP_GRACE_S} s without exiting on SIGINT: {', '.join(hung)}", file=sys.stderr)
    return code


def _exit_text(code: int) -> str:
    if code is not None and code < 0:
        return f"signal {signal.Signals(-code).name}"
    return f"exit code {code}"


def run_graph(experiment: str, out_dir: Path, processes: bool = False, domain_id=None,
              timeout: float = 3600.0, params: dict | None = None) -> int:
    """``nanostage graph``: run, record ``out_dir/run.mcap``, print the trial results.

    A previous run's recording in ``out_dir`` is removed first. ``params``
    (``{node: {parameter: value}}``) needs ``processes``. Returns 0 (every trial complete,
    recording intact), :data:`EXIT_ABORTED`, :data:`EXIT_TIMEOUT` or :data:`EXIT_RECORDING_CUT`.
    """
    if params and not processes:
        raise ValueError("node parameters need processes=True (one process per node)")
    import json

    from experiment_runner.experiment import load_experiment
    load_experiment(experiment)            # a bad experiment file is a ConfigError before any node starts
    out_dir.mkdir(parents=True, exist_ok=True)
    bag = out_dir / "run"
    _clear_previous_run(out_dir)
    t0 = time.monotonic()
    if processes:
        code = run_processes(experiment, bag, timeout, domain_id, params=params)
    else:
        summary = run_one_process(experiment, bag, timeout, domain_id)
        code = 0 if summary["done"] and not summary["aborted"] else (
            EXIT_ABORTED if summary["aborted"] else EXIT_TIMEOUT)
        if summary["aborted"]:
            print(f"run aborted: {summary['aborted']}", file=sys.stderr)
        elif code:
            print(f"run timed out after {timeout} s", file=sys.stderr)
    from experiment_runner.recording import bag_layout, read_recording
    bag_dir, mcap = bag_layout(bag)
    final = out_dir / "run.mcap"
    if mcap.exists():                      # make out_dir itself the rosbag2 bag: run.mcap + metadata.yaml
        for f in bag_dir.iterdir():
            f.replace(out_dir / f.name)
        bag_dir.rmdir()
    extra = sorted(p for p in out_dir.glob("run_*") if p.is_dir())
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


def _clear_previous_run(out_dir: Path):
    """Remove the recording a previous run left in ``out_dir`` (``run.mcap``,
    ``metadata.yaml``, ``run/``, ``run_<i>/``), so nothing of it is read as this run's."""
    import shutil
    for name in ("run.mcap", "metadata.yaml"):
        (out_dir / name).unlink(missing_ok=True)
    for d in [out_dir / "run", *out_dir.glob("run_*")]:
        if d.is_dir():
            shutil.rmtree(d)
