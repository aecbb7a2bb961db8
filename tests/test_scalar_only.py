"""A survey flown with a scalar magnetometer alone (a towed bird, a stinger on a quiet
carrier): no compensation model can be fitted, and the flight still gets its map, of the
uncompensated field, said so in the summary, the run log and the console."""

from __future__ import annotations

import json

import pytest

from tests.conftest import run_sim
from tests.corpus import run_cli

CONFIG = (
    "config_version = 1\n[audit]\nenabled = false\n[map]\narima = '1,1,1'\n"
    "[navigate]\nenabled = false\nnavigability = false\n"
)


@pytest.fixture(scope="module")
def scalar_only(tmp_path_factory):
    from pipeline.simulate import write_simulation

    folder = tmp_path_factory.mktemp("scalar-only")
    sim = run_sim("uav-small", 3)
    sim.streams.pop("/mag/vector")
    src = write_simulation(sim, folder / "flight.mcap")
    cfg = folder / "c.toml"
    cfg.write_text(CONFIG)
    return folder, src, cfg


def test_the_flow_maps_the_uncompensated_field(scalar_only):
    from flows.postflight import run_plain

    folder, src, cfg = scalar_only
    s = run_plain(str(src), str(folder / "out"), str(cfg))
    assert s["map"]["field"] == "raw" and "/map/anomaly" in s["channels_written"]
    assert "/mag/compensated" not in s["channels_written"]
    xo = s["map"]["crossover_rms_nT"]
    assert xo["after"] is not None and xo["after"] < xo["before"]
    for report in ("flight.report.md", "flight.report.html"):
        assert "uncompensated scalar field" in (folder / "out" / report).read_text()


def test_aeromag_map_maps_the_uncompensated_field(scalar_only, tmp_path, capsys):
    _, src, cfg = scalar_only
    out, js = tmp_path / "m.mcap", tmp_path / "m.json"
    code, stdout, stderr = run_cli(
        ["map", str(src), "--out", str(out), "--json", str(js), "--config", str(cfg)], capsys
    )
    assert code == 0, stdout + stderr
    assert "uncompensated field" in stdout
    assert json.loads(js.read_text())["map"]["field"] == "raw"
