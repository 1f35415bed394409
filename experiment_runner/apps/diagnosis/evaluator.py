"""The whitened force residual of a model on the fit and held-out samples: the fits' cost.

Cost
    The whitened force residual (:class:`.predict.NoiseFloor`): its mean square ``J`` is 1
    when the model leaves only what a perfect model leaves (noise and quantization seen
    through the observer). :class:`Evaluator` runs the compiled force observer once per
    residual evaluation (a few ms per second of data) on the fit trials (capped at
    ``max_fit_seconds`` of data, whole trials in order) or the held-out ones, and gives the
    least-squares vector of a fit (:meth:`Evaluator.fit_vector`) and the mean squares ``J``
    (:meth:`Evaluator.J`, :meth:`Evaluator.both`). Every evaluation passes the search budget's
    checkpoint (:func:`.budget.checkpoint`).
Effective sample count
    :func:`n_eff`: the number of independent samples of a whitened residual, from its
    autocorrelation (the correlation time inflates a fit's covariance, :mod:`.fit`, and sets a
    floor's scatter, :mod:`.floors`).
"""
from __future__ import annotations

import itertools
import threading
import time

import numpy as np

from .budget import checkpoint
from .model import ModelSpec
from .observer import Observer
from .predict import NoiseFloor

__all__ = ["Evaluator", "n_eff"]

_TOKENS = itertools.count()


class Evaluator:
    """Whitened residuals of a model on the fit and held-out samples.

    Parameters
    ----------
    obs : Observer
        The force observer on the data.
    floor : NoiseFloor
        The base model's force-residual floor (whitening).
    max_fit_seconds : float, optional
        Cap of the fit set [s of data] (whole trials, in order).
    """

    def __init__(self, obs: Observer, floor: NoiseFloor, max_fit_seconds: float = 3.0):
        self.obs = obs
        self.floor = floor
        d = obs.data
        self.data = d
        B = d.shape[1]
        fit_cols = [b for b in range(B) if d.fit[:, b].any()]
        held_cols = [b for b in range(B) if d.held[:, b].any()]
        # cap the fit set (speed): whole trials, in order, up to max_fit_seconds
        if len(fit_cols) > 1:
            keep, tot = [], 0.0
            for b in fit_cols:
                if keep and tot >= max_fit_seconds:
                    break
                keep.append(b)
                tot += d.fit[:, b].sum() / d.rate
            fit_cols = keep
        self.fit_cols = np.array(fit_cols, int)
        rows = np.flatnonzero(d.fit[:, self.fit_cols].any(axis=1))
        self.fit_stop = int(rows[-1]) + 1 if len(rows) else d.shape[0]
        """Samples a run for the fit samples alone goes through (to the last one)."""
        self.held_cols = np.array(held_cols, int)
        self.same = set(fit_cols) == set(held_cols)
        self.evals = 0
        self.seconds = 0.0
        self._lock = threading.Lock()
        self.token = next(_TOKENS)      # the run cache's key on the specs (an id() could be reused)

    def _run(self, spec, cols, stop: int | None = None):
        """The observer's residual of ``spec`` on trial columns ``cols`` (through sample ``stop``,
        default all): ``(r, bad)`` of :class:`.observer.ObsResult`, run once per spec, observer,
        columns and stop (kept on the spec: the candidates of a step score their start against the
        same current model, and a fit's held-out J after its own floor repeats the run its figures
        made). Every call counts as an evaluation (:attr:`evals`); :attr:`seconds` are the runs'."""
        checkpoint()          # a search whose budget is spent stops here (:mod:`.budget`)
        key = ("evaluator_run", self.token, tuple(int(c) for c in cols), stop)
        hit = spec._compiled.get(key)
        t = time.perf_counter()
        if hit is None:
            res = self.obs.run(spec, cols=cols, stop=stop)
            hit = spec._compiled[key] = (res.r, res.bad)
        with self._lock:
            self.evals += 1
            self.seconds += time.perf_counter() - t
        return hit

    def fit_vector(self, spec: ModelSpec, bad: float = 1e3) -> np.ndarray:
        """Whitened residual on the fit samples (the least-squares vector); ``bad`` in every
        sample where the observer diverged (the observer runs to the last fit sample,
        :attr:`fit_stop`: the samples after it are not the fit's).

        Parameters
        ----------
        spec : ModelSpec
            The model.
        bad : float, optional
            The value of every sample when the observer diverges.

        Returns
        -------
        numpy.ndarray
        """
        r, diverged = self._run(spec, self.fit_cols, self.fit_stop)
        m = self.data.fit[:, self.fit_cols]
        if diverged:          # not whitened: a diverged residual is no spectrum
            return np.full(int(m.sum()), bad)
        return self.floor.whiten(r, m)[m]

    def J(self, spec: ModelSpec, which: str = "held", floor: NoiseFloor | None = None) -> float:
        """Whitened mean square of ``spec``'s force residual on the held-out (or fit) samples; inf when the observer diverges.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        which : {'held', 'fit'}, optional
            The samples.
        floor : NoiseFloor, optional
            The floor whose units are used (default the evaluator's).

        Returns
        -------
        float
        """
        cols = self.held_cols if which == "held" else self.fit_cols
        mask = (self.data.held if which == "held" else self.data.fit)[:, cols]
        r, diverged = self._run(spec, cols, None if which == "held" else self.fit_stop)
        if diverged:
            return float("inf")
        return (floor or self.floor).ms(r, mask)

    def both(self, spec: ModelSpec, floor: NoiseFloor | None = None) -> tuple[float, float, float]:
        """(J_fit, J_held, n_eff_held) in one or two observer runs.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        floor : NoiseFloor, optional
            The floor whose units are used (default the evaluator's).

        Returns
        -------
        tuple of float
        """
        fl = floor or self.floor
        cols = np.union1d(self.fit_cols, self.held_cols)
        r, diverged = self._run(spec, cols)
        if diverged:
            return float("inf"), float("inf"), 1.0
        idx = {c: i for i, c in enumerate(cols)}
        mf = np.zeros(r.shape, bool)
        mh = np.zeros(r.shape, bool)
        for c in self.fit_cols:
            mf[:, idx[c]] = self.data.fit[:, c]
        for c in self.held_cols:
            mh[:, idx[c]] = self.data.held[:, c]
        wh = fl.whiten(r, mh)
        return fl.ms(r, mf), float(np.sum(wh[mh] ** 2) / max(1, mh.sum())), n_eff(wh, mh)


def n_eff(w: np.ndarray, mask: np.ndarray, max_lag: int = 200) -> float:
    """Effective number of independent samples of a (whitened) residual over ``mask``.

    Parameters
    ----------
    w : numpy.ndarray
        (T, B) whitened residual.
    mask : numpy.ndarray
        (T, B) bool.
    max_lag : int, optional
        Largest lag of the autocorrelation summed.

    Returns
    -------
    float
    """
    n = int(mask.sum())
    if n < 10:
        return float(max(n, 1))
    rho_sum = 0.0
    x = np.where(mask, w, 0.0)
    c0 = np.sum(x * x)
    if c0 <= 0:
        return float(n)
    for lag in range(1, min(max_lag, x.shape[0] - 1)):
        c = np.sum(x[lag:] * x[:-lag]) / c0
        if c < 0.02:
            break
        rho_sum += c
    return float(n / (1.0 + 2.0 * rho_sum))
