"""Reading a recording into numpy arrays (:func:`read_recording`), and the damage found in it."""
from __future__ import annotations

import io
from collections import Counter
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

import numpy as np

from experiment_runner.core.errors import RecordingError
from experiment_runner.core.recording.mcap import RawRecording, load_raw
from msg_defs import cdr, convert
from msg_defs.topics import (BEARING, COMMAND, COMMAND_KINDS, CONFIG, CONTRACT_TOPICS, DITHER, EVENTS, EXTERNAL_FORCE,
                             ISOLATOR, MEASURED, MOTOR, REFERENCE, RESULTS, SOURCE_CHANNELS, TABLE, TOPICS, TRUTH)
from stage_sim.validation import ConfigError, load_yaml


@dataclass
class JointSeries:
    """A JointState topic as arrays; rows follow ``stamp_ns``, columns ``names``."""
    stamp_ns: np.ndarray          # (n,) int64 stage time [ns]
    names: list[str]
    position: np.ndarray          # (n, len(names)); nan where a message has no value
    velocity: np.ndarray
    effort: np.ndarray

    @property
    def t(self) -> np.ndarray:
        """Stage time [s]."""
        return self.stamp_ns * 1e-9

    def joint(self, name: str, field: str = "position") -> np.ndarray:
        """Column of joint ``name`` (nan if the joint is absent)."""
        if name not in self.names:
            return np.full(len(self.stamp_ns), np.nan)
        return getattr(self, field)[:, self.names.index(name)]

    def __len__(self):
        return len(self.stamp_ns)


@dataclass
class Trial:
    """One trial of a recording, cut by its ``/experiment/events``."""
    trial: int
    case: str | None
    step_index: int | None
    start: int                    # first sample (index into the Recording arrays)
    stop: int                     # one past the last sample
    start_ns: int
    end_ns: int | None            # None: no trial_end (run cut short or aborted)
    window_m: float | None
    target_m: float | None
    settle_start_ns: int | None
    complete: bool                # trial_end seen, no abort/fault for it, no damage in its samples
    events: list[dict] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)   # why it is not complete (one line each)

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


@dataclass
class Recording:
    """A recording's signals (SI units), one entry per control sample."""
    path: Path
    stamp_ns: np.ndarray          # (N,) int64 stage time [ns]
    t: np.ndarray                 # (N,) stage time [s]
    x_ref: np.ndarray             # reference position [m]
    v_ref: np.ndarray             # reference velocity [m/s]
    u: np.ndarray                 # servo force command [N]
    y: np.ndarray                 # measured table position [m]
    y_bearing: np.ndarray         # measured bearing position [m] (nan without a sensor)
    events: list[dict]            # /experiment/events objects (+ "log_time_ns")
    results: list[dict]           # /experiment/results objects (+ "log_time_ns")
    config: str | None            # /experiment/config YAML
    truth: JointSeries | None
    dither: JointSeries | None
    isolator: JointSeries | None
    topics: dict[str, str]        # every topic in the file -> its type
    counts: dict[str, int]        # messages read per topic
    profile: str
    salvaged: str | None = None   # what was read from a file cut short (None = intact)
    warnings: list[str] = field(default_factory=list)
    open_loop: bool = False       # no /stage/reference: the recorded command drove the plant (x_ref, v_ref nan)
    external_force: np.ndarray | None = None   # known external force on the table [N] (/stage/external_force;
    #                                            None: the recording has none; nan where a sample lacks it)
    source: JointSeries | None = None          # /source/channels: columns an importer kept, as in the file
    damage: list = field(default_factory=list)  # Damage: what in the control samples is damaged (also in warnings)

    def __len__(self):
        return len(self.stamp_ns)

    def config_doc(self) -> dict:
        """``/experiment/config`` as read by the project's YAML loader
        (:func:`stage_sim.validation.load_yaml`: safe, bounded, duplicate keys refused): a
        mapping, ``{}`` when the recording carries none. A damaged configuration (not YAML, a
        tag, a NUL byte, not a mapping) raises :class:`~stage_sim.validation.ConfigError`
        naming the recording and the topic."""
        source = f"{self.path}: {CONFIG.name}"
        doc = load_yaml(self.config, source) if self.config else None
        if doc is None:
            return {}
        if not isinstance(doc, dict):
            raise ConfigError(f"{source}: top level must be a mapping, got {type(doc).__name__}")
        return doc

    @property
    def axis(self) -> str:
        """``"linear"`` or ``"rotary"``: ``run.axis`` of ``/experiment/config`` (an imported
        recording), else the preset's ``stage.kind`` (a simulated one), else linear. A
        damaged configuration raises (see :meth:`config_doc`): the axis sets the units."""
        cfg = self.config_doc()
        run, preset = cfg.get("run"), cfg.get("preset")
        stage = preset.get("stage") if isinstance(preset, dict) else None
        kind = (run.get("axis") if isinstance(run, dict) else None) or \
            (stage.get("kind") if isinstance(stage, dict) else None)
        return kind if kind in ("linear", "rotary") else "linear"

    @property
    def command_kind(self) -> str:
        """What ``/stage/command`` holds: ``"drive"`` -- a command to a drive with a force
        constant (the force applied may differ from it: force-constant ratio, delay, saturation)
        -- or ``"measured"`` -- the force actually applied, measured (no force-constant error
        is possible). ``/experiment/config`` ``command.kind`` (msg_defs/README.md); a recording
        without it (every simulated one, and any written before the key existed) is ``drive``.
        A value other than these two raises :class:`~stage_sim.validation.ConfigError` naming
        the recording and the key: the kind decides which physics a diagnosis may consider."""
        cmd = self.config_doc().get("command")
        if cmd is None:
            return "drive"
        kind = cmd.get("kind", "drive") if isinstance(cmd, dict) else cmd
        if kind not in COMMAND_KINDS:
            raise ConfigError(f"{self.path}: {CONFIG.name}: command.kind: got {kind!r}; expected drive (a command "
                              "to a drive with a force constant) or measured (the force applied, measured)")
        return kind

    @property
    def duration(self) -> float:
        """Stage time from the first to the last control sample [s]."""
        return float((self.stamp_ns[-1] - self.stamp_ns[0]) * 1e-9) if len(self) else 0.0

    def trials(self) -> list[Trial]:
        """The trials marked by ``trial_start`` / ``trial_end`` events, in order."""
        out = []
        evs = sorted(self.events, key=lambda e: e["stamp_ns"])
        for i, ev in enumerate(evs):
            if ev["event"] != "trial_start":
                continue
            mine = [ev]
            end = nxt = None
            for later in evs[i + 1:]:
                if later["event"] == "trial_start":
                    nxt = later
                    break
                if later.get("trial") == ev["trial"] and later["event"] in ("trial_end", "abort", "fault"):
                    mine.append(later)
                    if later["event"] == "trial_end":
                        end = later
                        break
            start = int(np.searchsorted(self.stamp_ns, ev["stamp_ns"], "left"))
            problems = [f"{e['event']}" + (f" ({e['node']})" if e.get("node") else "")
                        + f": {e.get('reason') or 'no reason given'}" for e in mine if e["event"] in ("abort", "fault")]
            if end is not None:
                stop = int(np.searchsorted(self.stamp_ns, end["stamp_ns"], "right"))
            elif nxt is not None:         # no trial_end: up to the next trial
                stop = int(np.searchsorted(self.stamp_ns, nxt["stamp_ns"], "left"))
                problems += [] if problems else ["no trial_end before the next trial_start"]
            else:                         # no trial_end: up to the end of the recording
                stop = len(self.stamp_ns)
                problems += [] if problems else [
                    "no trial_end: the recording ends first" + (" (cut short)" if self.salvaged else "")]
            problems += [p for p in (d.within(start, stop, self.t) for d in self.damage) if p]
            out.append(Trial(
                trial=ev["trial"], case=ev.get("case"), step_index=ev.get("step_index"), start=start,
                stop=stop, start_ns=ev["stamp_ns"], end_ns=end["stamp_ns"] if end else None,
                window_m=ev.get("window_m"), target_m=ev.get("target_m"),
                settle_start_ns=ev.get("settle_start_ns"), complete=not problems, events=mine, problems=problems))
        return out


@dataclass(frozen=True, slots=True)
class _Joints:
    """A JointState as the reader needs it (read by :class:`msg_defs.cdr.JointStateReader`)."""
    stamp_ns: int
    name: tuple
    position: tuple
    velocity: tuple
    effort: tuple


def _joint_series(topic: str, items) -> JointSeries:
    """(log_time, decoded JointState) pairs -> arrays, columns by joint name."""
    n = len(items)
    stamps = np.fromiter((lt for lt, _ in items), np.int64, n)
    first = tuple(items[0][1].name) if n else ()
    shapes = {(tuple(m.name), len(m.position), len(m.velocity), len(m.effort)) for _, m in items}
    if len(shapes) == 1 and len(set(first)) == len(first):       # every message names the same joints
        _, *lens = next(iter(shapes))
        arrs = {}
        for k, ln in zip(("position", "velocity", "effort"), lens):
            if ln and ln != len(first):
                raise RecordingError(f"{topic}: message at {items[0][0]} ns has {len(first)} names but "
                                     f"{ln} {k} values")
            arrs[k] = (np.array([getattr(m, k) for _, m in items], float).reshape(n, len(first)) if ln
                       else np.full((n, len(first)), np.nan))
        return JointSeries(stamps, list(first), arrs["position"], arrs["velocity"], arrs["effort"])
    names: list[str] = []
    for _, m in items:
        for nm in m.name:
            if nm not in names:
                names.append(nm)
    col = {nm: i for i, nm in enumerate(names)}
    arrs = {k: np.full((n, len(names)), np.nan) for k in ("position", "velocity", "effort")}
    for r, (lt, m) in enumerate(items):
        idx = [col[x] for x in m.name]
        for k, a in arrs.items():
            vals = getattr(m, k)
            if len(vals):
                if len(vals) != len(idx):
                    raise RecordingError(f"{topic}: message at {lt} ns has {len(idx)} names but "
                                         f"{len(vals)} {k} values")
                a[r, idx] = vals
    return JointSeries(stamps, names, arrs["position"], arrs["velocity"], arrs["effort"])


def _need(series: JointSeries, topic: str, name: str, fld: str) -> np.ndarray:
    if name not in series.names:
        raise RecordingError(f"{topic} has no joint {name!r} (names: {series.names})")
    col = series.joint(name, fld)
    if np.all(np.isnan(col)):
        raise RecordingError(f"{topic}: joint {name!r} has no {fld} values")
    return col


@dataclass
class _JointTopic:
    """A JointState topic as read: its arrays and each message's ``header.stamp`` [ns]."""
    series: JointSeries
    header_ns: np.ndarray

    @property
    def stamp_mismatch(self) -> np.ndarray:
        """Log times of the messages whose ``header.stamp`` is not their log time."""
        return self.series.stamp_ns[self.header_ns != self.series.stamp_ns]


def _joint_topic(path, topic: str, msg_type: str, items) -> _JointTopic:
    """(log time, CDR bytes) pairs of a JointState topic -> :class:`_JointTopic`: at once where
    every message has the first's canonical layout (:func:`msg_defs.cdr.read_joint_states`, what
    a recorder writes), else message by message."""
    log_ns = np.fromiter((lt for lt, _ in items), np.int64, len(items))
    bulk = cdr.read_joint_states([d for _, d in items])
    if bulk is not None:
        header, names, *arrays = bulk
        if len(set(names)) == len(names) and all(a.shape[1] in (0, len(names)) for a in arrays):
            pos, vel, eff = (a if a.shape[1] else np.full((len(items), len(names)), np.nan) for a in arrays)
            return _JointTopic(JointSeries(log_ns, list(names), pos, vel, eff), header)
    read = cdr.JointStateReader().read
    decoded = []
    for lt, data in items:
        try:
            decoded.append((lt, _Joints(*read(data))))
        except Exception as err:          # noqa: BLE001
            raise RecordingError(f"{path}: {topic}: message at {lt} ns does not decode as {msg_type} ({err})") from None
    header = np.fromiter((m.stamp_ns for _, m in decoded), np.int64, len(decoded))
    return _JointTopic(_joint_series(topic, decoded), header)


def read_recording(path, require_reference: bool = True) -> Recording:
    """Read a contract recording into arrays.

    Parameters
    ----------
    path : str or Path
        The MCAP file, or the bag directory holding it.
    require_reference : bool
        A recording without ``/stage/reference`` is an open-loop record (the recorded
        command drove the plant; ``nanostage convert`` writes one from a table without a
        reference column). Tools that need a reference (closed-loop replay) refuse it: the
        default. With ``False`` it is read with ``open_loop = True`` and nan ``x_ref``/``v_ref``.

    Returns
    -------
    Recording
        Control samples are those present on all contract topics the file has (matched by
        log time). ``salvaged`` describes what was recovered from a file cut short.
        ``external_force`` holds ``/stage/external_force`` at the control samples.

    Raises
    ------
    RecordingError
        Not an MCAP file, not profile ``ros2``, a contract topic missing or of the wrong
        type, or messages that do not decode.
    """
    from mcap_ros2.decoder import DecoderFactory
    raw = load_raw(path)
    where = f"{raw.path}" + (f" ({raw.salvaged})" if raw.salvaged else "")
    for c in raw.channels.values():
        if not c.topic or not c.topic.isprintable():
            raise RecordingError(f"{where}: damaged: channel {c.id} has the topic name {c.topic!r}")
    topics = {c.topic: (raw.schemas[c.schema_id].name if c.schema_id in raw.schemas else "?")
              for c in raw.channels.values()}
    missing = [t for t in CONTRACT_TOPICS if t not in topics]
    open_loop = missing == [REFERENCE.name] and not require_reference
    if missing and not open_loop:
        hint = ("; a recording without it is open-loop, which this reader was not asked to take "
                "(read_recording(..., require_reference=False))") if missing == [REFERENCE.name] else ""
        raise RecordingError(f"{where}: missing contract topic(s) {', '.join(missing)}; "
                             f"topics present: {sorted(topics) or 'none'}{hint}")
    for c in raw.channels.values():
        if c.topic in TOPICS and c.schema_id not in raw.schemas:
            raise RecordingError(f"{where}: {c.topic} (channel {c.id}) refers to schema {c.schema_id}, which "
                                 "the file does not hold")
    for name, typ in topics.items():
        if name in TOPICS and typ != TOPICS[name].msg_type:
            raise RecordingError(f"{raw.path}: {name} has type {typ}, the contract says {TOPICS[name].msg_type}")

    factory = DecoderFactory()
    by_topic: dict[str, list] = {t: [] for t in TOPICS}
    counts: Counter = Counter()
    decoders = {}
    joint_channels = set()
    for m in raw.messages:
        ch = raw.channels.get(m.channel_id)
        if ch is None:
            raise RecordingError(f"{where}: a message at {m.log_time} ns is on channel {m.channel_id}, which the "
                                 "file does not declare")
        counts[ch.topic] += 1
        if ch.topic not in TOPICS:
            continue                       # a reader ignores topics it does not know
        dec = decoders.get(ch.id)
        if dec is None:
            schema = raw.schemas.get(ch.schema_id)
            said = io.StringIO()
            try:
                with redirect_stdout(said), redirect_stderr(said):   # the ros2msg parser prints what it dislikes
                    dec = factory.decoder_for(ch.message_encoding, schema)
            except Exception as err:      # noqa: BLE001
                printed = said.getvalue().strip().splitlines()
                detail = printed[-1].strip() if printed else f"{type(err).__name__}: {err}"
                raise RecordingError(f"{raw.path}: {ch.topic}: schema does not parse ({detail})") from None
            if dec is None:
                raise RecordingError(
                    f"{raw.path}: {ch.topic}: cannot decode message encoding {ch.message_encoding!r} with "
                    f"schema encoding {getattr(schema, 'encoding', None)!r}; the contract wants cdr + ros2msg")
            decoders[ch.id] = dec
            if TOPICS[ch.topic].msg_type == cdr.JOINT_STATE:      # the schema parsed: read its CDR directly,
                joint_channels.add(ch.id)                          # all of the topic at once (below)
        if ch.id in joint_channels:
            by_topic[ch.topic].append((m.log_time, m.data))
            continue
        try:
            by_topic[ch.topic].append((m.log_time, dec(m.data)))
        except Exception as err:          # noqa: BLE001
            raise RecordingError(f"{raw.path}: {ch.topic}: message at {m.log_time} ns does not decode "
                                 f"as {topics[ch.topic]} ({err})") from None
    joints = {t: _joint_topic(raw.path, t, topics[t], items) for t, items in by_topic.items()
              if items and TOPICS[t].msg_type == cdr.JOINT_STATE}

    empty = [t for t in CONTRACT_TOPICS if not by_topic[t] and not (open_loop and t == REFERENCE.name)]
    if empty:
        raise RecordingError(f"{where}: contract topic(s) {', '.join(empty)} hold no messages")
    try:
        return _assemble(raw, where, topics, by_topic, joints, counts, open_loop)
    except RecordingError:
        raise
    except (AttributeError, TypeError, ValueError, IndexError, KeyError) as err:
        raise RecordingError(f"{where}: messages lack the fields of their contract type ({type(err).__name__}: "
                             f"{err}); the schema was altered or the file is damaged") from None


def _assemble(raw: RawRecording, where: str, topics: dict, by_topic: dict, joints: dict, counts: Counter,
              open_loop: bool = False) -> Recording:
    """Decoded messages -> :class:`Recording` (control samples on all contract topics); what is
    damaged in them -> ``Recording.damage`` (:func:`_find_damage`)."""
    warnings = []
    series = {t: joints[t].series for t in (*CONTRACT_TOPICS, TRUTH.name, DITHER.name, ISOLATOR.name,
                                             EXTERNAL_FORCE.name, SOURCE_CHANNELS.name)
              if t in joints}
    sample_topics = tuple(t for t in CONTRACT_TOPICS if not (open_loop and t == REFERENCE.name))
    for t in series:
        if t not in sample_topics:
            bad = len(joints[t].stamp_mismatch)
            if bad:
                warnings.append(f"{t}: {bad} message(s) with header.stamp != log time (log time used)")

    # control samples: stamps present on all three contract topics (two in an open-loop record)
    firsts = {t: np.unique(series[t].stamp_ns, return_index=True) for t in sample_topics}
    common = firsts[sample_topics[0]][0]
    for t in sample_topics[1:]:
        common = np.intersect1d(common, firsts[t][0], assume_unique=True)
    if not len(common):
        raise RecordingError(f"{where}: no control sample has messages on all of {', '.join(sample_topics)}")
    cols = {}
    for t in sample_topics:
        uniq, idx = firsts[t]
        cols[t] = idx[np.searchsorted(uniq, common)]
    cmd, meas = series[COMMAND.name], series[MEASURED.name]
    if open_loop:
        x_ref = v_ref = np.full(len(common), np.nan)
    else:
        ref = series[REFERENCE.name]
        x_ref = _need(ref, REFERENCE.name, TABLE, "position")[cols[REFERENCE.name]]
        v_ref = ref.joint(TABLE, "velocity")[cols[REFERENCE.name]]
    u = _need(cmd, COMMAND.name, MOTOR, "effort")[cols[COMMAND.name]]
    y = _need(meas, MEASURED.name, TABLE, "position")[cols[MEASURED.name]]
    y_b = meas.joint(BEARING, "position")[cols[MEASURED.name]]
    f_ext = None
    if EXTERNAL_FORCE.name in series:
        ext = series[EXTERNAL_FORCE.name]
        uniq, idx = np.unique(ext.stamp_ns, return_index=True)
        pos = np.minimum(np.searchsorted(uniq, common), len(uniq) - 1)
        hit = uniq[pos] == common
        f_ext = np.where(hit, _need(ext, EXTERNAL_FORCE.name, TABLE, "effort")[idx[pos]], np.nan)
        if not hit.all():
            warnings.append(f"{EXTERNAL_FORCE.name}: {int((~hit).sum())} control sample(s) without a value (nan)")

    def _json_list(topic, parse):
        out = []
        for lt, m in by_topic[topic]:
            try:
                rec = parse(m.data)
            except ValueError as err:
                warnings.append(f"{topic}: message at {lt} ns skipped: {err}")
                continue
            if not isinstance(rec, dict):
                warnings.append(f"{topic}: message at {lt} ns is not a JSON object; skipped")
                continue
            rec["log_time_ns"] = lt
            out.append(rec)
        return out

    events = _json_list(EVENTS.name, convert.parse_event)
    results = _json_list(RESULTS.name, convert.from_json)
    configs = by_topic[CONFIG.name]
    if len(configs) > 1:
        warnings.append(f"{CONFIG.name}: {len(configs)} messages; the first is used")
    rec = Recording(
        path=raw.path, stamp_ns=common.astype(np.int64), t=common * 1e-9, x_ref=x_ref, v_ref=v_ref, u=u, y=y,
        y_bearing=y_b, events=events, results=results, config=configs[0][1].data if configs else None,
        truth=series.get(TRUTH.name), dither=series.get(DITHER.name), isolator=series.get(ISOLATOR.name),
        topics=topics, counts=dict(counts), profile=raw.profile, salvaged=raw.salvaged, warnings=warnings,
        open_loop=open_loop, external_force=f_ext, source=series.get(SOURCE_CHANNELS.name))
    back = {raw.channels[c].topic: v for c, v in raw.backwards.items() if raw.channels[c].topic in sample_topics}
    rec.damage = _find_damage(rec, {t: joints[t] for t in sample_topics},
                              back)
    rec.warnings += [d.text for d in rec.damage]
    return rec


LIMITS = {"position": 1e6, "velocity": 1e6, "effort": 1e9}
"""Largest magnitude of a value in a recording, per JointState field (SI: m or rad, m/s or
rad/s, N or N·m), far beyond any stage: a larger one is damage (a unit or scale error, a
corrupt sample), never data -- it would overflow the diagnosis' sums of squares."""
_UNITS = {"position": "m (rad)", "velocity": "m/s (rad/s)", "effort": "N (N·m)"}


def beyond_limits(values: np.ndarray, fld: str) -> np.ndarray:
    """Mask of ``values`` (of JointState field ``fld``) that are not finite or beyond
    :data:`LIMITS` -- the one rule of what value is damage (the reader and ``convert`` use it).

    >>> beyond_limits(np.array([0.0, np.nan, -np.inf, 1e300, -2e-3]), "position").tolist()
    [False, True, True, True, False]
    """
    with np.errstate(invalid="ignore"):
        return ~(np.abs(values) <= LIMITS[fld])


@dataclass(frozen=True)
class Damage:
    """One defect of a recording's control samples, found by the reader (:func:`read_recording`).

    ``kind``: ``"value"`` (non-finite or beyond :data:`LIMITS`: the samples cannot be used),
    ``"gap"`` (samples missing on every contract topic), ``"dropped"`` (samples missing on one
    topic, so dropped from all), ``"duplicate"`` (two messages with one stamp), ``"backwards"``
    (a stamp before the one written before it), ``"stamp"`` (``header.stamp`` != log time).
    ``indices`` are the control samples concerned (into the :class:`Recording` arrays; for a
    missing sample, the one after it; one entry per sample or message), ``index`` the first,
    ``text`` one line naming the topic, sample and time.
    """
    kind: str
    topic: str
    indices: np.ndarray = field(repr=False, compare=False)
    text: str

    WHAT: ClassVar[dict] = {"value": "non-finite or absurd value(s)", "gap": "sample(s) missing on every topic",
                            "dropped": "sample(s) dropped (missing on this topic)", "duplicate": "duplicate stamp(s)",
                            "backwards": "stamp(s) going backwards", "stamp": "header stamp(s) != log time"}

    @property
    def index(self) -> int:
        return int(self.indices[0])

    @property
    def unusable(self) -> bool:
        """The samples it touches cannot be used as a regular record (all kinds but ``"stamp"``,
        where the log time is a good stamp)."""
        return self.kind != "stamp"

    @property
    def count(self) -> int:
        return len(self.indices)

    def within(self, start: int, stop: int, t: np.ndarray | None = None) -> str | None:
        """What of it lies in samples ``[start, stop)`` (one line; with the sample times ``t``,
        the first one's time), or None."""
        k = self.indices[(self.indices >= start) & (self.indices < stop)]
        if not len(k):
            return None
        when = f" (t = {t[int(k[0])]:.6f} s)" if t is not None else ""
        return f"{self.topic}: {len(k)} {self.WHAT[self.kind]}, the first at sample {int(k[0])}{when}"


def _at(rec: Recording, i: int) -> str:
    i = min(max(int(i), 0), len(rec) - 1)
    return f"sample {i}, t = {rec.t[i]:.6f} s"


def _find_damage(rec: Recording, topics: dict, back: dict) -> list[Damage]:
    """The damage of ``rec``'s control samples (see :class:`Damage`): ``topics`` the contract
    topics as read (:class:`_JointTopic`), ``back`` what went back in file order
    (:func:`_backwards`, by topic)."""
    series = {t: jt.series for t, jt in topics.items()}
    out: list[Damage] = []
    n, stamps = len(rec), rec.stamp_ns

    def add(kind, topic, indices, text):
        out.append(Damage(kind, topic, np.clip(np.atleast_1d(np.asarray(indices, np.int64)), 0, n - 1),
                          f"{topic}: {text}"))

    # values: non-finite or absurd (a signal that is absent -- all nan -- is not damage)
    signals = [(COMMAND.name, "effort", MOTOR, rec.u), (MEASURED.name, "position", TABLE, rec.y),
               (MEASURED.name, "position", BEARING, rec.y_bearing)]
    if not rec.open_loop:
        signals[:0] = [(REFERENCE.name, "position", TABLE, rec.x_ref), (REFERENCE.name, "velocity", TABLE, rec.v_ref)]
    if rec.external_force is not None:
        f = rec.external_force
        signals.append((EXTERNAL_FORCE.name, "effort", TABLE, np.where(np.isnan(f), 0.0, f)))   # nan: no message
    for topic, fld, joint, a in signals:
        if np.all(np.isnan(a)):
            continue
        bad = np.flatnonzero(beyond_limits(a, fld))
        if len(bad):
            i = int(bad[0])
            add("value", topic, bad, f"{len(bad)} sample(s) with a non-finite or absurd {joint} {fld} "
                f"(beyond ±{LIMITS[fld]:g} {_UNITS[fld]}), the first at {_at(rec, i)}: {float(a[i])!r}")
    # stamps
    for topic, ser in series.items():
        if topic in back:
            k, lt, step = back[topic]
            add("backwards", topic, np.full(k, np.searchsorted(stamps, lt)),
                f"{k} message(s) stamped before the message written before them, the first "
                f"{step * 1e-6:.6g} ms earlier, at t = {lt * 1e-9:.6f} s")
        wrong = topics[topic].stamp_mismatch
        if len(wrong):
            add("stamp", topic, np.searchsorted(stamps, wrong),
                f"{len(wrong)} message(s) with header.stamp != log time (log time used), the first at "
                f"t = {wrong[0] * 1e-9:.6f} s")
        ordered = np.sort(ser.stamp_ns)
        dup = ordered[1:][np.diff(ordered) == 0]
        if len(dup):
            add("duplicate", topic, np.searchsorted(stamps, dup),
                f"{len(dup)} duplicate stamp(s) (the first message of each kept), the first at "
                f"t = {dup[0] * 1e-9:.6f} s")
    union = np.unique(np.concatenate([ser.stamp_ns for ser in series.values()]))
    if len(union) > n:
        for topic, ser in series.items():
            lack = np.setdiff1d(union, ser.stamp_ns, assume_unique=False)
            if len(lack):
                i = int(np.searchsorted(stamps, lack[0]))
                add("dropped", topic, np.searchsorted(stamps, lack),
                    f"no message at {len(lack)} control sample(s) the other contract topics have, so they are "
                    f"dropped; the first at t = {lack[0] * 1e-9:.6f} s (before {_at(rec, i)})")
    # gaps: intervals of more than 1.5 sample periods between the stamps of any contract topic (samples
    # missing on all of them), inside a trial (or anywhere, without trials)
    if len(union) > 2:
        d = np.diff(union)
        period = float(np.median(d))
        spans = [(int(stamps[tr.start]), int(stamps[tr.stop - 1])) for tr in rec.trials() if tr.stop > tr.start] \
            or [(int(union[0]), int(union[-1]))]
        inside = np.zeros(len(d), bool)
        for a, b in spans:
            inside |= (union[:-1] >= a) & (union[1:] <= b)
        gaps = np.flatnonzero((d > 1.5 * period) & inside)
        if len(gaps):
            missing = np.rint(d[gaps] / period).astype(np.int64) - 1
            j = int(gaps[0])
            i = int(np.searchsorted(stamps, union[j + 1]))
            add("gap", "control samples", np.repeat(np.searchsorted(stamps, union[gaps + 1]), missing),
                f"{int(missing.sum())} sample(s) missing on every contract topic in {len(gaps)} gap(s) inside "
                f"trials, the first {missing[0]} between t = {union[j] * 1e-9:.6f} s and {union[j + 1] * 1e-9:.6f} s "
                f"(before {_at(rec, i)}; sample period {period * 1e-9:.6g} s)")
    return out


