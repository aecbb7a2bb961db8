"""The second-order terms of the audit's competing explanation for a manoeuvre-following
current (``ModelSpec.second_order``), against the exact field magnitude: a large eddy field
E dB/dt adds |E dB_perp|^2 / 2|B| to the scalar reading, quadratic in the rates, which
first-order T-L cannot follow and a motor current (whose size follows the manoeuvres') took
up on simulated fixed-wing flights."""

from __future__ import annotations

import numpy as np

from pipeline.audit.extended import AuditData, ModelSpec, design
from pipeline.geo.frames import ned_to_body

B_NED_NT = np.array([20_000.0, 1_500.0, 45_000.0])


def manoeuvres(rate_hz: float = 10.0):
    """Roll, pitch and yaw oscillations (5-10 deg, 4-7 s periods) on four headings: time (s)
    and the body-frame field (nT; x forward, y right, z down)."""
    t = np.arange(0.0, 4 * 90.0, 1.0 / rate_hz)
    local = t % 90.0
    # turns of 10 s between the legs, at their ends (no jump in heading, so no false rate)
    heading = 90.0 * (t // 90.0) + 90.0 * np.clip((local - 80.0) / 10.0, 0.0, 1.0)
    roll = np.where(local < 27, 10 * np.sin(2 * np.pi * local / 4.5), 0.0)
    pitch = np.where((local >= 26) & (local < 52), 5 * np.sin(2 * np.pi * (local - 26) / 6.5), 0.0)
    yaw = np.where((local >= 52) & (local < 79.5), 5 * np.sin(2 * np.pi * (local - 52) / 5.5), 0.0)
    b = ned_to_body(np.tile(B_NED_NT, (t.size, 1)), roll, pitch, heading + yaw)
    return t, b


def residual_after(columns: np.ndarray, y: np.ndarray) -> float:
    """RMS of ``y`` left by a least-squares fit of ``columns`` (with a constant)."""
    a = np.column_stack([np.ones(y.size), columns])
    ok = np.all(np.isfinite(a), axis=1) & np.isfinite(y)
    coef, *_ = np.linalg.lstsq(a[ok], y[ok], rcond=None)
    return float(np.sqrt(np.mean((y[ok] - a[ok] @ coef) ** 2)))


def test_the_second_order_terms_follow_the_square_of_a_large_eddy_field():
    t, b = manoeuvres()
    eddy_s = np.array([[0.02, 0.006, -0.004], [-0.003, 0.015, 0.007], [0.005, -0.008, 0.011]])
    e = np.gradient(b, t, axis=0) @ eddy_s.T  # the eddy field, nT (a fixed-wing's: up to 200 nT)
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    # what the magnitude holds beyond T-L's first order: |b + e| - |b| - u . e
    rest = np.linalg.norm(b + e, axis=1) - np.linalg.norm(b, axis=1) - np.sum(u * e, axis=1)
    data = AuditData(t, np.zeros(t.size), b, None)
    first = design(data, ModelSpec()).columns
    second = design(data, ModelSpec(second_order=True)).columns
    size = float(np.std(rest))
    assert size > 0.02  # the term is there to be followed (nT)
    assert residual_after(first, rest) > 0.5 * size  # T-L leaves most of it
    assert residual_after(second, rest) < 0.2 * residual_after(first, rest)
