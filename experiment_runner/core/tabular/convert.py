"""Writing converted signals as a recording, and the ``nanostage convert`` command line."""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from experiment_runner.core.nominal_model import add_convert_nominal_arguments, main_convert_nominal
from experiment_runner.core.outputs import add_overwrite_argument, check_recording
from experiment_runner.core.recording import TrialSignals, bag_layout, read_recording, write_trials
from experiment_runner.core.tabular.mapping import (EMPS_MAPPING, EMPS_PULSES_MAPPING, MAPPING_KEYS, Mapping, count_value,
                                                    load_mapping, mapping_from_dict)
from experiment_runner.core.tabular.reading import read_table
from experiment_runner.core.tabular.signals import Signals, prepare
from msg_defs.topics import BEARING, COMMAND, EXTERNAL_FORCE, MEASURED, MOTOR, REFERENCE, SOURCE_CHANNELS, TABLE
from stage_sim.validation import ConfigError, ConfigWarning


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
    p.add_argument("--mapping", metavar="YAML", help="mapping file (keys: " + ", ".join(MAPPING_KEYS)
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
        skip = count_value(args.skip_rows, "command line: --skip-rows") if args.skip_rows is not None else None
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
