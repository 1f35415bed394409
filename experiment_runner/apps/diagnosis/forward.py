"""Forward selection: the effects adopted one by one, each by the closed-loop replay.

Each step (:meth:`ForwardSelection.step`) fits every candidate (re-fitting the adopted ones with it,
:mod:`.tasks`); the force observer proposes and ranks, the replay decides (:mod:`.selection`,
:mod:`.refining`): the best candidate whose replay is stable and beyond the run-to-run floor of the
current model is adopted (:func:`.adoption.adopt_best`), its statistically equivalent alternatives
are reported, never adopted too. The walk stops when the current model's replay is within its own
floor or nothing is adoptable. When the greedy walk ends beyond its floor (in distribution, and in
size: RMS above the run-to-run floor), a second walk starts from step 1's runner-up (:meth:`ForwardSelection.second_start`) and is kept only if its held-out replay is
better beyond the first walk's floor (the adoption test). A second walk whose adopted effects become
those of the greedy walk after one of its steps (each the same effect or one reported confounded with
it: a force constant for a mass) has joined it: from there it would walk the greedy path again, so it
stops; the greedy walk is kept, unless the second walk holds a confounded alternative in the greedy
effect's place and its held-out replay is better beyond the greedy walk's floor (the adoption test:
the two models differ, and the greedy effect may still be withdrawn as not identified).

With a :class:`.budget.Budget`, a step stopped by it (time spent, or an interruption) is dropped
whole: the walk keeps the model of its last completed step, and an unfinished second walk is not
compared.
"""
from __future__ import annotations

import copy

from .adoption import adopt_best, keep_refit, refit_selected
from .budget import Budget, BudgetReached
from .context import Context
from .joint import spec_with
from .refining import refine_rows
from .selection import Candidate, FirstStep, JudgedRow, Path, Problem, choose, judge_rows, rank, step_rows
from .tasks import fit_candidates

__all__ = ["ForwardSelection"]


class ForwardSelection:
    """The forward selection of one diagnosis (:meth:`run`).

    Parameters
    ----------
    problem : Problem
        What the selection works on.
    context : Context
        The located context of the recording (each walk starts from it).
    budget : Budget, optional
        The diagnosis's budget (progress lines; a step it stops is dropped whole).
    """

    def __init__(self, problem: Problem, context: Context, budget: Budget | None = None):
        self.problem = problem
        self.context = context
        self.budget = budget if budget is not None else Budget(None, progress=False)
        self.budget.jobs = problem.options.n_jobs
        self.first_step: FirstStep | None = None
        self.path: Path | None = None
        self.greedy: Path | None = None
        """The greedy walk."""
        self.greedy_sets: list[dict] = []
        """The adopted effects of the greedy walk after each of its steps (:func:`_adopted`)."""
        self.joined: dict | None = None
        """Where the second walk joined the greedy one (``step``, ``greedy_step``, ``effects``,
        ``greedy_effects``), or None."""

    def run(self) -> Path:
        """The greedy walk, and the walk from step 1's runner-up when the greedy one ends beyond its
        floor (in distribution, and in size: RMS above the run-to-run floor).

        Returns
        -------
        Path
            The kept walk: the greedy one, or the second walk when its held-out replay is better
            beyond the greedy walk's floor. Its ``second_start`` (when a second walk started) says
            what both found and why one was kept; :attr:`path` is the same object.
        """
        problem, judge = self.problem, self.problem.judge
        a = self.walk()
        second = self.second_start(a)
        if second is None:
            return a
        if not self.budget.allows(f"second start from {second.fit.key}"):
            self.path = a
            return a
        problem.options.log(f"second start: {second.fit.key} first (the path from {a.steps[0]['accepted']} "
                            "left a residual beyond its floor)")
        b = self.walk(first=second)
        if self.joined is not None:
            j = self.joined
            why = (f"joined the greedy path: after its step {j['step']} it had adopted {', '.join(j['effects'])}, "
                   f"the greedy path's effects of step {j['greedy_step']} ({', '.join(j['greedy_effects'])}"
                   + (", or one confounded with each" if j["effects"] != j["greedy_effects"] else "")
                   + "); walked no further")
            # an alternative stands for the effect it is confounded with in the walk, not in the model:
            # the two models differ, and the data decide between them as between two walks
            c = (judge.compare(a.replay_floor, b.replay_floor.replay)
                 if j["effects"] != j["greedy_effects"] and b.replay_floor.replay.ok else None)
            if c is not None and c.accepted:
                return self._keep(b, a, b, second, f"{why}; its held-out replay {c.why}", joined=j)
            return self._keep(a, a, b, second, why, joined=j)
        if self.budget.stopped is not None:        # an unfinished walk is not compared
            self.budget.skip(f"second start from {second.fit.key} (unfinished, not compared)")
            self.path = a
            problem.evaluator.floor = a.floor.noise
            return a
        c = judge.compare(a.replay_floor, b.replay_floor.replay) if b.replay_floor.replay.ok else None
        return self._keep(b if c is not None and c.accepted else a, a, b, second,
                          c.why if c is not None else "unstable")

    def _keep(self, chosen: Path, a: Path, b: Path, second: JudgedRow, why: str, joined: dict | None = None) -> Path:
        """Keep ``chosen`` (the greedy walk ``a`` or the second walk ``b``), saying in its
        ``second_start`` what both walks found and why.

        Parameters
        ----------
        chosen : Path
            The kept walk.
        a : Path
            The greedy walk.
        b : Path
            The second walk.
        second : JudgedRow
            The second walk's first step.
        why : str
            Why ``chosen`` is kept.
        joined : dict, optional
            Where the second walk joined the greedy one (:attr:`joined`).

        Returns
        -------
        Path
            ``chosen``.
        """
        problem, judge = self.problem, self.problem.judge
        chosen.second_start = {
            "first": second.fit.key, "chosen": chosen is b,
            "effects": [fe["effect"] for fe in b.found], "greedy_effects": [fe["effect"] for fe in a.found],
            "replay_D": judge.D(b.replay_floor.replay, a.replay_floor) if b.replay_floor.replay.ok else None,
            "replay_D_greedy": judge.D(a.replay_floor.replay, a.replay_floor), "why": why}
        if joined is not None:
            chosen.second_start["joined"] = dict(joined)
        self.path = chosen
        problem.evaluator.floor = chosen.floor.noise
        problem.options.log(f"second start: {[fe['effect'] for fe in chosen.found]} kept "
                            f"({chosen.second_start['why']})")
        return chosen

    def walk(self, first: JudgedRow | None = None) -> Path:
        """One forward path from the base model: steps until none is adopted.

        A step cut short by the budget (or an interruption) is dropped whole and ends the walk; a
        second walk (``first`` given) also ends where it joins the greedy walk (:attr:`joined`).

        Parameters
        ----------
        first : JudgedRow, optional
            A judged candidate of an earlier walk's first step, adopted at step 1 in place of
            the step's own choice (:meth:`second_start`). None: the greedy walk.

        Returns
        -------
        Path
            The walk (also :attr:`path`; the greedy one is also kept as :attr:`greedy`).
        """
        p = self.problem
        self.path = Path(current=p.base, J_held=p.J_held_base, J_fit=p.J_fit_base, floor=p.base_floor,
                         replay_floor=p.base_replay_floor, context=self.context)
        p.evaluator.floor = p.base_floor.noise
        for step in range(1, p.options.max_steps + 1):
            kept = _snapshot(self.path)
            self.budget.say(f"forward step {step}" + (" of the second start" if first is not None else "") + " ...")
            try:
                self.budget.check()
                going = self.step(step, first if step == 1 else None)
                if self.budget.stopped is not None:    # something in the step was cut short: not adopted
                    raise BudgetReached(self.budget.stopped)
            except (BudgetReached, KeyboardInterrupt) as err:
                if isinstance(err, KeyboardInterrupt):     # SIGINT / SIGTERM: a partial report, then exit
                    self.budget.halt(f"interrupted ({err or 'SIGINT'})")
                    self.budget.interrupt = err
                self.path = _restore(self.path, kept)
                p.evaluator.floor = self.path.floor.noise
                todo = [c.effect.key for c in self.candidates()]
                self.budget.skip(f"forward step {step}" + (" of the second start" if first is not None else "")
                                 + (f" (cut short, none adopted; {len(todo)} candidates: {', '.join(todo)})"
                                    if todo else " (cut short, none adopted)")
                                 + (" and later" if step < p.options.max_steps else ""))
                break
            last = self.path.steps[-1] if self.path.steps and self.path.steps[-1]["step"] == step else {}
            self.budget.done(f"forward step {step}" + (" of the second start" if first is not None else ""),
                             f"adopted {last['accepted']}" if last.get("accepted") else "nothing adopted")
            now = _adopted(self.path)
            if first is None:
                self.greedy_sets.append(now)
            elif going:
                # the greedy path's confounded marks as it reported them in the end (a mark is
                # withdrawn when the data demanded both effects)
                final = _adopted(self.greedy) if self.greedy is not None else {}
                adopted = set().union(*self.greedy_sets)
                k = next((i for i, g in enumerate(self.greedy_sets)
                          if _same_effects(now, {e: final.get(e, c) for e, c in g.items()}, adopted)), None)
                if k is not None:       # the greedy path from here on: not walked again
                    self.joined = {"step": step, "greedy_step": k + 1, "effects": sorted(now),
                                   "greedy_effects": sorted(self.greedy_sets[k])}
                    break
            if not going:
                break
        if first is None:
            self.greedy = self.path
        return self.path

    def second_start(self, a: Path) -> JudgedRow | None:
        """The first step's runner-up, when the greedy path ``a`` ends with a replay beyond its own
        run-to-run floor: the best adoptable candidate of step 1 other than the adopted one and the
        ones confounded with it (by the selection's complexity-penalised replay). Forward selection
        commits to its first choice; where that choice is a stand-in that absorbs what two other
        effects do (12 Maxwell-slip blocks for a compliant joint plus a Stribeck curve), the path
        from the runner-up is the only way back.

        Parameters
        ----------
        a : Path
            The greedy walk (:meth:`walk` without ``first``).

        Returns
        -------
        JudgedRow or None
            Step 1's runner-up; None when the path adopted nothing, its replay is within its own
            floor (or unstable), or step 1 had no other adoptable candidate -- or when its replay
            is beyond its floor in distribution only (RMS within it): ``a.second_start`` then says
            why no second walk is taken.
        """
        if self.first_step is None or not a.found or a.steps[0].get("accepted") is None:
            return None
        judge, rp = self.problem.judge, a.replay_floor.replay
        if judge.consistency(rp, a.replay_floor) <= judge.t_q or not rp.ok:
            return None
        st = a.steps[0]
        skip = {st["accepted"], *st["confounded_with"]}
        ok = sorted([j for j in self.first_step.judged if j.ok and j.fit.key not in skip],
                    key=lambda j: rank(j, self.problem.options.complexity))
        if not ok:
            return None
        ratio = judge.floor_ratio(rp, a.replay_floor)
        if ratio <= 1.0:
            # beyond its floor in distribution (the consistency test) but not in size: a stand-in that
            # absorbed two effects leaves a misfit above the noise (pair 93 ended 3.7x above its floor),
            # and a second walk is kept only where it replays better beyond the greedy one's floor,
            # with no room left for that (power case 029: an FI joint adopted, RMS ratio 0.86,
            # consistency z 8.8; the walk from LuGre, step 1's runner-up, cost 2.4x the greedy walk
            # and ended at D 35 against 1.5)
            a.second_start = {"first": ok[0].fit.key, "chosen": False, "greedy_effects": [fe["effect"] for fe in a.found],
                              "skipped": f"the greedy path replays within its run-to-run floor (RMS ratio {ratio:.2f}): "
                                         "no room for a path that replays better beyond it"}
            self.problem.options.log(f"no second start from {ok[0].fit.key}: {a.second_start['skipped']}")
            return None
        return ok[0]

    def continuations(self) -> list[str]:
        """Keys of the effects that continue an adopted integer effect below its grid step
        (:attr:`.effects.base.Effect.continues`: a fractional delay after a whole-sample one) and have
        not been tried on the current model: tried before the selection stops within the floor.

        Returns
        -------
        list of str
            Effect keys, in the library's order (empty: nothing left to try below a grid step).
        """
        p, path = self.problem, self.path
        taken = {f.key for f in path.selected}
        return [k for k in p.keys if k not in taken and k not in path.banned and k not in path.continued
                and set(p.library[k].continues) & taken]

    def candidates(self, only=None) -> list[Candidate]:
        """Every candidate of this step (``only``: those keys alone). A member of an exclusive group
        (alternative friction laws) whose one adopted member is the only conflict is a *replacement*:
        fitted on the model without that member (the more flexible member the data preferred first
        may not be the physics: Dahl for a GMS, Dahl for a Stribeck curve).

        Left out: adopted or banned effects, stochastic ones, drive effects when the recorded
        command is the measured force, parts of an adopted effect, members clashing with more than
        one adopted effect, and effects not applicable to the model they would be fitted on.

        Parameters
        ----------
        only : collection of str, optional
            Effect keys to keep (the others are left out); None: every key of the library.

        Returns
        -------
        list of Candidate
            In the library's order; a replacement's ``Candidate`` names the adopted member it
            replaces.
        """
        p, path = self.problem, self.path
        taken = {f.key for f in path.selected}
        todo = []
        for k in p.keys:
            e = p.library[k]      # bound to this recording: its applicability may depend on it
            if k in taken or k in path.banned or e.kind not in ("deterministic", "integer"):
                continue
            if only is not None and k not in only:
                continue
            if e.in_drive and p.data.command_kind == "measured":
                continue                 # the recorded command is the force applied: no drive between
            clash = p.library.exclusive_of(k) & taken
            if taken & set(e.not_after):
                continue                 # a part of an adopted effect (the Coulomb level of position friction)
            if len(clash) > 1:
                continue
            rep = next(iter(clash)) if clash else None
            try:
                cur = path.current if rep is None else spec_with([f for f in path.selected if f.key != rep], p.base)
            except Exception:     # noqa: BLE001 - e.g. an asymmetry larger than the friction left without rep
                continue
            if e.applicable(cur) is not None:
                continue
            todo.append(Candidate(e, rep))
        return todo

    def _stop_record(self, step: int, z: float) -> dict:
        """The record of a step that stops because the current model's replay is within its floor."""
        judge, path = self.problem.judge, self.path
        fl = path.replay_floor
        return {"step": step, "J_held_before": path.J_held, "replay_D_before": judge.D(fl.replay, fl),
                "replay_z_before": z, "z_critical": judge.t_q,
                "floor_rms": {"command_N": fl.sigma_u, "position_m": fl.sigma_y},
                "threshold": None, "accepted": None, "confounded_with": [], "candidates": [],
                "stopped": "replay within the run-to-run floor"}

    def step(self, step: int, first: JudgedRow | None = None) -> bool:
        """Forward step ``step``: propose, fit, judge and refine every candidate, choose one
        (:func:`.selection.choose`), record the step in ``path.steps`` and adopt the choice.

        When the current model's replay is already within its run-to-run floor only the
        continuations (:meth:`continuations`) are tried; with none, the step records the stop.

        Parameters
        ----------
        step : int
            The step number, from 1.
        first : JudgedRow, optional
            A judged candidate of an earlier walk's first step, adopted at step 1 from that
            step's record without refitting (:meth:`second_start`).

        Returns
        -------
        bool
            Whether the selection goes on (False: nothing adopted, no candidate fitted, or the
            replay is within its floor).
        """
        p, path = self.problem, self.path
        opt, judge = p.options, p.judge
        if first is not None:
            path.steps.append(dict(self.first_step.record, accepted=first.fit.key, confounded_with=[],
                                   second_start=True))
            first.rule = ("second start: step 1's runner-up, walked from because the greedy path left a replay "
                          "beyond its floor")
            adopt_best(p, path, step, first, [], [])
            return True
        refit_selected(p, path, step)
        J_held, floor = path.J_held, path.replay_floor
        z_cur = judge.consistency(floor.replay, floor)
        only = None
        if z_cur <= judge.t_q:
            # the current model's replay is within its run-to-run floor (calibrated z): nothing to explain,
            # once the fraction below an adopted integer effect's grid step has been tried
            only = self.continuations()
            if not only:
                path.steps.append(self._stop_record(step, z_cur))
                opt.log(f"step {step}: replay z {z_cur:.3g} <= {judge.t_q:.3g}: within the floor, stop")
                return False
            opt.log(f"step {step}: replay z {z_cur:.3g} <= {judge.t_q:.3g}: within the floor; "
                    f"{', '.join(only)} tried before stopping")
        path.continued |= set(self.continuations())      # tried on this model (with the others, or alone)
        fits, failed = fit_candidates(p, self.candidates(only), path.current, path.selected, path.J_fit, path.context)
        if not fits:
            return False
        sim_blocks = judge.sim_blocks(floor.replay, floor)
        judged = judge_rows(p, fits, floor, sim_blocks, first=not path.selected, ctx=path.context)
        D_cur = judge.D(floor.replay, floor)
        judged = refine_rows(p, path, judged, sim_blocks)
        best, conf, alts = choose(p, judged, floor)
        rows = step_rows(p, judged, J_held, p.n_eff)
        kept = best is None and keep_refit(p, path)
        path.steps.append({"step": step, "J_held_before": J_held, "replay_D_before": D_cur,
                           "replay_z_before": z_cur, "z_critical": judge.t_q,
                           "floor_rms": {"command_N": floor.sigma_u, "position_m": floor.sigma_y},
                           "threshold": min((r["threshold"] for r in rows), default=None),
                           "accepted": best.fit.key if best else None,
                           "confounded_with": [j.fit.key for j in conf or []], "candidates": rows,
                           "refit_kept": kept, "failed": dict(failed),
                           **({"within_floor_tried": list(only)} if only else {})})
        if step == 1:
            self.first_step = FirstStep(judged=judged, record=path.steps[-1])
        opt.log(f"step {step}: replay D {D_cur:.4g} -> " + ", ".join(
            f"{r['effect']} {r['replay']['D_after']:.4g} ({r['why']})" for r in rows[:5])
            + f"; accepted {best.fit.key if best else None}")
        if best is None:
            return False
        adopt_best(p, path, step, best, conf, alts)
        return True


def _adopted(path: Path) -> dict:
    """The adopted effects of ``path``: key -> the keys reported as confounded with it."""
    conf = {fe["effect"]: set(fe.get("confounded_with") or ()) for fe in path.found}
    return {f.key: frozenset(conf.get(f.key, ())) for f in path.selected}


def _same_effects(a: dict, b: dict, adopted=frozenset()) -> bool:
    """Whether the adopted effects ``a`` and ``b`` (:func:`_adopted`) are the same, an effect of ``a``
    standing for one of ``b`` confounded with it (a force constant for a mass: the selection found
    them equivalent) unless it is in ``adopted`` itself (the effects ``b``'s path adopted: the data
    demanded it beside the other).

    >>> _same_effects({"force_constant": frozenset(), "viscous": frozenset()},
    ...               {"viscous": frozenset(), "mass": frozenset({"force_constant"})})
    True
    >>> _same_effects({"coulomb": frozenset()}, {"viscous": frozenset({"coulomb"})}, adopted={"viscous", "coulomb"})
    False
    >>> _same_effects({"mass": frozenset()}, {"force_constant": frozenset()})
    False
    """
    if len(a) != len(b):
        return False
    left = dict(b)
    for k, ck in a.items():
        m = k if k in left else None if k in adopted else next(
            (g for g, cg in left.items() if g in ck or k in cg), None)
        if m is None:
            return False
        left.pop(m)
    return True


def _snapshot(path: Path) -> tuple:
    """What a step may change of ``path`` (:func:`_restore` puts it back when the step is dropped)."""
    return (copy.copy(path), list(path.steps), list(path.selected), copy.deepcopy(path.found), set(path.banned),
            [(f, f.theta, f.sigma, f.derived) for f in path.selected])


def _restore(path: Path, kept: tuple) -> Path:
    """``path`` as :func:`_snapshot` saw it."""
    old, steps, selected, found, banned, fits = kept
    for f, theta, sigma, derived in fits:
        f.theta, f.sigma, f.derived = theta, sigma, derived
    old.steps, old.selected, old.found, old.banned = steps, selected, found, banned
    return old
