"""Start the graph's nodes: all in one process, or one process per node.

:func:`run_one_process` runs every node (:data:`experiment_runner.ros.nodes.NODES`)
under one executor in this process; :func:`run_processes` starts each node's console
script as its own process. Both run on an explicit ROS domain with localhost-only
discovery. :class:`NodeProcesses` starts, signals (kill, stop/continue, restart) and
reaps the node processes of one run; every wait is bounded, so a run never hangs.
``nanostage graph`` (:mod:`experiment_runner.apps.graph`) is built on these.
"""
from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from experiment_runner.core.outputs import interrupts_deferred
from experiment_runner.ros.nodes import NODE_NAMES, NODES, node
from experiment_runner.ros.run import isolate, make_executor, spin_for, teardown

EXIT_ABORTED, EXIT_TIMEOUT, EXIT_RECORDING_CUT = 1, 124, 3
"""Exit codes of a graph run besides 0 (every trial complete, recording intact): a trial
was aborted; the run did not end within its timeout (every process killed); the run
completed but the recording was cut short (its recorder died; salvaged) or misses samples
(a ``recording_incomplete`` fault of the recorder)."""

STOP_GRACE_S = 10.0
"""Wall-clock time a node process gets to exit after SIGTERM before it is killed [s]."""

STARTING = -signal.SIGTERM
"""Exit code of a node process stopped before it could act on SIGTERM: it was still starting
(importing; :func:`~experiment_runner.ros.run.run_node` makes SIGTERM a clean stop)."""


class NodeProcesses:
    """The node processes of one run (console scripts), started on the current domain.

    Parameters
    ----------
    experiment : str
        Experiment name or YAML path (the sequencer's ``experiment`` parameter).
    out : Path
        Recording path (the recorder's ``out`` parameter).
    nodes : sequence of str
        Node executables to start, in order (default: all, :data:`~experiment_runner.ros.nodes.NODES`).
    params : dict, optional
        ``{node: {parameter: value}}`` given as ``-p parameter:=value`` (e.g. the test-only
        ``fault.*`` parameters of :class:`experiment_runner.ros.node.StageNode`).
    stderr_dir : Path, optional
        Write each node's stderr to ``stderr_dir/<node>.stderr`` (default: inherited).
    env : mapping, optional
        The node processes' environment, which holds the run's domain (default: this process's,
        as :func:`~experiment_runner.ros.run.isolate` set it; e.g.
        :func:`~experiment_runner.ros.run.domain_env`); kept for restarts.
    ros_args : dict, optional
        ``{node: [argument, ...]}``: more ROS arguments of a node after ``--ros-args``, e.g.
        ``["--params-file", "plant.yaml"]``.
    """

    def __init__(self, experiment: str, out: Path, nodes=NODE_NAMES, params: dict | None = None,
                 stderr_dir: Path | None = None, env=None, ros_args: dict | None = None):
        self.experiment, self.out = experiment, Path(out)
        self.params = params or {}
        self.ros_args = {name: list(args) for name, args in (ros_args or {}).items()}
        self.stderr_dir = stderr_dir
        self.bindir = Path(sys.executable).parent
        self.env = dict(os.environ if env is None else env)    # the domain of the run, also for restarts
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
        values = {**run_args(self.experiment, self.out, self.params).get(name, {}), **(params or {})}
        for key, val in values.items():
            args += ["-p", f"{key}:={_param_text(val)}"]
        args += self.ros_args.get(name, [])
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

    def stderr(self, name: str) -> str:
        """What node ``name`` wrote to its stderr file so far (every start of it; needs ``stderr_dir``)."""
        return (self.stderr_dir / f"{name}.stderr").read_text()

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
        """End every node still running: SIGCONT (a stopped process cannot act on a signal),
        SIGTERM, then SIGKILL after :data:`STOP_GRACE_S` (reported as ``"hung"``). The recorder
        goes first, while the publishers still hold what it has not taken yet. A node still
        starting ends at once, quietly (Python's default for SIGTERM; SIGINT would print a
        ``KeyboardInterrupt`` traceback from the middle of its imports): :data:`STARTING`.
        Returns every node's exit code."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGCONT)
        self.stopped.clear()
        first = [n for n in self.procs if n == "recorder"]
        for group in (first, [n for n in self.procs if n not in first]):
            live = {n: self.procs[n] for n in group if self.procs[n].poll() is None}
            for p in live.values():
                p.send_signal(signal.SIGTERM)
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


def _param_text(val) -> str:
    """A parameter value as ``-p name:=<text>`` (YAML) takes it: strings quoted ("nan", "true",
    "1" stay strings), floats with a decimal point (a list of them stays a double array)."""
    if isinstance(val, str):
        return "'" + val.replace("'", "''") + "'"
    if isinstance(val, (list, tuple)):
        return "[" + ", ".join(_param_text(v) for v in val) + "]"
    if isinstance(val, float):
        return f"{val:.17e}" if math.isfinite(val) else {math.inf: ".inf", -math.inf: "-.inf"}.get(val, ".nan")
    return str(val).lower() if isinstance(val, bool) else str(val)


def run_args(experiment: str, out: Path, params: dict | None = None) -> dict:
    """``{node: {parameter: value}}`` of a run: the sequencer's experiment, the recorder's
    output, then ``params``."""
    args = {"experiment_sequencer": {"experiment": str(experiment)}, "recorder": {"out": str(out)}}
    for name, values in (params or {}).items():
        node(name)                                  # KeyError naming the nodes for a typo
        args[name] = {**args.get(name, {}), **values}
    return args


def run_one_process(experiment: str, out: Path, timeout: float = 600.0, domain_id=None,
                    params: dict | None = None) -> dict:
    """Every node of :data:`~experiment_runner.ros.nodes.NODES` in this process, under one
    executor (:func:`~experiment_runner.ros.run.make_executor`); ``params``:
    ``{node: {parameter: value}}`` (e.g. ``{"sai_manager": {"initial_correction": [...]}}``).
    An existing recording at ``out`` is replaced. Returns the sequencer's ``results``, the
    number of ``trials``, ``aborted`` (None or a dict), ``done``, ``wall_s`` and the ``recording`` path."""
    isolate(domain_id)
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    args = run_args(experiment, out, params)
    args["recorder"]["overwrite"] = True
    # SIGINT / SIGTERM: noted and raised between spins (an error for the CLI: one line), never inside
    # a callback, nor rclpy's own shutdown
    with interrupts_deferred() as interrupted:
        rclpy.init(signal_handler_options=SignalHandlerOptions.NO)
        return _run_nodes(args, timeout, interrupted)


def _run_nodes(args: dict, timeout: float, interrupted) -> dict:
    """:func:`run_one_process` in an initialised rclpy; ``interrupted()`` raises once a signal came."""
    import importlib

    import rclpy
    from rclpy.parameter import Parameter

    try:
        made = {}
        for spec in NODES:
            cls = getattr(importlib.import_module(spec.module), spec.cls)
            made[spec.name] = cls(parameter_overrides=[Parameter(k, value=v)
                                                       for k, v in args.get(spec.name, {}).items()])
        for n in made.values():
            n.warm_up()                          # kernels loaded before any node spins (StageNode.warm_up)
            interrupted()
        seq, recorder = made["experiment_sequencer"], made["recorder"]
        ex = make_executor()
        for n in made.values():
            ex.add_node(n)
        t0 = time.monotonic()
        while not seq.done and time.monotonic() - t0 < timeout:
            spin_for(ex, 0.05)
            interrupted()
        spin_for(ex, 0.5)                        # deliver the last events to the recorder
        recorder.close()
        summary = {"results": seq.results, "trials": len(seq.trials), "aborted": seq.aborted, "done": seq.done,
                   "wall_s": time.monotonic() - t0, "recording": str(recorder.rec.path if recorder.rec else None)}
        teardown(ex, *made.values())             # executor first, while nodes and context live
    finally:
        rclpy.shutdown()
    return summary


def run_processes(experiment: str, out: Path, timeout: float = 600.0, domain_id=None,
                  params: dict | None = None) -> int:
    """One process per node; returns the sequencer's exit code (0 complete, 1 aborted), or
    :data:`EXIT_TIMEOUT` if the run did not end within ``timeout`` [s]. A node process that
    ends before the sequencer is reported on stderr; every process is gone on return."""
    isolate(domain_id)
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
        if code is not None and code < 0:
            print(f"node experiment_sequencer ended early ({_exit_text(code)})", file=sys.stderr)
            code = EXIT_ABORTED
    finally:
        codes = graph.stop()
    if code is None:
        starting = sorted(n for n, c in codes.items() if c == STARTING)
        print(f"run timed out after {timeout:g} s (--timeout): the experiment did not finish"
              + (f"; still starting: {', '.join(starting)}" if starting else "") + "; every node is stopped",
              file=sys.stderr)
        code = EXIT_TIMEOUT
    hung = [n for n, c in codes.items() if c == "hung"]
    if hung:
        print(f"killed after {STOP_GRACE_S} s without exiting on SIGTERM: {', '.join(hung)}", file=sys.stderr)
    return code


def _exit_text(code: int) -> str:
    if code is not None and code < 0:
        return f"signal {signal.Signals(-code).name}"
    return f"exit code {code}"
