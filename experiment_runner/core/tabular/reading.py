"""Reading a table file of any supported format into a :class:`Table`."""
from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from stage_sim.validation import ConfigError, input_file_problem, read_text_file


_TEXT_DELIMS = ("\t", ";", ",")
MAX_TEXT_BYTES = 512 << 20
"""Largest text or JSON table read [bytes] (a 10 kHz, 5-column log of 15 minutes is ~400 MB)."""
MAX_HEADER_LINES = 50
"""Header lines above a text table's names kept in the recording's provenance (200 characters each)."""

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


