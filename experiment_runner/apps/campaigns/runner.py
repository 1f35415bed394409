"""Run a campaign: :func:`run_campaign` (one campaign, any kind) and :func:`main_job` (the README's first command).

:func:`run_campaign` loads the campaign, applies the :class:`~experiment_runner.apps.campaigns.base.RunSettings`
that change it (``trials``, ``dwell``) and hands it to its kind
(:func:`~experiment_runner.apps.campaigns.kinds.kind_of`), which calibrates, runs and writes
``results.csv``, ``results.json``, ``calibration.json``, ``report.md``, plots and MCAP
recordings to the output folder.
"""
from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

from experiment_runner.apps.campaigns.base import CampaignRun, RunSettings
from experiment_runner.apps.campaigns.frequency_response import frf_lines
from experiment_runner.apps.campaigns.kinds import kind_of
from experiment_runner.apps.campaigns.report import write_index
from experiment_runner.apps.campaigns.spec import Calibration, Campaign, load_campaign
from experiment_runner.core import outputs
from experiment_runner.core.executor import make_executor
from stage_sim.config import ConfigError

__all__ = ["run_campaign", "as_run", "main_job", "MAIN_JOB", "MAIN_JOB_FRF"]

MAIN_JOB = ("table_4_2", "table_5_2")
"""Campaigns of :func:`main_job` (``nanostage campaign --main``)."""
MAIN_JOB_FRF = {"table_4_2": "frf_fi", "table_5_2": "frf_sai"}
"""Frequency-response campaigns the main job runs next to a point-to-point one (Fig. 4.6 next to Table 4.2)."""


def as_run(camp: Campaign, settings: RunSettings) -> Campaign:
    """The campaign with the settings' ``trials`` (the calibration's trials capped to it) and ``dwell``.

    Parameters
    ----------
    camp : Campaign
        The campaign as loaded.
    settings : RunSettings
        Its ``trials`` and ``dwell`` [s] replace the campaign's where given.

    Returns
    -------
    Campaign
        ``camp`` itself when neither is given, else a validated copy.

    Raises
    ------
    stage_sim.config.ConfigError
        ``dwell`` given for a campaign that is not point-to-point.
    """
    if settings.trials is None and settings.dwell is None:
        return camp
    data = camp.model_dump()
    if settings.trials is not None:
        data["trials"] = int(settings.trials)
        if isinstance(camp.calibration, Calibration):
            data["calibration"]["trials"] = min(data["calibration"]["trials"], int(settings.trials))
    if settings.dwell is not None:
        if "dwell" not in type(camp.test).model_fields:
            raise ConfigError(f"--dwell applies to point-to-point campaigns only ({camp.name} is "
                              f"{camp.test.kind})")
        data["test"]["dwell"] = float(settings.dwell)
    return Campaign.model_validate(data)


def run_campaign(campaign, out_dir, settings: RunSettings | None = None, **changes) -> CampaignRun:
    """Run a campaign into ``out_dir`` (created; nanostage's files in it are replaced, a folder
    nanostage did not write needs ``overwrite=True``: :mod:`experiment_runner.core.outputs`).

    Parameters
    ----------
    campaign : str, Path or Campaign
        A shipped campaign's name, a campaign file, or a loaded campaign.
    out_dir : str or pathlib.Path
        Its output folder.
    settings : RunSettings, optional
        How to run it (default ``RunSettings()``: as ``nanostage campaign NAME``).
    **changes
        Fields of ``settings`` to change, e.g. ``trials=4, plots=False``.

    Returns
    -------
    CampaignRun
    """
    settings = replace(settings or RunSettings(), **changes)
    camp = campaign if isinstance(campaign, Campaign) else load_campaign(campaign)
    camp = as_run(camp, settings)
    return kind_of(camp).run(camp, Path(out_dir), settings)


def main_job(out_dir="out/campaigns", settings: RunSettings | None = None, **changes) -> Path:
    """Tables 4.2 and 5.2 end to end (``nanostage campaign --main``).

    Calibration, all trials on the batch engine, one representative trial per case and step
    size through the ROS graph (``graph=True`` unless changed), and the frequency responses of
    the same stages; writes ``out_dir/<campaign>/...``, the headline ratios
    ``out_dir/headline.json`` and the summary ``out_dir/report.md``.

    Parameters
    ----------
    out_dir : str or pathlib.Path
        Output folder (:func:`experiment_runner.core.outputs.prepare_folder`).
    settings : RunSettings, optional
        How to run (default ``RunSettings(graph=True)``); one pool of workers serves every campaign.
    **changes
        Fields of ``settings`` to change.

    Returns
    -------
    pathlib.Path
        The summary ``report.md``.
    """
    t0 = time.monotonic()
    settings = replace(settings or RunSettings(graph=True), **changes)
    out_dir = outputs.prepare_folder(out_dir, settings.overwrite, option="--out")
    with make_executor(settings.workers, settings.cluster) as ex:      # one pool, warmed once, for all
        runs = [run_campaign(name, out_dir / name, settings, executor=ex) for name in MAIN_JOB]
    extras = {}
    for cr in runs:
        if cr.campaign.name in MAIN_JOB_FRF:
            name = MAIN_JOB_FRF[cr.campaign.name]
            frf = run_campaign(name, out_dir / name, progress=settings.progress, overwrite=settings.overwrite)
            extras[cr.campaign.name] = frf_lines(frf, cr, images=f"{name}/plots")
    return write_index(runs, out_dir, time.monotonic() - t0, extras)
