"""The candidate fits of a forward-selection step: on threads of this process, or as executor tasks.

The fits of a step are independent: by default they run on ``Options.n_jobs`` threads (the compiled
kernels release the GIL); with ``Options.workers`` or ``Options.cluster`` they are tasks
(:func:`candidate_task`) on an :class:`experiment_runner.core.executor.Executor` -- local processes or a
Dask cluster. Each worker process rebuilds the observer from the recording once per diagnosis
(cached by a token), and the fits come back in the order the candidates were submitted, so every
path gives the same report (same effects, bit-identical parameters).
"""
from __future__ import annotations

import math
import os
import pickle
import threading
import uuid

from threadpoolctl import threadpool_limits

from .budget import checkpoint, parallel_map, progress
from .context import Context
from .evaluator import Evaluator
from .fit import FitResult, fit_effect
from .floors import light_floor
from .joint import fit_with, spec_with
from .model import ModelSpec
from .observer import Observer
from .predict import NoiseFloor
from .selection import Candidate, Problem, for_fits_on

__all__ = ["fit_candidate", "candidate_task", "fit_candidates", "shared_state", "forget", "warm_up"]

_STATE: dict = {}                # token -> per-process state of the candidate-fit tasks
_STATE_LOCK = threading.Lock()


def fit_candidate(e, current: ModelSpec, selected: list, J_fit_cur: float, ev: Evaluator, ctx: Context,
                  base: ModelSpec, own_floor: bool, floor_seed: int) -> FitResult | None:
    """Fit candidate effect ``e`` on ``current`` (with the ``selected`` effects re-fitted, from
    step 2 on) and judge it on held-out data; None if it does not apply.

    Parameters
    ----------
    e : Effect
        The candidate (bound to the recording).
    current : ModelSpec
        The current model.
    selected : list of FitResult
        The adopted effects (re-fitted with the candidate from step 2 on).
    J_fit_cur : float
        The current model's force-residual J on the fit samples.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        The located context of this step.
    base : ModelSpec
        The model every path starts from.
    own_floor : bool
        Judge against the candidate's own noise floor.
    floor_seed : int
        Noise seed of that floor's simulated recording.

    Returns
    -------
    FitResult or None
    """
    ctx = for_fits_on(ctx, selected)
    f = fit_with(e, selected, base, ev, ctx) if selected and e.kind == "deterministic" else None
    f = f or fit_effect(e, current, ev, ctx)
    if f is not None and own_floor:
        # judge the candidate against its own noise floor: a change of the drive or the
        # dynamics also changes what noise leaves in the residual (e.g. a force-constant
        # ratio scales the drive noise). A candidate that does not even fit the fit set
        # better than the current model (against the current floor) may only look good
        # by making its own floor noisier (e.g. a stiff, undamped joint): then the larger
        # of the two counts. One that does fit better is not held back by a quieter own
        # floor (e.g. viscous damping over a quantization-only floor): the smaller counts
        f.J_held_base = f.J_held
        try:
            J_own = ev.J(f.spec, "held", floor=light_floor(f.spec, ev.data, ev.obs.f_o, floor_seed, ev.data.smooth_hz))
        except ValueError:        # its simulated recording diverged: no floor of its own, no credit
            J_own = math.inf
        f.J_held = min(J_own, f.J_held_base) if f.J_fit < J_fit_cur else max(J_own, f.J_held_base)
    return f


def shared_state(problem: Problem) -> tuple[str, bytes]:
    """``(token, blob)``: what every candidate-fit task of one diagnosis needs, pickled once (the
    recording smoothed and masked, observer bandwidth, fit-set cap, base model).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on.

    Returns
    -------
    tuple
        ``(token, blob)``.
    """
    opt = problem.options
    blob = pickle.dumps({"data": problem.data, "f_o": problem.observer.f_o, "max_fit_seconds": opt.max_fit_seconds,
                         "base": problem.base, "own_floor": opt.own_floor, "floor_seed": opt.floor_seeds[0]},
                        protocol=pickle.HIGHEST_PROTOCOL)
    return uuid.uuid4().hex, blob


def forget(token: str | None) -> None:
    """Drop this process's copy of diagnosis ``token``'s task state (an executor running the tasks here).

    Parameters
    ----------
    token : str or None
        The diagnosis (None: nothing).
    """
    with _STATE_LOCK:
        _STATE.pop(token, None)


def _task_state(token: str, blob: bytes) -> dict:
    """This process's observer and context of diagnosis ``token`` (built from ``blob`` once;
    the last two diagnoses are kept)."""
    with _STATE_LOCK:
        st = _STATE.get(token)
        if st is None:
            st = pickle.loads(blob)
            # the recording was smoothed and masked by the caller's observer: not redone here
            data = st.pop("data")
            st["obs"] = Observer(data, bandwidth=st.pop("f_o"), smooth_hz=data.smooth_hz)
            while len(_STATE) >= 2:
                _STATE.pop(next(iter(_STATE)))
            _STATE[token] = st
        return st


def candidate_task(token: str, blob: bytes, e, current: ModelSpec, selected: list, J_fit_cur: float,
                   floor: NoiseFloor, ctx: Context):
    """Executor task: :func:`fit_candidate` of the bound effect ``e`` against noise ``floor``.

    ``blob`` is diagnosis ``token``'s shared state (:func:`shared_state`); ``ctx`` the located
    context of this step. BLAS runs single-threaded, as in :func:`.pipeline.diagnose`. Returns
    ``(FitResult or None, error repr or None, evaluations, evaluation seconds)``.

    Parameters
    ----------
    token : str
        The diagnosis.
    blob : bytes
        Its shared state.
    e : Effect
        The bound candidate.
    current : ModelSpec
        The current model.
    selected : list of FitResult
        The adopted effects (re-fitted with the candidate from step 2 on).
    J_fit_cur : float
        The current model's force-residual J on the fit samples.
    floor : NoiseFloor
        The current model's force-residual floor.
    ctx : Context
        The located context of this step.

    Returns
    -------
    tuple
    """
    st = _task_state(token, blob)
    ev = Evaluator(st["obs"], floor, st["max_fit_seconds"])
    with threadpool_limits(limits=1, user_api="blas"):
        try:
            f, err = fit_candidate(e, current, selected, J_fit_cur, ev, ctx, st["base"], st["own_floor"],
                                   st["floor_seed"]), None
        except Exception as exc:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
            f, err = None, repr(exc)
    return f, err, ev.evals, ev.seconds


def fit_candidates(problem: Problem, todo: list[Candidate], current: ModelSpec, selected: list, J_fit_cur: float,
                   ctx: Context) -> tuple[list[FitResult], dict]:
    """Fit every candidate of ``todo`` by the force observer (with the selected effects re-fitted, from step 2 on).

    A replacement (``Candidate.replaces`` set) is fitted on the model without the adopted member
    it replaces. The fits run on the problem's executor (worker processes) when it has one,
    else on ``problem.options.n_jobs`` threads; a failed fit is logged and left out, never
    stops the diagnosis.

    Parameters
    ----------
    problem : Problem
        What the selection works on (options, executor, base model, evaluator).
    todo : list of Candidate
        The step's candidates; sorted in place, most parameters first (for load balance).
    current : ModelSpec
        The current model the candidates are added to.
    selected : list of FitResult
        The adopted effects of ``current``.
    J_fit_cur : float
        The current model's force-residual J on the fit samples (:class:`.selection.Path`
        ``J_fit``), the reference each fit is scored against.
    ctx : Context
        The located context for fits on top of ``selected``.

    Returns
    -------
    fits : list of FitResult
        The successful fits, best first by held-out J times ``1 + complexity x parameters``
        (``problem.options.complexity``).
    failed : dict
        Effect key -> error message of every candidate whose fit failed.
    """
    opt, ex, base, ev = problem.options, problem.executor, problem.base, problem.evaluator
    failed = {}
    # slow (multi-parameter, stiff) candidates first for a better balance; the fits are
    # collected in this order on every path (ties of the score below keep it)
    todo.sort(key=lambda c: -len(c.effect.params(current, ctx)))

    def on(rep):
        """(model, selected effects) a candidate replacing ``rep`` (or none) is fitted on."""
        if rep is None:
            return current, selected
        sel = [f for f in selected if f.key != rep]
        return spec_with(sel, base), sel

    if ex is not None:
        out = [None] * len(todo)
        args = ((i, (problem.token, problem.blob, c.effect) + on(c.replaces) + (J_fit_cur, ev.floor, ctx))
                for i, c in enumerate(todo))
        for i, (f, err, n, sec) in ex.map(candidate_task, args):
            ev.evals += n
            ev.seconds += sec
            if err is not None:
                opt.log(f"fit {todo[i].effect.key} failed: {err}")
                failed[todo[i].effect.key] = err
            out[i] = f
            if f is not None:
                f.replaces = todo[i].replaces
            progress(f"  fitted {todo[i].effect.key}" + ("" if f is not None else " (failed)"))
        fits = [f for f in out if f is not None]
    else:
        def one(c: Candidate):
            try:
                checkpoint()          # the budget spent: the rest is not fitted (the step is dropped)
                f = fit_candidate(c.effect, *on(c.replaces), J_fit_cur, ev, ctx, base, opt.own_floor,
                                  opt.floor_seeds[0])
            except Exception as err:     # noqa: BLE001 - one bad candidate must not stop the diagnosis
                opt.log(f"fit {c.effect.key} failed: {err!r}")
                failed[c.effect.key] = repr(err)
                return None
            if f is not None:
                f.replaces = c.replaces
            progress(f"  fitted {c.effect.key}" + ("" if f is not None else " (failed)"))
            return f
        # the compiled kernels release the GIL: candidates are fitted on parallel threads
        current.compiled()
        fits = [f for f in parallel_map(one, todo, opt.n_jobs) if f is not None]
    fits.sort(key=lambda f: f.J_held * (1 + opt.complexity * len(f.theta)))
    return fits, failed


def _started() -> int:
    """Executor task that does nothing: its worker process has imported this module by now."""
    return os.getpid()


def warm_up(ex) -> None:
    """Run one :func:`_started` per worker of ``ex`` (a background thread of :func:`.pipeline.diagnose`:
    the worker processes import while this one predicts and locates).

    Parameters
    ----------
    ex : experiment_runner.core.executor.Executor
        The executor of the candidate fits.
    """
    try:
        for _ in ex.map(_started, [(i, ()) for i in range(ex.workers)]):
            pass
    except Exception:    # noqa: BLE001 - a broken pool or a lost scheduler fails the candidate fits themselves
        return
