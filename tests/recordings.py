"""Reading a written recording back in tests: every message validated against its channel's
schema, and every record (messages, attachments, metadata, channels) for byte-level checks;
where the independent recordings are (``INDEPENDENT``)."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
from mcap.reader import make_reader

from pipeline.io.contract import rule_for_topic

# ../shared/recordings beside the checkout (a worktree sits one level deeper): flights made
# by a generator that is not aeromag's, with their truth; tests skip when absent
INDEPENDENT = next(
    (
        p / "shared" / "recordings"
        for p in Path(__file__).resolve().parents[1:4]
        if (p / "shared" / "recordings").is_dir()
    ),
    Path("shared") / "recordings",
)


def validate_every_message(path, topics: set[str] | None = None) -> int:
    """Validate each message of each contract channel (or of ``topics`` only: what a command
    added) with the reference validator."""
    validators = {}
    n = 0
    with open(path, "rb") as f:
        for sch, ch, msg in make_reader(f).iter_messages(
            topics=sorted(topics) if topics else None, log_time_order=False
        ):
            rule = rule_for_topic(ch.topic)
            assert rule is not None, f"{ch.topic} is not in the contract"
            assert sch.name == rule.schema_name and sch.encoding == "jsonschema"
            assert ch.message_encoding == "json"
            if sch.name not in validators:
                validators[sch.name] = jsonschema.Draft202012Validator(json.loads(sch.data))
            payload = json.loads(msg.data)
            validators[sch.name].validate(payload)
            stamp = payload["timestamp"]
            assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == msg.log_time
            n += 1
    return n


def records(path: Path) -> tuple[list, list, list, dict]:
    """Messages with their channel and schema content, attachments, metadata, channel list."""
    with path.open("rb") as f:
        r = make_reader(f)
        msgs = [
            (
                c.topic,
                c.message_encoding,
                dict(c.metadata),
                (s.name, s.encoding, s.data) if s else None,
                m.log_time,
                m.publish_time,
                m.sequence,
                m.data,
            )
            for s, c, m in r.iter_messages(log_time_order=False)
        ]
        atts = [
            (a.name, a.media_type, a.log_time, a.create_time, a.data) for a in r.iter_attachments()
        ]
        meta = [(m.name, dict(m.metadata)) for m in r.iter_metadata()]
        summ = r.get_summary()
        chans = {c.topic: c.message_encoding for c in summ.channels.values()} if summ else {}
    return msgs, atts, meta, chans
