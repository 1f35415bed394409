"""The seed's headline ratios, seed vs simulation, each with its bar and its mechanism verdict.

The main job (``nanostage campaign --main``) reproduces the eight ratios the seed's argument rests on
(Table 4.2: FI against No FI; Table 5.2: FI and SAI against the Baseline). Each ratio is the mean
of ``case`` over the mean of ``versus`` at one step size; its *bar* is half the seed's change:
a ratio the seed puts at ``r_s`` holds when the simulation's is at least half as far from 1 in the
same direction, i.e. beyond ``(1 + r_s) / 2`` (a "similar" ratio holds within its tolerance of 1).
The verdict says, from the representative trials' settling mechanism
(:mod:`experiment_runner.apps.campaigns.mechanism`), whether the simulation gets there for the seed's
reason. These checks live in the report, not in tests: a test asserts physics, the report says how
close the numbers come.

Examples
--------
>>> bar(0.36), holds(0.41, 0.36), holds(0.70, 0.36), holds(1.34, 1.69), holds(0.95, 1.0, 0.3)
(0.68, True, False, False, True)
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import numpy as np

from experiment_runner.apps.campaigns.mechanism import TAIL_S
from experiment_runner.apps.campaigns.registry import METRICS

__all__ = ["Ratio", "HEADLINE", "PREMOTION_TAU_MIN", "bar", "holds", "evaluate", "report_lines"]


class Ratio(NamedTuple):
    """One headline ratio: ``metric`` of ``case`` over ``versus`` at ``step`` in ``campaign``.

    Parameters
    ----------
    campaign : str
        Campaign name.
    case, versus : str
        The cases of the numerator and the denominator.
    step : float
        Step size [m] of the condition.
    metric : str
        Metric name (:data:`~experiment_runner.apps.campaigns.registry.METRICS`).
    similar : float, optional
        Tolerance of a "similar" ratio around 1 (None: a change).
    """
    campaign: str
    case: str
    versus: str
    step: float
    metric: str
    similar: Optional[float] = None      # tolerance of a "similar" ratio (None: a change)


QUANTISATION_RMS = 4.88e-9 / math.sqrt(12.0)
"""RMS of the 4.88 nm encoder's quantisation (Sec. 3.3, 5.2), the floor of the seed's in-position error."""

PREMOTION_TAU_MIN = 1.0 / (2 * math.pi * 10.0)
"""Fastest pre-motion creep the seed allows [s]: its closed-loop bandwidth is "less than 10 Hz" in the
pre-motion regime (Sec. 4.3, Fig. 4.6a)."""

HEADLINE = (
    Ratio("table_4_2", "fi", "nofi", 5e-3, "settling_time_s"),
    Ratio("table_4_2", "fi", "nofi", 5e-6, "settling_time_s"),
    Ratio("table_4_2", "fi", "nofi", 5e-3, "rms_in_position_m"),
    Ratio("table_5_2", "fi", "baseline", 5e-3, "settling_time_s"),
    Ratio("table_5_2", "fi", "baseline", 5e-6, "settling_time_s"),
    Ratio("table_5_2", "sai", "baseline", 5e-3, "settling_time_s"),
    Ratio("table_5_2", "sai", "baseline", 5e-6, "settling_time_s"),
    Ratio("table_5_2", "sai", "baseline", 5e-3, "rms_in_position_m", similar=0.3),
)
"""The eight ratios of the main job's report, in the seed's order."""


def bar(seed_ratio: float) -> float:
    """The simulated ratio that keeps half the seed's change: ``(1 + seed_ratio) / 2``.

    Parameters
    ----------
    seed_ratio : float
        The seed's ratio.

    Returns
    -------
    float

    Examples
    --------
    >>> bar(0.36)
    0.68
    """
    return round((1.0 + seed_ratio) / 2.0, 12)


def holds(sim: float, seed: float, similar: Optional[float] = None) -> bool:
    """Whether ``sim`` keeps at least half the seed's change (or, for a "similar" ratio, lies within
    ``similar`` of 1).

    Parameters
    ----------
    sim, seed : float
        The simulated and the seed's ratio (non-finite: does not hold).
    similar : float, optional
        Tolerance of a "similar" ratio.

    Returns
    -------
    bool

    Examples
    --------
    >>> holds(0.41, 0.36), holds(1.09, 1.69), holds(1.02, 1.0, similar=0.3)
    (True, False, True)
    """
    if not (math.isfinite(sim) and math.isfinite(seed)):
        return False
    if similar is not None:
        return abs(sim - 1.0) <= similar
    b = bar(seed)
    return sim <= b if seed < 1.0 else sim >= b


def _cond(cr, step):
    return next(c for c in cr.conditions if c.step == step)


def _ms(v):
    return "–" if v is None or not math.isfinite(v) else f"{v * 1e3:.1f} ms"


def _nm(v):
    a = abs(v)
    return f"{v * 1e6:.2f} µm" if a >= 1e-6 else f"{v * 1e9:.0f} nm"


def _settling_verdict(r: Ratio, cr, cond, seed_case: float) -> tuple[str, bool]:
    """Mechanism of a settling ratio from the two representative trials."""
    mv = cr.runs[(r.versus, cond.key)].mechanism or {}
    mc = cr.runs[(r.case, cond.key)].mechanism or {}
    lv, lc = cr.campaign.case(r.versus).label, cr.campaign.case(r.case).label
    if not mv or not mc:
        return "mechanism not analysed", False
    n_rev = len([x for x in mv["reversals"] if x["t_s"] > -0.005])
    parts = [f"{lv}: {'friction-limited' if mv['friction_limited'] else 'not friction-limited'} "
             f"({_ms(mv['settling_time_s'])} vs twin {_ms(mv['twin_settling_time_s'])}, {n_rev} reversal(s), "
             f"{'pre-motion' if mv['settled_in_premotion'] else 'no pre-motion'} creep)"]
    sw = mc.get("switch")
    if sw is None:
        parts.append(f"{lc}: {'friction-limited' if mc['friction_limited'] else 'not friction-limited'} "
                     f"({_ms(mc['settling_time_s'])} vs twin {_ms(mc['twin_settling_time_s'])})")
        ok = mv["friction_limited"] and not mc["friction_limited"]
        return "; ".join(parts) + (": **the seed's mechanism**" if ok else ": not the seed's mechanism"), ok
    # a switched case: after the lock it is the versus stage, starting from the switch state
    e, w = sw["error_m"], cr.campaign.test.window
    tau = sw.get("tau_effective_s", math.nan)
    tau = tau if math.isfinite(tau) else sw["tau_locked_s"]
    left = max(0.0, seed_case - sw["t_lock_s"])
    need = w * math.exp(left / tau)
    need_46 = w * math.exp(left / PREMOTION_TAU_MIN)
    parts.append(f"{lc}: locks {sw['t_lock_s'] * 1e3:.1f} ms after the reference stops (the seed's switch), "
                 f"table {_nm(abs(e))} {'past' if e > 0 else 'short of'} the target; locked, it creeps in like the "
                 f"{lv} (τ = {tau * 1e3:.0f} ms; slow pole (kp + k_f)/ki {sw['tau_locked_s'] * 1e3:.0f} ms, on the "
                 f"flexure {sw['tau_compliant_s'] * 1e3:.1f} ms): {_ms(mc['settling_time_s'])}")
    ok = abs(e) <= need
    parts.append(f"the seed's {seed_case * 1e3:.0f} ms needs the table within {_nm(need)} at the lock "
                 f"({_nm(need_46)} even at the fastest pre-motion creep the seed allows, 10 Hz, Fig. 4.6a)"
                 + (" — it is" if ok else f" — it is {abs(e) / need:.0f}× farther: not reachable with the "
                                           "seed's stated model (stiff = conventional stage, switch at the "
                                           "reference stop, Step II learned at rest)"))
    return "; ".join(parts), ok


def _rms_verdict(r: Ratio, cr, cond) -> tuple[str, bool]:
    """Mechanism of an in-position ratio: the noise part above each case's own noise-free floor."""
    out, parts = {}, []
    for who in (r.case, r.versus):
        m = cr.runs[(who, cond.key)].mechanism or {}
        tot = cr.stat(who, cond.key, r.metric).mean
        fl = m.get("rms_noise_free_m")
        if fl is None or not math.isfinite(tot):
            return "noise-free floor not measured", False
        out[who] = (tot, fl, math.sqrt(max(tot ** 2 - fl ** 2, 0.0)))
        parts.append(f"{cr.campaign.case(who).label}: {tot * 1e9:.2f} nm = noise-free floor {fl * 1e9:.2f} nm "
                     f"(quantisation, hunting, integrator tail) ⊕ drive noise {out[who][2] * 1e9:.2f} nm")
    if r.similar is not None:
        mc = cr.runs[(r.case, cond.key)].mechanism or {}
        ok = bool(mc.get("switch")) and abs(out[r.case][0] / out[r.versus][0] - 1.0) <= r.similar
        return "; ".join(parts) + (": locked after the move, the SAI holds position as the Baseline does "
                                   "(the seed's reason)" if ok else ""), ok
    nc, nv = out[r.case][2], out[r.versus][2]
    ratio = nc / nv if nv > 0 else math.inf
    ok = ratio > 1.0
    lc, lv = cr.campaign.case(r.case).label, cr.campaign.case(r.versus).label
    txt = ("; ".join(parts) + f"; drive-noise parts {lc}/{lv} = "
           + ("∞ (the stiff stage does not respond)" if not math.isfinite(ratio) else f"{ratio:.1f}")
           + (" (seed, above its 1.41 nm quantisation: "
              f"{_excess(r, cr, r.case) / _excess(r, cr, r.versus):.1f})" if _excess(r, cr, r.versus) else "")
           + (": the FI's excess is the drive noise through the softer stiffness (the seed's Sec. 4.4.1 reason)"
              if ok else ": not the seed's reason"))
    mc, mv = (cr.runs[(w, cond.key)].mechanism or {} for w in (r.case, r.versus))
    a, b = mc.get("rms_after_tail_m"), mv.get("rms_after_tail_m")
    if a and b:
        txt += (f"; from {TAIL_S * 1e3:.0f} ms after settling (without the integrator's tail inside the window, "
                f"{lv} {b * 1e9:.2f} nm) the ratio is {a / b:.2f} (representative trials)")
    return txt, ok


def _excess(r: Ratio, cr, who) -> float:
    """The seed's in-position error above the encoder's quantisation floor, in quadrature [m]."""
    v = cr.campaign.seed_value(who, r.metric, step=r.step)
    return math.sqrt(max(v ** 2 - QUANTISATION_RMS ** 2, 0.0)) if v else 0.0


def evaluate(runs) -> list[dict]:
    """The headline ratios over campaign runs.

    Parameters
    ----------
    runs : list of CampaignRun
        Campaigns as run; ratios of campaigns not among them are skipped.

    Returns
    -------
    list of dict
        One row per ratio of :data:`HEADLINE` (the content of ``headline.json``): the seed's and
        the simulated ratio (mean and median), the bar, whether it holds, and the mechanism verdict.
    """
    by_name = {cr.campaign.name: cr for cr in runs}
    out = []
    for r in HEADLINE:
        cr = by_name.get(r.campaign)
        if cr is None:
            continue
        cond = _cond(cr, r.step)
        camp = cr.campaign
        sc = camp.seed_value(r.case, r.metric, step=r.step)
        sv = camp.seed_value(r.versus, r.metric, step=r.step)
        sa, sb = cr.stat(r.case, cond.key, r.metric), cr.stat(r.versus, cond.key, r.metric)
        a, b = sa.mean, sb.mean
        sim = a / b if b else math.nan
        med = _median(sa) / _median(sb) if _median(sb) else math.nan
        seed = sc / sv
        if r.metric == "settling_time_s":
            why, mech_ok = _settling_verdict(r, cr, cond, sc)
        else:
            why, mech_ok = _rms_verdict(r, cr, cond)
        out.append({"campaign": r.campaign, "case": r.case, "versus": r.versus, "step": r.step, "metric": r.metric,
                    "label": f"{camp.case(r.case).label}/{camp.case(r.versus).label}",
                    "condition": cond.label, "seed": seed, "seed_case": sc, "seed_versus": sv,
                    "sim": sim, "sim_case": a, "sim_versus": b, "sim_median": med,
                    "bar": (1.0 - r.similar, 1.0 + r.similar) if r.similar is not None else bar(seed),
                    "holds": holds(sim, seed, r.similar), "holds_median": holds(med, seed, r.similar),
                    "mechanism_ok": mech_ok, "mechanism": why})
    return out


def _median(st) -> float:
    v = [x for x in st.values if x is not None]
    return float(np.median(v)) if v else math.nan


def report_lines(runs) -> list[str]:
    """Markdown: the headline table and, per ratio, its mechanism verdict.

    Parameters
    ----------
    runs : list of CampaignRun
        Campaigns as run.

    Returns
    -------
    list of str
        Lines of Markdown (empty when no ratio's campaign is among ``runs``).
    """
    rows = evaluate(runs)
    if not rows:
        return []
    n = sum(r["holds"] for r in rows)
    L = ["## Headline: the seed's ratios", "",
         f"**{n} of {len(rows)} hold** (at least half the seed's change: the simulated ratio beyond (1 + seed)/2; "
         "a 'similar' ratio within its tolerance of 1). Ratio of the means over all trials.", "",
         "| # | table | ratio | condition | seed | simulation | bar | holds | mechanism |",
         "|---|---|---|---|---|---|---|---|---|"]
    for i, r in enumerate(rows, 1):
        unit = METRICS[r["metric"]]
        b = r["bar"]
        bar_s = f"{b[0]:.2f}–{b[1]:.2f}" if isinstance(b, tuple) else (f"≤ {b:.3g}" if r["seed"] < 1 else f"≥ {b:.3g}")
        L.append(f"| {i} | {r['campaign']} | {r['label']} {unit.label} | {r['condition']} | "
                 f"{r['seed']:.2f} ({unit.compact(r['seed_case'])} / {unit.compact(r['seed_versus'])}) | "
                 f"**{r['sim']:.2f}** ({unit.compact(r['sim_case'])} / {unit.compact(r['sim_versus'])}) | {bar_s} | "
                 f"{'yes' if r['holds'] else '**no**'} | {'seed' if r['mechanism_ok'] else 'differs'} |")
    L += ["", "Mechanism verdicts (representative trials; `report.md` of each campaign has the plots):", ""]
    for i, r in enumerate(rows, 1):
        tail = ""
        if r["holds"] != r["holds_median"]:
            tail = (f" The ratio of the medians, {r['sim_median']:.2f}, "
                    + ("holds" if r["holds_median"] else "does not hold")
                    + ": a few trials decide the mean (see the campaign's distribution plot).")
        L.append(f"{i}. **{r['label']} {METRICS[r['metric']].label}, {r['condition']}** ({r['sim']:.2f} vs seed "
                 f"{r['seed']:.2f}): {r['mechanism']}.{tail}")
    return L + [""]
