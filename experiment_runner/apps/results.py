"""``docs/results.md`` written from the reports it quotes: ``python -m experiment_runner.apps.results``.

Every number on the page comes from a report that a nanostage command wrote; nothing is typed by
hand. The reports are read from one folder (``--from``, default ``out``) in this layout, each
made by the command beside it:

===============================  ==========================================================
``campaigns/headline.json``      ``nanostage campaign --main --out DIR/campaigns``
``selftest.json``                ``nanostage diagnose --selftest --json > DIR/selftest.json``
``power/power.json``             ``nanostage diagnose --selftest --power --out DIR/power``
``paper/claims.json``            ``nanostage paper --out DIR/paper``
``bench.json``                   ``nanostage bench --json > DIR/bench.json``
``scaling.json``                 ``scripts/device_scaling.sh`` (its ``$OUT/scaling.json``)
===============================  ==========================================================

A report that is not there gives its section a line naming the command that makes it (the page
says what was not measured, never an old number). The page opens with the command that wrote
it. Interpretation and derivations live in ``docs/headline.md``; how the figures changed over
time, in ``CHANGELOG.md``.

Bad input (a folder that is not there, a report that is not JSON or lacks a field) is one
message naming the file and the field, exit status 2.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

__all__ = ["SOURCES", "ResultsError", "render", "write_results", "main"]

#: report file (relative to ``--from``) -> the command that writes it
SOURCES = {
    "campaigns/headline.json": "nanostage campaign --main --out DIR/campaigns",
    "selftest.json": "nanostage diagnose --selftest --json > DIR/selftest.json",
    "power/power.json": "nanostage diagnose --selftest --power --out DIR/power",
    "paper/claims.json": "nanostage paper --out DIR/paper",
    "bench.json": "nanostage bench --json > DIR/bench.json",
    "scaling.json": "scripts/device_scaling.sh (copy its $OUT/scaling.json)",
}

#: ``nanostage bench`` figures quoted, in order, with what each measures and its goal (None: no goal)
BENCH = (
    ("core_single_rtf", "one FI-stage 5 mm point-to-point trajectory, simulated s per wall s", 200),
    ("core_batch_rtf_all_cores", "100 such trials, batch engine on every core, simulated s per wall s", 1000),
    ("core_batch_rtf", "100 trials on one core, simulated s per wall s", None),
    ("core_ns_per_substep_per_trial", "one-core batch, ns per sub-step and trial", None),
    ("campaign_trials_per_s_1", "Table 4.2 campaign trials/s, one worker of one thread", None),
    ("campaign_scale_out_", "campaign trials/s on N worker processes over one (goal >= 0.85 N)", None),
    ("campaign_trials_per_s_dask_", "the same N workers as a Dask LocalCluster, trials/s", None),
    ("threads_scale_all_cores", "one process on every core's threads over one thread", None),
    ("diagnose_seconds_10s", "nanostage diagnose of a 10 s, 10 kHz recording, s", 15),
    ("graph_message_rate_vs_rclpy", "ROS graph messages/s over raw rclpy's", 0.6),
    ("graph_loop_hz_processes", "ROS graph control samples/s, one process per node", 1000),
    ("main_job_seconds", "nanostage campaign --main, wall s", 90),
    ("peak_memory_mb", "peak resident memory of the bench, MB", None),
)


class ResultsError(ValueError):
    """A report that cannot be quoted: the message names the file, the field and what was found."""


def _load(path: Path):
    """The JSON in ``path``, or None when the file is not there; :class:`ResultsError` when unreadable."""
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ResultsError(f"{path}: not a JSON report ({err})") from None


def _field(doc, key: str, path: Path):
    """``doc[key]``, or :class:`ResultsError` naming ``path`` and ``key``."""
    if not isinstance(doc, dict) or key not in doc:
        raise ResultsError(f"{path}: field {key!r} missing (is this the report `{_command(path)}` writes?)")
    return doc[key]


def _command(path: Path) -> str:
    return next((c for f, c in SOURCES.items() if str(path).endswith(f)), "?")


def _num(x, digits: int = 3) -> str:
    """``x`` to ``digits`` significant figures; '--' for None."""
    if x is None:
        return "--"
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return str(x)
    return f"{x:.{digits}g}"


def _missing(name: str) -> str:
    return f"Not measured for this page: run `{SOURCES[name]}`.\n"


def _campaigns(doc, path: Path) -> str:
    ratios = _field(doc, "ratios", path)
    rows = ["| campaign | ratio | condition | metric | seed | ours (mean) | ours (median) | holds | mechanism |",
            "|---|---|---|---|---|---|---|---|---|"]
    for r in ratios:
        for k in ("campaign", "label", "condition", "metric", "seed", "sim", "holds"):
            _field(r, k, path)
        holds = "yes" if r["holds"] else ("median only" if r.get("holds_median") else "**no**")
        mech = {True: "seed's", False: "**other**"}.get(r.get("mechanism_ok"), "--")
        rows.append(f"| {r['campaign']} | {r['label']} | {r['condition']} | {r['metric']} | {_num(r['seed'])} "
                    f"| {_num(r['sim'])} | {_num(r.get('sim_median'))} | {holds} | {mech} |")
    n = sum(bool(r["holds"]) for r in ratios)
    return (f"The seed's headline ratios: **{n} of {len(ratios)} hold** at least half the seed's change "
            "(each campaign's `report.md` beside `headline.json` gives the mechanism in words).\n\n"
            + "\n".join(rows) + "\n")


def _selftest(doc, path: Path) -> str:
    cases, passed = _field(doc, "cases", path), _field(doc, "passed", path)
    fp, neg = _field(doc, "false_positives", path), _field(doc, "negative_controls", path)
    times = sorted(r["runtime_s"] for r in doc.get("results", []) if isinstance(r.get("runtime_s"), (int, float)))
    median = f"; median {_num(times[len(times) // 2])} s per case" if times else ""
    failed = [r.get("case", "?") for r in doc.get("results", []) if not r.get("passed")]
    text = (f"Concealed-truth self-test: **{passed} of {cases} cases pass**, {fp} false positives "
            f"({neg} negative controls){median}.\n")
    if failed:
        text += "\nFailed: " + ", ".join(f"`{c}`" for c in failed) + ".\n"
    return text


def _power(doc, path: Path) -> str:
    p = _field(doc, "power", path)

    def pct(rate, n):
        return "--" if rate is None else f"{100 * rate:.1f} % of {n}"
    rows = ["| figure | value |", "|---|---|",
            f"| true effect named first (single effects at >= {_num(p.get('threshold_floor_units'))}x the floor) "
            f"| {pct(p.get('named_first_rate'), p.get('named_first_cases'))} |",
            f"| both effects of a pair named | {pct(p.get('pair_rate'), p.get('pair_cases'))} |",
            f"| parameters within +-20 % | {pct(p.get('params_rate'), p.get('params_cases'))} |",
            f"| false positives (negative controls) | {pct(_field(doc, 'false_positive_rate', path), doc.get('negatives'))} |",
            f"| cases (singles, pairs, negatives) | {_field(doc, 'cases', path)} ({doc.get('singles')}, "
            f"{doc.get('pairs')}, {doc.get('negatives')}) |",
            f"| cases that failed with an error | {doc.get('errors')} |",
            f"| wall time | {_num(doc.get('wall_s'))} s |"]
    return "\n".join(rows) + "\n"


def _paper(doc, path: Path) -> str:
    if not isinstance(doc, list):
        raise ResultsError(f"{path}: expected a list of claims (the report `{SOURCES['paper/claims.json']}` writes)")
    rows = ["| source | claim | seed | ours | agrees |", "|---|---|---|---|---|"]
    for c in doc:
        for k in ("source", "claim", "seed", "ours", "agrees"):
            _field(c, k, path)
        cell = lambda s: str(s).replace("|", "\\|").replace("\n", " ")  # noqa: E731 - a table cell
        rows.append(f"| {cell(c['source'])} | {cell(c['claim'])} | {cell(c['seed'])} | {cell(c['ours'])} "
                    f"| {'yes' if c['agrees'] else '**no**'} |")
    n = sum(bool(c["agrees"]) for c in doc)
    return f"**{n} of {len(doc)} claims agree** (derivations: `claims.md` beside `claims.json`).\n\n" + "\n".join(rows) + "\n"


def _bench(doc, path: Path) -> str:
    if not isinstance(doc, dict):
        raise ResultsError(f"{path}: expected one JSON object (the output of `nanostage bench --json`)")
    rows = ["| figure | measures | value | goal |", "|---|---|---|---|"]
    for key, what, goal in BENCH:
        keys = [k for k in doc if k == key or (key.endswith("_") and k.startswith(key) and k[len(key):].isdigit())]
        for k in keys:
            rows.append(f"| `{k}` | {what} | {_num(doc[k])} | {_num(goal) if goal is not None else '--'} |")
    return "\n".join(rows) + "\n"


def _scaling(doc, path: Path) -> str:
    meta, camp = _field(doc, "meta", path), _field(doc, "campaign", path)
    cpu = meta.get("cpu", {}) if isinstance(meta, dict) else {}
    rows = [f"Machine: {cpu.get('model', '?')}, {meta.get('cores', '?')} cores, numba {meta.get('numba', '?')} "
            f"({meta.get('threading_layer', '?')}), numpy {meta.get('numpy', '?')}, Python {meta.get('python', '?')}.",
            "", "| run | trials/s | x one worker of one thread |", "|---|---|---|"]

    def order(k):
        tail = k.split("_")[1]
        return (k.split("_")[0] != "pool", int(tail) if tail.isdigit() else 0, k)
    for k in sorted(camp, key=order):
        r = camp[k]
        ratio = r.get("scale") if "scale" in r else (f"{_num(r['vs_pool'])} of the pool" if "vs_pool" in r else None)
        rows.append(f"| `{k}` | {_num(r.get('trials_per_s'), 4)} | {_num(ratio, 4)} |")
    for k, r in sorted((doc.get("threads") or {}).items()):
        rows.append(f"| one process, `threads_{k}` | {_num(r.get('trials_per_s'), 4)} | {_num(r.get('scale'))} |")
    return "\n".join(rows) + "\n"


SECTIONS = (
    ("Campaigns", "campaigns/headline.json", _campaigns),
    ("Diagnosis self-test", "selftest.json", _selftest),
    ("Diagnosis power study", "power/power.json", _power),
    ("The dissertation's simulation claims", "paper/claims.json", _paper),
    ("Speed", "bench.json", _bench),
    ("Scale-out on many cores", "scaling.json", _scaling),
)


def render(source: Path, command: str) -> str:
    """The page for the reports under ``source``.

    Parameters
    ----------
    source : Path
        Folder holding the reports in the layout of :data:`SOURCES`.
    command : str
        The command line that writes the page, quoted at its top.

    Returns
    -------
    str
        Markdown: the command, then one section per report (or the command that makes a missing one).

    Examples
    --------
    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     page = render(Path(d), "python -m experiment_runner.apps.results --from out")
    >>> page.splitlines()[2]
    'Generated by `python -m experiment_runner.apps.results --from out` from the reports it quotes; do not edit by hand.'
    >>> page.count("Not measured for this page")
    6
    """
    source = Path(source)
    if not source.is_dir():
        raise ResultsError(f"--from {source}: not a folder (expected the reports' folder: {', '.join(SOURCES)})")
    parts = ["# Results: what nanostage reproduces and how fast", "",
             f"Generated by `{command}` from the reports it quotes; do not edit by hand.",
             "Each section names its report (relative to the `--from` folder) and the command that wrote it;"
             " interpretation and derivations: [headline.md](headline.md); how the figures changed: CHANGELOG.md.",
             ""]
    for title, name, fmt in SECTIONS:
        path = source / name
        doc = _load(path)
        parts += [f"## {title}", "", f"Report `{name}`, written by `{SOURCES[name]}`.", ""]
        parts.append(_missing(name) if doc is None else fmt(doc, path))
    return "\n".join(parts)


def write_results(source, out, command: str, overwrite: bool = False) -> Path:
    """Render the page for ``source`` and write it to ``out`` atomically.

    Parameters
    ----------
    source : str or Path
        Folder holding the reports (:data:`SOURCES`).
    out : str or Path
        The Markdown file to write (its folder must exist). A file already there is replaced only
        when this generator wrote it (its third line is the "Generated by" line) or ``overwrite``;
        a link is never followed.
    command : str
        The command line quoted at the top of the page.
    overwrite : bool, optional
        Replace ``out`` even when it was written by hand.

    Returns
    -------
    Path
        ``out``.
    """
    out = Path(out)
    text = render(Path(source), command)
    if out.is_symlink() or (out.exists() and not out.is_file()):
        raise ResultsError(f"--out {out}: a link or a folder is there; choose a plain file")
    if out.exists() and not overwrite:
        lines = out.read_text(encoding="utf-8", errors="replace").splitlines()
        if len(lines) < 3 or not lines[2].startswith("Generated by `python -m experiment_runner.apps.results"):
            raise ResultsError(f"--out {out}: exists and was not written by this generator; "
                               "give --overwrite to replace it")
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, out)
    finally:
        tmp.unlink(missing_ok=True)
    return out


def main(argv: list[str] | None = None) -> int:
    """Command line: ``python -m experiment_runner.apps.results [--from DIR] [--out FILE]``.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 written, 2 bad input (one message on stderr).
    """
    parser = argparse.ArgumentParser(prog="python -m experiment_runner.apps.results", description=__doc__.splitlines()[0])
    parser.add_argument("--from", dest="source", default="out", help="folder holding the reports (default out)")
    parser.add_argument("--out", default="docs/results.md", help="page to write (default docs/results.md)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out even if it was written by hand")
    args = parser.parse_args(argv)
    command = f"python -m experiment_runner.apps.results --from {args.source} --out {args.out}"
    try:
        path = write_results(args.source, args.out, command, args.overwrite)
    except (ResultsError, OSError) as err:
        print(f"experiment_runner.apps.results: {err}", file=sys.stderr)
        return 2
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
