"""Translate a recording's ``nominal_model`` block into a nanostage preset.

A rig whose software states its model in its own terms writes, in ``/experiment/config``, a
``nominal_model`` block (and ``conventions`` defining every symbol; the independent simulator of
``shared/independent`` writes this form)::

    nominal_model:
      plant: {m: 2.0, friction: dahl, F_C: 5.31, c: 20.0, k_sigma: 2.19e6, noise_std: 0.02}
      controller: {type: PID, Kp: ..., Ki: ..., Kd: ..., f_d: 1000.0, design: "..."}
      Ts: 1.0e-4
      quantization_m: 4.88e-9

:func:`preset_from_nominal` gives the equivalent preset mapping, term by term (all SI):

========================================  =====================================================
``nominal_model``                         preset
========================================  =====================================================
rigid mass ``m``                          ``stage.table.mass``
``friction: dahl``: ``dF/dt = k_sigma     ``stage.table_friction``: ``dahl`` with ``shape`` 1
(v - |v| F/F_C)``, ``F + c v``            (``dF/dx = k_sigma (1 - F/F_C sgn dx)``, the same law
                                          in the displacement domain), ``f_c``, ``viscous: c``
``friction: coulomb``: ``F_C tanh(v /    ``regularized_coulomb`` (``f_c tanh(v / v_reg)``),
v_eps) + c v``                            ``v_reg: v_eps``, ``viscous: c``
white drive force ``N(0, noise_std^2)``,  ``stage.drive.noise_current_rms = noise_std`` with
one draw per ``Ts``, held, at the plant   ``force_constant`` 1 N/A (the command is a force),
                                          ``noise_cutoff`` none (white at the control rate)
encoder ``round(x/q) q``                  ``stage.encoder.resolution: quantization_m``
``u_k`` from ``y_k``, applied over        ``stage.drive.delay_samples: 1`` (the batch engine
``[t_{k+1}, t_{k+2})``                    applies the command of sample k over [k, k+1))
PID ``u = Kp e + I + D``, ``I_k =         ``controller.pid``: ``kp, ki, kd``,
I_{k-1} + Ki Ts e_k``, ``D_k = a D_{k-1}  ``derivative_cutoff: f_d``,
+ Kd (1-a)/Ts (e_k - e_{k-1})``,          ``derivative_discretization: matched``
``a = exp(-2 pi f_d Ts)``                 (:func:`stage_control.servo.derivative_filter`)
``Ts``                                    ``controller.rate = 1/Ts``
========================================  =====================================================

What the block does not state is chosen so that it never acts: no force limit (peak and
continuous force 1e5 N), a travel of +-1 m, no stiction (the laws above have none). Each term the
block holds must be one the conventions define; anything else (another friction law, a
controller that is not a PID, a field the conventions do not name) is refused with a
:class:`~stage_sim.validation.ConfigError` naming ``nominal_model.<field>``, its value and what is
allowed -- a term dropped in silence would be a nominal model the recording's rig never had.

Used by ``nanostage diagnose REC`` (no NOMINAL: the recording's block is translated) and written
out by ``nanostage convert nominal REC --out preset.yaml`` (:func:`main_convert_nominal`).

Examples
--------
>>> block = {"plant": {"m": 2.0, "friction": "dahl", "F_C": 5.31, "c": 20.0, "k_sigma": 2.19e6,
...                    "noise_std": 0.02},
...          "controller": {"type": "PID", "Kp": 2.0e6, "Ki": 3.1e8, "Kd": 1500.0, "f_d": 1000.0},
...          "Ts": 1e-4, "quantization_m": 4.88e-9}
>>> p = preset_from_nominal(block)
>>> p["stage"]["table_friction"]["model"], p["stage"]["drive"]["delay_samples"]
('dahl', 1)
>>> p["controller"]["rate"], p["controller"]["pid"]["derivative_discretization"]
(10000.0, 'matched')
>>> preset_from_nominal(dict(block, plant=dict(block["plant"], friction="lugre")))
Traceback (most recent call last):
...
stage_sim.validation.ConfigError: nominal_model.plant.friction = 'lugre': not a law the conventions define; allowed: 'dahl' (dF/dt = k_sigma (v - |v| F/F_C), F_fric = F + c v) or 'coulomb' (F_fric = F_C tanh(v/v_eps) + c v)
"""
from __future__ import annotations

import math
from pathlib import Path

from experiment_runner.core import outputs
from experiment_runner.core.outputs import add_overwrite_argument
from experiment_runner.core.recording import read_recording
from stage_sim.config import preset_from_dict
from stage_sim.validation import ConfigError, load_yaml, plausibility_problems

__all__ = ["has_nominal_model", "preset_from_nominal", "nominal_preset_from_config", "nominal_preset_from_doc", "preset_yaml",
           "add_convert_nominal_arguments", "main_convert_nominal"]

# the terms the conventions define, per part of the block: field -> meaning (the refusal lists them)
PLANT_FIELDS = {"m": "rigid mass [kg]", "friction": "'dahl' or 'coulomb'", "F_C": "Coulomb force [N]",
                "c": "viscous coefficient [N·s/m]", "k_sigma": "Dahl stiffness [N/m] (dahl)",
                "v_eps": "tanh regularisation velocity [m/s] (coulomb)",
                "noise_std": "white drive force per Ts, RMS [N]"}
LAW_FIELDS = {"dahl": ("k_sigma",), "coulomb": ("v_eps",)}
LAWS = {"dahl": "dF/dt = k_sigma (v - |v| F/F_C), F_fric = F + c v",
        "coulomb": "F_fric = F_C tanh(v/v_eps) + c v"}
CONTROLLER_FIELDS = {"type": "'PID'", "Kp": "[N/m]", "Ki": "[N/(m·s)]", "Kd": "[N·s/m]",
                     "f_d": "derivative filter corner [Hz]", "design": "free text"}
BLOCK_FIELDS = {"plant": "the plant", "controller": "the PID", "Ts": "control period [s]",
                "quantization_m": "encoder quantum [m]"}
NO_LIMIT_N = 1e5
"""Peak and continuous force of the translated drive [N]: the block states no limit."""
TRAVEL_M = 1.0
"""Half travel of the translated stage [m]: the block states none."""

# preset field -> the block's field it comes from (to name the user's field in a plausibility error)
_ORIGIN = {"stage.table.mass": "plant.m", "stage.table_friction.f_c": "plant.F_C",
           "stage.table_friction.viscous": "plant.c", "stage.table_friction.k_sigma": "plant.k_sigma",
           "stage.table_friction.v_reg": "plant.v_eps", "stage.drive.noise_current_rms": "plant.noise_std",
           "stage.encoder.resolution": "quantization_m", "controller.rate": "Ts", "controller.pid.kp": "controller.Kp",
           "controller.pid.ki": "controller.Ki", "controller.pid.kd": "controller.Kd",
           "controller.pid.derivative_cutoff": "controller.f_d"}


def has_nominal_model(doc) -> bool:
    """Whether a parsed ``/experiment/config`` carries a ``nominal_model`` block.

    >>> has_nominal_model({"nominal_model": {"plant": {}}}), has_nominal_model({"preset": {}})
    (True, False)
    """
    return isinstance(doc, dict) and "nominal_model" in doc


def _where(source: str | None, field: str) -> str:
    name = f"nominal_model.{field}" if field else "nominal_model"
    return f"{source}: {name}" if source else name


def _mapping(obj, field: str, source) -> dict:
    if not isinstance(obj, dict):
        raise ConfigError(f"{_where(source, field)} = {obj!r}: must be a mapping")
    return obj


def _unknown(part: dict, allowed: dict, prefix: str, source) -> None:
    for k in part:
        if k not in allowed:
            raise ConfigError(f"{_where(source, prefix + str(k))} = {part[k]!r}: not a term the conventions define, "
                              f"so it cannot be expressed faithfully; allowed: {', '.join(allowed)}")


def _number(part: dict, key: str, prefix: str, source, lo: float = 0.0, strict: bool = False) -> float:
    """A required finite number ``>= lo`` (``> lo`` if ``strict``)."""
    if key not in part:
        raise ConfigError(f"{_where(source, prefix + key)}: missing ({(PLANT_FIELDS | CONTROLLER_FIELDS | BLOCK_FIELDS).get(key, '')}"
                          f"{'; 0 for none' if not strict else ''})")
    v = part[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise ConfigError(f"{_where(source, prefix + key)} = {v!r}: must be a finite number")
    if v < lo or (strict and v == lo):
        raise ConfigError(f"{_where(source, prefix + key)} = {v!r}: must be {'>' if strict else '>='} {lo:g}")
    return float(v)


def preset_from_nominal(block: dict, source: str | None = None, name: str = "nominal",
                        conventions: dict | None = None) -> dict:
    """The preset mapping equivalent to a ``nominal_model`` block (see the module docstring).

    Parameters
    ----------
    block : dict
        The ``nominal_model`` mapping: ``plant``, ``controller``, ``Ts``, ``quantization_m``.
    source : str, optional
        Where the block comes from (a recording), named in errors.
    name : str
        The preset's name.
    conventions : dict, optional
        The recording's ``conventions``; their names are noted in the preset's description.

    Returns
    -------
    dict
        A preset mapping, validated (:func:`stage_sim.config.preset_from_dict`) and plausible.

    Raises
    ------
    ConfigError
        A term that cannot be expressed, missing or not a number, naming ``nominal_model.<field>``.
    """

    block = _mapping(block, "", source)
    _unknown(block, BLOCK_FIELDS, "", source)
    plant = _mapping(block.get("plant"), "plant", source)
    ctrl = _mapping(block.get("controller"), "controller", source)
    _unknown(plant, PLANT_FIELDS, "plant.", source)
    _unknown(ctrl, CONTROLLER_FIELDS, "controller.", source)

    law = plant.get("friction")
    if law not in LAWS:
        raise ConfigError(f"{_where(source, 'plant.friction')} = {law!r}: not a law the conventions define; "
                          f"allowed: " + " or ".join(f"{k!r} ({v})" for k, v in LAWS.items()))
    m = _number(plant, "m", "plant.", source, strict=True)
    f_c = _number(plant, "F_C", "plant.", source, strict=law == "dahl")
    c = _number(plant, "c", "plant.", source)
    noise = _number(plant, "noise_std", "plant.", source)
    if law == "dahl":
        friction = {"model": "dahl", "k_sigma": _number(plant, "k_sigma", "plant.", source, strict=True),
                    "f_c": f_c, "shape": 1.0, "viscous": c}
    else:
        friction = {"model": "regularized_coulomb", "f_c": f_c,
                    "v_reg": _number(plant, "v_eps", "plant.", source, strict=True), "viscous": c}
    unused = [k for ls, keys in LAW_FIELDS.items() if ls != law for k in keys if k in plant]

    kind = ctrl.get("type", "PID")
    if kind != "PID":
        raise ConfigError(f"{_where(source, 'controller.type')} = {kind!r}: only 'PID' (the conventions' parallel "
                          "PID) can be expressed")
    ts = _number(block, "Ts", "", source, strict=True)
    pid = {"kp": _number(ctrl, "Kp", "controller.", source), "ki": _number(ctrl, "Ki", "controller.", source),
           "kd": _number(ctrl, "Kd", "controller.", source),
           "derivative_cutoff": _number(ctrl, "f_d", "controller.", source, strict=True),
           "derivative_discretization": "matched"}
    q = _number(block, "quantization_m", "", source)

    notes = [f"translated from the nominal_model block of {source or 'a recording'} (nanostage "
             "experiment_runner.core.nominal_model): friction law " + LAWS[law],
             "one-sample computation delay -> drive.delay_samples 1; PID derivative pole exp(-2 pi f_d Ts) -> "
             "derivative_discretization matched; drive noise white per Ts -> noise_current_rms at force_constant 1 N/A",
             f"not stated by the block, chosen never to act: force limits {NO_LIMIT_N:g} N, travel +-{TRAVEL_M:g} m"]
    if unused:
        notes.append(f"ignored (no term of the {law} law): " + ", ".join(f"plant.{k}" for k in unused))
    if ctrl.get("design"):
        notes.append(f"controller design (as stated): {ctrl['design']}")
    if isinstance(conventions, dict):
        notes.append("the block's conventions (" + ", ".join(map(str, conventions)) + ") are those translated here")
    preset = {
        "name": name,
        "description": "\n".join(notes),
        "stage": {"kind": "linear", "table": {"mass": m}, "bearings": [], "table_friction": friction,
                  "drive": {"force_constant": 1.0, "peak_force": NO_LIMIT_N, "continuous_force": NO_LIMIT_N,
                            "noise_current_rms": noise, "delay_samples": 1},
                  "encoder": {"resolution": q}, "travel": {"min": -TRAVEL_M, "max": TRAVEL_M}},
        "controller": {"rate": 1.0 / ts, "pid": pid},
    }
    where = source or "nominal_model"
    p = preset_from_dict(preset, f"{where} (translated nominal_model)")
    problems = plausibility_problems(p)
    if problems:
        pr = problems[0]
        origin = _ORIGIN.get(pr.path, pr.path)
        raise ConfigError(f"{_where(source, origin)}: implausible as {pr.path}: {pr.message}")
    return p.model_dump(mode="json")


def nominal_preset_from_config(config_text: str | None, source: str | None = None, name: str | None = None):
    """The translated preset of a recording's ``/experiment/config`` text, or ``None`` when it
    carries no ``nominal_model`` block (see :func:`preset_from_nominal`).

    Examples
    --------
    >>> nominal_preset_from_config("run: {case: x}") is None
    True
    """
    if not config_text:
        return None
    doc = load_yaml(config_text, source or "/experiment/config")
    return nominal_preset_from_doc(doc, source, name)


def nominal_preset_from_doc(doc, source: str | None = None, name: str | None = None):
    """:func:`nominal_preset_from_config` of the parsed configuration ``doc`` (e.g.
    :meth:`experiment_runner.core.recording.Recording.config_doc`)."""
    if not has_nominal_model(doc):
        return None
    case = doc.get("case") if isinstance(doc.get("case"), str) else None
    return preset_from_nominal(doc["nominal_model"], source=source, conventions=doc.get("conventions"),
                               name=name or (f"{case}_nominal" if case else "nominal"))


def preset_yaml(preset: dict) -> str:
    """The preset as YAML with its translation notes as a comment header (runs as is:
    ``nanostage diagnose REC preset.yaml``)."""
    import yaml
    head = f"# {preset['name']}: written by nanostage convert nominal (how each term was translated: description)\n"
    return head + yaml.safe_dump(preset, sort_keys=False, allow_unicode=True, width=100)


# --------------------------------------------------------------------------- nanostage convert nominal
def add_convert_nominal_arguments(p):
    p.add_argument("recording", help="contract recording (MCAP file or bag directory) whose /experiment/config "
                                     "carries a nominal_model block")
    p.add_argument("--out", required=True, help="preset YAML to write")
    add_overwrite_argument(p)
    return p


def main_convert_nominal(args) -> int:
    """``nanostage convert nominal REC --out preset.yaml``: write the translated preset
    (:mod:`experiment_runner.core.outputs`: atomic, never through a link, an existing file that
    nanostage did not write only with ``--overwrite``)."""
    rec = read_recording(args.recording, require_reference=False)
    preset = nominal_preset_from_doc(rec.config_doc(), source=str(args.recording))
    if preset is None:
        raise ConfigError(f"{args.recording}: /experiment/config carries no nominal_model block "
                          "(fields plant, controller, Ts, quantization_m)")
    out = Path(args.out)
    if out.exists() and not out.is_symlink() and not args.overwrite:
        raise ConfigError(f"{out}: exists; pass --overwrite to replace it")
    outputs.prepare_folder(out.parent, overwrite=args.overwrite, files=(out.name,))
    outputs.write_text(out, preset_yaml(preset))
    print(f"{out}: preset {preset['name']!r} translated from the nominal_model of {args.recording}")
    return 0
