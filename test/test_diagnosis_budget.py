"""Issue 25 item 5: a diagnosis in bounded time with visible progress (``nanostage diagnose
--max-seconds``, ``--quiet``; :mod:`experiment_runner.apps.diagnosis.budget`).

Each test synthesises a short concealed-effect record (the self-test's ``coulomb_+30%`` truth on
three quarter-second circle trials; a full diagnosis adopts ``coulomb``) and runs the command
line on it.
"""
import json
import math
import os
import signal

import pytest
import yaml

from experiment_runner.apps.cli import main
from experiment_runner.apps.diagnosis import tasks
from experiment_runner.apps.diagnosis.budget import Budget, BudgetReached, checkpoint, halt_search
from experiment_runner.apps.diagnosis.effects.base import NOMINAL
from experiment_runner.apps.diagnosis.selftest import CASES, EXPERIMENTS
from experiment_runner.apps.diagnosis.synth import synth


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """A 0.75 s concealed Coulomb (+30 %) record and its nominal (MCAP)."""
    tmp = tmp_path_factory.mktemp("budget")
    case = next(c for c in CASES if c.name == "coulomb_+30%")
    exp = dict(EXPERIMENTS["circle"], name="diag_budget", trials=3)
    exp["profile"] = dict(exp["profile"], cycles=0.25 / (2 * math.pi * 1.0e-3 / 0.02))
    (tmp / "truth.yaml").write_text(yaml.safe_dump(case.truth_doc(), sort_keys=False))
    (tmp / "experiment.yaml").write_text(yaml.safe_dump(exp, sort_keys=False))
    return synth(tmp / "truth.yaml", tmp / "experiment.yaml", tmp / "rec.mcap")


def _diagnose(record, out, *extra):
    return main(["diagnose", str(record), NOMINAL, "--out", str(out), "--no-plots", *extra])


@pytest.mark.slow
def test_tiny_budget_ends_early_with_the_statement_leading_the_report(record, tmp_path, capsys):
    """--max-seconds 1: the search stops (the record alone takes longer to read, predict and
    locate), nothing is adopted from the unfinished step, and report.md, report.json and stdout
    lead with what was not examined; exit status 0 (a report was written)."""
    out = tmp_path / "d"
    assert _diagnose(record, out, "--max-seconds", "1") == 0
    cap = capsys.readouterr()
    rep = json.loads((out / "report.json").read_text())
    b = rep["budget"]
    assert b["max_seconds"] == 1.0 and b["reached"] is True and b["stopped"] == "time budget"
    assert b["spent_s"] >= 1.0
    assert any(x.startswith("forward step 1") for x in b["not_examined"]), b["not_examined"]
    assert "drive-noise level" in b["not_examined"]
    assert rep["found"] == []                     # coulomb is adopted by a full run; none here
    assert rep["verdict"].endswith("(partial: the time budget was reached)")
    md = [ln for ln in (out / "report.md").read_text().splitlines() if ln.strip()]
    assert md[0].startswith("# Diagnosis") and "time budget of 1 s reached after stage" in md[1]
    assert "not examined: forward step 1" in md[1]
    assert cap.out.splitlines()[0].startswith("partial: time budget of 1 s reached after stage")
    assert (out / "improved_preset.yaml").is_file()


@pytest.mark.slow
def test_progress_on_stderr_and_quiet_silences_it(record, tmp_path, capsys):
    """A progress line per stage with the elapsed seconds on stderr by default; none with --quiet
    (stdout, the answer, is the same)."""
    assert _diagnose(record, tmp_path / "a", "--max-seconds", "1") == 0
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.startswith("[diagnose")]
    stages = [ln.split("] ", 1)[1].split(" done")[0] for ln in lines if " done" in ln]
    assert stages[:4] == ["read", "predict", "locate", "prepare"], lines
    assert all(ln[len("[diagnose"):].split("s]")[0].strip().replace(".", "").isdigit() for ln in lines)
    assert _diagnose(record, tmp_path / "b", "--max-seconds", "1", "--quiet") == 0
    assert "[diagnose" not in capsys.readouterr().err


@pytest.mark.parametrize("value, expected", [
    ("0", "argument --max-seconds: got 0; expected a finite number > 0"),
    ("-3", "argument --max-seconds: got -3; expected a finite number > 0"),
    ("nan", "argument --max-seconds: got nan; expected a finite number > 0"),
    ("inf", "argument --max-seconds: got inf; expected a finite number > 0"),
    ("soon", "argument --max-seconds: got 'soon'"),
])
def test_invalid_max_seconds_refused_in_one_line(tmp_path, capsys, monkeypatch, value, expected):
    """Refused by the parser before any work: one line naming the option, the value and what is
    allowed; exit 2, no traceback, nothing written."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as ex:
        main(["diagnose", "r.mcap", NOMINAL, "--max-seconds", value])
    assert ex.value.code == 2
    err = capsys.readouterr().err
    assert expected in err.strip().splitlines()[-1] and "Traceback" not in err
    assert not any(tmp_path.iterdir())


def test_budget_refuses_a_bad_value_and_checkpoints_only_while_searching():
    for bad in (0, -1.0, float("nan"), float("inf"), "60"):
        with pytest.raises(ValueError, match="max_seconds: got"):
            Budget(bad)
    assert not Budget(None).spent()                # no limit
    b = Budget(1e-9, progress=False)
    checkpoint()                                   # no search running: nothing
    b.check()                                      # not searching: nothing
    with b.searching():
        with pytest.raises(BudgetReached):
            checkpoint()
    checkpoint()
    assert b.summary()["reached"] and b.summary()["after_stage"] is None


@pytest.mark.slow
def test_a_step_cut_short_is_dropped_whole(record, tmp_path, capsys, monkeypatch):
    """The budget runs out while step 1's candidates are being fitted (after the first fit, with
    a generous budget otherwise): step 1 is not adopted from the candidates that were fitted, the
    model stays the nominal."""
    fit = tasks.fit_candidate
    done = []

    def fit_then_run_out(*a, **k):
        f = fit(*a, **k)
        if not done:                               # the first fit to finish (fits run on threads)
            done.append(1)
            halt_search("time budget")
        return f
    monkeypatch.setattr(tasks, "fit_candidate", fit_then_run_out)
    out = tmp_path / "d"
    assert _diagnose(record, out, "--max-seconds", "600", "--quiet") == 0
    rep = json.loads((out / "report.json").read_text())
    assert rep["budget"]["reached"] and rep["budget"]["after_stage"] == "prepare"
    assert rep["found"] == [] and rep["selection"]["steps"] == []
    assert "time budget of 600 s reached after stage prepare" in (out / "report.md").read_text()


@pytest.mark.slow
def test_interrupted_search_leaves_its_partial_report(record, tmp_path, capsys, monkeypatch):
    """SIGTERM during the search: the partial report is written (marked interrupted) and the
    command ends as interrupted (exit 128 + 15)."""
    fit = tasks.fit_candidate
    sent = []

    def fit_then_sigterm(*a, **k):
        if not sent:
            sent.append(1)
            os.kill(os.getpid(), signal.SIGTERM)
        return fit(*a, **k)
    monkeypatch.setattr(tasks, "fit_candidate", fit_then_sigterm)
    out = tmp_path / "d"
    assert _diagnose(record, out, "--quiet") == 128 + signal.SIGTERM
    err = capsys.readouterr().err
    assert f"partial report (interrupted): {out / 'report.md'}" in err
    rep = json.loads((out / "report.json").read_text())
    assert rep["budget"]["stopped"] == "interrupted (SIGTERM)" and rep["found"] == []
    assert rep["verdict"].endswith("(partial: interrupted (SIGTERM))")
    md = [ln for ln in (out / "report.md").read_text().splitlines() if ln.strip()]
    assert "interrupted (SIGTERM) after stage prepare; not examined: forward step 1" in md[1]
