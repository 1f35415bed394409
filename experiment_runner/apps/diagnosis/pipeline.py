"""The diagnosis pipeline: predict -> locate -> name -> fit and choose -> show.

:func:`diagnose` takes a contract recording and the nominal model that was supposed to predict it
and returns the report (a JSON-able dict, fields documented in :mod:`.report`); with ``out`` it also
writes ``report.json``, ``report.md``, plots and the improved model (``improved_preset.yaml``).

The stages, in order, each a function returning a typed result the later ones read:
:func:`.stages.read` -> :func:`.stages.quantization` -> :func:`.stages.predict` ->
:func:`.stages.drive_noise_prior` -> :func:`.stages.locate` -> :func:`.stages.prepare` -> the forward selection
(:class:`.forward.ForwardSelection`: candidates fitted by :mod:`.tasks`, judged and chosen by
:mod:`.selection`, refined by :mod:`.refining` / :mod:`.refinement`, adopted by :mod:`.adoption`)
-> :func:`.closing.refit_jointly` -> :func:`.closing.drive_noise` -> :func:`.uncertainty.widen` ->
:func:`.verdict.withdraw_unidentified` -> :func:`.verdict.validate` -> :func:`.verdict.assemble`. Same data, same decision: no random draw;
the candidate fits give the same report on threads, local processes or a Dask cluster
(:mod:`.tasks`).

Time is bounded (:mod:`.budget`, ``Options.max_seconds``): once the budget is spent the selection
stops, keeping the model of its last completed step (a step cut short is dropped whole), the joint
refit, drive-noise level, uncertainty widening and sparse regression are skipped, and the validation
and the report follow, led by the statement of what was not examined (report ``budget``). A SIGINT
or SIGTERM during the selection ends it the same way; the partial report (marked interrupted) is
written and the interruption raised again. Each stage and step prints a progress line on stderr
(``Options.progress``).
"""
from __future__ import annotations

import contextlib
import threading
import time

from threadpoolctl import threadpool_limits

from experiment_runner.core.executor import make_executor

from . import closing, signatures, stages, uncertainty
from .budget import Budget
from .data import DiagData
from .forward import ForwardSelection
from .options import Options
from .report import write_report
from .tasks import forget, shared_state, warm_up
from .locate import locate as locate_residual
from .verdict import (Run, assemble, detection_limits, improved_name, plot_arrays, sparse_terms, validate,
                      withdraw_unidentified)

__all__ = ["diagnose", "diagnose_stages"]


def diagnose(recording, nominal, out=None, options: Options | None = None, data: DiagData | None = None) -> dict:
    """Diagnose ``recording`` (path / Recording) against ``nominal`` (preset name/path/model file,
    :class:`.model.ModelSpec` or mapping); ``data``: the recording already loaded (``recording`` may
    then be None). Returns the report with ``_improved_spec`` (the improved model)
    (:func:`diagnose_stages`' report).

    Parameters
    ----------
    recording : str, pathlib.Path or Recording
        A contract recording (MCAP file or bag folder); None when ``data`` is given.
    nominal : str, pathlib.Path, dict or ModelSpec
        The model that was supposed to predict it (:func:`.model.load_model`).
    out : str or pathlib.Path, optional
        Output folder of ``report.json``, ``report.md``, ``improved_preset.yaml`` and the plots (None: nothing written).
    options : Options, optional
        How to diagnose (:class:`.options.Options`; default ``Options()``).
    data : DiagData, optional
        The recording already loaded.

    Returns
    -------
    dict
        The report (fields in :mod:`.report`), with ``_improved_spec``.
    """
    return diagnose_stages(recording, nominal, out, options, data)[0]


def diagnose_stages(recording, nominal, out=None, options: Options | None = None,
                    data: DiagData | None = None) -> tuple[dict, Run]:
    """:func:`diagnose`, returning the report and every stage's result (:class:`.verdict.Run`: the
    judges, the selection's path with the adopted fits, the final model).

    BLAS runs single-threaded meanwhile (``threadpoolctl``): the diagnosis works on small
    matrices, many at a time on its own threads, where BLAS threads only contend (3x slower
    on a shared 2-core machine).

    Raises
    ------
    ValueError
        ``options.max_seconds`` not a finite number > 0 (nor None).
    stage_sim.config.ConfigError
        ``options.workers`` below 1, or the Dask scheduler ``options.cluster`` cannot be
        reached (before any work is done); a nominal that does not fit the recording.

    Parameters
    ----------
    recording : str, pathlib.Path or Recording
        A contract recording (MCAP file or bag folder); None when ``data`` is given.
    nominal : str, pathlib.Path, dict or ModelSpec
        The model that was supposed to predict it (:func:`.model.load_model`).
    out : str or pathlib.Path, optional
        Output folder of ``report.json``, ``report.md``, ``improved_preset.yaml`` and the plots (None: nothing written).
    options : Options, optional
        How to diagnose (:class:`.options.Options`; default ``Options()``).
    data : DiagData, optional
        The recording already loaded.

    Returns
    -------
    tuple
        ``(report, Run)``.
    """
    opt = options or Options()
    budget = Budget(opt.max_seconds, progress=opt.progress)
    with threadpool_limits(limits=1, user_api="blas"), contextlib.ExitStack() as stack:
        ex = None
        if opt.workers is not None or opt.cluster is not None:
            ex = stack.enter_context(make_executor(opt.workers, opt.cluster))
            if ex.kind != "inline":
                # start the worker processes (their imports) while this one predicts and locates
                warm = threading.Thread(target=warm_up, args=(ex,), daemon=True, name="nanostage-diagnose-warm-up")
                warm.start()
                stack.callback(warm.join)          # before the executor closes
        return _run(recording, nominal, out, opt, data, ex, budget)


def _run(recording, nominal, out, opt: Options, data: DiagData | None, ex, budget: Budget) -> tuple[dict, Run]:
    """Every stage in order (module docstring)."""
    T0 = time.perf_counter()
    timing: dict = {}
    setup = stages.read(recording, nominal, opt, data, timing)
    budget.done("read", "the nominal replayed")
    lattice = stages.quantization(setup, opt)
    pred = stages.predict(setup, lattice.base, opt, timing)
    pred = stages.drive_noise_prior(setup, lattice, pred, opt, timing)
    budget.done("predict", "force residual, floors")
    loc = stages.locate(setup, lattice.base, pred, opt, timing)
    budget.done("locate")
    t = time.perf_counter()
    problem, J_fit_nominal, J_held_nominal, tol_ad = stages.prepare(setup, lattice.base, pred, loc, opt, ex)
    prior = lattice.stochastic.get("noise_prior", {})
    problem.noise_ratio = 1.0 if "adopted" in prior else prior.get("ratio")
    if ex is not None:        # the candidate-fit tasks' shared state, once
        problem.token, problem.blob = shared_state(problem)
    budget.done("prepare")
    with budget.searching():
        path = ForwardSelection(problem, loc.context, budget).run()
    forget(problem.token)     # this process's copy (an executor running the tasks here, workers=1)
    found = lattice.found + path.found
    n_det = sum(f.effect.kind == "deterministic" for f in path.selected)
    joint = (closing.refit_jointly(problem, path, found)
             if n_det < 2 or budget.allows("joint refit of the adopted effects") else None)
    timing["fit_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if budget.allows("drive-noise level"):
        closing.drive_noise(problem, path, found, lattice.stochastic)
    else:
        lattice.stochastic["noise_level"] = {"nominal_A": problem.base.preset.stage.drive.noise_current_rms,
                                             "found": False, "note": "not examined (time budget)"}
    timing["noise_s"] = time.perf_counter() - t
    t = time.perf_counter()
    if (path.selected and budget.allows("uncertainty widening (the ± given are the fits' own: lower bounds)")
            and uncertainty.widen(pred.fit_judge, found, path.selected, problem.base, path.current, opt)):
        timing["uncertainty_s"] = time.perf_counter() - t
    withdrawn = withdraw_unidentified(problem, path, found)
    if withdrawn and budget.allows("uncertainty widening after a withdrawal"):   # the others' errors without it
        uncertainty.widen(pred.fit_judge, found, path.selected, problem.base, path.current, opt)
        withdrawn += withdraw_unidentified(problem, path, found)
    budget.done("selection", ", ".join(fe["effect"] for fe in found) or "nothing adopted")
    t = time.perf_counter()
    val = validate(setup, pred, problem, path, opt)
    detection = located = None
    if val.adequate:
        if budget.allows("detection limits (what the record could have revealed)"):
            detection = detection_limits(problem, path)
    else:
        located = locate_residual(setup.data, val.residual, path.floor.res_a, path.floor.sim_a,
                                    setup.observer.f_o, setup.band_hz)[0]
    timing["validate_s"] = time.perf_counter() - t
    budget.done("validate")
    sparse = None
    if opt.sparse and not val.adequate and budget.allows("sparse regression of the remaining residual"):
        t = time.perf_counter()
        sparse = sparse_terms(setup.data, val.residual, path.context, setup.band_hz)
        timing["sparse_s"] = time.perf_counter() - t
    left = None
    if not val.adequate:      # keep looking: what the improved model leaves, as numbers (signatures.py)
        t = time.perf_counter()
        left = signatures.remaining(setup.data, val.residual.r, val.held, setup.band_hz,
                                    val.figures["force_residual_rms_N"]["floor"])
        timing["remaining_s"] = time.perf_counter() - t
    run = Run(nominal_source=nominal, setup=setup, stochastic=lattice.stochastic, prediction=pred,
              locate_summary=loc.summary, problem=problem, path=path, found=found, joint=joint,
              J_fit_nominal=J_fit_nominal, J_held_nominal=J_held_nominal, adequacy_tolerance=tol_ad, validation=val,
              withdrawn=withdrawn, detection=detection, remaining=located)
    timing["total_s"] = time.perf_counter() - T0
    path.current = improved_name(path.current, setup.nominal, found)
    report = assemble(run, timing, sparse)
    report["budget"] = budget.summary()
    if budget.stopped is not None:         # never a confident answer from an unfinished search
        report["verdict"] += (" (partial: the time budget was reached)" if budget.stopped == "time budget"
                              else f" (partial: {budget.stopped})")
    arrays = plot_arrays(run, loc.arrays)
    if left is not None:
        arrays["remaining"] = left.pop("arrays")
        report["remaining"] = left
    if out is not None:
        write_report(out, report, path.current, setup.nominal, setup.data, arrays, plots=opt.plots)
        report["timing_s"]["total_s"] = time.perf_counter() - T0
        budget.done("report", str(out))
    report["_improved_spec"] = path.current
    if budget.interrupt is not None:      # the partial report is written: end as interrupted
        raise budget.interrupt
    return report, run
