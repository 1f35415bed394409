"""The campaign kinds, listed once: ``test.kind`` -> its :class:`~experiment_runner.apps.campaigns.base.CampaignKind`.

To add a kind, see :class:`~experiment_runner.apps.campaigns.base.CampaignKind`.

Examples
--------
>>> sorted(KINDS)
['circle', 'frequency_response', 'point_to_point']
"""
from __future__ import annotations

import typing

from experiment_runner.apps.campaigns.base import CampaignKind
from experiment_runner.apps.campaigns.frequency_response import FREQUENCY_RESPONSE
from experiment_runner.apps.campaigns.spec import Campaign, Test
from experiment_runner.apps.campaigns.trial_kinds import CIRCLE, POINT_TO_POINT

__all__ = ["KINDS", "kind_of", "schemas"]

KINDS: dict[str, CampaignKind] = {k.name: k for k in (POINT_TO_POINT, CIRCLE, FREQUENCY_RESPONSE)}


def schemas() -> tuple:
    """The test schema classes of the campaign file's ``test`` union.

    Returns
    -------
    tuple of type
        The pydantic classes of :mod:`~experiment_runner.apps.campaigns.schema` (the ``Test`` union of
        :mod:`~experiment_runner.apps.campaigns.spec`); each has its kind in :data:`KINDS`.
    """
    return typing.get_args(typing.get_args(Test)[0])


def kind_of(camp: Campaign) -> CampaignKind:
    """The kind of a campaign (its ``test.kind``).

    Parameters
    ----------
    camp : Campaign
        The campaign.

    Returns
    -------
    CampaignKind
        Its entry in :data:`KINDS`.
    """
    return KINDS[camp.test.kind]
