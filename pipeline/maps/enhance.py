"""Map enhancements by FFT (harmonica): reduction to the pole, vertical and horizontal
derivatives, tilt angle, analytic signal, upward continuation.

The grid is prepared for the Fourier transform the usual way: masked cells (NaN) are filled
from the nearest covered cell, the plane fitting the grid's border cells (level and regional
gradient) is removed, and the residual is padded on every side by half the grid's larger
dimension with a linear ramp down to zero (no step at the periodic edges); the products are
computed on the padded grid, cropped back and the masked cells masked again. The plane is
added back to the reduction to the pole and the upward continuation (a plane is harmonic: it
continues unchanged) and its slopes to the horizontal derivatives; its vertical derivative is
zero.

Products (``name``: channel, value field, units):

- ``rtp``: ``/map/rtp``, ``rtp_nT``: reduced to the pole with the main field's inclination and
  declination (IGRF at the survey centre and date), magnetisation assumed induced;
- ``dz``: ``/map/vertical_derivative``, ``vertical_derivative_nT_per_m``: first derivative
  upward (harmonica's ``derivative_upward``: negative over a positive anomaly, which decays
  upward);
- ``thd``: ``/map/horizontal_derivative``, ``horizontal_derivative_nT_per_m``: total
  horizontal derivative sqrt(dT/dx^2 + dT/dy^2) (centred finite differences);
- ``tilt``: ``/map/tilt``, ``tilt_deg``: arctan(-dT/dz / THD) with dT/dz the upward
  derivative: the tilt angle of Miller and Singh (1994), positive over a source, degrees;
- ``as``: ``/map/analytic_signal``, ``analytic_signal_nT_per_m``: amplitude of the analytic
  signal (total gradient) sqrt(dx^2 + dy^2 + dz^2);
- ``up:H``: ``/map/upward_<H>m``, ``upward_<H>m_nT``: the field continued H m upward.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.defaults import default_field
from pipeline.maps.grid import Grid

KINDS = {
    "rtp": ("/map/rtp", "rtp_nT"),
    "dz": ("/map/vertical_derivative", "vertical_derivative_nT_per_m"),
    "thd": ("/map/horizontal_derivative", "horizontal_derivative_nT_per_m"),
    "tilt": ("/map/tilt", "tilt_deg"),
    "as": ("/map/analytic_signal", "analytic_signal_nT_per_m"),
}
PAD_FRACTION = 0.5  # padding on each side, fraction of the grid's larger dimension


@dataclass(frozen=True)
class Product:
    """One enhancement: ``kind`` (rtp, dz, thd, tilt, as, up) and, for ``up``, the height."""

    kind: str
    height_m: float = 0.0

    @property
    def topic(self) -> str:
        """Output channel."""
        if self.kind == "up":
            return f"/map/upward_{_height_text(self.height_m)}m"
        return KINDS[self.kind][0]

    @property
    def field_name(self) -> str:
        """Name of the grid's value field (units in the suffix)."""
        if self.kind == "up":
            return f"upward_{_height_text(self.height_m)}m_nT"
        return KINDS[self.kind][1]


def grid_field_of_topic(topic: str) -> str | None:
    """The value field of an enhancement grid channel (``/map/tilt`` -> ``tilt_deg``,
    ``/map/upward_100m`` -> ``upward_100m_nT``); None for any other topic."""
    for t, f in KINDS.values():
        if topic == t:
            return f
    name = topic.removeprefix("/map/")
    if topic.startswith("/map/upward_") and name.endswith("m"):
        return f"{name}_nT"
    return None


def _height_text(h: float) -> str:
    """100.0 -> "100", 12.5 -> "12.5", 1e7 -> "10000000" (no exponent: topic names)."""
    return np.format_float_positional(float(h), trim="-")


def parse_products(items) -> list[Product]:
    """``["rtp", "dz", "up:100"]`` -> products (order kept, duplicates dropped).

    Raises
    ------
    ValueError
        An unknown product, or an upward continuation without a height > 0 m.
    """
    out: list[Product] = []
    for item in items:
        text = str(item).strip().lower()
        if text.startswith("up"):
            _, _, h = text.partition(":")
            try:
                height = float(h)
            except ValueError:
                height = float("nan")
            if not (np.isfinite(height) and height > 0):
                raise ValueError(f"enhancement {item!r}: use up:H with a height H > 0 (m)")
            p = Product("up", height)
        elif text in KINDS:
            p = Product(text)
        else:
            raise ValueError(
                f"unknown enhancement {item!r}: use some of rtp, dz, thd, tilt, as, up:H"
            )
        if p not in out:
            out.append(p)
    return out


@dataclass
class EnhanceSettings:
    """The ``[enhance]`` keys (defaults: the shipped configuration's)."""

    products: list[Product] = default_field("enhance", "products", lambda v: parse_products(v))
    source: str = default_field("enhance", "source")  # anomaly_filtered | anomaly
    pad_fraction: float = PAD_FRACTION


def fill_gaps(values: np.ndarray) -> np.ndarray:
    """NaN cells take the value of the nearest finite cell (Euclidean, in cells).

    Raises
    ------
    ValueError
        No finite cell.
    """
    from scipy.ndimage import distance_transform_edt

    bad = ~np.isfinite(values)
    if bad.all():
        raise ValueError("the grid has no finite cell")
    if not bad.any():
        return values.copy()
    idx = distance_transform_edt(bad, return_distances=False, return_indices=True)
    return values[tuple(idx)]


@dataclass
class _Prepared:
    """A grid ready for the FFT: the padded, tapered residual (DataArray, dims northing,
    easting; m) and the plane removed from it (grid-shaped values, east and north slopes)."""

    residual: object
    plane: np.ndarray
    slope_east: float  # nT/m
    slope_north: float  # nT/m


BORDER_FRACTION = 0.05  # the plane is fitted to this fraction of the cells along each edge


def _prepare(grid: Grid, pad: int) -> _Prepared:
    """Fill the gaps, remove the plane that fits the grid's border (a regional gradient would
    otherwise step at the periodic edges; an isolated anomaly, near zero at the border, keeps
    its shape), pad with a linear ramp of the residual down to zero."""
    import xarray as xr

    v = fill_gaps(grid.values)
    ny, nx = grid.shape
    east, north = grid.coordinates()
    ee, nn = np.meshgrid(east - east.mean(), north - north.mean())
    w = max(2, int(BORDER_FRACTION * min(ny, nx)))
    ring = np.zeros((ny, nx), bool)
    ring[:w], ring[-w:], ring[:, :w], ring[:, -w:] = True, True, True, True
    design = np.column_stack([np.ones(ring.sum()), ee[ring], nn[ring]])
    (c, a, b), *_ = np.linalg.lstsq(design, v[ring], rcond=None)
    plane = c + a * ee + b * nn
    r = np.pad(v - plane, pad, mode="linear_ramp", end_values=0.0)
    e_pad = grid.east0_m + grid.cell_m * (np.arange(nx + 2 * pad) - pad)
    n_pad = grid.north0_m + grid.cell_m * (np.arange(ny + 2 * pad) - pad)
    da = xr.DataArray(r, coords={"northing": n_pad, "easting": e_pad}, dims=("northing", "easting"))
    return _Prepared(da, plane, float(a), float(b))


# the reduction to the pole multiplies a map's errors by up to 1 / sin^2(I) (wavenumbers across
# the declination): beyond ten times (|I| under 18.4 deg) the map's errors, not its geology,
# fill the product
MAX_RTP_GAIN = 10.0


def rtp_refusal(inclination_deg: float) -> str | None:
    """Why the reduction to the pole is not computed at ``inclination_deg`` (degrees), or
    None: its largest gain 1 / sin^2(I) above :data:`MAX_RTP_GAIN`."""
    s2 = float(np.sin(np.radians(inclination_deg)) ** 2)
    if s2 * MAX_RTP_GAIN >= 1.0:
        return None
    least = float(np.degrees(np.arcsin(np.sqrt(1.0 / MAX_RTP_GAIN))))
    gain = f"{1.0 / s2:.3g}x" if s2 > 0 else "without bound"
    return (
        f"reduction to the pole skipped: at inclination {inclination_deg:.1f} deg it multiplies "
        f"the map's errors up to {gain} (at most {MAX_RTP_GAIN:.0f}x: |inclination| >= "
        f"{least:.1f} deg)"
    )


def refused(products: list[Product], inclination_deg: float) -> list[str]:
    """Why each of ``products`` that is not computed at ``inclination_deg`` is left out (the
    reduction to the pole, :func:`rtp_refusal`); empty when every one is made."""
    why = rtp_refusal(inclination_deg)
    return [why] if why and any(p.kind == "rtp" for p in products) else []


def enhance(
    grid: Grid,
    products: list[Product],
    inclination_deg: float,
    declination_deg: float,
    pad_fraction: float = PAD_FRACTION,
) -> dict[str, Grid]:
    """Compute ``products`` of a total-field anomaly grid (nT, cells in metres).

    Parameters
    ----------
    grid
        The anomaly; NaN cells are filled for the transform and masked in every product.
    products
        From :func:`parse_products`.
    inclination_deg, declination_deg
        Main-field direction at the survey (IGRF), degrees (inclination positive down,
        declination east of north); used by ``rtp``.
    pad_fraction
        Padding on each side as a fraction of the larger grid dimension.

    Returns
    -------
    dict
        Channel topic -> the product on the same grid geometry; without ``/map/rtp`` where
        :func:`rtp_refusal` refuses it.
    """
    import warnings

    import harmonica as hm

    with warnings.catch_warnings():  # xarray/xrft deprecations inside harmonica
        warnings.simplefilter("ignore", FutureWarning)
        return _enhance(hm, grid, products, inclination_deg, declination_deg, pad_fraction)


def _enhance(hm, grid, products, inclination_deg, declination_deg, pad_fraction):
    pad = max(int(np.ceil(pad_fraction * max(grid.shape))), 2)
    prep = _prepare(grid, pad)
    da = prep.residual
    ny, nx = grid.shape
    mask = ~np.isfinite(grid.values)

    def crop(a) -> np.ndarray:
        return np.asarray(a, float)[pad : pad + ny, pad : pad + nx]

    cache: dict[str, np.ndarray] = {}

    def deriv(which: str) -> np.ndarray:
        """nT/m on the grid cells; the plane's slopes added back to the horizontal ones (a
        plane is harmonic: its vertical derivative is zero)."""
        if which not in cache:
            if which == "z":
                cache[which] = crop(hm.derivative_upward(da))
            elif which == "x":
                cache[which] = crop(hm.derivative_easting(da)) + prep.slope_east
            else:
                cache[which] = crop(hm.derivative_northing(da)) + prep.slope_north
        return cache[which]

    out: dict[str, Grid] = {}
    for p in products:
        if p.kind == "rtp" and rtp_refusal(inclination_deg):
            continue
        if p.kind == "rtp":  # the plane (k ~ 0, where the operator is undefined) kept as is
            v = crop(hm.reduction_to_pole(da, inclination_deg, declination_deg)) + prep.plane
        elif p.kind == "dz":
            v = deriv("z")
        elif p.kind == "thd":
            v = np.hypot(deriv("x"), deriv("y"))
        elif p.kind == "tilt":
            v = np.degrees(np.arctan2(-deriv("z"), np.hypot(deriv("x"), deriv("y"))))
        elif p.kind == "as":
            v = np.sqrt(deriv("x") ** 2 + deriv("y") ** 2 + deriv("z") ** 2)
        else:  # upward continuation: a plane is harmonic and continues unchanged
            v = crop(hm.upward_continuation(da, p.height_m)) + prep.plane
        v = np.array(v, float)
        v[mask] = np.nan
        out[p.topic] = grid.with_values(v)
    return out
