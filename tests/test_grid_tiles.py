"""Minimum curvature in tiles (large grids) against the same grid in one solve.

The field: a regional gradient and twenty buried point sources (20-80 m deep, tens of nT)
sampled along lines 20 m apart with ties, 5 m cells. Solved in tiles of 96 cells with the
production overlap, every cell within 0.1 nT of the single solve (RMS under 0.005 nT, on a
field of 12 nT standard deviation) and the same cells masked; a block with one far stray
line (most tiles empty) still grids, its empty tiles masked.
"""

from __future__ import annotations

import numpy as np
import pytest

import pipeline.maps.grid as grid_mod
from pipeline.maps.grid import minimum_curvature


def _survey(extent_m: float, seed: int = 1):
    rng = np.random.default_rng(seed)
    lines = np.arange(0.0, extent_m, 20.0)
    along = np.linspace(0.0, extent_m, 3000)
    ties = np.arange(0.0, extent_m, 150.0)
    e = np.r_[
        np.repeat(lines, along.size) + rng.normal(0, 1.0, lines.size * along.size),
        np.tile(along, ties.size),
    ]
    n = np.r_[np.tile(along, lines.size), np.repeat(ties, along.size)]
    src = rng.uniform(0, extent_m, (20, 2))
    depth, amp = rng.uniform(20, 80, 20), rng.normal(0, 50, 20)
    v = 0.01 * e - 0.02 * n
    for (x, y), d, a in zip(src, depth, amp, strict=True):
        v = v + a * d**3 / ((e - x) ** 2 + (n - y) ** 2 + d**2) ** 1.5
    return e, n, v + rng.normal(0, 0.05, e.size)


def test_tiles_match_one_solve(monkeypatch):
    e, n, v = _survey(1500.0)
    monkeypatch.setattr(grid_mod, "TILE_CELLS", 10**9)
    whole = minimum_curvature(e, n, v, 5.0)
    monkeypatch.setattr(grid_mod, "TILE_CORE_CELLS", 96)
    monkeypatch.setattr(grid_mod, "TILE_CELLS", 1)
    tiled = minimum_curvature(e, n, v, 5.0)
    assert tiled.values.shape == whole.values.shape and whole.values.size > 90_000
    ok = np.isfinite(whole.values)
    assert np.array_equal(ok, np.isfinite(tiled.values))
    d = (tiled.values - whole.values)[ok]
    assert np.nanstd(whole.values) > 10.0
    assert np.max(np.abs(d)) < 0.1, np.max(np.abs(d))
    assert np.sqrt(np.mean(d**2)) < 0.005


@pytest.mark.parametrize("core", [64])
def test_tiles_without_data_stay_masked(monkeypatch, core):
    rng = np.random.default_rng(2)
    e = np.r_[np.repeat(np.arange(5) * 20.0, 400), np.linspace(-1500, 0, 3000)]
    n = np.r_[np.tile(np.linspace(0, 400, 400), 5), np.linspace(-1500, 0, 3000)]
    v = np.sin(e / 80.0) + rng.normal(0, 0.01, e.size)
    monkeypatch.setattr(grid_mod, "TILE_CORE_CELLS", core)
    monkeypatch.setattr(grid_mod, "TILE_CELLS", 1)
    g = minimum_curvature(e, n, v, 5.0)
    ok = np.isfinite(g.values)
    assert 0 < ok.mean() < 0.2  # the block and the line's corridor only
    fit = g.interpolate(e, n)
    good = np.isfinite(fit)
    assert good.mean() > 0.95
    assert np.sqrt(np.mean((fit[good] - v[good]) ** 2)) < 0.05


def test_symmetric_solve_equals_the_general_one():
    """Minimum curvature's normal equations are solved by SuperLU in its symmetric mode
    (``grid._solve_spd``): the same solution as the general factorisation on a positive
    definite system, one column or several; a singular system falls back to the general
    one (its warning and non-finite solution, not an exception)."""
    import warnings

    import scipy.sparse as sp
    from scipy.sparse.linalg import MatrixRankWarning, spsolve

    from pipeline.maps.grid import _laplacian, _solve_spd

    rng = np.random.default_rng(5)
    nx, ny, m = 23, 31, 300
    rows = np.repeat(np.arange(m), 1)
    cols = rng.integers(0, nx * ny, m)
    a = sp.csr_matrix((np.ones(m), (rows, cols)), shape=(m, nx * ny))
    lap = _laplacian(ny, nx)
    lhs = (a.T @ a + 1e-3 * (lap.T @ lap)).tocsc()
    rhs = np.asarray(a.T @ rng.normal(size=(m, 2)))
    want = spsolve(lhs, rhs)
    got = _solve_spd(lhs, rhs)
    assert np.max(np.abs(got - want)) <= 1e-9 * np.max(np.abs(want))
    one = _solve_spd(lhs, rhs[:, :1])
    assert one.shape == (nx * ny, 1)
    assert np.allclose(one[:, 0], want[:, 0], rtol=0, atol=1e-9 * np.max(np.abs(want)))
    singular = sp.csc_matrix(np.ones((2, 2)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", MatrixRankWarning)
        out = _solve_spd(singular, np.ones((2, 1)))
    assert out.shape == (2, 1) and not np.isfinite(out).all()
