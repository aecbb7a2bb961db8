"""Recordings that do not follow the channel contract: a topic-mapping file.

A mapping (TOML) names, for each of a recorder's topics, the role it plays and where its
values are in the decoded message; ROS 2 (CDR, ``mcap-ros2-support``), protobuf
(``mcap-protobuf-support``, e.g. Foxglove's ``foxglove.LocationFix``) and JSON channels are
decoded by their MCAP encodings::

    [topics."/imu/mag"]            # sensor_msgs/msg/MagneticField
    role = "vector"                # scalar | vector | attitude | position | base | aux
    fields = ["magnetic_field.x", "magnetic_field.y", "magnetic_field.z"]
    scale = 1e9                    # tesla -> nT
    frame = "flu"                  # ROS REP-103 body axes: x forward, y left, z up

    [topics."/imu/data"]           # sensor_msgs/msg/Imu
    role = "attitude"
    quaternion = "orientation"     # x, y, z, w
    frame = "flu"                  # body FLU in world ENU (REP-103); "frd": body FRD in NED

Our frames: body x forward, y right, z down (FRD); navigation NED. A FLU vector maps to FRD
as (x, -y, -z); a REP-103 orientation (FLU body in ENU) becomes R_ned_frd = T R T' ... see
:func:`quaternion_to_euler_deg`. Times: ``header.stamp`` when the message has one (the
sensor's instant), else the MCAP log time. Scalar values are checked to be an Earth field in
nT after scaling (a missing ``scale = 1e9`` on tesla data is caught).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.defaults import read_toml
from pipeline.errors import AeromagError
from pipeline.io.contract import TopicRule
from pipeline.io.plausibility import check_units
from pipeline.io.series import TopicSeries
from pipeline.io.writer import OutputChannel, write_with_new_channels

ROLES = ("scalar", "vector", "attitude", "position", "base", "aux")
_NFIELDS = {"scalar": 1, "base": 1, "aux": 1, "vector": 3, "position": 3, "attitude": 3}
# world ENU -> NED and body FLU -> FRD: both swap/flip axes and are their own inverses
_ENU_TO_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
_FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])


@dataclass
class TopicMap:
    """How one recorder topic maps to a pipeline role (a ``[topics."<topic>"]`` table).

    Attributes
    ----------
    topic, role : str
        The recorder's topic and its role (see ``ROLES``).
    fields : list of str
        Paths of the values in the decoded message.
    quaternion : str or None
        Path of an (x, y, z, w) orientation (attitude).
    scale : float
        Factor applied to the values (e.g. 1e9: tesla -> nT).
    frame : str
        ``frd`` (body x forward, y right, z down; NED world) or ``flu`` (ROS REP-103 body FLU,
        ENU world).
    unit : str
        Unit label of the values (auxiliary channels).
    name : str
        Sensor id or auxiliary name (default: from the topic).
    """

    topic: str
    role: str
    fields: list[str] = field(default_factory=list)
    quaternion: str | None = None
    scale: float = 1.0
    frame: str = "frd"  # frd | flu
    unit: str = ""
    name: str = ""  # sensor id / aux name (default: from the topic)


@dataclass
class Mapping:
    """A topic-mapping file: the :class:`TopicMap` of each mapped topic and the file's path."""

    topics: dict[str, TopicMap]
    source: str

    @classmethod
    def load(cls, path: str | Path) -> Mapping:
        """Read and check a topic-mapping file (TOML, ``[topics."<topic>"]`` tables).

        Parameters
        ----------
        path : str or Path
            The mapping file.

        Returns
        -------
        Mapping

        Raises
        ------
        AeromagError
            Missing file, invalid TOML, unknown key, role or frame (``frd``: body x forward,
            y right, z down in NED; ``flu``: body x forward, y left, z up in ENU, ROS REP-103),
            wrong field count, or no topic at all.
        """
        p = Path(path)
        doc = read_toml(p, "mapping")
        extra = set(doc) - {"topics"}
        if extra:
            raise AeromagError(f"unknown mapping key {sorted(extra)[0]!r}", file=p)
        out = {}
        allowed = {"role", "fields", "quaternion", "scale", "frame", "unit", "name"}
        for topic, spec in (doc.get("topics") or {}).items():
            bad = set(spec) - allowed
            if bad:
                raise AeromagError(f"unknown key {sorted(bad)[0]!r}", file=p, channel=topic)
            tm = TopicMap(topic, **spec)
            if tm.role not in ROLES:
                raise AeromagError(
                    f"role {tm.role!r}: use one of {', '.join(ROLES)}", file=p, channel=topic
                )
            if tm.frame not in ("frd", "flu"):
                raise AeromagError(f"frame {tm.frame!r}: use frd or flu", file=p, channel=topic)
            need = _NFIELDS[tm.role]
            if not (tm.role == "attitude" and tm.quaternion) and len(tm.fields) != need:
                raise AeromagError(
                    f"role {tm.role} needs {need} field(s)"
                    + (" or a quaternion" if tm.role == "attitude" else ""),
                    file=p,
                    channel=topic,
                )
            out[topic] = tm
        if not out:
            raise AeromagError("the mapping names no topic", file=p)
        return cls(out, str(p))


def get_path(obj: Any, path: str) -> Any:
    """Follow a dotted path (``"header.stamp.sec"``) through dicts and attributes.

    Parameters
    ----------
    obj : Any
        A decoded message (dict for JSON, object for ROS 2 / protobuf).
    path : str
        Field names separated by dots.

    Returns
    -------
    Any
        The value at the end of the path.

    Raises
    ------
    KeyError, AttributeError
        When a part of the path is absent.
    """
    for part in path.split("."):
        obj = obj[part] if isinstance(obj, dict) else getattr(obj, part)
    return obj


def _stamp_ns(msg: Any, log_time: int) -> int:
    try:
        st = get_path(msg, "header.stamp")
    except (AttributeError, KeyError, TypeError):
        return int(log_time)
    sec = get_path(st, "sec")
    nsec = get_path(st, "nanosec") if _has(st, "nanosec") else get_path(st, "nsec")
    return int(sec) * 1_000_000_000 + int(nsec)


def _has(obj: Any, name: str) -> bool:
    return name in obj if isinstance(obj, dict) else hasattr(obj, name)


def quaternion_to_euler_deg(q_xyzw: np.ndarray, frame: str) -> np.ndarray:
    """(roll, pitch, yaw) in degrees, Z-Y-X, body FRD in NED, from quaternions (n, 4).

    ``frame = "flu"``: the quaternion rotates body FLU into world ENU (ROS REP-103), so
    R_ned_frd = T_ned_enu R_enu_flu T_flu_frd.
    """
    from scipy.spatial.transform import Rotation  # here: reading a flight needs no scipy

    r = Rotation.from_quat(np.asarray(q_xyzw, float)).as_matrix()
    if frame == "flu":
        r = _ENU_TO_NED @ r @ _FLU_TO_FRD
    ypr = Rotation.from_matrix(r).as_euler("ZYX", degrees=True)
    return np.column_stack([ypr[:, 2], ypr[:, 1], np.mod(ypr[:, 0], 360.0)])


def decoded_messages(path: Path, topics: list[str]) -> dict[str, list[tuple[int, Any]]]:
    """Decoded messages of ``topics`` (ROS 2, protobuf or JSON), in file order."""
    from mcap.decoder import DecoderFactory
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoder
    from mcap_ros2.decoder import DecoderFactory as Ros2Decoder

    class JsonDecoder(DecoderFactory):
        def decoder_for(self, message_encoding, schema):
            return json.loads if message_encoding == "json" else None

    out: dict[str, list[tuple[int, Any]]] = {t: [] for t in topics}
    try:
        with path.open("rb") as f:
            reader = make_reader(
                f,
                validate_crcs=True,
                decoder_factories=[Ros2Decoder(), ProtobufDecoder(), JsonDecoder()],
            )
            for _s, ch, msg, obj in reader.iter_decoded_messages(
                topics=topics, log_time_order=False
            ):
                out[ch.topic].append((msg.log_time, obj))
    except AeromagError:
        raise
    except Exception as exc:  # noqa: BLE001 - decoder libraries raise many kinds
        raise AeromagError(
            f"could not decode mapped topics ({type(exc).__name__}: "
            f"{' '.join(str(exc).split())[:200]})",
            file=path,
        ) from None
    return out


def mapped_columns(
    tm: TopicMap, msgs: list[tuple[int, Any]], path: Path
) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(time_ns, values, labels) of one mapped topic, in our units and frames."""
    n = len(msgs)
    t = np.array([_stamp_ns(m, lt) for lt, m in msgs], dtype=np.int64)
    try:
        if tm.role == "attitude" and tm.quaternion:
            q = np.array(
                [[float(get_path(get_path(m, tm.quaternion), a)) for a in "xyzw"] for _, m in msgs]
            ).reshape(n, 4)
            vals = quaternion_to_euler_deg(q, tm.frame)
        else:
            vals = (
                np.array([[float(get_path(m, f)) for f in tm.fields] for _, m in msgs]).reshape(
                    n, len(tm.fields)
                )
                * tm.scale
            )
    except (AttributeError, KeyError, TypeError, IndexError) as exc:
        raise AeromagError(
            f"field not found in the message ({exc})", file=path, channel=tm.topic
        ) from None
    if tm.role == "vector" and tm.frame == "flu":
        vals = vals @ _FLU_TO_FRD
    name = tm.name or tm.topic.strip("/").replace("/", "_")
    labels: dict[str, np.ndarray] = {"sensor_id": np.full(n, name, dtype=object)}
    if tm.role in ("scalar", "base"):
        values = {"total_nT": vals[:, 0]}
        _check_nT(values["total_nT"], path, tm.topic)
    elif tm.role == "vector":
        values = {"x_nT": vals[:, 0], "y_nT": vals[:, 1], "z_nT": vals[:, 2]}
        _check_nT(np.linalg.norm(vals, axis=1), path, tm.topic)
    elif tm.role == "attitude":
        values = {"roll_deg": vals[:, 0], "pitch_deg": vals[:, 1], "yaw_deg": vals[:, 2]}
    elif tm.role == "position":
        values = {"latitude": vals[:, 0], "longitude": vals[:, 1], "altitude": vals[:, 2]}
    else:
        values = {"value": vals[:, 0]}
        labels = {"unit": np.full(n, tm.unit, dtype=object)}
    return t, values, labels


def _check_nT(v: np.ndarray, path: Path, topic: str) -> None:

    check_units("the field", v, path, topic)


# --------------------------------------------------------------------------------------------
KNOWN_TYPES = {
    "sensor_msgs/msg/MagneticField": (
        "vector",
        {
            "fields": ["magnetic_field.x", "magnetic_field.y", "magnetic_field.z"],
            "scale": 1e9,
            "frame": "flu",
        },
    ),
    "sensor_msgs/msg/NavSatFix": ("position", {"fields": ["latitude", "longitude", "altitude"]}),
    "sensor_msgs/msg/Imu": ("attitude", {"quaternion": "orientation", "frame": "flu"}),
    "foxglove.LocationFix": ("position", {"fields": ["latitude", "longitude", "altitude"]}),
    "std_msgs/msg/Float64": ("scalar", {"fields": ["data"]}),
}


def suggest_mapping(path: str | Path) -> str:
    """A mapping file for the recorder's topics whose message types are known (TOML text)."""
    from mcap.reader import make_reader

    p = Path(path)
    with p.open("rb") as f:
        summ = make_reader(f).get_summary()
    if summ is None:
        raise AeromagError("no summary section: cannot list the channels", file=p)
    lines = [
        f"# topic mapping suggested by aeromag for {p.name}; check roles, scales and",
        "# frames before use (scalar magnetometers in tesla need scale = 1e9)",
        "",
    ]
    for ch in sorted(summ.channels.values(), key=lambda c: c.topic):
        sc = summ.schemas.get(ch.schema_id)
        name = sc.name if sc else ""
        if name not in KNOWN_TYPES:
            lines.append(f"# {ch.topic}: {name or 'no schema'} ({ch.message_encoding}): not mapped")
            continue
        role, spec = KNOWN_TYPES[name]
        lines.append(f'[topics."{ch.topic}"]  # {name}')
        lines.append(f'role = "{role}"')
        for k, v in spec.items():
            lines.append(f"{k} = {json.dumps(v)}" if not isinstance(v, float) else f"{k} = {v:g}")
        lines.append("")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
CONTRACT_TOPIC = {
    "scalar": ("/mag/scalar", "aeromag.ScalarField"),
    "vector": ("/mag/vector", "aeromag.VectorField"),
    "attitude": ("/ins/attitude", "aeromag.Attitude"),
    "position": ("/gnss/fix", "foxglove.LocationFix"),
    "base": ("/base/scalar", "aeromag.ScalarField"),
    "aux": ("/aux", "aeromag.Scalar"),
}


def import_mapped(src: str | Path, dst: str | Path, mapping: Mapping) -> dict[str, str]:
    """Write ``src`` plus contract channels holding its mapped topics (in nT, FRD/NED):
    every aeromag command then reads the result without the mapping. Returns mapped ->
    contract topic."""

    p = Path(src)
    series = mapped_series(p, mapping)
    used: dict[str, int] = {}
    channels, names = [], {}
    for topic, s in sorted(series.items()):
        base, schema = CONTRACT_TOPIC[s.rule.role]
        k = used.get(base, 0)
        used[base] = k + 1
        if s.rule.role == "aux":
            out_topic = f"/aux/{s.rule.alias}"
        elif s.rule.role in ("scalar", "vector"):
            out_topic = base if k == 0 else f"{base}/{s.rule.alias}"
        else:
            if k:
                raise AeromagError(
                    f"a second {s.rule.role} topic: map only one", file=p, channel=topic
                )
            out_topic = base
        ch = OutputChannel(out_topic, schema)
        for i, tn in enumerate(s.time_ns):
            payload = {f: float(v[i]) for f, v in s.values.items()}
            if s.rule.role in ("scalar", "vector", "base"):
                payload["sensor_id"] = str(s.labels["sensor_id"][i])
            if s.rule.role == "aux":
                payload["unit"] = str(s.labels["unit"][i])
            if s.rule.role == "position":
                payload.update(
                    frame_id="gnss", position_covariance=[0.0] * 9, position_covariance_type=0
                )
            ch.add(int(tn), payload)
        channels.append(ch)
        names[topic] = out_topic
    write_with_new_channels(
        p,
        dst,
        channels,
        metadata={
            "aeromag.import": {"source": str(p), "format": "mapped", "mapping": mapping.source}
        },
    )
    return names


def mapped_series(path: Path, mapping: Mapping) -> dict[str, TopicSeries]:
    """Series of the topics a mapping file names (any encoding), as the reader aligns them."""
    decoded = decoded_messages(path, list(mapping.topics))
    out = {}
    for topic, tm in mapping.topics.items():
        msgs = decoded.get(topic) or []
        if not msgs:
            raise AeromagError(
                "the mapping names this topic but the recording has no message on it",
                file=path,
                channel=topic,
            )
        t, values, labels = mapped_columns(tm, msgs, path)
        order = np.argsort(t, kind="stable")
        t = t[order]
        keep = np.r_[True, np.diff(t) > 0]
        finite = np.all(np.column_stack([np.isfinite(v[order]) for v in values.values()]), axis=1)
        keep &= finite
        problems = []
        if (~keep).any():
            problems.append(f"{int((~keep).sum())} samples dropped (duplicate times or NaN)")
        rule = TopicRule(
            topic, "", tm.role, tuple(values), alias=tm.name or topic.strip("/").replace("/", "_")
        )
        out[topic] = TopicSeries(
            topic,
            rule,
            t[keep],
            {k: v[order][keep] for k, v in values.items()},
            {k: v[order][keep] for k, v in labels.items()},
            problems,
            len(msgs),
        )
    return out
