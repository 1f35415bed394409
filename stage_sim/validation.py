"""Uniform input errors and unit-plausibility checks for every validated file.

Presets, experiments and campaigns are pydantic models; a failed validation becomes a
:class:`ConfigError` whose message names, one line per problem (:func:`field_line`,
also used for node parameters), the file, the field path (``stage.bearings.0.joint.stiffness``), the bad value and what
is allowed (the constraint, the allowed keys or tags, and the field's description with
its unit)::

    fi_stage.yaml: invalid preset
      stage.table.mass: got -1; expected greater than 0 (moving table mass [kg])
      stage.table.mas: unknown key (got 3); allowed keys: mass

Unit plausibility
-----------------
A dimensional field carries its SI unit and a generous *plausible* range for a
nanopositioning stage as Field metadata (``json_schema_extra=unit("N/m", 1, 1e10)``).
A value outside that range is reported, and when a power-of-a-thousand change of unit
(a prefix: ×1e±3, 1e±6, 1e±9) brings it into range the message says which unit it was
likely given in::

    stage.bearings.0.joint.stiffness: got 0.04135 N/m, outside the plausible range
      1 to 1e+10 N/m; likely given in N/µm instead of N/m (0.04135 N/µm = 4.135e+04 N/m)

Zero is always plausible for a field that allows it (it means "none"/"off").

Rotary stages (``stage.kind: rotary``) hold rad, N·m, kg·m² in the same fields: the ranges
and the messages are then the rotary ones (:data:`ROTARY_UNITS`, :func:`plausible_range`).
A rotary quantity is the linear one seen at a radius r (torque F·r, angle x/r, stiffness and
viscous coefficient k·r², inertia m·r²), so a rotary range is the linear range carried over
every radius of :data:`ROTARY_RADIUS` (1 mm to 1 m: a small servo motor to a roll). A
viscous coefficient of 1e-4 N·m·s/rad or a pre-sliding stiffness of 1 N·m/rad (a small
rotary servo) is plausible; the hints name rotary units (N·mm, mrad, kg·cm², ...)::

    stage.table.mass: got 3000 kg·m², outside the plausible range 1e-10 to 1000 kg·m²; likely
      given in kg·cm² (3000 kg·cm² = 0.3 kg·m²) or kg·mm² (...) or g·cm² (...) instead of kg·m²

Choice: an implausible value is an **error** by default. A stiffness a million times
too small simulates nonsense without any other sign, and the ranges are wide (several
decades around the seed's values, linear and rotary stages alike), so a real value
outside them is rare and deliberate. Such a file opts out with the top-level key
``plausibility: warn`` (report, go on) or ``plausibility: off``. The check applies to
what comes from files -- a loaded preset (:func:`stage_sim.config.load_preset`), and
overrides given with their ``source`` (:func:`stage_sim.config.with_overrides`) -- not
to presets that code builds on purpose (a fit exploring wide bounds, a test driving a
stage to divergence: :func:`stage_sim.config.preset_from_dict`, ``with_overrides``
without a source).

Reading YAML
------------
Every YAML input -- presets, experiments, campaigns, mappings, model files, and the
configuration stored in a recording (``/experiment/config``) -- goes through
:func:`load_yaml` (text) or :func:`load_yaml_file` (a file): ``yaml.SafeLoader`` (no object
construction, no code) that also refuses duplicate keys, which plain YAML silently resolves
to the last, and bounds the work a document can ask for:

* at most :data:`MAX_YAML_BYTES` of text (checked before parsing: a 50 MB string is refused
  at once);
* at most :data:`MAX_NODES` values with its aliases expanded (a "billion laughs" file of a few
  hundred bytes expands to 10**9 values: refused while it is read, before anything is built);
  an alias to a collection that contains it is refused too;
* at most :data:`MAX_DEPTH` levels of nesting, and numbers of at most
  :data:`MAX_NUMBER_CHARS` characters.

:func:`read_text_file` refuses, before opening it, anything that is not a regular file (a
FIFO or a device would block or never end) and kernel pseudo-files (``/proc``, ``/sys``),
then reads without blocking, at most its limit. Errors are :class:`ConfigError` naming the
source (and the line).
"""
from __future__ import annotations

import io
import math
import os
import stat
import types
import typing
import warnings
from dataclasses import dataclass
from typing import Annotated, Literal, Union, get_args, get_origin

import yaml
from pydantic import BaseModel, ValidationError

__all__ = ["ConfigError", "ConfigWarning", "Problem", "unit", "plausible_range", "model_axis", "ROTARY_UNITS",
           "ROTARY_RADIUS", "format_validation_error", "field_line",
           "plausibility_problems", "check_plausible", "load_yaml", "load_yaml_file", "read_text_file",
           "input_file_problem", "is_number_type", "MAX_YAML_BYTES", "MAX_NODES", "MAX_DEPTH", "MAX_NUMBER_CHARS"]


@dataclass(frozen=True)
class Problem:
    """One bad input: the dotted field path, the value found and what is wrong / allowed."""
    path: str
    value: object
    message: str


class ConfigError(ValueError):
    """A configuration file or mapping failed validation; the message says where and why.

    ``problems`` lists each bad field (:class:`Problem`), when known.
    """

    def __init__(self, message: str, problems: list[Problem] | tuple = ()):
        super().__init__(message)
        self.problems = list(problems)


class ConfigWarning(UserWarning):
    """An implausible value accepted because its file says ``plausibility: warn``."""


# =========================================================================== units
UNIT_ALTERNATIVES = {
    "N/m": (("N/mm", 1e3), ("N/µm", 1e6)),
    "N·s/m": (("N·s/mm", 1e3), ("N·s/µm", 1e6)),
    "N/(m·s)": (("N/(mm·s)", 1e3), ("N/(µm·s)", 1e6)),
    "N·s": (("mN·s", 1e-3), ("µN·s", 1e-6)),
    "N": (("mN", 1e-3), ("kN", 1e3)),
    "kg": (("g", 1e-3),),
    "m": (("mm", 1e-3), ("µm", 1e-6), ("nm", 1e-9)),
    "m/s": (("mm/s", 1e-3), ("µm/s", 1e-6)),
    "s": (("ms", 1e-3), ("µs", 1e-6)),
    "Hz": (("kHz", 1e3), ("MHz", 1e6)),
    "A": (("mA", 1e-3), ("µA", 1e-6)),
    # rotary stages
    "N·m": (("mN·m", 1e-3), ("N·mm", 1e-3), ("N·cm", 1e-2)),
    "N·m/rad": (("N·m/mrad", 1e3), ("N·m/µrad", 1e6), ("N·mm/rad", 1e-3)),
    "N·m·s/rad": (("N·mm·s/rad", 1e-3), ("N·m·s/mrad", 1e3)),
    "N·m/(rad·s)": (("N·mm/(rad·s)", 1e-3),),
    "N·m·s": (("mN·m·s", 1e-3), ("N·mm·s", 1e-3)),
    "kg·m²": (("kg·cm²", 1e-4), ("kg·mm²", 1e-6), ("g·cm²", 1e-7)),
    "rad": (("mrad", 1e-3), ("µrad", 1e-6), ("deg", math.pi / 180)),
    "rad/s": (("mrad/s", 1e-3), ("deg/s", math.pi / 180), ("rpm", math.pi / 30)),
    "N·m/A": (("mN·m/A", 1e-3), ("N·mm/A", 1e-3)),
}
"""Units a value is commonly given in by mistake, with their factor to the SI unit."""

ROTARY_UNITS = {
    "N": ("N·m", 1), "N/m": ("N·m/rad", 2), "N·s/m": ("N·m·s/rad", 2), "N/(m·s)": ("N·m/(rad·s)", 2),
    "N·s": ("N·m·s", 1), "kg": ("kg·m²", 2), "1/kg": ("1/(kg·m²)", -2), "m": ("rad", -1), "m/s": ("rad/s", -1),
    "N/A": ("N·m/A", 1),
}
"""A linear SI unit -> (the unit the same field holds on a rotary stage, the power p of the
radius r with rotary value = linear value * r**p). Units not listed (s, Hz, A, 1/s, 1) are
the same on both."""
ROTARY_RADIUS = (1e-3, 1.0)
"""Radii [m] over which a linear plausible range is carried to a rotary one."""

_PREFIX_FACTORS = (1e3, 1e6, 1e9, 1e-3, 1e-6, 1e-9)


def unit(name: str, lo: float, hi: float) -> dict:
    """Field metadata: SI unit ``name`` and the plausible range ``[lo, hi]`` of the value's size.

    Use as ``Field(..., json_schema_extra=unit("N/m", 1.0, 1e10))``.
    """
    return {"unit": name, "plausible": (float(lo), float(hi))}


def plausible_range(meta: dict, axis: str = "linear") -> tuple[str, float, float]:
    """``(unit, lo, hi)`` of a field's metadata (:func:`unit`) on a ``linear`` or ``rotary`` axis.

    >>> plausible_range(unit("N·s/m", 1e-3, 1e5), "rotary")
    ('N·m·s/rad', 1e-09, 100000.0)
    >>> plausible_range(unit("Hz", 1.0, 1e5), "rotary")
    ('Hz', 1.0, 100000.0)
    """
    lo, hi = meta["plausible"]
    name = meta["unit"]
    if axis != "rotary" or name not in ROTARY_UNITS:
        return name, lo, hi
    rot, p = ROTARY_UNITS[name]
    ends = [r ** p for r in ROTARY_RADIUS]
    return rot, float(f"{lo * min(ends):.12g}"), float(f"{hi * max(ends):.12g}")


def model_axis(model) -> str:
    """``"rotary"`` when ``model`` (or its ``stage``) says ``kind: rotary``, else ``"linear"``;
    ``model`` may be a validated model or its mapping."""
    for obj in (model, model.get("stage") if isinstance(model, dict) else getattr(model, "stage", None)):
        kind = obj.get("kind") if isinstance(obj, dict) else getattr(obj, "kind", None)
        if kind == "rotary":
            return "rotary"
    return "linear"


def _hint(value: float, unit_name: str, lo: float, hi: float) -> str:
    a = abs(value)
    named = [(alt, f) for alt, f in UNIT_ALTERNATIVES.get(unit_name, ()) if lo <= a * f <= hi]
    if named:
        return "; likely given in " + " or ".join(
            f"{alt} ({value:g} {alt} = {value * f:.4g} {unit_name})" for alt, f in named) + f" instead of {unit_name}"
    factors = [f for f in _PREFIX_FACTORS if lo <= a * f <= hi]
    if factors:
        return "; likely off by a unit prefix (x" + " or x".join(f"{f:g}" for f in factors) + ")"
    return ""


def _implausible(path: str, value: float, meta: dict, axis: str = "linear") -> Problem | None:
    u, lo, hi = plausible_range(meta, axis)
    if value == 0 or lo <= abs(value) <= hi:
        return None
    return Problem(path, value, f"got {value:g} {u}, outside the plausible range {lo:g} to {hi:g} {u}"
                   f"{_hint(value, u, lo, hi)}")


def plausibility_problems(model: BaseModel, paths=None, axis: str | None = None) -> list[Problem]:
    """Fields of a validated ``model`` (recursively) whose value is outside its plausible range.

    Parameters
    ----------
    model : pydantic.BaseModel
    paths : iterable of str, optional
        Check only fields at or below these dotted paths (e.g. the paths overrides set).
    axis : {"linear", "rotary"}, optional
        Units and ranges (:func:`plausible_range`); default the model's own (:func:`model_axis`).
    """
    axis = axis or model_axis(model)
    sel = None if paths is None else [p.split(".") for p in paths]
    out: list[Problem] = []

    def wanted(parts: list[str]) -> bool:
        return sel is None or any(parts[:len(s)] == s or s[:len(parts)] == parts for s in sel)

    def walk(obj, parts):
        if isinstance(obj, BaseModel):
            for name, info in type(obj).model_fields.items():
                sub = parts + [name]
                if not wanted(sub):
                    continue
                val = getattr(obj, name)
                meta = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
                if "plausible" in meta:
                    vals = val if isinstance(val, list) else [val]
                    for i, v in enumerate(vals):
                        if isinstance(v, (int, float)) and not isinstance(v, bool):
                            p = _implausible(".".join(sub + ([str(i)] if isinstance(val, list) else [])), v, meta,
                                             axis)
                            if p:
                                out.append(p)
                else:
                    walk(val, sub)
        elif isinstance(obj, list):
            for i, v in enumerate(obj):
                if wanted(parts + [str(i)]):
                    walk(v, parts + [str(i)])

    walk(model, [])
    return out


def check_plausible(model: BaseModel, source: str, mode: str = "error", paths=None) -> None:
    """Raise :class:`ConfigError` (``mode="error"``) or warn (``"warn"``) on implausible values.

    ``source`` names the file; ``paths`` restricts the check (see :func:`plausibility_problems`).
    """
    if mode == "off":
        return
    problems = plausibility_problems(model, paths)
    if not problems:
        return
    text = "\n".join([f"{source}: implausible value(s) (a wrong unit?)"]
                     + [f"  {p.path}: {p.message}" for p in problems])
    if mode == "warn":
        warnings.warn(text, ConfigWarning, stacklevel=3)
        return
    raise ConfigError(text + "\n  (a deliberate value? set 'plausibility: warn' at the top of the preset, "
                      "or as an override)", problems)


# =========================================================================== validation errors
def _strip(tp):
    """Annotated[X, ...] -> X; Optional[X] -> X."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
        elif origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
            else:
                return Union[tuple(args)]
        else:
            return tp


def is_number_type(annotation) -> bool:
    """True for ``int``, ``float`` and integer ``Literal`` annotations (also ``Optional``/``Annotated``)."""
    tp = _strip(annotation)
    if tp in (int, float):
        return True
    return get_origin(tp) is Literal and all(isinstance(a, int) and not isinstance(a, bool) for a in get_args(tp))


def _is_model(tp) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _tagged(member, tag) -> bool:
    if member.__name__ == tag:
        return True
    for info in member.model_fields.values():
        ann = _strip(info.annotation)
        if get_origin(ann) is Literal and tag in get_args(ann):
            return True
    return False


def _resolve(root, loc) -> tuple[list[str], object, object]:
    """Walk ``loc`` through the model ``root``: (path without union tags, FieldInfo, type)."""
    tp, info, path = root, None, []
    for part in loc:
        tp = _strip(tp) if tp is not None else None
        if get_origin(tp) in (Union, types.UnionType) and isinstance(part, str):
            member = next((m for m in get_args(tp) if _is_model(m) and _tagged(m, part)), None)
            if member is not None:          # a union tag in the location, not a key of the file
                tp = member
                continue
        if isinstance(part, int):
            args = get_args(tp) if get_origin(tp) in (list, tuple) else ()
            tp, info = (args[0] if args else None), None
        elif _is_model(tp) and part in tp.model_fields:
            info = tp.model_fields[part]
            tp = info.annotation
        else:
            tp, info = None, None
        path.append(str(part))
    return path, info, (_strip(tp) if tp is not None else None)


def _show(value) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _about(info, axis: str = "linear") -> str:
    if info is None:
        return ""
    desc = info.description or ""
    meta = info.json_schema_extra if isinstance(info.json_schema_extra, dict) else {}
    if meta.get("unit"):
        u = plausible_range(meta, axis)[0] if "plausible" in meta else meta["unit"]
        desc = desc.replace(f"[{meta['unit']}]", f"[{u}]")
        if f"[{u}]" not in desc:
            desc = f"{desc} [{u}]".strip()
    return f" -- {desc}" if desc else ""


def field_line(path: str, value, problem: str) -> str:
    """One problem line, ``  path: got value; problem`` -- the format of every input error
    (config files here, node parameters in :mod:`experiment_runner.ros.node`)."""
    return f"  {path}: got {_show(value)}; {problem}"


def format_validation_error(err: ValidationError, source: str, kind: str = "configuration",
                            root: type[BaseModel] | None = None, axis: str = "linear") -> ConfigError:
    """A :class:`ConfigError` for a pydantic ``err``: one line per problem, naming the field
    path, the bad value and what is allowed (``root``: the model validated, for field
    descriptions, units and allowed keys; ``axis``: units of a ``rotary`` stage's fields)."""
    lines = [f"{source}: invalid {kind}"]
    problems = []
    for e in err.errors():
        kind_ = e["type"]
        path, info, _ = _resolve(root, e["loc"]) if root else ([str(p) for p in e["loc"]], None, None)
        where = ".".join(path) or "(top level)"
        value = e.get("input")
        ctx = e.get("ctx") or {}
        if kind_ == "missing":
            line = f"  {where}: required field is missing{_about(info, axis)}"
        elif kind_ == "extra_forbidden":
            parent = _resolve(root, e["loc"][:-1])[2] if root else None
            allowed = f"; allowed keys: {', '.join(parent.model_fields)}" if _is_model(parent) else ""
            line = f"  {where}: unknown key (got {_show(value)}){allowed}"
        elif kind_ == "union_tag_invalid":
            where = f"{where}.{ctx.get('discriminator', '').strip(chr(39))}".rstrip(".")
            value = ctx.get("tag")
            line = field_line(where, value, f"expected one of {ctx.get('expected_tags')}")
        elif kind_ == "union_tag_not_found":
            where = f"{where}.{ctx.get('discriminator', '').strip(chr(39))}".rstrip(".")
            line = f"  {where}: required field is missing (it selects the kind)"
            value = None
        elif kind_ in ("value_error", "assertion_error"):
            msg = e["msg"].removeprefix("Value error, ").removeprefix("Assertion failed, ")
            shown = "" if isinstance(value, (dict, list)) else f" (got {_show(value)})"
            line = f"  {where}: {msg}{shown}"
        else:
            expected = e["msg"].removeprefix("Input should be ")
            if isinstance(value, float) and not math.isfinite(value) and "finite" not in expected:
                expected = f"a finite number, {expected}"
            line = field_line(where, value, f"expected {expected}{_about(info, axis)}")
        lines.append(line)
        problems.append(Problem(where, value, line.split(": ", 1)[1]))
    return ConfigError("\n".join(lines), problems)


# =========================================================================== input files
MAX_YAML_BYTES = 1 << 20
"""Largest YAML input [bytes] (a preset is a few kB; a recording's configuration tens of kB)."""
MAX_NODES = 200_000
"""Most values (scalars and collections) a YAML document may hold with its aliases expanded."""
MAX_DEPTH = 100
"""Deepest nesting of collections in a YAML document."""
MAX_NUMBER_CHARS = 100
"""Longest number in a YAML document [characters] (a float needs 25)."""

_FILE_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
               (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
               (stat.S_ISSOCK, "a socket"))


def _pseudo_filesystems() -> dict:
    """Device ids of the kernel's pseudo-file systems mounted here (``/proc``, ``/sys``)."""
    out = {}
    for root in ("/proc", "/sys"):
        try:
            out[os.stat(root).st_dev] = root
        except OSError:
            pass
    return out


def input_file_problem(path) -> str | None:
    """Why ``path`` is not safe to read as an input file, or None if it is.

    Only a regular file is read: a FIFO, a socket or a device could block forever or never
    end, and a kernel pseudo-file (``/proc/kmsg``, ``/sys/...``) may block, consume what it
    gives, or have no end. Decided from ``os.stat`` alone, before the file is opened.

    >>> input_file_problem("/dev/zero")
    'not a regular file (a character device); only a regular file is read'
    >>> input_file_problem("/no/such/file")
    'no such file'
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "no such file"
    except OSError as err:
        return f"cannot read it ({err.strerror or err})"
    if not stat.S_ISREG(st.st_mode):
        what = next((name for test, name in _FILE_KINDS if test(st.st_mode)), "not a file")
        return f"not a regular file ({what}); only a regular file is read"
    root = _pseudo_filesystems().get(st.st_dev)
    if root is not None:
        return f"a kernel pseudo-file (under {root}), not a file of yours; it is not read"
    return None


def read_text_file(path, what: str = "input", max_bytes: int = MAX_YAML_BYTES, fallback: str | None = None) -> str:
    """The UTF-8 text of a small input file, read safely; :class:`ConfigError` naming the file.

    Refuses what :func:`input_file_problem` refuses, and a file over ``max_bytes`` (from its
    size before reading, and again from what the read returns), without blocking. A leading
    UTF-8 byte-order mark is dropped. Text that is not UTF-8 is refused, or decoded with the
    ``fallback`` encoding when one is given (e.g. ``"latin-1"`` for a data logger's export).
    """
    problem = input_file_problem(path)
    if problem is not None:
        raise ConfigError(f"{path}: {problem if problem != 'no such file' else f'no such {what} file'}")
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the {what} file ({err.strerror or err})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):                 # replaced since it was checked
            raise ConfigError(f"{path}: not a regular file; only a regular file is read")
        if st.st_size > max_bytes:
            raise ConfigError(f"{path}: {st.st_size} bytes; a {what} file has at most {max_bytes} bytes "
                              "(is it the right file?)")
        chunks, size = [], 0
        while size <= max_bytes:
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
    except BlockingIOError:
        raise ConfigError(f"{path}: reading it would block (not an ordinary file); it is not read") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the {what} file ({err.strerror or err})") from None
    finally:
        os.close(fd)
    if size > max_bytes:
        raise ConfigError(f"{path}: more than {max_bytes} bytes; a {what} file has at most {max_bytes} bytes")
    data = b"".join(chunks)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        if fallback:
            return data.decode(fallback, errors="replace")
        raise ConfigError(f"{path}: not UTF-8 text (byte {err.start}: {data[err.start:err.start + 1]!r}); "
                          f"a {what} file is YAML text") from None


# =========================================================================== YAML
class _Refused(yaml.MarkedYAMLError):
    """A document beyond a limit of :func:`load_yaml` (not a syntax error)."""


class _UniqueKeyLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` refusing duplicate mapping keys and documents beyond the limits
    (:data:`MAX_NODES` values with aliases expanded, :data:`MAX_DEPTH` levels,
    :data:`MAX_NUMBER_CHARS`-character numbers), while it composes them: nothing is built
    from a refused document."""

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0
        self._size: dict[int, int] = {}        # id(node) -> values in it, aliases expanded

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            target = self.anchors.get(event.anchor)
            if target is not None and id(target) not in self._size:
                raise _Refused(None, None, f"alias *{event.anchor} refers to a collection that contains it "
                                           "(a recursive structure)", event.start_mark)
            return super().compose_node(parent, index)
        if self._depth >= MAX_DEPTH:
            raise _Refused(None, None, f"nested deeper than {MAX_DEPTH} levels", self.peek_event().start_mark)
        self._depth += 1
        try:
            node = super().compose_node(parent, index)
        finally:
            self._depth -= 1
        if isinstance(node, yaml.MappingNode):
            size = 1 + sum(self._size[id(k)] + self._size[id(v)] for k, v in node.value)
        elif isinstance(node, yaml.SequenceNode):
            size = 1 + sum(self._size[id(v)] for v in node.value)
        else:
            size = 1
        if size > MAX_NODES:
            raise _Refused(None, None, f"it holds more than {MAX_NODES} values with its aliases expanded "
                                       "(aliases of aliases: a 'billion laughs' document?)", node.start_mark)
        self._size[id(node)] = size
        return node


def _number(construct):
    def bounded(loader, node):
        if len(node.value) > MAX_NUMBER_CHARS:
            raise _Refused(None, None, f"a number of {len(node.value)} characters; at most {MAX_NUMBER_CHARS}",
                           node.start_mark)
        return construct(loader, node)
    return bounded


def _mapping(loader: _UniqueKeyLoader, node: yaml.MappingNode, deep: bool = False):
    seen = {}
    for key_node, _ in node.value:
        if key_node.tag == "tag:yaml.org,2002:merge":
            continue                       # '<<: *anchor' entries may be overridden by explicit keys
        key = loader.construct_object(key_node, deep=deep)
        if isinstance(key, typing.Hashable):
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark,
                    f"found duplicate key {key!r} (first at line {seen[key] + 1})", key_node.start_mark)
            seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_UniqueKeyLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)
for _tag, _construct in (("int", yaml.SafeLoader.construct_yaml_int),
                         ("float", yaml.SafeLoader.construct_yaml_float)):
    _UniqueKeyLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _number(_construct))


def load_yaml(text: str, source: str):
    """Parse YAML safely (``SafeLoader``: plain data only, no code) refusing duplicate keys
    and documents beyond the limits (see the module docstring); :class:`ConfigError` naming
    ``source`` and the line on any error.

    >>> load_yaml("a: [1, 2.5, x]", "demo")
    {'a': [1, 2.5, 'x']}
    >>> load_yaml("a: 1\\na: 2", "demo.yaml")
    Traceback (most recent call last):
    stage_sim.validation.ConfigError: demo.yaml: not valid YAML at line 2, column 1: found duplicate key 'a' (first at line 1) (while constructing a mapping)
    >>> load_yaml("a: &a [x, x]\\nb: &b [*a, *a]\\nc: &c [*b, *b]", "bomb.yaml")["c"][1][0]
    ['x', 'x']
    """
    if len(text) > MAX_YAML_BYTES:
        raise ConfigError(f"{source}: {len(text)} characters of YAML; at most {MAX_YAML_BYTES} are read")
    stream = io.StringIO(text)
    stream.name = str(source)              # named in YAML's error marks
    try:
        return yaml.load(stream, Loader=_UniqueKeyLoader)   # noqa: S506 - a SafeLoader subclass
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        what = getattr(err, "problem", None) or str(err)
        if isinstance(err, yaml.reader.ReaderError):        # a NUL or other control character
            where = f" at character {err.position + 1}"
            code = err.character if isinstance(err.character, int) else ord(err.character)
            what = f"character #x{code:04x}: {err.reason} (a NUL or control character)"
        context = getattr(err, "context", None)
        head = "refused" if isinstance(err, _Refused) else "not valid YAML"
        raise ConfigError(f"{source}: {head}{where}: {what}" + (f" ({context})" if context else "")) from None
    except (ValueError, OverflowError) as err:     # a scalar that matches a type but does not build (2021-13-01)
        raise ConfigError(f"{source}: not valid YAML: {err}") from None


def load_yaml_file(path, what: str = "input"):
    """:func:`load_yaml` of a file read by :func:`read_text_file` (a ``what`` file, in errors)."""
    return load_yaml(read_text_file(path, what), str(path))
