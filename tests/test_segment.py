"""Segmentation against the simulator's truth (never read by the segmenter)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import AeromagError
from pipeline.io.reader import read_flight
from pipeline.products.channels import segment_channel
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.conftest import FIXTURES, run_sim


def truth_labels(sim, flight):
    """Per-epoch truth label and manoeuvre from the truth document's segment intervals."""
    t = (flight.time_ns - sim.start_ns) / 1e9
    lab = np.full(t.size, "transit", dtype=object)
    man = np.full(t.size, "", dtype=object)
    for s in sim.truth["segments"]:
        m = (t >= s["start_s"]) & (t < s["end_s"])
        lab[m] = s["label"]
        man[m] = s["manoeuvre"] if s["label"] == "calibration" else ""
    return lab, man


def three_class(lab):
    return np.where(np.isin(lab, ["calibration", "survey"]), lab, "other")


@pytest.fixture(
    scope="module",
    params=[("uav-small", 1), ("uav-small", 2), ("fixed-wing", 1), ("calibration-only", 3)],
    ids=lambda p: f"{p[0]}-{p[1]}",
)
def segmented(request, tmp_path_factory):
    name, seed = request.param
    sim = run_sim(name, seed)
    path = write_simulation(sim, tmp_path_factory.mktemp("seg") / f"{name}.mcap")
    flight = read_flight(path)
    return sim, flight, segment_flight(flight)


def test_calibration_vs_survey_vs_other_at_least_98_percent(segmented):
    sim, flight, seg = segmented
    lab, _ = truth_labels(sim, flight)
    assert seg.source == "inferred"
    acc = np.mean(three_class(seg.label) == three_class(lab))
    assert acc >= 0.98, acc
    # the finer labels too, on this kind of flight
    assert np.mean(seg.label == lab) >= 0.97


def test_calibration_boxes_are_the_12_of_each_pass(segmented):
    sim, flight, seg = segmented
    passes = int(sim.scenario["calibration"]["passes"])
    boxes = seg.boxes()
    assert len(boxes) == 12 * passes
    assert {(b.cardinal, b.manoeuvre) for b in boxes} == {
        (c, m) for c in "NESW" for m in ("roll", "pitch", "yaw")
    }
    lab, man = truth_labels(sim, flight)
    both = (lab == "calibration") & (seg.label == "calibration")
    # boundaries move by a second or two; the boxes' cores agree
    assert np.mean(seg.manoeuvre[both] == man[both]) >= 0.8


def test_survey_lines_are_numbered_across_the_block(segmented):
    sim, flight, seg = segmented
    n_lines = sum(1 for s in sim.truth["segments"] if s["label"] == "survey")
    ids = {i for i in seg.line_id[seg.mask("survey")]}
    assert len(ids) == n_lines
    for lid in ids:
        h = seg.heading_deg[seg.line_id == lid]
        line_heading = sim.scenario["survey"]["line_heading_deg"]
        assert (
            min(
                abs(((h[0] - line_heading) + 180) % 360 - 180),
                abs(((h[0] - line_heading - 180) + 180) % 360 - 180),
            )
            < 2.0
        )


def test_plan_markers_are_used_when_present(tmp_path):
    sim = run_sim("uav-small", 5, ["sensors.plan_markers=true"])
    flight = read_flight(write_simulation(sim, tmp_path / "plan.mcap"))
    seg = segment_flight(flight)
    lab, _ = truth_labels(sim, flight)
    assert seg.source == "plan"
    assert np.mean(seg.label == lab) > 0.995  # only the sub-sample offset of marker times
    assert len(seg.boxes()) == 12


def test_segment_channel_marks_each_change(segmented):
    _sim, flight, seg = segmented
    ch = segment_channel(flight, seg)
    keys = [(p["label"], p["line_id"], p["manoeuvre"]) for _t, p in ch.messages]
    assert len(ch.messages) == len(seg.changes()) > 10
    assert all(a != b for a, b in zip(keys[:-1], keys[1:], strict=True))
    times = [t for t, _p in ch.messages]
    assert times == sorted(times) and times[0] == int(flight.time_ns[0])
    assert all(p["heading_deg"] is None or 0 <= p["heading_deg"] < 360 for _t, p in ch.messages)


def test_without_gnss_or_plan_a_clear_error():
    flight = read_flight(FIXTURES / "box_scalar_vector_only.mcap")
    with pytest.raises(AeromagError, match="/gnss/fix: segmentation needs /gnss/fix"):
        segment_flight(flight)


def _short_block(tmp_path, heading_order: str, box_centre_m: float, seed: int):
    """A short UAV block (five 400 m N-S lines, three 200 m E-W ties, two calibration
    passes, the box centred at ``box_centre_m`` east and north): the simulation, its
    flight read back and that flight's segmentation."""
    from pipeline.simulate import Scenario, simulate

    sc = Scenario.load(
        "uav-small",
        [
            "calibration.passes=2",
            f'calibration.heading_order="{heading_order}"',
            "survey.length_m=400.0",
            "survey.width_m=200.0",
            "survey.line_spacing_m=50.0",
            "survey.tie_spacing_m=150.0",
            "survey.validation=false",
            "survey.enabled=true",
            f"calibration.centre_east_m={box_centre_m!r}",
            f"calibration.centre_north_m={box_centre_m!r}",
            "flight.transit_s=10.0",
        ],
    )
    sim = simulate(sc, seed)
    flight = read_flight(write_simulation(sim, tmp_path / "block.mcap"))
    return sim, flight, segment_flight(flight)


def test_survey_found_when_transits_and_ties_outlength_the_lines(tmp_path):
    """A short UAV block (five 400 m N-S lines, three 200 m E-W ties) reached by long E-W
    transits: E-W carries more length than N-S, yet the survey runs N-S (found by the most
    lines on a grid, not the most length)."""
    sim, flight, seg = _short_block(tmp_path, "ESWN", -250.0, 3)
    lab, _ = truth_labels(sim, flight)
    for kind in ("survey", "tie"):
        truth = lab == kind
        assert np.mean(seg.label[truth] == kind) > 0.9, kind


def test_survey_found_among_many_longer_transit_directions(tmp_path):
    """The same short block with the calibration box 2.8 km away: the transits there and
    back, and the straights between the box's legs, run in four directions other than the
    lines', each carrying more length than the five 400 m lines. Every direction is tried,
    so the block is still the one with the most lines on a grid."""
    sim, flight, seg = _short_block(tmp_path, "ENWS", -2000.0, 10)
    lab, _ = truth_labels(sim, flight)
    for kind in ("survey", "tie"):
        truth = lab == kind
        assert np.mean(seg.label[truth] == kind) > 0.9, kind
    # nothing else is a survey line (a line end's sub-second refinement aside)
    assert np.mean(~np.isin(lab[seg.mask("survey")], ["survey", "turn"])) < 0.01


def test_a_leg_across_the_block_at_another_height_is_no_tie(tmp_path):
    """A straight leg that crosses the block like a tie but is flown far above the survey
    lines (a transit climbing to a calibration box at another height) reads a different
    field: its crossovers would compare the anomaly at two heights. It is not a tie; the
    ties flown at the lines' height stay ties, also when every line follows terrain (a
    drape of +-30 m); a line entered in a descent along its track keeps its level part."""
    sim, flight, seg = _short_block(tmp_path, "ESWN", -250.0, 3)
    ties = sorted(set(seg.line_id[seg.mask("tie")]))
    assert len(ties) >= 3
    d = flight.data
    t = d["time_s"].to_numpy()
    # a drape: the altitude follows a smooth terrain along the whole flight
    d["alt_m"] = d["alt_m"].to_numpy() + 30.0 * np.sin(2 * np.pi * t / 97.0)
    assert sorted(set(segment_flight(flight).line_id[seg.mask("tie")])) == ties
    # one tie flown 600 m higher: no longer a tie, nor any other line of the block (the
    # lines are named again by position)
    high = seg.line_id == ties[1]
    d.loc[high, "alt_m"] = d.loc[high, "alt_m"] + 600.0
    again = segment_flight(flight)
    assert np.array_equal(again.mask("tie"), seg.mask("tie") & ~high)
    assert not np.any(again.mask("survey", "tie", "validation")[high])
    # the survey lines are untouched
    assert np.array_equal(again.mask("survey"), seg.mask("survey"))
    # a descent along a survey line's track into its first 40 %: the line keeps the rest
    # (to within a second of refinement), the descent is no line
    lines = sorted(set(seg.line_id[seg.mask("survey")]))
    ix = np.flatnonzero(seg.line_id == lines[2])
    cut = ix[: int(0.4 * ix.size)]
    d.loc[cut, "alt_m"] = d.loc[cut, "alt_m"] + np.linspace(600.0, 300.0, cut.size)
    third = segment_flight(flight)
    assert not np.any(third.mask("survey", "tie", "validation")[cut])
    kept = ix[int(0.4 * ix.size) :]
    rate = 1.0 / float(np.median(np.diff(t)))
    assert np.sum(third.mask("survey")[kept]) >= kept.size - rate


def _leg_with_turns(heading_deg: float, lead_turn: bool, trail_turn: bool):
    """A 100 s leg at 10 Hz flown at ``heading_deg`` with 5 deg yaw swings in its last
    third, optionally entered and left by an 80 deg turn in place (a hovering multicopter:
    the position stays on the line, only the heading swings)."""
    from types import SimpleNamespace

    import pandas as pd

    from pipeline.segment.segmenter import _Leg

    t = np.arange(0.0, 100.0, 0.1)
    dev = np.where((t > 60) & (t < 90), 5.0 * np.sin(2 * np.pi * (t - 60) / 5.0), 0.0)
    if trail_turn:
        dev = np.where(t >= 95.0, 80.0 * np.clip((t - 95.0) / 4.0, 0, 1), dev)
    if lead_turn:
        dev = np.where(t < 5.0, -80.0 * np.clip((5.0 - t) / 4.0, 0, 1), dev)
    yaw = (heading_deg + dev) % 360.0
    flight = SimpleNamespace(data=pd.DataFrame({"yaw_deg": yaw}))
    return flight, _Leg(0, t.size - 1, heading_deg), t


@pytest.mark.parametrize("heading_deg", [0.0, 270.0, 128.0])
def test_a_turn_in_place_at_a_legs_end_is_not_part_of_the_leg(heading_deg):
    # the track cannot end the leg (the position does not move), the heading does: cut back
    # to where the turn began; the yaw swings of the box stay in the leg, and a heading near
    # north (0/360) is no turn
    from pipeline.segment.segmenter import SegmentParams, _without_turns_in_place

    p = SegmentParams()
    flight, leg, t = _leg_with_turns(heading_deg, lead_turn=True, trail_turn=True)
    cut = _without_turns_in_place(flight, leg, t, p)
    assert 94.0 <= t[cut.i1] <= 95.0 and 5.0 <= t[cut.i0] <= 6.0
    flight, leg, t = _leg_with_turns(heading_deg, lead_turn=False, trail_turn=False)
    kept = _without_turns_in_place(flight, leg, t, p)
    assert (kept.i0, kept.i1) == (leg.i0, leg.i1)


def test_a_box_ended_by_a_hover_turn_keeps_its_yaw_manoeuvre():
    # an independent generator's multicopter box: its last leg runs on into a deceleration
    # and a turn in place; the turn's 80 deg ramp had set the yaw axis' scale and the leg's
    # 5 deg yaw block was labelled steady ("manoeuvre(s) not flown: W-yaw")
    from tests.recordings import INDEPENDENT

    path = INDEPENDENT / "realism_none.mcap"
    if not path.exists():
        pytest.skip(f"{path} absent")
    seg = segment_flight(read_flight(path))
    found = {(b.cardinal, b.manoeuvre) for b in seg.boxes()}
    assert found == {(c, m) for c in "NESW" for m in ("roll", "pitch", "yaw")}
