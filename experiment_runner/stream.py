"""Campaign trials in chunks on an executor, streamed to disk, resumable.

:func:`run_trials` runs the trials of one case at one condition of a campaign as chunks
of a few trials (:func:`chunk_task`) on an :class:`~experiment_runner.executor.Executor`
(in process, local processes or Dask), and appends every trial's metrics to the
campaign's stream as its chunk completes. Only metrics travel and stay in memory, never
trajectories, so memory does not grow with the number of trials beyond a few numbers each
(a chunk's trajectories live only while it runs).

The stream, ``trials.jsonl`` in the campaign's output folder, is JSON lines: a header

``{"format": "nanostage-trials", "version": 1, "campaign": NAME, "key": K, "code": C}``

then one line per trial, ``{"case", "condition", "trial", "x0_m", "metrics"}`` (floats as
Python's :mod:`json` writes them, ``NaN`` for undefined metrics). ``key`` is a hash of
everything that decides a trial's result (the campaign's test, trial count, start
positions, cases with their fully resolved presets, i.e. including overrides,
calibrated and swept values), ``code`` a hash of the model code
(:data:`CODE_MODULES`). A rerun into the same folder skips the trials already in the
stream (a line cut by an interruption is dropped); a stream of another campaign,
other settings or other model code is refused (:class:`~stage_sim.config.ConfigError`),
never mixed in.

Trial ``i`` is simulated and judged exactly as by
:func:`experiment_runner.campaign.simulate_case`: the batch engine's noise is a pure
function of (trial seed, sample, channel) and trials do not interact, so a trial's
result does not depend on which chunk, process or machine ran it.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import os
from pathlib import Path
from typing import Optional

import numpy as np

from stage_sim.config import ConfigError

__all__ = ["TrialStream", "run_trials", "simulate_trials", "representative_trial", "chunk_task",
           "campaign_key", "code_fingerprint", "STREAM_NAME", "CODE_MODULES"]

FORMAT = "nanostage-trials"
VERSION = 1
STREAM_NAME = "trials.jsonl"
_ROOT = Path(__file__).resolve().parent.parent
CODE_MODULES = ("stage_sim/config.py", *sorted(f"stage_sim/friction/{p.name}" for p in
                                                (_ROOT / "stage_sim" / "friction").glob("*.py")),
                "stage_sim/plant.py",
                "stage_control/dither.py", "stage_control/filters.py", "stage_control/sai.py",
                "stage_control/servo.py", "experiment_runner/batch.py", "experiment_runner/metrics.py",
                "experiment_runner/experiment.py", "experiment_runner/profiles.py",
                "experiment_runner/stream.py")
"""Source files (relative to the repository) whose content decides a trial's result."""
CHUNK_BYTES = 64e6
"""Budget of one chunk's recorded trajectories [bytes] (about 13 float64 signals per sample)."""
_BYTES_PER_SAMPLE = 13 * 8 * 2    # signals x float64 x (engine buffers + BatchResult copy)


# =========================================================================== identity
def _digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":")).encode()).hexdigest()[:16]


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> str:
    """Hash of the model code (:data:`CODE_MODULES`), read once per process."""
    h = hashlib.sha256()
    for rel in CODE_MODULES:
        h.update(rel.encode())
        h.update((_ROOT / rel).read_bytes())
    return h.hexdigest()[:16]


def campaign_key(camp, presets: dict) -> str:
    """Hash of what decides the campaign's trials.

    Parameters
    ----------
    camp : experiment_runner.campaign.Campaign
        The campaign as run (trial count and dwell overrides applied).
    presets : dict
        ``(case name, condition key) -> Preset`` as run (overrides, calibration, sweep applied).
    """
    return _digest({
        "test": camp.test.model_dump(mode="json"), "trials": camp.trials,
        "starts": camp.starts.model_dump(mode="json"),
        "cases": [{"name": c.name, "step_ii": c.step_ii.model_dump(mode="json") if c.step_ii else None}
                  for c in camp.cases],
        "presets": {f"{case}/{cond}": p.model_dump(mode="json") for (case, cond), p in sorted(presets.items())},
    })


# =========================================================================== the stream
class TrialStream:
    """Append-only JSON-lines file of a campaign's per-trial metrics (see the module docstring).

    Parameters
    ----------
    path : path
        The stream file (created with its parent folder).
    campaign : str
        Campaign name (header; named in errors).
    key, code : str
        :func:`campaign_key` and :func:`code_fingerprint` of this run.
    resume : bool
        Keep the trials of an existing stream with the same ``key`` and ``code`` (else the
        file is started anew).

    Raises
    ------
    ConfigError
        ``resume`` and the existing file is not a stream of this campaign, settings and
        code, or is damaged before its last line.
    """

    def __init__(self, path, campaign: str, key: str, code: str, resume: bool = True):
        self.path = Path(path)
        self.header = {"format": FORMAT, "version": VERSION, "campaign": campaign, "key": key, "code": code}
        self._done: dict[tuple, set] = {}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if resume and self.path.exists() and self._load():
            self._file = open(self.path, "a", encoding="utf-8")
        else:
            self._file = open(self.path, "w", encoding="utf-8")
            self._write([self.header])

    def _load(self) -> bool:
        """Index the trials of the existing file; False if it has no complete header."""
        with open(self.path, "rb") as f:
            first = f.readline()
            if not first.endswith(b"\n"):
                return False                 # interrupted before the header was complete
            try:
                head = json.loads(first)
            except ValueError:
                head = None
            if not isinstance(head, dict) or head.get("format") != FORMAT:
                raise ConfigError(f"{self.path}: not a nanostage trial stream (first line {first[:80]!r}); "
                                  "remove it or choose another output folder")
            self._check_header(head)
            good = f.tell()
            lineno = 1
            for line in f:
                lineno += 1
                try:
                    if not line.endswith(b"\n"):
                        raise ValueError("incomplete line")
                    r = json.loads(line)
                    key, trial = (r["case"], r["condition"]), int(r["trial"])
                except (ValueError, KeyError, TypeError) as err:
                    if f.read(1):           # not the last line: damaged, not interrupted
                        raise ConfigError(f"{self.path}:{lineno}: damaged trial record ({err}); "
                                          "remove the file or run with --restart") from None
                    break
                self._done.setdefault(key, set()).add(trial)
                good = f.tell()
        if good < self.path.stat().st_size:           # drop the line cut by an interruption
            os.truncate(self.path, good)
        return True

    def _check_header(self, head: dict) -> None:
        mine = self.header
        if head.get("version") != VERSION:
            why = f"stream format version {head.get('version')} (this is {VERSION})"
        elif head.get("campaign") != mine["campaign"]:
            why = f"campaign {head.get('campaign')!r} (this is {mine['campaign']!r})"
        elif head.get("key") != mine["key"]:
            why = (f"other settings (key {head.get('key')} vs {mine['key']}: trials, test, starts, "
                   "presets, overrides or calibrated values differ)")
        elif head.get("code") != mine["code"]:
            why = f"other model code (code {head.get('code')} vs {mine['code']})"
        else:
            return
        raise ConfigError(f"{self.path}: cannot resume, the trials there were run with {why}; run with "
                          "--restart (resume=False) to discard them, or choose another output folder")

    def _write(self, records) -> None:
        self._file.write("".join(json.dumps(r) + "\n" for r in records))
        self._file.flush()
        os.fsync(self._file.fileno())

    def done(self, case: str, condition: str) -> set:
        """Trial indices of ``case`` at ``condition`` already in the stream."""
        return self._done.get((case, condition), set())

    def append(self, records: list) -> None:
        """Append trial records (dicts with case, condition, trial, x0_m, metrics) and flush them to disk."""
        new = [r for r in records if int(r["trial"]) not in self.done(r["case"], r["condition"])]
        self._write(new)
        for r in new:
            self._done.setdefault((r["case"], r["condition"]), set()).add(int(r["trial"]))

    def read(self, case: str, condition: str, n: int) -> tuple[list, list]:
        """Metrics dicts and start positions [m] of trials ``0 .. n-1`` of ``case`` at ``condition``."""
        mets, x0 = [None] * n, [None] * n
        self._file.flush()
        with open(self.path, encoding="utf-8") as f:
            f.readline()
            for line in f:
                r = json.loads(line)
                i = r["trial"]
                if r["case"] == case and r["condition"] == condition and 0 <= i < n and mets[i] is None:
                    mets[i], x0[i] = r["metrics"], r["x0_m"]
        missing = [i for i, m in enumerate(mets) if m is None]
        if missing:
            raise RuntimeError(f"{self.path}: {len(missing)} trials of {case} at {condition} missing "
                               f"(first {missing[:5]})")
        return mets, x0

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "TrialStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# =========================================================================== trials
def simulate_trials(camp, case, cond, preset, indices, correction=None, models=None):
    """Trials ``indices`` of ``case`` at ``cond`` on the batch engine.

    Returns
    -------
    ref : profiles.Reference
        The shared (start-at-0) reference.
    trials : list of experiment.Trial
        As :func:`experiment_runner.campaign.make_trials` gives them (index, start, seed).
    res : batch.BatchResult
        Row ``j`` is trial ``indices[j]``; not checked (failed trials have a status).
    """
    from experiment_runner.batch import simulate
    from experiment_runner.campaign import reference, start_position
    from experiment_runner.experiment import Trial
    ref = reference(camp, cond, preset.controller.rate)
    base = preset.simulation.seed
    trials = []
    for i in indices:
        x0 = start_position(camp, preset, ref, int(i))
        trials.append(Trial(case=case.name, index=int(i), x_ref=ref.x + x0, v_ref=np.asarray(ref.v),
                            seed=base + int(i), window=camp.test.window, segments=tuple(ref.segments)))
    x0 = np.array([tr.x_ref[0] - ref.x[0] for tr in trials])
    res = simulate(preset, ref.x, ref.v, n_trials=len(trials), x0=x0, seeds=[tr.seed for tr in trials],
                   correction=correction, models=models, check=False)
    return ref, trials, res


def _metric_record(trial, res, j, rate) -> dict:
    """Per-trial metrics as :func:`experiment_runner.campaign.simulate_case` gives them."""
    from experiment_runner.campaign import METRIC_INFO
    from experiment_runner.experiment import trial_metrics
    from stage_sim.plant import STATUS_TEXT
    if res.status[j] != 0:
        return {"trial": trial.index, "case": trial.case, **{k: None for k in METRIC_INFO},
                "failed": STATUS_TEXT[int(res.status[j])]}
    return trial_metrics(trial, res.y[j], res.x_ref[j], rate)


@functools.lru_cache(maxsize=8)
def _campaign(camp_json: str):
    from experiment_runner.campaign import Campaign
    return Campaign.model_validate_json(camp_json)


@functools.lru_cache(maxsize=8)
def _preset_models(preset_json: str):
    from experiment_runner.batch import Models
    from stage_sim.config import Preset
    preset = Preset.model_validate_json(preset_json)
    return preset, Models.from_preset(preset)


def chunk_task(camp_json: str, case_name: str, cond_key: str, preset_json: str,
               correction: Optional[list], indices: list, code: str) -> list:
    """Executor task: simulate and judge trials ``indices`` of one case at one condition.

    Parameters
    ----------
    camp_json : str
        ``Campaign.model_dump_json()`` of the campaign as run.
    case_name, cond_key : str
        The case and the condition's key.
    preset_json : str
        ``Preset.model_dump_json()`` of the case's preset at the condition (all overrides applied).
    correction : list of float or None
        Learned SAI Step II correction [m].
    indices : list of int
        Trial indices.
    code : str
        :func:`code_fingerprint` of the process that streams the results.

    Returns
    -------
    list of dict
        One stream record per trial: case, condition, trial, x0_m [m], metrics.
    """
    from experiment_runner.campaign import conditions
    if code != code_fingerprint():
        import socket
        raise RuntimeError(f"worker on {socket.gethostname()} (pid {os.getpid()}) runs other model code "
                           f"({code_fingerprint()}) than the campaign ({code}): install the same version")
    camp = _campaign(camp_json)
    case = camp.case(case_name)
    cond = next(c for c in conditions(camp) if c.key == cond_key)
    preset, models = _preset_models(preset_json)
    corr = None if correction is None else np.asarray(correction, float)
    ref, trials, res = simulate_trials(camp, case, cond, preset, indices, corr, models)
    rate = preset.controller.rate
    return [{"case": case_name, "condition": cond_key, "trial": tr.index, "x0_m": float(tr.x_ref[0] - ref.x[0]),
             "metrics": _plain(_metric_record(tr, res, j, rate))} for j, tr in enumerate(trials)]


def _plain(d: dict) -> dict:
    """numpy scalars -> Python numbers (JSON)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, np.integer):
            v = int(v)
        elif isinstance(v, np.floating):
            v = float(v)
        out[k] = v
    return out


def chunk_size(n: int, samples: int, workers: int) -> int:
    """Trials per chunk: at least two chunks per worker, at most :data:`CHUNK_BYTES` of trajectories."""
    cap = max(1, int(CHUNK_BYTES // (samples * _BYTES_PER_SAMPLE)))
    return max(1, min(cap, math.ceil(n / (2 * workers))))


def run_trials(camp, case, cond, preset, correction, executor, stream: TrialStream,
               chunk: Optional[int] = None, on_chunk=None) -> tuple[list, list]:
    """All ``camp.trials`` trials of ``case`` at ``cond``: the ones not in ``stream`` run in chunks
    on ``executor`` and are appended to it as they complete; then all are read back from it.

    Parameters
    ----------
    camp, case, cond, preset
        Campaign (as run), case, condition and the case's preset at it.
    correction : array_like or None
        SAI Step II correction [m].
    executor : experiment_runner.executor.Executor
    stream : TrialStream
    chunk : int, optional
        Trials per task (default :func:`chunk_size`).
    on_chunk : callable, optional
        ``on_chunk(done, n)`` after every completed chunk: trials of this case and condition
        in the stream, of ``n`` (progress).

    Returns
    -------
    metrics : list of dict
        Per trial ``0 .. n-1``, as :func:`experiment_runner.campaign.simulate_case`.
    x0 : list of float
        Start position of every trial [m].
    """
    from experiment_runner.campaign import reference
    n = camp.trials
    todo = sorted(set(range(n)) - stream.done(case.name, cond.key))
    if todo:
        samples = len(reference(camp, cond, preset.controller.rate).x)
        size = chunk or chunk_size(len(todo), samples, executor.workers)
        camp_json, preset_json = camp.model_dump_json(), preset.model_dump_json()
        corr = None if correction is None else np.asarray(correction, float).tolist()
        tasks = ((("chunk", case.name, cond.key, todo[a]),
                  (camp_json, case.name, cond.key, preset_json, corr, todo[a:a + size], stream.header["code"]))
                 for a in range(0, len(todo), size))
        for _, records in executor.map(chunk_task, tasks):
            stream.append(records)
            if on_chunk is not None:
                on_chunk(len(stream.done(case.name, cond.key)), n)
    return stream.read(case.name, cond.key, n)


def representative_trial(camp, case, cond, preset, index: int, correction, metrics: dict):
    """Trial ``index`` simulated again on its own (for its trace), checked against its streamed ``metrics``.

    Returns
    -------
    ref, trial, res
        As :func:`simulate_trials` for the one trial (``res`` has one row).

    Raises
    ------
    RuntimeError
        The trial's metrics differ from the stream's (the stream is stale: model code
        outside :data:`CODE_MODULES` changed; rerun with ``--restart``).
    """
    ref, (trial,), res = simulate_trials(camp, case, cond, preset, [index], correction)
    again = _plain(_metric_record(trial, res, 0, preset.controller.rate))
    if json.dumps(again, sort_keys=True) != json.dumps(metrics, sort_keys=True):
        raise RuntimeError(f"trial {index} of {case.name} at {cond.key} gives {again}, the stream has {metrics}: "
                           "the stream is stale; rerun with --restart")
    return ref, trial, res
