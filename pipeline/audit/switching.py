"""A current's coupling seen where the current switches: the scalar field steps with it.

A load that is switched (a payload, a strobe, a heater) changes its current within a sample
or two. A coupling of c nT per unit (a vector in the body frame) then steps the scalar
reading by dI (u . c) as it switches, u the field's direction (body frame). The calibration fit's
band-pass keeps little of a step, and a current that switches rarely may switch only a
few times during the calibration; but every switch of the whole flight shows it, the survey
included, where the field changes slowly along a straight line. Each switch gives one step:
the compensated field fitted, over a few seconds on either side, as a line (geology and the
diurnal vary slowly over those seconds) plus a multiple of the channel itself. Regressing the steps
on dI estimates the coupling from data the calibration fit never saw, and predicting each step from
the others (leave-one-out) measures the gain.

Hand-written: no library fits steps at known instants (ruptures finds unknown ones).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from pipeline.audit.evidence import HeldOut, paired_point_gain

WINDOW_S = 6.0  # fitted on each side of a switch: a load settles within seconds


@dataclass(frozen=True)
class SwitchSteps:
    """The field's steps at a channel's switches.

    Attributes
    ----------
    time_s : ndarray, shape (k,)
        Switch instants, s.
    change : ndarray, shape (k,)
        The channel's change across each switch (its unit).
    step_nT : ndarray, shape (k,)
        The compensated field's change with the channel across each switch, nT.
    """

    time_s: np.ndarray
    change: np.ndarray
    step_nT: np.ndarray


@dataclass(frozen=True)
class SwitchCoupling:
    """A channel's coupling estimated from its switches (:func:`switch_coupling`)."""

    total_field_nT_per_unit: float  # k: the field's change per unit of the channel
    p_value: float  # t-test of k against none
    switches: int
    heldout: HeldOut  # leave-one-out steps without and with the coupling


def switch_instants(
    time_s: np.ndarray, channel: np.ndarray, span_s: float = 1.0, min_jump_sigma: float = 8.0
) -> np.ndarray:
    """Times (s) where ``channel`` switches: its change over ``span_s`` exceeds
    ``min_jump_sigma`` robust standard deviations of such changes (MAD) and 5 % of its
    range. A load that settles over seconds changes little from one sample to the next, so
    changes are taken over ``span_s``; each run of large changes counts once, at the middle
    of its largest change."""
    t = np.asarray(time_s, float)
    x = np.asarray(channel, float)
    if t.size < 20:
        return np.array([])
    k = max(1, int(round(span_s / float(np.median(np.diff(t))))))
    d = x[k:] - x[:-k]
    ok = np.isfinite(d)
    if ok.sum() < 10:
        return np.array([])
    sigma = float(stats.median_abs_deviation(d[ok], scale="normal"))
    span = float(np.nanpercentile(x, 99) - np.nanpercentile(x, 1))
    if span <= 0:
        return np.array([])
    big = np.flatnonzero(
        ok & (np.abs(np.where(ok, d, 0.0)) > max(min_jump_sigma * sigma, 0.05 * span))
    )
    if big.size == 0:
        return np.array([])
    runs = np.split(big, np.flatnonzero(np.diff(big) > k) + 1)
    out = []
    for r in runs:
        i = r[np.argmax(np.abs(d[r]))]
        out.append(0.5 * (t[i] + t[i + k]))
    return np.array(out)


def switch_steps(
    time_s: np.ndarray,
    field_nT: np.ndarray,
    channel: np.ndarray,
    usable: np.ndarray | None = None,
    window_s: float = WINDOW_S,
) -> SwitchSteps | None:
    """The field's change with the channel around each clean switch of ``channel``.

    Within ``window_s`` of a switch the field is fitted as a line (the slow field: geology
    along track, the diurnal) plus k times the channel itself, so a load that settles over
    seconds is followed as it settles; the step is k times the channel's change.

    Parameters
    ----------
    time_s : ndarray, shape (n,)
        Epoch times, s.
    field_nT : ndarray, shape (n,)
        Compensated scalar field, nT.
    channel : ndarray, shape (n,)
        The candidate channel (e.g. a current, A).
    usable : ndarray of bool, shape (n,), optional
        Epochs whose field may be used (e.g. not in turns).
    window_s : float
        Half-width of the fit window around a switch, s.

    Returns
    -------
    SwitchSteps or None
        None when fewer than 4 switches have clean windows (no other switch, no gap, every
        epoch usable and finite).
    """
    t = np.asarray(time_s, float)
    y = np.asarray(field_nT, float)
    x = np.asarray(channel, float)
    use = np.ones(t.size, bool) if usable is None else np.asarray(usable, bool)
    inst = switch_instants(t, x)
    rows = []
    for j, ts in enumerate(inst):
        lo, hi = ts - window_s, ts + window_s
        # another switch inside the window would mix two steps
        if (j > 0 and inst[j - 1] > lo) or (j + 1 < inst.size and inst[j + 1] < hi):
            continue
        a, b = np.searchsorted(t, [lo, hi])
        if b - a < 10 or not np.all(use[a:b]):
            continue
        tt, yy, xx = t[a:b] - ts, y[a:b], x[a:b]
        if not (np.all(np.isfinite(yy)) and np.all(np.isfinite(xx))):
            continue
        if np.max(np.diff(tt)) > 0.1 * window_s:  # a sampling gap
            continue
        a_mat = np.column_stack([np.ones(tt.size), tt, xx])
        coef, *_ = np.linalg.lstsq(a_mat, yy, rcond=None)
        change = float(np.mean(xx[tt > 0]) - np.mean(xx[tt < 0]))
        rows.append((ts, change, float(coef[2]) * change))
    if len(rows) < 4:
        return None
    ts, ch, st = (np.array(v) for v in zip(*rows, strict=True))
    return SwitchSteps(ts, ch, st)


def switch_coupling(steps: SwitchSteps) -> SwitchCoupling | None:
    """Coupling as the total field sees it, k nT per unit, from the steps: step = k dI
    (least squares through the origin; the field's direction changes little between
    switches, so the vector c = k u is not resolved), its t-test against no coupling and the
    leave-one-out gain (each step predicted by the fit to the others against predicting 0,
    :func:`pipeline.audit.evidence.paired_point_gain`). None: fewer than 4 switches."""
    g, y = steps.change, steps.step_nT
    n = y.size
    if n < 4 or not np.any(g):
        return None
    k = float(g @ y / (g @ g))
    r = y - k * g
    se = float(np.sqrt((r @ r) / (n - 1) / (g @ g)))
    p = float(2 * stats.t.sf(abs(k) / se, n - 1)) if se > 0 else 0.0
    h = g**2 / (g @ g)  # leverages
    loo = r / np.clip(1.0 - h, 1e-9, None)
    return SwitchCoupling(
        total_field_nT_per_unit=k,
        p_value=p,
        switches=int(n),
        heldout=paired_point_gain(y, loo),
    )
