"""A diagnosis model: a preset plus additive table forces the preset cannot express.

:class:`ModelSpec` is what every hypothesis modifies and every kernel runs. Its preset part
is a validated :class:`stage_sim.config.Preset` (so the improved model is a preset YAML the
simulator runs as is); its ``additive`` part lists forces on the table that the preset
schema cannot express yet (position-periodic ripple, position-dependent friction, offset,
a force at a fixed frequency, sparse-regression terms). They are run by the diagnosis
kernels (:mod:`.engine`) and written to the extended model file (``model.yaml``:
``{preset: ..., additive_forces: [...]}``), which ``nanostage synth`` also accepts as a truth.

Additive force kinds (force on the table [N], ``+`` = in the +x direction)
--------------------------------------------------------------------------
``offset``       ``c``
``sign_v``       ``c tanh(v / v_eps)``                         par: v_eps [m/s]
``velocity``     ``c v``
``sin_x``        ``c sin(2 pi x / period + phase)``            par: period [m], phase [rad]
``friction_x``   ``c phi_f ((x - center)/scale)^power``        par: center, scale [m], power
                 (``phi_f`` = nominal table friction / its F_C, -1..1, follows pre-motion)
``sin_t``        ``c sin(2 pi f t + phase)``                   par: f [Hz], phase [rad]
``poly_x``       ``c ((x - center)/scale)^power``              par: center, scale [m], power
``v_abs_v``      ``c v |v|``
``abs_friction`` ``c |phi_f|``                                  (direction-asymmetric friction level)
``abs_v``        ``c |v|``                                      (direction-asymmetric viscous friction)
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from stage_sim.config import ConfigError, Preset, load_preset, preset_from_dict, set_dotted
from stage_sim.plant import build_plant

from .engine import ADD_KINDS, N_ADD_PAR, mechanical

__all__ = ["AddTerm", "ModelSpec", "Compiled", "load_model", "friction_elements", "table_mass"]


@dataclass(frozen=True)
class AddTerm:
    """One additive table force ``coef * phi(kind, par)`` (see module docstring)."""
    kind: str
    coef: float
    par: tuple = ()
    label: str = ""

    def to_dict(self) -> dict:
        names = {"sign_v": ["v_eps"], "sin_x": ["period", "phase"], "friction_x": ["center", "scale", "power"],
                 "sin_t": ["frequency", "phase"], "poly_x": ["center", "scale", "power"]}.get(self.kind, [])
        d = {"kind": self.kind, "coef": float(self.coef)}
        d.update({k: float(v) for k, v in zip(names, self.par)})
        if self.label:
            d["label"] = self.label
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "AddTerm":
        d = dict(d)
        kind = {"ripple": "sin_x"}.get(d.get("kind"), d.get("kind"))
        d.pop("kind", None)
        if kind not in ADD_KINDS:
            raise ConfigError(f"additive force kind {kind!r} unknown (known: {', '.join(ADD_KINDS)})")
        label = d.pop("label", "")
        coef = float(d.pop("coef", d.pop("amplitude", 0.0)))
        order = {"sign_v": ["v_eps"], "sin_x": ["period", "phase"], "friction_x": ["center", "scale", "power"],
                 "sin_t": ["frequency", "phase"], "poly_x": ["center", "scale", "power"]}.get(kind, [])
        par = tuple(float(d.pop(k, 0.0)) for k in order)
        if d:
            raise ConfigError(f"additive force {kind!r}: unknown key(s) {sorted(d)}")
        return cls(kind, coef, par, label)


def friction_elements(preset: Preset) -> list[tuple[str, object]]:
    """``(dotted path, friction config)`` of every friction element of the stage."""
    out = []
    st = preset.stage
    if st.table_friction is not None:
        out.append(("stage.table_friction", st.table_friction))
    for i, b in enumerate(st.bearings):
        out.append((f"stage.bearings.{i}.friction", b.friction))
    return out


def table_mass(preset: Preset) -> float:
    """Mass moving with the table at high frequency: table + rigidly bolted bearings [kg]."""
    st = preset.stage
    return st.table.mass + sum(b.mass for b in st.bearings if b.joint is None)


def total_mass(preset: Preset) -> float:
    """Every body of the stage [kg] (the low-frequency rigid-body mass)."""
    st = preset.stage
    return st.table.mass + sum(b.mass for b in st.bearings) + sum(m.mass_ratio * st.table.mass for m in st.modes)


def coulomb_total(preset: Preset) -> float:
    """Sum of the Coulomb forces of the friction elements [N]."""
    return float(sum(getattr(fr, "f_c", 0.0) for _, fr in friction_elements(preset)))


@dataclass
class Compiled:
    """Arrays the kernels need for one :class:`ModelSpec`."""
    pm: object             # mechanical PlantModel (noise-free unless keep_noise)
    pm_full: object        # the full PlantModel (drive noise etc.)
    kf: float
    delay: int
    peak: float
    cont: float
    th_alpha: float
    noise_std: float
    noise_a: float
    noise_gain: float
    kinds: np.ndarray
    par: np.ndarray
    coef: np.ndarray
    fc_tot: float
    m_eff: float

    def drive_args(self):
        return (self.kf, self.delay, self.peak, self.cont, self.th_alpha)

    def add_args(self):
        return (self.kinds, self.par, self.coef, self.fc_tot)


@dataclass
class ModelSpec:
    """Preset (validated) + additive table forces."""
    preset: Preset
    additive: tuple = ()
    notes: tuple = ()
    _compiled: dict = field(default_factory=dict, repr=False, compare=False)

    # ------------------------------------------------------------------ editing
    def with_changes(self, changes: dict | None = None, edit=None, add=(), notes=()) -> "ModelSpec":
        """New spec: dotted-path ``changes``, then ``edit(dict)`` on the preset mapping,
        plus additive terms ``add``."""
        data = self.preset.model_dump()
        for dotted, value in (changes or {}).items():
            set_dotted(data, dotted, value)
        if edit is not None:
            edit(data)
        preset = preset_from_dict(data, f"{self.preset.name} (diagnosis)")
        return ModelSpec(preset, tuple(self.additive) + tuple(add), tuple(self.notes) + tuple(notes))

    # ------------------------------------------------------------------ compiling
    def compiled(self, for_sim: bool = False) -> Compiled:
        """Kernel arrays; ``for_sim`` keeps quantization and random friction (closed-loop
        simulation), otherwise the plant is noise-free and unquantized (observer)."""
        key = bool(for_sim)
        if key in self._compiled:
            return self._compiled[key]
        p = self.preset
        sim = p.simulation
        full = build_plant(p.stage, p.controller.rate, sim.max_omega_h, sim.max_substeps)
        pm = mechanical(full, keep_noise=for_sim, keep_quantization=for_sim)
        d = p.stage.drive
        m = len(self.additive)
        kinds = np.array([ADD_KINDS[a.kind] for a in self.additive], np.int64)
        par = np.zeros((m, N_ADD_PAR))
        for j, a in enumerate(self.additive):
            par[j, :len(a.par)] = a.par
            if a.kind == "sign_v" and par[j, 0] <= 0:
                par[j, 0] = 1e-6
        coef = np.array([a.coef for a in self.additive], float)
        fc_tot = sum(getattr(fr, "f_c", 0.0) for path, fr in friction_elements(p)
                     if path == "stage.table_friction" or p.stage.bearings[int(path.split(".")[2])].joint is None)
        c = Compiled(pm=pm, pm_full=full, kf=d.force_constant_ratio, delay=d.delay_samples, peak=d.peak_force,
                     cont=d.continuous_force, th_alpha=full.th_alpha, noise_std=full.noise_std,
                     noise_a=full.noise_a, noise_gain=full.noise_gain, kinds=kinds, par=par, coef=coef,
                     fc_tot=float(fc_tot), m_eff=table_mass(p))
        self._compiled[key] = c
        return c

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict:
        return {"preset": self.preset.model_dump(mode="json"),
                "additive_forces": [a.to_dict() for a in self.additive]}

    def preset_yaml(self) -> str:
        head = f"# {self.preset.name}: written by nanostage diagnose\n"
        for n in self.notes:
            head += f"# {n}\n"
        if self.additive:
            head += ("# NOTE: the diagnosed model also has additive table forces this preset schema cannot\n"
                     "# express; see model.yaml (additive_forces), which `nanostage synth` runs.\n")
        return head + yaml.safe_dump(self.preset.model_dump(mode="json"), sort_keys=False)

    def model_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)


def load_model(source) -> ModelSpec:
    """A preset name/path, a preset mapping, or an extended model ``{preset, additive_forces}``."""
    if isinstance(source, ModelSpec):
        return source
    if isinstance(source, Preset):
        return ModelSpec(source)
    if isinstance(source, dict):
        data = source
        where = "<mapping>"
    else:
        path = Path(source)
        if not path.suffix:
            return ModelSpec(load_preset(source))
        if not path.is_file():
            raise ConfigError(f"{source}: no such file")
        where = str(path)
        try:
            data = yaml.safe_load(path.read_text())
        except yaml.YAMLError as err:
            raise ConfigError(f"{path}: not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: top level must be a mapping")
    if "additive_forces" in data or ("preset" in data and "stage" not in data):
        extra = set(data) - {"preset", "additive_forces"}
        if extra:
            raise ConfigError(f"{where}: unknown key(s) {sorted(extra)} (a model file has preset, additive_forces)")
        pre = data["preset"]
        if isinstance(pre, str):
            base = Path(where).parent if where != "<mapping>" else Path(".")
            cand = base / pre
            preset = load_preset(cand if cand.suffix and cand.is_file() else pre)
        else:
            preset = preset_from_dict(pre, f"{where}: preset")
        terms = tuple(AddTerm.from_dict(t) for t in (data.get("additive_forces") or []))
        return ModelSpec(preset, terms)
    return ModelSpec(preset_from_dict(data, where))
