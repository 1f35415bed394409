"""Validated configuration of a simulated stage, its controller and its experiment add-ons.

A *preset* is one YAML file (see ``stage_sim/presets/``) holding a :class:`Preset`:
the stage (:class:`Stage`), the servo controller (:class:`Controller`), and optionally
the dither generator (:class:`Dither`) and SAI switch manager (:class:`SaiManager`).
All values are SI (m, kg, s, N, rad, N·m, A). Unknown keys, missing fields, NaN and
out-of-range values are refused with a :class:`ConfigError` that names the file,
the field, the bad value and what is allowed.

Examples
--------
>>> from stage_sim.config import load_preset
>>> p = load_preset("fi_stage")
>>> p.stage.table.mass > 0
True
"""
from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal, Optional, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

PRESET_DIR = Path(__file__).with_name("presets")

Pos = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNeg = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Finite = Annotated[float, Field(allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]


class ConfigError(ValueError):
    """A configuration file or mapping failed validation; the message says where and why."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


# --------------------------------------------------------------------------- friction
class DahlFriction(_Strict):
    """Dahl model, Eq. 1.1 (shape factor ``shape``) / Eq. 4.3 (shape = 1)."""
    model: Literal["dahl"]
    k_sigma: Pos = Field(description="initial contact stiffness [N/m]")
    f_c: Pos = Field(description="Coulomb force [N]")
    shape: Pos = Field(1.0, description="shape factor nu [-]")
    viscous: NonNeg = Field(0.0, description="viscous coefficient to ground [N·s/m]")


class GmsFriction(_Strict):
    """Generalized Maxwell-slip model with Coulomb slip, Eq. 4.4."""
    model: Literal["gms"]
    k: list[Pos] = Field(min_length=1, description="block stiffnesses k_i [N/m]")
    alpha: list[Pos] = Field(min_length=1, description="block saturation fractions alpha_i [-]")
    f_c: Pos = Field(description="Coulomb force [N]")
    viscous: NonNeg = Field(0.0, description="viscous coefficient to ground [N·s/m]")

    @model_validator(mode="after")
    def _same_length(self):
        if len(self.k) != len(self.alpha):
            raise ValueError(f"k has {len(self.k)} blocks but alpha has {len(self.alpha)}")
        return self


class LugreFriction(_Strict):
    """LuGre model with Stribeck curve g(v) = F_C + (F_S - F_C) exp(-|v/v_s|^exponent)."""
    model: Literal["lugre"]
    sigma0: Pos = Field(description="bristle stiffness [N/m]")
    sigma1: NonNeg = Field(0.0, description="bristle damping [N·s/m]")
    viscous: NonNeg = Field(0.0, description="viscous coefficient sigma2 [N·s/m]")
    f_c: Pos = Field(description="Coulomb force [N]")
    f_s: Pos = Field(description="static (break-away) force [N]")
    v_s: Pos = Field(description="Stribeck velocity [m/s]")
    exponent: Pos = Field(2.0, description="Stribeck exponent [-]")


class CoulombFriction(_Strict):
    """Coulomb + viscous friction with stiction (stick while |force| <= f_s)."""
    model: Literal["coulomb"]
    f_c: NonNeg = Field(description="Coulomb force [N]")
    f_s: Optional[NonNeg] = Field(None, description="static force [N]; default f_c")
    viscous: NonNeg = Field(0.0, description="viscous coefficient [N·s/m]")


Friction = Annotated[Union[DahlFriction, GmsFriction, LugreFriction, CoulombFriction],
                     Field(discriminator="model")]


# --------------------------------------------------------------------------- stage
class Table(_Strict):
    mass: Pos = Field(description="moving table mass [kg] (rotary: inertia [kg·m²])")


class Joint(_Strict):
    """Compliant joint (FI flexure, VAN flexure, SAI flexure) between table and bearing."""
    stiffness: Pos = Field(description="axial stiffness [N/m]")
    damping: NonNeg = Field(0.0, description="axial damping [N·s/m]")


class Bearing(_Strict):
    """A bearing carriage. Without ``joint`` it is rigidly bolted to the table (No FI)."""
    mass: Pos = Field(description="bearing (carriage + joint outer platform) mass [kg]")
    joint: Optional[Joint] = None
    friction: Friction
    dither_channel: Optional[Literal[0, 1]] = Field(None, description="piezo driving it (VAN)")
    force_noise_rms: NonNeg = Field(0.0, description="random friction force, per control sample [N]")


class StructuralMode(_Strict):
    """Lightly damped mode: a mass ``mass_ratio*m_table`` on a spring-damper to the table."""
    frequency: Pos = Field(description="blocked natural frequency [Hz]")
    damping_ratio: Annotated[float, Field(gt=0, lt=1, allow_inf_nan=False)]
    mass_ratio: Pos = Field(description="modal mass / table mass [-]")


class Drive(_Strict):
    force_constant: Pos = Field(description="motor force constant [N/A]")
    force_constant_ratio: Pos = Field(1.0, description="true / nominal force constant [-]")
    peak_force: Pos = Field(description="peak force limit [N]")
    continuous_force: Pos = Field(description="continuous (thermal, RMS) force limit [N]")
    thermal_time_constant: Pos = Field(5.0, description="I²t averaging time [s]")
    noise_current_rms: NonNeg = Field(0.0, description="drive current noise, RMS [A]")
    noise_cutoff: Optional[Pos] = Field(None, description="noise low-pass corner [Hz]; None = white at the control rate")
    delay_samples: Annotated[int, Field(ge=0, le=100)] = 0

    @model_validator(mode="after")
    def _limits(self):
        if self.continuous_force > self.peak_force:
            raise ValueError(f"continuous_force={self.continuous_force} exceeds peak_force={self.peak_force}")
        return self


class Sensor(_Strict):
    resolution: NonNeg = Field(description="quantization step [m]; 0 = ideal")


class Travel(_Strict):
    min: Finite
    max: Finite

    @model_validator(mode="after")
    def _order(self):
        if not self.max > self.min:
            raise ValueError(f"travel max={self.max} must exceed min={self.min}")
        return self


class SaiJoint(_Strict):
    """Semi-active isolator lock (Ch. 5): solenoids + PMs lock the flexure by contact friction.

    Applies to bearing 0, whose ``joint`` is the compliant flexure. In stiff mode a
    stick-slip element of stiffness ``lock_stiffness`` holds the flexure deflection
    present at locking; on unlocking the stored flexure force is released.
    """
    lock_stiffness: Pos = Field(description="stiffness of the friction lock [N/m]")
    lock_damping: NonNeg = Field(0.0, description="damping of the lock contact [N·s/m]")
    lock_capacity: Pos = Field(description="force the lock holds before slipping [N]")
    rc_cutoff: Optional[Pos] = Field(None, description="RC filter on the solenoid voltage [Hz]; None = no filter")
    switch_delay: NonNeg = Field(0.0, description="armature travel time after the filtered voltage crosses the threshold [s]")
    impact_impulse: NonNeg = Field(description="impulse of the armature impact on locking [N·s]")
    impact_duration: Pos = Field(description="duration of the impact force pulse [s]")
    cushioning: Fraction = Field(0.0, description="fraction of the impact removed by the rubber sheets [-]")


class Stage(_Strict):
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

    @model_validator(mode="after")
    def _consistency(self):
        if self.sai is not None and (not self.bearings or self.bearings[0].joint is None):
            raise ValueError("sai needs bearings[0] with a compliant joint")
        if self.bearing_sensor is not None and not any(b.joint for b in self.bearings):
            raise ValueError("bearing_sensor needs a bearing on a compliant joint")
        return self


# --------------------------------------------------------------------------- control
class Pid(_Strict):
    """PID with filtered derivative and clamping anti-windup, C = kp + ki/s + kd s/(s/wd + 1)."""
    kp: NonNeg = Field(description="proportional gain [N/m]")
    ki: NonNeg = Field(0.0, description="integral gain [N/(m·s)]")
    kd: NonNeg = Field(0.0, description="derivative gain [N·s/m]")
    derivative_cutoff: Optional[Pos] = Field(None, description="derivative filter corner [Hz]; None = unfiltered")
    output_limit: Optional[Pos] = Field(None, description="command saturation [N]; None = drive peak force")


class Dob(_Strict):
    """Inverse-model disturbance observer (Eq. C.1-C.5): G_n = gain / (s (s + pole))."""
    pole: NonNeg = Field(description="P of Eq. C.1 [1/s]")
    gain: Pos = Field(description="Z of Eq. C.1 for a force input [1/kg] (= Z[N/(A·kg)] / K_f)")
    q_cutoff: Pos = Field(description="Q filter bandwidth f_Q [Hz] (Eq. C.2)")


class Feedforward(_Strict):
    """Feedforward friction compensation from the reference (Fig. 4.15)."""
    friction: Friction
    stiffness_error: Annotated[float, Field(gt=-1, allow_inf_nan=False)] = 0.0


class Niasa(_Strict):
    """NIASA (Eq. A.1): nonlinear integral gain following a nominal Dahl model."""
    tau_d: Pos = Field(description="design time constant [s]")
    k_sigma: Pos = Field(description="nominal Dahl stiffness [N/m]")
    f_c: Pos = Field(description="nominal Coulomb force [N]")


class Controller(_Strict):
    rate: Pos = Field(10_000.0, description="control rate [Hz]")
    pid: Pid
    dob: Optional[Dob] = None
    feedforward: Optional[Feedforward] = None
    niasa: Optional[Niasa] = None


class Dither(_Strict):
    """Dither generator and harmonic-cancelling (HC) controller for a VAN stage (Ch. 3)."""
    amplitude: NonNeg = Field(description="dither force amplitude A per piezo [N]")
    frequency: Pos = Field(description="dither frequency f [Hz]")
    hc_gain: NonNeg = Field(0.0, description="K_HC of Eq. 3.3 [N/m]; 0 disables HC")
    regulation: Literal["continuous", "on_off"] = "continuous"
    off_after: NonNeg = Field(0.0, description="on-off regulation: dither off this long after the reference reaches its target [s]")
    preemptive: NonNeg = Field(0.0, description="dither starts this long before the first move [s]")


class Ilc(_Strict):
    """P-type ILC of Eq. 5.2 with a Butterworth low-pass."""
    iterations: Annotated[int, Field(ge=0, le=100)] = 10
    cutoff: Pos = Field(200.0, description="LPF corner [Hz]")
    order: Annotated[int, Field(ge=1, le=8)] = 4
    length: Pos = Field(0.1, description="length of the learned correction after a switch [s]")


class SaiManager(_Strict):
    """SAI switching rules (Ch. 5) and two-step error mitigation."""
    rule: Literal["point_to_point", "tracking", "always_compliant", "always_stiff"] = "point_to_point"
    release_lead: NonNeg = Field(0.005, description="p2p: go compliant this long before a move [s]")
    reversal_window: NonNeg = Field(0.0, description="tracking: compliant while |v_ref| below this [m/s]")
    ilc: Optional[Ilc] = None


class Simulation(_Strict):
    max_omega_h: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = Field(
        0.25, description="largest (stiffest-mode angular frequency x sub-step) allowed [-]")
    max_substeps: Annotated[int, Field(ge=1, le=1000)] = 200
    seed: Annotated[int, Field(ge=0)] = 0


class Preset(_Strict):
    name: str
    description: str = ""
    stage: Stage
    controller: Controller
    dither: Optional[Dither] = None
    sai_manager: Optional[SaiManager] = None
    simulation: Simulation = Simulation()


# --------------------------------------------------------------------------- loading
def _format(err: ValidationError, source: str) -> str:
    lines = [f"{source}: invalid configuration"]
    for e in err.errors():
        field = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden":
            msg = "unknown key"
        elif e["type"] == "missing":
            msg = "required field is missing"
        val = e.get("input")
        shown = "" if e["type"] == "missing" else f" (got {val!r})"
        lines.append(f"  {field}: {msg}{shown}")
    return "\n".join(lines)


def preset_from_dict(data: dict, source: str = "<dict>") -> Preset:
    """Validate a mapping as a :class:`Preset`; raise :class:`ConfigError` naming the field."""
    try:
        return Preset.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format(err, source)) from None


def read_yaml_file(name_or_path: str | Path, directory: Path, kind: str) -> tuple[dict, Path]:
    """Safely read a YAML mapping given by name (``directory/<name>.yaml``) or path.

    Returns ``(data, path)``; a missing file, invalid YAML or a non-mapping top level
    raise :class:`ConfigError` naming the file (and the shipped names of this ``kind``).
    No code is ever executed (``yaml.safe_load``).
    """
    path = Path(name_or_path)
    if not path.suffix:
        path = directory / f"{name_or_path}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in directory.glob("*.yaml")))
        raise ConfigError(f"{name_or_path}: no such {kind} file (shipped {kind}s: {known})")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: top level must be a mapping, got {type(data).__name__}")
    return data, path


def load_preset(name_or_path: str | Path) -> Preset:
    """Load a preset by name (``stage_sim/presets/<name>.yaml``) or path, safely (no code)."""
    data, path = read_yaml_file(name_or_path, PRESET_DIR, "preset")
    return preset_from_dict(data, str(path))


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


def with_overrides(preset: Preset, changes: dict) -> Preset:
    """Return a copy with dotted-path overrides, re-validated, e.g. ``{"stage.table.mass": 2}``."""
    data = preset.model_dump()
    for dotted, value in changes.items():
        set_dotted(data, dotted, value)
    return preset_from_dict(data, f"{preset.name} (overridden)")

