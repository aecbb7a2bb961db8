"""Import of the DAF-MIT / SGL MagNav flight data (HDF5 or XYZ text) into the channel contract.

Field layout in ``shared/docs/sgl-layout.md``; the mapping (stated in ``schemas/README.md``):

| SGL field | channel | schema |
|---|---|---|
| ``year`` + ``doy`` + ``tt`` (s past midnight UTC) | every message's timestamp | |
| ``mag_1_uc`` ... ``mag_6_uc`` | ``/mag/scalar/1`` ... | aeromag.ScalarField |
| ``mag_1_c`` (compensated reference) | ``/reference/mag_1_c`` | aeromag.ScalarField |
| ``flux_a_x/y/z`` ... ``flux_d_*`` | ``/mag/vector/a`` ... | aeromag.VectorField |
| ``ins_roll``, ``ins_pitch``, ``ins_yaw`` (deg) | ``/ins/attitude`` | aeromag.Attitude |
| ``lat``, ``lon`` (deg), ``utm_z`` (GPS height, ellipsoid) | ``/gnss/fix`` | foxglove.LocationFix |
| ``ins_lat``, ``ins_lon`` (rad), ``ins_alt``, ``ins_vn/vw/vu``, attitude | ``/ins/solution`` | |
| ``diurnal``, ``igrf`` | ``/reference/diurnal``, ``/reference/igrf`` | aeromag.ScalarField |
| ``cur_*`` (A), ``vol_*`` / ``v_*`` (V) | ``/aux/cur_*``, ``/aux/vol_*`` | aeromag.Scalar |
| ``line`` | ``/plan/line`` at each change | aeromag.LineMarker |

XYZ files name the columns in upper case with hyphens (``UNCOMPMAG1``, ``FLUXA_X``, ``UTM-Z``,
``LONG``, ``ROLL``/``PITCH``/``AZIMUTH`` ...); they are mapped to the HDF5 names first. A
missing value (``*``, NaN) drops that sample from that channel only. Plausibility checks stop
the import with a one-line error when magnetometer values are not in nT (tesla, uT, gauss)
or the attitude is in radians.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from pipeline.errors import AeromagError, missing_file
from pipeline.io.plausibility import check_degrees, check_units
from pipeline.io.writer import McapOutput, encode, stamp

XYZ_NAMES = {
    "LINE": "line",
    "FLT": "flight",
    "YEAR": "year",
    "DOY": "doy",
    "TIME": "tt",
    "UTM-X": "utm_x",
    "UTM-Y": "utm_y",
    "UTM-Z": "utm_z",
    "MSL-Z": "msl",
    "LAT": "lat",
    "LONG": "lon",
    "BARO": "baro",
    "RADAR": "radar",
    "TOPO": "topo",
    "DEM": "dem",
    "DRAPE": "drape",
    "PITCH": "ins_pitch",
    "ROLL": "ins_roll",
    "AZIMUTH": "ins_yaw",
    "DIURNAL": "diurnal",
    "COMPMAG1": "mag_1_c",
    "LAGMAG1": "mag_1_lag",
    "DCMAG1": "mag_1_dc",
    "IGRFMAG1": "mag_1_igrf",
    "OGS_MAG": "ogs_mag",
    "OGS_HGT": "ogs_alt",
    "IGRF": "igrf",
    "INS_HGT": "ins_alt",
    "INS_VEL_N": "ins_vn",
    "INS_VEL_W": "ins_vw",
    "INS_VEL_V": "ins_vu",
}


def _xyz_name(col: str) -> str:
    if col in XYZ_NAMES:
        return XYZ_NAMES[col]
    m = re.fullmatch(r"UNCOMPMAG(\d)", col)
    if m:
        return f"mag_{m.group(1)}_uc"
    m = re.fullmatch(r"FLUX([A-D])_(X|Y|Z|TOT)", col)
    if m:
        axis = "t" if m.group(2) == "TOT" else m.group(2).lower()
        return f"flux_{m.group(1).lower()}_{axis}"
    if col.startswith("V_"):
        return "vol_" + col[2:].lower()
    return col.lower().replace("-", "_")


def read_xyz(path: Path) -> dict[str, np.ndarray]:
    """Read an SGL XYZ text file into columns, by their HDF5 names.

    The last header line (beginning with ``/``) names the columns; ``*`` is a missing value
    (NaN). Values keep the file's units (nT, deg, m; ``tt`` in s past midnight UTC).

    Parameters
    ----------
    path : Path

    Returns
    -------
    dict of str to ndarray

    Raises
    ------
    AeromagError
        Not UTF-8 text, no header, ragged or non-numeric data lines, no data.
    """
    header: list[str] = []
    rows: list[list[str]] = []
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise AeromagError(
            "not an SGL XYZ text file (not UTF-8 text) nor HDF5", file=path
        ) from None
    for line in text.splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith("/"):
            header.append(s.lstrip("/").strip())
            continue
        rows.append(s.split())
    if not header:
        raise AeromagError(
            "no header line (lines beginning with '/') naming the columns", file=path
        )
    cols = [_xyz_name(c) for c in header[-1].split()]
    bad = [k for k, r in enumerate(rows) if len(r) != len(cols)]
    if bad:
        raise AeromagError(
            f"data line {bad[0] + 1} has {len(rows[bad[0]])} values for {len(cols)} columns",
            file=path,
        )
    if not rows:
        raise AeromagError("no data lines", file=path)
    table = np.array(rows, dtype=object)
    out = {}
    for k, name in enumerate(cols):
        vals = table[:, k]
        try:
            out[name] = np.array([np.nan if v == "*" else float(v) for v in vals])
        except ValueError:
            bad = next(i for i, v in enumerate(vals) if v != "*" and not _is_number(v))
            raise AeromagError(
                f"data line {bad + 1}: {vals[bad]!r} is not a number",
                file=path,
                channel=header[-1].split()[k],
            ) from None
    return out


def _is_number(v: str) -> bool:
    try:
        float(v)
    except ValueError:
        return False
    return True


def read_h5(path: Path) -> dict[str, np.ndarray]:
    """Read the 1-D datasets of an SGL HDF5 file (those of the most common length).

    Parameters
    ----------
    path : Path

    Returns
    -------
    dict of str to ndarray
        Dataset name -> float values in the file's units.

    Raises
    ------
    AeromagError
        Not a readable HDF5 file, or no 1-D dataset.
    """
    import h5py

    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise AeromagError(f"not a readable HDF5 file ({exc})", file=path) from None
    with f:
        sizes = {k: f[k].shape for k in f.keys() if isinstance(f[k], h5py.Dataset)}
        lengths = [s[0] for s in sizes.values() if len(s) == 1]
        if not lengths:
            raise AeromagError("no 1-D datasets", file=path)
        n = max(set(lengths), key=lengths.count)
        return {
            k: np.asarray(f[k][()], float) for k, s in sizes.items() if len(s) == 1 and s[0] == n
        }


def read_sgl(path: str | Path) -> dict[str, np.ndarray]:
    """The fields of an SGL file, by their HDF5 names (lower case)."""
    p = Path(path)
    if not p.is_file():
        raise missing_file(p)
    head = p.read_bytes()[:8]
    fields = read_h5(p) if head.startswith(b"\x89HDF") else read_xyz(p)
    missing = [k for k in ("tt", "year", "doy") if k not in fields]
    if missing:
        raise AeromagError(
            f"no {', '.join(missing)} field: cannot build timestamps", file=p, channel=missing[0]
        )
    return fields


def _times_ns(fields: dict[str, np.ndarray], path: Path) -> np.ndarray:
    y, d, t = fields["year"], fields["doy"], fields["tt"]
    ok = np.isfinite(y) & np.isfinite(d) & np.isfinite(t)
    if not ok.any():
        raise AeromagError("no sample has year, doy and tt", file=path, channel="tt")
    y0, d0 = int(np.nanmedian(y[ok])), int(np.nanmedian(d[ok]))
    day = datetime(y0, 1, 1, tzinfo=UTC) + timedelta(days=d0 - 1)
    base_ns = int(day.timestamp()) * 1_000_000_000
    out = np.full(t.size, -1, dtype=np.int64)
    day_ns = np.rint(((d - d0) * 86400.0 + t) * 1e9)
    out[ok] = base_ns + day_ns[ok].astype(np.int64)
    return out


INS_COLUMNS = ("ins_lat", "ins_lon", "ins_alt", "ins_vn", "ins_vw", "ins_vu")


def ins_solution(f: dict[str, np.ndarray], path: Path) -> dict[str, np.ndarray] | None:
    """The SGL INS columns as ``/ins/solution`` fields (deg, m, NED m/s, deg), or None when
    the file lacks one of them.

    SGL gives the INS position in radians and the velocity north, west and up; the contract
    wants degrees and north, east, down. A file whose INS position is already in degrees is
    recognised against the GNSS position (the unit that lies nearer to it), or, without one,
    by values outside the radian range.
    """
    att = ("ins_roll", "ins_pitch", "ins_yaw")
    if not all(k in f for k in (*INS_COLUMNS, *att)):
        return None
    lat, lon = f["ins_lat"], f["ins_lon"]
    in_radians = bool(np.nanmax(np.abs(lat)) <= np.pi / 2 and np.nanmax(np.abs(lon)) <= np.pi)
    if in_radians and "lat" in f and "lon" in f:
        as_rad = np.nanmedian(np.abs(np.degrees(lat) - f["lat"]))
        as_deg = np.nanmedian(np.abs(lat - f["lat"]))
        in_radians = bool(as_rad <= as_deg)
    if not np.isfinite(lat).any():
        raise AeromagError("no finite INS latitude", file=path, channel="ins_lat")
    scale = 180.0 / np.pi if in_radians else 1.0
    return {
        "latitude_deg": lat * scale,
        "longitude_deg": lon * scale,
        "altitude_m": f["ins_alt"],
        "velocity_north_m_s": f["ins_vn"],
        "velocity_east_m_s": -f["ins_vw"],
        "velocity_down_m_s": -f["ins_vu"],
        "roll_deg": f["ins_roll"],
        "pitch_deg": f["ins_pitch"],
        "yaw_deg": np.mod(f["ins_yaw"], 360.0),
    }


# --------------------------------------------------------------------------------------------
def import_sgl(
    src: str | Path,
    dst: str | Path,
    lines: list[str] | None = None,
    calibration_lines: list[str] | None = None,
) -> dict:
    """Convert an SGL file into a contract MCAP; returns what was written."""
    p = Path(src)
    fields = read_sgl(p)
    t_ns = _times_ns(fields, p)
    keep = t_ns >= 0
    line_vals = fields.get("line")
    if lines:
        if line_vals is None:
            raise AeromagError(
                "--lines given but the file has no line field", file=p, channel="line"
            )
        wanted = {round(float(x), 2) for x in lines}
        keep &= np.isin(np.round(line_vals, 2), list(wanted))
        if not keep.any():
            raise AeromagError(
                f"none of the lines {', '.join(lines)} is in the file", file=p, channel="line"
            )
    order = np.argsort(t_ns[keep], kind="stable")
    idx = np.flatnonzero(keep)[order]
    t = t_ns[idx]
    f = {k: v[idx] for k, v in fields.items()}
    scalars = sorted(k for k in f if re.fullmatch(r"mag_\d_uc", k))
    if not scalars:
        raise AeromagError(
            "no uncompensated scalar magnetometer (mag_N_uc)", file=p, channel="mag_1_uc"
        )
    for k in scalars:
        check_units(k, f[k], p, k)
    fluxes = sorted({m.group(1) for k in f if (m := re.fullmatch(r"flux_([a-d])_x", k))})
    for c in fluxes:
        check_units(
            f"flux_{c}",
            np.linalg.norm(np.column_stack([f[f"flux_{c}_{a}"] for a in "xyz"]), axis=1),
            p,
            f"flux_{c}_x",
        )
    att = ("ins_roll", "ins_pitch", "ins_yaw")
    check_degrees(f, att, p)
    written: dict[str, int] = {}
    with McapOutput(Path(dst)) as out:

        def emit(topic: str, schema: str, rows: Iterable[tuple[int, dict]]) -> None:
            cid = out.channel(topic, schema)
            n = 0
            for tn, payload in rows:
                payload = {"timestamp": stamp(int(tn)), **payload}
                out.write(cid, int(tn), encode(payload))
                n += 1
            written[topic] = n

        def finite(*names):
            return np.all(np.column_stack([np.isfinite(f[n]) for n in names]), axis=1)

        for k in scalars:
            sid = k.split("_")[1]
            ok = finite(k)
            emit(
                f"/mag/scalar/{sid}",
                "aeromag.ScalarField",
                (
                    (tn, {"sensor_id": f"mag_{sid}", "total_nT": float(v)})
                    for tn, v in zip(t[ok], f[k][ok], strict=True)
                ),
            )
        for c in fluxes:
            names = [f"flux_{c}_{a}" for a in "xyz"]
            ok = finite(*names)
            xyz = np.column_stack([f[n][ok] for n in names])
            emit(
                f"/mag/vector/{c}",
                "aeromag.VectorField",
                (
                    (
                        tn,
                        {
                            "sensor_id": f"flux_{c}",
                            "x_nT": float(a),
                            "y_nT": float(b),
                            "z_nT": float(z),
                        },
                    )
                    for tn, (a, b, z) in zip(t[ok], xyz, strict=True)
                ),
            )
        if all(a in f for a in att):
            ok = finite(*att)
            emit(
                "/ins/attitude",
                "aeromag.Attitude",
                (
                    (
                        tn,
                        {"roll_deg": float(r), "pitch_deg": float(pp), "yaw_deg": float(y % 360.0)},
                    )
                    for tn, r, pp, y in zip(
                        t[ok], f["ins_roll"][ok], f["ins_pitch"][ok], f["ins_yaw"][ok], strict=True
                    )
                ),
            )
        ins = ins_solution(f, p)
        if ins is not None:
            ok = np.all(np.isfinite(np.column_stack(list(ins.values()))), axis=1)
            emit(
                "/ins/solution",
                "aeromag.InsSolution",
                (
                    (tn, {k: float(v[i]) for k, v in ins.items()})
                    for i, tn in zip(np.flatnonzero(ok), t[ok], strict=True)
                ),
            )
        alt = next((a for a in ("utm_z", "alt", "ins_alt") if a in f), None)
        if "lat" in f and "lon" in f and alt:
            ok = finite("lat", "lon", alt)
            emit(
                "/gnss/fix",
                "foxglove.LocationFix",
                (
                    (
                        tn,
                        {
                            "frame_id": "gnss",
                            "latitude": float(la),
                            "longitude": float(lo),
                            "altitude": float(h),
                            "position_covariance": [0.0] * 9,
                            "position_covariance_type": 0,
                        },
                    )
                    for tn, la, lo, h in zip(
                        t[ok], f["lat"][ok], f["lon"][ok], f[alt][ok], strict=True
                    )
                ),
            )
        for ref in ("mag_1_c", "diurnal", "igrf"):
            if ref in f:
                ok = finite(ref)
                emit(
                    f"/reference/{ref}",
                    "aeromag.ScalarField",
                    (
                        (tn, {"sensor_id": ref, "total_nT": float(v)})
                        for tn, v in zip(t[ok], f[ref][ok], strict=True)
                    ),
                )
        for k in sorted(f):
            if k.startswith(("cur_", "vol_")):
                ok = finite(k)
                unit = "A" if k.startswith("cur_") else "V"
                emit(
                    f"/aux/{k}",
                    "aeromag.Scalar",
                    (
                        (tn, {"value": float(v), "unit": unit})
                        for tn, v in zip(t[ok], f[k][ok], strict=True)
                    ),
                )
        if line_vals is not None:
            cal = {round(float(x), 2) for x in (calibration_lines or [])}
            lv = np.round(f["line"], 2)
            change = np.r_[True, lv[1:] != lv[:-1]]
            rows = []
            for i in np.flatnonzero(change):
                v = lv[i]
                if not np.isfinite(v) or v == 0:
                    rows.append((t[i], {"line_id": "", "kind": "transit"}))
                else:
                    rows.append(
                        (
                            t[i],
                            {
                                "line_id": f"{v:.2f}",
                                "kind": "calibration" if v in cal else "survey",
                            },
                        )
                    )
            emit("/plan/line", "aeromag.LineMarker", rows)
        out.metadata(
            "aeromag.import", {"source": str(p), "format": "sgl", "samples": str(int(t.size))}
        )
    return {
        "samples": int(t.size),
        "channels": written,
        "span_s": float((t[-1] - t[0]) / 1e9) if t.size else 0.0,
    }
