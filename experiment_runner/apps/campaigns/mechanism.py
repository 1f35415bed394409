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
* ``rms_noise_free_m``: the trial's RMS in-position error without the drive noise: the floor
  that the encoder's quantisation, the integrator's hunting around the target count and its
  tail inside the window leave (the seed attributes the in-position error to the drive noise,
  Sec. 4.4.1 / Fig. 5.1-5.2). ``rms_after_tail_m`` / ``rms_after_tail_noise_free_m``: the same
  from :data:`TAIL_S` after the settling instant, without the integrator's tail inside the window.
* ``switch`` (SAI trials only, :func:`switch_state`): the state of the stage when the
  isolator locks after the move (Sec. 5.3: it is switched to stiff "once the reference
  command reaches the target position"): the lock instant, the table's error, the flexure's
  deflection, the table's and the bearing's velocities, and the slow closed-loop time
  constants with the bearing locked and on the flexure (:func:`creep_time_constant`).

The time constant of the creep: in the pre-motion regime the bearing is a spring ``k_f`` to
ground, and the PID's slow pole is ``ki / (kp + k)`` for whatever stiffness ``k`` the table
feels (``m s^3 + kd s^2 + (kp + k) s + ki = 0`` with the fast poles far above it): ``k_f``
(locked, the seed's k_c -> k_f of Sec. 5.1) against ``k_fi`` (compliant).

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

from experiment_runner.apps.campaigns.trials import simulate_trials
from experiment_runner.core import outputs
from experiment_runner.core.experiment import trial_metrics
from stage_sim.config import with_overrides

__all__ = ["turning_points", "frictionless_twin", "premotion_range", "initial_stiffness", "creep_time_constant",
           "lock_delay", "switch_state", "analyse", "summary"]

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
    and table), no isolator lock, SAI manager or dither; controller, masses, modes and drive kept.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage and its controller.

    Returns
    -------
    stage_sim.config.Preset
    """
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
    the virgin range), ``2 x 3 F_C / k_sigma`` for Dahl (95% of the swing); nan for other models.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage and its controller.

    Returns
    -------
    float
    """
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


def initial_stiffness(preset) -> float:
    """The bearings' pre-motion stiffness right after a reversal [N/m] (in parallel): ``sum k_i`` of
    a GMS model (and its rate-and-state variant), ``k_sigma`` of Dahl; nan for other models.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage and its controller.

    Returns
    -------
    float
    """
    tot, seen = 0.0, False
    for b in preset.stage.bearings:
        f = b.friction
        if f is None:
            continue
        if f.model in ("gms", "gms_rate_state"):
            tot, seen = tot + float(sum(f.k)), True
        elif f.model == "dahl":
            tot, seen = tot + float(f.k_sigma), True
    return tot if seen else math.nan


def creep_time_constant(preset, stiffness: float) -> float:
    """Slow closed-loop time constant ``(kp + k) / ki`` [s] of the preset's PID on a table held by a
    spring ``stiffness`` [N/m] to ground (the creep of the last micrometres in the pre-motion regime).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage and its controller.
    stiffness : float
        The spring [N/m] (e.g. :func:`initial_stiffness`).

    Returns
    -------
    float

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> p = load_preset("sai_stage")
    >>> round(creep_time_constant(p, 2.19e6) * 1e3, 1), round(creep_time_constant(p, 5e4) * 1e3, 1)
    (50.1, 7.9)
    """
    pid = preset.controller.pid
    return (pid.kp + stiffness) / pid.ki if pid.ki > 0 else math.inf


def lock_delay(preset) -> float:
    """Time from the stiff command to the lock [s]: the solenoid voltage's RC filter falling to half
    (``ln 2 / (2 pi f_RC)``) plus the armature's travel (``switch_delay``), as the plant models it.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        A stage with a semi-active isolator.

    Returns
    -------
    float
    """
    sai = preset.stage.sai
    if sai is None:
        return 0.0
    rc = 0.0 if sai.rc_cutoff is None else math.log(2.0) / (2 * math.pi * sai.rc_cutoff)
    return rc + sai.switch_delay


def switch_state(preset, res, row: int, k0: int, target: float, sign: float, window: float) -> Optional[dict]:
    """The stage's state when the SAI locks after the move (None without a compliant -> stiff switch).

    Parameters
    ----------
    preset : stage_sim.config.Preset
    res : experiment_runner.core.batch.BatchResult
    row : int
        Trial row of ``res``.
    k0 : int
        Sample at which the reference reaches the target.
    target : float
        Target position [m].
    sign : float
        Direction of the move (+1 / -1): errors and deflections are signed along it.
    window : float
        Settling window half-width [m].

    Returns
    -------
    dict or None
        ``t_command_s`` and ``t_lock_s`` (after the reference stopped), ``error_m`` (table minus
        target), ``deflection_m`` (table minus bearing), ``v_table_m_s``, ``v_bearing_m_s``,
        ``tau_locked_s`` / ``tau_compliant_s`` (:func:`creep_time_constant` with the bearings'
        initial stiffness in series with the lock, and with the flexure), ``k_locked`` [N/m], and
        ``creep_estimate_s``: ``tau_locked ln(|e| k / ((kp + k) w))``, the time the locked stage's
        slow pole needs to bring the part of the error the proportional action leaves down to the
        window ``w`` (0 when already inside).
    """
    mode = res.mode[row]
    edges = np.flatnonzero((mode[:-1] == 1.0) & (mode[1:] == 0.0)) + 1
    edges = edges[edges >= k0 - 1]
    if edges.size == 0 or preset.stage.sai is None:
        return None
    rate = preset.controller.rate
    kc = int(edges[0])
    T = res.x_table.shape[1]
    kl = min(T - 2, kc + int(math.ceil(lock_delay(preset) * rate)))
    xt, xb = res.x_table[row], res.x_bearing[row]
    e = float((xt[kl] - target) * sign)
    kf = initial_stiffness(preset)
    k_lock = preset.stage.sai.lock_stiffness
    k = kf * k_lock / (kf + k_lock) if math.isfinite(kf) else math.nan
    joints = [b.joint.stiffness for b in preset.stage.bearings if b.joint is not None]
    tau_l = creep_time_constant(preset, k)
    kp = preset.controller.pid.kp
    slow = abs(e) * k / (kp + k) if math.isfinite(k) else math.nan
    return {"t_command_s": (kc - k0) / rate, "t_lock_s": (kl - k0) / rate, "error_m": e,
            "deflection_m": float((xt[kl] - xb[kl]) * sign),
            "v_table_m_s": float((xt[kl + 1] - xt[kl - 1]) * rate / 2 * sign),
            "v_bearing_m_s": float((xb[kl + 1] - xb[kl - 1]) * rate / 2 * sign),
            "k_locked": k, "tau_locked_s": tau_l,
            "tau_compliant_s": creep_time_constant(preset, sum(joints)) if joints else math.nan,
            "creep_estimate_s": (tau_l * math.log(slow / window) if slow > window else 0.0)
            if math.isfinite(slow) else math.nan}


def creep_fit(e, k_from: int, k_to: int, rate: float, window: float) -> dict:
    """Decay of ``|e|`` from sample ``k_from`` (plus 2 ms) to ``k_to`` (the settling instant): the time
    constant of a log-linear fit over the samples outside the window, and its amplitude at ``k_from``.

    Parameters
    ----------
    e : numpy.ndarray
        Position error [m] per sample.
    k_from, k_to : int
        First and last sample of the fit.
    rate : float
        Sample rate [Hz].
    window : float
        Half-width of the settling window [m].

    Returns
    -------
    dict
        ``tau_effective_s`` and ``creep_amplitude_m`` (nan without 5 ms of samples outside the window).

    Examples
    --------
    >>> t = np.arange(0, 0.1, 1e-4)
    >>> d = creep_fit(2e-6 * np.exp(-t / 0.02), 0, 800, 1e4, 25e-9)
    >>> round(d["tau_effective_s"], 4), round(d["creep_amplitude_m"] * 1e6, 3)
    (0.02, 2.0)
    """
    k = np.arange(k_from + int(round(2e-3 * rate)), min(k_to, len(e)))
    a = np.abs(np.asarray(e, float)[k]) if k.size else np.zeros(0)
    k, a = k[a > window], a[a > window]
    if k.size < 5e-3 * rate:
        return {"tau_effective_s": math.nan, "creep_amplitude_m": math.nan}
    slope, icpt = np.polyfit((k - k_from) / rate, np.log(a), 1)
    if slope >= 0:
        return {"tau_effective_s": math.inf, "creep_amplitude_m": float(np.exp(icpt))}
    return {"tau_effective_s": float(-1.0 / slope), "creep_amplitude_m": float(np.exp(icpt))}


TAIL_S = 0.1
"""The integrator's tail inside the window: the in-position RMS is also given from this long after the
settling instant (two slow-pole time constants of the stiff stage, ~50 ms, Fig. 4.6a's < 10 Hz)."""


def _rms_after(y, target, k0, ts, rate) -> Optional[float]:
    """RMS of the measured error from ``TAIL_S`` after the settling instant to the end (None if unsettled)."""
    if ts is None:
        return None
    k = k0 + int(round((ts + TAIL_S) * rate))
    if k >= len(y) - 1:
        return None
    return float(np.sqrt(np.mean(np.square(np.asarray(y[k:], float) - target))))


def _settling(camp, trial, res, row, rate) -> Optional[float]:
    m = trial_metrics(trial, res.y[row], res.x_ref[row], rate)
    v = m.get("settling_time_s")
    return None if v is None or not math.isfinite(v) else float(v)


def analyse(camp, case, cond, preset, trial: int, correction=None, hysteresis: float = 5e-9) -> dict:
    """Settling mechanism of trial ``trial`` of ``case`` at ``cond`` (see the module docstring).

    Returns a dict of plain numbers (SI) and, under ``"trace"``, the arrays of the plot:
    ``t`` [s] after the reference stopped, ``e`` and ``e_twin`` (true table position minus
    target, signed along the move) [m].

    Parameters
    ----------
    camp : Campaign
        The campaign as run.
    case : Case
        The case.
    cond : Condition
        The condition.
    preset : stage_sim.config.Preset
        The stage and its controller.
    trial : int
        The trial (simulated again, with its :func:`frictionless_twin`).
    correction : numpy.ndarray, optional
        SAI Step II correction.
    hysteresis : float, optional
        Return [m] that makes an extremum a reversal (:func:`turning_points`).

    Returns
    -------
    dict
    """
    rate = preset.controller.rate
    ref, (tr,), res = simulate_trials(camp, case, cond, preset, [trial], correction)
    twin = frictionless_twin(preset)
    _, (trt,), rest = simulate_trials(camp, case, cond, twin, [trial], None)
    quiet = with_overrides(preset, {"stage.drive.noise_current_rms": 0.0})
    _, (trq,), resq = simulate_trials(camp, case, cond, quiet, [trial], correction)
    rms_quiet = trial_metrics(trq, resq.y[0], resq.x_ref[0], rate).get("rms_in_position_m")
    ts_q = _settling(camp, trq, resq, 0, rate)
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
    sw = switch_state(preset, res, 0, k0, target, sign, camp.test.window)
    if sw is not None:
        sw.update(creep_fit(e, k0 + int(round(sw["t_lock_s"] * rate)), k_end, rate, camp.test.window))
    return {
        "case": case.name, "condition": cond.key, "trial": int(trial),
        "settling_time_s": ts, "twin_settling_time_s": ts_twin, "friction_limited": bool(limited),
        "end_error_m": float(e[k0]), "overshoot_m": float(max(0.0, np.max(e[k_mid:k_end + 1]))),
        "excursion_m": float(e[k0 + int(np.argmax(np.abs(e[k0:k_end + 1])))]) if k_end >= k0 else float(e[k0]),
        "reversals": revs, "travel_after_last_reversal_m": after, "premotion_range_m": pm,
        "settled_in_premotion": (after is not None and math.isfinite(pm) and after < pm),
        "switch": sw,
        "rms_noise_free_m": None if rms_quiet is None or not math.isfinite(rms_quiet) else float(rms_quiet),
        "rms_after_tail_m": _rms_after(res.y[0], target, k0, ts, rate),
        "rms_after_tail_noise_free_m": _rms_after(resq.y[0], target, k0, ts_q, rate),
        "trace": {"t": (np.arange(k_start, k_plot) - k0) / rate, "e": e[k_start:k_plot],
                  "e_twin": e_twin[k_start:k_plot], "reversal_t": [r["t_s"] for r in revs],
                  "reversal_e": [r["error_m"] for r in revs], "window": camp.test.window,
                  "deflection": (res.x_table[0, k_start:k_plot] - res.x_bearing[0, k_start:k_plot]) * sign},
    }


def _nm(x):
    a = abs(x)
    if a >= 1e-6:
        return f"{x * 1e6:.2f} µm"
    return f"{x * 1e9:.0f} nm"


def switch_summary(sw: dict) -> str:
    """One clause: where the table is when the SAI locks, and what the locked stage then has to do.

    Parameters
    ----------
    sw : dict
        :func:`switch_state`'s result.

    Returns
    -------
    str
    """
    e = sw["error_m"]
    return (f"locks {sw['t_lock_s'] * 1e3:+.1f} ms after the reference stops with the table {_nm(abs(e))} "
            f"{'past' if e > 0 else 'short of'} the target (flexure deflection {_nm(sw['deflection_m'])}, table "
            f"{sw['v_table_m_s'] * 1e3:+.2f} mm/s, bearing {sw['v_bearing_m_s'] * 1e3:+.2f} mm/s); locked, it creeps "
            f"in with a time constant of {_tau(sw.get('tau_effective_s'))} (slow pole (kp + k_f)/ki with the "
            f"bearing's initial stiffness {sw['tau_locked_s'] * 1e3:.0f} ms, on the flexure "
            f"{sw['tau_compliant_s'] * 1e3:.1f} ms)")


def _tau(v) -> str:
    return "–" if v is None or not math.isfinite(v) else f"{v * 1e3:.0f} ms"


def summary(m: dict) -> str:
    """One sentence: how the trial ended its move, reversed and settled, and whether friction set the time.

    Parameters
    ----------
    m : dict
        :func:`analyse`'s result.

    Returns
    -------
    str
    """
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
    sw = m.get("switch")
    if sw:
        s.insert(0, switch_summary(sw))
    ts, tw = m["settling_time_s"], m["twin_settling_time_s"]
    fmt = (lambda v: "not settled" if v is None else f"{v * 1e3:.1f} ms")
    s.append(f"settles in {fmt(ts)}, friction-free twin {fmt(tw)}: "
             + ("**friction-limited**" if m["friction_limited"] else "not friction-limited"))
    return "; ".join(s) + "."


# --------------------------------------------------------------------------- report
def report_lines(cr, images: str = "") -> list[str]:
    """Markdown: the settling mechanism of every case and condition's representative trial; with
    ``images`` (the plots folder relative to the report, e.g. ``"table_4_2/plots"``) the
    mechanism plots are embedded too.

    Parameters
    ----------
    cr : CampaignRun
        A point-to-point campaign as run (its representative trials' ``mechanism``).
    images : str, optional
        Plots folder relative to the report ('' : no images).

    Returns
    -------
    list of str
    """
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
    return L + switch_lines(cr, images)


def switch_lines(cr, images: str = "") -> list[str]:
    """Markdown: each switched (SAI) case at its switch, beside the seed's account of it
    (``seed_mechanism`` of the case); with ``images`` the switch plots are embedded.

    Parameters
    ----------
    cr : CampaignRun
        A point-to-point campaign as run (its representative trials' ``mechanism``).
    images : str, optional
        Plots folder relative to the report.

    Returns
    -------
    list of str
    """
    L = []
    for case in cr.campaign.cases:
        ms = [(cond, cr.runs[(case.name, cond.key)].mechanism) for cond in cr.conditions
              if (case.name, cond.key) in cr.runs]
        ms = [(cond, m) for cond, m in ms if m and m.get("switch")]
        if not ms:
            continue
        L += [f"### {case.label} at the switch", ""]
        if case.seed_mechanism:
            L += [f"Seed: {case.seed_mechanism.strip()}", ""]
        for cond, m in ms:
            L.append(f"* {cond.label}: {switch_summary(m['switch'])}; settles in "
                     + ("–" if m["settling_time_s"] is None else f"{m['settling_time_s'] * 1e3:.1f} ms") + ".")
        L.append("")
        if images:
            L += [f"![{case.label} switch {cond.label}]({images}/switch_{case.name}_{cond.key}.png)"
                  for cond, _ in ms] + [""]
    return L


def plot(cr, plt, out) -> list:
    """``out/mechanism_<condition>.png`` for every condition: |error| (log) through the settling portion
    of each case's representative trial, its reversal instants (▼) and the friction-free twin (dashed).

    Parameters
    ----------
    cr : CampaignRun
        A point-to-point campaign as run (its representative trials' ``mechanism``).
    plt : module
        ``matplotlib.pyplot``.
    out : pathlib.Path
        Plots folder.

    Returns
    -------
    list of pathlib.Path
    """
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
    return files + plot_switch(cr, plt, out)


def plot_switch(cr, plt, out) -> list:
    """``out/switch_<case>_<condition>.png`` for every switched (SAI) case: (a) table position minus
    target through the end of the move and the settling portion, with the other cases' representative
    trials, the stiff command, the lock and the reversals (▼); (b) the flexure's deflection; (c) |error|
    on a log scale with the window and the locked stage's slow-pole creep from the lock.

    Parameters
    ----------
    cr : CampaignRun
        A point-to-point campaign as run (its representative trials' ``mechanism``).
    plt : module
        ``matplotlib.pyplot``.
    out : pathlib.Path
        Plots folder.

    Returns
    -------
    list of pathlib.Path
    """
    files = []
    for case in cr.campaign.cases:
        for cond in cr.conditions:
            rr = cr.runs.get((case.name, cond.key))
            m = rr.mechanism if rr else None
            if not m or not m.get("switch"):
                continue
            sw, tr = m["switch"], m["trace"]
            others = [(cr.campaign.case(c.name).label, cr.runs[(c.name, cond.key)].mechanism)
                      for c in cr.campaign.cases if c.name != case.name and (c.name, cond.key) in cr.runs]
            others = [(lab, o) for lab, o in others if o]
            fig, ax = plt.subplots(3, 1, figsize=(9, 9), sharex=True)
            t_max = max(0.06, 1.3 * max([m["settling_time_s"] or 0.1] + [o["settling_time_s"] or 0.0
                                                                          for _, o in others]))
            scale = 1e6 if abs(cond.step) >= 1e-4 else 1e9
            unit = "µm" if scale == 1e6 else "nm"
            for (lab, o), ls in zip(others, ("--", ":", "-.")):
                ax[0].plot(o["trace"]["t"] * 1e3, o["trace"]["e"] * scale, ls, color="0.45", lw=1, label=lab)
                ax[1].plot(o["trace"]["t"] * 1e3, o["trace"]["deflection"] * 1e6, ls, color="0.45", lw=1, label=lab)
                ax[2].semilogy(o["trace"]["t"] * 1e3, np.maximum(np.abs(o["trace"]["e"]), 1e-10) * 1e9, ls,
                               color="0.45", lw=1, label=f"{lab}: " + ("–" if o["settling_time_s"] is None else
                                                                      f"{o['settling_time_s'] * 1e3:.1f} ms"))
            ax[0].plot(tr["t"] * 1e3, tr["e"] * scale, color="C3", lw=1.2, label=case.label)
            ax[1].plot(tr["t"] * 1e3, tr["deflection"] * 1e6, color="C3", lw=1.2, label=case.label)
            ax[2].semilogy(tr["t"] * 1e3, np.maximum(np.abs(tr["e"]), 1e-10) * 1e9, color="C3", lw=1.2,
                           label=f"{case.label}: " + ("–" if m["settling_time_s"] is None else
                                                      f"{m['settling_time_s'] * 1e3:.1f} ms"))
            rt, re_ = np.array(tr["reversal_t"]), np.array(tr["reversal_e"])
            if rt.size:
                ax[0].plot(rt * 1e3, re_ * scale, "v", color="C3", ms=6, label="reversal")
            te, amp = sw.get("tau_effective_s", math.nan), sw.get("creep_amplitude_m", math.nan)
            if math.isfinite(te) and math.isfinite(amp):
                tc = np.linspace(sw["t_lock_s"], t_max, 200)
                ax[2].semilogy(tc * 1e3, amp * np.exp(-(tc - sw["t_lock_s"]) / te) * 1e9, color="C0", lw=0.9,
                               ls="--", label=f"locked creep fit, τ = {te * 1e3:.0f} ms (slow pole with the initial "
                                              f"k_f: {sw['tau_locked_s'] * 1e3:.0f} ms)")
            near = np.abs(tr["e"][tr["t"] >= -0.05 * t_max])
            lim = 1.3 * float(np.max(near)) * scale if near.size else None
            if lim:
                ax[0].set_ylim(-lim, lim)
            ax[2].axhline(tr["window"] * 1e9, color="g", lw=0.8, label=f"±{tr['window'] * 1e9:g} nm window")
            for a in ax:
                a.axvline(sw["t_command_s"] * 1e3, color="k", lw=0.7, ls=":")
                a.axvline(sw["t_lock_s"] * 1e3, color="C0", lw=0.8)
                a.grid(alpha=0.3, which="both")
            ax[0].axhline(0.0, color="k", lw=0.5)
            ax[0].set_ylabel(f"table − target [{unit}]")
            ax[1].set_ylabel("flexure deflection\ntable − bearing [µm]")
            ax[2].set_ylabel("|table − target| [nm]")
            ax[2].set_ylim(0.5, None)
            ax[2].set_xlim(-0.25 * t_max * 1e3, t_max * 1e3)
            ax[2].set_xlabel("time after the reference reaches the target [ms] (dotted: stiff command, blue: lock)")
            e = sw["error_m"]
            ax[0].set_title(f"{cr.campaign.title}\n{case.label}, {cond.label}: locks {sw['t_lock_s'] * 1e3:.1f} ms "
                            f"after the reference stops, table {_nm(abs(e))} {'past' if e > 0 else 'short of'} "
                            "the target", fontsize=9)
            for a in ax:
                a.legend(fontsize=7, loc="upper right")
            fig.tight_layout()
            path = out / f"switch_{case.name}_{cond.key}.png"
            outputs.savefig(fig, path, dpi=110)
            plt.close(fig)
            files.append(path)
    return files
