#!/usr/bin/env python3
"""Build the fuzz corpus of the recording reader, deterministically.

Two tiny valid contract recordings are the seeds: one written by
:class:`~experiment_runner.core.recording.McapRecorder` (rosbags, uncompressed chunks, as
the recorder node writes) and one written by ``mcap_ros2`` (zstd-compressed chunks, as
other tools write). From each, mutations of these kinds are derived with a seeded
random generator (same bytes on every run):

``flip``      1-8 random bit flips;
``byte``      1-4 random bytes set to 0x00, 0xff or a random value;
``trunc``     cut at a random offset, and just before/after every record boundary;
``zero``      a random range (1-512 bytes) zero-filled;
``splice``    top-level records dropped, duplicated, swapped, or taken from the other seed;
``inner``     records inside an uncompressed chunk dropped, duplicated or swapped
              (the chunk's own length fields kept, then patched);
``length``    a record length field (top level or inside a chunk) set to 0, +-1,
              the remaining size, 2**31, 2**63 - 1 or 2**64 - 1;
``field``     chunk fields (uncompressed size, CRC, compression name), the header's
              profile, the footer's summary offsets and CRC set to bad values.

Output: ``test/fuzz_corpus/seed_recorder.mcap``, ``seed_zstd.mcap`` and
``corpus.tar.xz`` (every mutated file, named ``<seed>-<kind>-<n>.mcap``; the archive
is solid, so the near-identical files cost a few bytes each). ``test/test_fuzz_recording.py``
unpacks it and reads every case.

Usage: ``.venv/bin/python scripts/make_fuzz_corpus.py [--out test/fuzz_corpus]``
"""
from __future__ import annotations

import argparse
import io
import random
import struct
import sys
import tarfile
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MAGIC = b"\x89MCAP0\r\n"
CHUNK, FOOTER, HEADER = 0x06, 0x02, 0x01
DT_NS = 1_000_000                 # 1 kHz: a few samples span several chunks
SAMPLES = 12
PER_SEED = {"flip": 200, "byte": 80, "trunc": 70, "zero": 60, "splice": 60, "inner": 40, "length": 60,
            "field": 30}
"""Mutations per seed file and kind (the ``trunc`` kind adds one per record boundary)."""


# =========================================================================== seeds
def _seed_recorder(path: Path) -> bytes:
    """Contract recording by McapRecorder: config, events, 3 contract topics, chunk every 3 ms."""
    from rosbags.typesys import Stores, get_typestore

    from experiment_runner.core.recording import McapRecorder
    from msg_defs import convert
    ts = get_typestore(Stores.ROS2_JAZZY)
    with tempfile.TemporaryDirectory() as tmp:
        with McapRecorder(Path(tmp) / "seed", "run: {case: fuzz}\n", chunk_ns=3 * DT_NS) as rec:
            rec.write("/experiment/events", 0, convert.event_msg(ts, "trial_start", trial=0, case="fuzz",
                                                                stamp_ns=0, window_m=1e-6, node="fuzz"))
            for k in range(SAMPLES):
                s = k * DT_NS
                rec.write("/stage/reference", s, convert.joint_state(ts, s, ["table"], position=[k * 1e-7],
                                                                     velocity=[1e-4]))
                rec.write("/stage/command", s, convert.joint_state(ts, s, ["motor"], effort=[0.5 - k * 0.1]))
                rec.write("/stage/measured", s, convert.joint_state(ts, s, ["table"], position=[k * 1e-7 + 1e-9]))
            end = (SAMPLES - 1) * DT_NS
            rec.write("/experiment/events", end, convert.event_msg(ts, "trial_end", trial=0, case="fuzz",
                                                                  stamp_ns=end, node="fuzz"))
        data = rec.path.read_bytes()
    path.write_bytes(data)
    return data


def _seed_zstd(path: Path) -> bytes:
    """The contract topics written by mcap_ros2's writer: zstd chunks of ~400 bytes."""
    from mcap_ros2.writer import Writer
    from msg_defs.topics import TOPICS
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    buf = io.BytesIO()
    w = Writer(buf, chunk_size=400)
    schemas = {}

    def schema(msg_type):
        if msg_type not in schemas:
            schemas[msg_type] = w.register_msgdef(msg_type, ts.generate_msgdef(msg_type, ros_version=2)[0])
        return schemas[msg_type]

    def js(stamp, names, position=(), velocity=(), effort=()):
        return {"header": {"stamp": {"sec": stamp // 10**9, "nanosec": stamp % 10**9}, "frame_id": ""},
                "name": names, "position": list(position), "velocity": list(velocity), "effort": list(effort)}

    for k in range(SAMPLES):
        s = k * DT_NS
        for topic, msg in (("/stage/reference", js(s, ["table"], [k * 1e-7], [1e-4])),
                           ("/stage/command", js(s, ["motor"], effort=[0.5 - k * 0.1])),
                           ("/stage/measured", js(s, ["table"], [k * 1e-7 + 1e-9]))):
            w.write_message(topic, schema(TOPICS[topic].msg_type), msg, log_time=s, publish_time=s)
    w.finish()
    data = buf.getvalue()
    path.write_bytes(data)
    return data


# =========================================================================== structure
def records(data: bytes) -> list[tuple[int, int, int]]:
    """``(offset, opcode, total length)`` of each top-level record of a valid file."""
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data):
        op, n = struct.unpack_from("<BQ", data, pos)
        out.append((pos, op, 9 + n))
        pos += 9 + n
        if op == FOOTER:
            break
    return out


def chunk_inner(data: bytes, off: int) -> tuple[int, int, list[tuple[int, int]]]:
    """For an uncompressed chunk at ``off``: (records start, records length, [(inner offset, length)])."""
    p = off + 9 + 8 + 8 + 8 + 4                     # opcode+len, start, end, uncompressed size, crc
    clen = struct.unpack_from("<I", data, p)[0]
    p += 4 + clen                                   # compression string
    rlen = struct.unpack_from("<Q", data, p)[0]
    start = p + 8
    inner, q = [], start
    while q + 9 <= start + rlen:
        n = struct.unpack_from("<Q", data, q + 1)[0]
        inner.append((q, 9 + n))
        q += 9 + n
    return start, rlen, inner


def _patch_chunk(data: bytearray, off: int, new_records: bytes) -> bytes:
    """Replace the records of the uncompressed chunk at ``off``, fixing its lengths (CRC left stale)."""
    p = off + 9 + 16
    clen = struct.unpack_from("<I", data, p + 12)[0]
    head = bytearray(data[off:p + 16 + clen])
    struct.pack_into("<Q", head, 9 + 16, len(new_records))          # uncompressed size
    body = head[9:] + struct.pack("<Q", len(new_records)) + new_records
    return bytes([data[off]]) + struct.pack("<Q", len(body)) + bytes(body)


# =========================================================================== mutations
LENGTHS = (0, 1, 2**31, 2**63 - 1, 2**64 - 1)


def mutate(name: str, data: bytes, other: bytes, rng: random.Random):
    """Yield ``(file name, bytes)`` for every mutation of ``data``."""
    recs = records(data)
    chunks = [r for r in recs if r[1] == CHUNK]
    compressed = data[chunks[0][0] + 9 + 28:chunks[0][0] + 9 + 28 + 4] != b"\0\0\0\0" if chunks else True
    n = len(data)
    k = 0

    def out(kind, blob):
        nonlocal k
        k += 1
        return f"{name}-{kind}-{k:04d}.mcap", bytes(blob)

    for _ in range(PER_SEED["flip"]):
        b = bytearray(data)
        for _ in range(rng.randint(1, 8)):
            i = rng.randrange(n)
            b[i] ^= 1 << rng.randrange(8)
        yield out("flip", b)
    for _ in range(PER_SEED["byte"]):
        b = bytearray(data)
        for _ in range(rng.randint(1, 4)):
            b[rng.randrange(n)] = rng.choice((0x00, 0xFF, rng.randrange(256)))
        yield out("byte", b)
    cuts = {0, 1, 7, 8, 9, n - 1}
    for off, _, ln in recs:
        cuts |= {off, off + 1, off + 9, off + ln - 1}
    cuts |= {rng.randrange(n) for _ in range(PER_SEED["trunc"])}
    for c in sorted(c for c in cuts if 0 <= c < n):
        yield out("trunc", data[:c])
    for _ in range(PER_SEED["zero"]):
        b = bytearray(data)
        i = rng.randrange(n)
        ln = rng.randint(1, 512)
        b[i:i + ln] = bytes(len(b[i:i + ln]))
        yield out("zero", b)
    body = recs[1:-1]                                  # between header and footer
    other_recs = [(o, op, ln) for o, op, ln in records(other) if op not in (HEADER, FOOTER)]
    for _ in range(PER_SEED["splice"]):
        parts = [data[o:o + ln] for o, _, ln in body]
        op = rng.choice(("drop", "dup", "swap", "foreign"))
        i, j = rng.randrange(len(parts)), rng.randrange(len(parts))
        if op == "drop":
            del parts[i]
        elif op == "dup":
            parts.insert(j, parts[i])
        elif op == "swap":
            parts[i], parts[j] = parts[j], parts[i]
        else:
            o, _, ln = rng.choice(other_recs)
            parts.insert(i, other[o:o + ln])
        head, foot = recs[0], recs[-1]
        yield out("splice", data[:head[0] + head[2]] + b"".join(parts) + data[foot[0]:])
    if not compressed:
        for _ in range(PER_SEED["inner"]):
            off, _, ln = rng.choice(chunks)
            start, rlen, inner = chunk_inner(data, off)
            parts = [data[o:o + m] for o, m in inner]
            i, j = rng.randrange(len(parts)), rng.randrange(len(parts))
            op = rng.choice(("drop", "dup", "swap"))
            if op == "drop" and len(parts) > 1:
                del parts[i]
            elif op == "dup":
                parts.insert(j, parts[i])
            else:
                parts[i], parts[j] = parts[j], parts[i]
            new_chunk = _patch_chunk(bytearray(data), off, b"".join(parts))
            yield out("inner", data[:off] + new_chunk + data[off + ln:])
    length_sites = [off + 1 for off, _, _ in recs]
    if not compressed:
        for off, _, _ in chunks:
            length_sites += [o + 1 for o, _ in chunk_inner(data, off)[2]]
    for _ in range(PER_SEED["length"]):
        site = rng.choice(length_sites)
        cur = struct.unpack_from("<Q", data, site)[0]
        val = rng.choice(LENGTHS + (cur + 1, max(cur - 1, 0), n - site))
        b = bytearray(data)
        struct.pack_into("<Q", b, site, val % 2**64)
        yield out("length", b)
    for _ in range(PER_SEED["field"]):
        b = bytearray(data)
        what = rng.choice(("usize", "crc", "compression", "profile", "summary", "footer_crc"))
        if what in ("usize", "crc", "compression") and chunks:
            off = rng.choice(chunks)[0]
            if what == "usize":
                struct.pack_into("<Q", b, off + 9 + 16, rng.choice(LENGTHS[1:] + (0,)))
            elif what == "crc":
                struct.pack_into("<I", b, off + 9 + 24, rng.randrange(1, 2**32))
            else:
                clen = struct.unpack_from("<I", b, off + 9 + 28)[0]
                b[off + 9 + 32:off + 9 + 32 + clen] = bytes(rng.randrange(97, 123) for _ in range(clen))
        elif what == "profile":
            p = len(MAGIC) + 9
            plen = struct.unpack_from("<I", b, p)[0]
            b[p + 4:p + 4 + plen] = b"ros1"[:plen].ljust(plen, b"x")
        else:
            foot = recs[-1][0] + 9
            field = {"summary": 0, "footer_crc": 16}[what] + rng.choice((0, 8 if what == "summary" else 0))
            struct.pack_into("<Q" if what == "summary" else "<I", b, foot + field,
                             rng.choice((1, n, n + 100, 2**31)) if what == "summary" else rng.randrange(1, 2**32))
        yield out("field", b)


RNG_SEED = 20261121


def cases(seeds: dict[str, bytes]):
    """Yield ``(file name, bytes)`` of every case derived from ``seeds`` (name -> valid file)."""
    rng = random.Random(RNG_SEED)
    names = list(seeds)
    for i, name in enumerate(names):
        yield from mutate(name, seeds[name], seeds[names[(i + 1) % len(names)]], rng)


def build(out_dir: Path) -> tuple[int, int]:
    """Write the seeds and ``corpus.tar.xz`` into ``out_dir``; return (cases, archive bytes)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    seeds = {"recorder": _seed_recorder(out_dir / "seed_recorder.mcap"),
             "zstd": _seed_zstd(out_dir / "seed_zstd.mcap")}
    archive = out_dir / "corpus.tar.xz"
    count = 0
    with tarfile.open(archive, "w:xz", preset=9) as tar:
        for fname, blob in cases(seeds):
            info = tarfile.TarInfo(fname)
            info.size, info.mtime, info.mode = len(blob), 0, 0o644
            tar.addfile(info, io.BytesIO(blob))
            count += 1
    return count, archive.stat().st_size


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "test" / "fuzz_corpus")
    args = ap.parse_args(argv)
    count, size = build(args.out)
    print(f"{count} cases, {args.out / 'corpus.tar.xz'}: {size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
