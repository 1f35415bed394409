"""The power study's cases, each dealt from a seed fixed by its index (same study, same cases).

A case draws:

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

The nominal is the preset as a user would write it (:func:`nominal_doc`); each effect writes
its own truth into it (:func:`truth_effect`, the effect's
:meth:`~experiment_runner.apps.diagnosis.effects.base.Effect.conceal`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from stage_control.tuning import loop_shape_pid
from stage_sim import friction
from stage_sim.config import load_preset
from stage_sim.friction.base import FrictionVariation

from ..effects import LIBRARY
from ..effects.base import Draw, log_uniform
from ..effects.friction_laws import Gms
from ..effects.stochastic import NOISE

__all__ = ["PowerCase", "make_cases", "DEFAULT_CASES", "MASTER_SEED", "dealt_effects", "nominal_doc", "truth_effect"]

DEFAULT_CASES = 150
"""Default study size: 45 negative controls, 15 pairs, 90 single-effect cases (5 per effect)."""

MASTER_SEED = 20240611


def dealt_effects(library=LIBRARY) -> list[str]:
    """The keys of every effect a truth can be written with
    (:attr:`experiment_runner.apps.diagnosis.effects.base.Effect.deal`), in the order they are dealt
    (an effect whose truths are another's, ``truth_of``, is dealt as that one).

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
    laws) or declared apart (:attr:`experiment_runner.apps.diagnosis.effects.base.Effect.never_paired_with`:
    one drive delay, whole and fractional samples)."""
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
def truth_effect(e: str, q: float, rng, d: dict, case: PowerCase, info: dict) -> dict:
    """Apply effect ``e`` of size quantile ``q`` to the preset mapping ``d`` (in place, the effect's
    :meth:`~experiment_runner.apps.diagnosis.effects.base.Effect.conceal`; the sign is the generator's
    first draw). A friction law written over the bearings keeps the variation an earlier effect gave them.

    Parameters
    ----------
    e : str
        The effect's key.
    q : float
        Effect-size quantile (0...1 over its range).
    rng : numpy.random.Generator
        The case's generator for this effect.
    d : dict
        The preset mapping, changed in place.
    case : PowerCase
        The case (its stage, friction law and rate).
    info : dict
        What the record spans (``x_center``, ``half_span``, ``stroke``, ``v_max``).

    Returns
    -------
    dict
        The truth values of the effect's parameters.
    """
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
    (:meth:`~experiment_runner.apps.diagnosis.effects.base.Effect.conceal_on`), and an SAI stage only
    as the seed's (Dahl, 10 kHz)."""
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
