"""Diagnosis candidate fits on an executor: the same report in this process (threads), on a
local pool of two processes and on a Dask ``LocalCluster`` of two worker processes.

One small concealed case of the self-test (Coulomb + viscous friction on the circle
recording, three candidate effects), so that the second forward-selection step re-fits the
first effect together with each candidate (selected fits travel to the workers too).
"""
import argparse
import json
import pickle

import pytest
import yaml

from experiment_runner.apps.diagnosis import add_diagnose_arguments
from experiment_runner.apps.diagnosis.cli import diagnose_options
from experiment_runner.apps.diagnosis.model import load_model
from experiment_runner.apps.diagnosis.options import Options
from experiment_runner.apps.diagnosis.pipeline import diagnose
from experiment_runner.apps.diagnosis.report import jsonable
from experiment_runner.apps.diagnosis.selftest import CASES, EXPERIMENTS
from experiment_runner.apps.diagnosis.synth import synth
from stage_sim.config import ConfigError

EFFECTS = ["coulomb", "viscous", "offset"]
TIMES = {"timing_s", "seconds", "evaluation_s", "spent_s"}   # wall times: the only fields allowed to differ


def _canon(rep: dict) -> str:
    """Exact comparison form of a report without its wall times."""
    def strip(o):
        if isinstance(o, dict):
            return {k: strip(v) for k, v in o.items() if k not in TIMES}
        if isinstance(o, list):
            return [strip(v) for v in o]
        return o
    return json.dumps(strip(jsonable(rep)), sort_keys=True)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    d = tmp_path_factory.mktemp("diag_ex")
    c = next(c for c in CASES if c.name == "coulomb+viscous")
    exp = dict(EXPERIMENTS[c.experiment], preset=c.nominal)
    (d / "truth.yaml").write_text(yaml.safe_dump(c.truth_doc(), sort_keys=False))
    (d / "exp.yaml").write_text(yaml.safe_dump(exp, sort_keys=False))
    (d / "nominal.yaml").write_text(yaml.safe_dump(c.nominal_doc(), sort_keys=False))
    return synth(d / "truth.yaml", d / "exp.yaml", d / "rec.mcap"), d / "nominal.yaml"


@pytest.fixture(scope="module")
def threaded(case):
    rec, nominal = case
    return diagnose(rec, nominal, options=Options(plots=False, effects=EFFECTS))


@pytest.mark.slow
def test_threaded_reference_finds_both(threaded):
    # the reference is a real diagnosis: both effects named, re-fitting exercised in step 2
    assert [f["effect"] for f in threaded["found"]] == ["coulomb", "viscous"]
    assert threaded["found"][1]["params"][0]["value"] == pytest.approx(20.0, rel=0.2)
    assert len(threaded["selection"]["steps"][1]["candidates"]) == 2


@pytest.mark.slow
def test_local_processes_same_report(case, threaded):
    rec, nominal = case
    rep = diagnose(rec, nominal, options=Options(plots=False, effects=EFFECTS, workers=2))
    assert _canon(rep) == _canon(threaded)


def test_dask_local_cluster_same_report(case, threaded, dask_cluster):
    rec, nominal = case
    rep = diagnose(rec, nominal, options=Options(plots=False, effects=EFFECTS, cluster=dask_cluster))
    assert _canon(rep) == _canon(threaded)


@pytest.mark.slow
def test_a_library_object_selects_as_effect_keys_do(case, threaded):
    """``Diagnosis(library=...)`` proposes the candidates of the library it is given: the library of
    the three effects gives the report that selecting their keys from the default library gives."""
    from experiment_runner.apps.diagnosis.effects import LIBRARY
    from experiment_runner.apps.diagnosis.estimator import Diagnosis
    rec, nominal = case
    d = Diagnosis(library=LIBRARY.select(EFFECTS), plots=False).fit(rec, nominal)
    assert d.effects_ == ["coulomb", "viscous"]
    assert _canon(dict(d.report_, _improved_spec=d.model_)) == _canon(threaded)


@pytest.mark.slow
def test_bad_workers_named(case):
    rec, nominal = case
    with pytest.raises(ConfigError, match="--workers: must be >= 1"):
        diagnose(rec, nominal, options=Options(plots=False, effects=EFFECTS, workers=0))


@pytest.mark.slow
def test_cli_options():
    p = add_diagnose_arguments(argparse.ArgumentParser())
    opt = diagnose_options(p.parse_args(["rec.mcap", "--workers", "3", "--cluster", "tcp://h:8786"]))
    assert (opt.workers, opt.cluster) == (3, "tcp://h:8786")
    opt = diagnose_options(p.parse_args(["rec.mcap"]))
    assert (opt.workers, opt.cluster) == (None, None)


def test_model_spec_pickles_without_kernels():
    spec = load_model("fi_stage_nofi")
    spec.compiled()
    back = pickle.loads(pickle.dumps(spec))
    assert back.preset == spec.preset and back._compiled == {} and "c" in spec._compiled
    assert back.compiled().fc_tot == spec.compiled().fc_tot
