"""Appendix A: PID settling vs K_I (Fig. A.2) and NIASA robustness to k_sigma (Fig. A.3).

Seed (App. A.1/A.2, Table A.1): rigid 1.5 kg ALS-130H stage with Dahl pre-motion
friction (``k_sigma = 8 N/um``, ``F_C = 1 N``) under a PID (``K_P = 0.8 N/um``,
``K_D = 8.5e-4 N s/um``), ideal 50 nm and 500 nm step commands, +-20 % settling windows
(+-10 nm, +-100 nm). Benchmark: no friction and ``K_I = 0``. NIASA (Eq. A.1) replaces
``K_I`` by ``(k_sigma (1 - F_f/F_C sgn xdot) + K_P) / tau_d`` with ``tau_d = 4 ms`` and the
nominal ``k_sigma``; the *plant* stiffness is ``8e6 (1 + delta)`` N/m.

Our simulation: presets ``als130h`` / ``als130h_niasa`` unchanged (10 kHz discrete PID,
derivative on the error -> the ideal step gives the derivative kick ``K_D D`` as an
impulse, ideal sensor, no noise) run by :func:`experiment_runner.core.batch.simulate`; the
frictionless benchmark sets ``stage.table_friction`` to None. Each record is
``PRE`` s at rest, the ideal step, then ``DWELL`` s at the target.

Numerical definitions (all on the measured position ``y`` after the step):

* *settled*: :func:`~experiment_runner.core.metrics.settling_time` into ``D +- 20 % D`` is
  finite and the response then stays inside for at least the last ``HOLD`` s of the
  record (a bounded oscillation that happens to be inside at the last sample is not
  "settled");
* *unstable*: the engine flags the trial (diverged / out of travel) or ``max |y - D|``
  exceeds ``GROWTH x D`` (the response grows by orders of magnitude; with the preset's
  1 kN actuator limit an unstable loop ends in a mm-size saturated oscillation);
* *limit cycle*: not unstable, and the peak-to-peak of the last ``LC_WIN`` s is at least
  ``LC_MIN_PP x D`` and at least ``LC_SUSTAIN`` times that of the window ``LC_LAG`` s
  earlier (the oscillation neither decays nor grows);
* *stuck*: otherwise not settled (at rest outside the window: pre-motion stiffness).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from experiment_runner.apps.paper import Claim
from experiment_runner.core import outputs
from experiment_runner.core.batch import simulate
from experiment_runner.core.metrics import settling_time
from experiment_runner.core.profiles import point_to_point
from stage_sim.config import load_preset, with_overrides

STEPS = (50e-9, 500e-9)           # App. A step commands [m]
WINDOW = 0.20                     # +-20 % settling window (App. A.1; +-10 nm for 50 nm in A.2)
PRE, DWELL = 0.005, 0.5           # rest before the step, record after it [s]
HOLD = 0.10                       # must stay in the window for the last HOLD s to count as settled
LC_WIN, LC_LAG = 0.05, 0.15       # limit cycle: last 50 ms vs the 50 ms window 150 ms earlier
LC_SUSTAIN, LC_MIN_PP = 0.9, 0.01
GROWTH = 100.0                    # unstable: |y - D| beyond 100 D
UM = 1e6                          # N/(um s) -> N/(m s)
KI_GRID = (0.0, 10.0, 100.0, 300.0, 1e3, 2e3, 3e3, 4e3, 5e3, 6e3, 8e3, 1e4)   # [N/(um s)]
KI_BEST_SEED, KI_LC_SEED = 3e3, 6e3
ROUND_KI = tuple(float(k) for k in np.arange(2500.0, 3500.0 + 1.0, 100.0))   # rounds to "3 × 10^3"
ROUND_KI_CONT = (2500.0, 2750.0, 3000.0, 3250.0, 3500.0)                       # same, continuous check
DELTAS = (-0.65, -0.5, 0.0, 0.5, 1.0)
K_SIGMA_N = 8e6                   # nominal k_sigma [N/m] (Table A.1)
SPREAD_MIN = 0.25                 # "varies significantly": (max - min)/mean >= 25 %
SEED_SHORTER, SEED_SLOWER = 0.33, 0.31
TOL_PP = 0.10                     # +-10 percentage points on the seed's percentages


def _nan_to_none(v):
    return None if isinstance(v, float) and math.isnan(v) else v


def _references():
    """Per-trial step references (50 nm, 500 nm) of equal length, and the step instant."""
    refs = [point_to_point(d, shape="step", pre=PRE, dwell=DWELL) for d in STEPS]
    t_step = float(refs[0].t[refs[0].select("settle")[0].start])
    return np.stack([r.x for r in refs]), np.stack([r.v for r in refs]), t_step


def _classify(t, y, D, t_step, status, window=WINDOW):
    """Settling time and behaviour of one response (see the module docstring)."""
    dt = t[1] - t[0]
    ts = float(settling_time(t, y, D, t_step, window * D))
    after = y[t >= t_step]
    n_win, n_lag = int(round(LC_WIN / dt)), int(round(LC_LAG / dt))
    pp_last = float(np.ptp(after[-n_win:]))
    pp_prev = float(np.ptp(after[-n_win - n_lag:-n_lag]))
    dev = float(np.max(np.abs(after - D)))
    settled = math.isfinite(ts) and t_step + ts <= t[-1] - HOLD
    unstable = status != 0 or dev > GROWTH * D
    limit_cycle = (not unstable and pp_last >= LC_MIN_PP * D and pp_last >= LC_SUSTAIN * pp_prev)
    kind = ("unstable" if unstable else "settled" if settled
            else "limit cycle" if limit_cycle else "stuck")
    return dict(settling_time=ts if settled else math.nan, settled=settled, kind=kind,
                limit_cycle=limit_cycle, overshoot=float(np.max(after) / D - 1.0),
                pp_last=pp_last, pp_prev=pp_prev, max_dev=dev, final=float(after[-1]),
                status=int(status))


def _run(preset, x_ref, v_ref, t_step, window=WINDOW):
    r = simulate(preset, x_ref, v_ref, check=False)
    return r.t, r.y, [_classify(r.t, r.y[i], D, t_step, r.status[i], window)
                      for i, D in enumerate(STEPS)]


def _spread(values):
    v = np.asarray(values, float)
    return float((v.max() - v.min()) / v.mean())


def _ms(x):
    return "none" if not math.isfinite(x) else f"{x * 1e3:.1f} ms"


# --------------------------------------------------------------------------- plots
def _plot(out: Path, t, t_step, curves, title, fname, t_max=0.05):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6))
    for i, (ax, D) in enumerate(zip(axes, STEPS)):
        m = (t >= t_step - 0.002) & (t <= t_step + t_max)
        tt = (t[m] - t_step) * 1e3
        ax.axhspan((1 - WINDOW) * D * 1e9, (1 + WINDOW) * D * 1e9, color="0.9",
                   label=f"±{WINDOW:.0%} window (±{WINDOW * D * 1e9:.0f} nm)")
        ax.axhline(D * 1e9, color="0.6", lw=0.8)
        for label, y, info, style in curves:
            extra = "" if info[i]["kind"] == "settled" else f" [{info[i]['kind']}]"
            if info[i]["kind"] == "settled" and info[i]["limit_cycle"]:
                extra = f" [limit cycle {info[i]['pp_last'] * 1e9:.0f} nm p-p inside window]"
            ax.plot(tt, y[i][m] * 1e9, style, lw=1.2, label=label + extra)
        ax.set_ylim(-0.05 * D * 1e9, 2.1 * D * 1e9)
        ax.set_xlim(tt[0], tt[-1])
        ax.set_xlabel("time after step command [ms]")
        ax.set_ylabel("table position x [nm]")
        ax.set_title(f"({'ab'[i]}) {D * 1e9:.0f} nm step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower right")
    fig.suptitle(title)
    fig.tight_layout()
    outputs.savefig(fig, out / fname, dpi=110)
    plt.close(fig)


def _plot_sweep(out: Path, sweep, bench):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.2))
    ki = np.array(KI_GRID)
    for i, (D, c) in enumerate(zip(STEPS, ("C0", "C3"))):
        ts = np.array([s[i]["settling_time"] for s in sweep]) * 1e3
        ax.plot(ki, ts, "o-", color=c, label=f"{D * 1e9:.0f} nm, with friction")
        bad = ~np.isfinite(ts)
        ax.plot(ki[bad], np.full(bad.sum(), 400.0 * (1.0 + 0.25 * i)), "x", color=c, ms=9,
                label=f"{D * 1e9:.0f} nm: no settling (stuck / limit cycle / unstable)")
        ax.axhline(bench[i]["settling_time"] * 1e3, color=c, ls="--", lw=1,
                   label=f"{D * 1e9:.0f} nm benchmark (F_f = 0, K_I = 0)")
    ax.set_xscale("symlog", linthresh=10)
    ax.set_xlim(-1.0, 1.5e4)
    ax.set_yscale("log")
    ax.set_xlabel("integral gain K_I [N/(µm·s)]")
    ax.set_ylabel("settling time into ±20 % window [ms]")
    ax.set_title("Fig. A.2 sweep: PID settling time vs K_I (als130h, 10 kHz)")
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    outputs.savefig(fig, out / "appendix_a_fig_a2_sweep.png", dpi=110)
    plt.close(fig)


# --------------------------------------------------------------------------- claims
def _fig_a2(out, pid, x_ref, v_ref, t_step):
    """Fig. A.2: the frictionless benchmark and the K_I sweep (one simulate call per K_I, both steps); plots."""
    t, y_bench, bench = _run(with_overrides(pid, {"stage.table_friction": None}), x_ref, v_ref, t_step)
    sweep, ys = [], {}
    for ki in KI_GRID:
        _, y, info = _run(with_overrides(pid, {"controller.pid.ki": ki * UM}), x_ref, v_ref, t_step)
        sweep.append(info)
        ys[ki] = y
    by_ki = dict(zip(KI_GRID, sweep))
    shown = (0.0, 10.0, 100.0, 1e3, 3e3, 6e3)
    _plot(out, t, t_step,
          [("benchmark (F_f = 0, K_I = 0)", y_bench, bench, "k--")]
          + [(f"K_I = {ki:g} N/(µm·s)", ys[ki], by_ki[ki], "-") for ki in shown],
          "Fig. A.2: PID-controlled ALS-130H with Dahl friction (als130h preset)",
          "appendix_a_fig_a2.png")
    _plot_sweep(out, sweep, bench)
    return t, y_bench, bench, sweep, by_ki


def _fig_a3(out, x_ref, v_ref, t_step, t, y_bench, bench):
    """Fig. A.3: NIASA with plant k_sigma = k_sigma,n (1 + delta) per delta; plot."""
    niasa = load_preset("als130h_niasa")
    nres, ny = {}, {}
    for d in DELTAS:
        p = with_overrides(niasa, {"stage.table_friction.k_sigma": K_SIGMA_N * (1 + d)})
        _, y, info = _run(p, x_ref, v_ref, t_step)
        nres[d], ny[d] = info, y
    _plot(out, t, t_step,
          [("benchmark (F_f = 0, K_I = 0)", y_bench, bench, "k--")]
          + [(f"NIASA, δ = {d:g}", ny[d], nres[d], "-") for d in DELTAS],
          "Fig. A.3: NIASA (τ_d = 4 ms) with plant k_σ = 8 N/µm·(1+δ) (als130h_niasa preset)",
          "appendix_a_fig_a3.png")
    return nres, ny


def _claims_ki0(by_ki):
    """Claim 1: K_I = 0 with friction does not settle."""
    k0 = by_ki[0.0]
    return [Claim(
        id="A.2/ki0-no-settle", source="Fig. A.2",
        claim="with Dahl friction and K_I = 0 the stage does not settle into the ±20 % window (50 nm, 500 nm)",
        seed="no settling for either step",
        ours=(f"50 nm: stops at {k0[0]['final'] * 1e9:.1f} nm ({k0[0]['kind']}); "
              f"500 nm: stops at {k0[1]['final'] * 1e9:.0f} nm ({k0[1]['kind']})"),
        agrees=not k0[0]["settled"] and not k0[1]["settled"],
        numbers={"final_position": [k0[0]["final"], k0[1]["final"]],
                 "kind": [k0[0]["kind"], k0[1]["kind"]], "step": list(STEPS),
                 "record_after_step": DWELL},
        note=(f"agrees if neither response is settled (inside the window for the last {HOLD * 1e3:.0f} ms "
              f"of a {DWELL * 1e3:.0f} ms record). The PD force is balanced by the stiff "
              "pre-motion spring far from the target (a purely elastic k_σ would stop it at "
              "K_P D/(K_P + k_σ) = 9 % of D; the Dahl hysteresis after the derivative kick adds a little)."))]


def _claims_best_ki(sweep, by_ki, b50):
    """Claim 2: best 50 nm settling near K_I = 3e3, ~33 % shorter than the benchmark."""
    ts50 = np.array([s[0]["settling_time"] for s in sweep])
    i_best = int(np.nanargmin(ts50))
    ki_best, ts_best = KI_GRID[i_best], float(ts50[i_best])
    ts_3e3 = by_ki[KI_BEST_SEED][0]["settling_time"]
    red_best, red_3e3 = 1 - ts_best / b50, 1 - ts_3e3 / b50
    j = KI_GRID.index(KI_BEST_SEED)
    near = KI_GRID[j - 1] <= ki_best <= KI_GRID[j + 1]
    return [Claim(
        id="A.2/best-ki-50nm", source="Fig. A.2(a)",
        claim="over K_I = 0…1e4 N/(µm·s) the best 50 nm settling time is at K_I ≈ 3e3 and 33 % shorter than the benchmark",
        seed="best at K_I = 3e3 N/(µm·s), 33 % shorter than benchmark",
        ours=(f"best {_ms(ts_best)} at K_I = {ki_best:g} ({red_best:.0%} shorter than benchmark "
              f"{_ms(b50)}); K_I = 3e3: {_ms(ts_3e3)} ({red_3e3:.0%} shorter)"),
        agrees=bool(near and abs(red_best - SEED_SHORTER) <= TOL_PP),
        numbers={"ki_grid": [k * UM for k in KI_GRID],
                 "settling_time_50nm": [_nan_to_none(float(v)) for v in ts50],
                 "kind_50nm": [s[0]["kind"] for s in sweep],
                 "benchmark_50nm": b50, "ki_best": ki_best * UM, "settling_best": ts_best,
                 "settling_ki_3e3": ts_3e3, "reduction_best": red_best, "reduction_ki_3e3": red_3e3},
        note=(f"agrees if the grid minimum lies between the grid neighbours of 3e3 "
              f"({KI_GRID[j - 1]:g}…{KI_GRID[j + 1]:g}) and its reduction is within ±{TOL_PP * 100:.0f} "
              f"percentage points of 33 %. Settling times have a 0.1 ms (one-sample) resolution; "
              f"K_I = 3e3 and 4e3 differ by {abs(ts_3e3 - float(ts50[j + 1])) * 1e3:.1f} ms. "
              "The stability limit of the stuck (linear, k_f = k_σ) loop is "
              "K_I < (K_P + k_σ) K_D / m ≈ 5.0e3 N/(µm·s); K_I = 5e3 leaves a "
              f"{by_ki[5e3][0]['pp_last'] * 1e9:.1f} nm p-p "
              + ("sustained limit cycle" if by_ki[5e3][0]["limit_cycle"] else "oscillation")
              + (" inside the window (counted as settled)." if by_ki[5e3][0]["settled"]
                 else f" ({by_ki[5e3][0]['kind']}).")))]


def _claims_ki3e3_500nm(pid, x_ref, v_ref, t_step, sweep, by_ki, b500):
    """Claim 3: K_I = 3e3 on 500 nm is slower than the benchmark (seed +31 %), with the cross-checks."""
    ts500 = by_ki[KI_BEST_SEED][1]["settling_time"]
    rel = ts500 / b500 - 1 if math.isfinite(ts500) else math.inf
    ov500 = by_ki[KI_BEST_SEED][1]["overshoot"]
    cross = _continuous_check()
    cross["cont_dmeas_ki3e3_50nm"] = _continuous_run(KI_BEST_SEED * UM, True, False, D=STEPS[0])
    scan_eng, scan_dmeas = _rounding_scan(pid, x_ref, v_ref, t_step, b500, cross["cont_dmeas_bench"])
    eng_fin = [v for v in scan_eng if v is not None]
    dm_near = [ki for ki, v in zip(ROUND_KI_CONT, scan_dmeas) if v is not None and abs(v - SEED_SLOWER) <= TOL_PP]
    dm_unst = [ki for ki, v in zip(ROUND_KI_CONT, scan_dmeas) if v is None]
    red50_dm = 1 - cross["cont_dmeas_ki3e3_50nm"] / cross["cont_dmeas_bench"]
    return [Claim(
        id="A.2/ki3e3-500nm-slower", source="Fig. A.2(b)",
        claim="K_I = 3e3 N/(µm·s) (best for 50 nm) gives a very large overshoot and a 31 % longer 500 nm settling time than the benchmark",
        seed="very large overshoot, settling 31 % longer than benchmark",
        ours=(f"overshoot {ov500:.0%}; settling {_ms(ts500)} vs benchmark {_ms(b500)} "
              f"({rel:+.0%}); over K_I = 2.5e3…3.5e3 (what rounds to 3e3): "
              f"{min(eng_fin):+.0%} … {max(eng_fin):+.0%}"),
        agrees=bool(rel > 0 and abs(rel - SEED_SLOWER) <= TOL_PP),
        numbers={"settling_ki_3e3_500nm": _nan_to_none(ts500), "benchmark_500nm": b500,
                 "relative_change": _nan_to_none(float(rel)) if math.isfinite(rel) else None,
                 "overshoot": ov500,
                 "settling_time_500nm": [_nan_to_none(s[1]["settling_time"]) for s in sweep],
                 "kind_500nm": [s[1]["kind"] for s in sweep], **cross,
                 "rounding_ki": [k * UM for k in ROUND_KI],
                 "rounding_rel_change_engine": scan_eng,
                 "rounding_ki_cont": [k * UM for k in ROUND_KI_CONT],
                 "rounding_rel_change_cont_dmeas": scan_dmeas,
                 "cont_dmeas_reduction_50nm_ki3e3": red50_dm},
        note=("agrees if slower than the benchmark by 31 % ± 10 percentage points. DISAGREES: the large overshoot "
              "is reproduced, but after it the error re-enters the ±100 nm window on its first return "
              "and stays, so the step settles faster than the benchmark. Why the seed's number cannot be "
              "pinned by its parameters: at 500 nm the Dahl friction saturates (F_C/k_σ = 125 nm) and the "
              "sliding loop is unstable for K_I > K_P K_D/m ≈ 450 N/(µm·s); the response grows until the "
              "stage re-sticks, and its settling time in the ±20 % window jumps by about half an "
              "oscillation period when one lobe crosses the window edge. Over K_I = 2.5e3…3.5e3 N/(µm·s) "
              "(every value the seed's one-significant-figure '3 × 10^3' can stand for) the engine gives "
              + ", ".join(f"{v:+.0%}" if v is not None else "none" for v in scan_eng)
              + " (K_I step 100): the sign itself is not determined, and the late-lobe branch reaches "
              f"{max(eng_fin):+.0%}, short of +31 %. The controller's form is the other unstated detail: "
              "a continuous-time model (solve_ivp, same Table A.1 plant) gives "
              f"{_ms(cross['cont_ki3e3'])} vs {_ms(cross['cont_bench'])} with the derivative on the error "
              f"(as our servo and the seed's C(s) = K_p + K_i/s + K_d s of Eq. 6.2), and "
              f"{_ms(cross['cont_dmeas_ki3e3'])} vs {_ms(cross['cont_dmeas_bench'])} with the derivative on the "
              "measurement (no kick); at K_I = 2.5e3, 2.75e3 … 3.5e3 that form gives "
              + ", ".join(f"{v:+.0%}" if v is not None else "unstable" for v in scan_dmeas)
              + (f" — within ±10 points of +31 % at K_I = {', '.join(f'{k:g}' for k in dm_near)}" if dm_near else "")
              + (f", unstable from {min(dm_unst):g}" if dm_unst else "")
              + f"; it keeps the 50 nm claim ({red50_dm:.0%} at 3e3). So the seed's +31 % is "
              "consistent with a derivative on the measurement, but neither form is stated and the result "
              "flips within the rounding of K_I: we keep the preset (derivative on the error) and report "
              "the difference."))]


def _claims_ki6e3(by_ki):
    """Claim 4: K_I = 6e3 gives a limit cycle (50 nm) and an unstable response (500 nm)."""
    k6 = by_ki[KI_LC_SEED]
    return [Claim(
        id="A.2/ki6e3-unstable", source="Fig. A.2",
        claim="K_I = 6e3 N/(µm·s) gives a limit cycle for the 50 nm step and an unstable response for the 500 nm step",
        seed="50 nm: limit cycle; 500 nm: unstable",
        ours=(f"50 nm: {k6[0]['kind']} ({k6[0]['pp_last'] * 1e9:.0f} nm p-p, "
              f"{k6[0]['pp_last'] / k6[0]['pp_prev']:.2f}× the p-p 150 ms earlier); "
              f"500 nm: {k6[1]['kind']} (|x − D| up to {k6[1]['max_dev'] * 1e3:.1f} mm)"),
        agrees=k6[0]["kind"] == "limit cycle" and k6[1]["kind"] == "unstable",
        numbers={"pp_last_50nm": k6[0]["pp_last"], "pp_prev_50nm": k6[0]["pp_prev"],
                 "max_dev_500nm": k6[1]["max_dev"], "status_500nm": k6[1]["status"],
                 "kind": [k6[0]["kind"], k6[1]["kind"]],
                 "kind_8e3": [s["kind"] for s in by_ki[8e3]],
                 "kind_1e4": [s["kind"] for s in by_ki[1e4]]},
        note=(f"limit cycle: last {LC_WIN * 1e3:.0f} ms p-p ≥ {LC_MIN_PP:.0%} of D and ≥ {LC_SUSTAIN} × "
              f"the p-p {LC_LAG * 1e3:.0f} ms earlier; unstable: |x − D| > {GROWTH:g} D or an engine "
              "failure flag. Routh: with the friction stuck (k_f = k_σ) the loop is stable only for "
              "K_I < (K_P + k_σ) K_D/m ≈ 5.0e3 N/(µm·s); with saturated friction (k_f → 0) only for "
              "K_I < K_P K_D/m ≈ 450. At 6e3 the 50 nm oscillation grows until the Dahl stiffness "
              "drop balances it (limit cycle); the 500 nm one reaches gross sliding and runs away until "
              "the preset's 1 kN actuator limit bounds it as a mm-size saturated oscillation. "
              f"K_I = 8e3: {'/'.join(s['kind'] for s in by_ki[8e3])}, "
              f"1e4: {'/'.join(s['kind'] for s in by_ki[1e4])} (50/500 nm)."))]


def _claims_niasa(nres, ny, t, t_step):
    """Claims 5 and 6: NIASA robustness (50 nm) and the 500 nm responses over delta."""
    result: list[Claim] = []
    stable = [d for d in DELTAS if d >= -0.5]
    ok_stable = all(nres[d][i]["settled"] and nres[d][i]["kind"] == "settled"
                    and nres[d][i]["pp_last"] < LC_MIN_PP * STEPS[i]
                    for d in stable for i in range(2))
    st50 = [nres[d][0]["settling_time"] for d in stable]
    st500 = [nres[d][1]["settling_time"] for d in stable]
    ov500s = [nres[d][1]["overshoot"] for d in stable]
    sp50 = _spread(st50)
    lc = nres[-0.65][0]
    result.append(Claim(
        id="A.3/niasa-robustness", source="Fig. A.3(a)",
        claim=("NIASA (τ_d = 4 ms) is stable for δ ∈ [−0.5, 1] with settling that varies significantly "
               "over δ; δ = −0.65 gives a large limit cycle that fails the ±10 nm window (50 nm)"),
        seed="stable for δ ∈ [−0.5, 1], settling varies significantly; severe oscillation at δ = −0.5; δ = −0.65: limit cycle, no settling",
        ours=("50 nm settling " + ", ".join(f"δ={d:g}: {_ms(s)}" for d, s in zip(stable, st50))
              + f" (spread {sp50:.0%}); overshoot δ=−0.5 {nres[-0.5][0]['overshoot']:.0%} vs δ=0 "
              f"{nres[0.0][0]['overshoot']:.0%}; δ=−0.65: {lc['kind']}, {lc['pp_last'] * 1e9:.0f} nm p-p"),
        agrees=bool(ok_stable and sp50 >= SPREAD_MIN and lc["kind"] == "limit cycle"),
        numbers={"delta": list(DELTAS),
                 "settling_50nm": [_nan_to_none(nres[d][0]["settling_time"]) for d in DELTAS],
                 "overshoot_50nm": [nres[d][0]["overshoot"] for d in DELTAS],
                 "kind_50nm": [nres[d][0]["kind"] for d in DELTAS],
                 "settling_500nm": [_nan_to_none(nres[d][1]["settling_time"]) for d in DELTAS],
                 "overshoot_500nm": [nres[d][1]["overshoot"] for d in DELTAS],
                 "kind_500nm": [nres[d][1]["kind"] for d in DELTAS],
                 "pp_last_500nm": [nres[d][1]["pp_last"] for d in DELTAS],
                 "pp_last_50nm_delta_m065": lc["pp_last"], "spread_50nm": sp50},
        note=(f"agrees if every δ ∈ [−0.5, 1] settles (both steps, residual p-p < {LC_MIN_PP:.0%} D), the "
              f"50 nm settling-time spread (max−min)/mean ≥ {SPREAD_MIN:.0%}, and δ = −0.65 is a limit cycle "
              "(definition as for A.2). δ = −0.5 enters ±10 nm quickly but rings longer "
              f"(±5 nm after {_ms(_settle(t, ny[-0.5][0], STEPS[0], t_step, 0.1))} vs "
              f"{_ms(_settle(t, ny[0.0][0], STEPS[0], t_step, 0.1))} at δ = 0). For 500 nm the δ = −0.65 "
              f"limit cycle ({nres[-0.65][1]['pp_last'] * 1e9:.0f} nm p-p) stays inside ±100 nm, so that "
              "step counts as settled.")))

    sp500, spov = _spread(st500), _spread(ov500s)
    result.append(Claim(
        id="A.3/niasa-500nm", source="Fig. A.3(b)",
        claim="the NIASA 500 nm responses (overshoot, settling time) are highly affected by δ",
        seed="overshoot and settling time highly affected by δ",
        ours=(", ".join(f"δ={d:g}: {_ms(nres[d][1]['settling_time'])}/{nres[d][1]['overshoot']:.0%} OS"
                        + (" (limit cycle in window)" if nres[d][1]["limit_cycle"] else "")
                        for d in DELTAS) + f" (spread over [−0.5, 1]: settling {sp500:.0%}, overshoot {spov:.0%})"),
        agrees=bool(ok_stable and max(sp500, spov) >= SPREAD_MIN),
        numbers={"delta": list(DELTAS),
                 "settling_500nm": [_nan_to_none(nres[d][1]["settling_time"]) for d in DELTAS],
                 "overshoot_500nm": [nres[d][1]["overshoot"] for d in DELTAS],
                 "spread_settling": sp500, "spread_overshoot": spov},
        note=(f"agrees if the settling-time or overshoot spread (max−min)/mean over δ ∈ [−0.5, 1] is ≥ "
              f"{SPREAD_MIN:.0%} (same threshold as A.3(a)). The dependence is moderate: the settling time "
              "rises steadily with δ.")))
    return result


def claims(out: Path) -> list[Claim]:
    out = outputs.prepare_folder(out)
    x_ref, v_ref, t_step = _references()
    pid = load_preset("als130h")
    t, y_bench, bench, sweep, by_ki = _fig_a2(out, pid, x_ref, v_ref, t_step)
    nres, ny = _fig_a3(out, x_ref, v_ref, t_step, t, y_bench, bench)
    b50, b500 = bench[0]["settling_time"], bench[1]["settling_time"]
    return (_claims_ki0(by_ki) + _claims_best_ki(sweep, by_ki, b50)
            + _claims_ki3e3_500nm(pid, x_ref, v_ref, t_step, sweep, by_ki, b500)
            + _claims_ki6e3(by_ki) + _claims_niasa(nres, ny, t, t_step))


def _settle(t, y, D, t_step, frac):
    return float(settling_time(t, y, D, t_step, frac * D))


def _continuous_run(ki, fric, kick, D=STEPS[1], T=0.1):  # noqa: N803 (seed symbol)
    """Continuous-time (solve_ivp) settling time [s] of one Table A.1 step response (nan if none).

    ``m x'' = u - F``, ``dF/dt = k_s (v - F |v| / F_C)`` (Eq. 1.1, nu = 1), PID with the
    integral and proportional terms on the error. ``kick``: derivative on the error, the ideal
    step's kick is the impulse ``K_D D`` -> ``v(0+) = K_D D/m``; otherwise derivative on the
    measurement (no kick, ``v(0+) = 0``).
    """
    import warnings

    from scipy.integrate import solve_ivp

    p = load_preset("als130h")
    m, kp, kd = p.stage.table.mass, p.controller.pid.kp, p.controller.pid.kd
    ks, fc = p.stage.table_friction.k_sigma, p.stage.table_friction.f_c

    def f(_, s):
        x, v, F, integ = s
        return [v, (kp * (D - x) + integ - kd * v - (F if fric else 0.0)) / m,
                ks * (v - F * abs(v) / fc), ki * (D - x)]

    te = np.arange(0.0, T, 1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")          # LSODA complains once an unstable case diverges
        sol = solve_ivp(f, (0.0, T), [0.0, kd * D / m if kick else 0.0, 0.0, 0.0], t_eval=te,
                        method="LSODA", rtol=1e-9, atol=[1e-14, 1e-11, 1e-9, 1e-9], max_step=2e-5)
    if not sol.success or sol.t.size < te.size or np.max(np.abs(sol.y[0] - D)) > GROWTH * D:
        return math.nan
    return float(settling_time(sol.t, sol.y[0], D, 0.0, WINDOW * D))


def _continuous_check():
    """Continuous-time check of the 500 nm, K_I = 3e3 case vs the benchmark (see _continuous_run)."""
    return {"cont_bench": _continuous_run(0.0, False, True),
            "cont_ki3e3": _continuous_run(KI_BEST_SEED * UM, True, True),
            "cont_dmeas_bench": _continuous_run(0.0, False, False),
            "cont_dmeas_ki3e3": _continuous_run(KI_BEST_SEED * UM, True, False)}


def _rounding_scan(pid, x_ref, v_ref, t_step, b500, b500_dmeas):
    """500 nm settling time relative to the benchmark for K_I that round to 3e3.

    Engine (derivative on the error, 10 kHz) over ROUND_KI and continuous time with the
    derivative on the measurement over ROUND_KI_CONT; None where it does not settle (unstable)."""
    eng = []
    for ki in ROUND_KI:
        _, _, info = _run(with_overrides(pid, {"controller.pid.ki": ki * UM}), x_ref, v_ref, t_step)
        eng.append(info[1]["settling_time"] / b500 - 1.0)
    dmeas = [_continuous_run(ki * UM, True, False) / b500_dmeas - 1.0 for ki in ROUND_KI_CONT]
    return ([_nan_to_none(float(v)) for v in eng], [_nan_to_none(float(v)) for v in dmeas])
