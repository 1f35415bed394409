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


def lugre_rk4(forces, rate: float, m: float, sigma0: float, sigma1: float, f_c: float, f_s: float,
              v_s: float, c: float = 0.0, h: float = 1e-6) -> np.ndarray:
    """Positions [m] at the end of each control period of the LuGre model (Canudas de Wit et al.,
    1995) on a mass from rest at 0: ``m x'' = F_k - (sigma0 z + sigma1 z' + c v)``,
    ``z' = v - sigma0 |v| z / g(v)``, ``g(v) = F_C + (F_S - F_C) exp(-(v / v_s)^2)``, the force
    ``F_k`` held over period ``k`` (``1 / rate``): classical RK4 in (x, v, z) on a grid of
    about ``h`` [s]."""
    sub = max(1, int(round(1.0 / rate / h)))
    h = 1.0 / rate / sub
    out = np.empty(len(forces))
    y = np.zeros(3)                                  # x, v, z

    def rhs(y, F):
        v, z = y[1], y[2]
        g = f_c + (f_s - f_c) * np.exp(-(v / v_s) ** 2)
        zd = v - sigma0 * abs(v) * z / g
        return np.array([v, (F - sigma0 * z - sigma1 * zd - c * v) / m, zd])
    for k, F in enumerate(forces):
        for _ in range(sub):
            k1 = rhs(y, F)
            k2 = rhs(y + 0.5 * h * k1, F)
            k3 = rhs(y + 0.5 * h * k2, F)
            k4 = rhs(y + h * k3, F)
            y = y + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out[k] = y[0]
    return out
