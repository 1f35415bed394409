"""Campaigns: the seed's comparison tables as YAML files (``*.yaml`` here), calibrated, run and reported.

Modules, from the bottom up (each imports only those above it in this list; enforced by
``.importlinter``):

========================  =====================================================================
``registry``              the metric table: label, unit, formatter
``spec``                  the campaign model (assembling the kinds' test schemas), load / list,
                          conditions, the presets of every case
``schema``                the test schema of each kind, ``schema/<kind>.py``; ``schema/common.py``
``overrides``             dotted-path preset overrides (wildcards, set, scale, series_scale)
``base``                  run settings, run results, the ``CampaignKind`` protocol
``trials``                the one place trials are built, simulated and judged; Step II learning
``stream``                trial chunks on an executor, streamed to ``trials.jsonl``, resumable
``findings``              the seed's findings in the simulation
``mechanism``             why a point-to-point trial settles as it does
``calibration``           the baseline fit
``report``                report.md and plots (the parts shared by kinds)
``graph_runs``            representative trials through the ROS 2 graph
``trial_run``             running a trial campaign (calibrate, learn, simulate, judge, write)
``frf``                   frequency responses of a case (open-loop plant FRF, loops)
``trial_kinds``           the point-to-point and circle kinds
``frequency_response``    the frequency-response kind
``kinds``                 ``test.kind`` -> its kind
``runner``                ``run_campaign``, ``main_job``
``cli``                   ``nanostage campaign``
========================  =====================================================================
"""
