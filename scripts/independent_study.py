#!/usr/bin/env python3
"""Diagnose the independent concealed-effect corpus as a new user would, and score it.

The corpus (``../shared/independent``: ``python generate.py OUTDIR`` writes ``OUTDIR/hNN/``, one
contract recording each, and ``OUTDIR/manifest.json`` with the truths) is a servo stage simulated
by code written apart from nanostage; each recording's ``/experiment/config`` states only the
nominal model, in that simulator's terms (``nominal_model``), which ``nanostage diagnose``
translates itself (:mod:`experiment_runner.core.nominal_model`). Each case runs

    nanostage diagnose CORPUS/hNN --out OUT/cases/hNN          (CLI defaults, only --out)

in its own process (its own session: on the wall-time limit the whole process group is
stopped), progress on stderr; then the report is scored against the manifest:

* **single effects named first**: the first effect named (or a confounded set holding it) is one
  of the truth effect's nanostage keys (:data:`EFFECTS`);
* **pairs**: both truth effects named (anywhere in the order);
* **false positives**: a negative control (truth = nominal) naming anything; in the other cases
  every named effect that is no truth effect's key (``extra``);
* **parameters within +-20 %** of the truth, read from the improved preset the user gets
  (``improved_preset.yaml``), each in nanostage's terms (:data:`EFFECTS` says how; a quantity the
  nominal already has -- mass, force gain, delay, viscous coefficient -- is compared by its
  concealed *change*, so the nominal itself never passes; a phase within +-0.2 rad); scored
  only where the effect is named;
* wall time per case (and the status: ok, timeout, error).

Writes ``OUT/study.json`` (every case: truth, named, checks, replay, wall time) and
``OUT/study.md`` (per-case table and totals). ``--score-only`` re-scores existing case folders.

Usage::

    nice -n 10 .venv/bin/python scripts/independent_study.py /work/indep/corpus --out out/independent \\
        [--limit-s 1200] [--only h01,h02] [--score-only]
"""
from __future__ import annotations

import argparse
import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import yaml

TOL = 0.20          # relative tolerance of a parameter
PHASE_TOL = 0.2     # [rad] tolerance of a ripple phase


# --------------------------------------------------------------------------- the truth -> nanostage mapping
def _friction_elements(st: dict) -> list[dict]:
    return ([st["table_friction"]] if st.get("table_friction") else []) + [b["friction"] for b in st.get("bearings", [])]


def total_mass(st: dict) -> float:
    """Every body of a preset's stage [kg] (table, bearings, structural-mode masses)."""
    mt = st["table"]["mass"]
    return mt + sum(b["mass"] for b in st.get("bearings", [])) + sum(m["mass_ratio"] * mt for m in st.get("modes", []))


def _delay(st: dict) -> float:
    d = st["drive"]
    return d.get("delay_samples", 0) + d.get("delay_fraction", 0.0)


def _noise(st: dict) -> float:
    d = st["drive"]
    return d.get("noise_current_rms", 0.0) * d["force_constant"] * d.get("force_constant_ratio", 1.0)


def _k_premotion(st: dict) -> float | None:
    ks = [fr.get("k_sigma") or fr.get("sigma0") for fr in _friction_elements(st) if fr["model"] in ("dahl", "lugre")]
    return float(sum(ks)) if ks else None


def _mode(st: dict) -> dict | None:
    """The last structural mode: blocked frequency, damping ratio, mass / total mass."""
    if not st.get("modes"):
        return None
    m = st["modes"][-1]
    return {"f": m["frequency"], "zeta": m["damping_ratio"], "fraction": m["mass_ratio"] * st["table"]["mass"] / total_mass(st)}


def _joint(st: dict) -> dict | None:
    bs = [b for b in st.get("bearings", []) if b.get("joint")]
    if not bs:
        return None
    return {"k_fi": sum(b["joint"]["stiffness"] for b in bs), "c_fi": sum(b["joint"]["damping"] for b in bs),
            "m_bearing": sum(b["mass"] for b in bs)}


def _ripple(st: dict) -> dict | None:
    if not st.get("force_ripple"):
        return None
    r = max(st["force_ripple"], key=lambda r: abs(r["amplitude"]))
    a, ph = r["amplitude"], r["phase"]
    if a < 0:
        a, ph = -a, ph + math.pi
    return {"A": a, "period": r["period"], "phase": ph}


def _stribeck(st: dict) -> dict | None:
    els = [fr for fr in _friction_elements(st) if fr["model"] == "lugre"]
    if not els:
        return None
    return {"F_s": sum(fr["f_s"] for fr in els), "v_s": els[0]["v_s"]}


@dataclass(frozen=True)
class Mapping:
    """How one truth effect of the corpus is named and measured in nanostage.

    ``keys``: the nanostage effect keys that name it; ``checks(truth_params, nominal_plant,
    improved_stage, nominal_stage, Ts)`` -> ``[(quantity, truth, estimate or None, kind)]``, kind
    ``rel`` (within ``TOL`` of the truth) or ``phase`` (within ``PHASE_TOL``)."""
    keys: tuple
    checks: object
    how: str


def _posfric(tp, nom, st, st0, ts):
    g = [fr.get("f_c_gradient", 0.0) for fr in _friction_elements(st)]
    return [("dF_C/dx [N/m]", nom["F_C"] * tp["s"] / tp["L"], float(sum(g)), "rel")]


def _mass_check(tp, nom, st, st0, ts):
    return [("mass change [kg]", nom["m"] * tp["r"], total_mass(st) - total_mass(st0), "rel")]


def _res(tp, nom, st, st0, ts):
    m = _mode(st) or {}
    s = math.sqrt(1.0 - tp["mass_frac"])
    return [("f blocked [Hz]", tp["f_n"] * s, m.get("f"), "rel"), ("zeta blocked", tp["zeta"] * s, m.get("zeta"), "rel"),
            ("mass fraction", tp["mass_frac"], m.get("fraction"), "rel")]


def _iso(tp, nom, st, st0, ts):
    j = _joint(st) or {}
    return [(k, tp[k], j.get(k), "rel") for k in ("k_fi", "c_fi", "m_bearing")]


def _ripple_check(tp, nom, st, st0, ts):
    r = _ripple(st) or {}
    return [("A [N]", tp["ripple_A"], r.get("A"), "rel"), ("period [m]", tp["ripple_p"], r.get("period"), "rel"),
            ("phase [rad]", tp["ripple_phi"], r.get("phase"), "phase")]


def _stribeck_check(tp, nom, st, st0, ts):
    s = _stribeck(st) or {}
    return [("F_s [N]", tp["F_s"], s.get("F_s"), "rel"), ("v_s [m/s]", tp["v_s"], s.get("v_s"), "rel")]


def _viscous(tp, nom, st, st0, ts):
    c = lambda s: sum(fr.get("viscous", 0.0) for fr in _friction_elements(s))  # noqa: E731
    return [("viscous change [N·s/m]", tp["c_v"], c(st) - c(st0), "rel")]


EFFECTS: dict[str, Mapping] = {
    "premotion_dahl": Mapping(("dahl",), lambda tp, nom, st, st0, ts: [("k_sigma [N/m]", tp["k_sigma"], _k_premotion(st), "rel")],
                              "dahl: total k_sigma of the friction elements"),
    "isolator": Mapping(("fi_compliance",), _iso, "fi_compliance: bearing joint stiffness, damping, bearing mass"),
    "force_ripple": Mapping(("ripple",), _ripple_check, "ripple: amplitude, period, phase (sin(2 pi x/p + phase))"),
    "structural_resonance": Mapping(("structural_mode", "located_mode"), _res,
                                    "structural_mode / located_mode: nanostage states the BLOCKED mode (table held): "
                                    "f_b = f_n sqrt(1 - mass_frac), zeta_b = zeta sqrt(1 - mass_frac) of the corpus' "
                                    "free-free mode; mass fraction of the total mass"),
    "actuator_delay": Mapping(("delay", "fractional_delay"),
                              lambda tp, nom, st, st0, ts: [("extra delay [samples]", tp["tau"] / ts, _delay(st) - _delay(st0), "rel")],
                              "delay / fractional_delay: drive delay added to the nominal's (delay_samples + fraction)"),
    "force_gain_error": Mapping(("force_constant",),
                                lambda tp, nom, st, st0, ts: [("force gain error g", tp["g"],
                                                           st["drive"].get("force_constant_ratio", 1.0)
                                                           / st0["drive"].get("force_constant_ratio", 1.0) - 1.0, "rel")],
                                "force_constant: ratio - 1"),
    "position_dependent_friction": Mapping(("position_friction",), _posfric,
                                           "position_friction: friction gradient F_C s / L [N/m]"),
    "stribeck": Mapping(("stribeck",), _stribeck_check, "stribeck: static force F_s and Stribeck velocity v_s"),
    "viscous": Mapping(("viscous",), _viscous, "viscous: added viscous coefficient c_v"),
    "mass_error": Mapping(("mass",), _mass_check, "mass: change of the total mass, m r"),
    "drive_noise": Mapping(("noise_level",),
                           lambda tp, nom, st, st0, ts: [("noise factor", tp["noise_factor"],
                                                      _noise(st) / _noise(st0) if _noise(st0) > 0 else None, "rel")],
                           "noise_level: drive noise RMS / nominal"),
}
"""Every truth effect of the corpus (``truth_additions[*].effect``) -> its nanostage keys and checks.
The one place the scoring maps the corpus' terms onto nanostage's."""


# --------------------------------------------------------------------------- scoring
def _ok(truth, est, kind) -> bool | None:
    if est is None or truth is None:
        return None
    if kind == "phase":
        d = (est - truth + math.pi) % (2 * math.pi) - math.pi
        return abs(d) <= PHASE_TOL
    return abs(est - truth) <= TOL * abs(truth)


def score_case(case: dict, report: dict | None, improved: dict | None, nominal: dict | None) -> dict:
    """Score one case's report against its manifest entry (``case``).

    ``improved``/``nominal``: the improved and the translated nominal presets (mappings).
    Returns named (keys in order), first_ok, all_named, extra, false_positive, checks."""
    ts = float(case["nominal"]["Ts"])
    truth = [a["effect"] for a in case["truth_additions"]]
    out = {"truth": truth, "named": [], "first_ok": None, "all_named": None, "extra": [], "false_positive": None,
           "checks": []}
    if report is None:
        return out
    found = report.get("found") or []
    sets = [(f["effect"], {f["effect"]} | set(f.get("confounded_with") or [])) for f in found]
    out["named"] = [k for k, _ in sets]
    out["confounded"] = {k: sorted(s - {k}) for k, s in sets if len(s) > 1}
    if not truth:
        out["false_positive"] = bool(sets)
        out["extra"] = [k for k, _ in sets]
        return out
    unknown = [t for t in truth if t not in EFFECTS]
    if unknown:
        raise KeyError(f"truth effect(s) {unknown} have no nanostage mapping in EFFECTS")
    keys = {t: set(EFFECTS[t].keys) for t in truth}
    allk = set().union(*keys.values())
    out["first_ok"] = bool(sets) and bool(sets[0][1] & allk)
    named = {t: any(s & keys[t] for _, s in sets) for t in truth}
    out["detected"] = named
    out["all_named"] = all(named.values())
    out["extra"] = [k for k, s in sets if not (s & allk)]
    out["false_positive"] = bool(out["extra"])
    if improved is not None and nominal is not None:
        nom_plant = case["nominal"]["plant"]
        for a in case["truth_additions"]:
            if not named[a["effect"]]:
                continue
            for q, tv, ev, kind in EFFECTS[a["effect"]].checks(a["params"], nom_plant, improved["stage"], nominal["stage"], ts):
                out["checks"].append({"effect": a["effect"], "quantity": q, "truth": tv, "estimate": ev,
                                      "ok": _ok(tv, ev, kind)})
    return out


def _load_yaml(path: Path):
    try:
        return yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError):
        return None


def score_folder(cid: str, case: dict, folder: Path) -> dict:
    """Score a case from its diagnose output folder (``report.json``, ``improved_preset.yaml``);
    the nominal preset is the one the diagnosis used (translated from the recording's config)."""
    rep = None
    if (folder / "report.json").is_file():
        try:
            rep = json.loads((folder / "report.json").read_text())
        except (OSError, json.JSONDecodeError):
            rep = None
    improved = _load_yaml(folder / "improved_preset.yaml")
    from experiment_runner.core.nominal_model import preset_from_nominal
    nominal = preset_from_nominal(case["nominal"])
    s = score_case(case, rep, improved, nominal)
    if rep is not None:
        r = rep.get("replay") or {}
        s["verdict"] = rep.get("verdict")
        s["floor_ratio"] = r.get("floor_ratio")
        s["diagnose_s"] = (rep.get("timing_s") or {}).get("total_s")
    return s


# --------------------------------------------------------------------------- running
def _nanostage() -> str:
    exe = Path(sys.executable).with_name("nanostage")
    return str(exe) if exe.exists() else "nanostage"


def run_case(cid: str, rec: Path, out: Path, limit_s: float, exe: str) -> dict:
    """``nanostage diagnose REC --out OUT`` in its own process group; stopped at ``limit_s``."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [exe, "diagnose", str(rec), "--out", str(out / "diagnose")]
    t0 = time.monotonic()
    with open(out / "stdout.txt", "w") as so, open(out / "stderr.txt", "w") as se:
        p = subprocess.Popen(cmd, stdout=so, stderr=se, start_new_session=True)
        status = "ok"
        try:
            rc = p.wait(timeout=limit_s)
            if rc != 0:
                status = f"error (exit {rc})"
        except subprocess.TimeoutExpired:
            status = f"timeout ({limit_s:.0f} s)"
            for sig, grace in ((signal.SIGTERM, 15), (signal.SIGKILL, 15)):
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    p.wait(timeout=grace)
                    break
                except subprocess.TimeoutExpired:
                    continue
            rc = p.returncode
    wall = time.monotonic() - t0
    info = {"command": " ".join(cmd), "status": status, "returncode": rc, "wall_s": round(wall, 1)}
    (out / "run.json").write_text(json.dumps(info, indent=1))
    return info


# --------------------------------------------------------------------------- report
def _fmt(v) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


def summary(rows: list[dict]) -> dict:
    singles = [r for r in rows if len(r["truth"]) == 1]
    pairs = [r for r in rows if len(r["truth"]) >= 2]
    negs = [r for r in rows if not r["truth"]]
    checks = [c for r in rows for c in r["checks"]]
    walls = [r["run"]["wall_s"] for r in rows if r.get("run")]
    return {"cases": len(rows),
            "single_named_first": [sum(bool(r["first_ok"]) for r in singles), len(singles)],
            "pairs_both_named": [sum(bool(r["all_named"]) for r in pairs), len(pairs)],
            "negative_controls_clean": [sum(not r["false_positive"] for r in negs if r["false_positive"] is not None),
                                        len(negs)],
            "extra_wrong_names": sum(len(r["extra"]) for r in rows if r["truth"]),
            "params_within_20pct": [sum(bool(c["ok"]) for c in checks), len(checks)],
            "timeouts": sum(r.get("run", {}).get("status", "").startswith("timeout") for r in rows),
            "errors": sum(r.get("run", {}).get("status", "").startswith("error") for r in rows),
            "wall_s_max": max(walls) if walls else None, "wall_s_total": round(sum(walls), 1) if walls else None}


def markdown(rows: list[dict], summ: dict, corpus: Path, limit_s: float) -> str:
    def frac(p):
        return f"{p[0]}/{p[1]}"
    L = ["# Independent corpus: `nanostage diagnose` with CLI defaults", "",
         f"Corpus `{corpus}`; per-case wall-time limit {limit_s:.0f} s; scored by `scripts/independent_study.py` "
         f"(parameters within ±{100 * TOL:.0f} %, a phase within ±{PHASE_TOL} rad; changes of a nominal quantity "
         "compared by the change).", "",
         "| | result | goal |", "|---|---|---|",
         f"| single effects named first | {frac(summ['single_named_first'])} | ≥ 95 % |",
         f"| pairs, both named | {frac(summ['pairs_both_named'])} | ≥ 90 % |",
         f"| negative controls naming nothing | {frac(summ['negative_controls_clean'])} | all |",
         f"| extra wrong names (non-negative cases) | {summ['extra_wrong_names']} | 0 |",
         f"| parameters within ±20 % | {frac(summ['params_within_20pct'])} | |",
         f"| timeouts / errors | {summ['timeouts']} / {summ['errors']} | 0 |",
         f"| wall time max / total | {_fmt(summ['wall_s_max'])} s / {_fmt(summ['wall_s_total'])} s | < 300 s each |", "",
         "| case | experiment | truth | named (in order) | first | all | extra | parameters (estimate / truth) | "
         "verdict | error/floor nominal -> improved | wall [s] | status |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ps = "; ".join(f"{c['quantity']} {_fmt(c['estimate'])} / {_fmt(c['truth'])} {'✓' if c['ok'] else '✗'}"
                       for c in r["checks"]) or "-"
        fr = r.get("floor_ratio") or {}
        frs = f"{_fmt(fr.get('nominal'))} -> {_fmt(fr.get('improved'))}" if fr else "-"
        mark = lambda v: "-" if v is None else ("✓" if v else "✗")  # noqa: E731
        L.append(f"| {r['case']} | {r['experiment']} | {', '.join(r['truth']) or 'none'} | "
                 f"{', '.join(r['named']) or '-'} | {mark(r['first_ok'])} | {mark(r['all_named'])} | "
                 f"{', '.join(r['extra']) or '-'} | {ps} | {r.get('verdict') or '-'} | {frs} | "
                 f"{_fmt(r.get('run', {}).get('wall_s'))} | {r.get('run', {}).get('status', '-')} |")
    L += ["", "Mapping of the corpus' effects onto nanostage's (`EFFECTS` in the script):", ""]
    L += [f"- `{k}` -> {m.how}" for k, m in EFFECTS.items()]
    return "\n".join(L) + "\n"


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("corpus", type=Path, help="folder with hNN/ recordings and manifest.json")
    ap.add_argument("--manifest", type=Path, default=None, help="default CORPUS/manifest.json")
    ap.add_argument("--out", type=Path, required=True, help="output folder (cases/hNN/, study.json, study.md)")
    ap.add_argument("--limit-s", type=float, default=1200.0, help="wall-time limit per case [s] (default 1200)")
    ap.add_argument("--only", default=None, help="comma-separated case ids")
    ap.add_argument("--score-only", action="store_true", help="score existing case folders, run nothing")
    ap.add_argument("--force", action="store_true", help="re-run cases that already have a run.json")
    ap.add_argument("--nanostage", default=None, help="the nanostage executable (default: beside this Python)")
    a = ap.parse_args(argv)
    man = json.loads((a.manifest or a.corpus / "manifest.json").read_text())
    cases = man["cases"]
    ids = sorted(cases) if not a.only else [c.strip() for c in a.only.split(",")]
    exe = a.nanostage or _nanostage()
    a.out.mkdir(parents=True, exist_ok=True)
    rows = []
    t_all = time.monotonic()
    for i, cid in enumerate(ids, 1):
        case = cases[cid]
        folder = a.out / "cases" / cid
        truth = ", ".join(x["effect"] for x in case["truth_additions"]) or "none"
        if not a.score_only and (a.force or not (folder / "run.json").is_file()):
            print(f"[{i}/{len(ids)}] {cid} ({truth}; {case['experiment']}): diagnosing ...", file=sys.stderr, flush=True)
            run_case(cid, a.corpus / cid, folder, a.limit_s, exe)
        run = json.loads((folder / "run.json").read_text()) if (folder / "run.json").is_file() else {}
        row = {"case": cid, "experiment": case["experiment"], "run": run,
               **score_folder(cid, case, folder / "diagnose")}
        rows.append(row)
        print(f"[{i}/{len(ids)}] {cid}: {run.get('status', 'not run')}, {_fmt(run.get('wall_s'))} s; named "
              f"{', '.join(row['named']) or 'nothing'} (truth {truth}); elapsed {time.monotonic() - t_all:.0f} s",
              file=sys.stderr, flush=True)
        summ = summary(rows)
        _write(a.out / "study.json", json.dumps({"corpus": str(a.corpus), "limit_s": a.limit_s, "summary": summ,
                                                 "cases": rows}, indent=1, default=str))
        _write(a.out / "study.md", markdown(rows, summ, a.corpus, a.limit_s))
    print(json.dumps(summary(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
