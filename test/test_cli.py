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
