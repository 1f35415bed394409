"""The mapping of a table's columns onto the recording contract (:class:`Mapping`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from msg_defs.topics import COMMAND_KINDS
from stage_sim.config import read_yaml_file
from stage_sim.validation import ConfigError


EMPS_MAPPING = Path(__file__).parent.with_name("mappings") / "emps.yaml"
"""The mapping of the EMPS benchmark's ``DATA_EMPS.mat`` (``nanostage convert emps``)."""
EMPS_PULSES_MAPPING = EMPS_MAPPING.with_name("emps_pulses.yaml")
"""... and of its validation record with force pulses, ``DATA_EMPS_PULSES.mat``."""
_ROLES = ("time", "reference", "reference_velocity", "command", "measured", "bearing", "input")
AXIS_UNITS = {"linear": {"position": "m", "velocity": "m/s", "force": "N"},
              "rotary": {"position": "rad", "velocity": "rad/s", "force": "N·m"}}
"""SI units of a recording's signals per kind of axis (a mapping's ``units``)."""
MAPPING_KEYS = (*_ROLES, "rate", "time_unit", "skip_rows", "scale", "units", "command_kind", "command_includes_input",
                "sources", "extra", "resample", "resample_rate", "case", "notes")
"""The keys a mapping file may have (any other is refused, naming these)."""
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


def count_value(v, where: str) -> int:
    """A count of lines (``skip_rows``) from a mapping file or the command line, checked.

    Parameters
    ----------
    v : int or str
        The value as given.
    where : str
        Where it was given (file and field, or the option), for the error message.

    Returns
    -------
    int

    Raises
    ------
    ConfigError
        Naming ``where``, the value and what is allowed, when ``v`` is not a whole number >= 0.

    Examples
    --------
    >>> count_value("3", "m.yaml: skip_rows")
    3
    """
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
            kw["skip_rows"] = count_value(item["skip_rows"], f"{w}.skip_rows")
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
        raise ConfigError(f"{source}: a mapping must be a YAML mapping of keys ({', '.join(MAPPING_KEYS)}), "
                          f"got {type(data).__name__}")
    unknown = [k for k in data if k not in MAPPING_KEYS]
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {', '.join(map(repr, unknown))}; allowed keys: {', '.join(MAPPING_KEYS)}")
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
    if units not in AXIS_UNITS:
        raise ConfigError(f"{where('units')}: got {units!r}; expected linear (m, N) or rotary (rad, N·m)")
    kw["units"] = units
    if data.get("time_unit") is not None:
        if "time" not in kw:
            raise ConfigError(f"{source}: {lab('time_unit')} needs {lab('time')} (the time column it is the unit of)")
        kw["time_unit"] = _time_unit(data["time_unit"], where("time_unit"))
    if data.get("skip_rows") is not None:
        kw["skip_rows"] = count_value(data["skip_rows"], where("skip_rows"))
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


