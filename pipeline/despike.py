"""Despiking the scalar magnetometer: a Hampel test on its 4th difference.

A single-sample spike of amplitude A at sample k puts A (1, -4, 6, -4, 1) into the centred 4th
difference d4[k] = x[k-2] - 4 x[k-1] + 6 x[k] - 4 x[k+1] + x[k+2]; white noise of standard
deviation sigma gives d4 a standard deviation sqrt(70) sigma, and the smooth signal (geology,
manoeuvre interference at fractions of a Hz) hardly any. The Hampel identifier flags d4 where
it departs from its running median by more than ``threshold_sigma`` robust standard deviations
(1.4826 x the running median absolute deviation over ``window_s`` seconds: an odd number of
samples at the record's rate). Each cluster of
flagged differences is then explained on the record itself (FIT_MARGIN samples either side):
a cubic plus the set of at most MAX_TERMS spikes (at a sample of the cluster) and steps
(before one) that minimises RSS / sigma^2 + threshold_sigma^2 per term, sigma the noise from
the running scale. Steps are signal (a current switching on or off) and stay; each spike is
subtracted with its fitted amplitude. The search repeats on the repaired record (at most
MAX_ROUNDS), so a spike that a larger one hid is found next.

Everything runs per contiguous block of finite, regularly sampled epochs: a 4th difference is
never taken across a gap.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from pipeline.compensate.filters import contiguous_blocks
from pipeline.defaults import default_field
from pipeline.flight import Flight
from pipeline.noise import white_noise_nT

# the running robust scale never drops below this fraction of the block's global one, so a
# quiet stretch whose MAD happens to be small does not turn noise into spikes
SCALE_FLOOR_FRACTION = 0.75
# search rounds: the repaired record is searched again (a spike that a larger one hid)
MAX_ROUNDS = 5
# a cluster is explained on this many samples either side of it, by at most MAX_TERMS
# spikes and steps on top of a cubic
FIT_MARGIN = 3
MAX_TERMS = 3
# the 4th difference of white noise has sqrt(70) times the noise's standard deviation
D4_NOISE_GAIN = float(np.sqrt(70.0))

_SPIKE = np.array([1.0, -4.0, 6.0, -4.0, 1.0])


@dataclass
class DespikeSettings:
    """``[despike]``: on/off, Hampel window of the 4th difference (s), threshold."""

    enabled: bool = default_field("despike", "enabled")
    window_s: float = default_field("despike", "window_s")
    threshold_sigma: float = default_field("despike", "threshold_sigma")

    def __post_init__(self) -> None:
        if not self.window_s > 0:
            raise ValueError(f"despike.window_s = {self.window_s}: must be > 0 s")
        if not self.threshold_sigma > 0:
            raise ValueError(f"despike.threshold_sigma = {self.threshold_sigma}: must be > 0")

    def window_samples(self, rate_hz: float) -> int:
        """The window at ``rate_hz``: the nearest count of samples, made odd (up), at least 5
        (the 4th difference's own span)."""
        return max(int(round(self.window_s * rate_hz)) | 1, 5)


@dataclass
class DespikeResult:
    """The repaired record and what was found.

    Attributes
    ----------
    values_nT : ndarray
        The record with every spike sample replaced by its neighbours' cubic (nT).
    spike_index : ndarray
        Epoch indices of the spikes, ascending.
    amplitude_nT : ndarray
        Measured minus replaced value at each spike (nT).
    noise_nT : float
        White-noise level of the repaired record (nT, :func:`pipeline.noise.white_noise_nT`;
        a spike is as broadband as noise, so it is measured once the spikes are gone).
    """

    values_nT: np.ndarray
    spike_index: np.ndarray
    amplitude_nT: np.ndarray
    samples: int
    noise_nT: float
    settings: DespikeSettings
    steps: int = 0  # flagged clusters that look like level steps (left alone)
    rounds: int = 0
    notes: list[str] = field(default_factory=list)
    window_samples: int = 0  # the window at the record's rate (samples)

    @property
    def spikes(self) -> int:
        """Number of samples replaced as spikes."""
        return int(self.spike_index.size)

    @property
    def mask(self) -> np.ndarray:
        """True at every despiked epoch."""
        m = np.zeros(self.values_nT.size, bool)
        m[self.spike_index] = True
        return m

    def summary(self) -> dict[str, Any]:
        """The ``despike`` block of the summary JSON."""
        amp = np.abs(self.amplitude_nT)
        return {
            "spikes": self.spikes,
            "fraction": self.spikes / self.samples if self.samples else 0.0,
            "threshold_sigma": float(self.settings.threshold_sigma),
            "window_s": float(self.settings.window_s),
            "window_samples": int(self.window_samples),
            "noise_nT": self.noise_nT,
            "steps_left": int(self.steps),
            "rounds": int(self.rounds),
            "max_abs_amplitude_nT": float(amp.max()) if amp.size else None,
            "median_abs_amplitude_nT": float(np.median(amp)) if amp.size else None,
        }


def fourth_difference(x: np.ndarray) -> np.ndarray:
    """Centred 4th difference, NaN at the two samples of either end (nT)."""
    x = np.asarray(x, float)
    d = np.full(x.size, np.nan)
    if x.size >= 5:
        d[2:-2] = np.convolve(x, _SPIKE, mode="valid")
    return d


def hampel_flags(
    d4: np.ndarray, window: int, threshold_sigma: float
) -> tuple[np.ndarray, np.ndarray]:
    """Hampel identifier on a finite sequence: |d - running median| > k x running scale.

    The running scale is 1.4826 x the running median absolute deviation, floored at
    SCALE_FLOOR_FRACTION of the global one.

    Returns
    -------
    flags : ndarray of bool
    scale : ndarray
        The running robust standard deviation of ``d4``.
    """
    w = int(window) | 1  # odd
    med = median_filter(d4, size=w, mode="reflect")
    dev = np.abs(d4 - med)
    scale = 1.4826 * median_filter(dev, size=w, mode="reflect")
    floor = SCALE_FLOOR_FRACTION * 1.4826 * float(np.median(np.abs(d4 - np.median(d4))))
    scale = np.maximum(scale, max(floor, np.finfo(float).tiny))
    return dev > threshold_sigma * scale, scale


def explain_cluster(
    x: np.ndarray, first: int, last: int, sigma_nT: float, t_min: float
) -> list[tuple[str, int, float]]:
    """Spikes and steps that explain a cluster of flagged 4th differences.

    The record around the cluster (FIT_MARGIN samples either side of ``first`` .. ``last``)
    is fitted by least squares with a cubic plus terms chosen greedily from the candidates: a
    spike at any sample of the cluster, or a step before any of them. A term is kept while it
    lowers the residual sum of squares by more than (``t_min`` x ``sigma_nT``)^2 (its t
    statistic exceeds ``t_min``), at most MAX_TERMS.

    Returns
    -------
    list of (kind, index, amplitude nT)
        ``kind`` is "spike" (index: the sample) or "step" (index: the first sample after it).
    """
    lo, hi = max(first - FIT_MARGIN, 0), min(last + FIT_MARGIN + 1, x.size)
    seg = x[lo:hi]
    m = seg.size
    u = (np.arange(m) - (m - 1) / 2) / max(m / 2, 1.0)
    base = np.vander(u, 4)
    idx = np.arange(lo, hi)
    candidates = [("spike", k) for k in range(first, last + 1)]
    candidates += [("step", k) for k in range(max(first, lo + 1), min(last + 2, hi))]

    cand = np.column_stack(
        [(idx == k) if kind == "spike" else (idx >= k) for kind, k in candidates]
    ).astype(float)
    # project the cubic out of the record and of every candidate once; a subset's residual
    # sum of squares is then rss0 - g_S' G_SS^-1 g_S
    q, _ = np.linalg.qr(base)
    y = seg - q @ (q.T @ seg)
    c = cand - q @ (q.T @ cand)
    gram, g = c.T @ c, c.T @ y
    rss0 = float(y @ y)
    # every subset of up to MAX_TERMS candidates; the best costs RSS / sigma^2 + t_min^2 per
    # term (a term must lower the residual by t_min standard deviations to be worth it)
    penalty = t_min**2
    best: tuple[int, ...] = ()
    best_amp = np.zeros(0)
    best_cost = rss0 / sigma_nT**2
    for size in range(1, MAX_TERMS + 1):
        if size * penalty >= best_cost:
            break  # no larger model can win
        for sub in itertools.combinations(range(len(candidates)), size):
            s_ = list(sub)
            try:
                amp = np.linalg.solve(gram[np.ix_(s_, s_)], g[s_])
            except np.linalg.LinAlgError:
                continue
            cost = (rss0 - float(g[s_] @ amp)) / sigma_nT**2 + size * penalty
            if cost < best_cost:
                best, best_amp, best_cost = sub, amp, cost
    return [(*candidates[j], float(a)) for j, a in zip(best, best_amp, strict=True)]


def _despike_block(
    x: np.ndarray, s: DespikeSettings, window: int
) -> tuple[list[int], list[float], int, int]:
    """Spikes of one contiguous block (repaired in place; ``window`` samples of the running
    median): indices, amplitudes, steps, rounds."""
    found: list[int] = []
    amps: list[float] = []
    steps = rounds = 0
    if x.size < max(window, 9):
        return found, amps, steps, rounds
    for rounds in range(1, MAX_ROUNDS + 1):  # noqa: B007 - reported
        d4 = fourth_difference(x)
        flags = np.zeros(x.size, bool)
        scale = np.full(x.size, np.nan)
        flags[2:-2], scale[2:-2] = hampel_flags(d4[2:-2], window, s.threshold_sigma)
        idx = np.flatnonzero(flags)
        if idx.size == 0:
            break
        clusters = np.split(idx, np.flatnonzero(np.diff(idx) > 4) + 1)
        new = 0
        steps = 0
        for c in clusters:
            sigma = float(np.nanmax(scale[c])) / D4_NOISE_GAIN  # noise of x from d4's scale
            terms = explain_cluster(x, int(c[0]), int(c[-1]), sigma, s.threshold_sigma)
            for kind, k, a in terms:
                if kind == "step":
                    steps += 1
                    continue
                amps.append(a)
                found.append(k)
                x[k] -= a
                new += 1
        if new == 0:
            break
    return found, amps, steps, rounds


def despike(
    values_nT: np.ndarray, time_s: np.ndarray, settings: DespikeSettings | None = None
) -> DespikeResult:
    """Find and repair the spikes of a scalar record.

    Parameters
    ----------
    values_nT : ndarray
        The scalar magnetometer (nT); NaN epochs are gaps.
    time_s : ndarray
        Epoch times (s); sampling gaps split the record into blocks.
    settings : DespikeSettings, optional
        Window and threshold (the shipped ``[despike]`` values by default).

    Returns
    -------
    DespikeResult
    """
    s = settings or DespikeSettings()
    x = np.array(values_nT, float, copy=True)
    t = np.asarray(time_s, float)
    idx: list[int] = []
    amps: list[float] = []
    steps = rounds = 0
    window = s.window_samples(1.0 / float(np.median(np.diff(t)))) if t.size > 1 else 5
    for block in contiguous_blocks(np.isfinite(x), t) if x.size > 1 else []:
        xb = x[block]
        found, a, st, r = _despike_block(xb, s, window)
        x[block] = xb
        idx += [int(block[k]) for k in found]
        amps += a
        steps += st
        rounds = max(rounds, r)
    order = np.argsort(idx)
    sigma = white_noise_nT(x, t) if x.size > 1 else float("nan")  # of the repaired record
    n = int(np.isfinite(np.asarray(values_nT, float)).sum())
    return DespikeResult(
        x,
        np.asarray(idx, int)[order],
        np.asarray(amps, float)[order],
        n,
        sigma,
        s,
        steps,
        rounds,
        window_samples=window,
    )


def despike_flight(
    flight: Flight, settings: DespikeSettings | None = None
) -> tuple[Flight, DespikeResult]:
    """The flight with its primary scalar magnetometer despiked (a copy; other columns
    shared), and the result."""
    d = flight.data
    res = despike(d["scalar_nT"].to_numpy(float), d["time_s"].to_numpy(float), settings)
    if res.spikes == 0:
        return flight, res
    return dataclasses.replace(flight, data=d.assign(scalar_nT=res.values_nT)), res
