"""White-noise estimators compared: bias on white noise alone and under a smooth signal.

    .venv/bin/python benchmarks/bench_white_noise.py [--seeds 8] [--hours 0.5]

The candidates are the ones the stages used before there was one (docs/science.md, "White
noise"): the median absolute 4th difference over sqrt(70) (``mad-d4``: despike, maps,
quality, navigation) and the spectral level of the 4th difference (``spectral``: the audit;
Welch median over 128-sample segments, the difference's gain divided out, median over
0.5-0.95 of the Nyquist frequency; now :func:`pipeline.noise.white_noise_nT`). Records:
``pipeline.simulate.records.record`` (geology at 30 m/s, manoeuvre interference at
0.08-0.5 Hz up to 10 nT, a 2 nT step) plus white noise of 0.05 or 0.2 nT, at 1-50 Hz; the
same with one spike of 20 sigma per 500 samples; and white noise alone. Printed: the median
over seeds of estimate / truth and its 10-90 % range. Nothing here has a pass mark (a
comparison, not a target): the exit status is 0 unless an estimator returns NaN on a record
long enough for it.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np
from report import finish

from pipeline.noise import white_noise_nT
from pipeline.simulate.records import record

RATES_HZ = (1.0, 2.0, 5.0, 10.0, 20.0, 50.0)


def mad_d4_nT(x: np.ndarray) -> float:
    """The median absolute 4th difference (about its median) x 1.4826 / sqrt(70)."""
    d4 = np.diff(np.asarray(x, float), 4)
    d4 = d4[np.isfinite(d4)]
    return float(1.4826 * np.median(np.abs(d4 - np.median(d4))) / np.sqrt(70.0))


def cases(seed: int, rate_hz: float, sigma_nT: float, hours: float):
    """(label, record) triples: white noise alone, with the smooth signal, and with spikes."""
    n = int(hours * 3600 * rate_hz)
    t, x = record(seed, n, sigma_nT, rate_hz)
    rng = np.random.default_rng(10_000 + seed)
    white = rng.normal(0.0, sigma_nT, n)
    spiky = x.copy()
    k = rng.choice(n, size=n // 500, replace=False)
    spiky[k] += 20 * sigma_nT * rng.choice([-1.0, 1.0], k.size)
    return t, [("white", white), ("signal", x), ("signal+spikes", spiky)]


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=8)
    ap.add_argument("--hours", type=float, default=0.5)
    args = ap.parse_args()
    rows: list[tuple[str, str]] = []
    errors: list[str] = []
    for sigma in (0.05, 0.2):
        for rate in RATES_HZ:
            ratios: dict[tuple[str, str], list[float]] = {}
            for seed in range(args.seeds):
                t, recs = cases(seed, rate, sigma, args.hours)
                for label, x in recs:
                    for name, est in (
                        ("mad-d4", mad_d4_nT(x)),
                        ("spectral", white_noise_nT(x, t)),
                    ):
                        if not np.isfinite(est):
                            errors.append(f"{name} NaN on {label} at {rate:g} Hz")
                        ratios.setdefault((label, name), []).append(est / sigma)
            for (label, name), r in ratios.items():
                lo, med, hi = np.percentile(r, [10, 50, 90])
                rows.append(
                    (
                        f"sigma {sigma:g} nT, {rate:g} Hz, {label}, {name}",
                        f"{med:.3f} ({lo:.3f}-{hi:.3f})",
                    )
                )
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
