"""Locate: where the model and the recording disagree.

All views use the force residual ``r`` of the model (:class:`.predict.Observer`) and the
same residual of a recording simulated from the model (the *floor*: what a perfect model
leaves), low-passed at ``f_band`` (zero phase) unless said otherwise:

* **regime** (:func:`regimes`): each sample is labelled from the reference and the
  measured motion -- ``reversal`` (low speed around a change of direction),
  ``acceleration``, ``constant_velocity``, ``settling`` (the first ``t_settle`` after the
  reference stops) and ``in_position`` (at rest after that); per regime the RMS residual,
  the RMS floor, and the share of the residual energy (and of the excess over the floor);
* **time** (:func:`segments`): fixed blocks ranked by their excess energy;
* **frequency** (:func:`spectrum`): residual spectrum against the floor spectrum in
  bands, with peaks and narrow lines above the floor;
* **state** (:func:`state_bins`): the residual binned against position, velocity,
  acceleration, command and displacement since the last reversal; the share of residual
  energy a function of that variable alone explains (R^2 of the bin means), and a
  periodogram of the residual against position (ripple periods).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import signal

from experiment_runner.core.metrics import welch_csd

from .context import Context
from .frf import drive_frf, locate_modes, loop_from_excitation, noise_band_modes, psd_trials, transfer_ratio
from .judge import ReplayJudge
from .predict import taper
from .replay_floor import noise_free

__all__ = ["REGIMES", "regimes", "by_regime", "locate", "lowpass", "proposals", "PROPOSAL_KEYS", "transfer_modes",
           "noise_spectrum_modes"]

REGIMES = ("in_position", "settling", "reversal", "acceleration", "constant_velocity")


def lowpass(r: np.ndarray, mask: np.ndarray, rate: float, f_hi: float) -> np.ndarray:
    """The residual ``r`` (T, B) low-passed at ``f_hi`` [Hz] (zero phase, 2nd order) on ``mask``, zero elsewhere.

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) residual.
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    f_hi : float
        Cutoff [Hz].

    Returns
    -------
    numpy.ndarray
    """
    sos = signal.butter(2, min(0.95, 2 * f_hi / rate), output="sos")
    return np.where(mask, signal.sosfiltfilt(sos, taper(r, mask), axis=0), 0.0)


def regimes(x_ref, v_ref, valid, rate: float, t_settle: float = 0.02) -> np.ndarray:
    """Regime index per sample (T, B) into :data:`REGIMES` (-1 = padding).

    From the reference: at rest -> ``settling`` for ``t_settle`` after motion stops, else
    ``in_position``; below 10 % of the peak speed between motions of opposite direction
    -> ``reversal``; otherwise ``acceleration`` if |a_ref| > 30 % of its peak, else
    ``constant_velocity``.

    Parameters
    ----------
    x_ref, v_ref : numpy.ndarray
        (T, B) reference [m], [m/s].
    valid : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    t_settle : float, optional
        Seconds after a stop counted as settling.

    Returns
    -------
    numpy.ndarray
    """
    T, B = v_ref.shape
    lab = np.full((T, B), -1, int)
    n_settle = int(round(t_settle * rate))
    for b in range(B):
        n = int(valid[:, b].sum())
        if n == 0:
            continue
        v = v_ref[:n, b]
        a = np.gradient(v) * rate if n > 1 else np.zeros(n)
        vmax = float(np.max(np.abs(v)))
        amax = float(np.max(np.abs(a)))
        if vmax <= 0:
            lab[:n, b] = 0
            continue
        rest = np.abs(v) <= 1e-9 * vmax
        out = np.where(np.abs(a) > 0.3 * amax, 3, 4)
        low = (np.abs(v) < 0.1 * vmax) & ~rest
        k = 0
        while k < n:                      # low-speed runs between opposite directions
            if not low[k]:
                k += 1
                continue
            j = k
            while j < n and low[j]:
                j += 1
            before = np.sign(v[k - 1]) if k > 0 and not rest[k - 1] else 0.0
            after = np.sign(v[j]) if j < n and not rest[j] else 0.0
            if before != 0 and after != 0 and before != after:
                out[k:j] = 2
            k = j
        last_move = -10 ** 9
        for k in range(n):
            if not rest[k]:
                last_move = k
            else:
                out[k] = 1 if k - last_move <= n_settle else 0
        lab[:n, b] = out
    return lab


def _share(e, tot):
    return float(e / tot) if tot > 0 else 0.0


def by_regime(r: np.ndarray, mask: np.ndarray, lab: np.ndarray, min_samples: int = 1,
              floor: np.ndarray | None = None, floor_mask: np.ndarray | None = None) -> list[dict]:
    """Where a residual's energy lies by motion regime: one row per regime of :data:`REGIMES` with at
    least ``min_samples`` samples on ``mask``, in that order.

    Each row is ``{regime, samples, time_share, rms_N, energy_share}``: the regime's samples, their
    share of ``mask``'s, the residual's RMS there and the regime's share of the residual's energy
    on ``mask``. With a ``floor`` (the same residual of a recording simulated from the model, on
    ``floor_mask``) a row also has ``floor_rms_N`` (the floor's energy in the regime scaled to the
    regime's sample count) and ``excess_share`` (the regime's share of the energy above the floor,
    summed over the listed regimes), after ``rms_N``.

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) residual [N].
    mask : numpy.ndarray
        (T, B) bool: the samples examined.
    lab : numpy.ndarray
        (T, B) regime index per sample (:func:`regimes`).
    min_samples : int, optional
        Fewest samples of a regime listed.
    floor : numpy.ndarray, optional
        (T', B') the floor's residual [N].
    floor_mask : numpy.ndarray, optional
        (T', B') bool, its samples examined; labelled by ``lab`` too.

    Returns
    -------
    list of dict

    Examples
    --------
    >>> import numpy as np
    >>> r = np.array([[1.0], [1.0], [3.0], [3.0]])
    >>> lab = np.array([[0], [0], [4], [4]])
    >>> rows = by_regime(r, np.ones_like(r, bool), lab)
    >>> [(g["regime"], g["time_share"], g["rms_N"], g["energy_share"]) for g in rows]
    [('in_position', 0.5, 1.0, 0.1), ('constant_velocity', 0.5, 3.0, 0.9)]
    """
    tot = float(np.sum(r[mask] ** 2)) or 1e-300
    n_all = mask.sum()
    rows = []
    tot_ex = 0.0
    for i, name in enumerate(REGIMES):
        m = mask & (lab == i)
        n = m.sum()
        if n < max(1, min_samples):
            continue
        e = float(np.sum(r[m] ** 2))
        row = {"regime": name, "samples": int(n), "time_share": _share(n, n_all), "rms_N": float(np.sqrt(e / n))}
        if floor is not None:
            mf = floor_mask & (lab == i)
            ef = float(np.sum(floor[mf] ** 2)) * n / max(1, mf.sum())
            row["floor_rms_N"] = float(np.sqrt(ef / n))
            row["excess_energy"] = max(0.0, e - ef)
            tot_ex += row["excess_energy"]
        row["energy_share"] = _share(e, tot)
        rows.append(row)
    if floor is not None:
        for row in rows:
            row["excess_share"] = _share(row.pop("excess_energy"), tot_ex)
    return rows


def segments(rl, fl, mask, rate, block: float = 0.05, top: int = 8, lab=None, t0=None, trial_ids=None):
    """Time blocks ranked by excess residual energy (measured minus floor).

    Parameters
    ----------
    rl, fl : numpy.ndarray
        (T, B) low-passed residual of the data and of the floor [N].
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    block : float, optional
        Block length [s].
    top : int, optional
        Blocks listed.
    lab : numpy.ndarray, optional
        Regime per sample (:func:`regimes`).
    t0 : numpy.ndarray, optional
        Trial start times [s].
    trial_ids : list of int, optional
        Trial numbers.

    Returns
    -------
    rows : list of dict
        The ``top`` blocks, largest excess first.
    n : int
        Blocks examined.
    """
    T, B = rl.shape
    nb = max(1, int(round(block * rate)))
    rows = []
    tot_ex = 0.0
    for b in range(B):
        for s in range(0, T, nb):
            m = mask[s:s + nb, b]
            if m.sum() < nb // 4:
                continue
            e = float(np.sum(rl[s:s + nb, b][m] ** 2))
            f = float(np.sum(fl[s:s + nb, b][m] ** 2)) if fl is not None else 0.0
            ex = max(0.0, e - f)
            tot_ex += ex
            dom = None
            if lab is not None:
                ll = lab[s:s + nb, b][m]
                if len(ll):
                    dom = REGIMES[int(np.bincount(ll[ll >= 0], minlength=len(REGIMES)).argmax())]
            rows.append({"trial": int(trial_ids[b]) if trial_ids is not None else b,
                         "t_start_s": float((t0[b] if t0 is not None else 0.0) + s / rate),
                         "t_end_s": float((t0[b] if t0 is not None else 0.0) + min(s + nb, T) / rate),
                         "rms_N": float(np.sqrt(e / m.sum())), "floor_rms_N": float(np.sqrt(f / m.sum())),
                         "excess_energy": ex, "regime": dom})
    rows.sort(key=lambda r: -r["excess_energy"])
    for r in rows:
        r["excess_share"] = _share(r.pop("excess_energy"), tot_ex)
    return rows[:top], len(rows)


LINE_RATIO_ABOVE_BAND = 100.0
"""Residual / floor PSD ratio a spectral peak above the observer bandwidth needs to count."""


def spectrum(r, r_floor, mask, mask_floor, rate, f_obs, nperseg: int = 1024):
    """Residual PSD vs floor PSD: bands, peaks and narrow lines.

    Parameters
    ----------
    r, r_floor : numpy.ndarray
        (T, B) residual of the data and of the floor [N].
    mask, mask_floor : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    f_obs : float
        Observer bandwidth [Hz].
    nperseg : int, optional
        Welch segment length.

    Returns
    -------
    dict
    """
    def psd(x, m):
        out = []
        for b in range(x.shape[1]):
            mm = m[:, b]
            if mm.sum() < 64:
                continue
            f, p = welch_csd(x[mm, b], fs=rate, nperseg=min(nperseg, int(mm.sum())))
            out.append(np.interp(np.linspace(0, rate / 2, nperseg // 2 + 1), f, p))
        return np.mean(out, axis=0) if out else np.zeros(nperseg // 2 + 1)
    f = np.linspace(0, rate / 2, nperseg // 2 + 1)
    pm, pf = psd(r, mask), psd(r_floor, mask_floor)
    df = f[1] - f[0]
    edges = [e for e in (0, 1, 3, 10, 30, 100, 300, 1000, 3000, 10000, 30000) if e < rate / 2] + [rate / 2]
    bands = []
    tot_ex = float(np.sum(np.maximum(pm - pf, 0)) * df)
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (f >= lo) & (f < hi) if hi < rate / 2 else (f >= lo)
        if not sel.any():
            continue
        Pm, Pf = float(np.sum(pm[sel]) * df), float(np.sum(pf[sel]) * df)
        bands.append({"f_lo_hz": float(lo), "f_hi_hz": float(hi), "rms_N": float(np.sqrt(Pm)),
                      "floor_rms_N": float(np.sqrt(Pf)), "ratio": float(Pm / Pf) if Pf > 0 else None,
                      "excess_share": _share(max(0.0, Pm - Pf), tot_ex), "above_observer_bandwidth": bool(lo >= f_obs)})
    ratio = pm / np.maximum(pf, 1e-300)
    peaks = []
    lines = []
    for i in range(2, len(f) - 1):
        # above the observer bandwidth the force estimate is attenuated and its floor uncertain:
        # only lines far above the floor count there (a dither imbalance at 500 Hz)
        above = f[i] > f_obs
        if ratio[i] > (LINE_RATIO_ABOVE_BAND if above else 10) and pm[i] >= pm[i - 1] and pm[i] >= pm[i + 1]:
            # width: neighbouring bins above half the peak level
            j0 = i
            while j0 > 0 and pm[j0 - 1] > 0.5 * pm[i]:
                j0 -= 1
            j1 = i
            while j1 < len(f) - 1 and pm[j1 + 1] > 0.5 * pm[i]:
                j1 += 1
            # parabolic interpolation of the peak frequency
            a, b_, c = np.log(pm[i - 1] + 1e-300), np.log(pm[i] + 1e-300), np.log(pm[i + 1] + 1e-300)
            den = a - 2 * b_ + c
            off = 0.5 * (a - c) / den if den < 0 else 0.0
            fpk = float(f[i] + off * df)
            peaks.append({"f_hz": fpk, "ratio": float(ratio[i]), "excess_N2": float((pm[i] - pf[i]) * df),
                          "width_bins": int(j1 - j0 + 1)})
    peaks.sort(key=lambda p: -p["excess_N2"])
    for p in peaks:
        if p["width_bins"] <= 3 and p["ratio"] > 30:
            lines.append(p["f_hz"])
    return {"f_hz": f, "psd": pm, "psd_floor": pf, "bands": bands, "peaks": peaks[:8], "lines_hz": lines[:4]}


def _reversal_displacement(x, v, valid, v_dead):
    """Displacement since the last change of direction, signed positive along the motion."""
    s = np.zeros_like(x)
    for b in range(x.shape[1]):
        n = int(valid[:, b].sum())
        d = 0.0
        xr = x[0, b]
        for k in range(n):
            vk = v[k, b]
            if vk > v_dead and d <= 0:
                d, xr = 1.0, x[k, b] if d < 0 else xr
            elif vk < -v_dead and d >= 0:
                d, xr = -1.0, x[k, b] if d > 0 else xr
            s[k, b] = (x[k, b] - xr) * (d if d != 0 else 1.0)
    return s


def state_bins(rl, mask, variables: dict, n_bins: int = 16):
    """Per variable: bin centres, mean residual per bin, counts, explained share (R^2).

    Parameters
    ----------
    rl : numpy.ndarray
        (T, B) low-passed residual [N].
    mask : numpy.ndarray
        (T, B) bool.
    variables : dict
        Name -> (T, B) state variable.
    n_bins : int, optional
        Bins per variable.

    Returns
    -------
    dict
    """
    out = {}
    r = rl[mask]
    tot = float(np.sum(r ** 2)) or 1e-300
    for name, x in variables.items():
        xv = x[mask]
        if len(xv) < 4 * n_bins or np.ptp(xv) <= 0:
            continue
        edges = np.unique(np.quantile(xv, np.linspace(0, 1, n_bins + 1)))
        if len(edges) < 3:
            continue
        idx = np.clip(np.searchsorted(edges, xv, "right") - 1, 0, len(edges) - 2)
        cnt = np.bincount(idx, minlength=len(edges) - 1)
        sm = np.bincount(idx, weights=r, minlength=len(edges) - 1)
        mean = sm / np.maximum(cnt, 1)
        centres = np.bincount(idx, weights=xv, minlength=len(edges) - 1) / np.maximum(cnt, 1)
        expl = float(np.sum(cnt * mean ** 2) / tot)
        out[name] = {"explained_share": expl, "centres": centres, "mean_N": mean, "count": cnt}
    return out


def _lomb_scargle(x, y, w):
    """Normalised Lomb-Scargle periodogram (0...1) of samples ``y`` at positions ``x`` for
    angular frequencies ``w`` (vectorised; Scargle 1982 with the time shift tau)."""
    wx = np.outer(w, x)
    tau = 0.5 * np.arctan2(np.sin(2 * wx).sum(axis=1), np.cos(2 * wx).sum(axis=1))
    arg = wx - tau[:, None]
    c, s = np.cos(arg), np.sin(arg)
    yc, ys = c @ y, s @ y
    p = 0.5 * (yc ** 2 / np.maximum((c * c).sum(axis=1), 1e-300) + ys ** 2 / np.maximum((s * s).sum(axis=1), 1e-300))
    return p / max(0.5 * float(y @ y), 1e-300)


def ripple_periods(x, rl, v, mask, lam_min, lam_max, n: int = 300, top: int = 3):
    """Periods [m] of the strongest periodicity of the residual against position (moving
    samples, after removing the part that only depends on the direction of motion).

    Parameters
    ----------
    x, rl, v : numpy.ndarray
        (T, B) position [m], low-passed residual [N], velocity [m/s].
    mask : numpy.ndarray
        (T, B) bool.
    lam_min, lam_max : float
        Period range searched [m].
    n : int, optional
        Grid points.
    top : int, optional
        Periods returned.

    Returns
    -------
    best : list of float
        The strongest periods [m] (empty when there are too few moving samples).
    info : dict or None
        The scanned ``period_m`` grid and its ``power``.
    """
    if not (lam_max > lam_min > 0):
        return [], None
    vm = np.max(np.abs(v[mask])) if mask.any() else 0.0
    sel = mask & (np.abs(v) > 0.05 * vm)
    if sel.sum() < 200:
        return [], None
    xs, rs, ss = x[sel], rl[sel], np.sign(v[sel])
    for s in (-1.0, 1.0):
        m = ss == s
        if m.any():
            rs = rs.copy()
            rs[m] -= np.mean(rs[m])
    step = max(1, len(xs) // 6000)
    xs, rs = xs[::step], rs[::step]
    lam = np.logspace(np.log10(lam_min), np.log10(lam_max), n)
    p = _lomb_scargle(xs - xs.mean(), rs, 2 * np.pi / lam)
    order = []
    for i in np.argsort(-p):
        if all(abs(np.log(lam[i] / lam[j])) > 0.15 for j in order):
            order.append(i)
        if len(order) >= top:
            break
    # each peak refined on a fine grid over its whole neighbourhood (the same +-15 % that separates
    # peaks): trials at separate positions make the periodogram a comb of side lobes spaced by
    # lam/span (span: the whole range of recorded positions) under the envelope of one stroke, so the
    # coarse grid lands on any tooth; the fine grid's spacing lam/(4 span) leaves a phase drift of
    # at most pi/2 over the span, and the highest tooth is the coherent period
    xc = xs - xs.mean()
    span = max(float(np.ptp(xs)), 1e-12)
    best = []
    for i in order:
        lo, hi = lam[i] * np.exp(-0.15), lam[i] * np.exp(0.15)
        m_f = int(np.clip(0.3 / (lam[i] / (4 * span)), 41, 4000))
        fine = np.logspace(np.log10(max(lo, lam_min)), np.log10(min(hi, lam_max)), m_f)
        pf = np.concatenate([_lomb_scargle(xc, rs, 2 * np.pi / fine[k:k + 256]) for k in range(0, m_f, 256)])
        best.append(float(fine[int(np.argmax(pf))]))
    return best, {"period_m": lam, "power": p}


def locate(data, res, res_floor, floor_data, f_obs: float, f_band: float | None = None) -> tuple[dict, dict, Context]:
    """All views; returns (summary for the report, arrays for plots, the recording's :class:`.context.Context`
    for the effects).

    Parameters
    ----------
    data : DiagData
        The recording.
    res : ObsResult
        The model's force observer on it.
    res_floor : ObsResult
        The same on a simulated recording (the floor).
    floor_data : DiagData
        That recording.
    f_obs : float
        Observer bandwidth [Hz].
    f_band : float, optional
        Low-pass of the views [Hz].

    Returns
    -------
    tuple
    """
    rate = data.rate
    f_band = f_band or f_obs / 2
    mask = data.valid.copy()
    burn = (data.fit | data.held)
    mask &= burn
    rl = lowpass(res.r, mask, rate, f_band)
    mfl = floor_data.fit | floor_data.held
    fl = lowpass(res_floor.r, mfl, rate, f_band)
    lab = regimes(data.x_ref, data.v_ref, data.valid, rate)
    tot = float(np.sum(rl[mask] ** 2)) or 1e-300
    tot_f = float(np.sum(fl[mfl] ** 2))
    reg = by_regime(rl, mask, lab, floor=fl, floor_mask=mfl)
    segs, n_blocks = segments(rl, fl, mask, rate, lab=lab, t0=data.t0, trial_ids=data.trial_ids)
    n_typ = int(np.median(mask.sum(axis=0))) if mask.any() else 1024
    nper = int(2 ** np.clip(np.floor(np.log2(max(n_typ, 256))), 8, 14))
    spec = spectrum(res.r, res_floor.r, mask, mfl, rate, f_obs, nperseg=nper)
    spec["nperseg"] = nper
    # state variables (observer trajectory ~ measured)
    acc = np.gradient(data.vs, axis=0) * rate
    acc = lowpass(acc, data.valid, rate, f_band)
    vmax = float(np.max(np.abs(data.vs[mask]))) if mask.any() else 0.0
    disp = _reversal_displacement(res.x, data.vs, data.valid, 0.01 * vmax)
    variables = {"position": res.x, "velocity": data.vs, "acceleration": acc, "command": data.u,
                 "displacement_since_reversal": disp}
    st = state_bins(rl, mask, variables)
    # per-trial strokes, for the ripple search range and the pre-motion scale
    strokes = [float(np.ptp(data.y[data.valid[:, b], b])) for b in range(data.shape[1])]
    lam_max = 0.5 * float(np.median(strokes)) if strokes else 0.0
    # shortest period the observer's band shows: at the slower quarter of the moving samples (a ripple
    # too fast for the band at full speed is seen near reversals and at the ends of moves)
    moving = np.abs(data.vs[mask])
    moving = moving[moving > 0.05 * vmax]
    v_slow = float(np.quantile(moving, 0.25)) if len(moving) else vmax
    lam_min = max(2 * v_slow / max(f_band, 1e-9), 1e-7)
    periods, pgram = ripple_periods(res.x, rl, data.vs, mask, lam_min, lam_max)
    xs = res.x[mask]
    ctx = Context(u_max=float(np.max(np.abs(data.u[data.valid]))), v_max=vmax,
                  x_span=float(np.ptp(xs)) if len(xs) else 1e-3,
                  x_center=float(0.5 * (xs.max() + xs.min())) if len(xs) else 0.0,
                  x_half_span=float(0.5 * np.ptp(xs)) if len(xs) else 1e-3,
                  r_rms=float(np.sqrt(tot / max(1, mask.sum()))),
                  peak_hz=tuple(p["f_hz"] for p in spec["peaks"] if p["f_hz"] > 2.0),
                  line_hz=tuple(spec["lines_hz"]), ripple_period=tuple(periods),
                  stroke=float(np.median(strokes)) if strokes else 0.0, axis=data.axis or "linear")
    summary = {
        "f_band_hz": f_band,
        "residual_rms_N": ctx.r_rms,
        "floor_rms_N": float(np.sqrt(tot_f / max(1, mfl.sum()))),
        "regimes": reg,
        "segments": segs, "segments_total": n_blocks,
        "bands": spec["bands"], "peaks": spec["peaks"], "lines_hz": spec["lines_hz"],
        "state": {k: {"explained_share": v["explained_share"]} for k, v in st.items()},
        "ripple_periods_m": periods,
    }
    arrays = {"rl": rl, "fl": fl, "mask": mask, "labels": lab, "spectrum": spec, "state": st,
              "periodogram": pgram, "variables": variables}
    return summary, arrays, ctx


PROPOSAL_KEYS = ("ripple_period", "peak_hz", "line_hz")
"""The context's entries located again in what an adopted model leaves (:func:`proposals`)."""


def proposals(data, res, res_floor, floor_data, f_obs: float, f_band: float, ctx: Context) -> dict:
    """The context's proposal entries (:data:`PROPOSAL_KEYS`) from the force residual ``res`` of the
    current model (its floor's residual ``res_floor`` on the simulated recording ``floor_data``): new
    findings first, then the earlier ones of ``ctx`` not within 15 % of them (at most three periods;
    peaks and lines as located). Empty when the residual cannot be located (the earlier proposals stay).

    Parameters
    ----------
    data : DiagData
        The recording.
    res : ObsResult
        The current model's force observer.
    res_floor : ObsResult
        Its floor's.
    floor_data : DiagData
        The floor's simulated recording.
    f_obs : float
        Observer bandwidth [Hz].
    f_band : float
        Low-pass of the views [Hz].
    ctx : Context
        The context so far.

    Returns
    -------
    dict
    """
    try:
        _, _, c = locate(data, res, res_floor, floor_data, f_obs, f_band)
    except Exception:     # noqa: BLE001 - the earlier proposals stay
        return {}
    out = {}
    for k in PROPOSAL_KEYS:
        new = list(getattr(c, k))
        old = [v for v in getattr(ctx, k) if all(abs(math.log(v / w)) > 0.15 for w in new if v > 0 and w > 0)]
        out[k] = tuple((new + old)[:3] if k == "ripple_period" else new + old)
    return out


EXCITATION_RUNS = 4
"""Noise-free runs of the model under a known white table force that measure its closed loop
(:func:`.frf.loop_from_excitation`)."""


def noise_spectrum_modes(spec, data) -> tuple[list, dict]:
    """Modes located in the noise response of a closed-loop record (:func:`.frf.noise_band_modes`):
    the recorded command's departure from ``spec``'s noise-free replay against the same of
    ``spec``'s simulated recordings (the replay judge's fixed seeds, every trial), through the
    model's closed loop measured under a known white force of the drive noise's RMS. Returns
    ``(modes, info)``; nothing on an open-loop record or a model without drive noise (its
    simulated recordings would have no spread to compare with).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        A closed-loop record.

    Returns
    -------
    tuple
        ``(modes, diagnostics)``.
    """
    if data.open_loop:
        return [], {"why": "open-loop record (the transfer is measured directly)"}
    sig = float(spec.compiled().pm_full.noise_std)
    if not sig > 0:
        return [], {"why": "the model has no drive noise: its simulated recordings give no noise spectrum"}
    allv = dataclasses.replace(data, held=data.valid.copy())
    j = ReplayJudge(allv)
    rp = j.replay(spec)
    if not rp.ok:
        return [], {"why": f"the model's replay is unstable ({rp.why})"}
    rate = data.rate
    n_min = int(min(data.lengths[c] for c in j.cols))
    nps = int(2 ** max(6, math.floor(math.log2(max(64, min(n_min // 12, rate / 5))))))
    u_k, _, status, _ = j.simulate_recordings(spec, j.seeds)
    good = np.all(status == 0, axis=1)
    if good.sum() < 4:
        return [], {"why": "the model's simulated recordings diverged"}
    cols = np.tile(j.cols, EXCITATION_RUNS)
    dx = allv.subset(cols)
    rng = np.random.default_rng(20251)
    exc = rng.normal(0.0, sig, dx.shape) * dx.valid
    dx.f_ext = dx.known_force() + exc
    jx = ReplayJudge(dx)
    ux, _, sx, _ = jx.simulate_recordings(noise_free(spec), [0])
    mask = j.mask
    du = ux[0] - np.tile(rp.u, (1, EXCITATION_RUNS))
    mx = np.tile(mask, (1, EXCITATION_RUNS)) & (sx[0] == 0)[None, :]
    f = np.fft.rfftfreq(nps, 1.0 / rate)
    D = drive_frf(spec, f)
    X = loop_from_excitation(exc[:, jx.cols], du, mx, rate, nps, D)
    S_d = psd_trials(j.u - rp.u, mask, rate, nps)
    S_k = np.array([psd_trials(u_k[k] - rp.u, mask, rate, nps) for k in range(len(u_k)) if good[k]])
    S_det = psd_trials(rp.u, mask, rate, nps)
    modes, info = noise_band_modes(f, S_d, S_k, S_det, X, D, rate)
    info["nperseg"] = nps
    return modes, info


def transfer_modes(spec, data) -> tuple[list, dict]:
    """Modes of ``data`` against model ``spec``: narrow features of the measured transfer
    (:func:`.frf.locate_modes`, by instrument variables) and, on a closed-loop record, of the noise
    response (:func:`noise_spectrum_modes`) not within 15 % of one of them. Returns ``(modes,
    info)``: ``info`` holds the transfer's instruments and the noise spectrum's examined bands.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.

    Returns
    -------
    tuple
        ``(modes, diagnostics)``.
    """
    est = transfer_ratio(spec, data)
    modes = list(locate_modes(spec, data, est=est)) if est is not None else []
    info: dict = {}
    if est is not None:
        info["instruments"] = sorted(set(est[3].tolist()))
    nb, nb_info = noise_spectrum_modes(spec, data)
    info["noise_spectrum"] = nb_info
    for m in nb:
        if all(abs(math.log(m["f_hz"] / o["f_hz"])) > 0.15 for o in modes):
            modes.append(m)
    return modes, info
