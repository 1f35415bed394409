"""Predict: what the nominal model says about a recording, and where it is short.

Three views, all from the three contract topics alone:

1. **Closed-loop replay** (:func:`replay`): the recorded reference through the model and
   its controller in closed loop (:func:`experiment_runner.core.batch.simulate`). Compared with the recording: command
   error ``u_meas - u_sim`` (within the servo bandwidth, the force the model is missing)
   and position error ``y_meas - y_sim``.
2. **Force residual** (:class:`.observer.Observer`): the force observer of :mod:`.engine` -- the
   model, driven by the recorded command, follows the measured position; the tracking
   force ``r[k]`` is the force the model is missing at each sample (zero up to noise
   when the model is right). This is what the effects are fitted to.
3. **Open-loop windows** (:func:`open_loop_windows`): the recorded command through the
   model in open loop over short windows, each re-initialised from the observer state
   (which follows the measurement); the position drift at the window end, and the
   constant force that would explain it (``2 m e / T_w^2``).

The *noise floor* (:class:`NoiseFloor`) is the force residual of recordings simulated from
the model itself on the recorded reference (closed-loop replays with other noise seeds,
quantized like the sensor): what a perfect model would leave. Its spectrum defines the
*whitening* filter: residuals are compared in units of the noise floor (a whitened
mean square of 1 = indistinguishable from a perfect model).
"""
from __future__ import annotations


import math

import numpy as np
from scipy import signal

from experiment_runner.core.batch import simulate
from experiment_runner.core.metrics import welch_csd

from stage_sim.plant import PlantInputs, PlantState

from . import engine as E
from .data import DiagData
from .model import ModelSpec
from .observer import Observer, ObsResult
from .openloop import sim_batch as open_loop_sim_batch
from .openloop import window_replay

__all__ = ["replay", "sim_data", "sim_batch", "NoiseFloor", "open_loop_windows", "closed_loop", "band_rms",
           "force_resolution", "taper"]


# --------------------------------------------------------------------------- closed loop
def closed_loop(spec: ModelSpec, x_ref, v_ref, seeds, f_ext=None):
    """Closed-loop runs of ``spec`` on references (T, B) with noise ``seeds`` (B,) and the known
    external table force ``f_ext`` (T, B; None: none): the batch engine
    (:func:`experiment_runner.core.batch.simulate`) itself.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    x_ref, v_ref : numpy.ndarray
        (T, B) references [m], [m/s].
    seeds : array_like of int
        (B,) noise seeds.
    f_ext : numpy.ndarray, optional
        (T, B) known external table force [N].

    Returns
    -------
    y, u, x_true : numpy.ndarray
        (T, B) measured position [m], command [N], true table position [m].
    inputs : tuple of numpy.ndarray
        ``(d0, d1, mode)``: the plant's dither forces [N] and SAI command, (T, B) each.
    """
    fe = None if f_ext is None else np.asarray(f_ext, float).T
    res = simulate(spec.preset, np.asarray(x_ref, float).T, np.asarray(v_ref, float).T,
                   seeds=np.asarray(seeds, np.int64), check=False, f_ext=fe)
    inputs = (res.dither[..., 0].T.copy(), res.dither[..., 1].T.copy(), res.mode.T.copy())
    return res.y.T.copy(), res.u.T.copy(), res.x_table.T.copy(), inputs


def sim_batch(spec: ModelSpec, data: DiagData, seeds) -> list:
    """Recordings simulated from ``spec`` on the recorded reference, one per seed, in ONE batch
    call (trials x seeds); each is a :class:`DiagData` with the recording's masks and split.
    An open-loop record: :func:`.openloop.sim_batch` (the recorded command, no controller).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    seeds : iterable of int
        One simulated recording per seed (trial ``b`` gets ``seed + b``).

    Returns
    -------
    list of DiagData
    """
    if data.open_loop:
        return open_loop_sim_batch(spec, data, seeds)
    B = data.shape[1]
    seeds = list(seeds)
    xr = np.tile(data.x_ref, (1, len(seeds)))
    vr = np.tile(data.v_ref, (1, len(seeds)))
    fe = None if data.f_ext is None else np.tile(data.f_ext, (1, len(seeds)))
    y, u, _, inputs = closed_loop(spec, xr, vr, np.concatenate([s + np.arange(B) for s in seeds]), fe)
    part = lambda a, i: np.ascontiguousarray(a[:, i * B:(i + 1) * B])  # noqa: E731
    return [DiagData(rate=data.rate, t0=data.t0.copy(), x_ref=data.x_ref, v_ref=data.v_ref,
                     u=part(u, i), y=part(y, i), valid=data.valid.copy(), fit=data.fit.copy(), held=data.held.copy(),
                     lengths=data.lengths, trial_ids=list(data.trial_ids), source=f"simulated (seed {s})",
                     split=data.split, d0=part(inputs[0], i), d1=part(inputs[1], i), mode=part(inputs[2], i),
                     f_ext=data.f_ext)
            for i, s in enumerate(seeds)]


def replay(spec: ModelSpec, data: DiagData, seed: int = 1000):
    """Closed-loop replay of the recorded reference; returns dict of (T, B) arrays. An open-loop
    record: the model's open-loop windows re-initialised from the measurement, over all samples
    (:func:`.openloop.window_replay`; ``u`` is the recorded command).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    seed : int, optional
        Noise seed of the first trial (trial ``b``: ``seed + b``).

    Returns
    -------
    dict
        ``y`` [m], ``u`` [N], ``x`` [m], ``d0``, ``d1`` [N], ``mode``: (T, B) arrays.
    """
    if data.open_loop:
        return window_replay(spec, data)
    B = data.shape[1]
    y, u, x, inputs = closed_loop(spec, data.x_ref, data.v_ref, seed + np.arange(B), data.f_ext)
    return {"y": y, "u": u, "x": x, "d0": inputs[0], "d1": inputs[1], "mode": inputs[2]}


def sim_data(spec: ModelSpec, data: DiagData, seed: int) -> DiagData:
    """A recording simulated from ``spec`` on the recorded reference, same masks and split.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        The recording.
    seed : int
        Noise seed.

    Returns
    -------
    DiagData
    """
    return sim_batch(spec, data, [seed])[0]


def compare_replay(data: DiagData, rp: dict) -> dict:
    """RMS command and position errors of a replay against the recording (valid samples).

    Parameters
    ----------
    data : DiagData
        The recording.
    rp : dict
        A replay (:func:`replay`).

    Returns
    -------
    dict
        ``rms_command_error_N``, ``rms_position_error_m``, ``rms_command_N``.
    """
    m = data.valid
    du = (data.u - rp["u"])[m]
    dy = (data.y - rp["y"])[m]
    return {"rms_command_error_N": float(np.sqrt(np.mean(du ** 2))),
            "rms_position_error_m": float(np.sqrt(np.mean(dy ** 2))),
            "rms_command_N": float(np.sqrt(np.mean(data.u[m] ** 2)))}


# --------------------------------------------------------------------------- noise floor
def taper(r: np.ndarray, mask: np.ndarray, n_taper: int = 16) -> np.ndarray:
    """Residual with the masked-out samples set to zero, edges tapered (per column).

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) residual.
    mask : numpy.ndarray
        (T, B) bool: samples kept.
    n_taper : int, optional
        Samples of the raised-cosine taper at each end of a column's kept samples (columns
        with fewer than ``2 n_taper`` kept samples are not tapered).

    Returns
    -------
    numpy.ndarray
        (T, B).
    """
    out = np.where(mask, r, 0.0)
    if n_taper > 0:
        w = 0.5 - 0.5 * np.cos(np.pi * np.arange(n_taper) / n_taper)
        for b in range(r.shape[1]):
            idx = np.flatnonzero(mask[:, b])
            if len(idx) < 2 * n_taper:
                continue
            # taper at every edge of a run of valid samples
            brk = np.flatnonzero(np.diff(idx) > 1)
            starts = np.r_[idx[0], idx[brk + 1]]
            stops = np.r_[idx[brk], idx[-1]] + 1
            for s0, s1 in zip(starts, stops):
                nt = min(n_taper, (s1 - s0) // 2)
                if nt < 1:
                    continue
                ww = w[:: max(1, n_taper // nt)][:nt] if nt < n_taper else w
                out[s0:s0 + nt, b] *= ww[:nt]
                out[s1 - nt:s1, b] *= ww[:nt][::-1]
    return out


def force_resolution(spec, f_o: float) -> float:
    """The least force [N] a recording resolves through the force observer of bandwidth ``f_o``:
    the rigid mass (table and bearings) times the acceleration of the encoder's uniform
    quantization error (``q / sqrt(12)``) at ``f_o``.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    f_o : float
        Observer bandwidth [Hz].

    Returns
    -------
    float

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> from experiment_runner.apps.diagnosis.model import ModelSpec
    >>> f = force_resolution(ModelSpec(load_preset("fi_stage_nofi")), 40.0)
    >>> 1e-7 < f < 1e-3
    True
    """
    st = spec.preset.stage
    m = st.table.mass + sum(b.mass for b in st.bearings)
    return float(m * (2 * math.pi * f_o) ** 2 * max(st.encoder.resolution, 1e-12) / math.sqrt(12.0))


class NoiseFloor:
    """Spectrum of the force residual a perfect model leaves, and the whitening filter.

    Built from the force residual of simulated recordings (``residuals``: list of (T, B)
    arrays with their masks). ``W(f) = 1/sqrt(S(f))`` up to ``f_max``, rolled off above;
    :meth:`whiten` applies it (zero phase, FFT) so the floor has unit mean square. ``rms_min``
    [N]: the least residual a recording resolves (:func:`force_resolution`), a white floor under
    ``S(f)``: a model whose simulated recordings leave no residual at all (a stage held by
    Coulomb friction that never slips: its measurement never changes) still has a floor.

    Parameters
    ----------
    rate : float
        Sample rate [Hz].
    residuals : list of numpy.ndarray
        (T, B) force residuals [N] of simulated recordings.
    masks : list of numpy.ndarray
        (T, B) bool: their samples to use.
    f_max : float
        Whitening band [Hz]; rolled off above (8th order).
    nperseg : int, optional
        Welch segment length.
    rms_min : float, optional
        The least residual a recording resolves [N].

    Raises
    ------
    ValueError
        The simulated residual is not finite, or no column has 64 usable samples.
    """

    def __init__(self, rate: float, residuals, masks, f_max: float, nperseg: int = 1024, rms_min: float = 0.0):
        self.rate = rate
        self.f_max = f_max
        self._gains = {}      # (FFT length, scale) -> gain (:meth:`gain`)
        segs = []
        for r, m in zip(residuals, masks):
            if not np.all(np.isfinite(r[m])) or np.max(np.abs(r[m]), initial=0.0) > 1e100:
                raise ValueError("noise floor: the simulated residual is not finite (the model diverged)")
            rt = taper(r, m)
            for b in range(r.shape[1]):
                n = int(m[:, b].sum())
                if n < 64:
                    continue
                f, p = welch_csd(rt[:, b], fs=rate, nperseg=min(nperseg, n), detrend="constant")
                # welch on zero-filled data: scale by the valid fraction
                segs.append(np.interp(np.linspace(0, rate / 2, nperseg // 2 + 1), f, p) * len(rt) / n)
        if not segs:
            raise ValueError("noise floor: no usable simulated residual")
        self.f = np.linspace(0, rate / 2, nperseg // 2 + 1)
        s = np.maximum(np.mean(segs, axis=0), rms_min ** 2 / (rate / 2))
        # smooth in log-frequency, floor it
        s = signal.savgol_filter(np.log(np.maximum(s, 1e-300)), 9, 2, mode="interp") if len(s) > 9 else np.log(s)
        s = np.exp(s)
        s = np.maximum(s, 1e-6 * np.median(s))
        self.psd = s
        self.scale = 1.0
        # normalise: whitened simulated residuals have unit mean square
        ms = []
        for r, m in zip(residuals, masks):
            w = self.whiten(r, m)
            ms.append(np.sum(w[m] ** 2) / max(1, m.sum()))
        m_ = float(np.mean(ms))
        if not (m_ > 0 and math.isfinite(m_)):
            # no residual at all: the floor is the white bound; its whitened mean square (Parseval)
            roll2 = 1.0 / (1.0 + (self.f / f_max) ** 8)
            m_ = float(np.trapezoid(rms_min ** 2 / (rate / 2) / self.psd * roll2, self.f)) if rms_min > 0 else 1.0
        self.scale = 1.0 / math.sqrt(m_)
        self.sim_ms = [float(x * self.scale ** 2) for x in ms]

    def gain(self, n: int) -> np.ndarray:
        """The whitening gain on the ``rfft`` grid of ``n`` samples (scaled: unit mean square floor),
        computed once per length and scale (every residual a fit evaluates is whitened by it).

        Parameters
        ----------
        n : int
            FFT length.

        Returns
        -------
        numpy.ndarray
            ``n // 2 + 1`` gains [1/N] (read-only: shared by every call).
        """
        key = (n, self.scale)
        g = self._gains.get(key)
        if g is None:
            f = np.fft.rfftfreq(n, 1.0 / self.rate)
            g = 1.0 / np.sqrt(np.interp(f, self.f, self.psd))
            roll = 1.0 / np.sqrt(1.0 + (f / self.f_max) ** 8)
            g = g * roll
            g[0] = g[1] if len(g) > 1 else g[0]
            g = g * self.scale
            g.flags.writeable = False
            self._gains[key] = g
        return g

    def whiten(self, r: np.ndarray, mask: np.ndarray) -> np.ndarray:
        """Whitened residual (same shape); masked-out samples are zero before and after.

        Parameters
        ----------
        r : numpy.ndarray
            (T, B) residual [N].
        mask : numpy.ndarray
            (T, B) bool.

        Returns
        -------
        numpy.ndarray
        """
        T = r.shape[0]
        n = int(2 ** np.ceil(np.log2(2 * T)))
        g = self.gain(n)
        rt = taper(r, mask)
        w = np.fft.irfft(np.fft.rfft(rt, n=n, axis=0) * g[:, None], n=n, axis=0)[:T]
        return np.where(mask, w, 0.0)

    def ms(self, r: np.ndarray, mask: np.ndarray) -> float:
        """Whitened mean square over ``mask`` (1 = noise floor).

        Parameters
        ----------
        r : numpy.ndarray
            (T, B) residual [N].
        mask : numpy.ndarray
            (T, B) bool.

        Returns
        -------
        float
        """
        w = self.whiten(r, mask)
        return float(np.sum(w[mask] ** 2) / max(1, mask.sum()))


def band_rms(r: np.ndarray, mask: np.ndarray, rate: float, f_hi: float) -> float:
    """RMS [N] of the residual low-passed (zero phase, 2nd order) at ``f_hi``, over ``mask``.

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) residual [N].
    mask : numpy.ndarray
        (T, B) bool.
    rate : float
        Sample rate [Hz].
    f_hi : float
        Cutoff [Hz].

    Returns
    -------
    float
        NaN for an empty mask.
    """
    sos = signal.butter(2, min(0.95, 2 * f_hi / rate), output="sos")
    rl = signal.sosfiltfilt(sos, taper(r, mask), axis=0)
    return float(np.sqrt(np.mean(rl[mask] ** 2))) if mask.any() else float("nan")


# --------------------------------------------------------------------------- open-loop windows
def open_loop_windows(spec: ModelSpec, obs: Observer, res: ObsResult, length: int):
    """Open-loop windows from the observer snapshots (``res`` run with ``snap_every=length``).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    obs : Observer
        The observer that ran.
    res : ObsResult
        Its run, with snapshots.
    length : int
        Window length [samples].

    Returns
    -------
    dict
        ``start`` (W,), ``trial`` (W,), ``drift_m`` (W,) position error at the window end,
        ``force_N`` (W,) constant force explaining the drift (rigid-body approximation
        ``2 m e / T^2``), ``err`` (length, W) the position error over each window.
    """
    every, sz, sf, sps, sdb = res.snaps
    data = obs.data
    c = spec.compiled()
    T, B = data.shape
    starts, trials, outs = [], [], []
    for s in range(sz.shape[0]):
        k0 = s * every
        cols = [b for b in range(B) if k0 + length <= data.lengths[b] and data.valid[k0:k0 + length, b].all()]
        if not cols:
            continue
        st = [np.ascontiguousarray(a[s][..., cols]) for a in (sz, sf, sps, sdb)]
        st += [np.zeros((c.pm.n, len(cols))), np.zeros((2 * c.pm.n, len(cols))), np.zeros(len(cols))]
        out = np.empty((length, len(cols)))
        window = [np.ascontiguousarray(a[k0:k0 + length, cols]) for a in (obs.u,) + obs.inputs]
        fe = (np.ascontiguousarray(obs.fe[k0:k0 + length, cols]) if obs.fe is not None and np.any(obs.fe)
              else np.zeros((0, 0)))
        E.open_loop(c.pm, PlantInputs(*window, fe), k0, PlantState(*st), out)
        starts += [k0] * len(cols)
        trials += cols
        outs.append(out)
    if not starts:
        return None
    starts = np.array(starts, np.int64)
    trials = np.array(trials, np.int64)
    out = np.concatenate(outs, axis=1)
    idx = starts[None, :] + np.arange(length)[:, None]
    err = obs.ys[idx, trials[None, :]] - out
    Tw = (length - 1) / data.rate
    drift = err[-1]
    return {"start": starts, "trial": trials, "drift_m": drift, "force_N": 2 * c.m_eff * drift / Tw ** 2, "err": err}
