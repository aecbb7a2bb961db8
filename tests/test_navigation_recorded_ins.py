"""Navigation with the recording's own INS (/ins/solution): its errors are what the record
says, not a simulation's; a recorded INS that does not cover the track is one line."""

from __future__ import annotations

import numpy as np
import pytest
from pyproj import Geod

from pipeline.errors import AeromagError
from pipeline.io.reader import read_flight
from pipeline.io.writer import OutputChannel, write_with_new_channels
from tests.navmaps import navigate_box

EARTH_RADIUS_M = 6_371_000.0  # only for the velocities' size


def with_recorded_ins(box_path, path, drift_m_s=(0.05, -0.02), cover=1.0):
    """The box recording plus an /ins/solution: the GNSS track with a position error growing
    at ``drift_m_s`` (north, east; m/s) from 5 m north, and that rate as velocity error;
    only the first ``cover`` of the epochs recorded."""
    f = read_flight(box_path)
    d = f.data
    t = d["time_s"].to_numpy(float)
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    dn = 5.0 + drift_m_s[0] * (t - t[0])
    de = drift_m_s[1] * (t - t[0])
    v = np.gradient(np.column_stack([lat, lon]), t, axis=0)
    vn = np.radians(v[:, 0]) * EARTH_RADIUS_M + drift_m_s[0]
    ve = np.radians(v[:, 1]) * EARTH_RADIUS_M * np.cos(np.radians(lat)) + drift_m_s[1]
    # next to the GNSS's missing first and last epochs the difference has none
    vn, ve = np.nan_to_num(vn, nan=drift_m_s[0]), np.nan_to_num(ve, nan=drift_m_s[1])
    # the offset positions on the WGS-84 ellipsoid: north by dn, then east by de
    geod = Geod(ellps="WGS84")
    ok = np.isfinite(lat)
    lon_n, lat_n, _ = geod.fwd(lon[ok], lat[ok], np.zeros(ok.sum()), dn[ok])
    lon_e, lat_e, _ = geod.fwd(lon_n, lat_n, np.full(ok.sum(), 90.0), de[ok])
    lat_i, lon_i = np.full(t.size, np.nan), np.full(t.size, np.nan)
    lat_i[ok], lon_i[ok] = lat_e, lon_e
    ch = OutputChannel("/ins/solution", "aeromag.InsSolution")
    n = int(cover * t.size)
    for i in range(n):
        if not np.isfinite(lat[i]):
            continue
        ch.add(
            int(f.time_ns[i]),
            {
                "latitude_deg": float(lat_i[i]),
                "longitude_deg": float(lon_i[i]),
                "altitude_m": float(alt[i] + 2.0),
                "velocity_north_m_s": float(vn[i]),
                "velocity_east_m_s": float(ve[i]),
                "velocity_down_m_s": 0.0,
                "roll_deg": float(d["roll_deg"].iloc[i]),
                "pitch_deg": float(d["pitch_deg"].iloc[i]),
                "yaw_deg": float(d["yaw_deg"].iloc[i]),
            },
        )
    write_with_new_channels(box_path, path, [ch])
    return dn, de


def test_the_recorded_ins_errors_are_the_records(box_path, tmp_path):
    path = tmp_path / "ins.mcap"
    dn, de = with_recorded_ins(box_path, path)
    for ins in ("recorded", "auto"):
        run = navigate_box(path, ins=ins)
        assert run.ins_source == "recorded"
        assert run.summary()["ins"]["source"] == "recorded"
        got = run.ins_error_ne()
        want_n, want_e = dn[run.index], de[run.index]
        # north and east along the geodesic, as the offsets were made (not the UTM grid's
        # axes, turned by the meridian convergence)
        np.testing.assert_allclose(got[:, 0], want_n, atol=0.01)
        np.testing.assert_allclose(got[:, 1], want_e, atol=0.01)
        np.testing.assert_allclose(run.ins_error[:, 2], 2.0, atol=0.01)
    # without asking, a recording with no INS solution still gets a simulated one
    assert navigate_box(box_path, ins="auto").ins_source == "simulated"


def test_a_recorded_ins_that_does_not_cover_the_track_is_one_line(box_path, tmp_path):
    path = tmp_path / "half.mcap"
    with_recorded_ins(box_path, path, cover=0.5)
    with pytest.raises(AeromagError) as exc:
        navigate_box(path, ins="recorded")
    msg = str(exc.value)
    assert "/ins/solution" in msg and "does not cover" in msg and "\n" not in msg


def test_recorded_asked_of_a_recording_without_one_is_one_line(box_path):
    with pytest.raises(AeromagError, match="no INS solution"):
        navigate_box(box_path, ins="recorded")
