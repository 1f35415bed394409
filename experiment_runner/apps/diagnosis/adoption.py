"""What an adoption changes on a forward-selection path: the adopted effects' values, the model, the
floors, the effects a later one made redundant, and the next proposals.

:func:`adopt_best` adopts a step's choice; :func:`backward` withdraws an earlier effect the later
ones made redundant; :func:`refit_selected` continues the fit of the adopted effects before a step
(a candidate is credited only with what it adds to them); :func:`keep_refit` keeps the adopted
effects' best re-fit when a step adopts nothing.
"""
from __future__ import annotations

import dataclasses

from .fit import FitResult
from .floors import ForceFloor
from .joint import joint_fit, spec_with
from .locate import proposals
from .refinement import REFINE_JOINT_MAX, Refinement, refine_by_replay
from .selection import JudgedRow, Path, Problem, for_fits_on

__all__ = ["adopt_best", "backward", "refit_selected", "keep_refit", "renew_floor", "keep_joint_values"]


def keep_joint_values(problem: Problem, path: Path, jf: FitResult, new: FitResult | None = None) -> None:
    """Keep the re-fitted values of the adopted deterministic effects (joint fit ``jf``), and of
    ``new``, the effect being adopted, when ``jf`` was fitted with it (after the adopted ones).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    jf : FitResult
        The joint fit.
    new : FitResult, optional
        The effect being adopted.
    """
    base = problem.base
    k = 0
    for f, fe in zip(path.selected, path.found):
        if f.effect.kind != "deterministic":
            continue
        n = len(f.theta)
        f.theta, f.sigma = jf.theta[k:k + n], jf.sigma[k:k + n]
        fe["params"] = f.params()
        fe["derived"] = f.effect.derived(base, f.theta)
        k += n
    if new is not None and new.effect.kind == "deterministic" and len(jf.theta) >= k + len(new.theta):
        n = len(new.theta)
        new.theta, new.sigma = jf.theta[k:k + n], jf.sigma[k:k + n]
        new.derived = new.effect.derived(base, new.theta)


def _keep_refined(problem: Problem, path: Path, f: FitResult, ref: Refinement) -> None:
    """Keep a replay refinement ``ref`` of the adopted effect ``f``: the joint values of every adopted
    effect, or ``f``'s own."""
    if ref.joint is not None:
        keep_joint_values(problem, path, ref.joint)
        return
    k = next(i for i, s in enumerate(path.selected) if s is f)
    f.theta, f.sigma = ref.theta, ref.sigma
    path.found[k]["params"] = f.params()
    path.found[k]["derived"] = f.effect.derived(problem.base, f.theta)


def renew_floor(problem: Problem, path: Path, spec) -> None:
    """The noise floors of the current model ``spec`` re-estimated (after every change).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    spec : ModelSpec
        The current model.
    """
    opt, data, ev = problem.options, problem.data, problem.evaluator
    path.floor = ForceFloor(spec, data, problem.observer.f_o, opt.floor_seeds, data.smooth_hz)
    ev.floor = path.floor.noise
    path.J_fit, path.J_held, _ = ev.both(spec)
    path.replay_floor = problem.judge.floor(spec)


def keep_refit(problem: Problem, path: Path) -> bool:
    """When no candidate is adopted: the adopted effects' best re-fit their candidates' joint
    refinements reached (:func:`.refining.own_share`) replaces their values if the held-out replay is
    not worse; the floors are renewed. Returns whether it was kept.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.

    Returns
    -------
    bool
    """
    best, path.refit = path.refit, None
    if best is None:
        return False
    spec, jf = best
    if problem.held_out_D(spec, path.replay_floor) > problem.held_out_D(path.current, path.replay_floor):
        return False
    keep_joint_values(problem, path, jf)
    path.current = spec
    renew_floor(problem, path, spec)
    return True


def _n_deterministic(fits: list) -> int:
    """Parameters of the deterministic fits among ``fits``."""
    return sum(len(s.theta) for s in fits if s.effect.kind == "deterministic")


def _better(problem: Problem, path: Path, spec) -> bool:
    """``spec`` replays the fit samples better than the current model and the held-out ones not worse."""
    return (problem.fit_D(spec, path.replay_floor) < problem.fit_D(path.current, path.replay_floor)
            and not problem.held_out_D(spec, path.replay_floor) > problem.held_out_D(path.current, path.replay_floor))


def refit_selected(problem: Problem, path: Path, step: int) -> None:
    """From the second step on: continue the fit of the adopted effects alone first (a candidate is
    credited only with what it adds to them), kept if the replay of the fit samples is better and the
    held-out replay not worse; the floors renewed if it was; then :func:`_rerefine`.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    step : int
        The forward step (1 = first).
    """
    refitted = False
    for _ in range(3 if step > 1 else 0):
        rf = joint_fit(path.selected, problem.base, problem.evaluator, for_fits_on(path.context, path.selected),
                       min_effects=1, max_iter=8)
        if rf is None or rf.on_bound or not _better(problem, path, rf.spec):
            break
        keep_joint_values(problem, path, rf)
        path.current, path.J_held, path.J_fit = rf.spec, rf.J_held, rf.J_fit
        refitted = True
    if refitted:
        renew_floor(problem, path, path.current)
    if step > 1 and problem.refines:
        _rerefine(problem, path)


def _rerefine(problem: Problem, path: Path) -> None:
    """The adopted deterministic effects refined by the replay again, weighted by the current model's
    own floor, kept on the same terms as :func:`refit_selected`'s; the floors renewed if they were. A
    candidate refined together with them is then credited with what it adds, not with a continuation
    of their own refinement. On an open-loop record the floor's prewhitening depends on the model, and
    the last effect was refined under the floor of the model without it."""
    det = [s for s in path.selected if s.effect.kind == "deterministic"]
    if not det:
        return
    last = det[-1]
    others = [s for s in path.selected if s is not last]
    n_o = _n_deterministic(others)
    ref = refine_by_replay(last, others, problem.base, for_fits_on(path.context, others), problem.fit_judge,
                           path.replay_floor, with_selected=0 < n_o and n_o + len(last.theta) <= REFINE_JOINT_MAX,
                           max_nfev=20)
    if ref is None or ref.on_bound() or not _better(problem, path, ref.spec):
        return
    _keep_refined(problem, path, last, ref)
    path.current = ref.spec
    renew_floor(problem, path, ref.spec)


def backward(problem: Problem, path: Path, last: FitResult) -> bool:
    """Backward elimination after the adoption of ``last``: each earlier adopted deterministic effect
    is re-tested by removing it (the others, ``last`` with them, refined by the replay without it when
    that is better): if the model with it does not replay the held-out data better beyond the floor of
    the model without it (the same test as its adoption), the later effects made it redundant (a mass
    error adopted where a structural mode replayed as well, the mode adopted next): it is withdrawn and
    not proposed again. Returns whether one was.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    last : FitResult
        The effect just adopted.

    Returns
    -------
    bool
    """
    selected, judge = path.selected, problem.judge
    changed = False
    for e in [s for s in selected if s is not last and s.effect.kind == "deterministic"]:
        rest = [s for s in selected if s is not e]
        try:
            spec_wo = spec_with(rest, problem.base)
        except Exception:     # noqa: BLE001 - not a valid model without it: it stays
            continue
        best_wo = (problem.fit_D(spec_wo, path.replay_floor), spec_wo, None)
        others = [s for s in rest if s is not last]
        if problem.refines and last.effect.kind == "deterministic":
            n_o = _n_deterministic(others)
            ref = refine_by_replay(last, others, problem.base, for_fits_on(path.context, others), problem.fit_judge,
                                   path.replay_floor,
                                   with_selected=0 < n_o and n_o + len(last.theta) <= REFINE_JOINT_MAX)
            if ref is not None and not ref.on_bound():
                d = problem.fit_D(ref.spec, path.replay_floor)
                if d < best_wo[0]:
                    best_wo = (d, ref.spec, ref)
        # the adoption test of ``e`` on top of the model without it: the floor (simulated
        # recordings) of the model without it, the current model's replay as the candidate
        fl_wo = judge.floor(best_wo[1])
        if not fl_wo.replay.ok:
            continue
        c = judge.compare(fl_wo, path.replay_floor.replay)
        if c.accepted:
            continue          # the data demand it on top of the later effects
        i = next(k for k, s in enumerate(selected) if s is e)
        selected.pop(i)
        gone = path.found.pop(i)
        path.banned.add(e.key)
        if best_wo[2] is not None:
            _keep_refined(problem, path, last, best_wo[2])
        path.current = best_wo[1]
        path.found[-1].setdefault("withdraws", []).append(
            {"effect": gone["effect"], "step": gone["step"], "params": gone["params"],
             "replay": c.row(), "why": f"redundant after {last.key}: {c.why}"})
        problem.options.log(f"backward: {gone['effect']} withdrawn after {last.key} ({c.why})")
        changed = True
    return changed


def _adopted_values(problem: Problem, path: Path, step: int, best: JudgedRow):
    """The model with the chosen candidate ``best.fit`` and the adopted effects' values: their joint
    fit with it, or (an integer effect fitted with the others held) their re-fit with it; then all of
    them refined together by the replay of the fit samples, kept off their bounds and if the held-out
    replay is not worse. Returns the new model; the fits' values are updated."""
    bf, selected, base = best.fit, path.selected, problem.base
    new_spec = bf.spec
    if bf.joint is not None:
        keep_joint_values(problem, path, bf.joint)             # the adopted effects were re-fitted with this one
    elif step > 1:
        refit = joint_fit(selected + [bf], base, problem.evaluator, for_fits_on(path.context, selected + [bf]),
                          min_effects=1)
        if refit is not None and not refit.on_bound and \
                problem.held_out_D(refit.spec, path.replay_floor) <= best.comparison.D_after:
            keep_joint_values(problem, path, refit, new=bf)
            new_spec = refit.spec
    if problem.refines and bf.effect.kind == "deterministic":
        n_sel = _n_deterministic(selected)
        ref = refine_by_replay(bf, selected, base, for_fits_on(path.context, selected), problem.fit_judge,
                               path.replay_floor, with_selected=0 < n_sel and n_sel + len(bf.theta) <= REFINE_JOINT_MAX)
        if ref is not None and not ref.on_bound() and \
                problem.held_out_D(ref.spec, path.replay_floor) <= problem.held_out_D(new_spec, path.replay_floor):
            if ref.joint is not None:
                keep_joint_values(problem, path, ref.joint)
            new_spec, bf.theta, bf.sigma = ref.spec, ref.theta, ref.sigma
            bf.derived = bf.effect.derived(base, bf.theta)
            bf.refined = True
    return new_spec


def adopt_best(problem: Problem, path: Path, step: int, best: JudgedRow, conf: list, alts: list) -> None:
    """Adopt the chosen candidate ``best`` at ``step``: the member of its exclusive group it replaces
    leaves (and does not come back), the adopted effects keep their re-fit, the adopted effects are
    refined together by the replay (:func:`_adopted_values`), the floors are renewed, redundant earlier
    effects withdrawn (:func:`backward`) and the next proposals located in what the new model leaves.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on (data, evaluator, library, options).
    path : Path
        The selection's state: the current model, its floors, the adopted effects.
    step : int
        The forward step.
    best : JudgedRow
        The chosen candidate.
    conf : list
        Candidates the held-out replay cannot tell from it (confounded).
    alts : list
        Their report rows (alternatives).
    """
    bf, selected = best.fit, path.selected
    gone = None
    if bf.replaces is not None:
        i = next(i for i, f in enumerate(selected) if f.key == bf.replaces)
        selected.pop(i)
        gone = path.found.pop(i)
        path.banned.add(bf.replaces)
    new_spec = _adopted_values(problem, path, step, best)
    selected.append(bf)
    # a confounded alternative that states a known quantity (force constant) is not adopted later;
    # the others may be, if they add beyond the floor on top of this one (then they were not
    # confounded: the data demand both, and the earlier "confounded" mark is withdrawn)
    path.banned |= {j.fit.key for j in conf if j.fit.key in problem.library.known}
    for fe in path.found:
        if bf.key in fe["confounded_with"]:
            fe["confounded_with"] = [k for k in fe["confounded_with"] if k != bf.key]
            fe["alternatives"] = [a for a in fe["alternatives"] if a["effect"] != bf.key]
            fe.setdefault("also_adopted", []).append(bf.key)
    path.found.append({"effect": bf.key, "title": bf.title, "kind": bf.effect.kind, "step": step,
                       "params": bf.params(), "derived": bf.derived, "expressible": bf.expressible,
                       "confounded_with": [j.fit.key for j in conf], "alternatives": alts,
                       "chosen_by": best.rule or "the best replay",
                       "J_held": bf.J_held, "replay": best.comparison.row(),
                       "refined_by_replay": bool(bf.refined),
                       "replaces": None if gone is None else {"effect": gone["effect"], "step": gone["step"],
                                                              "params": gone["params"]}})
    path.current = new_spec
    path.continued = set()                       # a new model: its continuations are tried again
    renew_floor(problem, path, new_spec)         # the run-to-run floor re-estimated after every adoption
    if backward(problem, path, bf):
        renew_floor(problem, path, path.current)
    # the next proposals come from what the adopted model leaves: ripple periods, spectral peaks and
    # lines located again in its force residual (the nominal's was dominated by the adopted effect)
    obs = problem.observer
    path.context = dataclasses.replace(path.context, **proposals(
        problem.data, obs.run(new_spec), path.floor.res_a, path.floor.sim_a, obs.f_o, problem.band_hz, path.context))
