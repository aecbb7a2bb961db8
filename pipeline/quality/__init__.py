"""Survey quality: heading error at overlap points, map interpolation, crossovers, QC."""

from pipeline.quality.overlap import (
    OverlapSet,
    Track,
    group_stats,
    overlap_pairs,
    track_intersections,
)
from pipeline.quality.stage import QualityRun, QualitySettings, run_quality

__all__ = [
    "OverlapSet",
    "QualityRun",
    "QualitySettings",
    "Track",
    "group_stats",
    "overlap_pairs",
    "run_quality",
    "track_intersections",
]
