"""Heading classes relative to the direction of the pattern that was flown.

A calibration box is four legs 90 deg apart and a survey is lines and ties 90 deg apart (or
lines and their reciprocals), but neither need be cardinal: a box flown at 45 deg puts its legs
on the boundaries of north-based 90 deg sectors, where a leg's jitter or the rounding rule
decides its class. Classes are therefore taken relative to the pattern's own direction, the
circular mean of the headings on the ``fold``-times circle (period ``360 / fold`` deg), so
every leg lies near the middle of its class whatever the pattern's orientation.

Headings are degrees clockwise from true north (NED yaw or track direction).
"""

from __future__ import annotations

import numpy as np

CARDINALS = ("N", "E", "S", "W")


def pattern_direction_deg(
    heading_deg: np.ndarray, weight: np.ndarray | None = None, fold: int = 4
) -> float:
    """Direction of a pattern of headings repeated every ``360 / fold`` degrees.

    Parameters
    ----------
    heading_deg : array
        Headings (deg clockwise from north); NaNs are ignored.
    weight : array, optional
        Weight of each heading (e.g. a leg's duration in s or length in m).
    fold : int
        Symmetry of the pattern: 4 for legs 90 deg apart, 2 for lines and reciprocals.

    Returns
    -------
    float
        The pattern's offset from north in ``[-180/fold, 180/fold)`` deg (0 for a cardinal
        pattern when ``fold`` is 4), or 0 when no heading is finite.
    """
    h = np.asarray(heading_deg, float).ravel()
    w = np.ones_like(h) if weight is None else np.asarray(weight, float).ravel()
    ok = np.isfinite(h) & np.isfinite(w) & (w > 0)
    if not ok.any():
        return 0.0
    z = np.sum(w[ok] * np.exp(1j * fold * np.radians(h[ok])))
    if abs(z) == 0.0:
        return 0.0
    period = 360.0 / fold
    d = float(np.degrees(np.angle(z))) / fold
    return float((d + period / 2.0) % period - period / 2.0)


def heading_class(
    heading_deg: np.ndarray | float, reference_deg: float = 0.0, step_deg: float = 90.0
) -> np.ndarray:
    """Class of each heading in steps of ``step_deg`` around ``reference_deg``.

    Class ``k`` holds the headings within ``step_deg / 2`` of ``reference_deg + k * step_deg``
    (``k`` in ``0 .. 360/step_deg - 1``); NaN headings get class -1.
    """
    h = np.asarray(heading_deg, float)
    n = int(round(360.0 / step_deg))
    k = np.floor(np.mod(h - reference_deg + step_deg / 2.0, 360.0) / step_deg)
    return np.where(np.isfinite(h), np.nan_to_num(k).astype(int) % n, -1)


def cardinal_name(heading_deg: float, reference_deg: float = 0.0) -> str:
    """``N``, ``E``, ``S`` or ``W``: the leg's class relative to a box flown at
    ``reference_deg`` (from :func:`pattern_direction_deg`, within 45 deg of north), named after
    the cardinal heading nearest to the class's centre."""
    k = int(heading_class(heading_deg, reference_deg, 90.0))
    return CARDINALS[k] if k >= 0 else ""
