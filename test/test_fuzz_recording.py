"""Fuzz run of the recording reader over the committed corpus (``test/fuzz_corpus/``).

``scripts/make_fuzz_corpus.py`` derives >= 1000 mutated files (bit flips, byte
overwrites, truncations, zero-filled ranges, record splicing inside and between
chunks, corrupt length and chunk fields) from two tiny valid recordings, one written
by our recorder and one by ``mcap_ros2`` (zstd). Every case must end, within a time
bound, in a :class:`Recording` or a :class:`RecordingError` -- never another
exception, a hang, or data that differs from what was recorded.

Time bound: ``signal.setitimer`` raises :class:`_Hang` in the reader after
``CASE_SECONDS``. It derives from ``BaseException`` so that the reader's own
``except Exception`` fallbacks cannot swallow it. A Python signal handler only runs
between bytecodes, so a hang inside C code (a decompressor) would not be interrupted:
``faulthandler.dump_traceback_later(..., exit=True)`` is the backstop that ends the
process (failing the run, with every thread's traceback) if the whole corpus takes
longer than ``TOTAL_SECONDS``.
"""
import faulthandler
import importlib.util
import signal
import tarfile
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from experiment_runner.core.recording import RecordingError, read_recording

ROOT = Path(__file__).resolve().parents[1]
CORPUS = Path(__file__).with_name("fuzz_corpus")
CASE_SECONDS = 10.0
TOTAL_SECONDS = 600
SIGNALS = ("stamp_ns", "x_ref", "v_ref", "u", "y")


class _Hang(BaseException):
    """The reader ran past its time bound."""


def _alarm(signum, frame):
    raise _Hang()


def _generator():
    spec = importlib.util.spec_from_file_location("make_fuzz_corpus", ROOT / "scripts" / "make_fuzz_corpus.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def corpus(tmp_path_factory):
    """The unpacked cases (sorted paths) and the two seed recordings, read."""
    out = tmp_path_factory.mktemp("fuzz")
    with tarfile.open(CORPUS / "corpus.tar.xz") as tar:
        tar.extractall(out, filter="data")
    seeds = {name: read_recording(CORPUS / f"seed_{name}.mcap") for name in ("recorder", "zstd")}
    return sorted(out.glob("*.mcap")), seeds


def test_corpus_is_the_generators_output_and_large_enough():
    gen = _generator()
    seeds = {name: (CORPUS / f"seed_{name}.mcap").read_bytes() for name in ("recorder", "zstd")}
    with tarfile.open(CORPUS / "corpus.tar.xz") as tar:
        committed = {m.name: tar.extractfile(m).read() for m in tar.getmembers()}
    made = dict(gen.cases(seeds))
    assert len(made) >= 1000 and made == committed
    kinds = Counter(name.split("-")[1] for name in made)
    assert set(kinds) == {"flip", "byte", "trunc", "zero", "splice", "inner", "length", "field"}
    assert sum(p.stat().st_size for p in CORPUS.iterdir()) < 4 * 2**20


def _prefix_of(rec, seed) -> bool:
    n = len(rec)
    return 0 < n <= len(seed) and all(np.array_equal(getattr(rec, a), getattr(seed, a)[:n]) for a in SIGNALS)


def _read_all(paths, seeds, reader=read_recording, seconds=CASE_SECONDS):
    """Read every case under the time bound: (outcome counts, failure descriptions)."""
    outcomes, failures = Counter(), []
    previous = signal.signal(signal.SIGALRM, _alarm)
    faulthandler.dump_traceback_later(TOTAL_SECONDS, exit=True)
    try:
        for path in paths:
            seed = seeds[path.name.split("-")[0]]
            signal.setitimer(signal.ITIMER_REAL, seconds)
            try:
                rec = reader(path)
            except RecordingError as err:
                outcomes["error"] += 1
                if not str(err).startswith(str(path)):
                    failures.append(f"{path.name}: error does not name the file: {err}")
                continue
            except _Hang:
                failures.append(f"{path.name}: no result within {seconds} s")
                continue
            except Exception as err:  # noqa: BLE001 - the point of the test
                failures.append(f"{path.name}: {type(err).__name__}: {err}")
                continue
            finally:
                signal.setitimer(signal.ITIMER_REAL, 0)
            outcomes["salvaged" if rec.salvaged else "read"] += 1
            # what is read is what was recorded: all of it, or (salvaged) its beginning
            if not _prefix_of(rec, seed) or (rec.salvaged is None and len(rec) != len(seed)):
                failures.append(f"{path.name}: read {len(rec)} samples that differ from the recording "
                                f"(salvaged: {rec.salvaged})")
    finally:
        faulthandler.cancel_dump_traceback_later()
        signal.signal(signal.SIGALRM, previous)
    return outcomes, failures


@pytest.mark.slow
def test_every_case_ends_in_a_recording_or_a_recording_error(corpus):
    paths, seeds = corpus
    outcomes, failures = _read_all(paths, seeds)
    assert not failures, f"{len(failures)} of {len(paths)} cases:\n" + "\n".join(failures[:20])
    # the corpus exercises every outcome
    assert outcomes["error"] >= 100 and outcomes["salvaged"] >= 100 and outcomes["read"] >= 50, outcomes


@pytest.mark.slow
def test_the_guard_reports_hangs_crashes_and_wrong_data(corpus):
    """The checks of the fuzz run can fail: a reader that loops, raises or alters data is caught."""
    paths, seeds = corpus
    seed_path = CORPUS / "seed_recorder.mcap"
    case = next(p for p in paths if p.name.startswith("recorder-"))

    def hangs(path):
        while True:               # a pure-Python loop: the timer interrupts it
            pass

    def crashes(path):
        raise IndexError("boom")

    def alters(path):
        rec = read_recording(seed_path)
        rec.u = rec.u + 1e-12
        return rec

    for reader, expected in ((hangs, "no result within 0.2 s"), (crashes, "IndexError: boom"),
                             (alters, "samples that differ")):
        _, failures = _read_all([case], seeds, reader, seconds=0.2)
        assert len(failures) == 1 and expected in failures[0], failures


@pytest.mark.slow
def test_salvage_notes_and_damage_messages(corpus):
    """Truncated cases say how much they salvaged; damaged ones say where, and why."""
    paths, _ = corpus
    by_name = {p.name: p for p in paths}
    trunc = [p for name, p in by_name.items() if "-trunc-" in name]
    notes = []
    for p in trunc:
        try:
            rec = read_recording(p)
        except RecordingError:
            continue
        notes.append(rec.salvaged)
    assert notes and all(n and "salvaged" in n and "messages" in n for n in notes)
    assert any("cut short" in n and "stage time" in n and "complete chunk(s)" in n for n in notes)
    damaged = []
    for name in sorted(by_name):
        if "-flip-" in name or "-length-" in name:
            try:
                read_recording(by_name[name])
            except RecordingError as err:
                damaged.append(str(err))
    assert any("fails its CRC check" in d for d in damaged)
    assert any("the length is wrong" in d or "a length field is wrong" in d for d in damaged)


def test_every_prefix_of_the_magic_is_refused(tmp_path):
    """0..8 bytes of the MCAP magic: refused naming the file (no index error, no hang)."""
    magic = b"\x89MCAP0\r\n"
    for n in range(len(magic) + 1):
        p = tmp_path / f"m{n}.mcap"
        p.write_bytes(magic[:n])
        with pytest.raises(RecordingError, match=f"^{p}: (not an MCAP file|MCAP file cut short)"):
            read_recording(p)
