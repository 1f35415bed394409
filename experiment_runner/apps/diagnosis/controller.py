"""The recording's controller: does the model's servo give the recorded command, and the reference it would need.

Controller check
    The replay (:mod:`.judge`) needs the recording's controller. :func:`controller_check` runs the
    model's servo on the recorded reference and measurement; if it does not reproduce the
    recorded command (a loop the preset cannot express, e.g. the EMPS benchmark's
    velocity feedback on the measurement only), :func:`equivalent_reference` finds the
    reference for which it does (sample by sample, the servo's feedthrough inverted), and
    the replay follows that one (said so in the report).
"""
from __future__ import annotations

import numpy as np

from stage_control.servo import build_servo, init_servo_state, servo_step

from .data import DiagData
from .model import ModelSpec

__all__ = ["controller_check", "equivalent_reference"]


def _servo_on(spec: ModelSpec, data: DiagData, x_ref: np.ndarray, cols) -> np.ndarray:
    """The model's servo on the recorded measurement and the reference ``x_ref`` (T, B)."""
    p = spec.preset
    sm = build_servo(p.controller, p.stage)
    T = data.shape[0]
    B = len(cols)
    st = init_servo_state(sm, B)
    out = np.empty((T, B))
    uk = np.empty(B)
    xr = np.ascontiguousarray(x_ref[:, cols])
    vr = np.ascontiguousarray(data.v_ref[:, cols])
    y = np.ascontiguousarray(data.y[:, cols])
    for k in range(T):
        servo_step(sm, st, xr[k], vr[k], y[k], uk)
        out[k] = uk
    return out


def controller_check(spec: ModelSpec, data: DiagData, max_samples: int = 20000) -> float:
    """Relative RMS difference between the recorded command and the model's servo run on the
    recorded reference and measurement (0 when the preset's controller is the recording's).

    Parameters
    ----------
    spec : ModelSpec
        The model (its controller).
    data : DiagData
        The recording.
    max_samples : int, optional
        Samples per trial compared.

    Returns
    -------
    float
    """
    T = min(data.shape[0], max_samples)
    sub = data.subset(np.arange(data.shape[1]))
    for k in ("x_ref", "v_ref", "u", "y", "valid"):
        setattr(sub, k, np.ascontiguousarray(getattr(sub, k)[:T]))
    u = _servo_on(spec, sub, sub.x_ref, np.arange(sub.shape[1]))
    m = sub.valid
    den = float(np.sqrt(np.mean(sub.u[m] ** 2))) or 1.0
    return float(np.sqrt(np.mean((u - sub.u)[m] ** 2)) / den)


def equivalent_reference(spec: ModelSpec, data: DiagData) -> np.ndarray:
    """Reference (T, B) for which the model's servo, fed the recorded measurement, gives the
    recorded command: per sample, the servo's output is affine in the reference sample (for
    PID, DOB and NIASA; a feedforward friction model is solved by the secant through two
    trial values), so it is solved exactly and the servo advanced with the solution.

    Parameters
    ----------
    spec : ModelSpec
        The model (its controller, unsaturated).
    data : DiagData
        The recording.

    Returns
    -------
    numpy.ndarray
        (T, B) reference [m].
    """
    p = spec.preset
    sm = build_servo(p.controller, p.stage)._replace(limit=1e300)      # the affine law, unsaturated
    T, B = data.shape
    st = init_servo_state(sm, B)
    xr = np.ascontiguousarray(data.x_ref).copy()
    vr = np.ascontiguousarray(data.v_ref)
    y = np.ascontiguousarray(data.y)
    u = data.u
    ua, ub = np.empty(B), np.empty(B)
    scale = 1e-9
    for k in range(T):
        s0 = st.copy()
        a = xr[k].copy()
        servo_step(sm, st, a, vr[k], y[k], ua)
        st[:] = s0
        servo_step(sm, st, a + scale, vr[k], y[k], ub)
        st[:] = s0
        g = (ub - ua) / scale
        ok = np.abs(g) > 1e-300
        x = np.where(ok, a + (u[k] - ua) / np.where(ok, g, 1.0), a)
        servo_step(sm, st, x, vr[k], y[k], ua)
        xr[k] = x
    return xr
