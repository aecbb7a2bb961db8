"""The anomaly map as a navigation measurement model: a smooth interpolant with its gradient.

A cubic B-spline through the grid nodes gives the map value and its horizontal gradient (the
EKF's Jacobian, nT/m) anywhere inside it; masked cells are filled for the fit only and stay
invalid for the filters. Upward continuation to the flight's altitude
uses harmonica's FFT operator on an xarray grid.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import distance_transform_edt

from pipeline.maps.grid import Grid


def _fill_nearest(values: np.ndarray) -> np.ndarray:
    """Masked (NaN) cells take their nearest valid cell's value (for FFTs and spline fits)."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return values
    _, (iy, ix) = distance_transform_edt(bad, return_indices=True)
    return values[iy, ix]


def _fft_operator(
    values: np.ndarray, cell_east_m: float, cell_north_m: float, pad: bool, apply
) -> np.ndarray:
    """``apply`` (a harmonica FFT filter of an xarray grid) to ``values`` (rows north,
    columns east): masked cells filled with their nearest neighbour, and with ``pad`` the grid
    reflected by half its size on every side first (the FFT takes the grid as periodic), then
    cropped and re-masked."""
    import warnings

    import xarray as xr

    vals = _fill_nearest(np.asarray(values, float))
    ny, nx = vals.shape
    py, px = (ny // 2, nx // 2) if pad else (0, 0)
    padded = np.pad(vals, ((py, py), (px, px)), mode="reflect")
    ee = cell_east_m * np.arange(-px, nx + px)
    nn = cell_north_m * np.arange(-py, ny + py)
    da = xr.DataArray(padded, coords={"northing": nn, "easting": ee}, dims=("northing", "easting"))
    with warnings.catch_warnings():  # xarray/xrft deprecations inside harmonica
        warnings.simplefilter("ignore", FutureWarning)
        out = np.asarray(apply(da).values)[py : py + ny, px : px + nx].copy()
    out[~np.isfinite(values)] = np.nan
    return out


def upward_continue_values(
    values: np.ndarray, cell_east_m: float, cell_north_m: float, height_m: float, pad=True
) -> np.ndarray:
    """``values`` (rows north, columns east; cells ``cell_east_m`` by ``cell_north_m``)
    continued upward by ``height_m`` (> 0) with harmonica: ``exp(-|k| dz)`` in the wavenumber
    domain. ``pad=False`` is MagNav's ``upward_fft(map, dx, dy, dz; expand=false)``, the grid
    taken as periodic as it is; the default reflects it by half its size on every side first,
    which keeps one edge's field from wrapping onto the other."""
    import harmonica as hm

    if height_m <= 0:
        raise ValueError("upward continuation needs a positive height")
    return _fft_operator(
        values,
        cell_east_m,
        cell_north_m,
        pad,
        lambda da: hm.upward_continuation(da, height_displacement=float(height_m)),
    )


def upward_continue(grid: Grid, height_m: float) -> Grid:
    """The grid continued upward by ``height_m`` (> 0), reflection-padded
    (:func:`upward_continue_values`)."""
    c = grid.cell_m
    return grid.with_values(upward_continue_values(grid.values, c, c, height_m))


def vertical_derivative(grid: Grid) -> Grid:
    """d/d up of the grid's field, nT/m (``-|k|`` in the wavenumber domain, harmonica's
    ``derivative_upward``), reflection-padded as :func:`upward_continue`."""
    import harmonica as hm

    c = grid.cell_m
    return grid.with_values(_fft_operator(grid.values, c, c, True, hm.derivative_upward))


def _weights(t: float | np.ndarray) -> tuple:
    """Uniform cubic B-spline weights of the four nodes around ``t`` in [0, 1) and of their
    derivatives (per cell)."""
    u = 1.0 - t
    t2, t3 = t * t, t * t * t
    w = (
        u * u * u / 6.0,
        (3 * t3 - 6 * t2 + 4) / 6.0,
        (-3 * t3 + 3 * t2 + 3 * t + 1) / 6.0,
        t3 / 6.0,
    )
    d = (-u * u / 2.0, (3 * t2 - 4 * t) / 2.0, (-3 * t2 + 2 * t + 1) / 2.0, t2 / 2.0)
    return w, d


@dataclass
class MapModel:
    """Map value and gradient at local east/north metres (the grid's frame).

    The interpolant is the cubic B-spline through the grid nodes (coefficients from
    ``scipy.ndimage.spline_filter``, mirror boundary: ``map_coordinates(order=3,
    mode="mirror")`` gives the same values). Its evaluation is written out here (16 weighted
    coefficients, and their derivative weights for the gradient) because the filters call it
    once per epoch and per particle: scipy's per-call overhead (~70 us for a spline ``ev``,
    three calls for value and gradient) made a one-hour EKF take 20 s.

    Parameters
    ----------
    grid : Grid
        The anomaly map, nT, in a local metric frame (east, north).
    sigma_nT : float
        One-sigma uncertainty of the map value (added to the measurement noise).
    altitude_m : float or None
        Height of the map above the ellipsoid (None: unknown).
    method : {"cubic", "linear"}
        The interpolant: the cubic B-spline (default: a continuous gradient, which the EKF's
        linearisation wants) or bilinear (MagNav's ``map_interpolate(..., :linear)``, whose
        gradient jumps at cell edges; used to reproduce MagNav's test numbers).
    """

    grid: Grid
    sigma_nT: float = 0.0
    altitude_m: float | None = None
    method: str = "cubic"
    _coef: np.ndarray = field(init=False, repr=False)
    _valid: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from scipy.ndimage import spline_filter

        if self.method not in ("cubic", "linear"):
            raise ValueError(f"map interpolation {self.method!r}: use cubic or linear")

        vals = _fill_nearest(self.grid.values.astype(float))
        # one node of mirror padding on each side (and one more for the upper neighbour)
        self._coef = np.pad(spline_filter(vals, order=3, mode="mirror"), 2, mode="reflect")
        ok = np.isfinite(self.grid.values)
        # a point is on the map when the four cells around it are unmasked
        self._valid = np.pad(ok, ((0, 1), (0, 1)), constant_values=False)
        self._nodes = vals
        self._ny, self._nx = vals.shape

    def _frac(self, east_m, north_m):
        fx = (np.asarray(east_m, float) - self.grid.east0_m) / self.grid.cell_m
        fy = (np.asarray(north_m, float) - self.grid.north0_m) / self.grid.cell_m
        return fx, fy

    def inside(self, east_m, north_m) -> np.ndarray:
        """True where the point is within the grid and the cells around it are unmasked."""
        fx, fy = self._frac(east_m, north_m)
        box = (fx >= 0) & (fy >= 0) & (fx <= self._nx - 1) & (fy <= self._ny - 1)
        out = np.zeros(np.shape(fx), bool)
        if box.any():
            i = np.floor(fx[box]).astype(int)
            j = np.floor(fy[box]).astype(int)
            v = self._valid
            out[box] = v[j, i] & v[j, np.minimum(i + 1, self._nx - 1)]
            out[box] &= v[np.minimum(j + 1, self._ny - 1), i]
            out[box] &= v[np.minimum(j + 1, self._ny - 1), np.minimum(i + 1, self._nx - 1)]
        return out

    def value(self, east_m, north_m) -> np.ndarray:
        """Map value, nT (NaN outside the valid map); any array shape."""
        return self.value_and_gradient(east_m, north_m)[0]

    def gradient(self, east_m, north_m) -> tuple[np.ndarray, np.ndarray]:
        """Horizontal gradient (d/d east, d/d north), nT/m; any array shape."""
        return self.value_and_gradient(east_m, north_m)[1:]

    def value_and_gradient(self, east_m, north_m):
        """Value (NaN off the map) and gradient (d/d east, d/d north, nT/m) at many points."""
        shape = np.shape(east_m)
        e = np.ravel(np.asarray(east_m, float))
        n = np.ravel(np.asarray(north_m, float))
        fx, fy = self._frac(e, n)
        v, gx, gy = self._evaluate_many(fx, fy)
        v = np.where(self.inside(e, n), v, np.nan)
        c = self.grid.cell_m
        return v.reshape(shape), (gx / c).reshape(shape), (gy / c).reshape(shape)

    def _bilinear(self, fx, fy, i, j):
        """Bilinear value and its derivatives per cell (d/dfx, d/dfy) from the nodes."""
        v = self._nodes
        tx, ty = fx - i, fy - j
        v00, v10 = v[j, i], v[j, i + 1]
        v01, v11 = v[j + 1, i], v[j + 1, i + 1]
        lo, hi = v00 + tx * (v10 - v00), v01 + tx * (v11 - v01)
        dx = (1 - ty) * (v10 - v00) + ty * (v11 - v01)
        return lo + ty * (hi - lo), dx, hi - lo

    def _evaluate_many(self, fx: np.ndarray, fy: np.ndarray):
        fx = np.clip(fx, 0.0, self._nx - 1.0)
        fy = np.clip(fy, 0.0, self._ny - 1.0)
        i = np.minimum(np.floor(fx).astype(int), self._nx - 2)
        j = np.minimum(np.floor(fy).astype(int), self._ny - 2)
        if self.method == "linear":
            return self._bilinear(fx, fy, i, j)
        wx, dx = _weights(fx - i)
        wy, dy = _weights(fy - j)
        # 4 x 4 coefficient blocks around each point: (M, 4, 4)
        rows = (j + 1)[:, None] + np.arange(4)
        cols = (i + 1)[:, None] + np.arange(4)
        blk = self._coef[rows[:, :, None], cols[:, None, :]]
        wx, dx, wy, dy = (np.stack(w, axis=1) for w in (wx, dx, wy, dy))
        bx = (blk @ wx[:, :, None])[:, :, 0]
        bdx = (blk @ dx[:, :, None])[:, :, 0]
        return (wy * bx).sum(axis=1), (wy * bdx).sum(axis=1), (dy * bx).sum(axis=1)

    def at(self, east_m: float, north_m: float) -> tuple[float, float, float]:
        """Value and gradient (d/d east, d/d north, nT/m) at one point; NaN value off the
        valid map. Scalar arithmetic: the sequential filters' per-epoch call."""
        fx = (east_m - self.grid.east0_m) / self.grid.cell_m
        fy = (north_m - self.grid.north0_m) / self.grid.cell_m
        if not (0.0 <= fx <= self._nx - 1 and 0.0 <= fy <= self._ny - 1):
            return np.nan, 0.0, 0.0
        i = min(int(fx), self._nx - 2)
        j = min(int(fy), self._ny - 2)
        v = self._valid
        if not (v[j, i] and v[j, i + 1] and v[j + 1, i] and v[j + 1, i + 1]):
            return np.nan, 0.0, 0.0
        cell = self.grid.cell_m
        if self.method == "linear":
            val, ddx, ddy = self._bilinear(fx, fy, i, j)
            return float(val), float(ddx) / cell, float(ddy) / cell
        wx, dx = _weights(fx - i)
        wy, dy = _weights(fy - j)
        blk = self._coef[j + 1 : j + 5, i + 1 : i + 5]
        wx, dx, wy, dy = (np.array(w) for w in (wx, dx, wy, dy))
        bx = blk @ wx
        return float(wy @ bx), float(wy @ (blk @ dx)) / cell, float(dy @ bx) / cell

    def coverage(self, east_m, north_m) -> float:
        """Fraction of the points inside the valid map."""
        e = np.asarray(east_m, float)
        return float(self.inside(e, north_m).mean()) if e.size else 0.0

    def continued_to(self, altitude_m: float, tolerance_m: float = 1.0) -> tuple[MapModel, str]:
        """The map at ``altitude_m`` (upward continuation when the flight is higher), and a
        note of what was done. Downward continuation amplifies noise without bound and is not
        done: the map is then used as is, and the note says so."""
        if self.altitude_m is None:
            return self, "map altitude unknown: used as is (no continuation)"
        dh = float(altitude_m) - self.altitude_m
        if abs(dh) <= tolerance_m:
            return self, f"map altitude {self.altitude_m:.1f} m: flight within {tolerance_m} m"
        if dh < 0:
            return self, (
                f"flight {-dh:.1f} m below the map: no downward continuation (unstable); "
                "map used as is"
            )
        up = upward_continue(self.grid, dh)
        return (
            MapModel(up, self.sigma_nT, float(altitude_m), self.method),
            f"map continued upward by {dh:.1f} m (harmonica) to {altitude_m:.1f} m",
        )


def wiener_smooth(grid: Grid, noise_nT: float) -> tuple[Grid, float]:
    """The map with white noise of ``noise_nT`` (1 sigma per cell) filtered out: the Wiener
    gain ``max(0, 1 - N / P(k))`` per wavenumber, ``P(k)`` the map's own radially averaged
    power and ``N`` the noise's (flat) power, on the reflection-padded grid (masked cells
    filled for the FFT and re-masked).

    A filter linearises on the map's gradient: noise of a few nT per cell is a gradient of
    several hundredths of nT/m, as large as a quiet field's, and read as gradient it steers the
    position by chance while the filter's covariance shrinks (tried: 3 nT per cell on a
    20 nT field, map-aided worse than the INS alone, NEES 5-15). Taking all of the map's error
    as white is the cautious choice: a smooth error has its power at long wavelengths, where
    a map's own power is orders of magnitude above ``N`` and the gain is 1.

    Returns the smoothed grid, the RMS removed (nT) and the fraction of the map's error
    variance that is left (:func:`remaining_error_fraction`).
    """
    vals = np.asarray(grid.values, float)
    ok = np.isfinite(vals)
    if noise_nT <= 0 or ok.sum() < 16:
        return grid, 0.0, 1.0
    filled = _fill_nearest(vals)
    ny, nx = filled.shape
    padded = np.pad(filled - filled[ok].mean(), ((ny // 2,) * 2, (nx // 2,) * 2), mode="reflect")
    f = np.fft.fft2(padded)
    power = np.abs(f) ** 2 / padded.size  # white noise of variance s^2: s^2 per coefficient
    ky = np.fft.fftfreq(padded.shape[0])
    kx = np.fft.fftfreq(padded.shape[1])
    k = np.hypot(*np.meshgrid(kx, ky))
    edges = np.linspace(0.0, k.max() + 1e-12, 65)
    ring = np.clip(np.digitize(k, edges) - 1, 0, 63)
    mean_power = np.bincount(ring.ravel(), power.ravel(), 64) / np.maximum(
        np.bincount(ring.ravel(), None, 64), 1
    )
    gain = np.clip(1.0 - noise_nT**2 / np.maximum(mean_power[ring], 1e-300), 0.0, 1.0)
    out = np.real(np.fft.ifft2(f * gain))[ny // 2 : ny // 2 + ny, nx // 2 : nx // 2 + nx]
    out = out + filled[ok].mean()
    out[~ok] = np.nan
    removed = float(np.sqrt(np.mean((out[ok] - vals[ok]) ** 2)))
    left = remaining_error_fraction(noise_nT, removed, float(np.mean(gain)))
    return grid.with_values(out), removed, left


def remaining_error_fraction(noise_nT: float, removed_nT: float, mean_gain: float) -> float:
    """The share of a map error of ``noise_nT`` (1 sigma) left after a Wiener filter took
    ``removed_nT`` RMS out of the map: what it took was the error's (the filter only removes
    where the map's power is near the noise's), so ``1 - removed^2 / noise^2``; never below
    ``mean_gain``, the share of white noise any Wiener filter lets through."""
    if noise_nT <= 0:
        return 1.0
    return float(np.clip(1.0 - (removed_nT / noise_nT) ** 2, mean_gain, 1.0))
