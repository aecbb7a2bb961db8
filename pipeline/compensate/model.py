"""Tolles-Lawson and AGG-TL compensation of a scalar magnetometer.

Fit (paper 002): band-pass the regressors and the measured field (zero-phase Butterworth) over
each contiguous calibration block, trim the filter's edge samples, and solve a ridge
regression with a fixed lambda or the L-curve corner. Apply: interference = K theta with the
*unfiltered* T-L columns over the whole flight; compensated = measured - interference. AGG-TL
adds band-passed position columns to the fit only: they absorb the geomagnetic gradient that
manoeuvres leak into the calibration band, and are not subtracted (they are geology).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.compensate.estimator import bandpassed_design, fit_ridge
from pipeline.compensate.filters import (
    bandpass_blocks,
    bandpass_sos,
    contiguous_blocks,
    trim_samples,
)
from pipeline.compensate.guards import scaled_condition
from pipeline.compensate.ridge import LCurve
from pipeline.compensate.terms import BT_SCALE_NT, position_terms, tl16_terms, tl18_terms
from pipeline.defaults import default_field, default_value, ridge_problem
from pipeline.flight import Flight
from pipeline.geo.local import LocalFrame

MODELS = ("tl16", "tl18", "agg-tl", "tl-plus", "tl-nn")
# models that extend tl18 (pipeline.compensate.plus, pipeline.compensate.learned)
EXTENSIONS = ("tl-plus", "tl-nn")


@dataclass
class Measurements:
    """What compensation needs, on one time base.

    ``vector_nT`` is body-frame (x forward, y right, z down); positions are optional (AGG-TL):
    latitude/longitude in degrees, altitude above the ellipsoid in metres. ``attitude_deg``
    (roll, pitch, yaw; NED, yaw from true north) and ``aux`` (recorded auxiliary channels by
    name, in their own units, given by ``aux_units``) feed the extensions (tl-plus, tl-nn).
    """

    time_s: np.ndarray
    scalar_nT: np.ndarray
    vector_nT: np.ndarray
    lat_deg: np.ndarray | None = None
    lon_deg: np.ndarray | None = None
    alt_m: np.ndarray | None = None
    attitude_deg: np.ndarray | None = None
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    aux_units: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_flight(cls, flight: Flight) -> Measurements:
        """The compensation inputs of a flight.

        Time (s), scalar field (nT) and body-frame vector field (x forward, y right, z down; nT);
        latitude/longitude (deg) and ellipsoidal altitude (m) when the flight has all three.

        Raises
        ------
        AeromagError
            The flight has no vector channel.
        """
        flight.require("vector_x_nT", "vector_y_nT", "vector_z_nT", purpose="compensation")
        d = flight.data
        pos = flight.has("lat_deg", "lon_deg", "alt_m")
        att = ["roll_deg", "pitch_deg", "yaw_deg"]
        return cls(
            d["time_s"].to_numpy(float),
            d["scalar_nT"].to_numpy(float),
            d[["vector_x_nT", "vector_y_nT", "vector_z_nT"]].to_numpy(float),
            d["lat_deg"].to_numpy(float) if pos else None,
            d["lon_deg"].to_numpy(float) if pos else None,
            d["alt_m"].to_numpy(float) if pos else None,
            d[att].to_numpy(float) if flight.has(*att) else None,
            {c[4:]: d[c].to_numpy(float) for c in d.columns if c.startswith("aux_")},
            {c[4:]: flight.units.get(c, "") for c in d.columns if c.startswith("aux_")},
        )

    def take(self, idx: np.ndarray) -> Measurements:
        """The same inputs on the epochs ``idx`` (indices or a mask)."""

        def sub(a):
            return None if a is None else a[idx]

        return Measurements(
            self.time_s[idx],
            self.scalar_nT[idx],
            self.vector_nT[idx],
            sub(self.lat_deg),
            sub(self.lon_deg),
            sub(self.alt_m),
            sub(self.attitude_deg),
            {k: v[idx] for k, v in self.aux.items()},
            dict(self.aux_units),
        )

    @property
    def has_position(self) -> bool:
        """Whether positions are present (AGG-TL needs them)."""
        return self.lat_deg is not None

    @property
    def rate_hz(self) -> float:
        """Sample rate, Hz (from the median sample interval)."""
        return 1.0 / float(np.median(np.diff(self.time_s)))


@dataclass
class FitSettings:
    """How to fit: term set, band (None: no filtering), filter order, trim, ridge, and tl18's
    column scale (nT)."""

    # every default but the model is the shipped configuration's [compensation] value
    model: str = "tl16"
    band_hz: tuple[float, float] | None = default_field("compensation", "band_hz", tuple)
    # AGG-TL's T-L term set. tl18 by default: its induced terms scale with |B|, which the
    # regional gradient changes between the calibration site and the survey (hundreds of nT);
    # tl16 (paper 002's choice) cannot follow that and leaves a heading error.
    base: str = default_field("compensation", "agg_base")
    # AGG-TL's horizontal gradient: "fit" from the position columns, "legs" fixed at the
    # calibration legs' estimate (pipeline.compensate.agg_legs), "auto" the legs' unless
    # held-out calibration data prefer the fit's (pipeline.compensate.agg_choice)
    agg_gradient: str = default_field("compensation", "agg_gradient")
    poles: int = default_field("compensation", "poles")
    # the band-pass's edge transient dropped at each block end (s)
    trim_s: float = default_field("compensation", "trim_s")
    # a lambda, or "auto" for the L-curve corner
    ridge: float | str = default_field("compensation", "ridge")
    # tl18's induced and eddy columns are divided by it (MagNav's Bt_scale): with a fixed
    # lambda it sets how hard those coefficients are shrunk
    bt_scale_nT: float = default_field("compensation", "bt_scale_nT")

    # tl-plus / tl-nn: the held-out test an extension must pass against tl18 (one-sided p
    # below extension_alpha, held-out RMS reduction at least extension_min_gain)
    extension_alpha: float = default_field("compensation", "extension_alpha")
    extension_min_gain: float = default_field("compensation", "extension_min_gain")
    # the calibration legs' level check of a used extension (one-sided p of a worse level)
    level_guard_alpha: float = default_field("compensation", "level_guard_alpha")
    heading_levels_alpha: float = default_field("compensation", "heading_levels_alpha")
    # tl-nn's regressor: "hgb" (histogram gradient boosting) or "mlp"
    learner: str = default_field("compensation", "learner")
    seed: int = 0

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"unknown model {self.model!r} (use {', '.join(MODELS)})")
        if self.base not in ("tl16", "tl18"):
            raise ValueError(f"unknown AGG-TL base {self.base!r} (use tl16 or tl18)")
        if self.agg_gradient not in ("fit", "legs", "auto"):
            raise ValueError(
                f"unknown AGG-TL gradient {self.agg_gradient!r} (use fit, legs or auto)"
            )
        if self.learner not in ("hgb", "mlp"):
            raise ValueError(f"unknown learner {self.learner!r} (use hgb or mlp)")
        if not 0.0 < self.extension_alpha < 1.0:
            raise ValueError("extension_alpha: use a p-value between 0 and 1")
        if not 0.0 <= self.level_guard_alpha < 1.0:
            raise ValueError("level_guard_alpha: use a p-value in [0, 1) (0: no level guard)")
        if not 0.0 <= self.heading_levels_alpha < 1.0:
            raise ValueError("heading_levels_alpha: use a p-value in [0, 1) (0: no correction)")
        problem = ridge_problem(self.ridge)  # the rule Config loading applies
        if problem:
            raise ValueError(problem)
        if not self.bt_scale_nT > 0:
            raise ValueError(f"bt_scale_nT must be > 0 nT, not {self.bt_scale_nT!r}")


def tl_terms(
    model: str, meas: Measurements, base: str = "tl18", bt_scale_nT: float = BT_SCALE_NT
) -> tuple[np.ndarray, list[str]]:
    """The T-L columns a model compensates with (AGG-TL: those of its ``base`` term set)."""
    if model in ("tl18", *EXTENSIONS) or (model == "agg-tl" and base == "tl18"):
        return tl18_terms(meas.vector_nT, meas.time_s, bt_scale_nT)
    return tl16_terms(meas.vector_nT, meas.time_s)


@dataclass
class CompensationModel:
    """A fitted model: coefficients of ``terms`` (T-L first, then any position terms)."""

    settings: FitSettings
    terms: list[str]
    coefficients: np.ndarray
    n_tl: int  # the first n_tl coefficients compensate; the rest (positions) do not
    lambda_: float
    n_fit: int
    fit_residual_nT: float
    calibration_blocks: list[tuple[float, float]]  # (start_s, end_s) of each fitted block
    lcurve: LCurve | None = None
    reference: dict[str, float] = field(default_factory=dict)  # AGG-TL position origin
    coefficient_std: np.ndarray | None = None  # from the residual variance (no ridge)
    condition_number: float = float("nan")  # of the band-passed, column-scaled design
    weakest_terms: list[str] = field(default_factory=list)
    # samples trim_s dropped at each block end at the recording's rate (the channel's trim)
    trim_samples: int = 0
    # AGG-TL: where its horizontal gradient came from (pipeline.compensate.agg_legs)
    gradient_evidence: dict[str, Any] = field(default_factory=dict)

    @property
    def model(self) -> str:
        """The model name (one of :data:`MODELS`), from the settings."""
        return self.settings.model

    def interference_nT(self, meas: Measurements) -> np.ndarray:
        """Carrier interference at every epoch (T-L part, unfiltered columns), nT."""
        s = self.settings
        k, _ = tl_terms(self.model, meas, s.base, s.bt_scale_nT)
        return k @ self.coefficients[: self.n_tl]

    def compensate(self, meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
        """(compensated field, interference), nT."""
        interference = self.interference_nT(meas)
        return meas.scalar_nT - interference, interference

    def gradient_nT_per_m(self) -> dict[str, float] | None:
        """AGG-TL's estimate of the field gradient at the reference point (east, north, up)."""
        if self.n_tl == len(self.terms):
            return None
        c = dict(zip(self.terms, self.coefficients, strict=True))
        return {"east": float(c["pos_e"]), "north": float(c["pos_n"]), "up": float(c["pos_up"])}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description: settings, terms and coefficients, ridge lambda, fit residual
        (nT), calibration windows (s), AGG-TL's gradient (nT/m) and position reference.
        """
        s = self.settings
        return {
            "model": s.model,
            "base_terms": s.base if s.model == "agg-tl" else s.model,
            "terms": list(self.terms),
            "coefficients": [float(c) for c in self.coefficients],
            "compensating_terms": self.n_tl,
            "lambda": float(self.lambda_),
            "ridge": "auto" if s.ridge == "auto" else float(s.ridge),
            "band_hz": None if s.band_hz is None else [float(b) for b in s.band_hz],
            "poles": s.poles,
            "trim": int(self.trim_samples),
            "trim_s": float(s.trim_s),
            "samples": int(self.n_fit),
            "fit_residual_nT": float(self.fit_residual_nT),
            "calibration_windows_s": [[float(a), float(b)] for a, b in self.calibration_blocks],
            "gradient_nT_per_m": self.gradient_nT_per_m(),
            "reference": self.reference or None,
            **({"gradient_evidence": self.gradient_evidence} if self.gradient_evidence else {}),
        }


def design_of(
    settings: FitSettings, meas: Measurements, fit_mask: np.ndarray
) -> tuple[np.ndarray, list[str], int, dict[str, float]]:
    """A linear model's design on every epoch: (columns, names, compensating count, AGG-TL's
    position reference)."""
    k, names = tl_terms(settings.model, meas, settings.base, settings.bt_scale_nT)
    n_tl = k.shape[1]
    reference: dict[str, float] = {}
    if settings.model == "agg-tl":
        if not meas.has_position:
            raise ValueError("agg-tl needs positions (/gnss/fix)")
        sel = fit_mask & np.isfinite(meas.lat_deg) & np.isfinite(meas.lon_deg)
        lat0, lon0 = float(np.mean(meas.lat_deg[sel])), float(np.mean(meas.lon_deg[sel]))
        alt0 = float(np.mean(meas.alt_m[sel]))
        e, n, u = LocalFrame(lat0, lon0, alt0).to_enu(meas.lat_deg, meas.lon_deg, meas.alt_m)
        kp, pnames = position_terms(e, n, u)
        k, names = np.column_stack([k, kp]), names + pnames
        reference = {"latitude_deg": lat0, "longitude_deg": lon0, "altitude_m": alt0}
    if settings.band_hz is None:  # unfiltered fit: the constant level needs its own column
        k, names = np.column_stack([k, np.ones(len(k))]), names + ["bias"]
    return k, names, n_tl, reference


def fit_columns(
    meas: Measurements,
    mask: np.ndarray,
    s: FitSettings,
    k_full: np.ndarray,
    names: list[str],
    n_tl: int,
    reference: dict[str, float] | None = None,
) -> CompensationModel:
    """The band-passed ridge fit of the design ``k_full`` (columns ``names``, the first
    ``n_tl`` compensating) on the calibration epochs ``mask``."""
    kf, yf, where = bandpassed_design(
        k_full, meas.scalar_nT, meas.time_s, meas.rate_hz, mask, s.band_hz, s.poles, s.trim_s
    )
    if where.size < 2 * k_full.shape[1]:
        raise ValueError(
            f"only {where.size} usable calibration samples for {k_full.shape[1]} terms"
        )
    cond, weakest = scaled_condition(kf, names)
    fit = fit_ridge(kf, yf, s.ridge, uncertainty=True)
    valid = mask & np.isfinite(meas.scalar_nT) & np.all(np.isfinite(k_full), axis=1)
    blocks = contiguous_blocks(valid, meas.time_s)
    spans = [(float(meas.time_s[b[0]]), float(meas.time_s[b[-1]])) for b in blocks]
    return CompensationModel(
        s,
        names,
        fit.theta,
        n_tl,
        fit.lambda_,
        fit.n_rows,
        fit.residual_rms,
        spans,
        fit.lcurve,
        reference or {},
        fit.coefficient_std,
        cond,
        weakest,
        trim_samples(s.trim_s, meas.rate_hz),
    )


# --------------------------------------------------------------------------------------------
@dataclass
class FigureOfMerit:
    """Peak-to-peak of the band-passed signal in each calibration manoeuvre box, nT."""

    boxes: list[dict[str, Any]]
    passes: list[dict[str, Any]]

    @property
    def total(self) -> dict[str, float | None]:
        """Sum over the 12 boxes of the first complete pass (else the first pass)."""
        if not self.passes:
            return {"uncompensated": None, "compensated": None}
        best = next((p for p in self.passes if p["complete"]), self.passes[0])
        return {"uncompensated": best["uncompensated_nT"], "compensated": best["compensated_nT"]}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: the total FOM (uncompensated and compensated, nT) with the per-pass and
        per-box values.
        """
        return {**self.total, "passes": self.passes, "boxes": self.boxes}


def fom_band(
    band_hz: tuple[float, float] | None = None, poles: int | None = None
) -> tuple[tuple[float, float], int]:
    """The band and order a FOM is measured in: the given ones, else the shipped defaults
    (``[compensation] band_hz``, ``poles``)."""
    band = (
        tuple(band_hz) if band_hz is not None else tuple(default_value("compensation", "band_hz"))
    )
    return band, int(poles if poles is not None else default_value("compensation", "poles"))


def bandpassed(
    meas_time_s: np.ndarray, x: np.ndarray, band_hz: tuple[float, float], poles: int
) -> np.ndarray:
    """Band-pass ``x`` over each contiguous finite block of the whole flight (NaN elsewhere)."""
    out = np.full(x.shape, np.nan)
    rate = 1.0 / float(np.median(np.diff(meas_time_s)))
    sos = bandpass_sos(band_hz, rate, poles)
    blocks = contiguous_blocks(np.isfinite(x), meas_time_s)
    y, where = bandpass_blocks(x, blocks, sos, 0)
    out[where] = y
    return out


def figure_of_merit(
    time_s: np.ndarray,
    raw_nT: np.ndarray,
    compensated_nT: np.ndarray,
    boxes: list,
    band_hz: tuple[float, float] | None = None,
    poles: int | None = None,
) -> FigureOfMerit:
    """FOM of each box (see :class:`pipeline.segment.Box`) and per pass, raw vs compensated,
    band-passed with ``band_hz`` / ``poles`` (None: the shipped configuration's): pass the
    configured band so every FOM table of a run agrees."""
    band_hz, poles = fom_band(band_hz, poles)
    raw_bp = bandpassed(time_s, raw_nT, band_hz, poles)
    comp_bp = bandpassed(time_s, compensated_nT, band_hz, poles)
    rows = []
    for b in boxes:
        rows.append(
            {
                "pass": b.calibration_pass,
                "cardinal": b.cardinal,
                "manoeuvre": b.manoeuvre,
                "samples": int(b.index.size),
                "uncompensated_nT": _peak_to_peak(raw_bp[b.index]),
                "compensated_nT": _peak_to_peak(comp_bp[b.index]),
            }
        )
    passes = []
    for p in sorted({r["pass"] for r in rows}):
        mine = [r for r in rows if r["pass"] == p]
        # like with like: the boxes where both fields exist (a fluxgate that starts late
        # leaves the first legs uncompensated); complete when all 12 are such boxes
        both = [r for r in mine if None not in (r["uncompensated_nT"], r["compensated_nT"])]
        passes.append(
            {
                "pass": p,
                "boxes": len(mine),
                "boxes_compared": len(both),
                "complete": len(both) == 12,
                "uncompensated_nT": float(sum(r["uncompensated_nT"] for r in both)),
                "compensated_nT": float(sum(r["compensated_nT"] for r in both)),
            }
        )
    return FigureOfMerit(rows, passes)


def _peak_to_peak(x: np.ndarray) -> float | None:
    """Peak-to-peak (nT) of the finite samples, None with fewer than two."""
    x = x[np.isfinite(x)]
    return float(x.max() - x.min()) if x.size >= 2 else None
