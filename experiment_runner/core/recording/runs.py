"""Writing signals in memory as a recording: :func:`write_trials`, and batch-engine trials (:func:`write_run`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from experiment_runner.core.metrics import trial_metrics
from experiment_runner.core.recording.writer import McapRecorder, typestore
from msg_defs import cdr, convert
from msg_defs.topics import (BEARING, CLOCK, COMMAND, DITHER, EVENTS, ISOLATOR, ISOLATOR_JOINT, MEASURED, MOTOR,
                             PIEZOS, REFERENCE, RESULTS, TABLE, TRUTH)
from stage_sim.plant import OK, STATUS_TEXT


def run_config_yaml(preset, **run) -> str:
    """``/experiment/config`` YAML: the preset (as validated) and the run's parameters."""
    import yaml
    doc = {"recording_contract": 1, "run": convert.strict_json(run), "preset": preset.model_dump(mode="json")}
    return yaml.safe_dump(doc, sort_keys=False)


def _sample_stamps(start_ns: int, first: int, n: int, rate: float) -> np.ndarray:
    step = 1e9 / rate
    k = np.arange(first, first + n, dtype=np.int64)
    if float(step).is_integer():
        return start_ns + k * int(step)
    return start_ns + np.round(k * step).astype(np.int64)


@dataclass
class TrialSignals:
    """One trial of a contract recording, as :func:`write_trials` writes it.

    Attributes
    ----------
    stamps : numpy.ndarray
        Stage time of each sample [ns] (int64).
    series : list of tuple
        The per-sample ``sensor_msgs/JointState`` topics, in the order written at each sample:
        ``(topic, names, {field: (n, len(names)) array}, rows)``; ``rows`` the samples written
        (None: every one).
    events : dict
        Fields of the ``trial_start`` and ``trial_end`` events besides ``trial``, ``case`` and ``node``.
    fault : str, optional
        Reason of a ``fault`` event before ``trial_end`` (the trial failed).
    results : dict, optional
        The trial's ``/experiment/results`` (after ``trial_end``).
    clock : bool
        ``/clock`` at every sample, first.
    """
    stamps: np.ndarray
    series: list
    events: dict = field(default_factory=dict)
    fault: str | None = None
    results: dict | None = None
    clock: bool = False


def write_trials(path, config_yaml: str, trials, *, case: str = "", node: str = "batch", start_ns: int = 0,
                 overwrite: bool = False, atomic: bool = True) -> Path:
    """The one writer of contract recordings (:func:`write_run`'s batch trials,
    :func:`experiment_runner.core.tabular.convert.write_signals`' converted tables); returns the MCAP file.

    ``/experiment/config`` (``config_yaml``), ``run_start``, then for each :class:`TrialSignals`:
    ``trial_start``, per sample ``/clock`` (if asked) and its series, a ``fault`` if it failed,
    ``trial_end``, its results; ``run_end`` after the last trial. Written by :class:`McapRecorder`
    (``overwrite``, ``atomic`` as its own).
    """
    ts = typestore()
    with McapRecorder(path, config_yaml, start_ns=start_ns, overwrite=overwrite, atomic=atomic) as rec:
        w = rec.write
        end = None
        for j, tr in enumerate(trials):
            stamps = tr.stamps.tolist()
            if end is None:
                w(EVENTS.name, stamps[0], convert.event_msg(ts, "run_start", stamp_ns=stamps[0], case=case, node=node))
            w(EVENTS.name, stamps[0], convert.event_msg(ts, "trial_start", stamp_ns=stamps[0], trial=j, case=case,
                                                        **_event_order(tr.events, node)))
            series = []
            for topic, names, fields, rows in tr.series:
                names = tuple(str(n) for n in names)
                only = None if rows is None else set(np.asarray(rows).tolist())
                series.append((topic, names, cdr.JointStateWriter(), {f: np.asarray(v, float).reshape(len(stamps), -1)
                                                                      .tolist() for f, v in fields.items()}, only))
            for k, s in enumerate(stamps):
                if tr.clock:
                    w(CLOCK.name, s, cdr.clock(s))
                for topic, names, writer, fields, only in series:
                    if only is None or k in only:
                        w(topic, s, writer.pack(s, names, **{f: v[k] for f, v in fields.items()}))
            end = stamps[-1]
            if tr.fault is not None:
                w(EVENTS.name, end, convert.event_msg(ts, "fault", stamp_ns=end, trial=j, case=case, node=node,
                                                      reason=tr.fault))
            w(EVENTS.name, end, convert.event_msg(ts, "trial_end", stamp_ns=end, trial=j, case=case,
                                                  **_event_order(tr.events, node)))
            if tr.results is not None:
                w(RESULTS.name, end, convert.string_msg(ts, convert.to_json(
                    {"trial": j, "case": case, **tr.results, "node": node})))
        if end is not None:
            w(EVENTS.name, end, convert.event_msg(ts, "run_end", stamp_ns=end, case=case, node=node))
    return rec.path


def _event_order(events: dict, node: str) -> dict:
    """A trial event's fields in the order the recordings have always had: ``window_m`` (where
    given), ``node``, then the rest."""
    head = {"window_m": events["window_m"]} if "window_m" in events else {}
    return {**head, "node": node, **{k: v for k, v in events.items() if k != "window_m"}}


def write_run(path, result, preset, *, trials=None, reference=None, window: float | None = None,
              case: str = "", config_yaml: str | None = None, truth: bool = True, clock: bool = False,
              results: bool = True, start_ns: int = 0, node: str = "batch", overwrite: bool = False,
              atomic: bool = True) -> Path:
    """Write batch-engine trials as a contract recording (:func:`write_trials`); return the MCAP file.

    Trials follow each other in stage time: sample ``k`` of the ``j``-th written trial is
    at ``start_ns + (j * T + k) / rate`` (T samples per trial; a failed trial stops at
    its failing sample with a ``fault`` event). Per sample: ``/stage/reference``
    (x_ref incl. SAI correction, v_ref), ``/stage/command``, ``/stage/measured`` (with
    ``bearing`` if the stage has a bearing sensor), ``/stage/truth`` (positions of
    ``table`` and ``bearing``; the batch engine keeps no velocities), ``/stage/dither``
    (dither stages), ``/stage/isolator`` on each change (SAI stages), ``/clock`` if
    asked. Events: ``run_start``, per trial ``trial_start`` / ``trial_end`` (with
    ``window_m``, and ``target_m``, ``settle_start_ns``, ``step_index`` from the last
    ``"settle"`` segment of ``reference``), ``run_end``. With ``results`` (default) the
    metrics of :func:`experiment_runner.core.metrics.trial_metrics` go to ``/experiment/results``.

    Parameters
    ----------
    path : str or Path
        Bag directory (see :func:`bag_layout`).
    result : BatchResult
    preset : Preset
        The preset the result was simulated with.
    trials : iterable of int, optional
        Which trials (default all).
    reference : experiment_runner.core.profiles.Reference, optional
        The shared reference, for the settle segment (target and its start).
    window : float, optional
        Half-width of the settling band [m].
    overwrite, atomic : bool
        As :class:`McapRecorder`'s (default: written whole, then moved into place).
    """
    rate = float(preset.controller.rate)
    n_trials, T = result.y.shape
    trials = list(range(n_trials)) if trials is None else [int(i) for i in trials]
    settle = None
    if reference is not None:
        if len(reference.x) != T:
            raise ValueError(f"reference has {len(reference.x)} samples, the result {T}")
        segs = reference.select("settle")
        settle = segs[-1] if segs else None
    has_bsens = preset.stage.bearing_sensor is not None
    has_bearing = bool(preset.stage.bearings)
    has_dither = preset.dither is not None
    has_sai = preset.sai_manager is not None or preset.stage.sai is not None
    if config_yaml is None:
        config_yaml = run_config_yaml(preset, source=node, case=case, trials=trials, rate=rate,
                                      window_m=window, samples_per_trial=T)

    def signals(j: int, i: int) -> TrialSignals:
        failed = int(result.status[i]) != OK
        n = int(result.fail_step[i]) + 1 if failed else T
        stamps = _sample_stamps(start_ns, j * T, n, rate)
        extra = {}
        if settle is not None:
            extra = {"step_index": settle.index,
                     "settle_start_ns": int(_sample_stamps(start_ns, j * T + settle.start, 1, rate)[0]),
                     "target_m": float(settle.target + (result.x_ref[i, 0] - reference.x[0]))}
        x_ref, v_ref, u, y, yb = (a[i, :n] for a in (result.x_ref, result.v_ref, result.u, result.y, result.y_bearing))
        series = []
        if has_sai:
            mode = result.mode[i, :n]
            series.append((ISOLATOR.name, (ISOLATOR_JOINT,), {"position": mode},
                           np.flatnonzero(np.r_[True, mode[1:] != mode[:-1]])))
        series.append((REFERENCE.name, (TABLE,), {"position": x_ref, "velocity": v_ref}, None))
        if has_dither:
            series.append((DITHER.name, PIEZOS, {"effort": result.dither[i, :n]}, None))
        series.append((COMMAND.name, (MOTOR,), {"effort": u}, None))
        series.append((MEASURED.name, (TABLE, BEARING) if has_bsens else (TABLE,),
                       {"position": np.column_stack([y, yb]) if has_bsens else y}, None))
        if truth:
            series.append((TRUTH.name, (TABLE, BEARING) if has_bearing else (TABLE,),
                           {"position": (np.column_stack([result.x_table[i, :n], result.x_bearing[i, :n]])
                                         if has_bearing else result.x_table[i, :n])}, None))
        met = None
        if results:
            met = trial_metrics(stamps * 1e-9, x_ref, v_ref, y, window=window, target=extra.get("target_m"),
                                settle_start=extra["settle_start_ns"] * 1e-9 if extra else None)
        fault = (STATUS_TEXT.get(int(result.status[i]), f"plant status {int(result.status[i])}") if failed
                 else None)
        return TrialSignals(stamps, series, {"window_m": window, **extra}, fault, met, clock)

    return write_trials(path, config_yaml, (signals(j, i) for j, i in enumerate(trials)), case=case, node=node,
                        start_ns=start_ns, overwrite=overwrite, atomic=atomic)

