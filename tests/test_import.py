"""Importers: SGL / DAF-MIT MagNav HDF5 and XYZ files into the channel contract."""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import UTC, datetime

import numpy as np
import pytest
from mcap.reader import make_reader

from pipeline.errors import AeromagError
from pipeline.io.reader import read_flight
from pipeline.io.sgl import import_sgl
from tests.conftest import sha256
from tests.test_schemas import validate_every_message

XYZ_COLUMNS = ("LINE FLT YEAR DOY TIME UTM-X UTM-Y UTM-Z MSL-Z LAT LONG BARO RADAR TOPO DEM "
               "DRAPE PITCH ROLL AZIMUTH DIURNAL COMPMAG1 LAGMAG1 DCMAG1 IGRFMAG1 UNCOMPMAG1 "
               "UNCOMPMAG2 UNCOMPMAG3 FLUXB_X FLUXB_Y FLUXB_Z FLUXB_TOT FLUXC_X FLUXC_Y FLUXC_Z "
               "FLUXC_TOT CUR_HEAT CUR_STRB V_BAT_1").split()
H5_NAMES = ["line", "flight", "year", "doy", "tt", "utm_x", "utm_y", "utm_z", "msl", "lat",
            "lon", "baro", "radar", "topo", "dem", "drape", "ins_pitch", "ins_roll", "ins_yaw",
            "diurnal", "mag_1_c", "mag_1_lag", "mag_1_dc", "mag_1_igrf", "mag_1_uc",
            "mag_2_uc", "mag_3_uc", "flux_b_x", "flux_b_y", "flux_b_z", "flux_b_t", "flux_c_x",
            "flux_c_y", "flux_c_z", "flux_c_t", "cur_heat", "cur_strb", "vol_bat_1"]


def sgl_table(n: int = 600, seed: int = 0) -> dict[str, np.ndarray]:
    """One minute of a 10 Hz SGL-like flight over two lines, values in the real units."""
    rng = np.random.default_rng(seed)
    tt = 46370.0 + np.arange(n) / 10.0
    f = {"line": np.where(np.arange(n) < n // 2, 1002.02, 1002.20), "flight": np.full(n, 1002.0),
         "year": np.full(n, 2020.0), "doy": np.full(n, 174.0), "tt": tt}
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
        v = np.column_stack([18_000 + rng.normal(0, 5, n), -1500 + rng.normal(0, 5, n),
                             50_800 + rng.normal(0, 5, n)])
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
    lines = ["/ SGL 2020 flight 1002 (test data in the published layout)",
             "/ " + " ".join(XYZ_COLUMNS)]
    n = len(f["tt"])
    for i in range(n):
        vals = []
        for k in H5_NAMES:
            v = f[k][i]
            vals.append("*" if not np.isfinite(v) else (f"{v:.2f}" if k == "line"
                                                         else repr(float(v))))
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
    assert {"/mag/scalar/1", "/mag/scalar/2", "/mag/scalar/3", "/mag/vector/b",
            "/mag/vector/c", "/ins/attitude", "/gnss/fix", "/reference/mag_1_c",
            "/reference/diurnal", "/aux/cur_heat", "/aux/cur_strb", "/aux/vol_bat_1",
            "/plan/line"} <= set(a)
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
    res = subprocess.run([sys.executable, "-m", "flows.cli", "import", "sgl", str(h5),
                          "--out", str(tmp_path / "c.mcap"), "--lines", "1002.20"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    m = messages(tmp_path / "c.mcap")
    assert len(m["/mag/scalar/1"]) == 300
    assert [p["line_id"] for _, p in m["/plan/line"]] == ["1002.20"]
    bad = subprocess.run([sys.executable, "-m", "flows.cli", "import", "sgl", str(h5),
                          "--out", str(tmp_path / "d.mcap"), "--lines", "9999.01"],
                         capture_output=True, text=True, timeout=300)
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
