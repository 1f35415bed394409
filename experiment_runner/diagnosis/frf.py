"""Lightly damped modes anywhere between DC and Nyquist, from the command -> measurement transfer.

The force observer of :mod:`.predict` sees a missing force only below its bandwidth (rate/25);
a structural mode above it barely shows in the force residual. The command -> measurement
transfer does: :func:`measured_frf` estimates it from the recording (:func:`experiment_runner.metrics.cross_spectra`: ``scipy.signal.csd`` /
``welch``, with its coherence), :func:`model_frf` is the nominal plant's own (its exact ZOH
discretisation over a control period, force constant and drive delay included; friction
enters only through its viscous part), and :func:`locate_modes` looks for a narrow resonance or
anti-resonance in their ratio and fits it.

A mode whose mass is part of the table's (modal mass fraction ``phi`` of the rigid mass ``M``,
blocked frequency ``w`` and damping ratio ``zeta`` of the mode mass on its spring-damper) turns
the rigid body's transfer into ``R(s) = 1 / ((1 - phi) + phi g(s))`` times it, with
``g(s) = (w^2 + 2 zeta w s) / (s^2 + 2 zeta w s + w^2)``: an anti-resonance at ``w`` (the
table stands still while the mode mass swings) and a resonance at ``w / sqrt(1 - phi)``. The
fit of ``(w, zeta, phi)`` (and a complex gain for what else differs smoothly) to the measured
ratio near the feature is the start of the ``structural_mode`` hypothesis, which the judge
then decides on the held-out data like any other.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from .data import DiagData
from .model import ModelSpec
from experiment_runner.metrics import cross_spectra

__all__ = ["measured_frf", "model_frf", "mode_ratio", "locate_modes"]


def measured_frf(data: DiagData, nperseg: int | None = None):
    """Command -> measured position transfer ``H = P_uy / P_uu`` and coherence, averaged over the
    trials (valid samples, linear detrend per segment). Returns (f [Hz], H, coherence) or None."""
    num = den = syy = None
    n_min = int(data.lengths.min())
    nps = nperseg or int(2 ** max(6, math.floor(math.log2(max(64, n_min // 8)))))
    for b in range(data.shape[1]):
        n = int(data.lengths[b])
        if n < nps:
            continue
        u, y = data.u[:n, b], data.y[:n, b]
        f, puu, pyy, puy = cross_spectra(u, y, data.rate, nps, detrend="linear")
        w = n / nps
        num = puy * w if num is None else num + puy * w
        den = puu * w if den is None else den + puu * w
        syy = pyy * w if syy is None else syy + pyy * w
    if num is None:
        return None
    coh = np.abs(num) ** 2 / np.maximum(den * syy, 1e-300)
    return f, num / np.maximum(den, 1e-300), coh


def model_frf(spec: ModelSpec, f: np.ndarray) -> np.ndarray:
    """The model plant's command -> table position transfer at ``f`` [Hz]: exact ZOH of its linear
    part over a control period (``z = exp(j 2 pi f / rate)``), times the force-constant ratio and
    the drive delay (whole samples exactly, the fraction as ``exp(-j w tau)``)."""
    pm = spec.compiled().pm_full
    n2 = pm.phi.shape[0]
    Phi = np.linalg.matrix_power(pm.phi, pm.n_sub)
    Gam = np.zeros(n2)
    P = np.eye(n2)
    for _ in range(pm.n_sub):
        Gam += P @ pm.gam[:, 0]
        P = P @ pm.phi
    z = np.exp(2j * np.pi * np.asarray(f) * pm.dt)
    H = np.array([np.linalg.solve(zk * np.eye(n2) - Phi, Gam)[0] for zk in z])
    return pm.kf_ratio * H * z ** (-(pm.delay + pm.delay_frac))


def mode_ratio(f, f_b: float, zeta: float, phi: float) -> np.ndarray:
    """``R(j 2 pi f)``: a mode of blocked frequency ``f_b``, damping ``zeta`` and modal mass fraction
    ``phi`` taken out of a rigid table, over the rigid table (module docstring)."""
    s = 2j * np.pi * np.asarray(f)
    w = 2 * np.pi * f_b
    g = (w * w + 2 * zeta * w * s) / (s * s + 2 * zeta * w * s + w * w)
    return 1.0 / ((1.0 - phi) + phi * g)


def locate_modes(spec: ModelSpec, data: DiagData, min_coherence: float = 0.8, max_modes: int = 2) -> list[dict]:
    """Narrow features of ``|H_measured / H_model|`` (coherent bins, ratio detrended by a running
    median over an octave) at least 4 robust standard deviations out, each fitted by
    :func:`mode_ratio` times a complex gain over an octave each side; kept if lightly damped
    (zeta < 0.2), of a fraction of the mass (< 0.8) and fitting to 15 % RMS. Returns the fitted modes
    ``{f_hz, zeta, fraction, feature_hz, kind, depth_db, fit_rms}``, deepest first."""
    est = measured_frf(data)
    if est is None:
        return []
    f, H, coh = est
    ok = (coh >= min_coherence) & (f > 0) & (np.arange(len(f)) >= 3) & (f < 0.49 * data.rate)
    if ok.sum() < 12:
        return []
    fo, R = f[ok], H[ok] / model_frf(spec, f[ok])
    lr = np.log(np.abs(R))
    trend = np.array([np.median(lr[(fo >= fk / 1.41) & (fo <= fk * 1.41)]) for fk in fo])
    dev = lr - trend
    mad = 1.4826 * np.median(np.abs(dev - np.median(dev))) or 1e-12
    out, used = [], np.zeros(len(fo), bool)
    for _ in range(max_modes):
        cand = np.where(used, 0.0, np.abs(dev))
        i = int(np.argmax(cand))
        if cand[i] < 4 * mad or cand[i] < math.log(1.3):
            break
        fk = fo[i]
        band = (fo >= fk / 2) & (fo <= fk * 2)
        used |= (fo >= fk / 1.3) & (fo <= fk * 1.3)
        kind = "antiresonance" if dev[i] < 0 else "resonance"
        fit = _fit_mode(fo[band], R[band], fk, kind)
        # a lightly damped mode of a fraction of the mass, fitting the ratio to 15 % (log units): else a
        # broad misfit of the model (friction, the loop through which a closed-loop transfer is seen)
        if fit is not None and fit["zeta"] < 0.2 and fit["fraction"] < 0.8 and fit["fit_rms"] < 0.15:
            fit.update(feature_hz=float(fk), kind=kind, depth_db=float(20 * dev[i] / math.log(10)))
            out.append(fit)
    return out


def _fit_mode(f, R, fk, kind):
    """Least squares of ``log R - log(c mode_ratio)`` over ``(log f_b, log zeta, logit phi)`` and a
    complex gain ``c`` (solved in closed form per evaluation)."""
    lR = np.log(R)

    def res(p):
        fb, ze, ph = math.exp(p[0]), math.exp(p[1]), 1 / (1 + math.exp(-p[2]))
        e = lR - np.log(mode_ratio(f, fb, ze, ph))
        e = e - np.mean(e)                       # the complex gain
        return np.concatenate([e.real, e.imag])

    best = None
    for phi0 in (0.05, 0.2, 0.5):
        fb0 = fk if kind == "antiresonance" else fk * math.sqrt(1 - phi0)
        for z0 in (0.01, 0.05):
            try:
                r = optimize.least_squares(res, [math.log(fb0), math.log(z0), math.log(phi0 / (1 - phi0))],
                                           bounds=([math.log(fk / 3), math.log(1e-4), -8], [math.log(fk * 3), 0.0, 8]))
            except (ValueError, np.linalg.LinAlgError):
                continue
            if best is None or r.cost < best.cost:
                best = r
    if best is None:
        return None
    fb, ze, ph = math.exp(best.x[0]), math.exp(best.x[1]), 1 / (1 + math.exp(-best.x[2]))
    return {"f_hz": fb, "zeta": ze, "fraction": ph, "fit_rms": float(np.sqrt(2 * best.cost / len(best.fun)))}
