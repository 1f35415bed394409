"""Concealed-data self-test: ``nanostage diagnose --selftest [--json]``.

Each case writes a TRUTH (the nominal preset with one or two effects, or nothing for a
negative control; drive noise and quantization always on), an EXPERIMENT and the NOMINAL
model to a scratch folder as YAML files, runs ``synth`` (MCAP recording, truth concealed) and
then ``diagnose`` on the recording against the nominal -- the same path as the command line.
Recordings: point-to-point (``steps``: 5 um steps forward and back), the x-axis of a circle
(``circle``) and a stepped sine (``sine``).

A positive case passes when
  * the right effect is named first (or is in the confounded set named first); with two
    effects, the first named is one of them and both are named (each, or a confounded set
    containing it),
  * its parameters are within +-20 % of the truth (parameters whose truth is 0: within
    20 % of the largest truth parameter of the same unit, or 2 sigma),
  * the held-out error falls by >= 50 % (deterministic effects: the excess of the closed-loop
    replay error over the run-to-run floor, RMS ratio minus 1; drive noise: the |z| of the
    replay error among the model's simulated recordings;
    quantization: the relative lattice-step error on held-out samples),
  * and no effect the truth lacks is named.
A negative control (truth = nominal, another noise seed / experiment) passes when the
verdict is "model adequate". ``false_positives`` counts cases that named an effect the
truth lacks.
"""
from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import yaml

from experiment_runner.core import outputs

from .effects import LIBRARY, Case
from .effects.base import NOMINAL
from .effects.forces import no_ilc
from .options import Options
from .pipeline import diagnose
from .synth import synth
from .truth import check_params

__all__ = ["CASES", "EXPERIMENTS", "run_selftest", "judge", "diagnose_seconds"]

EXPERIMENTS = {
    # x-axis of a circle: reversals, acceleration, constant velocity; 6 trials at random starts
    "circle": {"name": "diag_circle", "preset": NOMINAL,
               "profile": {"kind": "circle", "radius": 1.0e-3, "speed": 0.02, "cycles": 1.0},
               "trials": 6, "starts": {"margin": 0.005, "seed": 3}, "window": 25.0e-9},
    # 5 um steps forward and back: pre-motion, settling and in-position
    "steps": {"name": "diag_steps", "preset": NOMINAL,
              "profile": {"kind": "step_sequence", "distance": 5.0e-6, "n_forward": 3, "n_backward": 3,
                          "dwell": 0.03},
              "trials": 4, "starts": {"margin": 0.005, "seed": 4}, "window": 25.0e-9},
    # stepped sine, 150 um at 8 and 25 Hz (one settling + four steady periods each): reversals
    # at two speeds and accelerations
    "sine": {"name": "diag_sine", "preset": NOMINAL,
             "profile": {"kind": "sine_sweep", "frequencies": [8.0, 25.0], "amplitude": 1.5e-4, "periods": 4,
                         "settle_periods": 1},
             "trials": 3, "starts": {"margin": 0.005, "seed": 5}, "window": 25.0e-9},
    # SAI stage (Ch. 5), 5 um point-to-point moves: compliant before each move, stiff (locked,
    # with the armature impact) when the reference reaches the target
    "sai_steps": {"name": "diag_sai_steps", "preset": "sai_stage",
                  "profile": {"kind": "point_to_point", "distance": 5.0e-6, "dwell": 0.03},
                  "trials": 6, "starts": {"margin": 0.003, "seed": 6}, "window": 25.0e-9},
}


def _cases() -> list[Case]:
    """Every effect's own cases (:meth:`.effects.base.Effect.selftest_cases`, in library order), then
    pairs of effects and the negative controls."""
    own = [c for e in LIBRARY.values() for c in e.selftest_cases()]
    first = {}
    for c in own:
        first.setdefault(c.effect, c)
    pairs = [Case.pair("coulomb+viscous", first["coulomb"], first["viscous"], seed=131),
             Case.pair("mass+offset", first["mass"], first["offset"], seed=132),
             Case.pair("ripple+viscous", first["ripple"], first["viscous"], seed=133),
             Case.pair("dahl+delay_steps", first["dahl"], first["delay"], seed=134),
             Case.pair("force_constant+asymmetry_sine", first["force_constant"], first["friction_asymmetry"],
                       experiment="sine", seed=135),
             Case.pair("mode+coulomb_sine", first["structural_mode"], first["coulomb"], experiment="sine", seed=136),
             Case.pair("mode+coulomb", first["structural_mode"], first["coulomb"], seed=137)]
    # negative controls: the truth is the nominal, on other noise seeds and recordings
    negatives = [Case("negative_circle_a", None, seed=211), Case("negative_circle_b", None, seed=212),
                 Case("negative_steps", None, experiment="steps", seed=213), Case("negative_circle_c", None, seed=214),
                 Case("negative_fi_stage", None, nominal="fi_stage", seed=215),
                 Case("negative_sine_a", None, experiment="sine", seed=221),
                 Case("negative_sine_b", None, experiment="sine", seed=222),
                 Case("negative_steps_b", None, experiment="steps", seed=223),
                 Case("negative_circle_d", None, seed=224),
                 Case("negative_fi_stage_sine", None, nominal="fi_stage", experiment="sine", seed=225),
                 Case("negative_van_stage", None, nominal="van_stage", experiment="steps", seed=227),
                 Case("negative_sai_stage", None, nominal="sai_stage", nominal_edit=no_ilc, experiment="sai_steps",
                      seed=226)]
    return own + pairs + negatives


CASES = _cases()
"""The self-test's cases (names unique)."""


def judge(case: Case, rep: dict) -> dict:
    """Whether a diagnosis passed its self-test case.

    Passed: the truth's effect(s) named first (or in the named effect's confounded set), every
    parameter within its tolerance of the truth, the held-out error's excess over the run-to-run
    floor down by at least 50 %, and no effect the truth lacks (a negative control: "model
    adequate" and nothing named).

    Parameters
    ----------
    case : Case
        The self-test case (its truth and expected parameters).
    rep : dict
        The diagnosis report.

    Returns
    -------
    dict
        ``passed``, ``false_positive``, ``named``, ``named_first``, ``extra_effects``, ``params``
        (the checks), ``held_out_fall`` and what it was measured on.
    """
    found = rep["found"]
    names = [f["effect"] for f in found]
    out = {"case": case.name, "truth_effect": case.effect, "verdict": rep["verdict"], "named": names}
    if case.effect is None:
        out["passed"] = rep["verdict"] == "model adequate" and not names
        out["false_positive"] = bool(names)
        return out
    truth = set(case.effects)
    # each named effect stands for itself and its confounded set
    sets = [(f, {f["effect"]} | set(f.get("confounded_with") or [])) for f in found]
    first_ok = bool(sets) and bool(sets[0][1] & truth)
    covered = {e for e in truth if any(e in st for _, st in sets)}
    named_first = first_ok and covered == truth
    extra = [f["effect"] for f, st in sets if not (st & truth)]
    checks, ok_params = {}, True
    for eff, expect in case.expects().items():
        entry = next((f for f in found if f["effect"] == eff), None)
        if entry is None:
            entry = next((a for f in found for a in f.get("alternatives") or [] if a["effect"] == eff), None)
        ok, ch = check_params(entry, expect)
        ok_params &= ok
        checks.update({(k if len(truth) == 1 else f"{eff}.{k}"): v for k, v in ch.items()})
    entry = next((f for f in found if f["effect"] == case.effects[0]), None)
    if len(truth) == 1 and entry is not None and entry.get("held_out"):
        ho = entry["held_out"]
        fall = 1 - ho["improved"] / ho["nominal"] if ho["nominal"] else None
        metric = ho["metric"]
    else:
        # what the user gets: the share of the held-out closed-loop replay error's excess over the
        # run-to-run floor (error/floor RMS ratio minus 1) that the improved model removes
        fr = rep["replay"]["floor_ratio"]
        fall = (1 - max(fr["improved"] - 1, 0.0) / (fr["nominal"] - 1)) if fr["nominal"] > 1 else None
        metric = "held-out closed-loop replay excess over the run-to-run floor"
    ok_fall = fall is not None and fall >= 0.5
    out.update({"named_first": named_first, "extra_effects": extra, "params": checks, "params_ok": bool(ok_params),
                "held_out_metric": metric, "held_out_fall": fall, "fall_ok": bool(ok_fall),
                "false_positive": bool(extra)})
    out["passed"] = bool(named_first and ok_params and ok_fall and not extra)
    return out


def run_selftest(only=None, as_json: bool = False, keep: str | None = None, verbose: bool = False,
                 workers: int | None = None, cluster=None, overwrite: bool = False, progress: bool = True) -> dict:
    """Run the concealed-truth cases (``nanostage diagnose --selftest``).

    Parameters
    ----------
    only : list of str, optional
        Run only the cases whose name starts with one of these.
    as_json : bool, optional
        Print nothing per case (the caller prints the summary as JSON).
    keep : str, optional
        Output folder for the recordings and reports; else a temporary folder, removed.
    verbose : bool, optional
        Print each diagnosis's steps.
    workers : int, optional
        Where each diagnosis runs its candidate fits (:class:`.options.Options`).
    cluster : str, optional
        A Dask scheduler for them instead.
    overwrite : bool, optional
        As :func:`experiment_runner.core.outputs.prepare_folder`'s, for ``keep``.
    progress : bool, optional
        With ``as_json``, a line on stderr as each case ends (count, elapsed seconds, pass/fail);
        without it each case's row is printed on stdout instead.

    Returns
    -------
    dict
        ``cases``, ``passed``, ``false_positives``, ``negative_controls``, ``by_profile`` and
        ``results`` (one :func:`judge` row per case, with its timings).
    """
    cases = [c for c in CASES if not only or any(c.name.startswith(o) for o in only)]
    tmp = outputs.prepare_folder(keep, overwrite, option="--keep") if keep else Path(tempfile.mkdtemp(prefix="nanostage_selftest_"))
    results = []
    start = time.perf_counter()
    try:
        for n, case in enumerate(cases, 1):
            t0 = time.perf_counter()
            d = tmp / case.name
            truth = outputs.write_text(d / "truth.yaml", yaml.safe_dump(case.truth_doc(), sort_keys=False))
            exp = dict(EXPERIMENTS[case.experiment])
            exp["preset"] = case.nominal
            exp_path = outputs.write_text(d / "experiment.yaml", yaml.safe_dump(exp, sort_keys=False))
            nominal = outputs.write_text(d / "nominal.yaml", yaml.safe_dump(case.nominal_doc(), sort_keys=False))
            try:
                rec = synth(truth, exp_path, d / "rec.mcap")
                t1 = time.perf_counter()
                rep = diagnose(rec, nominal, out=d / "diagnosis" if keep else None,
                               options=Options(plots=bool(keep), verbose=verbose, workers=workers, cluster=cluster,
                                               progress=False, max_seconds=None))   # a check: never cut by load
                res = judge(case, rep)
                res["profile"] = case.experiment
                res["synth_s"] = round(t1 - t0, 2)
                res["diagnose_s"] = round(rep["timing_s"]["total_s"], 2)
            except outputs.OutputError:
                raise
            except Exception as err:   # noqa: BLE001 - a crashing case is a failed case
                res = {"case": case.name, "truth_effect": case.effect, "passed": False, "false_positive": False,
                       "error": repr(err)}
            res["runtime_s"] = round(time.perf_counter() - t0, 2)
            results.append(res)
            if not as_json:
                _print_row(res)
            elif progress:
                print(f"[selftest {time.perf_counter() - start:6.0f} s] case {n}/{len(cases)} {case.name}: "
                      f"{'PASS' if res['passed'] else 'FAIL'} ({res['runtime_s']:.1f} s)", file=sys.stderr, flush=True)
    finally:
        if not keep:
            shutil.rmtree(tmp, ignore_errors=True)
    by_kind = {}
    for case, r in zip(cases, results):
        kind = "negative" if case.effect is None else ("pair" if len(case.effects) > 1 else "single")
        row = by_kind.setdefault(f"{case.experiment}/{kind}", {"cases": 0, "passed": 0, "false_positives": 0})
        row["cases"] += 1
        row["passed"] += bool(r["passed"])
        row["false_positives"] += bool(r.get("false_positive"))
    summary = {"cases": len(results), "passed": sum(r["passed"] for r in results),
               "false_positives": sum(bool(r.get("false_positive")) for r in results),
               "negative_controls": sum(r["truth_effect"] is None for r in results),
               "by_profile": by_kind, "results": results}
    return summary


def diagnose_seconds(duration: float = 10.0, keep: str | None = None) -> float:
    """Wall time [s] of ``diagnose`` on a synthetic recording of ``duration`` seconds at the
    nominal's 10 kHz (circle trials of 0.5 s, truth = nominal + 30 % Coulomb friction,
    concealed), written and read back as MCAP like any recording (``nanostage bench``).

    Parameters
    ----------
    duration : float, optional
        Seconds of recording.
    keep : str, optional
        Folder for the recording (else a temporary folder, removed).

    Returns
    -------
    float
        Seconds.
    """
    case = next(c for c in CASES if c.name == "coulomb_+30%")
    cycles = 0.5 / (2 * 3.141592653589793 * 1.0e-3 / 0.02)          # 0.5 s of circle per trial
    exp = dict(EXPERIMENTS["circle"], name="diag_bench", trials=max(2, int(round(duration / 0.5))))
    exp["profile"] = dict(exp["profile"], cycles=cycles)
    tmp = outputs.prepare_folder(keep) if keep else Path(tempfile.mkdtemp(prefix="nanostage_diagbench_"))
    try:
        outputs.write_text(tmp / "truth.yaml", yaml.safe_dump(case.truth_doc(), sort_keys=False))
        outputs.write_text(tmp / "experiment.yaml", yaml.safe_dump(exp, sort_keys=False))
        rec = synth(tmp / "truth.yaml", tmp / "experiment.yaml", tmp / "rec.mcap")
        t0 = time.perf_counter()
        diagnose(rec, NOMINAL, options=Options(plots=False, progress=False, max_seconds=None))
        return time.perf_counter() - t0
    finally:
        if not keep:
            shutil.rmtree(tmp, ignore_errors=True)


def _print_row(r: dict):
    mark = "PASS" if r["passed"] else "FAIL"
    if "error" in r:
        print(f"{mark}  {r['case']:24s} error: {r['error']}", flush=True)
        return
    par = ", ".join(f"{k} {v['estimate']:.4g} (truth {v['truth']:.4g})" if v["estimate"] is not None else f"{k} missing"
                    for k, v in (r.get("params") or {}).items())
    fall = r.get("held_out_fall")
    print(f"{mark}  {r['case']:24s} named {r['named'] or '-'}  {par}"
          + (f"  held-out fall {100 * fall:.0f} %" if fall is not None else "")
          + f"  [{r['runtime_s']:.1f} s]", flush=True)
