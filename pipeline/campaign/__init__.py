"""Campaigns: several processed sorties over one area, levelled jointly and gridded once.

:mod:`~pipeline.campaign.sorties` finds and checks the processed recordings and reads their
levelled line data (``/map/lines``, ``/map/frame``) into one common local frame;
:mod:`~pipeline.campaign.joint` finds the crossovers within and between flights and levels
every line and flight jointly (sparse least squares); :mod:`~pipeline.campaign.stage` grids the
result and :mod:`~pipeline.campaign.outputs` writes ``campaign.mcap``, the summary and the
report.
"""

from __future__ import annotations

__all__ = [
    "CampaignRun",
    "JointLeveling",
    "Sortie",
    "SortieInfo",
    "campaign_frame",
    "level_jointly",
    "read_sortie",
    "run_campaign",
    "sortie_crossovers",
    "validate_campaign",
]


def __getattr__(name: str):
    if name in ("Sortie", "SortieInfo", "campaign_frame", "read_sortie", "validate_campaign"):
        from pipeline.campaign import sorties

        return getattr(sorties, name)
    if name in ("JointLeveling", "level_jointly", "sortie_crossovers"):
        from pipeline.campaign import joint

        return getattr(joint, name)
    if name in ("CampaignRun", "run_campaign"):
        from pipeline.campaign import stage

        return getattr(stage, name)
    raise AttributeError(name)
