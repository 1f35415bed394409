"""Judge: a model by its closed-loop replay of held-out data against its run-to-run floor.

What the user gets from a model is its replay: the recorded reference through the model and
its controller in closed loop (:func:`experiment_runner.core.batch.simulate`), the recorded
command and measurement compared in physical units (N and m) on the *held-out* samples.
This module decides with it (the force observer of :mod:`.predict` only locates and
proposes):

Replay
    ``R(M)``: the noise-free replay of model ``M`` (drive and bearing noise off; the
    sensor's quantization kept: it is deterministic) on the held-out trials.
Run-to-run floor
    ``K`` recordings simulated from ``M`` itself on the same reference with fixed noise
    seeds (one batch call): their replay errors ``S_k - R(M)`` are what a perfect model
    leaves. Its RMS per channel (``sigma_u`` [N], ``sigma_y`` [m]) normalises the two
    channels; ``D(X)`` = mean over held-out samples of ``(e_u/sigma_u)^2 + (e_y/sigma_y)^2``
    (2 = at the floor).
Adoption test (:meth:`ReplayJudge.compare`)
    Effect ``E`` fitted on the fit samples is adopted on top of ``M`` only if its replay is
    stable and ``T = D(M) - D(M+E)`` on the held-out samples is (i) positive, (ii) beyond
    the run-to-run floor: above ``mean + t * sd`` of the same statistic on the ``K``
    simulated recordings of ``M`` (``t``: Student quantile, one-sided ``alpha``, ``K - 1``
    degrees of freedom: a likelihood-ratio test calibrated by simulation, the noise model
    being the model's own), and (iii) beyond the data's own noise: above ``z_block``
    standard errors of its noise part computed from the data's residual over held-out blocks
    (:func:`_score_se`; robust when the model's noise is not the data's). No
    random draw is involved: same data, same decision.
Stochastic changes (drive noise, quantization)
    do not move the noise-free replay much; they move the floor. :meth:`ReplayJudge.consistency` says
    how far the data's replay error is from each model's floor (a z-score of
    ``log D`` over the ``K`` simulated recordings).

What a replay, a floor and a comparison hold, and the rules they rest on (the model without its
noise, the least a recording resolves), are in :mod:`.replay_floor`; the check of the recording's
controller and the equivalent reference the replay follows when the preset cannot express it are
in :mod:`.controller`.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from scipy import stats

from experiment_runner.core.batch import Models, simulate

from .budget import checkpoint
from .data import DiagData
from .model import ModelSpec
from .replay_floor import Comparison, Floor, Replay, least_resolved, noise_free, own_resolution, replay_verdict

__all__ = ["FLOOR_SEEDS", "ReplayJudge"]

_TOKENS = itertools.count()
FLOOR_SEEDS = tuple(70001 + 1000 * i for i in range(16))
"""Noise seeds of the simulated recordings of the run-to-run floor (fixed: same data, same decision)."""


class ReplayJudge:
    """Closed-loop replay of the held-out trials of ``data`` and the tests above.

    Parameters
    ----------
    data : DiagData
        The recording. Held-out samples are judged (all usable samples if none are held out).
    seeds : tuple of int
        Noise seeds of the floor's simulated recordings (``K = len(seeds)``).
    alpha : float
        One-sided level of the simulation-calibrated test (per candidate).
    z_block : float
        Standard errors of the improvement's noise part (from the data's residual, per block)
        it must exceed.
    block_s : float
        Length of the held-out blocks [s] (at least 20 samples).
    x_ref : ndarray, optional
        Reference to replay (T, B) instead of the recorded one (:func:`equivalent_reference`).
    """

    def __init__(self, data: DiagData, seeds=FLOOR_SEEDS, alpha: float = 1e-3, z_block: float = 2.0,
                 block_s: float = 0.02, x_ref=None):
        held = data.held if data.held.any() else (data.fit | data.held)
        self.cols = np.array([b for b in range(data.shape[1]) if held[:, b].any()], int)
        c = self.cols
        self.rate = data.rate
        self.mask = np.ascontiguousarray(held[:, c])
        xr = data.x_ref if x_ref is None else x_ref
        self.x_ref = np.ascontiguousarray(xr[:, c])
        self.v_ref = np.ascontiguousarray(data.v_ref[:, c])
        fe = data.f_ext
        self.f_ext = None if fe is None or not np.any(fe[:, c]) else np.ascontiguousarray(fe[:, c])
        self.u = np.ascontiguousarray(data.u[:, c])
        self.y = np.ascontiguousarray(data.y[:, c])
        self.u_resolution = own_resolution(self.u, self.mask)
        self.y_resolution = own_resolution(self.y, self.mask)
        self.seeds = tuple(int(s) for s in seeds)
        self.K = len(self.seeds)
        self.t_q = float(stats.t.ppf(1 - alpha, self.K - 1)) * math.sqrt(1 + 1 / self.K)
        self.z_block = z_block
        self.n = int(self.mask.sum())
        # blocks: runs of held-out samples cut every block_s
        ids, nb = _held_out_blocks(self.mask, max(20, int(round(block_s * data.rate))))
        self.block = ids
        self.n_blocks = nb
        self.block_n = np.bincount(ids[self.mask], minlength=nb).astype(float)
        self.sims = 0
        self.token = next(_TOKENS)      # replay cache key on the specs (an id() could be reused)

    # ------------------------------------------------------------------ simulation
    def simulate_recordings(self, spec: ModelSpec, seeds):
        """Recordings of ``spec`` on the judged trials with noise ``seeds`` (one batch call): ``(u, y)``
        each (K, T, B), the simulator's status (K, B) and the preset.

        Parameters
        ----------
        spec : ModelSpec
            The model.
        seeds : sequence of int
            One recording per seed (trial ``b``: ``seed + b``).

        Returns
        -------
        tuple
            ``(u, y, status, preset)``.
        """
        checkpoint()          # a search whose budget is spent stops here (:mod:`.budget`)
        p = spec.preset
        K = len(seeds)
        B = len(self.cols)
        xr = np.tile(self.x_ref.T, (K, 1))
        vr = np.tile(self.v_ref.T, (K, 1))
        sd = np.concatenate([s + np.arange(B) for s in seeds]).astype(np.int64)
        models = spec._compiled.get("batch_models")
        if models is None:
            models = spec._compiled["batch_models"] = Models.from_preset(p)
        fe = None if self.f_ext is None else np.tile(self.f_ext.T, (K, 1))
        res = simulate(p, xr, vr, seeds=sd, check=False, models=models, f_ext=fe)
        self.sims += 1
        u = res.u.reshape(K, B, -1).transpose(0, 2, 1)
        y = res.y.reshape(K, B, -1).transpose(0, 2, 1)
        return u, y, res.status.reshape(K, B), p

    def replay(self, spec: ModelSpec) -> Replay:
        """Noise-free closed-loop replay of ``spec`` (cached on the spec).

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
        nf = noise_free(spec)
        u, y, status, p = self.simulate_recordings(nf, [0])
        u, y = u[0], y[0]
        ok, why = replay_verdict(u, y, status, self.u, self.mask, nf._compiled["batch_models"].servo.limit)
        r = Replay(u=u, y=y, ok=ok, why=why)
        spec._compiled[key] = r
        return r

    def floor(self, spec: ModelSpec) -> Floor:
        """Run-to-run floor of ``spec``: ``K`` simulated recordings (one batch call).

        Parameters
        ----------
        spec : ModelSpec
            The model.

        Returns
        -------
        Floor
        """
        rp = self.replay(spec)
        u, y, _, _ = self.simulate_recordings(spec, self.seeds)
        du = (u - rp.u[None])[:, self.mask]
        dy = (y - rp.y[None])[:, self.mask]
        su = float(np.sqrt(np.mean(du ** 2))) if du.size else 1.0
        sy = float(np.sqrt(np.mean(dy ** 2))) if dy.size else 1.0
        tiny_u, tiny_y = least_resolved(spec.preset.stage.encoder.resolution, self.u[self.mask],
                                         self.u_resolution, self.y_resolution)
        return Floor(spec=spec, replay=rp, u=u, y=y, sigma_u=max(su, tiny_u), sigma_y=max(sy, tiny_y))

    # ------------------------------------------------------------------ distances
    def _blocks(self, e2: np.ndarray) -> np.ndarray:
        """Per-block sums of ``e2`` (T, B) over the held-out samples."""
        return np.bincount(self.block[self.mask], weights=e2[self.mask], minlength=self.n_blocks)

    def _errors(self, u, y, rp: Replay, fl: Floor) -> list:
        """The channels' errors of ``(u, y)`` against ``rp`` in ``fl``'s floor units, (T, B) each:
        command and position. Every statistic below is built on them."""
        return [(u - rp.u) / fl.sigma_u, (y - rp.y) / fl.sigma_y]

    def _e2(self, u, y, rp: Replay, fl: Floor) -> np.ndarray:
        return sum(e ** 2 for e in self._errors(u, y, rp, fl))

    def residual(self, rp: Replay, fl: Floor) -> np.ndarray:
        """The data's replay error against ``rp`` on the judged samples in ``fl``'s floor units, as one
        vector (channel after channel): its sum of squares is ``n D``. What an output-error fit
        minimises.

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        numpy.ndarray
            (2 n,) command then position errors.
        """
        return np.concatenate([e[self.mask] for e in self._errors(self.u, self.y, rp, fl)])

    def difference(self, rp_a: Replay, rp_b: Replay, fl: Floor) -> np.ndarray:
        """``rp_a`` - ``rp_b`` on the judged samples in ``fl``'s floor units, as :meth:`residual`'s
        vector (a replay in place of the data).

        Parameters
        ----------
        rp_a, rp_b : Replay
            Two replays.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        numpy.ndarray
        """
        return np.concatenate([e[self.mask] for e in self._errors(rp_a.u, rp_a.y, rp_b, fl)])

    def sim_residuals(self, rp: Replay, fl: Floor) -> np.ndarray:
        """(K, n): :meth:`residual` of each of ``fl``'s simulated recordings against ``rp`` (what
        the data's residual would be, run to run, were ``fl``'s model the truth).

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        numpy.ndarray
            (K, 2 n).
        """
        return np.stack([np.concatenate([e[self.mask] for e in self._errors(fl.u[k], fl.y[k], rp, fl)])
                         for k in range(self.K)])

    def data_blocks(self, rp: Replay, fl: Floor) -> np.ndarray:
        """Per-block sums of the data's normalised squared replay error against ``rp``.

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        numpy.ndarray
            (n_blocks,).
        """
        return self._blocks(self._e2(self.u, self.y, rp, fl))

    def sim_blocks(self, rp: Replay, fl: Floor, of: Floor | None = None) -> np.ndarray:
        """(K, n_blocks): the same for the simulated recordings of ``of`` (default ``fl``),
        normalised by ``fl``.

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.
        of : Floor, optional
            Whose simulated recordings (default ``fl``).

        Returns
        -------
        numpy.ndarray
            (K, n_blocks).
        """
        of = of or fl
        return np.stack([self._blocks(self._e2(of.u[k], of.y[k], rp, fl)) for k in range(self.K)])

    def D(self, rp: Replay, fl: Floor) -> float:
        """Data's replay error against ``rp`` in units of ``fl``'s floor (2 = at the floor).

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        float
            Per judged sample, both channels summed.
        """
        return float(self.data_blocks(rp, fl).sum() / max(self.n, 1))

    def rms(self, rp: Replay) -> tuple[float, float]:
        """Physical RMS replay errors on the held-out samples: command [N], position [m].

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.

        Returns
        -------
        tuple of float
            NaN when no sample is judged.
        """
        if not self.n:
            return float("nan"), float("nan")
        return (float(np.sqrt(np.mean((self.u - rp.u)[self.mask] ** 2))),
                float(np.sqrt(np.mean((self.y - rp.y)[self.mask] ** 2))))

    # ------------------------------------------------------------------ tests
    def compare(self, fl: Floor, rp_new: Replay, fl_blocks=None, rp_base: Replay | None = None,
                of_base: Floor | None = None) -> Comparison:
        """Is ``rp_new`` (current model + an effect) a real improvement over ``fl``'s model (or over
        the replay ``rp_base``, e.g. a simpler alternative, whose model's simulated recordings
        ``of_base`` (its floor) give the run-to-run threshold; in ``fl``'s floor units)?

        Accepted when the improvement ``T`` is positive, beyond the simulation-calibrated
        threshold, and beyond ``z_block`` standard errors of its noise part from the data.

        Parameters
        ----------
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.
        rp_new : Replay
            The replay of the changed model.
        fl_blocks : numpy.ndarray, optional
            ``sim_blocks(fl.replay, fl)``, when already computed.
        rp_base : Replay, optional
            The replay to improve on (default ``fl.replay``).
        of_base : Floor, optional
            The floor of ``rp_base``'s model.

        Returns
        -------
        Comparison
        """
        rp0 = fl.replay if rp_base is None else rp_base
        b0 = self.data_blocks(rp0, fl)
        b1 = self.data_blocks(rp_new, fl)
        n = max(self.n, 1)
        D0, D1 = float(b0.sum() / n), float(b1.sum() / n)
        T = D0 - D1
        s0 = fl_blocks if (fl_blocks is not None and rp_base is None) else self.sim_blocks(rp0, fl, of=of_base)
        s1 = self.sim_blocks(rp_new, fl, of=of_base)
        Tk = (s0.sum(axis=1) - s1.sum(axis=1)) / n
        thr = float(np.mean(Tk) + self.t_q * np.std(Tk, ddof=1))
        se = _score_se(self, rp0, rp_new, fl, of=of_base)
        if not rp_new.ok:
            return Comparison(D0, D1, T, thr, se, False, False, f"unstable: {rp_new.why}")
        why = _rejection(T, thr, se, self.z_block)
        return Comparison(D0, D1, T, thr, se, True, not why, why or "beyond the floor")

    def equivalent(self, fl: Floor, rp_a: Replay, rp_b: Replay, margin: float = 0.05,
                   of_b: Floor | None = None) -> tuple[bool, float]:
        """Can the held-out data tell ``rp_a`` from the better ``rp_b``? With ``d = D(a) - D(b)``
        (in ``fl``'s floor units): equivalent when ``d`` is within 2 standard errors of the same
        difference over simulated recordings of ``b``'s model (``of_b``, its floor; default
        ``fl``'s), or ``D(a)`` is within ``margin`` of ``D(b)`` (replay errors a few per cent apart
        in RMS), or ``d`` is within 2 block-bootstrap standard errors (the data's own scatter)
        while ``D(a)`` is within 25 % of ``D(b)`` (the block bootstrap alone would call a large
        difference concentrated in a few blocks, e.g. at the reversals, "equivalent").
        Recordings of ``fl``'s model are the wrong reference when both replays are far from it:
        their difference then scatters with that distance; hence ``of_b``.

        Parameters
        ----------
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.
        rp_a, rp_b : Replay
            The two replays; ``rp_b`` the better.
        margin : float, optional
            Relative margin of ``D(a)`` over ``D(b)``.
        of_b : Floor, optional
            The floor of ``rp_b``'s model.

        Returns
        -------
        equivalent : bool
        d : float
            ``D(a) - D(b)``.
        """
        ba = self.data_blocks(rp_a, fl)
        bb = self.data_blocks(rp_b, fl)
        n = max(self.n, 1)
        Da, Db = float(ba.sum() / n), float(bb.sum() / n)
        d = Da - Db
        of_b = of_b or fl
        dk = (self.sim_blocks(rp_a, fl, of=of_b).sum(axis=1) - self.sim_blocks(rp_b, fl, of=of_b).sum(axis=1)) / n
        se_sim = float(np.std(dk, ddof=1))
        se_blk = _block_se(self, ba - bb, d)
        eq = d <= 2.0 * se_sim or Da <= (1 + margin) * Db or (d <= 2.0 * se_blk and Da <= 1.25 * Db)
        return bool(eq), d

    def consistency(self, rp: Replay, fl: Floor, norm: Floor | None = None) -> float:
        """z-score of the data's ``log(D + mean D_k)`` among ``fl``'s simulated recordings (both against
        ``rp``, normalised by ``norm``, default ``fl``): about N(0, 1) when the data could be
        a recording of ``fl``'s model; large positive = the data is further from the replay
        than run-to-run noise explains.

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The model whose simulated recordings the data are compared with.
        norm : Floor, optional
            The floor whose units normalise the errors (default ``fl``).

        Returns
        -------
        float
        """
        norm = norm or fl
        Dk = self.sim_blocks(rp, norm, of=fl).sum(axis=1) / max(self.n, 1)
        return _log_z(self.D(rp, norm), Dk)

    def floor_ratio(self, rp: Replay, fl: Floor) -> float:
        """Data's replay error over the floor's, RMS ratio (1 = at the run-to-run floor).

        Parameters
        ----------
        rp : Replay
            A replay on the judged trials.
        fl : Floor
            The floor whose units (``sigma_u``, ``sigma_y``) normalise the errors.

        Returns
        -------
        float
        """
        Dk = self.sim_blocks(rp, fl).sum(axis=1) / max(self.n, 1)
        # 2 per sample = at the floor by construction; less when the floor is degenerate (no noise)
        return float(math.sqrt(self.D(rp, fl) / max(float(np.mean(Dk)), 2.0)))



def _log_z(Dd: float, Dk: np.ndarray) -> float:  # noqa: N803 (D of the data, of the recordings)
    """z-score of ``log(Dd + c)`` among ``log(Dk + c)``, ``c`` the mean of ``Dk``: the log of D shifted
    by the floor's mean is multiplicative for large errors, with no heavy left tail when some
    simulated recordings are nearly their replay (a stuck stage, quantization only)."""
    c = max(float(np.mean(Dk)), 1e-300)
    lk = np.log(Dk + c)
    sd = float(np.std(lk, ddof=1)) or 1e-12
    return float((math.log(Dd + c) - np.mean(lk)) / sd)


# --------------------------------------------------------------------------- score test
# The data's own noise model of :meth:`ReplayJudge.compare` and :meth:`ReplayJudge.equivalent`.
def _rejection(T: float, thr: float, se: float, z_block: float) -> str:  # noqa: N803 (the statistic T)
    """Why the improvement ``T`` of a stable replay is not accepted ("" when it is): not positive,
    within the run-to-run threshold ``thr``, or within ``z_block`` score-test standard errors ``se``."""
    if T <= 0:
        return "replay not better"
    if T <= thr:
        return "improvement within the run-to-run floor"
    if T <= z_block * se:
        return "improvement within the data's own noise (score test over held-out blocks)"
    return ""


def _held_out_blocks(mask: np.ndarray, length: int) -> tuple[np.ndarray, int]:
    """Block ids (T, B) of the held-out samples ``mask``: each run of held-out samples of a trial cut
    into ``max(1, len(run) // length)`` near-equal blocks; -1 outside ``mask``. Returns ``(ids, n_blocks)``."""
    ids = np.full(mask.shape, -1, int)
    nb = 0
    for j in range(mask.shape[1]):
        idx = np.flatnonzero(mask[:, j])
        if not len(idx):
            continue
        brk = np.r_[0, np.flatnonzero(np.diff(idx) > 1) + 1, len(idx)]
        for a, b in zip(brk[:-1], brk[1:]):
            run = idx[a:b]
            k = max(1, len(run) // length)
            ids[run, j] = nb + np.minimum(np.arange(len(run)) * k // len(run), k - 1)
            nb += k
    return ids, nb


def _block_se(judge: ReplayJudge, tb: np.ndarray, T: float) -> float:  # noqa: N803 (the statistic T)
    """Block-bootstrap standard error of ``sum(tb) / n`` from the blocks' scatter about ``T`` per
    sample (0 with fewer than 3 blocks)."""
    nb = judge.n_blocks
    if nb < 3:
        return 0.0
    dev = tb - judge.block_n * T
    return float(np.sqrt(nb / (nb - 1) * np.sum(dev ** 2)) / max(judge.n, 1))


def _score_se(judge: ReplayJudge, rp0: Replay, rp1: Replay, fl: Floor, of: Floor | None = None) -> float:
    """Standard error of ``T = D(rp0) - D(rp1)`` under "no improvement" with the noise taken
    from the data: with ``e = data - rp1`` and ``d = rp1 - rp0`` (floor units),
    ``T = sum(d^2 + 2 e d) / n`` and its noise part ``2 sum(e d) / n`` has, over blocks
    that may be correlated inside, the variance ``4 sum_b (sum_{t in b} e d)^2 / n^2``. A
    likelihood-ratio test whose noise model is the data's own residual: a concentrated
    deterministic improvement (at reversals) passes, a change that only trades one misfit
    for another (large ``e`` where it acts) does not. The blocks span the noise's correlation
    time in the replay error (:func:`_score_span`, from the recordings ``of``, default ``fl``'s)."""
    if not judge.n:
        return 0.0
    d = judge._errors(rp1.u, rp1.y, rp0, fl)
    e = judge._errors(judge.u, judge.y, rp1, fl)
    sb = judge._blocks(sum(ei * di for ei, di in zip(e, d)))
    m = _score_span(judge, rp0, d, fl, of)
    return float(2.0 * np.sqrt(np.sum(_merged(sb, m) ** 2)) / judge.n)


def _merged(sb: np.ndarray, m: int) -> np.ndarray:
    """Sums over ``m`` consecutive blocks (..., n_blocks) -> (..., ceil(n_blocks / m))."""
    if m <= 1:
        return sb
    nb = sb.shape[-1]
    pad = (-nb) % m
    z = np.concatenate([sb, np.zeros(sb.shape[:-1] + (pad,))], axis=-1)
    return z.reshape(sb.shape[:-1] + (-1, m)).sum(axis=-1)


def _score_span(judge: ReplayJudge, rp0: Replay, d: list, fl: Floor, of: Floor | None = None) -> int:
    """How many consecutive held-out blocks the score test's blocks must span for its noise part
    to be independent from block to block: the smallest number (1, 2, 4, ...) at which the sum of
    the per-block variances of ``sum e_k d`` over the simulated recordings ``of`` (default
    ``fl``'s; errors against ``rp0``) reaches 70 % of the variance of the whole sum. Drive noise
    moves a friction contact's hold force for a whole hold and the loop integrates it: blocks of
    20 ms are then far from independent, and the score test took a wrong effect that trades one
    realisation's misfit for another (a delay for a mode) as beyond the data's noise."""
    of = of or fl
    if of.u.ndim != 3 or of.u.shape[0] < 3 or judge.n_blocks < 6:
        return 1
    S = np.stack([judge._blocks(sum(ei * di for ei, di in zip(judge._errors(of.u[k], of.y[k], rp0, fl), d)))
                  for k in range(of.u.shape[0])])
    whole = float(np.var(S.sum(axis=1), ddof=1))
    if not whole > 0:
        return 1
    m = 1
    while judge.n_blocks // m >= 3:
        if float(np.sum(np.var(_merged(S, m), axis=0, ddof=1))) >= 0.7 * whole:
            return m
        m *= 2
    return max(1, m // 2)
