"""The input channel contract (see ``schemas/README.md``).

Every message is JSON (``message_encoding="json"``, schema encoding ``jsonschema``); its MCAP
``log_time`` is the sample instant in ns since the Unix epoch (UTC) and the payload repeats it as
``timestamp: {sec, nsec}``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"


@dataclass(frozen=True)
class TopicRule:
    """One row of the contract: which topics, which schema, which role in the pipeline.

    ``topic`` is matched exactly; when ``prefix`` is true, ``topic/<id>`` matches as well.
    """

    topic: str
    schema_name: str
    role: str
    fields: tuple[str, ...]
    prefix: bool = False
    description: str = ""
    alias: str = ""  # column-name suffix of a mapped topic (see pipeline.io.mapping)
    pattern: str = ""  # regular expression a whole topic may match instead (/map/upward_100m)

    def matches(self, topic: str) -> bool:
        """True when ``topic`` is this rule's topic, or ``<topic>/<id>`` for a prefix rule.

        Parameters
        ----------
        topic : str
            An MCAP topic name, e.g. ``"/mag/scalar/2"``.

        Returns
        -------
        bool
        """
        if topic == self.topic or (self.pattern and re.fullmatch(self.pattern, topic)):
            return True
        sub = topic[len(self.topic) + 1 :]
        return self.prefix and topic.startswith(self.topic + "/") and bool(sub)


# /ins/solution's numeric fields and their units, in the order the reader keeps them
INS_UNITS = {
    "latitude_deg": "deg",
    "longitude_deg": "deg",
    "altitude_m": "m",
    "velocity_north_m_s": "m/s",
    "velocity_east_m_s": "m/s",
    "velocity_down_m_s": "m/s",
    "roll_deg": "deg",
    "pitch_deg": "deg",
    "yaw_deg": "deg",
}
INS_FIELDS = tuple(INS_UNITS)

INPUT_CONTRACT: tuple[TopicRule, ...] = (
    TopicRule(
        "/mag/scalar",
        "aeromag.ScalarField",
        "scalar",
        ("sensor_id", "total_nT"),
        True,
        "scalar (total-field) magnetometer",
    ),
    TopicRule(
        "/mag/vector",
        "aeromag.VectorField",
        "vector",
        ("sensor_id", "x_nT", "y_nT", "z_nT"),
        True,
        "vector magnetometer, body frame x forward, y right, z down (also "
        "/mag/vector/calibrated and /compensated written by aeromag vector)",
    ),
    TopicRule(
        "/ins/attitude",
        "aeromag.Attitude",
        "attitude",
        ("roll_deg", "pitch_deg", "yaw_deg"),
        description="attitude, Z-Y-X Euler angles, yaw = true heading",
    ),
    TopicRule(
        "/ins/solution",
        "aeromag.InsSolution",
        "ins",
        INS_FIELDS,
        description="the INS's own navigation solution (position, NED velocity, attitude), "
        "used by navigate as the recorded INS",
    ),
    TopicRule(
        "/gnss/fix",
        "foxglove.LocationFix",
        "position",
        ("latitude", "longitude", "altitude"),
        description="GNSS position, WGS-84, altitude above the ellipsoid",
    ),
    TopicRule(
        "/base/scalar",
        "aeromag.ScalarField",
        "base",
        ("sensor_id", "total_nT"),
        description="base-station magnetometer",
    ),
    TopicRule(
        "/aux",
        "aeromag.Scalar",
        "aux",
        ("value", "unit"),
        True,
        description="auxiliary channel (currents, voltages, temperatures)",
    ),
    TopicRule(
        "/plan/line",
        "aeromag.LineMarker",
        "plan",
        ("line_id", "kind"),
        description="start of a planned segment",
    ),
    TopicRule(
        "/reference",
        "aeromag.ScalarField",
        "reference",
        ("sensor_id", "total_nT"),
        True,
        description="another processor's product for comparison (e.g. SGL's "
        "compensated mag_1_c, diurnal, igrf); read, never processed",
    ),
)

# Channels aeromag writes. ``inspect`` validates them like input channels; the reader skips them
# (they are results, not measurements) and the writer refuses to write one twice.
OUTPUT_CONTRACT: tuple[TopicRule, ...] = (
    TopicRule(
        "/aeromag/log",
        "foxglove.Log",
        "output",
        ("level", "message"),
        description="human-readable processing log",
    ),
    TopicRule(
        "/flight/segment",
        "aeromag.Segment",
        "output",
        ("label", "line_id"),
        description="segment labels, at each change",
    ),
    TopicRule(
        "/mag/compensated",
        "aeromag.CompensatedField",
        "output",
        ("sensor_id", "total_nT", "interference_nT", "model"),
        True,
        description="compensated scalar field (/mag/compensated/<model> for others)",
    ),
    TopicRule(
        "/mag/despike",
        "aeromag.Spike",
        "output",
        ("sensor_id", "fiducial", "measured_nT", "replaced_nT", "amplitude_nT"),
        description="scalar samples the despike step replaced, one message per spike",
    ),
    TopicRule(
        "/compensation/model",
        "aeromag.CompensationModel",
        "output",
        ("model", "terms", "coefficients"),
        description="fitted compensation models",
    ),
    TopicRule(
        "/map/anomaly",
        "foxglove.Grid",
        "output",
        ("column_count", "data"),
        description="levelled total-field anomaly grid",
    ),
    TopicRule(
        "/map/anomaly_filtered",
        "foxglove.Grid",
        "output",
        ("column_count", "data"),
        description="anomaly grid after the ARIMA + Kalman filter",
    ),
    TopicRule(
        "/map/uncertainty",
        "foxglove.Grid",
        "output",
        ("column_count", "data"),
        description="1-sigma error of the anomaly grid per cell, nT (same cells)",
    ),
    TopicRule(
        "/map/navigability",
        "foxglove.Grid",
        "output",
        ("column_count", "data"),
        description="position CRLB (DRMS, m) of a vehicle flying into each cell",
    ),
    TopicRule(
        "/map/frame",
        "aeromag.MapFrame",
        "output",
        ("frame_id", "crs", "latitude", "longitude", "altitude_m", "utm_epsg"),
        description="georeference of the map grids (projected CRS, origin, UTM zone)",
    ),
    TopicRule(
        "/map/lines",
        "aeromag.LineSample",
        "output",
        ("line_id", "fiducial", "levelled_nT", "anomaly_nT"),
        description="levelled line data the anomaly grid is made from, one message per sample",
    ),
    *(
        TopicRule(
            topic,
            "foxglove.Grid",
            "output",
            ("column_count", "data"),
            description=f"enhancement of the levelled anomaly: {what}",
        )
        for topic, what in (
            ("/map/rtp", "reduced to the pole"),
            ("/map/vertical_derivative", "first vertical derivative"),
            ("/map/horizontal_derivative", "total horizontal derivative"),
            ("/map/tilt", "tilt angle"),
            ("/map/analytic_signal", "analytic signal amplitude"),
        )
    ),
    TopicRule(
        "/map/upward_<H>m",
        "foxglove.Grid",
        "output",
        ("column_count", "data"),
        pattern=r"/map/upward_[0-9]+(\.[0-9]+)?m",
        description="enhancement of the levelled anomaly: upward continued by H m",
    ),
    TopicRule(
        "/map/tracks",
        "foxglove.GeoJSON",
        "output",
        ("geojson",),
        description="flight lines as GeoJSON",
    ),
    TopicRule(
        "/quality/heading_error",
        "aeromag.HeadingErrorPoint",
        "output",
        ("kind", "validation_line", "map_line", "difference_nT"),
        description="validation-vs-map differences at overlap points, per model",
    ),
    TopicRule(
        "/quality/crossovers",
        "aeromag.Crossover",
        "output",
        ("survey_line", "tie_line", "difference_before_nT", "difference_after_nT"),
        description="survey-tie crossover differences before and after leveling",
    ),
    TopicRule(
        "/campaign/flight_offset",
        "aeromag.FlightOffset",
        "output",
        ("flight", "offset_nT", "lines", "crossovers_within", "crossovers_between"),
        description="per-flight level correction of a campaign's joint levelling",
    ),
    TopicRule(
        "/campaign/crossovers",
        "aeromag.CampaignCrossover",
        "output",
        ("kind", "flight_a", "line_a", "flight_b", "line_b", "difference_before_nT"),
        description="crossovers within and between a campaign's flights, before and after",
    ),
    TopicRule(
        "/audit/finding",
        "aeromag.AuditFinding",
        "output",
        ("effect", "accepted", "estimate", "message"),
        description="model-audit findings (effects the baseline misses)",
    ),
    TopicRule(
        "/nav/ins",
        "foxglove.LocationFix",
        "output",
        ("latitude", "longitude", "altitude", "position_covariance"),
        description="simulated INS-only position (aeromag navigate)",
    ),
    TopicRule(
        "/nav/map_aided",
        "foxglove.LocationFix",
        "output",
        ("latitude", "longitude", "altitude", "position_covariance"),
        description="map-aided navigation position (aeromag navigate)",
    ),
    TopicRule(
        "/nav/error",
        "aeromag.NavigationError",
        "output",
        ("ins_north_m", "ins_east_m", "map_aided_north_m", "map_aided_east_m", "crlb_drms_m"),
        description="navigation errors against /gnss/fix and the CRLB",
    ),
    TopicRule(
        "/nav/innovation",
        "aeromag.NavigationInnovation",
        "output",
        ("innovation_nT", "innovation_sigma_nT"),
        description="map measurements used by the navigation filter",
    ),
)

# Roles each processing stage needs; a stage must not demand more than it uses.
FULL_PIPELINE_ROLES = ("scalar", "vector", "attitude", "position")


def rule_for_topic(topic: str) -> TopicRule | None:
    """Contract rule for ``topic`` (input or output), or None for a topic outside the contract
    (kept untouched)."""
    for rule in (*INPUT_CONTRACT, *OUTPUT_CONTRACT):
        if rule.matches(topic):
            return rule
    return None
