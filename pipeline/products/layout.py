"""A Foxglove layout for a processed recording.

The layout is the JSON document Foxglove's "Import layout from file" reads: ``configById`` holds
one configuration per panel (key ``<PanelType>!<id>``) and ``layout`` arranges the panel keys in
a mosaic tree of ``{first, second, direction, splitPercentage}`` nodes. Panels refer to data by
message paths (``/topic.field``), so the layout is built from the channels a recording actually
holds: a recording without a vector stage or audit simply gets no such panel.

What it shows (top to bottom, left to right):

- Map: the GNSS track (``foxglove.LocationFix``) and the flight lines (``/map/tracks``, GeoJSON);
  with navigation, the simulated INS (``/nav/ins``) and map-aided (``/nav/map_aided``) tracks.
- 3D: the anomaly grid before and after ARIMA-Kalman filtering (``foxglove.Grid``, frame
  ``local_enu``: x east, y north, metres about the map origin), seen from above; the
  enhancement grids (``aeromag enhance``: RTP, derivatives, tilt, analytic signal, upward
  continuation), when present, one tab each in a Tab panel beside them.
- Plots: recorded (raw), T-L and AGG-TL total field; the interference each model removed;
  the navigation error (INS only, map-aided, CRLB) when ``/nav/error`` exists.
- State transitions: segment label, line and manoeuvre (``/flight/segment``).
- Log (``/aeromag/log``) and the audit findings (``/audit/finding``).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from pipeline.io.schemas import schema
from pipeline.maps.enhance import grid_field_of_topic

_PLAIN_TOPIC = re.compile(r"^[A-Za-z0-9_/]+$")

# the order models are plotted in, with their labels
MODEL_LABELS = {
    "tl16": "T-L (16 terms)",
    "tl18": "T-L (18 terms)",
    "agg-tl": "AGG-TL",
    "tl-plus": "T-L plus term groups",
    "tl-nn": "T-L plus learned residual",
    "extended": "extended model",
}
# the Map panel's tracks: the reference, the simulated INS and the map-aided navigation
TRACK_COLOURS = {"/gnss/fix": "#1f77b4", "/nav/ins": "#ff7f0e", "/nav/map_aided": "#2ca02c"}
COLOURS = ["#7f7f7f", "#1f77b4", "#2ca02c", "#d62728", "#9467bd", "#ff7f0e", "#8c564b"]


def message_path(topic: str, field: str) -> str:
    """Foxglove message path ``/topic.field``; topics with characters outside the plain
    identifier set (``agg-tl``) are quoted, as the path grammar requires."""
    head = topic if _PLAIN_TOPIC.match(topic) else '"' + topic.replace('"', '\\"') + '"'
    return f"{head}.{field}"


def path_topic_field(path: str) -> tuple[str, str]:
    """Inverse of :func:`message_path` (for checks): (topic, first field)."""
    if path.startswith('"'):
        end = path.index('"', 1)
        topic, rest = path[1:end], path[end + 2 :]
    else:
        topic, _, rest = path.partition(".")
    return topic, re.split(r"[.\[{]", rest, maxsplit=1)[0]


def _plot(title: str, series: list[tuple[str, str]], y_label: str) -> dict[str, Any]:
    return {
        "title": title,
        "paths": [
            {
                "value": p,
                "label": label,
                "enabled": True,
                "timestampMethod": "receiveTime",
                "color": COLOURS[k % len(COLOURS)],
            }
            for k, (p, label) in enumerate(series)
        ],
        "showXAxisLabels": True,
        "showYAxisLabels": True,
        "showLegend": True,
        "legendDisplay": "floating",
        "showPlotValuesInLegend": False,
        "isSynced": True,
        "xAxisVal": "timestamp",
        "sidebarDimension": 240,
        "yAxisLabel": y_label,
    }


def _grid_view(
    topic: str, field: str, centre_m: tuple[float, float] | None, span_m: float | None, frame: str
) -> dict[str, Any]:
    camera: dict[str, Any] = {
        "perspective": False,
        "phi": 0.0,
        "thetaOffset": 0.0,
        "fovy": 45.0,
        "near": 0.5,
        "far": 50000.0,
        "distance": max(span_m or 1000.0, 10.0) * 1.2,
        "targetOffset": [*(centre_m or (0.0, 0.0)), 0.0],
        "target": [0.0, 0.0, 0.0],
        "targetOrientation": [0.0, 0.0, 0.0, 1.0],
    }
    return {
        "followTf": frame,
        "followMode": "follow-none",
        "cameraState": camera,
        "scene": {"enableStats": False},
        "layers": {"grid": {"layerId": "foxglove.Grid", "visible": False}},
        "topics": {
            topic: {
                "visible": True,
                "colorField": field,
                "colorMode": "colormap",
                "colorMap": "turbo",
                "frameLocked": True,
            }
        },
        "transforms": {},
        "publish": {"type": "point"},
        "imageMode": {},
    }


def _split(first, second, direction: str, percent: float = 50.0):
    if first is None:
        return second
    if second is None:
        return first
    return {"first": first, "second": second, "direction": direction, "splitPercentage": percent}


def _stack(items: list, direction: str):
    """Equal shares for a list of mosaic nodes."""
    items = [i for i in items if i is not None]
    if not items:
        return None
    if len(items) == 1:
        return items[0]
    return _split(items[0], _stack(items[1:], direction), direction, 100.0 / len(items))


def foxglove_layout(
    channels: Mapping[str, str],
    *,
    grid_centre_m: tuple[float, float] | None = None,
    grid_span_m: float | None = None,
    grid_frame: str = "local_enu",
) -> dict[str, Any]:
    """Foxglove layout for a recording holding ``channels`` (topic -> schema name).

    Parameters
    ----------
    channels
        Every channel of the processed recording, input and output.
    grid_centre_m, grid_span_m
        Centre (east, north, metres in ``grid_frame``) and larger side of the anomaly grid, to
        point the 3D cameras at it; without them the camera looks at the frame origin.
    """
    cfg: dict[str, dict[str, Any]] = {}

    def topics_of(schema_name: str, prefix: str = "") -> list[str]:
        return sorted(t for t, s in channels.items() if s == schema_name and t.startswith(prefix))

    def has_field(topic: str, field: str) -> bool:
        try:
            return field in schema(channels[topic]).get("properties", {})
        except KeyError:
            return False

    fixes = topics_of("foxglove.LocationFix")
    geojson = topics_of("foxglove.GeoJSON")
    map_panel = None
    if fixes or geojson:
        colours = {t: TRACK_COLOURS.get(t, "#1f77b4") for t in fixes}
        cfg["map!aeromag-track"] = {
            "layer": "map",
            "zoomLevel": 15,
            "maxNativeZoom": 18,
            "disabledTopics": [],
            "followTopic": "/gnss/fix" if "/gnss/fix" in fixes else (fixes[0] if fixes else ""),
            "topicColors": {**colours, **{t: "#d62728" for t in geojson}},
        }
        map_panel = "map!aeromag-track"

    grids = [
        t for t in ("/map/anomaly", "/map/anomaly_filtered") if channels.get(t) == "foxglove.Grid"
    ]

    def grid_panel(topic: str, field: str) -> str:
        """A 3D panel of the grid ``topic`` coloured by ``field``; its key."""
        key = f"3D!aeromag-{topic.rsplit('/', 1)[-1].replace('_', '-')}"
        cfg[key] = _grid_view(topic, field, grid_centre_m, grid_span_m, grid_frame)
        return key

    grid_panels = [grid_panel(t, "anomaly_nT") for t in grids]
    # enhancement grids: several of them, so one tab each rather than a row of small panels
    tabs = []
    for t in sorted(channels):
        field = grid_field_of_topic(t) if channels[t] == "foxglove.Grid" else None
        if field is not None:
            title = t.removeprefix("/map/").replace("_", " ")
            tabs.append({"title": title, "layout": grid_panel(t, field)})
    if tabs:
        cfg["Tab!aeromag-enhancements"] = {"activeTabIdx": 0, "tabs": tabs}
        grid_panels.append("Tab!aeromag-enhancements")

    raw = topics_of("aeromag.ScalarField", "/mag/scalar")
    compensated = topics_of("aeromag.CompensatedField", "/mag/compensated")
    per_model = {t.rsplit("/", 1)[-1]: t for t in compensated if t != "/mag/compensated"}
    ordered = [m for m in MODEL_LABELS if m in per_model] + sorted(
        set(per_model) - set(MODEL_LABELS)
    )
    field_series = [
        (message_path(t, "total_nT"), f"raw {t}") for t in raw if has_field(t, "total_nT")
    ]
    field_series += [
        (message_path(per_model[m], "total_nT"), MODEL_LABELS.get(m, m)) for m in ordered
    ]
    if "/mag/compensated" in compensated:
        field_series.append((message_path("/mag/compensated", "total_nT"), "final"))
    plots = []
    if field_series:
        cfg["Plot!aeromag-field"] = _plot(
            "total field: raw, T-L, AGG-TL", field_series, "total field (nT)"
        )
        plots.append("Plot!aeromag-field")
    interference = [
        (message_path(per_model[m], "interference_nT"), MODEL_LABELS.get(m, m)) for m in ordered
    ]
    if interference:
        cfg["Plot!aeromag-interference"] = _plot(
            "platform interference removed", interference, "interference (nT)"
        )
        plots.append("Plot!aeromag-interference")
    if channels.get("/nav/error") == "aeromag.NavigationError":
        cfg["Plot!aeromag-navigation"] = _plot(
            "navigation: horizontal error",
            [
                (message_path("/nav/error", "ins_horizontal_m"), "INS only"),
                (message_path("/nav/error", "map_aided_horizontal_m"), "map-aided"),
                (message_path("/nav/error", "crlb_drms_m"), "CRLB (DRMS)"),
            ],
            "error (m)",
        )
        plots.append("Plot!aeromag-navigation")
    if channels.get("/flight/segment") == "aeromag.Segment":
        cfg["StateTransitions!aeromag-segments"] = {
            "paths": [
                {
                    "value": message_path("/flight/segment", f),
                    "timestampMethod": "receiveTime",
                    "label": f,
                }
                for f in ("label", "line_id", "manoeuvre")
            ],
            "isSynced": True,
        }
        plots.append("StateTransitions!aeromag-segments")

    logs = []
    for t in topics_of("foxglove.Log"):
        key = f"RosOut!aeromag-{t.strip('/').replace('/', '-')}"
        cfg[key] = {"topicToRender": t, "minLogLevel": 1, "searchTerms": [], "nameFilter": {}}
        logs.append(key)
    if channels.get("/audit/finding") == "aeromag.AuditFinding":
        cfg["RawMessages!aeromag-audit"] = {
            "topicPath": "/audit/finding",
            "diffEnabled": False,
            "diffMethod": "custom",
            "diffTopicPath": "",
            "showFullMessageForDiff": False,
            "expansion": "all",
        }
        logs.append("RawMessages!aeromag-audit")

    left = _split(map_panel, _stack(grid_panels, "row"), "column", 55.0)
    right = _split(_stack(plots, "column"), _stack(logs, "row"), "column", 70.0)
    layout = _split(left, right, "row", 45.0)
    return {
        "configById": cfg,
        "globalVariables": {},
        "userNodes": {},
        "linkedGlobalVariables": [],
        "playbackConfig": {"speed": 1.0},
        "layout": layout,
    }


def layout_panels(layout: Any, config: Mapping[str, Any] | None = None) -> list[str]:
    """Panel keys in a mosaic tree, left to right (for checks); with the layout's
    ``configById``, the panels inside Tab panels too (after their Tab panel)."""
    if layout is None:
        return []
    if isinstance(layout, str):
        inner = []
        if config is not None and layout.startswith("Tab!"):
            for tab in config[layout]["tabs"]:
                inner += layout_panels(tab.get("layout"), config)
        return [layout, *inner]
    return layout_panels(layout["first"], config) + layout_panels(layout["second"], config)


def layout_paths(config: Mapping[str, Any]) -> list[str]:
    """Every message path or topic a layout's panels read (for checks)."""
    out: list[str] = []
    for key, c in config.items():
        kind = key.split("!", 1)[0]
        if kind in ("Plot", "StateTransitions"):
            out += [p["value"] for p in c["paths"]]
        elif kind == "RosOut":
            out.append(c["topicToRender"])
        elif kind == "RawMessages":
            out.append(c["topicPath"])
        elif kind == "3D":
            out += list(c["topics"])
        elif kind == "map":
            out += list(c["topicColors"])
    return out


def recording_layout(path) -> dict[str, Any]:
    """The layout for a processed MCAP file: its channels, and the anomaly grid's extent read
    from the first ``/map/anomaly`` message.

    Raises
    ------
    AeromagError
        The file is not a readable MCAP recording.
    """
    import base64
    from pathlib import Path

    import orjson
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    from pipeline.errors import AeromagError

    path = Path(path)
    try:
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            if summary is None:
                raise AeromagError(
                    "no summary section (was it written by aeromag process?)", file=path
                )
            channels = {
                c.topic: summary.schemas[c.schema_id].name
                for c in summary.channels.values()
                if c.schema_id in summary.schemas
            }
            centre = span = None
            if channels.get("/map/anomaly") == "foxglove.Grid":
                for _, _, msg in reader.iter_messages(topics=["/map/anomaly"]):
                    g = orjson.loads(msg.data)
                    rows = len(base64.b64decode(g["data"])) // max(g["row_stride"], 1)
                    w = g["column_count"] * g["cell_size"]["x"]
                    h = rows * g["cell_size"]["y"]
                    p = g["pose"]["position"]
                    centre, span = (p["x"] + w / 2, p["y"] + h / 2), max(w, h)
                    break
    except FileNotFoundError:
        raise AeromagError("file not found", file=path) from None
    except (McapError, ValueError, KeyError, OSError) as exc:
        raise AeromagError(
            f"not a readable MCAP recording ({type(exc).__name__}: {exc})", file=path
        ) from None
    return foxglove_layout(channels, grid_centre_m=centre, grid_span_m=span)


def write_layout(path, out_path) -> list[str]:
    """``aeromag layout``: the layout of the processed recording ``path`` written to
    ``out_path`` (JSON, atomically); returns the panels' kinds, left to right."""
    from pipeline.io.writer import write_json_atomic

    doc = recording_layout(path)
    write_json_atomic(out_path, doc)
    return [k.split("!", 1)[0] for k in layout_panels(doc["layout"], doc["configById"])]
