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


def test_post_flight_reports_say_what_the_audit_left_unexplained(tmp_path):
    # the events, the null model's nuisances and the ties appear in both post-flight reports
    # (the Markdown one is also the flow's Prefect artifact), not in the audit's JSON only
    from pipeline.products.html import render_html
    from pipeline.products.markdown import report_markdown

    src = tmp_path / "f.mcap"
    src.write_bytes(b"x")
    s = build_summary(_Flight(src))
    s["config"] = {"hash": "0" * 64, "version": 1, "source": "defaults"}
    t0 = s["input"]["start_ns"]
    s["audit"] = {
        "baseline": {"model": "tl18", "residual_rms_nT": 0.09},
        "extended_model": ["tl18"],
        "unexplained_rms_nT": 0.08,
        "band_noise_floor_nT": 0.03,
        "noise_floor_nT": 0.08,
        "findings": [],
        "unexplained": {
            "events": [
                {
                    "kind": "step",
                    "start_ns": t0 + 370 * 10**9,
                    "end_ns": t0 + 381 * 10**9,
                    "size_nT": 1.77,
                    "evidence": "vector reference",
                }
            ],
            "nuisances": [
                {"name": "eddy_decay", "heldout_gain": 0.249, "estimate": {"tau_s": 0.1056}}
            ],
            "ambiguities": [
                {
                    "candidates": ["sensor_lag", "eddy_decay"],
                    "heldout_gain": {"sensor_lag": 0.133, "eddy_decay": 0.154},
                    "survey_difference_nT": 0.181,
                }
            ],
        },
    }
    md, page = report_markdown("f", s, {}), render_html("f", s, {})
    for text in (md, page):
        assert "step: 1.77 nT, from 370.0 s to 381.0 s (vector reference)" in text
        assert "eddy_decay" in text and "held-out gain 24.9 %" in text
        assert "differ by 0.181 nT RMS along the lines" in text


def test_the_post_flight_console_text_holds_on_a_damaged_or_partial_flight(tmp_path):
    # aeromag process prints the summary in brief: a damaged recording says what it lost,
    # a tie is said, and skipped stages or missing figures (no crossovers) print as such
    from pipeline.products.console import postflight_text

    src = tmp_path / "f.mcap"
    src.write_bytes(b"x")
    s = build_summary(_Flight(src))
    s["input"]["losses"] = [{"description": "file truncated at byte 10 (5 bytes lost)"}]
    s["map"] = {
        "grid_shape": [3, 4],
        "cell_m": 12.5,
        "crossover_rms_nT": {"before": None, "after": None},
        "arima_order": [1, 1, 1],
    }
    s["quality"] = {"skipped": "no validation lines"}
    s["audit"] = {
        "findings": [],
        "extended_model": ["tl18"],
        "unexplained": {
            "ambiguities": [
                {
                    "candidates": ["sensor_lag", "eddy_decay"],
                    "heldout_gain": {"sensor_lag": 0.1, "eddy_decay": 0.2},
                    "survey_difference_nT": 0.3,
                }
            ]
        },
    }
    s["outputs"] = {k: str(tmp_path / k) for k in ("mcap", "summary", "report", "report_html")}
    s["outputs"]["layout"] = str(tmp_path / "layout")
    lines = [b for b in postflight_text(s) if isinstance(b, str)]
    assert any(x.startswith("warning: data lost: file truncated") for x in lines)
    assert any("crossover RMS - -> - nT" in x for x in lines)
    assert any(x.startswith("audit: ambiguity, nothing named") and "0.3 nT" in x for x in lines)
    assert not any(x.startswith("heading error") for x in lines)
    s["map"] = {"skipped": "no survey lines"}
    assert not any(str(b).startswith("map:") for b in postflight_text(s))


def test_a_map_without_crossovers_is_reported_not_a_crash():
    """A survey whose lines never cross (tie lines along the block's ends, or none) levels on
    no crossovers: its summary holds None there, and the console and log say so."""
    from types import SimpleNamespace

    from pipeline.products.console import map_text
    from pipeline.products.log import map_lines

    s = {
        "grid_shape": [3, 4],
        "cell_m": 25.0,
        "line_spacing_m": 100.0,
        "crossover_rms_nT": {"before": None, "after": None},
        "leveling": {"crossovers": 0},
        "arima_order": [1, 1, 0],
        "arima_coefficients": {"ar": [0.5], "ma": []},
        "kalman": {"measurement_noise_nT": 0.1},
        "microlevel": {"enabled": False},
        "origin": {"crs_choice": "UTM zone 49N", "utm_zones_spanned": [49]},
    }
    assert "no crossovers" in str(map_text(s)[0])
    texts = [t for _, t in map_lines(SimpleNamespace(summary=lambda: s))]
    assert any("no crossovers" in t for t in texts)
