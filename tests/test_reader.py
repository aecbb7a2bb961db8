"""Reader: decoding, alignment onto the scalar epochs, gaps, missing channels, bad files."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import AeromagError
from pipeline.geo.local import LocalFrame
from pipeline.io.reader import read_flight
from pipeline.simulate import write_simulation
from tests.conftest import FIXTURES, run_sim
from tests.mcap_builder import NS, T0, attitude, build, scalar, ts, vector


def test_fixture_reads_into_aligned_columns(box_path):
    fl = read_flight(box_path)
    d = fl.data
    for col in (
        "time_s",
        "scalar_nT",
        "vector_x_nT",
        "roll_deg",
        "yaw_deg",
        "lat_deg",
        "alt_m",
        "base_nT",
        "aux_payload_current",
    ):
        assert col in d.columns
    assert fl.units["aux_payload_current"] == "A" and fl.units["alt_m"] == "m"
    assert len(d) == fl.series["/mag/scalar"].time_ns.size
    assert abs(fl.series["/mag/vector"].rate_hz - 10.0) < 1e-6
    assert abs(fl.series["/gnss/fix"].rate_hz - 2.0) < 1e-6
    assert fl.gaps == [] and fl.unknown_topics == []
    # interior epochs are fully populated; only the ends may fall outside slower streams
    assert d.iloc[20:-20].notna().all().all()


def test_alignment_reproduces_the_trajectory_at_scalar_epochs(box_sim_file):
    """Streams at 20/20/5 Hz on offset clocks, interpolated onto 10 Hz scalar epochs.

    Noise-free attitude is compared with the true trajectory: linear interpolation over 0.05 s
    of a roll manoeuvre (A w^2 ~ 11 deg/s^2) errs by (0.05^2/8) 11 ~ 0.004 deg; GNSS at 5 Hz
    in a 20 m turn (v^2/R ~ 2.5 m/s^2) by (0.2^2/8) 2.5 ~ 0.013 m.
    """
    sim = run_sim(
        "calibration-only",
        11,
        ["calibration.passes=1", "sensors.attitude_noise_deg=0.0", "sensors.gnss_noise_m=0.0"],
    )
    import tempfile
    from pathlib import Path

    path = write_simulation(sim, Path(tempfile.mkdtemp()) / "aligned.mcap")
    fl = read_flight(path)
    d = fl.data.dropna()
    t_s = (fl.time_ns[d.index] - sim.start_ns) / NS
    st = sim.trajectory.state(t_s)
    assert np.max(np.abs(d.roll_deg - st["roll_deg"])) < 0.006
    assert np.max(np.abs(d.pitch_deg - st["pitch_deg"])) < 0.006
    dyaw = (d.yaw_deg - st["yaw_deg"] + 180) % 360 - 180
    assert np.max(np.abs(dyaw)) < 0.01
    site = sim.truth["site"]
    e, n, u = LocalFrame(
        site["latitude_deg"], site["longitude_deg"], site["ground_altitude_m"]
    ).to_enu(d.lat_deg, d.lon_deg, d.alt_m)
    assert np.max(np.hypot(e - st["east_m"], n - st["north_m"])) < 0.02
    assert np.max(np.abs(u - st["up_m"])) < 0.02


def test_yaw_is_interpolated_across_north(tmp_path):
    msgs = [
        ("/ins/attitude", T0, attitude(T0, 0, 0, 359.0)),
        ("/ins/attitude", T0 + NS // 10, attitude(T0 + NS // 10, 0, 0, 1.0)),
        ("/mag/scalar", T0 + NS // 20, scalar(T0 + NS // 20, 5e4)),
        ("/mag/scalar", T0 + NS // 10, scalar(T0 + NS // 10, 5e4)),
    ]
    fl = read_flight(build(tmp_path / "yaw.mcap", msgs))
    assert abs(fl.data.yaw_deg.iloc[0] - 0.0) < 1e-9 or abs(fl.data.yaw_deg.iloc[0] - 360) < 1e-9


def test_longitude_is_interpolated_across_the_antimeridian(tmp_path):
    """A fix at 179.9999 deg then one at -179.9999 deg: the scalar epoch between them lies
    beside the antimeridian, not on the other side of the globe (0 deg)."""

    def fix(t, lon):
        return {"timestamp": ts(t), "latitude": -17.0, "longitude": lon, "altitude": 100.0}

    msgs = [
        ("/gnss/fix", T0, fix(T0, 179.9999)),
        ("/gnss/fix", T0 + NS // 10, fix(T0 + NS // 10, -179.9999)),
        ("/mag/scalar", T0 + NS // 40, scalar(T0 + NS // 40, 5e4)),
        ("/mag/scalar", T0 + NS // 20, scalar(T0 + NS // 20, 5e4)),
        ("/mag/scalar", T0 + 3 * NS // 40, scalar(T0 + 3 * NS // 40, 5e4)),
    ]
    lon = read_flight(build(tmp_path / "lon.mcap", msgs)).data.lon_deg.to_numpy()
    assert np.all((np.abs(lon) > 179.9998) & (np.abs(lon) <= 180.0))
    assert lon[0] > 0 > lon[-1]


def test_gap_in_a_stream_is_reported_and_left_empty(tmp_path):
    sim = run_sim(
        "calibration-only",
        1,
        [
            "calibration.passes=1",
            "sensors.dropouts=["
            '{topic="/ins/attitude", start_s=200.0, duration_s=3.0},'
            '{topic="/mag/scalar", start_s=300.0, duration_s=1.5}]',
        ],
    )
    fl = read_flight(write_simulation(sim, tmp_path / "gaps.mcap"))
    gaps = {g.topic: g for g in fl.gaps}
    assert set(gaps) == {"/ins/attitude", "/mag/scalar"}
    assert abs(gaps["/ins/attitude"].duration_s - 3.05) < 0.06
    assert abs(gaps["/mag/scalar"].duration_s - 1.6) < 0.06
    t = (fl.time_ns - sim.start_ns) / NS
    inside = (t > 200.05) & (t < 202.95)
    assert inside.sum() >= 28 and fl.data.roll_deg[inside].isna().all()
    assert fl.data.roll_deg[(t > 190) & (t < 199.9)].notna().all()
    assert any("/ins/attitude: gap of" in n for n in fl.notes)


def test_recording_with_only_the_magnetometers(tmp_path):
    fl = read_flight(FIXTURES / "box_scalar_vector_only.mcap")
    assert fl.has("scalar_nT", "vector_x_nT") and not fl.has("roll_deg")
    with pytest.raises(AeromagError, match=r"/ins/attitude: segmentation needs roll_deg"):
        fl.require("roll_deg", purpose="segmentation")


def test_secondary_sensors_and_unknown_topics(tmp_path):
    msgs = []
    for i in range(20):
        t = T0 + i * NS // 10
        msgs += [
            ("/mag/scalar/left", t, scalar(t, 5e4 + i, "left")),
            ("/mag/scalar/right", t, scalar(t, 6e4 + i, "right")),
            ("/mag/vector", t, vector(t, 2e4 + i, 2e3, 4e4)),
            ("/camera/raw", t, b"\x00\x01binary"),
        ]
    fl = read_flight(build(tmp_path / "multi.mcap", msgs, schema_of={"/camera/raw": "x.Image"}))
    assert fl.topic_of["scalar"] == "/mag/scalar/left"
    assert "scalar_right_nT" in fl.data and fl.data.scalar_right_nT.iloc[3] == 6e4 + 3
    assert fl.unknown_topics == ["/camera/raw"]
    fl2 = read_flight(tmp_path / "multi.mcap", scalar_topic="/mag/scalar/right")
    assert fl2.data.scalar_nT.iloc[0] == 6e4


def test_bad_payloads_are_dropped_and_reported(tmp_path):
    msgs = []
    for i in range(30):
        t = T0 + i * NS // 10
        msgs.append(("/mag/scalar", t, scalar(t, 5e4 + i)))
    bad_t = T0 + 5 * NS // 10
    msgs += [
        ("/mag/vector", T0, vector(T0, 2e4, 2, 4e4)),
        ("/mag/vector", T0 + NS, {"timestamp": ts(T0 + NS), "x_nT": "12", "y_nT": 0, "z_nT": 0}),
        ("/mag/vector", T0 + 2 * NS, b"\xff\xfe not json"),
        ("/mag/vector", T0 + 2 * NS, vector(T0 + 2 * NS, 2e4, 2, 4e4)),
        ("/mag/vector", T0, vector(T0, 9, 9, 4e4)),  # duplicate time, out of order
        (
            "/mag/vector",
            T0 + NS // 2,
            {"timestamp": ts(bad_t), "sensor_id": "v", "x_nT": None, "y_nT": 0, "z_nT": 0},
        ),
        ("/mag/vector", T0 + 3 * NS, vector(T0 + 3 * NS + 7, 2e4, 2, 4e4)),  # stamp mismatch
    ]
    fl = read_flight(build(tmp_path / "bad.mcap", msgs))
    s = fl.series["/mag/vector"]
    text = " | ".join(s.problems)
    assert "do not match the schema" in text and "not valid JSON" in text
    assert "payload timestamp that differs" in text and "duplicated timestamps" in text
    assert "not in time order" in text
    assert s.time_ns.tolist() == [T0, T0 + 2 * NS, T0 + 3 * NS]
    assert s.values["x_nT"][0] == 2e4  # the first of the duplicates is kept


@pytest.mark.parametrize(
    "content,expected",
    [
        (b"", "empty file"),
        (b"this is not an mcap file at all" * 10, "not a readable MCAP recording"),
    ],
)
def test_unreadable_files_give_one_line_errors(tmp_path, content, expected):
    p = tmp_path / "bad.mcap"
    p.write_bytes(content)
    with pytest.raises(AeromagError) as err:
        read_flight(p)
    assert expected in str(err.value) and str(p) in str(err.value) and "\n" not in str(err.value)


def test_missing_file_and_missing_scalar(tmp_path):
    with pytest.raises(AeromagError, match="file not found"):
        read_flight(tmp_path / "nope.mcap")
    with pytest.raises(AeromagError, match="a folder, not a file"):
        read_flight(tmp_path)
    p = build(tmp_path / "novec.mcap", [("/mag/vector", T0, vector(T0, 1, 2, 3))])
    with pytest.raises(AeromagError, match="/mag/scalar: no scalar magnetometer"):
        read_flight(p)


def test_recording_without_summary_reads_by_linear_scan(tmp_path):
    msgs = [("/mag/scalar", T0 + i * NS // 10, scalar(T0 + i * NS // 10, 5e4)) for i in range(50)]
    fl = read_flight(build(tmp_path / "nosummary.mcap", msgs, summary=False))
    assert len(fl.data) == 50
