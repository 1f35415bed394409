"""The errors that are the user's input, not a fault of nanostage: one home for all of them.

Each names the file, field or value at fault and what is allowed. The command line
(:func:`experiment_runner.apps.cli.main`) prints such an error as one line and exits 2, never a
traceback; any other exception is a fault of nanostage. :class:`ConfigError` is defined by the
simulator's configuration layer (``stage_sim.validation``, below every package that raises it)
and is one of them.

>>> issubclass(OutputError, ConfigError), sorted(e.__name__ for e in USER_ERRORS)
(True, ['ConfigError', 'DataMissing', 'DesignError', 'RecordingError'])
"""
from __future__ import annotations

from stage_sim.validation import ConfigError

__all__ = ["ConfigError", "DataMissing", "DesignError", "OutputError", "RecordingError", "USER_ERRORS"]


class RecordingError(ValueError):
    """A file is not a readable nanostage recording; the message says why."""


class OutputError(ConfigError):
    """An output nanostage must not write or remove there; the message says why and what to do."""


class DesignError(ValueError):
    """Bad input to the design advisor (message names the value)."""


class DataMissing(FileNotFoundError):
    """A real data set is not where it should be; the message says where it was looked for."""


USER_ERRORS = (ConfigError, RecordingError, DesignError, DataMissing)
"""What :func:`experiment_runner.apps.cli.main` reports as bad input (one line, exit 2);
:class:`OutputError` is a :class:`ConfigError`."""
