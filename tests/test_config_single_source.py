"""One source of defaults (issue 20, item 3): ``default_config.toml`` -> ``Config``.

The settings dataclasses take the shipped values, the single-stage commands take ``--config``
and their options override its keys, and with a non-default band every FOM table of a run (the
compensation stage's, the quality stage's box table, the report, the audit's gain) is measured
in that band.
"""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.config import Config
from pipeline.errors import AeromagError
from tests.conftest import FIXTURES, REPO, run_sim

BAND = [0.05, 0.5]  # not the shipped 0.1-0.9 Hz


def shipped() -> dict:
    return tomllib.loads((REPO / "pipeline" / "default_config.toml").read_text())


# --------------------------------------------------------------------------------------------
def test_settings_defaults_are_the_shipped_configuration():
    from pipeline.audit import AuditSettings
    from pipeline.audit.extended import BandSettings
    from pipeline.compensate import FitSettings
    from pipeline.maps.stage import MapSettings
    from pipeline.quality.stage import QualitySettings

    d, cfg = shipped(), Config.load()
    c = d["compensation"]
    fit = FitSettings()
    assert (fit.band_hz, fit.poles, fit.trim_s, fit.ridge, fit.base) == (
        tuple(c["band_hz"]),
        c["poles"],
        c["trim_s"],
        c["ridge"],
        c["agg_base"],
    )
    assert BandSettings() == BandSettings(tuple(c["band_hz"]), c["poles"], c["trim_s"])
    a = AuditSettings()
    assert (a.baseline, a.alpha, a.min_gain) == (
        d["audit"]["baseline"],
        d["audit"]["alpha"],
        d["audit"]["min_gain"],
    )
    q = QualitySettings()
    assert {k: getattr(q, k) for k in d["quality"]} == d["quality"]
    m = MapSettings()
    assert (
        m.cell_m or 0.0,
        m.noise_nT or 0.0,
        m.level_trend,
        m.direction,
        m.arima,
        m.min_crossing_angle_deg,
        m.microlevel,
        m.microlevel_wavelength_m,
        m.microlevel_along_m,
        m.microlevel_clip_nT,
    ) == (
        d["map"]["cell_m"],
        d["map"]["noise_nT"],
        d["map"]["level_trend"],
        d["map"]["direction"],
        d["map"]["arima"],
        d["map"]["min_crossing_angle_deg"],
        d["map"]["microlevel"],
        d["map"]["microlevel_wavelength_m"],
        d["map"]["microlevel_along_m"],
        d["map"]["microlevel_clip_nT"],
    )
    # the configuration's settings are the dataclasses' defaults: nothing re-typed between them
    assert cfg.fit_settings("tl16") == FitSettings()
    assert cfg.audit_settings() == AuditSettings()
    assert cfg.map_settings() == MapSettings()
    assert cfg.quality_settings() == QualitySettings()
    from pipeline.campaign.stage import CampaignSettings

    cs = CampaignSettings()
    assert cfg.campaign_settings() == cs
    assert (cs.cell_m, cs.level_trend, cs.min_crossing_angle_deg) == (
        m.cell_m,
        m.level_trend,
        m.min_crossing_angle_deg,
    )
    from pipeline.maps.enhance import EnhanceSettings, parse_products

    assert cfg.enhance_settings() == EnhanceSettings()
    assert EnhanceSettings().products == parse_products(d["enhance"]["products"])
    from pipeline.despike import DespikeSettings

    ds = DespikeSettings()
    assert {k: getattr(ds, k) for k in d["despike"]} == d["despike"]
    assert cfg.despike_settings() == ds
    from pipeline.navigation.stage import NavigationSettings

    nav = NavigationSettings()
    assert cfg.navigation_settings() == nav
    assert (nav.filter, nav.ins, nav.seed) == tuple(
        d["navigate"][k] for k in ("filter", "ins", "seed")
    )


def test_no_processing_default_is_retyped_in_the_code():
    """The band (and its order and trim) is written in the TOML only."""
    band = re.compile(r"\(\s*0\.1\s*,\s*0\.9\s*\)|\[\s*0\.1\s*,\s*0\.9\s*\]")
    hits = [
        f"{p.relative_to(REPO)}:{n}"
        for root in ("pipeline", "flows")
        for p in sorted((REPO / root).rglob("*.py"))
        for n, line in enumerate(p.read_text().splitlines(), 1)
        if band.search(line)
        or re.search(r"\b(poles|trim|trim_s)\s*[:=][^=].*\b(4|20|2\.0)\b", line)
    ]
    assert hits == []


def test_ridge_is_checked_when_the_configuration_is_loaded(tmp_path):
    f = tmp_path / "c.toml"
    for bad in ("-1", "'big'", "true"):
        f.write_text(f"[compensation]\nridge = {bad}\n")
        with pytest.raises(AeromagError, match=r"compensation.ridge = .*: use \"auto\""):
            Config.load(f)
    f.write_text("[compensation]\nridge = 0.001\n")
    assert Config.load(f).fit_settings("tl18").ridge == 0.001
    with pytest.raises(AeromagError, match="compensation.ridge"):
        Config.load().with_values({"compensation.ridge": -2.0})
    f.write_text("[compensation]\nband_hz = [0.9, 0.1]\n")
    with pytest.raises(AeromagError, match="compensation.band_hz"):
        Config.load(f).validate()


# --------------------------------------------------------------------------------------------
def test_single_stage_commands_take_a_configuration_their_options_override(tmp_path):
    """`compensate --config FILE` fits with the file's band and ridge; `--ridge` given on the
    command line overrides that key and leaves the others; an invalid override names the
    option."""
    import typer

    from flows.cli import app

    cmd = typer.main.get_command(app)
    for name in ("compensate", "map", "quality", "audit", "vector", "process"):
        assert "--config" in [o for p in cmd.commands[name].params for o in p.opts], name
    src = FIXTURES / "box_scalar_vector_only.mcap"
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f"config_version = 1\n[compensation]\nband_hz = {BAND}\nridge = 0.001\nmodels = ['tl18']\n"
    )
    runner = CliRunner()

    def run(*extra):
        js = tmp_path / f"s{len(list(tmp_path.glob('*.json')))}.json"
        res = runner.invoke(
            app,
            [
                "compensate",
                str(src),
                "--out",
                str(js.with_suffix(".mcap")),
                "--json",
                str(js),
                "--calibration",
                "all",
                "--config",
                str(cfg),
                *extra,
            ],
        )
        return res, js

    res, js = run()
    assert res.exit_code == 0, res.output
    s = json.loads(js.read_text())
    assert s["model"] == "tl18" and s["lambda"] == 0.001 and s["band_hz"] == BAND
    res, js = run("--ridge", "0.002", "--model", "tl16")
    assert res.exit_code == 0, res.output
    s = json.loads(js.read_text())
    assert s["model"] == "tl16" and s["lambda"] == 0.002 and s["band_hz"] == BAND
    res, js = run("--ridge", "-1")
    assert res.exit_code == 2 and "--ridge -1.0: compensation.ridge" in res.output
    assert not js.exists()


# --------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def processed(tmp_path_factory):
    """`process` (the plain steps) with the band 0.05-0.5 Hz; audit and vector off (slow, and
    the audit's FOM is checked on its own below), navigability off (the switch)."""
    from flows.postflight import run_plain
    from pipeline.simulate import write_simulation

    folder = tmp_path_factory.mktemp("band")
    src = write_simulation(run_sim("uav-small", 3), folder / "flight.mcap")
    cfg = folder / "c.toml"
    cfg.write_text(
        f"config_version = 1\n[compensation]\nband_hz = {BAND}\n"
        "models = ['tl18', 'agg-tl']\n[audit]\nenabled = false\n"
        "[vector]\nenabled = false\n[map]\narima = '1,1,1'\n[navigate]\nnavigability = false\n"
    )
    return src, run_plain(str(src), str(folder / "out"), str(cfg))


def test_the_navigability_step_follows_its_switch(processed):
    """``[navigate] navigability = false``: no step, no channel, no summary block."""
    _, s = processed
    assert "navigability" not in s and "navigability" not in s["timings_s"]
    assert "/map/anomaly" in s["channels_written"]
    assert "/map/navigability" not in s["channels_written"]


def test_every_fom_table_agrees_with_a_non_default_band(processed):
    from pipeline.io.reader import read_flight
    from pipeline.quality.stage import fom_table, state_key
    from pipeline.segment import segment_flight

    src, s = processed
    comp, table = s["compensation"], s["quality"]["fom_boxes"]
    assert table and set(comp) == {"final", "tl18", "agg-tl"}
    for m in ("tl18", "agg-tl"):
        assert comp[m]["band_hz"] == BAND
        boxes = comp[m]["fom_nT"]["boxes"]
        assert len(boxes) == len(table)
        for row, b in zip(table, boxes, strict=True):
            assert (row["pass"], row["cardinal"], row["manoeuvre"]) == (
                b["pass"],
                b["cardinal"],
                b["manoeuvre"],
            )
            assert row["uncompensated_nT"] == pytest.approx(b["uncompensated_nT"], rel=1e-9)
            assert row[f"{state_key(m)}_nT"] == pytest.approx(b["compensated_nT"], rel=1e-9)
    report = Path(s["outputs"]["report"]).read_text()
    for m in ("tl18", "agg-tl"):
        fom = comp[m]["fom_nT"]
        assert f"| {m} | {fom['uncompensated']:.2f} | {fom['compensated']:.2f} |" in report, m
    # the band matters: in the shipped band the same boxes measure differently
    flight = read_flight(src)
    t, raw = flight.data["time_s"].to_numpy(float), flight.data["scalar_nT"].to_numpy(float)
    shipped_band = fom_table(t, raw, {"raw": raw}, segment_flight(flight).boxes())
    assert not np.allclose(
        [r["uncompensated_nT"] for r in shipped_band],
        [r["uncompensated_nT"] for r in table],
        rtol=1e-3,
    )


def test_the_audit_measures_its_fom_in_the_configured_band(monkeypatch):
    """run_audit's FOM gain is measured in ``settings.band`` (the configured band): the
    search is stubbed out and the first FOM call is caught with its band."""
    import pipeline.audit.stage as audit_stage
    from pipeline.audit.extended import ModelSpec
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight

    class Caught(Exception):
        pass

    seen = []

    def spy(time_s, raw, comp, boxes, band_hz=None, poles=None):
        seen.append((tuple(band_hz), poles))
        raise Caught

    monkeypatch.setattr(audit_stage, "figure_of_merit", spy)
    monkeypatch.setattr(
        audit_stage.Auditor,
        "run",
        lambda self, progress=None: (ModelSpec(base=self.s.baseline), [], []),
    )
    cfg = Config.load().with_values({"compensation.band_hz": BAND, "compensation.poles": 3})
    flight = read_flight(FIXTURES / "box_uav.mcap")
    with pytest.raises(Caught):
        audit_stage.run_audit(flight, segment_flight(flight), cfg.audit_settings())
    assert seen == [(tuple(BAND), 3)]


def test_navigate_section_is_checked_when_the_configuration_is_validated(tmp_path):
    f = tmp_path / "c.toml"
    for bad, msg in (
        ('filter = "kf"', "navigate: filter 'kf': use ekf or pf"),
        ('ins = "consumer"', "navigate: ins 'consumer'"),
        ('map = "truth"', "navigate.map: use anomaly_filtered or anomaly"),
    ):
        f.write_text(f"[navigate]\n{bad}\n")
        with pytest.raises(AeromagError, match=re.escape(msg)):
            Config.load(f).validate()
    f.write_text('[navigate]\nfilter = "pf"\nseed = 3\n')
    st = Config.load(f).navigation_settings()
    assert (st.filter, st.seed, st.segments) == ("pf", 3, "validation")
