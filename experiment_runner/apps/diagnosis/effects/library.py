"""A library of effects: the registry a diagnosis proposes its candidates from.

The order of a library is the order its candidates are proposed and fitted in (the fits are
collected in that order, so it fixes the report's order among equal scores). What the selection
needs to know about the effects together is derived from their declarations: the exclusive groups
(:meth:`Library.exclusive_of`), the known quantities (:attr:`Library.known`).
"""
from __future__ import annotations

from typing import Iterable

from ..context import Context
from .base import Effect

__all__ = ["Library"]

SPARSE_REGRESSION = {
    "key": "sparse_regression", "title": "sparse regression (SINDy-style)", "kind": "fallback",
    "physics": "When no effect explains a residual: sequentially thresholded least squares of the "
               "residual on a library of state functions (1, v, sign v, v|v|, |v|, x, x^2, a, u, "
               "friction state phi_f, |phi_f|, phi_f x, phi_f x^2, sin/cos of x at the periodogram "
               "peak).",
    "signature": "any residual left above the noise floor after the effects",
    "parameters": [], "in_preset": False, "needs": "reported as terms; not simulated"}
"""The fallback the report lists after the effects (``--list-effects``): not a model change."""


class Library:
    """An ordered registry of effects, keyed by :attr:`.base.Effect.key`.

    Parameters
    ----------
    effects : iterable of Effect classes or instances
        In the order candidates are proposed.

    Examples
    --------
    >>> from experiment_runner.apps.diagnosis.effects import LIBRARY
    >>> LIBRARY.select(["mass", "force_constant"]).known
    frozenset({'force_constant'})
    >>> sorted(LIBRARY.exclusive_of("gms"))
    ['coulomb', 'dahl', 'lugre', 'regularized_coulomb', 'stribeck']
    """

    def __init__(self, effects: Iterable):
        self._effects: dict[str, Effect] = {}
        for e in effects:
            e = e() if isinstance(e, type) else e
            if not e.key or e.key in self._effects:
                raise ValueError(f"effect {type(e).__name__}: key {e.key!r} empty or given twice")
            self._effects[e.key] = e

    def __getitem__(self, key: str) -> Effect:
        try:
            return self._effects[key]
        except KeyError:
            raise KeyError(f"unknown effect {key!r} (known: {', '.join(self._effects)})") from None

    def __contains__(self, key) -> bool:
        return key in self._effects

    def __iter__(self):
        return iter(self._effects)

    def __len__(self) -> int:
        return len(self._effects)

    def keys(self):
        """The effect keys, in order.

        Returns
        -------
        KeysView of str
        """
        return self._effects.keys()

    def values(self):
        """The effects, in order.

        Returns
        -------
        ValuesView of Effect
        """
        return self._effects.values()

    def items(self):
        """``(key, effect)`` pairs, in order.

        Returns
        -------
        ItemsView
        """
        return self._effects.items()

    def select(self, keys: Iterable[str]) -> "Library":
        """The library of the effects ``keys`` (in that order; ``KeyError`` naming an unknown one).

        Parameters
        ----------
        keys : iterable of str
            Effect keys.

        Returns
        -------
        Library

        Examples
        --------
        >>> from experiment_runner.apps.diagnosis.effects import LIBRARY
        >>> list(LIBRARY.select(['viscous', 'coulomb']).keys())
        ['viscous', 'coulomb']
        """
        return Library([self[k] for k in keys])

    def bound(self, ctx: Context) -> "Library":
        """Every effect bound to a recording's located context ``ctx`` (:meth:`.base.Effect.bound`):
        one diagnosis' library. The effects of this library are not changed.

        Parameters
        ----------
        ctx : Context
            What was located on the recording.

        Returns
        -------
        Library
        """
        return Library([e.bound(ctx) for e in self._effects.values()])

    def candidates(self) -> list[str]:
        """The keys the forward selection proposes (deterministic and integer effects), in order.

        Returns
        -------
        list of str
        """
        return [k for k, e in self._effects.items() if e.kind in ("deterministic", "integer")]

    def exclusive_of(self, key: str) -> set:
        """The other effects sharing an exclusive group with ``key`` (of which at most one is adopted).

        Parameters
        ----------
        key : str
            An effect key.

        Returns
        -------
        set of str
        """
        groups = set(self[key].exclusive)
        return {k for k, e in self._effects.items() if k != key and groups & set(e.exclusive)}

    @property
    def known(self) -> frozenset:
        """Keys of the effects that state a quantity a nominal gives as known."""
        return frozenset(k for k, e in self._effects.items() if e.known_quantity)

    def dealt(self) -> list[Effect]:
        """The effects with a concealed truth of their own, in the power study's deal order.

        Returns
        -------
        list of Effect
        """
        return sorted((e for e in self._effects.values() if e.deal is not None), key=lambda e: e.deal)

    def describe(self, as_json: bool = False):
        """The library as text (``--list-effects``) or a list of dicts (``--json``).

        Parameters
        ----------
        as_json : bool, optional
            Rows as dicts instead of text.

        Returns
        -------
        str or list of dict
        """
        rows = [e.row() for e in self._effects.values()] + [dict(SPARSE_REGRESSION)]
        if as_json:
            return rows
        out = []
        for r in rows:
            out.append(f"{r['key']}  -  {r['title']}  [{r['kind']}{'' if r['in_preset'] else ', not in preset'}]")
            out.append(f"    physics:   {r['physics']}")
            out.append(f"    signature: {r['signature']}")
            if r["parameters"]:
                out.append("    params:    " + "; ".join(
                    f"{p['name']} [{p['unit']}" + (f"; rotary {p['unit_rotary']}" if p["unit_rotary"] != p["unit"] else "")
                    + f"] {p['meaning']}".rstrip() for p in r["parameters"]))
            if r["needs"]:
                out.append(f"    needs:     {r['needs']}")
        return "\n".join(out)
