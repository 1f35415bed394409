"""The forward selection's objects and its decisions: what a step judges and what it adopts.

:class:`Problem` is what the selection works on (fixed for one diagnosis); a :class:`Path` is one
walk of it (the current model, its floors, the adopted effects and the steps); each step proposes
:class:`Candidate` s, fits them (:mod:`.tasks`), and judges each by its closed-loop replay against
the current model's run-to-run floor (:func:`judge_rows` -> :class:`JudgedRow`); :func:`choose`
picks the one to adopt and the ones confounded with it.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from .context import Context
from .data import DiagData
from .effects import Library
from .effects.base import Effect
from .evaluator import Evaluator
from .fit import FitResult
from .floors import ForceFloor
from .judge import ReplayJudge
from .model import ModelSpec
from .observer import Observer
from .options import Options
from .replay_floor import Comparison, Floor, Replay

__all__ = ["Problem", "Candidate", "JudgedRow", "Path", "FirstStep", "judge_rows", "rank", "choose", "step_rows",
           "for_fits_on", "identification", "NOMINAL_Z"]

NOISE_QUIETER = 0.8
"""Data whose drive-noise level (read from the residual spectrum) is below this fraction of the
model's are quieter than the model: no candidate is refused for replaying closer to them than its
own recordings (:func:`consistent_from_below`)."""

NOMINAL_Z = 2.0
"""An effect whose every parameter is within this many standard errors of the current model's value
(a stated mass, force constant, delay) is not adopted: the data do not demand the change."""


@dataclass
class Problem:
    """What the forward selection works on: fixed for one diagnosis (the evaluator's floor follows
    the current model).

    Parameters
    ----------
    options : Options
        The diagnosis's options.
    data : DiagData
        The recording.
    observer : Observer
        The force observer on it.
    base : ModelSpec
        The nominal with the quantization found from the lattice: where every path starts.
    library : Library
        The effects, bound to the recording.
    keys : list
        The keys proposed, in order.
    evaluator : Evaluator
        The force-residual evaluator of candidate fits (its floor follows the current model).
    judge : ReplayJudge
        The held-out samples' judge (closed-loop replay, or open-loop windows).
    fit_judge : ReplayJudge, optional
        The fit samples' judge (the replay refinement's); None: no refinement.
    base_floor : ForceFloor
        The base model's force-residual floor.
    base_replay_floor : Floor
        The base model's run-to-run replay floor.
    J_held_base : float
        The base model's held-out force-residual J.
    J_fit_base : float
        The same on the fit samples.
    band_hz : float
        The force residual's band [Hz] (half the observer bandwidth).
    n_eff : float
        Effective sample count of the held-out force residual (the base model's floor; at least 10).
    executor : object
        Where candidate fits run (None: in this process).
    token : str, optional
        Identifies the fit data shared with worker processes.
    blob : bytes, optional
        That data, pickled once.
    noise_ratio : float, optional
        The data's drive-noise level over the base model's, read from the residual spectrum before
        judging (:func:`.stages.drive_noise_prior`; None: not read).
    """
    options: Options
    data: DiagData
    observer: Observer
    base: ModelSpec
    library: Library
    keys: list
    evaluator: Evaluator
    judge: ReplayJudge
    fit_judge: ReplayJudge | None
    base_floor: ForceFloor
    base_replay_floor: Floor
    J_held_base: float
    J_fit_base: float
    band_hz: float
    n_eff: float
    executor: object = None
    token: str | None = None
    blob: bytes | None = None
    noise_ratio: float | None = None

    @property
    def refines(self) -> bool:
        """Candidates are refined by the replay of the fit samples."""
        return self.fit_judge is not None

    def held_out_D(self, spec: ModelSpec, floor: Floor) -> float:
        """Replay error of the held-out samples in units of ``floor`` (inf: unstable).

        Parameters
        ----------
        spec : ModelSpec
            A model.
        floor : Floor
            The floor whose units are used.

        Returns
        -------
        float
        """
        rp = self.judge.replay(spec)
        return self.judge.D(rp, floor) if rp.ok else float("inf")

    def fit_D(self, spec: ModelSpec, floor: Floor) -> float:
        """Replay error of the fit samples in units of ``floor`` (the held-out one without a fit judge).

        Parameters
        ----------
        spec : ModelSpec
            A model.
        floor : Floor
            The floor whose units are used.

        Returns
        -------
        float
        """
        if self.fit_judge is None:
            return self.held_out_D(spec, floor)
        rp = self.fit_judge.replay(spec)
        return self.fit_judge.D(rp, floor) if rp.ok else float("inf")

    def params_of(self, f: FitResult, ctx: Context, spec: ModelSpec | None = None):
        """Candidate ``f``'s fitted parameters (:class:`.effects.base.Param`: bounds) on ``spec``
        (default: the base model), or None.

        Parameters
        ----------
        f : FitResult
            A candidate's fit.
        ctx : Context
            What was located on the recording.
        spec : ModelSpec, optional
            The model (default the base).

        Returns
        -------
        list of Param or None
        """
        try:
            ps = f.effect.params(self.base if spec is None else spec, ctx)
        except Exception:     # noqa: BLE001 - no ranges: the standard errors alone decide
            return None
        return ps if len(ps) == len(f.theta) else None

    def spans(self, f: FitResult, ctx: Context):
        """The ranges (hi - lo) of candidate ``f``'s parameters on the base model, or None.

        Parameters
        ----------
        f : FitResult
            A candidate's fit.
        ctx : Context
            What was located on the recording.

        Returns
        -------
        list of float or None
        """
        ps = self.params_of(f, ctx)
        return None if ps is None else [p.hi - p.lo for p in ps]

    def identification(self, f: FitResult, ctx: Context, spec: ModelSpec | None = None) -> tuple:
        """:func:`identification` of fit ``f`` (its bounds on ``spec``, default the base model; the
        plausible ranges the library documents, on the recording's axis).

        Parameters
        ----------
        f : FitResult
            A candidate's fit.
        ctx : Context
            What was located on the recording.
        spec : ModelSpec, optional
            The model (default the base).

        Returns
        -------
        tuple
            ``(why not, weak)`` as :func:`identification`.
        """
        if f.effect is None or f.effect.kind == "integer":
            return None, []
        doc = {p.name: p for p in f.effect.parameters}
        return identification(f.names, f.theta, f.sigma, self.params_of(f, ctx, spec), doc, self.data.axis)


@dataclass
class Candidate:
    """An effect proposed at a step; ``replaces``: the adopted member of its exclusive group it is
    fitted without (a replacement), else None.

    Parameters
    ----------
    effect : Effect
        The effect.
    replaces : str, optional
        Key of the adopted effect it replaces.
    """
    effect: Effect
    replaces: str | None = None


@dataclass
class JudgedRow:
    """A fitted candidate judged by its replay against the current model's run-to-run floor.

    Parameters
    ----------
    fit : FitResult
        The candidate's fit.
    replay : Replay
        Its replay of the held-out data.
    comparison : Comparison
        Against the current model (:meth:`.judge.ReplayJudge.compare`).
    on_bound : list
        Its parameters at a bound (and the adopted effects' when fitted together).
    ok : bool
        Adoptable: beyond the floor, identified, moved by the data.
    why : str
        Why not adoptable, in words ('' when it is).
    rule : str
        Chosen (:func:`choose`): the rule that chose it among the candidates the replay cannot tell
        apart.
    """
    fit: FitResult
    replay: Replay
    comparison: Comparison
    on_bound: list
    ok: bool
    why: str
    rule: str = ""


@dataclass
class Path:
    """One walk of the forward selection: the current model and what led to it.

    Parameters
    ----------
    current : ModelSpec
        The current model.
    J_held : float
        The current model's held-out force-residual J (its own floor).
    J_fit : float
        The same on the fit samples.
    floor : ForceFloor
        The current model's force-residual floor.
    replay_floor : Floor
        The current model's run-to-run replay floor.
    context : Context
        The located context (proposals renewed after every adoption).
    steps : list
        The report's step records.
    selected : list
        The adopted effects' fits, in order.
    found : list
        The report's rows of the adopted effects (one per selected fit).
    banned : set
        Keys not proposed again (withdrawn, replaced, a known quantity's confounded alternative).
    continued : set
        Continuations (:meth:`.forward.ForwardSelection.continuations`) tried on the current model
        (emptied by every adoption).
    refit : tuple, optional
        (model, joint fit): the best re-fit of the adopted effects alone a step's joint refinements
        reached.
    second_start : dict, optional
        What the walk from step 1's runner-up found (:meth:`.forward.ForwardSelection.run`).
    """
    current: ModelSpec
    J_held: float
    J_fit: float
    floor: ForceFloor
    replay_floor: Floor
    context: Context
    steps: list = field(default_factory=list)
    selected: list = field(default_factory=list)
    found: list = field(default_factory=list)
    banned: set = field(default_factory=set)
    continued: set = field(default_factory=set)
    refit: tuple | None = None
    second_start: dict | None = None


@dataclass
class FirstStep:
    """Step 1 of the greedy walk: its judged rows and its record (the second start begins there).

    Parameters
    ----------
    judged : list of JudgedRow
        The step's judged candidates.
    record : dict
        The step's report record.
    """
    judged: list
    record: dict


def for_fits_on(ctx: Context, selected: list) -> Context:
    """The located context for fits on top of ``selected``: with the Coulomb level adopted, the
    position-dependent friction has no level parameter of its own (``level_fitted``).

    Parameters
    ----------
    ctx : Context
        What was located on the recording.
    selected : list of FitResult
        The adopted effects.

    Returns
    -------
    Context
    """
    return dataclasses.replace(ctx, level_fitted=any(f.effect.sets_friction_level for f in selected))


def identification(names, theta, sigma, params=None, documented=None, axis: str = "linear") -> tuple:
    """Whether an effect's fitted values are identified: ``(why not, weak)``; ``why`` None when they are.

    Not identified (the effect is not adopted): a parameter at a bound of its fit (``params``, the
    :class:`.effects.base.Param` s it was fitted with, a physical lower bound excepted), or within
    its own standard error of one while determined (standard error below its magnitude; every
    parameter of a one-parameter effect); a value outside the plausible range the library documents
    for the axis (``documented``: name -> :class:`.effects.base.Parameter`; a signed parameter by
    its magnitude's upper end); or every parameter with a standard error above its magnitude.
    ``weak``: the names of the parameters whose standard error exceeds their magnitude (in an
    effect identified by its others: reported as not determined, never as a finding).

    Parameters
    ----------
    names : list of str
        Parameter names.
    theta : sequence of float
        Fitted values.
    sigma : sequence of float or None
        Their standard errors.
    params : list of Param, optional
        What they were fitted with (bounds).
    documented : dict, optional
        Name -> :class:`.effects.base.Parameter` (plausible ranges).
    axis : {'linear', 'rotary'}, optional
        The recording's axis.

    Returns
    -------
    tuple
        ``(why, weak)``: ``why`` None when identified; ``weak`` a list of names.

    Examples
    --------
    >>> from experiment_runner.apps.diagnosis.effects.base import Param, Parameter
    >>> ratio = [Param("ratio", "-", 0.3, 3.0, 1.0)]
    >>> identification(["ratio"], [0.3004], [0.01], ratio)[0]
    'ratio at its bound 0.3'
    >>> identification(["ratio"], [0.33], [0.05], ratio)[0]       # within its own sigma of the bound
    'ratio at its bound 0.3'
    >>> identification(["ratio"], [0.8], [0.01], ratio) == (None, [])
    True
    >>> c = [Param("c", "N·s/m", 0.0, 1e4, 10.0)]
    >>> print(identification(["c"], [16.0], [293.0], c)[0])
    every parameter's standard error exceeds its value (c 16 ± 293)
    >>> doc = {"c": Parameter("c", "N·s/m", "viscous", (1e-3, 1e5), (1e-7, 1e2))}
    >>> identification(["c"], [500.0], [1.0], c, doc, axis="rotary")[0]
    'c 500 outside the plausible range 1e-07 ... 100 on a rotary axis'
    >>> dc = {"dc": Parameter("dc", "N·s/m", "c+ - c-", (1e-3, 1e5), signed=True)}
    >>> identification(["dc"], [-75.6], [1.5], None, dc)      # a difference of either sign: by its magnitude
    (None, [])
    >>> identification(["dc"], [-2e5], [1.5], None, dc)[0]
    'dc -2e+05 outside the plausible range 0.001 ... 1e+05 on a linear axis'
    """
    th = np.asarray(theta, float)
    sig = np.asarray(sigma, float) if sigma is not None else np.full(len(th), np.nan)
    documented = documented or {}
    weak = [n for n, v, s in zip(names, th, sig) if np.isfinite(s) and s > abs(v)]
    if len(th) and np.all(np.isfinite(sig)) and len(weak) == len(th):
        return ("every parameter's standard error exceeds its value ("
                + ", ".join(f"{n} {v:.3g} ± {s:.3g}" for n, v, s in zip(names, th, sig)) + ")"), weak
    for i, (n, v, s) in enumerate(zip(names, th, sig)):
        p = params[i] if params is not None and i < len(params) else None
        if p is not None and p.hi > p.lo:
            # 0.1 % of the range in the optimiser's variable (log for a log parameter: a stiffness
            # ranging over decades is not at its lower bound 1e-3 of the way up in value), or its own
            # standard error where that determines it
            s_ok = np.isfinite(s) and s <= abs(v)
            if p.log and p.lo > 0 and v > 0:
                lt = 1e-3 * np.log(p.hi / p.lo)
                hi_b, lo_b = np.log(p.hi / v) <= lt, np.log(v / p.lo) <= lt
            else:
                t = 1e-3 * (p.hi - p.lo)
                hi_b, lo_b = abs(p.hi - v) <= t, abs(v - p.lo) <= t
            hi_b = hi_b or (s_ok and abs(p.hi - v) <= s)
            lo_b = lo_b or (s_ok and abs(v - p.lo) <= s)
            if hi_b:
                return f"{n} at its bound {p.hi:.4g}", weak
            if lo_b and not p.physical_lo:
                return f"{n} at its bound {p.lo:.4g}", weak
        d = documented.get(n)
        rng = d.plausible_on(axis) if d is not None else None
        if rng is not None:
            lo, hi = rng
            signed = d.signed or (p is not None and p.lo < 0)
            if (abs(v) > hi) if signed else not (lo <= v <= hi):
                return f"{n} {v:.4g} outside the plausible range {lo:.4g} ... {hi:.4g} on a {axis} axis", weak
    return None, weak


def _at_nominal(f: FitResult, spans=None) -> bool:
    """Every parameter of ``f`` has a current-model value and is within :data:`NOMINAL_Z` standard
    errors of it, or within 1e-4 of its range ``spans`` (hi - lo per parameter, if given) of it: a
    value of no change whose standard error is as small (a fractional delay of 1e-6 samples at its
    lower end, credited with what the refinement of the adopted effects did)."""
    if not f.names:
        return False
    nom = [f.nominal.get(n) for n in f.names]
    sig = np.asarray(f.sigma, float)
    if any(v is None for v in nom) or not np.all(np.isfinite(sig)) or len(sig) != len(nom):
        return False
    tol = NOMINAL_Z * sig
    if spans is not None and len(spans) == len(sig):
        tol = np.maximum(tol, 1e-4 * np.asarray(spans, float))
    return bool(np.all(np.abs(np.asarray(f.theta, float) - np.asarray(nom, float)) <= tol))


def judge_rows(problem: Problem, fits: list, floor: Floor, sim_blocks, first: bool, ctx: Context) -> list:
    """Each fit's replay judged against the current model's run-to-run ``floor`` (``sim_blocks``: its
    simulated recordings' block errors); ``first``: the first step (no share of the remaining excess
    is asked).

    Parameters
    ----------
    problem : Problem
        What the forward selection works on.
    fits : list of FitResult
        The step's fitted candidates.
    floor : Floor
        The current model's run-to-run floor.
    sim_blocks : numpy.ndarray
        (K, n_blocks) block errors of the floor's simulated recordings.
    first : bool
        The first step.
    ctx : Context
        What was located on the recording.

    Returns
    -------
    list of JudgedRow
    """
    opt, judge = problem.options, problem.judge
    out = []
    D_floor = float(np.mean(sim_blocks.sum(axis=1))) / max(judge.n, 1)
    for f in fits:
        rp = judge.replay(f.spec)
        c = judge.compare(floor, rp, fl_blocks=sim_blocks)
        share = c.T / max(c.D_before - D_floor, 1e-300)
        if c.accepted and not first and share < opt.min_share:
            c.accepted = False
            c.why = (f"removes {100 * share:.0f} % of the remaining replay excess over the floor "
                     f"(< {100 * opt.min_share:.0f} %)")
        bound = list(f.on_bound) + ([n for n in f.joint.on_bound if not n.startswith(f.key + ".")]
                                    if f.joint is not None else [])
        why = c.why
        unid = problem.identification(f, ctx)[0] if c.accepted and not bound else None
        if c.accepted and bound:
            why = f"not identified: {', '.join(bound)} at its bound"
        elif unid is not None:
            why = f"not identified: {unid}"
        elif c.accepted and _at_nominal(f, problem.spans(f, ctx)):
            why = (f"the data do not move it: every parameter within {NOMINAL_Z:g} standard errors of "
                   "the current model's value")
        elif c.accepted and f.effect.kind == "integer" and all(
                f.nominal.get(n) is not None and float(f.nominal[n]) == float(v) for n, v in zip(f.names, f.theta)):
            # the improvement is the re-fit of the others, not this effect
            why = "no change: the current model's value"
        out.append(JudgedRow(fit=f, replay=rp, comparison=c, on_bound=bound, ok=c.accepted and why == c.why, why=why))
    return out


def rank(row: JudgedRow, complexity: float) -> float:
    """A judged candidate's rank: its replay with the selection's complexity penalty per parameter (a
    12-block GMS must do clearly better than the one Coulomb level it contains).

    Parameters
    ----------
    row : JudgedRow
        A judged candidate.
    complexity : float
        Penalty per parameter.

    Returns
    -------
    float
        Lower is better.
    """
    return row.comparison.D_after * (1 + complexity * len(row.fit.theta))


def choose(problem: Problem, judged: list, floor: Floor) -> tuple:
    """``(best, confounded, alternatives)`` among the judged candidates of a step (best None: none
    adoptable). Candidates the held-out replay cannot tell from the best are confounded; one of them
    is adopted: not a quantity the nominal states as known unless the data demand it, then the
    simplest, then the best replay; a simpler adoptable candidate wins unless the more complex one
    improves on it beyond the floor.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on.
    judged : list of JudgedRow
        The step's judged candidates.
    floor : Floor
        The current model's run-to-run floor.

    Returns
    -------
    tuple
    """
    judge, known = problem.judge, problem.library.known
    ok = sorted([j for j in judged if j.ok], key=lambda j: rank(j, problem.options.complexity))
    ok, floors = consistent_from_below(problem, ok)
    best = conf = None
    alts = []
    if ok:
        top = ok[0]
        tfl = floors.get(id(top)) if len(ok) > 1 else None     # recordings of the best's model
        equiv = [top] + [j for j in ok[1:] if judge.equivalent(floor, j.replay, top.replay, of_b=tfl)[0]]
        best = min(equiv, key=lambda j: (j.fit.key in known, len(j.fit.theta), j.comparison.D_after))
        if best is top:
            rule = ("the best replay" + (": no other adoptable candidate replays the held-out data as well"
                                         if len(equiv) == 1 else ", and no fewer parameters among those "
                                         "that replay as well"))
        elif top.fit.key in known and best.fit.key not in known:
            rule = (f"a quantity the nominal states as known ({top.fit.key}) moves last: {best.fit.key} replays "
                    "the held-out data as well")
        else:
            rule = "parsimony: the fewest parameters among the candidates that replay the held-out data as well"
        for j in sorted(ok, key=lambda j: (len(j.fit.theta), j.comparison.D_after)):
            if len(j.fit.theta) >= len(best.fit.theta) or j.fit.key in known:
                continue
            # the threshold from recordings of the simpler model (the current model's scatter grows with
            # the distance from it: a candidate at the floor is "within the floor" of one far above)
            if not judge.compare(floor, best.replay, rp_base=j.replay, of_base=judge.floor(j.fit.spec)).accepted:
                conf = [best] + [x for x in equiv if x is not best]
                rule = (f"parsimony: {j.fit.key} ({len(j.fit.theta)} parameter(s)) replays within the floor of "
                        f"{best.fit.key} ({len(best.fit.theta)}), which does not improve on it beyond the floor")
                best = j
                break
        conf = [j for j in (conf or equiv) if j is not best]
        best.rule = rule
        alts = [{"effect": j.fit.key, "title": j.fit.title, "params": j.fit.params(),
                 "derived": j.fit.derived, "replay_D": j.comparison.D_after, "adoptable": True} for j in conf]
        alts += _equivalent_rejects(problem, judged, best, conf, floor)
    return best, conf, alts


def consistent_from_below(problem: Problem, ok: list) -> tuple:
    """The adoptable rows whose held-out data could be a recording of their own model: a candidate
    whose noise-free replay is closer to the data than its own simulated recordings are to that replay
    (consistency z below minus the critical value, each against its own run-to-run floor) replays the
    noise, not a physics: the one realisation's hold forces that drive noise left on a friction
    contact, or a floor its own change inflated (a lighter mass whose loop amplifies the drive noise).
    A model right up to noise sits near z = 0. The others are marked not adoptable (``ok`` False,
    ``why``). Only when the data are not quieter than the base model (``problem.noise_ratio`` read
    and at least :data:`NOISE_QUIETER`): with quieter data every candidate, the truth too, replays closer
    than its recordings, and no row is marked.

    Parameters
    ----------
    problem : Problem
        What the selection works on (its judge and ``noise_ratio``).
    ok : list of JudgedRow
        The adoptable rows.

    Returns
    -------
    kept : list of JudgedRow
        The consistent rows, in order.
    floors : dict
        ``id(row)`` -> the row's own run-to-run floor (:class:`.replay_floor.Floor`), for every row of ``ok``.
    """
    judge = problem.judge
    kept, floors = [], {}
    # data quieter than the model (its noise level read from the residual spectrum): every candidate,
    # the truth too, replays closer than the model's recordings; then this says nothing
    applies = problem.noise_ratio is not None and problem.noise_ratio >= NOISE_QUIETER
    for j in ok:
        fl = judge.floor(j.fit.spec)
        floors[id(j)] = fl
        z = judge.consistency(j.replay, fl) if fl.replay.ok else 0.0
        if applies and z < -judge.t_q:
            j.ok = False
            j.why = (f"replays the noise: the held-out data are closer to its replay than its own recordings are "
                     f"(consistency z {z:.3g} < -{judge.t_q:.3g}; a model right up to noise sits near 0)")
            continue
        kept.append(j)
    return kept, floors


def _equivalent_rejects(problem: Problem, judged: list, best: JudgedRow, conf: list, floor: Floor) -> list:
    """The report's alternatives among the candidates that were not adoptable (not identified, not
    moved by the data, ...) but whose held-out replay cannot be told from the chosen one's: listed
    with why they were not adopted (the user sees the confound, not only the choice)."""
    judge = problem.judge
    rest = [j for j in judged if not j.ok and j is not best and all(j is not c for c in conf)
            and j.comparison.stable and j.replay.ok and j.comparison.T > 0
            and j.comparison.D_after <= 1.5 * best.comparison.D_after]
    if not rest:
        return []
    bfl = judge.floor(best.fit.spec)       # recordings of the chosen model
    out = []
    for j in rest:
        if judge.equivalent(floor, j.replay, best.replay, of_b=bfl)[0]:
            out.append({"effect": j.fit.key, "title": j.fit.title, "params": j.fit.params(), "derived": j.fit.derived,
                        "replay_D": j.comparison.D_after, "adoptable": False, "why": j.why})
    return out


def _threshold(J: float, n_eff: float) -> float:
    """The force residual's significance threshold of a J change (the report's ``J_significant``)."""
    return max(6 * math.sqrt(max(J, 1.0) / n_eff), 0.05 * max(J - 1, 0.0), 0.02)


def step_rows(problem: Problem, judged: list, J_held: float, n_eff: float) -> list:
    """The report's rows of a step's candidates, best replay first.

    Parameters
    ----------
    problem : Problem
        What the forward selection works on.
    judged : list of JudgedRow
        The step's judged candidates.
    J_held : float
        The current model's held-out replay error.
    n_eff : float
        Effective held-out sample count.

    Returns
    -------
    list of dict
    """
    opt, judge = problem.options, problem.judge
    threshold = _threshold(J_held, n_eff)
    rows = []
    for j in judged:
        f, c = j.fit, j.comparison
        rows.append({"effect": f.key, "title": f.title, "J_fit": f.J_fit, "J_held": f.J_held,
                     "score": f.J_held * (1 + opt.complexity * len(f.theta)), "params": f.params(),
                     "derived": f.derived, "on_bound": j.on_bound, "evals": f.evals, "seconds": round(f.seconds, 3),
                     "J_improvement": J_held - f.J_held, "J_significant": bool(J_held - f.J_held > threshold),
                     "replay": c.row(), "improvement": c.T, "threshold": c.threshold_sim,
                     "block_se": c.se_block, "stable": c.stable, "significant": j.ok, "why": j.why,
                     "replay_rms": dict(zip(("command_N", "position_m"), judge.rms(j.replay)))})
    rows.sort(key=lambda r: r["replay"]["D_after"])
    return rows
