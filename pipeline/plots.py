"""Figures people look at (matplotlib, no display needed). Functions return figures; callers
save them."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.compensate.ridge import LCurve  # noqa: E402


def lcurve_figure(lc: LCurve, title: str = "L-curve") -> plt.Figure:
    """Log residual norm vs log solution norm, with the maximum-curvature corner marked."""
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    ax.loglog(lc.residual_norm, lc.solution_norm, "-", color="tab:blue", lw=1.5)
    c = lc.corner
    ax.loglog(lc.residual_norm[c], lc.solution_norm[c], "o", color="tab:red",
              label=f"corner: lambda = {lc.lambda_corner:.3g}")
    ax.set_xlabel("residual norm |K theta - y| (nT)")
    ax.set_ylabel("solution norm |theta|")
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(True, which="both", alpha=0.3)
    ax2.semilogx(lc.lambdas, lc.curvature, color="tab:green")
    ax2.axvline(lc.lambda_corner, color="tab:red", ls="--")
    ax2.set_xlabel("lambda")
    ax2.set_ylabel("curvature of the L-curve")
    ax2.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def compensation_figure(time_s: np.ndarray, raw_nT: np.ndarray, runs: dict[str, np.ndarray],
                        calibration: np.ndarray, title: str = "") -> plt.Figure:
    """Raw and compensated total field over the calibration epochs (means removed)."""
    fig, ax = plt.subplots(figsize=(11, 4))
    sel = calibration & np.isfinite(raw_nT)
    ax.plot(time_s[sel], raw_nT[sel] - np.nanmean(raw_nT[sel]), ".", ms=1, color="0.6",
            label="uncompensated")
    for name, comp in runs.items():
        ax.plot(time_s[sel], comp[sel] - np.nanmean(comp[sel]), ".", ms=1, label=name)
    ax.set_xlabel("time since first epoch (s)")
    ax.set_ylabel("total field - mean (nT)")
    ax.set_title(title or "calibration passes")
    ax.legend(markerscale=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig
