"""Where the real data sets are (``../shared/data``), and the error when one is not there."""
from __future__ import annotations

import os
from pathlib import Path

from experiment_runner.core.errors import DataMissing

__all__ = ["DataMissing", "data_root", "need_file"]


def data_root(explicit=None) -> Path:
    """The shared data folder (``shared/data``).

    ``explicit`` (or else ``$NANOSTAGE_DATA``), when given, is the only place looked in;
    otherwise ``../shared/data`` relative to the repository (this package's ``../../..``) and to
    the working directory, then ``/work/shared/data``. Raises :class:`DataMissing` naming
    every place tried.

    Parameters
    ----------
    explicit : str or pathlib.Path, optional
        The folder to use (``--data``).

    Returns
    -------
    pathlib.Path
        The first of the candidate folders that exists.
    """
    repo = Path(__file__).resolve().parents[3]
    given = explicit or os.environ.get("NANOSTAGE_DATA")
    cands = [Path(given)] if given else [repo.parent / "shared" / "data", Path.cwd().parent / "shared" / "data",
                                         Path("/work/shared/data")]
    for c in cands:
        if (c / "emps").is_dir() or (c / "microtribometer_reciprocating").is_dir():
            return c
    raise DataMissing("real data folder not found; tried " + ", ".join(str(c) for c in cands)
                      + " (it must hold emps/ or microtribometer_reciprocating/; set NANOSTAGE_DATA or pass --data)")


def need_file(path: Path, what: str) -> Path:
    """``path`` if it is a file, else :class:`DataMissing` naming ``what`` and the path.

    Parameters
    ----------
    path : pathlib.Path
        The file.
    what : str
        What it is, for the message (e.g. "EMPS data").

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    if not path.is_file():
        raise DataMissing(f"{what}: {path} does not exist")
    return path
