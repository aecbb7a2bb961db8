"""The calibration legs' heading levels as a correction of tl-plus, kept when the survey's
crossovers confirm it.

The band-passed fit sees nothing below its band, so a coefficient that interference outside
the model has biased leaves a level on every straight leg that depends on the heading: the
heading error a survey line, flown straight at a steady heading, takes its level from. Over
the calibration site the correctly compensated field, less the main field (IGRF at each
position) and the day's variation (the base station, when recorded), is the crust's field,
the same whatever the heading. So the legs' levels measure the heading error directly.

The correction is a permanent field. Over 10-s blocks along the legs, least squares of
level ~ c + p_x u_x + p_y u_y + g_e e + g_n n (u the unit field in the body frame, averaged
over each block; c the crust's level; g the horizontal gradient over the box, e and n local
positions). A box flies each heading on its own side, so a gradient across the box puts a
level into each heading exactly as a permanent field does; the ramps along the legs measure
the gradient and tell the two apart (without positions only c and p are fitted). On level
legs u_z hardly changes, so it is left to the constant. The correction is applied as
interference ``p_x u_x + p_y u_y`` on every epoch, and kept only when the survey's crossovers
(lines against ties, flown at other headings, data the fit never saw) agree: per survey
line, the sum over its crossings of the squared difference without the correction less that
with it, tested by the exact sign-flip test (the line is the unit: its crossings share its
level) at ``heading_levels_alpha``. Five lines reach p = 1/32 at best. Without ties,
positions or legs on three headings nothing is applied and the record says why.

Hand-written: a five-column least squares and a permutation test on the lines' sums.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.audit.legs import leg_block_means
from pipeline.compensate.heldout import sign_flip_p

MIN_HEADINGS = 3  # the constant and two field directions need three headings
BLOCK_S = 10.0  # the legs' block means (the audit's legs' gradient uses the same)
MIN_LEG_BLOCKS = 2  # a leg takes part with at least two blocks


@dataclass(frozen=True)
class HeadingCorrection:
    """A permanent-field correction fitted to the calibration legs' heading levels.

    Attributes
    ----------
    p_nT : ndarray, shape (2,)
        Permanent field along the body's x (forward) and y (right) axes, nT: the
        interference added is ``p_nT[0] u_x + p_nT[1] u_y`` (u the unit field, body frame).
    legs, headings : int
        Legs and headings fitted.
    level_spread_nT : float
        RMS of the legs' levels about their mean before the correction, nT.
    residual_spread_nT : float
        The same after it, nT.
    gradient_nT_per_m : tuple of float or None
        The horizontal gradient (east, north) fitted beside it, nT/m; None without positions.
    """

    p_nT: np.ndarray
    legs: int
    headings: int
    level_spread_nT: float
    residual_spread_nT: float
    gradient_nT_per_m: tuple[float, ...] | None = None

    def interference_nT(self, unit_field: np.ndarray) -> np.ndarray:
        """The correction's interference on every epoch (nT), ``unit_field`` (n, 3) body."""
        return unit_field[:, :2] @ self.p_nT


def fit_heading_correction(
    reduced_nT: np.ndarray,
    unit_field: np.ndarray,
    leg: np.ndarray,
    heading: np.ndarray,
    time_s: np.ndarray,
    east_m: np.ndarray | None = None,
    north_m: np.ndarray | None = None,
) -> HeadingCorrection:
    """Fit the permanent-field correction to the legs' levels (see the module docstring).

    Parameters
    ----------
    reduced_nT : ndarray, shape (n,)
        Compensated field less the main field and the day's variation, nT.
    unit_field : ndarray, shape (n, 3)
        Unit vector of the measured field, body frame (x forward, y right, z down).
    leg : ndarray of int, shape (n,)
        Calibration leg per epoch (negative: none).
    heading : ndarray of int, shape (n,)
        Heading class per epoch (the box's headings numbered; negative: none).
    time_s : ndarray, shape (n,)
        Epoch times, s.
    east_m, north_m : ndarray, shape (n,), optional
        Positions in a local frame, m: with them the field's horizontal gradient over the
        box is fitted beside the correction (from the ramps along the legs).

    Returns
    -------
    HeadingCorrection

    Raises
    ------
    ValueError
        Saying why no correction can be fitted: no leg with :data:`MIN_LEG_BLOCKS` blocks,
        legs on fewer than :data:`MIN_HEADINGS` headings, or no more blocks than unknowns.
    """
    cols = [reduced_nT, unit_field[:, 0], unit_field[:, 1], heading.astype(float)]
    if east_m is not None and north_m is not None:
        cols += [east_m, north_m]
    means, leg_of = leg_block_means(time_s, np.column_stack(cols), leg, BLOCK_S, MIN_LEG_BLOCKS)
    if means.shape[0] == 0:
        raise ValueError(f"no calibration leg with {MIN_LEG_BLOCKS} blocks of {BLOCK_S:g} s")
    headings = np.unique(np.round(means[:, 3]).astype(int))
    if headings.size < MIN_HEADINGS:
        raise ValueError(f"calibration legs on {headings.size} headings, fewer than {MIN_HEADINGS}")
    y = means[:, 0]
    a = np.column_stack([np.ones(y.size), means[:, 1:3], means[:, 4:]])
    if y.size <= a.shape[1]:
        raise ValueError(f"{y.size} leg blocks for {a.shape[1]} unknowns")
    coef, *_ = np.linalg.lstsq(a, y, rcond=None)
    resid = y - a @ coef
    return HeadingCorrection(
        p_nT=coef[1:3],
        legs=int(np.unique(leg_of).size),
        headings=int(headings.size),
        level_spread_nT=float(np.std(y)),
        residual_spread_nT=float(np.sqrt(np.mean(resid**2))),
        gradient_nT_per_m=tuple(float(g) for g in coef[3:]) or None,
    )


def crossover_improvement_p(
    line: list[str], before_nT: np.ndarray, after_nT: np.ndarray
) -> tuple[float, int]:
    """One-sided p that the crossover differences ``after_nT`` are smaller than
    ``before_nT`` (same crossings, survey line of each in ``line``): the sign-flip test on
    each line's sum of ``before^2 - after^2``. Returns (p, lines)."""
    gain = np.asarray(before_nT, float) ** 2 - np.asarray(after_nT, float) ** 2
    names = np.asarray(line)
    sums = np.array([gain[names == name].sum() for name in np.unique(names)])
    return sign_flip_p(sums), int(sums.size)
