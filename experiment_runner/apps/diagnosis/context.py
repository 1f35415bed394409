"""What the effects of the library need from a recording: its located scales and proposals.

The locate stage (:func:`.locate.locate`, :mod:`.pipeline`) reads them from the nominal's force
residual and the command -> measurement transfer; an effect's parameter bounds and start values
(:meth:`.effects.base.Effect.params`, :meth:`~.effects.base.Effect.starts`) and its bound form
(:meth:`~.effects.base.Effect.bound`) are computed from them. A :class:`Context` is immutable: the
forward selection replaces it (:func:`dataclasses.replace`) when it locates new proposals in what an
adopted model leaves.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["Context"]


@dataclass(frozen=True)
class Context:
    """The recording's scales and proposals (units of the axis: linear m, N; rotary rad, N·m).

    The defaults are what an effect assumes without a recording (a unit test's model alone).

    Parameters
    ----------
    u_max : float
        Largest recorded command magnitude [N].
    v_max : float
        Largest velocity magnitude of the smoothed measurement [m/s].
    x_span : float
        Range of the observer's positions over the judged samples [m].
    x_center : float
        Centre of that range [m] (position-dependent friction is written about it).
    x_half_span : float
        Half that range [m].
    r_rms : float
        RMS of the nominal's band-limited force residual [N] (scale of force amplitudes).
    stroke : float
        Median stroke of a trial [m].
    peak_hz : tuple
        Peaks of the force residual's spectrum above the floor [Hz], strongest first.
    line_hz : tuple
        Narrow lines of the force residual's spectrum [Hz].
    ripple_period : tuple
        Peaks of the residual's periodogram against position [m] (at most three).
    frf_modes : tuple
        Modes located on the command -> measurement transfer (:func:`.frf.locate_modes`: dicts with
        ``f_hz``, ``zeta``, ``fraction``).
    observer_hz : float
        The force observer's bandwidth [Hz]: it follows forces up to it, so a mode above it is
        proposed as located (:class:`.effects.body.LocatedMode`), not fitted by the observer.
    resolution : float
        Encoder step of the model the effects are added to [m] (the shortest Maxwell-slip distance).
    level_fitted : bool
        The Coulomb level is an adopted effect (position-dependent friction then has no level of its
        own).
    axis : {"linear", "rotary"}
        The recording's axis (scales written in its units, e.g. the Maxwell-slip distances).

    Examples
    --------
    >>> import dataclasses
    >>> c = Context(v_max=0.02, ripple_period=(4e-4,))
    >>> dataclasses.replace(c, level_fitted=True).ripple_period
    (0.0004,)
    """
    u_max: float = 10.0
    v_max: float = 1e-3
    x_span: float = 1e-3
    x_center: float = 0.0
    x_half_span: float = 1e-3
    r_rms: float = 0.1
    stroke: float = 0.0
    peak_hz: tuple = ()
    line_hz: tuple = ()
    ripple_period: tuple = ()
    frf_modes: tuple = ()
    observer_hz: float = 0.0
    resolution: float = 0.0
    level_fitted: bool = False
    axis: str = "linear"
