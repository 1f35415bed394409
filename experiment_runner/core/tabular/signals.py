"""A table mapped onto a regular grid in SI units, ready to write (:func:`prepare`)."""
from __future__ import annotations

import hashlib
import math
import re
from dataclasses import dataclass, field

import numpy as np

from experiment_runner.core.recording import LIMITS, beyond_limits
from experiment_runner.core.tabular.mapping import Mapping, TIME_UNITS, AXIS_UNITS
from experiment_runner.core.tabular.reading import Table
from msg_defs.topics import COMMAND_KINDS
from stage_sim.validation import ConfigError


INTERVAL_TOL = 0.05
"""A sample interval may differ from the mean period by this fraction (logger jitter)."""
GRID_TOL = 0.25
"""... and a sample lie this fraction of a period off the regular grid."""
SNAP_TOL = 0.01
"""The period is rounded to the ns when that moves no stamp by more than this fraction of it."""


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

    >>> from pathlib import Path
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
    unit = AXIS_UNITS[m.units]
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


