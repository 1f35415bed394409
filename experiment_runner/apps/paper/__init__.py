"""``nanostage paper``: reproduce the seed's *simulation* results claim by claim.

Each module of this package reproduces one group of the dissertation's simulation
figures and returns :class:`Claim` objects: what the seed states, what our
simulation gives, and whether they agree (with the reason where they do not).
:func:`run_paper` runs them all, prints ``claim | seed | ours | agrees``, and
writes ``claims.md``, ``claims.json`` and the PNG plots into the output folder.
"""
from __future__ import annotations

import importlib
import json
import textwrap
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from experiment_runner.core import outputs
from stage_sim.config import ConfigError

#: claim groups, in the order of the dissertation
GROUPS = ("appendix_a", "van", "appendix_b", "fi_design", "rotary")


@dataclass
class Claim:
    """One checkable statement of the seed and our reproduction of it."""
    id: str                 # short unique id, e.g. "A.2/ki0-no-settle"
    source: str             # figure / table / section of the seed
    claim: str              # the statement, in a sentence
    seed: str               # the seed's number or statement
    ours: str               # our number or statement
    agrees: bool
    numbers: dict = field(default_factory=dict)   # raw values (SI), for JSON
    note: str = ""          # why we disagree, or how the number was obtained


def _markdown(claims: list[Claim]) -> str:
    rows = ["| claim | seed | ours | agrees |", "|---|---|---|---|"]
    for c in claims:
        text = f"**{c.source}** {c.claim}" + (f" — *{c.note}*" if c.note else "")
        rows.append(f"| {text} | {c.seed} | {c.ours} | {'yes' if c.agrees else '**no**'} |")
    return "\n".join(rows) + "\n"


def _table(claims: list[Claim]) -> str:
    """Plain-text table, each cell wrapped to its column."""
    widths = (46, 34, 40, 6)
    sep = "-+-".join("-" * w for w in widths)
    lines = [" | ".join(h.ljust(w) for h, w in zip(("claim", "seed", "ours", "agrees"), widths)), sep]
    for c in claims:
        cells = [textwrap.wrap(text, w) or [""] for text, w in
                 zip((f"{c.source}: {c.claim}", c.seed, c.ours, "yes" if c.agrees else "NO"), widths)]
        for i in range(max(map(len, cells))):
            lines.append(" | ".join((col[i] if i < len(col) else "").ljust(w)
                                    for col, w in zip(cells, widths)))
        lines.append(sep)
    return "\n".join(lines)


def selected_groups(only=None) -> list[str]:
    """The claim groups whose name starts with one of ``only`` (all if ``only`` is empty).

    Raises
    ------
    stage_sim.config.ConfigError
        An entry of ``only`` that starts no group's name (the message lists the groups).

    Examples
    --------
    >>> selected_groups(["app"])
    ['appendix_a', 'appendix_b']
    """
    unknown = [o for o in only or () if not any(name.startswith(o) for name in GROUPS)]
    if unknown:
        raise ConfigError(f"--only {' '.join(unknown)}: no claim group starts with "
                          f"{'it' if len(unknown) == 1 else 'them'}; groups: {', '.join(GROUPS)}")
    return [name for name in GROUPS if not only or any(name.startswith(o) for o in only)]


def collect(out: Path, only=None, progress=print) -> list[Claim]:
    """Run the claim groups (all, or those whose name starts with one of ``only``).

    Raises
    ------
    stage_sim.config.ConfigError
        An entry of ``only`` that starts no group's name (the message lists the groups).
    """
    claims: list[Claim] = []
    for name in selected_groups(only):
        t0 = time.perf_counter()
        module = importlib.import_module(f"{__name__}.{name}")
        group = module.claims(out)
        claims.extend(group)
        progress(f"[paper] {name}: {sum(c.agrees for c in group)}/{len(group)} claims agree "
                 f"({time.perf_counter() - t0:.1f} s)")
    return claims


def run_paper(out="out/paper", as_json: bool = False, only=None, overwrite: bool = False) -> int:
    """Run every claim group; print the table (or JSON); write claims.md/json and plots
    (:mod:`experiment_runner.core.outputs`: ``overwrite`` lets ``out`` be a folder nanostage did not write)."""
    selected_groups(only)                  # a bad --only is refused before anything is written
    out = outputs.prepare_folder(out, overwrite, files=("claims.json", "claims.md"), option="--out")
    import sys
    claims = collect(out, only, progress=lambda m: print(m, file=sys.stderr, flush=True))
    data = [asdict(c) for c in claims]
    outputs.write_text(out / "claims.json", json.dumps(data, indent=2, default=float))
    outputs.write_text(out / "claims.md", "# Seed simulation claims reproduced by nanostage\n\n" + _markdown(claims))
    if as_json:
        print(json.dumps(data, indent=2, default=float))
    else:
        print(_table(claims))
        print(f"\n{sum(c.agrees for c in claims)}/{len(claims)} claims agree; "
              f"table and plots in {out}/ (claims.md, *.png)")
    return 0
