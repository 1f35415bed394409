"""``nanostage bench``: speed of the simulation core (never a pass/fail test).

Reports simulated seconds per wall-clock second for one FI-stage point-to-point
trajectory and for a batch of 100 such trials (on one core, and on all cores),
at the preset's control rate with the sub-steps the integrator needs, plus the
process's peak resident memory.
"""
from __future__ import annotations

import json
import resource
import time

import numba
import numpy as np

from experiment_runner.batch import Models, simulate
from experiment_runner.profiles import point_to_point
from stage_sim.config import load_preset


def _rtf(preset, ref, n_trials, models, repeats):
    """Best-of-``repeats`` aggregated real-time factor (simulated s / wall s)."""
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        simulate(preset, ref.x, ref.v, n_trials=n_trials, models=models)
        best = min(best, time.perf_counter() - t0)
    return n_trials * ref.t[-1] / best


def run_bench(as_json: bool = False, quick: bool = False) -> int:
    preset = load_preset("fi_stage")
    models = Models.from_preset(preset)
    ref = point_to_point(5e-3, dt=1.0 / preset.controller.rate)
    simulate(preset, ref.x, ref.v, n_trials=2, models=models)          # compile / load cache
    repeats = 2 if quick else 5
    threads = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = _rtf(preset, ref, 1, models, repeats)
        batch_one_core = _rtf(preset, ref, 100, models, max(1, repeats // 2))
    finally:
        numba.set_num_threads(threads)
    batch_all = _rtf(preset, ref, 100, models, max(1, repeats // 2))
    result = {
        "core_single_rtf": round(single, 1),
        "core_batch_rtf": round(batch_one_core, 1),
        "core_batch_rtf_all_cores": round(batch_all, 1),
        "cores": threads,
        "substeps_per_control_period": models.plant.n_sub,
        "control_rate_hz": preset.controller.rate,
        "trajectory_s": round(float(ref.t[-1]), 4),
        "peak_memory_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
    }
    if as_json:
        print(json.dumps(result))
    else:
        for k, v in result.items():
            print(f"{k:32s} {v}")
    return 0
