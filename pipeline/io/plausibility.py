"""Plausibility of units: magnetic fields in nT, attitude in degrees.

Recorders and converters get units wrong in a few typical ways (tesla from ROS, µT from phone
sensors, gauss from old fluxgates, radians from INS drivers). A wrong unit must stop processing
with a one-line error: compensated in the wrong unit, a flight gives plausible-looking nonsense.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from pipeline.errors import AeromagError


def check_units(name: str, values: np.ndarray, path: Path, channel: str) -> None:
    """Magnetic fields must be in nT: a median of 20 000-80 000 (Earth's field)."""
    v = np.abs(values[np.isfinite(values)])
    if v.size == 0:
        return
    med = float(np.median(v))
    if 1e4 <= med <= 1e5:
        return
    for unit, lo, hi in (
        ("tesla", 1e-5, 1e-4),
        ("uT", 10.0, 100.0),
        ("gauss", 0.1, 1.0),
        ("mG", 100.0, 1000.0),
    ):
        if lo <= med <= hi:
            raise AeromagError(
                f"{name} values look like {unit} (median {med:.4g}); expected nT",
                file=path,
                channel=channel,
            )
    raise AeromagError(
        f"{name} median {med:.4g} is not an Earth field in nT", file=path, channel=channel
    )


def check_degrees(fields: dict[str, np.ndarray], names: Iterable[str], path: Path) -> None:
    """Attitude must be in degrees: all of roll, pitch within +-pi and yaw within 0..2pi
    over a whole flight means radians."""
    vals = [fields[n][np.isfinite(fields[n])] for n in names if n in fields]
    if not vals or min(v.size for v in vals) < 10:
        return
    if (
        all(np.max(np.abs(v)) <= 2 * np.pi + 1e-6 for v in vals) and np.ptp(vals[-1]) > 0.5
    ):  # yaw varies, yet never beyond 2 pi
        raise AeromagError(
            "attitude looks like radians (every angle within 2 pi while the "
            "heading varies); expected degrees",
            file=path,
            channel="/ins/attitude",
        )
