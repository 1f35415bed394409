"""MCAP recordings of nanostage runs, after ``shared/contract/recording.md``.

Writing
    :class:`McapRecorder` writes a rosbag2 bag (version 9, MCAP storage) with the
    ``rosbags`` writer: a directory holding one MCAP file, ``<dir>/<dir name>.mcap``,
    and ``metadata.yaml`` (the layout ``ros2 bag record -s mcap -o <dir>`` makes), so
    ``ros2 bag``, ``rosbags`` and Foxglove/``mcap`` tools all open it. The MCAP file is
    self-contained (profile ``ros2``, ``ros2msg`` schemas with their dependencies, ``cdr``
    messages, chunk and message indexes, summary with statistics, each channel's
    ``offered_qos_profiles``, the bag metadata as a ``rosbag2`` metadata record). A chunk
    is closed and flushed every ``chunk_ns`` of stage time (0.1 s) or ``chunk_bytes``
    (1 MiB), so a killed process loses at most that much. Log time and ``header.stamp``
    of every message are the stage time of the sample [ns].
    :func:`write_trials` is the one writer of such a recording from signals in memory:
    :func:`write_run` writes batch-engine trials (:class:`~experiment_runner.core.batch.BatchResult`)
    through it, laid out as the ROS graph would record them, and
    :func:`experiment_runner.core.tabular.convert.write_signals` a converted table.

Reading
    :func:`read_recording` reads a recording (the MCAP file or its bag directory), from
    ours, a rig's or any tool that follows the contract, into numpy arrays
    (:class:`Recording`), with the optional ``/stage/external_force`` and
    ``/source/channels`` where present; a file without ``/stage/reference`` is an
    open-loop record, read only on request (``require_reference=False``).
    ``Recording.command_kind`` says what ``/stage/command`` holds (``drive`` or
    ``measured``: ``/experiment/config`` ``command.kind``, default ``drive``). It reads
    through the MCAP index; if the file was cut short (a
    killed recorder) it falls back to reading record by record up to the last complete
    chunk and says what it salvaged in ``Recording.salvaged`` (messages, of how many
    recorded when the bag's ``metadata.yaml`` tells, and the stage time span). A damaged
    file -- a chunk failing its CRC (every chunk we write carries one), a corrupt length
    or record in a file written to its end, a message on an undeclared channel -- is
    refused: a :class:`RecordingError` names the problem and its byte offset, as for
    anything else that keeps the file from being a contract recording (not MCAP, profile
    not ``ros2``, contract topics missing or of the wrong type, messages that do not
    decode). The reader never loops on its input: every step advances through the file.

The modules of this package: the MCAP file record by record (:mod:`.mcap`), writing
(:mod:`.writer`), reading (:mod:`.reading`), batch trials and signals -> recording (:mod:`.runs`);
this package re-exports their public API.
"""
from __future__ import annotations

from experiment_runner.core.errors import RecordingError
from experiment_runner.core.recording.mcap import bag_layout, mcap_file
from experiment_runner.core.recording.reading import (beyond_limits, Damage, JointSeries, LIMITS, read_recording,
                                                      Recording, Trial)
from experiment_runner.core.recording.runs import run_config_yaml, TrialSignals, write_run, write_trials
from experiment_runner.core.recording.writer import McapRecorder

__all__ = ["RecordingError", "McapRecorder", "Recording", "JointSeries", "Trial", "Damage", "read_recording",
           "TrialSignals", "write_trials", "write_run", "run_config_yaml", "mcap_file", "bag_layout", "LIMITS", "beyond_limits"]
