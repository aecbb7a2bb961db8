"""The survey lines' direction as an axis: north-south lines flown both ways have headings
on both sides of 0/180 deg, whose median taken mod 180 can come out east-west (then the
line spacing, the map's cell and its mask collapse)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.conftest import run_sim


def test_north_south_lines_at_5_hz_keep_their_spacing(tmp_path):
    """A small north-south survey (50 m spacing) sampled at 5 Hz: the map's line spacing and
    cell are those of the lines, not a fraction of a metre."""
    from pipeline.io.reader import read_flight
    from pipeline.maps.stage import MapSettings, anomaly_grid
    from pipeline.segment import segment_flight
    from pipeline.simulate import write_simulation

    small = ["survey.length_m=400", "survey.width_m=150", "survey.tie_spacing_m=400"]
    sim = run_sim("uav-small", 1, [*small, "calibration.cycles=2", "sensors.scalar_rate_hz=5"])
    flight = read_flight(write_simulation(sim, tmp_path / "f.mcap"))
    seg = segment_flight(flight)
    gm = anomaly_grid(flight, seg, flight.data["scalar_nT"].to_numpy(float), MapSettings())
    assert gm.spacing_m == pytest.approx(50.0, rel=0.05)
    assert gm.grid.cell_m == pytest.approx(12.5, rel=0.05)


def test_a_campaigns_north_south_lines_have_their_spacing():
    """Campaign merging measures the lines' axis and spacing the same way: lines tilted
    0.2 deg either side of north, 100 m apart."""
    from pipeline.campaign.sorties import line_spacing_m
    from pipeline.maps.level import Line

    lines, kinds = [], {}
    for k in range(6):
        tilt = np.radians(0.2 if k % 2 else -0.2)
        n = np.linspace(0.0, 1000.0, 200)
        e = 100.0 * k + (n - 500.0) * np.tan(tilt)
        lid = f"L{k}"
        t = np.linspace(0.0, 100.0, n.size)
        lines.append(Line(lid, "survey", e, n, t, np.zeros(n.size), np.arange(n.size)))
        kinds[lid] = "survey"
    heading, spacing = line_spacing_m(lines, kinds)
    assert min(heading, 180.0 - heading) < 1.0
    assert spacing == pytest.approx(100.0, rel=0.01)
