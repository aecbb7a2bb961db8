"""Map benchmarks: ARIMA-Kalman filter speed, gridding 10^6 samples, noise reduction.

    .venv/bin/python benchmarks/bench_maps.py

1. A 1000 x 1000 map (10^6 cells) serialised along its lines and Kalman-filtered with an
   ARIMA(2,1,1) model: ours vs statsmodels' KalmanFilter on the same model (time ratio, max
   difference).
2. Minimum-curvature gridding of 10^6 line samples (51 lines, 50 m apart, 0.7 m along-line
   sampling) of an analytic field: time and RMSE; then on a cell that asks for more than a
   million cells (solved in tiles): time, RMSE and the process's peak memory.
3. The same map with 1 nT of white noise: ARIMA (signal + known noise) identified by BIC,
   filtered in both directions: noise_reduction_pct against the analytic truth.
Exits non-zero when an output value is wrong (never because something is slow).
"""

from __future__ import annotations

import resource
import sys
import time

import numpy as np
from report import finish

from pipeline.maps.arima import ArimaModel, _level_state, fit_arima, kalman_filter
from pipeline.maps.grid import minimum_curvature
from pipeline.maps.stage import ARIMA_SAMPLE_LIMIT, filter_sequence, serialize


def field(x, y):
    return (
        40 * np.exp(-((x - 1200) ** 2 + (y - 5000) ** 2) / (2 * 400**2))
        - 25 * np.exp(-((x - 600) ** 2 + (y - 8000) ** 2) / (2 * 300**2))
        + 0.002 * y
    )


def _rmse_vs_field(g) -> float:
    """RMS of a grid's unmasked cells against :func:`field` at their centres (nT)."""
    gx, gy = np.meshgrid(*g.coordinates())
    ok = np.isfinite(g.values)
    return float(np.sqrt(np.mean((g.values[ok] - field(gx, gy)[ok]) ** 2)))


def main() -> int:
    rows, errors = [], []
    rng = np.random.default_rng(0)
    # 1. Kalman filter speed on 10^6 samples
    m = ArimaModel(2, 1, 1, np.array([-0.4178, -0.3517]), np.array([0.3]), 0.01)
    # a map-like sequence: anomalies of tens of nT along 1000 lines of 1000 cells, plus noise
    k = np.arange(10**6)
    y = 30 * np.sin(2 * np.pi * k / 700) * np.cos(2 * np.pi * k / 130_000) + rng.normal(
        0, 0.5, k.size
    )

    def best_of(fn, n=3):
        """Warm-up call, then the best of n: both filters timed the same way."""
        out = fn()
        times = []
        for _ in range(n):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return out, min(times)

    ours, t_ours = best_of(lambda: kalman_filter(y, m, 0.25))
    from statsmodels.tsa.statespace.kalman_filter import KalmanFilter

    t, r, z = m.harvey()
    kf = KalmanFilter(k_endog=1, k_states=3, k_posdef=1)
    kf.bind(y.reshape(-1, 1))
    kf["design"], kf["transition"] = z.reshape(1, -1), t
    kf["selection"], kf["state_cov"] = r.reshape(-1, 1), np.array([[m.sigma2]])
    kf["obs_cov"] = np.array([[0.25]])
    x0, p0 = _level_state(t, y[0]), np.eye(3) * 1e6 * np.var(y)
    kf.initialize_known(t @ x0, t @ p0 @ t.T + m.sigma2 * np.outer(r, r))
    res, t_sm = best_of(kf.filter)
    ref = z @ res.filtered_state
    diff = float(np.max(np.abs(ref - ours.filtered)))
    rows.append(
        (
            "ARIMA-KF, 1000 x 1000 cells",
            f"ours {t_ours:.3f} s, statsmodels {t_sm:.2f} s ({t_sm / t_ours:.0f}x, target "
            f">= 20x and <= 5 s; best of 3 after a warm-up); "
            f"max difference {diff:.1e} nT",
        )
    )
    if diff > 1e-6:
        errors.append(f"Kalman filter differs from statsmodels by {diff:.2e} nT")
    # 2. gridding 10^6 samples
    xs, ys = [], []
    for e0 in np.arange(0, 2501, 50):
        yy = np.arange(0, 13720, 0.7)
        xs.append(e0 + rng.normal(0, 0.5, yy.size))
        ys.append(yy)
    x, yv = np.concatenate(xs), np.concatenate(ys)
    v = field(x, yv)
    t0 = time.perf_counter()
    g = minimum_curvature(x, yv, v, 12.5, mask_distance_m=50)
    t_grid = time.perf_counter() - t0
    gx, gy = np.meshgrid(*g.coordinates())
    ok = np.isfinite(g.values)
    rmse = _rmse_vs_field(g)
    rows.append(
        (
            f"gridding {x.size:,} samples",
            f"{t_grid:.1f} s, {g.shape[0]} x {g.shape[1]} "
            f"cells of 12.5 m, RMSE vs analytic field {rmse:.3f} nT",
        )
    )
    if rmse > 0.1:
        errors.append(f"gridding RMSE {rmse:.3f} nT")
    # 2b. the same samples on a cell that asks for more than MAX_CELLS: a million-cell grid,
    # solved in tiles; the process's peak memory after it (MiB, ru_maxrss)
    t0 = time.perf_counter()
    fine = minimum_curvature(x, yv, v, 2.0, mask_distance_m=50)
    t_fine = time.perf_counter() - t0
    rmse_fine = _rmse_vs_field(fine)
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    rows.append(
        (
            f"gridding {x.size:,} samples on {fine.values.size:,} cells",
            f"{t_fine:.1f} s, {fine.shape[0]} x {fine.shape[1]} cells of {fine.cell_m:.2f} m, "
            f"RMSE vs analytic field {rmse_fine:.3f} nT, process peak {peak_mb:.0f} MiB",
        )
    )
    if rmse_fine > 0.1:
        errors.append(f"million-cell gridding RMSE {rmse_fine:.3f} nT")
    # 3. noise reduction of the ARIMA-Kalman filter on that map
    truth = field(gx, gy)
    noisy = g.with_values(np.where(ok, truth + rng.normal(0, 1.0, truth.shape), np.nan))
    seq, order = serialize(noisy, along_north=True)
    t0 = time.perf_counter()
    model = fit_arima(seq[np.isfinite(seq)][:ARIMA_SAMPLE_LIMIT], measurement_var=1.0)
    filt = np.full(seq.size, np.nan)
    filt[order] = filter_sequence(seq, model, 1.0)[0]
    t_f = time.perf_counter() - t0
    filt = filt.reshape(noisy.shape)
    before = float(np.std((noisy.values - truth)[ok]))
    after = float(np.std((filt - truth)[ok]))
    pct = 100 * (1 - after / before)
    rows.append(
        (
            "ARIMA-KF on a noisy map (1 nT)",
            f"ARIMA{model.order}, RMSE {before:.3f} -> {after:.3f} nT "
            f"(noise_reduction_pct {pct:.0f} %), {t_f:.1f} s",
        )
    )
    if pct < 30:
        errors.append(f"noise reduction {pct:.0f} % < 30 %")
    return finish(rows, errors)


if __name__ == "__main__":
    sys.exit(main())
