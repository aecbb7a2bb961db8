"""Micro-levelling (decorrugation) of a gridded survey: Urquhart (1988), Minty (1991).

Tie-line levelling leaves each line with the errors that its few crossings cannot see: drift
between ties, heading error that changes along the line, small offsets. On the grid they are
corrugations: stripes parallel to the lines, one line spacing wide. Micro-levelling estimates
them from the grid itself:

1. decorrugation filter on the grid (2-D Fourier domain, wavenumbers rotated into the line
   frame): a Butterworth high-pass across the lines, cutting off at ``wavelength_m``
   (default 4 line spacings), times a directional cosine filter |k_across / k|^n, which keeps
   only wavenumbers pointing across the lines, i.e. features elongated along them. The result
   is the corrugation grid: line-level errors plus any geology that is long along the lines
   and narrow across them;
2. the corrugation grid is sampled along each survey line and low-passed along the line
   (Gaussian, half power at ``along_m``, default 10 line spacings): level errors vary slowly
   along a line, geology does not;
3. the correction is clipped to +-``clip_nT`` (larger values are geology, not level error),
   subtracted from the line, and the lines are re-gridded by the caller.

Geology elongated along the lines and narrower than ``wavelength_m`` across them is
indistinguishable from corrugation and is partly removed (up to the clip): see
docs/science.md for the measured loss.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import distance_transform_edt, gaussian_filter1d

from pipeline.maps.grid import Grid

# Butterworth order of the across-line high-pass and power of the directional cosine filter
HIGHPASS_ORDER = 4
COSINE_POWER = 2
# defaults in line spacings when the configured length is 0
WAVELENGTH_SPACINGS = 4.0
ALONG_SPACINGS = 10.0
# half-power wavelength of a Gaussian: sigma = GAUSS_HALF_POWER x wavelength
GAUSS_HALF_POWER = float(np.sqrt(np.log(2.0) / 2.0) / np.pi)


@dataclass
class MicroLevel:
    """Per-line corrections (nT at each line sample, subtracted) and their figures."""

    corrections: dict[str, np.ndarray]
    wavelength_m: float
    along_m: float
    clip_nT: float
    clipped_fraction: float
    grid_change_rms_nT: float = float("nan")  # re-gridded minus original, over finite cells
    notes: list[str] = field(default_factory=list)

    @property
    def rms_nT(self) -> float:
        """RMS of the correction over every corrected line sample (the corrugation removed)."""
        c = np.concatenate(list(self.corrections.values())) if self.corrections else np.zeros(0)
        return float(np.sqrt(np.mean(c**2))) if c.size else 0.0

    def summary(self) -> dict[str, Any]:
        """The ``microlevel`` block of the map summary."""
        c = np.concatenate(list(self.corrections.values())) if self.corrections else np.zeros(0)
        per_line = {k: float(np.sqrt(np.mean(v**2))) for k, v in self.corrections.items()}
        return {
            "correction_rms_nT": self.rms_nT,
            "correction_max_abs_nT": float(np.abs(c).max()) if c.size else 0.0,
            "clipped_fraction": self.clipped_fraction,
            "grid_change_rms_nT": self.grid_change_rms_nT,
            "wavelength_m": self.wavelength_m,
            "along_m": self.along_m,
            "clip_nT": self.clip_nT,
            "lines": len(self.corrections),
            "line_rms_nT": per_line,
        }


def _filled(values: np.ndarray) -> np.ndarray:
    """Masked (NaN) cells take their nearest finite cell's value."""
    bad = ~np.isfinite(values)
    if not bad.any():
        return values
    _, (iy, ix) = distance_transform_edt(bad, return_indices=True)
    return values[iy, ix]


def decorrugation_filter(
    grid: Grid, heading_deg: float, wavelength_m: float, pad_cells: int | None = None
) -> np.ndarray:
    """The corrugation grid: across-line Butterworth high-pass x directional cosine filter.

    Parameters
    ----------
    grid : Grid
        The levelled anomaly grid (nT); masked cells are filled from their nearest neighbour
        for the transform (and are NaN again in the result).
    heading_deg : float
        Direction of the survey lines, degrees clockwise from north (modulo 180).
    wavelength_m : float
        Cut-off wavelength of the high-pass across the lines (m).
    pad_cells : int, optional
        Mirror padding on every side (default: the cut-off wavelength in cells, at least 8).

    Returns
    -------
    ndarray
        Grid-shaped corrugation estimate (nT).
    """
    v = _filled(grid.values)
    pad = pad_cells if pad_cells is not None else max(8, int(np.ceil(wavelength_m / grid.cell_m)))
    p = np.pad(v, pad, mode="symmetric")
    ny, nx = p.shape
    kx = np.fft.fftfreq(nx, grid.cell_m)[None, :]  # cycles per metre, east
    ky = np.fft.fftfreq(ny, grid.cell_m)[:, None]  # north
    h = np.radians(heading_deg)
    k_across = kx * np.cos(h) - ky * np.sin(h)  # across = (cos h, -sin h) in (east, north)
    k = np.hypot(kx, ky)
    r = (np.abs(k_across) * wavelength_m) ** (2 * HIGHPASS_ORDER)
    highpass = r / (1.0 + r)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.where(k > 0, np.abs(k_across) / k, 0.0) ** COSINE_POWER
    out = np.fft.ifft2(np.fft.fft2(p - p.mean()) * highpass * cosine).real
    out = out[pad : pad + v.shape[0], pad : pad + v.shape[1]]
    return np.where(np.isfinite(grid.values), out, np.nan)


def along_line_lowpass(distance_m: np.ndarray, values: np.ndarray, along_m: float) -> np.ndarray:
    """Gaussian low-pass along one line, half power at ``along_m`` (m); samples are taken
    as evenly spaced at their median step along the track."""
    if values.size < 3:
        return values.copy()
    step = float(np.median(np.abs(np.diff(distance_m))))
    if not step > 0:
        return np.full_like(values, float(np.mean(values)))
    return gaussian_filter1d(values, GAUSS_HALF_POWER * along_m / step, mode="nearest")


def microlevel_lines(
    lines: list,
    grid: Grid,
    heading_deg: float,
    spacing_m: float,
    wavelength_m: float | None = None,
    along_m: float | None = None,
    clip_nT: float = 5.0,
) -> MicroLevel:
    """Micro-levelling corrections of the survey lines from their grid.

    Parameters
    ----------
    lines : list of Line
        Levelled lines (``pipeline.maps.level.Line``); only ``kind == "survey"`` ones are
        corrected (ties keep their level).
    grid : Grid
        The grid made from ``lines`` (nT).
    heading_deg : float
        Survey-line direction, degrees clockwise from north.
    spacing_m : float
        Line spacing (m): the default lengths are multiples of it.
    wavelength_m : float, optional
        High-pass cut-off across the lines (m); None or 0: WAVELENGTH_SPACINGS x spacing.
    along_m : float, optional
        Low-pass half-power wavelength along the lines (m); None or 0: ALONG_SPACINGS x spacing.
    clip_nT : float
        Largest correction applied (nT).

    Returns
    -------
    MicroLevel
        Subtract ``corrections[line_id]`` from each line's ``value_nT`` and re-grid.
    """
    lam = wavelength_m or WAVELENGTH_SPACINGS * spacing_m
    al = along_m or ALONG_SPACINGS * spacing_m
    corr_grid = grid.with_values(decorrugation_filter(grid, heading_deg, lam))
    out: dict[str, np.ndarray] = {}
    clipped = total = 0
    for ln in lines:
        if ln.kind != "survey":
            continue
        c = corr_grid.interpolate(ln.east_m, ln.north_m)
        c = np.where(np.isfinite(c), c, 0.0)
        c = along_line_lowpass(ln.along_m, c, al)
        clipped += int(np.sum(np.abs(c) > clip_nT))
        total += c.size
        out[ln.line_id] = np.clip(c, -clip_nT, clip_nT)
    return MicroLevel(out, float(lam), float(al), float(clip_nT), clipped / total if total else 0.0)
