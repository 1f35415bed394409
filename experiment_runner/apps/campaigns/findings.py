"""The seed's findings in the simulation: the direction (lower / higher / similar) of every
finding a campaign file states, and every seed number or limit against the simulated value.

* Trial campaigns (:func:`evaluate_findings`): the means over the trials of two cases at a
  condition, z = their difference / its standard error; a 'lower' / 'higher' finding agrees
  when the sign matches and ``|z| >= 2``, a 'similar' one when the relative change is within
  the tolerance; a settling time one case never reaches within the dwell while the other does is
  right-censored (its direction is known, its change is a bound: :func:`_censored_settling`);
  ``over: sweep_spread`` compares the spreads of the means over a sweep.
* Frequency-response campaigns (:func:`evaluate_frf_findings`): one deterministic value per
  case and amplitude; :func:`seed_bound_check` checks the limits the seed states.
"""
from __future__ import annotations

import math

import numpy as np

from experiment_runner.apps.campaigns.spec import Campaign, Finding, conditions

__all__ = ["evaluate_findings", "evaluate_frf_findings", "seed_bound_check"]


def evaluate_findings(camp: Campaign, runs: dict) -> list[dict]:
    """Direction of every seed finding in the simulation (z: difference / its standard error).

    A 'lower' / 'higher' finding agrees when the difference of the trial means has the seed's sign
    and ``|z| >= 2``; a 'similar' one when the relative difference is within its tolerance.

    Parameters
    ----------
    camp : Campaign
        The campaign (its ``seed.findings`` and ``seed.values``).
    runs : dict
        ``(case, condition key)`` -> :class:`~experiment_runner.apps.campaigns.base.RunResult`.

    Returns
    -------
    list of dict
        One row per finding: ids, the seed's and the simulated values and change, ``z``,
        ``agrees``, ``status`` and the notes (e.g. trials that did not settle).
    """
    out = []
    conds = conditions(camp)
    for f in camp.seed.findings:
        if f.over == "sweep_spread":
            out.append(_spread_finding(camp, f, runs, [c for c in conds if c.matches(**f.at())]))
            continue
        cond = next(c for c in conds if c.matches(**f.at()))
        a = runs[(f.case, cond.key)].stats[f.metric]
        b = runs[(f.versus, cond.key)].stats[f.metric]
        sa = camp.seed_value(f.case, f.metric, **cond.at())
        sb = camp.seed_value(f.versus, f.metric, **cond.at())
        seed_rel = (sa - sb) / sb if sa is not None and sb not in (None, 0) else f.change
        rel = (a.mean - b.mean) / b.mean if b.mean and math.isfinite(a.mean) and math.isfinite(b.mean) else math.nan
        se = math.sqrt((a.std ** 2 / a.n_valid if a.n_valid > 1 else 0.0)
                       + (b.std ** 2 / b.n_valid if b.n_valid > 1 else 0.0))
        diff = a.mean - b.mean
        z = diff / se if se > 0 else (math.copysign(math.inf, diff) if diff else 0.0)
        reasons = []
        if f.relative_to is not None:       # difference of the reductions vs relative_to
            ref = runs[(f.relative_to, cond.key)].stats[f.metric].mean
            rel = (b.mean - a.mean) / ref if ref and math.isfinite(ref) and math.isfinite(rel) else math.nan
            z = math.nan
        censored = _censored_settling(camp, f, a, b)
        if censored is not None:
            agrees, status, rel = censored
        elif not math.isfinite(rel):
            agrees, status = False, "undefined (no settled trials)"
        elif f.direction == "similar":
            agrees, status = _similar(rel, f.tolerance, f"reductions vs {f.relative_to} " if f.relative_to else "")
        else:
            want = -1 if f.direction == "lower" else 1
            same_sign = np.sign(diff) == want
            significant = abs(z) >= 2.0
            agrees = bool(same_sign and significant)
            status = ("agrees" if agrees else ("same sign but within the trial scatter (|z| < 2)" if same_sign
                                                else "opposite direction"))
        for who, s in ((f.case, a), (f.versus, b)):
            if s.n_valid < s.n:
                reasons.append(f"{s.n - s.n_valid} of {s.n} trials of {who} did not settle within the dwell")
        out.append({"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": cond.label,
                    "condition_key": cond.key, **cond.at(), "metric": f.metric, "direction": f.direction,
                    "tolerance": f.tolerance if f.direction == "similar" else None,
                    "seed_case": sa, "seed_versus": sb, "seed_change": seed_rel,
                    "sim_case": a.mean, "sim_versus": b.mean, "sim_change": rel if math.isfinite(rel) else None,
                    "z": z if math.isfinite(z) else (None if z != z else (1e9 if z > 0 else -1e9)),
                    "agrees": bool(agrees), "status": status, "notes": reasons, "over": "mean",
                    "relative_to": f.relative_to,
                    "explanation": f.note if not agrees else ""})
    return out


def _censored_settling(camp: Campaign, f: Finding, a, b) -> tuple | None:
    """A settling-time finding where one case never settled within the dwell and the other did:
    the unsettled case's settling time is longer than the dwell (right-censored), so the direction
    is known though the mean is not -- (agrees, status, bound on the relative change: the settled
    mean against the dwell, an upper bound for 'lower', a lower bound for 'higher'). None where
    this does not apply (another metric, a 'similar' finding, both or neither settled, no dwell).
    E.g. table_4_2_dahl at 2 trials: the No FI table with Dahl bearings ratchets out of the window
    and never settles at 5 um, the FI table settles in 18 ms."""
    dwell = getattr(camp.test, "dwell", None)
    if f.metric != "settling_time_s" or f.direction == "similar" or f.relative_to is not None or not dwell:
        return None
    if (a.n_valid == 0) == (b.n_valid == 0):
        return None
    case_settles = a.n_valid > 0
    settled, never = (a, f.versus) if case_settles else (b, f.case)
    rel = (settled.mean - dwell) / dwell if case_settles else (dwell - settled.mean) / settled.mean
    lower = case_settles            # the case is faster when it settles and the other does not
    agrees = lower == (f.direction == "lower")
    bound = "at most" if lower else "at least"
    status = (f"{'agrees' if agrees else 'opposite direction'}: {never} never settled within the {dwell:g} s dwell "
              f"(right-censored; change {bound} {rel:+.0%})")
    return agrees, status, rel


def _similar(rel: float, tolerance: float, what: str = "") -> tuple[bool, str]:
    """A 'similar' finding: agrees when ``|rel| <= tolerance``; the status text."""
    agrees = abs(rel) <= tolerance
    return agrees, (f"{what}within ±{tolerance:.0%}" if agrees
                    else f"{what}differ by {rel:+.0%} (> ±{tolerance:.0%})")


def _spread_finding(camp: Campaign, f: Finding, runs: dict, conds: list) -> dict:
    """A ``sweep_spread`` finding: the standard deviation over the sweep values of each case's
    mean metric (e.g. the ±1σ band of Fig. 4.18 over the seven stiffness errors), case vs versus.
    Agrees when the sign matches ('lower'/'higher'; there is no trial-level z) or the relative
    difference is within the tolerance ('similar')."""
    spreads = []
    for who in (f.case, f.versus):
        means = np.array([runs[(who, c.key)].stats[f.metric].mean for c in conds], float)
        spreads.append(float(np.std(means, ddof=1)) if means.size > 1 and np.all(np.isfinite(means)) else math.nan)
    a, b = spreads
    rel = (a - b) / b if math.isfinite(a) and math.isfinite(b) and b > 0 else math.nan
    if f.relative_to is not None:          # spreads of the reductions vs relative_to, in reduction points
        ref = np.mean([runs[(f.relative_to, c.key)].stats[f.metric].mean for c in conds])
        rel = (a - b) / ref if math.isfinite(a) and math.isfinite(b) and ref > 0 else math.nan
    if not math.isfinite(rel):
        agrees, status = False, "undefined (unsettled trials or no spread)"
    elif f.direction == "similar":
        agrees, status = _similar(rel, f.tolerance,
                                  f"spreads of the reductions vs {f.relative_to} " if f.relative_to else "")
    else:
        agrees = bool(np.sign(rel) == (-1 if f.direction == "lower" else 1))
        status = "agrees" if agrees else "opposite direction"
    at = {k: v for k, v in conds[0].at().items() if k != "sweep"}
    label = conds[0].label.split(f", {camp.sweep.label} =")[0] + f", spread over {camp.sweep.label}"
    return {"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": label,
            "condition_key": conds[0].key.split("__")[0] + "__spread", **at, "metric": f.metric,
            "direction": f.direction, "tolerance": f.tolerance if f.direction == "similar" else None,
            "seed_case": None, "seed_versus": None, "seed_change": f.change,
            "sim_case": a if math.isfinite(a) else None, "sim_versus": b if math.isfinite(b) else None,
            "sim_change": rel if math.isfinite(rel) else None, "z": None, "agrees": bool(agrees), "status": status,
            "notes": [], "over": "sweep_spread", "relative_to": f.relative_to,
            "explanation": f.note if not agrees else ""}



def _seed_number(camp, case: str, metric: str, cond) -> float | None:
    """The seed's value of ``metric`` of ``case`` at ``cond``; None if none or only a limit ('< 10 Hz')."""
    for v in camp.seed.values:
        if v.case == case and v.metric == metric and cond.matches(**v.at()):
            return v.value if v.bound == "value" else None
    return None


def evaluate_frf_findings(camp, runs: dict) -> list[dict]:
    """Direction of every seed finding: one deterministic value per case and amplitude.

    A finding compares ``metric`` of ``case`` at its amplitude with ``versus`` at
    ``versus_amplitude`` (default: the same amplitude). 'lower' / 'higher' agree when the
    sign matches, 'similar' when the relative change ``(case - versus) / |versus|`` is within
    the tolerance.

    Parameters
    ----------
    camp : Campaign
        A frequency-response campaign.
    runs : dict
        ``(case, condition key)`` -> :class:`~experiment_runner.apps.campaigns.frequency_response.FrfRun`.

    Returns
    -------
    list of dict
        One row per finding, as :func:`evaluate_findings`'s.
    """
    conds = conditions(camp)
    out = []
    for f in camp.seed.findings:
        ca = next(c for c in conds if c.matches(**f.at()))
        cb = ca if f.versus_amplitude is None else next(c for c in conds if c.matches(amplitude=f.versus_amplitude))
        a = runs[(f.case, ca.key)].values[f.metric]
        b = runs[(f.versus, cb.key)].values[f.metric]
        sa, sb = _seed_number(camp, f.case, f.metric, ca), _seed_number(camp, f.versus, f.metric, cb)
        seed_rel = (sa - sb) / abs(sb) if sa is not None and sb not in (None, 0) else None
        ok = math.isfinite(a) and math.isfinite(b)
        rel = (a - b) / abs(b) if ok and b != 0 else (math.nan if not ok else math.copysign(math.inf, a - b))
        if not ok:
            agrees, status = False, "undefined (" + ", ".join(
                f"{who} has no {f.metric} in the measured range" for who, v in ((f.case, a), (f.versus, b))
                if not math.isfinite(v)) + ")"
        elif f.direction == "similar":
            agrees = abs(rel) <= f.tolerance
            status = f"within ±{f.tolerance:.0%}" if agrees else f"differs by {rel:+.0%} (> ±{f.tolerance:.0%})"
        else:
            agrees = (a < b) if f.direction == "lower" else (a > b)
            status = "agrees" if agrees else "opposite direction"
        label = ca.label if cb is ca else f"{ca.label} vs {cb.label}"
        out.append({"id": f.id, "claim": f.claim, "case": f.case, "versus": f.versus, "condition": label,
                    "condition_key": ca.key, "versus_condition_key": cb.key, **ca.at(),
                    "versus_amplitude": cb.amplitude, "metric": f.metric, "direction": f.direction,
                    "tolerance": f.tolerance if f.direction == "similar" else None,
                    "seed_case": sa, "seed_versus": sb, "seed_change": seed_rel,
                    "sim_case": a if math.isfinite(a) else None, "sim_versus": b if math.isfinite(b) else None,
                    "sim_change": rel if math.isfinite(rel) else None,
                    "z": None, "agrees": bool(agrees), "status": status, "notes": [],
                    "explanation": f.note if not agrees else "", "note": f.note})
    return out


def seed_bound_check(camp, runs: dict) -> list[dict]:
    """Every seed value vs the simulation (``bound: upper/lower`` values are limits the seed states).

    Parameters
    ----------
    camp : Campaign
        The campaign.
    runs : dict
        ``(case, condition key)`` -> :class:`~experiment_runner.apps.campaigns.frequency_response.FrfRun`.

    Returns
    -------
    list of dict
        One row per seed value: the seed's value or limit, the simulated one, their ratio, and
        ``within_bound`` (None where the seed states a value, not a limit, or the simulated one is undefined).
    """
    rows = []
    conds = conditions(camp)
    for v in camp.seed.values:
        cond = next(c for c in conds if c.matches(**v.at()))
        sim = runs[(v.case, cond.key)].values[v.metric]
        bound = v.bound
        ok = None
        if math.isfinite(sim):
            ok = sim <= v.value if bound == "upper" else (sim >= v.value if bound == "lower" else None)
        rows.append({"case": v.case, "condition": cond.label, "amplitude_n": cond.amplitude, "metric": v.metric,
                     "seed": v.value, "bound": bound, "source": v.source, "sim": sim if math.isfinite(sim) else None,
                     "sim_over_seed": sim / v.value if math.isfinite(sim) and v.value else None,
                     "within_bound": ok})
    return rows

