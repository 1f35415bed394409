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

The modules of this package: reading (:mod:`.reading`), mapping (:mod:`.mapping`), signals
(:mod:`.signals`), writing and the command line (:mod:`.convert`); this package re-exports their
public API.
"""
from __future__ import annotations

from experiment_runner.core.tabular.convert import add_convert_arguments, convert_emps, convert_table, main_convert
from experiment_runner.core.tabular.mapping import (EMPS_MAPPING, EMPS_PULSES_MAPPING, load_mapping, Mapping,
                                                    mapping_from_dict, Source, TIME_UNITS)
from experiment_runner.core.tabular.reading import header_like, read_table, Table, units_line
from experiment_runner.core.tabular.signals import header_time_unit, join, PLAUSIBLE_RATE, prepare, sha256, Signals
from msg_defs.topics import COMMAND_KINDS

__all__ = ["Table", "read_table", "Mapping", "load_mapping", "mapping_from_dict", "Signals", "prepare",
           "convert_table", "convert_emps", "join", "Source", "sha256", "EMPS_MAPPING", "EMPS_PULSES_MAPPING",
           "TIME_UNITS", "COMMAND_KINDS", "PLAUSIBLE_RATE", "header_like", "units_line", "header_time_unit",
           "add_convert_arguments", "main_convert"]
