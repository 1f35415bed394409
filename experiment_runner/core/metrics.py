"""Performance metrics for nanopositioning experiments (SI units).

Time-domain metrics (settling time, RMS in-position error, tracking errors)
follow seed Sec. 3.4 and 4.4; frequency-domain estimates (FRFs from
sine tests and broadband data) follow seed Sec. 4.3; the closed-loop
bandwidth and stability margins computed from them live with the loop
design in :mod:`stage_control.tuning`.
Time-domain functions accept a single record ``x`` of shape ``(T,)`` or a
batch of trials of shape ``(n_trials, T)`` sharing the time vector ``t``.
"""

import math

import numpy as np
from scipy import signal


def finite_or_none(v):
    """``float(v)``, or None for None, NaN and ±inf (JSON has no NaN).

    >>> finite_or_none(2), finite_or_none(float("nan")), finite_or_none(None)
    (2.0, None, None)
    """
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _window_mask(t, t_from, t_to):
    """Boolean mask ``t_from <= t <= t_to`` broadcast over a batch axis."""
    t_from = np.asarray(t_from, dtype=float)[..., None]
    t_to = np.asarray(t_to, dtype=float)[..., None]
    return (t >= t_from) & (t <= t_to)


def _scalar_or_array(value):
    return float(value) if np.ndim(value) == 0 else value


def settling_time(t, x, target, t_start, window, t_end=None):
    """Settling time [s] into the band ``target +- window``.

    The settling instant is the first sample in ``[t_start, t_end]`` after
    which ``|x - target| <= window`` holds up to ``t_end``; the settling time
    is that instant minus ``t_start``. Its resolution is one sample: the
    true (continuous-time) entry into the band lies between the last sample
    outside and the returned instant.

    Parameters
    ----------
    t : array_like, shape (T,)
        Time [s].
    x : array_like, shape (T,) or (n_trials, T)
        Measured position [m].
    target : float or array_like, shape (n_trials,)
        Target position [m].
    t_start : float or array_like, shape (n_trials,)
        Instant [s] the reference reaches the target (start of the settling
        portion).
    window : float
        Half-width of the settling band [m], e.g. 25e-9.
    t_end : float or array_like, optional
        End of the evaluated interval [s]; default ``t[-1]``.

    Returns
    -------
    float or numpy.ndarray
        Settling time [s] (0 if inside the band from ``t_start`` on), nan if
        ``x`` is outside the band at ``t_end`` or no sample lies in the
        interval. An array of shape ``(n_trials,)`` for batch input.

    Examples
    --------
    >>> t = np.arange(0, 0.1, 1e-4)
    >>> x = 1e-6 * np.exp(-t / 0.01)  # decays to 25 nm at t = 0.0369 s
    >>> round(settling_time(t, x, 0.0, 0.0, 25e-9), 4)
    0.0369
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    t_end = t[-1] if t_end is None else t_end
    in_interval = _window_mask(t, t_start, t_end)
    in_interval, x = np.broadcast_arrays(in_interval, x)
    target = np.asarray(target, dtype=float)[..., None]
    outside = in_interval & (np.abs(x - target) > window)
    last = t.size - 1
    last_in_interval = last - np.argmax(in_interval[..., ::-1], axis=-1)
    last_outside = last - np.argmax(outside[..., ::-1], axis=-1)
    ever_outside = outside.any(axis=-1)
    settle_idx = np.where(ever_outside, last_outside + 1,
                          np.argmax(in_interval, axis=-1))
    valid = in_interval.any(axis=-1) & ~(
        ever_outside & (last_outside == last_in_interval))
    t_settle = t[np.minimum(settle_idx, last)] - np.asarray(t_start)
    return _scalar_or_array(np.where(valid, t_settle, np.nan))


def rms_in_position(t, x, target, t_settled, t_end=None):
    """RMS in-position error [m] after settling.

    RMS of ``x - target`` over the samples with
    ``t_settled <= t <= t_end`` (seed Sec. 3.4.1, Table 4.2).

    Parameters
    ----------
    t : array_like, shape (T,)
        Time [s].
    x : array_like, shape (T,) or (n_trials, T)
        Measured position [m].
    target : float or array_like, shape (n_trials,)
        Target position [m].
    t_settled : float or array_like, shape (n_trials,)
        Absolute settling instant [s], i.e. ``t_start + settling_time(...)``;
        nan gives nan.
    t_end : float or array_like, optional
        End of the evaluated interval [s]; default ``t[-1]``.

    Returns
    -------
    float or numpy.ndarray
        RMS error [m], nan where no sample lies in the interval.

    Examples
    --------
    >>> t = np.arange(0, 1, 1e-4)
    >>> x = 2e-9 * np.sin(2 * np.pi * 50 * t)
    >>> round(rms_in_position(t, x, 0.0, 0.0) * 1e9, 4)  # 2 nm / sqrt(2)
    1.4142
    """
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    t_end = t[-1] if t_end is None else t_end
    mask = _window_mask(t, t_settled, t_end)
    err2 = (x - np.asarray(target, dtype=float)[..., None]) ** 2
    count = np.sum(mask, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        rms = np.sqrt(np.sum(np.where(mask, err2, 0.0), axis=-1) / count)
    return _scalar_or_array(rms)


def tracking_errors(x_ref, x):
    """Peak and RMS tracking error [m] along the last axis.

    Parameters
    ----------
    x_ref : array_like, shape (T,) or broadcastable to ``x``
        Reference position [m].
    x : array_like, shape (T,) or (n_trials, T)
        Measured position [m].

    Returns
    -------
    peak : float or numpy.ndarray
        ``max |x_ref - x|`` [m].
    rms : float or numpy.ndarray
        RMS of ``x_ref - x`` [m].

    Examples
    --------
    >>> t = np.arange(0, 1, 1e-4)
    >>> peak, rms = tracking_errors(np.zeros_like(t), 1e-6 * np.sin(2 * np.pi * t))
    >>> round(peak * 1e6, 6), round(rms * 1e6, 6)
    (1.0, 0.707107)
    """
    e = np.asarray(x_ref, dtype=float) - np.asarray(x, dtype=float)
    return (_scalar_or_array(np.max(np.abs(e), axis=-1)),
            _scalar_or_array(np.sqrt(np.mean(e**2, axis=-1))))


def sine_phasor(t, s, f):
    """Complex amplitude of a sine in a signal with offset and linear drift (least squares).

    Fits ``s(t) = Re{S exp(j 2 pi f t)} + c + d t`` over the given samples, so that a sine
    force ``A sin(2 pi f t)`` has ``S = -j A`` and an FRF is ``H = S_y / S_u``. The drift
    term absorbs a slow creep of a sliding stage; over whole periods it is orthogonal to
    the sine up to O(1/N) and costs no accuracy.

    Parameters
    ----------
    t : array_like, shape (n,)
        Sample times [s].
    s : array_like, shape (..., n)
        Signal(s) [any unit].
    f : float
        Frequency [Hz].

    Returns
    -------
    complex or numpy.ndarray
        ``S`` [unit of s], shape ``s.shape[:-1]``.

    Examples
    --------
    >>> t = np.arange(1000) * 1e-4
    >>> s = 2.0 * np.cos(2 * np.pi * 50 * t + 0.5) + 3.0 + 40.0 * t
    >>> S = sine_phasor(t, s, 50.0)
    >>> round(abs(S), 9), round(float(np.angle(S)), 9)
    (2.0, 0.5)
    """
    t = np.asarray(t, float)
    s = np.asarray(s, float)
    w = 2.0 * np.pi * f
    tc = t - t.mean()
    basis = np.stack([np.cos(w * t), np.sin(w * t), np.ones_like(t), tc / max(np.ptp(t), 1e-300)], axis=1)
    coef, *_ = np.linalg.lstsq(basis, s.reshape(-1, t.size).T, rcond=None)
    out = coef[0] - 1j * coef[1]
    return out.reshape(s.shape[:-1]) if s.ndim > 1 else complex(out[0])


def welch_csd(x, y=None, fs=1.0, nperseg=256, detrend="constant"):
    """Welch-averaged (cross) power spectral density: :func:`scipy.signal.csd` ``(x, y)`` (or
    :func:`scipy.signal.welch` ``(x)`` where ``y`` is None) with their defaults -- periodic Hann
    window, 50 % overlap, no padding, density scaling, one-sided, mean of the segments -- computed
    on every segment at once. scipy 1.17 detrends and transforms segment by segment in Python
    (``ShortTimeFFT.stft_detrend``): 0.6 ms a segment with a linear detrend, most of the
    diagnosis' mode location on a 10 kHz record. The same to rounding (a test compares both).

    Parameters
    ----------
    x : array_like, shape (T,)
        Signal.
    y : array_like, shape (T,), optional
        Second signal (same length); None: the PSD of ``x`` (real).
    fs : float
        Sample rate [Hz].
    nperseg : int
        Segment length (at most ``T``: longer is cut to ``T``, as scipy does).
    detrend : {"constant", "linear", False}
        Per-segment detrending.

    Returns
    -------
    f : numpy.ndarray
        Frequencies [Hz], ``rfftfreq(nperseg, 1 / fs)``.
    p : numpy.ndarray
        ``conj(X) Y`` density (complex), or the real PSD of ``x``.

    Examples
    --------
    >>> rng = np.random.default_rng(1)
    >>> x, y = rng.standard_normal((2, 3000))
    >>> f, p = welch_csd(x, y, fs=1e3, nperseg=256, detrend="linear")
    >>> bool(np.allclose(p, signal.csd(x, y, fs=1e3, nperseg=256, detrend="linear")[1], rtol=1e-10, atol=0))
    True
    """
    x = np.asarray(x, float)
    n = x.shape[-1]
    nperseg = int(min(nperseg, n))
    step = nperseg - nperseg // 2
    win = signal.get_window("hann", nperseg)

    def spectra(a):
        seg = np.lib.stride_tricks.sliding_window_view(a, nperseg)[::step]
        if detrend == "linear":
            t = np.arange(nperseg) - 0.5 * (nperseg - 1)
            seg = seg - seg.mean(axis=1, keepdims=True) - np.outer(seg @ t / (t @ t), t)
        elif detrend == "constant":
            seg = seg - seg.mean(axis=1, keepdims=True)
        elif detrend is not False:
            raise ValueError(f"detrend must be 'constant', 'linear' or False, not {detrend!r}")
        return np.fft.rfft(seg * win, axis=1)

    X = spectra(x)
    P = np.conj(X) * (X if y is None else spectra(np.asarray(y, float)))
    P = P.mean(axis=0) / (fs * float(win @ win))
    if nperseg % 2:
        P[1:] *= 2
    else:
        P[1:-1] *= 2
    return np.fft.rfftfreq(nperseg, 1.0 / fs), (P.real if y is None else P)


def cross_spectra(u, y, fs, nperseg, detrend="constant"):
    """Welch-averaged auto- and cross-spectra of an input and an output (Hann window, 50 %
    overlap): :func:`scipy.signal.welch` and :func:`scipy.signal.csd`.

    Parameters
    ----------
    u, y : array_like, shape (T,)
        Input (e.g. force [N]) and output (e.g. position [m]).
    fs : float
        Sample rate [Hz].
    nperseg : int
        Segment length [samples]; sets the resolution ``fs / nperseg`` [Hz].
    detrend : str
        Per-segment detrending (``"constant"`` or ``"linear"``; a drifting stage wants linear).

    Returns
    -------
    freqs_hz, s_uu, s_yy, s_uy : numpy.ndarray
        Frequencies [Hz] (0 to ``fs / 2``) and the spectral densities: the H1 FRF is
        ``s_uy / s_uu`` [unit of y / unit of u], the coherence ``|s_uy|**2 / (s_uu s_yy)``.

    Examples
    --------
    >>> u = np.random.default_rng(0).standard_normal(4000)
    >>> f, suu, syy, suy = cross_spectra(u, -2.0 * u, fs=1e3, nperseg=200)
    >>> bool(np.allclose(syy, 4.0 * suu) and np.allclose(suy, -2.0 * suu))
    True
    """
    f, s_uu = welch_csd(u, fs=fs, nperseg=nperseg, detrend=detrend)
    _, s_yy = welch_csd(y, fs=fs, nperseg=nperseg, detrend=detrend)
    _, s_uy = welch_csd(u, y, fs=fs, nperseg=nperseg, detrend=detrend)
    return f, s_uu, s_yy, s_uy


def error_spectrum(e, fs, window="hann"):
    """One-sided amplitude spectrum of an in-position error (seed Fig. 3.15).

    A single windowed FFT of the whole record (no averaging, resolution
    ``fs / T``), scaled so that a sinusoid of amplitude A on a frequency
    bin shows a peak of A (``2 |FFT(w e)| / sum(w)``; the DC and Nyquist
    bins are not doubled). With the default Hann window a tone between bins
    reads up to 15 % low; ``window="flattop"`` keeps that error below 0.1 %
    at the cost of a wider peak.

    Parameters
    ----------
    e : array_like, shape (..., T)
        Error signal [m], uniformly sampled.
    fs : float
        Sample rate [Hz].
    window : str or tuple
        Window specification for :func:`scipy.signal.get_window`.

    Returns
    -------
    freqs_hz : numpy.ndarray, shape (T // 2 + 1,)
        Frequencies [Hz].
    amplitude : numpy.ndarray, shape (..., T // 2 + 1)
        Amplitude spectrum [m].

    Examples
    --------
    >>> t = np.arange(2000) / 1e4
    >>> f, amp = error_spectrum(607e-9 * np.sin(2 * np.pi * 500 * t), fs=1e4)
    >>> float(f[np.argmax(amp)]), round(float(amp.max()) * 1e9, 6)
    (500.0, 607.0)
    """
    e = np.asarray(e, dtype=float)
    n = e.shape[-1]
    w = signal.get_window(window, n)
    amplitude = np.abs(np.fft.rfft(e * w, axis=-1)) * 2.0 / w.sum()
    amplitude[..., 0] /= 2.0
    if n % 2 == 0:
        amplitude[..., -1] /= 2.0
    return np.fft.rfftfreq(n, 1.0 / fs), amplitude


METRICS = ("settling_time_s", "rms_in_position_m", "peak_tracking_error_m", "rms_tracking_error_m")
"""Keys of the per-trial metrics published on ``/experiment/results``."""


def trial_metrics(t, x_ref, v_ref, y, *, window: float | None = None, target: float | None = None,
                  settle_start: float | None = None) -> dict:
    """Metrics of one trial from its samples (SI units).

    Parameters
    ----------
    t, x_ref, v_ref, y : array_like, shape (T,)
        Stage time [s], reference position [m] and velocity [m/s], measured position [m].
    window : float, optional
        Half-width of the settling band [m]; without it there is no settling time and the
        in-position RMS starts at ``settle_start``.
    target : float, optional
        Position the trial settles at [m]; default the last reference position.
    settle_start : float, optional
        Stage time [s] the reference reaches the target; default the sample after the
        last non-zero reference velocity (the trial's start if it never moves).

    Returns
    -------
    dict
        ``settling_time_s`` (nan if not settled), ``rms_in_position_m``,
        ``peak_tracking_error_m``, ``rms_tracking_error_m`` (``x_ref - y`` over the
        trial), plus the ``target_m`` and ``settle_start_s`` used.

    Examples
    --------
    >>> t = np.arange(6) * 1e-4
    >>> m = trial_metrics(t, [0, 1, 2, 2, 2, 2], [1, 1, 0, 0, 0, 0], [0, 0, 1, 2.5, 2, 2], window=0.1)
    >>> m["settle_start_s"], round(m["settling_time_s"], 6), m["peak_tracking_error_m"]
    (0.0002, 0.0002, 1.0)
    """
    t = np.asarray(t, float)
    x_ref = np.asarray(x_ref, float)
    y = np.asarray(y, float)
    if not t.size:
        return {k: math.nan for k in (*METRICS, "target_m", "settle_start_s")}
    if settle_start is None:
        moving = np.flatnonzero(np.nan_to_num(np.asarray(v_ref, float)) != 0)
        k = int(moving[-1]) + 1 if moving.size else 0
        settle_start = float(t[k]) if k < t.size else math.nan
    if target is None:
        target = float(x_ref[-1])
    peak, rms = tracking_errors(x_ref, y)
    if math.isnan(settle_start):
        ts = rms_ip = math.nan
    elif window:
        ts = float(settling_time(t, y, target, settle_start, window))
        rms_ip = float(rms_in_position(t, y, target, settle_start + ts)) if math.isfinite(ts) else math.nan
    else:
        ts = math.nan
        rms_ip = float(rms_in_position(t, y, target, settle_start))
    return {"settling_time_s": ts, "rms_in_position_m": rms_ip, "peak_tracking_error_m": float(peak),
            "rms_tracking_error_m": float(rms), "target_m": float(target), "settle_start_s": float(settle_start)}
