"""Outputs are safe by construction (:mod:`experiment_runner.core.outputs`, issue 24): every command writes
atomically, never through a link, never over or away what nanostage did not write, and SIGTERM /
SIGINT clean up like an error. Each test builds its inputs in ``tmp_path``; the property-based test
drives the helper directly over output folders holding users' files, folders, links and partials."""
from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from experiment_runner.apps.cli import main
from experiment_runner.core import outputs
from experiment_runner.core.outputs import MANIFEST, OutputError, listed
from experiment_runner.core.recording import read_recording

CLI = [sys.executable, "-m", "experiment_runner.apps.cli"]


def _csv(path: Path, n: int = 200) -> Path:
    """A closed-loop table for ``convert table`` (t, reference, command, measurement)."""
    t = np.arange(n) * 1e-3
    x = 1e-6 * np.sin(2 * np.pi * 5 * t)
    np.savetxt(path, np.column_stack([t, x, 0.1 * np.cos(t), x + 1e-9]), delimiter=",",
               header="time,x_ref,u,y", comments="")
    return path


def _convert(src: Path, out: Path, *extra) -> list[str]:
    return ["convert", "table", str(src), "--time", "time", "--reference", "x_ref", "--command", "u",
            "--measured", "y", "--out", str(out), *extra]


def _tree(root: Path) -> dict:
    """Everything under ``root`` (never following links): path -> file bytes, link target or 'dir'."""
    out = {}
    for dirpath, dirs, files in os.walk(root):
        for name in dirs + files:
            p = Path(dirpath) / name
            rel = str(p.relative_to(root))
            out[rel] = (f"-> {os.readlink(p)}" if p.is_symlink() else "dir" if p.is_dir() else p.read_bytes())
    return out


def _partials(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob("*") if ".partial-" in p.name)


def _one_line(err: str, *fragments) -> None:
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for f in fragments:
        assert f in err, err


# --------------------------------------------------------------------------- commands
def test_synth_never_deletes_a_users_folder(tmp_path, capsys):
    """``synth --out DIR`` with a user's file in DIR: refused without --overwrite; with it, the
    recording is written beside the file (before: DIR deleted with the file, exit 0)."""
    d = tmp_path / "thesis"
    d.mkdir()
    (d / "thesis.tex").write_text("\\chapter{draft}")
    args = ["synth", "fi_stage", "fi_p2p_5um", "--trials", "1", "--out", str(d)]
    assert main(args) == 2
    _one_line(capsys.readouterr().err, f"{d}: exists; pass --overwrite")
    assert sorted(os.listdir(d)) == ["thesis.tex"]
    assert main([*args, "--overwrite"]) == 0
    assert (d / "thesis.tex").read_text() == "\\chapter{draft}"
    assert listed(d) == {"thesis.mcap", "metadata.yaml"} and len(read_recording(d)) > 0


def test_convert_overwrite_onto_a_folder_that_is_not_a_recording_keeps_its_files(tmp_path, capsys):
    """``convert --overwrite`` onto a user's folder adds the recording and keeps the user's files
    (before: the folder was removed); a user's file with the recording's name is refused."""
    src = _csv(tmp_path / "rec.csv")
    d = tmp_path / "notes"
    (d / "sub").mkdir(parents=True)
    (d / "todo.txt").write_text("mine")
    (d / "sub" / "data.bin").write_bytes(b"\x00\x01")
    before = _tree(d)
    assert main(_convert(src, d)) == 2
    _one_line(capsys.readouterr().err, "exists; pass --overwrite")
    assert main(_convert(src, d, "--overwrite")) == 0
    assert {k: v for k, v in _tree(d).items() if k in before} == before
    assert len(read_recording(d)) == 200
    # a file of the user's named like one of the recording's: refused, not replaced
    clash = tmp_path / "clash"
    clash.mkdir()
    (clash / "metadata.yaml").write_text("the user's")
    capsys.readouterr()
    assert main(_convert(src, clash, "--overwrite")) == 2
    _one_line(capsys.readouterr().err, "metadata.yaml: exists and was not written by nanostage")
    assert sorted(os.listdir(clash)) == ["metadata.yaml"] and (clash / "metadata.yaml").read_text() == "the user's"
    assert _partials(tmp_path) == []


def test_convert_overwrite_onto_a_symlinked_output_is_refused_cleanly(tmp_path, capsys):
    """``--out LINK --overwrite`` (LINK -> a folder elsewhere): one line, exit 2, the folder the link
    points to untouched, no ``.partial-*`` left (before: a crash after writing, ``.partial-*.old`` left)."""
    src = _csv(tmp_path / "rec.csv")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "keep.txt").write_text("keep")
    link = tmp_path / "rec"
    link.symlink_to(elsewhere, target_is_directory=True)
    before = _tree(tmp_path)
    assert main(_convert(src, link, "--overwrite")) == 2
    _one_line(capsys.readouterr().err, f"{link}: a symbolic link (to {elsewhere})")
    assert _tree(tmp_path) == before and _partials(tmp_path) == []


def _marked_with_link(d: Path, name: str, target: Path) -> None:
    """``d``: an output folder of nanostage that wrote ``name``, which is now a link to ``target``."""
    outputs.prepare_folder(d)
    outputs.write_text(d / name, "nanostage's")
    (d / name).unlink()
    (d / name).symlink_to(target)


@pytest.mark.parametrize("command, name", [
    (["design", "fi_stage", "--rms", "2", "--grid", "coarse", "--trials", "1", "--no-plots"], "design.md"),
    (["campaign", "table_4_2", "--trials", "1", "--no-calibrate", "--no-plots", "--no-mcap", "--workers", "1",
      "--quiet"], "report.md"),
])
def test_design_and_campaign_never_write_through_a_link_in_out(tmp_path, capsys, command, name):
    """``DIR/NAME -> a file elsewhere``: refused (before the work), the file elsewhere untouched
    (before: overwritten with the report)."""
    outside = tmp_path / "notes.txt"
    outside.write_text("my notes")
    d = tmp_path / "out"
    _marked_with_link(d, name, outside)
    for extra in ([], ["--overwrite"]):
        assert main([*command, "--out", str(d), *extra]) == 2
        _one_line(capsys.readouterr().err, f"{d / name}: a symbolic link (to {outside})")
    assert outside.read_text() == "my notes" and (d / name).is_symlink()


@pytest.mark.slow
def test_diagnose_never_writes_through_a_link_in_out(tmp_path, capsys):
    """``diagnose REC NOMINAL --out DIR`` with ``DIR/report.md -> a file elsewhere``: refused before
    the diagnosis, the file untouched (before: the report written into it)."""
    rec = tmp_path / "rec.mcap"
    assert main(["synth", "fi_stage", "fi_p2p_5um", "--trials", "2", "--out", str(rec)]) == 0
    outside = tmp_path / "notes.txt"
    outside.write_text("my notes")
    d = tmp_path / "diag"
    _marked_with_link(d, "report.md", outside)
    capsys.readouterr()
    assert main(["diagnose", str(rec), "fi_stage", "--out", str(d), "--no-plots", "--effects", "coulomb",
                 "--max-fit-seconds", "0.2"]) == 2
    _one_line(capsys.readouterr().err, f"{d / 'report.md'}: a symbolic link (to {outside})")
    assert outside.read_text() == "my notes"


def test_graph_never_deletes_a_run_folder_it_did_not_make(tmp_path, capsys):
    """``graph --out DIR`` with a user's ``DIR/run/`` (before: deleted): refused, with or without
    --overwrite, before any node starts."""
    d = tmp_path / "g"
    (d / "run").mkdir(parents=True)
    (d / "run" / "data.txt").write_text("mine")
    assert main(["graph", "fi_p2p_5um", "--out", str(d)]) == 2
    _one_line(capsys.readouterr().err, f"--out {d}: a folder nanostage did not write (holding run)")
    assert main(["graph", "fi_p2p_5um", "--out", str(d), "--overwrite"]) == 2
    _one_line(capsys.readouterr().err, f"{d / 'run'}: a folder nanostage did not write")
    assert (d / "run" / "data.txt").read_text() == "mine"


@pytest.mark.ros
def test_graph_run_keeps_a_users_files_and_run_folders(tmp_path, ros_domain):
    """A graph run into a user's folder (--overwrite) writes its recording beside the user's
    ``run_notes/`` (before: every ``run_*`` folder was deleted), and a second run replaces only it."""
    d = tmp_path / "g"
    (d / "run_notes").mkdir(parents=True)
    (d / "run_notes" / "a.txt").write_text("mine")
    code = subprocess.run([*CLI, "graph", "fi_p2p_5um", "--out", str(d), "--overwrite", "--timeout", "300",
                           "--domain-id", str(ros_domain)],
                          capture_output=True, text=True, timeout=600)
    assert code.returncode == 0, code.stderr
    assert (d / "run_notes" / "a.txt").read_text() == "mine"
    assert listed(d) == {"run.mcap", "metadata.yaml"} and not (d / "run").exists()
    assert len(read_recording(d / "run.mcap")) > 0


# --------------------------------------------------------------------------- signals
def _as_from_a_terminal() -> None:
    """The child's SIGINT as a terminal's foreground job has it (default). A job started in the
    background of a non-interactive shell (``cmd &``, as a CI runner may start the suite) inherits
    SIGINT ignored, and Python then keeps it ignored: the Ctrl-C under test would never arrive."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _wait_for(predicate, timeout: float, proc) -> None:
    t0 = time.monotonic()
    while not predicate():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, "timed out"
        time.sleep(0.02)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signal_during_convert_leaves_no_partial_and_no_traceback(tmp_path, sig):
    """SIGTERM / SIGINT while ``convert`` writes: exit 128 + signal, one line, no traceback, no
    ``.rec.partial-*`` and no recording left (before: a 29 MB hidden partial, or a traceback)."""
    src = _csv(tmp_path / "big.csv", 150_000)
    proc = subprocess.Popen([*CLI, *_convert(src, tmp_path / "rec")], preexec_fn=_as_from_a_terminal,
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_for(lambda: any(p.stat().st_size > 0 for p in tmp_path.glob(".rec.partial-*/rec/rec.mcap")), 120, proc)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    _one_line(err, f"nanostage convert: interrupted ({signal.Signals(sig).name})")
    assert sorted(os.listdir(tmp_path)) == ["big.csv"]


@pytest.mark.slow
def test_ctrl_c_in_selftest_gives_no_traceback(tmp_path):
    """SIGINT during ``diagnose --selftest``: one line, exit 130, its temporary folder removed
    (before: a KeyboardInterrupt traceback)."""
    env = dict(os.environ, TMPDIR=str(tmp_path))
    proc = subprocess.Popen([*CLI, "diagnose", "--selftest", "--only", "coulomb"], preexec_fn=_as_from_a_terminal,
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)
    _wait_for(lambda: any(tmp_path.glob("nanostage_selftest_*/*/truth.yaml")), 120, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    _one_line(err, "nanostage diagnose: interrupted (SIGINT)")
    assert not list(tmp_path.glob("nanostage_selftest_*"))


@pytest.mark.ros
def test_ctrl_c_in_a_graph_run_gives_no_traceback(tmp_path, ros_domain):
    """SIGINT while ``graph`` runs its nodes in one process: one line, exit 130 -- raised between
    the executor's spins, never inside a node's callback (which rclpy logs as a fatal error)."""
    d = tmp_path / "g"
    proc = subprocess.Popen([*CLI, "graph", "fi_p2p_5um", "--out", str(d), "--domain-id", str(ros_domain)],
                            preexec_fn=_as_from_a_terminal,
                            stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _wait_for(lambda: (d / "run" / "run.mcap").exists(), 120, proc)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    _one_line(err, "nanostage graph: interrupted (SIGINT)")


_WRITE_RUN = """
import sys
import numpy as np
from experiment_runner.core.batch import BatchResult
from experiment_runner.core.recording import write_run
from stage_sim.config import load_preset
n = 400_000
z = np.zeros((1, n))
res = BatchResult(t=np.arange(n) * 1e-4, x_ref=z, x_correction=z, v_ref=z, y=z, y_bearing=z, u=z, x_table=z,
                  x_bearing=z, dither=np.zeros((1, n, 2)), mode=z, status=np.array([0]), fail_step=np.array([-1]))
write_run(sys.argv[1], res, load_preset("fi_stage"), results=False)
"""


@pytest.mark.slow
def test_a_recording_killed_while_written_leaves_nothing_at_its_path(tmp_path):
    """A campaign's recording (``write_run``) killed (SIGKILL) while written: nothing at its path --
    no 0-byte or cut ``.mcap`` (before: one at the final path); the next write there removes the
    dead process's partial."""
    bag = tmp_path / "recordings" / "case_batch"
    proc = subprocess.Popen([sys.executable, "-c", _WRITE_RUN, str(bag)], stderr=subprocess.PIPE)
    _wait_for(lambda: any(p.stat().st_size > 0 for p in bag.parent.glob(".case_batch.partial-*/*/*.mcap")),
              120, proc)
    proc.kill()
    proc.wait()
    assert not bag.exists()
    assert len(_partials(tmp_path)) == 1                 # the killed process's temporary, beside the bag
    with outputs.replacing_folder(bag) as p:
        p.mkdir()
        (p / "case_batch.mcap").write_text("x")
    assert _partials(tmp_path) == [] and sorted(os.listdir(bag)) == [MANIFEST, "case_batch.mcap"]


# --------------------------------------------------------------------------- the helper
_DEAD = []


def _dead_pid() -> int:
    """The process id of a process that has ended (one, checked again before each use)."""
    if not _DEAD or outputs.process_alive(_DEAD[0]):
        p = subprocess.Popen(["true"])
        p.wait()
        _DEAD[:] = [p.pid]
    return _DEAD[0]


def test_stale_partials_removed_when_their_process_is_gone_else_reported(tmp_path, capsys):
    d = tmp_path / "out"
    d.mkdir()
    dead, live = _dead_pid(), os.getppid()
    (d / f".report.md.partial-{dead}-abcdef").write_text("cut")
    (d / f".rec.partial-{dead}-012345").mkdir()
    (d / f".rec.partial-{dead}-012345" / "rec").mkdir()
    (d / f".plot.png.partial-{live}-abcdef").write_text("being written")
    (d / ".rec.partial-k2j4h5g6.old").mkdir()                  # an older nanostage's: no process id
    outputs.prepare_folder(d)
    assert sorted(os.listdir(d)) == sorted([MANIFEST, f".plot.png.partial-{live}-abcdef", ".rec.partial-k2j4h5g6.old"])
    err = capsys.readouterr().err
    assert f"partial of a running process (pid {live})" in err and "an older nanostage run" in err


def test_a_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path):
    d = outputs.prepare_folder(tmp_path / "out")
    outputs.write_text(d / "report.md", "old")
    with pytest.raises(ZeroDivisionError):
        with outputs.replacing(d / "report.md") as tmp:
            tmp.write_text("half")
            1 / 0
    with pytest.raises(ZeroDivisionError):
        with outputs.replacing(d / "new.md") as tmp:
            1 / 0
    assert (d / "report.md").read_text() == "old" and sorted(os.listdir(d)) == [MANIFEST, "report.md"]
    assert listed(d) == {"report.md"}


# kinds of an entry of the output folder before the command runs
ABSENT, USER_FILE, USER_DIR, USER_DIR_CLASH, LINK_FILE, LINK_DIR, NS_FILE, NS_DIR = (
    "absent", "user file", "user dir", "user dir holding a.mcap", "link to a file", "link to a dir",
    "nanostage's file", "nanostage's folder")
MIXED = "user dir nanostage wrote into"
USER = {USER_FILE, USER_DIR, USER_DIR_CLASH, LINK_FILE, LINK_DIR}
NAMES = ("report.md", "plots", "rec", "notes.txt")
OPS = st.one_of(
    st.tuples(st.just("write"), st.sampled_from(NAMES), st.booleans()),
    st.tuples(st.just("folder"), st.sampled_from(NAMES), st.booleans()),
    st.tuples(st.just("stream"), st.sampled_from(NAMES), st.booleans()),
    st.tuples(st.just("remove"), st.sampled_from(NAMES)),
    st.tuples(st.just("remove_out"),),
    st.tuples(st.just("prepare"), st.booleans()),
)
_count = itertools.count()


def _expect(op, kinds: dict) -> tuple[bool, dict]:
    """Whether ``op`` must succeed on entries of ``kinds``, and the kinds after it."""
    kinds = dict(kinds)
    kind = kinds.get(op[1]) if len(op) > 1 and isinstance(op[1], str) else None
    if op[0] in ("write", "stream") and not (op[0] == "write" and op[2]):
        ok = kind in (ABSENT, NS_FILE)
        new = NS_FILE
    elif op[0] == "write":                                   # into a sub-folder: NAME/f.txt
        ok = kind in (ABSENT, NS_DIR, MIXED)
        new = MIXED if kind == MIXED else NS_DIR
    elif op[0] == "folder":                                  # a recording folder at NAME
        overwrite = op[2]
        ok = kind == ABSENT or (overwrite and kind in (NS_DIR, MIXED, USER_DIR))
        new = NS_DIR if kind in (ABSENT, NS_DIR) else MIXED
    elif op[0] == "remove":
        ok = kind not in USER
        new = MIXED if kind == MIXED else ABSENT
    elif op[0] == "remove_out":
        return True, {n: (k if k in USER or k == MIXED else ABSENT) for n, k in kinds.items()}
    else:
        return True, kinds
    if ok:
        kinds[op[1]] = new
    return ok, kinds


def _make(out: Path, outside: Path, kinds: dict, marked: bool) -> None:
    out.mkdir()
    for name, kind in kinds.items():
        p = out / name
        if kind == USER_FILE:
            p.write_text(f"user's {name}")
        elif kind in (USER_DIR, USER_DIR_CLASH):
            p.mkdir()
            (p / ("a.mcap" if kind == USER_DIR_CLASH else "inner.txt")).write_text("user's")
        elif kind == LINK_FILE:
            p.symlink_to(outside / "secret.txt")
        elif kind == LINK_DIR:
            p.symlink_to(outside / "dir", target_is_directory=True)
    if marked:
        outputs.prepare_folder(out, overwrite=True)
        for name, kind in kinds.items():
            if kind == NS_FILE:
                outputs.write_text(out / name, "nanostage's")
            elif kind == NS_DIR:
                outputs.write_text(out / name / "f.txt", "nanostage's")


def _run(op, out: Path) -> str | None:
    """Do ``op`` on the helper; returns what a written file must hold."""
    text = f"content {next(_count)}"
    if op[0] == "write":
        outputs.write_text(out / op[1] / "f.txt" if op[2] else out / op[1], text)
    elif op[0] == "stream":
        with outputs.open_stream(out / op[1], append=op[2], header="head\n") as f:
            f.write(text)
    elif op[0] == "folder":
        with outputs.replacing_folder(out / op[1], overwrite=op[2]) as p:
            p.mkdir()
            (p / "a.mcap").write_text(text)
            (p / "metadata.yaml").write_text(text)
    elif op[0] == "remove":
        outputs.remove(out / op[1])
    elif op[0] == "remove_out":
        outputs.remove(out)
    else:
        outputs.prepare_folder(out, overwrite=op[1])
    return text


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@example(out_kind="absent", kinds=dict.fromkeys(NAMES, ABSENT), partials=[], overwrite=False,   # folders it made
         ops=[("remove_out",), ("write", "report.md", True), ("remove_out",)])                  # are its own
@given(out_kind=st.sampled_from(["absent", "folder", "nanostage's folder", "link"]),
       kinds=st.fixed_dictionaries({n: st.sampled_from([ABSENT, USER_FILE, USER_DIR, USER_DIR_CLASH, LINK_FILE,
                                                         LINK_DIR, NS_FILE, NS_DIR]) for n in NAMES}),
       partials=st.lists(st.sampled_from(["dead", "live", "legacy"]), max_size=3, unique=True),
       overwrite=st.booleans(), ops=st.lists(OPS, max_size=5))
@pytest.mark.slow
def test_property_nothing_outside_the_output_nor_a_users_entry_is_touched(out_kind, kinds, partials, overwrite,
                                                                          ops):
    """Over output folders holding users' files, folders, links to files and folders elsewhere,
    nanostage's own files and partials (of a process gone, of a running one, of an older
    nanostage): a command (prepare the folder, then write, write folders, stream, remove) never
    changes anything outside the folder nor any entry nanostage did not write; it refuses exactly
    what the rules refuse (OutputError, nothing else); what it writes holds what was written;
    no temporary of its own is left; a gone process's partials are removed."""
    with tempfile.TemporaryDirectory() as root:
        root = Path(root)
        outside = root / "outside"
        (outside / "dir").mkdir(parents=True)
        (outside / "secret.txt").write_text("secret")
        (outside / "dir" / "inner.txt").write_text("inner")
        (root / "sibling.txt").write_text("sibling")
        out = root / "out"
        if out_kind in ("folder", "nanostage's folder"):
            _make(out, outside, kinds, marked=out_kind == "nanostage's folder")
            if out_kind == "folder":
                kinds = {n: (ABSENT if k in (NS_FILE, NS_DIR) else k) for n, k in kinds.items()}
        else:
            kinds = dict.fromkeys(NAMES, ABSENT)
            if out_kind == "link":
                out.symlink_to(outside, target_is_directory=True)
        pnames = {"dead": f".report.md.partial-{_dead_pid()}-abcdef",
                  "live": f".rec.partial-{os.getppid()}-abcdef", "legacy": ".plots.partial-abcd1234.old"}
        if out_kind in ("folder", "nanostage's folder"):
            for p in partials:
                (out / pnames[p]).write_text(p)
        kept_partials = {pnames[p] for p in partials if p != "dead"} if out_kind != "absent" and out_kind != "link" \
            else set()
        users = {n for n, k in kinds.items() if k in USER}
        before_outside = _tree(outside), (root / "sibling.txt").read_text()
        before_users = {n: _tree(out / n) if (out / n).is_dir() and not (out / n).is_symlink()
                        else os.readlink(out / n) if (out / n).is_symlink() else (out / n).read_text() for n in users}

        # the command prepares its folder first: refused exactly for a link, or a folder with a
        # user's entries that nanostage did not write, without --overwrite
        must_refuse = out_kind == "link" or (out_kind == "folder" and bool(users) and not overwrite)
        try:
            outputs.prepare_folder(out, overwrite=overwrite)
            refused = False
        except OutputError:
            refused = True
        assert refused == must_refuse, (out_kind, kinds, overwrite)
        if not refused:
            assert not any(p.name.startswith(".report.md.partial-") for p in out.iterdir())   # the dead one
            for op in ops:
                ok, after = _expect(op, kinds)
                try:
                    text = _run(op, out)
                    done = True
                except OutputError:
                    done = False
                assert done == ok, (op, kinds)
                kinds = after
                if done and op[0] in ("write", "stream"):
                    written = out / op[1] / "f.txt" if op[0] == "write" and op[2] else out / op[1]
                    assert written.read_text().endswith(text) and not written.is_symlink()
                if done and op[0] == "folder":
                    assert (out / op[1] / "a.mcap").read_text() == text

        assert (_tree(outside), (root / "sibling.txt").read_text()) == before_outside
        for n, was in before_users.items():
            p = out / n
            now = (_tree(p) if p.is_dir() and not p.is_symlink() else os.readlink(p) if p.is_symlink()
                   else p.read_text())
            if isinstance(was, dict):                       # a user's folder: its entries unchanged
                now = {k: v for k, v in now.items() if k in was}
            assert now == was, (n, kinds)
        ours = [p for p in root.rglob(f"*.partial-{os.getpid()}-*")]
        assert ours == [], ours
        if out.is_dir() and not out.is_symlink():
            assert kept_partials <= set(os.listdir(out))
