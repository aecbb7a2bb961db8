"""Importers: SGL / DAF-MIT MagNav HDF5 and XYZ files into the channel contract."""

from __future__ import annotations

import json
from datetime import UTC, datetime

import numpy as np
import pytest
from mcap.reader import make_reader

import tests.cli
from pipeline.errors import AeromagError
from pipeline.io.reader import read_flight
from pipeline.io.sgl import import_sgl
from tests.conftest import sha256
from tests.recordings import validate_every_message

XYZ_COLUMNS = (
    "LINE FLT YEAR DOY TIME UTM-X UTM-Y UTM-Z MSL-Z LAT LONG BARO RADAR TOPO DEM "
    "DRAPE PITCH ROLL AZIMUTH DIURNAL COMPMAG1 LAGMAG1 DCMAG1 IGRFMAG1 UNCOMPMAG1 "
    "UNCOMPMAG2 UNCOMPMAG3 FLUXB_X FLUXB_Y FLUXB_Z FLUXB_TOT FLUXC_X FLUXC_Y FLUXC_Z "
    "FLUXC_TOT CUR_HEAT CUR_STRB V_BAT_1"
).split()
H5_NAMES = [
    "line",
    "flight",
    "year",
    "doy",
    "tt",
    "utm_x",
    "utm_y",
    "utm_z",
    "msl",
    "lat",
    "lon",
    "baro",
    "radar",
    "topo",
    "dem",
    "drape",
    "ins_pitch",
    "ins_roll",
    "ins_yaw",
    "diurnal",
    "mag_1_c",
    "mag_1_lag",
    "mag_1_dc",
    "mag_1_igrf",
    "mag_1_uc",
    "mag_2_uc",
    "mag_3_uc",
    "flux_b_x",
    "flux_b_y",
    "flux_b_z",
    "flux_b_t",
    "flux_c_x",
    "flux_c_y",
    "flux_c_z",
    "flux_c_t",
    "cur_heat",
    "cur_strb",
    "vol_bat_1",
]


def sgl_table(n: int = 600, seed: int = 0) -> dict[str, np.ndarray]:
    """One minute of a 10 Hz SGL-like flight over two lines, values in the real units."""
    rng = np.random.default_rng(seed)
    tt = 46370.0 + np.arange(n) / 10.0
    f = {
        "line": np.where(np.arange(n) < n // 2, 1002.02, 1002.20),
        "flight": np.full(n, 1002.0),
        "year": np.full(n, 2020.0),
        "doy": np.full(n, 174.0),
        "tt": tt,
    }
    f["utm_x"], f["utm_y"] = 400_000 + 60 * (tt - tt[0]), np.full(n, 5_030_000.0)
    f["utm_z"] = 1800 + rng.normal(0, 0.3, n)
    f["msl"] = f["utm_z"] + 34.0
    f["lat"], f["lon"] = 45.4 + 1e-5 * (tt - tt[0]), np.full(n, -76.2)
    for k in ("baro", "radar", "topo", "dem", "drape"):
        f[k] = rng.normal(100, 5, n)
    f["ins_pitch"] = 2 + rng.normal(0, 0.5, n)
    f["ins_roll"] = 10 * np.sin(2 * np.pi * (tt - tt[0]) / 6)
    f["ins_yaw"] = np.mod(90 + 5 * np.sin(2 * np.pi * (tt - tt[0]) / 8), 360)
    f["diurnal"] = 5 * np.sin(2 * np.pi * tt / 5400)
    base = 54_000 + 0.5 * (tt - tt[0])
    for k in ("mag_1_c", "mag_1_lag", "mag_1_dc", "mag_1_igrf"):
        f[k] = base + rng.normal(0, 0.1, n)
    for i in (1, 2, 3):
        f[f"mag_{i}_uc"] = base + 50 * i + rng.normal(0, 1, n)
    for c in ("b", "c"):
        v = np.column_stack(
            [
                18_000 + rng.normal(0, 5, n),
                -1500 + rng.normal(0, 5, n),
                50_800 + rng.normal(0, 5, n),
            ]
        )
        for a, col in zip("xyz", v.T, strict=True):
            f[f"flux_{c}_{a}"] = col
        f[f"flux_{c}_t"] = np.linalg.norm(v, axis=1)
    f["cur_heat"] = 2.0 + (tt > tt[0] + 30)
    f["cur_strb"] = 0.5 + 0.1 * np.sin(tt)
    f["vol_bat_1"] = 28.0 - 0.001 * (tt - tt[0])
    f["mag_2_uc"][17] = np.nan  # a missing value
    return f


def write_h5(path, f):
    import h5py

    with h5py.File(path, "w") as h:
        for k in H5_NAMES:
            h.create_dataset(k, data=f[k])
        h.create_dataset("N", data=len(f["tt"]))  # scalars some files carry


def write_xyz(path, f):
    lines = [
        "/ SGL 2020 flight 1002 (test data in the published layout)",
        "/ " + " ".join(XYZ_COLUMNS),
    ]
    n = len(f["tt"])
    for i in range(n):
        vals = []
        for k in H5_NAMES:
            v = f[k][i]
            vals.append(
                "*" if not np.isfinite(v) else (f"{v:.2f}" if k == "line" else repr(float(v)))
            )
        lines.append(" ".join(vals))
    path.write_text("\n".join(lines) + "\n")


def messages(path) -> dict[str, list]:
    out: dict[str, list] = {}
    with open(path, "rb") as fh:
        for _s, ch, m in make_reader(fh).iter_messages(log_time_order=True):
            out.setdefault(ch.topic, []).append((m.log_time, json.loads(m.data)))
    return out


@pytest.fixture
def sgl(tmp_path):
    f = sgl_table()
    h5, xyz = tmp_path / "Flt1002_train.h5", tmp_path / "Flt1002.xyz"
    write_h5(h5, f)
    write_xyz(xyz, f)
    return f, h5, xyz


def test_hdf5_and_xyz_import_to_the_same_contract_recording(sgl, tmp_path):
    f, h5, xyz = sgl
    before = (sha256(h5), sha256(xyz))
    r1 = import_sgl(h5, tmp_path / "a.mcap", calibration_lines=["1002.02"])
    r2 = import_sgl(xyz, tmp_path / "b.mcap", calibration_lines=["1002.02"])
    assert (sha256(h5), sha256(xyz)) == before
    assert r1["channels"] == r2["channels"] and r1["samples"] == 600
    a, b = messages(tmp_path / "a.mcap"), messages(tmp_path / "b.mcap")
    assert a.keys() == b.keys()
    for topic in a:
        assert [m[0] for m in a[topic]] == [m[0] for m in b[topic]], topic
        for (_, pa), (_, pb) in zip(a[topic], b[topic], strict=True):
            for k, v in pa.items():
                if isinstance(v, float):
                    assert v == pytest.approx(pb[k], rel=1e-12, abs=1e-9), (topic, k)
                else:
                    assert v == pb[k], (topic, k)
    assert {
        "/mag/scalar/1",
        "/mag/scalar/2",
        "/mag/scalar/3",
        "/mag/vector/b",
        "/mag/vector/c",
        "/ins/attitude",
        "/gnss/fix",
        "/reference/mag_1_c",
        "/reference/diurnal",
        "/aux/cur_heat",
        "/aux/cur_strb",
        "/aux/vol_bat_1",
        "/plan/line",
    } <= set(a)
    assert r1["channels"]["/mag/scalar/2"] == 599  # the missing sample is dropped
    assert validate_every_message(tmp_path / "a.mcap") > 0


def test_imported_recording_reads_with_the_right_times_and_values(sgl, tmp_path):
    f, h5, _ = sgl
    import_sgl(h5, tmp_path / "a.mcap", calibration_lines=["1002.02"])
    fl = read_flight(tmp_path / "a.mcap")
    assert fl.topic_of["scalar"] == "/mag/scalar/1" and fl.topic_of["vector"] == "/mag/vector/b"
    t0 = datetime(2020, 1, 1, tzinfo=UTC).timestamp() + 173 * 86400 + 46370.0
    assert fl.time_ns[0] == int(round(t0 * 1e9))
    np.testing.assert_allclose(fl.data["scalar_nT"], f["mag_1_uc"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(fl.data["vector_z_nT"], f["flux_b_z"], atol=1e-9)
    np.testing.assert_allclose(fl.data["roll_deg"], f["ins_roll"], atol=1e-9)
    np.testing.assert_allclose(fl.data["alt_m"], f["utm_z"], atol=1e-9)
    assert fl.units["aux_cur_heat"] == "A" and fl.units["aux_vol_bat_1"] == "V"
    kinds = dict(zip(fl.data["plan_line_id"], fl.data["plan_kind"], strict=True))
    assert kinds == {"1002.02": "calibration", "1002.20": "survey"}


def test_line_selection_and_the_command(sgl, tmp_path):
    _, h5, _ = sgl
    res = tests.cli.run(
        "import", "sgl", str(h5), "--out", str(tmp_path / "c.mcap"), "--lines", "1002.20"
    )
    assert res.returncode == 0, res.stderr
    m = messages(tmp_path / "c.mcap")
    assert len(m["/mag/scalar/1"]) == 300
    assert [p["line_id"] for _, p in m["/plan/line"]] == ["1002.20"]
    bad = tests.cli.run(
        "import", "sgl", str(h5), "--out", str(tmp_path / "d.mcap"), "--lines", "9999.01"
    )
    assert bad.returncode == 2 and "9999.01" in bad.stderr and "Traceback" not in bad.stderr
    assert not (tmp_path / "d.mcap").exists()


@pytest.mark.parametrize(("scale", "unit"), [(1e-9, "tesla"), (1e-3, "uT"), (1e-5, "gauss")])
def test_wrong_field_units_are_caught(tmp_path, scale, unit):
    f = sgl_table()
    for i in (1, 2, 3):
        f[f"mag_{i}_uc"] = f[f"mag_{i}_uc"] * scale
    write_h5(tmp_path / "t.h5", f)
    with pytest.raises(AeromagError) as exc:
        import_sgl(tmp_path / "t.h5", tmp_path / "t.mcap")
    assert unit in str(exc.value) and "mag_1_uc" in str(exc.value)
    assert not (tmp_path / "t.mcap").exists()


def test_attitude_in_radians_is_caught(tmp_path):
    f = sgl_table()
    f["ins_yaw"] = np.linspace(0.0, 180.0, f["tt"].size)  # a turn: the heading varies
    for k in ("ins_roll", "ins_pitch", "ins_yaw"):
        f[k] = np.radians(f[k])
    write_h5(tmp_path / "r.h5", f)
    with pytest.raises(AeromagError, match="radians"):
        import_sgl(tmp_path / "r.h5", tmp_path / "r.mcap")


# --------------------------------------------------------------------------------------------
# ROS 2 recordings and topic mapping
_SEP = "=" * 80
_HEADER = (
    "MSG: std_msgs/Header\nbuiltin_interfaces/Time stamp\nstring frame_id\n"
    f"{_SEP}\nMSG: builtin_interfaces/Time\nint32 sec\nuint32 nanosec\n"
)
_VEC3 = f"{_SEP}\nMSG: geometry_msgs/Vector3\nfloat64 x\nfloat64 y\nfloat64 z\n"
MSGDEFS = {
    "sensor_msgs/msg/MagneticField": (
        "std_msgs/Header header\ngeometry_msgs/Vector3 magnetic_field\n"
        f"float64[9] magnetic_field_covariance\n{_SEP}\n{_HEADER}{_VEC3}"
    ),
    "sensor_msgs/msg/Imu": (
        "std_msgs/Header header\ngeometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\ngeometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\ngeometry_msgs/Vector3 linear_acceleration\n"
        f"float64[9] linear_acceleration_covariance\n{_SEP}\n{_HEADER}"
        f"{_SEP}\nMSG: geometry_msgs/Quaternion\nfloat64 x 0\nfloat64 y 0\nfloat64 z 0\n"
        f"float64 w 1\n{_VEC3}"
    ),
    "sensor_msgs/msg/NavSatFix": (
        "std_msgs/Header header\nsensor_msgs/NavSatStatus status\nfloat64 latitude\n"
        "float64 longitude\nfloat64 altitude\nfloat64[9] position_covariance\n"
        f"uint8 position_covariance_type\n{_SEP}\n{_HEADER}{_SEP}\n"
        "MSG: sensor_msgs/NavSatStatus\nint8 status\nuint16 service\n"
    ),
    "std_msgs/msg/Float64": "float64 data\n",
}
MAPPING = """
[topics."/cesium/field"]
role = "scalar"
fields = ["data"]
scale = 1e9
name = "cs"

[topics."/imu/mag"]
role = "vector"
fields = ["magnetic_field.x", "magnetic_field.y", "magnetic_field.z"]
scale = 1e9
frame = "flu"

[topics."/imu/data"]
role = "attitude"
quaternion = "orientation"
frame = "flu"

[topics."/fix"]
role = "position"
fields = ["latitude", "longitude", "altitude"]
"""


def _stamp(t_ns):
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def write_ros2(sim, path):
    """The simulated flight as a ROS 2 robot records it: SI units (tesla), REP-103 frames
    (body FLU, world ENU), header stamps, a cesium magnetometer on std_msgs/Float64."""
    from mcap_ros2.writer import Writer
    from scipy.spatial.transform import Rotation

    from pipeline.io.mapping import _ENU_TO_NED, _FLU_TO_FRD

    start = int(sim.truth["start_time_ns"]) if "start_time_ns" in sim.truth else None
    with open(path, "wb") as f:
        w = Writer(f)
        sch = {k: w.register_msgdef(k, v) for k, v in MSGDEFS.items()}
        s = sim.streams
        t0 = start if start is not None else 1_781_485_200_000_000_000

        def ns(t):
            return t0 + int(round(t * 1e9))

        for t, v in zip(s["/mag/scalar"]["t"], s["/mag/scalar"]["cols"]["total_nT"], strict=True):
            # no header: the log time is the sample time
            w.write_message(
                "/cesium/field", sch["std_msgs/msg/Float64"], {"data": v * 1e-9}, log_time=ns(t)
            )
        vec = s["/mag/vector"]
        for t, x, y, z in zip(
            vec["t"], vec["cols"]["x_nT"], vec["cols"]["y_nT"], vec["cols"]["z_nT"], strict=True
        ):
            w.write_message(
                "/imu/mag",
                sch["sensor_msgs/msg/MagneticField"],
                {
                    "header": {"stamp": _stamp(ns(t)), "frame_id": "imu"},
                    "magnetic_field": {"x": x * 1e-9, "y": -y * 1e-9, "z": -z * 1e-9},
                    "magnetic_field_covariance": [0.0] * 9,
                },
                log_time=ns(t) + 1_000_000,
            )
        att = s["/ins/attitude"]
        r_frd_ned = Rotation.from_euler(
            "ZYX",
            np.column_stack(
                [att["cols"]["yaw_deg"], att["cols"]["pitch_deg"], att["cols"]["roll_deg"]]
            ),
            degrees=True,
        ).as_matrix()
        q = Rotation.from_matrix(_ENU_TO_NED @ r_frd_ned @ _FLU_TO_FRD).as_quat()
        for t, qq in zip(att["t"], q, strict=True):
            w.write_message(
                "/imu/data",
                sch["sensor_msgs/msg/Imu"],
                {
                    "header": {"stamp": _stamp(ns(t)), "frame_id": "imu"},
                    "orientation": {"x": qq[0], "y": qq[1], "z": qq[2], "w": qq[3]},
                    "orientation_covariance": [0.0] * 9,
                    "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "angular_velocity_covariance": [0.0] * 9,
                    "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 0.0},
                    "linear_acceleration_covariance": [0.0] * 9,
                },
                log_time=ns(t),
            )
        g = s["/gnss/fix"]
        for t, la, lo, h in zip(
            g["t"],
            g["cols"]["latitude"],
            g["cols"]["longitude"],
            g["cols"]["altitude"],
            strict=True,
        ):
            w.write_message(
                "/fix",
                sch["sensor_msgs/msg/NavSatFix"],
                {
                    "header": {"stamp": _stamp(ns(t)), "frame_id": "gnss"},
                    "status": {"status": 0, "service": 1},
                    "latitude": la,
                    "longitude": lo,
                    "altitude": h,
                    "position_covariance": [0.0] * 9,
                    "position_covariance_type": 0,
                },
                log_time=ns(t),
            )
        w.finish()
    return t0


def test_ros2_recording_compensates_like_the_json_one(tmp_path):
    from pipeline.compensate import FitSettings
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.mapping import Mapping
    from pipeline.simulate import write_simulation
    from tests.conftest import run_sim

    sim = run_sim(
        "calibration-only",
        5,
        [
            "calibration.passes=1",
            "sensors.clock_offset_s={scalar=0.0, vector=0.013, "
            "attitude=0.007, gnss=0.031, base=0.25, aux=0.041}",
        ],
    )
    json_path = write_simulation(sim, tmp_path / "json.mcap")
    ros_path = tmp_path / "ros2.mcap"
    write_ros2(sim, ros_path)
    (tmp_path / "map.toml").write_text(MAPPING)
    res = tests.cli.run("inspect", str(ros_path), "--suggest-mapping")
    assert res.returncode == 0, res.stderr
    assert '[topics."/imu/mag"]' in res.stdout and 'role = "attitude"' in res.stdout
    suggested = tmp_path / "suggested.toml"
    suggested.write_text(res.stdout)
    Mapping.load(suggested)  # loadable as printed
    mapping = Mapping.load(tmp_path / "map.toml")
    a = read_flight(json_path)
    b = read_flight(ros_path, mapping=mapping)
    assert b.topic_of["scalar"] == "/cesium/field" and b.topic_of["vector"] == "/imu/mag"
    # same epochs: the vector's header stamps are used, not its (1 ms late) log times
    np.testing.assert_array_equal(b.time_ns, a.time_ns)
    for col in ("scalar_nT", "vector_x_nT", "vector_y_nT", "vector_z_nT", "lat_deg", "alt_m"):
        np.testing.assert_allclose(b.data[col], a.data[col], rtol=1e-12, atol=1e-6)
    for col in ("roll_deg", "pitch_deg"):
        np.testing.assert_allclose(b.data[col], a.data[col], atol=1e-7)
    dyaw = (b.data["yaw_deg"] - a.data["yaw_deg"] + 180) % 360 - 180
    assert np.nanmax(np.abs(dyaw)) < 1e-7
    from pipeline.segment import segment_flight

    ca = run_compensation(a, segment_flight(a), FitSettings(model="tl18"))
    cb = run_compensation(b, segment_flight(b), FitSettings(model="tl18"))
    np.testing.assert_allclose(cb.model.coefficients, ca.model.coefficients, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(cb.compensated_nT, ca.compensated_nT, atol=1e-5)


def test_a_mapping_without_the_tesla_scale_is_caught(tmp_path):
    from pipeline.io.mapping import Mapping
    from tests.conftest import run_sim

    sim = run_sim("calibration-only", 5, ["calibration.passes=1"])
    write_ros2(sim, tmp_path / "r.mcap")
    (tmp_path / "m.toml").write_text(MAPPING.replace("scale = 1e9\nname", "name", 1))
    with pytest.raises(AeromagError, match="tesla") as exc:
        read_flight(tmp_path / "r.mcap", mapping=Mapping.load(tmp_path / "m.toml"))
    assert "/cesium/field" in str(exc.value)


def test_import_mapped_and_a_protobuf_location_fix(tmp_path):
    """`aeromag import mapped` turns the ROS 2 recording into one every command reads; a
    Foxglove protobuf LocationFix channel maps like the ROS one."""
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from mcap_protobuf.writer import Writer as PbWriter

    from pipeline.io.mapping import Mapping, mapped_series
    from tests.conftest import run_sim

    sim = run_sim("calibration-only", 5, ["calibration.passes=1"])
    ros = tmp_path / "ros2.mcap"
    write_ros2(sim, ros)
    (tmp_path / "map.toml").write_text(MAPPING)
    res = tests.cli.run(
        "import",
        "mapped",
        str(ros),
        "--mapping",
        str(tmp_path / "map.toml"),
        "--out",
        str(tmp_path / "c.mcap"),
    )
    assert res.returncode == 0, res.stderr
    assert "/imu/mag -> /mag/vector" in res.stdout
    direct = read_flight(ros, mapping=Mapping.load(tmp_path / "map.toml"))
    converted = read_flight(tmp_path / "c.mcap")
    np.testing.assert_allclose(converted.data["vector_y_nT"], direct.data["vector_y_nT"])
    np.testing.assert_allclose(converted.data["yaw_deg"], direct.data["yaw_deg"])
    ins = tests.cli.run("inspect", str(tmp_path / "c.mcap"))
    assert ins.returncode == 0 and "contract: ok" in ins.stdout
    # protobuf: a LocationFix channel next to the JSON contract channels
    pb = tmp_path / "pb.mcap"
    g = sim.streams["/gnss/fix"]
    t0 = int(sim.truth["start_time_ns"])
    with open(pb, "wb") as f:
        w = PbWriter(f)
        for t, la, lo, h in zip(
            g["t"],
            g["cols"]["latitude"],
            g["cols"]["longitude"],
            g["cols"]["altitude"],
            strict=True,
        ):
            msg = LocationFix(latitude=la, longitude=lo, altitude=h)
            w.write_message("/gps/fix_pb", msg, log_time=t0 + int(round(t * 1e9)))
        w.finish()
    sug = tests.cli.run("inspect", str(pb), "--suggest-mapping")
    assert '[topics."/gps/fix_pb"]' in sug.stdout and 'role = "position"' in sug.stdout
    (tmp_path / "pb.toml").write_text(sug.stdout)
    series = mapped_series(pb, Mapping.load(tmp_path / "pb.toml"))
    s = series["/gps/fix_pb"]
    np.testing.assert_allclose(s.values["latitude"], g["cols"]["latitude"])
    np.testing.assert_allclose(s.values["altitude"], g["cols"]["altitude"])


PEER_XYZ = (
    __import__("pathlib").Path(__file__).resolve().parents[1].parent
    / "shared"
    / "peer"
    / "magnav"
    / "Flt1003_sample.xyz"
)


def test_ins_solution_from_hdf5_in_radians_and_north_west_up(tmp_path):
    f = sgl_table()
    n = f["tt"].size
    f["ins_lat"] = np.radians(f["lat"] + 3e-4)  # SGL: radians; an INS 33 m off the GNSS
    f["ins_lon"] = np.radians(f["lon"])
    f["ins_alt"] = f["utm_z"] - 1.0
    f["ins_vn"], f["ins_vw"], f["ins_vu"] = np.full(n, 1.0), np.full(n, -60.0), np.full(n, 0.5)
    import h5py

    write_h5(tmp_path / "i.h5", f)
    with h5py.File(tmp_path / "i.h5", "a") as h:
        for k in ("ins_lat", "ins_lon", "ins_alt", "ins_vn", "ins_vw", "ins_vu"):
            h.create_dataset(k, data=f[k])
    r = import_sgl(tmp_path / "i.h5", tmp_path / "i.mcap")
    assert r["channels"]["/ins/solution"] == n
    assert validate_every_message(tmp_path / "i.mcap") > 0
    fl = read_flight(tmp_path / "i.mcap")
    assert fl.topic_of["ins"] == "/ins/solution"
    np.testing.assert_allclose(fl.data["ins_latitude_deg"], f["lat"] + 3e-4, atol=1e-9)
    np.testing.assert_allclose(fl.data["ins_longitude_deg"], f["lon"], atol=1e-9)
    # north, east, down from north, west, up
    np.testing.assert_allclose(fl.data["ins_velocity_east_m_s"], 60.0)
    np.testing.assert_allclose(fl.data["ins_velocity_down_m_s"], -0.5)
    np.testing.assert_allclose(fl.data["ins_yaw_deg"], f["ins_yaw"], atol=1e-9)
    assert fl.units["ins_velocity_north_m_s"] == "m/s" and fl.units["ins_altitude_m"] == "m"


def test_ins_solution_without_ins_columns_is_absent(sgl, tmp_path):
    _, h5, _ = sgl
    r = import_sgl(h5, tmp_path / "a.mcap")
    assert "/ins/solution" not in r["channels"]


@pytest.mark.skipif(not PEER_XYZ.is_file(), reason="shared/peer/magnav is not beside the repo")
def test_ins_solution_of_the_real_sgl_sample(tmp_path):
    r = import_sgl(PEER_XYZ, tmp_path / "s.mcap")
    assert r["channels"]["/ins/solution"] == r["channels"]["/gnss/fix"] > 0
    fl = read_flight(tmp_path / "s.mcap")
    d = fl.data
    # the INS position lies within a few hundred metres of the GNSS (it is in radians there)
    assert np.all(np.abs(d["ins_latitude_deg"] - d["lat_deg"]) < 0.01)
    assert np.all(np.abs(d["ins_longitude_deg"] - d["lon_deg"]) < 0.01)
    # its velocity points along its heading, and its climb matches the GNSS height's change
    course = np.degrees(np.arctan2(d["ins_velocity_east_m_s"], d["ins_velocity_north_m_s"]))
    off = (course - d["ins_yaw_deg"] + 180.0) % 360.0 - 180.0
    assert np.all(np.abs(off) < 20.0)
    assert np.all(d["ins_velocity_down_m_s"][:3] < 0) and np.diff(d["alt_m"][:3]).min() > 0
