"""A replay and its run-to-run floor: what the replay judge (:mod:`.judge`) computes with and returns.

Records
    :class:`Replay` (a closed-loop replay on the judged trials and whether it ran through),
    :class:`Floor` (a model's ``K`` simulated recordings, its noise-free replay and the channels'
    run-to-run RMS) and :class:`Comparison` (the outcome of the adoption test, as a report row).
Rules
    The replay is the model without its random parts (:func:`noise_free`); it fails when it
    diverges, leaves the travel or sits at the command limit more often than the recording
    (:func:`replay_verdict`). A floor is never below what the recording resolves
    (:func:`own_resolution`, :func:`least_resolved`): a model without noise has a degenerate
    floor, its simulated recordings being its replay.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .model import ModelSpec

__all__ = ["Replay", "Floor", "Comparison", "noise_free", "own_resolution", "replay_verdict", "least_resolved"]


def own_resolution(a: np.ndarray, mask: np.ndarray) -> float:
    """The finest difference a recorded signal ``a`` (T, B) resolves on the samples ``mask``: the
    white part of its sample-to-sample roughness (robust SD of its fourth differences / sqrt(70):
    a smooth motion's part of them is its fourth derivative times the sample time to the fourth,
    nothing), 0 where it is smooth to the last digit. A floor below it carries no information.
    Quantization on a lattice is the encoder's step (:func:`.noise.estimate_lattice`, taken into
    the model before judging): a signal at rest on its lattice reads 0 here.

    Parameters
    ----------
    a : numpy.ndarray
        (T, B) recorded signal.
    mask : numpy.ndarray
        (T, B) bool: the samples to use (a column needs more than 5).

    Returns
    -------
    float
        In ``a``'s unit.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> t = np.linspace(0.0, 1.0, 4000)[:, None]
    >>> x = 1e-3 * np.sin(2 * np.pi * t) + 1e-8 * rng.normal(size=t.shape)
    >>> bool(abs(own_resolution(x, np.ones_like(x, bool)) / 1e-8 - 1) < 0.1)
    True
    """
    d = []
    for b in range(a.shape[1]):
        col = a[mask[:, b], b]
        if len(col) > 5:
            d.append(np.diff(col, 4))
    if not d:
        return 0.0
    d = np.concatenate(d)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(70.0))


def noise_free(spec: ModelSpec) -> ModelSpec:
    """``spec`` without its random parts (drive current noise, random bearing friction).

    Parameters
    ----------
    spec : ModelSpec
        The model.

    Returns
    -------
    ModelSpec
        ``spec`` itself when it has none.
    """
    p = spec.preset
    if p.stage.drive.noise_current_rms == 0 and all(b.force_noise_rms == 0 for b in p.stage.bearings):
        return spec
    ch = {"stage.drive.noise_current_rms": 0.0}
    ch.update({f"stage.bearings.{i}.force_noise_rms": 0.0 for i in range(len(p.stage.bearings))})
    return spec.with_changes(ch)


@dataclass
class Replay:
    """A closed-loop replay on the judge's trials: (T, B) arrays, ``ok`` if every trial ran
    through (no divergence, inside the travel) and the command did not sit at its limit more
    than the recording's does.

    Parameters
    ----------
    u : numpy.ndarray
        (T, B) command [N].
    y : numpy.ndarray
        (T, B) measured position [m].
    ok : bool
        Every trial ran through.
    why : str
        Why not, when not ``ok``.
    """
    u: np.ndarray
    y: np.ndarray
    ok: bool
    why: str = ""


@dataclass
class Floor:
    """Run-to-run floor of one model: ``K`` simulated recordings and its noise-free replay.

    Parameters
    ----------
    spec : ModelSpec
        The model.
    replay : Replay
        Its noise-free replay.
    u, y : numpy.ndarray
        (K, T, B) simulated commands [N] and measurements [m].
    sigma_u, sigma_y : float
        RMS command [N] and position [m] error of a simulated recording against the replay.
    white : numpy.ndarray, optional
        Prewhitening filter of the errors (open-loop judge), else None.
    """
    spec: ModelSpec
    replay: Replay
    u: np.ndarray            # (K, T, B) simulated commands
    y: np.ndarray            # (K, T, B) simulated measurements
    sigma_u: float           # RMS command error of a simulated recording vs the replay [N]
    sigma_y: float           # RMS position error [m]
    white: np.ndarray | None = None     # prewhitening filter of the errors (open-loop judge), else None


@dataclass
class Comparison:
    """Outcome of :meth:`.judge.ReplayJudge.compare` (all ``D`` per held-out sample, floor units).

    Parameters
    ----------
    D_before, D_after : float
        The data's replay error before and after the change.
    T : float
        ``D_before - D_after``.
    threshold_sim : float
        Mean + t standard deviations of ``T`` over the simulated recordings.
    se_block : float
        Standard error of ``T``'s noise part from the data, over held-out blocks.
    stable : bool
        The new replay ran through.
    accepted : bool
        ``T`` beyond both the threshold and ``z_block`` standard errors.
    why : str
        The verdict in words.
    """
    D_before: float
    D_after: float
    T: float                 # D_before - D_after
    threshold_sim: float     # mean + t sd of T over the simulated recordings
    se_block: float          # block-bootstrap standard error of T
    stable: bool
    accepted: bool
    why: str

    def row(self) -> dict:
        """The comparison as a report row.

        Returns
        -------
        dict
            ``D_before``, ``D_after``, ``improvement``, ``threshold``, ``block_se``, ``stable``,
            ``beyond_floor``, ``why``.
        """
        return {"D_before": self.D_before, "D_after": self.D_after, "improvement": self.T,
                "threshold": self.threshold_sim, "block_se": self.se_block, "stable": self.stable,
                "beyond_floor": self.accepted, "why": self.why}


def replay_verdict(u: np.ndarray, y: np.ndarray, status: np.ndarray, u_rec: np.ndarray, mask: np.ndarray,
                   lim: float) -> tuple[bool, str]:
    """``(ok, why)`` of a noise-free replay ``(u, y)`` with simulator ``status`` against the recorded
    command ``u_rec`` on the judged samples ``mask``; ``lim`` the servo's command limit [N].

    Parameters
    ----------
    u, y : numpy.ndarray
        (T, B) replayed command [N] and position [m].
    status : numpy.ndarray
        The simulator's status per trial (0: ran through).
    u_rec : numpy.ndarray
        (T, B) recorded command [N].
    mask : numpy.ndarray
        (T, B) bool: the judged samples.
    lim : float
        The servo's command limit [N].

    Returns
    -------
    tuple
        ``(ok, why)``: the replay ran through and its command did not sit at the limit more often
        than recorded; why not, else "".
    """
    ok, why = True, ""
    if np.any(status != 0) or not (np.all(np.isfinite(u)) and np.all(np.isfinite(y))):
        ok, why = False, "replay diverged or left the travel"
    elif mask.sum():
        sat = float(np.mean(np.abs(u[mask]) >= 0.999 * lim))
        sat_rec = float(np.mean(np.abs(u_rec[mask]) >= 0.999 * lim))
        # a replay sitting at the command limit much more often than the recording: the loop
        # swings (an unstable model), whatever it does to the error statistics
        if sat > sat_rec + 0.01:
            ok, why = False, f"replay command at its limit ({lim:.4g} N) on {100 * sat:.1f} % of the samples"
    return ok, why


def least_resolved(q: float, u_held: np.ndarray, u_resolution: float, y_resolution: float) -> tuple[float, float]:
    """The least a rig resolves, ``(command [N], position [m])``: the floor of a model without noise.

    A model without noise (e.g. drive noise "unknown: 0") has a degenerate floor: its simulated
    recordings are its replay. The channels are then weighted by the least a rig resolves: the
    encoder step ``q`` (uniform quantization error), 1e-4 of the recorded command's RMS (``u_held``,
    the judged samples), and what the recorded signals themselves resolve (their sample-to-sample
    roughness): never a floor below the measurement's own resolution.

    Parameters
    ----------
    q : float
        The encoder step [m].
    u_held : numpy.ndarray
        The recorded command on the judged samples [N].
    u_resolution, y_resolution : float
        What the recorded command [N] and position [m] resolve (:func:`own_resolution`).

    Returns
    -------
    tuple of float
        ``(command [N], position [m])``.
    """
    tiny_u = max(1e-4 * (float(np.sqrt(np.mean(u_held ** 2))) if u_held.size else 1.0),
                 u_resolution) or 1e-12
    tiny_y = max(q / math.sqrt(12.0), y_resolution, 1e-12)
    return tiny_u, tiny_y
