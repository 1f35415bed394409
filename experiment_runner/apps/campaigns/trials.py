"""The trials of a campaign: the one place they are built, simulated and judged.

Trial ``i`` of a case at a condition starts where the one trial of an experiment with the campaign's
``starts.trial(i)`` starts (:class:`experiment_runner.core.experiment.Starts`: inside the travel that the
whole reference keeps within) with noise seed
``simulation.seed + i``: every trial is reproducible on its own and the same in every case
(common random numbers make the case comparisons paired), in every chunk, process or
machine that runs it. The one-trial experiment file written for the ROS graph
(:func:`graph_experiment`) reproduces exactly that trial. :func:`learn_step_ii` learns a
case's SAI Step II correction with trials at rest.
"""
from __future__ import annotations

import numpy as np

from experiment_runner.apps.campaigns.registry import TRIAL_METRICS
from experiment_runner.apps.campaigns.schema.common import Condition
from experiment_runner.apps.campaigns.spec import Campaign, Case, case_overrides, case_preset
from experiment_runner.core import profiles
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.experiment import Starts, Trial, trial_metrics
from stage_control.sai import ilc_update
from stage_sim.config import Preset
from stage_sim.plant import STATUS_TEXT

__all__ = ["reference", "start_position", "make_trials", "simulate_trials", "metric_record", "plain",
           "graph_experiment", "learn_step_ii"]


def reference(camp: Campaign, cond: Condition, rate: float) -> profiles.Reference:
    """The shared (start-at-0) reference of a condition at the control rate.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    cond : Condition
        The condition.
    rate : float
        Control rate [Hz].

    Returns
    -------
    experiment_runner.core.profiles.Reference
    """
    return camp.test.reference(cond, rate)


def start_position(camp: Campaign, preset: Preset, ref: profiles.Reference, i: int) -> float:
    """Start of trial ``i``: as :func:`experiment_runner.core.experiment.build_trials` for a one-trial
    experiment with the starts ``camp.starts.trial(i)``.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    preset : stage_sim.config.Preset
        The case's stage, as run.
    ref : experiment_runner.core.profiles.Reference
        The shared (start-at-0) reference.
    i : int
        Trial index.

    Returns
    -------
    float
        Start position [m], drawn inside the stage's travel less the campaign's margin.
    """
    return float(camp.starts.trial(i).positions(1, preset.stage.travel, extent=(float(ref.x.min()), float(ref.x.max())),
                                                where=f"campaign {camp.name} (test {camp.test.kind}, "
                                                      f"preset {preset.name})")[0])


def make_trials(camp: Campaign, case: Case, preset: Preset, ref: profiles.Reference, indices) -> list[Trial]:
    """Trials ``indices`` of ``case`` on ``ref`` (start position and noise seed of each).

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    case : Case
        The case.
    preset : stage_sim.config.Preset
        The case's stage, as run.
    ref : experiment_runner.core.profiles.Reference
        The shared (start-at-0) reference.
    indices : iterable of int
        Trial indices.

    Returns
    -------
    list of experiment_runner.core.experiment.Trial
        Noise seed of trial ``i``: the preset's ``simulation.seed + i``.
    """
    base = preset.simulation.seed
    out = []
    for i in indices:
        x0 = start_position(camp, preset, ref, int(i))
        out.append(Trial(case=case.name, index=int(i), x_ref=ref.x + x0, v_ref=np.asarray(ref.v),
                         seed=base + int(i), window=camp.test.window, segments=tuple(ref.segments)))
    return out


def simulate_trials(camp: Campaign, case: Case, cond: Condition, preset: Preset, indices, correction=None,
                    models=None):
    """Trials ``indices`` of ``case`` at ``cond`` on the batch engine.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    case : Case
        The case.
    cond : Condition
        The condition.
    preset : stage_sim.config.Preset
        The case's stage, as run.
    indices : iterable of int
        Trial indices.
    correction : numpy.ndarray, optional
        SAI Step II reference correction held by the manager.
    models : experiment_runner.core.batch.Models, optional
        The preset's compiled models, when already built.

    Returns
    -------
    ref : profiles.Reference
        The shared (start-at-0) reference.
    trials : list of experiment.Trial
        As :func:`make_trials` gives them (index, start, seed).
    res : batch.BatchResult
        Row ``j`` is trial ``indices[j]``; not checked (failed trials have a status).
    """
    ref = reference(camp, cond, preset.controller.rate)
    trials = make_trials(camp, case, preset, ref, indices)
    x0 = np.array([tr.x_ref[0] - ref.x[0] for tr in trials])
    res = simulate(preset, ref.x, ref.v, n_trials=len(trials), x0=x0, seeds=[tr.seed for tr in trials],
                   correction=correction, models=models, check=False)
    return ref, trials, res


def metric_record(trial: Trial, res, j: int, rate: float) -> dict:
    """Metrics of trial ``trial`` (row ``j`` of ``res``).

    Parameters
    ----------
    trial : experiment_runner.core.experiment.Trial
        The trial.
    res : experiment_runner.core.batch.BatchResult
        The batch it ran in.
    j : int
        Its row in ``res``.
    rate : float
        Control rate [Hz].

    Returns
    -------
    dict
        :func:`experiment_runner.core.experiment.trial_metrics` (SI units), or every metric None and
        ``failed`` (the plant's status) for a trial that failed.
    """
    if res.status[j] != 0:
        return {"trial": trial.index, "case": trial.case, **{k: None for k in TRIAL_METRICS},
                "failed": STATUS_TEXT[int(res.status[j])]}
    return trial_metrics(trial, res.y[j], res.x_ref[j], rate)


def plain(d: dict) -> dict:
    """numpy scalars -> Python numbers (JSON), one level deep.

    Parameters
    ----------
    d : dict
        Values possibly numpy scalars.

    Returns
    -------
    dict

    Examples
    --------
    >>> plain({"n": np.int64(3), "t": np.float64(0.5), "s": "x"})
    {'n': 3, 't': 0.5, 's': 'x'}
    """
    out = {}
    for k, v in d.items():
        if isinstance(v, np.integer):
            v = int(v)
        elif isinstance(v, np.floating):
            v = float(v)
        out[k] = v
    return out


def graph_experiment(camp: Campaign, case: Case, cond: Condition, trial: int, cal_values=None) -> dict:
    """A one-trial experiment file (:mod:`experiment_runner.core.experiment`) reproducing trial
    ``trial`` of ``case`` at ``cond`` through the ROS graph.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    case : Case
        The case.
    cond : Condition
        The condition.
    trial : int
        Trial index (its start position and noise seed).
    cal_values : dict, optional
        Calibrated values (``calibration.json`` ``values``).

    Returns
    -------
    dict
        The experiment document (its ``preset`` and ``overrides`` as the batch ran the trial).
    """
    preset = case_preset(camp, case, cal_values, cond)
    ov = case_overrides(camp, case, cal_values, cond)
    ov["simulation.seed"] = int(preset.simulation.seed + trial)
    t = camp.test
    return {"name": f"{camp.name}_{case.name}_{cond.key}_t{trial}",
            "description": f"{camp.title}: {case.label}, {cond.label}, trial {trial} (written by nanostage campaign)",
            "preset": case.preset, "overrides": ov, "profile": t.profile(cond).model_dump(mode="json", exclude_none=True), "trials": 1,
            "starts": camp.starts.trial(trial).model_dump(mode="json"), "window": t.window}


def learn_step_ii(camp: Campaign, case: Case, preset: Preset, progress=None, cond: Condition | None = None) -> dict:
    """Step II of Sec. 5.3: ILC (Eq. 5.2) of the reference correction after a switch.

    ``learn: at_rest`` (the seed's): the stage holds position, goes compliant for ``compliant_time``
    and back to stiff. ``learn: on_move`` (not the seed's; needs ``cond``): the error after the switch
    at the end of the condition's own move, i.e. the correction also learns whatever the locked stage
    repeatably does after the move.

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    case : Case
        The case.
    preset : stage_sim.config.Preset
        The case's stage, as run.
    progress : callable, optional
        Called with no argument after each iteration.
    cond : Condition, optional
        The condition of an ``on_move`` learning.

    Returns
    -------
    dict
        ``correction`` (the learned reference correction [m] per sample after the switch),
        ``rms_history_m`` / ``peak_history_m`` (the error per iteration [m]), ``iterations`` and the
        settings learned with (``length_s``, ``trials``, ``compliant_time_s``, ``learn``).
    """
    spec = case.step_ii
    ilc = preset.sai_manager.ilc
    rate = preset.controller.rate
    q = int(round(ilc.length * rate))
    travel = preset.stage.travel
    if spec.learn == "on_move":
        if cond is None:
            raise ValueError("learn_step_ii: learn on_move needs the condition")
        ref = reference(camp, cond, rate)
        x, v = np.asarray(ref.x, float), np.asarray(ref.v, float)
        lo, hi = travel.min - min(0.0, float(x.min())), travel.max - max(0.0, float(x.max()))
    else:
        n_pre = int(round(spec.settle_before * rate))
        n_comp = int(round(spec.compliant_time * rate))
        n_post = q + int(round(0.01 * rate))
        x = np.zeros(n_pre + n_comp + n_post)
        v = np.zeros_like(x)
        v[n_pre:n_pre + n_comp] = 1e-12       # p2p rule: compliant while v_ref != 0 (no feedforward uses it)
        lo, hi = travel.min, travel.max
    x0 = Starts(margin=camp.starts.margin, seed=camp.starts.seed + 100_000).positions(spec.trials, (lo, hi))
    seeds = preset.simulation.seed + 100_000 + np.arange(spec.trials)
    models = Models.from_preset(preset)
    iterations = ilc.iterations if spec.iterations is None else spec.iterations
    u = np.zeros(q)
    hist, peak = [], []
    for it in range(iterations + 1):
        r = simulate(preset, x, v, n_trials=spec.trials, x0=x0, seeds=seeds, correction=u, models=models)
        errs = []
        for b in range(spec.trials):
            edges = np.flatnonzero((r.mode[b, :-1] == 1.0) & (r.mode[b, 1:] == 0.0))
            k0 = int(edges[-1]) + 1
            e = (x0[b] + x - r.y[b])[k0:k0 + q]
            errs.append(np.pad(e, (0, q - e.size)))
        e_mean = np.mean(errs, axis=0)
        hist.append(float(np.sqrt(np.mean(np.square(errs)))))
        peak.append(float(np.max(np.abs(errs))))
        if progress:
            progress()
        if it < iterations:
            u = ilc_update(u, e_mean, ilc, rate)
    return {"correction": u, "rms_history_m": hist, "peak_history_m": peak, "iterations": iterations,
            "length_s": ilc.length, "trials": spec.trials, "compliant_time_s": spec.compliant_time,
            "learn": spec.learn}

