"""Estimates of a report against a concealed truth: what the self-test and the power study check."""
from __future__ import annotations

__all__ = ["estimate", "check_params"]


def estimate(found: dict, name: str):
    """``(value, sigma)`` of parameter or derived quantity ``name`` of a found effect (or an
    alternative) of a report: the joint fit's value, else its own, else the derived quantity
    (sigma None); ``(None, None)`` when it has none.

    Parameters
    ----------
    found : dict
        A found effect or alternative of ``report.json``.
    name : str
        Parameter or derived-quantity name.

    Returns
    -------
    value : float or None
        In the effect's unit.
    sigma : float or None
        Its standard error.
    """
    for key in ("params_joint", "params"):
        for p in found.get(key) or []:
            if p["name"].split(".")[-1] == name:
                return p["value"], p.get("sigma")
    if name in (found.get("derived") or {}):
        return found["derived"][name], None
    return None, None


def check_params(entry: dict | None, expect: dict) -> tuple[bool, dict]:
    """Estimates of ``entry`` (a found effect or an alternative) against the truth values ``expect``
    (name -> value): each within +-20 % of its truth (a truth of 0: within 20 % of the largest truth,
    or 2 sigma).

    Parameters
    ----------
    entry : dict or None
        A found effect or alternative of ``report.json`` (None: not found, fails).
    expect : dict
        Parameter name -> true value.

    Returns
    -------
    ok : bool
        Every estimate within its tolerance.
    checks : dict
        Name -> ``truth``, ``estimate``, ``rel_error``, ``ok``, ``sigma``, ``z``.

    Examples
    --------
    >>> check_params({"params": [{"name": "c", "value": 21.0, "sigma": 0.5}]}, {"c": 20.0})[0]
    True
    """
    checks = {}
    if entry is None:
        return False, checks
    ok_all = True
    nz = [abs(v) for v in expect.values() if v]
    for k, truth in expect.items():
        est, sig = estimate(entry, k)
        if est is None:
            checks[k] = {"truth": truth, "estimate": None, "ok": False}
            ok_all = False
            continue
        if truth:
            rel = est / truth - 1
            ok = abs(rel) <= 0.2
        else:
            rel = None
            ok = abs(est) <= 0.2 * max(nz or [1.0]) or (sig is not None and abs(est) <= 2 * sig)
        checks[k] = {"truth": truth, "estimate": est, "rel_error": rel, "ok": bool(ok), "sigma": sig,
                     "z": (est - truth) / sig if sig else None}
        ok_all &= ok
    return bool(ok_all), checks
