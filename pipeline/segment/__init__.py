"""Segmentation: which part of the flight is calibration, survey, tie, validation, turn, transit."""

from pipeline.segment.segmenter import (
    LABELS,
    MANOEUVRES,
    Box,
    Segmentation,
    SegmentParams,
    segment_flight,
)

__all__ = ["LABELS", "MANOEUVRES", "Box", "SegmentParams", "Segmentation", "segment_flight"]
