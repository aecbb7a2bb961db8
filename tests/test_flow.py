"""The post-flight flow under Prefect (test harness) and through the command line."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

from mcap.reader import make_reader

from tests.conftest import sha256
from tests.test_schemas import validate_every_message
from tests.test_writer import records


def test_postflight_flow_writes_input_plus_new_channels(prefect_harness, box_path, tmp_path):
    from flows.postflight import postflight

    src = tmp_path / "flight.mcap"
    shutil.copy(box_path, src)
    before = sha256(src)
    result = postflight(str(src), str(tmp_path / "out"))
    assert sha256(src) == before
    out = tmp_path / "out" / "flight.processed.mcap"
    summary = json.loads((tmp_path / "out" / "flight.summary.json").read_text())
    assert result["outputs"]["mcap"] == str(out) and summary["outputs"]["mcap"] == str(out)
    assert summary["input"]["sha256"] == before
    new = {"/aeromag/log", "/flight/segment", "/mag/compensated", "/mag/compensated/tl16",
           "/mag/compensated/tl18", "/compensation/model", "/audit/finding",
           "/mag/vector/compensated"}
    assert set(summary["channels_written"]) == new
    comp = summary["compensation"]
    assert comp["final"] == "agg-tl" and {"tl16", "tl18", "agg-tl"} <= set(comp)
    for m in ("tl16", "tl18", "agg-tl"):
        assert comp[m]["fom_nT"]["uncompensated"] > 5 * comp[m]["fom_nT"]["compensated"]
    assert summary["segments"]["boxes"] == 12
    assert summary["config"]["version"] == 1 and len(summary["config"]["hash"]) == 64
    assert "audit" in summary and summary["vector"]["method"] == "component-kf"
    assert (tmp_path / "out" / "flight.report.md").read_text().startswith("# Post-flight")
    for png in ("lcurve", "compensation", "audit_residual_time"):
        assert (tmp_path / "out" / f"flight.{png}.png").stat().st_size > 10000
    m_in, *_ = records(src)
    m_out, *_ = records(out)
    assert sorted(m for m in m_out if m[0] not in new) == sorted(m_in)
    with out.open("rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    assert topics == {m[0] for m in m_in} | new
    assert validate_every_message(out) == len(m_out)  # Foxglove's official Log schema included


def test_process_command_runs_the_flow_without_a_server(box_path, tmp_path):
    """`aeromag process` with no Prefect server configured: a temporary one is started."""
    env = {**os.environ, "PREFECT_HOME": str(tmp_path / "prefect")}
    env.pop("PREFECT_API_URL", None)
    res = subprocess.run([sys.executable, "-m", "flows.cli", "process", str(box_path), "--out",
                          str(tmp_path / "out")], capture_output=True, text=True, env=env,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]
    out = tmp_path / "out" / "box_uav.processed.mcap"
    assert f"output recording: {out}" in res.stdout
    insp = subprocess.run([sys.executable, "-m", "flows.cli", "inspect", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert insp.returncode == 0 and "/mag/compensated" in insp.stdout
