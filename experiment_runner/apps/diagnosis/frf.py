"""Lightly damped modes anywhere between DC and Nyquist, from the command -> measurement transfer.

The force observer of :mod:`.predict` sees a missing force only below its bandwidth (rate/25);
a structural mode above it barely shows in the force residual. The command -> measurement
transfer does: :func:`measured_frf` estimates it from the recording (:func:`experiment_runner.core.metrics.cross_spectra`: ``scipy.signal.csd`` /
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

**Closed loop.** In a loop ``u = K (r - y)`` driven by drive noise ``w`` (``y = G (D u + w)``),
the command -> measurement estimate ``P_uy / P_uu`` is ``-1 / K`` wherever the noise excites the
loop more than the reference: the controller, not the plant. :func:`transfer_ratio` therefore uses an *instrument* the noise does not
reach -- the recorded reference or the known external force on a closed-loop record, the command
on an open-loop one: ``G D = P_zy / (P_zu + P_zf / D)`` is unbiased for any such ``z`` (per bin
the instrument of the larger coherence with the measurement). Where neither excites the loop
(above the reference's bandwidth) the plant shows only in the *level* of the noise response:
:func:`noise_band_modes` compares the power spectrum of the recorded command's departure from the
model's noise-free replay with the same of the model's own simulated recordings (the run-to-run
spread of that ratio per bin is its noise), and fits a mode to the ratio through the model's
closed loop ``X = K G`` (measured on the model with a known white force, :func:`loop_from_excitation`):
``S'/S = |1 + D X|^2 / |1 + D' X R|^2 (beta |R|^2 + 1 - beta)``, ``beta`` the share of the
command's noise that enters at the plant (drive noise) rather than at the sensor (quantization),
``D'`` the drive with a free gain and delay. A mode is located where that fit beats the same fit
without the mode beyond what the simulated recordings' own ratios reach (a likelihood ratio
calibrated by simulation), with its damping and mass fraction inside their ranges.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import optimize, stats

from .data import DiagData
from .model import ModelSpec
from experiment_runner.core.metrics import cross_spectra, welch_csd

__all__ = ["measured_frf", "model_frf", "mode_ratio", "locate_modes", "transfer_ratio", "noise_band_modes",
           "loop_from_excitation", "drive_frf", "psd_trials"]


def _nperseg(data: DiagData, nperseg: int | None) -> int:
    n_min = int(data.lengths.min())
    return nperseg or int(2 ** max(6, math.floor(math.log2(max(64, n_min // 8)))))


def measured_frf(data: DiagData, nperseg: int | None = None):
    """Command -> measured position transfer ``H = P_uy / P_uu`` and coherence, averaged over the
    trials (valid samples, linear detrend per segment). Returns (f [Hz], H, coherence) or None.
    On a closed-loop record this is the plant only where the command is not driven by the loop's
    own noise (module docstring); :func:`transfer_ratio` is the estimate the diagnosis uses.

    Parameters
    ----------
    data : DiagData
        The recording.
    nperseg : int, optional
        Welch segment length (default from the trial lengths).

    Returns
    -------
    tuple or None
    """
    num = den = syy = None
    nps = _nperseg(data, nperseg)
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


def drive_frf(spec: ModelSpec, f) -> np.ndarray:
    """The model's drive at ``f`` [Hz]: force-constant ratio times the drive delay (whole samples
    exactly, the fraction as ``exp(-j w tau)``): what turns the command into table force.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    f : numpy.ndarray
        Frequencies [Hz].

    Returns
    -------
    numpy.ndarray
        Complex, [-] (force-constant ratio, delay).
    """
    pm = spec.compiled().pm_full
    return pm.kf_ratio * np.exp(-2j * np.pi * np.asarray(f) * pm.dt * (pm.delay + pm.delay_frac))


def model_frf(spec: ModelSpec, f: np.ndarray, drive: bool = True) -> np.ndarray:
    """The model plant's command -> table position transfer at ``f`` [Hz]: exact ZOH of its linear
    part over a control period (``z = exp(j 2 pi f / rate)``), times the force-constant ratio and
    the drive delay (whole samples exactly, the fraction as ``exp(-j w tau)``); ``drive=False``:
    the table force -> position transfer (a known external force's path).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    f : numpy.ndarray
        Frequencies [Hz].
    drive : bool, optional
        Include the drive (:func:`drive_frf`).

    Returns
    -------
    numpy.ndarray
        Complex [m/N].
    """
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
    return H * drive_frf(spec, f) if drive else H


def transfer_ratio(spec: ModelSpec, data: DiagData, nperseg: int | None = None):
    """The measured plant over the model's, ``R = G_measured / G_model`` (command -> position,
    drive included), by instrument variables (module docstring): for each instrument ``z`` the
    measurement ``y = G (D u + f) + noise`` gives ``P_zy = G D P_zu + G P_zf``, so
    ``R = P_zy / (H_model P_zu + H_force P_zf)`` with ``f`` the known external force. The
    instruments: the command on an open-loop record (the known force, if any, then enters
    exactly); the recorded reference and the known force on a closed-loop one, per bin the one
    of the larger coherence ``|P_zy|^2 / (P_zz P_yy)`` with the measurement. Averaged over the
    trials (valid samples, linear detrend per segment). The model's transfer is its linear part
    (:func:`model_frf`): where its friction holds the table (pre-sliding stiffness, low
    frequencies) ``R`` shows the friction, not a mass (:func:`locate_modes` reads narrow features
    only). Returns ``(f [Hz], R, coherence, instrument per bin)`` for ``f > 0``, or None (trials
    shorter than a segment).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    nperseg : int, optional
        Welch segment length (default from the trial lengths).

    Returns
    -------
    tuple or None
    """
    nps = _nperseg(data, nperseg)
    fk = data.known_force()
    names = ["command"] if data.open_loop else ["reference", "known force"]
    acc: dict = {}
    for b in range(data.shape[1]):
        n = int(data.lengths[b])
        if n < nps:
            continue
        y, u, fe = data.y[:n, b], data.u[:n, b], fk[:n, b]
        w = n / nps
        for name in names:
            z = u if name == "command" else (data.x_ref[:n, b] if name == "reference" else fe)
            if not np.any(z != z[0]):
                continue
            f, pzz, pyy, pzy = cross_spectra(z, y, data.rate, nps, detrend="linear")
            _, pzu = welch_csd(z, u, fs=data.rate, nperseg=nps, detrend="linear")
            _, pzf = welch_csd(z, fe, fs=data.rate, nperseg=nps, detrend="linear")
            a = acc.setdefault(name, [f, 0, 0, 0, 0, 0])
            for k, v in enumerate((pzz, pyy, pzy, pzu, pzf), 1):
                a[k] = a[k] + w * v
    if not acc:
        return None
    f = next(iter(acc.values()))[0][1:]
    Hm, Hf = None, None
    best_R, best_c, which = None, None, None
    for i, (name, (_, pzz, pyy, pzy, pzu, pzf)) in enumerate(acc.items()):
        pzz, pyy, pzy, pzu, pzf = (a[1:] for a in (pzz, pyy, pzy, pzu, pzf))
        if Hm is None:
            Hm, Hf = model_frf(spec, f), model_frf(spec, f, drive=False)
        den = Hm * pzu + Hf * pzf
        R = pzy / np.where(np.abs(den) > 0, den, 1e-300)
        c = np.abs(pzy) ** 2 / np.maximum(np.real(pzz) * np.real(pyy), 1e-300)
        if best_R is None:
            best_R, best_c, which = R, c, np.full(len(f), name, object)
        else:
            take = c > best_c
            best_R, best_c = np.where(take, R, best_R), np.where(take, c, best_c)
            which = np.where(take, name, which)
    return f, best_R, best_c, which


def mode_ratio(f, f_b: float, zeta: float, phi: float) -> np.ndarray:
    """``R(j 2 pi f)``: a mode of blocked frequency ``f_b``, damping ``zeta`` and modal mass fraction
    ``phi`` taken out of a rigid table, over the rigid table (module docstring).

    Parameters
    ----------
    f : numpy.ndarray
        Frequencies [Hz].
    f_b : float
        Blocked frequency [Hz].
    zeta : float
        Damping ratio.
    phi : float
        Modal mass fraction (0...1).

    Returns
    -------
    numpy.ndarray
        Complex.
    """
    s = 2j * np.pi * np.asarray(f)
    w = 2 * np.pi * f_b
    g = (w * w + 2 * zeta * w * s) / (s * s + 2 * zeta * w * s + w * w)
    return 1.0 / ((1.0 - phi) + phi * g)


def locate_modes(spec: ModelSpec, data: DiagData, min_coherence: float = 0.8, max_modes: int = 2,
                 est=None) -> list[dict]:
    """Narrow features of ``|R|`` (:func:`transfer_ratio`: measured over model transfer, by
    instrument variables; coherent bins, ratio detrended by a running median over an octave) at
    least 4 robust standard deviations out, each fitted by :func:`mode_ratio` times a complex gain
    over an octave each side; kept if lightly damped (zeta < 0.2), of a fraction of the mass (< 0.8),
    fitting to 15 % RMS and with no parameter at its bound. Returns the fitted modes ``{f_hz, zeta, fraction, feature_hz, kind,
    depth_db, fit_rms, source}``, deepest first. ``est``: :func:`transfer_ratio`'s result, if at hand.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    min_coherence : float, optional
        Bins below it are not used.
    max_modes : int, optional
        Most modes returned.
    est : tuple, optional
        :func:`transfer_ratio`'s result.

    Returns
    -------
    list of dict
    """
    est = transfer_ratio(spec, data) if est is None else est
    if est is None:
        return []
    f, Rall, coh, which = est
    ok = (coh >= min_coherence) & (np.arange(len(f)) >= 2) & (f < 0.49 * data.rate) & np.isfinite(Rall) & (Rall != 0)
    if ok.sum() < 12:
        return []
    fo, R = f[ok], Rall[ok]
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
        fit = fit_mode(fo[band], R[band], fk, kind)
        # a lightly damped mode of a fraction of the mass, fitting the ratio to 15 % (log units), no
        # parameter at its bound: else a broad misfit of the model (friction, the loop through which a
        # closed-loop transfer is seen) or a line of the excitation (a mode of zeta 1e-4, 0.05 % of the mass)
        if (fit is not None and fit["zeta"] < 0.2 and fit["fraction"] < 0.8 and fit["fit_rms"] < 0.15
                and not fit.pop("at_bound")):
            fit.update(feature_hz=float(fk), kind=kind, depth_db=float(20 * dev[i] / math.log(10)),
                       source=f"transfer ({which[ok][i]} as instrument)")
            out.append(fit)
    return out


# ----------------------------------------------------------------------------- closed loop, noise-excited
NOISE_Z_MIN = 4.0
"""Smoothed z of the command-noise spectrum ratio (data over the model's simulated recordings) where a
band is examined for a mode."""

NOISE_BAND_ALPHA = 1e-3
"""Level of the mode's likelihood-ratio test against the simulated recordings' own ratios."""


def psd_trials(x: np.ndarray, mask: np.ndarray, rate: float, nperseg: int) -> np.ndarray:
    """Welch PSD (Hann, 50 % overlap, linear detrend) of the masked samples of each column of ``x``
    (T, B), averaged over the columns weighted by their samples; columns shorter than a segment are
    skipped. Returns the PSD at ``rfftfreq(nperseg, 1/rate)`` (zeros if no column is long enough).

    Parameters
    ----------
    x : numpy.ndarray
        (T, B) signal.
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    nperseg : int
        Segment length.

    Returns
    -------
    numpy.ndarray
        PSD on ``nperseg // 2 + 1`` bins.
    """
    P, n = 0.0, 0
    for b in range(x.shape[1]):
        m = mask[:, b]
        k = int(m.sum())
        if k < nperseg:
            continue
        _, p = welch_csd(x[m, b], fs=rate, nperseg=nperseg, detrend="linear")
        P, n = P + p * k, n + k
    return P / n if n else np.zeros(nperseg // 2 + 1)


def loop_from_excitation(f_ext: np.ndarray, du: np.ndarray, mask: np.ndarray, rate: float, nperseg: int,
                         drive: np.ndarray) -> np.ndarray:
    """The model's closed loop ``X = K G`` (controller times table-force -> measurement transfer)
    from its noise-free response ``du`` (T, C: command minus the noise-free replay's) to a known
    white table force ``f_ext`` (T, C): the force -> command transfer is ``T = -X / (1 + D X)``
    (``D`` the drive, :func:`drive_frf`), so ``X = -T / (1 + D T)``. Along the recorded
    trajectory: friction enters as the model's own contact does there (a Dahl contact's stiffness
    while it sticks).

    Parameters
    ----------
    f_ext : numpy.ndarray
        (T, C) known white table force [N].
    du : numpy.ndarray
        (T, C) command response [N].
    mask : numpy.ndarray
        (T, C) bool.
    rate : float
        Sample rate [Hz].
    nperseg : int
        Segment length.
    drive : numpy.ndarray
        The drive at the segment's frequencies (:func:`drive_frf`).

    Returns
    -------
    numpy.ndarray
        Complex ``X``.
    """
    pff, pfu = 0.0, 0.0
    for c in range(f_ext.shape[1]):
        m = mask[:, c]
        if m.sum() < nperseg:
            continue
        _, a = welch_csd(f_ext[m, c], f_ext[m, c], fs=rate, nperseg=nperseg, detrend="linear")
        _, b = welch_csd(f_ext[m, c], du[m, c], fs=rate, nperseg=nperseg, detrend="linear")
        pff, pfu = pff + a, pfu + b
    T = pfu / np.where(np.abs(pff) > 0, pff, 1e-300)
    return -T / (1 + drive * T)


def _ratio_model(th, f, X, D, rate, mode: bool):
    """log of the modelled spectrum ratio (module docstring) for parameters ``th``: log scale, log
    gain, delay [samples] (+ log f_b, log zeta, logit phi, logit beta with a mode)."""
    Dp = D * math.exp(th[1]) * np.exp(-2j * np.pi * f * th[2] / rate)
    if mode:
        R = mode_ratio(f, math.exp(th[3]), math.exp(th[4]), 1 / (1 + math.exp(-th[5])))
        beta = 1 / (1 + math.exp(-th[6]))
        shape = beta * np.abs(R) ** 2 + 1 - beta
    else:
        R, shape = 1.0, 1.0
    return th[0] + np.log(np.abs(1 + D * X) ** 2 / np.maximum(np.abs(1 + Dp * X * R) ** 2, 1e-300) * shape)


def _fit_ratio(lr, sd, f, X, D, rate, fc, mode: bool, starts):
    lo = [-4.0, -0.7, -2.0] + ([math.log(fc / 2.2), math.log(1e-3), -6.0, -6.0] if mode else [])
    hi = [4.0, 0.7, 2.0] + ([math.log(fc * 2.2), math.log(0.3), 1.4, 6.0] if mode else [])
    best = None
    for s0 in starts:
        s0 = np.clip(s0, np.array(lo) + 1e-9, np.array(hi) - 1e-9)
        try:
            r = optimize.least_squares(lambda th: (lr - _ratio_model(th, f, X, D, rate, mode)) / sd, s0,
                                       bounds=(lo, hi), x_scale=1.0)
        except (ValueError, np.linalg.LinAlgError):
            continue
        if best is None or r.cost < best.cost:
            best = r
    return best, lo, hi


def noise_band_modes(f, S_data, S_sims, S_det, X, D, rate: float, max_modes: int = 2, window: float = 2.0) -> tuple:
    """Modes located in the closed loop's noise response (module docstring).

    Parameters
    ----------
    f : ndarray
        Frequencies [Hz] of the spectra.
    S_data : ndarray
        PSD of the recorded command minus the model's noise-free replay.
    S_sims : ndarray (K, F)
        The same for ``K`` recordings simulated from the model.
    S_det : ndarray
        PSD of the noise-free replay's command: bins where it exceeds the simulated recordings' noise
        carry the model's deterministic misfit, not the noise response, and are left out.
    X, D : ndarray
        The model's closed loop (:func:`loop_from_excitation`) and drive (:func:`drive_frf`) at ``f``.
    rate : float
        Sample rate [Hz].
    max_modes : int
        Most modes returned.
    window : float
        Each examined band is fitted from its centre / ``window`` to centre x ``window``.

    Returns
    -------
    modes : list of dict
        ``{f_hz, zeta, fraction, feature_hz, kind, depth_db, lr, lr_threshold, source}``, strongest first.
    info : dict
        The examined bands (centre, smoothed z, LR and its threshold, why not located) and the
        usable frequency range.
    """
    K = S_sims.shape[0]
    Sm = S_sims.mean(axis=0)
    ok = (f > 0) & (f < 0.45 * rate) & (Sm > 0) & (S_data > 0) & np.isfinite(X) & (S_det <= Sm)
    info = {"bins": int(ok.sum()), "bands": []}
    if ok.sum() < 16 or K < 4:
        info["why"] = "too few noise-dominated bins" if K >= 4 else "the model has fewer than 4 simulated recordings"
        return [], info
    info["f_range_hz"] = [float(f[ok].min()), float(f[ok].max())]
    with np.errstate(divide="ignore", invalid="ignore"):
        lrd = np.log(S_data / Sm)
        loo = np.array([np.log(S_sims[k] / np.delete(S_sims, k, 0).mean(axis=0)) for k in range(K)])
    loo *= math.sqrt((K - 1) / K)            # a leave-one-out ratio spreads (K / (K - 1)) more than the data's
    loo = np.where(np.isfinite(loo), loo, 0.0)
    sd_raw = np.sqrt(np.mean(loo ** 2, axis=0))
    fo = f[ok]
    sd = np.array([np.median(sd_raw[ok][(fo >= fk / 1.1) & (fo <= fk * 1.1)]) for fk in fo])
    sd = np.maximum(sd, 1e-3)
    l_d, l_k, Xo, Do = lrd[ok], loo[:, ok], X[ok], D[ok]

    def zscan(l):
        return np.array([l[(fo >= fk / 1.08) & (fo <= fk * 1.08)].sum()
                         / math.sqrt(np.sum(sd[(fo >= fk / 1.08) & (fo <= fk * 1.08)] ** 2)) for fk in fo])

    zd = zscan(l_d)
    t_q = float(stats.t.ppf(1 - NOISE_BAND_ALPHA, K - 1)) * math.sqrt(1 + 1 / K)
    chi = float(stats.chi2.ppf(1 - NOISE_BAND_ALPHA, 4))
    modes, used = [], np.zeros(len(fo), bool)
    for _ in range(3):
        cand = np.where(used, 0.0, np.abs(zd))
        i = int(np.argmax(cand))
        if cand[i] < NOISE_Z_MIN:
            break
        fc = float(fo[i])
        used |= (fo >= fc / 1.3) & (fo <= fc * 1.3)
        if any(fo[i] >= m["f_hz"] / 1.3 and fo[i] <= m["f_hz"] / math.sqrt(1 - m["fraction"]) * 1.3 for m in modes):
            continue        # the other side of a mode located already (its anti-resonance and resonance)
        win = (fo >= fc / window) & (fo <= fc * window)
        band = {"centre_hz": fc, "z": float(zd[i]), "bins": int(win.sum())}
        info["bands"].append(band)
        if win.sum() < 8:
            band["why"] = "too few bins"
            continue
        args = (sd[win], fo[win], Xo[win], Do[win], rate, fc)
        starts = [[0.0, 0.0, 0.0, math.log(fb), math.log(z0), math.log(ph / (1 - ph)), 0.0]
                  for fb in (fc / 1.15, fc, fc * 1.15) for z0 in (0.01, 0.05) for ph in (0.05, 0.2)]
        h0, _, _ = _fit_ratio(l_d[win], *args, mode=False, starts=[[0.0, 0.0, 0.0]])
        h1, lo, hi = _fit_ratio(l_d[win], *args, mode=True, starts=starts)
        if h0 is None or h1 is None:
            band["why"] = "fit failed"
            continue
        lr = 2 * (h0.cost - h1.cost)
        lrk = []
        for k in range(K):
            a, _, _ = _fit_ratio(l_k[k][win], *args, mode=False, starts=[[0.0, 0.0, 0.0]])
            b, _, _ = _fit_ratio(l_k[k][win], *args, mode=True, starts=[h1.x, starts[1], starts[-2]])
            if a is not None and b is not None:
                lrk.append(2 * (a.cost - b.cost))
        thr = max(float(np.mean(lrk) + t_q * np.std(lrk, ddof=1)) if len(lrk) > 2 else math.inf, chi)
        x = h1.x
        fb, ze, ph = math.exp(x[3]), math.exp(x[4]), 1 / (1 + math.exp(-x[5]))
        at = [k for k in range(3, 6) if min(x[k] - lo[k], hi[k] - x[k]) < 1e-3 * (hi[k] - lo[k])]
        band.update(lr=float(lr), lr_threshold=thr, f_hz=fb, zeta=ze, fraction=ph)
        if lr <= thr:
            band["why"] = "the mode's fit is within what the simulated recordings reach"
        elif at:
            band["why"] = "mode parameter at its bound: " + ", ".join(("f", "zeta", "fraction")[k - 3] for k in at)
        elif not (ze < 0.2 and ph < 0.8):
            band["why"] = "not a lightly damped mode of a fraction of the mass"
        elif any(abs(math.log(fb / m["f_hz"])) < 0.2 and m["lr"] / m["lr_threshold"] >= lr / thr for m in modes):
            band["why"] = "the same mode as a stronger one located already (blocked frequency within 20 %)"
        else:
            band["why"] = "located"
            # the other side of a mode located already, fitted more strongly here: this fit replaces it
            modes = [m for m in modes if abs(math.log(fb / m["f_hz"])) >= 0.2]
            dev = l_d[win] - _ratio_model(h0.x, fo[win], Xo[win], Do[win], rate, False)
            modes.append({"f_hz": fb, "zeta": ze, "fraction": ph, "feature_hz": fc,
                          "kind": "closed-loop noise response", "depth_db": float(10 * np.max(np.abs(dev)) / math.log(10)),
                          "lr": float(lr), "lr_threshold": thr, "source": "command noise spectrum vs the model's "
                          "simulated recordings"})
        if len(modes) >= max_modes:
            break
    modes.sort(key=lambda m: -m["lr"] / m["lr_threshold"])
    return modes, info


def fit_mode(f, R, fk, kind):
    """Least squares of ``log R - log(c mode_ratio)`` over ``(log f_b, log zeta, logit phi)`` and a
    complex gain ``c`` (solved in closed form per evaluation).

    ``f_b`` is bounded to ``fk / 3 ... 3 fk``, ``zeta`` to ``1e-4 ... 1``; six starts (three
    mass fractions, two damping ratios), the lowest cost kept.

    Parameters
    ----------
    f : numpy.ndarray
        Frequencies [Hz] of the band fitted.
    R : numpy.ndarray
        The measured-over-model transfer ratio at ``f`` (complex, dimensionless,
        :func:`transfer_ratio`), nonzero.
    fk : float
        Frequency of the feature [Hz] (the starts' blocked frequency).
    kind : {'resonance', 'antiresonance'}
        The feature's kind: an antiresonance starts ``f_b`` at ``fk``, a resonance at
        ``fk sqrt(1 - phi)``.

    Returns
    -------
    dict or None
        ``f_hz`` (blocked frequency [Hz]), ``zeta``, ``fraction`` (modal mass fraction),
        ``fit_rms`` (RMS of the real and imaginary parts of the log residual) and ``at_bound``
        (``'f'``, ``'zeta'``, ``'fraction'``: those within 0.1 % of their fitted (log or logit) range
        of a bound); None when no start could be fitted.
    """
    lR = np.log(R)

    def res(p):
        fb, ze, ph = math.exp(p[0]), math.exp(p[1]), 1 / (1 + math.exp(-p[2]))
        e = lR - np.log(mode_ratio(f, fb, ze, ph))
        e = e - np.mean(e)                       # the complex gain
        return np.concatenate([e.real, e.imag])

    best = None
    lo, hi = [math.log(fk / 3), math.log(1e-4), -8], [math.log(fk * 3), 0.0, 8]
    for phi0 in (0.05, 0.2, 0.5):
        fb0 = fk if kind == "antiresonance" else fk * math.sqrt(1 - phi0)
        for z0 in (0.01, 0.05):
            try:
                r = optimize.least_squares(res, [math.log(fb0), math.log(z0), math.log(phi0 / (1 - phi0))],
                                           bounds=(lo, hi))
            except (ValueError, np.linalg.LinAlgError):
                continue
            if best is None or r.cost < best.cost:
                best = r
    if best is None:
        return None
    fb, ze, ph = math.exp(best.x[0]), math.exp(best.x[1]), 1 / (1 + math.exp(-best.x[2]))
    at = [n for k, n in enumerate(("f", "zeta", "fraction")) if min(best.x[k] - lo[k], hi[k] - best.x[k]) < 1e-3 * (hi[k] - lo[k])]
    return {"f_hz": fb, "zeta": ze, "fraction": ph, "fit_rms": float(np.sqrt(2 * best.cost / len(best.fun))), "at_bound": at}
