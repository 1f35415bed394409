"""Import any tabular record of a positioning axis as a contract recording (``nanostage convert``).

A user's rig logs to whatever its software writes: a CSV or whitespace table, a MATLAB file
(v5, or v7.3 which is HDF5), a NumPy archive. :func:`convert_table` maps its columns onto the
recording contract (``shared/contract/recording.md``) and writes a recording that
:func:`~experiment_runner.recording.read_recording` and ``nanostage diagnose`` take::

    nanostage convert table run.csv --time t --reference x_ref --command u --measured x \\
        --scale x=1e-6 --out run.mcap

Reading (:func:`read_table`)
    The format is recognised from the file's first bytes, not its name: MATLAB v5
    (``scipy.io.loadmat``), HDF5 -- MATLAB v7.3 or any ``.h5`` (``h5py``; MATLAB's
    column-major datasets are transposed back), NumPy ``.npz`` / ``.npy``, else text. Text:
    comma-, semicolon-, tab- or whitespace-separated (from the first data line); lines
    starting with ``#`` or ``%`` are comments; the header is the first line if it is not
    numeric, else the last comment line above the data when it has one name per column
    (``numpy.savetxt(header=...)`` writes it so), else the columns are named ``1``, ``2``, ...
    A variable that is a vector is a column of its name; a matrix gives one column per
    column, ``NAME:1``, ``NAME:2``, ... (1-based; its longer side is the samples); MATLAB
    structs and HDF5 groups give ``outer.inner``; a one-element variable is a *scalar*,
    usable as a scale factor (``--scale vir=gtau``). ``nanostage convert table FILE --list``
    prints them.

Mapping (:class:`Mapping`, from flags or a YAML file, :func:`load_mapping`)
    ``time`` (a column, in s after its scale; or ``rate`` in Hz for a table without one),
    ``reference`` (optional: without it the record is *open-loop* -- no ``/stage/reference``
    is written, ``run.open_loop`` says so, and readers take it only when asked, see
    :func:`~experiment_runner.recording.read_recording`), ``reference_velocity`` (else the
    central difference of the reference, said so in the config), ``command``, ``measured``,
    ``bearing`` (a bearing displacement sensor), ``input`` (a known external force, written
    to ``/stage/external_force``), ``scale`` (column -> factor: a number or a scalar of the
    file; values are multiplied into SI), ``units`` (``linear``: m, N; ``rotary``: rad, N·m),
    ``extra`` (columns kept as they are on ``/source/channels``, with their units),
    ``resample``, ``case``, ``notes`` (free text carried into ``/experiment/config``).

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
    the period), and the config records it.

Output
    One trial (``trial_start``/``trial_end`` around the record). The recording is written to
    a temporary directory beside ``out`` and moved into place only when complete: a failed
    or interrupted conversion leaves no partial recording (and an existing one is replaced
    only with ``overwrite``). Every bad input is a :class:`~stage_sim.validation.ConfigError`
    of one line naming the file, the column or key, the value and what is allowed (the CLI
    prints it and exits 2).

``convert emps`` is this importer with the shipped mapping ``mappings/emps.yaml``
(:data:`EMPS_MAPPING`): the EMPS benchmark's arrays, the drive gain as the command's scale,
and its drive voltage ``vir`` kept on ``/source/channels``.
"""
from __future__ import annotations

import csv
import hashlib
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stage_sim.validation import ConfigError, input_file_problem

__all__ = ["Table", "read_table", "Mapping", "load_mapping", "mapping_from_dict", "Signals", "prepare",
           "convert_table", "convert_emps", "sha256", "EMPS_MAPPING", "add_convert_arguments", "main_convert"]

EMPS_MAPPING = Path(__file__).with_name("mappings") / "emps.yaml"
"""The mapping of the EMPS benchmark's ``DATA_EMPS.mat`` (``nanostage convert emps``)."""

INTERVAL_TOL = 0.05
"""A sample interval may differ from the mean period by this fraction (logger jitter)."""
GRID_TOL = 0.25
"""... and a sample lie this fraction of a period off the regular grid."""
SNAP_TOL = 0.01
"""The period is rounded to the ns when that moves no stamp by more than this fraction of it."""

_TEXT_DELIMS = ("\t", ";", ",")


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

    def where(self, row: int) -> str:
        """A row as the user finds it: the file's line (text) or the sample index (arrays)."""
        return f"line {int(self._lines[row])}" if self._lines is not None else f"sample {row}"

    def describe(self) -> str:
        """Columns (with their length) and scalars, one line each group."""
        cols = ", ".join(self.names) or "none"
        sc = ", ".join(f"{k} = {v:.6g}" for k, v in self.scalars.items()) or "none"
        return f"{self.path}: {self.format}\n  columns: {cols}\n  scalars: {sc}"

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
                        raise ConfigError(f"{self.path}: column {name!r} ({role}) {self.where(i)}: {shown} is not "
                                          "a number") from None
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


def read_table(path) -> Table:
    """Read a tabular file (text, MATLAB v5/v7.3, HDF5, NPZ/NPY) into a :class:`Table`.

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
    reader = {"hdf5": _read_hdf5, "mat": _read_mat, "npz": _read_npz, "npy": _read_npy, "text": _read_text}[kind]
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


def _read_text(path: Path) -> Table:
    data = path.read_bytes()
    if b"\x00" in data[:4096]:
        raise ConfigError(f"{path}: binary file of an unknown format (text, MATLAB .mat, HDF5, .npz or .npy "
                          "expected)")
    text = data.decode("utf-8-sig", errors="strict") if _utf8(data) else data.decode("latin-1")
    comment, rows, lines = None, [], []
    delim = None
    for no, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s:
            continue
        if s[0] in "#%":
            if not rows:
                comment = s.lstrip("#% \t")
            continue
        if delim is None:
            delim = next((d for d in _TEXT_DELIMS if d in s), " ")
        if delim == " ":
            fields = s.split()
        else:
            fields = [x.strip() for x in next(csv.reader(io.StringIO(s), delimiter=delim))]
        rows.append(fields)
        lines.append(no)
    if not rows:
        raise ConfigError(f"{path}: no data rows (a text table needs at least a row of numbers)")
    names = None
    if not all(_is_number(x) for x in rows[0]):
        names, rows, lines = rows[0], rows[1:], lines[1:]
    elif comment is not None:
        c = comment.split() if delim == " " else [x.strip() for x in next(csv.reader(io.StringIO(comment),
                                                                                       delimiter=delim))]
        if len(c) == len(rows[0]) and not all(_is_number(x) for x in c):
            names = c
    ncol = len(names) if names is not None else len(rows[0])
    if names is None:
        names = [str(j + 1) for j in range(ncol)]
    names = [n if n else str(j + 1) for j, n in enumerate(names)]
    seen = {}
    for j, n in enumerate(names):
        if n in seen:
            raise ConfigError(f"{path}: the header names column {n!r} twice (columns {seen[n] + 1} and {j + 1})")
        seen[n] = j
    if not rows:
        raise ConfigError(f"{path}: a header ({', '.join(names)}) but no data rows")
    for i, r in enumerate(rows):
        if len(r) != ncol:
            raise ConfigError(f"{path}: line {lines[i]} has {len(r)} fields, expected {ncol} "
                              f"({', '.join(names)})")
    cols = list(zip(*rows))
    raw = {n: list(cols[j]) for j, n in enumerate(names)}
    sep = {"\t": "tab", ";": "semicolon", ",": "comma", " ": "whitespace"}[delim]
    return Table(path=path, format=f"text table ({sep}-separated, {len(rows)} rows)", names=names, scalars={},
                 _raw=raw, _lines=np.asarray(lines))


def _utf8(data: bytes) -> bool:
    try:
        data.decode("utf-8-sig")
        return True
    except UnicodeDecodeError:
        return False


# =========================================================================== mapping
_ROLES = ("time", "reference", "reference_velocity", "command", "measured", "bearing", "input")
_UNITS = {"linear": {"position": "m", "velocity": "m/s", "force": "N"},
          "rotary": {"position": "rad", "velocity": "rad/s", "force": "N·m"}}
_KEYS = (*_ROLES, "rate", "scale", "units", "extra", "resample", "resample_rate", "case", "notes")


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
    scale: dict = field(default_factory=dict)          # column -> float or scalar name
    units: str = "linear"
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


def mapping_from_dict(data: dict, source: str = "mapping") -> Mapping:
    """Validate a mapping (the YAML file's content, or the flags); ``ConfigError`` of one line."""
    cli = source == "command line"

    def lab(k):
        return f"--{k.replace('_', '-')}" if cli else k

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
            pass                                        # a scalar's name, resolved against the file
        if isinstance(fac, float) and not (math.isfinite(fac) and fac != 0):
            raise ConfigError(f"{where('scale')}: {col}: got {fac!r}; expected a finite non-zero factor")
        sc[str(col)] = fac
    used = set(kw.get(r) for r in _ROLES)
    for col in sc:
        if col not in used:
            raise ConfigError(f"{where('scale')}: {col!r} is not one of the mapped columns "
                              f"({', '.join(sorted(c for c in used if c))})")
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
    from stage_sim.config import read_yaml_file
    data, path = read_yaml_file(path, EMPS_MAPPING.parent, "mapping")
    data = dict(data)
    source = str(path)
    if overrides:
        data.update(overrides)
        source = f"{path} with the command line's flags"
    return mapping_from_dict(data, source)


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


def _finite(tab: Table, name: str, role: str, a: np.ndarray) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        i = int(np.argmax(bad))
        raise ConfigError(f"{tab.path}: column {name!r} ({role}) has {int(bad.sum())} non-finite value(s), the "
                          f"first at {tab.where(i)} ({float(a[i])}); fill or cut them before converting")


_FIELDS = {"reference": "position", "reference_velocity": "velocity", "command": "effort", "measured": "position",
           "bearing": "position", "input": "effort"}
"""The JointState field each role's column becomes (for :data:`experiment_runner.recording.LIMITS`)."""
MAX_TIME = 9e9
"""Largest sample time [s] a recording can stamp (int64 nanoseconds reach 9.2e9 s)."""


def _within_limits(tab: Table, name: str, label: str, role: str, a: np.ndarray, unit: dict, scaled: str) -> None:
    """Refuse values a recording cannot hold: beyond :data:`~experiment_runner.recording.LIMITS`
    (the reader's rule of damage: absurd for any stage, a wrong scale or a corrupt value), or a
    time beyond :data:`MAX_TIME`."""
    from experiment_runner.recording import LIMITS, beyond_limits
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
    f = m.scale.get(col, 1.0)
    if isinstance(f, str):
        if f not in tab.scalars:
            sc = ", ".join(tab.scalars) or "none"
            raise ConfigError(f"{m.source}: {m.label('scale')} {col}={f}: {f!r} is neither a number nor a scalar "
                              f"of {tab.path} (scalars: {sc})")
        v = tab.scalars[f]
        if not (math.isfinite(v) and v != 0):
            raise ConfigError(f"{tab.path}: scalar {f!r} = {v!r} cannot scale {col!r} (finite, non-zero needed)")
        return v, f"{f} = {v:.6g}"
    return f, (f"{f:g}" if f != 1.0 else "")


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


def prepare(tab: Table, m: Mapping) -> Signals:
    """Select, scale, check and (if asked) resample the mapped columns of ``tab``."""
    unit = _UNITS[m.units]
    roles = m.roles()
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
        f, txt = _factor(tab, m, name)
        cols[role] = raw * f if f != 1.0 else raw
        how[role] = f"{name} * {txt}" if txt else name
        _within_limits(tab, name, m.label(role), role, cols[role], unit, txt)
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
           "provenance": {"file": tab.path.name, "sha256": sha256(tab.path), "format": tab.format,
                          "scalars": dict(tab.scalars)},
           "mapping": mapping}
    if x_ref is None:
        cfg["open_loop"] = ("no reference column: /stage/reference is not written; the recorded command drove "
                            "the plant (open-loop record)")
    if m.notes:
        cfg["notes"] = m.notes
    return Signals(stamp_ns=stamps, period=period, x_ref=x_ref, v_ref=v_ref, u=cols["command"],
                   y=cols["measured"], y_bearing=cols.get("bearing"), f_ext=cols.get("input"), extra=extra,
                   config=cfg)


def sha256(path) -> str:
    """Hex SHA-256 of a file (the provenance of an imported recording)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# =========================================================================== writing
def write_signals(sig: Signals, out, overwrite: bool = False, node: str = "convert") -> Path:
    """Write :class:`Signals` as a contract recording; returns the MCAP file.

    Written whole in a temporary folder beside ``out`` and moved into place
    (:mod:`experiment_runner.outputs`); an existing recording at ``out`` is replaced only with
    ``overwrite`` (an :class:`~experiment_runner.outputs.OutputError` otherwise, nothing written).
    """
    import yaml

    from experiment_runner.recording import McapRecorder, _typestore, bag_layout
    from msg_defs import cdr, convert
    from msg_defs.topics import (BEARING, COMMAND, EVENTS, EXTERNAL_FORCE, MEASURED, MOTOR, REFERENCE,
                                 SOURCE_CHANNELS, TABLE)
    ts = _typestore()
    case = sig.config["run"]["case"]
    st = sig.stamp_ns
    # per-sample topics: (topic, names, {field: (n, len(names)) values}), in write order
    per_sample = []
    if sig.x_ref is not None:
        per_sample.append((REFERENCE.name, (TABLE,), {"position": sig.x_ref[:, None],
                                                      "velocity": sig.v_ref[:, None]}))
    per_sample.append((COMMAND.name, (MOTOR,), {"effort": sig.u[:, None]}))
    if sig.y_bearing is not None:
        per_sample.append((MEASURED.name, (TABLE, BEARING),
                           {"position": np.column_stack([sig.y, sig.y_bearing])}))
    else:
        per_sample.append((MEASURED.name, (TABLE,), {"position": sig.y[:, None]}))
    if sig.f_ext is not None:
        per_sample.append((EXTERNAL_FORCE.name, (TABLE,), {"effort": sig.f_ext[:, None]}))
    if sig.extra:
        names = tuple(sig.extra)
        per_sample.append((SOURCE_CHANNELS.name, names,
                           {"position": np.column_stack([sig.extra[k] for k in names])}))
    per_sample = [(topic, names, cdr.JointStateWriter(), {f: v.tolist() for f, v in fields.items()})
                  for topic, names, fields in per_sample]
    with McapRecorder(out, yaml.safe_dump(sig.config, sort_keys=False, allow_unicode=True),
                      start_ns=int(st[0]), overwrite=overwrite, atomic=True) as rec:
        w = rec.write
        s0, s1 = int(st[0]), int(st[-1])
        w(EVENTS.name, s0, convert.event_msg(ts, "run_start", stamp_ns=s0, case=case, node=node))
        w(EVENTS.name, s0, convert.event_msg(ts, "trial_start", stamp_ns=s0, trial=0, case=case, node=node))
        for i, s in enumerate(st.tolist()):
            for topic, names, writer, fields in per_sample:
                w(topic, s, writer.pack(s, names, **{f: v[i] for f, v in fields.items()}))
        w(EVENTS.name, s1, convert.event_msg(ts, "trial_end", stamp_ns=s1, trial=0, case=case, node=node))
        w(EVENTS.name, s1, convert.event_msg(ts, "run_end", stamp_ns=s1, case=case, node=node))
    return bag_layout(out)[1]


def convert_table(path, mapping: Mapping | dict, out, overwrite: bool = False, source: str | None = None) -> Path:
    """Read ``path``, map it (``mapping``: :class:`Mapping` or its dict) and write the
    recording ``out`` (bag directory; ``NAME.mcap`` -> ``NAME/NAME.mcap``); returns the MCAP file.

    Raises :class:`~stage_sim.validation.ConfigError` (one line) on any bad input; nothing is
    written then.
    """
    from experiment_runner.outputs import check_recording
    from experiment_runner.recording import bag_layout
    m = mapping if isinstance(mapping, Mapping) else mapping_from_dict(mapping)
    check_recording(bag_layout(out)[0], overwrite)          # refused before any work
    tab = read_table(path)
    sig = prepare(tab, m)
    if source:
        sig.config["run"]["source"] = source
    return write_signals(sig, out, overwrite=overwrite)


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


def convert_emps(mat_path, out, overwrite: bool = True) -> Path:
    """Write ``DATA_EMPS.mat`` as a contract recording; returns the MCAP file.

    The table importer (:func:`convert_table`) with the shipped
    mapping :data:`EMPS_MAPPING` (README): ``/stage/reference``
    position ``qg`` and velocity (not in the source: central difference of ``qg``, said so in
    ``/experiment/config``), ``/stage/command`` effort ``gtau * vir`` [N], ``/stage/measured``
    position ``qm``, and the drive voltage ``vir`` [V] as logged on ``/source/channels``.
    Stamps are ``k * 1 ms`` (the mean period; the logged times jitter by ~2e-8 s around it);
    ``gtau``, ``kp``, ``kv`` are in the config (``provenance.scalars``). One trial.
    """
    return convert_table(mat_path, load_mapping(EMPS_MAPPING), out, overwrite=overwrite,
                         source="nanostage convert emps")


def add_convert_arguments(parser):
    from experiment_runner.outputs import add_overwrite_argument
    sub = parser.add_subparsers(dest="kind", required=True, metavar="KIND")
    p = sub.add_parser(
        "table", help="a CSV/TSV/whitespace text, MATLAB .mat (v5, v7.3), HDF5, .npz/.npy table",
        description="Map a table's columns onto the recording contract: "
                    "nanostage convert table FILE --time COL --reference COL --command COL --measured COL "
                    "[--input COL] [--scale COL=FACTOR] [--units linear|rotary] --out REC.mcap. "
                    "Values are multiplied by their --scale into SI (m, N; rad, N·m with --units rotary). "
                    "Samples must be regular (any rate) unless --resample. A table without --reference is an "
                    "open-loop record. Bad input: one line on stderr, exit 2, nothing written.")
    p.add_argument("source", metavar="FILE", help="the table (format recognised from its content)")
    p.add_argument("--mapping", metavar="YAML", help="mapping file (keys: time or rate, reference, "
                   "reference_velocity, command, measured, bearing, input, scale, units, extra, resample, "
                   "resample_rate, case, notes); flags given as well override its keys")
    for k, meta in _FLAGS.items():
        p.add_argument(f"--{k.replace('_', '-')}", dest=f"map_{k}", metavar=meta, help=_HELP[k])
    p.add_argument("--scale", action="append", default=[], metavar="COL=FACTOR",
                   help="multiply a column by FACTOR (a number, or a scalar of the file such as a gain) "
                        "to get SI; repeatable")
    p.add_argument("--units", metavar="linear|rotary", help="linear (m, N; default) or rotary (rad, N·m)")
    p.add_argument("--extra", action="append", default=[], metavar="COL[=UNIT]",
                   help="keep a further column as it is, on /source/channels; repeatable")
    p.add_argument("--resample", nargs="?", const=True, default=None, metavar="HZ",
                   help="interpolate irregular samples onto a regular grid (of HZ, default the median interval)")
    p.add_argument("--case", help="case name of the trial (default: the file's name)")
    p.add_argument("--list", action="store_true", help="list the file's columns and scalars, and exit")
    p.add_argument("--out", metavar="REC.mcap", help="recording to write (bag directory; NAME.mcap -> NAME/NAME.mcap)")
    add_overwrite_argument(p)
    p = sub.add_parser("emps", help="DATA_EMPS.mat of the EMPS benchmark (the table importer with mappings/emps.yaml)")
    p.add_argument("source", metavar="FILE", help="DATA_EMPS.mat")
    p.add_argument("--out", required=True, metavar="REC.mcap", help="recording to write")
    add_overwrite_argument(p)
    from experiment_runner.nominal_model import add_convert_nominal_arguments
    add_convert_nominal_arguments(sub.add_parser(
        "nominal", help="a recording's nominal_model block (/experiment/config) as a preset YAML",
        description="Translate the nominal_model block of a recording's /experiment/config (plant, PID, Ts, "
                    "quantization in the rig's own terms) into the equivalent nanostage preset "
                    "(experiment_runner.nominal_model), e.g. to inspect or edit it before "
                    "nanostage diagnose REC preset.yaml."))
    return parser


def _flags(args) -> dict:
    d = {k: getattr(args, f"map_{k}") for k in _FLAGS if getattr(args, f"map_{k}") is not None}
    for item in args.scale:
        col, eq, fac = item.rpartition("=")
        if not eq or not col or not fac:
            raise ConfigError(f"command line: --scale {item!r}: expected COL=FACTOR (e.g. x=1e-6, or vir=gtau "
                              "with a scalar of the file)")
        d.setdefault("scale", {})[col] = fac
    if args.units is not None:
        d["units"] = args.units
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


def main_convert(args) -> int:
    if args.kind == "nominal":
        from experiment_runner.nominal_model import main_convert_nominal
        return main_convert_nominal(args)
    if args.kind == "emps":
        print(convert_emps(args.source, args.out, overwrite=args.overwrite))
        return 0
    if args.list:
        print(read_table(args.source).describe())
        return 0
    flags = _flags(args)
    m = load_mapping(args.mapping, flags) if args.mapping else mapping_from_dict(flags, "command line")
    if not args.out:
        raise ConfigError("command line: --out is required (the recording to write)")
    path = convert_table(args.source, m, args.out, overwrite=args.overwrite)
    from experiment_runner.recording import read_recording
    rec = read_recording(path, require_reference=False)
    rate = 1.0 / float(np.median(np.diff(rec.stamp_ns)) * 1e-9)
    kind = ("open-loop record (no reference column: /stage/reference not written; the recorded command drove "
            "the plant)" if rec.open_loop else "closed-loop record")
    print(f"{path}: {len(rec)} samples at {rate:.6g} Hz, {rec.duration:.6g} s, {rec.axis} axis, {kind}"
          + (", with a known external force" if rec.external_force is not None else ""))
    return 0
