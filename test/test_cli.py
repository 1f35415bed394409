"""``nanostage`` entry point: a bad input file or recording is an error message and exit 2, not a traceback."""
from __future__ import annotations

import pytest

from experiment_runner.apps.cli import main


def test_bad_preset_file_names_field_and_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("stage:\n  table: {mass: -1}\n")
    assert main(["presets", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert "stage.table.mass: got -1" in err and str(bad) in err


def test_not_an_mcap_file_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"garbage\n")
    assert main(["replay", str(bad), "--check"]) == 2
    err = capsys.readouterr().err
    assert "not an MCAP file" in err and "Traceback" not in err


def test_graph_bad_or_malformed_experiment_exits_2_before_any_node(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("stage: {mass: -2.0}\nthis_key_does_not_exist: 1\n")
    broken = tmp_path / "broken.yaml"
    broken.write_text("not: [valid")
    assert main(["graph", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and str(bad) in err and "this_key_does_not_exist: unknown key" in err
    assert main(["graph", str(broken), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err
    assert "not valid YAML at line 1" in err and str(broken) in err
    assert not (tmp_path / "o" / "run.mcap").exists()


def _fails(argv, capsys, *expected) -> str:
    """``nanostage argv`` ends with exit 2 and a message (no traceback) holding ``expected``."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith(f"nanostage {argv[0]}: "), err
    for text in expected:
        assert text in err, err
    return err


def test_graph_bad_input_exits_2_naming_it(tmp_path, capsys, monkeypatch):
    out = tmp_path / "o"
    _fails(["graph", "no_such_experiment", "--out", str(out)], capsys,
           "no_such_experiment: no such experiment file", "shipped experiments: fi_p2p_5um")
    _fails(["graph", str(tmp_path / "missing.yaml"), "--out", str(out)], capsys, "missing.yaml: no such experiment file")
    _fails(["graph", "fi_p2p_5um", "--domain-id", "300", "--out", str(out)], capsys,
           "ROS domain ID (--domain-id): got 300; expected an integer from 0 to 232")
    monkeypatch.setenv("ROS_DOMAIN_ID", "lab")
    _fails(["graph", "fi_p2p_5um", "--out", str(out)], capsys,
           "ROS domain ID (environment variable ROS_DOMAIN_ID): got 'lab'")
    monkeypatch.delenv("ROS_DOMAIN_ID")
    _fails(["graph", "fi_p2p_5um", "--timeout", "0", "--out", str(out)], capsys, "--timeout: got 0.0; expected a positive")
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    _fails(["graph", "fi_p2p_5um", "--out", str(a_file)], capsys, f"--out {a_file}: a file is there")
    assert not out.exists()                                    # refused before anything was made


def test_replay_bad_input_exits_2_naming_it(tmp_path, capsys):
    from experiment_runner.core.experiment import experiment_preset, load_experiment, run_batch
    from experiment_runner.core.recording import write_run
    _fails(["replay", str(tmp_path / "missing.mcap")], capsys, "missing.mcap: no such file or directory")
    yml = tmp_path / "exp.yaml"
    yml.write_text("preset: fi_stage\n")
    _fails(["replay", str(yml), "--check"], capsys, "exp.yaml: not an MCAP file")
    (tmp_path / "empty").mkdir()
    _fails(["replay", str(tmp_path / "empty")], capsys, "empty")
    exp = load_experiment("fi_p2p_5um")
    _, res = run_batch(exp)
    rec = write_run(tmp_path / "run", res, experiment_preset(exp))
    _fails(["replay", str(rec), "--topics", "/stage/measured", "/nope"], capsys,
           "no topic /nope in the recording (its topics: /experiment/config")
    _fails(["replay", str(rec), "--domain-id", "233"], capsys, "got 233; expected an integer from 0 to 232")
    for bad in (["--rate", "-1"], ["--rate", "fast"], ["--wait-for", "-3"]):
        with pytest.raises(SystemExit) as exc:
            main(["replay", str(rec), *bad])
        assert exc.value.code == 2
        err = capsys.readouterr().err
        assert f"argument {bad[0]}: got '{bad[1]}'; expected a number >= 0" in err and "Traceback" not in err


def _refused_by_argparse(argv, capsys, *expected) -> str:
    """``nanostage argv`` stops in argument parsing: exit 2, argparse's one-line error."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"nanostage {argv[0]}: error: " in err, err
    for text in expected:
        assert text in err, err
    return err


def test_campaign_bad_input_exits_2_before_any_work(tmp_path, capsys):
    out = tmp_path / "o"
    _refused_by_argparse(["campaign", "table_4_2", "--trials", "-3", "--out", str(out)], capsys,
                         "argument --trials: got -3; expected an integer >= 1")
    _refused_by_argparse(["campaign", "table_4_2", "--workers", "0", "--out", str(out)], capsys,
                         "argument --workers: got 0; expected an integer >= 1")
    _refused_by_argparse(["campaign", "table_4_2", "--dwell", "nan", "--out", str(out)], capsys,
                         "argument --dwell: got nan; expected a finite number > 0")
    _refused_by_argparse(["campaign", "table_4_2", "--calibration-trials", "two", "--out", str(out)], capsys,
                         "argument --calibration-trials: got 'two'")
    _fails(["campaign", "no_such_campaign", "--out", str(out)], capsys,
           "no_such_campaign: no such campaign file", "shipped campaigns: ")
    _fails(["campaign", "table_4_2", "--calibration", str(tmp_path / "none.json"), "--out", str(out)], capsys,
           "--calibration", "none.json: no such calibration file")
    bad = tmp_path / "cal.json"
    bad.write_text("{not json")
    _fails(["campaign", "table_4_2", "--calibration", str(bad), "--out", str(out)], capsys, "invalid JSON")
    bad.write_text('{"values": {"ki_scale": "fast"}}')
    _fails(["campaign", "table_4_2", "--calibration", str(bad), "--out", str(out)], capsys,
           "field 'values' must map each calibrated quantity to a finite number")
    assert not out.exists()                                    # refused before anything was made


def test_paper_unknown_claim_group_exits_2_listing_the_groups(tmp_path, capsys):
    _fails(["paper", "--only", "appendix_z", "--out", str(tmp_path / "p")], capsys,
           "--only appendix_z: no claim group starts with it", "groups: appendix_a, van")
    assert not (tmp_path / "p").exists()


@pytest.mark.parametrize("argv, expected", [
    (["presets", "no_such_preset"], "no_such_preset: no such preset file"),
    (["graph"], "give an EXPERIMENT (name or YAML path), or --list"),
    (["campaign"], "give a CAMPAIGN (name or YAML path), --list or --main"),
    (["campaign", "frf_fi", "--dwell", "0.5", "--out", "c"], "--dwell applies to point-to-point campaigns only"),
    (["diagnose"], "give RECORDING [NOMINAL], or --list-effects, or --selftest"),
    (["convert", "table", "no_such.csv", "--rate", "1000", "--command", "u", "--measured", "y", "--out", "x.mcap"],
     "no_such.csv"),
    (["convert", "emps", "no_such_dir", "--out", "x.mcap"], "no_such_dir: no such file"),
    (["design", "fi_stage"], "give the required RMS in-position error: --rms NM"),
    (["design", "no_such_preset", "--rms", "2"], "no_such_preset: no such preset file"),
    (["synth", "no_such_truth", "fi_p2p_5um", "--out", "x.mcap"], "no_such_truth: no such preset file"),
    (["diagnose", "no_such.mcap", "--out", "d"], "no_such.mcap: no such file or directory"),
    (["realdata", "--data", "no_such_dir", "--out", "r"], "real data folder not found; tried no_such_dir"),
])
def test_other_commands_bad_input_exits_2_naming_it(tmp_path, capsys, monkeypatch, argv, expected):
    monkeypatch.chdir(tmp_path)
    _fails(argv, capsys, expected)


@pytest.mark.parametrize("argv, expected", [
    (["bench", "--quick=yes"], "argument --quick: ignored explicit argument 'yes'"),
    (["paper", "--json=yes"], "argument --json: ignored explicit argument 'yes'"),
    (["synth", "fi_stage"], "the following arguments are required"),
    (["realdata", "--only", "nothing"], "argument --only: invalid choice: 'nothing'"),
    (["design", "fi_stage", "--rms", "-2"], "argument --rms: got -2; expected a finite number > 0"),
])
def test_bad_arguments_are_argparse_errors(capsys, argv, expected):
    err = _refused_by_argparse(argv, capsys)
    assert expected in err, err


def test_every_command_has_a_bad_input_test():
    """Each ``nanostage`` subcommand appears in a bad-input case of this file."""
    import re
    from pathlib import Path

    from experiment_runner.apps.cli import build_parser
    commands = set(build_parser()._subparsers._group_actions[0].choices)
    tested = set(re.findall(r'\(\["(\w+)"', Path(__file__).read_text()))
    assert commands <= tested, f"no bad-input test for: {sorted(commands - tested)}"


@pytest.mark.slow
def test_a_closed_output_pipe_is_not_a_traceback():
    import subprocess
    import sys
    # far more output than a pipe holds (64 KiB), so the writer meets the closed pipe for sure
    child = ("import sys\nfrom experiment_runner.apps.cli import main\n"
             "for _ in range(400):\n    rc = main(['presets'])\n    if rc:\n        sys.exit(rc)\n")
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.readline()               # take one line, then stop listening (as `| head -1` does)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141 and "Traceback" not in err, err


@pytest.mark.slow
def test_a_command_imports_only_its_own_module():
    """``nanostage presets`` (the before-stop hook's alias-bomb probe) does not import the
    simulator, the diagnosis or the plotting stack: it starts in what reading a preset takes."""
    import subprocess
    import sys
    code = ("import sys\nfrom experiment_runner.apps.cli import main\nrc = main(['presets', 'fi_stage'])\n"
            "heavy = [m for m in ('experiment_runner.core.batch', 'experiment_runner.apps.design', 'experiment_runner.apps.diagnosis',"
            " 'matplotlib', 'control') if m in sys.modules]\nprint(rc, heavy, file=sys.stderr)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stderr.strip().splitlines()[-1] == "0 []", out.stderr


@pytest.mark.slow
def test_json_stdout_carries_only_what_python_prints():
    """A compiled library writing to descriptor 1 (LAPACK's 'On entry to DLASCL ...' on a NaN)
    must not break the JSON of a --json run: it goes to stderr, the JSON stays parseable."""
    import json
    import subprocess
    import sys
    code = ("import os, json\n"
            "from experiment_runner.apps.cli import python_only_stdout\n"
            "with python_only_stdout(True):\n"
            "    os.write(1, b' ** On entry to DLASCL parameter number  4 had an illegal value\\n')\n"
            "    print(json.dumps({'ok': 1}))\n"
            "print('after')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    first, after = out.stdout.splitlines()
    assert json.loads(first) == {"ok": 1} and after == "after"
    assert "DLASCL" in out.stderr


@pytest.mark.dask
def test_bench_json_is_one_json_object_with_every_figure(capsys):
    """``nanostage bench --json`` prints one JSON object and nothing else on stdout (the main
    job's library function printed its report path there), with issue 15's distance-to-limit
    figures: the bench's own code on tiny sizes (its timings are ``nanostage bench``'s, never a test's)."""
    import json

    from experiment_runner.apps.bench import Sizes, run_bench
    assert run_bench(as_json=True, graph=False, sizes=Sizes(repeats=1, campaign_trials=2, diagnose_seconds=1.0, emps=False)) == 0
    res = json.loads(capsys.readouterr().out)
    for key in ("core_single_rtf", "core_batch_rtf", "core_substeps_per_sample", "core_ns_per_substep_per_trial",
                "campaign_scale_out_2", "campaign_trials_per_s_dask_2", "diagnose_seconds_1s"):
        assert res[key] > 0, key
