"""``nanostage`` command line: one entry point, one subcommand per job.

Bad input has one path: a command raises one of :data:`experiment_runner.core.errors.USER_ERRORS` (a
configuration, recording, design or missing-data error naming the file, field, value and what is allowed) or
exits with a message (``SystemExit("...")``); :func:`main` prints ``nanostage COMMAND: message``
and returns 2, never a traceback. Bad arguments are argparse's one-line error (exit 2). SIGINT
and SIGTERM end a command like an error (:func:`experiment_runner.core.outputs.interrupts_as_errors`):
one line, exit 128 + the signal number.

Only the module of the command being run is imported (its arguments and entry point): a
command starts in what its own imports take (``nanostage presets`` in a fraction of a second,
not the seconds that the simulator, the diagnosis and the plotting stack take to import).
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import os
import signal
import sys

from experiment_runner.core.errors import USER_ERRORS, ConfigError
from experiment_runner.core.outputs import add_overwrite_argument, interrupts_as_errors


def _paper(args):
    from experiment_runner.apps.paper import run_paper
    return run_paper(out=args.out, as_json=args.json, only=args.only, overwrite=args.overwrite)


def _bench(args):
    from experiment_runner.apps.bench import run_bench
    return run_bench(as_json=args.json, quick=args.quick, graph=args.graph, main_job=args.main_job)


def _graph(args):
    from experiment_runner.core.experiment import list_experiments, load_experiment
    if args.list:
        for name in list_experiments():
            print(f"{name:20s} {load_experiment(name).description}")
        return 0
    if not args.experiment:
        raise ConfigError("give an EXPERIMENT (name or YAML path), or --list")
    from pathlib import Path

    from experiment_runner.apps.graph import run_graph
    return run_graph(args.experiment, Path(args.out), processes=args.processes, domain_id=args.domain_id,
                     timeout=args.timeout, overwrite=args.overwrite)


def _presets(args):
    from stage_sim.config import list_presets, load_preset
    if args.name:
        print(load_preset(args.name).model_dump_json(indent=2))
    else:
        for name in list_presets():
            print(f"{name:24s} {load_preset(name).description.splitlines()[0] if load_preset(name).description else ''}")
    return 0


MODULE_COMMANDS = [
    # subcommands whose arguments and entry point live in their module:
    # (name, help, module, add-arguments function, entry function)
    ("replay", "republish a recording on its topics with /clock (like ros2 bag play)",
     "experiment_runner.apps.replay", "add_replay_arguments", "main_replay"),
    ("campaign", "the seed's experiments as campaigns: calibrate, simulate, report",
     "experiment_runner.apps.campaigns.cli", "add_campaign_arguments", "main_campaign"),
    ("diagnose", "locate, name and fit what a nominal model misses in a recording",
     "experiment_runner.apps.diagnosis.cli", "add_diagnose_arguments", "main_diagnose"),
    ("synth", "simulate an experiment on a concealed truth into a recording",
     "experiment_runner.apps.diagnosis.synth", "add_synth_arguments", "main_synth"),
    ("convert", "import a table (CSV/text, MATLAB .mat, HDF5, .npz) or the EMPS benchmark as a recording",
     "experiment_runner.core.tabular", "add_convert_arguments", "main_convert"),
    ("realdata", "run the diagnosis on the real data sets of ../shared/data; report",
     "experiment_runner.apps.diagnosis.realdata", "add_realdata_arguments", "main_realdata"),
    ("design", "FI design advisor (Ch. 6) or VAN piezo power / flexure fatigue check (Sec. 3.3)",
     "experiment_runner.apps.design.cli", "add_design_arguments", "main_design"),
]


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The ``nanostage`` parser; with ``command`` (the one :func:`main` runs), only that
    subcommand's module is imported: the others are listed with their help only."""
    parser = argparse.ArgumentParser(prog="nanostage", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("paper", help="reproduce the seed's simulation results: claim | seed | ours | agrees")
    p.add_argument("--json", action="store_true", help="print the claims as JSON")
    p.add_argument("--out", default="out/paper", help="folder for plots and the Markdown table")
    p.add_argument("--only", nargs="*", default=None, help="run only the claim groups whose name starts with these "
                   "(e.g. appendix_a fi_design; a name no group has is refused, listing them)")
    add_overwrite_argument(p)
    p.set_defaults(func=_paper)

    p = sub.add_parser("bench", help="benchmark the simulation core (simulated s per wall s, memory)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="shorter runs")
    p.add_argument("--graph", action=argparse.BooleanOptionalAction, default=True,
                   help="also time the ROS 2 node graph (one process, one per node) and raw rclpy "
                        "round trips (default: on)")
    p.add_argument("--main-job", action="store_true",
                   help="also time the main job (nanostage campaign --main, about 2 minutes)")
    p.set_defaults(func=_bench)

    p = sub.add_parser("graph", help="run an experiment through the ROS 2 node graph and record it to MCAP")
    p.add_argument("experiment", nargs="?", help="experiment name (see --list) or YAML path")
    p.add_argument("--out", default="out/graph", help="output folder (run.mcap is written there)")
    p.add_argument("--processes", action="store_true", help="one process per node (default: one process)")
    add_overwrite_argument(p)
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID (default: env or 42)")
    p.add_argument("--timeout", type=float, default=3600.0, help="give up after this many seconds")
    p.add_argument("--list", action="store_true", help="list the shipped experiments")
    p.set_defaults(func=_graph)

    for name, help_, module, add_arguments, entry in MODULE_COMMANDS:
        p = sub.add_parser(name, help=help_)
        if command is None or command == name:          # never parsed otherwise: main passes the command run
            mod = importlib.import_module(module)
            getattr(mod, add_arguments)(p)
            p.set_defaults(func=getattr(mod, entry))

    p = sub.add_parser("presets", help="list the stage presets, or show one")
    p.add_argument("name", nargs="?")
    p.set_defaults(func=_presets)
    return parser


@contextlib.contextmanager
def python_only_stdout(enabled: bool):
    """With ``enabled`` (a ``--json`` run): stdout carries only what Python prints.

    Compiled libraries write diagnostics straight to file descriptor 1 (LAPACK's "On entry to
    DLASCL parameter number 4 had an illegal value" when a numerical routine meets a NaN, in
    this process or in worker processes, which inherit it), which would break the JSON a reader
    parses. Descriptor 1 is pointed at stderr for the command's duration; ``sys.stdout`` keeps
    writing to the real standard output.
    """
    if not enabled:
        yield
        return
    sys.stdout.flush()
    try:
        direct = sys.stdout.fileno() == 1           # else Python's stdout is elsewhere (a capture)
    except (AttributeError, OSError, ValueError):
        direct = False
    real = os.dup(1)
    os.dup2(2, 1)
    saved = sys.stdout
    if direct:
        sys.stdout = io.TextIOWrapper(os.fdopen(real, "wb", closefd=False),
                                      encoding=saved.encoding or "utf-8", line_buffering=True)
    try:
        yield
    finally:
        sys.stdout.flush()
        sys.stdout = saved
        os.dup2(real, 1)
        os.close(real)


def main(argv=None) -> int:
    """Run one ``nanostage`` subcommand; bad input prints its message (exit 2, see the module docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    args = build_parser(command).parse_args(argv)
    prefix = f"nanostage {args.command}: "
    try:
        with interrupts_as_errors(), python_only_stdout(bool(getattr(args, "json", False))):
            return int(args.func(args) or 0)
    except KeyboardInterrupt as err:              # SIGINT / SIGTERM: temporaries are gone, as on an error
        signum = getattr(err, "signum", signal.SIGINT)
        print(f"{prefix}interrupted ({signal.Signals(signum).name}); temporary files removed", file=sys.stderr)
        return 128 + signum
    except SystemExit as err:
        if not isinstance(err.code, str):          # an exit status (argparse's is 2): keep it
            raise
        print(err.code if err.code.startswith(prefix) else prefix + err.code, file=sys.stderr)
        return 2
    except BrokenPipeError:
        # the reader of our output went away (``nanostage presets | head``): not an error of ours;
        # point stdout at devnull so the interpreter's final flush does not fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141                        # 128 + SIGPIPE, as a shell reports it
    except Exception as err:
        if not isinstance(err, USER_ERRORS):
            raise
        print(f"{prefix}{err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
