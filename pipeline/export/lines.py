"""Levelled line data (``/map/lines``) as CSV and as a Geosoft-style XYZ file.

Columns, one row per sample, lines in order and samples by fiducial: ``line``, ``fiducial``
(epoch index in the recording), ``time`` (s since 1970-01-01 UTC), ``lon``, ``lat`` (WGS-84,
degrees), ``x``, ``y`` (easting, northing in the grids' CRS: ``/map/frame``'s, m),
``altitude`` (above the WGS-84 ellipsoid, m), ``raw``, ``compensated``, ``levelled``,
``anomaly`` (nT; see ``aeromag.LineSample`` in ``schemas/``). A missing value is empty in the
CSV and ``*`` in the XYZ.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from pipeline.export.source import MapFrame
from pipeline.io.writer import write_text_atomic

COLUMNS = (
    "line",
    "fiducial",
    "time",
    "lon",
    "lat",
    "x",
    "y",
    "altitude",
    "raw",
    "compensated",
    "levelled",
    "anomaly",
)
# column -> (payload key, decimals)
_FIELDS = {
    "lon": ("longitude", 8),
    "lat": ("latitude", 8),
    "altitude": ("altitude_m", 2),
    "raw": ("raw_nT", 3),
    "compensated": ("compensated_nT", 3),
    "levelled": ("levelled_nT", 3),
    "anomaly": ("anomaly_nT", 3),
}


def line_table(samples: list[tuple[int, dict]], frame: MapFrame) -> dict[str, np.ndarray]:
    """The ``/map/lines`` messages as columns (see the module docstring), ordered by line
    (survey lines, then tie lines, each by id) and fiducial."""
    from pyproj import Transformer

    def col(key: str) -> np.ndarray:
        return np.array([np.nan if p.get(key) is None else p[key] for _, p in samples], float)

    line = np.array([p["line_id"] for _, p in samples], object)
    kind = np.array([p["kind"] for _, p in samples], object)
    fid = np.array([p["fiducial"] for _, p in samples], np.int64)
    out: dict[str, np.ndarray] = {
        "line": line,
        "kind": kind,
        "fiducial": fid,
        "time": np.array([t for t, _ in samples], np.int64) / 1e9,
        **{c: col(key) for c, (key, _) in _FIELDS.items()},
    }
    to_crs = Transformer.from_crs("EPSG:4326", frame.crs, always_xy=True)
    out["x"], out["y"] = (np.asarray(a) for a in to_crs.transform(out["lon"], out["lat"]))
    order = np.lexsort((fid, line.astype(str), kind != "survey"))
    return {k: v[order] for k, v in out.items()}


def _cells(table: dict[str, np.ndarray], missing: str) -> list[list[str]]:
    digits = {"time": 3, "x": 2, "y": 2, **{c: d for c, (_, d) in _FIELDS.items()}}
    cols = []
    for c in COLUMNS:
        v = table[c]
        if c in digits:
            d = digits[c]
            cols.append([missing if not np.isfinite(x) else f"{x:.{d}f}" for x in v])
        else:
            cols.append([str(x) for x in v])
    return [list(r) for r in zip(*cols, strict=True)]


def write_csv(path: str | Path, table: dict[str, np.ndarray]) -> Path:
    """The table as CSV with a header row (missing values empty), written atomically."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(COLUMNS)
    w.writerows(_cells(table, ""))
    return write_text_atomic(path, buf.getvalue())


def write_xyz(path: str | Path, table: dict[str, np.ndarray], frame: MapFrame, title: str) -> Path:
    """The table as a Geosoft-style XYZ file, written atomically.

    ``/`` comment lines (title, units, CRS, then the column names), and per line a header
    ``Line <id>`` (survey) or ``Tie <id>`` (tie) followed by its rows, space-separated and
    right-aligned, ``*`` for a missing value. The line id is the ``line`` column's.
    """
    rows = _cells(table, "*")
    names = COLUMNS[1:]
    width = [
        max(len(n), *(len(r[k + 1]) for r in rows)) if rows else len(n) for k, n in enumerate(names)
    ]
    out = [
        f"/ aeromag levelled line data: {title}",
        f"/ x, y: {frame.crs} (m); lon, lat: WGS-84 (deg); altitude: above the "
        "WGS-84 ellipsoid (m); time: s since 1970-01-01 UTC; raw .. anomaly: nT; dummy *",
        "/ " + " ".join(n.rjust(w) for n, w in zip(names, width, strict=True)),
    ]
    current = None
    for k, r in enumerate(rows):
        if r[0] != current:
            current = r[0]
            out.append(f"{'Tie' if table['kind'][k] == 'tie' else 'Line'} {current}")
        out.append("  " + " ".join(v.rjust(w) for v, w in zip(r[1:], width, strict=True)))
    return write_text_atomic(path, "\n".join(out) + "\n")
