"""Gridders against analytic dipole fields (harmonica's forward model): equivalent sources
continue the field to another height and drape it over terrain; the cross-validated choice
picks a gridder that is nearly as good as the best one against the truth."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.errors import AeromagError
from pipeline.maps.gridders import (
    EquivalentSourceGridder,
    LineData,
    MinimumCurvatureGridder,
    choose_gridder,
    line_folds,
)

INCLINATION_DEG = 50.0
SPACING_M = 50.0


def total_field_anomaly_nT(east, north, up, sources):
    """Total-field anomaly (nT) of induced dipoles along the main field (declination 0)."""
    import harmonica as hm

    inc = np.radians(INCLINATION_DEG)
    direction = np.array([0.0, np.cos(inc), -np.sin(inc)])  # east, north, up
    coords = tuple(np.asarray(c, float).ravel() for c in (east, north, up))
    moments = np.outer(sources["moment_A_m2"], direction).T
    be, bn, bu = hm.dipole_magnetic(coords, sources["position_m"], moments, field="b")
    out = be * direction[0] + bn * direction[1] + bu * direction[2]
    return out.reshape(np.shape(east))


def _sources(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    k = 4
    return {
        "position_m": (
            rng.uniform(150, 850, k),
            rng.uniform(150, 850, k),
            -rng.uniform(120, 300, k),
        ),
        "moment_A_m2": rng.uniform(5e5, 2e6, k),
    }


def _survey(sources, height_m, seed: int = 0, noise_nT: float = 0.02) -> LineData:
    """North-south lines 50 m apart over 1 x 1 km, a sample every 4 m, two east-west ties;
    ``height_m``: a number or a function of (east, north) giving the flight height."""
    rng = np.random.default_rng(seed)
    along = np.arange(0.0, 1000.0, 4.0)
    parts = []
    for k, x in enumerate(np.arange(0.0, 1000.1, SPACING_M)):
        parts.append((np.full(along.size, x), along, f"L{k:03d}", "survey"))
    for k, y in enumerate((250.0, 750.0)):
        parts.append((along, np.full(along.size, y), f"T{k:03d}", "tie"))
    e = np.concatenate([p[0] for p in parts])
    n = np.concatenate([p[1] for p in parts])
    u = height_m(e, n) if callable(height_m) else np.full(e.size, float(height_m))
    v = total_field_anomaly_nT(e, n, u, sources) + rng.normal(0.0, noise_nT, e.size)
    line = np.concatenate([np.full(p[0].size, p[2], dtype=object) for p in parts])
    kind = np.concatenate([np.full(p[0].size, p[3], dtype=object) for p in parts])
    return LineData(e, n, u, v, line, kind)


def _cells(step=12.5):
    x = np.arange(75.0, 925.0, step)  # inside the lines, away from the edges
    return np.meshgrid(x, x)


def _rel_rms(pred, truth):
    return float(np.sqrt(np.mean((pred - truth) ** 2)) / np.std(truth))


def test_equivalent_sources_continue_the_field_upward():
    src = _sources(1)
    data = _survey(src, 100.0)
    gx, gy = _cells()
    eqs = EquivalentSourceGridder(depth_m=2 * SPACING_M, damping=1e-3, block_m=6.25).fit(data)
    for h in (100.0, 150.0):
        truth = total_field_anomaly_nT(gx, gy, np.full(gx.shape, h), src)
        assert _rel_rms(eqs.predict(gx, gy, np.full(gx.shape, h)), truth) < 0.05, h
    # the flight surface's map is not the field 50 m higher: continuation matters
    truth150 = total_field_anomaly_nT(gx, gy, np.full(gx.shape, 150.0), src)
    flat = total_field_anomaly_nT(gx, gy, np.full(gx.shape, 100.0), src)
    assert _rel_rms(flat, truth150) > 0.3


def test_draped_map_from_a_constant_altitude_flight():
    """Flown at a constant 180 m over a 90 m hill; the map draped 110 m above the terrain
    (so 20-110 m below the flight): equivalent sources downward-continue to the drape,
    minimum curvature only has the flight surface."""
    src = _sources(2)

    def terrain(e, n):
        return 90.0 * np.exp(-((e - 500.0) ** 2 + (n - 500.0) ** 2) / (2 * 250.0**2))

    data = _survey(src, 180.0)
    gx, gy = _cells()
    drape = terrain(gx, gy) + 110.0
    truth = total_field_anomaly_nT(gx, gy, drape, src)
    eqs = EquivalentSourceGridder(depth_m=2 * SPACING_M, damping=1e-3, block_m=6.25).fit(data)
    mc = MinimumCurvatureGridder(12.5, SPACING_M).fit(data)
    err_eqs = _rel_rms(eqs.predict(gx, gy, drape), truth)
    err_mc = _rel_rms(mc.predict(gx, gy), truth)
    assert err_eqs < 0.1
    assert err_mc > 3 * err_eqs


def test_line_folds_hold_out_interior_lines_only():
    data = _survey(_sources(3), 100.0)
    folds = line_folds(data, 5)
    held = set()
    for f in folds:
        held |= set(data.line[f].tolist())
    survey = sorted(set(data.line[data.kind == "survey"].tolist()))
    assert held == set(survey[1:-1])  # every interior survey line once, no edge, no tie
    assert sum(int(f.sum()) for f in folds) == int(np.isin(data.line, survey[1:-1]).sum())


@pytest.mark.parametrize("seed", [4, pytest.param(5, marks=pytest.mark.slow)])
def test_cross_validated_choice_is_nearly_the_best_against_truth(seed):
    src = _sources(seed)
    data = _survey(src, 100.0, seed=seed, noise_nT=0.1)
    gx, gy = _cells()
    truth = total_field_anomaly_nT(gx, gy, np.full(gx.shape, 100.0), src)
    choice = choose_gridder(data, "auto", 25.0, SPACING_M, None, dampings=(1e-3,), n_folds=3)
    errors = {}
    for name in choice.scores_nT:
        if name == "minimum_curvature":
            g = MinimumCurvatureGridder(25.0, SPACING_M).fit(data)
        else:
            ds, damp = float(name.split()[2]), float(name.split()[5])
            g = EquivalentSourceGridder(ds * SPACING_M, damp, 12.5).fit(data)
        errors[name] = _rel_rms(g.predict(gx, gy, np.full(gx.shape, 100.0)), truth)
    best = min(errors.values())
    picked = choice.describe()
    key = (
        "minimum_curvature"
        if picked["method"] == "minimum_curvature"
        else next(
            k
            for k in errors
            if k.startswith("equivalent_sources")
            and float(k.split()[2]) * SPACING_M == pytest.approx(picked["depth_m"])
            and float(k.split()[5]) == pytest.approx(picked["damping"])
        )
    )
    assert errors[key] <= 1.5 * best + 1e-3, (key, errors, choice.scores_nT)


def test_dem_that_does_not_cover_the_map_is_one_line(tmp_path):
    import rioxarray  # noqa: F401  (registers .rio)
    import xarray as xr

    from pipeline.maps.dem import dem_heights_m

    lon = np.linspace(108.0, 108.01, 20)
    lat = np.linspace(34.01, 34.0, 20)
    dem = xr.DataArray(
        np.full((20, 20), 400.0, np.float32), coords={"y": lat, "x": lon}, dims=("y", "x")
    ).rio.write_crs("EPSG:4326")
    path = tmp_path / "dem.tif"
    dem.rio.to_raster(path)
    inside = dem_heights_m(path, np.array([34.005]), np.array([108.005]))
    assert inside[0] == pytest.approx(400.0)
    with pytest.raises(AeromagError) as exc:
        dem_heights_m(path, np.array([34.005, 34.5]), np.array([108.005, 108.5]))
    msg = str(exc.value)
    assert "covers 50 %" in msg and "dem.tif" in msg and "\n" not in msg


def test_map_stage_grids_with_equivalent_sources(tmp_path):
    """``[map] gridder = "equivalent_sources"`` through the map stage on a simulated survey:
    the chosen depth and damping and their scores reach the summary, and the map matches the
    simulator's true anomaly as closely as minimum curvature's (both within the sensor's
    noise)."""
    from pipeline.compensate import FitSettings
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.maps.stage import MapSettings, build_map
    from pipeline.segment import segment_flight
    from pipeline.simulate import write_simulation
    from pipeline.simulate.truth import truth_on
    from tests.conftest import run_sim

    sim = run_sim("uav-small", 7)
    flight = read_flight(write_simulation(sim, tmp_path / "s.mcap"))
    seg = segment_flight(flight)
    comp = run_compensation(flight, seg, FitSettings(model="agg-tl")).compensated_nT
    errors = {}
    for method in ("minimum_curvature", "equivalent_sources"):
        mr = build_map(flight, seg, comp, MapSettings(gridder=method))
        truth = truth_on(sim, mr.grid, mr.frame)
        ok = np.isfinite(truth) & np.isfinite(mr.grid.values)
        d = mr.grid.values[ok] - truth[ok]
        errors[method] = float(np.sqrt(np.mean((d - d.mean()) ** 2)))
        info = mr.summary()["gridder"]
        assert info["method"] == method
    assert set(info) >= {"depth_m", "damping", "cv_rms_nT"} and len(info["cv_rms_nT"]) == 6
    noise = sim.truth["noise"]["scalar_nT"]
    assert errors["minimum_curvature"] < noise and errors["equivalent_sources"] < 2 * noise
