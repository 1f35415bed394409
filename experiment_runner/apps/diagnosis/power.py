"""Power study: ``nanostage diagnose --selftest --power [--cases N] [--json]``.

Randomized concealed-effect cases instead of a fixed list. Each case draws, from a seed fixed
by its index (same study, same cases):

* a **nominal**: the Ch. 4 stage rigid (``fi_stage_nofi``) or isolated (``fi_stage``; the
  SAI stage ``sai_stage`` without ILC for the isolator transient), with Dahl (Table 4.3),
  GMS (Table 4.4) or Coulomb friction, at 10 kHz (the seed's PID) or 1 kHz (the same
  loop shaping, ``loop_shape_pid(2 kg, 40 Hz)``), drive noise 0.5, 1 or 2 times the preset's;
* a **record**: single-trial point-to-point, multi-trial point-to-point, circle (x axis),
  stepped sine or step sequence, sizes and speeds drawn too;
* a **truth**: the nominal plus one effect of the library (every effect in turn), two effects
  (pairs), or nothing (negative control: another noise realisation); the effect size is
  drawn log-uniformly over a range from well below to well above what the record can show,
  stratified per effect so that every effect spans its range.

The recording is simulated from the truth (the batch engine, noise on) and handed to the
diagnosis in memory as a :class:`~.data.DiagData` (only what a rig gives: reference,
command, measurement, and the dither/SAI commands where the stage has them); the nominal
is the preset as a user would write it.

The **size that counts** is what the effect does to the replay: how much further the
nominal's held-out closed-loop replay is from recordings of the truth than from its own
(``replay_change``, in units of the nominal's run-to-run floor, :mod:`.judge`). Rates:

``power.named_first_rate``  single-effect cases with ``replay_change >= 3``: the true effect
                            (or a confounded set holding it) named first
``power.pair_rate``         pairs in which each effect changes the replay by >= 3 floors once the
                            other is in the model (``replay_change_given_other``: the nominal
                            plus the other effect against recordings of the truth, in that
                            model's floor): both named, the first named one of them.
                            ``pair_rate_alone`` counts pairs by each effect's change from the
                            nominal alone instead (an effect can be large alone and small beside
                            the other: a viscous term beside a GMS, 6.7x alone, 0.2x given it)
``power.params_rate``       of the correctly named effects above: every parameter within
                            +-20 % of the truth
``power.params_within_2sigma`` of their parameters with a reported 1-sigma: the share whose
                            error is within 2 sigma (honest uncertainties give ~95 %)
``false_positive_rate``     negative controls with any effect named

``report.md`` (with ``--out``) plots the detection rate against the replay change per
effect (``power_detection.png``) and lists every rejected-but-true effect (above the 3x
line, not named) and every accepted-but-harmful one (named though the truth lacks it, or
the improved model's replay worse than the nominal's) with the diagnosis' reason.
"""
from __future__ import annotations

import json
import math
import time
import traceback
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from experiment_runner.core import outputs
from experiment_runner.core.batch import simulate
from experiment_runner.core.executor import default_workers, make_executor
from experiment_runner.core.experiment import Experiment, build_trials
from stage_control.tuning import loop_shape_pid
from stage_sim import friction
from stage_sim.config import load_preset, preset_from_dict
from stage_sim.friction.base import FrictionVariation

from .data import from_trials
from .effects import LIBRARY
from .effects.base import Draw, log_uniform
from .effects.friction_laws import Gms
from .effects.stochastic import NOISE
from .judge import ReplayJudge
from .model import ModelSpec
from .options import Options
from .pipeline import diagnose
from .report import jsonable
from .truth import check_params

__all__ = ["PowerCase", "make_cases", "run_power", "DEFAULT_CASES", "dealt_effects"]

DEFAULT_CASES = 150
"""Default study size: 45 negative controls, 15 pairs, 90 single-effect cases (5 per effect)."""

MASTER_SEED = 20240611


def dealt_effects(library=LIBRARY) -> list[str]:
    """The keys of every effect a truth can be written with (:attr:`.effects.base.Effect.deal`), in the
    order they are dealt (an effect whose truths are another's, ``truth_of``, is dealt as that one).

    Parameters
    ----------
    library : Library, optional
        The library of effects.

    Returns
    -------
    list of str
    """
    return [e.key for e in library.dealt()]


def _never_paired(a: str, b: str, library=LIBRARY) -> bool:
    """Whether effects ``a`` and ``b`` are never dealt as a pair: of one exclusive group (two friction
    laws) or declared apart (:attr:`.effects.base.Effect.never_paired_with`: one drive delay, whole and
    fractional samples)."""
    return (b in library.exclusive_of(a) or b in library[a].never_paired_with
            or a in library[b].never_paired_with)


@dataclass
class PowerCase:
    """One case of the study, fixed by its index (same study, same cases).

    Parameters
    ----------
    index : int
        Its place in the study.
    effects : tuple of str
        Concealed effects: () a negative control, (e,) a single effect, (e1, e2) a pair.
    stage : {"rigid", "isolated", "sai"}
        The nominal stage (``fi_stage_nofi``, ``fi_stage``, ``sai_stage``).
    friction : {"dahl", "gms", "coulomb"}
        The nominal's bearing friction law.
    rate : float
        Control rate [Hz].
    noise : float
        Drive-noise factor on the nominal's level.
    record : {"p2p1", "p2p", "circle", "sine", "steps"}
        The recorded experiment.
    quantiles : tuple of float
        Effect-size quantile per effect (0...1 over its range, log-uniform).
    seed : int
        Noise seed of the truth's recording.
    profile : dict
        The experiment's profile.
    trials : int
        Trials recorded.
    """
    index: int
    effects: tuple                   # () negative control, (e,) single, (e1, e2) pair
    stage: str                       # rigid | isolated | sai
    friction: str                    # dahl | gms | coulomb
    rate: float                      # control rate [Hz]
    noise: float                     # drive noise factor
    record: str                      # p2p1 | p2p | circle | sine | steps
    quantiles: tuple = ()            # effect-size quantile per effect (0...1)
    seed: int = 0
    profile: dict = field(default_factory=dict)
    trials: int = 1

    @property
    def name(self) -> str:
        """``NNN_effects_record_stage_friction_Nk``, e.g. ``001_viscous_p2p1_isolated_gms_10k``."""
        what = "+".join(self.effects) or "negative"
        return f"{self.index:03d}_{what}_{self.record}_{self.stage}_{self.friction}_{int(self.rate / 1000)}k"

    @property
    def kind(self) -> str:
        """``negative``, ``single`` or ``pair``."""
        return "negative" if not self.effects else ("pair" if len(self.effects) > 1 else "single")


# --------------------------------------------------------------------------- nominals
def nominal_doc(case: PowerCase) -> dict:
    """The nominal preset (mapping) of a case.

    Parameters
    ----------
    case : PowerCase
        The case.

    Returns
    -------
    dict
        A preset mapping (drive noise scaled by ``case.noise``, PID re-shaped at another rate).
    """
    base = {"rigid": "fi_stage_nofi", "isolated": "fi_stage", "sai": "sai_stage"}[case.stage]
    d = load_preset(base).model_dump(mode="json")
    d["name"] = f"power_{case.name}_nominal"
    if case.stage == "sai":
        d["sai_manager"]["ilc"] = None
    for b in d["stage"]["bearings"]:
        fr = b["friction"]
        if case.friction == "gms":
            b["friction"] = Gms.table_4_4()
        elif case.friction == "coulomb":
            b["friction"] = friction.coulomb.element(fr["f_c"], viscous=fr.get("viscous", 0.0))
    if case.rate != d["controller"]["rate"]:
        d["controller"]["rate"] = case.rate
        d["controller"]["pid"].update(loop_shape_pid(2.0, 40.0, delay=0.5 / case.rate))
    d["stage"]["drive"]["noise_current_rms"] = NOISE * case.noise
    d["simulation"]["seed"] = 0
    return d


# --------------------------------------------------------------------------- truths
def _truth_effect(e: str, q: float, rng, d: dict, case: PowerCase, info: dict) -> dict:
    """Apply effect ``e`` of size quantile ``q`` to the preset mapping ``d`` (in place, the effect's
    :meth:`~.effects.base.Effect.conceal`; the sign is the generator's first draw); returns the truth
    values of the effect's parameters. A friction law written over the bearings keeps the variation
    an earlier effect gave them."""
    kept = [{k: b["friction"][k] for k in FrictionVariation.model_fields if k in b["friction"]}
            for b in d["stage"]["bearings"]]
    sign = 1.0 if rng.random() < 0.5 else -1.0
    out = LIBRARY[e].conceal(d, Draw(q=q, sign=sign, rng=rng, stage=case.stage, friction=case.friction,
                                     rate=case.rate, **info))
    for b, var in zip(d["stage"]["bearings"], kept):
        for k, v in var.items():
            b["friction"].setdefault(k, v)
    return out


# --------------------------------------------------------------------------- cases
def _compatible(e: str, stage: str, law: str, rate: float) -> bool:
    """Whether a truth of effect ``e`` can be written on this setting: the effect's own rule
    (:meth:`~.effects.base.Effect.conceal_on`), and an SAI stage only as the seed's (Dahl, 10 kHz)."""
    return LIBRARY[e].conceal_on(stage, law) and (stage != "sai" or (law == "dahl" and rate == 1e4))


def _draw_setting(rng, effects: tuple):
    for _ in range(200):
        stage = "sai" if "isolator_transient" in effects else str(rng.choice(["rigid", "rigid", "isolated"]))
        law = "dahl" if stage == "sai" else str(rng.choice(["dahl", "gms", "coulomb"]))
        rate = 1e4 if stage == "sai" else float(rng.choice([1e4, 1e3]))
        if all(_compatible(e, stage, law, rate) for e in effects):
            return stage, law, rate
    raise RuntimeError(f"no setting for {effects}")


def _draw_record(rng, case: PowerCase):
    kinds = ["p2p1", "p2p", "circle", "sine", "steps"]
    if case.stage == "sai":
        kinds = ["p2p", "p2p1"]
    rec = str(rng.choice(kinds))
    slow = case.rate < 5e3
    if rec in ("p2p1", "p2p"):
        dist = float(rng.choice([-1, 1])) * log_uniform(rng.random(), 2e-6, 2e-3)
        prof = {"kind": "point_to_point", "distance": dist, "dwell": 0.25 if slow else 0.06}
        trials = 1 if rec == "p2p1" else 4
    elif rec == "circle":
        prof = {"kind": "circle", "radius": log_uniform(rng.random(), 2e-4, 2e-3),
                "speed": log_uniform(rng.random(), 0.005, 0.04), "cycles": 1.0}
        r, v = prof["radius"], prof["speed"]
        period = 2 * math.pi * r / v
        if period > 0.6:              # keep the record affordable: at most ~0.6 s per trial
            prof["speed"] = 2 * math.pi * r / 0.6
        elif period < 0.25:           # and long enough to diagnose (>= 250 samples at 1 kHz)
            prof["speed"] = 2 * math.pi * r / 0.25
        trials = int(rng.integers(3, 7))
    elif rec == "sine":
        f1 = log_uniform(rng.random(), 3.0, 10.0) if slow else log_uniform(rng.random(), 5.0, 15.0)
        prof = {"kind": "sine_sweep", "frequencies": [f1, 3 * f1], "amplitude": log_uniform(rng.random(), 2e-5, 3e-4),
                "periods": 3, "settle_periods": 1}
        trials = 3
    else:
        prof = {"kind": "step_sequence", "distance": log_uniform(rng.random(), 2e-6, 5e-5), "n_forward": 3,
                "n_backward": 3, "dwell": 0.08 if slow else 0.03}
        trials = 3
    return rec, prof, trials


def make_cases(n: int = DEFAULT_CASES, master_seed: int = MASTER_SEED) -> list[PowerCase]:
    """The ``n`` cases of the study: 30 % negative controls, 10 % pairs, the rest single
    effects dealt over :func:`dealt_effects` in turn, sizes stratified per effect.

    Parameters
    ----------
    n : int, optional
        Cases.
    master_seed : int, optional
        Seed of the deal.

    Returns
    -------
    list of PowerCase
    """
    n = int(n)
    n_neg = max(1, round(0.3 * n)) if n >= 3 else 0
    n_pair = round(0.1 * n)
    n_single = max(0, n - n_neg - n_pair)
    rng0 = np.random.default_rng(master_seed)
    order = dealt_effects()
    singles = [order[i % len(order)] for i in range(n_single)]
    per = {e: singles.count(e) for e in order}
    strata = {e: list(rng0.permutation(per[e])) for e in order}
    pairs = []
    while len(pairs) < n_pair:
        a, b = (str(x) for x in rng0.choice([e for e in order if LIBRARY[e].paired], 2, replace=False))
        if _never_paired(a, b) or (a, b) in pairs or (b, a) in pairs:
            continue
        pairs.append((a, b))
    specs = [(s,) for s in singles] + pairs + [()] * n_neg
    cases = []
    seen = {e: 0 for e in order}
    for i, effs in enumerate(specs):
        rng = np.random.default_rng([master_seed, i])
        qs = []
        for e in effs:
            if len(effs) == 1:
                k = seen[e]
                seen[e] += 1
                qs.append(float((strata[e][k] + rng.random()) / per[e]))
            else:
                qs.append(float(rng.uniform(0.3, 1.0)))
        stage, friction, rate = _draw_setting(rng, effs)
        c = PowerCase(index=i, effects=tuple(effs), stage=stage, friction=friction, rate=rate,
                      noise=float(rng.choice([0.5, 1.0, 2.0])), record="", quantiles=tuple(qs),
                      seed=int(rng.integers(1, 2 ** 31 - 1)))
        c.record, c.profile, c.trials = _draw_record(rng, c)
        cases.append(c)
    return cases


# --------------------------------------------------------------------------- one case
def _trials(case: PowerCase, nominal):
    exp = Experiment.model_validate({"name": case.name, "preset": "fi_stage_nofi", "profile": case.profile,
                                     "trials": case.trials, "starts": {"margin": 0.005, "seed": case.seed % 100000},
                                     "window": 25e-9})
    return build_trials(exp, nominal)


def build_case(case: PowerCase):
    """Build a case: its nominal, its concealed truth and the truth's recording.

    Parameters
    ----------
    case : PowerCase
        The case.

    Returns
    -------
    tuple
        ``(nominal Preset, truth Preset, truth values {effect: {param: value}}, DiagData, trials)``.
    """
    nom_doc = nominal_doc(case)
    nominal = preset_from_dict(nom_doc, f"power case {case.name} nominal")
    tr = _trials(case, nominal)
    info = _info(tr)
    truth_doc = json.loads(json.dumps(nom_doc))
    expect = {}
    for i, (e, q) in enumerate(zip(case.effects, case.quantiles)):
        expect[e] = _truth_effect(e, q, np.random.default_rng([case.seed, 7, i]), truth_doc, case, info)
    truth_doc["name"] = f"power_{case.name}_truth"
    truth_doc["simulation"]["seed"] = case.seed % 1000000
    truth = preset_from_dict(truth_doc, f"power case {case.name} truth")
    data = record(truth, tr)
    return nominal, truth, expect, data, tr


def record(truth, trials):
    """What a rig records of ``trials`` run on ``truth`` (noise on).

    Parameters
    ----------
    truth : stage_sim.config.Preset
        The concealed truth.
    trials : list of experiment_runner.core.experiment.Trial
        The trials.

    Returns
    -------
    DiagData
    """

    res = simulate(truth, np.stack([t.x_ref for t in trials]), np.stack([t.v_ref for t in trials]),
                   seeds=[truth.simulation.seed + t.index for t in trials], check=False)
    B = len(trials)
    rows = lambda a: [a[b] for b in range(B)]  # noqa: E731
    dith = truth.dither is not None
    sai = truth.stage.sai is not None and truth.sai_manager is not None
    return from_trials(truth.controller.rate, np.zeros(B), rows(res.x_ref), rows(res.v_ref), rows(res.u), rows(res.y),
                       source="power study (simulated, truth concealed)",
                       d0=rows(res.dither[..., 0]) if dith else None, d1=rows(res.dither[..., 1]) if dith else None,
                       mode=rows(res.mode) if sai else None)


def replay_change(nominal, variants: dict, data) -> dict:
    """How far the nominal's held-out replay is from recordings of each variant (presets),
    beyond its own run-to-run floor: ``sqrt(|E D(variant) - E D(nominal)| / E D(nominal))``
    (:mod:`.judge`; 4 simulated recordings per variant).

    Parameters
    ----------
    nominal : stage_sim.config.Preset
        The nominal.
    variants : dict
        Name -> preset.
    data : DiagData
        The recording (its held-out trials are judged).

    Returns
    -------
    dict
        Name -> the change, in floor units (3 = the study's threshold of a detectable effect).
    """
    j = ReplayJudge(data)
    nom = ModelSpec(nominal)
    fl = j.floor(nom)
    n = max(j.n, 1)
    base = float(np.mean(j.sim_blocks(fl.replay, fl).sum(axis=1) / n))
    out = {}
    for k, p in variants.items():
        u, y, _, _ = j.simulate_recordings(ModelSpec(p), j.seeds[:4])
        e2 = [((u[i] - fl.replay.u) / fl.sigma_u) ** 2 + ((y[i] - fl.replay.y) / fl.sigma_y) ** 2 for i in range(4)]
        Dv = float(np.mean([np.sum(x[j.mask]) / n for x in e2]))
        # a floor without noise (a stage that never slips at its encoder step) counts as 2 per
        # sample, as :meth:`.judge.ReplayJudge.floor_ratio` counts it
        out[k] = float(math.sqrt(abs(Dv - base) / max(base, 2.0)))
    return out


def _named(rep: dict) -> list[tuple[str, set]]:
    return [(f["effect"], {f["effect"]} | set(f.get("confounded_with") or [])) for f in rep["found"]]


def judge_case(case: PowerCase, rep: dict, expect: dict, change: dict) -> dict:
    """Outcome of one case: named first / pair / false positive, parameter errors, reasons.

    Parameters
    ----------
    case : PowerCase
        The case.
    rep : dict
        The diagnosis report.
    expect : dict
        Effect -> parameter -> true value.
    change : dict
        Effect -> :func:`replay_change` of it.

    Returns
    -------
    dict
    """
    named = _named(rep)
    keys = [k for k, _ in named]
    truth = set(case.effects)
    out = {"case": case.name, "kind": case.kind, "effects": list(case.effects), "named": keys,
           "replay_change": change, "verdict": rep.get("verdict")}
    if not truth:
        out["false_positive"] = bool(keys)
        return out
    first_ok = bool(named) and bool(named[0][1] & truth)
    covered = {e for e in truth if any(e in st for _, st in named)}
    out["named_first"] = first_ok and covered == truth if len(truth) == 1 else first_ok
    out["both_named"] = first_ok and covered == truth
    out["detected"] = {e: e in covered for e in truth}
    out["extra"] = [k for k, st in named if not (st & truth)]
    params = {}
    for e, exp_ in expect.items():
        entry = next((f for f in rep["found"] if f["effect"] == e), None)
        if entry is None:
            entry = next((a for f in rep["found"] for a in f.get("alternatives") or [] if a["effect"] == e), None)
        ok, ch = check_params(entry, exp_)
        params[e] = {"ok": ok if entry is not None else None, "checks": ch}
    out["params"] = params
    return out


def _reason(rep: dict, effect: str) -> str:
    """Why the diagnosis did not adopt ``effect`` (from its selection steps)."""
    why = []
    for st in (rep.get("selection") or {}).get("steps", []):
        for c in st.get("candidates", []):
            if c.get("effect") == effect:
                r = c.get("why") or ("significant" if c.get("significant") else "not significant")
                why.append(f"step {st['step']}: {r}")
        if effect in (st.get("failed") or {}):
            why.append(f"step {st['step']}: the fit failed ({st['failed'][effect]})")
    if not why:
        return "never proposed (no candidate row)"
    return "; ".join(why[:3])


def run_case(case: PowerCase, keep=None) -> dict:
    """Build, diagnose and judge one case (an executor task); the warnings it raised listed
    in the result (``warnings``), not printed.

    Parameters
    ----------
    case : PowerCase
        The case.
    keep : str or pathlib.Path, optional
        Folder for the case's recording and report.

    Returns
    -------
    dict
        :func:`judge_case`'s result (or ``error`` when the case failed) with ``setting``, ``seconds`` and any ``warnings``.
    """
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:     # a worker process: per case, not per thread
        warnings.simplefilter("default")
        res = _run_case(case, keep)
    if caught:
        res["warnings"] = sorted({f"{w.category.__name__}: {w.message} ({Path(w.filename).name}:{w.lineno})"
                                  for w in caught})
    res["setting"] = {"stage": case.stage, "friction": case.friction, "rate_hz": case.rate, "noise": case.noise,
                      "record": case.record, "trials": case.trials}
    res["seconds"] = round(time.perf_counter() - t0, 2)
    return res


def _run_case(case: PowerCase, keep) -> dict:
    try:
        nominal, truth, expect, data, tr = build_case(case)
        variants = {"truth": truth}
        alldata = data.subset(np.arange(data.shape[1]))
        given = {}
        if len(case.effects) == 2:
            for i, (e, q) in enumerate(zip(case.effects, case.quantiles)):
                doc = nominal.model_dump(mode="json")
                _truth_effect(e, q, np.random.default_rng([case.seed, 7, i]), doc, case, _info(tr))
                variants[e] = preset_from_dict(doc, e)
            # what each effect adds to the truth once the other is in the model: the nominal plus
            # the other effect's replay against recordings of the truth, in that model's floor
            a, b = case.effects
            given = {a: replay_change(variants[b], {"truth": truth}, alldata)["truth"],
                     b: replay_change(variants[a], {"truth": truth}, alldata)["truth"]}
        change = replay_change(nominal, variants, alldata)
        truth_stable = ReplayJudge(data.subset(np.arange(data.shape[1]))).replay(ModelSpec(truth)).ok
        out_dir = None if keep is None else Path(keep) / case.name
        rep = diagnose(None, ModelSpec(nominal), out=out_dir, data=data, options=Options(plots=keep is not None,
                                                                                          n_jobs=1, progress=False,
                                                                                          max_seconds=None))
        res = judge_case(case, rep, expect, change)
        if given:
            res["replay_change_given_other"] = given
        res["expect"] = expect
        res["truth_stable"] = bool(truth_stable)
        res["diagnose_s"] = round(rep["timing_s"]["total_s"], 2)
        res["improved_worse"] = _improved_worse(rep)
        if case.effects:
            res["reasons"] = {e: _reason(rep, e) for e in case.effects if not res["detected"].get(e)}
        res["extra_reasons"] = {e: _extra_reason(rep, e) for e in res.get("extra") or (res["named"] if not case.effects else [])}
    except Exception as err:      # noqa: BLE001 - a crashing case is a failed case, reported
        res = {"case": case.name, "kind": case.kind, "effects": list(case.effects), "error": repr(err),
               "traceback": traceback.format_exc(limit=4), "named": [], "replay_change": {}}
    return res


def _info(tr):
    x = np.concatenate([t.x_ref for t in tr])
    v = np.concatenate([t.v_ref for t in tr])
    return {"x_center": float(0.5 * (x.max() + x.min())), "half_span": max(0.5 * float(np.ptp(x)), 1e-4),
            "stroke": max(float(np.median([np.ptp(t.x_ref) for t in tr])), 2e-6),
            "v_max": max(float(np.max(np.abs(v))), 1e-5)}


def _improved_worse(rep: dict):
    """The improved model's held-out replay unstable or further from the data than the nominal's."""
    r = rep.get("replay") or {}
    if not rep.get("found") or not r:
        return False
    fr = r["floor_ratio"]
    return bool(not r["stable"]["improved"] or fr["improved"] > 1.05 * fr["nominal"])


def _extra_reason(rep: dict, effect: str) -> str:
    for st in (rep.get("selection") or {}).get("steps", []):
        if st.get("accepted") == effect:
            c = next((c for c in st.get("candidates", []) if c.get("effect") == effect), {})
            if "improvement" in c and "threshold" in c:
                return (f"step {st['step']}: replay improvement {c['improvement']:.3g} vs threshold "
                        f"{c['threshold']:.3g} ({c.get('why', '')})")
            return f"step {st['step']}: J_held improvement {c.get('improvement', float('nan')):.3g} accepted"
    f = next((f for f in rep.get("found", []) if f["effect"] == effect), {})
    if f.get("kind") == "stochastic":
        return f"stochastic: {f.get('held_out')}"
    return "adopted"


# --------------------------------------------------------------------------- the study
def _task(case: PowerCase, keep):
    numba.set_num_threads(1)
    return run_case(case, keep)


def _pair_change(r: dict, e: str) -> float:
    """What effect ``e`` of pair case ``r`` adds to the replay once the other is in the model
    (floor units); its change from the nominal alone when that was not measured."""
    return (r.get("replay_change_given_other") or r["replay_change"]).get(e, 0.0)


def summarize(results: list[dict], threshold: float = 3.0) -> dict:
    """The study's rates from the case results.

    Parameters
    ----------
    results : list of dict
        :func:`run_case` results.
    threshold : float, optional
        Effect size (replay change, floor units) from which an effect counts as detectable.

    Returns
    -------
    dict
        ``power`` (the rates), ``false_positive_rate``, counts of cases, errors and warnings.
    """
    singles = [r for r in results if r["kind"] == "single" and "error" not in r]
    pairs = [r for r in results if r["kind"] == "pair" and "error" not in r]
    negs = [r for r in results if r["kind"] == "negative"]
    # a truth whose own noise-free replay is unstable (the concealed effect makes the loop swing) has no
    # meaningful replay change: such cases are counted apart
    unstable = [r for r in singles + pairs if not r.get("truth_stable", True)]
    singles = [r for r in singles if r.get("truth_stable", True)]
    pairs = [r for r in pairs if r.get("truth_stable", True)]
    big = [r for r in singles if r["replay_change"].get("truth", 0) >= threshold]
    pbig = [r for r in pairs if all(_pair_change(r, e) >= threshold for e in r["effects"])]
    palone = [r for r in pairs if all(r["replay_change"].get(e, 0) >= threshold for e in r["effects"])]
    named = [r for r in big if r["named_first"]]
    pok = [r for r in pbig if r["both_named"]]
    par = [r["params"][r["effects"][0]]["ok"] for r in named if r["params"][r["effects"][0]]["ok"] is not None]
    # are the reported uncertainties honest? each named effect's parameter error against its 1-sigma
    zs = [c["z"] for r in named for c in r["params"][r["effects"][0]]["checks"].values() if c.get("z") is not None]
    by = {}
    for r in [r for r in results if r["kind"] == "single"]:
        e = r["effects"][0]
        row = by.setdefault(e, {"cases": 0, "above_3x": 0, "named_first_above_3x": 0, "named_first": 0,
                                "params_ok": 0, "errors": 0})
        row["cases"] += 1
        if "error" in r:
            row["errors"] += 1
            continue
        above = r["replay_change"].get("truth", 0) >= threshold
        row["above_3x"] += above
        row["named_first"] += bool(r["named_first"])
        row["named_first_above_3x"] += bool(above and r["named_first"])
        row["params_ok"] += bool(above and r["named_first"] and r["params"][e]["ok"])
    errors = [r for r in results if "error" in r]
    fp = [r for r in negs if r.get("false_positive") or "error" in r]
    harmful = [r for r in results if r.get("extra") or r.get("improved_worse")]
    return {
        "power": {"named_first_rate": len(named) / len(big) if big else None, "named_first_cases": len(big),
                  "pair_rate": len(pok) / len(pbig) if pbig else None, "pair_cases": len(pbig),
                  "pair_rate_alone": (sum(r["both_named"] for r in palone) / len(palone)) if palone else None,
                  "pair_cases_alone": len(palone),
                  "params_rate": sum(par) / len(par) if par else None, "params_cases": len(par),
                  "params_within_2sigma": (sum(abs(z) <= 2 for z in zs) / len(zs)) if zs else None,
                  "params_with_sigma": len(zs),
                  "threshold_floor_units": threshold, "by_effect": by},
        "false_positive_rate": len(fp) / len(negs) if negs else None,
        "cases": len(results), "negatives": len(negs), "singles": len(singles) + sum(r["kind"] == "single" and "error" in r for r in results),
        "pairs": len([r for r in results if r["kind"] == "pair"]),
        "errors": len(errors),
        "truth_unstable": [r["case"] for r in unstable],
        "warnings": {r["case"]: r["warnings"] for r in results if r.get("warnings")},
        "harmful_or_wrong": len(harmful),
    }


def run_power(n_cases: int = DEFAULT_CASES, workers: int | None = None, cluster=None, out=None, keep=None,
              verbose: bool = False, only=None) -> dict:
    """Run the study (cases on ``workers`` local processes, default one per core this process may use
    (:func:`~experiment_runner.core.executor.default_workers`), or a Dask ``cluster``); returns the
    summary with ``results``; with ``out`` writes ``power.json``, ``report.md`` and the plot.

    Parameters
    ----------
    n_cases : int, optional
        Cases (:func:`make_cases`).
    workers : int, optional
        Local worker processes (default: one per core this process may use).
    cluster : str, optional
        Dask scheduler address (instead of local workers).
    out : str or pathlib.Path, optional
        Output folder.
    keep : str or pathlib.Path, optional
        Folder for every case's recording and report.
    verbose : bool, optional
        A line per case.
    only : list of str, optional
        Run only cases whose name contains one of these.

    Returns
    -------
    dict
        :func:`summarize`'s summary with ``wall_s`` and ``results``.
    """
    if workers is None and cluster is None:
        workers = default_workers()
    cases = make_cases(n_cases)
    if only:
        cases = [c for c in cases if any(o in c.name for o in only)]
    t0 = time.perf_counter()
    results = [None] * len(cases)
    with make_executor(workers, cluster) as ex:
        for k, (i, r) in enumerate(ex.map(_task, [(i, (c, keep)) for i, c in enumerate(cases)])):
            results[i] = r
            if verbose:
                print(f"[power {k + 1}/{len(cases)}] {r['case']}: named {r.get('named')} "
                      f"change {_fmt_change(r)} {r.get('error', '')} ({r['seconds']:.1f} s)", flush=True)
    s = summarize(results)
    s["wall_s"] = round(time.perf_counter() - t0, 1)
    s["results"] = results
    if out is not None:
        write_report(out, s)
    return s


def _fmt_change(r) -> str:
    given = r.get("replay_change_given_other") or {}
    return ", ".join(f"{k} {v:.3g}x" + (f" ({given[k]:.3g}x given the other)" if k in given else "")
                     for k, v in (r.get("replay_change") or {}).items())


# --------------------------------------------------------------------------- report
def write_report(out, s: dict) -> Path:
    """Write ``power.json``, ``report.md`` and the detection-rate plot into ``out``.

    Parameters
    ----------
    out : str or pathlib.Path
        Output folder (:func:`experiment_runner.core.outputs.prepare_folder`).
    s : dict
        :func:`run_power`'s summary.

    Returns
    -------
    pathlib.Path
        The folder.
    """
    out = outputs.prepare_folder(out)
    outputs.write_text(out / "power.json", json.dumps(jsonable(s), indent=1))
    plots = []
    try:
        plots = _plot(out, s)
    except Exception as err:       # noqa: BLE001 - the plot must not lose the report
        s.setdefault("notes", []).append(f"plot failed: {err!r}")
    outputs.write_text(out / "report.md", to_markdown(s, plots))
    return out


def _pct(x):
    return "–" if x is None else f"{100 * x:.1f} %"


def to_markdown(s: dict, plots=()) -> str:
    """The study's ``report.md``.

    Parameters
    ----------
    s : dict
        :func:`run_power`'s summary.
    plots : sequence of str, optional
        Plot file names to embed.

    Returns
    -------
    str
    """
    p = s["power"]
    L = ["# Diagnosis power study", "",
         f"{s['cases']} cases ({s['singles']} single effects, {s['pairs']} pairs, {s['negatives']} negative controls), "
         f"{s.get('wall_s', 0):.0f} s wall. Size that counts: the effect's change of the nominal's held-out replay in "
         f"units of the run-to-run floor (>= {p['threshold_floor_units']:g}x: should be found).", "",
         "| rate | value | over | goal |", "|---|---|---|---|",
         f"| named first (single effects >= 3x) | {_pct(p['named_first_rate'])} | {p['named_first_cases']} | >= 95 % |",
         f"| both named (pairs, each >= 3x given the other) | {_pct(p['pair_rate'])} | {p['pair_cases']} | >= 90 % |",
         f"| both named (pairs, each >= 3x alone) | {_pct(p.get('pair_rate_alone'))} | {p.get('pair_cases_alone', 0)} | |",
         f"| parameters within ±20 % (named, >= 3x) | {_pct(p['params_rate'])} | {p['params_cases']} | |",
         f"| parameter errors within 2σ of the reported σ (named, >= 3x) | {_pct(p.get('params_within_2sigma'))} | "
         f"{p.get('params_with_sigma', 0)} parameters | ~95 % |",
         f"| false positives (negative controls) | {_pct(s['false_positive_rate'])} | {s['negatives']} | <= 5 % |",
         f"| cases that failed to run | {s['errors']} | {s['cases']} | 0 |",
         f"| cases left out: the truth's own replay unstable | {len(s.get('truth_unstable') or [])} | {s['cases']} | |",
         f"| cases that raised warnings (listed in power.json, `warnings`) | {len(s.get('warnings') or {})} | "
         f"{s['cases']} | 0 |",
         "",
         "| effect | cases | >= 3x | named first (>= 3x) | named first (all) | params ok (>= 3x) |",
         "|---|---|---|---|---|---|"]
    for e, r in p["by_effect"].items():
        L.append(f"| {e} | {r['cases']} | {r['above_3x']} | {r['named_first_above_3x']} | {r['named_first']} | "
                 f"{r['params_ok']} |")
    for f in plots:
        L += ["", f"![detection rate vs effect size]({f})"]
    res = s["results"]
    L += ["", "## Rejected but true (>= 3x the floor, not named)", ""]
    rows = [r for r in res if r["kind"] != "negative" and "error" not in r
            and any((_pair_change(r, e) if r["kind"] == "pair" else r["replay_change"].get("truth", 0)) >= 3
                    and not r["detected"].get(e)
                    for e in r["effects"])]
    L += [f"- `{r['case']}` (change {_fmt_change(r)}): named {r['named'] or 'nothing'}; "
          + "; ".join(f"{e}: {w}" for e, w in (r.get("reasons") or {}).items()) for r in rows] or ["none"]
    L += ["", "## Named first but wrong (>= 3x, another effect first)", ""]
    rows = [r for r in res if r["kind"] == "single" and "error" not in r and r["replay_change"].get("truth", 0) >= 3
            and r["detected"].get(r["effects"][0]) and not r["named_first"]]
    L += [f"- `{r['case']}`: named {r['named']}" for r in rows] or ["none"]
    L += ["", "## Accepted but harmful (an effect the truth lacks, or the improved replay worse than the nominal's)", ""]
    rows = [r for r in res if r.get("extra") or r.get("improved_worse") or (r["kind"] == "negative" and r["named"])]
    L += [f"- `{r['case']}`: named {r['named']}" + (" — improved replay worse than nominal" if r.get("improved_worse") else "")
          + "".join(f"; {e}: {w}" for e, w in (r.get("extra_reasons") or {}).items()) for r in rows] or ["none"]
    L += ["", "## Parameter errors of correctly named effects (>= 3x)", ""]
    for r in res:
        if r["kind"] == "single" and "error" not in r and r.get("named_first") and r["replay_change"].get("truth", 0) >= 3:
            pr = r["params"][r["effects"][0]]
            if pr["ok"] is False:
                L.append(f"- `{r['case']}`: " + ", ".join(
                    (f"{k} {v['estimate']:.4g} vs {v['truth']:.4g}"
                     + (f" (± {v['sigma']:.3g}, z {v['z']:+.2g})" if v.get("z") is not None else ""))
                    if v.get("estimate") is not None else f"{k} missing"
                    for k, v in pr["checks"].items()))
    errs = [r for r in res if "error" in r]
    if errs:
        L += ["", "## Cases that failed to run", ""] + [f"- `{r['case']}`: {r['error']}" for r in errs]
    return "\n".join(L) + "\n"


def _plot(out: Path, s: dict) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    res = [r for r in s["results"] if r["kind"] == "single" and "error" not in r]
    effs = [e for e in dealt_effects() if any(r["effects"][0] == e for r in res)]
    if not effs:
        return []
    nc = 6
    nr = -(-len(effs) // nc)
    fig, axes = plt.subplots(nr, nc, figsize=(2.6 * nc, 2.2 * nr), squeeze=False, sharey=True)
    for ax in axes.ravel()[len(effs):]:
        ax.axis("off")
    for ax, e in zip(axes.ravel(), effs):
        rr = [r for r in res if r["effects"][0] == e]
        x = np.array([max(r["replay_change"].get("truth", 0), 1e-3) for r in rr])
        y = np.array([1.0 if r["named_first"] else 0.0 for r in rr])
        ax.semilogx(x, y + np.linspace(-0.04, 0.04, len(y)), "o", ms=4, color="C0", alpha=0.7)
        edges = np.logspace(-2, 3, 6)
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (x >= lo) & (x < hi)
            if m.any():
                ax.plot([lo, hi], [y[m].mean()] * 2, "C3-", lw=2)
        ax.axvline(3.0, color="k", ls=":", lw=0.8)
        ax.set_title(e, fontsize=8)
        ax.set_ylim(-0.1, 1.1)
        ax.set_xlim(1e-2, 1e3)
        ax.tick_params(labelsize=7)
    fig.supxlabel("replay change of the effect [run-to-run floors] (dotted: 3x)", fontsize=8)
    fig.supylabel("named first (dots: cases, bars: rate)", fontsize=8)
    fig.tight_layout()
    outputs.savefig(fig, out / "power_detection.png", dpi=90)
    plt.close(fig)
    return ["power_detection.png"]
