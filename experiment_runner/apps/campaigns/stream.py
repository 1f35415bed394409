"""Campaign trials in chunks on an executor, streamed to disk, resumable.

:func:`run_trial_jobs` runs the trials of a campaign's cases and conditions as chunks
of a few trials (:func:`chunk_task`) on an :class:`~experiment_runner.core.executor.Executor`
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
:func:`experiment_runner.apps.campaigns.trials.simulate_trials`: the batch engine's noise is a pure
function of (trial seed, sample, channel) and trials do not interact, so a trial's
result does not depend on which chunk, process or machine ran it.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import socket
import time
from pathlib import Path
from typing import Optional

import numpy as np

from experiment_runner.apps.campaigns.spec import Campaign, conditions
from experiment_runner.apps.campaigns.trials import metric_record, plain, reference, simulate_trials
from experiment_runner.core import outputs
from experiment_runner.core.batch import Models
from stage_sim.config import ConfigError, Preset

__all__ = ["TrialStream", "run_trials", "run_trial_jobs", "warm_up", "representative_trial", "chunk_task",
           "campaign_key", "code_fingerprint", "STREAM_NAME", "CODE_MODULES"]

FORMAT = "nanostage-trials"
VERSION = 1
STREAM_NAME = "trials.jsonl"
_ROOT = Path(__file__).resolve().parents[3]
CODE_MODULES = ("stage_sim/config.py", "stage_sim/schema.py", *sorted(f"stage_sim/friction/{p.name}" for p in
                                                (_ROOT / "stage_sim" / "friction").glob("*.py")),
                "stage_sim/plant.py", "stage_sim/plant_model.py",
                "stage_control/dither.py", "stage_control/filters.py", "stage_control/sai.py",
                "stage_control/servo.py", "experiment_runner/core/batch.py", "experiment_runner/core/metrics.py",
                "experiment_runner/core/experiment.py", "experiment_runner/core/profiles.py",
                "experiment_runner/apps/campaigns/trials.py", "experiment_runner/apps/campaigns/stream.py")
"""Source files (relative to the repository) whose content decides a trial's result."""
CHUNK_BYTES = 128e6
"""Budget of one chunk's recorded trajectories per core of the worker that runs it [bytes] (about
13 float64 signals per sample): ~40 trials of 1.5 s at 10 kHz on a worker of one thread. The batch
engine's time per trial falls with the trials per thread (table_4_2, one thread, CPU time: 2.0 ms
per trial alone, 1.7 in chunks of 3, 1.5 of 8, 1.2 of 40), so a worker of several threads gets a
chunk as many times larger."""
MIN_CHUNK = 8
"""Fewest trials of a chunk that :func:`chunk_size` makes smaller to balance the workers' last tasks."""
SYNC_SECONDS = 1.0
"""Longest time a streamed trial stays in the operating system's cache before it is on disk (fsync)."""
STREAM_BYTES_PER_SAMPLE = 13 * 8 * 2    # signals x float64 x 2 (the engine's buffers were copied into the
                                  # BatchResult; since it returns them, the 2 is headroom: kept, so chunks stay)


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
    camp : experiment_runner.apps.campaigns.spec.Campaign
        The campaign as run (trial count and dwell overrides applied).
    presets : dict
        ``(case name, condition key) -> Preset`` as run (overrides, calibration, sweep applied).

    Returns
    -------
    str
        Hex digest; a stream is resumed only under the same key.
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
        outputs.check_file(self.path)         # nanostage's own stream, never a link (made with its folder)
        good = self._load() if resume and self.path.exists() else None
        self._file = outputs.open_stream(self.path, append=good is not None, header=json.dumps(self.header) + "\n")
        self._synced = time.monotonic()
        if good is not None and good < os.fstat(self._file.fileno()).st_size:
            self._file.truncate(good)          # drop the line cut by an interruption

    def _load(self) -> int | None:
        """Index the trials of the existing file; returns the size of its complete records, None if
        it has no complete header."""
        with open(self.path, "rb") as f:
            first = f.readline()
            if not first.endswith(b"\n"):
                return None                  # interrupted before the header was complete
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
        return good

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
        self._file.flush()                      # the OS has it: a killed run keeps every record
        if time.monotonic() - self._synced >= SYNC_SECONDS:
            self._sync()

    def _sync(self) -> None:
        """On disk (fsync): once per :data:`SYNC_SECONDS` and at :meth:`close`, not per chunk (an fsync
        costs milliseconds, and on many workers chunks complete tens of times a second); a machine
        that loses power loses at most that much of the stream, which a resume runs again."""
        os.fsync(self._file.fileno())
        self._synced = time.monotonic()

    def done(self, case: str, condition: str) -> set:
        """Trial indices of ``case`` at ``condition`` already in the stream.

        Parameters
        ----------
        case : str
            Case name.
        condition : str
            Condition key.

        Returns
        -------
        set of int
        """
        return self._done.get((case, condition), set())

    def append(self, records: list) -> None:
        """Append trial records: written through to the operating system at once, on disk within :data:`SYNC_SECONDS`.

        Parameters
        ----------
        records : list of dict
            Each with ``case``, ``condition``, ``trial``, ``x0_m`` [m] and ``metrics``; trials
            already in the stream are skipped.
        """
        new = [r for r in records if int(r["trial"]) not in self.done(r["case"], r["condition"])]
        self._write(new)
        for r in new:
            self._done.setdefault((r["case"], r["condition"]), set()).add(int(r["trial"]))

    def read(self, case: str, condition: str, n: int) -> tuple[list, list]:
        """Metrics dicts and start positions [m] of trials ``0 .. n-1`` of ``case`` at ``condition``.

        Parameters
        ----------
        case : str
            Case name.
        condition : str
            Condition key.
        n : int
            Trials to read.

        Returns
        -------
        metrics : list of dict
            Per trial, as :func:`experiment_runner.apps.campaigns.trials.metric_record`.
        x0 : list of float
            Start position of every trial [m].

        Raises
        ------
        RuntimeError
            A trial of ``0 .. n-1`` is not in the stream.
        """
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
        """Flush, fsync and close the file (idempotent)."""
        if not self._file.closed:
            self._file.flush()
            self._sync()
            self._file.close()

    def __enter__(self) -> "TrialStream":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# =========================================================================== chunks
@functools.lru_cache(maxsize=8)
def _campaign(camp_json: str):
    return Campaign.model_validate_json(camp_json)


@functools.lru_cache(maxsize=8)
def _preset_models(preset_json: str):
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
    if code != code_fingerprint():
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
             "metrics": plain(metric_record(tr, res, j, rate))} for j, tr in enumerate(trials)]


def warm_up(camp, case, cond, preset, executor) -> None:
    """Warm ``executor``'s workers in the background (:meth:`~experiment_runner.core.executor.Executor.warm`).

    Each worker runs trial 0 of ``case`` at ``cond``: its modules imported, the batch engine's
    kernels loaded, the preset's models built (cached for the real chunks).

    Parameters
    ----------
    camp : experiment_runner.apps.campaigns.spec.Campaign
        The campaign as run.
    case : experiment_runner.apps.campaigns.spec.Case
        The case.
    cond : experiment_runner.apps.campaigns.schema.common.Condition
        The condition.
    preset : stage_sim.config.Preset
        The case's stage at that condition, as run.
    executor : experiment_runner.core.executor.Executor
        Where the trials will run.
    """
    executor.warm(chunk_task, (camp.model_dump_json(), case.name, cond.key, preset.model_dump_json(), None, [0],
                               code_fingerprint()))


def chunk_size(n: int, samples: int, workers: int, total: Optional[int] = None, threads: int = 1) -> int:
    """Trials of the next chunk of a job with ``n`` trials of ``samples`` samples each still to hand
    out, ``total`` trials (every job's, default ``n``) in all: as large as :data:`CHUNK_BYTES` per
    thread allows (larger batches run faster per trial), but no more than a ``2 * workers``-th of
    ``total`` (guided scheduling: as the work left shrinks, so do the chunks, down to
    :data:`MIN_CHUNK`, and the workers finish together instead of waiting for one worker's last large
    chunk); the job's rest is split into equal chunks of at most that.

    Parameters
    ----------
    n : int
        Trials of the job still to hand out.
    samples : int
        Samples per trial.
    workers : int
        Worker processes.
    total : int, optional
        Trials of every job still to hand out (default ``n``).
    threads : int, optional
        Threads per worker.

    Returns
    -------
    int
        Trials of the next chunk.

    Examples
    --------
    >>> chunk_size(40, 15_000, 2, total=160), chunk_size(40, 15_000, 1, total=160), chunk_size(50, 15_000, 2)
    (40, 40, 13)
    >>> chunk_size(500, 11_300, 16, total=2000), chunk_size(500, 11_300, 16, total=200)
    (50, 8)
    >>> chunk_size(500, 11_300, 1), chunk_size(500, 11_300, 1, threads=16)      # one worker of 1 / 16 threads
    (50, 250)
    """
    cap = max(1, int(CHUNK_BYTES * max(1, threads) // (samples * STREAM_BYTES_PER_SAMPLE)))
    want = max(1, min(cap, n, max(MIN_CHUNK, math.ceil((total or n) / (2 * workers)))))
    return math.ceil(n / math.ceil(n / want))


def run_trial_jobs(camp, jobs: list, executor, stream: TrialStream, chunk: Optional[int] = None,
                   on_chunk=None) -> None:
    """All ``camp.trials`` trials of every job not yet in ``stream``, in chunks on ``executor``, appended
    to ``stream`` as they complete. The chunks of all jobs go to the executor as one task list, so
    the workers never wait for the last chunk of one case and condition before the next starts.

    Parameters
    ----------
    camp : experiment_runner.apps.campaigns.spec.Campaign
        The campaign as run.
    jobs : list of (case, cond, preset, correction)
        A case, a condition, the case's preset at it and its SAI Step II correction [m] (or None).
    executor : experiment_runner.core.executor.Executor
    stream : TrialStream
    chunk : int, optional
        Trials per task (default :func:`chunk_size` of each job).
    on_chunk : callable, optional
        ``on_chunk(case, cond, done, n)`` after every completed chunk: trials of that case and
        condition in the stream, of ``n`` (progress).
    """
    n = camp.trials
    camp_json = camp.model_dump_json()
    code = stream.header["code"]
    named = {(case.name, cond.key): (case, cond) for case, cond, _, _ in jobs}
    todo = {key: sorted(set(range(n)) - stream.done(*key)) for key in named}
    total = sum(len(t) for t in todo.values())

    def tasks():             # consumed as workers free up: the sizes follow the work still to hand out
        rest = total
        for case, cond, preset, correction in jobs:
            left = todo[case.name, cond.key]
            if not left:
                continue
            samples = len(reference(camp, cond, preset.controller.rate).x)
            preset_json = preset.model_dump_json()
            corr = None if correction is None else np.asarray(correction, float).tolist()
            a = 0
            while a < len(left):
                size = chunk or chunk_size(len(left) - a, samples, executor.workers, rest, executor.threads)
                yield ((case.name, cond.key, left[a]),
                       (camp_json, case.name, cond.key, preset_json, corr, left[a:a + size], code))
                a += size
                rest -= size

    for (case_name, cond_key, _), records in executor.map(chunk_task, tasks()):
        stream.append(records)
        if on_chunk is not None:
            on_chunk(*named[case_name, cond_key], len(stream.done(case_name, cond_key)), n)


def run_trials(camp, case, cond, preset, correction, executor, stream: TrialStream,
               chunk: Optional[int] = None, on_chunk=None) -> tuple[list, list]:
    """All ``camp.trials`` trials of ``case`` at ``cond`` (:func:`run_trial_jobs` of one job), read
    back from ``stream``.

    Parameters
    ----------
    camp : experiment_runner.apps.campaigns.spec.Campaign
        The campaign as run.
    case : experiment_runner.apps.campaigns.spec.Case
        The case.
    cond : experiment_runner.apps.campaigns.schema.common.Condition
        The condition.
    preset : stage_sim.config.Preset
        The case's stage at that condition, as run.
    correction : numpy.ndarray or None
        SAI Step II correction held by the manager (None: none).
    executor : experiment_runner.core.executor.Executor
        Where the chunks run.
    stream : TrialStream
        The campaign's stream; trials already in it are not run again.
    chunk : int, optional
        Trials per chunk (default :func:`chunk_size`).
    on_chunk : callable, optional
        ``on_chunk(done, n)`` after each chunk (progress).

    Returns
    -------
    metrics : list of dict
        Per trial ``0 .. n-1``, as :func:`experiment_runner.apps.campaigns.trials.metric_record`.
    x0 : list of float
        Start position of every trial [m].
    """
    run_trial_jobs(camp, [(case, cond, preset, correction)], executor, stream, chunk,
                   None if on_chunk is None else (lambda _case, _cond, done, n: on_chunk(done, n)))
    return stream.read(case.name, cond.key, n=camp.trials)


def representative_trial(camp, case, cond, preset, index: int, correction, metrics: dict):
    """Trial ``index`` simulated again on its own (for its trace), checked against its streamed ``metrics``.

    Parameters
    ----------
    camp : experiment_runner.apps.campaigns.spec.Campaign
        The campaign as run.
    case : experiment_runner.apps.campaigns.spec.Case
        The case.
    cond : experiment_runner.apps.campaigns.schema.common.Condition
        The condition.
    preset : stage_sim.config.Preset
        The case's stage at that condition, as run.
    index : int
        The trial.
    correction : numpy.ndarray or None
        SAI Step II correction (None: none).
    metrics : dict
        The trial's metrics as streamed.

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
    again = plain(metric_record(trial, res, 0, preset.controller.rate))
    if json.dumps(again, sort_keys=True) != json.dumps(metrics, sort_keys=True):
        raise RuntimeError(f"trial {index} of {case.name} at {cond.key} gives {again}, the stream has {metrics}: "
                           "the stream is stale; rerun with --restart")
    return ref, trial, res
