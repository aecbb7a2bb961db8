"""Schemas: valid, documented, and every message of every channel validates against them."""

from __future__ import annotations

import json

import jsonschema
import pytest

from pipeline.io.contract import INPUT_CONTRACT, OUTPUT_CONTRACT
from pipeline.io.schemas import schema, schema_dir, schema_path
from tests.recordings import validate_every_message

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


def test_every_simulated_message_validates(box_path):
    assert validate_every_message(box_path) > 10000


def test_every_simulated_message_validates_with_plan_markers(tmp_path):
    from pipeline.simulate import write_simulation
    from tests.conftest import run_sim

    sim = run_sim("calibration-only", 3, ["calibration.passes=1", "sensors.plan_markers=true"])
    assert validate_every_message(write_simulation(sim, tmp_path / "p.mcap")) > 10000
