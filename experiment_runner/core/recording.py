"""MCAP recordings of nanostage runs, after ``shared/contract/recording.md``.

Writing
    :class:`McapRecorder` writes a rosbag2 bag (version 9, MCAP storage) with the
    ``rosbags`` writer: a directory holding one MCAP file, ``<dir>/<dir name>.mcap``,
    and ``metadata.yaml`` (the layout ``ros2 bag record -s mcap -o <dir>`` makes), so
    ``ros2 bag``, ``rosbags`` and Foxglove/``mcap`` tools all open it. The MCAP file is
    self-contained (profile ``ros2``, ``ros2msg`` schemas with their dependencies, ``cdr``
    messages, chunk and message indexes, summary with statistics, each channel's
    ``offered_qos_profiles``, the bag metadata as a ``rosbag2`` metadata record). A chunk
    is closed and flushed every ``chunk_ns`` of stage time (0.1 s) or ``chunk_bytes``
    (1 MiB), so a killed process loses at most that much. Log time and ``header.stamp``
    of every message are the stage time of the sample [ns].
    :func:`write_trials` is the one writer of such a recording from signals in memory:
    :func:`write_run` writes batch-engine trials (:class:`~experiment_runner.core.batch.BatchResult`)
    through it, laid out as the ROS graph would record them, and
    :func:`experiment_runner.core.tabular.write_signals` a converted table.

Reading
    :func:`read_recording` reads a recording (the MCAP file or its bag directory), from
    ours, a rig's or any tool that follows the contract, into numpy arrays
    (:class:`Recording`), with the optional ``/stage/external_force`` and
    ``/source/channels`` where present; a file without ``/stage/reference`` is an
    open-loop record, read only on request (``require_reference=False``).
    ``Recording.command_kind`` says what ``/stage/command`` holds (``drive`` or
    ``measured``: ``/experiment/config`` ``command.kind``, default ``drive``). It reads
    through the MCAP index; if the file was cut short (a
    killed recorder) it falls back to reading record by record up to the last complete
    chunk and says what it salvaged in ``Recording.salvaged`` (messages, of how many
    recorded when the bag's ``metadata.yaml`` tells, and the stage time span). A damaged
    file -- a chunk failing its CRC (every chunk we write carries one), a corrupt length
    or record in a file written to its end, a message on an undeclared channel -- is
    refused: a :class:`RecordingError` names the problem and its byte offset, as for
    anything else that keeps the file from being a contract recording (not MCAP, profile
    not ``ros2``, contract topics missing or of the wrong type, messages that do not
    decode). The reader never loops on its input: every step advances through the file.
"""
from __future__ import annotations

import io
import struct
import zlib
from collections import Counter
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import ClassVar

import numpy as np

from experiment_runner.core import outputs
from experiment_runner.core.errors import RecordingError
from experiment_runner.core.metrics import trial_metrics
from msg_defs import cdr, convert
from msg_defs.topics import (BEARING, CLOCK, COMMAND, COMMAND_KINDS, CONFIG, CONTRACT_TOPICS, DITHER, EVENTS,
                             EXTERNAL_FORCE, ISOLATOR, ISOLATOR_JOINT, MEASURED, MOTOR, PIEZOS, REFERENCE, RESULTS,
                             SOURCE_CHANNELS, TABLE, TOPICS, TRUTH, Qos, qos_yaml)
from stage_sim.plant import OK, STATUS_TEXT
from stage_sim.validation import ConfigError, input_file_problem, load_yaml, load_yaml_file

__all__ = ["RecordingError", "McapRecorder", "Recording", "JointSeries", "Trial", "Damage", "read_recording",
           "TrialSignals", "write_trials", "write_run", "run_config_yaml", "mcap_file", "bag_layout", "LIMITS", "beyond_limits"]

MCAP_MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
_NS = 1_000_000_000
_CHUNK_CRC_OFFSET = 9 + 8 + 8 + 8
"""Byte offset of ``uncompressed_crc`` in a chunk record (opcode, length, start, end, size)."""
_COMPRESSIONS = ("", "zstd", "lz4")
_MAX_CHUNK = 1 << 32
"""Largest uncompressed chunk a reader accepts [bytes] (the mcap library's record limit)."""
_MAX_RATIO = 1024
"""A compressed chunk may claim at most this many times its size uncompressed (or 64 MiB):
a corrupt size field must not make the reader allocate gigabytes."""


def _size_problem(compression: str, compressed: int, uncompressed: int) -> str | None:
    """Why a chunk's claimed sizes cannot be right (None if they can)."""
    limit = _MAX_CHUNK if not compression else min(_MAX_CHUNK, max(64 << 20, _MAX_RATIO * compressed))
    if uncompressed > limit or (not compression and uncompressed != compressed):
        return f"claiming {uncompressed} bytes uncompressed from {compressed} bytes ({compression or 'none'})"
    return None


# =========================================================================== writing
@lru_cache(maxsize=None)
def typestore():
    from rosbags.typesys import Stores, get_typestore
    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=None)
def _writer_classes():
    """rosbags' Writer with its MCAP storage closing (and flushing) chunks by stage time."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.metadata import dump_qos_v9
    from rosbags.rosbag2.storage_mcap import McapWriter

    class ChunkedMcap(McapWriter):
        chunk_ns = 100_000_000
        chunk_bytes = 1 << 20

        def add_connection(self, connection, offered_qos_profiles):
            # the channel's offered_qos_profiles in rosbag2's (yaml-cpp) layout and key order
            qos = qos_yaml(dump_qos_v9(list(connection.ext.offered_qos_profiles)))
            super().add_connection(connection, qos)

        def write(self, connection, timestamp, data):
            super().write(connection, timestamp, data)
            ck = self.chunk
            if ck.msgs and (ck.message_end_time - ck.message_start_time >= self.chunk_ns
                            or ck.bio.tell() >= self.chunk_bytes):
                self.close_chunk()

        def close_chunk(self):
            # rosbags leaves the chunk CRC 0 ("not computed"): write the CRC-32 of the
            # uncompressed records into the chunk record, so readers detect damage
            crc = zlib.crc32(self.chunk.bio.getbuffer())
            start = self.bio.tell()
            super().close_chunk()
            end = self.bio.tell()
            self.bio.seek(start + _CHUNK_CRC_OFFSET)
            self.bio.write(struct.pack("<I", crc))
            self.bio.seek(end)
            self.bio.flush()          # a killed process keeps every closed chunk

    class ChunkedWriter(Writer):
        STORAGE_PLUGINS = {**Writer.STORAGE_PLUGINS, StoragePlugin.MCAP: ChunkedMcap}

    return ChunkedWriter, StoragePlugin


def _rosbags_qos(q: Qos):
    from rosbags.interfaces import Qos as RQos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
    inf = QosTime(9223372036, 854775807)
    return RQos(QosHistory[q.history.upper()], q.depth, QosReliability[q.reliability.upper()],
                QosDurability[q.durability.upper()], inf, inf, QosLiveliness.AUTOMATIC, inf, False)


def bag_layout(path) -> tuple[Path, Path]:
    """``(bag directory, MCAP file)`` a recorder writes for ``path``.

    ``path`` names the bag directory; a trailing ``.mcap`` is dropped from it, so
    ``out/run`` and ``out/run.mcap`` both give ``out/run/run.mcap``.

    >>> [str(p) for p in bag_layout("out/run.mcap")]
    ['out/run', 'out/run/run.mcap']
    """
    path = Path(path)
    bag = path.with_suffix("") if path.suffix == ".mcap" else path
    return bag, bag / f"{bag.name}.mcap"


class McapRecorder:
    """Write a contract recording (rosbag2 bag, MCAP storage) message by message.

    Parameters
    ----------
    path : str or Path
        Bag directory to create (see :func:`bag_layout`); ``self.path`` is the MCAP file.
    config_yaml : str, optional
        YAML of the run's configuration, written first on ``/experiment/config``.
    start_ns : int
        Stage time [ns] of the config message.
    chunk_ns : int
        Close (and flush) a chunk once it spans this much stage time [ns].
    chunk_bytes : int
        ... or once it holds this many bytes (rosbags closes at 1 MiB anyway).
    overwrite : bool
        Replace an existing recording at ``path`` (only nanostage's files in it:
        :mod:`experiment_runner.core.outputs`); otherwise an existing one is refused
        (:class:`~experiment_runner.core.outputs.OutputError`).
    atomic : bool
        Write the bag in a temporary folder beside ``path`` and move it into place on
        :meth:`close` (a run that fails or is interrupted leaves nothing at ``path``: files
        written whole, such as a campaign's or ``synth``'s). Default: written in place, so a
        killed process leaves a file readable up to its last chunk (the ``recorder`` node).

    ``write(topic, stamp_ns, msg)`` takes rclpy messages, rosbags messages or raw CDR
    bytes. Topics of :data:`msg_defs.topics.TOPICS` get their contract type and QoS;
    others need :meth:`add_topic` (or a message, whose type is then used). Use it as a
    context manager, or call :meth:`close`, which writes the index and summary. Not
    thread-safe: call it from one thread (e.g. one recorder node's callbacks).
    """

    def __init__(self, path, config_yaml: str | None = None, *, start_ns: int = 0,
                 chunk_ns: int = 100_000_000, chunk_bytes: int = 1 << 20, overwrite: bool = False,
                 atomic: bool = False):
        self.bag_dir, self.path = bag_layout(path)
        self._install = outputs.replacing_folder(self.bag_dir, overwrite) if atomic else None
        if atomic:
            where = self._install.__enter__()
        else:
            outputs.prepare_recording(self.bag_dir, overwrite)
            where = self.bag_dir
        writer_cls, plugin = _writer_classes()
        self._store = typestore()
        self._conns: dict = {}
        self.counts: Counter = Counter()
        self._closed = False
        self._writer = None
        try:
            self._writer = writer_cls(where, version=9, storage_plugin=plugin.MCAP)
            self._writer.set_custom_data("nanostage_recording_contract", "1")
            self._writer.open()
            if not atomic:
                outputs.record(where, [self.path.name, "metadata.yaml"])
            self._writer.storage.chunk_ns = int(chunk_ns)
            self._writer.storage.chunk_bytes = int(chunk_bytes)
            if config_yaml is not None:
                self.write(CONFIG.name, start_ns, convert.string_msg(self._store, config_yaml))
        except BaseException as err:
            self._finish(err)
            raise

    # ------------------------------------------------------------------ topics
    def add_topic(self, name: str, msg_type: str | None = None, qos: Qos | None = None):
        """Declare a topic (contract topics need nothing; others need ``msg_type``)."""
        topic = TOPICS.get(name)
        if msg_type is None:
            if topic is None:
                raise KeyError(f"{name!r} is not a contract topic: give its msg_type")
            msg_type = topic.msg_type
        if topic is not None and msg_type != topic.msg_type:
            raise TypeError(f"{name} carries {topic.msg_type} by contract, not {msg_type}")
        if name in self._conns:
            return self._conns[name]
        if msg_type not in self._store.types:
            raise TypeError(f"{name}: {msg_type} is not a standard ROS 2 Jazzy interface")
        qos = qos or (topic.qos if topic else Qos())
        conn = self._writer.add_connection(name, msg_type, typestore=self._store, serialization_format="cdr",
                                           offered_qos_profiles=[_rosbags_qos(qos)])
        self._conns[name] = conn
        return conn

    # ------------------------------------------------------------------ writing
    def _serialize(self, msg_type: str, msg) -> bytes:
        """Canonical CDR (zero padding, nothing after the last field) of a message of any family."""
        return self._store.serialize_cdr(convert.to_rosbags(msg, self._store), msg_type)

    def write(self, topic: str, stamp_ns: int, msg) -> None:
        """Write one message at stage time ``stamp_ns`` [ns] (its MCAP log time).

        A message with a header (or a Clock) must carry the same stamp. ``msg`` may be
        raw CDR bytes (written as given). ``/experiment/config`` must come first, once.
        """
        if self._closed:
            raise ValueError(f"{self.path}: recorder is closed")
        stamp_ns = int(stamp_ns)
        raw = isinstance(msg, (bytes, bytearray, memoryview))
        if topic not in self._conns:
            self.add_topic(topic, None if raw or topic in TOPICS else convert.message_type_of(msg))
        conn = self._conns[topic]
        if topic == CONFIG.name and sum(self.counts.values()):
            raise ValueError(f"{CONFIG.name} must be written once, first (already written: "
                             f"{dict(self.counts)})")
        if raw:
            data = bytes(msg)
        else:
            msg_type = convert.message_type_of(msg)
            if msg_type != conn.msgtype:
                raise TypeError(f"{topic} carries {conn.msgtype}, got a {msg_type}")
            if hasattr(msg, "header") or hasattr(msg, "clock"):
                got = convert.stamp_ns(msg)
                if got != stamp_ns:
                    raise ValueError(f"{topic}: message stamp {got} ns != log time {stamp_ns} ns "
                                     "(both must be the sample's stage time)")
            data = self._serialize(msg_type, msg)
        self._writer.write(conn, stamp_ns, data)
        self.counts[topic] += 1

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def close(self) -> None:
        """Write the last chunk, the index and summary, and ``metadata.yaml`` (idempotent); an
        ``atomic`` recording is then moved into place."""
        self._finish(None)

    def _finish(self, err) -> None:
        if self._closed:
            return
        self._closed = True
        install, self._install = self._install, None
        try:
            if self._writer is not None and self._writer.storage is not None:
                self._writer.close()
        except BaseException as e:
            err = err or e
            raise
        finally:
            if install is not None:
                install.__exit__(*((type(err), err, err.__traceback__) if err else (None, None, None)))

    def __enter__(self):
        return self

    def __exit__(self, typ, err, tb):
        # after an error: in place, what was written stays readable; atomic, nothing is left
        self._finish(err)
        return False


# =========================================================================== reading
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


def mcap_file(path) -> Path:
    """The MCAP file of a recording given as the file, its bag directory, or the name a
    recorder was given (``out/run.mcap`` -> ``out/run/run.mcap``)."""
    p = Path(path)
    if p.is_dir():
        files = sorted(p.glob("*.mcap"))
        if not files:
            raise RecordingError(f"{p}: directory holds no .mcap file")
        if len(files) > 1:
            raise RecordingError(f"{p}: directory holds {len(files)} .mcap files "
                                 f"({', '.join(f.name for f in files)}); a recording is one MCAP file")
        return files[0]
    if p.exists():
        problem = input_file_problem(p)
        if problem is not None:
            raise RecordingError(f"{p}: {problem}")
        return p
    bag, inner = bag_layout(p)
    if p.suffix == ".mcap" and inner.is_file():
        return inner
    raise RecordingError(f"{p}: no such file or directory")


class _IndexMismatch(Exception):
    """The index and the summary statistics of a file disagree."""


class _Damage(Exception):
    """Where and why reading record by record stops; ``cut``: the file merely ends early
    (truncated, salvageable), else its bytes are wrong (damaged)."""

    def __init__(self, offset: int, why: str, cut: bool):
        super().__init__(why)
        self.offset, self.why, self.cut = offset, why, cut


def _opname(opcode: int) -> str:
    from mcap.opcode import Opcode
    try:
        return Opcode(opcode).name.lower()
    except ValueError:
        return f"opcode 0x{opcode:02x}"


def _has_closing_magic(f, size: int) -> bool:
    """True if the file ends with the MCAP magic (it was written to its end)."""
    f.seek(max(0, size - len(MCAP_MAGIC)))
    return size >= 2 * len(MCAP_MAGIC) and f.read(len(MCAP_MAGIC)) == MCAP_MAGIC


def _walk(f, size: int):
    """Yield ``(offset, opcode, body)`` for each whole record after the magic, up to the
    footer; raise :class:`_Damage` where the file stops making sense.

    A file that ends with the closing magic was written to its end: a record running
    past it is damage (a corrupt length), not a cut.
    """
    from mcap.opcode import Opcode
    cut = not _has_closing_magic(f, size)
    end = size if cut else size - len(MCAP_MAGIC)
    what = "the file ends" if cut else "the data ends (the file has its closing magic: a length field is wrong)"
    pos = len(MCAP_MAGIC)
    f.seek(pos)
    while True:
        head = f.read(9) if pos + 9 <= end else f.read(max(0, end - pos))
        if len(head) < 9:
            raise _Damage(pos, f"{what} without a footer" if not head else f"{what} inside a record header", cut)
        opcode, length = struct.unpack("<BQ", head)
        if length > end - pos - 9:
            raise _Damage(pos, f"a {_opname(opcode)} record of {length} bytes runs past the end of the "
                          f"{'file' if cut else 'data (the file has its closing magic: the length is wrong)'}", cut)
        body = f.read(length)
        yield pos, opcode, body
        pos += 9 + length
        if opcode == Opcode.FOOTER:
            return


def _parse(opcode: int, body: bytes):
    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Chunk, Header, Message, Schema, Statistics
    stream = ReadDataStream(io.BytesIO(body))
    if opcode == Opcode.CHUNK:
        return Chunk.read(stream)
    if opcode == Opcode.SCHEMA:
        return Schema.read(stream)
    if opcode == Opcode.CHANNEL:
        return Channel.read(stream)
    if opcode == Opcode.MESSAGE:
        return Message.read(stream, len(body))
    if opcode == Opcode.HEADER:
        return Header.read(stream)
    if opcode == Opcode.STATISTICS:
        return Statistics.read(stream)
    return None


@dataclass
class _Raw:
    """Undecoded content of an MCAP file."""
    path: Path
    profile: str
    schemas: dict
    channels: dict
    messages: list                # mcap.records.Message, in log-time order
    salvaged: str | None
    backwards: dict = field(default_factory=dict)   # channel id -> (count, log time, step back [ns]): see _backwards


def _header(path: Path, f, size: int):
    head = f.read(len(MCAP_MAGIC))
    if head != MCAP_MAGIC:
        raise RecordingError(f"{path}: not an MCAP file (starts with {head[:8]!r}, "
                             f"expected the MCAP magic {MCAP_MAGIC!r})")
    try:
        off, opcode, body = next(_walk(f, size))
        header = _parse(opcode, body)
    except _Damage:
        raise RecordingError(f"{path}: MCAP file cut short before the end of its header record "
                             "(nothing was recorded)") from None
    except Exception as err:      # noqa: BLE001 - parse errors
        raise RecordingError(f"{path}: MCAP file without a readable header record "
                             f"({type(err).__name__}: {err})") from None
    from mcap.records import Header
    if not isinstance(header, Header):
        raise RecordingError(f"{path}: MCAP file does not start with a header record "
                             f"(found a {_opname(opcode)} record)")
    return header


def _chunk_records(off: int, chunk) -> list:
    """The records of a chunk, CRC checked; :class:`_Damage` (not a cut) if it is wrong."""
    from mcap.stream_reader import CRCValidationError, breakup_chunk
    when = (f"a chunk (stage time {chunk.message_start_time * 1e-9:.6f} s to "
            f"{chunk.message_end_time * 1e-9:.6f} s)")
    if chunk.compression not in _COMPRESSIONS:
        raise _Damage(off, f"{when} with unknown compression {chunk.compression!r}", cut=False)
    problem = _size_problem(chunk.compression, len(chunk.data), chunk.uncompressed_size)
    if problem:
        raise _Damage(off, f"{when} {problem}", cut=False)
    try:
        return breakup_chunk(chunk, validate_crc=True)
    except CRCValidationError:
        raise _Damage(off, f"{when} fails its CRC check", cut=False) from None
    except Exception as err:      # noqa: BLE001 - a damaged chunk fails in many ways
        raise _Damage(off, f"{when} does not decode ({type(err).__name__}: {err})", cut=False) from None


def _recorded_count(path: Path) -> int | None:
    """Messages the bag's ``metadata.yaml`` says the file holds (None if unknown or unreadable;
    read by the project's bounded loader, :func:`stage_sim.validation.load_yaml_file`)."""
    meta = path.parent / "metadata.yaml"
    if not meta.exists():
        return None
    try:
        info = load_yaml_file(meta, "bag metadata")["rosbag2_bagfile_information"]
        for entry in info.get("files") or []:
            if Path(entry["path"]).name == path.name:
                return int(entry["message_count"])
    except (KeyError, TypeError, ValueError, AttributeError):   # ConfigError is a ValueError
        return None
    return None


def _salvage(path: Path, f, size: int, indexed_error: Exception) -> _Raw:
    """Read record by record up to a cut; keep whole chunks only. A damaged record (bad
    CRC, does not parse) raises :class:`RecordingError`: its data cannot be trusted."""
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema, Statistics
    schemas, channels, messages = {}, {}, []
    n_chunks = 0
    counted = None                # message count of the summary statistics, if read
    damage = None
    try:
        for off, opcode, body in _walk(f, size):
            try:
                rec = _parse(opcode, body)
            except Exception as err:      # noqa: BLE001 - any parse failure is damage here
                raise _Damage(off, f"a {_opname(opcode)} record does not parse ({err})", cut=False) from None
            inner = _chunk_records(off, rec) if opcode == Opcode.CHUNK else [rec]
            n_chunks += opcode == Opcode.CHUNK
            for r in inner:
                if isinstance(r, Schema):
                    schemas[r.id] = r
                elif isinstance(r, Channel):
                    channels[r.id] = r
                elif isinstance(r, Message):
                    messages.append(r)
                elif isinstance(r, Statistics):
                    counted = r.message_count
    except _Damage as d:
        damage = d
    backwards = _backwards(messages)
    messages.sort(key=lambda m: m.log_time)
    recorded = counted if counted is not None else _recorded_count(path)
    span = f"{len(messages)} message{'' if len(messages) == 1 else 's'}" + (
        f" of {recorded} recorded" if recorded is not None else "")
    if messages:
        span += (f", stage time {messages[0].log_time * 1e-9:.6f} s to "
                 f"{messages[-1].log_time * 1e-9:.6f} s")
    if damage is None and counted is not None and counted != len(messages):
        raise RecordingError(f"{path}: damaged: it holds {len(messages)} whole messages in {n_chunks} chunk(s), "
                             f"its summary counts {counted}; a damaged recording is not read")
    if damage is not None and not damage.cut:
        raise RecordingError(f"{path}: damaged: {damage.why} at byte {damage.offset} of {size}; the "
                             f"{n_chunks} chunk(s) before it ({span}) are intact, but a damaged recording "
                             f"is not read (re-record; or salvage them from a copy cut there: head -c {damage.offset} "
                             f"{path.name} > cut.mcap)")
    if damage is None and not _has_closing_magic(f, size):
        note = f"file cut short after its footer; salvaged {span}: all of its data"
    elif damage is not None:
        note = (f"file cut short: {damage.why} at byte {damage.offset} of {size}; salvaged {span} "
                f"from {n_chunks} complete chunk(s); anything after the last complete chunk is lost"
                + ("" if recorded is not None else " (how much was recorded is unknown: the file has no summary)"))
    else:
        why = f"{type(indexed_error).__name__}: {indexed_error}" if str(indexed_error) else type(indexed_error).__name__
        note = (f"index unreadable ({why}); read the whole "
                f"file record by record: {span} in {n_chunks} chunk(s)")
    return _Raw(path, "", schemas, channels, messages, note, backwards)


def load_raw(path) -> _Raw:
    """Schemas, channels and messages of an MCAP file: indexed, else salvaged."""
    from mcap.reader import SeekingReader
    path = mcap_file(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        header = _header(path, f, size)
        if header.profile != PROFILE:
            raise RecordingError(f"{path}: MCAP profile {header.profile!r}, a recording needs {PROFILE!r} "
                                 f"(written by {header.library!r})")
        try:
            f.seek(0)
            reader = SeekingReader(f, validate_crcs=True)
            summary = reader.get_summary()
            for ci in summary.chunk_indexes if summary is not None else ():
                problem = _size_problem(ci.compression, ci.compressed_size, ci.uncompressed_size)
                if problem:
                    raise _IndexMismatch(f"the index has a chunk {problem}")
            schemas, channels = {}, {}
            messages = indexed_messages(f, summary, validate_crcs=True)
            if messages is None:
                messages = []
                for schema, channel, message in reader.iter_messages(log_time_order=False):
                    if schema is not None:
                        schemas[schema.id] = schema
                    channels[channel.id] = channel
                    messages.append(message)
            # file order, then a stable sort by log time: the order iter_messages(log_time_order=True)
            # gives (ties by position in the file), without its per-message heap in Python
            backwards = _backwards(messages)
            messages.sort(key=lambda m: m.log_time)
            if summary is not None:
                schemas.update(summary.schemas)
                channels.update(summary.channels)
                stats = summary.statistics
                if stats is not None and stats.message_count != len(messages):
                    raise _IndexMismatch(f"the summary counts {stats.message_count} messages, "
                                         f"the index leads to {len(messages)}")
            raw = _Raw(path, header.profile, schemas, channels, messages, None, backwards)
        except Exception as err:          # noqa: BLE001 - truncated files fail in many ways
            f.seek(0)
            raw = _salvage(path, f, size, err)
            raw.profile = header.profile
    return raw


def _backwards(messages) -> dict:
    """Log times that go back on a channel, in file order (a writer writes each topic in time
    order): ``{channel id: (how many, the first such log time [ns], how far back it went [ns])}``.

    >>> from mcap.records import Message
    >>> msgs = [Message(channel_id=1, sequence=0, log_time=t, publish_time=t, data=b"") for t in (0, 10, 5, 20)]
    >>> _backwards(msgs)
    {1: (1, 5, 5)}
    """
    if not messages:
        return {}
    ch = np.fromiter((m.channel_id for m in messages), np.int64, len(messages))
    lt = np.fromiter((m.log_time for m in messages), np.int64, len(messages))
    out = {}
    for c in np.unique(ch):
        t = lt[ch == c]
        back = np.flatnonzero(np.diff(t) < 0)
        if len(back):
            i = int(back[0])
            out[int(c)] = (len(back), int(t[i + 1]), int(t[i] - t[i + 1]))
    return out


_RECORD_HEAD = struct.Struct("<BQ")                 # opcode, record length
_MESSAGE_HEAD = struct.Struct("<HIQQ")              # channel id, sequence, log time, publish time
_OP_MESSAGE = 0x05


def indexed_messages(f, summary, validate_crcs: bool = True) -> list | None:
    """The messages of an indexed MCAP file in the order ``SeekingReader.iter_messages(
    log_time_order=False)`` yields them (chunk index order, then record order in the chunk),
    as the same ``mcap.records.Message`` objects; ``None`` where that reader would not use
    the index (no summary or no chunk index). Chunks are read and CRC-checked by the mcap
    library; only the per-record loop is replaced (the library's Python stream reader costs
    ~10 us a message: half of reading a 10 kHz recording). A message on a channel the
    summary does not declare raises ``KeyError``, as the library does.

    >>> import io
    >>> from mcap.reader import make_reader
    >>> from mcap.writer import Writer
    >>> buf = io.BytesIO(); w = Writer(buf); w.start()
    >>> ch = w.register_channel("/t", "raw", w.register_schema("s", "raw", b""))
    >>> for t in (3, 1, 2): w.add_message(ch, log_time=t, data=bytes([t]), publish_time=t)
    >>> w.finish()
    >>> _ = buf.seek(0); reader = make_reader(buf)
    >>> ours = indexed_messages(buf, reader.get_summary())
    >>> ours == [m for _, _, m in reader.iter_messages(log_time_order=False)]
    True
    """
    from mcap.records import Chunk, Message
    from mcap.stream_reader import get_chunk_data_stream
    from mcap.data_stream import ReadDataStream
    if summary is None or not summary.chunk_indexes:
        return None
    head, msg_head = _RECORD_HEAD.unpack_from, _MESSAGE_HEAD.unpack_from
    out = []
    for ci in summary.chunk_indexes:
        f.seek(ci.chunk_start_offset + 1 + 8)
        chunk = Chunk.read(ReadDataStream(f))
        stream, n = get_chunk_data_stream(chunk, validate_crc=validate_crcs)
        buf = stream.read(n)
        off = 0
        while off < n:
            op, ln = head(buf, off)
            end = off + 9 + ln
            if end > n:
                raise ValueError(f"record at byte {off} of a chunk at {ci.chunk_start_offset} runs past "
                                 f"the chunk ({ln} bytes, {n - off - 9} left)")
            if op == _OP_MESSAGE:
                if ln < _MESSAGE_HEAD.size:
                    raise ValueError(f"message record of {ln} bytes in the chunk at {ci.chunk_start_offset}")
                cid, seq, log_time, pub_time = msg_head(buf, off + 9)
                summary.channels[cid]                        # noqa: B018 - undeclared channel: KeyError
                out.append(Message(channel_id=cid, sequence=seq, log_time=log_time,
                                   publish_time=pub_time, data=buf[off + 9 + _MESSAGE_HEAD.size:end]))
            off = end
    return out


@dataclass(frozen=True, slots=True)
class _Joints:
    """A JointState as the reader needs it (read by :class:`msg_defs.cdr.JointStateReader`)."""
    stamp_ns: int
    name: tuple
    position: tuple
    velocity: tuple
    effort: tuple


def _stamp_ns(m):
    """A message's header stamp [ns], None if it has none."""
    if isinstance(m, _Joints):
        return m.stamp_ns
    return convert.stamp_ns(m) if hasattr(m, "header") else None


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
    joint_readers = {}
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
            if TOPICS[ch.topic].msg_type == cdr.JOINT_STATE:      # the schema parsed: read its CDR directly
                joint_readers[ch.id] = cdr.JointStateReader().read
        try:
            jr = joint_readers.get(ch.id)
            by_topic[ch.topic].append((m.log_time, _Joints(*jr(m.data)) if jr is not None else dec(m.data)))
        except Exception as err:          # noqa: BLE001
            raise RecordingError(f"{raw.path}: {ch.topic}: message at {m.log_time} ns does not decode "
                                 f"as {topics[ch.topic]} ({err})") from None

    empty = [t for t in CONTRACT_TOPICS if not by_topic[t] and not (open_loop and t == REFERENCE.name)]
    if empty:
        raise RecordingError(f"{where}: contract topic(s) {', '.join(empty)} hold no messages")
    try:
        return _assemble(raw, where, topics, by_topic, counts, open_loop)
    except RecordingError:
        raise
    except (AttributeError, TypeError, ValueError, IndexError, KeyError) as err:
        raise RecordingError(f"{where}: messages lack the fields of their contract type ({type(err).__name__}: "
                             f"{err}); the schema was altered or the file is damaged") from None


def _assemble(raw: _Raw, where: str, topics: dict, by_topic: dict, counts: Counter,
              open_loop: bool = False) -> Recording:
    """Decoded messages -> :class:`Recording` (control samples on all contract topics); what is
    damaged in them -> ``Recording.damage`` (:func:`_find_damage`)."""
    warnings = []
    series = {t: _joint_series(t, by_topic[t]) for t in (*CONTRACT_TOPICS, TRUTH.name, DITHER.name, ISOLATOR.name,
                                                         EXTERNAL_FORCE.name, SOURCE_CHANNELS.name)
              if by_topic[t]}
    sample_topics = tuple(t for t in CONTRACT_TOPICS if not (open_loop and t == REFERENCE.name))
    for t in series:
        if t not in sample_topics:
            bad = sum(1 for lt, m in by_topic[t] if _stamp_ns(m) not in (None, lt))
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
    rec.damage = _find_damage(rec, {t: series[t] for t in sample_topics}, {t: by_topic[t] for t in sample_topics},
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


def _find_damage(rec: Recording, series: dict, items: dict, back: dict) -> list[Damage]:
    """The damage of ``rec``'s control samples (see :class:`Damage`): ``series`` / ``items`` the
    contract topics' JointSeries and (log time, message) pairs, ``back`` what went back in file
    order (:func:`_backwards`, by topic)."""
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
        wrong = [lt for lt, m in items[topic] if _stamp_ns(m) not in (None, lt)]
        if wrong:
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


# =========================================================================== batch -> recording
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
    :func:`experiment_runner.core.tabular.write_signals`' converted tables); returns the MCAP file.

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

