"""Show: ``report.json``, ``report.md``, plots and the improved model.

Files written to the output folder ``DIR``
-------------------------------------------
``report.json``          the report below (SI units; ``null`` where not applicable)
``report.md``            the same for people: verdict, effects with parameters, where the
                         residual lives, held-out proof, candidates per step
``improved_preset.yaml`` the improved model as a preset the simulator runs as is (every effect
                         of the library is a preset field; ``nanostage synth`` accepts it as a truth)
``residual_time.png``    force residual (band-limited) of nominal and improved model vs time,
                         regimes shaded, floor band
``residual_spectrum.png`` residual spectrum of nominal and improved model against the floor
``residual_state.png``   residual binned against position, velocity, acceleration, command,
                         displacement since reversal
``heldout_replay.png``   a held-out trial: recorded command vs closed-loop replay of nominal and
                         improved model

``report.json`` fields
----------------------
``verdict``             "model adequate" | "effects found" | "effects found, residual remains" |
                        "unexplained residual"
``found``               effects in the order they were named; each: ``effect`` (library key),
                        ``title``, ``kind``, ``step``, ``params`` [{name, unit, value, sigma (1 s.d.,
                        from the Jacobian), nominal, resolution (integer effects: ± half a grid
                        step, e.g. 0.5 sample of a whole-sample delay)}], ``derived`` (physical summaries, e.g. x_50),
                        ``expressible`` (in a preset), ``confounded_with`` (keys that explain the
                        held-out data as well), ``params_joint`` (after the joint fit), ``held_out``
                        (stochastic effects: their own held-out metric), ``refined_by_replay``
                        (values from the replay's output error), ``replaces`` (the member of its
                        exclusive group adopted earlier and replaced by it: effect, step, params),
                        ``withdraws`` (earlier adopted effects this one made redundant, withdrawn by
                        the backward test: effect, step, params, replay, why)
``recording``           source, rate_hz, trials, samples, duration_s, split, fit_trials,
                        held_out_trials, notes
``nominal``             name and source of the nominal model
``observer``            bandwidth_hz (force observer), smoothing_hz, band_hz (band of the reported
                        force RMS), evaluations and evaluation_s (observer runs)
``noise``               floor_check_J (whitened mean square of a second simulated recording, ~1),
                        n_eff_held (effective independent held-out samples), adequacy_tolerance
``predict``             closed_loop_replay {rms_command_error_N, rms_position_error_m, rms_command_N},
                        force_residual {rms_N, floor_rms_N, J_fit, J_held}, open_loop_windows
                        {window_s, windows, rms_drift_m, rms_force_N}
``locate``              residual_rms_N, floor_rms_N, regimes [{regime, samples, time_share, rms_N,
                        floor_rms_N, energy_share, excess_share}], segments (top time blocks by
                        excess energy), bands [{f_lo_hz, f_hi_hz, rms_N, floor_rms_N, ratio,
                        excess_share}], peaks, lines_hz, state {variable: {explained_share}},
                        ripple_periods_m
``replay``              the headline: held-out closed-loop replay error RMS {command_rms_N,
                        position_rms_m: {nominal, improved, floor_nominal, floor}}, floor_ratio,
                        consistency_z {nominal, improved, critical}, stable, held_out_trials,
                        predictor (how the held-out samples were predicted: closed-loop replay,
                        open-loop windows, or whole trials of a tiny-motion record), how
``least_squares_check`` open-loop records: the rigid body by ordinary least squares on the same
                        data (:func:`.openloop.least_squares_check`: samples, inertia, coulomb,
                        viscous {value, sigma, model, agree}, tolerance, agree); a disagreement is a finding
``selection``           steps [{step, replay_D_before, J_held_before, floor_rms, accepted,
                        confounded_with, candidates [{effect, replay {D_before, D_after,
                        improvement, threshold, block_se, stable, beyond_floor, why}, improvement,
                        threshold, significant (adoptable), why, J_fit, J_held, J_improvement,
                        params, derived, on_bound, evals, seconds}]}], J_held_start, J_held_final,
                        adequate_final, second_start (when the greedy path left a residual beyond its
                        floor: the path from step 1's runner-up {first, effects, greedy_effects,
                        replay_D, replay_D_greedy, chosen, why}; or, beyond the floor in
                        distribution only, {first, greedy_effects, chosen false, skipped})
``joint_fit``           effects, J_fit, J_held, params, correlation, confounded_parameters, used
``stochastic``          quantization {nominal_m, estimate_m, found, ...}, noise_level {nominal_A,
                        sigma, ratio, found, ...}
``sparse_regression``   terms {name: coefficient} and explained share, when a residual remains
``validation``          on held-out samples: force_residual_rms_N {nominal, improved, floor, fall},
                        J_held {nominal, improved, fall}, replay_command_rms_N and
                        replay_position_rms_m {nominal, improved, run_to_run, fall},
                        open_loop_drift_rms_m {nominal, improved, window_s}
``remaining``           only when the improved model is not adequate: what it leaves, located but not
                        explained (:func:`.signatures.remaining`): rms_N, floor_rms_N, ratio, lines
                        [{f_hz, amplitude_N, share, prominence_db, regime}], position_periodic
                        {period_m, amplitude_N, share}, stroke_level, regimes, signatures [{kind,
                        text, share}] (plot ``remaining.png``)
``improved_model``      name, preset_yaml (file name)
``timing_s``            wall time per stage
``budget``              the wall-clock budget (:mod:`.budget`): max_seconds, spent_s, reached,
                        stopped ("time budget" or "interrupted (SIGINT)" ...), after_stage,
                        not_examined [what the search did not get to], statement (report.md's and
                        stdout's leading line when reached)

``J`` is the whitened mean square of the force residual: 1 means "as a perfect model would
leave it" (noise and quantization only).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from experiment_runner.core import outputs

from .locate import REGIMES, lowpass, spectrum
from .units import axis_units

__all__ = ["write_report", "to_markdown", "jsonable"]


def jsonable(o):
    """``o`` as strict JSON types: numpy values as Python ones, non-finite floats as None, paths as
    strings, private (``_``-prefixed) dict entries dropped.

    Parameters
    ----------
    o : object
        Nested dicts, lists, tuples, numpy arrays and scalars, paths.

    Returns
    -------
    object

    Examples
    --------
    >>> jsonable({"a": np.float64("nan"), "_x": 1, "n": np.arange(2)})
    {'a': None, 'n': [0, 1]}
    """
    if isinstance(o, dict):
        return {str(k): jsonable(v) for k, v in o.items() if not str(k).startswith("_")}
    if isinstance(o, (list, tuple)):
        return [jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist())
    if isinstance(o, (np.floating,)):
        o = float(o)
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.bool_,)):
        return bool(o)
    if isinstance(o, float) and not np.isfinite(o):
        return None
    if isinstance(o, Path):
        return str(o)
    return o


def _fmt(v, unit=""):
    if v is None:
        return "–"
    if isinstance(v, (int, np.integer)):
        return f"{v}{(' ' + unit) if unit else ''}"
    return f"{v:.4g}{(' ' + unit) if unit else ''}"


def _md_headline(rep: dict) -> list[str]:
    """Title, the held-out replay table, the verdict and the recording."""
    L = []
    rc = rep["recording"]
    L.append(f"# Diagnosis: {Path(rc['source']).name} against `{rep['nominal']['name']}`\n")
    r = rep["replay"]
    U = rep.get("units") or axis_units("linear")
    fu, pu = U["force"], U["position"]
    if rep.get("recording", {}).get("open_loop"):
        how = r.get("predictor", "windows re-initialised from the measurement")
        L.append("**Held-out open-loop prediction** (an open-loop record: the recorded command and known force through "
                 f"the model, {how}, compared with the measurement; "
                 f"{len(r['held_out_trials'])} trial(s), {r['held_out_samples']} samples):\n")
    else:
        L.append("**Held-out closed-loop replay** (what the user gets: the recorded reference through the model and its "
                 f"controller, compared with the recorded command and measurement; {r['reference']} reference; "
                 f"{len(r['held_out_trials'])} trial(s), {r['held_out_samples']} samples):\n")
    L.append("| replay error RMS | nominal | improved | run-to-run floor (nominal) | run-to-run floor (improved) |")
    L.append("|---|---|---|---|---|")
    for k, name in (("command_rms_N", f"command [{fu}]"), ("position_rms_m", f"position [{pu}]")):
        x = r[k]
        L.append(f"| {name} | {_fmt(x['nominal'])} | {_fmt(x['improved'])} | {_fmt(x['floor_nominal'])} | "
                 f"{_fmt(x['floor'])} |")
    L.append(f"| error / floor | {_fmt(r['floor_ratio']['nominal'])}x | {_fmt(r['floor_ratio']['improved'])}x | 1 | 1 |")
    L.append(f"| stable | {r['stable']['nominal']} | {r['stable']['improved']} |  |  |\n")
    L.append(f"**Verdict: {rep['verdict']}.** An effect is adopted only if the improved model's replay is stable and "
             f"better beyond the run-to-run floor of the model before it (re-estimated after every adoption); the force "
             f"residual only locates and proposes.\n")
    L.append(f"Recording: {rc['trials']} trial(s), {rc['duration_s']:.3g} s at {rc['rate_hz']:.6g} Hz; "
             f"{rc['split']}. Force observer bandwidth {rep['observer']['bandwidth_hz']:.4g} Hz; "
             f"force residuals below are band-limited to {rep['observer']['band_hz']:.4g} Hz. "
             f"J = whitened mean square of the force residual (1 = noise floor; adequacy tolerance "
             f"{rep['noise']['adequacy_tolerance']:.3g}).\n")
    for n in rc.get("notes") or []:
        L.append(f"- note: {n}")
    return L


def _md_found(rep: dict) -> list[str]:
    """The effects found, with their parameters."""
    L = []
    L.append("\n## Effects found\n")
    if not rep["found"]:
        L.append("None: nothing beats the nominal model by more than run-to-run noise.\n")
    else:
        L.append("| # | effect | parameter | value | ± 1σ | nominal | confounded with |")
        L.append("|---|---|---|---|---|---|---|")
        for i, f in enumerate(rep["found"], 1):
            for j, p in enumerate(f["params"]):
                L.append(f"| {i if j == 0 else ''} | {f['title'] if j == 0 else ''} | {p['name']} [{p['unit']}] | "
                         f"{_fmt(p['value'])} | {_sigma(p)} | {_fmt(p['nominal'])} | "
                         f"{', '.join(f.get('confounded_with') or []) if j == 0 else ''} |")
            for k, v in (f.get("derived") or {}).items():
                L.append(f"|  |  | {k} (derived) | {_fmt(v)} |  |  |  |")
        L.append("")
    return L


def _md_findings(rep: dict) -> list[str]:
    """Every finding with its status, what was withdrawn, what the model change is, what the record
    could have revealed, and the figures that disagree."""
    L = []
    cmd = rep.get("recording", {}).get("command")
    if cmd:
        L.append(f"Command: **{cmd['kind']}** ({cmd['meaning']})"
                 + (f"; not proposed: {', '.join(cmd['not_proposed'])}" if cmd.get("not_proposed") else "") + ".\n")
    L.append("## Findings\n")
    L.append("| finding | status | detail |")
    L.append("|---|---|---|")
    for f in rep.get("findings") or []:
        det = []
        if f.get("not_determined"):
            det.append("not determined: " + ", ".join(f["not_determined"]))
        if f.get("chosen_by"):
            det.append("chosen by " + f["chosen_by"])
        if f.get("why"):
            det.append(f["why"])
        w = f.get("where") or {}
        if w.get("regime"):
            det.append(f"most excess in {w['regime']['regime']} ({100 * w['regime']['excess_share']:.0f} %)")
        if w.get("band_hz"):
            det.append(f"band {w['band_hz'][0]:.4g}–{w['band_hz'][1]:.4g} Hz "
                       f"({100 * w.get('band_excess_share', 0):.0f} %)")
        if w.get("peaks_hz"):
            det.append("peaks " + ", ".join(f"{x:.4g} Hz" for x in w["peaks_hz"]))
        L.append(f"| {f['finding']} | {f['status']} | {'; '.join(det)} |")
    for fe in rep.get("found") or []:
        for a in fe.get("alternatives") or []:
            L.append(f"\n- {fe['title']} and {a['title']} replay the held-out data alike (replay D "
                     f"{_fmt(a.get('replay_D'))}): " + ", ".join(f"{p['name']} = {_fmt(p['value'])}" for p in a["params"])
                     + ("" if a.get("adoptable", True) else f" (not adoptable: {a.get('why')})")
                     + f"; chosen by {fe.get('chosen_by')}.")
    dl = rep.get("detection_limits")
    if dl:
        L.append("\n**What this record could have revealed** on top of the final model (the smallest change the "
                 "adoption test passes in half the recordings, linearised; smaller ones would not show):\n")
        L.append("| effect | parameter | model value | smallest change | relative |")
        L.append("|---|---|---|---|---|")
        for d in dl:
            rel = "–" if d.get("relative") is None else f"{100 * d['relative']:.3g} %"
            L.append(f"| {d['title']} | {d['parameter']} [{d['unit']}] | {_fmt(d['model_value'])} | "
                     f"{_fmt(d['smallest_change'])} | {rel} |")
    lsq = rep.get("least_squares_check")
    if lsq:
        U = rep.get("units") or axis_units("linear")
        L.append(f"\n**Rigid-body least-squares check** (ordinary least squares of the drive force on acceleration, "
                 f"sign of velocity and velocity over the {lsq['samples']} moving samples, independent of the "
                 f"diagnosis' models; agreement: within {100 * lsq['tolerance']:.0f} % or 3 standard errors):\n")
        L.append("| quantity | improved model | least-squares check | agrees |")
        L.append("|---|---|---|---|")
        for k, unit in (("inertia", U["mass"]), ("coulomb", U["force"]), ("viscous", U["damping"])):
            c = lsq[k]
            L.append(f"| {k} [{unit}] | {_fmt(c['model'])} | {_fmt(c['value'])} ± {_fmt(c['sigma'])} | "
                     f"{'yes' if c['agree'] else '**no**'} |")
    ch = (rep.get("improved_model") or {}).get("changes")
    if ch:
        L.append(f"\n**The model change** (`{rep['improved_model']['name']}` against `{rep['nominal']['name']}`; "
                 "every field that moved, and the finding that moved it):\n")
        L.append("| field | nominal | improved | by |")
        L.append("|---|---|---|---|")
        for c in ch:
            L.append(f"| {c['field']} | {c['nominal']} | {c['improved']} | {', '.join(c['by']) or '–'} |")
    dis = (rep.get("validation") or {}).get("disagreements")
    if dis:
        L.append("\n**Figures that disagree:** " + " ".join(dis))
    L.append("")
    return L


def _md_proof(rep: dict) -> list[str]:
    """The held-out figures of both models."""
    L = []
    U = rep.get("units") or axis_units("linear")
    fu, pu = U["force"], U["position"]
    v = rep["validation"]
    L.append("## Held-out proof\n")
    L.append("| metric (held-out samples) | nominal | improved | fall | reference |")
    L.append("|---|---|---|---|---|")
    fr = v["force_residual_rms_N"]
    L.append(f"| force residual RMS [{fu}] | {_fmt(fr['nominal'])} | {_fmt(fr['improved'])} | "
             f"{_fmt(None if fr['fall'] is None else 100 * fr['fall'])} % | floor {_fmt(fr['floor'])} |")
    j = v["J_held"]
    L.append(f"| J (whitened) | {_fmt(j['nominal'])} | {_fmt(j['improved'])} | "
             f"{_fmt(None if j['fall'] is None else 100 * j['fall'])} % | 1 |")
    how = "open-loop prediction" if rep.get("recording", {}).get("open_loop") else "closed-loop replay"
    for key, name in (("replay_command_rms_N", f"{how}, command error RMS [{fu}]"),
                      ("replay_position_rms_m", f"{how}, position error RMS [{pu}]")):
        x = v[key]
        L.append(f"| {name} | {_fmt(x['nominal'])} | {_fmt(x['improved'])} | "
                 f"{_fmt(None if x['fall'] is None else 100 * x['fall'])} % | run-to-run {_fmt(x['run_to_run'])} |")
    o = v["open_loop_drift_rms_m"]
    L.append(f"| open-loop {o['window_s'] * 1e3:.3g} ms window drift RMS [{pu}] | {_fmt(o['nominal'])} | "
             f"{_fmt(o['improved'])} |  |  |")
    return L


def _sigma(p: dict) -> str:
    """A parameter's ± 1σ cell: its standard error, or the resolution of an integer effect's grid.

    >>> _sigma({"sigma": None, "resolution": 0.5})
    '±0.5 (whole steps)'
    """
    if p.get("sigma") is None and p.get("resolution") is not None:
        return f"±{p['resolution']:g} (whole steps)"
    return _fmt(p.get("sigma"))


def _md_locate(rep: dict) -> list[str]:
    """Where the nominal model disagrees."""
    L = []
    fu = (rep.get("units") or axis_units("linear"))["force"]
    loc = rep["locate"]
    L.append("\n## Where the nominal model disagrees\n")
    L.append(f"Force residual RMS {_fmt(loc['residual_rms_N'], fu)} against a floor of "
             f"{_fmt(loc['floor_rms_N'], fu)} (recordings simulated from the model).\n")
    L.append(f"| regime | time share | RMS [{fu}] | floor [{fu}] | energy share | excess share |")
    L.append("|---|---|---|---|---|---|")
    for r in loc["regimes"]:
        L.append(f"| {r['regime']} | {100 * r['time_share']:.1f} % | {_fmt(r['rms_N'])} | {_fmt(r['floor_rms_N'])} | "
                 f"{100 * r['energy_share']:.1f} % | {100 * r['excess_share']:.1f} % |")
    L.append(f"\n| band [Hz] | RMS [{fu}] | floor [{fu}] | power ratio | excess share |")
    L.append("|---|---|---|---|---|")
    for b in loc["bands"]:
        L.append(f"| {b['f_lo_hz']:.4g}–{b['f_hi_hz']:.4g}{' (above observer bw)' if b['above_observer_bandwidth'] else ''} | "
                 f"{_fmt(b['rms_N'])} | {_fmt(b['floor_rms_N'])} | {_fmt(b['ratio'])} | {100 * b['excess_share']:.1f} % |")
    if loc["peaks"]:
        L.append("\nSpectral peaks above the floor: " + ", ".join(f"{p['f_hz']:.4g} Hz (x{p['ratio']:.3g})" for p in loc["peaks"][:5]))
    L.append("\nResidual energy explained by one state variable (bin means): " + ", ".join(
        f"{k} {100 * s['explained_share']:.1f} %" for k, s in sorted(loc["state"].items(), key=lambda kv: -kv[1]["explained_share"])))
    if loc["segments"]:
        L.append("\nTime blocks with the largest excess: " + "; ".join(
            f"trial {s['trial']} {s['t_start_s']:.3f}–{s['t_end_s']:.3f} s ({s['regime']}, {100 * s['excess_share']:.1f} %)"
            for s in loc["segments"][:5]))
    return L


def _md_candidates(rep: dict) -> list[str]:
    """Each step's candidates, the second start and the joint fit."""
    L = []
    L.append("\n## Candidates\n")
    for st in rep["selection"]["steps"]:
        if st.get("stopped"):
            L.append(f"Step {st['step']}: stopped: {st['stopped']} (z {_fmt(st.get('replay_z_before'))} <= "
                     f"{_fmt(st.get('z_critical'))}).\n")
            continue
        L.append(f"Step {st['step']}: replay D before {_fmt(st.get('replay_D_before'))} "
                 f"({1 if rep.get('recording', {}).get('open_loop') else 2} = at the run-to-run floor), "
                 f"J_held before {_fmt(st['J_held_before'])}; accepted: **{st['accepted'] or 'none'}**"
                 + (" (second start: the greedy path's runner-up)" if st.get("second_start") else "")
                 + (f" (confounded with {', '.join(st['confounded_with'])}: not adopted)" if st["confounded_with"] else "")
                 + ("; the adopted effects' re-fit the candidates' refinements reached is kept"
                    if st.get("refit_kept") else "")
                 + "\n")
        L.append("| effect | replay D after | improvement | floor threshold | block SE | decision | J_held | parameters |")
        L.append("|---|---|---|---|---|---|---|---|")
        for c in st["candidates"]:
            ps = ", ".join(f"{p['name']}={_fmt(p['value'])}" for p in c["params"])
            L.append(f"| {c['effect']} | {_fmt(c['replay']['D_after'])} | {_fmt(c['improvement'])} | "
                     f"{_fmt(c['threshold'])} | {_fmt(c['block_se'])} | {'✓ ' if c['significant'] else ''}{c['why']} | "
                     f"{_fmt(c['J_held'])} | {ps} |")
        if st.get("failed"):
            L.append("\nNot judged (the fit failed): " + "; ".join(f"{k}: {v}" for k, v in st["failed"].items()))
        L.append("")
    ss = rep["selection"].get("second_start")
    if ss and ss.get("skipped"):
        L.append(f"No second start from **{ss['first']}** (step 1's runner-up): {ss['skipped']}.\n")
    elif ss:
        L.append(f"Second start (the greedy path, {', '.join(ss['greedy_effects'])}, left a residual beyond its "
                 f"floor): from **{ss['first']}** the selection found {', '.join(ss['effects'])}, replay D "
                 f"{_fmt(ss['replay_D'])} against the greedy path's {_fmt(ss['replay_D_greedy'])} (in its floor "
                 "units): " + (f"kept ({ss['why']})" if ss["chosen"] else f"not kept ({ss['why']})") + ".\n")
    jf = rep.get("joint_fit")
    if jf:
        L.append(f"Joint fit of {jf['effects']}: J_held {_fmt(jf['J_held'])} (used: {jf['used']}).")
        if jf.get("confounded_parameters"):
            L.append("Confounded parameters (|correlation| > 0.95): " + "; ".join(
                f"{a} ~ {b} ({c:+.3f})" for a, b, c in jf["confounded_parameters"]))
        L.append("")
    return L


def md_noise(rep: dict) -> list[str]:
    """Noise, quantization, sparse regression and the files.

    Parameters
    ----------
    rep : dict
        The diagnosis report (``report.json``'s content): ``stochastic``, ``timing_s`` and,
        when there, ``units``, ``remaining``, ``sparse_regression``, ``plots``.

    Returns
    -------
    list of str
        Markdown lines: the noise and quantization estimates, what the improved model leaves,
        the sparse regression, the files and the wall time.
    """
    L = []
    U = rep.get("units") or axis_units("linear")
    fu, pu = U["force"], U["position"]
    sto = rep["stochastic"]
    q = sto["quantization"]
    n = sto["noise_level"]
    L.append("## Noise and quantization\n")
    L.append(f"- encoder lattice: estimate {_fmt(q.get('estimate_m'), pu)}, model {_fmt(q.get('nominal_m'), pu)}"
             f"{' — differs' if q.get('found') else ''}")
    L.append(f"- drive noise: estimate {_fmt(n.get('sigma'), 'A')} (model {_fmt(n.get('nominal_A'), 'A')})"
             f"{' — differs' if n.get('found') else ''}")
    left = rep.get("remaining")
    if left:
        L.append("\n## What the improved model leaves (located, not explained)\n")
        ratio = f" ({left['ratio']:.3g}x its floor {_fmt(left['floor_rms_N'], fu)})" if left.get("ratio") else ""
        L.append(f"The improved model's replay is beyond its run-to-run floor; its held-out force residual is "
                 f"{_fmt(left['rms_N'], fu)} RMS{ratio}. No library effect was adopted for the signatures "
                 "below (each with its share of the residual's mean square):\n")
        for sg in left.get("signatures", []):
            L.append(f"- {sg['kind']}: {sg['text']} — {100 * sg['share']:.0f} %")
        if not left.get("signatures"):
            L.append("- no line, position signature or regime concentration stands out: the residual is "
                     "spread (see `remaining.png`)")
    sp = rep.get("sparse_regression")
    if sp:
        L.append("\n## Sparse regression of the remaining residual\n")
        L.append(f"Explained share {100 * sp['explained']:.1f} %; terms (missing table force [{fu}] = Σ coef·term): "
                 + (", ".join(f"{k}: {v:.4g}" for k, v in sp["terms"].items()) or "none"))
    L.append("\n## Files\n")
    L.append("`improved_preset.yaml` (runs as is), plots: "
             + ", ".join(f"`{p}`" for p in rep.get("plots", [])))
    L.append(f"\nWall time {rep['timing_s']['total_s']:.3g} s.")
    return L


def to_markdown(rep: dict) -> str:
    """``report.md`` from the report dict.

    Parameters
    ----------
    rep : dict
        The diagnosis report (``report.json`` content).

    Returns
    -------
    str
        Markdown, leading with the held-out replay headline.
    """
    L = []
    for section in (_md_headline, _md_found, _md_findings, _md_proof, _md_locate, _md_candidates, md_noise):
        L += section(rep)
    b = rep.get("budget") or {}
    if b.get("reached"):       # what was not examined leads, under the title
        L.insert(1, f"**Partial: {b['statement']}.** The model is the one of the last completed step; "
                    "a step cut short is not adopted.\n")
    return "\n".join(L) + "\n"


def _plots(out: Path, rep: dict, data, arr: dict) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    files = []
    rate = data.rate
    fb = arr["f_band"]
    mask = data.fit | data.held
    rn = lowpass(arr["res_nom"].r, mask, rate, fb)
    ri = lowpass(arr["res_new"].r, mask, rate, fb)
    lab = arr["loc"]["labels"]
    cols = list(range(min(3, data.shape[1])))
    fig, axes = plt.subplots(len(cols), 1, figsize=(11, 2.6 * len(cols)), squeeze=False)
    colors = {"in_position": "#dddddd", "settling": "#ffe0b0", "reversal": "#ffb0b0", "acceleration": "#c0d8ff",
              "constant_velocity": "#d0f0d0"}
    flr = rep["validation"]["force_residual_rms_N"]["floor"] or 0.0
    for ax, b in zip(axes[:, 0], cols):
        n = int(data.lengths[b])
        t = data.t0[b] + np.arange(n) / rate
        lb = lab[:n, b]
        k = 0
        while k < n:
            j = k
            while j < n and lb[j] == lb[k]:
                j += 1
            if lb[k] >= 0:
                ax.axvspan(t[k], t[min(j, n - 1)], color=colors[REGIMES[lb[k]]], lw=0)
            k = j
        ax.plot(t, rn[:n, b], "C3", lw=0.8, label="nominal")
        ax.plot(t, ri[:n, b], "C0", lw=0.8, label="improved")
        ax.axhspan(-2 * flr, 2 * flr, color="k", alpha=0.1, label="±2 floor")
        ax.set_ylabel(f"trial {data.trial_ids[b]}\nresidual [N]")
    axes[0, 0].legend(loc="upper right", fontsize=7, ncol=3)
    axes[-1, 0].set_xlabel("time [s]  (shading: " + ", ".join(f"{k}" for k in colors) + ")")
    fig.tight_layout()
    outputs.savefig(fig, out / "residual_time.png", dpi=90)
    plt.close(fig)
    files.append("residual_time.png")

    spn = arr["loc"]["spectrum"]
    sp_new = spectrum(arr["res_new"].r, arr["floor"].res_b.r, mask, arr["floor"].sim_b.fit | arr["floor"].sim_b.held,
                      rate, 1e9, nperseg=spn.get("nperseg", 1024))
    fig, ax = plt.subplots(figsize=(8, 4.5))
    f = spn["f_hz"]
    for psd, style, label in ((spn["psd"], "C3", "nominal model residual"),
                              (spn["psd_floor"], "k", "floor (nominal, simulated)"),
                              (sp_new["psd"], "C0", "improved model residual")):
        pos = psd[1:] > 0
        if pos.any():
            ax.loglog(f[1:][pos], psd[1:][pos], style, lw=0.8, label=label)
        else:        # a residual that is exactly zero (a stage held by friction, the encoder never moving)
            ax.plot([], [], style, lw=0.8, label=label + ": zero, not shown")
    ax.axvline(rep["observer"]["bandwidth_hz"], color="gray", ls=":", label="observer bandwidth")
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("force residual PSD [N²/Hz]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    outputs.savefig(fig, out / "residual_spectrum.png", dpi=90)
    plt.close(fig)
    files.append("residual_spectrum.png")

    st = arr["loc"]["state"]
    if st:
        fig, axes = plt.subplots(1, len(st), figsize=(3.2 * len(st), 3.2), squeeze=False)
        for ax, (name, s) in zip(axes[0], st.items()):
            ax.plot(s["centres"], s["mean_N"], "o-", ms=3, color="C3")
            ax.axhline(0, color="k", lw=0.5)
            ax.set_title(f"{name}\nR² {100 * s['explained_share']:.1f} %", fontsize=8)
            ax.tick_params(labelsize=7)
        axes[0, 0].set_ylabel("mean residual [N]")
        fig.tight_layout()
        outputs.savefig(fig, out / "residual_state.png", dpi=90)
        plt.close(fig)
        files.append("residual_state.png")

    held = arr["held"]
    hc = [b for b in range(data.shape[1]) if held[:, b].any()]
    if hc:
        b = hc[0]
        n = int(data.lengths[b])
        t = data.t0[b] + np.arange(n) / rate
        fig, axes = plt.subplots(2, 1, figsize=(10, 5.5), sharex=True)
        axes[0].plot(t, data.u[:n, b], "k", lw=0.8, label="recorded")
        axes[0].plot(t, arr["rp_nom"]["u"][:n, b], "C3", lw=0.7, label="nominal replay")
        axes[0].plot(t, arr["rp_new"]["u"][:n, b], "C0", lw=0.7, label="improved replay")
        axes[0].set_ylabel("command [N]")
        axes[0].legend(fontsize=8)
        axes[1].plot(t, data.u[:n, b] - arr["rp_nom"]["u"][:n, b], "C3", lw=0.7, label="recorded - nominal")
        axes[1].plot(t, data.u[:n, b] - arr["rp_new"]["u"][:n, b], "C0", lw=0.7, label="recorded - improved")
        axes[1].set_ylabel("command error [N]")
        axes[1].set_xlabel("time [s]")
        axes[1].legend(fontsize=8)
        fig.suptitle(f"held-out trial {data.trial_ids[b]}: closed-loop replay of the recorded reference", fontsize=9)
        fig.tight_layout()
        outputs.savefig(fig, out / "heldout_replay.png", dpi=90)
        plt.close(fig)
        files.append("heldout_replay.png")
    left = arr.get("remaining")
    if left and left.get("spectrum"):
        sp, sc = left["spectrum"], left.get("position_scan") or {}
        fig, ax = plt.subplots(1, 2 if len(sc.get("periods_m", [])) else 1, figsize=(11, 3.6), squeeze=False)
        a = ax[0, 0]
        a.loglog(sp["f_hz"][1:], sp["psd"][1:], lw=0.8)
        for fl in sp.get("lines_hz", []):
            a.axvline(fl, color="C3", lw=0.8, ls="--")
        a.set_xlabel("frequency [Hz]")
        a.set_ylabel("force residual PSD [N²/Hz]")
        a.set_title("what the improved model leaves: lines in time", fontsize=9)
        if ax.shape[1] > 1:
            b = ax[0, 1]
            b.semilogx(sc["periods_m"], 100 * sc["share"], lw=0.8)
            b.set_xlabel("period in position [m]")
            b.set_ylabel("explained share [%]")
            b.set_title("what the improved model leaves: periodic in position", fontsize=9)
        fig.tight_layout()
        outputs.savefig(fig, out / "remaining.png", dpi=90)
        plt.close(fig)
        files.append("remaining.png")
    return files


REPORT_FILES = ("report.md", "report.json", "improved_preset.yaml")
"""The files :func:`write_report` writes besides the plots (checked before a diagnosis starts)."""


def write_report(out, rep: dict, improved, nominal, data, arrays: dict, plots: bool = True) -> Path:
    """``report.json``, ``report.md``, ``improved_preset.yaml`` and the plots, each written atomically
    to the output folder ``out`` (:mod:`experiment_runner.core.outputs`).

    Parameters
    ----------
    out : str or pathlib.Path
        Output folder.
    rep : dict
        The report (gets the names of the files written).
    improved, nominal : ModelSpec
        The improved and the nominal model.
    data : DiagData
        The recording.
    arrays : dict
        Signals for the plots (replays, residuals).
    plots : bool, optional
        Write the PNG plots (a plot that fails is noted in the report, never loses it).

    Returns
    -------
    pathlib.Path
        ``out``.
    """
    out = outputs.prepare_folder(out)
    outputs.write_text(out / "improved_preset.yaml", improved.preset_yaml())
    rep["improved_model"]["preset_yaml"] = "improved_preset.yaml"
    rep["plots"] = []
    if plots:
        try:
            rep["plots"] = _plots(out, rep, data, arrays)
        except outputs.OutputError:
            raise
        except Exception as err:     # noqa: BLE001 - plots must not lose the report
            rep.setdefault("recording", {}).setdefault("notes", []).append(f"plots failed: {err!r}")
    outputs.write_text(out / "report.json", json.dumps(jsonable(rep), indent=1))
    outputs.write_text(out / "report.md", to_markdown(jsonable(rep)))
    return out
