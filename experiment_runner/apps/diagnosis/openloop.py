"""Open-loop records: the judge's predictor and the simulated recordings without a reference.

A record without ``/stage/reference`` (a force/torque-mode identification run, an open-loop
excitation) has no loop to replay: the recorded command drove the plant. What the user gets
from a model is then its **open-loop prediction**: the recorded command (and the known
external force, ``/stage/external_force``) through the model's plant over windows, each
window started from the model's state *re-initialised from the measurement* (the force
observer (:mod:`.observer`), which makes the model follow the measured position, gives the
state at the window start, friction and joint states included); the window's initial position
and velocity are then re-estimated from the measured window (least squares of an offset and a
velocity offset, :func:`_initial_offset`: the smoothed measurement's velocity at the start is
biased where the command steps). Over a window the model runs on its own, so a missing force
shows as a curvature of the predicted position away from the measured one.

:class:`OpenLoopJudge` is :class:`.judge.ReplayJudge` with this predictor: the same
statistics (run-to-run floor from ``K`` simulated recordings with fixed noise seeds,
the simulation-calibrated adoption test, the score test on the data's own residual, the
consistency z), one channel (position [m]; the command is an input, its "error" is zero by
construction). The floor's ``K`` simulated recordings are made near the data
(:func:`sim_batch`) and predicted exactly as the data is (windows re-initialised from their own
measurement), so the floor holds the model's noise (drive, bearing, quantization) and the
uncertainty of the re-initialised state.

The position errors are **prewhitened** before they are squared: a window's error is dominated by
the drift of the re-initialised state (drive noise integrated twice: its spectrum falls as
``1/f^4``), which buries whatever the model misses at higher frequencies (a 1.5 kHz mode of 20 % of
the mass: 8.9x the floor's spectrum in its band, 0.93x the floor in RMS). The filter is the
AR(:data:`AR_ORDER`) prediction-error filter of the floor's own window errors (least squares over
the ``K`` simulated recordings, lags inside a window; a window's first ``AR_ORDER`` samples are
left out), scaled to unit RMS on them -- the noise model of a generalised-least-squares test, the
floor's simulated recordings being whitened by the same filter, so the test keeps its calibration
(the truth model at 0.98-1.01x its floor on the mode, damper and regularised-Coulomb records at
1 and 10 kHz), and an output-error fit on it (:func:`.refinement.refine_by_replay`, through
:meth:`OpenLoopJudge.residual`) is weighted least squares with that noise model. The reported RMS
errors stay in metres.

:func:`sim_batch` makes whole simulated recordings of an open-loop record (for the force
observer's noise floor and the drive-noise components): the model driven by the recorded
command, the known force and the force the model is missing (its observer's tracking force on
the data, low-passed, passed on as a known force: :func:`missing_force`), with noise: a recording near the data whose observer
residual is the model's noise alone.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.signal import savgol_filter

from stage_sim.plant import PlantInputs, PlantState

from . import engine as E
from .data import DiagData, smooth
from .judge import FLOOR_SEEDS, ReplayJudge
from .model import ModelSpec, coulomb_total, total_mass, viscous_total
from .observer import Observer
from .replay_floor import Floor, Replay

__all__ = ["WINDOW_S", "TINY_MOTION_STEPS", "tiny_motion", "OpenLoopJudge", "sim_batch", "window_replay",
           "noisy_model", "quiet_model", "LSQ_AGREE", "least_squares_check"]

WINDOW_S = 0.05
"""Length of the judge's open-loop windows [s] (at least 20 samples)."""

AR_ORDER = 8
"""Order of the judge's prewhitening filter (an AR model of the floor's window errors)."""

TINY_MOTION_STEPS = 50
"""A record whose every trial moves over at most this many encoder steps (a pre-sliding or
pre-rolling run: motion of a few counts under a force below breakaway) is judged over whole trials
(:func:`tiny_motion`)."""


def tiny_motion(data: DiagData, resolution: float) -> bool:
    """Whether every trial of ``data`` moves over at most :data:`TINY_MOTION_STEPS` steps of the
    sensor's ``resolution`` (its lattice; 0: none, never tiny).

    Over a 50 ms window such a motion is a fraction of a step: the window's re-estimated start
    state absorbs it, and what a model misses there (a pre-sliding stiffness that makes the stage
    yield by a few counts where rigid friction holds it) never shows. Friction holds the stage, so the
    model's own prediction does not drift: :class:`OpenLoopJudge` then predicts each trial whole
    from its start, without re-estimating the start from the window, and compares it quantized
    like the sensor (the predictor's model keeps the quantization) -- a model off by less than a step
    reads as the same counts, one off by a step reads as a whole step.

    Parameters
    ----------
    data : DiagData
        The record.
    resolution : float
        The sensor's step [m] or [rad].

    Returns
    -------
    bool

    Examples
    --------
    >>> import numpy as np
    >>> from experiment_runner.apps.diagnosis.data import DiagData
    >>> y = 1e-6 * np.round(3 * np.sin(np.linspace(0, 6, 500)))[:, None]
    >>> ok = np.ones_like(y, bool)
    >>> d = DiagData(rate=1e3, t0=np.zeros(1), x_ref=y, v_ref=0 * y, u=0 * y, y=y, valid=ok, fit=ok, held=ok,
    ...              lengths=np.array([500]), trial_ids=[0])
    >>> tiny_motion(d, 1e-6), tiny_motion(d, 1e-8), tiny_motion(d, 0.0)
    (True, False, False)
    """
    if not resolution > 0:
        return False
    for b in range(data.shape[1]):
        col = data.y[data.valid[:, b], b]
        if not len(col) or np.ptp(col) > TINY_MOTION_STEPS * resolution:
            return False
    return True


def quiet_model(spec: ModelSpec):
    """The full plant of ``spec`` without its random parts, the sensor's quantization kept
    (deterministic): the predictor's model.

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    stage_sim.plant_model.PlantModel
    """
    pm = spec.compiled().pm_full
    return pm._replace(noise_std=0.0, fr_noise=np.zeros_like(pm.fr_noise), q_bearing=0.0)


def noisy_model(spec: ModelSpec):
    """The full plant of ``spec`` (noise and quantization): the simulated recordings' model.

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    stage_sim.plant_model.PlantModel
    """
    return spec.compiled().pm_full


class OpenLoopJudge(ReplayJudge):
    """:class:`.judge.ReplayJudge` whose predictor is the open-loop windows (module docstring).

    Parameters
    ----------
    data : DiagData
        The open-loop record; its held-out samples (all usable ones if none) inside complete
        windows are judged.
    obs : observer.Observer
        The force observer on ``data`` (its smoothing and masks): it re-initialises the windows.
    window_s : float
        Window length [s] (at least 20 samples); windows tile each trial from its start.
    seeds : tuple of int
        As :class:`.judge.ReplayJudge`.
    alpha, z_block, block_s : float
        As :class:`.judge.ReplayJudge`.
    resolution : float
        The sensor's step (the model's encoder resolution; 0: none). A record of tiny motion
        (:func:`tiny_motion`) is predicted over whole trials (the shortest trial's length) from the
        observer's start state, the start not re-estimated (``whole`` True).
    """

    def __init__(self, data: DiagData, obs, window_s: float = WINDOW_S, seeds=FLOOR_SEEDS, alpha: float = 1e-3,
                 z_block: float = 2.0, block_s: float = 0.02, resolution: float = 0.0):
        self.whole = tiny_motion(data, resolution)
        self.L = int(np.min(data.lengths)) if self.whole else max(20, int(round(window_s * data.rate)))
        held = data.held if data.held.any() else (data.fit | data.held)
        k = np.arange(data.shape[0])[:, None]
        covered = k < (data.lengths[None, :] // self.L) * self.L
        super().__init__(dataclasses.replace(data, held=held & covered), seeds=seeds, alpha=alpha,
                         z_block=z_block, block_s=block_s)
        self.obs = obs
        self.fe = np.ascontiguousarray(data.known_force()[:, self.cols])
        self.inputs = tuple(np.ascontiguousarray(a[:, self.cols]) for a in data.plant_inputs())
        # the windows holding a judged sample: per window start s, the judged columns (indices into cols)
        n_s = data.shape[0] // self.L
        self.windows = [(s, np.flatnonzero(self.mask[s * self.L:(s + 1) * self.L].any(axis=0)))
                        for s in range(n_s)]
        self.windows = [(s, j) for s, j in self.windows if len(j)]
        # initial position and velocity offsets of a window: least squares of (1, t) over the window
        tt = np.arange(self.L) / data.rate
        self._basis = np.linalg.pinv(np.stack([np.ones(self.L), tt], axis=1)), np.stack([np.ones(self.L), tt], axis=1)

    # ------------------------------------------------------------------ predictor
    def _observed(self, spec: ModelSpec):
        """Observer run of ``spec`` on the judged trials: (snapshots every window start, tracking
        force (T, B)) (cached on the spec)."""
        key = ("open_loop_obs", self.token)
        hit = spec._compiled.get(key)
        if hit is None:
            res = self.obs.run(spec, cols=self.cols, snap_every=self.L)
            hit = spec._compiled[key] = (res.snaps[1:], res.r)
        return hit

    def _windows(self, pm, snaps, y, u, fe, inputs, seeds, cols):
        """Measured positions over every judged window (columns ``cols`` of the judged trials,
        repeated for each seed): the command ``u``, known force ``fe`` and plant inputs (T, C)
        from the states ``snaps``; other samples keep ``y`` (T, C). Returns (y, bad windows)."""
        sz, sf, sps, sdb = snaps
        y = y.copy()
        bad = 0
        L, n = self.L, pm.n
        for s, j in self.windows:
            jj = np.concatenate([j + i * len(self.cols) for i in range(len(seeds))]) if len(seeds) > 1 else j
            k0 = s * L
            W = len(jj)
            st = [np.ascontiguousarray(a[s][..., jj]) for a in (sz, sf, sps, sdb)]
            st += [np.zeros((n, W)), np.zeros((2 * n, W)), np.zeros(W)]
            u_w, fe_w, *in_w = (np.ascontiguousarray(a[k0:k0 + L, jj]) for a in (u, fe) + tuple(inputs))
            sd = np.concatenate([sk + cols[j] for sk in seeds]).astype(np.int64)
            out_x, out_y = np.empty((L, W)), np.empty((L, W))
            bad += E.open_loop(pm, PlantInputs(u_w, *in_w, fe_w), k0, PlantState(*st), out_x, sd, out_y)
            y[k0:k0 + L, jj] = out_y if self.whole else out_y + _initial_offset(y[k0:k0 + L, jj] - out_y, self._basis)
        self.sims += 1
        return y, bad

    def replay(self, spec: ModelSpec) -> Replay:
        """Noise-free open-loop windows of ``spec`` (cached on the spec); ``u`` = the recorded command.

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        Replay
        """
        key = ("judge_replay", self.token)
        hit = spec._compiled.get(key)
        if hit is not None:
            return hit
        snaps, _ = self._observed(spec)
        y, bad = self._windows(quiet_model(spec), snaps, self.y, self.u, self.fe, self.inputs, [0], self.cols)
        ok, why = True, ""
        if bad or not np.all(np.isfinite(y[self.mask])):
            ok, why = False, f"open-loop prediction diverged or left the travel in {bad} window(s)"
        r = Replay(u=self.u, y=y, ok=ok, why=why)
        spec._compiled[key] = r
        return r

    def floor(self, spec: ModelSpec) -> Floor:
        """Run-to-run floor of ``spec``: ``K`` recordings simulated from it near the data (the
        recorded command, known force and the model's observer force, with noise; :func:`sim_batch`),
        each predicted as the data is -- windows re-initialised from ITS measurement -- so the floor
        holds the model's noise and the uncertainty of the re-initialised state. The simulated
        recording ``k`` is stored as the data's prediction plus its own prediction error, so the
        judge's statistics (``S_k - R``) are those of the closed-loop judge.

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        Floor
        """
        rp = self.replay(spec)
        _, r = self._observed(spec)
        r = missing_force(r, self.obs.data.lengths[self.cols], self.rate, self.obs.f_o)
        K, B = self.K, len(self.cols)
        tile = lambda a: np.ascontiguousarray(np.tile(a, (1, K)))  # noqa: E731
        pm = noisy_model(spec)
        fe = tile(self.fe + r)
        inputs = [tile(a) for a in self.inputs]
        st = list(E.new_state(pm, tile(self.obs.ys[:1, self.cols])[0], sai_mode=float(self.inputs[2][0, 0])))
        T = self.u.shape[0]
        out_x, ys = np.empty((T, B * K)), np.empty((T, B * K))
        sd = np.concatenate([s + self.cols for s in self.seeds]).astype(np.int64)
        u = tile(self.u)
        E.open_loop(pm, PlantInputs(u, *inputs, fe), 0, PlantState(*st), out_x, sd, ys)
        d = self.obs.data
        lengths = np.tile(d.lengths[self.cols], K)
        valid = tile(d.valid[:, self.cols])
        sim = DiagData(rate=d.rate, t0=np.tile(d.t0[self.cols], K), x_ref=ys, v_ref=tile(d.v_ref[:, self.cols]), u=u,
                       y=ys, valid=valid, fit=valid.copy(), held=valid.copy(), lengths=lengths,
                       trial_ids=list(range(B * K)), f_ext=fe, open_loop=True, d0=inputs[0], d1=inputs[1],
                       mode=inputs[2])
        so = Observer(sim, bandwidth=self.obs.f_o, smooth_hz=d.smooth_hz)
        res = so.run(spec, snap_every=self.L)
        pred, bad = self._windows(quiet_model(spec), res.snaps[1:], ys, u, fe, inputs, self.seeds, self.cols)
        eps = (ys - pred).reshape(T, K, B).transpose(1, 0, 2)
        y = rp.y[None] + eps
        de = eps[:, self.mask]
        q = spec.preset.stage.encoder.resolution
        sy = max(float(np.sqrt(np.mean(de ** 2))) if de.size else 1.0, q / math.sqrt(12.0), self.y_resolution, 1e-15)
        tiny_u = 1e-4 * (float(np.sqrt(np.mean(self.u[self.mask] ** 2))) if self.n else 1.0) or 1e-12
        return Floor(spec=spec, replay=rp, u=np.broadcast_to(self.u, y.shape), y=y, sigma_u=tiny_u,
                     sigma_y=sy, white=self._whitening(eps, sy))

    # ------------------------------------------------------------------ prewhitening
    def _whitening(self, eps: np.ndarray, sy: float) -> np.ndarray:
        """Prewhitening filter of the floor's window errors ``eps`` (K, T, B): the AR(``AR_ORDER``)
        prediction-error filter fitted by least squares to the simulated recordings' judged window
        errors (lags inside a window only), scaled so that their filtered RMS is 1. Without noise
        (errors ~ 0) the identity scaled by ``1 / sy``. Whole trials of tiny motion (``whole``): the
        identity scaled to unit RMS -- their errors are whole encoder steps that come and go, an AR
        filter of them is a near-differentiator that would cancel a missing slow motion of
        several steps (a Coulomb model that holds where the stage yields by +-4 counts: 2.6 steps
        RMS against its floor's 0.45, D 1.3 prewhitened, 34 not)."""
        if self.whole:
            s = float(np.sqrt(np.mean(eps[:, self.mask] ** 2))) if self.n else 0.0
            return np.array([1.0 / (s if s > 1e-12 * sy and np.isfinite(s) else sy)])
        p = AR_ORDER
        L = self.L
        n_s = eps.shape[1] // L
        E = eps[:, :n_s * L].reshape(eps.shape[0], n_s, L, -1)
        M = np.broadcast_to(self.mask[:n_s * L].reshape(n_s, L, -1)[None, :, p:], E[:, :, p:].shape)
        Y = E[:, :, p:][M]
        X = np.stack([E[:, :, p - l:L - l][M] for l in range(1, p + 1)], axis=1)
        a = np.r_[1.0, np.zeros(p)]
        if Y.size > 10 * p and np.any(Y):
            c, *_ = np.linalg.lstsq(X, Y, rcond=None)
            if np.all(np.isfinite(c)):
                a = np.r_[1.0, -c]
        w = np.stack([self._white(eps[k], a) for k in range(eps.shape[0])])[:, self.mask]
        s = float(np.sqrt(np.mean(w ** 2))) if w.size else 0.0
        return a / (s if s > 1e-12 * sy and np.isfinite(s) else sy)

    def _white(self, e: np.ndarray, a: np.ndarray) -> np.ndarray:
        """``e`` (T, C) through the filter ``a``, window by window: a window's first ``len(a) - 1``
        samples (whose lags would reach into the previous window) and the samples after the last
        complete window are 0."""
        L, p = self.L, len(a) - 1
        n_s = e.shape[0] // L
        E = e[:n_s * L].reshape(n_s, L, -1)
        out = np.zeros_like(e)
        O = out[:n_s * L].reshape(n_s, L, -1)
        O[:, p:] = a[0] * E[:, p:]
        for l in range(1, p + 1):
            O[:, p:] += a[l] * E[:, p - l:L - l]
        return out

    # ------------------------------------------------------------------ errors (whitened)
    def _errors(self, u, y, rp: Replay, fl: Floor) -> list:
        """One channel, the prewhitened position error (the command is the input: no error)."""
        return [self._white(y - rp.y, fl.white)]

    def rms(self, rp: Replay) -> tuple[float, float]:
        """RMS errors on the judged samples: command (0: it is the input), position [m].

        Parameters
        ----------
        rp : Replay
            A prediction on the judged samples.

        Returns
        -------
        tuple of float
        """
        if not self.n:
            return float("nan"), float("nan")
        return 0.0, float(np.sqrt(np.mean((self.y - rp.y)[self.mask] ** 2)))

    def floor_ratio(self, rp: Replay, fl: Floor) -> float:
        """Data's prediction error over the floor's, RMS ratio (1 = at the run-to-run floor; one channel).

        Parameters
        ----------
        rp : Replay
            A prediction.
        fl : Floor
            The floor whose units are used.

        Returns
        -------
        float
        """
        Dk = self.sim_blocks(rp, fl).sum(axis=1) / max(self.n, 1)
        return float(math.sqrt(self.D(rp, fl) / max(float(np.mean(Dk)), 1.0)))


MISSING_LP = 0.2
"""Cutoff of the low-pass of the observer force passed to the simulated recordings, in observer
bandwidths."""


def missing_force(r: np.ndarray, lengths, rate: float, f_o: float) -> np.ndarray:
    """The force a model misses on the data, for its simulated recordings: the observer's tracking
    force ``r`` (T, B) low-passed (zero phase) at ``MISSING_LP * f_o``. Near the smoothing cutoff the
    tracking force also holds the smoothing's own misfit of fast command changes; a simulated recording
    must show that misfit itself (as the data does), not have it added: below the cutoff it keeps the
    simulated recording near the data (the model's missing physics), above it the model runs free.

    Parameters
    ----------
    r : numpy.ndarray
        (T, B) observer tracking force [N].
    lengths : array_like of int
        Samples per trial.
    rate : float
        Sample rate [Hz].
    f_o : float
        Observer bandwidth [Hz].

    Returns
    -------
    numpy.ndarray
        (T, B) [N].
    """
    return smooth(r, rate, MISSING_LP * f_o, lengths)[0]


def _initial_offset(e: np.ndarray, basis) -> np.ndarray:
    """(L, W): the part of the window errors ``e`` (measured - predicted) that an initial position
    and velocity offset explain (least squares of ``a + b t`` per column): the window's start state
    re-estimated from the measurement over the window. The observer's state at the window start
    follows the *smoothed* measurement, whose velocity is biased where the command steps; left in,
    that bias is a model-dependent error a wrong delay or mass could cancel."""
    pinv, X = basis
    return X @ (pinv @ e)


def window_replay(spec: ModelSpec, data: DiagData) -> dict:
    """The open-loop windows of ``spec`` over every usable sample of ``data`` as a replay dict
    (:func:`.predict.replay`'s keys; ``u`` the recorded command, ``y``/``x`` the prediction).

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        An open-loop record.

    Returns
    -------
    dict
    """
    obs = Observer(data, bandwidth=data.rate / 25.0, smooth_hz=data.smooth_hz or None)
    j = OpenLoopJudge(dataclasses.replace(data, held=data.valid.copy()), obs,
                      resolution=spec.preset.stage.encoder.resolution)
    rp = j.replay(spec)
    y = data.y.copy()
    y[:, j.cols] = np.where(j.mask, rp.y, np.nan)
    d0, d1, mode = data.plant_inputs()
    return {"y": y, "u": data.u.copy(), "x": y, "d0": d0, "d1": d1, "mode": mode}


def sim_batch(spec: ModelSpec, data: DiagData, seeds) -> list:
    """Recordings simulated from ``spec`` on an open-loop record, one per seed (one kernel call):
    the recorded command, the known force plus ``spec``'s observer force on the data (as a known
    force), the model's noise; each a :class:`DiagData` with the record's masks and split.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    data : DiagData
        An open-loop record.
    seeds : iterable of int
        One recording per seed.

    Returns
    -------
    list of DiagData
    """
    obs = Observer(data, bandwidth=data.rate / 25.0, smooth_hz=data.smooth_hz or None)
    res = obs.run(spec)
    pm = noisy_model(spec)
    seeds = list(seeds)
    T, B = data.shape
    K = len(seeds)
    fe = data.known_force() + missing_force(res.r, data.lengths, data.rate, obs.f_o)
    st = list(E.new_state(pm, np.tile(obs.ys[0], K), sai_mode=float(obs.inputs[2][0, 0])))
    tile = lambda a: np.ascontiguousarray(np.tile(a, (1, K)))  # noqa: E731
    out_x, out_y = np.empty((T, B * K)), np.empty((T, B * K))
    sd = np.concatenate([s + np.arange(B) for s in seeds]).astype(np.int64)
    E.open_loop(pm, PlantInputs(tile(data.u), *(tile(a) for a in obs.inputs), tile(fe)), 0, PlantState(*st), out_x, sd,
                out_y)
    part = lambda a, i: np.ascontiguousarray(a[:, i * B:(i + 1) * B])  # noqa: E731
    out = []
    for i, s in enumerate(seeds):
        y = part(out_y, i)
        out.append(DiagData(rate=data.rate, t0=data.t0.copy(), x_ref=y, v_ref=data.v_ref, u=data.u, y=y,
                            valid=data.valid.copy(), fit=data.fit.copy(), held=data.held.copy(), lengths=data.lengths,
                            trial_ids=list(data.trial_ids), source=f"simulated open loop (seed {s})", split=data.split,
                            d0=data.d0, d1=data.d1, mode=data.mode, f_ext=fe, open_loop=True))
    return out


LSQ_AGREE = 0.10
"""Relative difference within which the model's rigid-body parameters agree with the least-squares
check (:func:`least_squares_check`)."""


def least_squares_check(data: DiagData, spec: ModelSpec) -> dict | None:
    """An ordinary least-squares check of a torque/force-mode record's rigid body, independent of
    the diagnosis' models: ``kf u + f_ext = J a + F_C sign(v) + c v`` over the moving samples,
    position, velocity and acceleration by a Savitzky-Golay filter (cubic, 25 ms) and the force by
    the same smoothing filter (both sides filtered alike), ``kf`` the model's force constant.

    The samples used move faster than 20 % of the trial's RMS velocity and at least 10 sensor steps
    per window (the sign of the velocity is then certain); standard errors from the residual's
    scatter over 40 ms blocks (the smoothing correlates neighbours). A model whose inertia, Coulomb
    or viscous term is off by more than :data:`LSQ_AGREE` and 3 standard errors of the check is
    worth a look (elasticity, a mode, or a friction law the rigid regression does not have moves
    the check itself).

    Parameters
    ----------
    data : DiagData
        An open-loop record.
    spec : ModelSpec
        The model compared (the improved one): its total mass, Coulomb force and viscous sum.

    Returns
    -------
    dict or None
        ``samples``, ``inertia``, ``coulomb``, ``viscous`` (each ``{value, sigma, model, agree}``;
        SI on the record's axis), ``tolerance`` (:data:`LSQ_AGREE`), ``agree`` (all three); None where fewer than 50 samples move
        or the regression is singular.

    Examples
    --------
    >>> import numpy as np
    >>> from experiment_runner.apps.diagnosis.model import load_model
    >>> from experiment_runner.apps.diagnosis.data import DiagData
    >>> rate, m = 1000.0, 2.0
    >>> t = np.arange(4000) / rate
    >>> v = 0.05 * np.sin(2 * np.pi * t)                        # a = v', x = integral of v
    >>> x, a = (0.05 / (2 * np.pi)) * (1 - np.cos(2 * np.pi * t)), 0.05 * 2 * np.pi * np.cos(2 * np.pi * t)
    >>> spec = load_model("fi_stage_nofi")
    >>> u = (m * a + 3.0 * np.sign(v) + 20.0 * v) / spec.preset.stage.drive.force_constant   # a drive command
    >>> ok = np.ones((4000, 1), bool)
    >>> d = DiagData(rate=rate, t0=np.zeros(1), x_ref=x[:, None], v_ref=0 * x[:, None], u=u[:, None],
    ...              y=x[:, None], valid=ok, fit=ok, held=ok, lengths=np.array([4000]), trial_ids=[0],
    ...              open_loop=True)
    >>> c = least_squares_check(d, spec)
    >>> [round(c[k]["value"], 2) for k in ("inertia", "coulomb", "viscous")]
    [2.0, 3.0, 20.0]
    """
    st = spec.preset.stage
    kf = st.drive.force_constant * st.drive.force_constant_ratio
    win = max(7, 2 * int(round(0.0125 * data.rate)) + 1)
    q = st.encoder.resolution
    rows, rhs, blocks = [], [], []
    F = data.u * kf + data.known_force()
    blk = max(1, int(round(0.04 * data.rate)))
    for b in range(data.shape[1]):
        n = int(data.lengths[b])
        if n < 3 * win:
            continue
        y = data.y[:n, b]
        v = savgol_filter(y, win, 3, deriv=1, delta=1.0 / data.rate)
        a = savgol_filter(y, win, 3, deriv=2, delta=1.0 / data.rate)
        f = savgol_filter(F[:n, b], win, 3)
        ok = data.valid[:n, b].copy()
        ok[:win] = ok[-win:] = False
        v_rms = float(np.sqrt(np.mean(v[ok] ** 2))) if ok.any() else 0.0
        ok &= np.abs(v) > max(0.2 * v_rms, 10 * q * data.rate / win)
        k = np.flatnonzero(ok)
        rows.append(np.c_[a[k], np.sign(v[k]), v[k]])
        rhs.append(f[k])
        blocks.append(b * 10 ** 9 + k // blk)
    if not rows or sum(len(r) for r in rhs) < 50:
        return None
    A, f, g = np.concatenate(rows), np.concatenate(rhs), np.concatenate(blocks)
    scale = np.maximum(np.sqrt(np.mean(A ** 2, axis=0)), 1e-300)
    As = A / scale
    try:
        theta, *_ = np.linalg.lstsq(As, f, rcond=None)
        inv = np.linalg.inv(As.T @ As)
    except np.linalg.LinAlgError:
        return None
    r = f - As @ theta
    _, gi = np.unique(g, return_inverse=True)
    S = np.zeros((gi.max() + 1, 3))
    np.add.at(S, gi, As * r[:, None])               # block-robust (cluster) sandwich
    cov = inv @ (S.T @ S) @ inv
    theta, sig = theta / scale, np.sqrt(np.maximum(np.diag(cov), 0.0)) / scale
    model = (total_mass(spec.preset), coulomb_total(spec.preset), viscous_total(spec.preset))
    out = {"samples": int(len(f)), "tolerance": LSQ_AGREE}
    for name, val, s, mv in zip(("inertia", "coulomb", "viscous"), theta, sig, model):
        off = abs(mv - val)
        out[name] = {"value": float(val), "sigma": float(s), "model": float(mv),
                     "agree": bool(off <= LSQ_AGREE * abs(val) or off <= 3 * s)}
    out["agree"] = all(out[k]["agree"] for k in ("inertia", "coulomb", "viscous"))
    return out
