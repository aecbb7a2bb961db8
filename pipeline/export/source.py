"""The map products of a processed recording, read back from the MCAP alone.

Every ``foxglove.Grid`` channel under ``/map/`` (``/map/anomaly``, ``/map/anomaly_filtered``,
the enhancements), the georeference ``/map/frame`` and the levelled line samples
``/map/lines``: what the exports and the enhancements start from. Nothing comes from the
summary JSON, so any reader of the MCAP can place the grids the same way.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson

from pipeline.errors import AeromagError
from pipeline.geo.projected import GridFrame, epsg_of
from pipeline.maps.grid import Grid

GRID_SCHEMA = "foxglove.Grid"
FRAME_TOPIC = "/map/frame"
LINES_TOPIC = "/map/lines"
MAKE_MAPS = "`aeromag process` (or `aeromag map`) makes them"


def positive_or_none(value, name: str) -> float | None:
    """``value`` as a positive finite number, None when absent; ValueError otherwise."""
    if value is None:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = float("nan")
    if not (np.isfinite(v) and v > 0):
        raise ValueError(f"{name} must be a positive number, not {value!r}")
    return v


@dataclass(frozen=True)
class MapFrame:
    """Georeference of the grids (``/map/frame``): the projected CRS they were computed in
    and the origin of the ``local_enu`` frame their poses are in.

    ``crs`` is ``EPSG:<code>`` with the origin's easting and northing in it; a recording
    processed before the grids were computed in a projected CRS has the PROJ string of an
    azimuthal equidistant projection about (latitude, longitude) and the origin (0, 0)
    (``legacy``). ``altitude_m`` is the origin's height above the WGS-84 ellipsoid (the mean
    survey altitude); inclination and declination (deg) are the IGRF's at the origin on the
    survey date.
    """

    latitude_deg: float
    longitude_deg: float
    altitude_m: float
    crs: str
    utm_epsg: int
    igrf_inclination_deg: float
    igrf_declination_deg: float
    time_ns: int
    origin_easting_m: float = 0.0
    origin_northing_m: float = 0.0
    # the map error's correlation length along a track, m (None: not recorded)
    error_length_m: float | None = None

    @classmethod
    def from_message(cls, m: dict, time_ns: int) -> MapFrame:
        """From a decoded ``aeromag.MapFrame`` payload (either kind: see the class)."""
        return cls(
            float(m["latitude"]),
            float(m["longitude"]),
            float(m["altitude_m"]),
            str(m["crs"]),
            int(m["utm_epsg"]),
            float(m.get("igrf_inclination_deg", float("nan"))),
            float(m.get("igrf_declination_deg", float("nan"))),
            int(time_ns),
            float(m.get("origin_easting_m", 0.0)),
            float(m.get("origin_northing_m", 0.0)),
            positive_or_none(m.get("error_correlation_length_m"), "error_correlation_length_m"),
        )

    @property
    def legacy(self) -> bool:
        """An older recording's frame: azimuthal equidistant about the origin, no EPSG."""
        return epsg_of(self.crs) is None

    @property
    def epsg(self) -> int | None:
        """EPSG code of ``crs`` (None in an older recording)."""
        return epsg_of(self.crs)

    def grid_frame(self) -> GridFrame:
        """The frame as a :class:`~pipeline.geo.projected.GridFrame` (positions <-> metres)."""
        return GridFrame(self.crs, self.origin_easting_m, self.origin_northing_m, self.altitude_m)

    @property
    def grid_declination_deg(self) -> float:
        """The IGRF declination from grid north (deg): the true one less the meridian
        convergence at the origin (what a reduction to the pole on the grid's axes takes)."""
        return self.igrf_declination_deg - self.grid_frame().convergence_deg()


@dataclass
class MapGrid:
    """One grid channel: its cells (:class:`Grid`, local_enu metres: about the frame's
    origin along its CRS's axes), the name of its value
    field (``anomaly_nT``, ``tilt_deg`` ...) and the message's log time (ns)."""

    topic: str
    grid: Grid
    field_name: str
    time_ns: int

    @property
    def name(self) -> str:
        """The topic below ``/map/`` (``anomaly``, ``upward_100m`` ...): the export name."""
        return self.topic.removeprefix("/map/")

    @property
    def units(self) -> str:
        """UDUNITS string of the values, from the field name's unit suffix."""
        return units_of(self.field_name)


def units_of(field_name: str) -> str:
    """``anomaly_nT`` -> ``nT``, ``..._nT_per_m`` -> ``nT/m``, ``tilt_deg`` -> ``degree``,
    ``navigability_m`` -> ``m``."""
    if field_name.endswith("_nT_per_m"):
        return "nT/m"
    if field_name.endswith("_nT"):
        return "nT"
    if field_name.endswith("_deg"):
        return "degree"
    if field_name.endswith("_m"):
        return "m"
    return "1"


@dataclass
class MapProducts:
    """The map channels of one processed recording."""

    path: Path
    frame: MapFrame
    grids: list[MapGrid]
    lines: list[tuple[int, dict]] = field(default_factory=list)  # (log time ns, payload)

    @property
    def stem(self) -> str:
        """Recording name without ``.processed.mcap`` / ``.mcap``: the export files' stem."""
        name = self.path.name
        for suffix in (".processed.mcap", ".mcap"):
            if name.endswith(suffix):
                return name[: -len(suffix)]
        return self.path.stem

    def grid(self, name: str) -> MapGrid | None:
        """The grid channel ``/map/<name>``, or None."""
        return next((g for g in self.grids if g.name == name), None)


def decode_grid(topic: str, payload: dict, time_ns: int, crs: str = "") -> MapGrid:
    """A ``foxglove.Grid`` message (one FLOAT32 field, as
    :func:`pipeline.products.channels.grid_channel` writes) as a :class:`MapGrid`; the
    pose's position is the south-west corner of the grid.

    Raises
    ------
    ValueError
        Not a single-field FLOAT32 grid with square cells and no rotation.
    """
    fields = payload["fields"]
    if len(fields) != 1 or fields[0]["type"] != 7 or payload.get("cell_stride", 4) != 4:
        raise ValueError("expected one FLOAT32 field per cell")
    cx, cy = payload["cell_size"]["x"], payload["cell_size"]["y"]
    if not np.isclose(cx, cy):
        raise ValueError(f"cells are not square ({cx} x {cy} m)")
    q = payload["pose"]["orientation"]
    if abs(q.get("w", 1.0)) < 1 - 1e-9:
        raise ValueError("rotated grids are not supported")
    nx = int(payload["column_count"])
    raw = np.frombuffer(base64.b64decode(payload["data"]), "<f4")
    stride = int(payload["row_stride"])
    if stride != 4 * nx or raw.size % nx:
        raise ValueError("row stride does not match the column count")
    values = raw.reshape(-1, nx).astype(np.float64)
    p = payload["pose"]["position"]
    grid = Grid(values, float(p["x"]) + cx / 2, float(p["y"]) + cy / 2, float(cx), crs)
    return MapGrid(topic, grid, str(fields[0]["name"]), int(time_ns))


def map_topics(path: Path) -> list[str] | None:
    """The ``/map/*`` topics listed in the recording's summary section (None: no readable
    summary; then every record is scanned). Reading only these keeps a long flight's millions
    of other messages out of memory."""
    from mcap.reader import make_reader

    try:
        with path.open("rb") as f:
            summary = make_reader(f).get_summary()
    except Exception:  # noqa: BLE001 - damaged or not MCAP: the salvaging scan decides
        return None
    if summary is None:
        return None
    return sorted({c.topic for c in summary.channels.values() if c.topic.startswith("/map/")})


def written_map_topics(channels, lines: bool = True) -> dict:
    """The ``/map/*`` channels of ``channels`` (:class:`~pipeline.io.writer.OutputChannel`;
    ``/map/lines`` only with ``lines``) as :func:`~pipeline.io.writer.write_with_new_channels`
    writes them: each message's bytes as the writer encodes them, in log-time order (ties:
    as given), as :func:`~pipeline.io.reader.read_topics` would read them back (topic ->
    ``RawTopic``)."""
    from pipeline.io.contract import MESSAGE_ENCODING, SCHEMA_ENCODING
    from pipeline.io.reader import RawTopic
    from pipeline.io.writer import ColumnMessages, encode, encode_rows

    out = {}
    for c in channels:
        if not c.topic.startswith("/map/") or not len(c.messages):
            continue
        if c.topic == LINES_TOPIC and not lines:
            continue
        times = c.log_times_ns()
        rank = np.argsort(times, kind="stable")
        if isinstance(c.messages, ColumnMessages):  # exact-size bytes, a block at a time
            block = 1 << 14
            data = [
                m
                for b in range(0, rank.size, block)
                for m in encode_rows(
                    c.messages.columns, rank[b : b + block], times[rank[b : b + block]]
                )
            ]
        else:
            data = [encode(c.messages[i][1]) for i in rank.tolist()]
        out[c.topic] = RawTopic(
            c.topic, c.schema_name, SCHEMA_ENCODING, MESSAGE_ENCODING, times[rank].tolist(), data
        )
    return out


def read_map_products(path: str | Path, lines: bool = False, written=None) -> MapProducts:
    """Read the map grids, the frame and (``lines``) the levelled line samples of a processed
    recording.

    ``written``: the map channels just written into ``path`` (:func:`written_map_topics`),
    decoded from the bytes the writer wrote instead of reading the whole file again.

    Raises
    ------
    AeromagError
        No map grid in the recording (``aeromag process`` makes them), no ``/map/frame``
        georeference, or a grid that cannot be decoded.
    """
    from pipeline.io.reader import read_topics

    path = Path(path)
    topics = written if written is not None else read_topics(path, map_topics(path)).topics
    grid_topics = sorted(
        t for t, r in topics.items() if t.startswith("/map/") and r.schema_name == GRID_SCHEMA
    )
    if not grid_topics:
        raise AeromagError(
            f"no map grid in the recording (/map/anomaly, /map/anomaly_filtered): {MAKE_MAPS}",
            file=path,
            channel="/map/anomaly",
        )
    fr = topics.get(FRAME_TOPIC)
    if fr is None or not fr.data:
        raise AeromagError(
            "no map georeference (the recording was processed by an older aeromag): "
            "process the original recording again with `aeromag process`",
            file=path,
            channel=FRAME_TOPIC,
        )
    try:
        frame = MapFrame.from_message(orjson.loads(fr.data[0]), fr.log_time_ns[0])
    except (orjson.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise AeromagError(
            f"unreadable map frame ({type(exc).__name__}: {exc})", file=path, channel=FRAME_TOPIC
        ) from None
    grids = []
    for t in grid_topics:
        raw = topics[t]
        try:
            grids.append(
                decode_grid(
                    t, orjson.loads(raw.data[-1]), raw.log_time_ns[-1], frame.grid_frame().grid_crs
                )
            )
        except (orjson.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise AeromagError(
                f"unreadable map grid ({type(exc).__name__}: {exc})", file=path, channel=t
            ) from None
    # the grids on the frame: anomaly first, then the others by name
    grids.sort(key=lambda g: (g.name != "anomaly", g.name != "anomaly_filtered", g.name))
    out = MapProducts(path, frame, grids)
    if lines:
        lr = topics.get(LINES_TOPIC)
        if lr is None or not lr.data:
            raise AeromagError(
                f"no levelled line data in the recording: {MAKE_MAPS}",
                file=path,
                channel=LINES_TOPIC,
            )
        out.lines = sorted(
            zip(lr.log_time_ns, (orjson.loads(d) for d in lr.data), strict=True),
            key=lambda tm: tm[0],
        )
    return out
