"""What is in a recording, and where it breaks the channel contract (``aeromag inspect``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import orjson

from pipeline.io.contract import FULL_PIPELINE_ROLES, INPUT_CONTRACT, rule_for_topic
from pipeline.io.reader import decode_topic, find_gaps, read_topics
from pipeline.io.schemas import validate
from pipeline.io.series import NS, Gap


@dataclass
class TopicReport:
    """What ``inspect`` found on one topic: schema, message encoding, message count, its role in
    the channel contract (None: outside it), rate (Hz), first and last log times (ns) and the
    gaps.
    """

    topic: str
    schema_name: str
    message_encoding: str
    count: int
    role: str | None  # None: outside the contract (kept untouched)
    rate_hz: float = float("nan")
    start_ns: int | None = None
    end_ns: int | None = None
    gaps: list[Gap] = field(default_factory=list)


@dataclass
class InspectReport:
    """``aeromag inspect`` on one recording: the per-topic reports, contract violations (non-zero
    exit), warnings, and whether the file has a summary section.
    """

    path: Path
    topics: list[TopicReport]
    violations: list[str]  # contract violations: ``inspect`` exits non-zero
    warnings: list[str]  # not violations (missing optional/pipeline channels, gaps)
    has_summary: bool

    @property
    def start_ns(self) -> int | None:
        """Earliest log time over all topics, ns since the Unix epoch (UTC); None when empty."""
        s = [t.start_ns for t in self.topics if t.start_ns is not None]
        return min(s) if s else None

    @property
    def end_ns(self) -> int | None:
        """Latest log time over all topics, ns since the Unix epoch (UTC); None when empty."""
        e = [t.end_ns for t in self.topics if t.end_ns is not None]
        return max(e) if e else None

    @property
    def gaps(self) -> list[Gap]:
        """Gaps of every topic, topic by topic."""
        return [g for t in self.topics for g in t.gaps]

    def to_dict(self) -> dict:
        """The report as a JSON-ready dict (``aeromag inspect --json``).

        Returns
        -------
        dict
            ``file``, ``start_ns`` / ``end_ns`` (ns, UTC), ``duration_s``, per-topic ``topics``
            (schema, encoding, messages, role, rate in Hz, gaps in s from the start),
            ``violations`` and ``warnings``.
        """
        t0 = self.start_ns
        return {
            "file": str(self.path),
            "start_ns": t0,
            "end_ns": self.end_ns,
            "duration_s": (self.end_ns - t0) / NS if t0 is not None else 0.0,
            "topics": [
                {
                    "topic": t.topic,
                    "schema": t.schema_name,
                    "encoding": t.message_encoding,
                    "messages": t.count,
                    "role": t.role,
                    "rate_hz": None if t.rate_hz != t.rate_hz else round(t.rate_hz, 4),
                    "gaps": [
                        {"start_s": (g.start_ns - t0) / NS, "duration_s": g.duration_s}
                        for g in t.gaps
                    ],
                }
                for t in self.topics
            ],
            "violations": self.violations,
            "warnings": self.warnings,
        }


def inspect_recording(path: str | Path, gap_factor: float = 3.0) -> InspectReport:
    """Topics, message counts, rates, span, gaps and contract violations of a recording.

    Every message of a contract topic is validated against its JSON Schema.
    """
    raw = read_topics(path)
    topics: list[TopicReport] = []
    violations: list[str] = []
    warnings: list[str] = []
    roles_present: set[str] = set()
    for name, rt in sorted(raw.topics.items()):
        rule = rule_for_topic(name)
        rep = TopicReport(
            name, rt.schema_name, rt.message_encoding, rt.count, rule.role if rule else None
        )
        topics.append(rep)
        if rt.count:
            rep.start_ns, rep.end_ns = min(rt.log_time_ns), max(rt.log_time_ns)
        if rule is None:
            continue
        if rt.schema_name != rule.schema_name:
            violations.append(
                f"{name}: schema is {rt.schema_name!r}, the contract says {rule.schema_name!r}"
            )
            continue
        if rt.message_encoding != "json":
            violations.append(
                f"{name}: message encoding is {rt.message_encoding!r}, the contract says 'json'"
            )
            continue
        if rt.schema_encoding != "jsonschema":
            violations.append(
                f"{name}: schema encoding is {rt.schema_encoding!r}, the contract says 'jsonschema'"
            )
        invalid, first = 0, ""
        for data in rt.data:
            try:
                problem = validate(rule.schema_name, orjson.loads(data))
            except orjson.JSONDecodeError:
                problem = "not valid JSON"
            if problem:
                invalid += 1
                first = first or problem
        if invalid:
            violations.append(
                f"{name}: {invalid} of {rt.count} messages do not match {rule.schema_name}: {first}"
            )
        series = decode_topic(rt, rule)
        # field problems were reported above against the full schema; keep the time-level ones
        violations.extend(
            f"{name}: {p}"
            for p in series.problems
            if "do not match the schema" not in p
            and "not valid JSON" not in p
            and "NaN or infinite" not in p
        )
        nonfinite = [p for p in series.problems if "NaN or infinite" in p]
        if nonfinite and rule.role != "output":  # NaN cells are how a grid masks
            violations.extend(f"{name}: {p}" for p in nonfinite)
        if series.time_ns.size:
            roles_present.add(rule.role)
            rep.rate_hz = series.rate_hz
            if rule.role != "output":  # results come at change points, not at a rate
                rep.gaps = find_gaps(series.time_ns, name, gap_factor)
        elif rt.count == 0:
            warnings.append(f"{name}: channel carries no messages")
    if "scalar" not in roles_present:
        violations.append("/mag/scalar: no scalar magnetometer messages: nothing to process")
    missing = [r for r in FULL_PIPELINE_ROLES if r not in roles_present]
    for role in missing:
        rule = next(r for r in INPUT_CONTRACT if r.role == role)
        if role != "scalar":
            warnings.append(
                f"{rule.topic}: absent ({rule.description}); stages that need it will not run"
            )
    unknown = [t.topic for t in topics if t.role is None]
    if unknown:
        warnings.append(
            f"{len(unknown)} topic(s) outside the contract, kept untouched: " + ", ".join(unknown)
        )
    # damage is a violation: the data it held is gone (the rest was salvaged and is reported)
    violations.extend(raw.loss_notes())
    if not raw.has_summary:
        warnings.append("no summary section (file read by a linear scan)")
    t0 = min((t.start_ns for t in topics if t.start_ns is not None), default=0)
    for t in topics:
        for g in t.gaps:
            warnings.append(
                f"{t.topic}: gap of {g.duration_s:.3f} s at {(g.start_ns - t0) / NS:.3f} s"
            )
    return InspectReport(raw.path, topics, violations, warnings, raw.has_summary)
