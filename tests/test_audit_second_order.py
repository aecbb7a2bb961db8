"""The second-order terms of the audit's competing explanation for a manoeuvre-following
current (``ModelSpec.second_order``), against the exact field magnitude: a large eddy field
E dB/dt adds |E dB_perp|^2 / 2|B| to the scalar reading, quadratic in the rates, which
first-order T-L cannot follow and a motor current (whose size follows the manoeuvres') took
up on simulated fixed-wing flights."""

from __future__ import annotations

import numpy as np

from pipeline.audit.extended import AuditData, ModelSpec, design
from tests.manoeuvres import manoeuvres


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
