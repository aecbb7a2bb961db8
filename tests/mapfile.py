"""A small synthetic processed recording with map channels (export and enhancement tests).

The anomaly is an analytic field of the frame's east/north metres, so exported cells can be
compared with it anywhere; a corner of the grid is masked (NaN). ``legacy=True`` writes the
``/map/frame`` of recordings processed before the grids were computed in a projected CRS
(azimuthal equidistant about the origin, no EPSG code, no origin easting/northing), as those
recordings hold it.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np

from pipeline.geo.local import LocalFrame
from pipeline.geo.projected import GridFrame, survey_frame, utm_epsg
from pipeline.io.writer import McapOutput, encode
from pipeline.maps.grid import Grid
from pipeline.products.channels import MAP_FRAME, grid_channel, map_frame_channel

LAT0, LON0, ALT0 = 34.26, 108.9, 500.0
T0 = 1_781_485_840_000_000_000
CELL = 25.0


def field_nT(east_m, north_m):
    """The synthetic anomaly, nT, smooth on the scale of a few cells."""
    e, n = np.asarray(east_m, float), np.asarray(north_m, float)
    return 50.0 * np.sin(e / 300.0) * np.cos(n / 400.0) + 0.02 * e


def map_frame(legacy: bool = False) -> LocalFrame | GridFrame:
    """The frame the synthetic grid is in: the survey's UTM zone (EPSG:32649) about a round
    origin near (LAT0, LON0), or (``legacy``) the older azimuthal equidistant frame."""
    if legacy:
        return LocalFrame(LAT0, LON0, ALT0)
    return survey_frame([LAT0], [LON0], [ALT0])


def synthetic_grid(ny: int = 30, nx: int = 40, legacy: bool = False) -> Grid:
    frame = map_frame(legacy)
    east0, north0 = -CELL * (nx // 2), -CELL * (ny // 2)
    e = east0 + CELL * np.arange(nx)
    n = north0 + CELL * np.arange(ny)
    ee, nn = np.meshgrid(e, n)
    v = field_nT(ee, nn)
    v[-5:, :6] = np.nan  # uncovered north-west corner
    return Grid(v, east0, north0, CELL, frame.crs if legacy else frame.grid_crs)


def frame_payload(legacy: bool = False) -> dict:
    """``/map/frame``: the map stage's writer's payload, or (``legacy``) the older fields."""
    if not legacy:
        run = SimpleNamespace(frame=map_frame(), main_field=(53000.0, 53.3, -4.2))
        return map_frame_channel(run, T0).messages[0][1]
    frame = LocalFrame(LAT0, LON0, ALT0)
    return {
        "frame_id": MAP_FRAME,
        "crs": frame.crs,
        "latitude": LAT0,
        "longitude": LON0,
        "altitude_m": ALT0,
        "utm_epsg": utm_epsg(LAT0, LON0),
        "igrf_inclination_deg": 53.3,
        "igrf_declination_deg": -4.2,
        "igrf_total_nT": 53000.0,
    }


def line_payloads(grid: Grid, legacy: bool = False) -> list[tuple[int, dict]]:
    """Samples along two survey lines (east-west) and a tie line (north-south)."""
    frame = map_frame(legacy)
    out = []
    k = 0
    tracks = [
        ("L0010", "survey", np.linspace(-400, 400, 30), np.full(30, -100.0)),
        ("L0020", "survey", np.linspace(400, -400, 30), np.full(30, 100.0)),
        ("T0010", "tie", np.full(20, 50.0), np.linspace(-300, 300, 20)),
    ]
    for line, kind, e, n in tracks:
        lat, lon, _ = frame.to_geodetic(e, n)
        for i in range(e.size):
            a = float(field_nT(e[i], n[i]))
            out.append(
                (
                    T0 + k * 100_000_000,
                    {
                        "line_id": line,
                        "kind": kind,
                        "fiducial": k,
                        "latitude": float(lat[i]),
                        "longitude": float(lon[i]),
                        "altitude_m": ALT0,
                        "east_m": float(e[i]),
                        "north_m": float(n[i]),
                        "raw_nT": None if k == 3 else 53000.0 + a,
                        "compensated_nT": 52990.0 + a,
                        "levelled_nT": 52990.0 + a,
                        "anomaly_nT": a,
                    },
                )
            )
            k += 1
    return out


def uncertainty_of(grid: Grid) -> Grid:
    """A ``/map/uncertainty`` for ``grid``: 0.3 nT growing with the field's size, same mask."""
    return grid.with_values(0.3 + 0.01 * np.abs(grid.values))


# the map error's correlation length a recording with /map/uncertainty states, m
ERROR_LENGTH_M = 120.0


def write_processed(
    path: Path,
    frame: bool = True,
    lines: bool = True,
    grids: bool = True,
    legacy: bool = False,
    uncertainty: bool = False,
) -> tuple[Path, Grid]:
    """A recording holding ``/map/frame``, ``/map/anomaly``, ``/map/anomaly_filtered`` and
    ``/map/lines`` (each optional; ``uncertainty``: ``/map/uncertainty`` too,
    :func:`uncertainty_of`, and the frame's ``error_correlation_length_m``) plus one scalar
    sample; ``legacy``: as processed before the grids were computed in a projected CRS."""
    grid = synthetic_grid(legacy=legacy)
    with McapOutput(path) as out:
        cid = out.channel("/mag/scalar", "aeromag.ScalarField")
        out.write(
            cid,
            T0,
            encode(
                {
                    "timestamp": {"sec": T0 // 10**9, "nsec": 0},
                    "sensor_id": "s",
                    "total_nT": 53000.0,
                }
            ),
        )
        if frame:
            p = {"timestamp": {"sec": T0 // 10**9, "nsec": 0}, **frame_payload(legacy)}
            if uncertainty:
                p["error_correlation_length_m"] = ERROR_LENGTH_M
            out.write(out.channel("/map/frame", "aeromag.MapFrame"), T0, encode(p))
        if grids:
            chosen = [
                ("/map/anomaly", grid, "anomaly_nT"),
                ("/map/anomaly_filtered", grid, "anomaly_nT"),
            ]
            if uncertainty:
                chosen.append(("/map/uncertainty", uncertainty_of(grid), "uncertainty_nT"))
            for topic, g, name in chosen:
                ch = grid_channel(topic, T0, g, name)
                t, p = ch.messages[0]
                out.write(out.channel(topic, "foxglove.Grid"), t, encode(p))
        if lines:
            cid = out.channel("/map/lines", "aeromag.LineSample")
            for t, p in line_payloads(grid, legacy):
                p = {"timestamp": {"sec": t // 10**9, "nsec": t % 10**9}, **p}
                out.write(cid, t, encode(p))
    return path, grid
