"""Speed mechanisms of the diagnosis that must not change its answer (issue 27 item 1).

- A second forward walk that adopts the greedy walk's effects has joined it and stops there
  (:class:`experiment_runner.apps.diagnosis.forward.ForwardSelection`): scripted steps, no simulation.
- The replay refinements of a step run on parallel threads (:func:`.refining.refine_rows`): one
  thread and two give the same report, bit for bit.
- ``nanostage bench``'s EMPS figure is left out, saying why, when the EMPS data are missing.

The work each evaluation saves without changing a number -- the evaluator's observer runs kept on
the spec, its fit runs stopped at the last fit sample, the whitening gain computed once per length,
a replay refinement's point replayed once -- is tested with those pieces in test_diagnosis.py.
"""
import json
from types import SimpleNamespace

import pytest
import yaml

from experiment_runner.apps.diagnosis.budget import Budget
from experiment_runner.apps.diagnosis.forward import ForwardSelection


def _canon(rep: dict) -> str:
    """Exact comparison form of a report without its wall times."""
    from experiment_runner.apps.diagnosis.report import jsonable

    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k not in {"timing_s", "seconds", "evaluation_s", "spent_s"}}
        if isinstance(o, list):
            return [strip(v) for v in o]
        return o
    return json.dumps(strip(jsonable(rep)), sort_keys=True)


class _Scripted(ForwardSelection):
    """A forward selection whose steps adopt (``+key``) or withdraw (``-key``) what a script says."""

    def __init__(self, greedy, second):
        opt = SimpleNamespace(max_steps=10, n_jobs=1, log=lambda *_: None)
        problem = SimpleNamespace(base=None, J_held_base=1.0, J_fit_base=1.0,
                                  base_floor=SimpleNamespace(noise=None), base_replay_floor=None,
                                  options=opt, evaluator=SimpleNamespace(floor=None))
        super().__init__(problem, context=None, budget=Budget(None, progress=False))
        self.scripts = {None: greedy, "second": second}
        self.steps_run = []

    def step(self, step, first=None):
        script = self.scripts[self.walking]
        if step > len(script):
            return False
        self.steps_run.append((self.walking, step))
        for op in script[step - 1].split():          # key~alternative: reported confounded with it
            if op.startswith("-"):
                self.path.selected = [f for f in self.path.selected if f.key != op[1:]]
                self.path.found = [fe for fe in self.path.found if fe["effect"] != op[1:]]
            else:
                key, *conf = op.split("~")
                for fe in self.path.found:       # as adoption.adopt_best: both demanded, not confounded
                    fe["confounded_with"] = [c for c in fe["confounded_with"] if c != key]
                self.path.selected.append(SimpleNamespace(key=key, theta=None, sigma=None, derived=None))
                self.path.found.append({"effect": key, "confounded_with": conf})
        self.path.steps.append({"step": step, "accepted": script[step - 1]})
        return True

    def candidates(self, only=None):
        return []

    def walk(self, first=None):
        self.walking = None if first is None else "second"
        return super().walk(first)


def test_a_second_walk_stops_where_it_joins_the_greedy_path():
    # EMPS: greedy viscous, mass, coulomb, friction_asymmetry; the second start from dither_imbalance
    # took coulomb, mass, withdrew dither_imbalance and took viscous: the greedy step-3 effects
    fs = _Scripted(["viscous", "mass", "coulomb", "friction_asymmetry"],
                   ["dither_imbalance", "coulomb", "mass -dither_imbalance", "viscous", "friction_asymmetry"])
    fs.walk()
    # the greedy walk's step 5 adopts nothing and ends it: five sets, the last two the same
    assert fs.joined is None and len(fs.greedy_sets) == 5 and fs.greedy_sets[3] == fs.greedy_sets[4]
    fs.walk(first=object())
    assert fs.joined == {"step": 4, "greedy_step": 3, "effects": ["coulomb", "mass", "viscous"],
                         "greedy_effects": ["coulomb", "mass", "viscous"]}
    assert ("second", 5) not in fs.steps_run and ("second", 4) in fs.steps_run


def test_a_confounded_alternative_counts_as_the_effect_it_stands_for():
    # EMPS on main e2d4ff4: the greedy path adopted viscous (Coulomb confounded with it at step 1, a
    # mark withdrawn when Coulomb was adopted too), the mass (the force constant confounded with it),
    # Coulomb and the asymmetry; the second start took the force constant in the mass' place. Coulomb
    # never stands for viscous (the greedy path adopted both): joined after step 4, not 3
    fs = _Scripted(["viscous~coulomb", "mass~force_constant", "coulomb", "friction_asymmetry"],
                   ["dither_imbalance", "coulomb~viscous", "force_constant~mass -dither_imbalance", "viscous",
                    "friction_asymmetry"])
    fs.walk()
    fs.walk(first=object())
    assert fs.joined is not None and fs.joined["step"] == 4 and fs.joined["greedy_step"] == 3
    assert fs.joined["effects"] == ["coulomb", "force_constant", "viscous"]
    assert ("second", 5) not in fs.steps_run


class _Judged(_Scripted):
    """:class:`_Scripted` run whole: each walk's replay tagged with the walk, the judge's adoption test
    accepting the second walk's replay over the greedy one's where ``second_better``."""

    def __init__(self, greedy, second, second_better):
        super().__init__(greedy, second)
        ok = SimpleNamespace(ok=True, walk=None)
        self.problem.base_replay_floor = SimpleNamespace(replay=ok, noise=None)
        self.problem.judge = SimpleNamespace(
            D=lambda rp, fl: 1.0,
            compare=lambda fl, rp: SimpleNamespace(accepted=second_better and rp.walk == "second",
                                                   why="better beyond the floor" if second_better else "not better"))

    def step(self, step, first=None):
        going = super().step(step, first)
        if going:
            self.path.replay_floor = SimpleNamespace(replay=SimpleNamespace(ok=True, walk=self.walking), noise=None)
            self.path.floor = SimpleNamespace(noise=None)
        return going

    def second_start(self, a):
        return SimpleNamespace(fit=SimpleNamespace(key="dahl"))


@pytest.mark.parametrize("second_better", [True, False])
def test_a_walk_joined_through_a_confounded_alternative_is_kept_where_its_replay_is_better(second_better):
    # power case 003 (a force constant; main eedbaf1): the greedy walk took LuGre (the force constant
    # confounded with it), later withdrawn as not identified; the second walk from Dahl took the force
    # constant and withdrew Dahl: joined, it was dropped though its replay was 2x closer to the data
    fs = _Judged(["lugre~force_constant"], ["dahl", "force_constant~lugre -dahl"], second_better)
    kept = fs.run()
    assert fs.joined is not None and fs.joined["effects"] == ["force_constant"]
    assert [fe["effect"] for fe in kept.found] == (["force_constant"] if second_better else ["lugre"])
    assert kept.second_start["chosen"] is second_better and kept.second_start["joined"] == fs.joined
    assert ("second", 3) not in fs.steps_run


def test_a_walk_joined_with_the_same_effects_keeps_the_greedy_walk():
    fs = _Judged(["viscous", "mass"], ["mass", "viscous"], second_better=True)
    kept = fs.run()
    assert fs.joined is not None and [fe["effect"] for fe in kept.found] == ["viscous", "mass"]
    assert kept.second_start["chosen"] is False


def test_a_second_walk_that_never_joins_walks_to_its_end():
    fs = _Scripted(["gms", "mass"], ["fi_compliance", "stribeck"])
    fs.walk()
    fs.walk(first=object())
    assert fs.joined is None and ("second", 2) in fs.steps_run


@pytest.mark.slow
def test_parallel_refinement_gives_the_same_report(tmp_path):
    from experiment_runner.apps.diagnosis.options import Options
    from experiment_runner.apps.diagnosis.pipeline import diagnose
    from experiment_runner.apps.diagnosis.selftest import CASES, EXPERIMENTS
    from experiment_runner.apps.diagnosis.synth import synth
    c = next(c for c in CASES if c.name == "coulomb+viscous")
    exp = dict(EXPERIMENTS[c.experiment], preset=c.nominal)
    (tmp_path / "truth.yaml").write_text(yaml.safe_dump(c.truth_doc(), sort_keys=False))
    (tmp_path / "exp.yaml").write_text(yaml.safe_dump(exp, sort_keys=False))
    (tmp_path / "nominal.yaml").write_text(yaml.safe_dump(c.nominal_doc(), sort_keys=False))
    rec = synth(tmp_path / "truth.yaml", tmp_path / "exp.yaml", tmp_path / "rec.mcap")
    eff = ["coulomb", "viscous", "offset", "mass"]
    one = diagnose(rec, tmp_path / "nominal.yaml", options=Options(plots=False, effects=eff, n_jobs=1,
                                                                   max_seconds=None))
    two = diagnose(rec, tmp_path / "nominal.yaml", options=Options(plots=False, effects=eff, n_jobs=2,
                                                                   max_seconds=None))
    assert [f["effect"] for f in one["found"]][:2] == ["coulomb", "viscous"]
    assert any("refined by the replay" in r["why"] for st in one["selection"]["steps"] for r in st["candidates"])
    assert _canon(one) == _canon(two)


def test_bench_emps_figure_skipped_without_the_data(tmp_path, monkeypatch, capsys):
    from experiment_runner.apps.bench import diagnose_seconds_emps
    monkeypatch.setenv("NANOSTAGE_DATA", str(tmp_path))
    assert diagnose_seconds_emps() is None
    err = capsys.readouterr().err
    assert "diagnose_seconds_emps skipped" in err and str(tmp_path) in err
