"""The ``aeromag`` command line.

Every user error prints one line ``aeromag: error: FILE: CHANNEL: problem`` and exits with
code 2; nothing prints a traceback (set ``AEROMAG_DEBUG=1`` to see one). Commands that run a
flow import Prefect lazily so that ``inspect`` and ``simulate`` start instantly.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from pipeline.errors import AeromagError

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Post-flight processing of airborne and UAV magnetic surveys (MCAP).",
)
console = Console(stderr=True, soft_wrap=True, highlight=False)
# Never wrap or mark up results: paths must survive copy and paste, brackets and all.
out = Console(soft_wrap=True, highlight=False)


import_app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Convert other recorders' flight data into the channel contract.",
)
app.add_typer(import_app, name="import")


def say(text: str) -> None:
    """Print a line to the console as is (no rich markup)."""
    out.print(text, markup=False)


def show(table: Table) -> None:
    """Print a table at its natural width, even into a pipe (rich assumes 80 columns)."""
    Console(width=max(out.width, 150), highlight=False).print(table)


def _fail(message: str, code: int = 2) -> None:
    console.print(f"aeromag: error: {message}", markup=False, highlight=False, soft_wrap=True)
    raise typer.Exit(code)


@app.command()
def simulate(
    out_path: Annotated[Path, typer.Option("--out", help="Recording to write (.mcap).")],
    truth: Annotated[Path | None, typer.Option(help="Truth document to write (.json).")] = None,
    scenario: Annotated[str, typer.Option(help="Built-in scenario name or a TOML file.")] = "demo",
    seed: Annotated[int, typer.Option(help="Random seed (same seed, same file).")] = 1,
    set_: Annotated[
        list[str] | None,
        typer.Option(
            "--set",
            help="Override a scenario value: key.sub=VALUE (repeatable), e.g. "
            "effects.sensor_lag.enabled=true",
        ),
    ] = None,
) -> None:
    """Simulate a flight: what the recorder writes goes to --out, the truth to --truth."""
    from pipeline.simulate import Scenario, write_simulation
    from pipeline.simulate import simulate as run

    sc = Scenario.load(scenario, set_ or [])
    with console.status(f"simulating scenario {sc.name} (seed {seed})"):
        sim = run(sc, seed)
    with console.status(f"writing {out_path}"):
        write_simulation(sim, out_path, truth)
    n = sum(len(s["t"]) for s in sim.streams.values())
    say(
        f"{out_path}: {sim.trajectory.duration_s / 60:.1f} min flight, {n} messages, "
        f"effects: {', '.join(sc.enabled_effects()) or 'none'}"
    )
    if truth:
        say(f"{truth}: truth")


@import_app.command("sgl")
def import_sgl(
    file: Annotated[Path, typer.Argument(help="SGL / DAF-MIT MagNav flight file (.h5 or .xyz).")],
    out_path: Annotated[Path, typer.Option("--out", help="Recording to write (.mcap).")],
    lines: Annotated[
        str | None, typer.Option(help="Only these lines, e.g. 1002.02,1002.20.")
    ] = None,
    calibration_lines: Annotated[
        str | None,
        typer.Option(
            help="Lines flown as calibration boxes (named in the flight's readme); marked "
            "kind=calibration in /plan/line."
        ),
    ] = None,
) -> None:
    """Import an SGL HDF5 or XYZ file (field mapping in schemas/README.md)."""
    from pipeline.io.sgl import import_sgl as run

    def split(v):
        return [x.strip() for x in v.split(",") if x.strip()] if v else None

    with console.status(f"importing {file.name}"):
        res = run(file, out_path, split(lines), split(calibration_lines))
    say(
        f"{out_path}: {res['samples']} samples over {res['span_s']:.1f} s, "
        f"{len(res['channels'])} channels"
    )


@import_app.command("mapped")
def import_mapped(
    file: Annotated[Path, typer.Argument(help="A recorder's MCAP (ROS 2, protobuf, JSON).")],
    mapping: Annotated[
        Path,
        typer.Option(
            "--mapping",
            help="Topic-mapping file (TOML); "
            "`aeromag inspect FILE "
            "--suggest-mapping` proposes one.",
        ),
    ],
    out_path: Annotated[Path, typer.Option("--out", help="Recording to write (.mcap).")],
) -> None:
    """Add contract channels (nT, body FRD, NED) for a recorder's mapped topics; every
    aeromag command then reads the output."""
    from flows.stages import require_readable
    from pipeline.io.mapping import Mapping
    from pipeline.io.mapping import import_mapped as run

    require_readable(file)
    with console.status(f"importing {file.name}"):
        names = run(file, out_path, Mapping.load(mapping))
    for a, b in names.items():
        say(f"{a} -> {b}")
    say(f"output recording: {out_path}")


@app.command()
def scenarios() -> None:
    """List the built-in simulation scenarios."""
    from pipeline.simulate import Scenario, builtin_scenarios

    for name in builtin_scenarios():
        say(f"{name:18s} {Scenario.load(name)['description']}")


@app.command()
def inspect(
    file: Annotated[Path, typer.Argument(help="MCAP recording.")],
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the report as JSON.")
    ] = None,
    suggest_mapping: Annotated[
        bool,
        typer.Option(
            "--suggest-mapping",
            help="Print a topic-mapping file (TOML) for the recorder's "
            "topics of known types (ROS 2, Foxglove protobuf).",
        ),
    ] = False,
) -> None:
    """Topics, counts, rates, span, gaps and contract violations (exit 1 on violations)."""
    from pipeline.io.inspect import inspect_recording
    from pipeline.io.writer import write_json_atomic

    if suggest_mapping:
        from flows.stages import require_readable
        from pipeline.io.mapping import suggest_mapping as suggest

        require_readable(file)
        out.print(suggest(file), markup=False, highlight=False, end="")
        return

    rep = inspect_recording(file)
    d = rep.to_dict()
    table = Table(title=f"{file}  ({d['duration_s']:.1f} s)", title_justify="left")
    for col in ("topic", "schema", "messages", "rate Hz", "gaps"):
        table.add_column(col, justify="right" if col in ("messages", "rate Hz", "gaps") else "left")
    for t in d["topics"]:
        rate = "" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
        table.add_row(t["topic"], t["schema"], str(t["messages"]), rate, str(len(t["gaps"])))
    show(table)
    for w in rep.warnings:
        say(f"warning: {w}")
    if json_out:
        write_json_atomic(json_out, d)
    if rep.violations:
        for v in rep.violations:
            console.print(f"violation: {file}: {v}", markup=False, highlight=False)
        raise typer.Exit(1)
    say("contract: ok")


# the arguments and options several commands share, written once
RecordingArg = Annotated[Path, typer.Argument(help="Flight recording (.mcap).")]
ProcessedArg = Annotated[Path, typer.Argument(help="Processed recording (.processed.mcap).")]
OutRecording = Annotated[Path, typer.Option("--out", help="Output recording (.mcap).")]
SummaryJson = Annotated[Path, typer.Option("--json", help="Summary JSON to write.")]
ConfigOption = Annotated[
    Path | None,
    typer.Option(
        "--config",
        help="Processing configuration (TOML; `aeromag config` prints the defaults); "
        "a command's options override its keys.",
    ),
]


def _check_config(config: Path | None) -> None:
    from pipeline.config import Config

    Config.load(config).validate()


def _shown(value) -> str:
    return (
        repr(value)
        if isinstance(value, str)
        else (" ".join(str(v) for v in value) if isinstance(value, list | tuple) else str(value))
    )


def _stage_config(config: Path | None, options: dict[str, tuple[str, object]]):
    """The configuration of a single-stage command: ``--config FILE`` (else the shipped
    defaults) with each option given (not None) overriding its key, ``{"--option": ("section.key",
    value)}``; checked like a file, an error names the option."""
    from pipeline.config import Config

    cfg = Config.load(config)
    cfg.validate()
    for option, (key, value) in options.items():
        if value is None:
            continue
        try:
            cfg = cfg.with_values({key: list(value) if isinstance(value, tuple) else value})
            cfg.validate()
        except AeromagError as exc:
            _fail(f"{option} {_shown(value)}: {exc.problem}")
    return cfg


@app.command()
def compensate(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    model: Annotated[
        str | None,
        typer.Option(
            help="tl16 | tl18 | agg-tl | tl-plus | tl-nn (default: the configuration's final "
            "model the recording can fit, as `aeromag process`)"
        ),
    ] = None,
    agg_base: Annotated[
        str | None,
        typer.Option(
            help="AGG-TL's T-L terms: tl18 (|B|-scaled) or tl16 (paper 002) "
            "(config: compensation.agg_base)"
        ),
    ] = None,
    band: Annotated[
        tuple[float, float] | None,
        typer.Option(help="Band-pass edges, Hz (config: compensation.band_hz)."),
    ] = None,
    poles: Annotated[
        int | None, typer.Option(help="Butterworth prototype order (config: compensation.poles).")
    ] = None,
    trim: Annotated[
        int | None,
        typer.Option(help="Samples dropped at each end of a block (config: compensation.trim)."),
    ] = None,
    ridge: Annotated[
        str | None,
        typer.Option(help="auto (L-curve corner) or a lambda (config: compensation.ridge)."),
    ] = None,
    calibration: Annotated[
        str, typer.Option(help="auto | all | T0:T1 (seconds from the first epoch, or Unix seconds)")
    ] = "auto",
    scalar: Annotated[str | None, typer.Option(help="Scalar magnetometer topic.")] = None,
    vector: Annotated[str | None, typer.Option(help="Vector magnetometer topic.")] = None,
    config: ConfigOption = None,
) -> None:
    """Fit a T-L / AGG-TL model, compensate the scalar field, write channels and a summary."""
    from flows.stages import compensate_recording, require_readable

    require_readable(recording)
    lam: object = ridge
    if ridge is not None and ridge != "auto":
        try:
            lam = float(ridge)
        except ValueError:
            pass  # the configuration's check names it
    cfg = _stage_config(
        config,
        {
            "--model": ("compensation.models", [model] if model else None),
            "--agg-base": ("compensation.agg_base", agg_base),
            "--band": ("compensation.band_hz", band),
            "--poles": ("compensation.poles", poles),
            "--trim": ("compensation.trim", trim),
            "--ridge": ("compensation.ridge", lam),
        },
    )
    settings = cfg.fit_settings(model) if model else None
    with console.status(f"compensating {recording.name}" + (f" ({model})" if model else "")):
        summary = compensate_recording(
            recording, out_path, json_out, settings, calibration, scalar, vector, cfg
        )
    for w in (summary.get("calibration_guards") or {}).get("warnings", []):
        console.print(f"warning: {w}", markup=False, highlight=False, soft_wrap=True)
    ext = summary.get("extension")
    if ext:
        say(f"{summary['model']}: {'used' if ext['used'] else 'not used'}: {ext['reason']}")
    fom = summary["fom_nT"]
    say(
        f"{summary['model']}: lambda {summary['lambda']:.3g}, {summary['samples']} samples, "
        f"fit residual {summary['fit_residual_nT']:.4f} nT"
    )
    if fom["uncompensated"] is not None:
        say(f"FOM: {fom['uncompensated']:.2f} nT uncompensated -> {fom['compensated']:.2f} nT")
    say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


@app.command("map")
def map_(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    cell: Annotated[
        float | None, typer.Option(help="Cell size, m; 0: line spacing / 4 (config: map.cell_m).")
    ] = None,
    arima: Annotated[
        str | None, typer.Option(help="auto (BIC) or p,d,q (config: map.arima)")
    ] = None,
    noise: Annotated[
        float | None,
        typer.Option(
            help="Measurement noise for the Kalman filter, nT; 0: estimated (config: map.noise_nT)"
        ),
    ] = None,
    level_trend: Annotated[
        bool | None,
        typer.Option(
            "--level-trend/--no-level-trend",
            help="Linear-in-time line corrections (config: map.level_trend).",
        ),
    ] = None,
    lag: Annotated[
        float,
        typer.Option(help="Magnetometer lag to remove, s (the sensor reports late by this much)."),
    ] = 0.0,
    config: ConfigOption = None,
) -> None:
    """Reduce, level, grid and ARIMA-Kalman-filter the anomaly map (runs the stages it needs,
    with the configuration's settings)."""
    from dataclasses import replace

    from flows.stages import map_recording, require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--cell": ("map.cell_m", cell),
            "--arima": ("map.arima", arima),
            "--noise": ("map.noise_nT", noise),
            "--level-trend": ("map.level_trend", level_trend),
        },
    )
    settings = replace(cfg.map_settings(), lag_s=lag)
    with console.status(f"mapping {recording.name}"):
        summary = map_recording(recording, out_path, json_out, settings, cfg)
    m = summary["map"]
    say(
        f"grid {m['grid_shape'][0]} x {m['grid_shape'][1]} cells of {m['cell_m']:.2f} m; "
        f"crossover RMS {m['crossover_rms_nT']['before']:.3f} -> "
        f"{m['crossover_rms_nT']['after']:.3f} nT; ARIMA{tuple(m['arima_order'])}"
    )
    say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


@app.command()
def export(
    recording: ProcessedArg,
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")],
    formats: Annotated[
        str,
        typer.Option(
            "--format",
            help="Comma-separated: geotiff (UTM), netcdf (CF-1.8), csv and xyz (levelled "
            "lines), magnav (MagNav.jl HDF5).",
        ),
    ] = "geotiff,netcdf,csv,xyz,magnav",
) -> None:
    """Write the map grids and the levelled line data of a processed recording as GeoTIFF,
    netCDF, CSV, Geosoft XYZ and MagNav.jl HDF5 (georeference from its /map/frame)."""
    from flows.stages import require_readable
    from pipeline.export import check_formats, export_recording

    require_readable(recording)
    chosen = check_formats([f for f in formats.split(",") if f.strip()], "--format")
    with console.status(f"exporting {recording.name}"):
        written = export_recording(recording, out_dir, chosen)
    for fmt, paths in written.items():
        for p in paths:
            say(f"{fmt}: {p}")


@app.command()
def enhance(
    recording: ProcessedArg,
    out_path: OutRecording,
    products: Annotated[
        str | None,
        typer.Option(
            help="Comma-separated: rtp, dz, thd, tilt, as, up:H (upward continuation by H m) "
            "(config: enhance.products)."
        ),
    ] = None,
    source: Annotated[
        str | None,
        typer.Option(help="Grid to enhance: anomaly or anomaly_filtered (config: enhance.source)."),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Map enhancements (harmonica): reduction to the pole, vertical and total horizontal
    derivatives, tilt angle, analytic signal, upward continuation -> /map/* grid channels."""
    from flows.stages import enhance_recording, require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--products": (
                "enhance.products",
                None if products is None else [p for p in products.split(",") if p.strip()],
            ),
            "--source": ("enhance.source", source),
        },
    )
    with console.status(f"enhancing {recording.name}"):
        result = enhance_recording(recording, out_path, cfg)
    for topic in result["channels"]:
        say(f"{topic}")
    say(
        f"from /map/{result['source']}; RTP with IGRF inclination "
        f"{result['inclination_deg']:.2f} deg, declination {result['declination_deg']:.2f} deg"
    )
    say(f"output recording: {out_path}")


@app.command()
def quality(
    recording: Annotated[Path, typer.Argument(help="Flight recording (.mcap), raw or processed.")],
    json_out: Annotated[
        Path, typer.Option("--json", help="Summary JSON to write (plots are written next to it).")
    ],
    overlap_m: Annotated[
        float | None,
        typer.Option(
            "--overlap-m",
            help="Largest horizontal distance of an overlap pair, m (config: quality.overlap_m).",
        ),
    ] = None,
    out_path: Annotated[
        Path | None,
        typer.Option("--out", help="Also write an output recording with the quality channels."),
    ] = None,
    noise_threshold: Annotated[
        float | None,
        typer.Option(
            help="4th-difference noise above which a line is flagged, nT "
            "(config: quality.noise_threshold_nT)."
        ),
    ] = None,
    height_tolerance: Annotated[
        float | None,
        typer.Option(
            help="Allowed flight-height deviation, m (config: quality.height_tolerance_m)."
        ),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Heading error at overlap points, interpolated-map comparison, crossovers and survey QC
    (runs segmentation, the configured compensation models and gridding itself when needed)."""
    from flows.stages import quality_recording, require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--overlap-m": ("quality.overlap_m", overlap_m),
            "--noise-threshold": ("quality.noise_threshold_nT", noise_threshold),
            "--height-tolerance": ("quality.height_tolerance_m", height_tolerance),
        },
    )
    settings = cfg.quality_settings()
    with console.status(f"quality statistics of {recording.name}"):
        summary = quality_recording(recording, json_out, settings, out_path, cfg)
    _print_quality(summary["quality"])
    if out_path:
        say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


def _print_quality(q: dict) -> None:
    """The paper-002 table: heading error per processing state."""
    floor = q["heading_error_noise_floor_nT"]
    say(
        f"heading error, validation X lines vs map lines: {q['intersections']} intersections, "
        f"{q['overlap_pairs']} pairs < {q['overlap_m']:g} m; white-noise floor at the "
        f"intersections {'-' if floor is None else f'{floor:.3f} nT'}; headline "
        f"heading_error_rms_nT = {q.get('heading_error_method', 'intersections')}"
    )
    inter = q.get("intersection_rms_nT", q["heading_error_rms_nT"])
    table = Table(
        title="RMS of B_validation - B_map (pairs, interpolated map: paper 002's "
        "statistics; intersections: ours)",
        title_justify="left",
    )
    for col in ("state", "pairs RMS nT", "intersections RMS nT", "interpolated map RMS nT"):
        table.add_column(col, justify="left" if col == "state" else "right")

    def f(x):
        return "-" if x is None else f"{x:.3f}"

    for s in q["states"]:
        name = s + (" (= tl)" if q.get("tl_alias") and s == q["tl_alias"].replace("-", "_") else "")
        table.add_row(
            name, f(q["overlap_pair_rms_nT"][s]), f(inter[s]), f(q["interpolated_rms_nT"][s])
        )
    show(table)
    xo, n = q["crossover_rms_nT"], q["noise_4th_diff_nT"]
    say(
        f"crossovers: RMS {f(xo['before'])} -> {f(xo['after'])} nT after leveling; "
        f"4th-difference noise {f(n)} nT"
    )


@app.command()
def audit(
    recording: RecordingArg,
    json_out: Annotated[Path, typer.Option("--json", help="AUDIT.json to write.")],
    report: Annotated[
        Path, typer.Option("--report", help="Folder for report.md and the PNG figures.")
    ],
    out_path: Annotated[
        Path | None,
        typer.Option(
            "--out",
            help="Also write an output "
            "recording: /audit/finding, "
            "/aeromag/log, compensated "
            "fields.",
        ),
    ] = None,
    baseline: Annotated[
        str | None,
        typer.Option(help="Baseline T-L term set: tl18 or tl16 (config: audit.baseline)."),
    ] = None,
    alpha: Annotated[
        float | None,
        typer.Option(help="Significance level per round (Holm) (config: audit.alpha)."),
    ] = None,
    min_gain: Annotated[
        float | None,
        typer.Option(
            help="Smallest held-out RMS reduction an effect must bring (fraction) "
            "(config: audit.min_gain)."
        ),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Find what the baseline model gets wrong, name the cause, extend it, measure the gain
    (in the configured fit band)."""
    from flows.stages import audit_recording, require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--baseline": ("audit.baseline", baseline),
            "--alpha": ("audit.alpha", alpha),
            "--min-gain": ("audit.min_gain", min_gain),
        },
    )
    settings = cfg.audit_settings()
    with console.status(f"auditing {recording.name}") as status:
        j = audit_recording(
            recording,
            json_out,
            report,
            settings,
            out_path,
            progress=lambda m: status.update(f"auditing {recording.name}: {m}"),
            cfg=cfg,
        )
    _print_audit(j)
    if out_path:
        say(f"output recording: {out_path}")
    say(f"report: {j['report']['markdown']}")
    say(f"audit: {json_out}")


def _print_audit(j: dict) -> None:
    b = j["baseline"]
    say(
        f"baseline {b['model']}: held-out calibration residual {b['residual_rms_nT']:.4f} nT; "
        f"noise floor in the same band {j['band_noise_floor_nT']:.4f} nT; sensor noise "
        f"{j['noise_floor_nT']:.4f} nT per sample"
    )
    table = Table(title="findings", title_justify="left")
    for col in (
        "effect",
        "estimate",
        "delta BIC",
        "p (Holm)",
        "gain metric",
        "before nT",
        "after nT",
    ):
        table.add_column(
            col,
            justify="right"
            if col in ("delta BIC", "p (Holm)", "before nT", "after nT")
            else "left",
        )
    for f in j["findings"]:
        est = ", ".join(
            f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
            for k, v in f["estimate"].items()
            if k
            not in (
                "at_acceptance",
                "lag_by_fold_s",
                "direction_body",
                "mismatch_rms_before_nT",
                "mismatch_rms_after_nT",
            )
        )
        g = f["gain"] or {}
        table.add_row(
            f["effect"],
            est,
            f"{f['delta_bic']:.1f}",
            f"{f['p_value_holm']:.2g}",
            g.get("metric", "-"),
            f"{g.get('before_nT', 0):.4f}",
            f"{g.get('after_nT', 0):.4f}",
        )
    if j["findings"]:
        show(table)
    else:
        say("no finding: no candidate effect improves held-out data beyond noise")
    say(
        f"extended model: {' + '.join(j['extended_model'])}; unexplained (held-out) "
        f"{j['unexplained_rms_nT']:.4f} nT"
    )
    if (j.get("unexplained") or {}).get("note"):
        say(f"unexplained: {j['unexplained']['note']}")
    for k, v in j["gain"].items():
        if v["before"] is not None:
            say(f"gain {k}: {v['before']:.4f} -> {v['after']:.4f}")


@app.command()
def vector(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    method: Annotated[
        str | None,
        typer.Option(
            help="ellipsoid-kf (online hard/soft-iron "
            "calibration -> /mag/vector/calibrated), "
            "component-kf or batch (21-parameter "
            "compensation -> /mag/vector/compensated) "
            "(config: vector.method)"
        ),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Calibrate or compensate the vector magnetometer (papers 003 and 000)."""
    from flows.stages import require_readable, vector_recording

    require_readable(recording)
    cfg = _stage_config(config, {"--method": ("vector.method", method)})
    method = cfg["vector"]["method"]
    with console.status(f"vector stage ({method}) on {recording.name}"):
        summary = vector_recording(recording, out_path, json_out, method)
    v = summary["vector"]
    for k, val in v.items():
        if isinstance(val, dict) and "before" in val and not isinstance(val["before"], list):
            say(f"{k}: {val['before']:.2f} -> {val['after']:.2f} nT")
    say(f"{v['output_topic']} written to {out_path}")
    say(f"summary: {json_out}")


@app.command()
def navigate(
    recording: Annotated[
        Path, typer.Argument(help="Flight recording (.mcap), raw or processed: the true track.")
    ],
    map_path: Annotated[
        Path,
        typer.Option(
            "--map",
            help="Map: a processed recording (.mcap), a GeoTIFF / netCDF grid, or a MagNav "
            "HDF5 map (.h5).",
        ),
    ],
    json_out: Annotated[Path, typer.Option("--json", help="Navigation summary JSON to write.")],
    out_path: Annotated[
        Path | None,
        typer.Option("--out", help="Also write a copy of the recording with the /nav channels."),
    ] = None,
    filter_: Annotated[
        str, typer.Option("--filter", help="ekf, or pf (marginalised particle filter).")
    ] = "ekf",
    ins: Annotated[str, typer.Option(help="INS grade: navigation (~1 nmi/h) or tactical.")] = (
        "navigation"
    ),
    segments: Annotated[
        str,
        typer.Option(help="Segments navigated and scored: validation, survey (with ties) or all."),
    ] = "validation",
    seed: Annotated[int, typer.Option(help="Seed of the INS errors (and particles).")] = 0,
    map_channel: Annotated[
        str, typer.Option("--map-channel", help="Grid channel of a recording map.")
    ] = "/map/anomaly_filtered",
    config: ConfigOption = None,
) -> None:
    """Magnetic anomaly navigation on a map: simulate an INS along the recorded track, aid it
    with the map (EKF or particle filter), and score both against /gnss/fix and the CRLB."""
    from flows.stages import navigate_recording, require_readable
    from pipeline.navigation.stage import NavigationSettings

    require_readable(recording)
    require_readable(map_path)
    cfg = _stage_config(config, {})
    settings = NavigationSettings(filter=filter_, ins=ins, segments=segments, seed=seed)
    with console.status(f"navigating {recording.name} on {map_path.name} ({filter_})"):
        summary = navigate_recording(
            recording, map_path, json_out, settings, out_path, map_channel, cfg
        )
    nav = summary["navigation"]
    d, c = nav["drms_m"], nav["cep50_m"]
    say(
        f"{filter_} on {segments} ({nav['epochs']['selected']} epochs, {ins}-grade INS, "
        f"seed {seed}): DRMS INS-only {d['ins_only']:.1f} m, map-aided {d['map_aided']:.2f} m, "
        f"CRLB {d['crlb']:.2f} m; CEP50 {c['ins_only']:.1f} -> {c['map_aided']:.2f} m"
    )
    for note in nav["notes"]:
        say(f"note: {note}")
    if out_path:
        say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


def _run_postflight(recording: Path, out_dir: Path, config: Path | None = None) -> dict:
    from flows import stages

    _check_config(config)
    # bad input fails here, in one line, before Prefect starts a run (or a server)
    with console.status(f"checking {recording.name}"):
        stages.validate_recording(recording)
    from flows.postflight import postflight

    try:
        with console.status(f"processing {recording.name} (Prefect flow 'postflight')"):
            return postflight(str(recording), str(out_dir), str(config) if config else None)
    finally:
        stages.forget_validated()


@app.command()
def config() -> None:
    """Print the default processing configuration (every parameter, commented)."""
    from pipeline.config import default_text

    out.print(default_text(), markup=False, highlight=False, end="")


@app.command()
def process(
    recording: RecordingArg,
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")],
    config: ConfigOption = None,
) -> None:
    """Run the post-flight flow on one recording."""
    _say_outputs(_run_postflight(recording, out_dir, config))


@app.command()
def reprocess(
    archive: Annotated[Path, typer.Argument(help="Folder of recordings (searched recursively).")],
    out_dir: Annotated[
        Path, typer.Option("--out", help="Output folder (job folders, index, quarantine).")
    ],
    workers: Annotated[int, typer.Option(help="Dask worker processes of the local cluster.")] = 2,
    dask_address: Annotated[
        str | None, typer.Option(help="Use an existing Dask cluster, e.g. tcp://HOST:8786.")
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Reprocess an archive on Dask: only recordings without an output for this input and
    configuration; bad files are quarantined, an index lists everything."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from flows import archive as arch

    if not archive.is_dir():
        _fail(f"{archive}: not a folder")
    if workers < 1:
        _fail(f"--workers {workers}: must be >= 1")
    _check_config(config)
    with (
        arch.prefect_api(),
        Progress(
            "[progress.description]{task.description}",
            BarColumn(),
            MofNCompleteColumn(),
            TimeElapsedColumn(),
            console=console,
        ) as prog,
    ):
        bar = prog.add_task("recordings", total=None)

        def progress(done, total, row):
            prog.update(
                bar,
                completed=done,
                total=total,
                description=f"{Path(row['input']).name}: {row['status']}",
            )

        arch.PROGRESS = progress
        runner = arch.dask_runner(workers, dask_address)
        result = arch.reprocess_archive.with_options(task_runner=runner)(
            str(archive), str(out_dir), str(config) if config else None
        )
        arch.PROGRESS = None
    say(
        f"{result['recordings']} recordings: {result['processed']} processed, "
        f"{result['done']} already done, {result['quarantined']} quarantined"
    )
    say(f"index: {result['index']['csv']}")


@app.command()
def campaign(
    folder: Annotated[
        Path, typer.Argument(help="Folder of processed recordings (*.processed.mcap), searched.")
    ],
    out_dir: Annotated[
        Path,
        typer.Option("--out", help="Output folder (campaign.mcap, exports, report, summary)."),
    ],
    workers: Annotated[int, typer.Option(help="Dask worker processes of the local cluster.")] = 2,
    dask_address: Annotated[
        str | None, typer.Option(help="Use an existing Dask cluster, e.g. tcp://HOST:8786.")
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Merge the processed flights of one area (several days, base stations): level them
    jointly on every crossover within and between flights, grid once, export."""
    from flows import archive as arch
    from pipeline.campaign.sorties import validate_campaign

    if workers < 1:
        _fail(f"--workers {workers}: must be >= 1")
    _check_config(config)
    # bad input fails here, in one line, before Prefect starts a server or a cluster
    with console.status(f"checking {folder}"):
        infos = validate_campaign(folder)
    from flows.campaign import campaign as campaign_flow

    with (
        arch.prefect_api(),
        console.status(f"campaign of {len(infos)} flights (Prefect flow 'campaign' on Dask)"),
    ):
        runner = arch.dask_runner(workers, dask_address)
        try:
            doc = campaign_flow.with_options(task_runner=runner)(
                str(folder), str(out_dir), str(config) if config else None
            )
        finally:  # a failed run's logs reach the server before it stops (no "Error logging")
            from prefect.logging.handlers import APILogWorker

            APILogWorker.drain_all(timeout=5)
    r = doc["crossover_rms_nT"]

    def f(x) -> str:
        return "-" if x is None else f"{x:.3f}"

    say(
        f"{len(doc['flights'])} flights: "
        + ", ".join(f"{k} {v:+.3f} nT" for k, v in doc["flight_offsets_nT"].items())
    )
    say(
        f"crossover RMS within flights {f(r['within_flight']['before'])} -> "
        f"{f(r['within_flight']['after'])} nT ({doc['crossovers']['within_flight']}), "
        f"between flights {f(r['between_flights']['before'])} -> "
        f"{f(r['between_flights']['after'])} nT ({doc['crossovers']['between_flights']})"
    )
    for w in doc["warnings"]:
        say(f"warning: {w}")
    g = doc["grid"]
    say(f"grid: {g['shape'][0]} x {g['shape'][1]} cells of {g['cell_m']:.2f} m")
    o = doc["outputs"]
    say(f"output recording: {o['mcap']}")
    say(f"summary: {o['summary']}")
    say(f"report: {o['report']}")
    for fmt, paths in (doc.get("exports") or {}).items():
        say(f"export ({fmt}): {', '.join(paths)}")


@app.command()
def serve(
    watch: Annotated[Path, typer.Option("--watch", help="Folder new recordings appear in.")],
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")],
    cron: Annotated[
        str, typer.Option(help="When to look for new recordings (cron).")
    ] = "*/10 * * * *",
    name: Annotated[str, typer.Option(help="Deployment name.")] = "aeromag-watch",
    config: ConfigOption = None,
) -> None:
    """Register a scheduled deployment that processes recordings appearing in a folder
    (incomplete ones wait); runs until stopped (SIGTERM)."""
    from flows import archive as arch

    if not watch.is_dir():
        _fail(f"{watch}: not a folder")
    _check_config(config)
    out_dir.mkdir(parents=True, exist_ok=True)
    with arch.prefect_api() as url:
        say(
            f"serving deployment process-new-recordings/{name} ({cron}) on {url}: "
            f"{watch} -> {out_dir}"
        )
        arch.process_new.serve(
            name=name,
            cron=cron,
            print_starting_message=False,
            parameters={
                "watch_dir": str(watch.resolve()),
                "out_dir": str(out_dir.resolve()),
                "config_path": str(config.resolve()) if config else None,
            },
        )


@app.command()
def layout(
    file: Annotated[Path, typer.Argument(help="Processed MCAP recording (aeromag process).")],
    out_path: Annotated[Path, typer.Option("--out", help="Layout file to write (JSON).")],
) -> None:
    """Write a Foxglove layout for a processed recording: map with track and flight lines,
    raw / T-L / AGG-TL field and interference plots, segment labels, anomaly grids, audit log.

    Open the recording in Foxglove, then Layouts -> Import from file... -> this file.
    """
    from pipeline.io.writer import write_json_atomic
    from pipeline.products.layout import layout_panels, recording_layout

    doc = recording_layout(file)
    write_json_atomic(out_path, doc)
    say(
        f"layout: {out_path} ({len(layout_panels(doc['layout'], doc['configById']))} panels: "
        + ", ".join(k.split("!", 1)[0] for k in layout_panels(doc["layout"], doc["configById"]))
        + ")"
    )


@app.command()
def demo(
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("demo-output"),
    seed: Annotated[int, typer.Option(help="Random seed of the simulated flight.")] = 1,
) -> None:
    """Simulate the built-in demo flight, run the post-flight flow on it, print the outputs."""
    from pipeline.simulate import Scenario, write_simulation
    from pipeline.simulate import simulate as run

    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    flight_path, truth_path = out_dir / "demo_flight.mcap", out_dir / "demo_truth.json"
    sc = Scenario.load("demo")
    with console.status("simulating the demo flight (002-style UAV survey)"):
        sim = run(sc, seed)
        write_simulation(sim, flight_path, truth_path)
    say(
        f"simulated flight: {flight_path} ({sim.trajectory.duration_s / 60:.1f} min), "
        f"truth: {truth_path}"
    )
    result = _run_postflight(flight_path, out_dir)
    inp = result["input"]
    say(
        f"ingested {inp['epochs']} epochs, {len(inp['topics'])} channels, {inp['duration_s']:.0f} s"
    )
    _print_compensation(result)
    m = result.get("map")
    if m:
        say(
            f"map: {m['grid_shape'][0]} x {m['grid_shape'][1]} cells of {m['cell_m']:.1f} m; "
            f"crossover RMS {m['crossover_rms_nT']['before']:.3f} -> "
            f"{m['crossover_rms_nT']['after']:.3f} nT; ARIMA{tuple(m['arima_order'])} + "
            f"Kalman; figures in {Path(result['outputs']['mcap']).parent}"
        )
    if result.get("audit"):
        a = result["audit"]
        say(
            "audit: "
            + ("; ".join(f"{f['effect']} found" for f in a["findings"]) or "no finding")
            + f"; extended model {' + '.join(a['extended_model'])}"
        )
    if result.get("quality"):
        _print_quality(result["quality"])
    _say_outputs(result)
    say(f"done in {time.perf_counter() - t0:.1f} s")


def _say_outputs(result: dict) -> None:
    """Where the post-flight flow wrote its outputs."""
    o = result["outputs"]
    say(f"output recording: {o['mcap']}")
    say(f"summary: {o['summary']}")
    say(
        f"report: {o['report_html']} (open in a browser; Markdown: {o['report']}); "
        f"Foxglove layout: {o['layout']}"
    )
    for fmt, paths in (result.get("exports") or {}).items():
        say(f"export ({fmt}): {', '.join(paths)}")


def _print_compensation(result: dict) -> None:
    comp = result.get("compensation")
    if not comp:
        return
    table = Table(
        title="compensation (calibration FOM: sum of 12 box peak-to-peaks)", title_justify="left"
    )
    for col in (
        "model",
        "FOM raw nT",
        "FOM comp nT",
        "lambda",
        "fit resid nT",
        "cal resid nT",
        "survey resid nT",
        "gradient E/N/U nT/m",
    ):
        table.add_column(col, justify="left" if col == "model" else "right")

    def f(x, fmt=".3f"):
        return "-" if x is None else format(x, fmt)

    for m in ("tl16", "tl18", "agg-tl"):
        if m not in comp:
            continue
        r = comp[m]
        g = r.get("gradient_nT_per_m")
        table.add_row(
            m,
            f(r["fom_nT"]["uncompensated"], ".2f"),
            f(r["fom_nT"]["compensated"], ".2f"),
            f(r["lambda"], ".3g"),
            f(r["fit_residual_nT"], ".4f"),
            f(r["residual_std_nT"]["calibration"]),
            f(r["residual_std_nT"]["survey"]),
            "-" if not g else f"{g['east']:.3f}/{g['north']:.3f}/{g['up']:.3f}",
        )
    show(table)
    for m in ("tl16", "tl18", "agg-tl"):
        for w in ((comp.get(m) or {}).get("calibration_guards") or {}).get("warnings", []):
            say(f"warning: {w}")


def main() -> None:
    """Console-script entry point: one-line errors, never a traceback."""
    try:
        app()
    except AeromagError as exc:
        if os.environ.get("AEROMAG_DEBUG"):
            raise
        console.print(f"aeromag: error: {exc}", markup=False, highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        console.print("aeromag: interrupted")
        sys.exit(130)
    except Exception as exc:  # noqa: BLE001 - an internal bug still gets one line
        if os.environ.get("AEROMAG_DEBUG"):
            raise
        text = " ".join(str(exc).split())
        console.print(
            f"aeromag: internal error: {type(exc).__name__}: {text} "
            "(set AEROMAG_DEBUG=1 for the traceback)",
            markup=False,
            highlight=False,
            soft_wrap=True,
        )
        sys.exit(3)


if __name__ == "__main__":
    main()
