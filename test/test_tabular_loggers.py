"""``nanostage convert table`` on what real data loggers write (issue 25, item 6).

Every input is built here: a logger's text export with a preamble above the column names (and
a units row), two loggers at 1 kHz and 250 Hz joined on their time columns, a time column in
ms, JSON tables (columns, records, one record per line), a drive input holding a test signal,
and the command kind (``drive`` / ``measured``) carried into the recording and read back. The
EMPS validation record (force pulses) is read from ``../shared/data`` when it is there.
"""
from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from experiment_runner.apps.cli import main
from experiment_runner.core.recording import McapRecorder, read_recording
from experiment_runner.core.recording.writer import typestore
from experiment_runner.core.tabular import convert_table, read_table
from msg_defs.convert import joint_state
from stage_sim.validation import ConfigError, ConfigWarning

RATE = 1000.0


def record(n: int = 400, rate: float = RATE, t0: float = 0.0, seed: int = 1) -> dict:
    """A closed-loop-looking record: a smooth reference, a measured position on a 1 nm grid and
    a command, every value exactly representable in the text written (12 significant digits)."""
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(n) / rate
    x_ref = np.round(1e-5 * np.sin(2 * np.pi * 2.0 * (t - t0)), 12)
    y = np.round((x_ref + 2e-8 * rng.standard_normal(n)) / 1e-9) * 1e-9
    u = np.round(3.0 * np.cos(2 * np.pi * 2.0 * (t - t0)) + 0.1 * rng.standard_normal(n), 9)
    return {k: _as_written(v) for k, v in {"t": t, "x_ref": x_ref, "y": y, "u": u}.items()}


def _as_written(a: np.ndarray) -> np.ndarray:
    """The values a text file written with ``%.12g`` gives back."""
    return np.array([float(f"{v:.12g}") for v in a])


def _csv(path, header_lines: list[str], names: list[str], cols: list[np.ndarray], fmt="%.12g"):
    with open(path, "w") as f:
        for h in header_lines:
            f.write(h + "\n")
        f.write(",".join(names) + "\n")
        np.savetxt(f, np.column_stack(cols), delimiter=",", fmt=fmt)
    return path


def _convert(args: list[str], capsys) -> tuple[int, str, str]:
    rc = main(["convert", "table", *args])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


FLAGS = ["--time", "t", "--reference", "x_ref", "--command", "u", "--measured", "y"]


# --------------------------------------------------------------------------- header rows
def test_a_three_line_logger_header_is_detected_or_skipped_and_a_wrong_skip_gets_the_hint(tmp_path, capsys):
    d = record()
    src = _csv(tmp_path / "logger.csv", ["ACME DataLogger 3000, firmware 2.1, serial 0042", "Start: 2024-05-02 10:31:07"],
               ["t", "x_ref", "y", "u"], [d["t"], d["x_ref"], d["y"], d["u"]])
    # detected: the two lines above the names are the logger's preamble
    tab = read_table(src)
    assert tab.names == ["t", "x_ref", "y", "u"] and len(tab.header) == 2 and "serial 0042" in tab.header[0]
    assert tab.where(0) == "line 4"
    rc, out, err = _convert([str(src), *FLAGS, "--out", str(tmp_path / "auto")], capsys)
    assert rc == 0, err
    rec = read_recording(tmp_path / "auto")
    for k in ("x_ref", "y", "u"):
        np.testing.assert_array_equal(getattr(rec, k), d[k])
    assert rec.config_doc()["provenance"]["header"][1] == "Start: 2024-05-02 10:31:07"
    # skipped: --skip-rows 2 reads the names line as the header, the same recording
    rc, out, err = _convert([str(src), *FLAGS, "--skip-rows", "2", "--out", str(tmp_path / "skip")], capsys)
    assert rc == 0, err
    np.testing.assert_array_equal(read_recording(tmp_path / "skip").u, d["u"])
    # a wrong skip: the error names the header-like line and the --skip-rows that reads it
    rc, out, err = _convert([str(src), *FLAGS, "--skip-rows", "1", "--out", str(tmp_path / "bad")], capsys)
    assert rc == 2 and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "logger.csv: line 3 has 4 fields, expected 1" in err
    assert "line 3 (t, x_ref, y, u) looks like a header line" in err and "pass --skip-rows 2" in err
    assert not (tmp_path / "bad").exists()


def test_a_units_row_under_the_names_and_a_header_line_inside_the_data(tmp_path, capsys):
    d = record(50)
    src = tmp_path / "units.txt"
    with open(src, "w") as f:
        f.write("[Header]\nDevice=rig 2\n[Data]\nt\tx_ref\ty\tu\n[s]\t[m]\t[m]\t[N]\n")
        np.savetxt(f, np.column_stack([d["t"], d["x_ref"], d["y"], d["u"]]), delimiter="\t", fmt="%.12g")
    tab = read_table(src)
    assert tab.names == ["t", "x_ref", "y", "u"] and tab.units == {"t": "[s]", "x_ref": "[m]", "y": "[m]", "u": "[N]"}
    assert tab.header == ["[Header]", "Device=rig 2", "[Data]"]
    rc, out, _ = _convert([str(src), "--list"], capsys)
    assert rc == 0 and "columns: t [s], x_ref [m], y [m], u [N]" in out and "header: Device=rig 2" in out
    # a second log appended to the first: its header line is named, with the hint
    text = src.read_text().splitlines()
    src.write_text("\n".join(text[:20] + ["t\tx_ref\ty\tu"] + text[20:]) + "\n")
    rc, out, err = _convert([str(src), *FLAGS, "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "units.txt: column 't' (--time) line 21: 't' is not a number" in err
    assert "line 21 (t, x_ref, y, u) looks like a header line" in err


# --------------------------------------------------------------------------- joining two loggers
def _two_loggers(tmp_path, force_t0=0.1, force_t1=1.9, force_unit_in_name=True):
    d = record(2000)                                            # 1 kHz, 0 .. 1.999 s
    pos = _csv(tmp_path / "pos.csv", [], ["t", "x_ref", "y"], [d["t"], d["x_ref"], d["y"]])
    rng = np.random.default_rng(7)
    t2 = np.round(np.arange(force_t0, force_t1, 0.004), 9)     # 250 Hz
    f2 = np.round(rng.normal(0.0, 2.0, len(t2)), 6)            # a force no smooth function would interpolate exactly
    name = "time [ms]" if force_unit_in_name else "time"
    force = _csv(tmp_path / "force.csv", ["LoadCell logger"], [name, "F"], [t2 * 1e3, f2], fmt="%.9g")
    return d, pos, force, t2, f2, name


def test_two_loggers_at_1khz_and_250hz_are_joined_by_interpolation_within_the_overlap(tmp_path, capsys):
    d, pos, force, t2, f2, tname = _two_loggers(tmp_path)
    rc, out, err = _convert([str(pos), "--time", "t", "--reference", "x_ref", "--measured", "y", "--command", "F",
                             "--command-kind", "measured", "--join", str(force), "--join-time", tname,
                             "--out", str(tmp_path / "j")], capsys)
    assert rc == 0, err
    # the warning says what was done, with both rates and the overlap
    assert "force.csv: joined at 250 Hz onto the time base of pos.csv (1 kHz): F linearly interpolated within the " \
           "overlap 0.1 .. 1.896 s; 203 of 2000 sample(s) of pos.csv outside it dropped" in err
    assert "joined force.csv (F, linear)" in out and "command: measured" in out
    rec = read_recording(tmp_path / "j")
    cfg = rec.config_doc()
    # overlap only: the primary's samples from 0.1 s to 1.896 s, on its own time base
    assert len(rec) == 1797 and cfg["run"]["time_offset_s"] == pytest.approx(0.1, abs=1e-12)
    np.testing.assert_array_equal(rec.y, d["y"][100:1897])
    np.testing.assert_array_equal(rec.x_ref, d["x_ref"][100:1897])
    assert set(np.diff(rec.stamp_ns)) == {1_000_000}
    # the force: equal at the shared instants (every 4th sample), the straight line between its
    # two neighbours in between (1, 2, 3 ms after a force sample: weights 1/4, 1/2, 3/4)
    np.testing.assert_allclose(rec.u[::4], f2[:len(rec.u[::4])], rtol=0, atol=1e-12)
    for i in (1, 2, 3):
        j = np.arange(i, len(rec.u) - 3, 4)
        k = (j - i) // 4
        np.testing.assert_allclose(rec.u[j], f2[k] + i / 4 * (f2[k + 1] - f2[k]), rtol=0, atol=1e-12)
    joined = cfg["provenance"]["joined"][0]
    assert joined["file"] == "force.csv" and joined["rate"] == pytest.approx(250.0) and joined["columns"] == ["F"]
    assert joined["time"] == "time [ms] [ms]" and len(joined["sha256"]) == 64
    assert "from force.csv at 250 Hz, linearly interpolated" in cfg["mapping"]["/stage/command.effort"]
    assert cfg["warnings"] and "250 Hz" in cfg["warnings"][0]


@pytest.mark.slow
def test_a_joined_held_command_and_the_refusals(tmp_path, capsys):
    d, pos, force, t2, f2, tname = _two_loggers(tmp_path)
    base = [str(pos), "--time", "t", "--reference", "x_ref", "--measured", "y", "--command", "F"]
    # a held command (a controller's own log): the last value at or before each time
    assert _convert([*base, "--join", str(force), "--join-time", tname, "--join-method", "hold",
                     "--out", str(tmp_path / "h")], capsys)[0] == 0
    np.testing.assert_array_equal(read_recording(tmp_path / "h").u, np.repeat(f2, 4)[:1797])
    cases = {
        # no overlap: the force logger starts after the position logger stopped
        "late": (dict(force_t0=5.0, force_t1=6.0), [], "no overlap of the time bases: pos.csv's 't' spans 0 .. 1.999 "
                                                      "s, force.csv's 'time [ms]' 5 .. 5.996 s (in ms)"),
        # units that differ: the ms column read as s spans 1796 s against 2 s
        "units": (dict(force_unit_in_name=False), [], "the time bases differ in span by x898: pos.csv's 't' spans"),
        # a unit given against the header's
        "contradiction": ({}, ["--join-time-unit", "s"], "the header gives time column 'time [ms]' in ms, "
                                                          "--join-time-unit says s"),
    }
    for name, (kw, more, frag) in cases.items():
        sub = tmp_path / name
        sub.mkdir()
        _, pos2, force2, _, _, tn = _two_loggers(sub, **kw)
        rc, out, err = _convert([str(pos2), "--time", "t", "--reference", "x_ref", "--measured", "y", "--command", "F",
                                 "--join", str(force2), "--join-time", tn, *more, "--out", str(sub / "o")], capsys)
        assert rc == 2 and frag in err and len(err.strip().splitlines()) == 1, (name, err)
        assert not (sub / "o").exists()
    rc, out, err = _convert([*base, "--join-time", tname, "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "--join-time without --join" in err
    # a time column that goes back
    text = force.read_text().splitlines()
    text[10], text[11] = text[11], text[10]
    force.write_text("\n".join(text) + "\n")
    rc, out, err = _convert([*base, "--join", str(force), "--join-time", tname, "--out", str(tmp_path / "o")], capsys)
    assert rc == 2 and "force.csv: column 'time [ms]' (time of force.csv) does not increase at line 12" in err


@pytest.mark.slow
def test_join_from_a_mapping_file_with_sources(tmp_path):
    d, pos, force, t2, f2, tname = _two_loggers(tmp_path)
    mp = tmp_path / "rig.yaml"
    mp.write_text(yaml.safe_dump({"time": "t", "reference": "x_ref", "measured": "y", "command": "F",
                                  "sources": [{"file": "force.csv", "time": tname, "time_unit": "ms"}]}))
    from experiment_runner.core.tabular import load_mapping
    with pytest.warns(ConfigWarning, match="joined at 250 Hz"):
        rec = read_recording(convert_table(pos, load_mapping(mp), tmp_path / "m"))
    np.testing.assert_allclose(rec.u[::4], f2[:len(rec.u[::4])], rtol=0, atol=1e-12)
    # the joined file's column named explicitly, and the mapping's refusals
    mp.write_text(yaml.safe_dump({"time": "t", "reference": "x_ref", "measured": "y", "command": "force.F",
                                  "sources": [{"file": "force.csv", "time": tname}]}))
    with pytest.warns(ConfigWarning):
        rec2 = read_recording(convert_table(pos, load_mapping(mp), tmp_path / "m2"))
    np.testing.assert_array_equal(rec2.u, rec.u)
    bad = {"rate: 1000\ncommand: F\nmeasured: y\nsources: [{file: force.csv, time: t}]\n": "sources needs time",
           "time: t\ncommand: F\nmeasured: y\nsources: [{file: force.csv}]\n": "sources[0].time: got None",
           "time: t\ncommand: F\nmeasured: y\nsources: [{file: f.csv, time: t, method: cubic}]\n":
               "sources[0].method: got 'cubic'; expected linear",
           "time: t\ncommand: F\nmeasured: y\nsources: [{file: f.csv, time: t, when: 1}]\n":
               "sources[0]: unknown key(s) 'when'"}
    for text, frag in bad.items():
        mp.write_text(text)
        with pytest.raises(ConfigError) as err:
            load_mapping(mp)
        assert frag in str(err.value) and "rig.yaml" in str(err.value), (text, str(err.value))


# --------------------------------------------------------------------------- time unit
@pytest.mark.slow
def test_a_time_column_in_ms_is_warned_about_and_read_right_with_time_unit(tmp_path, capsys):
    n = 12000
    d = record(n)
    src = _csv(tmp_path / "ms.csv", [], ["t", "x_ref", "y", "u"], [np.arange(n) * 1.0, d["x_ref"], d["y"], d["u"]])
    rc, out, err = _convert([str(src), *FLAGS, "--out", str(tmp_path / "s")], capsys)
    assert rc == 0
    assert ("ms.csv: time column 't' read in s gives 1 Hz over 11999 s (12000 samples): implausible for a servo "
            "record (20 Hz to 1 MHz); if it is in ms, pass --time-unit ms (1 kHz, 11.999 s)") in err
    assert "warnings" in read_recording(tmp_path / "s").config_doc()          # the recording keeps it too
    rc, out, err = _convert([str(src), *FLAGS, "--time-unit", "ms", "--out", str(tmp_path / "ms")], capsys)
    assert rc == 0 and err == ""
    rec = read_recording(tmp_path / "ms")
    assert set(np.diff(rec.stamp_ns)) == {1_000_000} and rec.duration == pytest.approx(11.999)
    assert "ms -> s, given" in rec.config_doc()["mapping"]["stamps"]
    # a header that says ms is read in ms; a unit against it is refused
    src2 = _csv(tmp_path / "ms2.csv", [], ["Time [ms]", "x_ref", "y", "u"], [np.arange(n) * 1.0, d["x_ref"], d["y"],
                                                                              d["u"]])
    flags2 = ["--time", "Time [ms]", *FLAGS[2:]]
    rc, out, err = _convert([str(src2), *flags2, "--out", str(tmp_path / "h")], capsys)
    assert rc == 0 and err == "" and "1000 Hz, 11.999 s" in out
    assert "ms -> s, from the file's header" in read_recording(tmp_path / "h").config_doc()["mapping"]["stamps"]
    rc, out, err = _convert([str(src2), *flags2, "--time-unit", "s", "--out", str(tmp_path / "x")], capsys)
    assert rc == 2 and "the header gives time column 'Time [ms]' in ms, --time-unit says s" in err
    rc, out, err = _convert([str(src), *FLAGS, "--time-unit", "minutes", "--out", str(tmp_path / "x")], capsys)
    assert rc == 2 and "--time-unit: got 'minutes'; expected one of s, ms, us, ns" in err
    # a plausible rate is not warned about
    with __import__("warnings").catch_warnings():
        __import__("warnings").simplefilter("error", ConfigWarning)
        convert_table(src, {"time": "t", "time_unit": "ms", "command": "u", "measured": "y"}, tmp_path / "q")


# --------------------------------------------------------------------------- JSON
def test_json_tables_in_columns_records_and_lines(tmp_path, capsys):
    d = record(300)
    cols = {"t": d["t"].tolist(), "x_ref": d["x_ref"].tolist(), "y_um": (d["y"] * 1e6).tolist(), "u": d["u"].tolist(),
            "gain": 2.0, "status": ["ok"] * 300}
    recs = [{"t": a, "x_ref": b, "y_um": c, "u": e, "meta": {"ok": True}}
            for a, b, c, e in zip(cols["t"], cols["x_ref"], cols["y_um"], cols["u"])]
    files = {"cols.json": json.dumps(cols), "records.json": json.dumps(recs),
             "lines.jsonl": "\n".join(json.dumps(r) for r in recs) + "\n",
             "split.json": json.dumps({"columns": ["t", "x_ref", "y_um", "u"],
                                       "data": [[r["t"], r["x_ref"], r["y_um"], r["u"]] for r in recs]})}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        flags = ["--time", "t", "--reference", "x_ref", "--command", "u", "--measured", "y_um", "--scale", "y_um=1e-6"]
        if name == "cols.json":
            flags += ["--scale", "u=gain"]                     # a number of the JSON is a scalar
        rc, out, err = _convert([str(tmp_path / name), *flags, "--out", str(tmp_path / name.split(".")[0])], capsys)
        assert rc == 0, (name, err)
        rec = read_recording(tmp_path / name.split(".")[0])
        np.testing.assert_array_equal(rec.x_ref, d["x_ref"])
        np.testing.assert_array_equal(rec.y, np.array(cols["y_um"]) * 1e-6)
        np.testing.assert_array_equal(rec.u, d["u"] * (2.0 if name == "cols.json" else 1.0))
    assert read_table(tmp_path / "records.json").names == ["t", "x_ref", "y_um", "u"]      # meta.ok: flags, not data
    # a bad value is named by its record; a key twice is refused
    recs[17]["u"] = "n/a"
    (tmp_path / "bad.json").write_text(json.dumps(recs))
    rc, out, err = _convert([str(tmp_path / "bad.json"), "--time", "t", "--command", "u", "--measured", "y_um",
                             "--out", str(tmp_path / "b")], capsys)
    assert rc == 2 and "bad.json: column 'u' (--command) record 17: 'n/a' is not a number" in err
    (tmp_path / "dup.json").write_text('{"t": [0, 1, 2], "u": [1, 2, 3], "u": [4, 5, 6]}')
    with pytest.raises(ConfigError, match=r"dup.json: key 'u' twice in one object"):
        read_table(tmp_path / "dup.json")
    (tmp_path / "broken.json").write_text('{"t": [0, 1, 2], "u": [1, 2,')
    with pytest.raises(ConfigError, match=r"broken.json: not valid JSON \(line 1, column 29"):
        read_table(tmp_path / "broken.json")


# --------------------------------------------------------------------------- command kind
def test_command_kind_round_trips_and_an_old_recording_reads_as_drive(tmp_path, capsys):
    d = record(100)
    src = _csv(tmp_path / "r.csv", [], ["t", "x_ref", "y", "u"], [d["t"], d["x_ref"], d["y"], d["u"]])
    for kind in ("measured", "drive"):
        rc, out, err = _convert([str(src), *FLAGS, "--command-kind", kind, "--out", str(tmp_path / kind)], capsys)
        assert rc == 0 and f"command: {kind}" in out
        rec = read_recording(tmp_path / kind)
        assert rec.command_kind == kind and rec.config_doc()["command"]["kind"] == kind
    mp = tmp_path / "m.yaml"
    mp.write_text("time: t\ncommand: u\nmeasured: y\nreference: x_ref\ncommand_kind: measured\n")
    assert _convert([str(src), "--mapping", str(mp), "--out", str(tmp_path / "mp")], capsys)[0] == 0
    assert read_recording(tmp_path / "mp").command_kind == "measured"
    assert read_recording(convert_table(src, {"time": "t", "command": "u", "measured": "y"},
                                        tmp_path / "default"), require_reference=False).command_kind == "drive"
    rc, out, err = _convert([str(src), *FLAGS, "--command-kind", "force", "--out", str(tmp_path / "x")], capsys)
    assert rc == 2 and "--command-kind: got 'force'; expected drive (a command to a drive with a force constant" in err
    # a recording written without the key (as every one before it, and every simulated one)
    ts = typestore()

    def old(path, config):
        with McapRecorder(path, config) as w:
            for k in range(5):
                s = k * 1_000_000
                w.write("/stage/reference", s, joint_state(ts, s, ["table"], position=[0.0], velocity=[0.0]))
                w.write("/stage/command", s, joint_state(ts, s, ["motor"], effort=[1.0]))
                w.write("/stage/measured", s, joint_state(ts, s, ["table"], position=[0.0]))
        return read_recording(path)
    assert old(tmp_path / "old", "recording_contract: 1\nrun: {axis: linear}\n").command_kind == "drive"
    assert old(tmp_path / "none", None).command_kind == "drive"
    with pytest.raises(ConfigError, match=r"/experiment/config: command.kind: got 'torque'; expected drive"):
        _ = old(tmp_path / "bad", "command: {kind: torque}\n").command_kind


def test_a_command_column_holding_the_known_force_is_split(tmp_path, capsys):
    """A test signal added to the drive input: the command column holds both; the command
    written is the controller's part, the signal goes to /stage/external_force, the sum is kept."""
    d = record(200)
    pulse = np.where((np.arange(200) // 50) % 2 == 1, 5.0, 0.0)
    total = d["u"] + 2.0 * pulse                                   # the drive input, pulse included
    src = _csv(tmp_path / "p.csv", [], ["t", "x_ref", "y", "u", "pulse"], [d["t"], d["x_ref"], d["y"], total, pulse])
    rc, out, err = _convert([str(src), *FLAGS, "--command", "u", "--input", "pulse", "--scale", "pulse=2",
                             "--command-includes-input", "--out", str(tmp_path / "o")], capsys)
    assert rc == 0, err
    assert "known external force on /stage/external_force: pulse * 2 [N]" in out
    rec = read_recording(tmp_path / "o")
    np.testing.assert_allclose(rec.u, d["u"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rec.external_force, 2.0 * pulse)
    np.testing.assert_allclose(rec.u + rec.external_force, total, rtol=0, atol=1e-12)
    rc, out, err = _convert([str(src), *FLAGS, "--command-includes-input", "--out", str(tmp_path / "x")], capsys)
    assert rc == 2 and "--command-includes-input needs --input" in err


# --------------------------------------------------------------------------- rotary
def test_a_small_rotary_servo_record_converts_in_rotary_units(tmp_path, capsys):
    """A torque-mode servo: µrad encoder steps, mN·m torques -- converted as they are, said rotary."""
    n = 500
    t = np.arange(n) / 2000.0
    theta = np.round(2e-4 * np.sin(2 * np.pi * 3 * t) / 1.2566e-4) * 1.2566e-4     # 50000 counts/rev
    tau = np.round(2e-3 * np.cos(2 * np.pi * 3 * t), 9)
    src = _csv(tmp_path / "servo.csv", [], ["t", "tau", "theta"], [t, tau, theta])
    rc, out, err = _convert([str(src), "--time", "t", "--command", "tau", "--measured", "theta", "--units", "rotary",
                             "--command-kind", "measured", "--out", str(tmp_path / "s")], capsys)
    assert rc == 0 and err == "" and "rotary axis, open-loop record" in out
    rec = read_recording(tmp_path / "s", require_reference=False)
    assert rec.axis == "rotary" and rec.command_kind == "measured"
    np.testing.assert_array_equal(rec.u, tau)
    assert "[N·m]" in rec.config_doc()["mapping"]["/stage/command.effort"]


# --------------------------------------------------------------------------- EMPS with force pulses
@pytest.fixture(scope="module")
def pulses_file(shared_file):
    return shared_file("emps/DATA_EMPS_PULSES.mat")


@pytest.mark.slow
def test_convert_emps_keeps_the_pulses_as_the_known_external_force(pulses_file, tmp_path, capsys):
    from scipy.io import loadmat
    m = loadmat(pulses_file)
    qg, qm, vir = (m[k].ravel() for k in ("qg", "qm", "vir"))
    pulses = m["pulses_N"].ravel().astype(float)
    gtau, kp, kv = (float(m[k].ravel()[0]) for k in ("gtau", "kp", "kv"))
    assert main(["convert", "emps", str(pulses_file), "--out", str(tmp_path / "p")]) == 0
    out = capsys.readouterr().out
    assert "known external force on /stage/external_force: pulses_N * gtau (35.1507) * 1.014 [N]" in out
    rec = read_recording(tmp_path / "p")
    # the pulse force on the load, in N: gtau * 1.014 V per unit of pulses_N (0 or 5): 0 or 178.2 N
    np.testing.assert_array_equal(rec.external_force, pulses * gtau * 1.014)
    assert set(np.round(np.unique(rec.external_force), 1)) == {0.0, 178.2}
    # the force on the load is all there: command + external force = gtau * vir
    np.testing.assert_allclose(rec.u + rec.external_force, gtau * vir, rtol=0, atol=1e-9)
    # ... and the command is the controller's part: the benchmark's control law within 0.02 V rms
    # (the pulses, 5.07 V, are not in it)
    qf = np.concatenate([[qm[0]], 0.5 * (qm[1:] + qm[:-1])])
    law = kp * kv * (qg - qm) - kv * np.concatenate([[0.0], np.diff(qf) / 0.001])
    assert np.std(rec.u / gtau - law) < 0.02 and np.std(gtau * vir / gtau - law) > 2.0
    assert rec.command_kind == "drive" and rec.source.names == ["vir", "pulses_N"]
    cfg = rec.config_doc()
    assert cfg["run"]["case"] == "EMPS_PULSES" and "pulses" in cfg["notes"]
    assert "the command column holds the known external force" in cfg["mapping"]["/stage/command.effort"]
