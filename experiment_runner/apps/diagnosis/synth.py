"""``nanostage synth TRUTH.yaml EXPERIMENT.yaml --out REC.mcap``: a concealed-truth recording.

TRUTH is a preset (name or YAML path) -- typically the nominal preset with one or more
effects (every effect of the library is a preset field) -- or a model file ``{preset: ...}``.
EXPERIMENT is an experiment (name or YAML path, :mod:`experiment_runner.core.experiment`): its
profile, trials, start positions and window are used with the TRUTH instead of the
experiment's own ``preset`` (the experiment's ``overrides`` are applied to the truth).

The recording is a contract recording written by
:func:`experiment_runner.core.recording.write_run`; the truth is *concealed*: no
``/stage/truth`` topic and an ``/experiment/config`` without the preset (only the run's
case, rate and trial layout), so a diagnosis can only use what a rig would give: besides the
three hardware topics, ``/stage/dither`` (piezo drive forces) on dither stages and
``/stage/isolator`` (solenoid command) on SAI stages, which a rig's controller knows too.
Drive noise and quantization are whatever the truth preset says.
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import yaml

from experiment_runner.core.batch import simulate
from experiment_runner.core.cliargs import positive_int
from experiment_runner.core.experiment import build_trials, load_experiment, reference
from experiment_runner.core.outputs import add_overwrite_argument, check_recording
from experiment_runner.core.recording import bag_layout, write_run
from stage_sim.config import with_overrides

from .model import load_model

__all__ = ["synth", "add_synth_arguments", "main_synth"]


def synth(truth, experiment, out, *, seed: int | None = None, trials: int | None = None, conceal: bool = True,
          overwrite: bool = True) -> Path:
    """Simulate ``experiment`` on ``truth`` and write the recording; returns the MCAP path.

    The recording is written whole and moved into place (:mod:`experiment_runner.core.outputs`); an
    existing one at ``out`` is replaced only with ``overwrite`` (refused before the simulation).

    Parameters
    ----------
    truth : str, pathlib.Path, dict or ModelSpec
        The concealed truth (:func:`.model.load_model`).
    experiment : str or pathlib.Path
        The experiment file (:mod:`experiment_runner.core.experiment`).
    out : str or pathlib.Path
        The recording to write.
    seed : int, optional
        Noise seed (default the truth's ``simulation.seed``).
    trials : int, optional
        Trials (default the experiment's).
    conceal : bool, optional
        Do not record the truth in the recording's ``/experiment/config``.
    overwrite : bool, optional
        Replace an existing recording at ``out``.

    Returns
    -------
    pathlib.Path
    """
    check_recording(bag_layout(out)[0], overwrite)
    spec = load_model(truth)
    exp = load_experiment(experiment)
    if trials is not None:
        exp = exp.model_copy(update={"trials": int(trials)})
    preset = with_overrides(spec.preset, exp.overrides) if exp.overrides else spec.preset
    if seed is not None:
        preset = with_overrides(preset, {"simulation.seed": int(seed)})
    tr = build_trials(exp, preset)
    rate = preset.controller.rate
    x_ref = np.stack([t.x_ref for t in tr])
    v_ref = np.stack([t.v_ref for t in tr])
    seeds = np.array([t.seed for t in tr])
    res = simulate(preset, x_ref, v_ref, seeds=seeds, check=False)
    ref = reference(exp.profile, 1.0 / rate)
    cfg = None
    if conceal:
        cfg = yaml.safe_dump({"recording_contract": 1, "run": {"source": "nanostage synth", "case": exp.name,
                                                               "trials": len(tr), "rate": rate,
                                                               "samples_per_trial": int(x_ref.shape[1]),
                                                               "truth": "concealed"}}, sort_keys=False)
    return write_run(out, res, preset, reference=ref if len(ref.x) == x_ref.shape[1] else None, window=exp.window,
                     case=exp.name, config_yaml=cfg, truth=not conceal, node="synth", overwrite=overwrite)


def add_synth_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the arguments of ``nanostage synth`` (wire with ``set_defaults(func=main_synth)``).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The subcommand's parser.

    Returns
    -------
    argparse.ArgumentParser
        ``parser``.
    """
    parser.add_argument("truth", help="truth preset (name or YAML) or model file {preset}")
    parser.add_argument("experiment", help="experiment (name or YAML): profile, trials, starts")
    parser.add_argument("--out", required=True, help="recording to write (bag directory; NAME.mcap -> NAME/NAME.mcap)")
    add_overwrite_argument(parser)
    parser.add_argument("--seed", type=int, default=None, help="simulation.seed of the truth (noise realisation)")
    parser.add_argument("--trials", type=positive_int, default=None,
                        help="override the experiment's number of trials")
    parser.add_argument("--reveal", action="store_true", help="also record /stage/truth and the preset in "
                                                              "/experiment/config (default: concealed)")
    return parser


def main_synth(args) -> int:
    """Run ``nanostage synth`` from parsed arguments: write the recording, print its path.

    Parameters
    ----------
    args : argparse.Namespace
        As :func:`add_synth_arguments` defines them.

    Returns
    -------
    int
        0 (errors are raised; the CLI turns bad input into one message and exit 2).
    """
    path = synth(args.truth, args.experiment, args.out, seed=args.seed, trials=args.trials, conceal=not args.reveal,
                 overwrite=args.overwrite)
    print(path)
    return 0
