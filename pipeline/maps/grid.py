"""Gridding line data by minimum curvature, on a sparse linear system.

Hand-written because no maintained Python library grids 10^6 line samples by minimum
curvature: verde's splines are dense (O(N^2) memory) and GMT's ``surface`` is not a Python
package. The method (Briggs 1974, in its least-squares form): block means of the samples are
bilinear constraints on the grid nodes, and the squared discrete Laplacian over the grid is
minimised with them, which gives the minimum-curvature (biharmonic) surface between the data.
The sparse normal equations are solved by SuperLU; a grid larger than one tile
(``TILE_CELLS``) is solved in overlapping tiles blended across their overlaps, because
SuperLU's fill-in grows faster than the cells (one million cells: 6.8 GB and 150 s in one
solve). Cells farther than ``mask_distance_m`` from every data block are masked (NaN).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu, spsolve
from scipy.spatial import cKDTree


@dataclass
class Grid:
    """Values on cell centres: ``values[row, col]`` at east0 + col*cell, north0 + row*cell.

    Coordinates are local east/north metres (see ``crs``); rows go north, columns east.
    """

    values: np.ndarray
    east0_m: float
    north0_m: float
    cell_m: float
    crs: str = ""

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, columns)``: rows go north, columns east."""
        return self.values.shape

    def coordinates(self) -> tuple[np.ndarray, np.ndarray]:
        """Cell-centre coordinates in the grid's local metric frame.

        Returns
        -------
        east_m : ndarray
            One per column, m east of the frame's origin.
        north_m : ndarray
            One per row, m north of the frame's origin.
        """
        ny, nx = self.shape
        return (
            self.east0_m + self.cell_m * np.arange(nx),
            self.north0_m + self.cell_m * np.arange(ny),
        )

    def interpolate(self, east_m: np.ndarray, north_m: np.ndarray) -> np.ndarray:
        """Bilinear interpolation; NaN outside the grid or next to a masked cell."""
        fx = (np.asarray(east_m, float) - self.east0_m) / self.cell_m
        fy = (np.asarray(north_m, float) - self.north0_m) / self.cell_m
        ny, nx = self.shape
        ix, iy = np.floor(fx).astype(int), np.floor(fy).astype(int)
        ok = (ix >= 0) & (iy >= 0) & (ix < nx - 1) & (iy < ny - 1)
        out = np.full(fx.shape, np.nan)
        i, j = ix[ok], iy[ok]
        tx, ty = fx[ok] - i, fy[ok] - j
        v = self.values
        out[ok] = (
            (1 - tx) * (1 - ty) * v[j, i]
            + tx * (1 - ty) * v[j, i + 1]
            + (1 - tx) * ty * v[j + 1, i]
            + tx * ty * v[j + 1, i + 1]
        )
        return out

    def with_values(self, values: np.ndarray) -> Grid:
        """The same grid geometry and CRS with other values (same shape, e.g. a filtered map)."""
        return Grid(values, self.east0_m, self.north0_m, self.cell_m, self.crs)


def _solve(
    fx: np.ndarray,
    fy: np.ndarray,
    bv: np.ndarray,
    nx: int,
    ny: int,
    smoothness: float,
    ridge: float = 0.0,
) -> np.ndarray:
    """The minimum-curvature nodes ((nx * ny, fields), row-major from the south-west) of
    block means ``bv`` at fractional cell coordinates ``fx``, ``fy``; ``ridge`` (relative
    to the mean diagonal) keeps a tile with few data solvable."""
    i0, j0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    tx, ty = fx - i0, fy - j0
    rows = np.repeat(np.arange(fx.size), 4)
    cols = np.stack(
        [j0 * nx + i0, j0 * nx + i0 + 1, (j0 + 1) * nx + i0, (j0 + 1) * nx + i0 + 1], axis=1
    ).ravel()
    w = np.stack([(1 - tx) * (1 - ty), tx * (1 - ty), (1 - tx) * ty, tx * ty], axis=1).ravel()
    keep = cols < nx * ny
    a = sp.csr_matrix((w[keep], (rows[keep], cols[keep])), shape=(fx.size, nx * ny))
    lap = _laplacian(ny, nx)
    lhs = a.T @ a + smoothness * (lap.T @ lap)
    if ridge > 0:
        lhs = lhs + ridge * float(lhs.diagonal().mean()) * sp.identity(nx * ny)
    return _solve_spd(lhs.tocsc(), np.asarray(a.T @ bv)).reshape(nx * ny, -1)


def _solve_spd(lhs: sp.csc_matrix, rhs: np.ndarray) -> np.ndarray:
    """``lhs^-1 rhs`` for a symmetric positive definite sparse ``lhs`` (the normal equations
    of a least-squares problem), one factorisation for every column of ``rhs``.

    SuperLU in its symmetric mode: a minimum-degree ordering of A + A^T and pivots on the
    diagonal, which a positive definite matrix needs no others than. Its default (a column
    ordering and partial pivoting, for any matrix) fills the grid's banded system about
    twice as much and takes about twice the time; scipy has no sparse Cholesky."""
    try:
        lu = splu(
            lhs,
            permc_spec="MMD_AT_PLUS_A",
            diag_pivot_thresh=0.0,
            options={"SymmetricMode": True},
        )
    except RuntimeError:  # a zero pivot (a singular system): the general factorisation
        return np.asarray(spsolve(lhs, rhs[:, 0] if rhs.shape[1] == 1 else rhs)).reshape(rhs.shape)
    return lu.solve(rhs)


def _solve_tiled(
    fx: np.ndarray, fy: np.ndarray, bv: np.ndarray, nx: int, ny: int, smoothness: float
) -> np.ndarray:
    """:func:`_solve` on overlapping tiles of ``TILE_CORE_CELLS`` cells square, each solved
    with the data within ``TILE_OVERLAP_CELLS`` of its core and blended with weights that
    fall from 1 at its core's edge to 0 at its own: SuperLU's fill-in grows faster than the
    cells (a million-cell grid took 6.8 GB and 150 s in one solve; in tiles, the memory of
    one tile and a time linear in the cells). Tiles without data stay empty (NaN)."""
    ov = TILE_OVERLAP_CELLS
    # tiles of equal size in each direction (a sliver of a tile at the edge would see too
    # few lines to extrapolate the margin as the whole grid does)
    cx = int(np.ceil(nx / np.ceil(nx / TILE_CORE_CELLS)))
    cy = int(np.ceil(ny / np.ceil(ny / TILE_CORE_CELLS)))
    acc = np.zeros((ny, nx, bv.shape[1]))
    wsum = np.zeros((ny, nx))
    for jc in range(0, ny, cy):
        for ic in range(0, nx, cx):
            ia, ib = max(0, ic - ov), min(nx, ic + cx + ov)
            ja, jb = max(0, jc - ov), min(ny, jc + cy + ov)
            sel = (fx >= ia) & (fx <= ib - 1) & (fy >= ja) & (fy <= jb - 1)
            if not sel.any():
                continue
            zt = _solve(
                np.minimum(fx[sel] - ia, ib - ia - 1 - 1e-9),
                np.minimum(fy[sel] - ja, jb - ja - 1 - 1e-9),
                bv[sel],
                ib - ia,
                jb - ja,
                smoothness,
                ridge=TILE_RIDGE,
            ).reshape(jb - ja, ib - ia, -1)
            wx = _ramp(np.arange(ia, ib), ic, min(nx, ic + cx), ov, nx)
            wy = _ramp(np.arange(ja, jb), jc, min(ny, jc + cy), ov, ny)
            w = wy[:, None] * wx[None, :]
            acc[ja:jb, ia:ib] += w[:, :, None] * zt
            wsum[ja:jb, ia:ib] += w
    with np.errstate(invalid="ignore", divide="ignore"):
        z = acc / wsum[:, :, None]
    return z.reshape(nx * ny, -1)


def _ramp(idx: np.ndarray, lo: int, hi: int, ov: int, n: int) -> np.ndarray:
    """Blending weight of cells ``idx`` for a tile whose core is [lo, hi): 1 inside, falling
    linearly to 0 over ``ov`` cells outside (not at the grid's own edges, 0 and ``n``)."""
    below = np.where(lo == 0, 1.0, 1.0 - (lo - idx) / (ov + 1.0))
    above = np.where(hi == n, 1.0, 1.0 - (idx - (hi - 1)) / (ov + 1.0))
    return np.clip(
        np.minimum(np.where(idx < lo, below, 1.0), np.where(idx >= hi, above, 1.0)), 0, 1
    )


def _laplacian(ny: int, nx: int) -> sp.csr_matrix:
    """Operator whose squared norm is the discrete thin-plate energy
    f_xx^2 + 2 f_xy^2 + f_yy^2 (second differences in cell units)."""

    def second_diff(n):
        return (
            sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n))
            if n > 2
            else sp.csr_matrix((0, n))
        )

    ix, iy = sp.identity(nx), sp.identity(ny)
    dxx = sp.kron(iy, second_diff(nx))
    dyy = sp.kron(second_diff(ny), ix)
    # curvature along x in every row, along y in every column, and the twist f_xy
    dxy = sp.kron(
        sp.diags([-1.0, 1.0], [0, 1], shape=(ny - 1, ny)),
        sp.diags([-1.0, 1.0], [0, 1], shape=(nx - 1, nx)),
    )
    return sp.vstack([dxx, dyy, np.sqrt(2.0) * dxy]).tocsr()


MAX_CELLS = 1_000_000  # a million-cell grid: ~20 tiles, about a minute
# grids larger than one tile are solved in tiles (the memory of one ~83 000-cell solve)
TILE_CORE_CELLS = 192
TILE_OVERLAP_CELLS = 48  # 12 line spacings at the customary cell (32 left 0.4 nT seams)
TILE_CELLS = (TILE_CORE_CELLS + 2 * TILE_OVERLAP_CELLS) ** 2
TILE_RIDGE = 1e-10  # relative to the mean diagonal: a tile whose data are few or collinear


def minimum_curvature(
    east_m: np.ndarray,
    north_m: np.ndarray,
    value: np.ndarray,
    cell_m: float,
    mask_distance_m: float | None = None,
    smoothness: float = 1e-3,
    margin_cells: int = 2,
    crs: str = "",
) -> Grid:
    """Grid scattered line data.

    Parameters
    ----------
    east_m, north_m, value
        Samples (NaN values dropped); local metres and nT.
    cell_m
        Cell size (a quarter of the line spacing is customary); enlarged when the extent
        would need more than ``MAX_CELLS`` cells.
    mask_distance_m
        Mask cells farther than this from the nearest data block (default 2 cells).
    smoothness
        Weight of the curvature term relative to the data (data are honoured closely when
        small); the curvature penalty is the sum of squared second differences (thin-plate
        energy: f_xx^2 + 2 f_xy^2 + f_yy^2) in cell units.
    """
    return minimum_curvature_fields(
        east_m, north_m, {"": value}, cell_m, mask_distance_m, smoothness, margin_cells, crs
    )[""]


def minimum_curvature_fields(
    east_m: np.ndarray,
    north_m: np.ndarray,
    values: dict[str, np.ndarray],
    cell_m: float,
    mask_distance_m: float | None = None,
    smoothness: float = 1e-3,
    margin_cells: int = 2,
    crs: str = "",
) -> dict[str, Grid]:
    """:func:`minimum_curvature` of several fields sampled at the same positions (name ->
    nT per sample; same parameters otherwise): the system depends on the positions alone, so
    fields with the same finite samples share one factorisation (one sparse solve with a
    column per field)."""
    e, n = np.asarray(east_m, float), np.asarray(north_m, float)
    groups: dict[bytes, tuple[np.ndarray, list[str]]] = {}
    for name, v in values.items():
        ok = np.isfinite(e) & np.isfinite(n) & np.isfinite(np.asarray(v, float))
        groups.setdefault(np.packbits(ok).tobytes(), (ok, []))[1].append(name)
    out: dict[str, Grid] = {}
    for ok, names in groups.values():
        vs = np.column_stack([np.asarray(values[k], float)[ok] for k in names])
        grids = _minimum_curvature(
            e[ok], n[ok], vs, cell_m, mask_distance_m, smoothness, margin_cells, crs
        )
        out.update(zip(names, grids, strict=True))
    return {k: out[k] for k in values}


def _minimum_curvature(
    e: np.ndarray,
    n: np.ndarray,
    vs: np.ndarray,
    cell_m: float,
    mask_distance_m: float | None,
    smoothness: float,
    margin_cells: int,
    crs: str,
) -> list[Grid]:
    """:func:`minimum_curvature_fields` of finite samples, ``vs`` a column per field."""
    # a cell far below the extent (a mis-measured line spacing, a stray far-away line)
    # would ask for terabytes: coarsen to at most MAX_CELLS (the grid reports its cell)
    span_cells = ((np.ptp(e) + cell_m) / cell_m) * ((np.ptp(n) + cell_m) / cell_m)
    if span_cells > MAX_CELLS:
        cell_m = float(cell_m * np.sqrt(span_cells / MAX_CELLS) * 1.01)
    east0 = np.floor(e.min() / cell_m) * cell_m - margin_cells * cell_m
    north0 = np.floor(n.min() / cell_m) * cell_m - margin_cells * cell_m
    nx = int(np.ceil((e.max() - east0) / cell_m)) + margin_cells + 1
    ny = int(np.ceil((n.max() - north0) / cell_m)) + margin_cells + 1
    # block means (one constraint per occupied cell, at the mean sample position)
    cx = np.clip(np.rint((e - east0) / cell_m).astype(int), 0, nx - 1)
    cy = np.clip(np.rint((n - north0) / cell_m).astype(int), 0, ny - 1)
    key = cy * nx + cx
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    be = np.bincount(inv, e) / counts
    bn = np.bincount(inv, n) / counts
    bv = np.column_stack([np.bincount(inv, v) / counts for v in vs.T])
    fx = np.clip((be - east0) / cell_m, 0, nx - 1 - 1e-9)
    fy = np.clip((bn - north0) / cell_m, 0, ny - 1 - 1e-9)
    if nx * ny <= TILE_CELLS:
        z = _solve(fx, fy, bv, nx, ny, smoothness)
    else:
        z = _solve_tiled(fx, fy, bv, nx, ny, smoothness)
    dist = mask_distance_m if mask_distance_m is not None else 2 * cell_m
    gx, gy = np.meshgrid(east0 + cell_m * np.arange(nx), north0 + cell_m * np.arange(ny))
    d, _ = cKDTree(np.column_stack([be, bn])).query(np.column_stack([gx.ravel(), gy.ravel()]))
    far = (d > dist).reshape(ny, nx)
    grids = []
    for k in range(z.shape[1]):
        grid = z[:, k].reshape(ny, nx)
        grid[far] = np.nan
        grids.append(Grid(grid, float(east0), float(north0), float(cell_m), crs))
    return grids
