"""The vector-magnetometer stage on a flight recording.

``ellipsoid-kf`` (paper 003): a prior batch ellipsoid fit on the first calibration pass (or
the first fifth of the flight), then the online filter over the whole flight, updating on the
calibration passes (straight lines carry no ellipsoid information) and calibrating each
sample with the state of that moment (what an online system outputs). The sphere's radius
is the IGRF total field (vectors rescaled to a constant radius).

``component-kf`` / ``batch`` (paper 000): the 21-parameter model fitted on the calibration
passes with T = IGRF (ppigrf, at each position and date) rotated into the body frame by the
measured attitude, then inverted over the whole flight. Body frame: x forward, y right,
z down; NED for the reference field.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

import numpy as np

from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.geo.frames import ned_to_body
from pipeline.geo.igrf import igrf_ned_nT, spaced_epochs
from pipeline.segment import Segmentation
from pipeline.vector.component import ComponentKF, ComponentParameters, batch_fit
from pipeline.vector.ellipsoid import Ellipsoid, EllipsoidKF, fit_ellipsoid

METHODS = ("ellipsoid-kf", "component-kf", "batch")


def reference_field_body_nT(
    flight: Flight, spacing_s: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """IGRF in the body frame at every epoch, and its time derivative (nT, nT/s): the NED
    field evaluated every ``spacing_s`` of time and interpolated, rotated by each epoch's
    attitude."""
    flight.require(
        "lat_deg",
        "lon_deg",
        "alt_m",
        "roll_deg",
        "pitch_deg",
        "yaw_deg",
        purpose="the reference field of component compensation",
    )
    d = flight.data
    lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
    t = d["time_s"].to_numpy(float)
    ok = np.flatnonzero(np.isfinite(lat) & np.isfinite(lon) & np.isfinite(alt))
    if ok.size < 2:
        raise AeromagError(
            "no valid position for the reference field", file=flight.source, channel="/gnss/fix"
        )
    pick = spaced_epochs(t, ok, spacing_s)
    when = datetime.fromtimestamp(int(np.median(flight.time_ns[ok])) / 1e9, tz=UTC)
    ned_p = igrf_ned_nT(lat[pick], lon[pick], alt[pick], when)
    ned = np.column_stack([np.interp(t, t[pick], ned_p[:, i]) for i in range(3)])
    body = ned_to_body(
        ned,
        d["roll_deg"].to_numpy(float),
        d["pitch_deg"].to_numpy(float),
        d["yaw_deg"].to_numpy(float),
    )
    return body, np.gradient(body, t, axis=0)


@dataclass
class VectorRun:
    """The vector stage's output.

    Attributes
    ----------
    method : str
        ``ellipsoid-kf``, ``component-kf`` or ``batch``.
    output_topic : str
        Topic the vectors are written to.
    vectors_nT : ndarray, shape (n, 3)
        Calibrated or compensated field, body frame (x forward, y right, z down), nT.
    parameters : dict
        The fitted parameters.
    figures : dict
        Figures of merit (RMS against the reference field, nT; filter diagnostics).
    converged_s : float or None
        Convergence time, s, when known.
    """

    method: str
    output_topic: str
    vectors_nT: np.ndarray  # (n, 3) calibrated / compensated, body frame
    parameters: dict[str, Any]
    figures: dict[str, float | int | None]
    converged_s: float | None = None

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary: method, output topic, parameters, figures and convergence time."""
        return {
            "method": self.method,
            "output_topic": self.output_topic,
            "parameters": self.parameters,
            **self.figures,
            "converged_s": self.converged_s,
        }


def _fit_mask(flight: Flight, seg: Segmentation | None) -> np.ndarray:
    n = flight.time_ns.size
    mask = np.zeros(n, bool)
    if seg is not None:
        for span in seg.passes():
            mask[span] = True
    if not mask.any():
        mask[: max(n // 5, 100)] = True
    return mask


def run_vector(
    flight: Flight, seg: Segmentation | None, method: str, settings: dict[str, Any] | None = None
) -> VectorRun:
    """Calibrate or compensate a flight's vector magnetometer.

    Parameters
    ----------
    flight : Flight
        Needs the vector channels (body frame, nT); ``component-kf`` and ``batch`` also need
        position and attitude for the IGRF reference (NED rotated into the body frame).
    seg : Segmentation or None
        Its calibration passes are the fitted (or filter-updated) epochs; without passes, the
        first fifth of the flight (at least 100 epochs).
    method : str
        ``ellipsoid-kf``, ``component-kf`` or ``batch``.
    settings : dict, optional
        The ``[vector]`` table (fuzzy-R settings of ``component-kf``).

    Returns
    -------
    VectorRun

    Raises
    ------
    ValueError
        Unknown method.
    AeromagError
        A needed channel is missing, there is no valid position (component methods), or
        fewer than 200 calibration epochs have vector, attitude and position.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r} (use {', '.join(METHODS)})")
    flight.require("vector_x_nT", "vector_y_nT", "vector_z_nT", purpose="the vector stage")
    d = flight.data
    m = d[["vector_x_nT", "vector_y_nT", "vector_z_nT"]].to_numpy(float)
    t = d["time_s"].to_numpy(float)
    mask = _fit_mask(flight, seg) & np.all(np.isfinite(m), axis=1)
    if method == "ellipsoid-kf":
        return _ellipsoid(flight, seg, m, t, mask)
    ref, rate = reference_field_body_nT(flight)
    fit = mask & np.all(np.isfinite(ref), axis=1) & np.all(np.isfinite(rate), axis=1)
    if fit.sum() < 200:
        raise AeromagError(
            f"only {int(fit.sum())} calibration epochs with vector, attitude and position",
            file=flight.source,
            channel="/mag/vector",
        )
    if method == "batch":
        params, resid, se = batch_fit(ref[fit], rate[fit], m[fit])
        extra: dict[str, Any] = {"fit_residual_nT": resid, "standard_errors": se.to_dict()}
    else:
        kf = ComponentKF.paper(scaled=True, fuzzy=True)
        kf.sample_s = float(np.median(np.diff(t)))  # the fuzzy window's seconds -> steps
        if settings is not None:  # the [vector] table: fuzzy-R window, b, clamp, sets
            kf.configure(settings)
        # the paper's R = 1e-3 nT^2 is far below a real fluxgate's noise: start from the
        # noise the batch residual shows and let the fuzzy rule adapt it
        _, resid, _ = batch_fit(ref[fit], rate[fit], m[fit])
        kf.r = resid**2 * np.eye(3)
        kf.q = 1e-12 * np.eye(21)
        params = kf.run(ref[fit], rate[fit], m[fit])
        h = kf.history
        extra = {
            "kalman_steps": int(fit.sum()),
            "r_scale_final": float(h.r_scale[-1]),
            "r_final_nT2": float(h.r_nT2[-1]),
            "ror_median": (float(np.nanmedian(h.ror)) if np.isfinite(h.ror).any() else None),
            "covariance_min_eigenvalue": float(np.nanmin(h.min_eig)),
            "covariance_max_asymmetry": float(h.asym.max()),
        }
    comp = params.compensate(m, rate)
    before = np.linalg.norm(m, axis=1) - np.linalg.norm(ref, axis=1)
    after = np.linalg.norm(comp, axis=1) - np.linalg.norm(ref, axis=1)
    figures = {
        "magnitude_vs_reference_rms_nT": {
            "before": float(np.sqrt(np.nanmean(before[fit] ** 2))),
            "after": float(np.sqrt(np.nanmean(after[fit] ** 2))),
        },
        "component_vs_reference_rms_nT": {
            "before": [float(v) for v in np.sqrt(np.nanmean((m - ref)[fit] ** 2, axis=0))],
            "after": [float(v) for v in np.sqrt(np.nanmean((comp - ref)[fit] ** 2, axis=0))],
        },
        "fit_epochs": int(fit.sum()),
        **extra,
    }
    return VectorRun(method, "/mag/vector/compensated", comp, params.to_dict(), figures)


def _ellipsoid(
    flight: Flight, seg, m_raw: np.ndarray, t: np.ndarray, mask: np.ndarray
) -> VectorRun:
    # The ellipsoid model needs a constant |H|, while the main field changes along a flight
    # (tens of nT per 10 km): each vector is scaled by field / IGRF total first, so the sphere
    # is the same at every epoch (the hard iron is scaled along, by far under 1 %). Not by
    # the scalar reading: that carries the carrier's interference at the scalar sensor.
    if flight.has("lat_deg", "lon_deg", "alt_m"):
        from pipeline.maps.reduce import igrf_total_nT

        d = flight.data
        reference = igrf_total_nT(
            flight.time_ns,
            d["lat_deg"].to_numpy(float),
            d["lon_deg"].to_numpy(float),
            d["alt_m"].to_numpy(float),
        )
        reference = np.where(np.isfinite(reference), reference, np.nanmedian(reference))
    else:
        reference = np.full(t.size, np.nanmedian(np.linalg.norm(m_raw, axis=1)))
    field = float(np.nanmedian(reference))
    scalar = reference
    m = m_raw * (field / scalar)[:, None]
    first = np.flatnonzero(mask)
    if seg is not None and seg.passes():
        p0 = seg.passes()[0]
        first = p0[np.all(np.isfinite(m[p0]), axis=1)]
    prior = fit_ellipsoid(m[first], field)
    noise = float(
        np.sqrt(np.mean((np.linalg.norm(prior.calibrate(m[first]), axis=1) - field) ** 2))
    )
    kf = EllipsoidKF.from_prior(prior, max(noise, 1e-3))
    ok = np.all(np.isfinite(m), axis=1)
    states = np.full((m.shape[0], 9), np.nan)
    # updates where the attitude varies (the calibration passes); the survey only applies it
    states[ok] = kf.run(m[ok], mask[ok])
    out = np.full(m.shape, np.nan)
    # one square root per second of data: W changes slowly once the filter has settled
    step = max(int(round(1.0 / float(np.median(np.diff(t))))), 1)
    idx = np.flatnonzero(ok)
    for k0 in range(0, idx.size, step):
        seg_ix = idx[k0 : k0 + step]
        e = Ellipsoid(states[seg_ix[0]], field)
        if e.valid():
            out[seg_ix] = e.calibrate(m[seg_ix])
    out = out * (scalar / field)[:, None]  # back to the measured field's scale
    final = kf.ellipsoid()
    cal = ok & mask  # where the reference is the field (survey lines carry geology)
    mag_before = np.linalg.norm(m[cal], axis=1) - field
    mag_after = np.linalg.norm(final.calibrate(m[cal]), axis=1) - field
    figures = {
        "field_nT": field,
        "prior_epochs": int(first.size),
        "update_epochs": int(cal.sum()),
        "magnitude_vs_reference_rms_nT": {
            "before": float(np.sqrt(np.mean(mag_before**2))),
            "after": float(np.sqrt(np.mean(mag_after**2))),
        },
        "covariance_min_eigenvalue": kf.min_eig,
    }
    return VectorRun(
        "ellipsoid-kf",
        "/mag/vector/calibrated",
        out,
        {**final.to_dict(), "prior": prior.to_dict()},
        figures,
    )


def component_truth(truth: dict) -> ComponentParameters:
    """The 21 parameters a simulated recording's fluxgate has (see the simulator): the
    carrier's field at the fluxgate (p_v, A_v, E_v) seen through the sensor errors
    m = F (b + b_v) + o: T_p = F p_v + o, A = F (I + A_v) - I, B = F E_v."""
    from pipeline.physics.vector_sensor import FluxgateErrors

    f = FluxgateErrors(**truth["fluxgate_errors"]).matrix()
    v = truth["interference"]["vector"]
    return ComponentParameters(
        f @ np.asarray(v["permanent_nT"]) + np.asarray(truth["fluxgate_errors"]["offset_nT"]),
        f @ (np.eye(3) + np.asarray(v["induced"])) - np.eye(3),
        f @ np.asarray(v["eddy_s"]),
    )
