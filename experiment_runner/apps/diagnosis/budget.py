"""The wall-clock budget of one diagnosis and its progress lines on stderr.

A :class:`Budget` starts with the diagnosis (:func:`.pipeline.diagnose`). Each stage reports to it
when done (:meth:`Budget.done`: a progress line ``[diagnose  12.3 s] ...`` on stderr unless
``progress`` is off). While the search runs (:meth:`Budget.searching`: the forward selection), the
candidate fits and refinements call :func:`checkpoint` between model evaluations: once the budget
is spent (or the run was interrupted, :meth:`Budget.halt`) it raises :class:`BudgetReached`, and the
selection drops the unfinished step whole -- a candidate that was mid-fit is never adopted -- and
keeps the model of the last completed step (:class:`.forward.ForwardSelection`). The stages after
the search that only refine the answer are skipped once the budget is spent
(:meth:`Budget.allows`); the validation and the report always run. What was not examined is listed
in the report (:meth:`Budget.summary`, :meth:`Budget.statement`).

Examples
--------
>>> b = Budget(60.0, progress=False)
>>> b.done("predict")
>>> b.allows("joint refit"), b.summary()["reached"]
(True, False)
>>> b.halt("time budget")                    # as when the clock runs out
>>> with b.searching():
...     try:
...         checkpoint()
...     except BudgetReached:
...         b.skip("forward step 1")
>>> b.allows("joint refit")
False
>>> b.statement()
'time budget of 60 s reached after stage predict; not examined: forward step 1, joint refit'
"""
from __future__ import annotations

import math
import sys
import threading
import time
from contextlib import contextmanager
from typing import Callable, Iterable

__all__ = ["Budget", "BudgetReached", "checkpoint", "halt_search", "progress", "parallel_map", "DEFAULT_MAX_SECONDS"]

DEFAULT_MAX_SECONDS = 240.0
"""Default wall-clock budget of a diagnosis [s] (``nanostage diagnose --max-seconds``): the search
stops there; the validation and the report follow."""

_ACTIVE: Budget | None = None
"""The budget of the search running in this process (:meth:`Budget.searching`), or None."""
_LOCK = threading.Lock()


class BudgetReached(Exception):
    """The search stops: the time budget is spent or the run was interrupted (:func:`checkpoint`)."""


class Budget:
    """The wall-clock budget and progress of one diagnosis.

    Parameters
    ----------
    max_seconds : float or None
        The budget [s], from the start (finite, > 0); None: no limit.
    progress : bool
        Progress lines on ``stream``.
    stream : file-like, optional
        Where they go (default ``sys.stderr``).
    """

    def __init__(self, max_seconds: float | None = DEFAULT_MAX_SECONDS, progress: bool = True, stream=None):
        if max_seconds is not None and not (isinstance(max_seconds, (int, float)) and math.isfinite(max_seconds)
                                            and max_seconds > 0):
            raise ValueError(f"max_seconds: got {max_seconds!r}; expected a finite number of seconds > 0 "
                             "(or None: no limit)")
        self.max_seconds = None if max_seconds is None else float(max_seconds)
        self.progress = progress
        self.stream = stream
        self.t0 = time.perf_counter()
        self.stage = None
        """The last stage completed."""
        self.stopped: str | None = None
        """Why the search stopped early (``"time budget"``, ``"interrupted (SIGINT)"``), or None."""
        self.after: str | None = None
        """The last stage completed when it stopped."""
        self.not_examined: list[str] = []
        self.interrupt: BaseException | None = None
        """The interruption (SIGINT / SIGTERM) to raise again once the partial report is written."""
        self._armed = False
        self.jobs = 1
        """Threads of the search's independent model evaluations (:func:`parallel_map`)."""

    def elapsed(self) -> float:
        """Seconds since the start.

        Returns
        -------
        float
        """
        return time.perf_counter() - self.t0

    def spent(self) -> bool:
        """Whether the search must stop (the budget is spent, or :meth:`halt` was called); the first
        time, the stage reached is noted.

        Returns
        -------
        bool
        """
        if self.stopped is None and self.max_seconds is not None and self.elapsed() >= self.max_seconds:
            self.halt("time budget")
        return self.stopped is not None

    def halt(self, why: str) -> None:
        """Stop the search now (``why``: ``"time budget"`` or ``"interrupted (SIGTERM)"`` ...).

        Parameters
        ----------
        why : str
            Why, as the report says it.
        """
        if self.stopped is None:
            self.stopped, self.after = why, self.stage

    def say(self, text: str) -> None:
        """A progress line with the elapsed seconds (when ``progress``).

        Parameters
        ----------
        text : str
            The line.
        """
        if self.progress:
            print(f"[diagnose {self.elapsed():7.1f} s] {text}", file=self.stream or sys.stderr, flush=True)

    def done(self, stage: str, detail: str = "") -> None:
        """Stage ``stage`` is complete (a progress line).

        Parameters
        ----------
        stage : str
            The stage's name.
        detail : str, optional
            Appended to the line.
        """
        self.stage = stage
        self.say(f"{stage} done" + (f": {detail}" if detail else ""))

    def skip(self, what: str) -> None:
        """``what`` was not examined (the budget was spent first).

        Parameters
        ----------
        what : str
            The stage or step, in words.
        """
        if what not in self.not_examined:
            self.not_examined.append(what)

    def allows(self, what: str) -> bool:
        """Whether the optional stage ``what`` may run; if not, it is noted as not examined.

        Parameters
        ----------
        what : str
            The stage, in words.

        Returns
        -------
        bool
        """
        if self.spent():
            self.skip(what)
            return False
        return True

    def check(self) -> None:
        """Raise :class:`BudgetReached` while searching once the budget is spent."""
        if self._armed and self.spent():
            raise BudgetReached(self.stopped)

    @contextmanager
    def searching(self):
        """Inside, :func:`checkpoint` (in the fits and refinements of this process) checks this budget."""
        global _ACTIVE
        with _LOCK:
            prev, _ACTIVE = _ACTIVE, self
        self._armed = True
        try:
            yield self
        finally:
            self._armed = False
            with _LOCK:
                _ACTIVE = prev

    def statement(self) -> str | None:
        """The report's leading sentence when the search stopped early, else None.

        Returns
        -------
        str or None
        """
        if self.stopped is None:
            return None
        what = "not examined: " + (", ".join(self.not_examined) if self.not_examined else "nothing")
        after = f"after stage {self.after}" if self.after else "before the first stage completed"
        if self.stopped == "time budget":
            return f"time budget of {self.max_seconds:g} s reached {after}; {what}"
        return f"{self.stopped} {after}; {what}"

    def summary(self) -> dict:
        """The report's ``budget`` section.

        Returns
        -------
        dict
            ``max_seconds``, ``spent_s``, ``reached``, ``stopped``, ``after_stage``, ``not_examined``, ``statement``.
        """
        return {"max_seconds": self.max_seconds, "spent_s": self.elapsed(), "reached": self.stopped is not None,
                "stopped": self.stopped, "after_stage": self.after, "not_examined": list(self.not_examined),
                "statement": self.statement()}


def checkpoint() -> None:
    """Between model evaluations of the search: raise :class:`BudgetReached` when the running
    search's budget is spent (no search running: nothing)."""
    b = _ACTIVE
    if b is not None:
        b.check()


def halt_search(why: str) -> None:
    """Stop the running search (an interruption noticed where the fits are waited on).

    Parameters
    ----------
    why : str
        Why, as the report says it.
    """
    b = _ACTIVE
    if b is not None:
        b.halt(why)


def progress(text: str) -> None:
    """A progress line of the running search (none running: nothing).

    Parameters
    ----------
    text : str
        The line.
    """
    b = _ACTIVE
    if b is not None:
        b.say(text)


_WORKER = threading.local()
"""``on`` in the threads of a :func:`parallel_map` (a nested one runs in its caller's thread)."""


def parallel_map(fn: Callable, items: Iterable, n_jobs: int | None = None) -> list:
    """``[fn(x) for x in items]`` on ``n_jobs`` threads (None: the running search's
    :attr:`Budget.jobs`, 1 when none runs), in the items' order: the search's independent model
    evaluations (the compiled kernels release the GIL), so that the result does not depend on the
    thread count. Called from a thread of another ``parallel_map``, it runs in that thread (the
    cores are busy already). An interruption (SIGINT / SIGTERM) halts the running search, so that
    the evaluations still running stop at their next :func:`checkpoint`, and is raised again; an
    exception of ``fn`` is raised as from the loop.

    Parameters
    ----------
    fn : callable
        One evaluation, ``fn(item)``; it must not depend on the other items' results.
    items : iterable
        The items, evaluated each once.
    n_jobs : int, optional
        Threads; None: the running search's :attr:`Budget.jobs` (1 when none runs).

    Returns
    -------
    list
        ``fn(item)`` for each item, in the items' order.

    Examples
    --------
    >>> parallel_map(lambda x: x * x, [1, 2, 3], n_jobs=2)
    [1, 4, 9]
    """
    items = list(items)
    if n_jobs is None:
        b = _ACTIVE
        n_jobs = b.jobs if b is not None else 1
    if n_jobs <= 1 or len(items) <= 1 or getattr(_WORKER, "on", False):
        return [fn(x) for x in items]
    from concurrent.futures import ThreadPoolExecutor

    def run(x):
        _WORKER.on = True
        try:
            return fn(x)
        finally:
            _WORKER.on = False
    with ThreadPoolExecutor(min(n_jobs, len(items))) as pool:
        try:
            return list(pool.map(run, items))
        except KeyboardInterrupt as err:
            halt_search(f"interrupted ({err or 'SIGINT'})")
            raise
