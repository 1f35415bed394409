"""Integrators written independently of the project's simulator, for tests that compare the
simulator (or the diagnosis) with records it did not write."""
import numpy as np


def regularized_coulomb_rk4(forces, rate: float, m: float, f_c: float, v_reg: float, c: float,
                            h: float = 1e-5) -> np.ndarray:
    """Positions [m] at the end of each control period of ``m x'' = F_k - F_C tanh(v / v_reg) - c v``
    from rest at 0, the force ``F_k`` held over period ``k`` (``1 / rate``): classical RK4 on a
    grid of about ``h`` [s]."""
    sub = max(1, int(round(1.0 / rate / h)))
    h = 1.0 / rate / sub
    out = np.empty(len(forces))
    x = v = 0.0
    for k, F in enumerate(forces):
        def acc(v):
            return (F - f_c * np.tanh(v / v_reg) - c * v) / m
        for _ in range(sub):
            a1 = acc(v)
            a2 = acc(v + 0.5 * h * a1)
            a3 = acc(v + 0.5 * h * a2)
            a4 = acc(v + h * a3)
            x += h / 6 * (6 * v + h * (a1 + a2 + a3))
            v += h / 6 * (a1 + 2 * a2 + 2 * a3 + a4)
        out[k] = x
    return out
