"""A step's judged candidates refined by the replay before they are compared.

The force observer proposes and gives the start; the replay of the fit samples sets the values
(:func:`.refinement.refine_by_replay`): at the observer's values a flexible wrong effect can beat
the right one whose fit is off where the replay is sensitive. :func:`refine_rows` refines the
stable candidates that may win, re-chooses an integer one (delay) by the replay, refines a mode
located (on the transfer or in the noise response), and judges each again; :func:`own_share` credits a candidate refined
together with the adopted effects with what it adds to their re-fit, not with the re-fit.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .budget import parallel_map, progress
from .effects.body import Mode
from .joint import spec_moved, spec_with
from .refinement import (REFINE_JOINT_MAX, REFINE_MAX_PARAMS, REFINE_MODE_PASSES, REFINE_PROPOSALS, REFINE_TOP,
                         refine_by_replay)
from .replay_floor import Floor
from .selection import JudgedRow, Path, Problem, for_fits_on, judge_rows

__all__ = ["refine_rows", "own_share"]


def _refine_integer(problem: Problem, path: Path, row: JudgedRow, sim_blocks, reach: int = 2) -> JudgedRow:
    """An integer candidate (delay) re-chosen by the replay of the fit samples among the values within
    ``reach`` of the force observer's pick (the others held); its row judged again if it moved."""
    f, selected, floor = row.fit, path.selected, path.replay_floor
    fj = problem.fit_judge
    e = f.effect
    try:
        prev = spec_with(selected, problem.base)
    except Exception:     # noqa: BLE001 - the observer's pick stays
        return row
    p = e.params(prev, for_fits_on(path.context, selected))[0]
    v0 = int(round(f.theta[0]))
    best = (float("inf"), v0, f.spec)
    vs = range(max(int(p.lo), v0 - reach), min(int(p.hi), v0 + reach) + 1)
    specs = [f.spec if v == v0 else e.apply(prev, [v]) for v in vs]
    for v, sp, rp in zip(vs, specs, parallel_map(fj.replay, specs)):
        d = fj.D(rp, floor) if rp.ok else float("inf")
        if d < best[0]:
            best = (d, v, sp)
    if best[1] == v0:
        return row
    f2 = dataclasses.replace(f, spec=best[2], theta=np.array([float(best[1])]), joint=None, refined=True)
    row2 = judge_rows(problem, [f2], floor, sim_blocks, first=not selected, ctx=path.context)[0]
    row2.why += " (chosen by the replay)"
    return row2


def _refine_located(problem: Problem, path: Path, row: JudgedRow, sim_blocks) -> JudgedRow:
    """A mode located on the transfer or in the noise response (``located_mode``) refined by the replay of the fit samples: its
    frequency, damping and mass fraction as a :class:`.effects.body.Mode`'s parameters, started at the
    transfer's fit (small finite-difference steps: a lightly damped mode's replay changes over a
    fraction of its bandwidth). The errors are weighted by the floor of the model with the mode (an
    open-loop floor's prewhitening weighs most where its model is quiet: a rigid model's floor would
    weigh the mode's band and the windows' re-initialisation of the mode), renewed after each of
    :data:`.refinement.REFINE_MODE_PASSES` passes. The row keeps its key, with the refined mode and
    its standard errors."""
    f, fj, ctx = row.fit, problem.fit_judge, path.context
    i = int(round(float(f.theta[0])))
    m = f.effect.mode(f.theta)
    mode = Mode().bound(ctx)
    bf = dataclasses.replace(f, key=mode.key, effect=mode, names=["f", "zeta", "fraction"],
                             theta=np.array([m["f_hz"], m["zeta"], m["fraction"]]), on_bound=[], joint=None)
    sel = [s for s in path.selected if s.key != f.replaces]
    ref, fl = None, fj.floor(f.spec)
    for _ in range(REFINE_MODE_PASSES):
        r = refine_by_replay(bf, sel, problem.base, for_fits_on(ctx, sel), fj, fl, max_nfev=30, diff_step=4e-3)
        if r is None or r.at_bound:
            break
        ref, bf = r, dataclasses.replace(bf, theta=r.theta)
        fl = fj.floor(r.spec)
    if ref is None:
        return row
    (fr, z, phi), sig = ref.theta, ref.sigma
    e2 = f.effect.with_mode(i, {"f_hz": float(fr), "zeta": float(z), "fraction": float(phi)})
    derived = {"f": float(fr), "zeta": float(z), "fraction": float(phi),
               "f_sigma": float(sig[0]), "zeta_sigma": float(sig[1]), "fraction_sigma": float(sig[2])}
    f2 = dataclasses.replace(f, spec=ref.spec, effect=e2, derived=derived, refined=True, joint=None)
    row2 = judge_rows(problem, [f2], path.replay_floor, sim_blocks, first=not path.selected, ctx=ctx)[0]
    row2.why += " (refined by the replay)"
    return row2


def _own_start(problem: Problem, path: Path, f, sel: list):
    """Start of the replay refinement of a candidate the observer left at a bound (where the replay
    may not move it: a Stribeck curve at v_s -> 0 is flat in both parameters): the best of the
    effect's own starts by the replay of the fit samples."""
    fj, e = problem.fit_judge, f.effect
    ctx = for_fits_on(path.context, sel)
    try:
        prev = spec_with(sel, problem.base)
        ps = e.params(prev, ctx)
    except Exception:     # noqa: BLE001 - no start of its own: the observer's
        return None
    best = (float("inf"), None)
    for th in e.starts(prev, ctx):
        th = [p.clip(v) for p, v in zip(ps, th)]
        try:
            rp = fj.replay(e.apply(prev, th))
        except Exception:     # noqa: BLE001 - an invalid start is no start
            continue
        d = fj.D(rp, path.replay_floor) if rp.ok else float("inf")
        if d < best[0]:
            best = (d, th)
    return best[1]


def _worth_refining(judged: list) -> tuple[list, list]:
    """``(rows to refine, rows the observer left worse than no change)``: the stable deterministic
    candidates among the :data:`~.refinement.REFINE_TOP` best replays, those with at most
    :data:`~.refinement.REFINE_MAX_PARAMS` parameters among the :data:`~.refinement.REFINE_PROPOSALS`
    best replays and observer fits, every one-parameter one (a level the observer fits off where the
    replay is sensitive may rank low on both: a Coulomb level behind multi-parameter fits of the
    observer residual), and every small one the observer's fit made worse than no change (where the
    observer sees little, a noisy 1 kHz observer at J near 1, its fits are noise, yet the replay may
    see the effect clearly: a friction slope at 150x the floor; these start from their own starts)."""
    stable = [j for j in judged if j.comparison.stable and j.fit.effect.kind == "deterministic"]
    by_replay = sorted(stable, key=lambda j: j.comparison.D_after)
    by_observer = sorted(stable, key=lambda j: j.fit.J_held)
    top = {id(j) for j in by_replay[:REFINE_TOP]}
    small = [j for j in by_replay[:REFINE_PROPOSALS] + by_observer[:REFINE_PROPOSALS]
             if len(j.fit.theta) <= REFINE_MAX_PARAMS] + [j for j in stable if len(j.fit.theta) == 1]
    lost = [j for j in stable if j.comparison.T < 0 and len(j.fit.theta) <= REFINE_MAX_PARAMS]
    small += lost
    return [j for j in stable if any(j is x for x in small) or id(j) in top], lost


def refine_rows(problem: Problem, path: Path, judged: list, sim_blocks) -> list:
    """Every judged candidate worth it refined by the replay (:func:`.refinement.refine_by_replay`)
    and judged again before candidates are compared; a refined row replaces the observer's.
    Candidates with more than :data:`~.refinement.REFINE_MAX_PARAMS` parameters are refined with
    fewer evaluations; from the second step on the adopted effects are refined with the candidate
    (at most :data:`~.refinement.REFINE_JOINT_MAX` parameters in all).

    An integer candidate (delay) is first re-chosen by the replay among the values next to the
    observer's pick, and a located mode is refined on the transfer; then :func:`own_share` judges
    the jointly refined rows against the adopted effects' best re-fit alone. Rows are refined on
    ``problem.options.n_jobs`` threads and returned in their input order.

    Parameters
    ----------
    problem : Problem
        What the selection works on; nothing is refined when it has no judge of the fit samples.
    path : Path
        The current walk (its adopted effects, context and run-to-run replay floor).
    judged : list of JudgedRow
        The step's judged candidates.
    sim_blocks : numpy.ndarray
        ``(K, n_blocks)`` the floor's simulated recordings' block errors, normalised by the floor
        (:meth:`.judge.ReplayJudge.sim_blocks`), for judging the refined rows again.

    Returns
    -------
    list of JudgedRow
        ``judged`` with every refined row replaced by its re-judged row (``why`` ends
        "(refined by the replay)"); the others unchanged.
    """
    if not problem.refines:
        return judged
    judged = [_refine_integer(problem, path, j, sim_blocks) if j.fit.effect.kind == "integer" else j
              for j in judged]
    judged = [_refine_located(problem, path, j, sim_blocks) if j.fit.key == "located_mode" and j.comparison.stable
              else j for j in judged]
    todo, lost = _worth_refining(judged)

    def refine(j: JudgedRow):
        """``(refinement, observer figures)`` of row ``j`` (refinement None: the row stays)."""
        f = j.fit
        sel = [s for s in path.selected if s.key != f.replaces]
        n_sel = sum(len(s.theta) for s in sel if s.effect.kind == "deterministic")
        blind = any(j is x for x in lost)
        ref = refine_by_replay(f, sel, problem.base, for_fits_on(path.context, sel), problem.fit_judge,
                               path.replay_floor,
                               start=_own_start(problem, path, f, sel) if f.on_bound or blind else None,
                               grid=blind, max_nfev=8 if len(f.theta) <= REFINE_MAX_PARAMS else 3,
                               with_selected=0 < n_sel and n_sel + len(f.theta) <= REFINE_JOINT_MAX)
        if ref is None:
            return None, None
        # the observer's figures of the refined model (the table shows them; they only rank)
        figures = problem.evaluator.both(ref.spec)
        progress(f"  refined {f.key} by the replay")
        return ref, figures

    # the refinements are independent (each its own model and least squares): on parallel threads
    # (the compiled kernels release the GIL), collected in the rows' order, so that the result does
    # not depend on the thread count
    rows = [j for j in judged if any(j is x for x in todo)]
    done = dict(zip(map(id, rows), parallel_map(refine, rows, problem.options.n_jobs)))
    out = []
    refits = []          # (row, the adopted effects alone at the row's joint values, the joint fit)
    for j in judged:
        f = j.fit
        ref, figures = done.get(id(j), (None, None))
        if ref is not None:
            J_fit, J_held, ne = figures
            sel = [s for s in path.selected if s.key != f.replaces]
            f2 = dataclasses.replace(f, spec=ref.spec, theta=ref.theta, sigma=ref.sigma, on_bound=ref.at_bound,
                                     derived=f.effect.derived(problem.base, ref.theta), joint=ref.joint,
                                     refined=True, J_fit=J_fit, J_held=J_held, n_eff_held=ne)
            j2 = judge_rows(problem, [f2], path.replay_floor, sim_blocks, first=not path.selected,
                            ctx=path.context)[0]
            if ref.joint is not None and f.replaces is None:
                refits.append((j2, spec_moved(sel, ref.joint.theta, problem.base), ref.joint))
            j2.why += " (refined by the replay)"
            out.append(j2)
            continue
        out.append(j)
    own_share(problem, path, refits, path.replay_floor)
    return out


def own_share(problem: Problem, path: Path, refits: list, floor: Floor) -> None:
    """Candidates refined together with the adopted effects are credited with what they add to the
    adopted effects' re-fit, not with the re-fit: the best re-fit of the adopted effects alone that
    their joint refinements reached (``refits``: (row, model of the adopted effects alone at the
    row's joint values, the joint fit); best by the replay of the fit samples) is the baseline a row
    must beat beyond the floor to stay adoptable, and is kept as :attr:`.selection.Path.refit`
    (:func:`.adoption.keep_refit`). Each candidate's joint refinement reaches a different re-fit.

    Rows that do not beat it are marked not adoptable (``ok`` False, ``why`` says so) in place.

    Parameters
    ----------
    problem : Problem
        What the selection works on.
    path : Path
        The current walk; its ``refit`` is set (None when no re-fit beats the current model).
    refits : list of tuple
        ``(row, spec, joint fit)``: a jointly refined :class:`.selection.JudgedRow`, the
        ``ModelSpec`` of the adopted effects alone at its joint values, and the joint ``FitResult``.
    floor : Floor
        The current model's run-to-run replay floor the comparison is made in.
    """
    path.refit = None

    def fit_D(spec):
        """The replay of the fit samples' D of ``spec``, or None when it is not a model."""
        try:
            return problem.fit_D(spec, path.replay_floor)
        except Exception:     # noqa: BLE001 - not a model: no baseline
            return None
    best, d_best = None, problem.fit_D(path.current, path.replay_floor)
    for (_, spec, jf), d in zip(refits, parallel_map(fit_D, [spec for _, spec, _ in refits])):
        if d is None:
            continue
        if d < d_best:
            best, d_best = (spec, jf), d
    if best is None:
        return
    rp0 = problem.judge.replay(best[0])
    if not rp0.ok:
        return
    path.refit = best
    for j, _, _ in refits:
        if not j.ok:
            continue
        c = problem.judge.compare(floor, j.replay, rp_base=rp0)
        if not c.accepted:
            j.ok = False
            j.why = (f"adds nothing beyond a re-fit of the adopted effects (replay D {c.D_before:.4g} "
                     f"without it, {c.D_after:.4g} with it: {c.why}) (refined by the replay)")
