"""Viewing: every output message of the demo against its schema (Foxglove's official ones for
foxglove.*), the Foxglove layout, and the HTML report rendered in headless Chromium."""

from __future__ import annotations

import json
import shutil
from collections import Counter
from pathlib import Path

import fastjsonschema
import orjson
import pytest
from mcap.reader import make_reader
from typer.testing import CliRunner

from flows.cli import app
from pipeline.io.contract import rule_for_topic
from pipeline.io.schemas import schema_dir, schema_path
from pipeline.products.layout import layout_panels, layout_paths, path_topic_field

CHROMIUM_FLAGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]


def test_foxglove_schemas_are_the_official_package():
    folder = schema_dir() / "foxglove"
    assert (folder / "VERSION").read_text().split() == ["@foxglove/schemas", "2.1.0"]
    assert (folder / "fetch.sh").is_file()
    # as published: Foxglove's own requirements, not ours (toolchain.md)
    grid = json.loads(schema_path("foxglove.Grid").read_text())
    assert {
        "timestamp",
        "frame_id",
        "pose",
        "column_count",
        "cell_size",
        "row_stride",
        "cell_stride",
        "fields",
        "data",
    } <= set(grid["required"])
    fix = json.loads(schema_path("foxglove.LocationFix").read_text())
    cov = fix["properties"]["position_covariance"]
    assert cov["minItems"] == cov["maxItems"] == 9


def test_every_output_message_of_the_demo_validates(demo_output):
    """All messages of all channels of the processed demo recording, input copies included,
    each against the schema its channel names: ours, or Foxglove's official file."""
    out, summary = demo_output
    validators: dict[str, object] = {}
    counts: Counter[str] = Counter()
    with open(out / "demo_flight.processed.mcap", "rb") as f:
        for sch, ch, msg in make_reader(f, validate_crcs=True).iter_messages(log_time_order=False):
            rule = rule_for_topic(ch.topic)
            assert rule is not None and sch.name == rule.schema_name, ch.topic
            assert sch.encoding == "jsonschema" and ch.message_encoding == "json"
            if sch.name not in validators:
                # the schema inside the recording is the committed file, byte for byte
                assert sch.data == schema_path(sch.name).read_bytes(), sch.name
                validators[sch.name] = fastjsonschema.compile(json.loads(sch.data))
            payload = orjson.loads(msg.data)
            try:
                validators[sch.name](payload)
            except fastjsonschema.JsonSchemaValueException as exc:
                pytest.fail(f"{ch.topic} at {msg.log_time}: {exc.message}")
            stamp = payload["timestamp"]
            assert stamp["sec"] * 1_000_000_000 + stamp["nsec"] == msg.log_time, ch.topic
            counts[ch.topic] += 1
    written = summary["channels_written"]
    assert {
        "/aeromag/log",
        "/map/anomaly",
        "/map/anomaly_filtered",
        "/map/tracks",
        "/mag/compensated",
        "/flight/segment",
    } <= set(written)
    assert all(counts[t] > 0 for t in written)
    assert {n for n in validators if n.startswith("foxglove.")} == {
        "foxglove.Log",
        "foxglove.Grid",
        "foxglove.GeoJSON",
        "foxglove.LocationFix",
    }
    # one compensated sample per epoch of the recording (the final model covers the flight,
    # but for the first and last few epochs, before the attitude and vector streams start)
    assert 0 <= summary["input"]["epochs"] - counts["/mag/compensated"] <= 10
    for topic, info in summary["input"]["topics"].items():
        assert counts[topic] == info["samples"], topic


def test_demo_layout_refers_to_real_channels_and_fields(demo_output, tmp_path):
    out, summary = demo_output
    s_map = summary["map"]
    doc = json.loads((out / "demo_flight.layout.json").read_text())
    # the command writes the same layout as the flow
    res = CliRunner().invoke(
        app,
        ["layout", str(out / "demo_flight.processed.mcap"), "--out", str(tmp_path / "layout.json")],
    )
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "layout.json").read_text()) == doc

    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(doc)
    panels = layout_panels(doc["layout"], doc["configById"])
    assert sorted(panels) == sorted(doc["configById"])  # every panel placed exactly once
    kinds = Counter(p.split("!", 1)[0] for p in panels)
    assert kinds == {
        "map": 1,
        "3D": 2,
        "Plot": 3,
        "StateTransitions": 1,
        "RosOut": 1,
        "RawMessages": 1,
    }

    with open(out / "demo_flight.processed.mcap", "rb") as f:
        s = make_reader(f).get_summary()
    channels = {c.topic: s.schemas[c.schema_id].name for c in s.channels.values()}
    for p in layout_paths(doc["configById"]):
        topic, field = path_topic_field(p) if "." in p else (p, "")
        assert topic in channels, p
        if field:
            props = json.loads(schema_path(channels[topic]).read_text())["properties"]
            assert field in props, p
    cfg = doc["configById"]
    assert set(cfg["map!aeromag-track"]["topicColors"]) == {
        "/gnss/fix",
        "/nav/ins",
        "/nav/map_aided",
        "/map/tracks",
    }
    field_plot = [p["value"] for p in cfg["Plot!aeromag-field"]["paths"]]
    assert field_plot[0] == "/mag/scalar.total_nT"
    assert "/mag/compensated/tl18.total_nT" in field_plot
    assert '"/mag/compensated/agg-tl".total_nT' in field_plot
    assert cfg["RosOut!aeromag-aeromag-log"]["topicToRender"] == "/aeromag/log"
    # the 3D cameras look at the grid's centre from above, far enough to see all of it
    with open(out / "demo_flight.processed.mcap", "rb") as f:
        _, _, msg = next(make_reader(f).iter_messages(topics=["/map/anomaly"]))
    g = json.loads(msg.data)
    rows, cols = s_map["grid_shape"]
    width, height = cols * g["cell_size"]["x"], rows * g["cell_size"]["y"]
    cam = cfg["3D!aeromag-anomaly"]["cameraState"]
    assert cam["targetOffset"][0] == pytest.approx(g["pose"]["position"]["x"] + width / 2)
    assert cam["targetOffset"][1] == pytest.approx(g["pose"]["position"]["y"] + height / 2)
    assert cam["distance"] >= max(width, height) and cam["phi"] == 0


def test_layout_command_refuses_a_non_mcap_file(tmp_path):
    bad = tmp_path / "notes.mcap"
    bad.write_text("not a recording")
    res = CliRunner().invoke(app, ["layout", str(bad), "--out", str(tmp_path / "l.json")])
    assert res.exit_code != 0
    assert not (tmp_path / "l.json").exists()


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail(
            "Debian's chromium is needed for the report test: `make test` installs it "
            "(apt-get install chromium)"
        )
    return exe


def test_report_renders_in_headless_chromium(demo_output, tmp_path):
    from playwright.sync_api import sync_playwright

    out, s = demo_output
    page_path = out / "demo_flight.report.html"
    figures = sorted(p.name for p in out.glob("demo_flight.*.png"))
    assert len(figures) >= 12
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=_chromium(), args=CHROMIUM_FLAGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(page_path.as_uri(), wait_until="load")
            images = page.evaluate(
                "Array.from(document.images).map(i => [i.alt, i.complete, i.naturalWidth])"
            )
            text = page.inner_text("body")
            shot = tmp_path / "report.png"
            page.screenshot(path=str(shot), full_page=True)
        finally:
            browser.close()

    # every figure of the run is in the page once, and every image decoded
    assert sorted(f"demo_flight.{alt}.png" for alt, _, _ in images) == figures
    assert all(ok and width > 100 for _, ok, width in images), images
    assert shot.stat().st_size > 50_000
    for heading in (
        "Flight and segments",
        "Calibration and compensation",
        "Calibration FOM per box",
        "Heading error: T-L vs AGG-TL",
        "Model audit",
        "Before and after ARIMA-Kalman filtering",
        "Quality control",
    ):
        assert heading in text, heading
    # the key numbers, as the summary has them
    q = s["quality"]
    for state in ("raw", "tl16", "tl18", "agg_tl"):
        assert f"{q['heading_error_rms_nT'][state]:.3f}" in text, state
    for model in ("tl16", "tl18", "agg-tl"):
        assert f"{s['compensation'][model]['fom_nT']['compensated']:.2f}" in text, model
    for fd in s["audit"]["findings"]:
        assert fd["effect"] in text
    assert f"{s['map']['crossover_rms_nT']['after']:.3f}" in text
    assert str(tuple(s["map"]["arima_order"])) in text
    assert f"{q['qc']['noise']['median_nT']:.4f}" in text or all(
        f"{v:.4f}" in text for v in q["qc"]["noise"]["per_line_nT"].values()
    )
    # the page is self-contained: no file or network reference besides data URIs
    page_html = page_path.read_text()
    assert 'src="data:image/png;base64,' in page_html and "http" not in page_html
    assert not list(Path(out).glob(".*partial*"))
