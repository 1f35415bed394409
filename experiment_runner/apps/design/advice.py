"""The FI recommendation (Sec. 6.3.2, 6.4.2): the seed's rule applied to a sweep (:mod:`.sweep`).

:func:`recommend` applies Sec. 6.3.2 ("designed to meet the RMS in-position error requirements
with the smallest stiffness and damping coefficient"). **Rule:** a grid point is feasible when
every trial settles within the dwell and the mean RMS in-position error is ``<= rms_required``;
the recommendation is the feasible point with the smallest ``k_fi`` and, at that ``k_fi``, the
smallest ``c_fi``. It reports the settling time this buys against the same stage with the
bearings bolted rigidly (No FI) and the FF accuracy at that stiffness (Sec. 6.4.2): ``γ`` = RMS
difference of the Dahl and GMS friction forces over one 5 mm circle cycle with ``η = k_fi/k_f``
(:func:`stage_control.isolator.gamma_curve`; GMS blocks of the preset when its
bearings use GMS, else Table 6.5's block distribution scaled to the preset's initial stiffness, as
:func:`stage_control.isolator.gms_consistent` does for Fig. 6.8) and ``κ`` of Eq. 4.2.
:func:`advise_isolator` sweeps and recommends in one call.

Caveat: with Dahl bearings (``fi_stage``) a stiff FI or No FI drifts out of the window after
settling (the single-state Dahl ratchet under drive noise, see the ``table_4_2`` campaign), so the
stiff corner of the maps and the No FI comparison are artefacts there; the GMS variants
(``fi_stage_gms``) settle normally.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from experiment_runner.core.errors import DesignError
from stage_control import isolator

from .sweep import GRIDS, STEP, Sweep, sweep_isolator


RULE = ("feasible: every trial settles within the dwell and mean RMS in-position error <= requirement; "
        "recommend the feasible grid point with the smallest k_fi, then the smallest c_fi at that k_fi "
        "(Sec. 6.3.2: 'meet the RMS in-position error requirements with the smallest stiffness and damping')")


@dataclass
class Point:
    """One FI design (stage totals) with its simulated and analysed performance (SI)."""
    k_fi: float
    c_fi: float
    k_fi_per_bearing: float
    c_fi_per_bearing: float
    settling_time_s: float
    rms_in_position_m: float
    zeta_fi: float        # FI mode damping ratio c_fi / (2 sqrt(k_fi m_t m_b/(m_t + m_b))) [-]
    ge_norm: float
    gd_norm: float
    eta: float            # k_fi / k_f
    gamma_n: float        # Sec. 6.4.2 RMS F_Dahl - F_GMS over one 5 mm circle cycle [N]
    gamma_bias_n: float   # mean (F_Dahl - F_GMS) sgn(v) [N]: + = Dahl over-compensates
    kappa: float          # Eq. 4.2 sensitivity of k_c to k_f [-]
    settling_reduction_vs_nofi: float   # 1 - ts / ts_NoFI (nan if No FI did not settle)
    index: tuple = ()     # (i, j) in the sweep grid, () if off-grid


@dataclass
class Advice:
    """Result of :func:`recommend` (SI units)."""
    preset: str
    rms_required_m: float
    rule: str
    feasible: np.ndarray                  # (n_k, n_c) bool
    recommended: Optional[Point]
    fastest_feasible: Optional[Point]     # feasible point with the shortest mean settling time
    preset_design: Point                  # the preset's own FI
    nofi: dict
    message: str
    sweep: Sweep = field(repr=False)

    @property
    def ok(self) -> bool:
        return self.recommended is not None


def _point(sw: Sweep, k, c, ts, rms, index=()) -> Point:
    lp = sw.lumped
    ge, gd = isolator.point_norms(lp.m_t, lp.m_b, lp.pid, k, c, lp.k_f, lp.c_f) if not index else (
        float(sw.ge[index]), float(sw.gd[index]))
    eta = k / lp.k_f if lp.k_f else math.inf
    gam, bias, _ = isolator.gamma_curve(np.array([eta]), lp.k_f, lp.f_c, lp.gms_k, lp.gms_alpha)
    ts0 = sw.nofi["settling_time_s"]
    zeta = float(c) / (2.0 * math.sqrt(k * lp.m_t * lp.m_b / (lp.m_t + lp.m_b)))
    return Point(k_fi=float(k), c_fi=float(c), k_fi_per_bearing=float(k) / lp.n_joints,
                 c_fi_per_bearing=float(c) / lp.n_joints, settling_time_s=float(ts),
                 rms_in_position_m=float(rms), zeta_fi=zeta, ge_norm=ge, gd_norm=gd, eta=float(eta),
                 gamma_n=float(gam[0]), gamma_bias_n=float(bias[0]), kappa=float(isolator.kappa_eq42(eta)),
                 settling_reduction_vs_nofi=float(1.0 - ts / ts0) if math.isfinite(ts0) else math.nan,
                 index=tuple(int(v) for v in index))


def _required(rms_required_m) -> float:
    """The requirement as a float [m]; :class:`DesignError` unless finite and > 0."""
    try:
        v = float(rms_required_m)
    except (TypeError, ValueError):
        v = math.nan
    if not (math.isfinite(v) and v > 0):
        raise DesignError(f"rms_required_m = {rms_required_m!r}: must be a finite value > 0 [m]")
    return v


def recommend(sw: Sweep, rms_required_m: float) -> Advice:
    """Apply :data:`RULE` to a sweep for a required RMS in-position error [m]."""
    rms_required_m = _required(rms_required_m)
    ts, rms = sw.ts_mean, sw.rms_mean
    with np.errstate(invalid="ignore"):
        feas = sw.settled & (rms <= rms_required_m)
    lp = sw.lumped
    design = _point(sw, lp.k_fi, lp.c_fi, sw.design["settling_time_s"], sw.design["rms_in_position_m"])
    rec = fast = None
    if feas.any():
        i = int(np.flatnonzero(feas.any(axis=1))[0])
        j = int(np.flatnonzero(feas[i])[0])
        rec = _point(sw, sw.k_grid[i], sw.c_grid[j], ts[i, j], rms[i, j], (i, j))
        fi, fj = np.unravel_index(np.nanargmin(np.where(feas, ts, np.nan)), ts.shape)
        fast = _point(sw, sw.k_grid[fi], sw.c_grid[fj], ts[fi, fj], rms[fi, fj], (fi, fj))
        edge = " (softest grid k_fi: extend the grid down)" if i == 0 else ""
        n = sw.nofi
        vs = (f"{100 * rec.settling_reduction_vs_nofi:.0f} % faster than No FI ({n['settling_time_s'] * 1e3:.1f} ms)"
              if n["settled"] == n["trials"] else
              f"No FI settled in only {n['settled']}/{n['trials']} trials within the {sw.moves.dwell:g} s dwell")
        msg = (f"recommended k_fi = {rec.k_fi:.3g} N/m, c_fi = {rec.c_fi:.3g} N·s/m{edge}: "
               f"{rec.rms_in_position_m * 1e9:.2f} nm RMS in position, settles in "
               f"{rec.settling_time_s * 1e3:.1f} ms; {vs}")
    else:
        best = np.nanmin(rms) if np.isfinite(rms).any() else math.nan
        msg = (f"no FI on the grid meets {rms_required_m * 1e9:.3g} nm RMS in position (best "
               f"{best * 1e9:.3g} nm): relax the requirement, use a stiffer/more damped FI than the grid, "
               f"or the semi-active isolator (Sec. 6.3.2, Ch. 5)")
    return Advice(preset=sw.preset, rms_required_m=rms_required_m, rule=RULE, feasible=feas,
                  recommended=rec, fastest_feasible=fast, preset_design=design, nofi=sw.nofi, message=msg,
                  sweep=sw)


def advise_isolator(preset, rms_required_m: float, step=STEP, grid="default", **kw) -> Advice:
    """Sweep a preset's FI and recommend the softest, least damped design meeting a requirement.

    Parameters
    ----------
    preset : str or Preset
        Preset with bearings on compliant joints (e.g. ``fi_stage``).
    rms_required_m : float
        Required RMS in-position error [m] (> 0).
    step : float
        Point-to-point step [m].
    grid : str or (array_like, array_like)
        ``"default"``, ``"coarse"``, ``"fine"`` or explicit (k_fi [N/m], c_fi [N·s/m]) stage totals.
    **kw
        Passed to :func:`sweep_isolator` (``window``, ``dwell``, ``n_trials``, ``progress``,
        ``workers``, ``cluster``).

    Returns
    -------
    Advice

    Examples
    --------
    >>> a = advise_isolator("fi_stage", 4e-9, grid=([3e4, 3e5], [1.0, 100.0]), n_trials=2, dwell=0.2)
    >>> a.recommended.rms_in_position_m <= 4e-9
    True
    """
    rms_required_m = _required(rms_required_m)
    if isinstance(grid, str):
        if grid not in GRIDS:
            raise DesignError(f"grid = {grid!r}: choose one of {', '.join(GRIDS)}")
        grid = GRIDS[grid]
    return recommend(sweep_isolator(preset, grid[0], grid[1], step=step, **kw), rms_required_m)
