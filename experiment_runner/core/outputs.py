"""Every file and folder nanostage writes, safe by construction.

All commands that write (``synth``, ``convert``, ``diagnose``, ``design``, ``campaign``,
``graph``, ``paper``, ``realdata``) write through this module, under four rules:

1. **Atomic.** A file is written to a fresh temporary sibling ``.NAME.partial-PID-XXXXXX``
   and renamed into place (:func:`os.replace`) once complete (:func:`replacing`,
   :func:`write_text`, :func:`savefig`); a recording -- a bag folder -- is written whole in
   such a temporary folder and moved into place (:func:`replacing_folder`). A failed,
   interrupted or killed run leaves the previous file or none, never a half-written one
   at the final path.
2. **Marked.** Every folder nanostage writes into holds a manifest, :data:`MANIFEST`,
   listing the files it wrote there; a sub-folder holding its own manifest is nanostage's
   too. Only what the manifests list is ever replaced or removed (:func:`remove`).
3. **Asked.** A folder that exists, is not empty and holds no manifest was not written by
   nanostage: it is refused unless the command is given ``--overwrite``
   (:func:`prepare_folder`), which lets nanostage add its files there and still replaces
   only its own: a user's file with the name of one nanostage writes is refused, with or
   without ``--overwrite``. A recording (``synth``, ``convert``) that exists is replaced
   only with ``--overwrite``.
4. **No links.** A symbolic link where nanostage would write or remove -- the output
   folder itself, or an entry or sub-folder in it -- is refused with a one-line message;
   nanostage never writes, nor deletes, through a link.

A partial left by a killed run (``.NAME.partial-PID-XXXXXX``) is removed the next time its
folder is prepared if its process is gone and it belongs to this user; any other partial
(a running process's, or one of an older nanostage) is reported on stderr and left.
SIGTERM and SIGINT raise :class:`Interrupted` inside :func:`interrupts_as_errors` (the CLI's
``main``), so a command cleans up its temporaries as on any error; a loop around calls that must
not be interrupted midway (the ROS executor's spins) defers them (:func:`interrupts_deferred`).

Every refusal is an :class:`OutputError`, a :class:`~stage_sim.validation.ConfigError`: the
CLI prints its one line and exits 2.

Examples
--------
>>> import tempfile
>>> top = Path(tempfile.mkdtemp()) / "out"
>>> prepare_folder(top) == top
True
>>> write_text(top / "report.md", "# report\\n").read_text()
'# report\\n'
>>> sorted(listed(top))
['report.md']
>>> _ = (top / "notes.txt").write_text("the user's")
>>> (top / "link.md").symlink_to(top / "notes.txt")
>>> write_text(top / "link.md", "x")
Traceback (most recent call last):
experiment_runner.core.errors.OutputError: .../out/link.md: a symbolic link (to .../out/notes.txt); ...
>>> remove(top)                            # nanostage's own files go, the user's stay
[PosixPath('.../out/link.md'), PosixPath('.../out/notes.txt')]
>>> sorted(p.name for p in top.iterdir()), listed(top)
(['.nanostage-output.json', 'link.md', 'notes.txt'], set())
"""
from __future__ import annotations

import fcntl
import json
import os
import re
import secrets
import shutil
import signal
import stat
import sys
import threading
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Iterator

from experiment_runner.core.errors import OutputError

__all__ = ["MANIFEST", "OutputError", "Interrupted", "prepare_folder", "check_recording", "prepare_recording",
           "replacing", "write_text", "savefig", "open_stream", "replacing_folder", "record", "move_into",
           "remove", "listed", "is_output_folder", "check_file", "interrupts_as_errors", "interrupts_deferred",
           "add_overwrite_argument"]

MANIFEST = ".nanostage-output.json"
"""File in every folder nanostage writes into: the names of the files it wrote there."""

_PARTIAL = re.compile(r"^\.(?P<name>.+)\.partial-(?P<pid>\d+)-[0-9a-f]{6}$")
"""A temporary of :func:`replacing` / :func:`replacing_folder`: target name, writing process."""
_LEGACY = re.compile(r"^\..+\.partial-[a-z0-9_]{8}(\.old)?$")
"""A temporary of nanostage before this module (no process id): reported, never removed."""


class Interrupted(KeyboardInterrupt):
    """SIGTERM or SIGINT arrived (:func:`interrupts_as_errors`); ``signum`` says which."""

    def __init__(self, signum: int):
        self.signum = int(signum)
        super().__init__(signal.Signals(self.signum).name)


# =========================================================================== what is ours
def _lstat(path) -> os.stat_result | None:
    try:
        return os.lstat(path)
    except FileNotFoundError:
        return None


def _refuse_link(path: Path, st) -> None:
    if st is not None and stat.S_ISLNK(st.st_mode):
        raise OutputError(f"{path}: a symbolic link (to {os.readlink(path)}); nanostage never writes or deletes "
                          "through a link: remove the link or choose another output")


def listed(folder) -> set[str] | None:
    """Names of the files nanostage wrote in ``folder`` (its :data:`MANIFEST`); None if it has none.

    A manifest that is not a regular file (of at most 16 MiB) or not nanostage's JSON counts as
    none; a listed name that is not a plain name in ``folder`` (``a/b``, ``..``) is ignored.
    """
    path = Path(folder) / MANIFEST
    st = _lstat(path)
    if st is None or not stat.S_ISREG(st.st_mode) or st.st_size > 1 << 24:
        return None
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        files = doc["files"] if doc.get("nanostage_output") == 1 else None
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return None
    if not isinstance(files, list):
        return None
    return {f for f in files if isinstance(f, str) and f not in ("", ".", "..") and "/" not in f and "\0" not in f}


def is_output_folder(path) -> bool:
    """``path`` is a folder (not a link to one) holding nanostage's :data:`MANIFEST`."""
    st = _lstat(path)
    return st is not None and stat.S_ISDIR(st.st_mode) and listed(path) is not None


def _foreign(folder: Path) -> list[str]:
    """Entries of a folder without a manifest that are not nanostage's: all but its output folders
    (and partials, which :func:`_clean_partials` handles)."""
    return sorted(e for e in os.listdir(folder)
                  if not (_PARTIAL.match(e) or _LEGACY.match(e) or is_output_folder(folder / e)))


@contextmanager
def _locked(folder: Path):
    """Hold an exclusive lock on ``folder`` (its manifest's read-modify-write; other processes too)."""
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_CLOEXEC)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)


def _update(folder: Path, add=(), drop=()) -> None:
    """Add ``add`` to / drop ``drop`` from ``folder``'s manifest (made if missing), atomically."""
    with _locked(folder):
        old = listed(folder) or set()
        new = (old | set(add)) - set(drop)
        if new == old and (folder / MANIFEST).exists():
            return
        tmp = folder / _temp_name(MANIFEST)
        tmp.write_text(json.dumps({"nanostage_output": 1, "files": sorted(new)}, indent=1) + "\n", encoding="utf-8")
        os.replace(tmp, folder / MANIFEST)


def record(folder, names) -> None:
    """Note that nanostage wrote (or is about to write) files ``names`` in output folder ``folder``."""
    _update(Path(folder), add=names)


# =========================================================================== partials
def _temp_name(name: str) -> str:
    return f".{name}.partial-{os.getpid()}-{secrets.token_hex(3)}"


def process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


_reported: set = set()


def _report(path: Path, why: str) -> None:
    if path not in _reported:
        _reported.add(path)
        print(f"nanostage: left {path}: {why}; remove it by hand once no nanostage run writes there",
              file=sys.stderr)


def _clean_partials(folder: Path, target: str | None = None) -> None:
    """Remove the partials in ``folder`` (of ``target`` only, if given) that a process now gone
    of this user left; report the others (a running process's, another user's, an older nanostage's)."""
    try:
        entries = os.listdir(folder)
    except OSError:
        return
    for e in entries:
        m = _PARTIAL.match(e)
        if m is None:
            if _LEGACY.match(e) and (target is None or e.startswith(f".{target}.partial-")):
                _report(folder / e, "a partial of an older nanostage run")
            continue
        if target is not None and m["name"] != target:
            continue
        path, pid = folder / e, int(m["pid"])
        st = _lstat(path)
        if st is None or pid == os.getpid():
            continue
        if stat.S_ISLNK(st.st_mode) or st.st_uid != os.getuid():
            _report(path, "named like a nanostage partial, but not one this user's nanostage made")
        elif process_alive(pid):
            _report(path, f"the partial of a running process (pid {pid})")
        elif stat.S_ISDIR(st.st_mode):
            shutil.rmtree(path, ignore_errors=True)
        else:
            with suppress(FileNotFoundError):
                os.unlink(path)


# =========================================================================== folders
def prepare_folder(path, overwrite: bool = False, files=(), option: str = "") -> Path:
    """Make ``path`` a folder nanostage may write into (the output folder of a command); returns it.

    Made (with its parents) if missing. An existing folder must be nanostage's (it holds a
    :data:`MANIFEST`), empty, or hold only nanostage's sub-folders -- or ``overwrite`` (the
    command's ``--overwrite``) is given, and nanostage adds its files beside the others.
    A link or a file at ``path`` is refused. Stale partials in it are cleaned. ``files``:
    names the command will write there, checked now (:func:`check_file`), so that a refusal
    comes before the work. ``option``: the command-line option that named ``path``
    (``"--out"``), for the messages.

    Raises
    ------
    OutputError
        ``path`` is a link, a file, a folder nanostage did not write (without ``overwrite``)
        or cannot be made; one of ``files`` may not be written.
    """
    path = Path(path)
    name = f"{option} {path}" if option else str(path)
    try:
        st = _lstat(path)
        _refuse_link(path, st)
        if st is None:
            _make_folders(path)
            st = _lstat(path)
            _refuse_link(path, st)
        if not stat.S_ISDIR(st.st_mode):
            raise OutputError("a file is there; expected a folder (made if missing)")
        if listed(path) is None:
            foreign = _foreign(path)
            if foreign and not overwrite:
                more = f" and {len(foreign) - 3} more" if len(foreign) > 3 else ""
                raise OutputError(f"a folder nanostage did not write (holding {', '.join(foreign[:3])}{more}); give "
                                  "--overwrite to write nanostage's files into it (nothing else in it is touched), "
                                  "or choose another output folder")
            _update(path)
    except OSError as err:
        raise OutputError(f"{name}: cannot make or write the output folder ({err.strerror or err})") from None
    except OutputError as err:            # the message names the option and the folder
        msg = str(err)
        msg = msg[len(str(path)) + 2:] if msg.startswith(f"{path}: ") else msg
        raise OutputError(f"{name}: {msg}") from None
    _clean_partials(path)
    for file in files:
        _check_file(path / file)
    return path


def _make_folders(path: Path) -> None:
    """Make ``path`` and its missing parents, each marked as nanostage's (an empty :data:`MANIFEST`):
    nanostage made them, so it may remove them again (:func:`remove`). A folder that appears
    meanwhile (another process) is left unmarked."""
    missing = []
    while _lstat(path) is None and path.parent != path:
        missing.append(path)
        path = path.parent
    for folder in reversed(missing):
        try:
            folder.mkdir()
        except FileExistsError:
            continue
        _update(folder)


def _folder(folder: Path) -> Path:
    """``folder`` ready for a write: no link on the way from the output folders it lies in (every
    entry of a marked folder on the way is a real folder), checked before anything is made; then
    prepared (:func:`prepare_folder`, without ``overwrite``) if it is not an output folder yet."""
    child = folder
    while child.parent != child:
        st = _lstat(child)
        if listed(child.parent) is not None:
            _refuse_link(child, st)
        elif st is not None:
            break
        child = child.parent
    if not is_output_folder(folder):
        prepare_folder(folder)
    return folder


def _check_file(path: Path) -> None:
    """``path`` may be (re)written by nanostage: absent, or a regular file its folder lists."""
    st = _lstat(path)
    if st is None:
        return
    _refuse_link(path, st)
    if not stat.S_ISREG(st.st_mode):
        raise OutputError(f"{path}: a folder (or other non-file) is there; nanostage writes a file of that name: "
                          "move it away or choose another output folder")
    if path.name not in (listed(path.parent) or ()):
        raise OutputError(f"{path}: exists and was not written by nanostage (not in {MANIFEST}); "
                          "move it away or choose another output folder")


# =========================================================================== writing files
@contextmanager
def replacing(path) -> Iterator[Path]:
    """Yield a fresh temporary path to write ``path``'s content to; on success it is renamed to
    ``path`` (atomic), on any error or interrupt removed.

    ``path``'s folder becomes an output folder (:func:`prepare_folder` without ``overwrite``);
    ``path`` must be absent or a file nanostage wrote there (else :class:`OutputError`, before
    anything is written).
    """
    path = Path(path)
    folder = _folder(path.parent)
    _check_file(path)
    existed = path.exists()
    record(folder, [path.name])
    tmp = folder / _temp_name(path.name)
    os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666))
    done = False
    try:
        yield tmp
        _check_file(path)                  # a link made meanwhile is refused, never replaced
        os.replace(tmp, path)
        done = True
    finally:
        with suppress(FileNotFoundError):
            os.unlink(tmp)
        if not done and not existed and _lstat(path) is None:
            _update(folder, drop=[path.name])


def write_text(path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`replacing`); returns ``path``."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def savefig(fig, path, **kwargs) -> Path:
    """``fig.savefig(path, **kwargs)`` atomically (:func:`replacing`; the format from ``path``'s
    suffix unless given); returns ``path``."""
    path = Path(path)
    kwargs.setdefault("format", path.suffix.lstrip(".") or None)
    with replacing(path) as tmp:
        fig.savefig(tmp, **kwargs)
    return path


def check_file(path) -> Path:
    """Refuse (:class:`OutputError`) a ``path`` nanostage may not write: a link, a folder, a file its
    folder's manifest does not list, a link on the way from the output folders it lies in. Its
    folder is made an output folder (:func:`prepare_folder`) if it is not one yet."""
    path = Path(path)
    _folder(path.parent)
    _check_file(path)
    return path


def open_stream(path, append: bool, header: str = ""):
    """A text file of ``path`` to append records to (a campaign's ``trials.jsonl``).

    ``append``: continue nanostage's existing file (it must be one its folder lists); else a
    new file holding ``header`` replaces it atomically. The file is opened without following
    a link.
    """
    path = check_file(path)
    if not append:
        with replacing(path) as tmp:
            tmp.write_text(header, encoding="utf-8")
    record(path.parent, [path.name])
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o666)
    return os.fdopen(fd, "a", encoding="utf-8")


def move_into(src, path) -> Path:
    """Move file ``src`` (written by nanostage, on the same file system) to ``path`` atomically,
    with :func:`replacing`'s checks; returns ``path``."""
    path = Path(path)
    folder = _folder(path.parent)
    _check_file(path)
    record(folder, [path.name])
    os.replace(src, path)
    return path


# =========================================================================== recordings (folders written whole)
def check_recording(path, overwrite: bool = False) -> None:
    """Refuse (:class:`OutputError`) a recording folder ``path`` that :func:`replacing_folder` would
    refuse: a link or a file there, or an existing folder without ``overwrite``. Call it before
    the work, so a refusal comes first."""
    path = Path(path)
    st = _lstat(path)
    _refuse_link(path, st)
    if st is None:
        return
    if not stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{path}: a file is there; a recording is a folder (NAME.mcap -> NAME/NAME.mcap)")
    if not overwrite:
        raise OutputError(f"{path}: exists; pass --overwrite to replace it (only nanostage's files in it are "
                          "replaced; nothing was written)")


def _recording_parent(path: Path, overwrite: bool) -> Path:
    """:func:`check_recording`; the folder the recording lies in made (marked, if nanostage makes or
    owns it); the partials a process now gone left for ``path`` removed. Returns the folder."""
    check_recording(path, overwrite)
    parent = path.parent
    if _lstat(parent) is None or is_output_folder(parent):
        _folder(parent)
    _clean_partials(parent, path.name)
    return parent


def prepare_recording(path, overwrite: bool = False) -> Path:
    """Ready ``path`` for a recording written in place (a recorder that streams to disk): refused as
    by :func:`check_recording`; with ``overwrite`` an existing one's files are removed
    (:func:`remove`: nanostage's only -- anything else left is an :class:`OutputError`)."""
    path = Path(path)
    _recording_parent(path, overwrite)
    if _lstat(path) is not None:
        kept = remove(path)
        if kept:
            raise OutputError(f"{path}: holds files nanostage did not write ({', '.join(p.name for p in kept)}); "
                              "move them away or choose another output")
    return path


@contextmanager
def replacing_folder(path, overwrite: bool = False) -> Iterator[Path]:
    """Yield a path (not yet existing) in a fresh temporary folder beside ``path``, for a writer
    that makes a whole folder (a rosbag2 bag); on success the folder is moved to ``path``, on any
    error or interrupt removed.

    A new ``path`` is one rename. An existing one (``overwrite`` only, :func:`check_recording`)
    keeps what nanostage did not write in it: each new file replaces nanostage's file of that
    name (a user's file of that name is refused), nanostage's files the new folder no longer
    has are removed. The folder gets its :data:`MANIFEST`.
    """
    path = Path(path)
    parent = _recording_parent(path, overwrite)
    tmp = parent / _temp_name(path.name)
    os.mkdir(tmp)
    try:
        new = tmp / path.name
        yield new
        files = set(os.listdir(new))
        bad = [f for f in files if not stat.S_ISREG(os.lstat(new / f).st_mode)]
        if bad:
            raise RuntimeError(f"{new}: the writer made {bad}; a recording folder holds files only")
        _update(new, add=files)
        check_recording(path, overwrite)
        if _lstat(path) is None:
            os.rename(new, path)
        else:
            old = listed(path) or set()
            for f in files:
                _check_file(path / f)
            _update(path, add=files)
            for f in sorted(files):
                os.replace(new / f, path / f)
            for f in sorted(old - files):          # nanostage's files of the recording replaced
                with suppress(FileNotFoundError):
                    remove(path / f)
    finally:
        if _lstat(tmp) is not None:
            shutil.rmtree(tmp, ignore_errors=True)


# =========================================================================== removing
def remove(path) -> list[Path]:
    """Remove what nanostage wrote at ``path``; returns what it left (not nanostage's).

    A file goes if its folder's manifest lists it. A folder with a manifest loses its listed
    files, its own sub-folders (recursively) and the partials of processes gone, and is
    removed if nothing else is left in it (else it keeps its manifest, listing what is left of
    nanostage's: nothing). Nothing at ``path``: nothing done.

    Raises
    ------
    OutputError
        ``path`` is a link, a file nanostage did not write, or a folder without a manifest.
    """
    path = Path(path)
    st = _lstat(path)
    if st is None:
        return []
    _refuse_link(path, st)
    if not stat.S_ISDIR(st.st_mode):
        _check_file(path)
        os.unlink(path)
        _update(path.parent, drop=[path.name])
        return []
    names = listed(path)
    if names is None:
        raise OutputError(f"{path}: a folder nanostage did not write (no {MANIFEST}); nanostage removes only its "
                          "own outputs: move it away or choose another output folder")
    _clean_partials(path)
    kept = []
    for e in sorted(os.listdir(path)):
        p = path / e
        est = _lstat(p)
        if e == MANIFEST or est is None:
            continue
        if stat.S_ISREG(est.st_mode) and e in names:
            os.unlink(p)
        elif stat.S_ISDIR(est.st_mode) and is_output_folder(p):
            kept += remove(p)
        else:
            kept.append(p)
    if kept:
        _update(path, drop={e for e in names if _lstat(path / e) is None})
    else:
        os.unlink(path / MANIFEST)
        with suppress(OSError):
            path.rmdir()
    return kept


# =========================================================================== command line
OVERWRITE_HELP = ("write into an existing output that nanostage did not write, or replace an existing recording; "
                  "only nanostage's own files are ever replaced or removed (docs/security.md, Outputs)")
"""Help of every command's ``--overwrite``."""


def add_overwrite_argument(parser) -> None:
    """``--overwrite`` (:data:`OVERWRITE_HELP`) on an ``argparse`` parser."""
    parser.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)


# =========================================================================== signals
@contextmanager
def interrupts_as_errors():
    """SIGTERM and SIGINT raise :class:`Interrupted` (a ``KeyboardInterrupt``) in the main thread
    while inside, so ``finally`` blocks remove temporaries as on any error. Elsewhere than in the
    main thread: nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        if frame is not None and frame.f_code.co_name == "__del__":
            # an exception raised in a finalizer is printed and dropped: deliver the signal again
            threading.Timer(0.01, os.kill, (os.getpid(), signum)).start()
            return
        raise Interrupted(signum)

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGINT)
           if signal.getsignal(s) is not signal.SIG_IGN}           # a signal the parent ignores stays ignored
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


@contextmanager
def interrupts_deferred():
    """Inside, SIGTERM and SIGINT are only noted; the yielded ``check()`` raises :class:`Interrupted`
    once one has arrived, and leaving the block raises it too. For loops around code that must not
    be interrupted mid-call -- ROS callbacks, which rclpy's executor would log as a fatal error --
    that call ``check()`` between calls. Elsewhere than in the main thread: signals unchanged."""
    got: list[int] = []

    def check() -> None:
        if got:
            raise Interrupted(got[0])

    if threading.current_thread() is not threading.main_thread():
        yield check
        return
    old = {s: signal.signal(s, lambda signum, frame: got.append(signum))
           for s in (signal.SIGTERM, signal.SIGINT) if signal.getsignal(s) is not signal.SIG_IGN}
    try:
        yield check
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    check()
