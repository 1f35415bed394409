"""Where independent tasks run: in this process, on a local process pool, or on Dask.

Campaign trial chunks (:mod:`experiment_runner.apps.campaigns.stream`), design sweeps and diagnosis
candidate fits are lists of independent tasks: a plain, picklable, module-level function
called with small arguments (preset JSON, trial indices, seeds, parameter values).
:func:`make_executor` returns one object with one method, :meth:`Executor.map`, that runs
them

* in this process, one after the other (``workers=1``, the default of the Python API: the batch
  engine's ``numba.prange`` spreads a chunk of trials over the process's threads);
* on a local pool of ``workers`` spawned processes, each with ``cores // workers`` numba
  threads;
* on a Dask distributed cluster (``cluster`` = scheduler address such as
  ``tcp://10.0.0.5:8786``, or a ``distributed`` cluster object such as ``LocalCluster``);
  every worker needs this package installed (same version). Tasks sharing one worker
  process run one at a time there (the numba kernels use the worker's threads).

and yields ``(task id, result)`` pairs as the tasks complete. :func:`default_workers` is the one
place that decides how many cores "every core" is (the CPUs this process may run on, capped by
its cgroup's CPU quota): the commands' default ``--workers`` (campaigns, design sweeps) and the
diagnosis' candidate-fit threads. Worker processes, not threads, are the default where a command
runs many similar tasks: on 16 cores, 16 one-thread processes ran Table 4.2 trials 15.96x as fast
as one, one process with 16 numba threads 5.14x (``docs/speed.md``). A cluster of several machines,
each with this package installed in the same version (``scripts/bootstrap.sh``)::

    dask scheduler                                   # on one machine: tcp://HOST:8786
    dask worker tcp://HOST:8786 --nworkers 2 --nthreads 1   # on each machine (processes x threads)
    nanostage campaign table_4_2 --trials 10000 --cluster tcp://HOST:8786

Only a few tasks are in flight at any time (``window``), so a long task list does not hold
all its arguments or results.
Compiled numba kernels are loaded from the on-disk cache (``cache=True``) once per worker
process; tasks can keep per-process caches of built models (``functools.lru_cache``).

Examples
--------
>>> with make_executor() as ex:
...     sorted(ex.map(pow, [("a", (2, 3)), ("b", (3, 2))]))
[('a', 8), ('b', 9)]
"""
from __future__ import annotations

import concurrent.futures as cf
import math
import os
import threading
import time
from pathlib import Path
from typing import Callable, Hashable, Iterable, Iterator, Optional

import numba

from experiment_runner.core.cliargs import dask_address, positive_int
from stage_sim.config import ConfigError

__all__ = ["Executor", "make_executor", "local_cluster", "default_workers", "cgroup_cpu_limit"]

Task = tuple[Hashable, tuple]
"""A task: its id (any hashable, e.g. ``(case, condition, first_trial)``) and the positional
arguments of the function."""


def cgroup_cpu_limit(root: str = "/sys/fs/cgroup", self_cgroup: str = "/proc/self/cgroup") -> Optional[float]:
    """CPUs this process's cgroup may use (CPU quota / period), the tightest along its path; None: no quota.

    Reads cgroup v2 ``cpu.max`` (``"200000 100000"``, or ``"max 100000"``: none) and v1
    ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us`` (quota -1: none), in the process's own cgroup
    (``/proc/self/cgroup``) and its parents, and at ``root`` itself (a container's namespace).

    Examples
    --------
    >>> import pathlib, tempfile
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = (d / "cpu.max").write_text("250000 100000\\n")
    >>> cgroup_cpu_limit(str(d), str(d / "none"))
    2.5
    """
    dirs = {Path(root), Path(root) / "cpu", Path(root) / "cpu,cpuacct"}
    try:
        lines = Path(self_cgroup).read_text().splitlines()
    except OSError:
        lines = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        if controllers == "" or "cpu" in controllers.split(","):
            base = Path(root) / ("" if controllers == "" else controllers)
            d = base / path.lstrip("/")
            while True:
                dirs.add(d)
                if d == base or d.parent == d:
                    break
                d = d.parent
    limits = []
    for d in dirs:
        try:
            quota, _, period = (d / "cpu.max").read_text().partition(" ")
            if quota != "max":
                limits.append(float(quota) / float(period))
            continue
        except (OSError, ValueError):
            pass
        try:
            quota = float((d / "cpu.cfs_quota_us").read_text())
            if quota > 0:
                limits.append(quota / float((d / "cpu.cfs_period_us").read_text()))
        except (OSError, ValueError):
            pass
    limits = [x for x in limits if x > 0]
    return min(limits) if limits else None


def default_workers() -> int:
    """Cores this process may use: the CPUs it may run on (``os.sched_getaffinity``), capped by its
    cgroup's CPU quota (:func:`cgroup_cpu_limit`, rounded up); at least 1. The default number of
    worker processes or threads of every command that spreads work over the machine."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:      # not Linux
        cpus = os.cpu_count() or 1
    quota = cgroup_cpu_limit()
    if quota is not None:
        cpus = min(cpus, math.ceil(quota))
    return max(1, cpus)


_THREADS: Optional[int] = None
"""Numba threads of this worker's tasks (set at its start-up)."""


def _set_numba_threads(threads: int) -> None:
    """Worker start-up: numba threads of this process's tasks (pool initializer, Dask ``client.run``).

    Numba's thread count is per calling thread: a pool worker runs its tasks in the thread that
    ran the initializer, a Dask worker in threads of its own, so :func:`_locked_call` applies
    :data:`_THREADS` again in the thread that runs the task."""
    global _THREADS
    _THREADS = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(_THREADS)


def _pool_worker_init(threads: int, parent: int) -> None:
    """Local pool worker start-up: numba threads, and exit when the parent process is gone
    (killed: a pool worker would otherwise wait for tasks forever)."""
    _set_numba_threads(threads)

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="nanostage-parent-watch").start()


_TASK_LOCK = threading.Lock()


def _locked_call(fn: Callable, args: tuple):
    """Run ``fn(*args)`` holding this process's task lock (Dask workers with several threads), with
    the worker's numba threads (not the default of every core: two workers of one thread each
    on two cores would otherwise run four numba threads)."""
    with _TASK_LOCK:
        if _THREADS is not None:
            numba.set_num_threads(_THREADS)
        return fn(*args)


class Executor:
    """Runs tasks and yields their results as they complete; use as a context manager.

    Attributes
    ----------
    kind : str
        ``"inline"``, ``"processes"`` or ``"dask"``.
    workers : int
        Worker processes (Dask: at the time of connecting), i.e. tasks that run at once.
    threads : int
        Numba threads of each worker (inline: this process's, at the time of asking).
    address : str or None
        Dask scheduler address.
    """

    def __init__(self, kind: str, workers: int, pool=None, client=None, own_client: bool = False,
                 threads: Optional[int] = None):
        self.kind = kind
        self.workers = workers
        self._threads = threads
        self._pool = pool
        self._client = client
        self._own_client = own_client
        self.address = client.scheduler_info()["address"] if client is not None else None

    @property
    def threads(self) -> int:
        return numba.get_num_threads() if self._threads is None else self._threads

    # ----------------------------------------------------------------- public
    def map(self, fn: Callable, tasks: Iterable[Task], window: Optional[int] = None) -> Iterator[tuple]:
        """Run ``fn(*args)`` for every ``(task_id, args)`` of ``tasks``; yield ``(task_id, result)``.

        Parameters
        ----------
        fn : callable
            A module-level (picklable) function; its arguments and result must pickle too.
        tasks : iterable of (hashable, tuple)
            Task ids and positional arguments; consumed lazily.
        window : int, optional
            Tasks in flight at most (default ``2 * workers``); bounds the memory held by
            pending arguments and results.

        Yields
        ------
        (task_id, result)
            In order of completion (in order of ``tasks`` for the inline executor).

        Raises
        ------
        Exception
            The first exception a task raised (with a note naming its task id); the tasks
            not yet started are cancelled.
        """
        if self.kind == "inline":
            for key, args in tasks:
                yield key, _run_noted(fn, args, key)
            return
        window = max(1, window or 2 * self.workers)
        it = iter(tasks)
        pending = {}
        try:
            self._fill(fn, it, pending, window)
            while pending:
                for fut in self._wait(list(pending)):
                    key = pending.pop(fut)
                    try:
                        result = fut.result()
                    except Exception as err:
                        err.add_note(f"in task {key!r} ({self.kind} executor)")
                        raise
                    yield key, result
                self._fill(fn, it, pending, window)
        finally:
            for fut in pending:
                fut.cancel()

    def warm(self, fn: Callable, args: tuple) -> None:
        """Start ``fn(*args)`` once per worker and return at once (the local pool only): the workers
        are spawned, import their modules and load their compiled kernels while this process does
        other work (a campaign's calibration); results and errors are dropped (the real tasks meet
        any error again)."""
        if self.kind == "processes":
            for _ in range(self.workers):
                self._pool.submit(fn, *args)

    def warm_all(self, fn: Callable, args: tuple, hold: float = 0.3, rounds: int = 10) -> int:
        """Run ``fn(*args)`` on every worker and return when each has (a benchmark's warm-up: every worker
        spawned, its modules imported, its kernels loaded before a clock starts); returns the workers
        seen. Rounds of one task per worker, each held ``hold`` seconds so that no worker takes two
        while another is still starting, until every worker process has run one.

        >>> with make_executor() as ex:
        ...     ex.warm_all(pow, (2, 3))
        1
        """
        if self.kind == "inline":
            fn(*args)
            return 1
        seen: set = set()
        for _ in range(rounds):
            tasks = [(i, (fn, tuple(args), hold)) for i in range(self.workers)]
            seen.update(pid for _, pid in self.map(_held, tasks, window=self.workers))
            if len(seen) >= self.workers:
                break
        return len(seen)

    def close(self) -> None:
        """Stop the pool / disconnect from Dask (a cluster passed in stays up)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._client is not None and self._own_client:
            self._client.close()
        self._client = None

    def __enter__(self) -> "Executor":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        where = f" at {self.address}" if self.address else ""
        return f"Executor({self.kind}, workers={self.workers}{where})"

    # ----------------------------------------------------------------- internals
    def _fill(self, fn, it, pending, window):
        while len(pending) < window:
            try:
                key, args = next(it)
            except StopIteration:
                return
            if self.kind == "processes":
                fut = self._pool.submit(fn, *args)
            else:
                fut = self._client.submit(_locked_call, fn, tuple(args), pure=False)
            pending[fut] = key

    def _wait(self, futures):
        if self.kind == "processes":
            done, _ = cf.wait(futures, return_when=cf.FIRST_COMPLETED)
        else:
            from distributed import wait
            done, _ = wait(futures, return_when="FIRST_COMPLETED")
        return [f for f in futures if f in done]     # submission order among the finished


def _held(fn: Callable, args: tuple, hold: float):
    """:meth:`Executor.warm_all`'s task: ``fn(*args)``, then wait until ``hold`` seconds have passed; the
    worker's (host, process id)."""
    t0 = time.monotonic()
    fn(*args)
    time.sleep(max(0.0, hold - (time.monotonic() - t0)))
    return os.uname().nodename, os.getpid()


def _run_noted(fn, args, key):
    try:
        return fn(*args)
    except Exception as err:
        err.add_note(f"in task {key!r} (inline executor)")
        raise


def add_executor_arguments(parser, what: str, workers_default: Optional[int] = None,
                           workers_help: str = "default: this process") -> None:
    """``--workers N`` and ``--cluster ADDRESS`` of a command that runs ``what`` through
    :func:`make_executor`."""
    parser.add_argument("--workers", type=positive_int, default=workers_default,
                        help=f"local worker processes for the {what} ({workers_help})")
    parser.add_argument("--cluster", type=dask_address, default=None, metavar="ADDRESS",
                        help=f"Dask scheduler address (e.g. tcp://host:8786) to run the {what} on")


WORKER_CONFIG = {
    # the worker's statistical profiler samples every thread's stack every 10 ms: a few % to tens of %
    # of a task that spends its time in Python and numba calls
    "distributed.worker.profile.enabled": False,
    # the nanny's default environment minus MALLOC_TRIM_THRESHOLD_=65536, which returns freed memory
    # to the system at once: every simulate() then page-faults its trajectory buffers in again
    "distributed.nanny.pre-spawn-environ": {"OMP_NUM_THREADS": 1, "MKL_NUM_THREADS": 1, "OPENBLAS_NUM_THREADS": 1},
}
"""Dask configuration of the workers that run the trials (:func:`local_cluster`). Measured on 2
cores: a chunk of 10 Table 4.2 trials took ~2x as long on a default ``LocalCluster`` worker as on
a pool worker, about the same with this. Workers of a cluster of your own: start them with the
same settings (``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False`` in their environment, and
``MALLOC_TRIM_THRESHOLD_`` not set by their nanny)."""


def local_cluster(workers: int, threads: int = 1):
    """A Dask ``LocalCluster`` of ``workers`` processes with ``threads`` threads each, configured
    with :data:`WORKER_CONFIG`; use as a context manager, pass it as ``cluster``."""
    import dask
    from distributed import LocalCluster
    with dask.config.set(WORKER_CONFIG):
        return LocalCluster(n_workers=workers, threads_per_worker=threads, processes=True, dashboard_address=None)


def make_executor(workers: Optional[int] = None, cluster=None) -> Executor:
    """An :class:`Executor` for ``workers`` local processes or a Dask cluster.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (default 1 = run in this process). Ignored with ``cluster``.
    cluster : str or distributed cluster, optional
        Dask scheduler address (``tcp://host:8786``) or a cluster object (``LocalCluster``).

    Returns
    -------
    Executor

    Raises
    ------
    stage_sim.config.ConfigError
        ``workers`` below 1, or the Dask scheduler cannot be reached (message names it).
    """
    if cluster is not None:
        from distributed import Client
        try:
            client = Client(cluster, timeout="20s")
        except (OSError, TimeoutError) as err:
            raise ConfigError(f"--cluster {cluster!r}: cannot connect to the Dask scheduler ({err})") from None
        info = client.scheduler_info()["workers"]
        for addr, w in info.items():     # numba threads = the worker's threads
            client.run(_set_numba_threads, w.get("nthreads", 1), workers=[addr])
        return Executor("dask", max(1, len(info)), client=client, own_client=True,
                        threads=min((w.get("nthreads", 1) for w in info.values()), default=1))
    workers = 1 if workers is None else int(workers)
    if workers < 1:
        raise ConfigError(f"--workers: must be >= 1 (got {workers})")
    if workers == 1:
        return Executor("inline", 1)
    import multiprocessing as mp
    threads = max(1, default_workers() // workers)
    pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                                  initializer=_pool_worker_init, initargs=(threads, os.getpid()))
    return Executor("processes", workers, pool=pool, threads=threads)
