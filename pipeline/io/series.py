"""The decoded streams of a recording and what they lack: :class:`TopicSeries` (one contract
topic's samples), :class:`Gap` (an interval without samples on a topic) and :class:`Loss` (a
damaged part of the file, salvaged around).

A leaf module: the scanner, the reader, the mapped-recording importer and :class:`Flight`
(:mod:`pipeline.flight`) all name these types, so they live where none of those is imported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pipeline.io.contract import TopicRule

NS = 1_000_000_000


@dataclass
class TopicSeries:
    """A decoded contract topic: sorted, de-duplicated sample times and numeric fields."""

    topic: str
    rule: TopicRule
    time_ns: np.ndarray
    values: dict[str, np.ndarray]
    labels: dict[str, np.ndarray]  # string fields (sensor_id, unit, line_id, kind)
    problems: list[str]
    n_messages: int
    dropped_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def dropped_ranges_ns(self, join_s: float = 5.0) -> list[tuple[int, int]]:
        """Log times of the dropped messages as [first, last] ranges (drops closer than
        ``join_s`` or 3 sample periods are one range)."""
        d = np.sort(self.dropped_ns)
        if d.size == 0:
            return []
        period = self.median_period_s
        join = max(join_s, 3 * period if np.isfinite(period) else 0.0) * NS
        cut = np.flatnonzero(np.diff(d) > join) + 1
        return [(int(g[0]), int(g[-1])) for g in np.split(d, cut)]

    @property
    def median_period_s(self) -> float:
        """Median interval between samples, s (NaN with fewer than 2 samples)."""
        if self.time_ns.size < 2:
            return float("nan")
        return float(np.median(np.diff(self.time_ns))) / NS

    @property
    def rate_hz(self) -> float:
        """Sample rate from the median period, Hz (NaN when undefined)."""
        p = self.median_period_s
        return 1.0 / p if p > 0 else float("nan")


@dataclass(frozen=True)
class Gap:
    """An interval without samples on a topic, longer than the gap tolerance."""

    topic: str
    start_ns: int
    end_ns: int

    @property
    def duration_s(self) -> float:
        """Length of the gap, s."""
        return (self.end_ns - self.start_ns) / NS


@dataclass
class Loss:
    """Data a damaged recording lost: where, why, and the time span if the record told it."""

    offset: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    bytes_lost: int = 0

    def describe(self, t0_ns: int | None = None) -> str:
        """One line; times in seconds after ``t0_ns`` when given, else in ns since 1970."""
        span = ""
        if self.start_ns is not None and self.end_ns is not None:
            if t0_ns is None:
                span = f", messages logged {self.start_ns} to {self.end_ns} ns"
            else:
                span = (
                    f", messages logged {(self.start_ns - t0_ns) / 1e9:.3f} s to "
                    f"{(self.end_ns - t0_ns) / 1e9:.3f} s"
                )
        return f"{self.reason} at byte {self.offset} ({self.bytes_lost} bytes lost{span})"
