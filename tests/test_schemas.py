"""Schemas: valid, documented, and every message of every channel validates against them."""

from __future__ import annotations

import json

import jsonschema
import pytest
from mcap.reader import make_reader

from pipeline.io.contract import INPUT_CONTRACT, OUTPUT_CONTRACT, rule_for_topic
from pipeline.io.schemas import schema, schema_dir, schema_path

SCHEMA_FILES = sorted(schema_dir().glob("aeromag.*.json"))


@pytest.mark.parametrize("path", SCHEMA_FILES, ids=lambda p: p.name)
def test_schema_is_valid_and_documented(path):
    doc = json.loads(path.read_text())
    jsonschema.Draft202012Validator.check_schema(doc)
    assert doc["title"] == path.name[:-5]
    readme = (schema_dir() / "README.md").read_text()
    assert f"`{doc['title']}`" in readme


def test_every_contract_rule_has_its_schema_and_a_readme_line():
    readme = (schema_dir() / "README.md").read_text()
    for rule in (*INPUT_CONTRACT, *OUTPUT_CONTRACT):
        assert schema_path(rule.schema_name).is_file(), rule.schema_name
        assert f"`{rule.topic}" in readme, rule.topic
        props = schema(rule.schema_name)["properties"]
        assert set(rule.fields) <= set(props), rule.topic


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


def test_every_simulated_message_validates(box_path):
    assert validate_every_message(box_path) > 10000


def test_every_simulated_message_validates_with_plan_markers(tmp_path):
    from pipeline.simulate import write_simulation
    from tests.conftest import run_sim

    sim = run_sim("calibration-only", 3, ["calibration.passes=1", "sensors.plan_markers=true"])
    assert validate_every_message(write_simulation(sim, tmp_path / "p.mcap")) > 10000
