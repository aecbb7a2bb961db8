"""Recording -> typed, aligned columns.

Reading happens in three steps, each usable on its own:

1. :func:`read_topics` — one pass over the MCAP file, raw payloads grouped by topic;
2. :func:`decode_topic` — contract topics decoded to numpy arrays, with a list of problems;
3. :func:`read_flight` — every decoded stream interpolated onto the scalar magnetometer's
   epochs (the sensors run at their own rates and clocks), gaps detected and reported.

Topics outside the contract are kept as raw records (the writer copies every input record
unchanged anyway); they are listed, never dropped silently.
"""

from __future__ import annotations

import gc
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import orjson
import pandas as pd

from pipeline.errors import AeromagError, missing_file
from pipeline.flight import Flight  # moved to pipeline.flight; re-exported here
from pipeline.io.contract import (
    INS_FIELDS,
    INS_UNITS,
    MESSAGE_ENCODING,
    TopicRule,
    rule_for_topic,
)
from pipeline.io.mapping import mapped_series
from pipeline.io.plausibility import check_degrees, check_units
from pipeline.io.scan import ScanError, scan_mcap
from pipeline.io.schemas import schema
from pipeline.io.series import NS, Gap, Loss, TopicSeries


# --------------------------------------------------------------------------------------------
# 1. raw pass
# --------------------------------------------------------------------------------------------
@dataclass
class RawTopic:
    """All messages of one topic, in file order."""

    topic: str
    schema_name: str
    schema_encoding: str
    message_encoding: str
    log_time_ns: list[int] = field(default_factory=list)
    data: list[bytes] = field(default_factory=list)

    @property
    def count(self) -> int:
        """Number of messages read on the topic."""
        return len(self.data)


@dataclass
class RawRecording:
    """The raw pass over a recording: the messages of each topic, whether the file has a summary
    section, and the damage salvaged around (``losses``).
    """

    path: Path
    topics: dict[str, RawTopic]
    has_summary: bool
    losses: list[Loss] = field(default_factory=list)  # damage salvaged around

    def loss_notes(self, t0_ns: int | None = None) -> list[str]:
        """One ``"salvaged: ..."`` line per damaged part of the file.

        Parameters
        ----------
        t0_ns : int, optional
            Reference instant (ns, UTC) for times given relative to the start of the recording.

        Returns
        -------
        list of str
        """
        return [f"salvaged: {x.describe(t0_ns)}" for x in self.losses]


def read_topics(path: str | Path, topics: Iterable[str] | None = None) -> RawRecording:
    """Read the raw payloads of a recording, grouped by topic.

    Damage is salvaged, not fatal: a truncated file, a chunk whose CRC does not match, a chunk
    declaring an absurd size or a malformed record loses only itself; every intact chunk is
    read and each loss is listed in ``losses`` (see :mod:`pipeline.io.scan`).

    Parameters
    ----------
    path
        MCAP file; opened read-only.
    topics
        Only these topics (default: all).

    Raises
    ------
    AeromagError
        The file is missing, empty, not MCAP, or nothing at all could be read from it.
    """
    path = Path(path)
    if not path.is_file():
        raise missing_file(path)
    wanted = set(topics) if topics is not None else None
    try:
        sc = scan_mcap(path, wanted)
    except ScanError as exc:
        raise AeromagError(str(exc), file=path) from None
    except OSError as exc:
        raise AeromagError(
            f"cannot read the file ({type(exc).__name__}: {exc})", file=path
        ) from None
    if not sc.channels and sc.losses:
        raise AeromagError(
            "not a readable MCAP recording (no intact channel or message; "
            + "; ".join(x.describe() for x in sc.losses[:2])
            + ")",
            file=path,
        )
    out: dict[str, RawTopic] = {}
    for ch in sc.channels.values():
        if wanted is not None and ch.topic not in wanted:
            continue
        name, enc = sc.schema_of(ch)
        raw = out.get(ch.topic)
        if raw is None:
            out[ch.topic] = RawTopic(
                ch.topic, name, enc, ch.message_encoding, ch.log_time_ns, ch.data
            )
        else:  # two channels on one topic: merged, decode_topic sorts by time
            raw.log_time_ns.extend(ch.log_time_ns)
            raw.data.extend(ch.data)
    losses = list(sc.losses)
    if sc.orphan_messages:
        losses.append(
            Loss(0, f"{sc.orphan_messages} messages on channels whose definition was lost")
        )
    return RawRecording(path=path, topics=out, has_summary=sc.summary_seen, losses=losses)


# --------------------------------------------------------------------------------------------
# 2. decoding
# --------------------------------------------------------------------------------------------
def _string_fields(schema_name: str) -> set[str]:
    """Fields the schema declares as strings (the rest of a rule's fields are numbers)."""
    props = schema(schema_name).get("properties", {})
    return {k for k, v in props.items() if v.get("type") == "string"}


@contextmanager
def _gc_paused():
    """Decoding builds millions of small dicts; each burst of allocations triggers Python's
    cyclic garbage collector, which then walks every live object (4x the decoding time on a
    2 h flight). None of these objects form cycles, so collection waits until we are done."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def decode_topic(raw: RawTopic, rule: TopicRule) -> TopicSeries:
    """Decode one topic's JSON payloads into arrays.

    Messages that cannot be decoded, lack a field, have a wrong type, or carry a non-finite
    value are dropped and counted in ``problems``; so are duplicate timestamps (first kept).
    A payload ``timestamp`` that disagrees with ``log_time`` is reported, ``log_time`` is used.
    """
    problems: list[str] = []
    if raw.schema_name != rule.schema_name:
        problems.append(f"schema is {raw.schema_name!r}, the contract says {rule.schema_name!r}")
    if raw.message_encoding != MESSAGE_ENCODING:
        problems.append(f"message encoding is {raw.message_encoding!r}, expected 'json'")
        return TopicSeries(raw.topic, rule, np.zeros(0, np.int64), {}, {}, problems, raw.count)
    string_fields = _string_fields(rule.schema_name)
    numeric = [f for f in rule.fields if f not in string_fields]
    strings = [f for f in rule.fields if f in string_fields]
    n = raw.count
    with _gc_paused():
        fast = _decode_columns(raw, numeric, strings)
        if fast is not None:
            t, vals, labs, ok, bad_stamp = fast
            bad_decode = bad_field = 0
            first_bad = None
        else:
            t, vals, labs, ok, bad_decode, bad_field, bad_stamp, first_bad = _decode_each(
                raw, numeric, strings
            )
    if bad_decode:
        problems.append(f"{bad_decode} of {n} messages are not valid JSON (dropped)")
    if bad_field:
        problems.append(
            f"{bad_field} of {n} messages do not match the schema: {first_bad} (dropped)"
        )
    if bad_stamp:
        problems.append(
            f"{bad_stamp} of {n} messages have a payload timestamp that differs "
            "from log_time (log_time used)"
        )
    finite = np.ones(n, bool)
    for f in numeric:
        finite &= np.isfinite(vals[f])
    n_nonfinite = int((ok & ~finite).sum())
    if n_nonfinite:
        problems.append(f"{n_nonfinite} of {n} messages carry NaN or infinite values (dropped)")
    keep = ok & finite
    idx = np.flatnonzero(keep)
    order = idx[np.argsort(t[idx], kind="stable")]
    if order.size and np.any(np.diff(t[idx]) < 0):
        problems.append("messages are not in time order (sorted)")
    tt = t[order]
    dup = np.zeros(tt.size, bool)
    dup[1:] = tt[1:] == tt[:-1]
    if dup.any():
        problems.append(f"{int(dup.sum())} duplicated timestamps (first kept)")
    dropped = np.concatenate([t[~keep], tt[dup]])
    order = order[~dup]
    return TopicSeries(
        topic=raw.topic,
        rule=rule,
        time_ns=t[order],
        values={f: v[order] for f, v in vals.items()},
        labels={f: np.asarray(v, dtype=object)[order] for f, v in labs.items()},
        problems=problems,
        n_messages=n,
        dropped_ns=dropped,
    )


def _decode_each(raw: RawTopic, numeric: list[str], strings: list[str]):
    """Message by message: slow, but tells exactly which messages are bad and why."""
    n = raw.count
    t = np.zeros(n, np.int64)
    vals = {f: np.full(n, np.nan) for f in numeric}
    labs: dict[str, list[str]] = {f: [""] * n for f in strings}
    ok = np.zeros(n, bool)
    bad_decode = bad_field = bad_stamp = 0
    first_bad: str | None = None
    for i, (lt, data) in enumerate(zip(raw.log_time_ns, raw.data, strict=True)):
        t[i] = lt
        try:
            msg = orjson.loads(data)
        except orjson.JSONDecodeError:
            bad_decode += 1
            continue
        try:
            for f in numeric:
                v = msg[f]
                if isinstance(v, bool) or not isinstance(v, int | float):
                    raise TypeError(f"field {f!r} is {type(v).__name__}, not a number")
                vals[f][i] = v
            for f in strings:
                v = msg.get(f, "") if f == "sensor_id" else msg[f]
                if not isinstance(v, str):
                    raise TypeError(f"field {f!r} is {type(v).__name__}, not a string")
                labs[f][i] = v
        except (KeyError, TypeError) as exc:
            bad_field += 1
            if first_bad is None:
                first_bad = (
                    f"field {exc.args[0]!r} missing" if isinstance(exc, KeyError) else str(exc)
                )
            continue
        except Exception:  # noqa: BLE001 - payload is not even an object
            bad_field += 1
            first_bad = first_bad or "payload is not a JSON object"
            continue
        ts = msg.get("timestamp") if isinstance(msg, dict) else None
        if not (
            isinstance(ts, dict)
            and isinstance(ts.get("sec"), int)
            and isinstance(ts.get("nsec"), int)
            and ts["sec"] * NS + ts["nsec"] == lt
        ):
            bad_stamp += 1
        ok[i] = True
    return t, vals, labs, ok, bad_decode, bad_field, bad_stamp, first_bad


def _decode_columns(raw: RawTopic, numeric: list[str], strings: list[str], batch: int = 1 << 15):
    """Whole-topic decoding: one JSON parse per ``batch`` payloads, straight into one array
    (numbers) or list (strings, equal ones shared) per field.

    About 4x faster than message by message; parsing a batch at a time keeps the decoded
    dicts (~400 bytes a message) to one batch instead of the whole topic. Returns None at the
    first irregularity (a payload that is not a JSON object, a missing field, a wrong type),
    and the caller falls back to :func:`_decode_each`, which finds and reports the bad
    messages.
    """
    n = raw.count
    if n == 0:
        return None
    number = {int, float}
    vals = {f: np.empty(n) for f in numeric}
    labs: dict[str, list[str]] = {f: [] for f in strings}
    shared: dict[str, str] = {}  # one object per distinct label (sensor ids repeat)
    sec = np.empty(n, np.int64)
    nsec = np.empty(n, np.int64)
    stamps_ok = True
    for b in range(0, n, batch):
        part = raw.data[b : b + batch]
        stop = b + len(part)
        try:
            msgs = orjson.loads(b"[" + b",".join(part) + b"]")
        except orjson.JSONDecodeError:
            return None
        del part
        if len(msgs) != stop - b or set(map(type, msgs)) != {dict}:
            return None
        try:
            for f in numeric:
                col = [m[f] for m in msgs]
                if not set(map(type, col)) <= number:
                    return None
                vals[f][b:stop] = np.array(col, dtype=float)
            for f in strings:
                col = [m.get(f, "") for m in msgs] if f == "sensor_id" else [m[f] for m in msgs]
                if set(map(type, col)) != {str}:
                    return None
                labs[f] += [shared.setdefault(v, v) for v in col]
        except (KeyError, TypeError, OverflowError):
            return None
        if stamps_ok:
            try:
                stamps = [m["timestamp"] for m in msgs]
                sec[b:stop] = np.array([st["sec"] for st in stamps], dtype=np.int64)
                nsec[b:stop] = np.array([st["nsec"] for st in stamps], dtype=np.int64)
            except (KeyError, TypeError, ValueError, OverflowError):
                stamps_ok = False
        del msgs
    t = np.array(raw.log_time_ns, dtype=np.int64)
    bad_stamp = int(np.count_nonzero(sec * NS + nsec != t)) if stamps_ok else n
    return t, vals, labs, np.ones(n, bool), bad_stamp


# --------------------------------------------------------------------------------------------
# 3. alignment
# --------------------------------------------------------------------------------------------
def find_gaps(time_ns: np.ndarray, topic: str, gap_factor: float = 3.0) -> list[Gap]:
    """Intervals between consecutive samples longer than ``gap_factor`` x the median period."""
    if time_ns.size < 3:
        return []
    dt = np.diff(time_ns)
    limit = gap_factor * float(np.median(dt))
    return [Gap(topic, int(time_ns[i]), int(time_ns[i + 1])) for i in np.flatnonzero(dt > limit)]


def _interp_onto(
    t_dst: np.ndarray,
    series: TopicSeries,
    values: np.ndarray,
    gaps: list[Gap],
    *,
    angle: bool = False,
    signed: bool = False,
) -> tuple[np.ndarray, int]:
    """Linear interpolation of ``values`` (at ``series.time_ns``) onto ``t_dst``.

    ``angle``: degrees, interpolated the short way round and returned in [0, 360), or in
    [-180, 180) when ``signed`` (longitude).

    Returns the interpolated array (NaN outside the span and inside gaps) and the number of
    destination epochs left without data.
    """
    t_src = series.time_ns
    out = np.full(t_dst.size, np.nan)
    if t_src.size == 0:
        return out, t_dst.size
    # Relative seconds keep float64 precision (absolute ns would lose it in np.interp).
    base = t_src[0]
    xs = (t_src - base) / NS
    xd = (t_dst - base) / NS
    v = np.unwrap(values, period=360.0) if angle else values
    if t_src.size == 1:
        inside = t_dst == t_src[0]
        out[inside] = v[0]
    else:
        inside = (t_dst >= t_src[0]) & (t_dst <= t_src[-1])
        out[inside] = np.interp(xd[inside], xs, v)
    for g in gaps:
        inside &= ~((t_dst > g.start_ns) & (t_dst < g.end_ns))
    out[~inside] = np.nan
    if angle:
        out = np.mod(out, 360.0)
        if signed:
            out = np.where(out >= 180.0, out - 360.0, out)
    return out, int((~inside).sum())


def _suffix(topic: str, rule: TopicRule) -> str:
    if rule.alias:
        return rule.alias
    return topic[len(rule.topic) + 1 :].replace("/", "_") if topic != rule.topic else ""


def _check_plausible(series: dict[str, TopicSeries], path: Path) -> None:
    """Fields in nT and attitude in degrees, or a one-line error naming the channel."""
    for topic, s in series.items():
        if s.time_ns.size == 0:
            continue
        role = s.rule.role
        if role in ("scalar", "base"):  # /reference/* may be a diurnal or a residual
            check_units("total_nT", s.values["total_nT"], path, topic)
        elif role == "vector":
            mag = np.sqrt(sum(s.values[f"{ax}_nT"] ** 2 for ax in "xyz"))
            check_units("the vector magnitude", mag, path, topic)
        elif role in ("attitude", "ins"):
            check_degrees(
                {f: s.values[f] for f in ("roll_deg", "pitch_deg", "yaw_deg")},
                ("roll_deg", "pitch_deg", "yaw_deg"),
                path,
            )


def read_flight(
    path: str | Path,
    *,
    mapping=None,
    scalar_topic: str | None = None,
    vector_topic: str | None = None,
    gap_factor: float = 3.0,
) -> Flight:
    """Read a recording and align every contract stream onto the primary scalar epochs.

    Parameters
    ----------
    path
        MCAP recording (read-only).
    scalar_topic, vector_topic
        Primary magnetometers (default ``/mag/scalar`` and ``/mag/vector``; when absent, the
        first ``/mag/scalar/<id>`` resp. ``/mag/vector/<id>`` in name order).
    gap_factor
        A gap is an interval longer than ``gap_factor`` x the stream's median period.

    Raises
    ------
    AeromagError
        Unreadable file, or no usable scalar magnetometer stream.
    """
    raw = read_topics(path)
    path = raw.path
    series: dict[str, TopicSeries] = {}
    unknown: list[str] = []
    notes: list[str] = []
    if mapping is not None:
        series.update(mapped_series(path, mapping))
        for s_ in series.values():
            notes.extend(f"{s_.topic}: {p}" for p in s_.problems)
    for topic, rt in sorted(raw.topics.items()):
        if topic in series:
            continue
        rule = rule_for_topic(topic)
        if rule is None:
            unknown.append(topic)
            continue
        if rule.role == "output":  # an earlier run's result, not a measurement
            continue
        s = decode_topic(rt, rule)
        rt.data = []  # the payloads are decoded: free them before the next topic's
        series[topic] = s
        notes.extend(f"{topic}: {p}" for p in s.problems)

    def pick(role: str, wanted: str | None, default: str) -> str | None:
        if wanted is not None:
            if wanted not in series or series[wanted].rule.role != role:
                raise AeromagError(
                    f"no {role} magnetometer messages on this topic", file=path, channel=wanted
                )
            return wanted
        if default in series:
            return default
        others = sorted(t for t, s in series.items() if s.rule.role == role)
        if others:
            notes.append(f"{default} absent: using {others[0]} as the primary {role} sensor")
            return others[0]
        return None

    primary = pick("scalar", scalar_topic, "/mag/scalar")
    if primary is None:
        raise AeromagError(
            "no scalar magnetometer channel (/mag/scalar or /mag/scalar/<id>)",
            file=path,
            channel="/mag/scalar",
        )
    _check_plausible(series, path)
    ps = series[primary]
    if ps.time_ns.size < 2:
        detail = "; ".join(ps.problems) or f"{ps.n_messages} messages"
        raise AeromagError(f"fewer than 2 usable samples ({detail})", file=path, channel=primary)
    vprimary = pick("vector", vector_topic, "/mag/vector")

    t = ps.time_ns
    notes[:0] = raw.loss_notes(int(t[0]))
    gaps_all: list[Gap] = []
    cols: dict[str, np.ndarray] = {"time_s": (t - t[0]) / NS, "scalar_nT": ps.values["total_nT"]}
    units: dict[str, str] = {"time_s": "s", "scalar_nT": "nT"}
    topic_of = {"scalar": primary}
    gaps_all.extend(find_gaps(t, primary, gap_factor))

    for topic, s in series.items():
        if topic == primary:
            continue
        role = s.rule.role
        gaps = find_gaps(s.time_ns, topic, gap_factor)
        gaps_all.extend(gaps)
        if s.time_ns.size == 0:
            notes.append(f"{topic}: no usable samples")
            continue

        def put(
            name: str,
            values: np.ndarray,
            unit: str,
            angle: bool = False,
            signed: bool = False,
            _s: TopicSeries = s,
            _g: list[Gap] = gaps,
        ) -> None:
            arr, missing = _interp_onto(t, _s, values, _g, angle=angle, signed=signed)
            cols[name] = arr
            units[name] = unit
            if missing:
                notes.append(
                    f"{_s.topic}: {missing} of {t.size} epochs without data "
                    "(outside its span or in a gap)"
                )

        if role == "scalar":
            put(f"scalar_{_suffix(topic, s.rule)}_nT", s.values["total_nT"], "nT")
        elif role == "vector":
            stem = "vector" if topic == vprimary else f"vector_{_suffix(topic, s.rule)}"
            if topic == vprimary:
                topic_of["vector"] = topic
            for ax in "xyz":
                put(f"{stem}_{ax}_nT", s.values[f"{ax}_nT"], "nT")
        elif role == "attitude":
            topic_of["attitude"] = topic
            put("roll_deg", s.values["roll_deg"], "deg")
            put("pitch_deg", s.values["pitch_deg"], "deg")
            put("yaw_deg", s.values["yaw_deg"], "deg", angle=True)
        elif role == "ins":
            # the recorded INS, column ins_<field> (its own rate is kept in flight.series)
            topic_of["ins"] = topic
            for name in INS_FIELDS:
                put(f"ins_{name}", s.values[name], INS_UNITS[name], angle=name == "yaw_deg")
        elif role == "position":
            topic_of["position"] = topic
            put("lat_deg", s.values["latitude"], "deg")
            # an angle: a track across the antimeridian is interpolated across it, not
            # through the other 359 degrees
            put("lon_deg", s.values["longitude"], "deg", angle=True, signed=True)
            put("alt_m", s.values["altitude"], "m")
        elif role == "base":
            topic_of["base"] = topic
            put("base_nT", s.values["total_nT"], "nT")
        elif role == "reference":
            put(f"reference_{_suffix(topic, s.rule)}_nT", s.values["total_nT"], "nT")
        elif role == "aux":
            name = f"aux_{_suffix(topic, s.rule)}"
            unit = str(s.labels["unit"][0]) if s.labels["unit"].size else ""
            put(name, s.values["value"], unit)
        elif role == "plan":
            # Markers hold until the next one: take the last marker at or before each epoch.
            k = np.searchsorted(s.time_ns, t, side="right") - 1
            valid = k >= 0
            for f, col in (("line_id", "plan_line_id"), ("kind", "plan_kind")):
                arr = np.full(t.size, "", dtype=object)
                arr[valid] = s.labels[f][k[valid]]
                cols[col] = arr
                units[col] = ""
    for g in gaps_all:
        notes.append(
            f"{g.topic}: gap of {g.duration_s:.3f} s from "
            f"{(g.start_ns - t[0]) / NS:.3f} s to {(g.end_ns - t[0]) / NS:.3f} s"
        )
    return Flight(
        source=path,
        time_ns=t,
        data=pd.DataFrame(cols),
        units=units,
        series=series,
        topic_of=topic_of,
        gaps=gaps_all,
        notes=notes,
        unknown_topics=unknown,
        losses=raw.losses,
        all_topics=sorted(raw.topics),
    )
