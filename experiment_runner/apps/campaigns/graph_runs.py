"""Representative campaign trials through the ROS 2 node graph, on spawned processes.

Each job is a one-trial experiment file (:func:`experiment_runner.apps.campaigns.trials.graph_experiment`)
run by :func:`experiment_runner.ros.launch.run_one_process` in a worker process on its own ROS domain,
a learned SAI Step II correction given to the SAI manager node as its ``initial_correction``
parameter; :func:`compare_graph` sets the recording beside the batch engine's same trial.
"""
from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np

from experiment_runner.apps.campaigns.base import RunResult
from experiment_runner.apps.campaigns.registry import TRIAL_METRICS
from experiment_runner.core.recording import read_recording
from experiment_runner.ros.launch import run_one_process

__all__ = ["run_graph_jobs", "compare_graph"]


def _run_graph_with_correction(experiment: str, out: Path, timeout: float, domain_id, correction) -> dict:
    """:func:`experiment_runner.ros.launch.run_one_process` with a learned Step II correction held by the
    SAI manager node from its start (its ``initial_correction`` parameter)."""
    corr = [float(v) for v in np.asarray(correction, float).ravel()]
    return run_one_process(experiment, out, timeout, domain_id,
                           params={"sai_manager": {"initial_correction": corr}} if corr else None)


def _graph_worker(jobs: list, domain_id: int) -> list:
    """Run graph jobs one after the other in this (spawned) process."""
    out = []
    for job in jobs:
        t0 = time.monotonic()
        try:
            if job.get("correction") is not None:
                s = _run_graph_with_correction(job["experiment"], Path(job["bag"]), job["timeout"], domain_id,
                                               job["correction"])
            else:
                            s = run_one_process(job["experiment"], Path(job["bag"]), job["timeout"], domain_id)
            s = {k: s[k] for k in ("results", "aborted", "done", "recording")}
        except Exception as err:       # noqa: BLE001 - reported, the batch results stand
            s = {"results": [], "aborted": {"reason": f"{type(err).__name__}: {err}"}, "done": False,
                 "recording": None}
        s["key"] = job["key"]
        s["wall_s"] = time.monotonic() - t0
        out.append(s)
    return out


def run_graph_jobs(jobs: list, workers: int = 2, bar=None) -> list:
    """Run graph jobs on ``workers`` spawned processes, each on its own ROS domain.

    Parameters
    ----------
    jobs : list of dict
        The graph trials (each with its ``samples``, for balancing the processes' load).
    workers : int, optional
        Processes (at most one per job).
    bar : tqdm.tqdm, optional
        Progress bar updated as each process's trials finish.

    Returns
    -------
    list of dict
        The trials' results, in the order the processes finished.
    """
    if not jobs:
        return []
    workers = max(1, min(workers, len(jobs)))
    parts = [[] for _ in range(workers)]
    load = [0] * workers
    for job in sorted(jobs, key=lambda j: -j["samples"]):
        w = load.index(min(load))
        parts[w].append(job)
        load[w] += job["samples"]
    base = 20 + (os.getpid() % 35) * 2
    results = []
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn")) as ex:
        futs = [ex.submit(_graph_worker, part, base + w) for w, part in enumerate(parts)]
        for fut in cf.as_completed(futs):
            got = fut.result()
            results += got
            if bar is not None:
                bar.update(len(got))
    return results


def compare_graph(g: dict, rr: RunResult) -> dict:
    """Graph trial vs the same batch trial: metrics and the largest difference of the measured position.

    Parameters
    ----------
    g : dict
        The graph trial's result (:func:`run_graph_jobs`).
    rr : RunResult
        The batch run of the same case and condition.

    Returns
    -------
    dict
        Completion, wall time, recording, both trials' metrics and ``max_abs_diff_m`` /
        ``max_abs_ref_diff_m`` [m] (or ``read_error`` when the recording cannot be read).
    """
    out = {"done": g["done"], "aborted": g["aborted"], "wall_s": g["wall_s"], "recording": g["recording"],
           "results": g["results"]}
    if g["results"]:
        r = g["results"][0]
        b = rr.metrics[rr.rep]
        out["metrics"] = {k: r.get(k) for k in TRIAL_METRICS}
        out["batch_metrics"] = {k: b.get(k) for k in TRIAL_METRICS}
    try:
        rec = read_recording(g["recording"])
        n = min(len(rec.y), len(rr.trace.y))
        out["samples"] = int(len(rec.y))
        out["batch_samples"] = int(len(rr.trace.y))
        out["max_abs_diff_m"] = float(np.max(np.abs(rec.y[:n] - rr.trace.y[:n]))) if n else None
        out["max_abs_ref_diff_m"] = float(np.max(np.abs(rec.x_ref[:n] - rr.trace.x_ref[:n]))) if n else None
    except Exception as err:     # noqa: BLE001
        out["read_error"] = f"{type(err).__name__}: {err}"
    return out

