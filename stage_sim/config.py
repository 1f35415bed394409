"""Validated configuration of a simulated stage, its controller and its experiment add-ons.

A *preset* is one YAML file (see ``stage_sim/presets/``) holding a :class:`Preset`:
the stage (:class:`Stage`), the servo controller (:class:`Controller`), and optionally
the dither generator (:class:`Dither`) and SAI switch manager (:class:`SaiManager`).
All values are SI (m, kg, s, N, rad, N·m, A). Unknown keys, missing fields, NaN,
true/false for a number and out-of-range values are refused with a :class:`ConfigError`
that names the file, the field, the bad value and what is allowed. Dimensional fields
carry their unit and a plausible range (``json_schema_extra=unit(...)``): a preset file
value outside it -- most likely a wrong unit, e.g. N/µm for N/m -- is refused too, unless
the file sets ``plausibility: warn`` or ``off`` (see :mod:`stage_sim.validation`).

Examples
--------
>>> from stage_sim.config import load_preset
>>> p = load_preset("fi_stage")
>>> p.stage.table.mass > 0
True
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Literal, Optional

from pydantic import Field, ValidationError, model_validator

from stage_sim.friction import FRICTION
from stage_sim.friction import CoulombFriction, DahlFriction, GmsFriction, LugreFriction  # noqa: F401  (re-exported)
from stage_sim.schema import Finite, Fraction, NonNeg, Pos, Number, StrictModel  # noqa: F401  (re-exported)
from stage_sim.validation import (ConfigError, check_plausible, format_validation_error, load_yaml_file, model_axis,
                                  unit)

PRESET_DIR = Path(__file__).with_name("presets")



# --------------------------------------------------------------------------- friction
# Each law's schema lives with the law (stage_sim/friction/<law>.py); the registry builds the union.
Friction = FRICTION
"""A friction element: any law of the registry (:mod:`stage_sim.friction`), told apart by ``model``."""


# --------------------------------------------------------------------------- stage
class Table(StrictModel):
    mass: Pos = Field(description="moving table mass [kg] (rotary: inertia [kg·m²])",
                      json_schema_extra=unit("kg", 1e-4, 1e3))


class Joint(StrictModel):
    """Compliant joint (FI flexure, VAN flexure, SAI flexure) between table and bearing."""
    stiffness: Pos = Field(description="axial stiffness [N/m]", json_schema_extra=unit("N/m", 1.0, 1e10))
    damping: NonNeg = Field(0.0, description="axial damping [N·s/m]", json_schema_extra=unit("N·s/m", 1e-3, 1e5))


class Bearing(StrictModel):
    """A bearing carriage. Without ``joint`` it is rigidly bolted to the table (No FI)."""
    mass: Pos = Field(description="bearing (carriage + joint outer platform) mass [kg]",
                      json_schema_extra=unit("kg", 1e-4, 1e3))
    joint: Optional[Joint] = None
    friction: Friction
    dither_channel: Optional[Annotated[Literal[0, 1], Number]] = Field(None, description="piezo driving it (VAN)")
    force_noise_rms: NonNeg = Field(0.0, description="random friction force, per control sample [N]",
                                    json_schema_extra=unit("N", 1e-6, 1e2))


class StructuralMode(StrictModel):
    """Lightly damped mode: a mass ``mass_ratio*m_table`` on a spring-damper to the table."""
    frequency: Pos = Field(description="blocked natural frequency [Hz]", json_schema_extra=unit("Hz", 1.0, 1e5))
    damping_ratio: Annotated[float, Number, Field(gt=0, lt=1, allow_inf_nan=False)]
    mass_ratio: Pos = Field(description="modal mass / table mass [-]")


class Drive(StrictModel):
    force_constant: Pos = Field(description="motor force constant [N/A]", json_schema_extra=unit("N/A", 1e-2, 1e3))
    force_constant_ratio: Pos = Field(1.0, description="true / nominal force constant [-]")
    peak_force: Pos = Field(description="peak force limit [N]", json_schema_extra=unit("N", 1e-2, 1e5))
    continuous_force: Pos = Field(description="continuous (thermal, RMS) force limit [N]",
                                  json_schema_extra=unit("N", 1e-2, 1e5))
    thermal_time_constant: Pos = Field(5.0, description="I²t averaging time [s]",
                                       json_schema_extra=unit("s", 1e-2, 1e4))
    noise_current_rms: NonNeg = Field(0.0, description="drive current noise, RMS [A]",
                                      json_schema_extra=unit("A", 1e-7, 1e1))
    noise_cutoff: Optional[Pos] = Field(None, description="noise low-pass corner [Hz]; None = white at the control rate",
                                        json_schema_extra=unit("Hz", 1e-1, 1e6))
    delay_samples: Annotated[int, Number, Field(ge=0, le=100)] = 0
    delay_fraction: Annotated[float, Number, Field(ge=0, lt=1, allow_inf_nan=False)] = Field(
        0.0, description="fractional part of the drive delay [samples]: the command of sample k acts over "
        "[k + delay_samples + delay_fraction, k + 1 + delay_samples + delay_fraction) control periods "
        "(exact delayed zero-order hold)")

    @model_validator(mode="after")
    def _limits(self):
        if self.continuous_force > self.peak_force:
            raise ValueError(f"continuous_force={self.continuous_force} exceeds peak_force={self.peak_force}")
        return self


class Sensor(StrictModel):
    resolution: NonNeg = Field(description="quantization step [m]; 0 = ideal",
                               json_schema_extra=unit("m", 1e-12, 1e-3))


class Travel(StrictModel):
    min: Finite
    max: Finite

    @model_validator(mode="after")
    def _order(self):
        if not self.max > self.min:
            raise ValueError(f"travel max={self.max} must exceed min={self.min}")
        return self


class SaiJoint(StrictModel):
    """Semi-active isolator lock (Ch. 5): solenoids + PMs lock the flexure by contact friction.

    Applies to bearing 0, whose ``joint`` is the compliant flexure. In stiff mode a
    stick-slip element of stiffness ``lock_stiffness`` holds the flexure deflection
    present at locking; on unlocking the stored flexure force is released.
    """
    lock_stiffness: Pos = Field(description="stiffness of the friction lock [N/m]",
                                json_schema_extra=unit("N/m", 1e2, 1e10))
    lock_damping: NonNeg = Field(0.0, description="damping of the lock contact [N·s/m]",
                                 json_schema_extra=unit("N·s/m", 1e-3, 1e6))
    lock_capacity: Pos = Field(description="force the lock holds before slipping [N]",
                               json_schema_extra=unit("N", 1e-3, 1e4))
    rc_cutoff: Optional[Pos] = Field(None, description="RC filter on the solenoid voltage [Hz]; None = no filter",
                                     json_schema_extra=unit("Hz", 1e-1, 1e6))
    switch_delay: NonNeg = Field(0.0, description="armature travel time after the filtered voltage crosses the threshold [s]",
                                 json_schema_extra=unit("s", 1e-7, 1.0))
    impact_impulse: NonNeg = Field(description="impulse of the armature impact on locking [N·s]",
                                   json_schema_extra=unit("N·s", 1e-9, 1e1))
    impact_duration: Pos = Field(description="duration of the impact force pulse [s]",
                                 json_schema_extra=unit("s", 1e-7, 1.0))
    cushioning: Fraction = Field(0.0, description="fraction of the impact removed by the rubber sheets [-]")


class ForceRipple(StrictModel):
    """Position-periodic force on the table (motor cogging / commutation ripple):
    ``F = amplitude sin(2 pi x / period + phase)``."""
    amplitude: Finite = Field(description="force amplitude [N]")
    period: Pos = Field(description="spatial period [m]")
    phase: Finite = Field(0.0, description="phase at x = 0 [rad]")


class PeriodicForce(StrictModel):
    """Force on the table at a fixed frequency (e.g. net force of imbalanced dither piezos, a
    disturbance): ``F = amplitude sin(2 pi frequency t + phase)``, ``t`` = time since the trial start."""
    amplitude: Finite = Field(description="force amplitude [N]")
    frequency: Pos = Field(description="frequency [Hz]")
    phase: Finite = Field(0.0, description="phase at t = 0 [rad]")


class Stage(StrictModel):
    kind: Literal["linear", "rotary"] = "linear"
    table: Table
    bearings: list[Bearing] = Field(default_factory=list, max_length=2)
    table_friction: Optional[Friction] = Field(None, description="friction acting directly on the table")
    modes: list[StructuralMode] = Field(default_factory=list)
    drive: Drive
    encoder: Sensor
    bearing_sensor: Optional[Sensor] = None
    travel: Travel
    sai: Optional[SaiJoint] = None
    force_offset: Finite = Field(0.0, description="constant force on the table, +x (cable drag, tilt, amplifier offset) [N]")
    force_ripple: list[ForceRipple] = Field(default_factory=list, description="position-periodic table forces")
    periodic_force: list[PeriodicForce] = Field(default_factory=list, description="fixed-frequency table forces")

    @model_validator(mode="after")
    def _consistency(self):
        if self.sai is not None and (not self.bearings or self.bearings[0].joint is None):
            raise ValueError("sai needs bearings[0] with a compliant joint")
        if self.bearing_sensor is not None and not any(b.joint for b in self.bearings):
            raise ValueError("bearing_sensor needs a bearing on a compliant joint")
        return self


# --------------------------------------------------------------------------- control
class Pid(StrictModel):
    """PID with filtered derivative and clamping anti-windup, C = kp + ki/s + kd s/(s/wd + 1).

    ``derivative_discretization`` says how the filtered derivative becomes a difference equation
    (``D_k`` from the errors ``e_k``, ``dt`` the control period, ``wd = 2 pi derivative_cutoff``):

    * ``backward_euler`` (default): ``s = (1 - z^-1)/dt``, i.e. ``D_k = a D_{k-1} + kd (1 - a)/dt
      (e_k - e_{k-1})`` with ``a = 1/(1 + wd dt)``;
    * ``matched``: the pole matched, ``a = exp(-wd dt)`` in the same recurrence (zero at ``z = 1``,
      the derivative slope ``kd`` kept at low frequency) -- a common drive firmware form.

    Both tend to ``kd (e_k - e_{k-1})/dt`` for ``wd dt -> inf``; without ``derivative_cutoff`` the
    derivative is that plain difference whichever is chosen.
    """
    kp: NonNeg = Field(description="proportional gain [N/m]", json_schema_extra=unit("N/m", 1.0, 1e10))
    ki: NonNeg = Field(0.0, description="integral gain [N/(m·s)]", json_schema_extra=unit("N/(m·s)", 1e-2, 1e14))
    kd: NonNeg = Field(0.0, description="derivative gain [N·s/m]", json_schema_extra=unit("N·s/m", 1e-3, 1e7))
    derivative_cutoff: Optional[Pos] = Field(None, description="derivative filter corner [Hz]; None = unfiltered",
                                             json_schema_extra=unit("Hz", 1e-1, 1e6))
    derivative_discretization: Literal["backward_euler", "matched"] = Field(
        "backward_euler", description="difference equation of the filtered derivative: backward Euler "
        "(pole 1/(1 + wd dt)) or matched pole (exp(-wd dt)); see the class docstring")
    output_limit: Optional[Pos] = Field(None, description="command saturation [N]; None = drive peak force",
                                        json_schema_extra=unit("N", 1e-3, 1e5))


class Dob(StrictModel):
    """Inverse-model disturbance observer (Eq. C.1-C.5): G_n = gain / (s (s + pole))."""
    pole: NonNeg = Field(description="P of Eq. C.1 [1/s]", json_schema_extra=unit("1/s", 1e-3, 1e6))
    gain: Pos = Field(description="Z of Eq. C.1 for a force input [1/kg] (= Z[N/(A·kg)] / K_f)",
                      json_schema_extra=unit("1/kg", 1e-3, 1e4))
    q_cutoff: Pos = Field(description="Q filter bandwidth f_Q [Hz] (Eq. C.2)",
                          json_schema_extra=unit("Hz", 1e-1, 1e6))


class Feedforward(StrictModel):
    """Feedforward friction compensation from the reference (Fig. 4.15)."""
    friction: Friction
    stiffness_error: Annotated[float, Number, Field(gt=-1, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _no_variation(self):
        fr = self.friction
        if fr.f_c_difference or fr.viscous_difference or fr.f_c_gradient or fr.f_c_curvature:
            raise ValueError("feedforward friction models no friction variation: f_c_difference, "
                             "viscous_difference, f_c_gradient and f_c_curvature must be 0")
        return self


class Niasa(StrictModel):
    """NIASA (Eq. A.1): nonlinear integral gain following a nominal Dahl model."""
    tau_d: Pos = Field(description="design time constant [s]", json_schema_extra=unit("s", 1e-6, 1e1))
    k_sigma: Pos = Field(description="nominal Dahl stiffness [N/m]", json_schema_extra=unit("N/m", 1e2, 1e10))
    f_c: Pos = Field(description="nominal Coulomb force [N]", json_schema_extra=unit("N", 1e-3, 1e3))


class Controller(StrictModel):
    rate: Pos = Field(10_000.0, description="control rate [Hz]", json_schema_extra=unit("Hz", 1e1, 1e6))
    pid: Pid
    dob: Optional[Dob] = None
    feedforward: Optional[Feedforward] = None
    niasa: Optional[Niasa] = None


class Dither(StrictModel):
    """Dither generator and harmonic-cancelling (HC) controller for a VAN stage (Ch. 3)."""
    amplitude: NonNeg = Field(description="dither force amplitude A per piezo [N]",
                              json_schema_extra=unit("N", 1e-3, 1e4))
    frequency: Pos = Field(description="dither frequency f [Hz]", json_schema_extra=unit("Hz", 1.0, 1e6))
    hc_gain: NonNeg = Field(0.0, description="K_HC of Eq. 3.3 [N/m]; 0 disables HC",
                            json_schema_extra=unit("N/m", 1.0, 1e12))
    regulation: Literal["continuous", "on_off"] = "continuous"
    off_after: NonNeg = Field(0.0, description="on-off regulation: dither off this long after the reference reaches its target [s]",
                              json_schema_extra=unit("s", 1e-6, 1e3))
    preemptive: NonNeg = Field(0.0, description="dither starts this long before the first move [s]",
                               json_schema_extra=unit("s", 1e-6, 1e3))


class Ilc(StrictModel):
    """P-type ILC of Eq. 5.2 with a Butterworth low-pass."""
    iterations: Annotated[int, Number, Field(ge=0, le=100)] = 10
    cutoff: Pos = Field(200.0, description="LPF corner [Hz]", json_schema_extra=unit("Hz", 1e-1, 1e6))
    order: Annotated[int, Number, Field(ge=1, le=8)] = 4
    length: Pos = Field(0.1, description="length of the learned correction after a switch [s]",
                        json_schema_extra=unit("s", 1e-5, 1e2))


class SaiManager(StrictModel):
    """SAI switching rules (Ch. 5) and two-step error mitigation."""
    rule: Literal["point_to_point", "tracking", "always_compliant", "always_stiff"] = "point_to_point"
    release_lead: NonNeg = Field(0.005, description="p2p: go compliant this long before a move [s]",
                                 json_schema_extra=unit("s", 1e-6, 1e1))
    reversal_window: NonNeg = Field(0.0, description="tracking: compliant while |v_ref| below this [m/s]",
                                    json_schema_extra=unit("m/s", 1e-9, 1e1))
    ilc: Optional[Ilc] = None


class Simulation(StrictModel):
    max_omega_h: Annotated[float, Number, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.25, description="largest (stiffest-mode angular frequency x sub-step) allowed [-]")
    max_substeps: Annotated[int, Number, Field(ge=1, le=1000)] = 200
    seed: Annotated[int, Number, Field(ge=0)] = 0


NO_CONTROLLER = {"rate": 10_000.0, "pid": {"kp": 0.0}}
"""The controller of a preset that states none (a model of an open-loop record, e.g. a force-mode
identification run): no feedback (zero command), the default rate. A closed-loop tool given such a
preset runs its plant with zero command; the diagnosis refuses it for a record with a reference."""


class Preset(StrictModel):
    name: str
    description: str = ""
    stage: Stage
    controller: Controller = Field(default_factory=lambda: Controller(**NO_CONTROLLER),
                                   description="servo controller; omitted = no feedback (a model of open-loop data)")
    dither: Optional[Dither] = None
    sai_manager: Optional[SaiManager] = None
    simulation: Simulation = Simulation()
    plausibility: Literal["error", "warn", "off"] = Field(
        "error", description="a value outside its field's plausible range (a wrong unit?) is an error, "
        "a warning, or not checked (see stage_sim.validation)")


# --------------------------------------------------------------------------- loading
def _model_named(name: str, cls=None):
    for sub in (cls or StrictModel).__subclasses__():
        if sub.__name__ == name:
            return sub
        found = _model_named(name, sub)
        if found is not None:
            return found
    return None


def schema_error_message(err: ValidationError, source: str, kind: str = "configuration") -> str:
    """The message of :func:`stage_sim.validation.format_validation_error` for a schema of this
    package or one built on :class:`StrictModel` (experiments, campaigns), found by name."""
    return str(format_validation_error(err, source, kind if kind != "configuration" else err.title.lower(),
                                       _model_named(err.title)))


def preset_from_dict(data: dict, source: str = "<dict>") -> Preset:
    """Validate a mapping as a :class:`Preset`; raise :class:`ConfigError` naming the field."""
    try:
        return Preset.model_validate(data)
    except ValidationError as err:
        raise format_validation_error(err, source, "preset", Preset, model_axis(data)) from None


def read_yaml_file(name_or_path: str | Path, directory: Path, kind: str) -> tuple[dict, Path]:
    """Safely read a YAML mapping given by name (``directory/<name>.yaml``: a bare name without
    suffix) or path.

    Returns ``(data, path)``; a missing file, invalid YAML or a non-mapping top level
    raise :class:`ConfigError` naming the file (and the shipped names of this ``kind``).
    No code is ever executed, and the work is bounded (:func:`stage_sim.validation.load_yaml_file`:
    YAML's safe loader, which also refuses duplicate keys, size, alias-expansion, nesting and
    number-length limits, and anything but a regular file).
    """
    path = Path(name_or_path)
    if not path.suffix and len(path.parts) == 1:        # a bare name: a shipped file
        path = directory / f"{name_or_path}.yaml"
    if not os.path.lexists(path):
        known = ", ".join(sorted(p.stem for p in directory.glob("*.yaml")))
        raise ConfigError(f"{name_or_path}: no such {kind} file (shipped {kind}s: {known})")
    data = load_yaml_file(path, kind)
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data, path


def load_preset(name_or_path: str | Path) -> Preset:
    """Load a preset by name (``stage_sim/presets/<name>.yaml``) or path, safely (no code).

    Values outside their field's plausible range (a wrong unit?) are refused, unless
    the file sets ``plausibility: warn`` or ``off`` (see :mod:`stage_sim.validation`).
    """
    data, path = read_yaml_file(name_or_path, PRESET_DIR, "preset")
    preset = preset_from_dict(data, str(path))
    check_plausible(preset, str(path), preset.plausibility)
    return preset


def list_presets() -> list[str]:
    """Names of the presets shipped with the package."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.yaml"))


def set_dotted(data: dict, dotted: str, value) -> None:
    """Set ``value`` at a dotted path of a nested mapping, list items by index
    (``"stage.bearings.0.mass"``), in place."""
    node = data
    keys = dotted.split(".")
    for k in keys[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    if isinstance(node, list):
        node[int(keys[-1])] = value
    else:
        node[keys[-1]] = value


def _no_such(data, dotted: str) -> str:
    """Why ``dotted`` names nothing in ``data`` (the first key or index that is not there)."""
    node, done = data, []
    for part in dotted.split(".")[:-1]:
        if isinstance(node, list):
            if not (part.lstrip("-").isdigit() and -len(node) <= int(part) < len(node)):
                return f"{'.'.join(done)} has {len(node)} item(s), no item {part!r}"
            node = node[int(part)]
        elif isinstance(node, dict):
            if part not in node:
                return f"{'.'.join(done) or 'the preset'} has no field {part!r} (fields: {', '.join(node)})"
            node = node[part]
        else:
            return f"{'.'.join(done)} is {node!r}, not a mapping"
        done.append(part)
    return "not a settable field"


def with_overrides(preset: Preset, changes: dict, source: str | None = None) -> Preset:
    """Return a copy with dotted-path overrides, re-validated, e.g. ``{"stage.table.mass": 2}``.

    ``source`` names where the overrides come from (an experiment or campaign file, a
    command line) in errors; with a ``source`` the values set are also checked for
    plausibility like a preset file's (see :func:`load_preset`). Without one (code
    choosing values on purpose, e.g. a test driving a stage to divergence) they are not.
    """
    checked = source is not None
    source = source or f"{preset.name} (overridden)"
    data = preset.model_dump()
    for dotted, value in changes.items():
        try:
            set_dotted(data, dotted, value)
        except (KeyError, IndexError, ValueError, TypeError):
            raise ConfigError(f"{source}: override {dotted!r}: {_no_such(data, dotted)}") from None
    new = preset_from_dict(data, source)
    if checked:
        check_plausible(new, source, new.plausibility, paths=list(changes))
    return new

