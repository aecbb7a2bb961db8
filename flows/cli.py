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


def emit(command: str, result: dict) -> None:
    """Print a command's result as :mod:`pipeline.products.console` words it (its
    ``<command>_text``): lines as they are, tables at their natural width."""
    from pipeline.products import console as text

    for b in getattr(text, f"{command}_text")(result):
        if not isinstance(b, text.TextTable):
            say(b)
            continue
        table = Table(title=b.title, title_justify=b.title_justify)
        for name, justify in b.columns:
            table.add_column(name, justify=justify)
        for row in b.rows:
            table.add_row(*row)
        show(table)


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
    from pipeline.io.mapping import Mapping
    from pipeline.io.mapping import import_mapped as run
    from pipeline.run.outputs import require_readable

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
        from pipeline.io.mapping import suggest_mapping as suggest
        from pipeline.run.outputs import require_readable

        require_readable(file)
        out.print(suggest(file), markup=False, highlight=False, end="")
        return

    rep = inspect_recording(file)
    d = rep.to_dict()
    emit("inspect", {**d, "file": str(file), "warnings": rep.warnings})
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


def _stage_config(config: Path | None, options: dict[str, tuple[str, object]]):
    """:func:`pipeline.run.commands.command_config`; a refused option exits 2 with one line."""
    from pipeline.run.commands import OptionError, command_config

    try:
        return command_config(config, options)
    except OptionError as exc:
        _fail(str(exc))


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
    from pipeline.run.commands import compensate_recording
    from pipeline.run.outputs import require_readable

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
    with console.status(f"compensating {recording.name}" + (f" ({model})" if model else "")):
        summary = compensate_recording(
            recording, out_path, json_out, cfg, calibration, scalar, vector
        )
    for w in (summary.get("calibration_guards") or {}).get("warnings", []):
        console.print(f"warning: {w}", markup=False, highlight=False, soft_wrap=True)
    emit("compensate", summary)
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
    from pipeline.run.commands import map_recording
    from pipeline.run.outputs import require_readable

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
    with console.status(f"mapping {recording.name}"):
        summary = map_recording(recording, out_path, json_out, cfg, lag)
    emit("map", summary["map"])
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
    from pipeline.export import check_formats, export_recording
    from pipeline.run.outputs import require_readable

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
    from pipeline.run.commands import enhance_recording
    from pipeline.run.outputs import require_readable

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
    emit("enhance", result)
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
    from pipeline.run.commands import quality_recording
    from pipeline.run.outputs import require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--overlap-m": ("quality.overlap_m", overlap_m),
            "--noise-threshold": ("quality.noise_threshold_nT", noise_threshold),
            "--height-tolerance": ("quality.height_tolerance_m", height_tolerance),
        },
    )
    with console.status(f"quality statistics of {recording.name}"):
        summary = quality_recording(recording, json_out, cfg, out_path)
    emit("quality", summary["quality"])
    if out_path:
        say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


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
    from pipeline.run.commands import audit_recording
    from pipeline.run.outputs import require_readable

    require_readable(recording)
    cfg = _stage_config(
        config,
        {
            "--baseline": ("audit.baseline", baseline),
            "--alpha": ("audit.alpha", alpha),
            "--min-gain": ("audit.min_gain", min_gain),
        },
    )
    with console.status(f"auditing {recording.name}") as status:
        j = audit_recording(
            recording,
            json_out,
            report,
            cfg,
            out_path,
            progress=lambda m: status.update(f"auditing {recording.name}: {m}"),
        )
    emit("audit", j)
    if out_path:
        say(f"output recording: {out_path}")
    say(f"report: {j['report']['markdown']}")
    say(f"audit: {json_out}")


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
    from pipeline.run.commands import vector_recording
    from pipeline.run.outputs import require_readable

    require_readable(recording)
    cfg = _stage_config(config, {"--method": ("vector.method", method)})
    method = cfg["vector"]["method"]
    with console.status(f"vector stage ({method}) on {recording.name}"):
        summary = vector_recording(recording, out_path, json_out, cfg)
    emit("vector", summary["vector"])
    say(f"{summary['vector']['output_topic']} written to {out_path}")
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
        str | None,
        typer.Option(
            "--filter", help="ekf, or pf (marginalised particle filter) (config: navigate.filter)."
        ),
    ] = None,
    ins: Annotated[
        str | None,
        typer.Option(
            help="INS: recorded (/ins/solution), navigation (~1 nmi/h) or tactical (simulated), "
            "auto: recorded when present (config: navigate.ins)."
        ),
    ] = None,
    segments: Annotated[
        str,
        typer.Option(help="Segments navigated and scored: validation, survey (with ties) or all."),
    ] = "validation",
    seed: Annotated[
        int | None,
        typer.Option(help="Seed of the INS errors (and particles) (config: navigate.seed)."),
    ] = None,
    map_channel: Annotated[
        str | None,
        typer.Option(
            "--map-channel", help="Grid channel of a recording map (config: /map/<navigate.map>)."
        ),
    ] = None,
    map_sigma: Annotated[
        float | None,
        typer.Option(
            "--map-sigma",
            help="The map's 1-sigma error, nT, everywhere (default: the map's /map/uncertainty "
            "when it has one, else navigate.map_sigma_nT).",
        ),
    ] = None,
    config: ConfigOption = None,
) -> None:
    """Magnetic anomaly navigation on a map: simulate an INS along the recorded track, aid it
    with the map (EKF or particle filter), and score both against /gnss/fix and the CRLB."""
    from pipeline.run.navigate import navigate_recording
    from pipeline.run.outputs import require_readable

    require_readable(recording)
    require_readable(map_path)
    cfg = _stage_config(config, {})
    with console.status(f"navigating {recording.name} on {map_path.name}"):
        summary = navigate_recording(
            recording,
            map_path,
            json_out,
            cfg,
            out_path,
            map_channel,
            filter=filter_,
            ins=ins,
            segments=segments,
            seed=seed,
            map_sigma_nT=map_sigma,
        )
    emit("navigate", summary["navigation"])
    if out_path:
        say(f"output recording: {out_path}")
    say(f"summary: {json_out}")


@app.command()
def navigability(
    recording: Annotated[Path, typer.Argument(help="Processed recording (.mcap) with its map.")],
    out_path: Annotated[Path, typer.Option("--out", help="Copy of it with /map/navigability.")],
    speed: Annotated[
        float | None,
        typer.Option(help="Vehicle speed, m/s (default: the recording's median ground speed)."),
    ] = None,
    heading: Annotated[
        str, typer.Option(help="Heading from grid north, deg, or all (four directions).")
    ] = "all",
    config: ConfigOption = None,
) -> None:
    """The position accuracy (CRLB, m) a vehicle reaches flying into each cell of the map."""
    import json

    from pipeline.run.navigate import navigability_recording
    from pipeline.run.outputs import require_readable

    require_readable(recording)
    cfg = _stage_config(config, {})
    with console.status(f"navigability of {recording.name}'s map"):
        result = navigability_recording(recording, out_path, cfg, speed, heading)
    say(json.dumps(result))
    say(f"output recording: {out_path}")


def _run_postflight(recording: Path, out_dir: Path, config: Path | None = None) -> dict:
    from flows import postflight as pf

    _check_config(config)
    # bad input fails here, in one line, before Prefect starts a run (or a server); the flow
    # takes over the flight read for the check
    with console.status(f"checking {recording.name}") as status, pf.checked(recording):
        status.update(f"processing {recording.name} (Prefect flow 'postflight')")
        return pf.postflight(str(recording), str(out_dir), str(config) if config else None)


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
    emit("outputs", _run_postflight(recording, out_dir, config))


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

        runner = arch.dask_runner(workers, dask_address)
        with arch.progress_to(progress):
            result = arch.reprocess_archive.with_options(task_runner=runner)(
                str(archive), str(out_dir), str(config) if config else None
            )
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
    emit("campaign", doc)


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
    emit("demo", _run_postflight(flight_path, out_dir))
    say(f"done in {time.perf_counter() - t0:.1f} s")


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
