"""Frames, reference field and map projections."""

from pipeline.geo.frames import attitude_rotation, body_to_ned, ned_to_body
from pipeline.geo.igrf import igrf_ned_nT, main_field_direction
from pipeline.geo.local import LocalFrame
from pipeline.geo.projected import GridFrame, survey_frame, utm_epsg

__all__ = [
    "GridFrame",
    "LocalFrame",
    "attitude_rotation",
    "body_to_ned",
    "igrf_ned_nT",
    "main_field_direction",
    "ned_to_body",
    "survey_frame",
    "utm_epsg",
]
