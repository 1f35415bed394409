"""VAN check (Sec. 3.3, 3.4.3): piezo drive voltage, piezo power and flexure fatigue of a VAN preset.

:func:`check_van` computes the piezo drive voltage for the preset's dither force, the piezo
power of Eq. 3.7 and the flexure fatigue check of Eq. 3.4-3.6 with Table 3.2's data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

from experiment_runner.core.errors import DesignError

from .sweep import as_preset


@dataclass(frozen=True)
class Piezo:
    """Piezo stack of the VAN stage (Sec. 3.3: PI P-842.10; datasheet values, SI)."""
    free_stroke: float = 15e-6      # stroke at v_max without load [m] (P-842.10; van_stage preset note)
    blocking_force: float = 300.0   # force at v_max against a rigid wall [N] (P-842.10)
    v_max: float = 100.0            # max operating voltage [V] (Sec. 3.3)
    # derived: Sec. 3.4.3 gives 0.3 W per actuator at V_pp = 20 V, f = 500 Hz; Eq. 3.7 then needs
    # C = 0.3/(500*20^2) = 1.5 uF, which is the P-842.10 datasheet capacitance
    capacitance: float = 1.5e-6     # [F]

    @property
    def stiffness(self) -> float:
        """Piezo stiffness = blocking force / free stroke [N/m]."""
        return self.blocking_force / self.free_stroke


@dataclass(frozen=True)
class Flexure:
    """VAN flexure strength data (Sec. 3.3, Table 3.2: 304 stainless steel; SI)."""
    s_ut: float = 517e6             # Table 3.2: ultimate tensile strength [Pa]
    s_y: float = 207e6              # Table 3.2: yield strength [Pa]
    h: float = 19e-3                # Sec. 3.3: hinge height [m]
    d: float = 1e-3                 # Sec. 3.3: hinge thickness [m]
    # Table 3.2: S_max = 47 MPa "with the maximum applied load of 77 N" (the text of Sec. 3.3 says
    # 43 MPa for the same load; the larger, conservative value is used). Stress is linear in load.
    stress_ref: float = 47e6        # [Pa] at load_ref
    load_ref: float = 77.0          # [N]
    p_c: float = 1.0                # loading factor (Sec. 3.3: 1)
    p_d: float = 1.0                # temperature factor (Sec. 3.3: 1)
    p_e: float = 0.814              # reliability factor, 99 % (Sec. 3.3)
    p_f: float = 1.0                # miscellaneous (Sec. 3.3: 1)


@dataclass
class VanCheck:
    """Result of :func:`check_van` (SI; stresses in Pa)."""
    preset: str
    dither_amplitude_n: float
    dither_frequency_hz: float
    n_piezos: int
    flexure_stiffness: float        # [N/m]
    force_per_volt: float           # flexure force per piezo volt [N/V]
    v_pp: float                     # piezo peak-to-peak voltage for the dither [V]
    power_per_piezo_w: float        # Eq. 3.7
    power_total_w: float
    heat_w: float                   # 10 % of the electrical power (Sec. 3.4.3)
    heat_per_move_j: float          # over one move of move_time
    max_load_n: float               # piezo at v_max against the flexure (worst case)
    d_e: float                      # Eq. 3.6 equivalent diameter [m]
    p_a: float
    p_b: float
    s_e_nominal: float              # S'_e = S_ut/2
    s_e: float                      # Eq. 3.4
    s_max: float                    # stress at max_load
    s_dither: float                 # stress at the dither's peak load (unipolar 0..2A)
    fatigue_safety: float           # S_e / S_max (worst case)
    yield_safety: float             # S_y / S_max
    fatigue_safety_dither: float    # S_e / S_dither
    passed: bool
    message: str


def check_van(preset, piezo: Piezo = Piezo(), flexure: Flexure = Flexure(), v_pp: Optional[float] = None,
              move_time: float = 0.25, heat_fraction: float = 0.1, min_safety: float = 1.0) -> VanCheck:
    """Piezo power (Eq. 3.7) and flexure fatigue (Eq. 3.4-3.6, Table 3.2) of a VAN preset.

    The piezo (stiffness ``k_p``) drives the flexure (stiffness ``k_j`` = the preset's joint) in
    series, so the flexure force per volt is ``k_j (x_free/v_max) k_p/(k_p + k_j)`` and the dither's
    ``2A`` peak-to-peak force needs ``V_pp = 2A / that``. ``P = f C V_pp²`` per piezo (Eq. 3.7).
    Fatigue: ``S_e = p_a p_b p_c p_d p_e p_f S'_e``, ``S'_e = S_ut/2``, ``p_a = 4.51 S_ut^-0.265``
    (S_ut in MPa), ``p_b = 1.24 d_e^-0.107``, ``d_e = 0.808 sqrt(h d)`` (mm); infinite life when
    the worst-case stress (piezo at ``v_max``) is below ``S_e`` (Sec. 3.3).

    Parameters
    ----------
    preset : str or Preset
        A preset with ``dither`` and dithered bearings on joints (e.g. ``van_stage``).
    piezo, flexure : Piezo, Flexure
        Actuator and flexure data (defaults: the seed's P-842.10 and Table 3.2).
    v_pp : float, optional
        Piezo peak-to-peak voltage [V]; default derived from the dither amplitude.
    move_time : float
        Duration of one point-to-point move for the heat estimate [s] (Sec. 3.4.3: 250 ms).
    heat_fraction : float
        Fraction of the electrical power turned into heat (Sec. 3.4.3: up to 10 %).
    min_safety : float
        Required fatigue and yield safety factors [-].

    Returns
    -------
    VanCheck

    Examples
    --------
    >>> v = check_van("van_stage", v_pp=20.0)
    >>> round(v.power_per_piezo_w, 3), round(v.s_e / 1e6, 1), v.passed
    (0.3, 196.4, True)
    """
    p = as_preset(preset)
    if p.dither is None:
        raise DesignError(f"preset {p.name}: no dither section, so there is no VAN design to check")
    dith = [b for b in p.stage.bearings if b.dither_channel is not None]
    if not dith or any(b.joint is None for b in dith):
        raise DesignError(f"preset {p.name}: the dithered bearings need compliant joints (the VAN flexures)")
    if not (min_safety > 0 and move_time > 0 and 0 <= heat_fraction <= 1):
        raise DesignError("min_safety and move_time must be > 0, heat_fraction in [0, 1]")
    k_j = dith[0].joint.stiffness
    kp = piezo.stiffness
    fpv = k_j * (piezo.free_stroke / piezo.v_max) * kp / (kp + k_j)
    A, f = p.dither.amplitude, p.dither.frequency
    vpp = 2.0 * A / fpv if v_pp is None else float(v_pp)
    if not (vpp >= 0 and math.isfinite(vpp)):
        raise DesignError(f"v_pp = {v_pp!r}: must be a finite voltage >= 0")
    pw = f * piezo.capacitance * vpp ** 2
    total = pw * len(dith)
    d_e = 0.808 * math.sqrt(flexure.h * 1e3 * flexure.d * 1e3) * 1e-3
    p_a = 4.51 * (flexure.s_ut / 1e6) ** -0.265
    p_b = 1.24 * (d_e * 1e3) ** -0.107
    s_e0 = 0.5 * flexure.s_ut
    s_e = p_a * p_b * flexure.p_c * flexure.p_d * flexure.p_e * flexure.p_f * s_e0
    f_max = piezo.v_max * fpv
    per_n = flexure.stress_ref / flexure.load_ref
    s_max, s_dith = per_n * f_max, per_n * fpv * vpp
    nf, ny = s_e / s_max, flexure.s_y / s_max
    passed = nf >= min_safety and ny >= min_safety
    msg = (f"{'PASS' if passed else 'FAIL'}: worst-case flexure stress {s_max / 1e6:.1f} MPa at {f_max:.0f} N "
           f"(piezo at {piezo.v_max:.0f} V); endurance limit S_e = {s_e / 1e6:.1f} MPa -> fatigue safety "
           f"{nf:.2f}, yield safety {ny:.2f} (required {min_safety:g})"
           + ("" if passed else ": finite fatigue life or yielding, redesign the flexure"))
    return VanCheck(preset=p.name, dither_amplitude_n=A, dither_frequency_hz=f, n_piezos=len(dith),
                    flexure_stiffness=k_j, force_per_volt=fpv, v_pp=vpp, power_per_piezo_w=pw, power_total_w=total,
                    heat_w=heat_fraction * total, heat_per_move_j=heat_fraction * total * move_time,
                    max_load_n=f_max, d_e=d_e, p_a=p_a, p_b=p_b, s_e_nominal=s_e0, s_e=s_e, s_max=s_max,
                    s_dither=s_dith, fatigue_safety=nf, yield_safety=ny, fatigue_safety_dither=s_e / s_dith
                    if s_dith > 0 else math.inf, passed=passed, message=msg)
