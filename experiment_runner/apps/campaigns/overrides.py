"""Dotted-path preset overrides: paths with ``*`` wildcards expanded, values set or scaled.

A campaign names what it changes in a preset by dotted paths (``stage.bearings.*.friction.f_c``):
a case's ``overrides``, its calibrated parameters and its sweep
(:func:`experiment_runner.apps.campaigns.spec.case_overrides`). This module turns such a path
and a value, factor or series stiffness into absolute overrides of one preset, which
:func:`stage_sim.config.with_overrides` applies.

Examples
--------
>>> expand_path({"k": [1.0, 2.0]}, "k.*")
[('k.0', 1.0), ('k.1', 2.0)]
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from stage_sim.config import ConfigError, Preset

__all__ = ["expand_path", "resolve", "to_python"]


def expand_path(data, path: str) -> list[tuple[str, object]]:
    """Dotted path with '*' wildcards -> [(concrete path, value)] in ``data`` (a model_dump).

    Parameters
    ----------
    data : dict
        A nested mapping (a preset's ``model_dump()``).
    path : str
        Dotted path; a part is a mapping key, a list index (negative counts from the end) or
        ``*`` (every item of a list or mapping).

    Returns
    -------
    list of tuple
        ``(concrete dotted path, value)`` of every match, in order; list indices non-negative.

    Raises
    ------
    stage_sim.config.ConfigError
        A part that is not there (the message names the fields or item count there).

    Examples
    --------
    >>> expand_path({"a": [{"b": 1}, {"b": 2}]}, "a.*.b")
    [('a.0.b', 1), ('a.1.b', 2)]
    >>> expand_path({"a": [{"b": 1}, {"b": 2}]}, "a.-1.b")
    [('a.1.b', 2)]
    """
    nodes = [(data, [])]
    for part in path.split("."):
        nxt = []
        for node, pre in nodes:
            if part == "*":
                if isinstance(node, list):
                    nxt += [(v, pre + [str(i)]) for i, v in enumerate(node)]
                elif isinstance(node, dict):
                    nxt += [(v, pre + [k]) for k, v in node.items()]
                else:
                    raise ConfigError(f"{path}: '*' at {'.'.join(pre) or 'top'} which is not a list or mapping")
            elif isinstance(node, list):
                if not part.lstrip("-").isdigit() or not -len(node) <= int(part) < len(node):
                    raise ConfigError(f"{path}: {'.'.join(pre)} has {len(node)} items, no {part!r}")
                nxt.append((node[int(part)], pre + [str(int(part) % len(node))]))
            elif isinstance(node, dict):
                if part not in node:
                    raise ConfigError(f"{path}: {'.'.join(pre) or 'preset'} has no field {part!r} "
                                      f"(fields: {', '.join(node)})")
                nxt.append((node[part], pre + [part]))
            else:
                raise ConfigError(f"{path}: {'.'.join(pre)} is {node!r}, not a mapping")
        nodes = nxt
    if not nodes:
        raise ConfigError(f"{path}: matches nothing")
    return [(".".join(pre), v) for v, pre in nodes]


def _scaled(v, factor, path, series=None):
    if isinstance(v, list):
        return [_scaled(x, factor, path, series) for x in v]
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        k = float(v) * float(factor)
        if series is None:
            return k
        if k <= 0:
            raise ConfigError(f"{path}: series_scale needs a positive stiffness, got {k!r}")
        return 1.0 / (1.0 / float(series) + 1.0 / k)
    raise ConfigError(f"{path}: cannot scale {v!r}")


def resolve(preset: Preset, paths, mode: str, value, series: Optional[float] = None) -> dict:
    """Absolute dotted-path overrides setting (``mode: value``), scaling (``scale``) or
    scaling and combining in series with ``series`` (``series_scale``) ``paths``.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The case's preset.
    paths : list of str
        Dotted paths (with ``*`` over list items).
    mode : {'value', 'scale', 'series_scale'}
        How ``value`` applies.
    value : float
        The value or factor.
    series : float, optional
        The element combined in series (``series_scale``).

    Returns
    -------
    dict
        Absolute dotted-path overrides.

    Examples
    --------
    >>> from stage_sim.config import load_preset
    >>> p = load_preset("fi_stage_gms")
    >>> o = resolve(p, ["stage.bearings.*.friction.f_c"], "scale", 2.0)
    >>> o
    {'stage.bearings.0.friction.f_c': 5.31, 'stage.bearings.1.friction.f_c': 5.31}
    >>> k = resolve(p, ["stage.bearings.0.friction.k"], "series_scale", 1.0, series=8.27e4)
    >>> round(k["stage.bearings.0.friction.k"][0])      # 1 / (1/8.27e4 + 1/6.7e5)
    73614
    """
    if mode == "series_scale" and series is None:
        raise ConfigError(f"{paths}: mode series_scale needs a series stiffness")
    data = preset.model_dump()
    out = {}
    for path in paths:
        for concrete, old in expand_path(data, path):
            out[concrete] = (_scaled(old, value, concrete, series if mode == "series_scale" else None)
                             if mode in ("scale", "series_scale") else to_python(value))
    return out


def to_python(v):
    """``v`` with numpy scalars as Python numbers, also inside lists, tuples and dicts (for YAML/JSON).

    Parameters
    ----------
    v : object
        A value, list, tuple or dict.

    Returns
    -------
    object
        The same with every ``numpy.generic`` replaced by its ``item()``; tuples become lists.

    Examples
    --------
    >>> to_python({"k": (np.float64(1.5), np.int64(2))})
    {'k': [1.5, 2]}
    """
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, (list, tuple)):
        return [to_python(x) for x in v]
    if isinstance(v, dict):
        return {k: to_python(x) for k, x in v.items()}
    return v
