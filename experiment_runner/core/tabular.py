"""Import any tabular record of a positioning axis as a contract recording (``nanostage convert``).

A user's rig logs to whatever its software writes: a CSV or whitespace table, JSON, a MATLAB
file (v5, or v7.3 which is HDF5), a NumPy archive -- often from two loggers at different rates.
:func:`convert_table` maps its columns onto the recording contract
(``shared/contract/recording.md``) and writes a recording that
:func:`~experiment_runner.core.recording.read_recording` and ``nanostage diagnose`` take::

    nanostage convert table run.csv --time t --reference x_ref --command u --measured x \\
        --scale x=1e-6 --out run.mcap

Reading (:func:`read_table`)
    The format is recognised from the file's first bytes, not its name: MATLAB v5
    (``scipy.io.loadmat``), HDF5 -- MATLAB v7.3 or any ``.h5`` (``h5py``; MATLAB's
    column-major datasets are transposed back), NumPy ``.npz`` / ``.npy``, JSON (text starting
    with ``{``, or ``[`` when it parses), else text. Text and JSON are read through
    :func:`stage_sim.validation.read_text_file` (regular files only, at most
    :data:`MAX_TEXT_BYTES`; UTF-8, else Latin-1).

    Text: comma-, semicolon-, tab- or whitespace-separated (from the first data line); lines
    starting with ``#`` or ``%`` are comments. *The header is found*: the data start at the
    first line of numbers that is not followed by a header-like line (more text fields than
    numbers: a lone version number or year above the names is not data); every line above
    is header. Of those, the last with one field per column is the names, unless it is a row
    of units (``s, um, N``; ``[ms] [m] [V]``), which is then kept as the columns' units with the
    line above it as the names; the lines above the names are a logger's preamble, kept in the
    recording's ``provenance.header``. Without such a line the names are the last comment line
    above the data when it has one name per column (``numpy.savetxt(header=...)``), else
    ``1``, ``2``, ... ``skip_rows`` (``--skip-rows N``) instead skips the first N lines of the
    file and takes the next as the header (when it is not numbers; a units row under it too).
    An error on a header-like line (a wrong ``--skip-rows``, a second log appended) names the
    line and the ``--skip-rows`` that would read it as the header.

    JSON: columns (``{"t": [...], "x": [...]}``; nested objects give ``outer.inner``; pandas'
    ``orient="columns"`` and ``"split"``), records (``[{"t": 0, "x": 1}, ...]``, also one
    object per line, pandas' ``"records"`` / ``"index"``; a bad value is named by its record),
    or rows (``[[0, 1], ...]``: columns ``1``, ``2``, ...); ``null`` is nan (refused where
    used); a number outside a list is a scalar; booleans and text are not data; a key twice
    in an object is refused.

    A variable that is a vector is a column of its name; a matrix gives one column per
    column, ``NAME:1``, ``NAME:2``, ... (1-based; its longer side is the samples); MATLAB
    structs and HDF5 groups give ``outer.inner``; a one-element variable is a *scalar*,
    usable as a scale factor (``--scale vir=gtau``). ``nanostage convert table FILE --list``
    prints them (with the units and header lines a text header gives).

Mapping (:class:`Mapping`, from flags or a YAML file, :func:`load_mapping`)
    ``time`` (a column; or ``rate`` in Hz for a table without one), ``time_unit`` (``s``,
    ``ms``, ``us``, ``ns``; default the header's -- a units row, or a name such as ``t [ms]``,
    ``time_ms`` -- else s; a unit given against the header's is refused), ``skip_rows``,
    ``reference`` (optional: without it the record is *open-loop* -- no ``/stage/reference``
    is written, ``run.open_loop`` says so, and readers take it only when asked, see
    :func:`~experiment_runner.core.recording.read_recording`), ``reference_velocity`` (else the
    central difference of the reference, said so in the config), ``command``,
    ``command_kind`` (``drive``, default: a command to a drive with a force constant;
    ``measured``: the force applied, measured -- ``/experiment/config`` ``command.kind``,
    :data:`msg_defs.topics.COMMAND_KINDS`), ``measured``, ``bearing`` (a bearing displacement
    sensor), ``input`` (a known external force, written to ``/stage/external_force``),
    ``command_includes_input`` (the command column holds the input as well -- a test signal
    added to the drive input: the command written is command - input, so command + external
    force is what the column held), ``scale`` (column -> factor: a number, a scalar of the
    file, or a product of them such as ``gtau*1.014``; values are multiplied into SI),
    ``units`` (``linear``: m, N; ``rotary``: rad, N·m), ``sources`` (files joined on their
    time columns, below), ``extra`` (columns kept as they are on ``/source/channels``, with
    their units), ``resample``, ``case``, ``notes`` (free text carried into
    ``/experiment/config``).

Joining two loggers (``sources``; ``--join FILE --join-time COL``)
    Each joined file (a :class:`Source`: ``file`` -- relative to the mapping file --, ``time``,
    ``time_unit``, ``skip_rows``, ``method``, ``time_offset`` [s] added to its times) must
    have a strictly increasing time column. The record is the primary file's samples within
    the overlap of all time bases (the rest is dropped, not extrapolated); a mapped column the
    primary lacks is taken from the joined file that has it (``STEM.COL``, the file's name
    without its suffix, names a joined file's column explicitly: when several files have it,
    or the primary too) and put on the primary's times: ``linear`` interpolation between its two neighbouring
    samples (a sampled signal: a load cell, a second encoder), or ``hold`` (its last sample at
    or before the time: a held command). Refused: no overlap, a time column that goes back,
    and time bases whose spans differ by 100x or more (time units that differ). Each join is
    warned about with both rates, the overlap and the samples dropped (and when the joined
    file is the faster one: no anti-alias filter is applied -- make the faster logger the
    primary), and recorded in ``provenance.joined``.

Sampling
    Any rate. The stamps are the regular grid ``k * T`` to the ns (``T`` the mean period of
    the time column, snapped to a whole ns when that moves no sample by more than 1 % of
    ``T``; or ``1 / rate`` exactly); the source time of the
    first sample is ``run.time_offset_s``. Irregular stamps (an interval off the mean by more
    than 5 %, or a sample more than 25 % of ``T`` off the grid: dropped samples, a changed
    rate, a time column that is not time) are refused with the row and values, unless
    ``resample`` is asked: positions and velocities are then interpolated linearly onto a
    grid of the median interval (or the given rate), the command and the external force are
    held from the last sample at or before each grid time (a drive holds its command over
    the period), and the config records it. A rate outside :data:`PLAUSIBLE_RATE` (20 Hz to
    1 MHz) is warned about, with the time unit that would make it plausible (a ms column read
    as s gives a 1 kHz record 1 Hz): :class:`~stage_sim.validation.ConfigWarning`, on stderr
    from the command line, and in the config's ``warnings``.

Output
    One trial (``trial_start``/``trial_end`` around the record). The recording is written to
    a temporary directory beside ``out`` and moved into place only when complete: a failed
    or interrupted conversion leaves no partial recording (and an existing one is replaced
    only with ``overwrite``). Every bad input is a :class:`~stage_sim.validation.ConfigError`
    of one line naming the file, the column or key, the value and what is allowed (the CLI
    prints it and exits 2).

``convert emps`` (:func:`convert_emps`) is this importer with a shipped mapping:
``mappings/emps.yaml`` (:data:`EMPS_MAPPING`) for ``DATA_EMPS.mat`` -- the EMPS benchmark's
arrays, the drive gain as the command's scale, its drive voltage ``vir`` kept on
``/source/channels`` -- and ``mappings/emps_pulses.yaml`` (:data:`EMPS_PULSES_MAPPING`) for a
file with ``pulses_N`` (``DATA_EMPS_PULSES.mat``): the pulses, added to the drive input
(``vir`` = control law + 1.014 ``pulses_N`` V), act on the load as ``gtau * 1.014 * pulses_N``
N (+x; 0 or 178.2 N), written to ``/stage/external_force``; ``/stage/command`` is
``gtau * vir`` minus that (the controller's force).
"""
from __future__ import annotations

import csv
import hashlib
import io
import math
import re
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from experiment_runner.core.nominal_model import add_convert_nominal_arguments, main_convert_nominal
from experiment_runner.core.outputs import add_overwrite_argument, check_recording
from experiment_runner.core.recording import (LIMITS, TrialSignals, bag_layout, beyond_limits, read_recording,
                                         write_trials)
from msg_defs.topics import (BEARING, COMMAND, COMMAND_KINDS, EXTERNAL_FORCE, MEASURED, MOTOR, REFERENCE,
                             SOURCE_CHANNELS, TABLE)
from stage_sim.config import read_yaml_file
from stage_sim.validation import ConfigError, ConfigWarning, input_file_problem, read_text_file

__all__ = ["Table", "read_table", "Mapping", "load_mapping", "mapping_from_dict", "Signals", "prepare",
           "convert_table", "convert_emps", "join", "Source", "sha256", "EMPS_MAPPING", "EMPS_PULSES_MAPPING",
           "TIME_UNITS", "COMMAND_KINDS", "PLAUSIBLE_RATE", "header_like", "units_line", "header_time_unit",
           "add_convert_arguments", "main_convert"]

EMPS_MAPPING = Path(__file__).with_name("mappings") / "emps.yaml"
"""The mapping of the EMPS benchmark's ``DATA_EMPS.mat`` (``nanostage convert emps``)."""
EMPS_PULSES_MAPPING = EMPS_MAPPING.with_name("emps_pulses.yaml")
"""... and of its validation record with force pulses, ``DATA_EMPS_PULSES.mat``."""

INTERVAL_TOL = 0.05
"""A sample interval may differ from the mean period by this fraction (logger jitter)."""
GRID_TOL = 0.25
"""... and a sample lie this fraction of a period off the regular grid."""
SNAP_TOL = 0.01
"""The period is rounded to the ns when that moves no stamp by more than this fraction of it."""

_TEXT_DELIMS = ("\t", ";", ",")
MAX_TEXT_BYTES = 512 << 20
"""Largest text or JSON table read [bytes] (a 10 kHz, 5-column log of 15 minutes is ~400 MB)."""
MAX_HEADER_LINES = 50
"""Header lines above a text table's names kept in the recording's provenance (200 characters each)."""


# =========================================================================== reading
@dataclass
class Table:
    """A file's columns (1-D float arrays, one value per sample) and scalars.

    ``column(name)`` converts and checks a column on first use, so a bad value in a column
    nobody asked for does not stop the import; errors name the file, column, row and value.
    """
    path: Path
    format: str
    names: list[str]
    scalars: dict[str, float]
    _raw: dict = field(repr=False, default_factory=dict)          # name -> ndarray or list[str]
    _lines: np.ndarray | None = field(repr=False, default=None)   # text: file line of each row
    _cache: dict = field(repr=False, default_factory=dict)
    header: list = field(default_factory=list)     # text: the lines above the column names (a logger's preamble)
    units: dict = field(default_factory=dict)      # text: column -> unit, from a units row under the names
    row_word: str = "sample"                       # how a row is called where there is no line ("record": JSON)
    first_row: int = 0                             # the file's row of row 0 (a table cut to a joined file's overlap)
    origin: dict = field(default_factory=dict)     # column -> where it came from (a joined file), for the config

    def where(self, row: int) -> str:
        """A row as the user finds it: the file's line (text) or the sample index (arrays)."""
        return (f"line {int(self._lines[row])}" if self._lines is not None
                else f"{self.row_word} {row + self.first_row}")

    def describe(self) -> str:
        """Columns (with their units where a header row gives them) and scalars, a line each
        group; the header lines skipped."""
        unit = {n: str(u).strip().strip("[]()").strip() for n, u in self.units.items()}
        cols = ", ".join(f"{n} [{unit[n]}]" if unit.get(n) else n for n in self.names) or "none"
        sc = ", ".join(f"{k} = {v:.6g}" for k, v in self.scalars.items()) or "none"
        head = "".join(f"\n  header: {h}" for h in self.header)
        return f"{self.path}: {self.format}{head}\n  columns: {cols}\n  scalars: {sc}"

    def _unknown(self, name: str, role: str) -> ConfigError:
        also = f"; scalars: {', '.join(self.scalars)}" if self.scalars else ""
        return ConfigError(f"{self.path}: no column {name!r} ({role}); columns: {', '.join(self.names) or 'none'}"
                           f"{also}")

    def column(self, name: str, role: str = "column") -> np.ndarray:
        """Column ``name`` as float64; ``ConfigError`` if it is absent or not numeric."""
        if name in self._cache:
            return self._cache[name]
        if name not in self._raw:
            raise self._unknown(name, role)
        raw = self._raw[name]
        if isinstance(raw, np.ndarray):
            if raw.dtype.kind not in "biuf":
                raise ConfigError(f"{self.path}: column {name!r} ({role}) holds {raw.dtype} values, not numbers")
            col = raw.astype(np.float64)
        else:
            try:
                col = np.array(raw, dtype=np.float64)
            except ValueError:
                for i, v in enumerate(raw):
                    try:
                        float(v)
                    except ValueError:
                        shown = repr(v) if v else "an empty field"
                        hint = ""
                        if self._lines is not None:
                            row = [self._raw[n][i] for n in self.names if not isinstance(self._raw[n], np.ndarray)]
                            hint = skip_rows_hint(row, int(self._lines[i]))
                        raise ConfigError(f"{self.path}: column {name!r} ({role}) {self.where(i)}: {shown} is not "
                                          f"a number{hint}") from None
                raise
        self._cache[name] = col
        return col


def _sniff(path: Path) -> str:
    with open(path, "rb") as f:
        head = f.read(1024)
    if head.startswith(b"\x89HDF\r\n\x1a\n") or head[512:520] == b"\x89HDF\r\n\x1a\n":
        return "hdf5"
    if head.startswith(b"MATLAB"):
        return "mat"
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return "npz"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    return "text"


def read_table(path, skip_rows: int | None = None) -> Table:
    """Read a tabular file (text, JSON, MATLAB v5/v7.3, HDF5, NPZ/NPY) into a :class:`Table`.

    ``skip_rows``: a text table's first lines not to read (a logger's preamble); the next
    line is the header when it is not numbers. Without it the header is found: every line
    above the first two lines of numbers (see the module docstring).

    >>> import os, tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     p = os.path.join(d, "run.csv")
    ...     _ = open(p, "w").write("# a comment\\nt,x\\n0,1.5\\n0.001,2.5\\n")
    ...     tab = read_table(p)
    >>> tab.names, tab.column("x").tolist(), tab.where(1)
    (['t', 'x'], [1.5, 2.5], 'line 4')
    """
    path = Path(path)
    problem = input_file_problem(path)
    if problem is not None:
        raise ConfigError(f"{path}: {problem}")
    kind = _sniff(path)
    if skip_rows and kind != "text":
        raise ConfigError(f"{path}: skip_rows = {skip_rows} applies to text tables; this is a {kind} file")
    reader = {"hdf5": _read_hdf5, "mat": _read_mat, "npz": _read_npz, "npy": _read_npy,
              "text": lambda p: _read_text(p, skip_rows)}[kind]
    try:
        return reader(path)
    except ConfigError:
        raise
    except MemoryError:
        raise
    except Exception as err:       # noqa: BLE001 - third-party readers fail in many ways on a bad file
        raise ConfigError(f"{path}: not a readable {kind} file ({type(err).__name__}: {err})") from None


def _add_array(raw: dict, scalars: dict, name: str, arr) -> None:
    """One variable: scalar, column, or matrix (one column per column, ``NAME:j``)."""
    a = np.asarray(arr)
    if a.dtype.names:                                   # structured / record array
        for f in a.dtype.names:
            _add_array(raw, scalars, f"{name}.{f}" if name else f, a[f])
        return
    if a.dtype.kind not in "biuf" or a.size == 0:
        return                                          # text, cells, objects, complex: not data
    if a.size == 1:
        scalars[name] = float(a.reshape(-1)[0])
        return
    a = np.squeeze(a)
    if a.ndim == 1:
        raw[name] = a
    elif a.ndim == 2:
        m = a if a.shape[0] >= a.shape[1] else a.T       # samples along the longer side
        for j in range(m.shape[1]):
            raw[f"{name}:{j + 1}"] = m[:, j]


def _table(path, fmt, raw, scalars, lines=None) -> Table:
    if not raw:
        what = f" (scalars only: {', '.join(scalars)})" if scalars else ""
        raise ConfigError(f"{path}: {fmt} holds no numeric column{what}")
    return Table(path=path, format=fmt, names=list(raw), scalars=scalars, _raw=raw, _lines=lines)


def _read_mat(path: Path) -> Table:
    from scipy.io import loadmat
    try:
        m = loadmat(path, simplify_cells=True)
    except NotImplementedError:                         # v7.3 is HDF5 (scipy says so)
        return _read_hdf5(path)
    raw, scalars = {}, {}

    def walk(prefix, obj):
        if isinstance(obj, dict):
            for k, v in obj.items():
                if not k.startswith("__"):
                    walk(f"{prefix}.{k}" if prefix else k, v)
        elif isinstance(obj, np.ndarray) or np.isscalar(obj):
            if not isinstance(obj, (str, bytes)):
                _add_array(raw, scalars, prefix, obj)
    walk("", m)
    return _table(path, "MATLAB v5 MAT file (scipy.io.loadmat)", raw, scalars)


def _read_hdf5(path: Path) -> Table:
    import h5py
    raw, scalars = {}, {}
    matlab = False
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            nonlocal matlab
            if not isinstance(obj, h5py.Dataset) or name.startswith("#refs#"):
                return
            cls = obj.attrs.get("MATLAB_class")
            if cls is not None:
                matlab = True
                cls = cls.decode() if isinstance(cls, bytes) else str(cls)
                if cls not in ("double", "single", "int8", "uint8", "int16", "uint16", "int32", "uint32",
                               "int64", "uint64", "logical"):
                    return                              # char, cell, struct references
            if obj.dtype.kind not in "biuf" and not obj.dtype.names:
                return
            a = obj[()]
            if cls is not None and np.ndim(a) >= 2:
                a = np.asarray(a).T                     # MATLAB writes column-major
            _add_array(raw, scalars, name.replace("/", "."), a)
        f.visititems(visit)
    fmt = "MATLAB v7.3 MAT file (HDF5, h5py)" if matlab else "HDF5 file (h5py)"
    return _table(path, fmt, raw, scalars)


def _read_npz(path: Path) -> Table:
    raw, scalars = {}, {}
    with np.load(path, allow_pickle=False) as z:
        for k in z.files:
            try:
                a = z[k]
            except ValueError:                          # object arrays need pickle: not data
                continue
            _add_array(raw, scalars, k, a)
    return _table(path, "NumPy .npz archive", raw, scalars)


def _read_npy(path: Path) -> Table:
    a = np.load(path, allow_pickle=False)
    raw, scalars = {}, {}
    if a.dtype.names:
        _add_array(raw, scalars, "", a)
    elif a.ndim == 2:
        m = a if a.shape[0] >= a.shape[1] else a.T
        for j in range(m.shape[1]):
            raw[str(j + 1)] = m[:, j]
    else:
        _add_array(raw, scalars, "1", a)
    return _table(path, "NumPy .npy array", raw, scalars)


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def _split(s: str, delim: str) -> list[str]:
    if delim == " ":
        return s.split()
    return [x.strip() for x in next(csv.reader(io.StringIO(s), delimiter=delim))]


def _delimiter(s: str) -> str:
    return next((d for d in _TEXT_DELIMS if d in s), " ")


def _numbers(s: str) -> tuple[str, int] | None:
    """``(delimiter, fields)`` of a line that is all numbers, else None."""
    d = _delimiter(s)
    f = _split(s, d)
    return (d, len(f)) if f and all(_is_number(x) for x in f) else None


def header_like(fields) -> bool:
    """A row that reads as a header (names, units, a logger's preamble), not data: more
    fields that are text than numbers.

    >>> header_like(["Time [ms]", "Position [um]"]), header_like(["0", "", "1.5"])
    (True, False)
    """
    text = sum(1 for x in fields if x and not _is_number(x))
    return text > sum(1 for x in fields if _is_number(x))


_UNIT_WORDS = frozenset(
    "s ms us µs ns min h m mm um µm nm rad mrad urad µrad deg ° rev n mn kn nm n·m n*m mnm n.m v mv a ma "
    "counts count cnt inc 1 - % hz khz m/s mm/s um/s µm/s rad/s deg/s rpm m/s^2 m/s² g kg".split())


def units_line(fields) -> bool:
    """A header row of units (``s, um, N``, ``[ms] [m] [V]``): every field a unit or empty.

    >>> units_line(["[s]", "um", "N"]), units_line(["time", "pos", "force"])
    (True, False)
    """
    words = [x.strip().strip("[]()").strip().lower() for x in fields]
    return any(words) and all(not w or w in _UNIT_WORDS for w in words)


def skip_rows_hint(fields, line_no: int) -> str:
    """The hint added to an error on a line that looks like a header line ('' otherwise)."""
    if not header_like(fields):
        return ""
    shown = ", ".join(fields)
    shown = shown if len(shown) <= 60 else shown[:57] + "..."
    return (f"; line {line_no} ({shown}) looks like a header line: a header of several lines? pass --skip-rows "
            f"{line_no - 1} (mapping: skip_rows) to read it as the header, or cut it from the file")


def _read_text(path: Path, skip_rows: int | None = None) -> Table:
    text = read_text_file(path, "table", max_bytes=MAX_TEXT_BYTES, fallback="latin-1")
    if "\x00" in text[:4096]:
        raise ConfigError(f"{path}: binary file of an unknown format (text, JSON, MATLAB .mat, HDF5, .npz or .npy "
                          "expected)")
    head = text.lstrip()[:1]
    if head in "{[" and head:
        tab = _read_json(path, text, strict=head == "{")
        if tab is not None:
            return tab                                    # else: text after all (an INI-like "[Header]")
    all_lines = text.splitlines()
    first = 0
    if skip_rows:
        if skip_rows >= len(all_lines):
            raise ConfigError(f"{path}: skip_rows = {skip_rows} skips all {len(all_lines)} lines of the file")
        first = skip_rows
    # the file's lines that hold something: (line number, text); comments apart
    content, comments = [], {}
    for no, line in enumerate(all_lines[first:], first + 1):
        s = line.strip()
        if not s:
            continue
        if s[0] in "#%":
            comments[len(content)] = s.lstrip("#% \t")    # the last comment above content[i]
            continue
        content.append((no, s))
    if not content:
        raise ConfigError(f"{path}: no data rows (a text table needs at least a row of numbers)")
    preamble = []
    if skip_rows is None:
        # the data start at the first line of numbers not followed by a header line (a lone number
        # above a header -- a version, a year -- is not data); every line above is the header
        start = None
        for i, (no, s) in enumerate(content):
            here = _numbers(s)
            if here is None:
                continue
            if i + 1 == len(content) or not header_like(_split(content[i + 1][1], here[0])):
                start = i
                break
        if start is None:
            raise ConfigError(f"{path}: no data rows: no line holds only numbers (a text table needs rows of "
                              "numbers; header lines above them are read as the header)")
        delim = _numbers(content[start][1])[0]
        ncol = len(_split(content[start][1], delim))
        above = content[:start]
    else:                                                 # skip_rows: the next line is the header (+ units)
        above = [] if _numbers(content[0][1]) else content[:1]
        if above and len(content) > 1 and units_line(_split(content[1][1], _delimiter(content[0][1]))):
            above = content[:2]
        start = len(above)
        delim = _delimiter(content[start][1]) if start < len(content) else _delimiter(content[0][1])
        ncol = None
    names = units = None
    if above:
        split_above = [(no, _split(s, delim)) for no, s in above]
        if ncol is None:
            names = split_above[0][1]
            units = split_above[1][1] if len(split_above) > 1 else None
        else:
            # the header block: the lines right above the data with one field per column; its
            # first is the names, the next (if any) the units; lines above it are preamble
            k = len(split_above)
            while k > 0 and len(split_above[k - 1][1]) == ncol and header_like(split_above[k - 1][1]):
                k -= 1
            block = split_above[k:]
            if len(block) >= 2 and units_line(block[-1][1]):
                names, units = block[-2][1], block[-1][1]
                preamble = [s for _, s in above[:-2]]
            elif block:
                names = block[-1][1]
                preamble = [s for _, s in above[:-1]]
            else:
                preamble = [s for _, s in above]
    rows = [_split(s, delim) for _, s in content[start:]]
    lines = [no for no, _ in content[start:]]
    if not rows:
        raise ConfigError(f"{path}: a header ({', '.join(names or [])}) but no data rows")
    if ncol is None:
        ncol = len(names) if names is not None else len(rows[0])
    if names is None and start in comments:
        c = _split(comments[start], delim)
        if len(c) == ncol and not all(_is_number(x) for x in c):
            names = c                                     # numpy.savetxt(header=...) writes it so
    if names is None:
        names = [str(j + 1) for j in range(ncol)]
    names = [n if n else str(j + 1) for j, n in enumerate(names)]
    seen = {}
    for j, n in enumerate(names):
        if n in seen:
            raise ConfigError(f"{path}: the header names column {n!r} twice (columns {seen[n] + 1} and {j + 1})")
        seen[n] = j
    for i, r in enumerate(rows):
        if len(r) != ncol:
            raise ConfigError(f"{path}: line {lines[i]} has {len(r)} fields, expected {ncol} "
                              f"({', '.join(names)}){skip_rows_hint(r, lines[i])}")
    cols = list(zip(*rows))
    raw = {n: list(cols[j]) for j, n in enumerate(names)}
    sep = {"\t": "tab", ";": "semicolon", ",": "comma", " ": "whitespace"}[delim]
    how = f"text table ({sep}-separated, {len(rows)} rows"
    if skip_rows:
        how += f"; {skip_rows} line(s) skipped"
    elif preamble:
        how += f"; {len(preamble)} header line(s) above the names skipped"
    how += ")"
    return Table(path=path, format=how, names=names, scalars={}, _raw=raw, _lines=np.asarray(lines),
                 header=[p[:200] for p in preamble[:MAX_HEADER_LINES]],
                 units=dict(zip(names, units)) if units else {})


def _unique_keys(pairs):
    out = {}
    for k, v in pairs:
        if k in out:
            raise ConfigError(f"key {k!r} twice in one object")
        out[k] = v
    return out


def _read_json(path: Path, text: str, strict: bool = True) -> Table | None:
    """A JSON table: columns (``{"t": [...], "x": [...]}``, nested objects giving ``outer.inner``,
    pandas' ``orient="columns"`` and ``"split"``), records (``[{"t": 0, "x": 1}, ...]``, also one
    per line, pandas' ``orient="records"``/``"index"``) or rows (``[[0, 1], ...]``: columns 1, 2, ...);
    a number outside a list is a scalar. Not ``strict`` (text starting with ``[``): None when it
    is not JSON at all (a logger's ``[Header]`` line)."""
    import json
    try:
        try:
            doc = json.loads(text, object_pairs_hook=_unique_keys)
            form = "JSON"
        except json.JSONDecodeError as err:
            if err.msg != "Extra data":
                raise
            doc = [json.loads(s, object_pairs_hook=_unique_keys) for s in text.splitlines() if s.strip()]
            form = "JSON lines"
    except json.JSONDecodeError as err:
        if not strict:
            return None
        raise ConfigError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    except ConfigError as err:
        raise ConfigError(f"{path}: {err}") from None
    except RecursionError:
        raise ConfigError(f"{path}: JSON nested too deeply to be a table") from None
    except ValueError as err:                             # e.g. an integer of thousands of digits
        raise ConfigError(f"{path}: not a readable JSON table ({err})") from None
    raw, scalars = {}, {}
    row_word = "sample"

    def column(name, values):
        if any(isinstance(v, (list, dict)) for v in values):
            if all(isinstance(v, dict) for v in values):
                records(name, values)
                return
            try:
                _add_array(raw, scalars, name, np.asarray([[math.nan if x is None else x for x in v]
                                                           for v in values], dtype=np.float64))
            except (TypeError, ValueError):
                pass                                      # ragged or text: not a table of numbers
            return
        if any(isinstance(v, bool) for v in values):
            return                                        # flags, not data
        if all(v is None or isinstance(v, (int, float)) for v in values):
            raw[name] = np.array([math.nan if v is None else v for v in values], dtype=np.float64)
        elif any(isinstance(v, (int, float)) or isinstance(v, str) and _is_number(v) for v in values):
            raw[name] = ["null" if v is None else str(v) for v in values]   # checked (with the record) on use
        if len(values) == 1 and isinstance(raw.get(name), np.ndarray):
            scalars[name] = float(raw.pop(name)[0])      # a one-element list: a scalar, as in a MAT file

    def records(prefix, recs):
        nonlocal row_word
        keys = {}
        flat = []
        for i, r in enumerate(recs):
            if not isinstance(r, dict):
                raise ConfigError(f"{path}: record {i} is {type(r).__name__}, not an object like record 0")
            f = {}
            _flatten(r, "", f)
            flat.append(f)
            for k in f:
                keys.setdefault(k, None)
        for k in keys:
            column(f"{prefix}.{k}" if prefix else k, [f.get(k) for f in flat])
        row_word = "record"

    def walk(prefix, obj):
        if isinstance(obj, dict):
            if obj and all(_index_key(k) for k in obj):
                vals = [obj[k] for k in sorted(obj, key=int)]
                if all(isinstance(v, dict) for v in vals):
                    records(prefix, vals)                 # pandas orient="index"
                elif not any(isinstance(v, (dict, list)) for v in vals):
                    column(prefix or "1", vals)           # pandas orient="columns": one column per key
                return
            if set(obj) >= {"columns", "data"} and isinstance(obj["columns"], list) \
                    and isinstance(obj["data"], list) and all(isinstance(r, list) for r in obj["data"]):
                cols = [str(c) for c in obj["columns"]]       # pandas orient="split"
                if any(len(r) != len(cols) for r in obj["data"]):
                    i = next(i for i, r in enumerate(obj["data"]) if len(r) != len(cols))
                    raise ConfigError(f"{path}: data row {i} has {len(obj['data'][i])} values, expected "
                                      f"{len(cols)} ({', '.join(cols)})")
                for j, c in enumerate(cols):
                    column(f"{prefix}.{c}" if prefix else c, [r[j] for r in obj["data"]])
                return
            for k, v in obj.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(obj, list):
            if obj and all(isinstance(v, dict) for v in obj):
                records(prefix, obj)
            elif obj and all(isinstance(v, list) for v in obj):
                lens = {len(v) for v in obj}
                if len(lens) != 1:
                    i = next(i for i, v in enumerate(obj) if len(v) != len(obj[0]))
                    raise ConfigError(f"{path}: row {i} has {len(obj[i])} values, row 0 has {len(obj[0])}")
                if prefix:
                    column(prefix, obj)
                else:
                    for j in range(len(obj[0])):
                        column(str(j + 1), [r[j] for r in obj])
            else:
                column(prefix or "1", obj)
        elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
            scalars[prefix or "1"] = float(obj)

    walk("", doc)
    tab = _table(path, f"{form} ({'records' if row_word == 'record' else 'columns'})", raw, scalars)
    tab.row_word = row_word
    return tab


def _index_key(k) -> bool:
    return isinstance(k, str) and k.isdigit()


def _flatten(obj: dict, prefix: str, out: dict) -> None:
    for k, v in obj.items():
        name = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            _flatten(v, name, out)
        else:
            out[name] = v


# =========================================================================== mapping
_ROLES = ("time", "reference", "reference_velocity", "command", "measured", "bearing", "input")
_UNITS = {"linear": {"position": "m", "velocity": "m/s", "force": "N"},
          "rotary": {"position": "rad", "velocity": "rad/s", "force": "N·m"}}
_KEYS = (*_ROLES, "rate", "time_unit", "skip_rows", "scale", "units", "command_kind", "command_includes_input",
         "sources", "extra", "resample", "resample_rate", "case", "notes")
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9}
"""Units a time column may be in (``time_unit``), with their factor to s."""
JOIN_METHODS = ("linear", "hold")
_SOURCE_KEYS = ("file", "time", "time_unit", "skip_rows", "method", "time_offset")


@dataclass(frozen=True)
class Source:
    """A second file joined on its time column (mapping ``sources``; ``--join``): its columns
    are interpolated onto the primary file's times (``method`` linear, or ``hold``: the last
    value at or before each time), within the overlap of the two time bases only."""
    file: str
    time: str
    time_unit: str | None = None  # None: the file's header says (a units row, "t [ms]"), else s
    skip_rows: int | None = None
    method: str = "linear"
    time_offset: float = 0.0      # [s] added to this file's times (after time_unit) to put them on the primary's


@dataclass(frozen=True)
class Mapping:
    """Which column is what (see the module docstring). ``source`` names where it came from
    (a mapping file or ``command line``) for the error messages."""
    command: str
    measured: str
    time: str | None = None
    rate: float | None = None
    reference: str | None = None
    reference_velocity: str | None = None
    bearing: str | None = None
    input: str | None = None
    scale: dict = field(default_factory=dict)          # column -> float or scalar name (or a product: "gtau*1.014")
    units: str = "linear"
    time_unit: str | None = None                       # None: the file's header says (a units row, "t [ms]"), else s
    skip_rows: int | None = None
    command_kind: str = "drive"
    command_includes_input: bool = False
    sources: tuple = ()                                # Source, joined on their time columns
    extra: dict = field(default_factory=dict)          # column -> unit text ("" unknown)
    resample: bool = False
    resample_rate: float | None = None
    case: str | None = None
    notes: dict = field(default_factory=dict)
    source: str = "mapping"

    def label(self, role: str) -> str:
        """How the user named a role: ``--measured`` on the command line, ``measured`` in a file."""
        return f"--{role.replace('_', '-')}" if self.source == "command line" else role

    def roles(self) -> dict[str, str]:
        """Role -> column, for the roles given."""
        return {r: getattr(self, r) for r in _ROLES if getattr(self, r) is not None}


def _positive(v, where: str) -> float:
    try:
        x = float(v) if not isinstance(v, bool) else math.nan
    except (TypeError, ValueError):
        x = math.nan
    if not (math.isfinite(x) and x > 0):
        raise ConfigError(f"{where}: got {v!r}; expected a positive number")
    return x


def _count(v, where: str) -> int:
    if isinstance(v, bool) or not isinstance(v, (int, str)) or not str(v).strip().isdigit():
        raise ConfigError(f"{where}: got {v!r}; expected a number of lines (0 or more)")
    return int(v)


def _time_unit(v, where: str) -> str:
    if v not in TIME_UNITS:
        raise ConfigError(f"{where}: got {v!r}; expected one of s, ms, us, ns (the unit of the time column)")
    return "us" if v == "µs" else v


def _factor_parts(fac: str, where: str) -> None:
    """A factor given as text: a scalar's name, or a product ``gtau*1.014`` of names and numbers."""
    for part in fac.split("*"):
        part = part.strip()
        if not part:
            raise ConfigError(f"{where}: got {fac!r}; expected a number, a scalar of the file, or a product of "
                              "them (gtau*1.014)")
        try:
            x = float(part)
        except ValueError:
            continue
        if not (math.isfinite(x) and x != 0):
            raise ConfigError(f"{where}: got {fac!r}; expected a finite non-zero factor")


def _sources(items, where: str, base: Path | None) -> tuple:
    if isinstance(items, dict):
        items = [items]
    if not isinstance(items, (list, tuple)):
        raise ConfigError(f"{where}: got {items!r}; expected a list of files to join, each with file and time")
    out = []
    for i, item in enumerate(items):
        w = f"{where}[{i}]"
        if not isinstance(item, dict):
            raise ConfigError(f"{w}: got {item!r}; expected a mapping with file and time")
        unknown = [k for k in item if k not in _SOURCE_KEYS]
        if unknown:
            raise ConfigError(f"{w}: unknown key(s) {', '.join(map(repr, unknown))}; allowed keys: "
                              f"{', '.join(_SOURCE_KEYS)}")
        for k in ("file", "time"):
            v = item.get(k)
            if isinstance(v, bool) or not isinstance(v, (str, int)) or str(v) == "":
                raise ConfigError(f"{w}.{k}: got {v!r}; expected " + ("a file" if k == "file" else "a column name"))
        f = Path(str(item["file"]))
        if base is not None and not f.is_absolute():
            f = base / f                                  # relative to the mapping file
        kw = {"file": str(f), "time": str(item["time"])}
        if item.get("time_unit") is not None:
            kw["time_unit"] = _time_unit(item["time_unit"], f"{w}.time_unit")
        if item.get("skip_rows") is not None:
            kw["skip_rows"] = _count(item["skip_rows"], f"{w}.skip_rows")
        method = item.get("method", "linear")
        if method not in JOIN_METHODS:
            raise ConfigError(f"{w}.method: got {method!r}; expected linear (interpolate: a sampled signal) or "
                              "hold (the last value at or before each time: a held command)")
        kw["method"] = method
        off = item.get("time_offset", 0.0)
        try:
            off = float(off) if not isinstance(off, bool) else math.nan
        except (TypeError, ValueError):
            off = math.nan
        if not math.isfinite(off):
            raise ConfigError(f"{w}.time_offset: got {item.get('time_offset')!r}; expected seconds (a finite number)")
        kw["time_offset"] = off
        out.append(Source(**kw))
    return tuple(out)


def mapping_from_dict(data: dict, source: str = "mapping", base: Path | None = None) -> Mapping:
    """Validate a mapping (the YAML file's content, or the flags); ``ConfigError`` of one line.
    ``base``: the folder relative ``sources`` files are in (the mapping file's)."""
    cli = source == "command line"

    def lab(k):
        return ("--join" if k == "sources" else f"--{k.replace('_', '-')}") if cli else k

    where = (lambda k: f"{source}: {lab(k)}")
    if not isinstance(data, dict):
        raise ConfigError(f"{source}: a mapping must be a YAML mapping of keys ({', '.join(_KEYS)}), "
                          f"got {type(data).__name__}")
    unknown = [k for k in data if k not in _KEYS]
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(map(repr, unknown))}; allowed keys: {', '.join(_KEYS)}")
    kw = {}
    for r in _ROLES:
        v = data.get(r)
        if v is None:
            continue
        if isinstance(v, bool) or not isinstance(v, (str, int)) or str(v) == "":
            raise ConfigError(f"{where(r)}: got {v!r}; expected a column name")
        kw[r] = str(v)
    for r in ("command", "measured"):
        if r not in kw:
            raise ConfigError(f"{source}: {lab(r)} is required (the column of the "
                              f"{'drive command' if r == 'command' else 'measured position'})")
    if data.get("rate") is not None:
        kw["rate"] = _positive(data["rate"], where("rate"))
    if "rate" in kw and (data.get("resample") or data.get("resample_rate") is not None):
        raise ConfigError(f"{source}: {lab('resample')} needs {lab('time')} (a table sampled at a given "
                          f"{lab('rate')} is regular already)")
    if ("time" in kw) == ("rate" in kw):
        raise ConfigError(f"{source}: give {lab('time')} (the time column) or {lab('rate')} (the sampling rate "
                          f"[Hz] of a table without one), " + ("not both" if "time" in kw else "one of them"))
    units = data.get("units", "linear")
    if units not in _UNITS:
        raise ConfigError(f"{where('units')}: got {units!r}; expected linear (m, N) or rotary (rad, N·m)")
    kw["units"] = units
    if data.get("time_unit") is not None:
        if "time" not in kw:
            raise ConfigError(f"{source}: {lab('time_unit')} needs {lab('time')} (the time column it is the unit of)")
        kw["time_unit"] = _time_unit(data["time_unit"], where("time_unit"))
    if data.get("skip_rows") is not None:
        kw["skip_rows"] = _count(data["skip_rows"], where("skip_rows"))
    kind = data.get("command_kind", "drive")
    if kind not in COMMAND_KINDS:
        raise ConfigError(f"{where('command_kind')}: got {kind!r}; expected "
                          + " or ".join(f"{k} ({v.split(':')[0]})" for k, v in COMMAND_KINDS.items()))
    kw["command_kind"] = kind
    inc = data.get("command_includes_input", False)
    if not isinstance(inc, bool):
        raise ConfigError(f"{where('command_includes_input')}: got {inc!r}; expected true or false")
    if inc and "input" not in kw:
        raise ConfigError(f"{source}: {lab('command_includes_input')} needs {lab('input')} (the known force the "
                          "command column holds as well)")
    kw["command_includes_input"] = inc
    if data.get("sources"):
        if "time" not in kw:
            raise ConfigError(f"{source}: {lab('sources')} needs {lab('time')} (files are joined on their time "
                              "columns)")
        kw["sources"] = _sources(data["sources"], where("sources"), base)
    scale = data.get("scale") or {}
    if not isinstance(scale, dict):
        raise ConfigError(f"{where('scale')}: got {scale!r}; expected a mapping of column to factor")
    sc = {}
    for col, fac in scale.items():
        if isinstance(fac, bool) or not isinstance(fac, (int, float, str)) or fac == "":
            raise ConfigError(f"{where('scale')}: {col}: got {fac!r}; expected a number or a scalar of the file")
        try:
            fac = float(fac)
        except ValueError:
            _factor_parts(fac, f"{where('scale')}: {col}")   # scalars' names, resolved against the file
        if isinstance(fac, float) and not (math.isfinite(fac) and fac != 0):
            raise ConfigError(f"{where('scale')}: {col}: got {fac!r}; expected a finite non-zero factor")
        sc[str(col)] = fac
    used = set(kw.get(r) for r in _ROLES)
    for col in sc:
        if col not in used:
            raise ConfigError(f"{where('scale')}: {col!r} is not one of the mapped columns "
                              f"({', '.join(sorted(c for c in used if c))})")
    if kw.get("time_unit") is not None and kw.get("time") in sc:
        raise ConfigError(f"{source}: give {lab('time_unit')} or {lab('scale')} for the time column "
                          f"{kw['time']!r}, not both")
    kw["scale"] = sc
    extra = data.get("extra") or {}
    if isinstance(extra, (list, tuple)):
        extra = {str(c): "" for c in extra}
    if not isinstance(extra, dict):
        raise ConfigError(f"{where('extra')}: got {extra!r}; expected a list of columns or column: unit")
    kw["extra"] = {str(k): "" if v is None else str(v) for k, v in extra.items()}
    res = data.get("resample", False)
    if not isinstance(res, bool):
        raise ConfigError(f"{where('resample')}: got {res!r}; expected true or false")
    kw["resample"] = res
    if data.get("resample_rate") is not None:
        kw["resample_rate"] = _positive(data["resample_rate"], where("resample_rate"))
        kw["resample"] = True
    if data.get("case") is not None:
        kw["case"] = str(data["case"])
    notes = data.get("notes") or {}
    if not isinstance(notes, dict):
        raise ConfigError(f"{where('notes')}: got {notes!r}; expected a mapping (free text for the config)")
    kw["notes"] = notes
    return Mapping(source=source, **kw)


def load_mapping(path, overrides: dict | None = None) -> Mapping:
    """A mapping YAML file (keys of :class:`Mapping`; a bare name is a shipped mapping of
    ``mappings/``, e.g. ``emps``), ``overrides`` (flags) on top."""
    data, path = read_yaml_file(path, EMPS_MAPPING.parent, "mapping")
    data = dict(data)
    source = str(path)
    if overrides:
        data.update(overrides)
        source = f"{path} with the command line's flags"
    return mapping_from_dict(data, source, Path(path).parent)


# =========================================================================== signals
@dataclass
class Signals:
    """A record on a regular grid, in SI, ready to write (see :func:`prepare`)."""
    stamp_ns: np.ndarray
    period: float                 # [s]
    x_ref: np.ndarray | None      # None: open loop
    v_ref: np.ndarray | None
    u: np.ndarray
    y: np.ndarray
    y_bearing: np.ndarray | None
    f_ext: np.ndarray | None
    extra: dict                   # name -> values as in the file
    config: dict                  # /experiment/config content
    warnings: list = field(default_factory=list)    # what the user must know (implausible rate, a join), one line each


def _finite(tab: Table, name: str, role: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        i = int(np.argmax(bad))
        raise ConfigError(f"{tab.path}: column {name!r} ({role}) has {int(bad.sum())} non-finite value(s), the "
                          f"first at {tab.where(i)} ({float(a[i])}); fill or cut them before converting")


_FIELDS = {"reference": "position", "reference_velocity": "velocity", "command": "effort", "measured": "position",
           "bearing": "position", "input": "effort"}
"""The JointState field each role's column becomes (for :data:`experiment_runner.core.recording.LIMITS`)."""
MAX_TIME = 9e9
"""Largest sample time [s] a recording can stamp (int64 nanoseconds reach 9.2e9 s)."""


def _within_limits(tab: Table, name: str, label: str, role: str, a: np.ndarray, unit: dict, scaled: str) -> None:
    """Refuse values a recording cannot hold: beyond :data:`~experiment_runner.core.recording.LIMITS`
    (the reader's rule of damage: absurd for any stage, a wrong scale or a corrupt value), or a
    time beyond :data:`MAX_TIME`."""
    if role == "time":
        bad, limit, u = ~(np.abs(a) <= MAX_TIME), MAX_TIME, "s"
    elif role in _FIELDS:
        fld = _FIELDS[role]
        bad, limit = beyond_limits(a, fld), LIMITS[fld]
        u = unit["force" if fld == "effort" else fld]
    else:
        return
    if bad.any():
        i = int(np.argmax(bad))
        raise ConfigError(f"{tab.path}: column {name!r} ({label}) has {int(bad.sum())} value(s) beyond ±{limit:g} {u}"
                          f"{' after scaling (' + scaled + ')' if scaled else ''}, the first at {tab.where(i)} "
                          f"({float(a[i]):g} {u}): absurd for a stage; a wrong scale or unit, or a corrupt value?")


def _factor(tab: Table, m: Mapping, col: str) -> tuple[float, str]:
    """The scale of ``col``: a number, a scalar of the file, or a product of them (``gtau*1.014``)."""
    f = m.scale.get(col, 1.0)
    if not isinstance(f, str):
        return f, (f"{f:g}" if f != 1.0 else "")
    value, shown = 1.0, []
    for part in (p.strip() for p in f.split("*")):
        try:
            value *= float(part)
            shown.append(part)
            continue
        except ValueError:
            pass
        if part not in tab.scalars:
            sc = ", ".join(tab.scalars) or "none"
            raise ConfigError(f"{m.source}: {m.label('scale')} {col}={f}: {part!r} is neither a number nor a scalar "
                              f"of {tab.path} (scalars: {sc})")
        v = tab.scalars[part]
        if not (math.isfinite(v) and v != 0):
            raise ConfigError(f"{tab.path}: scalar {part!r} = {v!r} cannot scale {col!r} (finite, non-zero needed)")
        value *= v
        shown.append(f"{part} = {v:.6g}" if "*" not in f else f"{part} ({v:.6g})")
    return value, " * ".join(shown)


def _grid(tab: Table, m: Mapping, t: np.ndarray) -> tuple[float, float]:
    """Check ``t`` is a regular grid (unless resampling): ``(mean period [s], largest deviation
    of a sample from the grid [s])``."""
    n = len(t)
    role = m.label("time")
    dt = np.diff(t)
    bad = np.flatnonzero(~(dt > 0))
    if len(bad):
        i = int(bad[0])
        raise ConfigError(f"{tab.path}: column {m.time!r} ({role}) does not increase at {tab.where(i + 1)} "
                          f"({t[i]:.9g} then {t[i + 1]:.9g}); time must increase strictly (sort the rows, drop "
                          "repeated samples)")
    period = (t[-1] - t[0]) / (n - 1)
    dev = t - (t[0] + np.arange(n) * period)
    off = np.abs(dt - period) / period
    j = int(np.argmax(off))
    if not m.resample and (off[j] > INTERVAL_TOL or np.max(np.abs(dev)) > GRID_TOL * period):
        med = float(np.median(dt))
        k = j if off[j] > INTERVAL_TOL else max(0, int(np.argmax(np.abs(dev))) - 1)
        raise ConfigError(
            f"{tab.path}: column {m.time!r} ({role}) is not regularly sampled: the interval at {tab.where(k + 1)} is "
            f"{dt[k]:.6g} s ({t[k]:.9g} -> {t[k + 1]:.9g}) against a median of {med:.6g} s (allowed: within "
            f"{INTERVAL_TOL:.0%} of the period, no sample off the grid by {GRID_TOL:.0%} of it); pass "
            f"{m.label('resample')} to interpolate onto a regular grid")
    return period, float(np.max(np.abs(dev)))


def _stamps(n: int, period: float, snap_ok: bool = True) -> tuple[np.ndarray, float]:
    """Regular stamps [ns] from 0 and the period actually used [s]: a period estimated from a
    time column is snapped to the ns when that is harmless; a given rate is kept exact."""
    p_ns = period * 1e9
    snap = round(p_ns)
    if snap > 0 and (snap == p_ns or snap_ok and abs(snap - p_ns) * max(n - 1, 1) <= SNAP_TOL * p_ns):
        return np.arange(n, dtype=np.int64) * int(snap), snap / 1e9
    if p_ns < 1:
        raise ConfigError(f"sampling period {period!r} s is below 1 ns")
    return np.round(np.arange(n) * p_ns).astype(np.int64), period


HOLD_TOL = 1e-6
"""A joined file's sample counts as "at or before" a time within this fraction of its period
(stamps written in different units round differently)."""
PLAUSIBLE_RATE = (20.0, 1e6)
"""Sampling rates [Hz] of a servo record; a rate outside is warned about (a time column in ms read
as s gives a 1 kHz record 1 Hz)."""
_UNIT_IN_NAME = re.compile(r"[\[(]\s*(s|ms|us|µs|ns)\s*[\])]\s*$|[_ ](s|ms|us|ns)$", re.IGNORECASE)


def header_time_unit(tab: Table, col: str) -> str | None:
    """The unit a file's header gives its time column ``col``: its units row, or the name
    (``t [ms]``, ``time(us)``, ``time_ms``); None when it says none.

    >>> header_time_unit(Table(Path("x"), "", ["Time [ms]"], {}), "Time [ms]")
    'ms'
    """
    u = str(tab.units.get(col, "")).strip().strip("[]()").strip()
    if u in TIME_UNITS:
        return "us" if u == "µs" else u
    hit = _UNIT_IN_NAME.search(col)
    if hit:
        u = (hit.group(1) or hit.group(2)).lower()
        return "us" if u == "µs" else u
    return None


def _unit_of_time(tab: Table, col: str, given: str | None, where: str) -> tuple[str, str]:
    """``(unit, how it was decided)`` of a time column: the mapping's, else the header's, else s.
    A mapping contradicting the header is refused."""
    said = header_time_unit(tab, col)
    if given is not None:
        if said is not None and said != given:
            raise ConfigError(f"{tab.path}: the header gives time column {col!r} in {said}, {where} says {given}; "
                              f"give {where} {said} (or correct the header)")
        return given, "given"
    return (said, "from the file's header") if said else ("s", "default")


def _time_factor(tab: Table, m: Mapping) -> tuple[float, str]:
    """Factor to s of the primary time column and how it was decided (``--time-unit``, the
    header's unit, or ``--scale``)."""
    if m.time in m.scale:
        return _factor(tab, m, m.time)
    u, why = _unit_of_time(tab, m.time, m.time_unit, m.label("time_unit"))
    if u == "s":
        return 1.0, ""
    return TIME_UNITS[u], f"{TIME_UNITS[u]:g} ({u} -> s, {why})"


def _hz(rate: float) -> str:
    """A rate as people say it: ``250 Hz``, ``1 kHz``, ``2 MHz``."""
    for f, u in ((1e6, "MHz"), (1e3, "kHz")):
        if rate >= f * (1 - 1e-9):
            return f"{rate / f:.4g} {u}"
    return f"{rate:.4g} Hz"


def _rate_warning(tab: Table, m: Mapping, period: float, n: int) -> str | None:
    """A warning when the sampling rate is implausible for a servo record, with the time unit
    that would make it plausible."""
    rate, dur = 1.0 / period, (n - 1) * period
    lo, hi = PLAUSIBLE_RATE
    if lo <= rate <= hi:
        return None
    if m.time is None:
        return (f"{tab.path}: {m.label('rate')} {_hz(rate)} ({n} samples, {dur:.6g} s) is outside the rates of a "
                f"servo record ({_hz(lo)} to {_hz(hi)}): is it the right rate?")
    now = _time_factor(tab, m)[0]
    fits = sorted((abs(math.log10(rate * now / f / 2e3)), u, rate * now / f, dur * f / now)
                  for u, f in TIME_UNITS.items() if u != "µs" and f != now and lo <= rate * now / f <= hi)
    hint = " or ".join(f"in {u}, pass {m.label('time_unit')} {u} ({_hz(r)}, {d:.6g} s)" for _, u, r, d in fits[:2])
    unit_now = next((u for u, f in TIME_UNITS.items() if f == now), f"s x {now:g}")
    return (f"{tab.path}: time column {m.time!r} read in {unit_now} gives {_hz(rate)} over {dur:.6g} s ({n} "
            f"samples): implausible for a servo record ({_hz(lo)} to {_hz(hi)})"
            + (f"; if it is {hint}" if hint else "; check the time column and its unit"))


def _increasing(tab: Table, col: str, t: np.ndarray, label: str) -> None:
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if len(bad):
        i = int(bad[0])
        raise ConfigError(f"{tab.path}: column {col!r} ({label}) does not increase at {tab.where(i + 1)} "
                          f"({t[i]:.9g} then {t[i + 1]:.9g}); time must increase strictly (sort the rows, drop "
                          "repeated samples)")


def _cut(tab: Table, a: int, b: int) -> Table:
    """Rows ``a:b`` of a table (every column; the rows keep their lines / sample numbers)."""
    raw = {k: v[a:b] for k, v in tab._raw.items()}
    return Table(path=tab.path, format=tab.format, names=list(tab.names), scalars=dict(tab.scalars), _raw=raw,
                 _lines=None if tab._lines is None else tab._lines[a:b], header=tab.header, units=tab.units,
                 row_word=tab.row_word, first_row=tab.first_row + a, origin=dict(tab.origin))


def join(tab: Table, m: Mapping, joined, warns: list) -> tuple[Table, list]:
    """The primary table cut to the overlap of every time base, with the mapped columns of the
    joined files (``(Source, Table)`` pairs) interpolated at its times; ``warns`` gets one line
    per joined file (its rate, the primary's, the overlap). Returns the table and the
    provenance of the joined files.

    Refused: a time column not increasing, time bases without overlap, or whose spans differ by
    100x or more (time units that differ), a mapped column in no file or in several.
    """
    f, _ = _time_factor(tab, m)
    tp = tab.column(m.time, m.label("time"))
    _finite(tab, m.time, m.label("time"), tp)
    tp = tp * f
    _increasing(tab, m.time, tp, m.label("time"))
    bases = []
    cli = m.source == "command line"
    for i, (src, jt) in enumerate(joined):
        label = f"time of {jt.path.name}"
        tj = jt.column(src.time, label)
        _finite(jt, src.time, label, tj)
        u, _ = _unit_of_time(jt, src.time, src.time_unit, "--join-time-unit" if cli else f"sources[{i}].time_unit")
        tj = tj * TIME_UNITS[u] + src.time_offset
        _increasing(jt, src.time, tj, label)
        if len(tj) < 2:
            raise ConfigError(f"{jt.path}: {len(tj)} sample(s); a joined file needs at least 2")
        sp, sj = tp[-1] - tp[0], tj[-1] - tj[0]
        ratio = max(sp, sj) / max(min(sp, sj), 1e-300)
        span = (f"{tab.path.name}'s {m.time!r} spans {tp[0]:.6g} .. {tp[-1]:.6g} s, {jt.path.name}'s {src.time!r} "
                f"{tj[0]:.6g} .. {tj[-1]:.6g} s (in {u}{f', offset {src.time_offset:g} s' if src.time_offset else ''})")
        if ratio >= 100:
            raise ConfigError(f"{jt.path}: the time bases differ in span by x{ratio:.3g}: {span}: time units that "
                              f"differ? (give each file's time unit: {m.label('time_unit')}, "
                              f"{'--join-time-unit' if cli else 'sources[].time_unit'})")
        if tj[-1] < tp[0] or tj[0] > tp[-1]:
            raise ConfigError(f"{jt.path}: no overlap of the time bases: {span} (a clock offset? "
                              f"{'--join-offset' if cli else 'sources[].time_offset'})")
        bases.append((src, jt, tj, u))
    lo = max([tp[0]] + [b[2][0] for b in bases])
    hi = min([tp[-1]] + [b[2][-1] for b in bases])
    a, b = int(np.searchsorted(tp, lo, "left")), int(np.searchsorted(tp, hi, "right"))
    if b - a < 3:
        raise ConfigError(f"{tab.path}: {b - a} sample(s) of {m.time!r} within the overlap {lo:.6g} .. {hi:.6g} s "
                          "of the joined files; a record needs at least 3")
    out = _cut(tab, a, b)
    tq = tp[a:b]
    rate_p = 1.0 / float(np.median(np.diff(tp)))
    wanted = [c for c in [*m.roles().values(), *m.extra] if c not in tab._raw]
    info = []
    taken = {i: [] for i in range(len(bases))}
    for col in dict.fromkeys(wanted):
        hits = [(i, name) for i, (src, jt, _, _) in enumerate(bases)
                for name in (col, col[len(jt.path.stem) + 1:] if col.startswith(jt.path.stem + ".") else None)
                if name is not None and name in jt._raw]
        if not hits:
            continue                                      # prepare names the missing column with the files' columns
        if len({i for i, _ in hits}) > 1:
            files = " and ".join(bases[i][1].path.name for i, _ in hits)
            raise ConfigError(f"{m.source}: column {col!r} is in {files}: name it STEM.{col} (the file's name "
                              "without its suffix)")
        i, name = hits[0]
        src, jt, tj, _ = bases[i]
        v = jt.column(name, f"from {jt.path.name}")
        _finite(jt, name, f"from {jt.path.name}", v)
        if len(v) != len(tj):
            raise ConfigError(f"{jt.path}: column {name!r} has {len(v)} samples, its time {src.time!r} {len(tj)}")
        if src.method == "hold":                          # at or before: a stamp equal but for rounding counts
            tol = HOLD_TOL * float(np.median(np.diff(tj)))
            out._raw[col] = v[np.clip(np.searchsorted(tj, tq + tol, "right") - 1, 0, len(tj) - 1)]
        else:
            out._raw[col] = np.interp(tq, tj, v)
        out.names.append(col)
        rate_j = 1.0 / float(np.median(np.diff(tj)))
        out.origin[col] = (f"from {jt.path.name} at {_hz(rate_j)}, "
                           f"{'held' if src.method == 'hold' else 'linearly interpolated'} at the times of "
                           f"{tab.path.name}")
        taken[i].append(col)
    for i, (src, jt, tj, u) in enumerate(bases):
        rate_j = 1.0 / float(np.median(np.diff(tj)))
        cols = ", ".join(taken[i]) or "no mapped column"
        faster = (f"; it is faster than {tab.path.name}: its values are taken at the slower times without "
                  "anti-alias filtering (make the faster logger the primary file)" if rate_j > 1.5 * rate_p else "")
        warns.append(f"{jt.path}: joined at {_hz(rate_j)} onto the time base of {tab.path.name} ({_hz(rate_p)}): "
                     f"{cols} {'held' if src.method == 'hold' else 'linearly interpolated'} within the overlap "
                     f"{lo:.6g} .. {hi:.6g} s; {a + len(tp) - b} of {len(tp)} sample(s) of {tab.path.name} outside "
                     f"it dropped{faster}")
        info.append({"file": jt.path.name, "sha256": sha256(jt.path), "format": jt.format,
                     "time": f"{src.time} [{u}]" + (f" + {src.time_offset:g} s" if src.time_offset else ""),
                     "rate": rate_j, "method": src.method, "columns": taken[i],
                     "scalars": dict(jt.scalars)})
    for k, v in ((k, v) for src, jt, _, _ in bases for k, v in jt.scalars.items()):
        out.scalars.setdefault(k, v)
    return out, info


def prepare(tab: Table, m: Mapping, joined=()) -> Signals:
    """Select, scale, check and (if asked) resample the mapped columns of ``tab``; ``joined``:
    ``(Source, Table)`` pairs of the files joined on their time columns (:func:`join`)."""
    unit = _UNITS[m.units]
    roles = m.roles()
    warns = []
    join_info = []
    if joined:
        tab, join_info = join(tab, m, joined, warns)
    cols, how = {}, {}
    n = None
    for role, name in roles.items():
        raw = tab.column(name, m.label(role))
        if n is None:
            n, first = len(raw), (role, name)
        elif len(raw) != n:
            raise ConfigError(f"{tab.path}: column {name!r} ({m.label(role)}) has {len(raw)} samples, "
                              f"{first[1]!r} ({m.label(first[0])}) has {n}")
        _finite(tab, name, m.label(role), raw)
        f, txt = _time_factor(tab, m) if role == "time" else _factor(tab, m, name)
        cols[role] = raw * f if f != 1.0 else raw
        how[role] = (f"{name} * {txt}" if txt else name) + (f" ({tab.origin[name]})" if name in tab.origin else "")
        _within_limits(tab, name, m.label(role), role, cols[role], unit, txt)
    if m.command_includes_input:
        cols["command"] = cols["command"] - cols["input"]
        how["command"] = (f"({how['command']}) - ({how['input']}) (the command column holds the known external "
                          "force as well: it is on /stage/external_force)")
    extra = {}
    for name in m.extra:
        raw = tab.column(name, f"{m.label('extra')}")
        if len(raw) != n:
            raise ConfigError(f"{tab.path}: column {name!r} ({m.label('extra')}) has {len(raw)} samples, "
                              f"{first[1]!r} ({m.label(first[0])}) has {n}")
        extra[name] = raw
    if n < 3:
        raise ConfigError(f"{tab.path}: {n} sample(s); a record needs at least 3")

    resampled = None
    if m.time is not None:
        t = cols["time"]
        period, max_dev = _grid(tab, m, t)
        t0 = float(t[0])
        if m.resample:
            dt = np.diff(t)
            irregular = bool(np.max(np.abs(dt - period)) > INTERVAL_TOL * period)
            grid_p = 1.0 / m.resample_rate if m.resample_rate else float(np.median(dt))
            grid_p = max(round(grid_p * 1e9), 1) / 1e9        # the grid is ours to choose: whole ns
            tg = t0 + np.arange(int(math.floor((t[-1] - t0) / grid_p * (1 + 1e-12))) + 1) * grid_p
            if len(tg) < 3:
                raise ConfigError(f"{tab.path}: resampling at {1 / grid_p:g} Hz leaves {len(tg)} sample(s)")
            hold = np.clip(np.searchsorted(t, tg, "right") - 1, 0, len(t) - 1)
            for role in list(cols):
                if role == "time":
                    continue
                cols[role] = cols[role][hold] if role in ("command", "input") else np.interp(tg, t, cols[role])
            extra = {k: np.interp(tg, t, v) for k, v in extra.items()}
            resampled = {"from_samples": int(n), "to_samples": int(len(tg)), "period_s": grid_p,
                         "source_irregular": irregular,
                         "method": "linear interpolation of positions/velocities/extra columns; command and "
                                   "external force held from the last source sample at or before each grid time"}
            n, period, max_dev = len(tg), grid_p, 0.0
        stamps, period = _stamps(n, period)
        timing = (f"k * {period:.9g} s: the regular grid of {how['time']} (source time of sample 0: {t0:.9g} s; "
                  f"largest deviation of a source time from the grid {max_dev:.3g} s)")
    else:
        t0 = 0.0
        stamps, period = _stamps(n, 1.0 / m.rate, snap_ok=False)
        timing = f"k * {period:.9g} s (rate {m.rate:g} Hz given; the table has no time column)"
    rate_warning = _rate_warning(tab, m, period, n)
    if rate_warning:
        warns.append(rate_warning)

    x_ref = cols.get("reference")
    v_ref = None
    mapping = {}
    if x_ref is not None:
        mapping["/stage/reference.position"] = f"{how['reference']} [{unit['position']}]"
        if "reference_velocity" in cols:
            v_ref = cols["reference_velocity"]
            mapping["/stage/reference.velocity"] = f"{how['reference_velocity']} [{unit['velocity']}]"
        else:
            v_ref = np.gradient(x_ref, period)
            mapping["/stage/reference.velocity"] = (f"central difference of {roles['reference']} "
                                                    f"[{unit['velocity']}] (not in the source)")
    mapping["/stage/command.effort"] = f"{how['command']} [{unit['force']}]"
    mapping["/stage/measured.position"] = f"{how['measured']} [{unit['position']}]" + (
        f"; bearing: {how['bearing']} [{unit['position']}]" if "bearing" in cols else "")
    if "input" in cols:
        mapping["/stage/external_force.effort"] = f"{how['input']} [{unit['force']}]"
    if extra:
        mapping["/source/channels.position"] = ", ".join(
            f"{k} [{u}]" if u else k for k, u in m.extra.items()) + " (as in the file, unscaled)"
    mapping["stamps"] = timing
    run = {"source": "nanostage convert", "case": m.case or tab.path.stem, "trials": 1, "rate": 1.0 / period,
           "samples_per_trial": int(n), "axis": m.units, "open_loop": x_ref is None, "time_offset_s": t0}
    if resampled:
        run["resampled"] = resampled
    cfg = {"recording_contract": 1, "run": run,
           "command": {"kind": m.command_kind, "meaning": COMMAND_KINDS[m.command_kind]},
           "provenance": {"file": tab.path.name, "sha256": sha256(tab.path), "format": tab.format,
                          "scalars": dict(tab.scalars)},
           "mapping": mapping}
    if tab.header:
        cfg["provenance"]["header"] = list(tab.header)
    if join_info:
        cfg["provenance"]["joined"] = join_info
    if warns:
        cfg["warnings"] = list(warns)
    if x_ref is None:
        cfg["open_loop"] = ("no reference column: /stage/reference is not written; the recorded command drove "
                            "the plant (open-loop record)")
    if m.notes:
        cfg["notes"] = m.notes
    return Signals(stamp_ns=stamps, period=period, x_ref=x_ref, v_ref=v_ref, u=cols["command"],
                   y=cols["measured"], y_bearing=cols.get("bearing"), f_ext=cols.get("input"), extra=extra,
                   config=cfg, warnings=warns)


def sha256(path) -> str:
    """Hex SHA-256 of a file (the provenance of an imported recording)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# =========================================================================== writing
def write_signals(sig: Signals, out, overwrite: bool = False, node: str = "convert") -> Path:
    """Write :class:`Signals` as a contract recording of one trial
    (:func:`experiment_runner.core.recording.write_trials`); returns the MCAP file.

    Written whole in a temporary folder beside ``out`` and moved into place
    (:mod:`experiment_runner.core.outputs`); an existing recording at ``out`` is replaced only with
    ``overwrite`` (an :class:`~experiment_runner.core.outputs.OutputError` otherwise, nothing written).
    """
    import yaml

    series = []                             # (topic, names, {field: values}, every sample), in write order
    if sig.x_ref is not None:
        series.append((REFERENCE.name, (TABLE,), {"position": sig.x_ref, "velocity": sig.v_ref}, None))
    series.append((COMMAND.name, (MOTOR,), {"effort": sig.u}, None))
    if sig.y_bearing is not None:
        series.append((MEASURED.name, (TABLE, BEARING), {"position": np.column_stack([sig.y, sig.y_bearing])}, None))
    else:
        series.append((MEASURED.name, (TABLE,), {"position": sig.y}, None))
    if sig.f_ext is not None:
        series.append((EXTERNAL_FORCE.name, (TABLE,), {"effort": sig.f_ext}, None))
    if sig.extra:
        names = tuple(sig.extra)
        series.append((SOURCE_CHANNELS.name, names, {"position": np.column_stack([sig.extra[k] for k in names])},
                       None))
    write_trials(out, yaml.safe_dump(sig.config, sort_keys=False, allow_unicode=True),
                 [TrialSignals(np.asarray(sig.stamp_ns, dtype=np.int64), series)], case=sig.config["run"]["case"],
                 node=node, start_ns=int(sig.stamp_ns[0]), overwrite=overwrite, atomic=True)
    return bag_layout(out)[1]


def convert_table(path, mapping: Mapping | dict, out, overwrite: bool = False, source: str | None = None) -> Path:
    """Read ``path``, map it (``mapping``: :class:`Mapping` or its dict) and write the
    recording ``out`` (bag directory; ``NAME.mcap`` -> ``NAME/NAME.mcap``); returns the MCAP file.

    Raises :class:`~stage_sim.validation.ConfigError` (one line) on any bad input; nothing is
    written then.
    """
    m = mapping if isinstance(mapping, Mapping) else mapping_from_dict(mapping)
    check_recording(bag_layout(out)[0], overwrite)          # refused before any work
    tab = read_table(path, m.skip_rows)
    joined = [(src, read_table(src.file, src.skip_rows)) for src in m.sources]
    sig = prepare(tab, m, joined)
    if source:
        sig.config["run"]["source"] = source
    for w in sig.warnings:
        warnings.warn(w, ConfigWarning, stacklevel=2)
    return write_signals(sig, out, overwrite=overwrite)


def convert_emps(path, out, overwrite: bool = False) -> Path:
    """``nanostage convert emps``: an EMPS benchmark file with its shipped mapping --
    :data:`EMPS_MAPPING` for ``DATA_EMPS.mat``, :data:`EMPS_PULSES_MAPPING` for a file with
    ``pulses_N`` (``DATA_EMPS_PULSES.mat``: the pulses go to ``/stage/external_force``, see the
    mapping); returns the MCAP file.

    ``DATA_EMPS.mat`` (README): ``/stage/reference`` position ``qg`` and velocity (not in the
    source: central difference of ``qg``, said so in ``/experiment/config``), ``/stage/command``
    effort ``gtau * vir`` [N], ``/stage/measured`` position ``qm``, and the drive voltage ``vir``
    [V] as logged on ``/source/channels``. Stamps are ``k * 1 ms`` (the mean period; the logged
    times jitter by ~2e-8 s around it); ``gtau``, ``kp``, ``kv`` are in the config
    (``provenance.scalars``). One trial."""
    mapping = EMPS_PULSES_MAPPING if "pulses_N" in read_table(path).names else EMPS_MAPPING
    return convert_table(path, load_mapping(mapping), out, overwrite=overwrite, source="nanostage convert emps")


# =========================================================================== command line
_FLAGS = {"time": "COL", "rate": "HZ", "reference": "COL", "reference_velocity": "COL", "command": "COL",
          "measured": "COL", "bearing": "COL", "input": "COL"}
_HELP = {"time": "column of the sample times [s after --scale]",
         "rate": "sampling rate [Hz] of a table without a time column",
         "reference": "column of the reference position (omit for an open-loop record)",
         "reference_velocity": "column of the reference velocity (default: central difference of the reference)",
         "command": "column of the drive command (force; torque with --units rotary)",
         "measured": "column of the measured position",
         "bearing": "column of a bearing displacement sensor, if any",
         "input": "column of a known external force on the table (-> /stage/external_force)"}


def add_convert_arguments(parser):
    sub = parser.add_subparsers(dest="kind", required=True, metavar="KIND")
    p = sub.add_parser(
        "table", help="a CSV/TSV/whitespace text, JSON, MATLAB .mat (v5, v7.3), HDF5, .npz/.npy table",
        description="Map a table's columns onto the recording contract: "
                    "nanostage convert table FILE --time COL --reference COL --command COL --measured COL "
                    "[--input COL] [--scale COL=FACTOR] [--units linear|rotary] [--command-kind drive|measured] "
                    "--out REC.mcap. "
                    "Values are multiplied by their --scale into SI (m, N; rad, N·m with --units rotary). "
                    "Samples must be regular (any rate) unless --resample. A table without --reference is an "
                    "open-loop record. A second logger's file joins on its time column (--join FILE --join-time "
                    "COL). Bad input: one line on stderr, exit 2, nothing written; warnings (an implausible rate, "
                    "a join) on stderr.")
    p.add_argument("source", metavar="FILE", help="the table (format recognised from its content)")
    p.add_argument("--mapping", metavar="YAML", help="mapping file (keys: " + ", ".join(_KEYS)
                   + "); flags given as well override its keys")
    for k, meta in _FLAGS.items():
        p.add_argument(f"--{k.replace('_', '-')}", dest=f"map_{k}", metavar=meta, help=_HELP[k])
    p.add_argument("--time-unit", metavar="s|ms|us|ns", help="unit of the time column (default: the header's, "
                   "e.g. 'Time [ms]' or a units row, else s)")
    p.add_argument("--skip-rows", metavar="N", help="lines of a text file not to read (a logger's preamble); the "
                   "next line is the header. Default: every line above the first two lines of numbers is header")
    p.add_argument("--scale", action="append", default=[], metavar="COL=FACTOR",
                   help="multiply a column by FACTOR (a number, a scalar of the file such as a gain, or a product "
                        "of them: gtau*1.014) to get SI; repeatable")
    p.add_argument("--units", metavar="linear|rotary", help="linear (m, N; default) or rotary (rad, N·m)")
    p.add_argument("--command-kind", metavar="drive|measured",
                   help="what --command is: drive (default: a command to a drive with a force constant; the force "
                        "applied may differ by its ratio, delay, saturation) or measured (the force applied, "
                        "measured: a load cell, a drive's force estimate)")
    p.add_argument("--command-includes-input", action="store_true", default=None,
                   help="the command column holds the --input force as well (a test signal added to the drive "
                        "input): the command written is command - input")
    p.add_argument("--join", action="append", default=[], metavar="FILE",
                   help="a second logger's file, joined on its time column: its mapped columns are interpolated "
                        "at this file's times within the overlap; STEM.COL names its column COL where this file "
                        "has one of that name too; repeatable")
    p.add_argument("--join-time", action="append", default=[], metavar="COL",
                   help="time column of the --join file (one for all, or one per --join)")
    p.add_argument("--join-time-unit", action="append", default=[], metavar="s|ms|us|ns",
                   help="unit of the --join file's time column (default: its header's, else s)")
    p.add_argument("--join-skip-rows", action="append", default=[], metavar="N", help="--skip-rows of the --join file")
    p.add_argument("--join-method", action="append", default=[], metavar="linear|hold",
                   help="linear (default: a sampled signal) or hold (the last value at or before each time: a "
                        "held command)")
    p.add_argument("--join-offset", action="append", default=[], metavar="S",
                   help="seconds added to the --join file's times to put them on this file's clock")
    p.add_argument("--extra", action="append", default=[], metavar="COL[=UNIT]",
                   help="keep a further column as it is, on /source/channels; repeatable")
    p.add_argument("--resample", nargs="?", const=True, default=None, metavar="HZ",
                   help="interpolate irregular samples onto a regular grid (of HZ, default the median interval)")
    p.add_argument("--case", help="case name of the trial (default: the file's name)")
    p.add_argument("--list", action="store_true", help="list the file's columns (with units where a header row "
                   "gives them), scalars and header lines, and exit")
    p.add_argument("--out", metavar="REC.mcap", help="recording to write (bag directory; NAME.mcap -> NAME/NAME.mcap)")
    add_overwrite_argument(p)
    p = sub.add_parser("emps", help="an EMPS benchmark file: DATA_EMPS.mat (mappings/emps.yaml) or "
                                    "DATA_EMPS_PULSES.mat (mappings/emps_pulses.yaml: the force pulses on "
                                    "/stage/external_force)")
    p.add_argument("source", metavar="FILE", help="DATA_EMPS.mat or DATA_EMPS_PULSES.mat")
    p.add_argument("--out", required=True, metavar="REC.mcap", help="recording to write")
    add_overwrite_argument(p)
    add_convert_nominal_arguments(sub.add_parser(
        "nominal", help="a recording's nominal_model block (/experiment/config) as a preset YAML",
        description="Translate the nominal_model block of a recording's /experiment/config (plant, PID, Ts, "
                    "quantization in the rig's own terms) into the equivalent nanostage preset "
                    "(experiment_runner.core.nominal_model), e.g. to inspect or edit it before "
                    "nanostage diagnose REC preset.yaml."))
    return parser


_JOIN_FLAGS = {"time": "join_time", "time_unit": "join_time_unit", "skip_rows": "join_skip_rows",
               "method": "join_method", "time_offset": "join_offset"}


def _flags(args) -> dict:
    import os
    d = {k: getattr(args, f"map_{k}") for k in _FLAGS if getattr(args, f"map_{k}") is not None}
    for item in args.scale:
        col, eq, fac = item.rpartition("=")
        if not eq or not col or not fac:
            raise ConfigError(f"command line: --scale {item!r}: expected COL=FACTOR (e.g. x=1e-6, or vir=gtau "
                              "with a scalar of the file)")
        d.setdefault("scale", {})[col] = fac
    for k in ("units", "time_unit", "skip_rows", "command_kind", "command_includes_input"):
        if getattr(args, k) is not None:
            d[k] = getattr(args, k)
    if args.join:
        d["sources"] = [{"file": os.path.abspath(f)} for f in args.join]
        for key, attr in _JOIN_FLAGS.items():
            given = getattr(args, attr)
            flag = f"--{attr.replace('_', '-')}"
            if len(given) not in (0, 1, len(args.join)):
                raise ConfigError(f"command line: {len(given)} {flag} for {len(args.join)} --join: give one for "
                                  "all, or one per --join")
            for i, src in enumerate(d["sources"]):
                if given:
                    src[key] = given[i if len(given) > 1 else 0]
        if "time" not in d["sources"][0]:
            raise ConfigError("command line: --join needs --join-time (the joined file's time column)")
    else:
        extra = [f"--{a.replace('_', '-')}" for a in _JOIN_FLAGS.values() if getattr(args, a)]
        if extra:
            raise ConfigError(f"command line: {', '.join(extra)} without --join")
    if args.extra:
        d["extra"] = {}
        for item in args.extra:
            col, _, u = item.partition("=")
            d["extra"][col] = u
    if args.resample is not None:
        d["resample"] = True
        if args.resample is not True:
            d["resample_rate"] = args.resample
    if args.case is not None:
        d["case"] = args.case
    return d


def _summary(path: Path) -> str:
    """The line ``convert`` prints: what the recording holds and where the columns went."""
    rec = read_recording(path, require_reference=False)
    rate = 1.0 / float(np.median(np.diff(rec.stamp_ns)) * 1e-9)
    kind = ("open-loop record (no reference column: /stage/reference not written; the recorded command drove "
            "the plant)" if rec.open_loop else "closed-loop record")
    cfg = rec.config_doc()
    line = (f"{path}: {len(rec)} samples at {rate:.6g} Hz, {rec.duration:.6g} s, {rec.axis} axis, {kind}, "
            f"command: {rec.command_kind}")
    force = cfg.get("mapping", {}).get("/stage/external_force.effort")
    if force:
        line += f"\n  known external force on /stage/external_force: {force}"
    for j in cfg.get("provenance", {}).get("joined", []):
        line += f"\n  joined {j['file']} ({', '.join(j['columns']) or 'no column'}, {j['method']})"
    return line


def main_convert(args) -> int:
    if args.kind == "nominal":
        return main_convert_nominal(args)
    if args.kind == "emps":
        print(_summary(convert_emps(args.source, args.out, overwrite=args.overwrite)))
        return 0
    if args.list:
        skip = _count(args.skip_rows, "command line: --skip-rows") if args.skip_rows is not None else None
        print(read_table(args.source, skip).describe())
        return 0
    flags = _flags(args)
    m = load_mapping(args.mapping, flags) if args.mapping else mapping_from_dict(flags, "command line")
    if not args.out:
        raise ConfigError("command line: --out is required (the recording to write)")
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always", ConfigWarning)
        path = convert_table(args.source, m, args.out, overwrite=args.overwrite)
    for w in got:
        if issubclass(w.category, ConfigWarning):
            print(f"warning: {w.message}", file=sys.stderr)
        else:
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
    print(_summary(path))
    return 0
