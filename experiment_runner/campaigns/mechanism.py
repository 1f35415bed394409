"""Why a point-to-point trial settles as it does: overshoot, reversal, friction regime, twin.

The seed's explanation of its headline result (Sec. 4.3, Fig. 4.6-4.8): after the move the
stage without isolation overshoots the target (or otherwise stops), *reverses*, and starts
again from rest in the pre-motion regime, where the bearings' frictional stiffness k_f is
of the order of the PID's own stiffness k_p; the closed loop then has a bandwidth below
10 Hz and the last few hundred nanometres take tens of milliseconds. With a friction
isolator the table only feels k_fi << k_p and the same PID closes them quickly.

:func:`analyse` checks that story on one trial of a campaign case, from the simulated
*true* table position (the encoder's 4.88 nm counts would hide the turning points):

* ``end_error_m``: table position minus target when the reference stops (sign: + beyond
  the target in the direction of the move, - short of it);
* ``overshoot_m``: how far the table goes beyond the target before it settles;
* ``reversals``: every turning point of the table between the middle of the move and the
  settling instant (zig-zag with a hysteresis of ``hysteresis`` metres, so noise and
  quantisation hunting are not counted), each with its time after the reference stopped and
  its position relative to the target;
* ``travel_after_last_reversal_m``: how far the table moved from its last turning point to
  where it settled. Less than the pre-motion range of the bearings (the displacement at
  which their friction saturates) means the stage settled in the pre-motion regime;
* ``twin_settling_time_s``: the same trial on the *friction-free twin* (bearings rigidly
  attached, no friction, no isolator, no dither: the "equivalent frictionless stage" of
  Sec. 1.3). ``friction_limited`` is true when the trial takes at least 1.5 times as long
  and 5 ms more than its twin.

Examples
--------
>>> import numpy as np
>>> x = np.array([0, 5, 10, 8, 9, 12, 11.5, 3])
>>> turning_points(x, 1.0)
[2, 3, 5]
"""
from __future__ import annotations

import math
from typing import Optional

import numpy as np

from experiment_runner import outputs
from experiment_runner.campaigns.trials import simulate_trials
from experiment_runner.experiment import trial_metrics
from stage_sim.config import with_overrides

__all__ = ["turning_points", "frictionless_twin", "premotion_range", "analyse", "summary"]

FRICTION_LIMITED_RATIO = 1.5     # settling / twin settling at least this ...
FRICTION_LIMITED_MARGIN = 5e-3   # ... and at least this much longer [s]


def turning_points(x, hysteresis: float) -> list[int]:
    """Indices of the reversals of ``x``: extrema followed by a return of more than ``hysteresis``.

    Parameters
    ----------
    x : array_like
        Samples of a position [m].
    hysteresis : float
        Least excursion back from an extremum that counts as a reversal [m].

    Returns
    -------
    list of int
        Sample indices of the extrema at which ``x`` turned, in order.
    """
    x = np.asarray(x, float)
    out: list[int] = []
    if x.size < 2:
        return out
    k_ext, direction = 0, 0            # direction of the current run: +1 up, -1 down, 0 unknown
    for k in range(1, x.size):
        if direction >= 0:
            if x[k] > x[k_ext]:
                k_ext = k
                direction = 1 if direction == 0 and x[k] - x[0] > hysteresis else direction
            elif x[k_ext] - x[k] > hysteresis:
                if direction == 1:
                    out.append(k_ext)
                direction, k_ext = -1, k
                continue
        if direction <= 0:
            if x[k] < x[k_ext]:
                k_ext = k
                direction = -1 if direction == 0 and x[0] - x[k] > hysteresis else direction
            elif x[k] - x[k_ext] > hysteresis:
                if direction == -1:
                    out.append(k_ext)
                direction, k_ext = 1, k
    return out


def frictionless_twin(preset):
    """The preset's equivalent frictionless stage: bearings bolted rigidly, no friction (bearings
    and table), no isolator lock, SAI manager or dither; controller, masses, modes and drive kept."""
    ov = {"stage.table_friction": None, "stage.sai": None, "stage.bearing_sensor": None,
          "sai_manager": None, "dither": None}
    for i in range(len(preset.stage.bearings)):
        ov[f"stage.bearings.{i}.joint"] = None
        ov[f"stage.bearings.{i}.friction"] = {"model": "coulomb", "f_c": 0.0}
        ov[f"stage.bearings.{i}.dither_channel"] = None
    return with_overrides(preset, ov)


def premotion_range(preset) -> float:
    """Displacement after a reversal at which the bearings' friction is (nearly) saturated [m]:
    the largest block's ``2 alpha_i F_C / k_i`` for GMS and its rate-and-state variant (Masing: twice
    the virgin range), ``2 x 3 F_C / k_sigma`` for Dahl (95% of the swing); nan for other models."""
    out = []
    for b in preset.stage.bearings:
        f = b.friction
        if f is None:
            continue
        if f.model in ("gms", "gms_rate_state"):
            out.append(max(2 * a * f.f_c / k for a, k in zip(f.alpha, f.k)))
        elif f.model == "dahl":
            out.append(2 * 3 * f.f_c / f.k_sigma)
    return max(out) if out else math.nan


def _settling(camp, trial, res, row, rate) -> Optional[float]:
    m = trial_metrics(trial, res.y[row], res.x_ref[row], rate)
    v = m.get("settling_time_s")
    return None if v is None or not math.isfinite(v) else float(v)


def analyse(camp, case, cond, preset, trial: int, correction=None, hysteresis: float = 5e-9) -> dict:
    """Settling mechanism of trial ``trial`` of ``case`` at ``cond`` (see the module docstring).

    Returns a dict of plain numbers (SI) and, under ``"trace"``, the arrays of the plot:
    ``t`` [s] after the reference stopped, ``e`` and ``e_twin`` (true table position minus
    target, signed along the move) [m].
    """
    rate = preset.controller.rate
    ref, (tr,), res = simulate_trials(camp, case, cond, preset, [trial], correction)
    twin = frictionless_twin(preset)
    _, (trt,), rest = simulate_trials(camp, case, cond, twin, [trial], None)
    move, settle = ref.select("move")[0], ref.select("settle")[0]
    k0 = settle.start
    target = float(tr.x_ref[settle.stop - 1])
    sign = 1.0 if cond.step > 0 else -1.0
    e = (res.x_table[0] - target) * sign
    e_twin = (rest.x_table[0] - target) * sign
    ts = _settling(camp, tr, res, 0, rate)
    ts_twin = _settling(camp, trt, rest, 0, rate)
    k_end = res.x_table.shape[1] - 1 if ts is None else min(res.x_table.shape[1] - 1, k0 + int(round(ts * rate)))
    k_mid = (move.start + move.stop) // 2
    tps = [k_mid + k for k in turning_points(res.x_table[0, k_mid:k_end + 1], hysteresis)]
    revs = [{"t_s": (k - k0) / rate, "error_m": float(e[k]),
             "side": "past the target" if e[k] > 0 else "short of the target"} for k in tps]
    after = float(abs(res.x_table[0, k_end] - res.x_table[0, tps[-1]])) if tps else None
    pm = premotion_range(preset)
    limited = (ts is not None and ts_twin is not None and ts >= FRICTION_LIMITED_RATIO * ts_twin
               and ts - ts_twin >= FRICTION_LIMITED_MARGIN)
    k_plot = min(res.x_table.shape[1], k0 + int(round(max(0.15, 2.0 * (ts or 0.1)) * rate)))
    k_start = max(0, k0 - int(round(0.3 * (move.stop - move.start))))
    return {
        "case": case.name, "condition": cond.key, "trial": int(trial),
        "settling_time_s": ts, "twin_settling_time_s": ts_twin, "friction_limited": bool(limited),
        "end_error_m": float(e[k0]), "overshoot_m": float(max(0.0, np.max(e[k_mid:k_end + 1]))),
        "excursion_m": float(e[k0 + int(np.argmax(np.abs(e[k0:k_end + 1])))]) if k_end >= k0 else float(e[k0]),
        "reversals": revs, "travel_after_last_reversal_m": after, "premotion_range_m": pm,
        "settled_in_premotion": (after is not None and math.isfinite(pm) and after < pm),
        "trace": {"t": (np.arange(k_start, k_plot) - k0) / rate, "e": e[k_start:k_plot],
                  "e_twin": e_twin[k_start:k_plot], "reversal_t": [r["t_s"] for r in revs],
                  "reversal_e": [r["error_m"] for r in revs], "window": camp.test.window},
    }


def _nm(x):
    a = abs(x)
    if a >= 1e-6:
        return f"{x * 1e6:.2f} µm"
    return f"{x * 1e9:.0f} nm"


def summary(m: dict) -> str:
    """One sentence: how the trial ended its move, reversed and settled, and whether friction set the time."""
    e0 = m["end_error_m"]
    s = [f"ends the move {_nm(abs(e0))} {'past' if e0 > 0 else 'short of'} the target"]
    ex = m.get("excursion_m", e0)
    if abs(ex) > 2 * abs(e0) and abs(ex) > m["trace"]["window"]:
        s.append(f"then gets {_nm(abs(ex))} {'past' if ex > 0 else 'short of'} it")
    if m["overshoot_m"] > m["trace"]["window"]:
        s.append(f"overshoots by {_nm(m['overshoot_m'])}")
    revs = [r for r in m["reversals"] if r["t_s"] > -0.005]
    if revs:
        r = revs[0]
        s.append(f"reverses {len(revs)}× after the reference stops (first at {r['t_s'] * 1e3:+.1f} ms, "
                 f"{_nm(abs(r['error_m']))} {r['side']})")
    else:
        s.append("no reversal")
    if m["travel_after_last_reversal_m"] is not None and m["reversals"]:
        s.append(f"moves {_nm(m['travel_after_last_reversal_m'])} after its last reversal "
                 + ("(inside the bearings' pre-motion range "
                    f"{_nm(m['premotion_range_m'])}: pre-motion regime)" if m["settled_in_premotion"] else
                    "(beyond the pre-motion range: gross sliding)"))
    ts, tw = m["settling_time_s"], m["twin_settling_time_s"]
    fmt = (lambda v: "not settled" if v is None else f"{v * 1e3:.1f} ms")
    s.append(f"settles in {fmt(ts)}, friction-free twin {fmt(tw)}: "
             + ("**friction-limited**" if m["friction_limited"] else "not friction-limited"))
    return "; ".join(s) + "."


# --------------------------------------------------------------------------- report
def report_lines(cr, images: str = "") -> list[str]:
    """Markdown: the settling mechanism of every case and condition's representative trial; with
    ``images`` (the plots folder relative to the report, e.g. ``"table_4_2/plots"``) the
    mechanism plots are embedded too."""
    rows = [(cr.campaign.case(k[0]).label, rr.cond.label, rr.mechanism) for k, rr in cr.runs.items()
            if rr.mechanism]
    if not rows:
        return []
    L = ["## Settling mechanism", "",
         "Representative trial of each case (true table position, not the encoder counts): where it ends the "
         "move, its reversals after the reference stops (turning points by more than 5 nm), whether it settles "
         "in the bearings' pre-motion regime, and its friction-free twin (bearings bolted rigidly, no friction, "
         "no isolator: the seed's \"equivalent frictionless stage\", Sec. 1.3). Friction-limited = at least "
         f"{FRICTION_LIMITED_RATIO:g}× and {FRICTION_LIMITED_MARGIN * 1e3:g} ms slower than the twin. "
         "Plots: `plots/mechanism_*.png` (|error| on a log scale through the settling portion, reversals ▼).", "",
         "| case | condition | settling | twin | friction-limited | reversals | overshoot | mechanism |",
         "|---|---|---|---|---|---|---|---|"]
    fmt = (lambda v: "–" if v is None else f"{v * 1e3:.1f} ms")
    for label, cond, m in rows:
        n_rev = len([r for r in m["reversals"] if r["t_s"] > -0.005])
        L.append(f"| {label} | {cond} | {fmt(m['settling_time_s'])} | {fmt(m['twin_settling_time_s'])} | "
                 f"{'yes' if m['friction_limited'] else 'no'} | {n_rev} | {_nm(m['overshoot_m'])} | {summary(m)} |")
    L.append("")
    if images:
        L += [f"![mechanism {c.label}]({images}/mechanism_{c.key}.png)" for c in cr.conditions] + [""]
    return L


def plot(cr, plt, out) -> list:
    """``out/mechanism_<condition>.png`` for every condition: |error| (log) through the settling portion
    of each case's representative trial, its reversal instants (▼) and the friction-free twin (dashed)."""
    files = []
    cols = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for cond in cr.conditions:
        ms = [(cr.campaign.case(c.name).label, cr.runs[(c.name, cond.key)].mechanism) for c in cr.campaign.cases]
        ms = [(lab, m) for lab, m in ms if m]
        if not ms:
            continue
        fig, ax = plt.subplots(figsize=(9, 5))
        t_max = 0.05
        for (lab, m), c in zip(ms, cols):
            tr = m["trace"]
            ts = m["settling_time_s"]
            ax.semilogy(tr["t"] * 1e3, np.maximum(np.abs(tr["e"]), 1e-10) * 1e9, color=c, lw=1,
                        label=f"{lab}: {'not settled' if ts is None else f'{ts * 1e3:.1f} ms'}"
                              + (" (friction-limited)" if m["friction_limited"] else ""))
            ax.semilogy(tr["t"] * 1e3, np.maximum(np.abs(tr["e_twin"]), 1e-10) * 1e9, color=c, lw=0.8, ls="--",
                        alpha=0.7, label=f"{lab}, friction-free twin: "
                        + ("–" if m["twin_settling_time_s"] is None else f"{m['twin_settling_time_s'] * 1e3:.1f} ms"))
            rt, re_ = np.array(tr["reversal_t"]), np.array(tr["reversal_e"])
            if rt.size:
                ax.plot(rt * 1e3, np.maximum(np.abs(re_), 1e-10) * 1e9 * 1.6, "v", color=c, ms=6)
            if ts is not None:
                ax.axvline(ts * 1e3, color=c, lw=0.6, ls=":")
            t_max = max(t_max, 1.5 * (ts or 0.1))
        w = ms[0][1]["trace"]["window"]
        ax.axhline(w * 1e9, color="g", lw=0.8, label=f"±{w * 1e9:g} nm window")
        ax.set_xlim(-0.3 * t_max * 1e3, t_max * 1e3)
        ax.set_ylim(0.5, None)
        ax.set_xlabel("time after the reference reaches the target [ms]")
        ax.set_ylabel("|table position − target| [nm] (true position)")
        ax.set_title(f"{cr.campaign.title}\n{cond.label}: settling mechanism (▼ = reversal of the table)", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper right")
        fig.tight_layout()
        path = outputs.savefig(fig, out / f"mechanism_{cond.key}.png", dpi=110)
        plt.close(fig)
        files.append(path)
    return files
