"""No cold-start surprise: the kernels a run calls are the ones the warm-up compiled.

numba compiles one specialization per argument-type signature; a run that calls a kernel
with types the warm-up did not (a read-only array, another layout) compiles again inside it,
minutes on a fresh machine.
"""
import json

import numpy as np
import pytest

from experiment_runner.apps import warmup
from experiment_runner.core import batch
from experiment_runner.core.batch import Models, simulate
from experiment_runner.core.profiles import point_to_point
from stage_sim.config import load_preset


def test_one_batch_kernel_specialization_whatever_the_trials_and_the_inputs():
    preset = load_preset("fi_stage")
    models = Models.from_preset(preset)
    ref = point_to_point(5e-6, dwell=0.002, dt=1.0 / preset.controller.rate)
    simulate(preset, ref.x, ref.v, n_trials=3, models=models, check=False)
    before = set(batch.run_chunks.signatures)
    simulate(preset, ref.x, ref.v, n_trials=1, models=models, check=False)    # one trial: a read-only broadcast
    x, v = np.tile(ref.x, (2, 1)), np.tile(ref.v, (2, 1))
    corr = np.zeros(4)
    for a in (x, v, corr):
        a.flags.writeable = False
    simulate(preset, x, v, models=models, check=False, correction=corr,
             f_ext=np.broadcast_to(np.zeros(1), ref.x.shape), seeds=np.array([3.0, 4.0]))
    assert set(batch.run_chunks.signatures) == before


@pytest.mark.slow
def test_the_warm_up_compiles_what_a_graph_node_calls():
    from experiment_runner.ros.plant_node import PlantTrial
    from stage_sim.plant import plant_step
    warmup.warm_up(["graph"], out=None)
    before = set(plant_step.signatures)
    trial = PlantTrial(Models.from_preset(load_preset("fi_stage")), 1e-3, 7)
    assert trial.step(0.0, 0.0, 0.0, 1.0) == 0
    assert set(plant_step.signatures) == before


def test_a_complete_warm_up_is_not_repeated_for_the_same_code(tmp_path, monkeypatch, capsys):
    ran = []
    monkeypatch.setattr(warmup, "STEPS", {"a": ("step a", lambda: ran.append("a")),
                                          "b": ("step b", lambda: ran.append("b"))})
    marker = tmp_path / "numba-0123" / "warmed.json"
    marker.parent.mkdir()
    monkeypatch.setattr(warmup, "_marker_path", lambda: marker)
    assert not warmup.is_warm()
    warmup.main([])
    err = capsys.readouterr().err
    assert "[1/2] step a" in err and "[2/2] step b: done in" in err and ran == ["a", "b"]
    assert warmup.is_warm()
    assert warmup.warm_up() == {} and ran == ["a", "b"]              # this code's kernels: compiled already
    warmup.warm_up(["b"], out=None)                                     # a named step always runs
    warmup.warm_up(force=True, out=None)
    assert ran == ["a", "b", "b", "a", "b"]
    marker.write_text(json.dumps({**json.loads(marker.read_text()), "numba": "0.0"}))   # another numba
    assert not warmup.is_warm()
    with pytest.raises(SystemExit):
        warmup.main(["c"])
    assert "unknown warm-up step(s) c" in capsys.readouterr().err
