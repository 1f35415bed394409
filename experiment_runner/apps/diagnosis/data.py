"""The recording as the diagnosis sees it: the three contract topics, cut into trials.

:func:`load_data` reads a contract recording (or takes a :class:`Recording`), keeps only
what a hardware rig gives -- ``/stage/reference`` (x_ref, v_ref), ``/stage/command`` (u)
and ``/stage/measured`` (y) -- cuts it into trials (``/experiment/events``, else the
whole record is one trial) and stacks them as (T, B) arrays, trial axis last, padded with
the last sample and masked. The plant's other inputs -- the piezo dither forces (``/stage/dither``) and the SAI solenoid
command (``/stage/isolator``, held from each message's stamp) -- are taken from the recording
where it has them; otherwise the pipeline fills them from the nominal model's own dither
generator and SAI manager on the recorded reference (:meth:`DiagData.plant_inputs`). A known
external force (``/stage/external_force``) is applied to the model's table wherever the model
runs (:meth:`DiagData.known_force`). An *open-loop* record (no ``/stage/reference``: the recorded
command drove the plant) has ``open_loop`` set and the measured position as ``x_ref`` (its
low-passed derivative as ``v_ref``), so the motion regimes are read from the measurement.
It splits the samples into a *fit* set and a *held-out* set:
whole trials when there are two or more (every third trial held out, at least one),
otherwise contiguous blocks of the single trial (every third of six blocks held out).
The first ``burn_in`` seconds of each trial are in neither set (the model starts relaxed).

Damage the reader found (:class:`~experiment_runner.core.recording.Damage`: non-finite or absurd
values, samples missing, duplicated or stamped backwards) is never fitted nor judged: a trial
holding any is excluded, and said so (``DiagData.excluded``, the notes of the report); a
recording whose every trial is damaged is refused (:class:`~experiment_runner.core.recording.RecordingError`
naming the topic, sample and time).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import signal

from experiment_runner.core.recording import Recording, RecordingError, beyond_limits, read_recording
from msg_defs.topics import ISOLATOR_JOINT, PIEZOS

__all__ = ["DiagData", "load_data", "from_trials", "smooth"]


@dataclass
class DiagData:
    """A recording as the diagnosis works on it: trials as columns, padded, split into fit and held-out.

    Arrays are (T, B): T samples (the longest trial), B trials; shorter trials are padded
    (``valid`` False). Units are SI, or their rotary counterparts on a rotary axis
    (:mod:`~experiment_runner.apps.diagnosis.units`).

    Parameters
    ----------
    rate : float
        Control rate [Hz].
    t0 : numpy.ndarray
        (B,) start time of each trial [s].
    x_ref, v_ref : numpy.ndarray
        (T, B) reference position [m] and velocity [m/s].
    u : numpy.ndarray
        (T, B) command [N] (``command_kind``).
    y : numpy.ndarray
        (T, B) measured position [m].
    valid, fit, held : numpy.ndarray
        (T, B) bool: a real sample (not padding); used for fitting; held out for judging.
    lengths : numpy.ndarray
        (B,) samples per trial.
    trial_ids : list of int
        Trial numbers of the recording.
    source : str
        Where the data came from (the recording's path).
    split : str
        How the trials were split into fit and held-out, in words.
    ys, vs : numpy.ndarray, optional
        (T, B) zero-phase smoothed position and its velocity (:func:`smooth`).
    smooth_hz : float
        Cutoff of that smoothing [Hz].
    notes : list of str
        What the reader noticed (excluded trials, gaps bridged).
    d0, d1 : numpy.ndarray, optional
        (T, B) dither force of piezo 1 and 2 [N] (None: no dither).
    mode : numpy.ndarray, optional
        (T, B) SAI solenoid command, 1 compliant, 0 stiff (None: compliant).
    f_ext : numpy.ndarray, optional
        (T, B) known external force on the table [N] (``/stage/external_force``; None: none).
    open_loop : bool
        No reference: the recorded command drove the plant (``x_ref`` is the measured position).
    axis : {"linear", "rotary"}
        The recording's ``run.axis`` (or the preset's ``stage.kind``).
    command_kind : {"drive", "measured"}
        What ``/stage/command`` holds: a drive's command, or the force applied.
    excluded : list of str
        Trials left out as damaged ("trial N: why"; also in ``notes``).
    incomplete : list of str
        Trials kept though incomplete (aborted, cut short).
    """
    rate: float                   # control rate [Hz]
    t0: np.ndarray                # (B,) start time of each trial [s]
    x_ref: np.ndarray             # (T, B) [m]
    v_ref: np.ndarray             # (T, B) [m/s]
    u: np.ndarray                 # (T, B) command [N]
    y: np.ndarray                 # (T, B) measured position [m]
    valid: np.ndarray             # (T, B) bool: a real sample (not padding)
    fit: np.ndarray               # (T, B) bool: used for fitting
    held: np.ndarray              # (T, B) bool: held out
    lengths: np.ndarray           # (B,) samples per trial
    trial_ids: list               # trial numbers of the recording
    source: str = ""
    split: str = ""
    ys: np.ndarray = None         # smoothed y (zero phase)
    vs: np.ndarray = None         # its velocity
    smooth_hz: float = 0.0
    notes: list = field(default_factory=list)
    d0: np.ndarray = None         # (T, B) dither force of piezo 1 [N] (None: no dither)
    d1: np.ndarray = None         # (T, B) dither force of piezo 2 [N]
    mode: np.ndarray = None       # (T, B) SAI solenoid command, 1 compliant, 0 stiff (None: compliant)
    f_ext: np.ndarray = None      # (T, B) known external force on the table [N] (/stage/external_force; None: none)
    open_loop: bool = False       # no reference: the recorded command drove the plant (x_ref = measured position)
    axis: str = "linear"          # linear (m, N) or rotary (rad, N·m): the recording's run.axis / preset stage.kind
    command_kind: str = "drive"   # what /stage/command holds: "drive" (a drive's command) or "measured" (the force applied)
    excluded: list = field(default_factory=list)   # trials left out as damaged: "trial N: why" (also in notes)
    incomplete: list = field(default_factory=list)  # trials kept though incomplete (aborted, cut short): "trial N: why"

    def plant_inputs(self) -> tuple:
        """``(d0, d1, mode)`` as (T, B) arrays: zero dither and a compliant (no) isolator where absent.

        Returns
        -------
        tuple of numpy.ndarray
        """
        zero = np.zeros(self.shape)
        return (zero if self.d0 is None else self.d0, zero if self.d1 is None else self.d1,
                np.ones(self.shape) if self.mode is None else self.mode)

    def known_force(self) -> np.ndarray:
        """The known external table force (T, B) [N]: ``f_ext``, zero where absent.

        Returns
        -------
        numpy.ndarray
        """
        return np.zeros(self.shape) if self.f_ext is None else self.f_ext

    @property
    def dt(self) -> float:
        """Control period [s]."""
        return 1.0 / self.rate

    @property
    def shape(self):
        """(T, B) of the arrays."""
        return self.u.shape

    def subset(self, cols) -> "DiagData":
        """The same data restricted to trials ``cols`` (indices into the batch axis).

        Parameters
        ----------
        cols : array_like of int
            Trial columns.

        Returns
        -------
        DiagData
        """
        cols = np.asarray(cols, int)
        kw = {k: None if getattr(self, k) is None else getattr(self, k)[:, cols]
              for k in ("x_ref", "v_ref", "u", "y", "valid", "fit", "held", "ys", "vs", "d0", "d1", "mode", "f_ext")}
        return DiagData(rate=self.rate, t0=self.t0[cols], lengths=self.lengths[cols],
                        trial_ids=[self.trial_ids[c] for c in cols], source=self.source, split=self.split,
                        smooth_hz=self.smooth_hz, notes=list(self.notes), open_loop=self.open_loop, axis=self.axis,
                        command_kind=self.command_kind, **kw)


def smooth(y: np.ndarray, rate: float, cutoff: float, lengths=None):
    """Zero-phase 2nd-order Butterworth low-pass of each column and its velocity.

    Parameters
    ----------
    y : numpy.ndarray
        (T, B) positions.
    rate : float
        Sample rate [Hz].
    cutoff : float
        Cutoff [Hz] (at most 0.95 of Nyquist).
    lengths : array_like of int, optional
        Samples of each column (the rest is padding, held at the last value).

    Returns
    -------
    ys : numpy.ndarray
        (T, B) smoothed positions.
    vs : numpy.ndarray
        (T, B) their velocity (``np.gradient`` x rate; zero in the padding).
    """
    wn = min(0.95, 2.0 * cutoff / rate)
    sos = signal.butter(2, wn, output="sos")
    ys = np.empty_like(y)
    vs = np.empty_like(y)
    T, B = y.shape
    for b in range(B):
        n = T if lengths is None else int(lengths[b])
        col = y[:n, b]
        if n > 12:
            s = signal.sosfiltfilt(sos, col, padtype="constant" if n < 60 else "odd",
                                   padlen=min(n - 1, 3 * int(rate / cutoff) + 6))
        else:
            s = col.copy()
        ys[:n, b] = s
        vs[:n, b] = np.gradient(s) * rate if n > 1 else 0.0
        ys[n:, b] = s[-1] if n else 0.0
        vs[n:, b] = 0.0
    return ys, vs


def _stack(cols, T):
    out = np.empty((T, len(cols)))
    for b, c in enumerate(cols):
        out[:len(c), b] = c
        out[len(c):, b] = c[-1] if len(c) else 0.0
    return out


def load_data(source, burn_in: float = 0.005, min_trial: float = 0.02, max_trials: int | None = None) -> DiagData:
    """Read ``source`` (path or :class:`~experiment_runner.core.recording.Recording`) into :class:`DiagData`.

    Parameters
    ----------
    source : str, pathlib.Path or Recording
        A contract recording (MCAP file or bag folder).
    burn_in : float, optional
        Seconds at the start of each trial left out of fit and held-out sets.
    min_trial : float, optional
        Trials shorter than this [s] (and than 10 samples) are left out.
    max_trials : int, optional
        Use at most this many trials.

    Returns
    -------
    DiagData

    Raises
    ------
    experiment_runner.core.recording.RecordingError
        Fewer than 10 control samples, or a damaged recording.
    """
    rec = source if isinstance(source, Recording) else read_recording(source, require_reference=False)
    n = len(rec)
    if n < 10:
        raise RecordingError(f"{rec.path}: only {n} control samples; the diagnosis needs at least 10")
    axis = rec.axis                                      # a damaged /experiment/config is refused here
    dts = np.diff(rec.stamp_ns)
    dt = float(np.median(dts)) * 1e-9
    rate = 1.0 / dt
    notes = [f"recording {rec.salvaged}"] if rec.salvaged else []
    notes += [f"recording: {w}" for w in rec.warnings]
    if np.any(np.abs(dts * 1e-9 - dt) > 0.01 * dt):
        notes.append(f"{int(np.sum(np.abs(dts * 1e-9 - dt) > 0.01 * dt))} irregular sample interval(s)")
    trials = [tr for tr in rec.trials() if tr.stop - tr.start >= max(10, min_trial * rate)]
    slices = [(tr.trial, tr.start, tr.stop) for tr in trials]
    if not slices:
        slices = [(0, 0, n)]
        notes.append("no trial events: the whole record is one trial")
    slices, excluded = _undamaged(rec, slices)
    notes += [f"excluded {e}" for e in excluded]
    kept = {s[0] for s in slices}
    incomplete = [f"trial {tr.trial}: " + "; ".join(tr.problems) for tr in trials if tr.problems and tr.trial in kept]
    notes += [f"incomplete {e} (its samples are data: used)" for e in incomplete]
    # damaged values (in excluded trials only) are bridged before anything filters across trials
    x_ref, v_ref = _bridged(rec.x_ref, "position"), _bridged(rec.v_ref, "velocity")
    u, y = _bridged(rec.u, "effort"), _bridged(rec.y, "position")
    if rec.open_loop:
        # no reference: the recorded command drove the plant. The regimes (reversal, constant velocity, ...)
        # are read from the measurement itself, low-passed (zero phase) at rate/50
        _, vs = smooth(y[:, None], rate, rate / 50.0)
        x_ref, v_ref = y.copy(), vs[:, 0]
        notes.append("open-loop record (no /stage/reference): the recorded command drove the plant; judged by "
                     "open-loop windows re-initialised from the measurement")
    elif np.all(np.isnan(v_ref)):
        v_ref = np.gradient(x_ref) * rate
        notes.append("reference velocity absent: differentiated from the reference position")
    v_ref = np.nan_to_num(v_ref)
    if max_trials is not None:
        slices = slices[:max_trials]
    d0 = d1 = mode = None
    if rec.dither is not None and len(rec.dither):
        d0, d1 = (_at_samples(rec.dither, rec.stamp_ns, name, "effort") for name in PIEZOS)
        notes.append("dither forces from /stage/dither")
    if rec.isolator is not None and len(rec.isolator):
        mode = _at_samples(rec.isolator, rec.stamp_ns, ISOLATOR_JOINT, "position", hold=True)
        notes.append("SAI mode from /stage/isolator")
    f_ext = None
    if rec.external_force is not None:
        f_ext = np.nan_to_num(np.asarray(rec.external_force, float))
        notes.append("known external force from /stage/external_force (applied to the model's table)")
    cut = lambda a: None if a is None else [a[s0:s1] for _, s0, s1 in slices]  # noqa: E731
    out = from_trials(rate, [rec.t[s0] for _, s0, _ in slices], cut(x_ref), cut(v_ref), cut(u), cut(y),
                      trial_ids=[s[0] for s in slices], source=str(rec.path), notes=notes, burn_in=burn_in,
                      d0=cut(d0), d1=cut(d1), mode=cut(mode), f_ext=cut(f_ext), open_loop=rec.open_loop)
    out.axis = axis
    out.command_kind = rec.command_kind
    out.excluded, out.incomplete = excluded, incomplete
    return out


def _bridged(a: np.ndarray, fld: str) -> np.ndarray:
    """``a`` with its damaged values (:func:`~experiment_runner.core.recording.beyond_limits`)
    interpolated from the good ones (an absent, all-nan signal as it is)."""
    bad = beyond_limits(a, fld)
    if not bad.any() or bad.all():
        return a
    i = np.arange(len(a))
    return np.where(bad, np.interp(i, i[~bad], a[~bad]), a)


def _undamaged(rec, slices) -> tuple[list, list[str]]:
    """``slices`` without the trials that hold damage (:attr:`Damage.unusable`), and why each
    was left out; :class:`RecordingError` if none is left."""
    bad = [d for d in rec.damage if d.unusable]
    keep, excluded = [], []
    for tid, s0, s1 in slices:
        why = [w for w in (d.within(s0, s1, rec.t) for d in bad) if w]
        if why:
            excluded.append(f"trial {tid}: " + "; ".join(why))
        else:
            keep.append((tid, s0, s1))
    if not keep:
        raise RecordingError(f"{rec.path}: damaged: every trial holds samples the diagnosis cannot use (it never "
                             "fits or judges non-finite, absurd, missing or misordered samples): "
                             + "; ".join(d.text for d in bad))
    return keep, excluded


def from_trials(rate: float, t0, x_ref, v_ref, u, y, trial_ids=None, source: str = "", notes=None,
                burn_in: float = 0.005, d0=None, d1=None, mode=None, f_ext=None, open_loop: bool = False) -> DiagData:
    """:class:`DiagData` of trials given as lists of 1-D arrays (one per trial; ``d0, d1, mode``,
    ``f_ext`` optional; ``open_loop``: no reference, ``x_ref`` is the measured position), stacked, masked and split into fit and held-out sets as :func:`load_data` does.

    Parameters
    ----------
    rate : float
        Control rate [Hz].
    t0 : array_like
        Start time of each trial [s].
    x_ref, v_ref, u, y : list of numpy.ndarray
        Per trial: reference [m], reference velocity [m/s], command [N], measured position [m].
    trial_ids : list of int, optional
        Trial numbers (default 0..B-1).
    source : str, optional
        Where the data came from.
    notes : list of str, optional
        Notes carried into the data.
    burn_in : float, optional
        Seconds at the start of each trial left out of fit and held-out sets.
    d0, d1, mode, f_ext : list of numpy.ndarray, optional
        Per trial: dither forces [N], SAI solenoid command, known external force [N].
    open_loop : bool, optional
        The command drove the plant without a reference.

    Returns
    -------
    DiagData
    """
    B = len(u)
    T = max(len(a) for a in u)
    lengths = np.array([len(a) for a in u])
    valid = np.arange(T)[:, None] < lengths[None, :]
    burn = int(round(burn_in * rate))
    usable = valid & (np.arange(T)[:, None] >= burn)
    fit = np.zeros_like(valid)
    held = np.zeros_like(valid)
    trial_ids = list(range(B)) if trial_ids is None else list(trial_ids)
    if B >= 2:
        hold_cols = [b for b in range(B) if b % 3 == 2] or [B - 1]
        for b in range(B):
            (held if b in hold_cols else fit)[:, b] = usable[:, b]
        split = f"by trial: held out {', '.join(str(trial_ids[b]) for b in hold_cols)} of {B}"
    else:
        blocks = np.minimum((np.arange(T) * 6) // max(1, lengths[0]), 5)
        h = (blocks % 3 == 2)[:, None]
        held = usable & h
        fit = usable & ~h
        split = "one trial: blocks 3 and 6 of 6 held out"
    st = lambda a: None if a is None else _stack(a, T)  # noqa: E731
    return DiagData(rate=float(rate), t0=np.asarray(t0, float), x_ref=st(x_ref), v_ref=st(v_ref), u=st(u), y=st(y),
                    valid=valid, fit=fit, held=held, lengths=lengths, trial_ids=trial_ids, source=source,
                    split=split, notes=list(notes or []), d0=st(d0), d1=st(d1), mode=st(mode), f_ext=st(f_ext),
                    open_loop=bool(open_loop))


def _at_samples(series, stamp_ns, joint: str, field: str, hold: bool = False) -> np.ndarray:
    """``series``' ``field`` of ``joint`` at each sample stamp: the message of that stamp (0 where
    none), or with ``hold`` the last message at or before it (the first one before any)."""
    values = np.nan_to_num(series.joint(joint, field))
    i = np.searchsorted(series.stamp_ns, stamp_ns, side="right") - 1
    if hold:
        return values[np.clip(i, 0, None)]
    hit = (i >= 0) & (series.stamp_ns[np.clip(i, 0, None)] == stamp_ns)
    return np.where(hit, values[np.clip(i, 0, None)], 0.0)
