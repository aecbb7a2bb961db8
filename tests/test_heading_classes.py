"""Heading classes relative to the flown pattern's direction, not to north."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.compensate.guards import check_calibration
from pipeline.geo.heading import cardinal_name, heading_class, pattern_direction_deg
from pipeline.quality.overlap import heading_sector
from pipeline.segment.segmenter import SegmentParams, _assign_passes, _Leg


@pytest.mark.parametrize("orientation_deg", np.arange(0.0, 360.0, 7.5))
def test_four_legs_get_four_classes_at_any_orientation(orientation_deg):
    rng = np.random.default_rng(int(orientation_deg * 10))
    for _ in range(20):
        legs = orientation_deg + np.array([0.0, 90.0, 180.0, 270.0]) + rng.normal(0, 3.0, 4)
        ref = pattern_direction_deg(legs)
        # the reference is the pattern's offset from north, within the jitter
        off = (ref - orientation_deg + 45.0) % 90.0 - 45.0
        assert abs(off) < 6.0
        assert sorted(heading_class(legs, ref)) == [0, 1, 2, 3]
        assert len({cardinal_name(h, ref) for h in legs}) == 4


def test_north_based_rounding_would_merge_legs_of_a_45_deg_box():
    legs = np.array([44.8, 135.3, 224.7, 315.2])
    # the rule this replaces: two legs share a class, so a pass would be split in two
    assert len(set(np.round(legs / 90.0).astype(int) % 4)) < 4
    assert sorted(heading_class(legs, pattern_direction_deg(legs))) == [0, 1, 2, 3]


def test_a_45_deg_box_is_one_pass_of_four_legs():
    t = np.arange(0.0, 2000.0, 0.1)
    legs = []
    for k, h in enumerate([44.8, 135.3, 224.7, 315.2]):
        i0 = int(k * 4000)
        legs.append(_Leg(i0, i0 + 3000, h, kind="calibration"))
    _assign_passes(legs, t, SegmentParams())
    assert {lg.calibration_pass for lg in legs} == {1}
    assert sorted(lg.cardinal for lg in legs) == ["E", "N", "S", "W"]


def test_guard_sees_every_heading_of_a_45_deg_box():
    rate = 10.0
    y = np.concatenate(
        [np.full(600, h) + np.sin(np.arange(600) / 5.0) for h in (45, 135, 225, 315)]
    )
    t = np.arange(y.size) / rate
    chk = check_calibration("tl18", 10.0, [], t, y, np.ones(y.size, bool), None, min_heading_s=30.0)
    assert sorted(chk.headings_s.values()) == pytest.approx([60.0] * 4)
    assert not any("misses heading" in w for w in chk.warnings)


def test_overlap_sectors_centred_on_the_lines():
    # lines at 22.5 deg (and reciprocals), crossed at 45 deg: every line in one sector
    lines = 22.5 + np.array([0.0, 180.0] * 50) + np.random.default_rng(1).normal(0, 2.0, 100)
    ref = pattern_direction_deg(lines)
    assert len(set(heading_sector(lines, reference_deg=ref))) == 2
    # north-based sectors split them
    assert len(set(heading_sector(lines))) > 2
