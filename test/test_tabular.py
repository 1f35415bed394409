"""``nanostage convert table``: tables written by other tools come back as contract recordings.

Round trips: a closed-loop record made by a small integrator in this file (a 2 kg mass with
viscous friction under a PD loop, with a known external force pulse; not the project's
simulator) is written with numpy (CSV with a header line, whitespace text with a commented
header, headerless TSV, ``.npz``), ``scipy.io.savemat`` (v5), ``h5py`` (a MATLAB v7.3 file:
512-byte MATLAB header, column-major datasets) and pandas (or the ``csv`` module when pandas
is not installed), at 1 kHz and 10 kHz, converted, and read back with ``read_recording``:
the values must come back bit for bit (after the stated scale), the stamps be exactly
``k / rate``. Every refusal is a one-line message (file, column or key, value, what is
allowed), exit 2, and nothing written. ``convert emps`` must give the recording the
pre-importer converter gave (re-implemented here from its mapping).
"""
from __future__ import annotations

import csv
import os

import numpy as np
import pytest
import yaml

from experiment_runner.apps.cli import main
from experiment_runner.core.recording import RecordingError, read_recording
from experiment_runner.core.tabular import EMPS_MAPPING, convert_table, load_mapping, read_table
from stage_sim.validation import ConfigError

T0 = 12.5            # source time of the first sample [s]: stamps start at 0, the offset goes to the config
N = 2000             # samples per record


def closed_loop(rate: float, n: int = N) -> dict:
    """A PD-controlled 2 kg mass with viscous friction (semi-implicit Euler, command held over
    each period) tracking a smooth 20 µm step, with a 0.5 N external force pulse."""
    dt = 1.0 / rate
    m, c, kp, kd = 2.0, 15.0, 4.0e5, 1.2e3
    t = T0 + np.arange(n) * dt
    s = np.clip((np.arange(n) * dt - 0.02) / 0.05, 0.0, 1.0)
    x_ref = 20e-6 * (s * s * (3 - 2 * s))
    f = np.where((np.arange(n) * dt > 0.1) & (np.arange(n) * dt < 0.12), 0.5, 0.0)
    x = v = 0.0
    y, u = np.empty(n), np.empty(n)
    rng = np.random.default_rng(int(rate))
    for k in range(n):
        y[k] = np.round((x + 2e-9 * rng.standard_normal()) / 1e-9) * 1e-9          # 1 nm encoder
        e = x_ref[k] - y[k]
        u[k] = kp * e - kd * (y[k] - (y[k - 1] if k else y[k])) / dt
        v += dt * (u[k] + f[k] - c * v) / m
        x += dt * v
    return {"time": t, "x_ref": x_ref, "u": u, "y_um": y * 1e6, "f": f}


COLS = ("time", "x_ref", "u", "y_um", "f")


def _flags(names: dict, scale: str | None = None) -> list[str]:
    out = ["--time", names["time"], "--reference", names["x_ref"], "--command", names["u"],
           "--measured", names["y_um"], "--input", names["f"], "--scale", f"{names['y_um']}={scale or '1e-6'}"]
    return out


# --------------------------------------------------------------------------- writers (other tools)
def w_savetxt_csv(d, p):
    p = p / "rec.csv"
    np.savetxt(p, np.column_stack([d[c] for c in COLS]), delimiter=",", header=",".join(COLS), comments="")
    return p, {c: c for c in COLS}, None


def w_savetxt_commented_header(d, p):
    p = p / "rec.txt"
    np.savetxt(p, np.column_stack([d[c] for c in COLS]), header=" ".join(COLS))     # '# time x_ref ...'
    return p, {c: c for c in COLS}, None


def w_savetxt_tsv_headerless(d, p):
    p = p / "rec.tsv"
    np.savetxt(p, np.column_stack([d[c] for c in COLS]), delimiter="\t")
    return p, {c: str(i + 1) for i, c in enumerate(COLS)}, None


def w_npz(d, p):
    p = p / "rec.npz"
    np.savez(p, **d, um=1e-6)
    return p, {c: c for c in COLS}, "um"                  # the scale is a scalar of the file


def w_savemat_v5(d, p):
    from scipy.io import savemat
    p = p / "rec.mat"
    savemat(p, {"time": d["time"][:, None], "meas": {"y_um": d["y_um"][:, None]},
                "sig": np.column_stack([d["x_ref"], d["u"], d["f"]]), "um": 1e-6, "label": "run 3"})
    return p, {"time": "time", "x_ref": "sig:1", "u": "sig:2", "f": "sig:3", "y_um": "meas.y_um"}, "um"


def w_h5py_matlab73(d, p):
    import h5py
    p = p / "rec73.mat"
    with h5py.File(p, "w", userblock_size=512) as f:
        for c in ("time", "x_ref", "u"):
            ds = f.create_dataset(c, data=d[c][None, :])       # MATLAB column (N,1) is stored (1,N)
            ds.attrs["MATLAB_class"] = np.bytes_("double")
        ds = f.create_dataset("data", data=np.column_stack([d["y_um"], d["f"]]).T)   # (N,2) stored (2,N)
        ds.attrs["MATLAB_class"] = np.bytes_("double")
        ds = f.create_dataset("um", data=np.array([[1e-6]]))
        ds.attrs["MATLAB_class"] = np.bytes_("double")
        ds = f.create_dataset("note", data=np.frombuffer(b"run3", np.uint8).astype(np.uint16)[:, None])
        ds.attrs["MATLAB_class"] = np.bytes_("char")
    head = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(p, "r+b") as f:
        f.write(head.ljust(116) + b"\0" * 8 + b"\x00\x02" + b"IM")
    return p, {"time": "time", "x_ref": "x_ref", "u": "u", "y_um": "data:1", "f": "data:2"}, "um"


def w_pandas_or_csv(d, p):
    p = p / "rec_pd.csv"
    try:
        import pandas as pd
        pd.DataFrame({c: d[c] for c in COLS}).to_csv(p, index=False)
    except ImportError:                     # pandas is not a dependency: the csv module writes the same
        with open(p, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(COLS)
            w.writerows(zip(*(d[c].tolist() for c in COLS)))
    return p, {c: c for c in COLS}, None


WRITERS = [w_savetxt_csv, w_savetxt_commented_header, w_savetxt_tsv_headerless, w_npz, w_savemat_v5,
           w_h5py_matlab73, w_pandas_or_csv]


@pytest.mark.parametrize("rate", [1000.0, 10000.0])
@pytest.mark.parametrize("writer", WRITERS, ids=lambda w: w.__name__[2:])
@pytest.mark.slow
def test_round_trip_of_files_written_by_other_tools(writer, rate, tmp_path, capsys):
    d = closed_loop(rate)
    src, names, scale = writer(d, tmp_path)
    out = tmp_path / "out" / "rec.mcap"
    assert main(["convert", "table", str(src), *_flags(names, scale), "--out", str(out)]) == 0
    said = capsys.readouterr().out
    assert f"{N} samples at {rate:g} Hz" in said and "closed-loop" in said and "external force" in said
    rec = read_recording(out.with_suffix("") / "rec.mcap")
    assert len(rec) == N and not rec.open_loop and rec.axis == "linear"
    np.testing.assert_array_equal(rec.stamp_ns, np.arange(N) * int(1e9 / rate))
    np.testing.assert_array_equal(rec.x_ref, d["x_ref"])
    np.testing.assert_array_equal(rec.u, d["u"])
    np.testing.assert_array_equal(rec.y, d["y_um"] * 1e-6)
    np.testing.assert_array_equal(rec.external_force, d["f"])
    np.testing.assert_array_equal(rec.v_ref, np.gradient(d["x_ref"], 1.0 / rate))
    assert np.all(np.isnan(rec.y_bearing)) and rec.warnings == []
    assert [(e["event"], e["stamp_ns"]) for e in rec.events] == [
        ("run_start", 0), ("trial_start", 0), ("trial_end", rec.stamp_ns[-1]), ("run_end", rec.stamp_ns[-1])]
    (trial,) = rec.trials()
    assert trial.complete and trial.slice == slice(0, N)
    cfg = yaml.safe_load(rec.config)
    assert cfg["run"]["rate"] == pytest.approx(rate, rel=1e-12)
    assert cfg["run"]["time_offset_s"] == pytest.approx(T0, abs=1e-12)
    assert cfg["run"]["open_loop"] is False and cfg["run"]["samples_per_trial"] == N
    assert cfg["provenance"]["file"] == src.name and len(cfg["provenance"]["sha256"]) == 64
    assert "central difference" in cfg["mapping"]["/stage/reference.velocity"]
    # the diagnosis' own reader takes it: one trial at the file's rate, the same signals
    from experiment_runner.apps.diagnosis.data import load_data
    dd = load_data(rec)
    assert dd.rate == pytest.approx(rate, rel=1e-12) and dd.u.shape == (N, 1)
    np.testing.assert_array_equal(dd.u[:, 0], d["u"])


def test_list_shows_columns_and_scalars(tmp_path, capsys):
    d = closed_loop(1000.0, 50)
    src, _, _ = w_savemat_v5(d, tmp_path)
    assert main(["convert", "table", str(src), "--list"]) == 0
    out = capsys.readouterr().out
    assert "MATLAB v5" in out and "time, meas.y_um, sig:1, sig:2, sig:3" in out and "um = 1e-06" in out
    import h5py
    with h5py.File(tmp_path / "plain.h5", "w") as f:       # plain HDF5: groups give dotted names, not transposed
        f["run/t"] = d["time"]
        f["run/xy"] = np.column_stack([d["x_ref"], d["u"]])
    tab = read_table(tmp_path / "plain.h5")
    assert tab.format == "HDF5 file (h5py)" and tab.names == ["run.t", "run.xy:1", "run.xy:2"]
    np.testing.assert_array_equal(tab.column("run.xy:2"), d["u"])


def test_semicolon_table_with_rate_instead_of_time(tmp_path):
    p = tmp_path / "rig.csv"
    p.write_text("% exported by a rig\nref;cmd;pos\n" + "".join(f"{i * 1e-6};{0.1 * i};{i * 1e-6 + 1e-9}\n"
                                                            for i in range(300)))
    path = convert_table(p, {"rate": 3000, "reference": "ref", "command": "cmd", "measured": "pos"}, tmp_path / "r")
    rec = read_recording(path)
    # 3 kHz: the period is no whole number of ns; stamps are the nearest ns of k / 3000 s
    np.testing.assert_array_equal(rec.stamp_ns, np.round(np.arange(300) * 1e9 / 3000).astype(np.int64))
    np.testing.assert_array_equal(rec.u, 0.1 * np.arange(300))
    assert yaml.safe_load(rec.config)["run"]["rate"] == pytest.approx(3000.0)


def test_open_loop_record_without_reference(tmp_path, capsys):
    d = closed_loop(1000.0, 500)
    src, names, _ = w_savetxt_csv(d, tmp_path)
    out = tmp_path / "ol"
    assert main(["convert", "table", str(src), "--time", "time", "--command", "u", "--measured", "y_um",
                 "--scale", "y_um=1e-6", "--out", str(out)]) == 0
    assert "open-loop record" in capsys.readouterr().out
    with pytest.raises(RecordingError, match="missing contract topic.*/stage/reference.*open-loop"):
        read_recording(out)                              # a tool needing a reference refuses it, clearly
    rec = read_recording(out, require_reference=False)
    assert rec.open_loop and "/stage/reference" not in rec.topics and len(rec) == 500
    assert np.all(np.isnan(rec.x_ref)) and np.all(np.isnan(rec.v_ref))
    np.testing.assert_array_equal(rec.u, d["u"])
    np.testing.assert_array_equal(rec.y, d["y_um"] * 1e-6)
    assert rec.external_force is None
    cfg = yaml.safe_load(rec.config)
    assert cfg["run"]["open_loop"] is True and "open-loop" in cfg["open_loop"]
    assert "/stage/reference.position" not in cfg["mapping"]


def test_rotary_units_and_bearing_and_reference_velocity(tmp_path):
    n = 400
    t = np.arange(n) * 2e-4
    np.savez(tmp_path / "rot.npz", t=t, th_ref=np.sin(t), w_ref=np.cos(t), tau=0.2 * t, th=np.sin(t) + 1e-6,
             th_b=0.5 * np.sin(t))
    path = convert_table(tmp_path / "rot.npz", {"time": "t", "reference": "th_ref", "reference_velocity": "w_ref",
                                                "command": "tau", "measured": "th", "bearing": "th_b",
                                                "units": "rotary"}, tmp_path / "rot")
    rec = read_recording(path)
    assert rec.axis == "rotary"
    np.testing.assert_array_equal(rec.v_ref, np.cos(t))                   # given, not differentiated
    np.testing.assert_array_equal(rec.y_bearing, 0.5 * np.sin(t))
    m = yaml.safe_load(rec.config)["mapping"]
    assert m["/stage/command.effort"] == "tau [N·m]" and m["/stage/reference.velocity"] == "w_ref [rad/s]"
    assert "th_b [rad]" in m["/stage/measured.position"]


def test_mapping_file_equals_flags_and_flags_override_it(tmp_path, capsys):
    d = closed_loop(1000.0, 300)
    src, names, _ = w_npz(d, tmp_path)
    mp = tmp_path / "map.yaml"
    mp.write_text("time: time\nreference: x_ref\ncommand: u\nmeasured: y_um\ninput: f\n"
                  "scale: {y_um: um, u: '2.0'}\nextra: {y_um: um}\ncase: bench 3\n"
                  "notes: {rig: test bench}\n")
    a = read_recording(convert_table(src, load_mapping(mp), tmp_path / "a"))
    assert main(["convert", "table", str(src), *_flags(names, "um"), "--scale", "u=2", "--extra", "y_um=um",
                 "--case", "bench 3", "--out", str(tmp_path / "b")]) == 0
    b = read_recording(tmp_path / "b")
    for k in ("stamp_ns", "x_ref", "v_ref", "u", "y", "external_force"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    np.testing.assert_array_equal(a.u, 2.0 * d["u"])
    assert a.source.names == ["y_um"]
    np.testing.assert_array_equal(a.source.position[:, 0], d["y_um"])        # kept unscaled
    assert a.events[1]["case"] == "bench 3" and yaml.safe_load(a.config)["notes"] == {"rig": "test bench"}
    # a flag given with --mapping overrides the file's key
    capsys.readouterr()
    assert main(["convert", "table", str(src), "--mapping", str(mp), "--case", "other", "--out",
                 str(tmp_path / "c")]) == 0
    assert read_recording(tmp_path / "c").events[1]["case"] == "other"


@pytest.mark.slow
def test_irregular_stamps_are_refused_or_resampled_on_request(tmp_path, capsys):
    rng = np.random.default_rng(3)
    n = 400
    t = np.arange(n) * 1e-3
    t[1:-1] += rng.uniform(-0.3e-3, 0.3e-3, n - 2)        # a logger without a clock: ±30 % jitter
    t = np.sort(t)
    y = 3e-6 * t + 1e-7                                  # linear: interpolation is exact
    u = np.floor(t / 0.01)                               # a staircase command
    src = tmp_path / "irr.csv"
    np.savetxt(src, np.column_stack([t, y, u]), delimiter=",", header="t,y,u", comments="")
    args = ["convert", "table", str(src), "--time", "t", "--command", "u", "--measured", "y"]
    assert main([*args, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "irr.csv" in err and "column 't'" in err
    assert "not regularly sampled" in err and "line " in err and "--resample" in err
    assert not (tmp_path / "r").exists()
    assert main([*args, "--resample", "--out", str(tmp_path / "r")]) == 0
    rec = read_recording(tmp_path / "r", require_reference=False)
    per_ns = round(float(np.median(np.diff(t))) * 1e9)  # the median interval, to the ns
    tg = np.arange(len(rec)) * (per_ns / 1e9)
    np.testing.assert_array_equal(rec.stamp_ns, np.arange(len(rec)) * per_ns)
    np.testing.assert_allclose(rec.y, 3e-6 * tg + 1e-7, rtol=0, atol=1e-18)
    held = u[np.searchsorted(t, tg, "right") - 1]       # the command is held, not interpolated
    np.testing.assert_array_equal(rec.u, held)
    r = yaml.safe_load(rec.config)["run"]["resampled"]
    assert r["from_samples"] == n and r["source_irregular"] is True and r["to_samples"] == len(rec)
    assert main([*args, "--resample", "2000", "--out", str(tmp_path / "r2")]) == 0
    rec2 = read_recording(tmp_path / "r2", require_reference=False)
    assert set(np.diff(rec2.stamp_ns)) == {500_000} and len(rec2) == 799      # 0 ... 0.399 s


def test_a_dropped_sample_is_irregular(tmp_path):
    t = np.delete(np.arange(100) * 1e-4, 57)
    np.savez(tmp_path / "drop.npz", t=t, u=np.ones(99), y=np.zeros(99))
    with pytest.raises(ConfigError, match=r"drop.npz: column 't' \(time\) is not regularly sampled: the interval "
                                          r"at sample 57 is 0.0002 s"):
        convert_table(tmp_path / "drop.npz", {"time": "t", "command": "u", "measured": "y"}, tmp_path / "x")


# --------------------------------------------------------------------------- refusals
def _table(tmp_path):
    d = closed_loop(1000.0, 100)
    return w_savetxt_csv(d, tmp_path)[0]


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


BAD = {
    # case: (source maker, extra args, fragments of the one-line message)
    "missing file": (lambda p: p / "nope.csv", [], ["nope.csv: no such file"]),
    "unknown column": (_table, ["--measured", "pos"],
                       ["rec.csv: no column 'pos' (--measured); columns: time, x_ref, u, y_um, f"]),
    "non-numeric": (lambda p: _write(p, "t.csv", "time,x_ref,u,y_um\n0,0,0,0\n0.001,0,oops,0\n0.002,0,0,0\n"),
                    [], ["t.csv: column 'u' (--command) line 3: 'oops' is not a number"]),
    "empty field": (lambda p: _write(p, "t.csv", "time,x_ref,u,y_um\n0,0,0,0\n0.001,0,,0\n0.002,0,0,0\n"),
                    [], ["t.csv: column 'u' (--command) line 3: an empty field is not a number"]),
    "nan": (lambda p: _write(p, "t.csv", "time,x_ref,u,y_um\n0,0,0,0\n0.001,0,0,0\n0.002,0,0,nan\n"),
            [], ["t.csv: column 'y_um' (--measured) has 1 non-finite value(s), the first at line 4 (nan)"]),
    "units word": (_table, ["--units", "radial"], ["--units: got 'radial'; expected linear (m, N) or rotary"]),
    "scale syntax": (_table, ["--scale", "y_um*1e-6"], ["--scale 'y_um*1e-6': expected COL=FACTOR"]),
    "scale of no column": (_table, ["--scale", "q=2"], ["--scale: 'q' is not one of the mapped columns"]),
    "scale by an unknown scalar": (_table, ["--scale", "u=gain"],
                                   ["--scale u=gain: 'gain' is neither a number nor a scalar of", "rec.csv"]),
    "zero scale": (_table, ["--scale", "u=0"], ["--scale: u: got 0.0; expected a finite non-zero factor"]),
    "time not increasing": (lambda p: _write(p, "t.csv", "time,x_ref,u,y_um\n0,0,0,0\n0.001,0,0,0\n0.001,0,0,0\n"),
                            [], ["t.csv: column 'time' (--time) does not increase at line 4 (0.001 then 0.001)"]),
    "ragged row": (lambda p: _write(p, "t.csv", "time,x_ref,u,y_um\n0,0,0,0\n0.001,0,0\n"),
                   [], ["t.csv: line 3 has 3 fields, expected 4 (time, x_ref, u, y_um)"]),
    "time and rate": (_table, ["--rate", "1000"], ["give --time (the time column) or --rate", "not both"]),
    "resample with rate": (lambda p: _write(p, "t.csv", "x_ref,u,y_um\n0,0,0\n"),
                           ["--time", None, "--rate", "100", "--resample", "50"],
                           ["--resample needs --time"]),
    "bad rate": (lambda p: _write(p, "t.csv", "x_ref,u,y_um\n0,0,0\n"), ["--time", None, "--rate", "-5"],
                 ["--rate: got '-5'; expected a positive number"]),
    "binary junk": (lambda p: p / "j.dat" if (p / "j.dat").write_bytes(b"\x00\x01junk" * 50) else None, [],
                    ["j.dat: binary file of an unknown format"]),
    "broken mat": (lambda p: p / "b.mat" if (p / "b.mat").write_bytes(b"MATLAB 5.0 MAT-file" + b"\x00" * 20) else None,
                   [], ["b.mat: not a readable mat file"]),
    "different lengths": (lambda p: (np.savez(p / "l.npz", time=np.arange(5.0), x_ref=np.zeros(5), u=np.zeros(4),
                                              y_um=np.zeros(5)), p / "l.npz")[1], [],
                          ["l.npz: column 'u' (--command) has 4 samples, 'time' (--time) has 5"]),
}


@pytest.mark.parametrize("case", list(BAD))
def test_every_bad_input_is_one_line_exit_2_and_nothing_written(case, tmp_path, capsys):
    make, extra, fragments = BAD[case]
    src = make(tmp_path)
    args = {"--time": "time", "--reference": "x_ref", "--command": "u", "--measured": "y_um"}
    it = iter(extra)
    more = []
    for flag in it:
        val = next(it)
        if flag in args and flag != "--scale":
            args[flag] = val
        else:
            more += [flag, val]
    flat = [x for k, v in args.items() if v is not None for x in (k, v)]
    before = set(os.listdir(tmp_path))
    rc = main(["convert", "table", str(src), *flat, *more, "--out", str(tmp_path / "out.mcap")])
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("nanostage convert: "), err
    assert "Traceback" not in err
    for frag in fragments:
        assert frag in err, (frag, err)
    assert set(os.listdir(tmp_path)) == before          # no output, no temporary left behind


def test_mapping_file_errors_name_the_file_and_key(tmp_path, capsys):
    src = _table(tmp_path)
    cases = {"time: time\ncomand: u\nmeasured: y_um\n": "unknown key(s) 'comand'; allowed keys: time,",
             "time: time\nmeasured: y_um\n": "command is required",
             "time: time\ncommand: u\nmeasured: y_um\nunits: angular\n": "units: got 'angular'; expected linear",
             "time: time\ncommand: u\nmeasured: y_um\nscale: 3\n": "scale: got 3; expected a mapping",
             "time: time\ncommand: u\nmeasured: [y_um]\n": "measured: got ['y_um']; expected a column name",
             "time: time\ncommand: u\ncommand: y\n": "duplicate key 'command'",
             "- time\n": "top level must be a mapping"}
    for i, (text, frag) in enumerate(cases.items()):
        mp = _write(tmp_path, f"m{i}.yaml", text)
        assert main(["convert", "table", str(src), "--mapping", str(mp), "--out", str(tmp_path / "o")]) == 2
        err = capsys.readouterr().err.strip()
        assert f"m{i}.yaml" in err and frag in err and len(err.splitlines()) == 1, (text, err)
    assert main(["convert", "table", str(src), "--mapping", str(tmp_path / "none.yaml"), "--out", "o"]) == 2
    assert "none.yaml: no such mapping file (shipped mappings: emps, emps_pulses)" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_existing_output_is_kept_unless_overwrite(tmp_path, capsys):
    src = _table(tmp_path)
    args = ["convert", "table", str(src), "--time", "time", "--reference", "x_ref", "--command", "u",
            "--measured", "y_um", "--out", str(tmp_path / "rec")]
    assert main(args) == 0
    mcap = tmp_path / "rec" / "rec.mcap"
    data = mcap.read_bytes()
    assert main([*args, "--scale", "u=2"]) == 2
    assert "rec: exists; pass --overwrite" in capsys.readouterr().err
    assert mcap.read_bytes() == data
    assert main([*args, "--scale", "u=2", "--overwrite"]) == 0
    np.testing.assert_array_equal(read_recording(mcap).u, 2 * closed_loop(1000.0, 100)["u"])


def test_a_conversion_failing_while_writing_leaves_nothing_half_written(tmp_path, monkeypatch):
    from experiment_runner.core import recording
    src = _table(tmp_path)
    mapping = {"time": "time", "reference": "x_ref", "command": "u", "measured": "y_um"}
    good = convert_table(src, mapping, tmp_path / "rec")
    data = good.read_bytes()
    real = recording.McapRecorder.write
    calls = {"n": 0}

    def failing(self, *a, **k):             # the disk fills up after 150 messages
        calls["n"] += 1
        if calls["n"] > 150:
            raise OSError(28, "No space left on device")
        return real(self, *a, **k)
    monkeypatch.setattr(recording.McapRecorder, "write", failing)
    with pytest.raises(OSError, match="No space"):
        convert_table(src, mapping, tmp_path / "new")
    calls["n"] = 0
    with pytest.raises(OSError, match="No space"):
        convert_table(src, dict(mapping, scale={"u": 3.0}), tmp_path / "rec", overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["rec", "rec.csv"]        # no 'new', no temporaries
    assert good.read_bytes() == data                                   # the old recording is intact


# --------------------------------------------------------------------------- EMPS
@pytest.fixture(scope="module")
def emps_file(shared_file):
    return shared_file("emps/DATA_EMPS.mat")


@pytest.mark.realdata
@pytest.mark.slow
def test_convert_emps_is_the_table_importer_and_gives_the_same_recording(emps_file, tmp_path, capsys):
    from scipy.io import loadmat
    m = loadmat(emps_file)
    qg, qm, vir = (m[k].ravel() for k in ("qg", "qm", "vir"))
    gtau = float(m["gtau"].ravel()[0])
    assert main(["convert", "emps", str(emps_file), "--out", str(tmp_path / "emps")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"{tmp_path / 'emps' / 'emps.mcap'}: 24841 samples at 1000 Hz") and "command: drive" in out
    assert "external_force" not in out                     # DATA_EMPS.mat has no pulses
    rec = read_recording(tmp_path / "emps")
    assert rec.command_kind == "drive" and rec.external_force is None
    # the pre-importer converter's mapping (convert_emps before issue 12), value for value
    n = len(qg)
    np.testing.assert_array_equal(rec.stamp_ns, np.arange(n) * 1_000_000)
    np.testing.assert_array_equal(rec.x_ref, qg)
    np.testing.assert_array_equal(rec.v_ref, np.gradient(qg, 0.001))
    np.testing.assert_array_equal(rec.u, gtau * vir)
    np.testing.assert_array_equal(rec.y, qm)
    assert [(e["event"], e["stamp_ns"], e["case"]) for e in rec.events] == [
        ("run_start", 0, "EMPS"), ("trial_start", 0, "EMPS"), ("trial_end", (n - 1) * 1_000_000, "EMPS"),
        ("run_end", (n - 1) * 1_000_000, "EMPS")]
    # ... and now keeps the file family's own channel and constants
    assert rec.source.names == ["vir"]
    np.testing.assert_array_equal(rec.source.position[:, 0], vir)
    cfg = yaml.safe_load(rec.config)
    assert cfg["provenance"]["scalars"] == {k: float(m[k].ravel()[0]) for k in ("gtau", "kp", "kv")}
    assert cfg["run"]["source"] == "nanostage convert emps" and "gtau" in cfg["mapping"]["/stage/command.effort"]
    # the same as the generic command with the shipped mapping
    assert main(["convert", "table", str(emps_file), "--mapping", str(EMPS_MAPPING), "--out",
                 str(tmp_path / "t")]) == 0
    t = read_recording(tmp_path / "t")
    for k in ("stamp_ns", "x_ref", "v_ref", "u", "y"):
        np.testing.assert_array_equal(getattr(t, k), getattr(rec, k))


def test_external_force_topic_is_read_per_control_sample(tmp_path):
    """``/stage/external_force`` written by any writer (here McapRecorder message by message)
    comes back aligned with the control samples; a sample without it is nan, with a warning."""
    from experiment_runner.core.recording import McapRecorder
    from experiment_runner.core.recording.writer import typestore
    from msg_defs.convert import joint_state
    from msg_defs.topics import EXTERNAL_FORCE, TOPICS
    assert EXTERNAL_FORCE.units.startswith("N") and TOPICS["/stage/external_force"] is EXTERNAL_FORCE
    ts = typestore()
    with McapRecorder(tmp_path / "f", "run: {axis: rotary}\n") as rec:
        for k in range(10):
            s = k * 100_000
            rec.write("/stage/reference", s, joint_state(ts, s, ["table"], position=[0.0], velocity=[0.0]))
            rec.write("/stage/command", s, joint_state(ts, s, ["motor"], effort=[1.0]))
            rec.write("/stage/measured", s, joint_state(ts, s, ["table"], position=[k * 1e-9]))
            if k not in (3, 7):
                rec.write("/stage/external_force", s, joint_state(ts, s, ["table"], effort=[0.5 * k]))
    r = read_recording(tmp_path / "f")
    want = 0.5 * np.arange(10.0)
    want[[3, 7]] = np.nan
    np.testing.assert_array_equal(r.external_force, want)
    assert any("/stage/external_force: 2 control sample(s) without a value" in w for w in r.warnings)
    assert r.axis == "rotary" and r.source is None and not r.open_loop
