"""What the improved model leaves: the largest signatures of its remaining force residual.

When the improved model's held-out replay is still beyond its run-to-run floor the diagnosis does
not stop silently: :func:`remaining` describes the residual the selection could not explain, each
signature as numbers with its share of the residual's mean square (held-out samples, band-limited
like the rest of the diagnosis):

- **lines in time**: narrow peaks of the residual's spectrum at least 10 dB above the spectrum's
  running median (frequency, sinusoid amplitude, share, and the motion regime where the line is
  strongest);
- **periodic in position**: the sinusoid of the measured position of the largest explained share
  (period, amplitude; at least three periods along the stroke), e.g. a motor revolution or a
  magnet pitch;
- **a level along the stroke**: the straight line in position (slope, share);
- **by regime**: the residual's RMS and energy share per motion regime
  (:func:`.locate.by_regime`, as the locate stage has them).

These are *located, not explained*: no library effect was adopted for them. Modes of the
transfer are in ``locate.frf_modes``.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import signal

from .frf import psd_trials
from .locate import by_regime, lowpass, regimes
from .units import axis_units

__all__ = ["remaining", "LINE_PROMINENCE_DB", "MIN_SHARE"]

LINE_PROMINENCE_DB = 10.0
"""A spectral line stands this far above the residual spectrum's running median."""

MIN_SHARE = 0.1
"""Smallest share of the residual's mean square for a position signature to be listed."""


def _lines(r, held, rate, lab, max_lines: int = 3) -> tuple[list, dict]:
    n_min = int(min(held[:, b].sum() for b in range(held.shape[1]) if held[:, b].any()))
    nps = int(2 ** max(6, math.floor(math.log2(max(64, min(n_min // 4, 8192))))))
    P = psd_trials(r, held, rate, nps)
    f = np.fft.rfftfreq(nps, 1.0 / rate)
    df = f[1] - f[0]
    total = float(np.sum(P) * df)
    if not total > 0:
        return [], {"f_hz": f, "psd": P}
    base = signal.medfilt(P, 31)
    prom = P / np.maximum(base, 1e-300)
    peaks, _ = signal.find_peaks(prom, height=10 ** (LINE_PROMINENCE_DB / 10))
    peaks = [int(k) for k in peaks if k > 2]
    out = []
    for k in sorted(peaks, key=lambda k: -(P[k] - base[k]))[:max_lines]:
        sl = slice(max(1, k - 2), min(len(P), k + 3))
        power = float(np.sum(np.maximum(P[sl] - base[sl], 0.0)) * df)
        fk = float(np.sum(f[sl] * P[sl]) / np.sum(P[sl]))
        row = {"f_hz": fk, "amplitude_N": math.sqrt(2 * power), "share": power / total,
               "prominence_db": float(10 * math.log10(prom[k]))}
        # where in the motion the line lives: its band-passed RMS per regime
        lo, hi = max(fk - 3 * df, df) / (rate / 2), min(fk + 3 * df, 0.49 * rate) / (rate / 2)
        if lo < hi < 1:
            sos = signal.butter(2, [lo, hi], btype="band", output="sos")
            rb = np.where(held, signal.sosfiltfilt(sos, np.where(held, r, 0.0), axis=0), 0.0)
            rms = {g["regime"]: g["rms_N"] for g in by_regime(rb, held, lab, min_samples=20)}
            if rms:
                row["regime"] = max(rms, key=rms.get)
                row["rms_by_regime_N"] = rms
        out.append(row)
    return out, {"f_hz": f, "psd": P, "lines_hz": [o["f_hz"] for o in out]}


def _position(r, y, held, moving) -> tuple[dict | None, dict | None, dict]:
    sel = held & moving if (held & moving).sum() >= 200 else held
    x, e = y[sel], r[sel]
    if len(x) < 50:
        return None, None, {}
    x = x - np.mean(x)
    ms = float(np.mean(e ** 2))
    stroke = float(np.ptp(x))
    if not (ms > 0 and stroke > 0):
        return None, None, {}
    # periodic in position: a sinusoid of the position, at least 3 periods along the stroke, at most
    # one period per 20 distinct positions; fitted together with a level along the stroke (a
    # straight line in position), each credited with what it adds to the other
    dx = np.diff(np.unique(np.round(x / (stroke * 1e-6))))
    n_pos = len(dx) + 1
    p_min = max(stroke / max(n_pos / 20, 3.0), stroke / 2000)
    periods = np.geomspace(stroke / 3, p_min, 300) if stroke / 3 > p_min else np.array([])

    def fit(*cols):
        A = np.column_stack([np.ones_like(x), *cols])
        c, *_ = np.linalg.lstsq(A, e, rcond=None)
        return c, float(np.mean((e - A @ c) ** 2))

    best, scan = None, []
    for p in periods:
        w = 2 * np.pi * x / p
        c, m = fit(x, np.sin(w), np.cos(w))
        scan.append(1 - m / ms)
        if best is None or m < best[1]:
            best = (p, m, c)
    c_line, m_line = fit(x)
    best_out = None
    if best is None:
        level_share = 1 - m_line / ms
        slope = c_line[1]
    else:
        p, m_all, c = best
        w = 2 * np.pi * x / p
        _, m_nox = fit(np.sin(w), np.cos(w))
        level_share, slope = (m_nox - m_all) / ms, c[1]
        best_out = {"period_m": float(p), "amplitude_N": float(math.hypot(c[2], c[3])),
                    "share": float((m_line - m_all) / ms), "periods_on_stroke": float(stroke / p)}
    level = {"slope_N_per_m": float(slope), "change_over_stroke_N": float(slope * stroke), "stroke_m": stroke,
             "share": float(level_share)}
    best = best_out
    return level, best, {"periods_m": periods, "share": np.array(scan)}


def remaining(data, r: np.ndarray, held: np.ndarray, f_band: float, floor_rms: float | None = None) -> dict:
    """The largest remaining signatures of the force residual ``r`` (T, B) [N] on the samples
    ``held`` of ``data`` (module docstring), low-passed at ``f_band`` [Hz] for the position and regime
    views (the lines are read on the full band).

    Returns ``{rms_N, floor_rms_N, ratio, lines, position_periodic, stroke_level, regimes,
    signatures, arrays}``: ``signatures`` the listed ones ordered by share, each ``{kind, text,
    share}`` (the text in the axis' units, :func:`.units.axis_units`; the keys say the linear
    ones); ``arrays`` what the report plots (not written to report.json).

    Examples
    --------
    >>> import numpy as np
    >>> from experiment_runner.apps.diagnosis.data import from_trials
    >>> t = np.arange(20000) / 1e4
    >>> x = 1e-3 * np.sin(2 * np.pi * 0.5 * t)
    >>> d = from_trials(1e4, [0.0], [x], [np.gradient(x) * 1e4], [0 * t], [x])
    >>> r = (0.3 * np.sin(2 * np.pi * 120 * t) + 0.01 * np.random.default_rng(0).normal(size=t.size))[:, None]
    >>> out = remaining(d, r, d.valid, 1000.0)
    >>> round(out["lines"][0]["f_hz"]), round(out["lines"][0]["amplitude_N"], 1)
    (120, 0.3)

    Parameters
    ----------
    data : DiagData
        The recording.
    r : numpy.ndarray
        (T, B) force residual [N].
    held : numpy.ndarray
        (T, B) bool: the samples examined.
    f_band : float
        Low-pass cutoff of the position and regime views [Hz].
    floor_rms : float, optional
        RMS of the model's own floor residual [N] (the ``ratio``'s denominator).

    Returns
    -------
    dict
    """
    U = axis_units(getattr(data, "axis", "linear") or "linear")
    fu, pu = U["force"], U["position"]
    r = np.where(held, np.nan_to_num(r), 0.0)
    rms = float(np.sqrt(np.mean(r[held] ** 2))) if held.any() else 0.0
    out: dict = {"rms_N": rms, "floor_rms_N": floor_rms,
                 "ratio": rms / floor_rms if floor_rms and floor_rms > 0 else None}
    lab = regimes(data.x_ref, data.v_ref, data.valid, data.rate)
    lines, spec = _lines(r, held, data.rate, lab)
    out["lines"] = lines
    rl = lowpass(r, held, data.rate, f_band) if f_band < 0.45 * data.rate else r
    vmax = float(np.max(np.abs(data.v_ref[data.valid]))) if data.valid.any() else 0.0
    moving = np.abs(data.v_ref) > 0.05 * vmax if vmax > 0 else np.zeros_like(held)
    level, periodic, scan = _position(rl, data.y, held, moving)
    out["stroke_level"], out["position_periodic"] = level, periodic
    ms = float(np.mean(rl[held] ** 2)) if held.any() else 0.0
    reg = [{k: g[k] for k in ("regime", "time_share", "rms_N", "energy_share")}
           for g in by_regime(rl, held, lab, min_samples=20)] if ms > 0 else []
    out["regimes"] = reg
    sig = [{"kind": "line in time", "share": ln["share"],
            "text": f"line at {ln['f_hz']:.4g} Hz, amplitude {ln['amplitude_N']:.3g} {fu}"
                    + (f", strongest in {ln['regime']}" if "regime" in ln else "")} for ln in lines]
    if periodic and periodic["share"] >= MIN_SHARE:
        sig.append({"kind": "periodic in position", "share": periodic["share"],
                    "text": f"period {periodic['period_m']:.4g} {pu}, amplitude {periodic['amplitude_N']:.3g} {fu} "
                            f"({periodic['periods_on_stroke']:.3g} periods on the stroke)"})
    if level and level["share"] >= MIN_SHARE:
        sig.append({"kind": "level along the stroke", "share": level["share"],
                    "text": f"{level['change_over_stroke_N']:+.3g} {fu} over the {level['stroke_m']:.3g} {pu} stroke"})
    if reg:
        top = max(reg, key=lambda g: g["energy_share"] - g["time_share"])
        if top["energy_share"] - top["time_share"] >= MIN_SHARE:
            sig.append({"kind": "regime", "share": top["energy_share"],
                        "text": f"{top['regime']}: {100 * top['energy_share']:.0f} % of the residual in "
                                f"{100 * top['time_share']:.0f} % of the time (RMS {top['rms_N']:.3g} {fu})"})
    out["signatures"] = sorted(sig, key=lambda s: -s["share"])
    out["arrays"] = {"spectrum": spec, "position_scan": scan}
    return out
