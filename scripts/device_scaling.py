"""Scaling experiments for a many-core machine (issue 27); run by ``scripts/device_scaling.sh``.

Measures, with the bench's own functions (:func:`experiment_runner.apps.bench.campaign_trials_per_s`):

* ``campaign``: Table 4.2 campaign trials/s on 1, 2, 4, ... local worker processes of one thread
  each and on a Dask ``LocalCluster`` of as many; on all cores also with the chunking of before
  (one chunk size per job, an fsync per chunk: ``legacy``);
* ``threads``: one process with 1 and with every core as numba threads, with this version's
  chunks (a memory budget per thread) and the legacy ones, and the share of the wall time spent
  inside the compiled batch kernel (the rest is Python between kernel calls: Amdahl);
* ``kernel``: the hypotheses for the threads' scaling, on the batch engine alone
  (:func:`experiment_runner.core.batch.simulate`, Table 4.2's No FI case, 5 mm): for ``size`` trials
  per thread, the time of ``size`` trials on one thread against ``N * size`` trials on ``N``
  threads (efficiency 1 = perfect), with each threading layer numba has here (a process each),
  and against ``N`` processes each running ``size`` trials at once (no shared memory). The
  batch size's own effect cancels (both sides run chunks of ``size``); what is left is what
  threads share: false sharing of neighbouring chunks' state, page faults in one address
  space, the threading layer's start and join (OpenMP also with ``OMP_WAIT_POLICY=passive``:
  no spinning at its barriers) -- or, where processes fall short as much, the machine itself
  (memory bandwidth, SMT siblings, clocks).

Writes ``$OUT/scaling.json`` after every measurement (a run cut short keeps what it has) and
``$OUT/scaling.md`` at the end. ``--tiny``: a few trials of each, for a check on a small machine.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

T_START = time.monotonic()


def _cpu_info() -> dict:
    info = {"cpu_count": os.cpu_count(), "affinity": len(os.sched_getaffinity(0)), "kernel": platform.release()}
    try:
        models = [ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                  if ln.startswith("model name")]
        info["model"] = models[0] if models else None
    except OSError:
        pass
    try:
        sib = Path("/sys/devices/system/cpu/cpu0/topology/thread_siblings_list").read_text().strip()
        info["cpu0_thread_siblings"] = sib           # "0,8" or "0-1": SMT (hyper-threads share a core)
    except OSError:
        pass
    try:
        info["smt_active"] = Path("/sys/devices/system/cpu/smt/active").read_text().strip()
    except OSError:
        pass
    return info


class Report:
    """The results, rewritten to ``$OUT/scaling.json`` after every change."""

    def __init__(self, out: Path, meta: dict):
        self.path = out / "scaling.json"
        self.data = {"meta": meta, "campaign": {}, "threads": {}, "kernel": {}, "notes": []}
        self.save()

    def put(self, section: str, key: str, value) -> None:
        self.data[section][key] = value
        print(f"[{time.monotonic() - T_START:6.1f} s] {section} {key}: {json.dumps(value)}", flush=True)
        self.save()

    def save(self) -> None:
        self.data["meta"]["elapsed_s"] = round(time.monotonic() - T_START, 1)
        self.data["meta"]["loadavg"] = os.getloadavg()
        self.path.write_text(json.dumps(self.data, indent=1))


# =========================================================================== legacy chunking
def legacy(stream_mod):
    """Context: the chunking of before this change (one size per job from the job's trials and the
    whole campaign's, a memory budget per worker whatever its threads, an fsync per chunk)."""
    import contextlib

    @contextlib.contextmanager
    def patched():
        saved = stream_mod.chunk_size, stream_mod.SYNC_SECONDS
        first = {}

        def old_size(n, samples, workers, total=None, threads=1):
            key = samples                      # one size per job (the jobs of one condition share it)
            if key not in first:
                cap = max(1, int(stream_mod.CHUNK_BYTES // (samples * stream_mod.STREAM_BYTES_PER_SAMPLE)))
                want = max(1, min(cap, n, math.ceil((total or n) / (2 * workers))))
                first[key] = math.ceil(n / math.ceil(n / want))
            return min(n, first[key])

        stream_mod.chunk_size, stream_mod.SYNC_SECONDS = old_size, 0.0
        try:
            yield
        finally:
            stream_mod.chunk_size, stream_mod.SYNC_SECONDS = saved
    return patched()


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


# =========================================================================== campaign on workers
def campaign_part(rep: Report, cores: int, per_case: int, deadline: float) -> None:
    from experiment_runner.apps.bench import campaign_trials_per_s
    from experiment_runner.apps.campaigns import stream as stream_mod
    widths = [w for w in (1, 2, 4, 8, 16, 32, 64) if w <= cores]
    if widths[-1] != cores:
        widths.append(cores)
    order = [1, cores] + [w for w in widths if w not in (1, cores)]     # the figures that matter first
    one = None
    for w in order:
        if time.monotonic() > deadline:
            rep.data["notes"].append(f"campaign: stopped before {w} workers (deadline)")
            break
        n = per_case * w
        c0 = _cpu_s()
        r = campaign_trials_per_s(w, n, threads=1)
        entry = {"trials_per_case": n, "trials_per_s": round(r, 1), "parent_cpu_s": round(_cpu_s() - c0, 2)}
        if w == 1:
            one = r
        if one:
            entry["scale"] = round(r / one, 2)
            entry["efficiency"] = round(r / (one * w), 3)
        rep.put("campaign", f"pool_{w}", entry)
        if w == cores and cores > 1:
            with legacy(stream_mod):
                r_old = campaign_trials_per_s(w, n, threads=1)
            rep.put("campaign", f"pool_{w}_legacy", {"trials_per_case": n, "trials_per_s": round(r_old, 1),
                                                     "scale": round(r_old / one, 2) if one else None})
            if time.monotonic() < deadline:
                try:
                    r_dask = campaign_trials_per_s(w, n, dask=True, threads=1)
                    rep.put("campaign", f"dask_{w}", {"trials_per_case": n, "trials_per_s": round(r_dask, 1),
                                                      "vs_pool": round(r_dask / r, 3)})
                except Exception as err:        # noqa: BLE001 - Dask missing or broken here: say so, go on
                    rep.put("campaign", f"dask_{w}", {"error": f"{type(err).__name__}: {err}"[:300]})


# =========================================================================== threads in one process
def threads_part(rep: Report, cores: int, per_case: int) -> None:
    from experiment_runner.apps import bench
    from experiment_runner.apps.campaigns import stream as stream_mod
    from experiment_runner.core import batch
    kernel, jobs = batch.run_chunks, bench.run_trial_jobs
    spent, wall = [0.0], [0.0]

    def timed_kernel(*args):
        t0 = time.perf_counter()
        try:
            return kernel(*args)
        finally:
            spent[0] += time.perf_counter() - t0

    def timed_jobs(*args, **kw):                     # the bench's timed part: the campaign's trials
        spent[0] = 0.0
        t0 = time.perf_counter()
        try:
            return jobs(*args, **kw)
        finally:
            wall[0] = time.perf_counter() - t0

    batch.run_chunks, bench.run_trial_jobs = timed_kernel, timed_jobs
    try:
        base = {}
        for mode in ("now", "legacy"):
            for t in sorted({1, cores}):
                if mode == "legacy":
                    with legacy(stream_mod):
                        r = bench.campaign_trials_per_s(1, per_case, threads=t)
                else:
                    r = bench.campaign_trials_per_s(1, per_case, threads=t)
                if t == 1:
                    base[mode] = r
                rep.put("threads", f"{mode}_{t}", {
                    "trials_per_s": round(r, 1), "scale": round(r / base[mode], 2),
                    "kernel_share": round(spent[0] / wall[0], 3), "kernel_s": round(spent[0], 2),
                    "other_s": round(wall[0] - spent[0], 2)})
    finally:
        batch.run_chunks, bench.run_trial_jobs = kernel, jobs


# =========================================================================== kernel hypotheses
def _job():
    from experiment_runner.apps.campaigns.spec import case_preset, conditions, load_campaign
    from experiment_runner.apps.campaigns.trials import reference
    from experiment_runner.core.batch import Models
    camp = load_campaign("table_4_2")
    cond = conditions(camp)[0]
    preset = case_preset(camp, camp.cases[0], None, cond)
    return preset, Models.from_preset(preset), reference(camp, cond, preset.controller.rate)


def _best(n: int, reps: int) -> tuple[float, int]:
    """Best wall time of ``simulate`` of ``n`` trials, and the minor page faults of one call."""
    from experiment_runner.core.batch import simulate
    preset, models, ref = _JOB
    best, faults = math.inf, 0
    for _ in range(reps):
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t0 = time.perf_counter()
        simulate(preset, ref.x, ref.v, n_trials=n, models=models, check=False)
        best = min(best, time.perf_counter() - t0)
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0
    return best, faults


_JOB = None


def _proc_task(size: int, reps: int, start_at: float) -> float:
    """A worker process's part of the processes reference: ``size`` trials, best of ``reps``,
    started together with the others (``start_at``: wall clock)."""
    global _JOB
    import numba
    numba.set_num_threads(1)
    if _JOB is None:
        _JOB = _job()
        _best(size, 1)
    time.sleep(max(0.0, start_at - time.time()))
    return _best(size, reps)[0]


def kernel_child(sizes: list, reps: int, cores: int) -> dict:
    """In a process of its own (its threading layer): one-thread and all-thread times per size."""
    global _JOB
    import numba
    _JOB = _job()
    numba.set_num_threads(1)
    _best(2, 1)                                       # compile / load the kernel, start the layer
    out = {"layer": numba.threading_layer(), "numba": numba.__version__, "threads": cores, "sizes": {}}
    for size in sizes:
        numba.set_num_threads(1)
        t1, f1 = _best(size, reps)
        numba.set_num_threads(cores)
        tn, fn = _best(cores * size, reps)
        out["sizes"][str(size)] = {"t1_ms": round(t1 * 1e3, 2), "tN_ms": round(tn * 1e3, 2),
                                   "efficiency": round(t1 / tn, 3), "faults_1": f1, "faults_N": fn,
                                   "ms_per_trial_1": round(t1 * 1e3 / size, 3)}
    return out


def kernel_part(rep: Report, cores: int, sizes: list, reps: int, deadline: float) -> None:
    import numba
    variants = {"omp": {"NUMBA_THREADING_LAYER": "omp"},
                "omp_passive": {"NUMBA_THREADING_LAYER": "omp", "OMP_WAIT_POLICY": "passive"},
                "workqueue": {"NUMBA_THREADING_LAYER": "workqueue"}, "tbb": {"NUMBA_THREADING_LAYER": "tbb"}}
    for layer, extra in variants.items():
        if time.monotonic() > deadline:
            rep.data["notes"].append(f"kernel: stopped before layer {layer} (deadline)")
            return
        env = {**os.environ, **extra, "NUMBA_NUM_THREADS": str(max(cores, 1))}
        code = (f"import json, sys; sys.path.insert(0, {str(Path(__file__).parent)!r}); import device_scaling as d; "
                f"print('RESULT ' + json.dumps(d.kernel_child({sizes!r}, {reps}, {cores})))")
        try:
            run = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                 timeout=max(10.0, deadline - time.monotonic()))
            lines = [ln for ln in run.stdout.splitlines() if ln.startswith("RESULT ")]
            err = (run.stderr or run.stdout).strip().splitlines() or ["no output"]
            val = json.loads(lines[-1][7:]) if lines else {
                "error": next((ln for ln in reversed(err) if "Error" in ln), err[-1])[:300]}
        except subprocess.TimeoutExpired:
            val = {"error": "timed out"}
        rep.put("kernel", f"threads_{layer}", val)
    if time.monotonic() > deadline:
        return
    from experiment_runner.core.executor import make_executor
    with make_executor(cores) as ex:                  # one thread each
        ex.warm_all(_proc_task, (sizes[0], 1, 0.0))
        res = {}
        for size in sizes:
            start = time.time() + 1.0
            times = [t for _, t in ex.map(_proc_task, [(i, (size, reps, start)) for i in range(cores)],
                                          window=cores)]
            res[str(size)] = {"mean_ms": round(1e3 * sum(times) / len(times), 2),
                              "max_ms": round(1e3 * max(times), 2)}
        rep.put("kernel", "processes", {"processes": cores, "sizes": res})
    del numba


# =========================================================================== Markdown
def markdown(data: dict) -> str:
    m = data["meta"]
    lines = [f"# Scaling on {m['cpu'].get('model')} ({m['cores']} cores usable; cpu0 SMT siblings "
             f"{m['cpu'].get('cpu0_thread_siblings')}; load {', '.join(f'{x:.1f}' for x in m['loadavg'])})", "",
             f"numba {m.get('numba')} ({m.get('threading_layer')}), numpy {m.get('numpy')}, Python {m['python']}; "
             f"warm-up (compile) {m.get('warmup_s')} s; total {m['elapsed_s']} s", ""]
    c = data["campaign"]
    if c:
        lines += ["## Campaign trials/s (Table 4.2, no calibration), worker processes of one thread", "",
                  "| workers | trials/s | x one worker | efficiency | parent CPU s |", "|---|---|---|---|---|"]
        for k in sorted((k for k in c if k.startswith("pool_") and not k.endswith("legacy")),
                        key=lambda k: int(k.split("_")[1])):
            e = c[k]
            lines.append(f"| {k.split('_')[1]} | {e['trials_per_s']} | {e.get('scale', '')} | "
                         f"{e.get('efficiency', '')} | {e.get('parent_cpu_s', '')} |")
        for k, e in c.items():
            if k.endswith("legacy"):
                lines.append(f"| {k.split('_')[1]} (chunks of before) | {e['trials_per_s']} | {e.get('scale', '')} "
                             "| | |")
            if k.startswith("dask_"):
                lines.append(f"| Dask LocalCluster({k.split('_')[1]}) | {e.get('trials_per_s', e.get('error'))} | | "
                             f"vs pool {e.get('vs_pool', '')} | |")
        lines.append("")
    t = data["threads"]
    if t:
        lines += ["## One process, numba threads (campaign trials/s)", "",
                  "| chunks | threads | trials/s | x one thread | in the kernel s | outside s (Python between calls) |",
                  "|---|---|---|---|---|---|"]
        for k, e in t.items():
            mode, n = k.rsplit("_", 1)
            lines.append(f"| {mode} | {n} | {e['trials_per_s']} | {e['scale']} | {e['kernel_s']} | {e['other_s']} |")
        lines.append("")
    kern = data["kernel"]
    if kern:
        lines += ["## Batch kernel alone: efficiency of N threads (t one thread, size trials / t N threads, N x size)",
                  "", "| layer | " + " | ".join(f"{s} per thread" for s in data["meta"]["sizes"]) + " |",
                  "|---|" + "---|" * len(data["meta"]["sizes"])]
        for k, e in kern.items():
            if k.startswith("threads_"):
                if "sizes" in e:
                    cells = [f"{e['sizes'][str(s)]['efficiency']} ({e['sizes'][str(s)]['ms_per_trial_1']} ms/trial)"
                             for s in data["meta"]["sizes"] if str(s) in e["sizes"]]
                    lines.append(f"| {k[8:]} ({e['layer']}) | " + " | ".join(cells) + " |")
                else:
                    lines.append(f"| {k[8:]} | {e.get('error', '')[:120]} |")
        if "processes" in kern and "threads_omp" in kern and "sizes" in kern["threads_omp"]:
            ref = kern["threads_omp"]["sizes"]
            cells = [f"{round(ref[str(s)]['t1_ms'] / v['mean_ms'], 3)}"
                     for s, v in ((int(s), v) for s, v in kern["processes"]["sizes"].items())]
            lines.append(f"| {kern['processes']['processes']} processes (t1 / mean) | " + " | ".join(cells) + " |")
        lines.append("")
    if data["notes"]:
        lines += ["Notes: " + "; ".join(data["notes"]), ""]
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tiny", action="store_true", help="a few trials of each (a check on a small machine)")
    ap.add_argument("--budget", type=float, default=330.0, help="seconds for the measurements (after the warm-up)")
    ap.add_argument("--warmup-s", type=float, default=None, help="the warm-up's time, for the report")
    args = ap.parse_args()
    import numba
    import numpy
    from experiment_runner.core.executor import default_workers
    out = Path(os.environ.get("OUT") or "out/device_scaling")
    out.mkdir(parents=True, exist_ok=True)
    cores = default_workers()
    sizes = [1, 3] if args.tiny else [1, 3, 8, 32]
    meta = {"cores": cores, "cpu": _cpu_info(), "python": platform.python_version(), "numba": numba.__version__,
            "numpy": numpy.__version__, "tiny": args.tiny, "warmup_s": args.warmup_s, "sizes": sizes}
    rep = Report(out, meta)
    deadline = T_START + args.budget
    per_case_pool = 4 if args.tiny else 500
    per_case_threads = 6 if args.tiny else 500
    try:
        campaign_part(rep, cores, per_case_pool, deadline - 150 if not args.tiny else deadline)
        rep.data["meta"]["threading_layer"] = numba.threading_layer()
        if time.monotonic() < deadline - 60:
            threads_part(rep, cores, per_case_threads)
        else:
            rep.data["notes"].append("threads: skipped (deadline)")
        kernel_part(rep, cores, sizes, 3 if args.tiny else 5, deadline)
    finally:
        rep.save()
        (out / "scaling.md").write_text(markdown(rep.data))
        print((out / "scaling.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
