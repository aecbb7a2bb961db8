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


def compensation_figure(time_s: np.ndarray, raw_bp_nT: np.ndarray,
                        comp_bp_nT: dict[str, np.ndarray], passes: list[np.ndarray],
                        band_hz: tuple[float, float] = (0.1, 0.9)) -> plt.Figure:
    """Band-passed field over each calibration pass: uncompensated (top row) and each
    model's compensated signal (bottom row, its own scale: what the FOM measures)."""
    n = max(len(passes), 1)
    fig, axes = plt.subplots(2, n, figsize=(6.5 * n, 6), squeeze=False, sharex="col")
    for k, span in enumerate(passes):
        t = time_s[span] - time_s[span[0]]
        top, bottom = axes[0, k], axes[1, k]
        top.plot(t, raw_bp_nT[span], color="0.45", lw=0.7)
        top.set_title(f"calibration pass {k + 1}: uncompensated, {band_hz[0]}-{band_hz[1]} Hz")
        for name, comp in comp_bp_nT.items():
            bottom.plot(t, comp[span], lw=0.7, label=name)
        bottom.set_title("compensated")
        bottom.set_xlabel(f"time since pass start (s), pass starts at {time_s[span[0]]:.0f} s")
        for ax in (top, bottom):
            ax.set_ylabel("nT")
            ax.grid(alpha=0.3)
        bottom.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return fig


def map_figure(grid, lines, title: str, vmin: float | None = None,
               vmax: float | None = None) -> plt.Figure:
    """An anomaly grid with colour bar and the flight lines (local metres)."""
    e, n = grid.coordinates()
    half = grid.cell_m / 2
    extent = (e[0] - half, e[-1] + half, n[0] - half, n[-1] + half)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig, ax = plt.subplots(figsize=(6.5, min(max(4.0, 5.5 * aspect), 11)))
    im = ax.imshow(grid.values, origin="lower", extent=extent, cmap="RdYlBu_r",
                   vmin=vmin, vmax=vmax, interpolation="nearest")
    for ln in lines:
        ax.plot(ln.east_m[::20], ln.north_m[::20], "-", lw=0.4,
                color="k" if ln.kind == "survey" else "0.35", alpha=0.6)
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label("total-field anomaly (nT)")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title)
    ax.set_aspect("equal")
    fig.tight_layout()
    return fig
