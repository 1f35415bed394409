"""Discrete SISO state-space filters shared by the controllers.

Filters are discretized once, at build time, with :func:`discretize` and advanced one
sample at a time, for a whole batch of trials, with the compiled :func:`ss_step`.
Matrices use the standard shapes ``A (n, n)``, ``B (n, 1)``, ``C (1, n)``, ``D (1, 1)``
(float64, C-contiguous); the state of a batch is ``(n, n_batch)`` (trial axis last).

Examples
--------
>>> import numpy as np
>>> A, B, C, D = discretize([1.0], [1.0, 1.0], 1e-3, "tustin")   # 1/(s+1)
>>> x, u, y = np.zeros((1, 3)), np.array([1.0, 2.0, 0.0]), np.zeros(3)
>>> for _ in range(20000):
...     ss_step(A, B, C, D, x, u, y)
>>> bool(np.allclose(y, u, atol=1e-6))
True
"""
from __future__ import annotations

import numpy as np
from numba import njit
from scipy import signal

__all__ = ["discretize", "realize", "dc_state", "ss_coefficients", "ss_step", "SS1_FIELDS", "SS2_FIELDS"]

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


SS1_FIELDS = ("a", "b", "c", "d")
SS2_FIELDS = ("a00", "a01", "a10", "a11", "b0", "b1", "c0", "c1", "d")


def ss_coefficients(prefix: str, A, B, C, D) -> dict:
    """Realization of order 1 or 2 as named float fields, e.g. ``{"q_a00": ..., "q_d": ...}``.

    Names: ``SS1_FIELDS`` (``a, b, c, d``) or ``SS2_FIELDS`` (``a00 a01 a10 a11`` of ``A``,
    ``b0 b1``, ``c0 c1``, ``d``), each prefixed with ``prefix + "_"``.

    Compiled step functions take filter coefficients as plain float fields of the model
    NamedTuple: they are passed by value and unpacked into registers, whereas every
    array field costs a reference-count increment/decrement pair (two atomic operations)
    and nine words of argument passing per call. (A nested tuple field would be as cheap,
    but Numba cannot pass tuples of tuples into a ``prange`` region, issue numba#9098.)
    """
    A, B, C, D = (np.asarray(m, float) for m in (A, B, C, D))
    n = A.shape[0]
    if n == 1:
        vals = (A[0, 0], B[0, 0], C[0, 0], D[0, 0])
        names = SS1_FIELDS
    elif n == 2:
        vals = (A[0, 0], A[0, 1], A[1, 0], A[1, 1], B[0, 0], B[1, 0], C[0, 0], C[0, 1], D[0, 0])
        names = SS2_FIELDS
    else:
        raise ValueError(f"only orders 1 and 2 are supported, got {n}")
    return {f"{prefix}_{k}": float(v) for k, v in zip(names, vals)}


@njit(cache=True, error_model="numpy")
def ss_step(A, B, C, D, x, u, y):
    """Advance a batch of identical discrete SISO filters by one sample.

    Batch-inner layout: the trial axis is last and innermost, so the loops over the
    batch run over contiguous memory and vectorize; nothing is allocated for ``n <= 2``
    (the only orders the controllers use; they inline the same arithmetic).

    Parameters
    ----------
    A, B, C, D : ndarray
        Realization from :func:`discretize`.
    x : ndarray, shape (n, n_batch)
        Filter state of every trial, updated in place.
    u : ndarray, shape (n_batch,)
        Input at this sample.
    y : ndarray, shape (n_batch,)
        Written: output ``y = C x + D u`` (computed before the state update).
    """
    n = x.shape[0]
    nb = x.shape[1]
    d = D[0, 0]
    if n == 0:
        for b in range(nb):
            y[b] = d * u[b]
    elif n == 1:
        a, bb, c = A[0, 0], B[0, 0], C[0, 0]
        for b in range(nb):
            ub = u[b]
            x0 = x[0, b]
            y[b] = d * ub + c * x0
            x[0, b] = a * x0 + bb * ub
    elif n == 2:
        a00, a01, a10, a11 = A[0, 0], A[0, 1], A[1, 0], A[1, 1]
        b0, b1, c0, c1 = B[0, 0], B[1, 0], C[0, 0], C[0, 1]
        for b in range(nb):
            ub = u[b]
            x0 = x[0, b]
            x1 = x[1, b]
            y[b] = d * ub + c0 * x0 + c1 * x1
            x[0, b] = a00 * x0 + a01 * x1 + b0 * ub
            x[1, b] = a10 * x0 + a11 * x1 + b1 * ub
    else:
        # general order: one scratch copy of the old state per call (not used in the loops)
        xo = x.copy()
        for b in range(nb):
            y[b] = d * u[b]
        for i in range(n):
            ci = C[0, i]
            for b in range(nb):
                y[b] += ci * xo[i, b]
        for i in range(n):
            bi = B[i, 0]
            for b in range(nb):
                x[i, b] = 0.0
            for j in range(n):
                aij = A[i, j]
                for b in range(nb):
                    x[i, b] += aij * xo[j, b]
            for b in range(nb):
                x[i, b] += bi * u[b]
