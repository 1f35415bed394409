"""The power study: every case run (:mod:`.case_run`), the rates, ``power.json`` and ``report.md``.

Rates (:func:`summarize`):

``power.named_first_rate``  single-effect cases with ``replay_change >= 3``: the true effect
                            (or a confounded set holding it) named first
``power.pair_rate``         pairs in which each effect changes the replay by >= 3 floors once the
                            other is in the model (``replay_change_given_other``: the nominal
                            plus the other effect against recordings of the truth, in that
                            model's floor): both named, the first named one of them.
                            ``pair_rate_alone`` counts pairs by each effect's change from the
                            nominal alone instead (an effect can be large alone and small beside
                            the other: a viscous term beside a GMS, 6.7x alone, 0.2x given it)
``power.params_rate``       of the correctly named effects above: every parameter within
                            +-20 % of the truth
``power.params_within_2sigma`` of their parameters with a reported 1-sigma: the share whose
                            error is within 2 sigma (honest uncertainties give ~95 %)
``false_positive_rate``     negative controls with any effect named

``report.md`` (with ``--out``) plots the detection rate against the replay change per
effect (``power_detection.png``) and lists every rejected-but-true effect (above the 3x
line, not named) and every accepted-but-harmful one (named though the truth lacks it, or
the improved model's replay worse than the nominal's) with the diagnosis' reason.
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numba
import numpy as np

from experiment_runner.core import outputs
from experiment_runner.core.executor import default_workers, make_executor

from ..report import jsonable
from .case_run import run_case
from .cases import DEFAULT_CASES, PowerCase, dealt_effects, make_cases

__all__ = ["run_power", "summarize", "write_report", "to_markdown"]

def _task(case: PowerCase, keep):
    numba.set_num_threads(1)
    return run_case(case, keep)


def _pair_change(r: dict, e: str) -> float:
    """What effect ``e`` of pair case ``r`` adds to the replay once the other is in the model
    (floor units); its change from the nominal alone when that was not measured."""
    return (r.get("replay_change_given_other") or r["replay_change"]).get(e, 0.0)


def summarize(results: list[dict], threshold: float = 3.0) -> dict:
    """The study's rates from the case results.

    Parameters
    ----------
    results : list of dict
        :func:`run_case` results.
    threshold : float, optional
        Effect size (replay change, floor units) from which an effect counts as detectable.

    Returns
    -------
    dict
        ``power`` (the rates), ``false_positive_rate``, counts of cases, errors and warnings.
    """
    singles = [r for r in results if r["kind"] == "single" and "error" not in r]
    pairs = [r for r in results if r["kind"] == "pair" and "error" not in r]
    negs = [r for r in results if r["kind"] == "negative"]
    # a truth whose own noise-free replay is unstable (the concealed effect makes the loop swing) has no
    # meaningful replay change: such cases are counted apart
    unstable = [r for r in singles + pairs if not r.get("truth_stable", True)]
    singles = [r for r in singles if r.get("truth_stable", True)]
    pairs = [r for r in pairs if r.get("truth_stable", True)]
    big = [r for r in singles if r["replay_change"].get("truth", 0) >= threshold]
    pbig = [r for r in pairs if all(_pair_change(r, e) >= threshold for e in r["effects"])]
    palone = [r for r in pairs if all(r["replay_change"].get(e, 0) >= threshold for e in r["effects"])]
    named = [r for r in big if r["named_first"]]
    pok = [r for r in pbig if r["both_named"]]
    par = [r["params"][r["effects"][0]]["ok"] for r in named if r["params"][r["effects"][0]]["ok"] is not None]
    # are the reported uncertainties honest? each named effect's parameter error against its 1-sigma
    zs = [c["z"] for r in named for c in r["params"][r["effects"][0]]["checks"].values() if c.get("z") is not None]
    by = {}
    for r in [r for r in results if r["kind"] == "single"]:
        e = r["effects"][0]
        row = by.setdefault(e, {"cases": 0, "above_3x": 0, "named_first_above_3x": 0, "named_first": 0,
                                "params_ok": 0, "errors": 0})
        row["cases"] += 1
        if "error" in r:
            row["errors"] += 1
            continue
        above = r["replay_change"].get("truth", 0) >= threshold
        row["above_3x"] += above
        row["named_first"] += bool(r["named_first"])
        row["named_first_above_3x"] += bool(above and r["named_first"])
        row["params_ok"] += bool(above and r["named_first"] and r["params"][e]["ok"])
    errors = [r for r in results if "error" in r]
    fp = [r for r in negs if r.get("false_positive") or "error" in r]
    harmful = [r for r in results if r.get("extra") or r.get("improved_worse")]
    return {
        "power": {"named_first_rate": len(named) / len(big) if big else None, "named_first_cases": len(big),
                  "pair_rate": len(pok) / len(pbig) if pbig else None, "pair_cases": len(pbig),
                  "pair_rate_alone": (sum(r["both_named"] for r in palone) / len(palone)) if palone else None,
                  "pair_cases_alone": len(palone),
                  "params_rate": sum(par) / len(par) if par else None, "params_cases": len(par),
                  "params_within_2sigma": (sum(abs(z) <= 2 for z in zs) / len(zs)) if zs else None,
                  "params_with_sigma": len(zs),
                  "threshold_floor_units": threshold, "by_effect": by},
        "false_positive_rate": len(fp) / len(negs) if negs else None,
        "cases": len(results), "negatives": len(negs), "singles": len(singles) + sum(r["kind"] == "single" and "error" in r for r in results),
        "pairs": len([r for r in results if r["kind"] == "pair"]),
        "errors": len(errors),
        "truth_unstable": [r["case"] for r in unstable],
        "warnings": {r["case"]: r["warnings"] for r in results if r.get("warnings")},
        "harmful_or_wrong": len(harmful),
    }


def run_power(n_cases: int = DEFAULT_CASES, workers: int | None = None, cluster=None, out=None, keep=None,
              progress: bool = True, only=None) -> dict:
    """Run the study (cases on ``workers`` local processes, default one per core this process may use
    (:func:`~experiment_runner.core.executor.default_workers`), or a Dask ``cluster``); returns the
    summary with ``results``; with ``out`` writes ``power.json``, ``report.md`` and the plot.

    Parameters
    ----------
    n_cases : int, optional
        Cases (:func:`make_cases`).
    workers : int, optional
        Local worker processes (default: one per core this process may use).
    cluster : str, optional
        Dask scheduler address (instead of local workers).
    out : str or pathlib.Path, optional
        Output folder.
    keep : str or pathlib.Path, optional
        Folder for every case's recording and report.
    progress : bool, optional
        A line on stderr as each case ends (count, elapsed seconds, what it named); default on.
    only : list of str, optional
        Run only cases whose name contains one of these.

    Returns
    -------
    dict
        :func:`summarize`'s summary with ``wall_s`` and ``results``.
    """
    if workers is None and cluster is None:
        workers = default_workers()
    cases = make_cases(n_cases)
    if only:
        cases = [c for c in cases if any(o in c.name for o in only)]
    t0 = time.perf_counter()
    results = [None] * len(cases)
    with make_executor(workers, cluster) as ex:
        for k, (i, r) in enumerate(ex.map(_task, [(i, (c, keep)) for i, c in enumerate(cases)])):
            results[i] = r
            if progress:
                print(f"[power {time.perf_counter() - t0:6.0f} s] case {k + 1}/{len(cases)} {r['case']}: "
                      f"named {r.get('named')}, change {_fmt_change(r)} {r.get('error', '')} ({r['seconds']:.1f} s)",
                      file=sys.stderr, flush=True)
    s = summarize(results)
    s["wall_s"] = round(time.perf_counter() - t0, 1)
    s["results"] = results
    if out is not None:
        write_report(out, s)
    return s


def _fmt_change(r) -> str:
    given = r.get("replay_change_given_other") or {}
    return ", ".join(f"{k} {v:.3g}x" + (f" ({given[k]:.3g}x given the other)" if k in given else "")
                     for k, v in (r.get("replay_change") or {}).items())


# --------------------------------------------------------------------------- report
def write_report(out, s: dict) -> Path:
    """Write ``power.json``, ``report.md`` and the detection-rate plot into ``out``.

    Parameters
    ----------
    out : str or pathlib.Path
        Output folder (:func:`experiment_runner.core.outputs.prepare_folder`).
    s : dict
        :func:`run_power`'s summary.

    Returns
    -------
    pathlib.Path
        The folder.
    """
    out = outputs.prepare_folder(out)
    outputs.write_text(out / "power.json", json.dumps(jsonable(s), indent=1))
    plots = []
    try:
        plots = _plot(out, s)
    except Exception as err:       # noqa: BLE001 - the plot must not lose the report
        s.setdefault("notes", []).append(f"plot failed: {err!r}")
    outputs.write_text(out / "report.md", to_markdown(s, plots))
    return out


def _pct(x):
    return "–" if x is None else f"{100 * x:.1f} %"


def to_markdown(s: dict, plots=()) -> str:
    """The study's ``report.md``.

    Parameters
    ----------
    s : dict
        :func:`run_power`'s summary.
    plots : sequence of str, optional
        Plot file names to embed.

    Returns
    -------
    str
    """
    p = s["power"]
    L = ["# Diagnosis power study", "",
         f"{s['cases']} cases ({s['singles']} single effects, {s['pairs']} pairs, {s['negatives']} negative controls), "
         f"{s.get('wall_s', 0):.0f} s wall. Size that counts: the effect's change of the nominal's held-out replay in "
         f"units of the run-to-run floor (>= {p['threshold_floor_units']:g}x: should be found).", "",
         "| rate | value | over | goal |", "|---|---|---|---|",
         f"| named first (single effects >= 3x) | {_pct(p['named_first_rate'])} | {p['named_first_cases']} | >= 95 % |",
         f"| both named (pairs, each >= 3x given the other) | {_pct(p['pair_rate'])} | {p['pair_cases']} | >= 90 % |",
         f"| both named (pairs, each >= 3x alone) | {_pct(p.get('pair_rate_alone'))} | {p.get('pair_cases_alone', 0)} | |",
         f"| parameters within ±20 % (named, >= 3x) | {_pct(p['params_rate'])} | {p['params_cases']} | |",
         f"| parameter errors within 2σ of the reported σ (named, >= 3x) | {_pct(p.get('params_within_2sigma'))} | "
         f"{p.get('params_with_sigma', 0)} parameters | ~95 % |",
         f"| false positives (negative controls) | {_pct(s['false_positive_rate'])} | {s['negatives']} | <= 5 % |",
         f"| cases that failed to run | {s['errors']} | {s['cases']} | 0 |",
         f"| cases left out: the truth's own replay unstable | {len(s.get('truth_unstable') or [])} | {s['cases']} | |",
         f"| cases that raised warnings (listed in power.json, `warnings`) | {len(s.get('warnings') or {})} | "
         f"{s['cases']} | 0 |",
         "",
         "| effect | cases | >= 3x | named first (>= 3x) | named first (all) | params ok (>= 3x) |",
         "|---|---|---|---|---|---|"]
    for e, r in p["by_effect"].items():
        L.append(f"| {e} | {r['cases']} | {r['above_3x']} | {r['named_first_above_3x']} | {r['named_first']} | "
                 f"{r['params_ok']} |")
    for f in plots:
        L += ["", f"![detection rate vs effect size]({f})"]
    res = s["results"]
    L += ["", "## Rejected but true (>= 3x the floor, not named)", ""]
    rows = [r for r in res if r["kind"] != "negative" and "error" not in r
            and any((_pair_change(r, e) if r["kind"] == "pair" else r["replay_change"].get("truth", 0)) >= 3
                    and not r["detected"].get(e)
                    for e in r["effects"])]
    L += [f"- `{r['case']}` (change {_fmt_change(r)}): named {r['named'] or 'nothing'}; "
          + "; ".join(f"{e}: {w}" for e, w in (r.get("reasons") or {}).items()) for r in rows] or ["none"]
    L += ["", "## Named first but wrong (>= 3x, another effect first)", ""]
    rows = [r for r in res if r["kind"] == "single" and "error" not in r and r["replay_change"].get("truth", 0) >= 3
            and r["detected"].get(r["effects"][0]) and not r["named_first"]]
    L += [f"- `{r['case']}`: named {r['named']}" for r in rows] or ["none"]
    L += ["", "## Accepted but harmful (an effect the truth lacks, or the improved replay worse than the nominal's)", ""]
    rows = [r for r in res if r.get("extra") or r.get("improved_worse") or (r["kind"] == "negative" and r["named"])]
    L += [f"- `{r['case']}`: named {r['named']}" + (" — improved replay worse than nominal" if r.get("improved_worse") else "")
          + "".join(f"; {e}: {w}" for e, w in (r.get("extra_reasons") or {}).items()) for r in rows] or ["none"]
    L += ["", "## Parameter errors of correctly named effects (>= 3x)", ""]
    for r in res:
        if r["kind"] == "single" and "error" not in r and r.get("named_first") and r["replay_change"].get("truth", 0) >= 3:
            pr = r["params"][r["effects"][0]]
            if pr["ok"] is False:
                L.append(f"- `{r['case']}`: " + ", ".join(
                    (f"{k} {v['estimate']:.4g} vs {v['truth']:.4g}"
                     + (f" (± {v['sigma']:.3g}, z {v['z']:+.2g})" if v.get("z") is not None else ""))
                    if v.get("estimate") is not None else f"{k} missing"
                    for k, v in pr["checks"].items()))
    errs = [r for r in res if "error" in r]
    if errs:
        L += ["", "## Cases that failed to run", ""] + [f"- `{r['case']}`: {r['error']}" for r in errs]
    return "\n".join(L) + "\n"


def _plot(out: Path, s: dict) -> list[str]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    res = [r for r in s["results"] if r["kind"] == "single" and "error" not in r]
    effs = [e for e in dealt_effects() if any(r["effects"][0] == e for r in res)]
    if not effs:
        return []
    nc = 6
    nr = -(-len(effs) // nc)
    fig, axes = plt.subplots(nr, nc, figsize=(2.6 * nc, 2.2 * nr), squeeze=False, sharey=True)
    for ax in axes.ravel()[len(effs):]:
        ax.axis("off")
    for ax, e in zip(axes.ravel(), effs):
        rr = [r for r in res if r["effects"][0] == e]
        x = np.array([max(r["replay_change"].get("truth", 0), 1e-3) for r in rr])
        y = np.array([1.0 if r["named_first"] else 0.0 for r in rr])
        ax.semilogx(x, y + np.linspace(-0.04, 0.04, len(y)), "o", ms=4, color="C0", alpha=0.7)
        edges = np.logspace(-2, 3, 6)
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (x >= lo) & (x < hi)
            if m.any():
                ax.plot([lo, hi], [y[m].mean()] * 2, "C3-", lw=2)
        ax.axvline(3.0, color="k", ls=":", lw=0.8)
        ax.set_title(e, fontsize=8)
        ax.set_ylim(-0.1, 1.1)
        ax.set_xlim(1e-2, 1e3)
        ax.tick_params(labelsize=7)
    fig.supxlabel("replay change of the effect [run-to-run floors] (dotted: 3x)", fontsize=8)
    fig.supylabel("named first (dots: cases, bars: rate)", fontsize=8)
    fig.tight_layout()
    outputs.savefig(fig, out / "power_detection.png", dpi=90)
    plt.close(fig)
    return ["power_detection.png"]
