"""Command line of the design advisor: ``nanostage design PRESET [--rms NM] [--van] ...``."""
from __future__ import annotations

from pathlib import Path

from experiment_runner.core import outputs
from experiment_runner.core.cliargs import nonnegative_float, nonzero_float, positive_float, positive_int
from experiment_runner.core.errors import DesignError
from experiment_runner.core.executor import add_executor_arguments, default_workers
from stage_sim.config import Preset, with_overrides
from stage_sim.validation import load_yaml

from .advice import advise_isolator
from .report import advice_table, text_table, van_rows, write_report
from .sweep import DWELL, GRIDS, N_TRIALS, STEP, as_preset, lumped_stage
from .van import check_van


def add_design_arguments(parser):
    """Arguments of ``nanostage design`` (wire with ``set_defaults(func=main_design)``)."""
    parser.add_argument("preset", help="preset name or YAML path (FI: bearings on joints; VAN: with dither)")
    parser.add_argument("--rms", type=positive_float, default=None, metavar="NM",
                        help="required RMS in-position error [nm] (FI sweep)")
    parser.add_argument("--van", action="store_true",
                        help="VAN check (piezo power, flexure fatigue); default: automatic when the preset dithers")
    parser.add_argument("--out", default=None, help="output folder (default out/design/PRESET)")
    parser.add_argument("--json", action="store_true", help="print design.json instead of the table")
    parser.add_argument("--grid", choices=sorted(GRIDS), default="default", help="k_fi x c_fi grid")
    parser.add_argument("--step-um", type=nonzero_float, default=STEP * 1e6, help="point-to-point step [µm]")
    parser.add_argument("--trials", type=positive_int, default=N_TRIALS, help="trials per grid point")
    parser.add_argument("--dwell", type=positive_float, default=DWELL, help="settling portion after each move [s]")
    parser.add_argument("--vpp", type=nonnegative_float, default=None,
                        help="VAN piezo voltage p-p [V] (default: from the dither force)")
    parser.add_argument("--set", action="append", default=[], metavar="PATH=VALUE",
                        help="preset override, e.g. stage.drive.noise_current_rms=7e-4 (YAML value; repeatable)")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    outputs.add_overwrite_argument(parser)
    add_executor_arguments(parser, "sweep", default_workers(), "default: one per core; 1 = this process")
    return parser


def _overridden(p: Preset, sets) -> Preset:
    """Apply ``PATH=VALUE`` overrides (VALUE parsed as YAML) to a preset."""
    over = {}
    for item in sets:
        path, eq, value = item.partition("=")
        if not eq or not path:
            raise DesignError(f"--set {item!r}: expected PATH=VALUE")
        over[path.strip()] = load_yaml(value, f"--set {item!r}: value")     # ConfigError if not YAML
    return with_overrides(p, over, "nanostage design --set") if over else p   # ConfigError names a bad path or value


def main_design(args) -> int:
    """Run ``nanostage design``: 0 = a design meets the requirement / VAN passes, 1 = none does /
    VAN fails; bad input raises :class:`DesignError` / ``ConfigError`` (the CLI's message, exit 2)."""
    import sys
    p = _overridden(as_preset(args.preset), args.set)
    van_mode = args.van or p.dither is not None
    if not van_mode:
        if args.rms is None:
            raise DesignError("give the required RMS in-position error: --rms NM")
        lumped_stage(p)
    out = outputs.prepare_folder(args.out or f"out/design/{p.name}", args.overwrite,
                                 files=("design.md", "design.json"), option="--out")          # refused before the sweep
    progress = None if args.json else (lambda s: print(s, file=sys.stderr))
    advice = van = None
    if van_mode:
        if args.rms is not None:
            print("nanostage design: --rms is not used by the VAN check", file=sys.stderr)
        van = check_van(p, v_pp=args.vpp)
    else:
        advice = advise_isolator(p, args.rms * 1e-9, step=args.step_um * 1e-6, grid=args.grid,
                                 n_trials=args.trials, dwell=args.dwell, progress=progress,
                                 workers=args.workers, cluster=args.cluster)
    files = write_report(out, advice, van, plots=not args.no_plots, overrides=args.set)
    if args.json:
        print(Path(files["json"]).read_text())
    else:
        if advice is not None:
            print(text_table(advice_table(advice)))
            print(advice.message)
        if van is not None:
            print(text_table(van_rows(van)))
            print(van.message)
        print(f"report: {files['markdown']}")
    ok = (advice is None or advice.ok) and (van is None or van.passed)
    return 0 if ok else 1
