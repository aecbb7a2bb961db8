"""The summary builder: one document shape whichever command writes it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pipeline.products.summary import build_summary, jsonable


class _Stage:
    def __init__(self, doc):
        self.doc = doc

    def summary(self):
        return self.doc


class _Flight:
    """The little of a Flight that ``flight_summary`` reads."""

    def __init__(self, path: Path):
        self.source = path
        self.time_ns = np.array([0, 10**9], dtype=np.int64)
        self.series, self.unknown_topics, self.gaps, self.notes, self.losses = {}, [], [], [], []


def test_sections_in_flow_order_and_plain_json(tmp_path):
    src = tmp_path / "f.mcap"
    src.write_bytes(b"x")
    s = build_summary(
        _Flight(src),
        quality=_Stage({"rms_nT": np.float64(0.5)}),
        map_run=_Stage({"cell_m": np.float32(10.0), "bad": float("nan")}),
        enhancements=["/map/tilt_deg"],
        navigation="no map",
        extra_key=np.int64(3),
        outputs={"summary": tmp_path / "s.json"},
    )
    assert list(s) == [
        "aeromag_version",
        "input",
        "map",
        "navigation",
        "quality",
        "extra_key",
        "outputs",
    ]
    assert s["map"]["bad"] is None and s["map"]["enhancements"] == ["/map/tilt_deg"]
    assert s["navigation"] == {"skipped": "no map"}
    assert isinstance(s["extra_key"], int) and s["outputs"]["summary"].endswith("s.json")
    assert math.isclose(s["input"]["duration_s"], 1.0)
    assert len(s["input"]["sha256"]) == 64


def test_jsonable_handles_numpy_nan_and_paths():
    v = jsonable({"a": [np.float32(1.5), np.nan], 2: (Path("/x"), True, None)})
    assert v == {"a": [1.5, None], "2": ["/x", True, None]}
