"""The noise parts' sizes: the position lattice's step and the drive-noise level.

Quantization
    :func:`estimate_lattice`: the step of the lattice the measured positions lie on (the
    smallest spacing many pairs of distinct values share, accepted when nearly every value is an
    integer multiple of it, refined by least squares), or None.
Drive noise
    :func:`noise_components` simulates recordings of the model with drive noise off and at a
    reference level and takes their force residuals' spectra (the quantization-only part and the
    drive-noise part); :func:`fit_noise_level` reads the drive-noise RMS current from the
    measured residual's spectrum in the bands where drive noise dominates the floor (a median of
    summed-power ratios over groups of bands).
"""
from __future__ import annotations

import math

import numpy as np

from experiment_runner.core.metrics import welch_csd

from .data import DiagData
from .model import ModelSpec
from .predict import sim_batch

__all__ = ["estimate_lattice", "noise_components", "fit_noise_level", "SPREAD_MAX"]

SPREAD_MAX = 0.35
"""Largest relative spread of :func:`fit_noise_level`'s group ratios of a level read alike in every
band (a deterministic remnant makes some groups stand out)."""


def estimate_lattice(y: np.ndarray, min_frac: float = 0.995):
    """Quantization step of measured positions, or None if they are not on a lattice.

    The smallest spacing between distinct values is the candidate; it is accepted if
    (nearly) every value is an integer multiple of it from the first value, then refined
    by least squares.

    Parameters
    ----------
    y : numpy.ndarray
        Measured positions [m].
    min_frac : float, optional
        Share of values that must lie on the lattice.

    Returns
    -------
    float or None
        The step [m].
    """
    y = np.asarray(y, float).ravel()
    y = y[np.isfinite(y)]
    if len(y) < 50:
        return None
    u = np.unique(y)
    if len(u) < 3:
        return None
    scale = max(np.max(np.abs(u)), 1e-300)
    du = np.diff(u)
    du = du[du > 1e-12 * scale]
    if not len(du):
        return None
    q1 = float(np.min(du))
    # the minimum could be an outlier: use the smallest spacing that many pairs share
    small = du[du < 1.5 * q1]
    q1 = float(np.median(small))
    n = np.round((u - u[0]) / q1)
    frac = np.abs((u - u[0]) / q1 - n)
    ok = frac < 0.02
    if ok.mean() < min_frac:
        return None
    q = float(np.sum((u - u[0])[ok] * n[ok]) / max(np.sum(n[ok] ** 2), 1e-300))
    return q


def noise_components(spec: ModelSpec, data: DiagData, obs_factory, seeds=(7001,), sigma_ref=None):
    """Force-residual spectra of simulated recordings: quantization-only and drive-noise parts.

    Returns (f, S_q, S_n, sigma_ref): with drive noise sigma, S(f) ~ S_q + (sigma/sigma_ref)^2 S_n.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    obs_factory : callable
        Builds the force observer of a simulated recording.
    seeds : tuple of int, optional
        Noise seeds.
    sigma_ref : float, optional
        Reference drive-noise RMS current [A].

    Returns
    -------
    tuple
    """
    s0 = spec.preset.stage.drive.noise_current_rms
    sigma_ref = sigma_ref or (s0 if s0 > 0 else 1e-3)
    out = []
    for sig in (0.0, sigma_ref):
        sp = spec.with_changes({"stage.drive.noise_current_rms": sig})
        psd = []
        for dd in sim_batch(sp, data, seeds):      # all seeds in one batch call
            ob = obs_factory(dd)
            r = ob.run(sp).r
            for b in range(r.shape[1]):
                m = dd.held[:, b] | dd.fit[:, b]
                if m.sum() < 256:
                    continue
                f, p = welch_csd(r[m, b], fs=data.rate, nperseg=min(1024, int(m.sum())))
                psd.append(np.interp(np.linspace(0, data.rate / 2, 513), f, p))
        if not psd:
            raise ValueError("every trial is shorter than 256 samples: no residual spectrum to read a "
                             "drive-noise level from")
        out.append(np.mean(psd, axis=0))
    f = np.linspace(0, data.rate / 2, 513)
    return f, out[0], np.maximum(out[1] - out[0], 0.0), sigma_ref


def fit_noise_level(r_meas: np.ndarray, mask: np.ndarray, rate: float, comps, f_max: float | None = None,
                    f_min: float = 0.0) -> dict:
    """Drive-noise RMS current implied by the measured residual spectrum (robust median over
    the bands between ``f_min`` and ``f_max`` where drive noise dominates the floor).

    Parameters
    ----------
    r_meas : numpy.ndarray
        (T, B) measured force residual [N].
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    comps : tuple
        :func:`noise_components`' result.
    f_max : float, optional
        Upper end of the bands [Hz].
    f_min : float, optional
        Lower end [Hz].

    Returns
    -------
    dict
        ``ok`` and, when ok, ``sigma`` [A] with its uncertainty, the groups' ratios, their relative
        ``spread`` and ``noise_spread``, the spread noise alone gives them (chi-square power of the
        data's Welch spectrum); else ``why``.
    """
    f, S_q, S_n, sigma_ref = comps
    psd, dof, df = [], 0.0, 0.0
    for b in range(r_meas.shape[1]):
        m = mask[:, b]
        if m.sum() < 256:
            continue
        n_seg = min(1024, int(m.sum()))
        ff, p = welch_csd(r_meas[m, b], fs=rate, nperseg=n_seg)
        psd.append(np.interp(f, ff, p))
        dof += 2.0 * max(1, (int(m.sum()) - n_seg // 2) // (n_seg - n_seg // 2))    # Hann, half overlap
        df = max(df, float(ff[1] - ff[0]))
    if not psd:
        return {"ok": False, "why": "not enough samples"}
    S_m = np.mean(psd, axis=0)
    inband = (np.arange(len(f)) >= 4) & (f >= f_min) & (f <= (f_max or f[-1]))
    dom = (S_n > 1.0 * S_q) & inband
    if dom.sum() < 6:
        dom = (S_n > 0.3 * S_q) & inband
    if dom.sum() < 3:
        return {"ok": False, "why": "drive noise is nowhere above the quantization part of the floor"}
    # ratio of summed power in groups of bins (unbiased, unlike a median of per-bin ratios),
    # median over the groups (robust to a group holding a deterministic remnant)
    idx = np.flatnonzero(dom)
    groups = np.array_split(idx, min(8, max(1, len(idx) // 4)))
    k2s = np.array([(S_m[g] - S_q[g]).sum() / max(S_n[g].sum(), 1e-300) for g in groups])
    k2 = float(np.median(k2s))
    sigma = sigma_ref * math.sqrt(max(k2, 0.0))
    sig_k2 = float(np.std(k2s) / math.sqrt(len(k2s))) if len(k2s) > 1 else abs(k2)
    # a deterministic remnant makes the low groups stand out: the group ratios disagree
    spread = float(np.std(k2s) / max(abs(np.mean(k2s)), 1e-300)) if len(k2s) > 1 else 1.0
    # what noise alone gives that spread: a group's power is chi-square with 2 dof per Welch segment
    # and per independent frequency bin of the data's spectrum (coarser than f on a short record)
    indep = [max(1.0, min(len(g), len(g) * float(f[1] - f[0]) / max(df, 1e-300))) for g in groups]
    noise_spread = float(np.mean([math.sqrt(2.0 / (dof * k)) for k in indep])) if len(k2s) > 1 else 1.0
    return {"ok": True, "group_ratios": [float(v) for v in k2s], "spread": spread, "noise_spread": noise_spread,
            "sigma": sigma, "sigma_unc": sigma_ref * 0.5 * sig_k2 / max(math.sqrt(max(k2, 1e-12)), 1e-12),
            "bands": int(dom.sum()), "groups": len(groups), "f_lo": float(f[dom].min()), "f_hi": float(f[dom].max())}
