"""Effects fitted together: a candidate with the adopted effects, and the adopted effects jointly.

Use (:mod:`.tasks`, :mod:`.selection`)
    Every candidate is fitted on top of the current model -- from the second step on together
    with the adopted effects, all their parameters free again (:func:`fit_with`; integer ones
    held) -- and its held-out ``J`` is taken against its *own* noise floor (a candidate that
    changes the drive or the dynamics changes what noise leaves; if it does not fit the fit set
    better than the current model, the larger of its own-floor and current-floor ``J`` counts).
    The force residual proposes, ranks and gives start values; the closed-loop replay decides
    (:mod:`.judge`, :mod:`.selection`). After the selection the adopted effects are fitted jointly
    (:func:`joint_fit`); parameters correlating above 0.95 across effects are reported as
    confounded.
Joint parameter vector
    :class:`JointEffect` is several effects applied in sequence as one effect, its parameters
    the parts' in order (named ``key.name``), each part's bounds relative to the model its
    predecessors made; :func:`spec_with` builds a model with adopted effects at their values
    (stochastic and integer ones first), :func:`spec_moved` with the deterministic ones at joint
    values. The fits themselves are :func:`.fit.fit_effect`'s.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .effects.base import Effect, Param
from .evaluator import Evaluator
from .fit import FitResult, fit_effect
from .model import ModelSpec

__all__ = ["fit_with", "joint_fit", "JointEffect", "spec_with", "spec_moved"]


class JointEffect(Effect):
    """Several fitted effects applied in sequence, all parameters free.

    Parameters
    ----------
    parts : list of tuple
        ``(effect, number of its parameters)``, in the order applied.
    thetas : list, optional
        The parts' fitted values (each part's bounds are relative to its predecessors').
    """

    def __init__(self, parts: list[tuple[Effect, int]], thetas: list | None = None):
        self.key = "+".join(e.key for e, _ in parts)
        self.title = " + ".join(e.title for e, _ in parts)
        self.parts = parts
        self.thetas = thetas      # fitted values of the parts: bounds of each relative to its predecessors

    def params(self, spec, ctx):
        out = []
        s = spec
        for k, (e, _) in enumerate(self.parts):
            ps = e.params(s, ctx)
            out += [Param(f"{e.key}.{p.name}", p.unit, p.lo, p.hi, p.x0, p.log, physical_lo=p.physical_lo) for p in ps]
            if self.thetas is not None:
                # e.g. the asymmetry's bounds scale with the Coulomb force an earlier part added
                s = e.apply(s, self.thetas[k])
        return out

    def apply(self, spec, theta):
        i = 0
        s = spec
        for e, n in self.parts:
            s = e.apply(s, theta[i:i + n])
            i += n
        return s


def spec_with(selected: list[FitResult], base: ModelSpec) -> ModelSpec:
    """``base`` with the ``selected`` effects at their current values (stochastic and integer ones
    first, as :func:`fit_with` builds them).

    Parameters
    ----------
    selected : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.

    Returns
    -------
    ModelSpec
    """
    spec = base
    for f in selected:
        if f.effect.kind != "deterministic":
            spec = f.effect.apply(spec, f.theta)
    for f in selected:
        if f.effect.kind == "deterministic":
            spec = f.effect.apply(spec, f.theta)
    return spec


def spec_moved(selected: list[FitResult], theta, base: ModelSpec) -> ModelSpec:
    """:func:`spec_with` with the deterministic ``selected`` effects at the joint values ``theta``
    (theirs, in order, first).

    Parameters
    ----------
    selected : list of FitResult
        The adopted effects.
    theta : sequence of float
        Joint values of the deterministic effects' parameters.
    base : ModelSpec
        The model the effects are added to.

    Returns
    -------
    ModelSpec
    """
    k, moved = 0, []
    for f in selected:
        if f.effect.kind == "deterministic":
            n = len(f.theta)
            f = dataclasses.replace(f, theta=np.asarray(theta[k:k + n], float))
            k += n
        moved.append(f)
    return spec_with(moved, base)


def joint_fit(fits: list[FitResult], base: ModelSpec, ev: Evaluator, ctx: dict,
              min_effects: int = 2, max_iter: int = 4) -> FitResult | None:
    """Re-fit all selected deterministic effects together (integer ones held at their value;
    at most ``max_iter`` Gauss-Newton iterations); None if there are fewer than
    ``min_effects`` of them.

    Parameters
    ----------
    fits : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        What was located on the recording.
    min_effects : int, optional
        Fewest deterministic effects to fit jointly.
    max_iter : int, optional
        Most Gauss-Newton iterations.

    Returns
    -------
    FitResult or None
    """
    cont = [f for f in fits if f.effect.kind == "deterministic"]
    fixed = [f for f in fits if f.effect.kind != "deterministic"]
    if len(cont) < max(1, min_effects):
        return None
    spec0 = base
    for f in fixed:
        spec0 = f.effect.apply(spec0, f.theta)
    joint = JointEffect([(f.effect, len(f.theta)) for f in cont], [f.theta for f in cont])
    x0 = np.concatenate([f.theta for f in cont])
    # bounds of each part relative to the model it is applied to
    r = fit_effect(joint, spec0, ev, ctx, starts=[list(x0)], max_nfev=max_iter)
    return r


def fit_with(effect: Effect, selected: list[FitResult], base: ModelSpec, ev: Evaluator, ctx: dict) -> FitResult | None:
    """Fit ``effect`` together with the already ``selected`` deterministic effects (all their
    parameters free again, started at their values; integer ones held), on top of ``base``.

    Forward selection with re-fitting: a second effect is judged with the first one re-fitted
    in its presence, so an error the first fit made while the second was missing does not
    stay in the residual. Returns the candidate's :class:`FitResult` (its own parameters;
    ``spec`` and ``J`` are the joint model's) with ``joint`` = the joint :class:`FitResult`.

    Parameters
    ----------
    effect : Effect
        The candidate.
    selected : list of FitResult
        The adopted effects.
    base : ModelSpec
        The model the effects are added to.
    ev : Evaluator
        The force-residual evaluator.
    ctx : Context
        What was located on the recording.

    Returns
    -------
    FitResult or None
    """
    cont = [f for f in selected if f.effect.kind == "deterministic"]
    if effect.kind != "deterministic" or not cont:
        return None
    spec0 = base
    for f in selected:
        if f.effect.kind != "deterministic":
            spec0 = f.effect.apply(spec0, f.theta)
    effect = effect.bound(ctx)
    n_e = len(effect.params(spec0, ctx))
    x_sel = list(np.concatenate([f.theta for f in cont]))
    cur = spec0
    for f in cont:
        cur = f.effect.apply(cur, f.theta)
    starts = effect.starts(cur, ctx)
    joint = JointEffect([(f.effect, len(f.theta)) for f in cont] + [(effect, n_e)],
                   [f.theta for f in cont] + [starts[0]])
    jf = fit_effect(joint, spec0, ev, ctx, starts=[x_sel + list(st) for st in starts])
    if jf is None:
        return None
    k = len(x_sel)
    th = jf.theta[k:]
    return FitResult(key=effect.key, title=effect.title, names=[p.name for p in effect.params(spec0, ctx)],
                     units=jf.units[k:], theta=th, sigma=jf.sigma[k:],
                     corr=None if jf.corr is None else jf.corr[k:, k:], spec=jf.spec, J_fit=jf.J_fit,
                     J_held=jf.J_held, n_eff_held=jf.n_eff_held, evals=jf.evals, seconds=jf.seconds,
                     nominal=effect.nominal(spec0), derived=effect.derived(cur, th), expressible=effect.expressible,
                     on_bound=[n.split(".", 1)[1] for n in jf.on_bound if n.startswith(effect.key + ".")],
                     joint=jf, effect=effect)
