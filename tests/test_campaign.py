"""Campaigns: sorties of one area levelled jointly on every crossover, gridded once.

Three uav-small sorties over one geology on three days, each with its own diurnal level and
line positions (pipeline/simulate/campaign.py), simulated and processed once for the module.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.campaign.joint import level_jointly
from pipeline.campaign.sorties import validate_campaign
from pipeline.campaign.stage import run_campaign
from pipeline.errors import AeromagError
from pipeline.maps.level import Crossover, Line
from pipeline.simulate.campaign import (
    SORTIES,
    Truth,
    all_crossovers,
    campaign_plan,
    grid_rmse_nT,
    simulate_campaign,
    sorties_and_frame,
    true_levels_nT,
)
from tests.conftest import REPO
from tests.recordings import validate_every_message


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("campaign")
    return folder, simulate_campaign(folder)


@pytest.fixture(scope="module")
def merged(flights):
    """The campaign through its plain steps (the flow's, without Prefect), with exports."""
    from flows.campaign import run_plain

    folder, proc = flights
    cfg = folder / "campaign.toml"
    cfg.write_text('config_version = 1\n[export]\nformats = ["geotiff", "netcdf"]\n')
    return folder / "out", run_plain(proc, folder / "out", str(cfg))


# --------------------------------------------------------------------------------------------
def test_design_recovers_flight_and_line_offsets_exactly():
    """Noise-free crossovers of a synthetic campaign: two flights of two survey lines and a
    tie each; the solution is the injected offsets minus their means (the constraints)."""
    rng = np.random.default_rng(1)
    flight = np.array([3.0, -1.0])
    line = {"0:L1": 0.5, "0:L2": -0.2, "0:T1": -0.3, "1:L1": 0.1, "1:L2": 0.4, "1:T1": -0.5}
    keys = sorted(line)
    xs, between = [], []
    for a in keys:
        for b in keys:
            if a < b and (a[0] != b[0] or "T" in a + b) and a[2] != b[2]:
                va = flight[int(a[0])] + line[a]
                vb = flight[int(b[0])] + line[b]
                xs.append(Crossover(a, b, 0.0, 0.0, va, vb, 10.0, 20.0))
                between.append(a[0] != b[0])
    times = {k: rng.uniform(0, 100, 20) for k in keys}
    lev = level_jointly(times, 2, xs, np.array(between))
    np.testing.assert_allclose(lev.flight_offsets_nT, flight - flight.mean(), atol=1e-9)
    for f in "01":
        mine = [k for k in keys if k[0] == f]
        want = np.array([line[k] for k in mine]) - np.mean([line[k] for k in mine])
        np.testing.assert_allclose([lev.line_offsets[k][0] for k in mine], want, atol=1e-9)
    assert np.max(np.abs(lev.after_nT)) < 1e-9
    rms = lev.rms_nT()
    assert rms["between_flights"]["before"] > 1.0 and rms["between_flights"]["after"] < 1e-9


def test_flights_no_crossover_ties_are_grouped():
    from pipeline.campaign.stage import untied_groups

    xs = [Crossover(a, b, 0, 0, 0, 0, 0, 0) for a, b in (("0:L1", "1:T1"), ("2:L1", "3:T1"))]
    xs.append(Crossover("0:L1", "0:T1", 0, 0, 0, 0, 0, 0))
    assert untied_groups(4, xs, np.array([True, True, False])) == [[0, 1], [2, 3]]
    assert untied_groups(2, xs[:1], np.array([True])) == [[0, 1]]


def test_line_trends_fit_drifting_lines():
    """Slopes in time on two survey lines crossed by three ties: offsets alone leave the
    drift in the crossovers, offsets and trends fit them exactly (with trends a line's
    corrections are not unique; the ridge takes the smallest)."""
    from pipeline.maps.level import crossovers

    t = np.linspace(0, 100, 101)
    n = np.arange(101)
    survey = [
        Line("0:L1", "survey", np.zeros(101), t, t, 0.05 * (t - 50.0) + 1.0, n),
        Line("0:L2", "survey", np.full(101, 30.0), t, t + 120, -0.02 * (t - 50.0), n),
    ]
    ties = [
        Line(f"0:T{k}", "tie", t - 50, np.full(101, y), t + 300 + 200 * k, np.full(101, c), n)
        for k, (y, c) in enumerate(((20.0, 0.3), (50.0, -0.2), (80.0, 0.0)))
    ]
    xs = crossovers(survey, ties)
    assert len(xs) == 6
    times = {ln.line_id: ln.time_s for ln in survey + ties}
    dc = level_jointly(times, 1, xs, np.zeros(6, bool), trend=False)
    tr = level_jointly(times, 1, xs, np.zeros(6, bool), trend=True)
    assert np.sqrt(np.mean(dc.after_nT**2)) > 0.5
    assert np.max(np.abs(tr.after_nT)) < 1e-6
    assert abs(sum(v[0] for v in tr.line_offsets.values())) < 1e-9  # the flight's level


def test_joint_levelling_against_the_truth(flights, merged):
    """Per-flight offsets recover the sorties' levels (up to the common datum), the merged
    grid beats merging the flights as each levelled itself, and between-flight crossovers end
    within 1.2x the within-flight RMS."""
    folder, proc = flights
    _, doc = merged
    frame, sorties = sorties_and_frame(proc)
    truth = Truth(folder / "day1.truth.json")
    level = true_levels_nT(sorties, truth, frame)
    offsets = np.array([doc["flight_offsets_nT"][name] for name, *_ in SORTIES])
    injected = np.array([lv for *_, lv, _ in SORTIES])
    np.testing.assert_allclose(offsets, level, atol=0.15)
    np.testing.assert_allclose(offsets, injected - injected.mean(), atol=0.6)
    assert abs(offsets.sum()) < 1e-9
    rms = doc["crossover_rms_nT"]
    assert rms["between_flights"]["before"] > 3.0
    assert rms["between_flights"]["after"] <= 1.2 * rms["within_flight"]["after"]
    assert doc["between_over_within_after"] <= 1.2 and doc["warnings"] == []
    # the merged grid against the truth: joint levelling vs each flight levelled alone
    xs, between = all_crossovers(sorties)
    run = run_campaign(sorties, frame, xs, between, per_flight_grid=True)
    joint = grid_rmse_nT(run.grid, truth, frame)
    alone = grid_rmse_nT(run.per_flight_grid, truth, frame)
    assert joint < 0.5 * alone and joint < 0.3, (joint, alone)
    assert doc["grid"]["cell_m"] == pytest.approx(12.5, abs=0.1)  # a quarter of 50 m


def test_outputs_validate_and_exports_place_the_grid(merged, flights):
    out, doc = merged
    mcap = out / "campaign.mcap"
    topics = {
        "/map/anomaly",
        "/map/frame",
        "/map/lines",
        "/campaign/flight_offset",
        "/campaign/crossovers",
    }
    n = validate_every_message(mcap)
    samples = sum(f["samples"] for f in doc["flights"])
    assert n == 2 + samples + 3 + sum(doc["crossovers"].values())
    from pipeline.export import export_recording
    from pipeline.export.source import read_map_products

    mp = read_map_products(mcap, lines=True)
    assert len(mp.lines) == samples
    # the line data carry the joint correction: per flight, flight offset + line offsets
    # (zero mean over the flight's lines) below each flight's own levelled anomaly
    _, proc = flights
    for f in doc["flights"]:
        own = read_map_products(proc / f"{f['flight']}.processed.mcap", lines=True).lines
        mine = [p for _, p in mp.lines if p["line_id"].startswith(f["flight"] + ".")]
        lines = {p["line_id"].split(".", 1)[1] for p in mine}
        ours = {(p["line_id"], p["fiducial"]): p["anomaly_nT"] for _, p in own}
        d = {}
        for p in mine:
            line = p["line_id"].split(".", 1)[1]
            d.setdefault(line, []).append(ours[(line, p["fiducial"])] - p["anomaly_nT"])
        per_line = np.array([np.mean(v) for v in d.values()])
        assert len(lines) == f["lines"] and np.ptp([np.ptp(v) for v in d.values()]) < 1e-6
        assert abs(per_line.mean() - f["offset_nT"]) < 1e-6
    assert sorted(export_recording(mcap, out / "lines", ["csv", "xyz"])) == ["csv", "xyz"]
    assert [g.name for g in mp.grids] == ["anomaly"]
    assert abs(mp.frame.latitude_deg - doc["grid"]["origin"]["latitude_deg"]) < 1e-12
    from pipeline.io.reader import read_topics

    assert set(read_topics(mcap).topics) == topics
    assert sorted(Path(p).name for ps in doc["exports"].values() for p in ps) == [
        "campaign.anomaly.tif",
        "campaign.maps.nc",
    ]
    import rasterio

    with rasterio.open(out / "campaign.anomaly.tif") as ds:
        assert ds.crs.to_epsg() == mp.frame.utm_epsg and ds.tags(1)["units"] == "nT"
    for name in ("campaign.report.md", "campaign.map.png", "campaign.crossovers.png"):
        assert (out / name).stat().st_size > 500, name
    assert "between flights" in (out / "campaign.report.md").read_text()
    assert [f["flight"] for f in doc["flights"]] == ["day1", "day2", "day3"]
    assert set(doc["crossover_rms_nT"]) == {"within_flight", "between_flights"}
    assert not [p for p in out.iterdir() if ".partial" in p.name]


# --------------------------------------------------------------------------------------------
def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "flows.cli", "campaign", *args],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
    )


def _synthetic(path: Path, dlat_deg: float = 0.0, legacy: bool = False) -> Path:
    """A tiny processed recording with map channels (tests/mapfile.py), its grid moved north
    by ``dlat_deg`` (1 deg: 111 km); ``legacy``: with the /map/frame of recordings processed
    before the grids were computed in a projected CRS."""
    from pipeline.io.reader import read_topics
    from pipeline.io.writer import McapOutput, encode
    from tests.mapfile import write_processed

    src, _ = write_processed(path.with_name("." + path.name), legacy=legacy)
    rec = read_topics(src)
    with McapOutput(path) as out:
        for topic, raw in rec.topics.items():
            cid = out.channel(topic, raw.schema_name)
            for t, data in zip(raw.log_time_ns, raw.data, strict=True):
                p = json.loads(data)
                if topic == "/map/frame":
                    p["latitude"] += dlat_deg
                    if "origin_northing_m" in p:
                        p["origin_northing_m"] += dlat_deg * 111_000.0
                out.write(cid, t, encode(p))
    src.unlink()
    return path


def test_bad_input_is_one_line_naming_what_is_missing(tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AeromagError) as exc:
        validate_campaign(empty)
    assert "no processed recordings" in str(exc.value) and "aeromag process" in str(exc.value)
    # a recording without map channels (the calibration box fixture, renamed)
    nomap = tmp_path / "nomap"
    nomap.mkdir()
    _synthetic(nomap / "a.processed.mcap")
    (nomap / "b.processed.mcap").write_bytes((REPO / "fixtures" / "box_uav.mcap").read_bytes())
    with pytest.raises(AeromagError) as exc:
        validate_campaign(nomap)
    msg = str(exc.value)
    assert "b.processed.mcap" in msg and "/map/frame" in msg and "aeromag process" in msg
    assert "\n" not in msg
    (nomap / "b.processed.mcap").unlink()
    with pytest.raises(AeromagError, match="2 or more processed recordings"):
        validate_campaign(nomap)


def test_cli_refuses_disjoint_areas_in_one_line_before_any_flow(tmp_path, monkeypatch, capsys):
    """Three flights, one of them 11 km north of the others (the console entry point, in
    process: what `aeromag campaign` prints)."""
    from flows.cli import main

    _synthetic(tmp_path / "a.processed.mcap")
    _synthetic(tmp_path / "b.processed.mcap")
    _synthetic(tmp_path / "c.processed.mcap", dlat_deg=0.1)
    argv = ["aeromag", "campaign", str(tmp_path), "--out", str(tmp_path / "o")]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit) as exc:
        main()
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "disjoint areas" in lines[0] and "a, b | c" in lines[0], err
    assert not (tmp_path / "o").exists()


def test_a_recording_processed_before_the_projected_frame_joins_a_campaign(tmp_path):
    """An older recording (azimuthal equidistant /map/frame, no EPSG) and a new one (UTM)
    over one area: each grid's box is placed by its own frame (its lines fall inside it),
    one group, and both flights' lines read into the campaign's UTM frame."""
    from pipeline.campaign.sorties import campaign_frame, read_sortie

    _synthetic(tmp_path / "new.processed.mcap")
    _synthetic(tmp_path / "old.processed.mcap", legacy=True)
    infos = validate_campaign(tmp_path)  # disjoint boxes would be refused here
    assert [i.name for i in infos] == ["new", "old"] and infos[1].frame.legacy
    frame = campaign_frame(infos)
    assert frame.crs == "EPSG:32649" and frame.zones == (32649,)
    for k, info in enumerate(infos):
        sortie = read_sortie(k, info, frame)
        assert len(sortie.lines) == 3
        e = np.concatenate([ln.east_m for ln in sortie.lines])
        n = np.concatenate([ln.north_m for ln in sortie.lines])
        lat, lon, _ = frame.to_geodetic(e, n)
        assert info.lat_range_deg[0] < lat.min() and lat.max() < info.lat_range_deg[1]
        assert info.lon_range_deg[0] < lon.min() and lon.max() < info.lon_range_deg[1]


def test_disjoint_groups_are_named(tmp_path):
    for name, dlat in (("n1", 0.1), ("n2", 0.1), ("s1", 0.0), ("s2", 0.0)):
        _synthetic(tmp_path / f"{name}.processed.mcap", dlat)
    with pytest.raises(AeromagError, match=r"n1, n2 \| s1, s2"):
        validate_campaign(tmp_path)
    (tmp_path / "n1.processed.mcap").unlink()
    (tmp_path / "n2.processed.mcap").unlink()
    assert [i.name for i in validate_campaign(tmp_path)] == ["s1", "s2"]


@pytest.mark.slow
def test_cli_campaign_on_a_dask_cluster(flights, tmp_path):
    """`aeromag campaign` end to end: its own Prefect server, a 2-worker Dask cluster."""
    _, proc = flights
    res = _cli(str(proc), "--out", str(tmp_path / "out"), "--workers", "2")
    assert res.returncode == 0, res.stderr[-3000:]
    doc = json.loads((tmp_path / "out" / "campaign.summary.json").read_text())
    assert "between flights" in res.stdout and doc["between_over_within_after"] <= 1.2
    assert (tmp_path / "out" / "campaign.anomaly.tif").is_file()


@pytest.mark.slow
def test_six_sorties_against_the_truth(tmp_path):
    """Six sorties (levels drawn from N(0, 5) nT, lines shifted by 12.5 m steps): offsets
    within 0.15 nT of the true levels, the between-flight target, the grid against truth."""
    from flows.campaign import run_plain

    plan = campaign_plan(6)
    proc = simulate_campaign(tmp_path, plan)
    doc = run_plain(proc, tmp_path / "out")
    frame, sorties = sorties_and_frame(proc)
    truth = Truth(tmp_path / "day1.truth.json")
    level = true_levels_nT(sorties, truth, frame)
    offsets = np.array([doc["flight_offsets_nT"][s.name] for s in sorties])
    np.testing.assert_allclose(offsets, level, atol=0.15)
    assert doc["between_over_within_after"] <= 1.2 and doc["crossovers"]["between_flights"] > 300
    xs, between = all_crossovers(sorties)
    run = run_campaign(sorties, frame, xs, between, per_flight_grid=True)
    joint = grid_rmse_nT(run.grid, truth, frame)
    assert joint < 0.5 * grid_rmse_nT(run.per_flight_grid, truth, frame) and joint < 0.3


@pytest.mark.slow
def test_cli_a_sortie_failing_on_a_dask_worker_is_one_line(tmp_path):
    """Line samples without their anomaly pass the checks and fail when read on a worker:
    Prefect's task and flow logs and the CLI each say it in one line, nothing is written."""
    from pipeline.io.reader import read_topics
    from pipeline.io.writer import McapOutput, encode

    _synthetic(tmp_path / "a.processed.mcap")
    src = _synthetic(tmp_path / ".b.mcap")
    rec = read_topics(src)
    with McapOutput(tmp_path / "b.processed.mcap") as out:
        for topic, raw in rec.topics.items():
            cid = out.channel(topic, raw.schema_name)
            for t, data in zip(raw.log_time_ns, raw.data, strict=True):
                p = json.loads(data)
                if topic == "/map/lines":
                    p.pop("anomaly_nT")
                out.write(cid, t, encode(p))
    src.unlink()
    res = _cli(str(tmp_path), "--out", str(tmp_path / "o"), "--workers", "1")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr[-3000:]
    assert "Error logging" not in res.stderr
    want = "b.processed.mcap: /map/lines: unreadable line samples (KeyError: 'anomaly_nT')"
    assert res.stderr.strip().splitlines()[-1] == f"aeromag: error: {tmp_path}/{want}"
    assert not (tmp_path / "o" / "campaign.summary.json").exists()
