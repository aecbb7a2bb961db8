"""The sorties of a campaign: processed recordings found, checked and read into one frame.

A sortie is one processed flight (``<name>.processed.mcap``, written by ``aeromag process``):
what the campaign takes from it is its levelled line data (``/map/lines``) and georeference
(``/map/frame``), read back from the MCAP alone like the exports. Checks come first and cost
little (the recording's summary section, the frame and the anomaly grid): no processed
recording, a recording without map channels, or flights over disjoint areas are refused in one
line before any line data is read.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from pipeline.errors import AeromagError
from pipeline.export.source import FRAME_TOPIC, LINES_TOPIC, MAKE_MAPS, MapFrame, decode_grid
from pipeline.geo.heading import pattern_direction_deg
from pipeline.geo.projected import GridFrame, survey_frame
from pipeline.maps.level import Line

PROCESSED_SUFFIX = ".processed.mcap"
GRID_TOPIC = "/map/anomaly"
# every one of these must be in a sortie: the line data levelled, its georeference, the grid
# whose covered cells give the survey's bounding box
REQUIRED_TOPICS = (FRAME_TOPIC, LINES_TOPIC, GRID_TOPIC)


@dataclass(frozen=True)
class SortieInfo:
    """What the checks learn of a sortie: its name (the recording's without
    ``.processed.mcap``), path, georeference and the bounding box of its covered grid cells
    (WGS-84 degrees)."""

    name: str
    path: Path
    frame: MapFrame
    lat_range_deg: tuple[float, float]
    lon_range_deg: tuple[float, float]


@dataclass
class Sortie:
    """One flight's levelled lines in the campaign frame.

    ``lines`` carry ``line_id`` = ``"<flight index>:<line id>"`` (unique in the campaign),
    east/north m in the campaign frame, time s since 1970 (UTC) and the flight's levelled
    anomaly (``/map/lines`` ``anomaly_nT``).
    """

    index: int
    name: str
    path: Path
    lines: list[Line]
    kinds: dict[str, str]  # line_id -> survey | tie
    heading_deg: float  # survey-line direction, 0..180 east of north
    spacing_m: float  # median spacing of the survey lines
    time_range_s: tuple[float, float]
    samples: int
    # line key -> the other /map/lines columns of its samples, in the line's order: time_ns
    # (the messages' log times), latitude, longitude, altitude_m, raw_nT (NaN: none),
    # compensated_nT, levelled_nT (as the flight levelled itself)
    columns: dict[str, dict[str, np.ndarray]] = field(repr=False, default_factory=dict)

    def survey_box_m(self) -> tuple[float, float, float, float]:
        """(east min, east max, north min, north max) of the survey and tie samples, m."""
        e = np.concatenate([ln.east_m for ln in self.lines])
        n = np.concatenate([ln.north_m for ln in self.lines])
        return float(e.min()), float(e.max()), float(n.min()), float(n.max())


def sortie_name(path: Path) -> str:
    """``DAY1.processed.mcap`` -> ``DAY1``."""
    return path.name.removesuffix(PROCESSED_SUFFIX)


def find_processed(folder: str | Path) -> list[Path]:
    """The processed recordings under ``folder`` (recursively, by name; hidden and partial
    files left out).

    Raises
    ------
    AeromagError
        ``folder`` is not a folder, or holds no processed recording.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise AeromagError("not a folder", file=folder)
    found = [
        p
        for p in sorted(folder.rglob(f"*{PROCESSED_SUFFIX}"))
        if not p.name.startswith(".") and p.is_file()
    ]
    if not found:
        raise AeromagError(
            f"no processed recordings (*{PROCESSED_SUFFIX}) in the folder: `aeromag process` "
            "makes them (with /map/lines and /map/frame) from each flight recording",
            file=folder,
        )
    return found


def _topics(path: Path) -> set[str] | None:
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - damaged or not MCAP: the salvaging reader decides
        return None
    return None if summary is None else {c.topic for c in summary.channels.values()}


def check_sortie(path: str | Path) -> SortieInfo:
    """Check that a processed recording has the map channels a campaign needs, and read its
    georeference and bounding box.

    Raises
    ------
    AeromagError
        A map channel is missing (naming it; ``aeromag process`` makes them) or unreadable.
    """
    from pipeline.io.reader import read_topics

    path = Path(path)
    topics = _topics(path)
    if topics is None:  # no summary section: the (salvaging) scan lists what is there
        topics = set(read_topics(path, REQUIRED_TOPICS).topics)
    missing = [t for t in REQUIRED_TOPICS if t not in topics]
    if missing:
        raise AeromagError(
            f"no map channels {', '.join(missing)} in the recording: a campaign merges the "
            f"levelled line data of processed flights; {MAKE_MAPS}",
            file=path,
            channel=missing[0],
        )
    rec = read_topics(path, [FRAME_TOPIC, GRID_TOPIC])
    try:
        fr, gr = rec.topics[FRAME_TOPIC], rec.topics[GRID_TOPIC]
        frame = MapFrame.from_message(orjson.loads(fr.data[0]), fr.log_time_ns[0])
        grid = decode_grid(GRID_TOPIC, orjson.loads(gr.data[-1]), gr.log_time_ns[-1]).grid
    except (KeyError, IndexError, TypeError, ValueError, orjson.JSONDecodeError) as exc:
        raise AeromagError(
            f"unreadable map channels ({type(exc).__name__}: {exc})", file=path, channel=GRID_TOPIC
        ) from None
    covered = np.isfinite(grid.values)
    if not covered.any():
        raise AeromagError("the anomaly grid has no covered cell", file=path, channel=GRID_TOPIC)
    east, north = grid.coordinates()
    rows, cols = np.flatnonzero(covered.any(axis=1)), np.flatnonzero(covered.any(axis=0))
    half = grid.cell_m / 2
    ce = [east[cols[0]] - half, east[cols[-1]] + half]
    cn = [north[rows[0]] - half, north[rows[-1]] + half]
    lat, lon, _ = frame.grid_frame().to_geodetic(np.repeat(ce, 2), np.tile(cn, 2))
    return SortieInfo(
        sortie_name(path),
        path,
        frame,
        (float(lat.min()), float(lat.max())),
        (float(lon.min()), float(lon.max())),
    )


def campaign_frame(infos: list[SortieInfo], epsg: int | None = None) -> GridFrame:
    """The common frame (:func:`pipeline.geo.projected.survey_frame`): the projected CRS
    ``epsg`` (``map.crs``) or the UTM zone of the centre of the sorties' joint bounding box,
    origin near that centre, "up" zero at the mean of their observation heights (m above
    the ellipsoid)."""
    lat = np.array([v for i in infos for v in i.lat_range_deg for _ in range(2)])
    lon = np.array([v for i in infos for _ in range(2) for v in i.lon_range_deg])
    frame = survey_frame(lat, lon, 0.0, epsg)
    alt0 = float(np.mean([i.frame.altitude_m for i in infos]))
    return GridFrame(
        frame.crs, frame.origin_east_m, frame.origin_north_m, alt0, frame.note, frame.zones
    )


def _box_m(info: SortieInfo, frame: GridFrame) -> tuple[float, float, float, float]:
    la, lo = info.lat_range_deg, info.lon_range_deg
    e, n, _ = frame.to_enu(np.repeat(la, 2), np.tile(lo, 2))
    return float(e.min()), float(e.max()), float(n.min()), float(n.max())


def overlap_groups(infos: list[SortieInfo], frame: GridFrame) -> list[list[int]]:
    """The sorties grouped by overlap: two are in one group when their bounding boxes
    overlap or touch, directly or through others (connected components)."""
    boxes = [_box_m(i, frame) for i in infos]
    parent = list(range(len(infos)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    for a in range(len(boxes)):
        for b in range(a + 1, len(boxes)):
            ea0, ea1, na0, na1 = boxes[a]
            eb0, eb1, nb0, nb1 = boxes[b]
            if ea0 <= eb1 and eb0 <= ea1 and na0 <= nb1 and nb0 <= na1:
                parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for k in range(len(infos)):
        groups.setdefault(root(k), []).append(k)
    return sorted(groups.values())


def validate_campaign(folder: str | Path) -> list[SortieInfo]:
    """Every processed recording of ``folder``, checked: at least two, each with its map
    channels, all over one area (bounding boxes overlapping or touching, directly or through
    other flights).

    Raises
    ------
    AeromagError
        One line naming what is missing, or the flights of disjoint areas.
    """
    folder = Path(folder)
    paths = find_processed(folder)
    if len(paths) < 2:
        raise AeromagError(
            f"a campaign needs 2 or more processed recordings; found only {paths[0].name}",
            file=folder,
        )
    infos = [check_sortie(p) for p in paths]
    names = [i.name for i in infos]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise AeromagError(
            f"two processed recordings named {', '.join(dup)}: flight names must be unique",
            file=folder,
        )
    groups = overlap_groups(infos, campaign_frame(infos))
    if len(groups) > 1:
        text = " | ".join(", ".join(infos[k].name for k in g) for g in groups)
        raise AeromagError(
            f"recordings of disjoint areas in one campaign: {text} (their survey bounding "
            "boxes neither overlap nor touch); make one campaign per area",
            file=folder,
        )
    return infos


def _direction(east: np.ndarray, north: np.ndarray) -> np.ndarray:
    xy = np.column_stack([east, north])
    return np.linalg.svd(xy - xy.mean(axis=0), full_matrices=False)[2][0]


def line_spacing_m(lines: list[Line], kinds: dict[str, str]) -> tuple[float, float]:
    """(heading deg 0..180, median spacing m) of the survey lines: the mean axis of their
    principal axes, and the median gap between their cross-track positions (as the map
    stage measures it)."""
    survey = [ln for ln in lines if kinds[ln.line_id] == "survey"]
    if not survey:
        return float("nan"), float("nan")
    heads = []
    for ln in survey:
        d = _direction(ln.east_m, ln.north_m)
        heads.append(np.degrees(np.arctan2(d[0], d[1])) % 180.0)
    # their axis (a median of angles mod 180 straddles 0/180 on north-south lines)
    heading = float(np.mod(pattern_direction_deg(np.array(heads), fold=2), 180.0))
    along = np.array([np.sin(np.radians(heading)), np.cos(np.radians(heading))])
    across = np.array([along[1], -along[0]])
    offs = np.sort([np.median(ln.east_m * across[0] + ln.north_m * across[1]) for ln in survey])
    gaps = np.diff(offs)
    gaps = gaps[gaps > 1e-6]
    return heading, float(np.median(gaps)) if gaps.size else float("nan")


def read_sortie(index: int, info: SortieInfo, frame: GridFrame) -> Sortie:
    """Read a sortie's levelled line samples (``/map/lines``) into the campaign frame.

    Parameters
    ----------
    index : int
        The flight's number in the campaign (line ids become ``"<index>:<line id>"``).
    info : SortieInfo
        From :func:`check_sortie`.
    frame : GridFrame
        The campaign frame (:func:`campaign_frame`).

    Raises
    ------
    AeromagError
        No line data, or lines without positions or values.
    """
    from pipeline.export.source import read_map_products

    mp = read_map_products(info.path, lines=True)
    samples = mp.lines
    try:
        lid = np.array([p["line_id"] for _, p in samples], object)
        kind = np.array([p["kind"] for _, p in samples], object)
        fid = np.array([p["fiducial"] for _, p in samples], np.int64)
        lat = np.array([p["latitude"] for _, p in samples], float)
        lon = np.array([p["longitude"] for _, p in samples], float)
        alt = np.array([p.get("altitude_m", np.nan) for _, p in samples], float)
        val = np.array([p["anomaly_nT"] for _, p in samples], float)
        comp = np.array([p["compensated_nT"] for _, p in samples], float)
        lev = np.array([p["levelled_nT"] for _, p in samples], float)
        raw = np.array([np.nan if p.get("raw_nT") is None else p["raw_nT"] for _, p in samples])
    except (KeyError, TypeError, ValueError) as exc:
        raise AeromagError(
            f"unreadable line samples ({type(exc).__name__}: {exc})",
            file=info.path,
            channel=LINES_TOPIC,
        ) from None
    t_ns = np.array([tn for tn, _ in samples], np.int64)
    t = t_ns / 1e9
    e, n, _ = frame.to_enu(lat, lon)
    lines, kinds, columns = [], {}, {}
    for line in sorted(set(lid)):
        ix = np.flatnonzero((lid == line) & np.isfinite(val) & np.isfinite(e))
        if ix.size < 10:
            continue
        ix = ix[np.argsort(fid[ix], kind="stable")]
        key = f"{index}:{line}"
        kinds[key] = str(kind[ix[0]])
        lines.append(Line(key, kinds[key], e[ix], n[ix], t[ix], val[ix], fid[ix]))
        columns[key] = {
            "time_ns": t_ns[ix],
            "latitude": lat[ix],
            "longitude": lon[ix],
            "altitude_m": alt[ix],
            "raw_nT": raw[ix].astype(float),
            "compensated_nT": comp[ix],
            "levelled_nT": lev[ix],
        }
    if not lines:
        raise AeromagError("no line with 10 or more samples", file=info.path, channel=LINES_TOPIC)
    heading, spacing = line_spacing_m(lines, kinds)
    return Sortie(
        index,
        info.name,
        info.path,
        lines,
        kinds,
        heading,
        spacing,
        (float(t.min()), float(t.max())),
        int(sum(ln.east_m.size for ln in lines)),
        columns,
    )
