"""Despiking the scalar magnetometer: a Hampel test on its 4th difference.

A single-sample spike of amplitude A at sample k puts A (1, -4, 6, -4, 1) into the centred 4th
difference d4[k] = x[k-2] - 4 x[k-1] + 6 x[k] - 4 x[k+1] + x[k+2]; white noise of standard
deviation sigma gives d4 a standard deviation sqrt(70) sigma, and the smooth signal (geology,
manoeuvre interference at fractions of a Hz) hardly any. The Hampel identifier flags d4 where
it departs from its running median by more than ``threshold_sigma`` robust standard deviations
(1.4826 x the running median absolute deviation over ``window_samples``). Each cluster of
flagged d4 values is then attributed: a spike when the local d4 pattern fits the spike
template (1, -4, 6, -4, 1) better than a step (1, -3, 3, -1), which a current switching on or
off leaves and which is signal, not a spike. The spike sample is replaced by the cubic through
its four neighbours, p = (-x[k-2] + 4 x[k-1] + 4 x[k+1] - x[k+2]) / 6 (then d4[k] = 0), and the
search repeats on the repaired record so that adjacent spikes are found one by one.

Everything runs per contiguous block of finite, regularly sampled epochs: a 4th difference is
never taken across a gap.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.ndimage import median_filter

from pipeline.compensate.filters import contiguous_blocks
from pipeline.defaults import default_field
from pipeline.flight import Flight

# the running robust scale never drops below this fraction of the block's global one, so a
# quiet stretch whose MAD happens to be small does not turn noise into spikes
SCALE_FLOOR_FRACTION = 0.75
# search rounds: each finds at most one spike per cluster of flagged differences
MAX_ROUNDS = 5
# the 4th difference of white noise has sqrt(70) times the noise's standard deviation
D4_NOISE_GAIN = float(np.sqrt(70.0))

_SPIKE = np.array([1.0, -4.0, 6.0, -4.0, 1.0])
_STEP = np.array([1.0, -3.0, 3.0, -1.0])


@dataclass
class DespikeSettings:
    """``[despike]``: on/off, Hampel window (samples of the 4th difference), threshold."""

    enabled: bool = default_field("despike", "enabled")
    window_samples: int = default_field("despike", "window_samples")
    threshold_sigma: float = default_field("despike", "threshold_sigma")

    def __post_init__(self) -> None:
        if self.window_samples < 5:
            raise ValueError(f"despike.window_samples = {self.window_samples}: use 5 or more")
        if not self.threshold_sigma > 0:
            raise ValueError(f"despike.threshold_sigma = {self.threshold_sigma}: must be > 0")


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
        White-noise level of the record from the median absolute 4th difference (nT).
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

    @property
    def spikes(self) -> int:
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
            "window_samples": int(self.settings.window_samples),
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


def hampel_flags(d4: np.ndarray, window: int, threshold_sigma: float) -> np.ndarray:
    """Hampel identifier on a finite sequence: |d - running median| > k x running scale.

    The running scale is 1.4826 x the running median absolute deviation, floored at
    SCALE_FLOOR_FRACTION of the global one.
    """
    w = int(window) | 1  # odd
    med = median_filter(d4, size=w, mode="reflect")
    dev = np.abs(d4 - med)
    scale = 1.4826 * median_filter(dev, size=w, mode="reflect")
    floor = SCALE_FLOOR_FRACTION * 1.4826 * float(np.median(np.abs(d4 - np.median(d4))))
    scale = np.maximum(scale, max(floor, np.finfo(float).tiny))
    return dev > threshold_sigma * scale


def _is_spike(d4: np.ndarray, k: int) -> bool:
    """Does d4 around k fit a spike at k better than a step next to it (least squares)?"""
    lo, hi = max(k - 3, 0), min(k + 4, d4.size)
    seg = d4[lo:hi]
    ok = np.isfinite(seg)  # the block's ends have no centred difference
    seg = np.where(ok, seg, 0.0)

    def misfit(template: np.ndarray, first: int) -> float:
        t = np.zeros(hi - lo)
        for j, v in enumerate(template):
            if lo <= first + j < hi:
                t[first + j - lo] = v
        t[~ok] = 0.0
        tt = float(t @ t)
        a = float(t @ seg) / tt if tt else 0.0
        r = seg - a * t
        return float(r @ r)

    spike = misfit(_SPIKE, k - 2)
    # a step between k and k+1 peaks at k (-3s) and k+1 (3s); between k-1 and k at k-1, k
    steps = min(misfit(_STEP, k - 2), misfit(_STEP, k - 1))
    return spike < steps


def _despike_block(x: np.ndarray, s: DespikeSettings) -> tuple[list[int], list[float], int, int]:
    """Spikes of one contiguous block (repaired in place): indices, amplitudes, steps, rounds."""
    found: list[int] = []
    amps: list[float] = []
    steps = rounds = 0
    if x.size < max(s.window_samples, 9):
        return found, amps, steps, rounds
    for rounds in range(1, MAX_ROUNDS + 1):  # noqa: B007 - reported
        d4 = fourth_difference(x)
        core = d4[2:-2]
        flags = np.zeros(x.size, bool)
        flags[2:-2] = hampel_flags(core, s.window_samples, s.threshold_sigma)
        idx = np.flatnonzero(flags)
        if idx.size == 0:
            break
        clusters = np.split(idx, np.flatnonzero(np.diff(idx) > 4) + 1)
        new = 0
        steps = 0
        for c in clusters:
            k = int(c[np.argmax(np.abs(d4[c]))])
            if k < 2 or k > x.size - 3:
                continue
            if not _is_spike(d4, k):
                steps += 1
                continue
            p = (-x[k - 2] + 4 * x[k - 1] + 4 * x[k + 1] - x[k + 2]) / 6.0
            amps.append(float(x[k] - p))
            found.append(k)
            x[k] = p
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
    noise = []
    for block in contiguous_blocks(np.isfinite(x), t) if x.size > 1 else []:
        xb = x[block]
        d4 = fourth_difference(xb)[2:-2]
        if d4.size:
            noise.append(np.abs(d4 - np.median(d4)))
        found, a, st, r = _despike_block(xb, s)
        x[block] = xb
        idx += [int(block[k]) for k in found]
        amps += a
        steps += st
        rounds = max(rounds, r)
    order = np.argsort(idx)
    sigma = (
        float(1.4826 * np.median(np.concatenate(noise)) / D4_NOISE_GAIN) if noise else float("nan")
    )
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
