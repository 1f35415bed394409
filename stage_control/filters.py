"""Discrete SISO state-space filters shared by the controllers.

Filters are discretized once, at build time, with :func:`discretize` and advanced one
sample at a time with the compiled :func:`ss_step`. Matrices use the standard shapes
``A (n, n)``, ``B (n, 1)``, ``C (1, n)``, ``D (1, 1)`` (float64, C-contiguous).

Examples
--------
>>> import numpy as np
>>> A, B, C, D = discretize([1.0], [1.0, 1.0], 1e-3, "tustin")   # 1/(s+1)
>>> x = np.zeros(1)
>>> y = [ss_step(A, B, C, D, x, 1.0) for _ in range(20000)]
>>> abs(y[-1] - 1.0) < 1e-6
True
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy import signal

__all__ = ["discretize", "realize", "dc_state", "ss_step"]

_METHODS = {"zoh": "zoh", "tustin": "bilinear", "backward": "backward_diff"}


def _as_ss(A, B, C, D):
    """Standard-shaped, C-contiguous float64 copies of a SISO realization."""
    A = np.ascontiguousarray(np.atleast_2d(np.asarray(A, float)))
    n = A.shape[0]
    return (A.reshape(n, n).copy(), np.ascontiguousarray(np.asarray(B, float).reshape(n, 1)),
            np.ascontiguousarray(np.asarray(C, float).reshape(1, n)),
            np.ascontiguousarray(np.asarray(D, float).reshape(1, 1)))


def discretize(num, den, dt: float, method: str = "tustin", prewarp: float | None = None):
    """Discretize a proper continuous SISO transfer function ``num(s)/den(s)``.

    Parameters
    ----------
    num, den : array_like
        Polynomial coefficients in descending powers of ``s``.
    dt : float
        Sample time [s].
    method : {"zoh", "tustin", "backward"}
        Zero-order hold, bilinear (Tustin) or backward-Euler (``s = (1 - z^-1)/dt``).
    prewarp : float, optional
        Tustin only: frequency [rad/s] at which the discrete response matches the
        continuous one exactly (``s = w/tan(w dt/2) (z-1)/(z+1)``).

    Returns
    -------
    A, B, C, D : ndarray
        Discrete realization, shapes ``(n, n), (n, 1), (1, n), (1, 1)``.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}")
    if prewarp is not None and method != "tustin":
        raise ValueError("prewarp is only defined for the tustin method")
    num = np.atleast_1d(np.asarray(num, float))
    den = np.atleast_1d(np.asarray(den, float))
    if len(np.trim_zeros(num, "f")) > len(np.trim_zeros(den, "f")):
        raise ValueError("transfer function must be proper")
    # Prewarped Tustin == plain Tustin with the scaled sample time 2 tan(w dt/2)/w.
    t_map = dt if prewarp is None else 2.0 * np.tan(prewarp * dt / 2.0) / prewarp
    Ac, Bc, Cc, Dc = signal.tf2ss(num, den)
    Ad, Bd, Cd, Dd, _ = signal.cont2discrete((Ac, Bc, Cc, Dc), t_map, method=_METHODS[method])
    return _as_ss(Ad, Bd, Cd, Dd)


def realize(num, den):
    """Realization of a proper *discrete* transfer function ``num(z)/den(z)``.

    Coefficients in descending powers of ``z``; same shapes as :func:`discretize`.
    """
    return _as_ss(*signal.tf2ss(np.asarray(num, float), np.asarray(den, float)))


def dc_state(A, B):
    """State per unit constant input at equilibrium, ``(I - A)^-1 B`` as shape ``(n,)``.

    Used to start a filter at rest on its first input (bumpless start).
    """
    n = A.shape[0]
    return np.ascontiguousarray(np.linalg.solve(np.eye(n) - A, B[:, 0]))


@njit(cache=True)
def ss_step(A, B, C, D, x, u):
    """Advance a discrete SISO filter by one sample.

    Parameters
    ----------
    A, B, C, D : ndarray
        Realization from :func:`discretize`.
    x : ndarray, shape (n,)
        Filter state, updated in place (may be a view into a state row).
    u : float
        Input at this sample.

    Returns
    -------
    float
        Output ``y = C x + D u`` (computed before the state update).
    """
    n = x.shape[0]
    y = D[0, 0] * u
    for i in range(n):
        y += C[0, i] * x[i]
    if n == 1:
        x[0] = A[0, 0] * x[0] + B[0, 0] * u
    elif n == 2:
        x0 = x[0]
        x1 = x[1]
        x[0] = A[0, 0] * x0 + A[0, 1] * x1 + B[0, 0] * u
        x[1] = A[1, 0] * x0 + A[1, 1] * x1 + B[1, 0] * u
    elif n > 2:
        xn = A @ x + B[:, 0] * u
        x[:] = xn
    return y
