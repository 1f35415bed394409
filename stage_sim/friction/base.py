"""What every friction law shares: the optional force variations of its schema and the
batch driver of its Python model class (hysteresis loops, virgin curves)."""
from __future__ import annotations

import numpy as np
from pydantic import Field, model_validator

from stage_sim.schema import Finite, StrictModel

__all__ = ["FrictionVariation", "Model", "virgin_curve", "variation_entries"]


class FrictionVariation(StrictModel):
    """Optional variations of a friction element's force (all default off = exactly the base model).

    The element's force (pre-motion and sliding alike) is multiplied by
    ``s(x) (1 +- f_c_difference / (2 f_c))`` (``+`` while the element's force resists motion
    in +x, i.e. moving +), and a direction-dependent viscous force ``-(viscous_difference/2) |v|``
    is added; ``x``, ``v`` are the position and velocity of the body the element acts on and
    ``s(x) = max(0, 1 + (f_c_gradient (x - position_center) + f_c_curvature (x - position_center)^2) / f_c)``.
    So the Coulomb force is ``F_C(x) = f_c s(x)``, ``F_C+ - F_C- = f_c_difference`` and
    ``c+ - c- = viscous_difference``. Every law's schema derives from it and has ``f_c`` [N]
    and ``viscous`` [N·s/m].
    """
    f_c_difference: Finite = Field(0.0, description="Coulomb force moving + minus moving - [N]; |.| < 2 f_c")
    viscous_difference: Finite = Field(0.0, description="viscous coefficient moving + minus moving - [N·s/m]")
    f_c_gradient: Finite = Field(0.0, description="slope of the Coulomb force along the travel [N/m]")
    f_c_curvature: Finite = Field(0.0, description="curvature of the Coulomb force along the travel [N/m²]")
    position_center: Finite = Field(0.0, description="position about which f_c_gradient/f_c_curvature apply [m]")

    @model_validator(mode="after")
    def _variation(self):
        if abs(self.f_c_difference) >= 2 * self.f_c and self.f_c_difference != 0.0:
            raise ValueError(f"f_c_difference={self.f_c_difference} must be smaller in size than 2 f_c = {2 * self.f_c}")
        if self.f_c == 0 and (self.f_c_gradient or self.f_c_curvature):
            raise ValueError("f_c_gradient/f_c_curvature need f_c > 0")
        return self


def variation_entries(fields: dict) -> dict:
    """The friction variation entries ``fields`` (names of :class:`FrictionVariation`) of an
    element mapping, checked by name: what a law's ``element`` constructor appends.

    >>> variation_entries({"f_c_difference": 0.4})
    {'f_c_difference': 0.4}
    >>> variation_entries({"f_c_diff": 0.4})
    Traceback (most recent call last):
    ...
    TypeError: unknown friction variation field(s) f_c_diff (known: f_c_difference, viscous_difference, f_c_gradient, f_c_curvature, position_center)
    """
    unknown = [k for k in fields if k not in FrictionVariation.model_fields]
    if unknown:
        raise TypeError(f"unknown friction variation field(s) {', '.join(unknown)} "
                        f"(known: {', '.join(FrictionVariation.model_fields)})")
    return dict(fields)


class Model:
    """Batch driver shared by the law's Python model classes: state per trial, driven by ``x``."""

    n_state = 1

    def __init__(self, n_trials: int = 1):
        self.n_trials = int(n_trials)
        self.reset()

    def reset(self):
        """Relax the model (zero internal state) for every trial."""
        self.state = np.zeros((self.n_trials, self.n_state))
        self._x = None

    def drive(self, x, dt: float = 1e-4):
        """Drive the model with a displacement history.

        Parameters
        ----------
        x : array_like, shape (T,) or (T, n_trials)
            Bearing displacement history [m]; the first sample is the start point.
        dt : float
            Sample time [s] (only rate-dependent models use it).

        Returns
        -------
        ndarray, same shape as ``x``
            Friction force at each sample [N].
        """
        x = np.asarray(x, dtype=float)
        squeeze = x.ndim == 1
        xs = x[:, None] * np.ones(self.n_trials) if squeeze else x
        out = np.empty_like(xs)
        self._x = xs[0].copy()
        out[0] = self.force()
        for t in range(1, xs.shape[0]):
            out[t] = self.step(xs[t] - self._x, dt)
            self._x = xs[t].copy()
        return out[:, 0] if squeeze and self.n_trials == 1 else out


def virgin_curve(model: Model, x_max: float, n: int = 200):
    """Force-displacement curve from the relaxed state up to ``x_max`` [m].

    Returns ``(x, F)`` with ``x`` from 0 to ``x_max`` in ``n`` samples.
    """
    model.reset()
    x = np.linspace(0.0, x_max, n)
    f = model.drive(x)
    return x, np.asarray(f).reshape(n, -1)[:, 0]
