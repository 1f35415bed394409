"""Issue 24: every input is bounded and checked where it enters.

Bounded parsing (one YAML loader, :func:`stage_sim.validation.load_yaml`, for presets,
experiments, campaigns, mappings, model files and the configuration stored in a recording):
alias bombs, deep nesting, long numbers, huge files and files that are not regular files are
refused with one line naming the file. Values: schema ranges the code can run, CLI options.
Damage inside recordings (non-finite or absurd values, missing, misordered samples, aborted
trials) is reported by the reader (:class:`experiment_runner.core.recording.Damage`), never
"agrees" in ``replay --check``, and is excluded (or refused) by the diagnosis. Every input is
built in the test.
"""
from __future__ import annotations

import contextlib
import json
import os
import signal

import numpy as np
import pytest
import yaml

from experiment_runner.apps.cli import main
from experiment_runner.apps.diagnosis.data import load_data
from experiment_runner.core.metrics import trial_metrics
from experiment_runner.core.recording import McapRecorder, RecordingError, read_recording
from experiment_runner.core.recording.writer import typestore
from msg_defs import convert
from stage_sim.config import ConfigError, load_preset
from stage_sim.validation import load_yaml

TS = typestore()
DT_NS = 100_000                                    # 10 kHz


@contextlib.contextmanager
def _at_most(seconds: float):
    """Fail (TimeoutError) instead of hanging: a generous guard, not a timing assertion."""
    def stop(*_):
        raise TimeoutError(f"still running after {seconds} s")
    old = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _cli_error(argv, capsys, *expected) -> str:
    """``nanostage argv`` fails with one message (exit 2, no traceback) holding ``expected``."""
    try:
        code = main(argv)
    except SystemExit as exc:                      # argparse's usage error: usage lines, then the error
        code = exc.code
    assert code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and f"nanostage {argv[0]}: " in err, err
    for text in expected:
        assert text in err, err
    return err


# =========================================================================== bounded parsing
def _bomb(levels: int = 9) -> str:
    """A "billion laughs" document: 10 aliases of the level below, ``levels`` deep (10**levels values)."""
    lines = ["a0: &a0 [x,x,x,x,x,x,x,x,x,x]"]           # as the before-stop hook builds it
    lines += [f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, levels)]
    return "\n".join(lines) + "\n"


def test_billion_laughs_preset_is_refused_while_it_is_read(tmp_path, capsys):
    """A 430-byte file expanding to 10**9 values (before: 87 s and 3.35 GB for 10**8, one more
    level never ending) is refused while it is composed, naming the file and the line."""
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(_bomb())
    assert bomb.stat().st_size < 500
    with _at_most(60), pytest.raises(ConfigError, match=r"bomb.yaml: refused at line \d+.*aliases expanded"):
        load_preset(bomb)
    with _at_most(60):
        _cli_error(["presets", str(bomb)], capsys, str(bomb), "more than 200000 values with its aliases expanded")
    # aliases themselves stay allowed, and an alias to its own container is refused
    assert load_yaml("a: &a [1, 2]\nb: [*a, *a]\n", "ok")["b"] == [[1, 2], [1, 2]]
    with pytest.raises(ConfigError, match="refers to a collection that contains it"):
        load_yaml("a: &a [1, *a]\n", "self.yaml")


def test_5000_digit_integer_is_a_clean_error(tmp_path, capsys):
    """Before: Python's int limit raised ValueError with a traceback."""
    f = tmp_path / "digits.yaml"
    f.write_text("stage:\n  table:\n    mass: " + "9" * 5000 + "\n")
    _cli_error(["presets", str(f)], capsys, f"{f}: refused at line 3", "a number of 5000 characters; at most 100")


def test_100000_deep_nesting_is_a_clean_error(tmp_path, capsys):
    """Before: RecursionError with a traceback."""
    f = tmp_path / "deep.yaml"
    f.write_text("stage: " + "[" * 100_000 + "]" * 100_000 + "\n")
    _cli_error(["presets", str(f)], capsys, f"{f}: refused at line 1", "nested deeper than 100 levels")


def test_50_mb_string_is_refused_before_parsing(tmp_path, capsys):
    """Before: > 200 s parsing it. The size is checked before the file is read (and for text,
    before it is parsed)."""
    f = tmp_path / "big.yaml"
    with open(f, "w") as out:
        out.write('description: "')
        out.write("x" * 50_000_000)
        out.write('"\n')
    with _at_most(60):
        _cli_error(["presets", str(f)], capsys, f"{f}: {f.stat().st_size} bytes; a preset file has at most "
                                                "1048576 bytes")
        with pytest.raises(ConfigError, match="at most 1048576 are read"):
            load_yaml("a: " + "x" * 2_000_000, "text")


def test_a_fifo_or_kernel_file_given_as_input_is_refused_before_it_is_opened(tmp_path, capsys):
    """A FIFO would block forever (no writer), /proc/kmsg blocks and consumes the kernel log:
    refused from os.stat alone, for presets, experiments, campaigns, mappings, model files and
    --calibration JSON."""
    fifo = tmp_path / "p.yaml"
    os.mkfifo(fifo)
    with _at_most(60):
        for argv in (["presets", str(fifo)], ["graph", str(fifo), "--out", str(tmp_path / "g")],
                     ["campaign", str(fifo), "--out", str(tmp_path / "c")],
                     ["campaign", "table_4_2", "--calibration", str(fifo), "--out", str(tmp_path / "c")]):
            _cli_error(argv, capsys, f"{fifo}: not a regular file (a FIFO (named pipe))")
        for pseudo in ("/proc/self/status", "/proc/kmsg"):
            if os.path.exists(pseudo):
                _cli_error(["presets", pseudo], capsys, f"{pseudo}: a kernel pseudo-file (under /proc)")
        from experiment_runner.apps.diagnosis.model import load_model
        with pytest.raises(ConfigError, match="not a regular file"):
            load_model(fifo)
        from experiment_runner.core.tabular import load_mapping, read_table
        with pytest.raises(ConfigError, match="not a regular file"):
            load_mapping(fifo)
        with pytest.raises(ConfigError, match="a kernel pseudo-file"):
            read_table("/proc/self/status")


# =========================================================================== recordings: builder
CONFIG = {"recording_contract": 1, "run": {"source": "test", "case": "p2p"}}


def _write(path, *, trials=3, T=300, config=None, edit=None, drop=(), drop_on=None, back=None, abort=None,
           results=None, preset=None):
    """A contract recording of ``trials`` trials of ``T`` samples (a 5 µm ramp and hold, a
    measured position 1 nm off, a small command), each with its events and the metrics of
    /experiment/results computed from the undamaged samples (as a run publishes them); then
    damaged: ``edit`` {signal: {sample: value}}, ``drop`` samples missing on every topic (or on
    ``drop_on`` only),
    ``back`` {sample: ns earlier}, ``abort`` a trial ended by an abort event, ``results`` raw
    texts instead of the metrics."""
    n = trials * T
    t = np.arange(T) * DT_NS * 1e-9
    one = np.minimum(t / 0.01, 1.0) * 5e-6
    sig = {"x_ref": np.tile(one, trials), "v_ref": np.tile(np.where(t < 0.01, 5e-4, 0.0), trials)}
    sig["y"] = sig["x_ref"] - 1e-9 * np.cos(np.arange(n))
    sig["u"] = 0.1 * np.sin(np.arange(n) / 7.0)
    clean = {k: v.copy() for k, v in sig.items()}
    for name, changes in (edit or {}).items():
        for k, v in changes.items():
            sig[name][k] = v
    cfg = config if config is not None else yaml.safe_dump({**CONFIG, **({"preset": preset} if preset else {})})
    with McapRecorder(path, cfg, chunk_ns=10_000_000) as rec:
        for j in range(trials):
            s0, s1 = j * T * DT_NS, ((j + 1) * T - 1) * DT_NS
            rec.write("/experiment/events", s0, convert.event_msg(TS, "trial_start", trial=j, case="p2p",
                                                                 stamp_ns=s0, window_m=25e-9, target_m=5e-6))
            for k in range(j * T, (j + 1) * T):
                s = k * DT_NS - (back or {}).get(k, 0)
                for topic, msg in (
                        ("/stage/reference", convert.joint_state(TS, s, ["table"], position=[sig["x_ref"][k]],
                                                                 velocity=[sig["v_ref"][k]])),
                        ("/stage/command", convert.joint_state(TS, s, ["motor"], effort=[sig["u"][k]])),
                        ("/stage/measured", convert.joint_state(TS, s, ["table"], position=[sig["y"][k]]))):
                    if k not in drop or drop_on not in (None, topic):
                        rec.write(topic, s, msg)
            if j == abort:
                rec.write("/experiment/events", s1, convert.event_msg(TS, "abort", trial=j, stamp_ns=s1,
                                                                     reason="operator stop", node="sequencer"))
                continue
            rec.write("/experiment/events", s1, convert.event_msg(TS, "trial_end", trial=j, case="p2p",
                                                                 stamp_ns=s1, window_m=25e-9))
            sl = slice(j * T, (j + 1) * T)
            met = trial_metrics(t + j * T * DT_NS * 1e-9, clean["x_ref"][sl], clean["v_ref"][sl], clean["y"][sl],
                                window=25e-9, target=5e-6)
            if results is None:
                rec.write("/experiment/results", s1, convert.string_msg(TS, convert.to_json({"trial": j, **met})))
        for text in results or ():
            rec.write("/experiment/results", (n - 1) * DT_NS, convert.string_msg(TS, text))
    return rec.path


def _check(path, capsys):
    """``nanostage replay PATH --check --no-publish``: (exit code, stdout, stderr)."""
    code = main(["replay", str(path), "--check", "--no-publish"])
    out = capsys.readouterr()
    assert "Traceback" not in out.err
    return code, out.out, out.err


def _check_json(path, capsys) -> tuple[int, dict]:
    code = main(["replay", str(path), "--check", "--no-publish", "--json"])
    return code, json.loads(capsys.readouterr().out)["check"]


def test_the_intact_recording_agrees(tmp_path, capsys):
    """The builder's undamaged recording: every trial agrees, complete, no warning, exit 0 (the
    baseline of the damage tests below)."""
    code, out, err = _check(_write(tmp_path / "ok"), capsys)
    assert code == 0 and out.count("| agrees") == 3 and "INCOMPLETE" not in out and err == ""
    code, chk = _check_json(_write(tmp_path / "ok2"), capsys)
    assert code == 0 and chk["ok"] is True and chk["complete"] is True and chk["warnings"] == []


# =========================================================================== configuration stored in a recording
@pytest.mark.parametrize("config, expected", [
    ("!!python/object/apply:os.system ['echo owned']\n",
     "could not determine a constructor for the tag 'tag:yaml.org,2002:python/object/apply:os.system'"),
    ("run: [not closed\n", "not valid YAML at line 2"),
    ("run: {case: a\x00b}\n", "character #x0000"),
    ("recording_contract: 1\nrun: {case: a}\nrun: {case: b}\n", "found duplicate key 'run'"),
    ("- a list\n", "top level must be a mapping, got list"),
])
def test_damaged_stored_config_is_a_clean_error_naming_the_recording_and_topic(tmp_path, capsys, config, expected):
    """Before: a YAML traceback (nothing executed), duplicate keys silently taken."""
    rec = _write(tmp_path / "r", config=config)
    err = _cli_error(["diagnose", str(rec), "--out", str(tmp_path / "d")], capsys,
                     f"{rec}: /experiment/config", expected)
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "d").exists()


def test_invalid_stored_preset_names_recording_topic_and_field(tmp_path, capsys):
    """Before: ``<mapping>: invalid preset``."""
    preset = load_preset("fi_stage").model_dump(mode="json")
    preset["stage"]["table"]["mass"] = -1.0
    rec = _write(tmp_path / "r", preset=preset)
    err = _cli_error(["diagnose", str(rec), "--out", str(tmp_path / "d")], capsys,
                     f"{rec}: /experiment/config preset: invalid preset", "stage.table.mass: got -1.0")
    assert "<mapping>" not in err


def test_text_in_results_does_not_crash_the_check(tmp_path, capsys):
    """Before: ValueError traceback from int('zero'). Text and non-numbers are warned about
    and never agree."""
    rec = _write(tmp_path / "r", results=["this is not JSON", '{"trial": "zero", "settling_time_s": 0.1}',
                                          '{"trial": 1, "settling_time_s": "fast"}'])
    code, out, err = _check(rec, capsys)
    assert code == 1
    assert "warning: /experiment/results: message at" in err and "skipped" in err
    assert "has trial 'zero', not an integer; not compared" in err
    assert "1 | p2p |" in out and "DIFFERS: settling_time_s" in out


# =========================================================================== values checked where they enter
def test_a_1000_m_move_is_refused_naming_the_move_and_the_travel(tmp_path, capsys):
    """Before: ``margin leaves no room inside the travel range`` (ValueError traceback)."""
    doc = {"name": "huge", "preset": "fi_stage", "trials": 1, "starts": {"margin": 0.005, "seed": 1},
           "profile": {"kind": "point_to_point", "distance": 1000.0, "dwell": 0.01}}
    exp = tmp_path / "huge.yaml"
    exp.write_text(yaml.safe_dump(doc))
    err = _cli_error(["synth", "fi_stage", str(exp), "--out", str(tmp_path / "r")], capsys,
                     "the reference moves over 1000 m", "more than the travel -0.025 to 0.025 m")
    assert "margin" not in err
    # a margin that leaves no room for a move that fits is blamed on the margin
    doc["profile"]["distance"], doc["starts"]["margin"] = 0.01, 0.03
    exp.write_text(yaml.safe_dump(doc))
    _cli_error(["synth", "fi_stage", str(exp), "--out", str(tmp_path / "r")], capsys,
               "the margin 0.03 m kept at both travel ends leaves no room for a start")


def test_dwell_1e9_is_refused_by_a_size_estimate_before_allocation(tmp_path, capsys):
    """Before: numpy tried to allocate 72.8 TiB (``--dwell 1e9``, a traceback). The reference's
    length is checked before anything is allocated, naming the value and the limit."""
    from experiment_runner.core.profiles import MAX_SAMPLES, point_to_point
    with pytest.raises(ConfigError, match=r"dwell 1e\+09 s at 10000 Hz is 1e\+13 samples .*at most 5e\+07 samples"):
        point_to_point(5e-6, dwell=1e9)
    assert MAX_SAMPLES == 50_000_000
    doc = {"name": "long", "preset": "fi_stage", "trials": 1,
           "profile": {"kind": "point_to_point", "distance": 5e-6, "dwell": 1e9}}
    exp = tmp_path / "long.yaml"
    exp.write_text(yaml.safe_dump(doc))
    _cli_error(["synth", "fi_stage", str(exp), "--out", str(tmp_path / "r")], capsys,
               "dwell 1e+09 s at 10000 Hz is 1e+13 samples", "a reference holds at most 5e+07 samples")


def test_batch_memory_estimate_refuses_what_cannot_fit():
    from experiment_runner.core.batch import BYTES_PER_SAMPLE, check_memory
    have = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    check_memory(10, 10_000, 1e4)                                         # 10 MB: fine
    with pytest.raises(ConfigError, match=r"100000 trial\(s\) of .* GiB of memory"):
        check_memory(100_000, int(have / BYTES_PER_SAMPLE / 1000) + 1, 1e4)


@pytest.mark.parametrize("argv, expected", [
    (["synth", "fi_stage", "fi_p2p_5um", "--trials", "0", "--out", "r"],
     "argument --trials: got 0; expected an integer >= 1"),
    (["diagnose", "r.mcap", "fi_stage", "--bandwidth", "-5"],
     "argument --bandwidth: got -5; expected a finite number > 0"),
    (["diagnose", "r.mcap", "fi_stage", "--max-fit-seconds", "nan"],
     "argument --max-fit-seconds: got nan; expected a finite number > 0"),
    (["diagnose", "r.mcap", "fi_stage", "--cluster", "notanaddr"],
     "argument --cluster: got 'notanaddr'; expected a Dask scheduler address such as tcp://HOST:PORT"),
    (["campaign", "table_4_2", "--cluster", "tcp://host", "--out", "c"], "argument --cluster: got 'tcp://host'"),
    (["design", "fi_stage", "--rms", "2", "--cluster", "http://x:1"], "unknown address scheme 'http'"),
    (["diagnose", "r.mcap", "fi_stage", "--effects", "viscous,nosuch"],
     "argument --effects: got 'viscous,nosuch'; unknown effect key(s) 'nosuch'; expected comma-separated keys of: "
     "dahl, gms,"),
    (["diagnose", "--selftest", "--effects", "nosuch"], "unknown effect key(s) 'nosuch'"),
    (["diagnose", "--selftest", "--power", "--cases", "0"], "argument --cases: got 0"),
    (["design", "fi_stage", "--rms", "-2"], "argument --rms: got -2; expected a finite number > 0"),
    (["design", "fi_stage", "--rms", "2", "--dwell", "1e999"], "argument --dwell: got 1e999"),
    (["design", "fi_stage", "--rms", "2", "--step-um", "nan"], "argument --step-um: got nan"),
])
def test_cli_options_are_checked_before_any_work(tmp_path, capsys, monkeypatch, argv, expected):
    """Before: tracebacks (--trials 0, --bandwidth -5, --cluster notanaddr, --effects nosuch with
    candidates fitted) or silently accepted (--effects elsewhere, --max-fit-seconds nan)."""
    monkeypatch.chdir(tmp_path)
    err = _cli_error(argv, capsys, expected)
    assert expected in err.strip().splitlines()[-1] and ": error: argument" in err   # argparse's one-line error
    assert not any(tmp_path.iterdir())


def test_effect_keys_are_those_of_list_effects(capsys):
    from experiment_runner.apps.diagnosis.cli import effect_keys
    assert main(["diagnose", "--list-effects", "--json"]) == 0
    listed = [e["key"] for e in json.loads(capsys.readouterr().out) if e["kind"] != "fallback"]
    assert len(listed) > 10 and effect_keys(",".join(listed)) == listed


# =========================================================================== damage inside recordings
def test_nan_measured_sample_excludes_its_trial_and_says_so(tmp_path):
    """Before: diagnose crashed after writing report.json (not report.md). The reader reports
    topic, sample and time; the diagnosis leaves the trial out and says so."""
    rec_path = _write(tmp_path / "r", edit={"y": {450: np.nan}})
    rec = read_recording(rec_path)
    (d,) = rec.damage
    assert (d.kind, d.topic, d.index) == ("value", "/stage/measured", 450)
    assert "sample 450, t = 0.045000 s: nan" in d.text and d.text in rec.warnings
    data = load_data(rec)
    assert data.trial_ids == [0, 2] and np.isfinite(data.y).all()
    assert data.excluded == ["trial 1: /stage/measured: 1 non-finite or absurd value(s), the first at sample 450 "
                             "(t = 0.045000 s)"]
    assert f"excluded {data.excluded[0]}" in data.notes


def test_nan_reference_is_damage_not_a_diverged_model(tmp_path):
    """Before: NaN in the reference was simulated and read as "model diverged"."""
    rec = read_recording(_write(tmp_path / "r", edit={"x_ref": {20: np.nan}}))
    assert [(d.topic, d.index) for d in rec.damage] == [("/stage/reference", 20)]
    data = load_data(rec)
    assert data.trial_ids == [1, 2] and "trial 0: /stage/reference" in data.excluded[0]


def test_a_damaged_single_trial_is_refused_naming_topic_sample_and_time(tmp_path):
    rec = _write(tmp_path / "r", trials=1, edit={"y": {100: 1e300}})
    with pytest.raises(RecordingError, match=r"every trial holds samples the diagnosis cannot use.*/stage/measured: "
                                             r"1 sample\(s\) .* the first at sample 100, t = 0.010000 s: 1e\+300"):
        load_data(rec)


def test_1e300_position_refused_by_convert_and_flagged_in_a_recording(tmp_path, capsys):
    """Before: convert accepted it; diagnose then raised OverflowError."""
    n = 200
    t = np.arange(n) * 1e-3
    y = 1e-6 * np.sin(t)
    y[50] = 1e300
    np.savez(tmp_path / "t.npz", t=t, u=np.cos(t), y=y)
    _cli_error(["convert", "table", str(tmp_path / "t.npz"), "--time", "t", "--command", "u", "--measured", "y",
                "--out", str(tmp_path / "c.mcap")], capsys,
               "column 'y' (--measured) has 1 value(s) beyond ±1e+06 m, the first at sample 50 (1e+300 m)")
    assert not (tmp_path / "c").exists()
    rec = _write(tmp_path / "r", edit={"y": {700: 1e300}})
    code, out, err = _check(rec, capsys)
    assert code == 1 and "2 | p2p |" in out and "INCOMPLETE: /stage/measured: 1 non-finite or absurd value(s)" in out
    data = load_data(read_recording(rec))
    assert data.trial_ids == [0, 1] and np.abs(data.y).max() < 1e-5


def test_inf_command_never_agrees(tmp_path, capsys):
    """Before: "agrees", exit 0 (the metrics do not use the command)."""
    rec = _write(tmp_path / "r", edit={"u": {350: np.inf}})
    code, out, err = _check(rec, capsys)
    assert code == 1
    line = next(ln for ln in out.splitlines() if ln.startswith("1 | p2p"))
    assert "agrees" not in line and "INCOMPLETE: /stage/command: 1 non-finite or absurd value(s)" in line
    assert "warning: /stage/command: 1 sample(s) with a non-finite or absurd motor effort" in err and ": inf" in err
    code, chk = _check_json(rec, capsys)
    assert chk["ok"] is False and chk["complete"] is False and chk["trials"][1]["complete"] is False


@pytest.mark.slow
def test_a_stamp_5_ms_backwards_never_agrees(tmp_path, capsys):
    """Before: "agrees". The message written 5 ms back is named (topic, time) and its trial
    is incomplete."""
    rec = _write(tmp_path / "r", back={400: 5_000_000})
    r = read_recording(rec)
    kinds = {(d.kind, d.topic) for d in r.damage}
    assert ("backwards", "/stage/measured") in kinds and ("backwards", "/stage/command") in kinds
    code, out, err = _check(rec, capsys)
    assert code == 1
    line = next(ln for ln in out.splitlines() if ln.startswith("1 | p2p"))
    assert "agrees" not in line and "stamp(s) going backwards" in line
    assert "warning: /stage/measured: 1 message(s) stamped before the message written before them, the first " \
           "4.9 ms earlier, at t = 0.035000 s" in err


def test_dropped_samples_give_a_reason_and_the_json_is_not_complete(tmp_path, capsys):
    """Before: "DIFFERS" with no reason, and ``complete: true`` in the JSON."""
    rec = _write(tmp_path / "r", drop=set(range(400, 410)))
    code, out, err = _check(rec, capsys)
    assert code == 1
    line = next(ln for ln in out.splitlines() if ln.startswith("1 | p2p"))
    assert "DIFFERS" in line and "INCOMPLETE: control samples: 10 sample(s) missing on every topic, the first at " \
                                 "sample 400" in line
    assert "warning: control samples: 10 sample(s) missing on every contract topic in 1 gap(s)" in err
    code, chk = _check_json(rec, capsys)
    assert chk["complete"] is False and chk["trials"][1]["complete"] is False
    assert chk["trials"][1]["problems"] == ["control samples: 10 sample(s) missing on every topic, the first at "
                                            "sample 400 (t = 0.041000 s)"]
    # samples missing on one topic only are dropped from all, naming that topic
    r = read_recording(_write(tmp_path / "one", drop={5, 6}, drop_on="/stage/measured"))
    (d,) = r.damage
    assert (d.kind, d.topic, d.count, len(r)) == ("dropped", "/stage/measured", 2, 898)
    assert "no message at 2 control sample(s) the other contract topics have, so they are dropped" in d.text


def test_aborted_trial_is_not_printed_as_complete(tmp_path, capsys):
    """Before: printed like the others, exit 0. The abort's reason is the trial's problem; the
    diagnosis keeps its samples and says it is incomplete."""
    rec = _write(tmp_path / "r", abort=2)
    code, out, err = _check(rec, capsys)
    assert code == 1
    line = next(ln for ln in out.splitlines() if ln.startswith("2 | p2p"))
    assert "INCOMPLETE: abort (sequencer): operator stop" in line
    assert "INCOMPLETE: the recording has incomplete or damaged trials" in out
    code, chk = _check_json(rec, capsys)
    assert chk["complete"] is False and [r["complete"] for r in chk["trials"]] == [True, True, False]
    # the diagnosis uses its samples (they are data) and says the trial is incomplete
    data = load_data(read_recording(rec))
    assert data.trial_ids == [0, 1, 2] and data.excluded == []
    assert data.incomplete == ["trial 2: abort (sequencer): operator stop"]
    assert "incomplete trial 2: abort (sequencer): operator stop (its samples are data: used)" in data.notes


def test_a_recording_cut_short_is_not_printed_as_complete(tmp_path, capsys):
    """A killed recorder: the trial it was recording has no end; the check says so (exit 1)."""
    path = _write(tmp_path / "r")
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:int(len(data) * 0.7)])
    code, out, err = _check(cut, capsys)
    assert code == 1
    last = [ln for ln in out.splitlines() if " | p2p |" in ln][-1]
    assert "INCOMPLETE: no trial_end: the recording ends first (cut short)" in last and "agrees" not in last
    code, chk = _check_json(cut, capsys)
    assert chk["complete"] is False and chk["salvaged"].startswith("file cut short")
    # the bag's metadata.yaml (read for the count recorded) goes through the bounded loader: a FIFO
    # there is not opened (before: the read blocked forever)
    meta = path.parent / "metadata.yaml"
    meta.unlink()
    os.mkfifo(meta)
    path.write_bytes(data[:int(len(data) * 0.7)])
    with _at_most(60):
        rec = read_recording(path)
    assert rec.salvaged.startswith("file cut short") and len(rec) > 0


@pytest.mark.slow
def test_diagnose_with_a_nan_sample_excludes_its_trial_in_report_and_stdout(tmp_path, capsys):
    """End to end: ``nanostage diagnose`` on a simulated 3-trial recording with one NaN
    measured sample finishes (report.md written), and report.md and stdout say which trial
    was excluded and why. Before: a TypeError after report.json."""
    from experiment_runner.apps.diagnosis.synth import synth
    src = read_recording(synth("fi_stage", "fi_p2p_5um", tmp_path / "clean", trials=3))
    path = tmp_path / "nan"
    with McapRecorder(path, src.config) as rec:
        for k, s in enumerate(src.stamp_ns):
            s = int(s)
            rec.write("/stage/reference", s, convert.joint_state(TS, s, ["table"], position=[src.x_ref[k]],
                                                                 velocity=[src.v_ref[k]]))
            rec.write("/stage/command", s, convert.joint_state(TS, s, ["motor"], effort=[src.u[k]]))
            y = np.nan if k == len(src) // 2 else src.y[k]
            rec.write("/stage/measured", s, convert.joint_state(TS, s, ["table"], position=[y]))
        for ev in src.events:
            ev = {k: v for k, v in ev.items() if k != "log_time_ns"}
            rec.write("/experiment/events", ev["stamp_ns"], convert.event_msg(TS, ev.pop("event"), **ev))
    out = tmp_path / "d"
    assert main(["diagnose", str(rec.path), "fi_stage", "--no-plots", "--out", str(out)]) == 0
    std = capsys.readouterr()
    assert "excluded as damaged (1 trial(s), neither fitted nor judged):" in std.out
    assert "trial 1: /stage/measured: 1 non-finite or absurd value(s)" in std.out
    assert "warning: /stage/measured: 1 sample(s) with a non-finite" in std.err
    md = (out / "report.md").read_text()
    assert "excluded trial 1: /stage/measured" in md
    rep = json.loads((out / "report.json").read_text())
    assert rep["recording"]["trials"] == 2
