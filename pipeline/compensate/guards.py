"""Calibration quality guards: is the calibration able to determine the coefficients?

A T-L fit always returns numbers; whether they mean anything depends on the calibration
flight. Three things go wrong in practice, and each is checked and reported (summary, log
channel, report) instead of silently producing wild coefficients:

- **ill-conditioning**: the band-passed design matrix (columns scaled to unit norm) has a
  condition number far above what a complete calibration gives. Measured on the complete box
  of ``fixtures/box_uav.mcap``: tl16 73, tl18 2.6e4, agg-tl 3.0e4 (the |B|-scaled induced terms
  of tl18 are nearly collinear by construction: u_x² + u_y² + u_z² = 1); a calibration of steady
  flight only reaches 1e6. The limits are set a factor ~4-15 above the complete box.
- **too few samples per manoeuvre**: a roll/pitch/yaw box shorter than a few oscillation
  periods cannot separate the manoeuvre's terms from noise.
- **missing headings**: the permanent and induced terms are only separable when the aircraft
  flies all four cardinal headings; a calibration on N and S only extrapolates to E and W.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.geo.heading import CARDINALS, heading_class, pattern_direction_deg

CONDITION_LIMITS = {"tl16": 1e3, "tl18": 1e5, "agg-tl": 1e5}
MANOEUVRES = ("roll", "pitch", "yaw")


def scaled_condition(k: np.ndarray, names: list[str]) -> tuple[float, list[str]]:
    """Condition number of ``k`` with unit-norm columns, and the terms that dominate its
    weakest direction (right singular vector of the smallest singular value)."""
    norms = np.linalg.norm(k, axis=0)
    keep = norms > 0
    if keep.sum() == 0 or k.shape[0] < k.shape[1]:
        return float("inf"), list(names)
    kn = k[:, keep] / norms[keep]
    _, s, vt = np.linalg.svd(kn, full_matrices=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    weak = np.abs(vt[-1])
    kept = [n for n, k_ in zip(names, keep, strict=True) if k_]
    top = [kept[i] for i in np.argsort(weak)[::-1][:3] if weak[i] > 0.2]
    dead = [n for n, k_ in zip(names, keep, strict=True) if not k_]
    return (float("inf") if dead else cond), dead + top


@dataclass
class CalibrationCheck:
    """What the guards measured, and the warnings they raised."""

    model: str
    condition_number: float
    condition_limit: float
    weakest_terms: list[str]
    headings_s: dict[str, float]  # seconds of calibration flown in each cardinal sector
    boxes: list[dict[str, Any]]  # pass, cardinal, manoeuvre, samples, seconds
    warnings: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no guard raised a warning."""
        return not self.warnings

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready fields; an infinite condition number becomes None."""
        cond = self.condition_number
        return {
            "ok": self.ok,
            "condition_number": cond if np.isfinite(cond) else None,
            "condition_limit": self.condition_limit,
            "weakest_terms": self.weakest_terms,
            "headings_s": self.headings_s,
            "boxes": self.boxes,
            "warnings": self.warnings,
        }


def check_calibration(
    model: str,
    condition_number: float,
    weakest_terms: list[str],
    time_s: np.ndarray,
    yaw_deg: np.ndarray | None,
    mask: np.ndarray,
    boxes: list | None,
    *,
    min_box_s: float = 5.0,
    min_heading_s: float = 10.0,
) -> CalibrationCheck:
    """Run the three guards on a fitted calibration.

    Parameters
    ----------
    model
        tl16 | tl18 | agg-tl (sets the condition limit).
    condition_number, weakest_terms
        From :func:`scaled_condition` on the band-passed design matrix of the fit.
    time_s, yaw_deg, mask
        Epoch times, heading (deg, NED: 0 = north, clockwise) and the calibration epochs.
    boxes
        The segmentation's manoeuvre boxes (:class:`pipeline.segment.Box`), if any.
    min_box_s, min_heading_s
        Shortest acceptable manoeuvre box, and least calibration time per cardinal heading.
    """
    rate = 1.0 / float(np.median(np.diff(time_s))) if time_s.size > 1 else 1.0
    limit = CONDITION_LIMITS.get(model, 1e5)
    warnings: list[str] = []
    if not np.isfinite(condition_number) or condition_number > limit:
        warnings.append(
            f"{model}: ill-conditioned calibration (scaled condition number "
            f"{condition_number:.3g} > {limit:.0e}); weakest combination of terms: "
            f"{', '.join(weakest_terms) or '-'}; fly the full box (4 headings x roll, pitch, "
            "yaw) or use a simpler model"
        )
    headings: dict[str, float] = {}
    if yaw_deg is not None:
        y = np.asarray(yaw_deg, float)[mask]
        y = y[np.isfinite(y)]
        # sectors around the box's own direction: a box flown at 45 deg would otherwise put
        # its legs on the boundaries of north-based sectors
        sector = heading_class(y, pattern_direction_deg(y))
        headings = {c: round(float(np.sum(sector == k)) / rate, 2) for k, c in enumerate(CARDINALS)}
        missing = [c for c in CARDINALS if headings[c] < min_heading_s]
        if missing:
            warnings.append(
                f"{model}: calibration misses heading(s) {', '.join(missing)} "
                f"(< {min_heading_s:g} s each); the coefficients extrapolate to "
                "those headings"
            )
    rows = []
    for b in boxes or []:
        idx = b.index[mask[b.index]]
        rows.append(
            {
                "pass": b.calibration_pass,
                "cardinal": b.cardinal,
                "manoeuvre": b.manoeuvre,
                "samples": int(idx.size),
                "seconds": round(idx.size / rate, 2),
            }
        )
    if boxes is not None and rows:
        short = [r for r in rows if 0 < r["seconds"] < min_box_s]
        if short:
            names = ", ".join(
                f"C{r['pass']}{r['cardinal']}-{r['manoeuvre']} ({r['seconds']:g} s)"
                for r in short[:6]
            )
            warnings.append(
                f"{model}: {len(short)} manoeuvre(s) shorter than {min_box_s:g} s: {names}"
            )
        flown = {(r["cardinal"], r["manoeuvre"]) for r in rows if r["samples"]}
        absent = [
            f"{c}-{m}"
            for c in CARDINALS
            for m in MANOEUVRES
            if (c, m) not in flown and headings.get(c, 0.0) >= min_heading_s
        ]
        if absent:
            warnings.append(f"{model}: manoeuvre(s) not flown: {', '.join(absent)}")
    return CalibrationCheck(model, condition_number, limit, weakest_terms, headings, rows, warnings)
