"""A diagnosis model: a validated preset (every effect of the library is a preset field).

:class:`ModelSpec` is what every hypothesis modifies and every kernel runs: a validated
:class:`stage_sim.config.Preset`, so the improved model is a preset YAML the simulator (batch
engine and ROS graph) runs as is. Forces on the table are plant features too (a model file's
``additive_forces`` block is refused with a message naming these fields): ``stage.force_offset``, ``stage.force_ripple``, ``stage.periodic_force`` and
the friction variations (``f_c_difference``, ``viscous_difference``, ``f_c_gradient``,
``f_c_curvature``, ``position_center`` of each friction element).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import yaml

from stage_sim.config import ConfigError, Preset, load_preset, preset_from_dict, set_dotted
from stage_sim.validation import load_yaml_file
from stage_sim.plant_model import build_plant

from .engine import observer_model

__all__ = ["ModelSpec", "Compiled", "load_model", "friction_elements", "table_mass"]


def friction_elements(preset: Preset) -> list[tuple[str, object]]:
    """``(dotted path, friction config)`` of every friction element of the stage.

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage.

    Returns
    -------
    list of tuple
        The table's friction first (if any), then each bearing's, e.g. ``("stage.bearings.0.friction", cfg)``.
    """
    out = []
    st = preset.stage
    if st.table_friction is not None:
        out.append(("stage.table_friction", st.table_friction))
    for i, b in enumerate(st.bearings):
        out.append((f"stage.bearings.{i}.friction", b.friction))
    return out


def table_mass(preset: Preset) -> float:
    """Mass moving with the table at high frequency: table + rigidly bolted bearings [kg].

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage.

    Returns
    -------
    float
    """
    st = preset.stage
    return st.table.mass + sum(b.mass for b in st.bearings if b.joint is None)


def total_mass(preset: Preset) -> float:
    """Every body of the stage [kg] (the low-frequency rigid-body mass).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage.

    Returns
    -------
    float
        Table, bearings and the modes' split-off masses.
    """
    st = preset.stage
    return st.table.mass + sum(b.mass for b in st.bearings) + sum(m.mass_ratio * st.table.mass for m in st.modes)


def coulomb_total(preset: Preset) -> float:
    """Sum of the Coulomb forces of the friction elements [N].

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage.

    Returns
    -------
    float
    """
    return float(sum(getattr(fr, "f_c", 0.0) for _, fr in friction_elements(preset)))


def viscous_total(preset: Preset) -> float:
    """The stage's total viscous coefficient, table and bearings [N·s/m].

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The stage.

    Returns
    -------
    float
    """
    st = preset.stage
    c = st.table_friction.viscous if st.table_friction is not None else 0.0
    return c + sum(b.friction.viscous for b in st.bearings)


@dataclass
class Compiled:
    """What the kernels need for one :class:`ModelSpec`.

    Parameters
    ----------
    pm : stage_sim.plant_model.PlantModel
        The observer's plant model (noise-free, ideal sensor; drive kept).
    pm_full : stage_sim.plant_model.PlantModel
        The full plant model.
    fc_tot : float
        Coulomb force of the friction elements on the table's degree of freedom [N].
    m_eff : float
        Table mass at high frequency [kg] (:func:`table_mass`).
    """
    pm: object             # observer PlantModel (noise-free, ideal sensor; drive kept)
    pm_full: object        # the full PlantModel
    fc_tot: float          # Coulomb force of the friction elements on the table DOF [N]
    m_eff: float           # table mass at high frequency [kg]


@dataclass
class ModelSpec:
    """A validated preset (and notes for the improved-preset header).

    Parameters
    ----------
    preset : stage_sim.config.Preset
        The model.
    notes : tuple of str
        Lines of the header of the written preset (:meth:`preset_yaml`).
    _compiled : dict
        Cache of :meth:`compiled` (not compared, not pickled).
    """
    preset: Preset
    notes: tuple = ()
    _compiled: dict = field(default_factory=dict, repr=False, compare=False)

    def with_changes(self, changes: dict | None = None, edit=None, notes=()) -> "ModelSpec":
        """New spec: dotted-path ``changes``, then ``edit(dict)`` on the preset mapping.

        Parameters
        ----------
        changes : dict, optional
            Dotted path (``"stage.table.mass"``) -> value (SI units).
        edit : callable, optional
            ``edit(data)`` changes the preset mapping in place, after ``changes``.
        notes : tuple of str
            Appended to the spec's notes.

        Returns
        -------
        ModelSpec
            Validated again (:func:`stage_sim.config.preset_from_dict`).
        """
        data = self.preset.model_dump()
        for dotted, value in (changes or {}).items():
            set_dotted(data, dotted, value)
        if edit is not None:
            edit(data)
        preset = preset_from_dict(data, f"{self.preset.name} (diagnosis)")
        return ModelSpec(preset, tuple(self.notes) + tuple(notes))

    def compiled(self) -> Compiled:
        """Kernel arrays (built once per spec).

        Returns
        -------
        Compiled
        """
        if "c" in self._compiled:
            return self._compiled["c"]
        p = self.preset
        sim = p.simulation
        full = build_plant(p.stage, p.controller.rate, sim.max_omega_h, sim.max_substeps)
        fc_tot = sum(getattr(fr, "f_c", 0.0) for path, fr in friction_elements(p)
                     if path == "stage.table_friction" or p.stage.bearings[int(path.split(".")[2])].joint is None)
        c = Compiled(pm=observer_model(full), pm_full=full, fc_tot=float(fc_tot), m_eff=table_mass(p))
        self._compiled["c"] = c
        return c

    def __getstate__(self) -> dict:
        """Pickle (process pool / Dask candidate fits) without the compiled kernel arrays:
        they are rebuilt on first use where the spec lands."""
        state = dict(self.__dict__)
        state["_compiled"] = {}
        return state

    # ------------------------------------------------------------------ files
    def preset_yaml(self) -> str:
        """The preset as YAML, headed by its notes as comments (the improved model a user can load).

        Returns
        -------
        str
        """
        head = f"# {self.preset.name}: written by nanostage diagnose\n"
        for n in self.notes:
            head += f"# {n}\n"
        return head + yaml.safe_dump(self.preset.model_dump(mode="json"), sort_keys=False)


def load_model(source) -> ModelSpec:
    """A preset name/path, a preset mapping, a :class:`Preset`, or a model file ``{preset: ...}``.

    Parameters
    ----------
    source : str, pathlib.Path, dict, Preset or ModelSpec
        A shipped preset's name, a YAML file (a preset or ``{preset: ...}``), a mapping, a preset,
        or a spec (returned as is).

    Returns
    -------
    ModelSpec

    Raises
    ------
    stage_sim.config.ConfigError
        Not a mapping, an invalid preset, or a field no longer supported (``additive_forces``).
    """
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
        where = str(path)
        data = load_yaml_file(path, "model")
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: top level must be a mapping")
    if "additive_forces" in data:
        raise ConfigError(f"{where}: additive_forces are no longer supported: use the preset fields "
                          "stage.force_offset, stage.force_ripple, stage.periodic_force and the friction "
                          "variations (f_c_difference, viscous_difference, f_c_gradient, f_c_curvature)")
    if "preset" in data and "stage" not in data:
        extra = set(data) - {"preset"}
        if extra:
            raise ConfigError(f"{where}: unknown key(s) {sorted(extra)} (a model file has preset)")
        pre = data["preset"]
        if isinstance(pre, str):
            base = Path(where).parent if where != "<mapping>" else Path(".")
            cand = base / pre
            return ModelSpec(load_preset(cand if cand.suffix and cand.is_file() else pre))
        return ModelSpec(preset_from_dict(pre, f"{where}: preset"))
    return ModelSpec(preset_from_dict(data, where))
