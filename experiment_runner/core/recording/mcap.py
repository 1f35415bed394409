"""The MCAP file of a recording, record by record: its index, and salvage of a file cut short (:func:`load_raw`)."""
from __future__ import annotations

import io
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from experiment_runner.core.errors import RecordingError
from stage_sim.validation import input_file_problem, load_yaml_file


MCAP_MAGIC = b"\x89MCAP0\r\n"
PROFILE = "ros2"
_NS = 1_000_000_000
CHUNK_CRC_OFFSET = 9 + 8 + 8 + 8
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
class RawRecording:
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


def _salvage(path: Path, f, size: int, indexed_error: Exception) -> RawRecording:
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
    return RawRecording(path, "", schemas, channels, messages, note, backwards)


def load_raw(path) -> RawRecording:
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
            raw = RawRecording(path, header.profile, schemas, channels, messages, None, backwards)
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


