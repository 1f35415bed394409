"""``nanostage`` entry point: a bad input file or recording is an error message and exit 2, not a traceback."""
from __future__ import annotations

from experiment_runner.cli import main


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
