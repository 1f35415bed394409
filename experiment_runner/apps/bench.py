"""``nanostage bench``: speed of the simulation core (never a pass/fail test).

Reports simulated seconds per wall-clock second for one FI-stage point-to-point
trajectory and for a batch of 100 such trials (on one core, and on all cores; the one-core
figures also per CPU second, ``core_*_rtf_cpu``, which a loaded machine disturbs less),
at the preset's control rate with the sub-steps the integrator needs
(``core_substeps_per_sample``; ``core_ns_per_substep_per_trial`` is the one-core batch's
wall time per sub-step and trial), plus the process's peak resident memory.

``main_job_seconds`` (only with ``main_job=True``, ``nanostage bench --main-job``): wall
time of ``nanostage campaign --main`` in a temporary folder, with the CLI's default workers.

``campaign_trials_per_s_1`` / ``_N`` (``N`` = :func:`~experiment_runner.core.executor.default_workers`,
the cores this process may use): Table 4.2 campaign trials (both cases, both step sizes, 1 s
dwell, no calibration; 500 trials of each on one worker, 2000 in all, several seconds of work, and
``250 N`` of each on ``N``, so that a large campaign's throughput is timed, not a run's start and
end) per wall-clock second on one worker of one thread (this process) and on ``N`` local worker
processes of one thread each (:func:`campaign_trials_per_s`); ``campaign_scale_out_N`` = ``_N /
_1`` (the goal: >= 0.85 N); ``campaign_trials_per_s_dask_N``: the same ``N`` workers as a Dask
``LocalCluster``; ``campaign_trials_per_s_all_cores_1``: this process with ``N`` numba threads, as
``nanostage campaign --workers 1`` runs, and ``threads_scale_all_cores`` its ratio to one thread
(in-process thread scaling; ``docs/speed.md`` says why it stays below the processes').

``diagnose_seconds_10s``: wall time of ``nanostage diagnose`` (reading the MCAP file
included) on a 10 s, 10 kHz synthetic recording with one concealed effect
(:func:`experiment_runner.apps.diagnosis.selftest.diagnose_seconds`), after the same on a 1 s
recording (so a compile or cache load of the kernels is not in the figure: it was, 25-40 s
instead of 12-13 s, whenever a source file had changed since the kernels were cached).
``diagnose_seconds_emps``: wall time of ``nanostage diagnose REC emps_nominal.yaml`` with the CLI's
defaults (its wall-clock budget included) on the EMPS main record (``nanostage convert emps
DATA_EMPS.mat``, conversion not timed), after the 10 s figure (kernels warm); left out with
``quick``, and, with the reason on stderr, when the EMPS data are not under the shared data folder
(:func:`diagnose_seconds_emps`).

With ``graph=True`` (``nanostage bench --graph``, the default) it also runs the ROS 2
node graph on an FI-stage point-to-point experiment, once in one process and once
with one process per node, and reports control samples per wall-clock second over
the trial portion (``trial_start`` of trial 1 to the last ``trial_end``, as heard by
a listener in its own context; trial 0 is the warm-up), next to the raw rclpy
publish-subscribe round-trip rate measured in the same run (two nodes in one process,
``sensor_msgs/JointState`` ping -> pong with the lockstep topics' reliable QoS), with
the executor the graph uses and with rclpy's ``SingleThreadedExecutor``. The fair
ceiling is per message: ``graph_message_rate_one_process`` (the graph's messages per
second) against ``rclpy_message_rate`` (2 x round trips/s: one publish and one delivery
each), see :func:`run_graph_bench`.
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import resource
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import NamedTuple, Optional

import numba
import numpy as np

from experiment_runner.apps.campaigns.runner import main_job
from experiment_runner.apps.campaigns.spec import Campaign, case_preset, conditions, load_campaign
from experiment_runner.apps.campaigns.stream import TrialStream, chunk_task, code_fingerprint, run_trial_jobs
from experiment_runner.apps.diagnosis import add_diagnose_arguments, main_diagnose
from experiment_runner.apps.diagnosis.datasets import DataMissing, data_root, need_file
from experiment_runner.apps.diagnosis.emps import EMPS_NOMINAL
from experiment_runner.apps.diagnosis.selftest import diagnose_seconds
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.executor import default_workers, local_cluster, make_executor
from experiment_runner.core.profiles import point_to_point
from experiment_runner.core.tabular import convert_emps
from stage_sim.config import load_preset


class Sizes(NamedTuple):
    """How much work each figure of :func:`run_bench` times. Every figure is a rate or a time per
    unit of work: a size changes its noise, not what it measures (``diagnose_seconds_<T>s`` names
    its recording's length)."""
    repeats: int = 5                 # core figures: the best of this many runs
    campaign_trials: int = 500       # campaign figures: trials of every case and condition on one worker
    diagnose_seconds: float = 10.0   # the synthetic recording diagnosed (after a 1 s one, the warm-up) [s]
    graph_trials: int = 8            # graph figures: trials of the graph run
    roundtrips: int = 20000          # graph figures: raw rclpy round trips
    emps: bool = True                # diagnose_seconds_emps: the EMPS main record diagnosed (CLI defaults)


FULL = Sizes()
"""``nanostage bench``."""
QUICK = Sizes(repeats=2, campaign_trials=12, graph_trials=3, roundtrips=5000, emps=False)
"""``nanostage bench --quick``."""


def _rtf(preset, ref, n_trials, models, repeats, clock=time.perf_counter):
    """Best-of-``repeats`` aggregated real-time factor (simulated s / ``clock`` s: wall time, or
    with ``time.process_time`` the process's CPU time, which a loaded machine disturbs less)."""
    best = np.inf
    for _ in range(repeats):
        t0 = clock()
        simulate(preset, ref.x, ref.v, n_trials=n_trials, models=models)
        best = min(best, clock() - t0)
    return n_trials * ref.t[-1] / best


def core_figures(repeats: int = FULL.repeats) -> dict:
    """The ``core_*`` figures: FI-stage point-to-point (5 mm), one trial and 100 trials on one
    core (per wall and per CPU second), 100 trials on all cores, the sub-steps per sample and the
    wall time per sub-step and trial; each the best of ``repeats`` runs."""
    preset = load_preset("fi_stage")
    models = Models.from_preset(preset)
    ref = point_to_point(5e-3, dt=1.0 / preset.controller.rate)
    simulate(preset, ref.x, ref.v, n_trials=2, models=models)          # compile / load cache
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = _rtf(preset, ref, 1, models, repeats)
        single_cpu = _rtf(preset, ref, 1, models, repeats, time.process_time)
        batch_one_core = _rtf(preset, ref, 100, models, repeats)
        batch_cpu = _rtf(preset, ref, 100, models, repeats, time.process_time)
    finally:
        numba.set_num_threads(threads)
    batch_all = _rtf(preset, ref, 100, models, repeats)
    return {
        "core_single_rtf": round(single, 1),
        "core_batch_rtf": round(batch_one_core, 1),
        "core_single_rtf_cpu": round(single_cpu, 1),
        "core_batch_rtf_cpu": round(batch_cpu, 1),
        "core_batch_rtf_all_cores": round(batch_all, 1),
        "cores": threads,
        # the distance to the limit: sub-steps the integrator needs per control sample, and
        # the wall time of one sub-step of one trial in the one-core batch
        "core_substeps_per_sample": models.plant.n_sub,
        "core_ns_per_substep_per_trial": round(1e9 / (preset.controller.rate * batch_one_core
                                                      * models.plant.n_sub), 1),
        "control_rate_hz": preset.controller.rate,
        "trajectory_s": round(float(ref.t[-1]), 4),
    }


def run_graph_bench(sizes: Sizes = FULL) -> dict:
    """The graph part of the benchmark, all figures from this run.

    ``graph_message_rate_one_process`` (messages/s of the one-process graph: control samples/s
    x ``graph_messages_per_sample``) against ``rclpy_message_rate`` (2 x raw rclpy round trips/s
    on the graph's executor: the middleware's cost per message, one publish and one delivery);
    ``rclpy_message_rate_serialized``: the same with the message as CDR bytes both ways, as
    the graph sends its per-sample messages (the middleware's floor for them);
    ``graph_loop_hz_*``: control samples/s in one process and with one process per node;
    ``rclpy_roundtrip_hz*``: raw round trips/s (events executor, and the single-threaded one).
    """
    from experiment_runner.ros.run import executor_kind
    from experiment_runner.ros.timing import graph_loop_hz, rclpy_roundtrip_hz
    trials, n_rt = sizes.graph_trials, sizes.roundtrips
    one = graph_loop_hz(False, trials)
    procs = graph_loop_hz(True, trials)
    rt = rclpy_roundtrip_hz(n_rt)
    rt_raw = rclpy_roundtrip_hz(n_rt, serialized=True)
    rt_single = rclpy_roundtrip_hz(max(1000, n_rt // 5), executor="single")
    def r(x, nd=1):
        return None if x is None else round(x, nd)
    per_sample = one["messages_per_sample"]
    msg_rate = one["hz"] * per_sample if one["hz"] and per_sample else None
    return {
        "graph_messages_per_sample": r(per_sample, 3),
        "graph_message_rate_one_process": r(msg_rate),
        "rclpy_message_rate": round(2 * rt, 1),
        "graph_message_rate_vs_rclpy": r(msg_rate and msg_rate / (2 * rt), 3),
        "rclpy_message_rate_serialized": round(2 * rt_raw, 1),
        "graph_message_rate_vs_rclpy_serialized": r(msg_rate and msg_rate / (2 * rt_raw), 3),
        "graph_loop_hz_one_process": r(one["hz"]),
        "graph_loop_hz_processes": r(procs["hz"]),
        "graph_samples_timed": f"{one['samples']} / {procs['samples']}",
        "graph_executor": executor_kind(),
        "rclpy_roundtrip_hz": round(rt, 1),
        "rclpy_roundtrip_hz_single": round(rt_single, 1),
        "graph_one_process_vs_roundtrip": r(one["hz"] and one["hz"] / rt, 3),
        "graph_one_process_vs_roundtrip_single": r(one["hz"] and one["hz"] / rt_single, 3),
    }


def campaign_trials_per_s(workers: int, trials: int = 40, campaign: str = "table_4_2", *, dask: bool = False,
                          threads: Optional[int] = None) -> float:
    """Campaign trials per wall-clock second on ``workers`` workers, as ``nanostage campaign`` runs
    them: chunks of all cases and conditions on one executor, metrics streamed to disk
    (:func:`experiment_runner.apps.campaigns.stream.run_trial_jobs`); ``trials`` trials of every case and
    condition of ``campaign``, no calibration. Every worker is started and warm (numba kernels
    loaded, each case's models built: :meth:`~experiment_runner.core.executor.Executor.warm_all`) before
    the clock starts.

    Parameters
    ----------
    workers : int
        1: in this process; more: a local process pool (or, with ``dask``, a Dask ``LocalCluster``)
        of that many worker processes.
    threads : int, optional
        Numba threads per worker in this process or on Dask (default, and always on a process pool: the
        cores shared out, ``cores // workers``).
    """
    threads = threads or max(1, default_workers() // workers)
    camp = load_campaign(campaign)
    jobs = [(c, cond, case_preset(camp, c, None, cond), None) for c in camp.cases for cond in conditions(camp)]
    timed = Campaign.model_validate({**camp.model_dump(), "trials": trials})
    with ExitStack() as stack:
        if dask:
            ex = stack.enter_context(make_executor(cluster=stack.enter_context(local_cluster(workers, threads))))
        elif workers == 1:
            before = numba.get_num_threads()
            numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
            stack.callback(numba.set_num_threads, before)
            ex = stack.enter_context(make_executor(1))
        else:
            ex = stack.enter_context(make_executor(workers))
        tmp = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        for case, cond, preset, _ in jobs:       # a chunk of several trials: the kernels the timed chunks run
            ex.warm_all(chunk_task, (timed.model_dump_json(), case.name, cond.key, preset.model_dump_json(), None,
                                     [0, 1, 2], code_fingerprint()))
        with TrialStream(tmp / "timed.jsonl", camp.name, "timed", code_fingerprint(), resume=False) as stream:
            t0 = time.perf_counter()
            run_trial_jobs(timed, jobs, ex, stream)
            wall = time.perf_counter() - t0
    return len(jobs) * trials / wall


def main_job_seconds() -> float:
    """Wall time [s] of the README's main job (``nanostage campaign --main``: calibration,
    every trial, the graph runs, report and plots) in a temporary folder."""
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        main_job(tmp, progress=False, resume=False, workers=default_workers())     # as the CLI runs it
        return time.perf_counter() - t0


def diagnose_seconds_emps() -> float | None:
    """Wall time [s] of ``nanostage diagnose`` with the CLI's defaults (``--out`` a temporary
    folder, progress off) on the EMPS main record and the shipped nominal; None, saying why on
    stderr, when ``DATA_EMPS.mat`` is not under the shared data folder
    (:func:`experiment_runner.apps.diagnosis.datasets.data_root`)."""
    try:
        mat = need_file(data_root() / "emps" / "DATA_EMPS.mat", "EMPS main record")
    except DataMissing as err:
        print(f"bench: diagnose_seconds_emps skipped: {err}", file=sys.stderr)
        return None
    with tempfile.TemporaryDirectory(prefix="nanostage_bench_emps_") as tmp:
        rec = convert_emps(mat, Path(tmp) / "rec")
        p = argparse.ArgumentParser()
        add_diagnose_arguments(p)
        args = p.parse_args([str(rec), str(EMPS_NOMINAL), "--out", str(Path(tmp) / "diagnosis"), "--quiet"])
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io.StringIO()):
            main_diagnose(args)
        return time.perf_counter() - t0


def run_bench(as_json: bool = False, quick: bool = False, graph: bool = True, main_job: bool = False,
              sizes: Optional[Sizes] = None) -> int:
    """Measure and print the figures (one JSON object with ``as_json``); ``sizes``: :data:`QUICK` with
    ``quick``, else :data:`FULL` (a test runs the same code on tiny ones)."""
    sizes = sizes or (QUICK if quick else FULL)
    result = core_figures(sizes.repeats)
    result["peak_memory_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1)
    cores = default_workers()
    n_camp = sizes.campaign_trials
    one = campaign_trials_per_s(1, n_camp, threads=1)
    result["campaign_trials_per_s_1"] = round(one, 1)
    if cores > 1:             # one worker of one thread per core; on 2 cores the same trials as on one worker
        n_pool = n_camp * cores // 2
        pool = campaign_trials_per_s(cores, n_pool, threads=1)
        result[f"campaign_trials_per_s_{cores}"] = round(pool, 1)
        result[f"campaign_scale_out_{cores}"] = round(pool / one, 2)
        result[f"campaign_trials_per_s_dask_{cores}"] = round(campaign_trials_per_s(cores, n_pool, dask=True,
                                                                                    threads=1), 1)
    all_threads = campaign_trials_per_s(1, n_camp, threads=cores)
    result["campaign_trials_per_s_all_cores_1"] = round(all_threads, 1)
    result["threads_scale_all_cores"] = round(all_threads / one, 2)
    diagnose_seconds(1.0)         # warm-up: numba's compile / cache load is not timed (as for the core figures)
    result[f"diagnose_seconds_{sizes.diagnose_seconds:g}s"] = round(diagnose_seconds(sizes.diagnose_seconds), 1)
    emps = diagnose_seconds_emps() if sizes.emps else None
    if emps is not None:
        result["diagnose_seconds_emps"] = round(emps, 1)
    if graph:
        result.update(run_graph_bench(sizes))
    if main_job:
        result["main_job_seconds"] = round(main_job_seconds(), 1)
    if as_json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k:32s} {v}")
    return 0
