"""A campaign's outputs: ``campaign.mcap``, the exports, the report and the summary.

``campaign.mcap`` is a new recording (the flights' records stay in their own files) holding
``/map/anomaly`` (the merged grid, ``foxglove.Grid``), ``/map/frame`` (the campaign frame),
``/map/lines`` (every flight's line samples, jointly levelled), ``/campaign/flight_offset``
and ``/campaign/crossovers``; the exports read it back like any processed recording's
(:func:`pipeline.export.export_recording`). Every file is written
atomically and the summary last: a folder with ``campaign.summary.json`` is complete.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import __version__
from pipeline.campaign.joint import flight_of, line_of
from pipeline.campaign.stage import CampaignRun
from pipeline.io.writer import McapOutput, OutputChannel, encode, write_json_atomic
from pipeline.products.channels import grid_channel, map_frame_channel


def _iso(t_s: float) -> str:
    return datetime.fromtimestamp(t_s, tz=UTC).isoformat().replace("+00:00", "Z")


def flight_offset_channel(run: CampaignRun) -> OutputChannel:
    """``/campaign/flight_offset``: one message per flight, at its first line sample."""
    ch = OutputChannel("/campaign/flight_offset", "aeromag.FlightOffset")
    lev = run.leveling
    fa = np.array([flight_of(c.line_a) for c in lev.crossovers], int)
    fb = np.array([flight_of(c.line_b) for c in lev.crossovers], int)
    for s in run.sorties:
        dcs = [lev.line_offsets[ln.line_id][0] for ln in s.lines]
        mine = (fa == s.index) | (fb == s.index)
        ch.add(
            int(round(s.time_range_s[0] * 1e9)),
            {
                "flight": s.name,
                "recording": s.path.name,
                "offset_nT": float(lev.flight_offsets_nT[s.index]),
                "line_offset_rms_nT": float(np.sqrt(np.mean(np.square(dcs)))),
                "lines": len(s.lines),
                "samples": s.samples,
                "crossovers_within": int(np.sum(mine & ~lev.between)),
                "crossovers_between": int(np.sum(mine & lev.between)),
                "start_time": _iso(s.time_range_s[0]),
                "end_time": _iso(s.time_range_s[1]),
                "line_spacing_m": None if not np.isfinite(s.spacing_m) else round(s.spacing_m, 3),
                "line_heading_deg": (
                    None if not np.isfinite(s.heading_deg) else round(s.heading_deg, 3)
                ),
            },
        )
    ch.messages.sort(key=lambda m: m[0])
    return ch


def crossovers_channel(run: CampaignRun) -> OutputChannel:
    """``/campaign/crossovers``: every crossover, before and after the joint levelling."""
    ch = OutputChannel("/campaign/crossovers", "aeromag.CampaignCrossover")
    lev = run.leveling
    xs = lev.crossovers
    if not xs:
        return ch
    lat, lon, _ = run.frame.to_geodetic([c.east_m for c in xs], [c.north_m for c in xs])
    names = [s.name for s in run.sorties]
    for k, c in enumerate(xs):
        ch.add(
            int(round(max(c.time_a_s, c.time_b_s) * 1e9)),
            {
                "kind": "between_flights" if lev.between[k] else "within_flight",
                "flight_a": names[flight_of(c.line_a)],
                "line_a": line_of(c.line_a),
                "flight_b": names[flight_of(c.line_b)],
                "line_b": line_of(c.line_b),
                "east_m": round(float(c.east_m), 3),
                "north_m": round(float(c.north_m), 3),
                "latitude": float(lat[k]),
                "longitude": float(lon[k]),
                "angle_deg": round(float(c.angle_deg), 3),
                "difference_before_nT": float(lev.before_nT[k]),
                "difference_after_nT": float(lev.after_nT[k]),
                "time_separation_s": round(float(c.time_b_s - c.time_a_s), 3),
            },
        )
    ch.messages.sort(key=lambda m: m[0])
    return ch


def campaign_line_id(flight: str, line: str) -> str:
    """A line's id in the campaign's line data: ``<flight>.<line>`` (``day1.L0010``)."""
    return f"{flight}.{line}"


def line_samples_channel(run: CampaignRun) -> OutputChannel:
    """``/map/lines``: every sample of every flight's lines, jointly levelled (what the grid
    was made from), in time order; ``line_id`` is :func:`campaign_line_id`, ``fiducial`` the
    sample's epoch index in its own flight's recording. ``levelled_nT`` and ``anomaly_nT``
    carry the joint correction; ``raw_nT`` and ``compensated_nT`` are the flight's."""
    parts = []
    for s, ln, value in run.levelled_lines():
        cols = s.columns[ln.line_id]
        corr = ln.value_nT - value
        parts.append(
            {
                "line_id": np.full(ln.index.size, campaign_line_id(s.name, line_of(ln.line_id))),
                "kind": np.full(ln.index.size, ln.kind),
                "fiducial": ln.index,
                "east_m": ln.east_m,
                "north_m": ln.north_m,
                "anomaly_nT": value,
                **{k: v for k, v in cols.items() if k != "levelled_nT"},
                "levelled_nT": cols["levelled_nT"] - corr,
            }
        )
    col = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    order = np.argsort(col["time_ns"], kind="stable")
    col = {k: v[order] for k, v in col.items()}

    def payload(k: int) -> dict:  # made when written (one message per sample)
        raw = col["raw_nT"][k]
        return {
            "line_id": str(col["line_id"][k]),
            "kind": str(col["kind"][k]),
            "fiducial": int(col["fiducial"][k]),
            "latitude": float(col["latitude"][k]),
            "longitude": float(col["longitude"][k]),
            "altitude_m": float(col["altitude_m"][k]),
            "east_m": round(float(col["east_m"][k]), 3),
            "north_m": round(float(col["north_m"][k]), 3),
            "raw_nT": float(raw) if np.isfinite(raw) else None,
            "compensated_nT": float(col["compensated_nT"][k]),
            "levelled_nT": float(col["levelled_nT"][k]),
            "anomaly_nT": float(col["anomaly_nT"][k]),
        }

    return OutputChannel.rows("/map/lines", "aeromag.LineSample", col["time_ns"], payload)


def write_campaign_mcap(path: str | Path, run: CampaignRun, config_hash: str) -> Path:
    """``campaign.mcap``: the merged grid, its frame, the flight offsets and the crossovers
    (messages in log-time order), written atomically."""
    channels = [
        grid_channel("/map/anomaly", run.time_ns, run.grid),
        map_frame_channel(run, run.time_ns),
        line_samples_channel(run),
        flight_offset_channel(run),
        crossovers_channel(run),
    ]
    rows = sorted(
        (int(t), k, i) for k, ch in enumerate(channels) for i, t in enumerate(ch.log_times_ns())
    )
    with McapOutput(path) as w:
        ids = [w.channel(ch.topic, ch.schema_name) for ch in channels]
        for t, k, i in rows:
            w.write(ids[k], t, encode(channels[k].messages[i][1]))
        w.metadata(
            "aeromag.run",
            {"version": __version__, "command": "campaign", "config_hash": config_hash},
        )
    return Path(path)


# --------------------------------------------------------------------------------------------
def map_figure(run: CampaignRun):
    """The merged anomaly grid with every flight's lines over it, one colour per flight."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    g = run.grid
    east, north = g.coordinates()
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    h = g.cell_m / 2
    im = ax.imshow(
        g.values,
        origin="lower",
        extent=(east[0] - h, east[-1] + h, north[0] - h, north[-1] + h),
        cmap="RdBu_r",
        alpha=0.85,
    )
    fig.colorbar(im, ax=ax, shrink=0.8, label="anomaly (nT), jointly levelled")
    colours = plt.get_cmap("tab10")
    for s in run.sorties:
        c = colours(s.index % 10)
        for k, ln in enumerate(s.lines):
            ax.plot(
                ln.east_m,
                ln.north_m,
                color=c,
                lw=0.9 if ln.kind == "survey" else 1.4,
                label=s.name if k == 0 else None,
            )
    xs = run.leveling.crossovers
    b = run.leveling.between
    if xs:
        e = np.array([c.east_m for c in xs])
        n = np.array([c.north_m for c in xs])
        ax.plot(e[~b], n[~b], "k+", ms=5, label="crossover within a flight")
        ax.plot(e[b], n[b], "kx", ms=5, label="crossover between flights")
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("campaign: merged anomaly and flight lines")
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=3)
    fig.tight_layout()
    return fig


def crossover_figure(run: CampaignRun):
    """Histograms of the crossover differences before and after the joint levelling, within
    flights and between flights."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lev = run.leveling
    rms = lev.rms_nT()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    for ax, (key, m) in zip(
        axes, (("within_flight", ~lev.between), ("between_flights", lev.between)), strict=True
    ):
        before, after = lev.before_nT[m], lev.after_nT[m]
        if before.size:
            top = float(np.max(np.abs(np.r_[before, after]))) or 1.0
            bins = np.linspace(-top, top, 31)
            r = rms[key]
            ax.hist(before, bins, alpha=0.55, label=f"before (RMS {r['before']:.3f} nT)")
            ax.hist(after, bins, alpha=0.55, label=f"after (RMS {r['after']:.3f} nT)")
            ax.legend(fontsize=8)
        ax.set_title(f"{key.replace('_', ' ')}: {int(m.sum())} crossovers")
        ax.set_xlabel("difference a - b (nT)")
    axes[0].set_ylabel("crossovers")
    fig.tight_layout()
    return fig


def summary(
    run: CampaignRun, outputs: dict[str, str], exports: dict, config_hash: str, timings: dict
) -> dict[str, Any]:
    """The campaign's summary document (``campaign.summary.json``)."""
    lev = run.leveling
    rms = lev.rms_nT()
    within, between = rms["within_flight"]["after"], rms["between_flights"]["after"]
    ny, nx = run.grid.shape
    total, incl, decl = run.main_field
    return {
        "aeromag_version": __version__,
        "config_hash": config_hash,
        "flights": [
            {
                "flight": s.name,
                "recording": str(s.path),
                "offset_nT": float(lev.flight_offsets_nT[s.index]),
                "lines": len(s.lines),
                "samples": s.samples,
                "start_time": _iso(s.time_range_s[0]),
                "end_time": _iso(s.time_range_s[1]),
                "line_spacing_m": s.spacing_m if np.isfinite(s.spacing_m) else None,
                "line_heading_deg": s.heading_deg if np.isfinite(s.heading_deg) else None,
            }
            for s in run.sorties
        ],
        "flight_offsets_nT": {s.name: float(lev.flight_offsets_nT[s.index]) for s in run.sorties},
        "crossovers": {
            "within_flight": int(np.sum(~lev.between)),
            "between_flights": int(np.sum(lev.between)),
        },
        "crossover_rms_nT": rms,
        "between_over_within_after": (between / within if within and between is not None else None),
        "leveling": {
            "unknowns": "one offset per line"
            + (" and a slope in time" if lev.trend else "")
            + ", one offset per flight",
            "constraints": "line offsets of each flight sum to 0; flight offsets sum to 0",
            "solver": "KKT system of the constrained least squares, scipy.sparse spsolve",
            "trend": lev.trend,
        },
        "grid": {
            "shape": [ny, nx],
            "cell_m": run.grid.cell_m,
            "line_spacing_m": run.spacing_m,
            "origin": {
                "east_m": run.grid.east0_m,
                "north_m": run.grid.north0_m,
                "latitude_deg": run.frame.lat0_deg,
                "longitude_deg": run.frame.lon0_deg,
                "altitude_m": run.frame.alt0_m,
                "crs": run.frame.crs,
                "epsg": run.frame.epsg,
                "easting_m": run.frame.origin_east_m,
                "northing_m": run.frame.origin_north_m,
                "crs_choice": run.frame.note,
                "utm_zones_spanned": list(run.frame.zones),
            },
            "main_field": {"total_nT": total, "inclination_deg": incl, "declination_deg": decl},
            "anomaly_range_nT": [
                float(np.nanmin(run.grid.values)),
                float(np.nanmax(run.grid.values)),
            ],
        },
        "warnings": list(run.warnings),
        "outputs": outputs,
        "exports": exports,
        "timings_s": {k: round(v, 3) for k, v in timings.items()},
    }


def report_markdown(doc: dict[str, Any], figures: dict[str, str]) -> str:
    """The campaign report (Markdown; the figures beside it)."""
    r = doc["crossover_rms_nT"]

    def f(x) -> str:
        return "-" if x is None else f"{x:.3f}"

    lines = [
        "# Campaign report",
        "",
        f"{len(doc['flights'])} flights levelled jointly on {doc['crossovers']['within_flight']}"
        f" crossovers within flights and {doc['crossovers']['between_flights']} between "
        f"flights, gridded once ({doc['grid']['shape'][0]} x {doc['grid']['shape'][1]} cells "
        f"of {doc['grid']['cell_m']:.2f} m; median line spacing "
        f"{doc['grid']['line_spacing_m']:.1f} m).",
        "",
        "## Crossover RMS (nT)",
        "",
        "| crossovers | before (each flight levelled on its own) | after (joint) |",
        "|---|---|---|",
        f"| within flights | {f(r['within_flight']['before'])} | "
        f"{f(r['within_flight']['after'])} |",
        f"| between flights | {f(r['between_flights']['before'])} | "
        f"{f(r['between_flights']['after'])} |",
        "",
        f"Between / within after: {f(doc['between_over_within_after'])}.",
        "",
        *[f"**Warning:** {w}\n" for w in doc["warnings"]],
        "## Flights",
        "",
        "| flight | start (UTC) | lines | samples | line spacing (m) | offset (nT) |",
        "|---|---|---|---|---|---|",
    ]
    for fl in doc["flights"]:
        lines.append(
            f"| {fl['flight']} | {fl['start_time']} | {fl['lines']} | {fl['samples']} | "
            f"{f(fl['line_spacing_m'])} | {fl['offset_nT']:+.3f} |"
        )
    lines += ["", "The flight offsets are subtracted and sum to zero (the campaign's datum).", ""]
    for title, name in figures.items():
        lines += [f"## {title}", "", f"![{title}]({name})", ""]
    return "\n".join(lines)


def write_campaign(
    run: CampaignRun,
    out_dir: str | Path,
    config_hash: str,
    formats=(),
    timings: dict[str, float] | None = None,
) -> dict[str, Any]:
    """Every output of a campaign into ``out_dir``: ``campaign.mcap``, the exports
    (``formats``, as ``[export] formats``), ``campaign.report.md`` with its PNGs, and last
    ``campaign.summary.json``.

    Returns
    -------
    dict
        The summary document.
    """
    import matplotlib.pyplot as plt

    from pipeline.export import export_recording
    from pipeline.io.writer import atomic_path, write_text_atomic

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timings = dict(timings or {})
    mcap = write_campaign_mcap(out / "campaign.mcap", run, config_hash)
    exports = export_recording(mcap, out, list(formats)) if formats else {}
    figures = {
        "Campaign map": ("campaign.map.png", map_figure),
        "Crossovers before and after": ("campaign.crossovers.png", crossover_figure),
    }
    for name, make in figures.values():
        fig = make(run)
        with atomic_path(out / name) as tmp:
            fig.savefig(tmp, dpi=110)
        plt.close(fig)
    outputs = {
        "mcap": str(mcap),
        "report": str(out / "campaign.report.md"),
        "summary": str(out / "campaign.summary.json"),
        "figures": [str(out / name) for name, _ in figures.values()],
    }
    doc = summary(run, outputs, exports, config_hash, timings)
    write_text_atomic(
        out / "campaign.report.md",
        report_markdown(doc, {title: name for title, (name, _) in figures.items()}),
    )
    write_json_atomic(out / "campaign.summary.json", doc)
    return doc
