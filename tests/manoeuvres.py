"""A calibration's manoeuvres for the audit's unit tests: roll, pitch and yaw oscillations on
four headings, and the body-frame field a sensor on the carrier reads through them."""

from __future__ import annotations

import numpy as np

from pipeline.geo.frames import ned_to_body

B_NED_NT = np.array([20_000.0, 1_500.0, 45_000.0])


def manoeuvres(rate_hz: float = 10.0):
    """Roll, pitch and yaw oscillations (5-10 deg, 4-7 s periods) on four headings: time (s)
    and the body-frame field (nT; x forward, y right, z down)."""
    t = np.arange(0.0, 4 * 90.0, 1.0 / rate_hz)
    local = t % 90.0
    # turns of 10 s between the legs, at their ends (no jump in heading, so no false rate)
    heading = 90.0 * (t // 90.0) + 90.0 * np.clip((local - 80.0) / 10.0, 0.0, 1.0)
    roll = np.where(local < 27, 10 * np.sin(2 * np.pi * local / 4.5), 0.0)
    pitch = np.where((local >= 26) & (local < 52), 5 * np.sin(2 * np.pi * (local - 26) / 6.5), 0.0)
    yaw = np.where((local >= 52) & (local < 79.5), 5 * np.sin(2 * np.pi * (local - 52) / 5.5), 0.0)
    b = ned_to_body(np.tile(B_NED_NT, (t.size, 1)), roll, pitch, heading + yaw)
    return t, b
