"""The options of one diagnosis (:func:`.pipeline.diagnose`, ``nanostage diagnose``)."""
from __future__ import annotations

from dataclasses import dataclass, field

from experiment_runner.core.executor import default_workers

from .budget import DEFAULT_MAX_SECONDS
from .effects import LIBRARY, Library

__all__ = ["Options", "CONTROLLER_TOL"]

CONTROLLER_TOL = 0.02
"""The model's servo on the recorded reference and measurement must reproduce the recorded command
to this relative RMS, else the replay follows the equivalent reference
(:func:`.controller.equivalent_reference`)."""


@dataclass
class Options:
    """How a diagnosis runs and what it may propose.

    Examples
    --------
    >>> from experiment_runner.apps.diagnosis.effects import LIBRARY
    >>> Options(library=LIBRARY.select(["coulomb", "viscous"]), plots=False).candidates()
    ['coulomb', 'viscous']
    >>> Options(effects=["mass"]).candidates()
    ['mass']

    Parameters
    ----------
    bandwidth : float, optional
        Force-observer bandwidth [Hz] (None: rate / 25).
    max_fit_seconds : float
        Cap of the fit set (whole trials) [s].
    effects : list, optional
        Keys of the library to propose (None: every candidate of the library).
    library : Library, optional
        The effects (an :class:`.effects.Library`; None: :data:`.effects.LIBRARY`).
    floor_seeds : tuple
        Noise seeds of the force residual's simulated recordings (floor).
    window_s : float
        Open-loop window length of the report's drift figures [s].
    max_steps : int
        Forward-selection steps (each must pass the replay judge).
    plots : bool
        Write the PNG plots.
    sparse : bool
        SINDy-style regression of what the final model leaves, when it is not adequate.
    complexity : float
        Penalty per parameter of a candidate's rank (held-out replay error x (1 + complexity p)).
    n_jobs : int
        Threads for the candidate fits (neither workers nor cluster).
    workers : int, optional
        Candidate fits as tasks on this many local processes (1: in turn in this one).
    cluster : object
        Candidate fits on this Dask cluster (scheduler address or cluster object).
    own_floor : bool
        Judge each candidate's force residual against its own noise floor.
    min_share : float
        After the first effect: share of the remaining replay excess over the floor a candidate must
        remove (the remnant of an imperfect fit is not "explained" by extras).
    verbose : bool
        Step summaries on stdout.
    max_seconds : float, optional
        Wall-clock budget of the diagnosis [s]: the search stops there, keeping the model of its
        last completed step; the validation and the report follow (:mod:`.budget`). None: no limit.
    progress : bool
        A progress line per stage and step on stderr, with the elapsed seconds.
    extra : dict
        Not read by the diagnosis (a place for a caller's own settings).
    """
    bandwidth: float | None = None
    max_fit_seconds: float = 3.0
    effects: list | None = None
    library: Library | None = None
    floor_seeds: tuple = (90001, 90002)
    window_s: float = 0.01
    max_steps: int = 6
    plots: bool = True
    sparse: bool = True
    complexity: float = 0.02
    n_jobs: int = field(default_factory=default_workers)
    workers: int | None = None
    cluster: object = None
    own_floor: bool = True
    min_share: float = 0.25
    verbose: bool = False
    max_seconds: float | None = DEFAULT_MAX_SECONDS
    progress: bool = True
    extra: dict = field(default_factory=dict)

    def effect_library(self) -> Library:
        """The library the candidates come from (the options' or :data:`.effects.LIBRARY`).

        Returns
        -------
        Library
        """
        return self.library if self.library is not None else LIBRARY

    def candidates(self) -> list[str]:
        """Keys of the effects the forward selection proposes, in order.

        Returns
        -------
        list of str
        """
        return list(self.effects) if self.effects else self.effect_library().candidates()

    def log(self, *parts) -> None:
        """Progress on stdout (``verbose``).

        Parameters
        ----------
        *parts : object
            Printed separated by spaces.
        """
        if self.verbose:
            print("[diagnose]", *parts, flush=True)
