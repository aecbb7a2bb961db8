"""Figures people look at (matplotlib, no display needed). Functions return figures; callers
save them."""

from __future__ import annotations

from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.compensate.ridge import LCurve  # noqa: E402
from pipeline.flight import Flight  # noqa: E402
from pipeline.maps.grid import Grid  # noqa: E402

if TYPE_CHECKING:
    from pipeline.quality.stage import QualityRun


def lcurve_figure(lc: LCurve, title: str = "L-curve") -> plt.Figure:
    """Log residual norm vs log solution norm, with the maximum-curvature corner marked."""
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    ax.loglog(lc.residual_norm, lc.solution_norm, "-", color="tab:blue", lw=1.5)
    c = lc.corner
    ax.loglog(
        lc.residual_norm[c],
        lc.solution_norm[c],
        "o",
        color="tab:red",
        label=f"corner: lambda = {lc.lambda_corner:.3g}",
    )
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


def compensation_figure(
    time_s: np.ndarray,
    raw_bp_nT: np.ndarray,
    comp_bp_nT: dict[str, np.ndarray],
    passes: list[np.ndarray],
    band_hz: tuple[float, float] | None = None,
) -> plt.Figure:
    """Band-passed field over each calibration pass: uncompensated (top row) and each
    model's compensated signal (bottom row, its own scale: what the FOM measures);
    ``band_hz`` names the band in the titles (None: the shipped configuration's)."""
    from pipeline.compensate.model import fom_band

    band_hz, _ = fom_band(band_hz)
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


def map_figure(
    grid,
    lines,
    title: str,
    vmin: float | None = None,
    vmax: float | None = None,
    label: str = "total-field anomaly (nT)",
) -> plt.Figure:
    """A map grid with colour bar (``label``) and the flight lines (local metres)."""
    e, n = grid.coordinates()
    half = grid.cell_m / 2
    extent = (e[0] - half, e[-1] + half, n[0] - half, n[-1] + half)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig, ax = plt.subplots(figsize=(6.5, min(max(4.0, 5.5 * aspect), 11)))
    im = ax.imshow(
        grid.values,
        origin="lower",
        extent=extent,
        cmap="RdYlBu_r",
        vmin=vmin,
        vmax=vmax,
        interpolation="nearest",
    )
    for ln in lines:
        ax.plot(
            ln.east_m[::20],
            ln.north_m[::20],
            "-",
            lw=0.4,
            color="k" if ln.kind == "survey" else "0.35",
            alpha=0.6,
        )
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.set_label(label)
    ax.set_xlabel("east of the map origin (m, /map/frame)")
    ax.set_ylabel("north of the map origin (m)")
    ax.set_title(title)
    ax.set_aspect("equal")
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------------
# quality (paper 002, Figs. 5 and 6)
def heading_error_figure(summary: dict) -> plt.Figure:
    """RMS of B_validation - B_map per processing state: at exact track intersections, at
    sample pairs closer than the overlap distance, and against the interpolated map."""
    states = summary["states"]
    inter = summary.get("intersection_rms_nT", summary["heading_error_rms_nT"])
    series = [
        (
            f"pairs < {summary['overlap_m']:g} m (paper 002's overlap statistic)",
            summary["overlap_pair_rms_nT"],
        ),
        ("track intersections (ours, interpolated along track)", inter),
        ("interpolated map (paper 002's 2nd statistic)", summary["interpolated_rms_nT"]),
    ]
    fig, ax = plt.subplots(figsize=(max(6.5, 1.6 * len(states) + 3), 4.4))
    width = 0.8 / len(series)
    x = np.arange(len(states))
    for k, (label, vals) in enumerate(series):
        v = np.array([np.nan if vals.get(s) is None else vals[s] for s in states], float)
        bars = ax.bar(x + (k - (len(series) - 1) / 2) * width, v, width, label=label)
        for b, val in zip(bars, v, strict=True):
            if np.isfinite(val):
                ax.annotate(
                    f"{val:.3g}",
                    (b.get_x() + b.get_width() / 2, val),
                    ha="center",
                    va="bottom",
                    fontsize=7,
                    xytext=(0, 1),
                    textcoords="offset points",
                )
    ax.set_yscale("log")
    ax.set_xticks(x, states)
    ax.set_ylabel("RMS of B_validation - B_map (nT)")
    ax.set_title(
        f"heading error at overlap points ({summary['intersections']} intersections, "
        f"{summary['overlap_pairs']} pairs; headline: "
        f"{summary.get('heading_error_method', 'intersections')})"
    )
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig


def profile_figure(profiles, states: list[str]) -> plt.Figure:
    """Each validation line (paper 002, Fig. 6): top, the measured profile and the map
    interpolated along it for the last state; bottom, validation minus interpolated map for
    every state. Gaps (NaN) where the track leaves the map."""
    n = max(len(profiles), 1)
    fig, axes = plt.subplots(
        2 * n, 1, figsize=(10, 5.2 * n), squeeze=False, gridspec_kw={"height_ratios": [1.4, 1] * n}
    )
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    final = states[-1]
    for k, p in enumerate(profiles):
        top, bottom = axes[2 * k, 0], axes[2 * k + 1, 0]
        top.plot(
            p.distance_m,
            p.validation_nT[final],
            "-",
            color="k",
            lw=1.0,
            label=f"validation line ({final})",
        )
        top.plot(
            p.distance_m,
            p.interpolated_nT[final],
            "--",
            color="tab:red",
            lw=1.0,
            label="map interpolated (bilinear)",
        )
        top.set_title(f"validation line {p.line_id}")
        top.set_ylabel("reduced field (nT)")
        top.legend(fontsize=8, loc="best")
        for j, s in enumerate(states):
            d = p.validation_nT[s] - p.interpolated_nT[s]
            rms = np.sqrt(np.nanmean(d**2)) if np.isfinite(d).any() else np.nan
            bottom.plot(
                p.distance_m,
                d,
                "-",
                color=colours[j % len(colours)],
                lw=0.7,
                label=f"{s}: RMS {rms:.3f} nT",
            )
        bottom.axhline(0.0, color="0.5", lw=0.5)
        bottom.set_ylabel("validation - map (nT)")
        bottom.set_xlabel("distance along the line (m)")
        bottom.legend(fontsize=8, ncol=len(states), loc="best")
        for ax in (top, bottom):
            ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def crossover_figure(tracks, leveling, title: str = "tie-line crossovers") -> plt.Figure:
    """Crossover differences on the track map, before and after leveling (local metres)."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 6.5), sharey=True)
    xs = leveling.crossovers if leveling is not None else []
    before = np.array([c.difference_nT for c in xs])
    after = np.asarray(leveling.residuals_nT) if xs else np.zeros(0)
    lim = float(np.max(np.abs(before))) if before.size else 1.0
    for ax, vals, name in (
        (axes[0], before, "before leveling"),
        (axes[1], after, "after leveling"),
    ):
        for t in tracks:
            ax.plot(
                t.east_m[::20],
                t.north_m[::20],
                "-",
                lw=0.7,
                color={"survey": "0.3", "tie": "0.55"}.get(t.kind, "tab:purple"),
                alpha=0.7,
            )
        if xs:
            sc = ax.scatter(
                [c.east_m for c in xs],
                [c.north_m for c in xs],
                c=vals,
                cmap="RdBu_r",
                vmin=-lim,
                vmax=lim,
                s=28,
                edgecolors="k",
                linewidths=0.3,
                zorder=3,
            )
            rms = float(np.sqrt(np.mean(vals**2)))
            ax.set_title(f"{name}: RMS {rms:.3f} nT")
        ax.set_xlabel("east (m)")
        ax.set_aspect("equal")
    axes[0].set_ylabel("north (m)")
    if xs:
        fig.colorbar(sc, ax=axes, shrink=0.8, label="survey - tie (nT)")
    fig.suptitle(title)
    return fig


# --------------------------------------------------------------------------------------------
# model audit: measured vs simulated, before and after the extension
def _cal_segments(time_s, where, gap_s=5.0):
    t = time_s[where]
    breaks = np.flatnonzero(np.diff(t) > gap_s) + 1
    return np.split(np.arange(where.size), breaks)


def audit_time_figure(
    time_s: np.ndarray, where: np.ndarray, residuals: dict[str, np.ndarray], labels: dict[str, str]
) -> plt.Figure:
    """Band-passed measured - simulated over the calibration passes, baseline vs extended."""
    segs = [s for s in _cal_segments(time_s, where, 60.0) if s.size > 10]
    n = max(len(segs), 1)
    fig, axes = plt.subplots(n, 1, figsize=(11, 3.0 * n), squeeze=False)
    colours = {"baseline": "0.55", "extended": "tab:blue"}
    for ax, seg in zip(axes[:, 0], segs, strict=False):
        t = time_s[where[seg]]
        for name, r in residuals.items():
            rms = float(np.sqrt(np.nanmean(r[seg] ** 2)))
            ax.plot(
                t,
                r[seg],
                lw=0.6,
                color=colours.get(name),
                label=f"{labels.get(name, name)}: RMS {rms:.4f} nT",
            )
        ax.set_ylabel("measured - simulated (nT)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel("time since the first epoch (s)")
    axes[0, 0].set_title("calibration passes: band-passed residual of the simulated flight")
    fig.tight_layout()
    return fig


def audit_position_figure(
    east_m: np.ndarray,
    north_m: np.ndarray,
    residuals: dict[str, np.ndarray],
    labels: dict[str, str],
) -> plt.Figure:
    """Where on the calibration box the residual is (RMS over 2 s, coloured track)."""
    fig, axes = plt.subplots(
        1, len(residuals), figsize=(5.5 * len(residuals), 5.0), squeeze=False, sharey=True
    )
    lim = max(float(np.nanpercentile(np.abs(r), 99)) for r in residuals.values())
    for ax, (name, r) in zip(axes[0], residuals.items(), strict=True):
        sc = ax.scatter(east_m, north_m, c=np.abs(r), s=2, cmap="viridis", vmin=0, vmax=lim)
        ax.set_title(labels.get(name, name), fontsize=9)
        ax.set_xlabel("east of the calibration site (m)")
        ax.set_aspect("equal")
    axes[0, 0].set_ylabel("north (m)")
    fig.colorbar(sc, ax=axes[0].tolist(), shrink=0.8, label="|measured - simulated| (nT)")
    return fig


def audit_heading_figure(
    heading_deg: np.ndarray,
    residuals: dict[str, np.ndarray],
    labels: dict[str, str],
    by_heading: dict[str, list] | None = None,
) -> plt.Figure:
    """Residual RMS by heading on the calibration passes, and (when a survey exists) the
    heading error (validation - map mean by map-line heading) before and after."""
    ncol = 2 if by_heading else 1
    fig, axes = plt.subplots(1, ncol, figsize=(6 * ncol, 4.2), squeeze=False)
    ax = axes[0, 0]
    edges = np.arange(0, 361, 30)
    mid = edges[:-1] + 15
    h = np.mod(heading_deg, 360)
    for name, r in residuals.items():
        rms = [
            np.sqrt(np.nanmean(r[(h >= a) & (h < b)] ** 2))
            if np.any((h >= a) & (h < b))
            else np.nan
            for a, b in zip(edges[:-1], edges[1:], strict=True)
        ]
        ax.plot(mid, rms, "o-", label=labels.get(name, name))
    ax.set_xlabel("heading (deg)")
    ax.set_ylabel("band-passed residual RMS (nT)")
    ax.set_title("calibration residual by heading")
    ax.set_xticks(range(0, 361, 90))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if by_heading:
        ax2 = axes[0, 1]
        width = 0.38
        keys = sorted(
            {
                (g["validation_heading_deg"], g["map_heading_deg"])
                for rows in by_heading.values()
                for g in rows
            }
        )
        x = np.arange(len(keys))
        for k, (name, rows) in enumerate(by_heading.items()):
            d = {(g["validation_heading_deg"], g["map_heading_deg"]): g for g in rows}
            mean = [d[key]["mean_nT"] if key in d else np.nan for key in keys]
            ci = [d[key]["ci_nT"] or 0.0 if key in d else 0.0 for key in keys]
            ax2.bar(
                x + (k - 0.5) * width, mean, width, yerr=ci, capsize=2, label=labels.get(name, name)
            )
        ax2.set_xticks(x, [f"{a:.0f}/{b:.0f}" for a, b in keys], fontsize=7)
        ax2.set_xlabel("validation / map line heading (deg)")
        ax2.set_ylabel("mean B_validation - B_map (nT), 95 % CI")
        ax2.set_title("heading error at validation intersections")
        ax2.axhline(0, color="0.5", lw=0.5)
        ax2.grid(alpha=0.3, axis="y")
        ax2.legend(fontsize=8)
    fig.tight_layout()
    return fig


def audit_gain_figure(gain: dict[str, dict[str, float | None]]) -> plt.Figure:
    """Before vs after for every gain metric (log scale)."""
    rows = [
        (k, v["before"], v["after"])
        for k, v in gain.items()
        if v["before"] is not None and v["after"] is not None
    ]
    fig, ax = plt.subplots(figsize=(8, 4))
    x = np.arange(len(rows))
    ax.bar(x - 0.2, [r[1] for r in rows], 0.4, label="baseline", color="0.6")
    ax.bar(x + 0.2, [r[2] for r in rows], 0.4, label="extended", color="tab:blue")
    for i, r in enumerate(rows):
        for dx, v in ((-0.2, r[1]), (0.2, r[2])):
            ax.annotate(f"{v:.3g}", (i + dx, v), ha="center", va="bottom", fontsize=7)
    ax.set_xticks(x, [r[0].replace("_nT", "").replace("_", " ") for r in rows], fontsize=8)
    ax.set_yscale("log")
    ax.set_ylabel("nT")
    ax.set_title("gain of the extended model")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y", which="both")
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------------
# flight overview

SEGMENT_COLOURS = {
    "calibration": "tab:red",
    "survey": "tab:blue",
    "tie": "tab:green",
    "validation": "tab:purple",
    "turn": "0.75",
    "transit": "0.55",
}


def _runs_apart(sel: np.ndarray, *values: np.ndarray) -> list[np.ndarray]:
    """``values`` at the epochs of ``sel``, with one NaN where a run of ``sel`` ends."""
    idx = np.flatnonzero(sel)
    breaks = np.flatnonzero(np.diff(idx) > 1) + 1
    return [np.insert(np.asarray(v, float)[idx], breaks, np.nan) for v in values]


def flight_map_figure(
    east_m: np.ndarray,
    north_m: np.ndarray,
    labels: np.ndarray,
    title: str = "flight track by segment",
) -> plt.Figure:
    """The GNSS track in local east/north metres, coloured by segment label.

    Turns and transits are drawn thin and grey so the calibration box and the lines stand out.
    """
    fig, ax = plt.subplots(figsize=(7.5, 6.0))
    labels = np.asarray(labels).astype(str)
    for label, colour in SEGMENT_COLOURS.items():
        sel = labels == label
        if not sel.any():
            continue
        # NaN between runs of the label, so separate pieces are not joined by straight lines
        # (one NaN per gap: a path of the label's epochs only, not of the whole flight)
        e, n = _runs_apart(sel, east_m, north_m)
        minor = label in ("turn", "transit")
        ax.plot(
            e,
            n,
            "-",
            color=colour,
            lw=0.6 if minor else 1.2,
            label=f"{label} ({sel.sum()} epochs)",
            zorder=1 if minor else 2,
        )
    ax.plot(east_m[:1], north_m[:1], "k^", ms=7, label="start")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


# --------------------------------------------------------------------------------------------
# navigation (issue 18, item 6)
def navigation_track_figure(run, title: str = "navigation on the validation lines") -> plt.Figure:
    """The reference track (``/gnss/fix``), the INS alone and the map-aided track over the map
    (local east/north metres of the map's frame), scored epochs only (NaN elsewhere).

    ``run`` is a :class:`pipeline.navigation.stage.NavigationRun`.
    """
    grid = run.geomap.grid
    e, n = grid.coordinates()
    half = grid.cell_m / 2
    extent = (e[0] - half, e[-1] + half, n[0] - half, n[-1] + half)
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    fig, ax = plt.subplots(figsize=(7.0, min(max(4.5, 6.0 * aspect), 11)))
    im = ax.imshow(
        grid.values,
        origin="lower",
        extent=extent,
        cmap="Greys",
        alpha=0.6,
        interpolation="nearest",
    )
    fig.colorbar(im, ax=ax, shrink=0.8).set_label("map anomaly (nT)")
    sel = run.selected
    d = run.summary()["drms_m"]
    for xy, colour, label in (
        (run.true_en, "tab:blue", "reference (/gnss/fix)"),
        (run.ins_en(), "tab:orange", f"INS only (DRMS {d['ins_only']:.1f} m)"),
        (run.aided_en(), "tab:green", f"map-aided (DRMS {d['map_aided']:.2f} m)"),
    ):
        e_sel, n_sel = np.where(sel, xy[:, 0], np.nan), np.where(sel, xy[:, 1], np.nan)
        ax.plot(e_sel, n_sel, "-", lw=1.2, color=colour, label=label)
        ax.plot(xy[~sel, 0], xy[~sel, 1], ":", lw=0.6, color=colour)
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title(title)
    ax.set_aspect("equal")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig


def navigation_error_figure(run, title: str = "horizontal position error") -> plt.Figure:
    """Horizontal error against time: INS only and map-aided, with the posterior CRLB's and
    the filter's DRMS (±) as bands; unscored epochs (turns) shaded.

    ``run`` is a :class:`pipeline.navigation.stage.NavigationRun`.
    """
    t = (run.time_ns - run.time_ns[0]) / 1e9
    ins = np.hypot(*run.ins_error_ne().T)
    aid = np.hypot(*run.aided_error_ne().T)
    c = run.crlb_cov_m2
    bound = np.sqrt(np.maximum(c[:, 0, 0] + c[:, 1, 1], 0.0))
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    ax.semilogy(t, ins, color="tab:orange", lw=1.0, label="INS only")
    ax.semilogy(t, np.maximum(aid, 1e-3), color="tab:green", lw=1.0, label="map-aided")
    ax.semilogy(t, bound, "k--", lw=0.8, label="CRLB (DRMS)")
    ax.set_ylabel("horizontal error (m)")
    ax.set_title(title)
    ax.legend(loc="best", fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ea = run.aided_error_ne()
    for k, (comp, colour) in enumerate((("north", "tab:green"), ("east", "tab:olive"))):
        ax2.plot(t, ea[:, k], color=colour, lw=0.9, label=f"map-aided {comp} error")
    ax2.fill_between(t, -bound, bound, color="0.6", alpha=0.35, label="± CRLB (DRMS)")
    ax2.set_xlabel("time since the window's start (s)")
    ax2.set_ylabel("error (m)")
    ax2.legend(loc="best", fontsize=8)
    ax2.grid(True, alpha=0.3)
    for a in (ax, ax2):
        off = ~run.selected
        if off.any():
            a.fill_between(
                t, 0, 1, where=off, color="0.9", transform=a.get_xaxis_transform(), zorder=0
            )
    fig.tight_layout()
    return fig


ENHANCE_LABELS = {
    "rtp_nT": "reduced to the pole (nT)",
    "vertical_derivative_nT_per_m": "vertical derivative, upward (nT/m)",
    "horizontal_derivative_nT_per_m": "total horizontal derivative (nT/m)",
    "tilt_deg": "tilt angle (deg)",
    "analytic_signal_nT_per_m": "analytic signal amplitude (nT/m)",
}


def map_figures(mr) -> dict[str, object]:
    """Figures of a map run (levelled anomaly and ARIMA-Kalman filtered, one colour scale
    from the 1st-99th percentile, nT).

    Returns
    -------
    dict of str to Figure
        ``anomaly``, ``anomaly_filtered``.
    """
    lo, hi = np.nanpercentile(mr.grid.values, [1, 99])
    return {
        "anomaly": map_figure(mr.grid, mr.lines, "levelled anomaly (nT)", lo, hi),
        "anomaly_filtered": map_figure(
            mr.filtered, mr.lines, f"ARIMA{tuple(mr.model.order)} + Kalman filtered", lo, hi
        ),
    }


def enhancement_figures(grids: dict[str, Grid], settings, lines) -> dict[str, object]:
    """One figure per enhancement grid (``enhance_<channel name>``; colour scale from the
    1st-99th percentile)."""
    names = {p.topic: p.field_name for p in settings.products}
    out = {}
    for topic, g in grids.items():
        field_name = names[topic]
        label = ENHANCE_LABELS.get(field_name, field_name.replace("_nT", " (nT)"))
        lo, hi = np.nanpercentile(g.values, [1, 99])
        name = topic.removeprefix("/map/")
        out[f"enhance_{name}"] = map_figure(g, lines, name.replace("_", " "), lo, hi, label)
    return out


def quality_figures(q: QualityRun) -> dict[str, object]:
    """Figures of a quality run.

    Returns
    -------
    dict of str to Figure
        ``heading_error``, ``validation_profiles``, ``crossovers``.
    """
    s = q.summary()
    states = [st for st in q.states if st != "raw"] or q.states
    return {
        "heading_error": heading_error_figure(s),
        "validation_profiles": profile_figure(q.profiles, states),
        "crossovers": crossover_figure(
            [t for t in q.tracks if t.kind != "validation"],
            q.leveling,
            f"tie-line crossovers ({s['qc']['field']})",
        ),
    }


def navigation_figures(nav) -> dict[str, object]:
    """The track plot (reference, INS, map-aided over the map) and error against time with
    the CRLB."""
    from pipeline.products.figures import navigation_error_figure, navigation_track_figure

    return {
        "navigation_track": navigation_track_figure(nav),
        "navigation_error": navigation_error_figure(nav),
    }


def navigability_figure(grid: Grid, lines) -> plt.Figure:
    """The navigability map: the position CRLB (DRMS, m) per cell on a log colour scale
    (the bound spans decades between rich and flat parts of a map), the flight lines over it
    (local metres of the map frame)."""
    from matplotlib.colors import LogNorm

    v = grid.values[np.isfinite(grid.values) & (grid.values > 0)]
    lo, hi = np.percentile(v, [1, 99]) if v.size else (1.0, 10.0)
    hi = max(hi, lo * 1.01)
    fig = map_figure(grid, lines, "navigability: position CRLB flying into each cell", lo, hi)
    im = fig.axes[0].images[0]
    im.set_cmap("viridis_r")  # dark: poor navigation
    im.set_norm(LogNorm(vmin=lo, vmax=hi))
    fig.axes[1].set_ylabel("CRLB DRMS (m, log scale)")
    return fig


def flight_map(flight: Flight, seg):
    """The flight track over local east/north (m), coloured by segment label."""
    from pipeline.geo.local import local_east_north

    e, n = local_east_north(flight.data["lat_deg"], flight.data["lon_deg"])
    return flight_map_figure(e, n, seg.label)
