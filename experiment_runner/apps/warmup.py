"""Compile the numba kernels once, with visible progress: ``python -m experiment_runner.apps.warmup``.

numba compiles a kernel at its first call and caches it on disk (:mod:`stage_sim.numba_cache`, one
cache per version of the compiled code); on a fresh machine, or after an edit of a compiled
module, the first campaign, diagnosis or graph run would otherwise spend minutes compiling
inside its first step (measured: ~90 s of a 16-core machine's first bench figure, ~200 s of a
loaded machine's first main-job calibration). ``scripts/bootstrap.sh`` runs this module once;
run it again after editing a compiled module to pay the compile up front.

Each step calls the kernels as the application does, with the argument types it passes (numba
compiles one specialization per type signature; every shipped preset gives the same model
types, so one preset stands for all):

1. the batch engine (campaign trials, calibration, design sweeps);
2. the frequency-response kernel;
3. the one-trial step functions of the graph's nodes (plant, servo, dither, SAI manager);
4. the diagnosis, on a short synthetic recording (observer, open-loop replays);
5. matplotlib's font cache (the first plot of a fresh install builds it).

Once every step has run, a marker in the cache folder (``warmed.json``: numba's version and this
processor) makes the next call return at once; the cache folder is named by the compiled code,
so an edit of a compiled module starts a fresh one and the warm-up runs again (``--force``: always).
"""
from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import llvmlite.binding
import numba
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from experiment_runner.apps.campaigns.frf import plant_frf
from experiment_runner.apps.campaigns.spec import load_campaign
from experiment_runner.apps.diagnosis.selftest import diagnose_seconds
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.profiles import point_to_point
from stage_control.dither import dither_step
from stage_control.sai import sai_step
from stage_control.servo import servo_step
from stage_sim import numba_cache
from stage_sim.config import load_preset
from stage_sim.plant import plant_inputs, plant_step

__all__ = ["STEPS", "warm_up", "is_warm", "main"]

PRESET = "sai_stage"
"""The preset the steps run (every shipped preset compiles to the same kernel types)."""


def batch_engine() -> None:
    """:func:`experiment_runner.core.batch.simulate`: a chunk of several trials, as a campaign runs it."""
    preset = load_preset(PRESET)
    ref = point_to_point(5e-6, dwell=0.01, dt=1.0 / preset.controller.rate)
    simulate(preset, ref.x, ref.v, n_trials=3, models=Models.from_preset(preset), check=False)


def frequency_response() -> None:
    """:func:`experiment_runner.apps.campaigns.frf.plant_frf` on two short columns."""
    test = load_campaign("frf_fi").test.model_copy(update=dict(
        f_min=200.0, f_max=300.0, points_per_decade=2, cycles=1, min_measure_time=0.0, measure_force_time=None,
        ramp_cycles=1.0, min_ramp_time=0.0, settle_cycles=0.0, min_settle_time=0.0))
    plant_frf(load_preset(PRESET), test, amplitudes=[test.amplitudes[-1]])


def graph_steps() -> None:
    """The step functions of the graph's nodes, with one-trial arrays as each node passes them
    (:mod:`experiment_runner.ros.plant_node`, ``servo_node``, ``dither_node``, ``sai_node``)."""
    models = Models.from_preset(load_preset(PRESET))
    init = models.initial_state([0.0])
    one = lambda: np.zeros(1)          # noqa: E731 - a one-trial input or output
    plant_step(models.plant, init.plant, plant_inputs(1), 0, np.array([1], np.int64), init.meas,
               np.zeros(1, np.int64))
    servo_step(models.servo, init.servo, one(), one(), one(), one())
    dither_step(models.dither, init.dither, 0, one(), one(), one(), np.zeros((2, 1)))
    sai_step(models.sai, init.sai, np.asarray([], float), 0, one(), one(), one(), one())


def diagnosis() -> None:
    """``nanostage diagnose`` on a 1 s synthetic recording
    (:func:`experiment_runner.apps.diagnosis.selftest.diagnose_seconds`)."""
    diagnose_seconds(1.0)


def plots() -> None:
    """matplotlib's font cache: one figure drawn off screen (the Agg canvas, whatever the backend)."""
    fig = Figure()
    ax = fig.subplots()
    ax.plot([0, 1], [0, 1], label="warm-up")
    ax.legend()
    FigureCanvasAgg(fig).draw()


STEPS = {"batch": ("batch engine", batch_engine), "frf": ("frequency responses", frequency_response),
         "graph": ("graph node steps", graph_steps), "diagnosis": ("diagnosis", diagnosis),
         "plots": ("plots", plots)}
"""Every warm-up step, in order: key -> (what it compiles, function)."""


@contextmanager
def _ticking(label: str, out, every: float = 10.0):
    """Print ``label`` now and the elapsed time every ``every`` seconds until the block ends."""
    done = threading.Event()
    t0 = time.monotonic()
    print(f"  {label} ...", file=out, flush=True)

    def tick():
        while not done.wait(every):
            print(f"  {label}: {time.monotonic() - t0:.0f} s", file=out, flush=True)

    th = threading.Thread(target=tick, daemon=True, name="nanostage-warm-up-ticker")
    th.start()
    try:
        yield
    finally:
        done.set()
        th.join()


def _marker() -> dict:
    """What a complete warm-up's marker records: numba's version and the processor it compiled for."""
    return {"numba": numba.__version__, "cpu": llvmlite.binding.get_host_cpu_name()}


def _marker_path() -> Path | None:
    return Path(numba_cache.CACHE_DIR) / "warmed.json" if numba_cache.CACHE_DIR else None


def is_warm() -> bool:
    """Every step has run for this compiled code, numba version and processor (:func:`warm_up`)."""
    path = _marker_path()
    try:
        return path is not None and json.loads(path.read_text()) == _marker()
    except (OSError, ValueError):
        return False


def warm_up(steps=None, out=sys.stderr, force: bool = False) -> dict:
    """Run the warm-up ``steps`` (keys of :data:`STEPS`; default all, unless :func:`is_warm` and not
    ``force``), printing progress to ``out`` (None: quiet); returns ``{step: seconds}``.

    >>> sorted(warm_up(["plots"], out=None))
    ['plots']
    """
    every = steps is None
    steps = list(STEPS) if every else list(steps)
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        raise ValueError(f"unknown warm-up step(s) {', '.join(unknown)}; known: {', '.join(STEPS)}")
    if every and not force and is_warm():
        if out is not None:
            print(f"nanostage: the numba kernels of this code are compiled (cache {numba_cache.CACHE_DIR})", file=out)
        return {}
    if out is not None:
        print(f"nanostage: compiling the numba kernels once (cache {numba_cache.CACHE_DIR or 'numba default'}; "
              "minutes on a fresh machine, a few seconds when cached)", file=out, flush=True)
    times = {}
    for i, key in enumerate(steps, 1):
        what, fn = STEPS[key]
        label = f"[{i}/{len(steps)}] {what}"
        t0 = time.monotonic()
        if out is None:
            fn()
        else:
            with _ticking(label, out):
                fn()
        times[key] = round(time.monotonic() - t0, 1)
        if out is not None:
            print(f"  {label}: done in {times[key]:.1f} s", file=out, flush=True)
    path = _marker_path()
    if every and path is not None:
        try:
            path.write_text(json.dumps(_marker()))
        except OSError:            # a read-only cache: warm, but without the marker
            pass
    return times


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m experiment_runner.apps.warmup",
                                     description="Compile the numba kernels once, with progress.")
    parser.add_argument("steps", nargs="*", metavar="STEP", help=f"steps to run (default all): {', '.join(STEPS)}")
    parser.add_argument("--force", action="store_true", help="run every step even if this code's kernels are warm")
    args = parser.parse_args(argv)
    t0 = time.monotonic()
    try:
        warm_up(args.steps or None, out=sys.stderr, force=args.force)
    except ValueError as err:
        parser.error(str(err))
    print(f"nanostage: kernels ready ({time.monotonic() - t0:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
