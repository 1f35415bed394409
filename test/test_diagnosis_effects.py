"""The effect library: every effect declares what the diagnosis, the power study and the self-test
need of it, in its own class (``experiment_runner/apps/diagnosis/effects``)."""
from __future__ import annotations

import importlib
import inspect
import pkgutil

import numpy as np
import pytest

from experiment_runner.apps.diagnosis import effects as effects_pkg
from experiment_runner.apps.diagnosis.power.cases import PowerCase, dealt_effects, nominal_doc
from experiment_runner.apps.diagnosis.context import Context
from experiment_runner.apps.diagnosis.effects import LIBRARY, SHIPPED, Draw, Effect, Library
from experiment_runner.apps.diagnosis.model import ModelSpec
from experiment_runner.apps.diagnosis.selftest import CASES, EXPERIMENTS
from experiment_runner.apps.diagnosis.units import unit_for
from stage_sim.config import preset_from_dict

SETTINGS = [(stage, law) for stage in ("rigid", "isolated", "sai") for law in ("dahl", "gms", "coulomb")]


def _own(e: Effect) -> Effect:
    """The effect whose truths stand for ``e``'s (itself unless it declares ``truth_of``)."""
    return LIBRARY[e.truth_of] if e.truth_of else e


def test_every_effect_class_is_shipped():
    classes = set()
    for m in pkgutil.iter_modules(effects_pkg.__path__):
        mod = importlib.import_module(f"{effects_pkg.__name__}.{m.name}")
        classes |= {c for _, c in inspect.getmembers(mod, inspect.isclass)
                    if issubclass(c, Effect) and c is not Effect and c.__module__ == mod.__name__}
    assert classes == set(SHIPPED)


@pytest.mark.parametrize("key", list(LIBRARY))
def test_every_effect_has_a_concealed_truth_and_a_selftest_case(key):
    e = LIBRARY[key]
    own = _own(e)
    assert own.truth_of is None, f"{key}: truth_of {e.truth_of} has truths of another"
    assert type(own).conceal is not Effect.conceal, f"{own.key}: no concealed-truth writer (Effect.conceal)"
    assert own.deal is not None, f"{own.key}: not dealt in the power study (Effect.deal)"
    assert any(own.key in c.effects for c in CASES), f"{own.key}: no self-test case (Effect.selftest_cases)"
    assert e.parameters and all(p.meaning for p in e.parameters), f"{key}: undocumented parameters"
    assert e.title and e.physics and e.signature


def test_the_deal_is_one_number_per_effect():
    deals = sorted(e.deal for e in LIBRARY.values() if e.deal is not None)
    assert deals == list(range(1, len(deals) + 1))
    assert dealt_effects()[:3] == ["coulomb", "viscous", "mass"]


@pytest.mark.parametrize("key", dealt_effects())
def test_each_truth_writer_writes_a_valid_preset_with_the_effects_parameters(key):
    """On every setting the effect accepts, its truth is a valid preset and the truth values it returns
    are parameters or derived quantities of the effect (what the power study compares)."""
    e = LIBRARY[key]
    settings = [(s, f) for s, f in SETTINGS if e.conceal_on(s, f) and (s != "sai" or f == "dahl")]
    assert settings, key
    for stage, law in settings:
        case = PowerCase(index=0, effects=(key,), stage=stage, friction=law, rate=1e4, noise=1.0, record="p2p")
        d = nominal_doc(case)
        spec = ModelSpec(preset_from_dict(d))
        draw = Draw(q=0.5, sign=-1.0, rng=np.random.default_rng(0), stage=stage, friction=law, rate=1e4,
                    x_center=1e-3, half_span=1e-3, stroke=2e-3, v_max=0.02)
        truth = e.conceal(d, draw)
        preset_from_dict(d)
        ctx = Context(x_center=1e-3, x_half_span=1e-3, line_hz=(120.0,))
        b = e.bound(ctx)
        ps = b.params(spec, ctx)
        names = {p.name for p in ps} | set(b.derived(spec, [p.x0 for p in ps]))
        assert set(truth) <= names, (key, stage, law, truth)


@pytest.mark.slow
def test_selftest_cases_are_unique_and_valid():
    names = [c.name for c in CASES]
    assert len(names) == len(set(names)) == 47
    for c in CASES:
        assert c.experiment in EXPERIMENTS, c.name
        assert all(k in LIBRARY for k in c.effects), c.name
        preset_from_dict(c.truth_doc())
        preset_from_dict(c.nominal_doc())


def test_rotary_plausible_ranges_where_the_unit_differs():
    for e in LIBRARY.values():
        for p in e.parameters:
            if unit_for(p.unit, "rotary") != p.unit and p.plausible is not None:
                assert p.plausible_rotary is not None, (e.key, p.name)
                lo, hi = p.plausible_on("rotary")
                assert 0 < lo < hi, (e.key, p.name)


def test_library_selects_and_derives_groups():
    lib = LIBRARY.select(["viscous", "dahl", "gms", "force_constant"])
    assert list(lib) == ["viscous", "dahl", "gms", "force_constant"]
    assert lib.exclusive_of("dahl") == {"gms"} and lib.exclusive_of("viscous") == set()
    assert lib.known == {"force_constant"}
    assert lib.candidates() == ["viscous", "dahl", "gms", "force_constant"]
    with pytest.raises(KeyError, match="unknown effect 'stiction'"):
        LIBRARY.select(["stiction"])
    with pytest.raises(ValueError, match="given twice"):
        Library([LIBRARY["mass"], LIBRARY["mass"]])
    # binding copies: the library's own effects keep no recording
    bound = LIBRARY.bound(Context(x_center=0.5))
    assert bound["position_friction"].derived(None, [0.0, 0.0, 0.0]) == {"x_center": 0.5}
    assert LIBRARY["position_friction"].derived(None, [0.0, 0.0, 0.0]) == {"x_center": 0.0}
