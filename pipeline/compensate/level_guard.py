"""The calibration legs' heading levels as a check on an extension of tl18 (tl-plus, tl-nn).

The band-passed fit sees nothing below its band, so the level of the compensated field on a
calibration leg flown at one heading is data no coefficient was fitted to. Over the
calibration site the correctly compensated field, less the main field (IGRF at each
position) and the day's variation (the base station, when recorded), is the crust's field:
the same whatever the heading. A heading error of the compensation (a level that depends
on the heading) is what a survey line, flown straight at a steady heading, takes its level
error from, and an extension's columns extrapolate exactly there: a second-order term's
level on a steady leg is never seen by the fit, and the held-out blocks, band-passed like
it, cannot see it either.

The test: per heading of the box, the mean of each model's reduced field over that
heading's legs, about the headings' mean. The crust under the box and the day's
variation add the same to both models' levels, so the two are paired (the same legs), and
the Pitman-Morgan test asks whether the extension's levels spread wider than tl18's (for
paired normal draws the variances are equal exactly when sum and difference are
uncorrelated; t on headings - 2 degrees of freedom). A box's legs of one heading share
their heading error, so the heading, not the leg, is the unit. The extension is reverted
to tl18 when its levels spread wider at p below ``level_guard_alpha`` (a test level). With
fewer than three headings (or no positions) the guard is recorded as not applied.

Hand-written: the Pitman-Morgan test is a correlation and a t quantile (scipy.stats has no
paired test of variances).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

MIN_HEADINGS = 3  # the paired test of spreads has headings - 2 degrees of freedom


@dataclass(frozen=True)
class LevelCheck:
    """The legs' level comparison of an extension against tl18.

    ``p_value``: one-sided p that the extension's heading levels spread wider;
    ``spread_nT`` and ``tl18_spread_nT``: each field's RMS heading level about their mean
    (nT); ``headings``: how many took part.
    """

    p_value: float
    spread_nT: float
    tl18_spread_nT: float
    headings: int


def heading_levels(
    reduced_nT: np.ndarray, heading: np.ndarray, mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per heading class, the mean of ``reduced_nT`` over the epochs of ``mask``.

    Parameters
    ----------
    reduced_nT : ndarray
        Compensated total field less the main field and the day's variation (nT).
    heading : ndarray of int
        Heading class per epoch (the box's headings numbered; negative: none).
    mask : ndarray of bool
        The calibration legs' epochs.

    Returns
    -------
    levels_nT, headings : ndarray
        The headings present and each one's mean (nT).
    """
    ok = mask & (np.asarray(heading) >= 0) & np.isfinite(reduced_nT)
    headings = np.unique(np.asarray(heading)[ok])
    levels = np.array([reduced_nT[ok & (heading == h)].mean() for h in headings])
    return levels, headings


def pitman_morgan_greater(x: np.ndarray, y: np.ndarray) -> float:
    """One-sided p of the Pitman-Morgan test that paired ``x`` spread more than ``y``.

    For paired normal draws var(x) = var(y) exactly when x + y and x - y are uncorrelated;
    their correlation r gives t = r sqrt((n - 2) / (1 - r^2)) on n - 2 degrees of freedom.
    1.0 when the two are equal (nothing to test).
    """
    s, d = np.asarray(x, float) + y, np.asarray(x, float) - y
    if np.allclose(d, 0.0, atol=1e-12) or np.ptp(s) == 0.0:
        return 1.0
    r = float(np.clip(np.corrcoef(s, d)[0, 1], -1 + 1e-15, 1 - 1e-15))
    n = s.size
    return float(stats.t.sf(r * np.sqrt((n - 2) / (1 - r * r)), n - 2))


def compare_levels(
    extended_nT: np.ndarray, tl18_nT: np.ndarray, heading: np.ndarray, mask: np.ndarray
) -> LevelCheck | None:
    """Do the extension's heading levels spread wider than tl18's? (see the module
    docstring).

    ``extended_nT`` / ``tl18_nT``: the two compensated fields less the main field and the
    day's variation (nT); ``heading`` and ``mask`` as :func:`heading_levels`. None when
    fewer than :data:`MIN_HEADINGS` headings have epochs in both fields.
    """
    both = mask & np.isfinite(extended_nT) & np.isfinite(tl18_nT)
    x, h_ext = heading_levels(extended_nT, heading, both)
    y, _ = heading_levels(tl18_nT, heading, both)
    if h_ext.size < MIN_HEADINGS:
        return None
    x, y = x - x.mean(), y - y.mean()
    return LevelCheck(
        p_value=pitman_morgan_greater(x, y),
        spread_nT=float(np.sqrt(np.mean(x**2))),
        tl18_spread_nT=float(np.sqrt(np.mean(y**2))),
        headings=int(h_ext.size),
    )
