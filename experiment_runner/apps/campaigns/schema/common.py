"""What the campaign schemas share: the identifier type, length labels and a test condition.

Examples
--------
>>> fmt_length(5e-6), slug("5 µm")
('5 µm', '5um')
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Optional

from pydantic import Field

__all__ = ["Name", "Condition", "fmt_length", "slug"]

Name = Annotated[str, Field(pattern=r"^[A-Za-z][A-Za-z0-9_]*$", max_length=40)]
"""An identifier in a campaign file: a letter, then letters, digits and ``_``; at most 40."""


def fmt_length(x: float) -> str:
    """``5e-3 -> '5 mm'``, ``5e-6 -> '5 µm'``, ``5e-8 -> '50 nm'``.

    Parameters
    ----------
    x : float
        A length [m].

    Returns
    -------
    str

    Examples
    --------
    >>> fmt_length(5e-3), fmt_length(-5e-6), fmt_length(2e-5)
    ('5 mm', '-5 µm', '20 µm')
    """
    a = abs(x)
    for unit, s in (("m", 1.0), ("mm", 1e-3), ("µm", 1e-6), ("nm", 1e-9)):
        if a >= s * 0.9999:
            return f"{x / s:.4g} {unit}"
    return f"{x * 1e12:.4g} pm"


def slug(s: str) -> str:
    """A label as an identifier: letters and digits kept, ``µ`` as ``u``, spaces dropped, the rest ``_``.

    Parameters
    ----------
    s : str
        A label (``'R 5 mm, 1 mm/s'``).

    Returns
    -------
    str
        Letters, digits and ``_`` only, no leading or trailing ``_`` (condition keys, file names).

    Examples
    --------
    >>> slug("r5 mm_v1 mm/s")
    'r5mm_v1mm_s'
    """
    return "".join(ch if ch.isalnum() else "_" for ch in s.replace("µ", "u").replace(" ", "")).strip("_")


@dataclass(frozen=True)
class Condition:
    """One test condition (a step size, a radius and speed, or a force amplitude) and sweep value.

    The coordinates a kind does not use are None.

    Parameters
    ----------
    key : str
        Identifier of the condition, letters, digits and ``_`` only (``'5mm'``), unique in the
        campaign: used in file names and result keys.
    label : str
        The condition as the reports show it (``'5 mm'``).
    step : float, optional
        Point-to-point step size [m] (signed).
    radius : float, optional
        Circle radius [m].
    speed : float, optional
        Circle tangential speed [m/s].
    sweep : float, optional
        The campaign sweep's value (in the sweep's ``unit``).
    amplitude : float, optional
        Frequency response: force amplitude at the plant input [N].

    Examples
    --------
    >>> c = Condition("5mm__k_2", "5 mm, k = 2", step=5e-3, sweep=2.0)
    >>> c.matches(step=5e-3), c.matches(step=5e-3, sweep=1.0), c.matches(radius=1e-3)
    (True, False, False)
    >>> c.at()
    {'step': 0.005, 'sweep': 2.0}
    """
    key: str
    label: str
    step: Optional[float] = None
    radius: Optional[float] = None
    speed: Optional[float] = None
    sweep: Optional[float] = None
    amplitude: Optional[float] = None          # frequency_response: force amplitude [N]

    def matches(self, step=None, radius=None, speed=None, sweep=None, amplitude=None) -> bool:
        """Whether this condition has every coordinate given (equal to a relative 1e-9; None: any).

        Parameters
        ----------
        step : float, optional
            Step size [m].
        radius : float, optional
            Circle radius [m].
        speed : float, optional
            Tangential speed [m/s].
        sweep : float, optional
            Sweep value.
        amplitude : float, optional
            Force amplitude [N].

        Returns
        -------
        bool
            False when a given coordinate differs or this condition does not have it.
        """
        for mine, want in ((self.step, step), (self.radius, radius), (self.speed, speed), (self.sweep, sweep),
                           (self.amplitude, amplitude)):
            if want is not None and (mine is None or not math.isclose(mine, want, rel_tol=1e-9, abs_tol=0.0)):
                return False
        return True

    def at(self) -> dict:
        """The coordinates this condition has, as :meth:`matches` takes them.

        Returns
        -------
        dict
            ``step``, ``radius``, ``speed``, ``sweep``, ``amplitude`` -> value, the ones not None.
        """
        return {k: getattr(self, k) for k in ("step", "radius", "speed", "sweep", "amplitude")
                if getattr(self, k) is not None}
