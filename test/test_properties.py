"""Property-based tests (hypothesis) of the input checks and the message conversions.

Configs: every shipped preset survives dump -> YAML -> load unchanged, also with random
valid changes; any bad value (NaN, inf, text, true/false, a list, a mapping, a negative
mass or gain), unknown key or missing required field is refused by a ConfigError that
names the field's path; a value moved out of its plausible range by a unit prefix is
refused as "likely given in ...". Messages: arrays -> messages -> arrays (and through
CDR) round-trip bit for bit for random sizes and values, NaN and inf included; JSON
topics turn NaN/inf into null; events refuse non-finite windows.

Examples are derandomized (the same on every run) and have no deadline (the machine
is shared; timing is not what is tested).
"""
import math
import warnings

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from rosbags.typesys import Stores, get_typestore

from experiment_runner.core.recording import run_config_yaml
from msg_defs import convert
from stage_sim.config import ConfigError, Preset, list_presets, load_preset, preset_from_dict, with_overrides
from stage_sim.validation import ConfigWarning, load_yaml, model_axis, plausible_range

TS = get_typestore(Stores.ROS2_JAZZY)
PRESETS = {name: load_preset(name) for name in list_presets()}
SETTINGS = settings(max_examples=150, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


# =========================================================================== config helpers
def _leaves(model: BaseModel, prefix=()):
    """(path, value, FieldInfo) of every number in a preset (list items by index)."""
    for name, info in type(model).model_fields.items():
        val = getattr(model, name)
        path = prefix + (name,)
        if isinstance(val, BaseModel):
            yield from _leaves(val, path)
        elif isinstance(val, list):
            for i, item in enumerate(val):
                if isinstance(item, BaseModel):
                    yield from _leaves(item, path + (str(i),))
                elif isinstance(item, (int, float)) and not isinstance(item, bool):
                    yield ".".join(path + (str(i),)), item, info
        elif isinstance(val, (int, float)) and not isinstance(val, bool):
            yield ".".join(path), val, info


def _nodes(model: BaseModel, prefix=()):
    """(path, model) of every sub-model of a preset, the preset itself first."""
    yield ".".join(prefix), model
    for name in type(model).model_fields:
        val = getattr(model, name)
        items = [(str(i), v) for i, v in enumerate(val)] if isinstance(val, list) else [("", val)]
        for idx, item in items:
            if isinstance(item, BaseModel):
                yield from _nodes(item, prefix + (name,) + ((idx,) if idx else ()))


def _get(data, path: str):
    for part in path.split(".") if path else []:
        data = data[int(part)] if isinstance(data, list) else data[part]
    return data


NUMBERS = [(name, path, val, info) for name, p in PRESETS.items() for path, val, info in _leaves(p)]
PLAUSIBLE = [(name, path, val, info) for name, path, val, info in NUMBERS
             if isinstance(info.json_schema_extra, dict) and "plausible" in info.json_schema_extra]
NODES = [(name, path, type(node)) for name, p in PRESETS.items() for path, node in _nodes(p)]
MASS_OR_GAIN = ("mass", "kp", "ki", "kd", "gain", "hc_gain", "stiffness", "k_sigma", "k", "sigma0", "lock_stiffness")


def _field_name(path: str) -> str:
    """The last key of a path (not a list index)."""
    return next(p for p in reversed(path.split(".")) if not p.isdigit())


def _refused(data, source="props.yaml") -> ConfigError:
    with pytest.raises(ConfigError) as err:
        preset_from_dict(data, source)
    assert str(err.value).startswith(f"{source}: invalid preset")
    return err.value


# =========================================================================== config properties
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_round_trips_through_yaml_and_the_recording_config(name):
    p = PRESETS[name]
    text = yaml.safe_dump(p.model_dump(mode="json"), sort_keys=False)
    assert preset_from_dict(load_yaml(text, f"{name}.yaml"), name) == p
    doc = load_yaml(run_config_yaml(p, case="x"), "/experiment/config")
    assert preset_from_dict(doc["preset"], "/experiment/config") == p


@SETTINGS
@given(st.data())
@pytest.mark.slow
def test_random_valid_changes_round_trip(data):
    name, path, val, info = data.draw(st.sampled_from(PLAUSIBLE))
    _, lo, hi = plausible_range(info.json_schema_extra, model_axis(PRESETS[name]))
    new = data.draw(st.floats(math.log10(lo), math.log10(hi)).map(lambda e: 10.0 ** e))
    new = math.copysign(new, val) if val else new
    try:
        changed = with_overrides(PRESETS[name], {path: new})
    except ConfigError as err:            # a cross-field rule (e.g. continuous <= peak force)
        assert all("plausible" not in p.message for p in err.problems)
        assume(False)
    assert _get(changed.model_dump(), path) == new
    again = preset_from_dict(load_yaml(yaml.safe_dump(changed.model_dump(mode="json")), "x.yaml"))
    assert again == changed


BAD = st.sampled_from([math.nan, math.inf, -math.inf, "abc", "", True, False, [1.0], {"value": 1.0}, None])


@SETTINGS
@given(st.sampled_from(NUMBERS), BAD)
def test_a_bad_number_is_refused_naming_its_field(leaf, bad):
    name, path, _, info = leaf
    assume(not (bad is None and not info.is_required() and info.default is None))   # None may mean "off"
    data = PRESETS[name].model_dump()
    parent, _, key = path.rpartition(".")
    node = _get(data, parent)
    node[int(key) if isinstance(node, list) else key] = bad
    err = _refused(data)
    assert path in [p.path for p in err.problems], (path, bad, str(err))
    assert f"  {path}: " in str(err)


@SETTINGS
@given(st.sampled_from([n for n in NUMBERS if _field_name(n[1]) in MASS_OR_GAIN]), st.floats(1e-12, 1e12))
def test_a_negative_mass_gain_or_stiffness_is_refused(leaf, size):
    name, path, _, _ = leaf
    data = PRESETS[name].model_dump()
    parent, _, key = path.rpartition(".")
    node = _get(data, parent)
    node[int(key) if isinstance(node, list) else key] = -size
    err = _refused(data)
    line = next(p for p in err.problems if p.path == path)
    assert line.value == -size and "greater than" in line.message


@SETTINGS
@given(st.sampled_from(NODES), st.text("abcdefghijklmnopqrstuvwxyz_", min_size=1, max_size=12))
def test_an_unknown_key_is_refused_with_the_allowed_keys(node, key):
    name, path, cls = node
    assume(key not in cls.model_fields)
    data = PRESETS[name].model_dump()
    _get(data, path)[key] = 1.0
    err = _refused(data)
    where = f"{path}.{key}" if path else key
    assert where in [p.path for p in err.problems]
    assert f"  {where}: unknown key (got 1.0); allowed keys: {', '.join(cls.model_fields)}" in str(err)


REQUIRED = [(name, path, key) for name, path, cls in NODES for key, info in cls.model_fields.items()
            if info.is_required()]


@SETTINGS
@given(st.sampled_from(REQUIRED))
def test_a_missing_required_field_is_refused(req):
    name, path, key = req
    data = PRESETS[name].model_dump()
    del _get(data, path)[key]
    err = _refused(data)
    where = f"{path}.{key}" if path else key
    if key == "model":                    # the friction model selects the schema
        assert f"  {where}: required field is missing (it selects the kind)" in str(err)
    else:
        assert f"  {where}: required field is missing" in str(err) and where in [p.path for p in err.problems]


PREFIXES = (1e3, 1e6, 1e9, 1e-3, 1e-6, 1e-9)


@SETTINGS
@given(st.sampled_from(PLAUSIBLE), st.sampled_from(PREFIXES), st.floats(0.0, 1.0))
@pytest.mark.slow
def test_a_value_off_by_a_unit_prefix_is_refused_as_likely_a_wrong_unit(leaf, prefix, where):
    name, path, val, info = leaf
    unit_name, lo, hi = plausible_range(info.json_schema_extra, model_axis(PRESETS[name]))   # rotary: rotary
    true = 10 ** (math.log10(lo) + where * (math.log10(hi) - math.log10(lo)))
    wrong = true / prefix                 # what a value in the wrong unit reads as in SI
    assume(not lo <= wrong <= hi)
    try:
        with_overrides(PRESETS[name], {path: wrong}, "exp.yaml")
    except ConfigError as err:
        assume(err.problems and "plausible" in err.problems[0].message)   # else a cross-field rule spoke first
        line = next(p for p in err.problems if p.path == path)
        assert line.value == wrong and "likely" in line.message and f" {unit_name}" in line.message
        assert str(err).startswith("exp.yaml: implausible value(s)")
    else:
        raise AssertionError(f"{path} = {wrong} accepted")
    # a file may accept it deliberately
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        p = with_overrides(PRESETS[name], {path: wrong, "plausibility": "warn"}, "exp.yaml")
    assert _get(p.model_dump(), path) == wrong
    assert any(issubclass(w.category, ConfigWarning) and path in str(w.message) for w in got)


def test_shipped_values_are_plausible():
    """The ranges hold every value the seed gives (else the check would refuse the seed)."""
    from stage_sim.validation import plausibility_problems
    assert {name: plausibility_problems(p) for name, p in PRESETS.items() if plausibility_problems(p)} == {}
    assert Preset.model_fields["plausibility"].default == "error"


@pytest.mark.parametrize("kind", ["experiment", "campaign"])
@pytest.mark.slow
def test_shipped_experiments_and_campaigns_round_trip_through_yaml(kind):
    from experiment_runner.apps.campaigns import spec as campaign
    from experiment_runner.core import experiment
    if kind == "experiment":
        items = [(experiment.Experiment, experiment.load_experiment(n)) for n in experiment.list_experiments()]
    else:
        items = [(campaign.Campaign, campaign.load_campaign(n, check_presets=False)) for n in campaign.list_campaigns()]
    assert items
    for cls, obj in items:
        text = yaml.safe_dump(obj.model_dump(mode="json"), sort_keys=False)
        assert cls.model_validate(load_yaml(text, f"{obj.name}.yaml")) == obj


def _experiment_leaves():
    from experiment_runner.core.experiment import list_experiments, load_experiment
    return [(name, path) for name in list_experiments()
            for path, _, _ in _leaves(load_experiment(name)) if not path.startswith("overrides")]


@SETTINGS
@given(st.sampled_from(_experiment_leaves()), BAD.filter(lambda b: b is not None))
@pytest.mark.slow
def test_a_bad_number_in_an_experiment_file_is_refused_naming_file_and_field(tmp_path_factory, leaf, bad):
    from experiment_runner.core.experiment import load_experiment
    name, path = leaf
    data = load_experiment(name).model_dump(mode="json")
    parent, _, key = path.rpartition(".")
    _get(data, parent)[key] = bad
    f = tmp_path_factory.mktemp("exp") / f"{name}.yaml"
    f.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as err:
        load_experiment(f)
    assert str(err.value).startswith(f"{f}: invalid experiment\n")
    assert f"\n  {path}: " in str(err.value)


# =========================================================================== message properties
FLOATS = st.floats(allow_nan=True, allow_infinity=True, width=64)
NAMES = st.lists(st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=8),
                 max_size=6, unique=True)
STAMP = st.integers(-(2**31) * 10**9, (2**31 - 1) * 10**9 + 999_999_999)
FAMILIES = st.sampled_from(["rosbags", "rclpy"])


def _family(name):
    return TS if name == "rosbags" else None


def _bits(a):
    return np.asarray(a, np.float64).view(np.int64).tolist()


def _through_cdr(msg, family):
    """The message serialized and read back (CDR, the bytes a recording holds)."""
    if family == "rosbags":
        typ = msg.__msgtype__
        return TS.deserialize_cdr(TS.serialize_cdr(msg, typ), typ)
    from rclpy.serialization import deserialize_message, serialize_message
    return deserialize_message(serialize_message(msg), type(msg))


@SETTINGS
@given(FAMILIES, STAMP, NAMES, st.data())
@pytest.mark.slow
def test_joint_state_round_trips_bit_for_bit(family, stamp, names, data):
    n = len(names)
    arrays = {k: data.draw(st.one_of(st.just([]), st.lists(FLOATS, min_size=n, max_size=n)))
              for k in ("position", "velocity", "effort")}
    msg = convert.joint_state(_family(family), stamp, names, **arrays)
    for m in (msg, _through_cdr(msg, family)):
        assert convert.stamp_ns(m) == stamp and list(m.name) == names
        for k, v in arrays.items():
            assert _bits(convert.values(getattr(m, k))) == _bits(v)
        for i, name in enumerate(names):
            want = arrays["position"][i] if arrays["position"] else math.nan
            got = convert.joint(m, name)
            assert got == want or (math.isnan(got) and math.isnan(want))


@SETTINGS
@given(FAMILIES, NAMES.filter(bool), st.integers(0, 5))
def test_joint_state_refuses_arrays_of_the_wrong_length(family, names, extra):
    assume(extra != 0)
    with pytest.raises(ValueError, match=f"has {len(names) + extra} values for {len(names)} names"):
        convert.joint_state(_family(family), 0, names, position=[0.0] * (len(names) + extra))


@SETTINGS
@given(FAMILIES, st.lists(FLOATS, max_size=50), st.data())
@pytest.mark.slow
def test_trajectory_round_trips(family, x, data):
    v = data.draw(st.lists(FLOATS, min_size=len(x), max_size=len(x)))
    trial = data.draw(st.integers(0, 2**31 - 1))
    case = data.draw(st.text(st.characters(codec="utf-8", exclude_characters="\x00"), max_size=20))
    start = data.draw(st.integers(0, 2**40))
    rate = data.draw(st.floats(1.0, 1e6))
    msg = convert.trajectory_to_msg(_family(family), x, v, trial=trial, case=case, start=start, rate=rate)
    for m in (msg, _through_cdr(msg, family)):
        tr = convert.trajectory_from_msg(m)
        assert _bits(tr.x_ref) == _bits(x) and _bits(tr.v_ref) == _bits(v)
        assert (tr.trial, tr.case, tr.start, tr.rate) == (trial, case, start, rate)


@SETTINGS
@given(FAMILIES, st.lists(FLOATS, max_size=50), st.integers(0, 1000), st.floats(1.0, 1e6))
def test_correction_round_trips(family, c, iteration, rate):
    msg = convert.correction_to_msg(_family(family), c, iteration=iteration, rate=rate)
    for m in (msg, _through_cdr(msg, family)):
        got = convert.correction_from_msg(m)
        assert _bits(got.values) == _bits(c) and (got.iteration, got.rate) == (iteration, rate)


@SETTINGS
@given(st.integers(-(2**62), 2**62))
def test_time_split_round_trips(ns):
    sec, nanosec = convert.split_ns(ns)
    assert 0 <= nanosec < 10**9 and sec * 10**9 + nanosec == ns
    assert convert.stamp_ns(convert.time_msg(TS, ns)) == ns


JSONABLE = st.recursive(st.none() | st.booleans() | st.integers(-(2**53), 2**53) | FLOATS | st.text(max_size=10),
                        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner,
                                                                                    max_size=4), max_leaves=20)


def _nan_to_none(obj):
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


@SETTINGS
@given(JSONABLE)
@pytest.mark.slow
def test_json_topics_write_nan_and_inf_as_null(obj):
    text = convert.to_json(obj)
    assert "NaN" not in text and "Infinity" not in text
    assert convert.from_json(text) == _nan_to_none(obj)


@SETTINGS
@given(st.sampled_from(["run_start", "trial_start", "trial_end", "abort", "fault", "run_end"]),
       st.integers(0, 2**62), st.integers(0, 10**6), st.one_of(st.none(), st.floats(0, 1.0)),
       st.text(max_size=12))
def test_events_round_trip_and_refuse_non_finite_windows(kind, stamp, trial, window, case):
    rec = convert.event(kind, stamp_ns=stamp, trial=trial, case=case, window_m=window, node="n")
    assert convert.parse_event(convert.event_json(kind, stamp_ns=stamp, trial=trial, case=case,
                                                  window_m=window, node="n")) == rec
    for bad in (math.nan, math.inf, -math.inf, -1e-9):
        with pytest.raises(ValueError, match="window_m"):
            convert.event(kind, stamp_ns=stamp, trial=trial, window_m=bad)
