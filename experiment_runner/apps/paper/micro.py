"""Micrometre settling physics of the Ch. 4 stage (issue 13, item 3): a standalone study.

Run: ``python -m experiment_runner.apps.paper.micro`` (~6 min; prints the tables of docs/headline.md).

The seed's App. C.1 step sequence (Fig. C.2, 8 steps of 5 µm forward, 8 back, ±25 nm window)
shows the No FI settling time *growing* with every same-direction step: 47.8 ms at the first,
85 ms at the eighth, 69.1 ms mean over the 16; its 50 µm steps take 237 ms (first) and 214 ms
(eighth), far longer than the 5 mm move of Table 4.2 (44 ms). A rate-independent friction
model (the seed's GMS with Coulomb slip, Eq. 4.4; Dahl) makes the n-th same-direction step
*faster* than the first (after a same-direction stop the slipped blocks stay at their limit).

Candidate physics, now also the simulator's friction law ``gms_rate_state``
(:mod:`stage_sim.friction.gms_rate_state`, whose block kernels this loop calls): each GMS block
``i`` (Table 4.4: ``k_i``, limit ``lim_i = α_i F_C``) keeps its spring, and its Coulomb slider
becomes a **rate-and-state slider** (Dieterich-Ruina, aging law)::

    df_i/dt = k_i (v - w_i)
    w_i     = v_r (L_i/(v_r θ_i))^(b/a) exp((|f_i|/lim_i - 1)/a) sgn(f_i)
    dθ_i/dt = 1 - |w_i| θ_i / L_i,          L_i = lim_i / k_i

so a slipping block carries ``lim_i [1 + a ln(w/v_r) + b ln(v_r θ/L_i)]``: the *direct effect*
``a`` (force relaxes — creeps — as the slip slows) and the *aging* ``b`` (the contact
strengthens with time at rest, θ ≈ dwell time). Steady sliding carries
``lim_i [1 + (a - b) ln(w/v_r)]``; the seed models gross motion by Coulomb friction (Sec. 4.4.3),
so ``b = a``: then the steady slip force is exactly ``lim_i`` at any speed, and ``v_r`` drops out
exactly. ``L_i`` is the block's own pre-sliding distance (no new parameter); ``θ_i(0)`` = 1 s at
rest before the record (0.1-10 s: the eighth 5 µm step moves by < 0.1 ms). One unknown: ``a``.
``a → 0`` is the seed's GMS; ``b = 0`` is pure logarithmic creep (relaxation without aging).

Mechanism: a forward move that ends without a reversal leaves the slipped blocks at their
limit; at rest their force relaxes (direct effect) and the PID's integral must follow the
relaxing friction, a ramp it tracks with a lag. The force stored in slipped blocks grows with
every same-direction step (the virgin curve: 0.8 N after 5 µm, 3.3 N after 40 µm), and so does
the lag: the settling time grows with the step count. Aging arrests the relaxation (the
relaxed force grows as ln ln t instead of ln t), which is what keeps the 5 mm move, whose blocks
all slip, from over-running the target.

The closed loop here is a standalone copy of the Ch. 4 stage: rigid table (its appended mode
mass included, the ~400 Hz mode itself left out), bearings through the FI for ``fi_stage_gms``
or rigidly for ``fi_stage_nofi_gms``, the preset's PID discretised as in
:mod:`stage_control.servo` (backward Euler integral and filtered derivative on the error,
10 kHz, zero-order hold), 4.88 nm encoder, no noise. Its ``a = 0`` case reproduces the engine
(:func:`engine_sequence`) step by step to 0.5 ms, and at ``a = b = 0.02`` the engine with the
simulator's law (``engine_sequence(..., overrides=rate_state_overrides())``) to 1.4 ms per step
(30.0 -> 87.9 ms vs 30.1 -> 87.3 ms here).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from experiment_runner.apps.campaigns.spec import load_campaign
from experiment_runner.core.batch import simulate
from experiment_runner.core.metrics import settling_time
from experiment_runner.core.profiles import DT, point_to_point, step_sequence, steps_reference
from stage_sim.config import load_preset, with_overrides
from stage_sim.friction.gms_rate_state import slider_step

PRESET = "fi_stage_nofi_gms"        # Ch. 4 No FI stage with the Table 4.4 GMS bearings
PRESET_FI = "fi_stage_gms"          # the same stage with the FIs (k_fi = 8.27e4 N/m, Table 4.3)
WINDOW = 25e-9                      # App. C.1 / Sec. 4.4.1: ±25 nm
DWELL = 0.4                         # rest after each step [s] (not stated; > the 237 ms of Fig. C.3)
V_R = 2 * 5e-3 / 0.125              # gross-motion speed of the 5 mm move [m/s] (Sec. 3.4.1)
THETA0 = 1.0                        # aging state at the start: 1 s at rest before the record [s]
N_SUB = 10                          # plant sub-steps per control sample (k_sigma/m: ω h = 0.01)

# seed numbers this study is judged against (App. C.1, Fig. C.2/C.3; Table 4.2)
SEED = {"5um_first": 0.0478, "5um_eighth": 0.085, "5um_mean16": 0.0691,
        "50um_first": 0.237, "50um_eighth": 0.214, "5mm": 0.044}


def stage(preset=PRESET):
    """Table mass (incl. appended mode mass) and bearing mass [kg], FI (k_fi [N/m], c_fi [N s/m];
    0 for No FI), PID (kp, ki, kd, wd [rad/s]), GMS (k [N/m], alpha, F_C [N]), dt [s], encoder q [m]."""
    p = load_preset(preset)
    st, pid = p.stage, p.controller.pid
    m_t = st.table.mass * (1.0 + sum(md.mass_ratio for md in st.modes))
    m_b = sum(b.mass for b in st.bearings)
    joints = [b.joint for b in st.bearings if b.joint is not None]
    k_fi = sum(j.stiffness for j in joints)
    c_fi = sum(j.damping for j in joints)
    fr = [b.friction for b in st.bearings]
    k = np.concatenate([np.asarray(f.k, float) for f in fr])
    f_c = float(sum(f.f_c for f in fr))
    alpha = np.concatenate([np.asarray(f.alpha, float) * f.f_c for f in fr]) / f_c
    wd = 2.0 * math.pi * pid.derivative_cutoff
    return (m_t, m_b, k_fi, c_fi, (pid.kp, pid.ki, pid.kd, wd), (k, alpha, f_c),
            1.0 / p.controller.rate, st.encoder.resolution)


@njit(cache=True)
def closed_loop(x_ref, m_t, m_b, k_fi, c_fi, kp, ki, kd, wd, dt, q, k, lim, a, v_r, n_sub,
                b=0.0, theta0=1.0):
    """Stage + rate-dependent GMS bearings under the discrete PID.

    ``b > 0`` adds the aging state of rate-and-state friction to every slider (Dieterich's
    aging law): ``w = v_r (L_i/(v_r θ_i))^(b/a) exp((|f|/lim - 1)/a)``,
    ``dθ_i/dt = 1 - |w| θ_i/L_i``, ``L_i = lim_i/k_i`` (the block's own pre-sliding distance),
    ``θ_i(0) = theta0`` [s] (time at rest before the record). Steady sliding then carries
    ``lim (1 + (a - b) ln(w/v_r))``: ``b = a`` keeps the seed's rate-independent Coulomb slip
    and adds only the transients (relaxation after a stop, strengthening with dwell time).

    ``k_fi > 0``: table ``m_t`` on the bearings ``m_b`` through the FI (``k_fi``, ``c_fi``);
    otherwise one rigid mass ``m_t + m_b`` (No FI). Returns the measured table position, the
    true table and bearing positions [m] at the control samples."""
    n = x_ref.size
    nb = k.size
    f = np.zeros(nb)
    theta = np.full(nb, theta0)
    ell = lim / k
    rigid = k_fi <= 0.0
    m_all = m_t + m_b
    xt, vt, xb, vb = x_ref[0], 0.0, x_ref[0], 0.0
    integ, ud, e_prev = 0.0, 0.0, 0.0
    y_out = np.empty(n)
    xt_out = np.empty(n)
    xb_out = np.empty(n)
    h = dt / n_sub
    for t in range(n):
        xm = xt if q <= 0.0 else q * math.floor(xt / q + 0.5)
        e = x_ref[t] - xm
        if t == 0:
            e_prev = e
        ud = (ud + kd * wd * (e - e_prev)) / (1.0 + wd * dt)
        integ += ki * dt * e
        u = kp * e + integ + ud
        e_prev = e
        y_out[t] = xm
        xt_out[t] = xt
        xb_out[t] = xb
        for _ in range(n_sub):
            F = 0.0
            for i in range(nb):
                F += f[i]
            if rigid:
                vt += h * (u - F) / m_all
                dxb = h * vt
                xt += dxb
                xb = xt
            else:
                f_fi = k_fi * (xt - xb) + c_fi * (vt - vb)
                vt += h * (u - f_fi) / m_t
                vb += h * (f_fi - F) / m_b
                xt += h * vt
                dxb = h * vb
                xb += dxb
            for i in range(nb):
                f[i], theta[i] = slider_step(f[i], theta[i], dxb, k[i], lim[i], ell[i], a, b, v_r, h)
    return y_out, xt_out, xb_out


def _settling(t, y, ref):
    """Settling time [s] of every settle segment of ``ref`` (nan if not settled by its end)."""
    out = []
    for s in ref.select("settle"):
        t0, t1 = t[s.start], t[s.stop - 1]
        out.append(float(settling_time(t, y, s.target, t0, WINDOW, t1)))
    return np.array(out)


def _standalone(ref, a, preset, v_r, b=0.0, theta0=THETA0):
    m_t, m_b, k_fi, c_fi, (kp, ki, kd, wd), (k, alpha, f_c), dt, q = stage(preset)
    y, _, xb = closed_loop(ref.x, m_t, m_b, k_fi, c_fi, kp, ki, kd, wd, dt, q, k, alpha * f_c, a, v_r,
                           N_SUB, b, theta0)
    return _settling(ref.t, y, ref), xb


def standalone_sequence(step, a, n_forward=8, n_backward=8, dwell=DWELL, v_r=V_R, preset=PRESET, b=0.0,
                        theta0=THETA0):
    """Settling time [s] per step of the App. C.1 sequence on the standalone loop."""
    ref = step_sequence(step, n_forward, n_backward, dwell=dwell, shape="triangular")
    return _standalone(ref, a, preset, v_r, b, theta0)[0]


def standalone_single(step, a, dwell=DWELL, v_r=V_R, preset=PRESET, b=0.0, theta0=THETA0):
    """Settling time [s] of one move from the virgin state on the standalone loop."""
    ref = point_to_point(step, dwell=dwell, shape="triangular")
    return float(_standalone(ref, a, preset, v_r, b, theta0)[0][0])


def rate_state_overrides(a=None):
    """Preset overrides that give both bearings the simulator's ``gms_rate_state`` law, as the
    campaign ``table_4_2_aging`` (its home, with the value's derivation); ``a`` replaces its ``a``.
    Only the law's own fields: the campaign's other overrides (the main job's gross-motion viscous
    friction) are not part of the law."""
    law = ("friction.model", "friction.a", "friction.b", "friction.v_r", "friction.theta0")
    ov = {k: v for k, v in load_campaign("table_4_2_aging", check_presets=False).overrides.items()
          if k.endswith(law)}
    if a is not None:
        ov.update({k: a for k in ov if k.endswith("friction.a")})
    return ov


def engine_sequence(step, n_forward=8, n_backward=8, dwell=DWELL, preset=PRESET, overrides=None):
    """Settling time [s] per step of the sequence on the engine (preset, drive noise off, then
    ``overrides``, e.g. :func:`rate_state_overrides`)."""
    p = with_overrides(load_preset(preset), {"stage.drive.noise_current_rms": 0.0, **(overrides or {})})
    ref = step_sequence(step, n_forward, n_backward, dwell=dwell, shape="triangular")
    r = simulate(p, ref.x, ref.v, x0=0.0)
    return _settling(r.t, r.y[0], ref)


def saturated_force(x, k=None, alpha=None, f_c=None):
    """Force [N] carried by fully slipped blocks on the virgin curve after a displacement ``x`` [m]."""
    if k is None:
        _, _, _, _, _, (k, alpha, f_c), _, _ = stage()
    lim = alpha * f_c
    return float(lim[k * x >= lim].sum())


MODELS = {"GMS (seed, a = 0)": (0.0, 0.0), "creep only (a = 0.02, b = 0)": (0.02, 0.0),
          "rate-and-state (a = b = 0.02)": (0.02, 0.02)}


def study(models=MODELS):
    """The App. C.1 / Table 4.2 numbers of each model (settling times [s]).

    Per model: the 5 µm and 50 µm sequences (8 forward, 8 back) and a 5 mm move, No FI and FI."""
    out = {}
    for name, (a, b) in models.items():
        row = {}
        for label, preset in (("nofi", PRESET), ("fi", PRESET_FI)):
            row[f"{label}_5um"] = standalone_sequence(5e-6, a, b=b, preset=preset)
            row[f"{label}_50um"] = standalone_sequence(5e-5, a, b=b, preset=preset)
            row[f"{label}_5mm"] = standalone_single(5e-3, a, b=b, preset=preset)
        out[name] = row
    return out


PREV_MOVES = (5e-3, -5e-3)          # the move that brought the stage to its "random position"


def history(step, a, b=None, preset=PRESET, prev_moves=PREV_MOVES, dwell=DWELL):
    """Settling time [s] of ``step`` after each previous move in ``prev_moves`` [m] (and its dwell).

    Table 4.2's trials start "at random positions of the table", i.e. after a move of unknown
    size and direction; with a rate-dependent slider the direction matters (b defaults to a)."""
    b = a if b is None else b
    out = []
    for p in prev_moves:
        ref = _two_moves(p, step, dwell)
        out.append(_standalone(ref, a, preset, V_R, b)[0][1])
    return np.array(out)


def _two_moves(first, second, dwell):
    return steps_reference([first, second], 0.0, 0.005, dwell, DT, None, "triangular")


def _fmt(s):
    return "  ".join("  -  " if not np.isfinite(v) else f"{v * 1e3:5.1f}" for v in s)


def _summary(row):
    s5, s50, f5, f50 = row["nofi_5um"], row["nofi_50um"], row["fi_5um"], row["fi_50um"]
    return (f"No FI 5 µm {s5[0] * 1e3:.1f} → {s5[7] * 1e3:.1f} ms (mean16 {np.nanmean(s5) * 1e3:.1f}), "
            f"50 µm {s50[0] * 1e3:.0f} → {s50[7] * 1e3:.0f}, 5 mm {row['nofi_5mm'] * 1e3:.1f}; "
            f"FI 5 µm {f5[0] * 1e3:.1f} → {f5[7] * 1e3:.1f} (mean16 {np.nanmean(f5) * 1e3:.1f}), "
            f"50 µm {f50[0] * 1e3:.0f} → {f50[7] * 1e3:.0f}, 5 mm {row['fi_5mm'] * 1e3:.1f}")


if __name__ == "__main__":                      # python -m experiment_runner.apps.paper.micro
    print("force in slipped blocks after n x 5 µm (virgin curve):",
          ", ".join(f"{saturated_force(n * 5e-6):.2f}" for n in range(1, 9)), "N")
    for name, row in study().items():
        print(f"{name}: {_summary(row)}")
        for key, v in row.items():
            if np.ndim(v):
                print(f"    {key:10s} {_fmt(v)}")
    for name, (a, b) in MODELS.items():
        h5, h5m = history(5e-6, a, b), history(5e-3, a, b)
        print(f"{name}, after a +5 mm / -5 mm move: No FI 5 µm {h5[0] * 1e3:.1f} / {h5[1] * 1e3:.1f} ms "
              f"(mean {h5.mean() * 1e3:.1f}; Table 4.2: 62), 5 mm {h5m[0] * 1e3:.1f} / {h5m[1] * 1e3:.1f} ms "
              f"(Table 4.2: 44)")
    eng = engine_sequence(5e-6, overrides=rate_state_overrides())
    print(f"simulator, law gms_rate_state (campaign table_4_2_aging): No FI 5 µm {_fmt(eng)} "
          f"(mean16 {np.nanmean(eng) * 1e3:.1f})")
    print("seed: No FI 5 µm 47.8 → 85 ms (mean16 69.1), 50 µm 237 → 214, 5 mm 44 (Table 4.2); "
          "FI 5 µm 10.5 → 10.2 (mean16 10.3), 50 µm 43.6 → 453, 5 mm 16 (Table 4.2)")
