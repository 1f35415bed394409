"""Units of the diagnosis on a linear or a rotary axis.

The plant runs the same equations on both (``stage_sim.plant``): on a rotary stage
(``stage.kind: rotary``) the fields named mass, force, position, stiffness and viscous hold
inertia [kg·m²], torque [N·m], angle [rad], rotational stiffness [N·m/rad] and viscous
coefficient [N·m·s/rad]. The diagnosis computes in those SI values and writes every unit it
reports -- hypothesis parameters, the replay headline, ``report.md``/``report.json`` and stdout
-- through :func:`unit_for`.

Examples
--------
>>> unit_for("N·s/m", "rotary")
'N·m·s/rad'
>>> unit_for("kg", "linear")
'kg'
"""
from __future__ import annotations

__all__ = ["ROTARY", "unit_for", "axis_units", "convert_units"]

ROTARY = {"kg": "kg·m²", "N": "N·m", "m": "rad", "m/s": "rad/s", "m/s²": "rad/s²", "N/m": "N·m/rad",
          "N·s/m": "N·m·s/rad", "N·s": "N·m·s", "N/m^2": "N·m/rad²", "N/m²": "N·m/rad²", "1/m": "1/rad",
          "N/A": "N·m/A"}
"""Linear unit -> its rotary counterpart (units not listed, e.g. Hz, s, A, -, are the same)."""


def unit_for(unit: str, kind: str = "linear") -> str:
    """``unit`` (written for a linear axis) on an axis of ``kind`` (``linear`` or ``rotary``).

    Parameters
    ----------
    unit : str
        A linear unit (:data:`ROTARY`'s keys change on a rotary axis, others do not).
    kind : {"linear", "rotary"}
        The axis.

    Returns
    -------
    str
    """
    return ROTARY.get(unit, unit) if kind == "rotary" else unit


def axis_units(kind: str = "linear") -> dict:
    """The units of the report's quantities on an axis of ``kind``.

    Parameters
    ----------
    kind : {"linear", "rotary"}
        The axis.

    Returns
    -------
    dict
        ``axis`` and quantity -> unit (mass, force, position, ...).

    Examples
    --------
    >>> axis_units("rotary")["force"]
    'N·m'
    """
    base = {"position": "m", "velocity": "m/s", "force": "N", "mass": "kg", "stiffness": "N/m",
            "damping": "N·s/m", "impulse": "N·s"}
    return {"axis": kind, **{k: unit_for(v, kind) for k, v in base.items()}}


def convert_units(obj, kind: str):
    """``obj`` (nested dicts/lists of a report) with every ``"unit"`` value converted to ``kind``.

    Parameters
    ----------
    obj : dict or list
        Converted in place.
    kind : {"linear", "rotary"}
        The axis.

    Returns
    -------
    dict or list
        ``obj``.

    Examples
    --------
    >>> convert_units({"params": [{"unit": "N/m"}]}, "rotary")
    {'params': [{'unit': 'N·m/rad'}]}
    """
    if kind == "linear":
        return obj
    if isinstance(obj, dict):
        for k, v in obj.items():
            if k == "unit" and isinstance(v, str):
                obj[k] = unit_for(v, kind)
            else:
                convert_units(v, kind)
    elif isinstance(obj, list):
        for v in obj:
            convert_units(v, kind)
    return obj
