"""The ``aeromag`` command line.

Every user error prints one line ``aeromag: error: FILE: CHANNEL: problem`` and exits with
code 2; nothing prints a traceback (set ``AEROMAG_DEBUG=1`` to see one). Commands that run a
flow import Prefect lazily so that ``inspect`` and ``simulate`` start instantly.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Annotated, get_type_hints

import typer
from rich.console import Console
from rich.table import Table

from pipeline.errors import AeromagError, user_error

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
    from pipeline.simulate import simulate_recording

    with console.status(f"simulating scenario {scenario} (seed {seed})"):
        emit("simulation", simulate_recording(scenario, seed, set_ or [], out_path, truth))


@import_app.command("sgl")
def import_sgl(
    file: Annotated[Path, typer.Argument(help="SGL / DAF-MIT MagNav flight file (.h5 or .xyz).")],
    out_path: Annotated[Path, typer.Option("--out", help="Recording to write (.mcap).")],
    lines: Annotated[
        str | None, typer.Option(help="Only these lines, e.g. 1002.02,1002.20.")
    ] = None,
    calibration_lines: Annotated[
        str | None, typer.Option(help="Lines flown as calibration boxes (kind=calibration).")
    ] = None,
) -> None:
    """Import an SGL HDF5 or XYZ file (field mapping in schemas/README.md)."""
    from pipeline.io.sgl import import_sgl as run

    with console.status(f"importing {file.name}"):
        res = run(file, out_path, _names(lines), _names(calibration_lines))
    say(
        f"{out_path}: {res['samples']} samples over {res['span_s']:.1f} s, "
        f"{len(res['channels'])} channels"
    )


@import_app.command("mapped")
def import_mapped(
    file: Annotated[Path, typer.Argument(help="A recorder's MCAP (ROS 2, protobuf, JSON).")],
    mapping: Annotated[
        Path, typer.Option(help="Topic mapping (TOML); `aeromag inspect --suggest-mapping`.")
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
        bool, typer.Option(help="Print a topic mapping (TOML) for ROS 2 / protobuf topics.")
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


Workers = Annotated[int, typer.Option(help="Dask worker processes of the local cluster.")]
DaskAddress = Annotated[
    str | None, typer.Option(help="Use an existing Dask cluster, e.g. tcp://HOST:8786.")
]


def _dask_checks(workers: int, config: Path | None) -> None:
    if workers < 1:
        _fail(f"--workers {workers}: must be >= 1")
    _check_config(config)


@contextlib.contextmanager
def _on_dask(workers: int, address: str | None):
    """A Prefect API and a Dask task runner for a flow over many recordings."""
    from flows import archive as arch

    with arch.prefect_api():
        yield arch.dask_runner(workers, address)


def setting(key: str, *decls: str, text: str | None = None, convert: Callable | None = None):
    """An option that overrides the configuration key ``key``; its help is the key's comment
    in the shipped defaults (one description of each setting) unless ``text`` is given.
    :func:`_stage_config` finds it in the command's signature; ``convert`` turns the typed
    value into the key's (one model into the list of models, say)."""
    from pipeline.defaults import default_comment

    text = text or default_comment(key)
    info = typer.Option(*decls, help=f"{text[0].upper()}{text[1:]} (config: {key}).")
    info.aeromag_setting = (key, convert)
    return info


def _check_config(config: Path | None) -> None:
    from pipeline.config import Config

    Config.load(config).validate()


def _stage_config(config: Path | None, command: Callable, given: dict, *inputs: Path):
    """A single-stage command's configuration (:func:`pipeline.run.commands.command_config`):
    each :func:`setting` option of ``command`` given in ``given`` overrides its key. The
    inputs are checked readable first; a refused value exits 2 with one line."""
    from pipeline.run.commands import OptionError, command_config
    from pipeline.run.outputs import require_readable

    for path in inputs:
        require_readable(path)
    options = {}
    for name, hint in get_type_hints(command, include_extras=True).items():
        for info in getattr(hint, "__metadata__", ()):
            if (found := getattr(info, "aeromag_setting", None)) is None:
                continue
            key, convert = found
            flags = [d.split("/")[0] for d in info.param_decls if d.startswith("--")]
            value = given[name]
            value = convert(value) if convert is not None and value is not None else value
            options[flags[0] if flags else "--" + name.replace("_", "-")] = (key, value)
    try:
        return command_config(config, options)
    except OptionError as exc:
        _fail(str(exc))


def _written(out_path: Path | None, json_out: Path | None = None) -> None:
    if out_path:
        say(f"output recording: {out_path}")
    if json_out:
        say(f"summary: {json_out}")


def _ridge(value: str) -> object:
    try:
        return value if value == "auto" else float(value)
    except ValueError:
        return value  # the configuration's check names it


def _names(value: str | None) -> list[str] | None:
    return [p.strip() for p in value.split(",") if p.strip()] if value else None


@app.command()
def compensate(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    model: Annotated[
        str | None,
        setting(
            "compensation.models",
            text="tl16 | tl18 | agg-tl | tl-plus | tl-nn (default: the configuration's final "
            "model the recording can fit, as `aeromag process`)",
            convert=lambda m: [m],
        ),
    ] = None,
    agg_base: Annotated[str | None, setting("compensation.agg_base")] = None,
    band: Annotated[tuple[float, float] | None, setting("compensation.band_hz")] = None,
    poles: Annotated[int | None, setting("compensation.poles")] = None,
    trim_s: Annotated[float | None, setting("compensation.trim_s", "--trim-s")] = None,
    ridge: Annotated[str | None, setting("compensation.ridge", convert=_ridge)] = None,
    calibration: Annotated[
        str, typer.Option(help="auto | all | T0:T1 (seconds from the first epoch, or Unix seconds)")
    ] = "auto",
    scalar: Annotated[str | None, typer.Option(help="Scalar magnetometer topic.")] = None,
    vector: Annotated[str | None, typer.Option(help="Vector magnetometer topic.")] = None,
    config: ConfigOption = None,
) -> None:
    """Fit a T-L / AGG-TL model, compensate the scalar field, write channels and a summary."""
    from pipeline.run.commands import compensate_recording

    cfg = _stage_config(config, compensate, locals(), recording)
    with console.status(f"compensating {recording.name}" + (f" ({model})" if model else "")):
        summary = compensate_recording(
            recording, out_path, json_out, cfg, calibration, scalar, vector
        )
    for w in (summary.get("calibration_guards") or {}).get("warnings", []):
        console.print(f"warning: {w}", markup=False, highlight=False, soft_wrap=True)
    emit("compensate", summary)
    _written(out_path, json_out)


@app.command("map")
def map_(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    cell: Annotated[float | None, setting("map.cell_m")] = None,
    arima: Annotated[str | None, setting("map.arima")] = None,
    noise: Annotated[float | None, setting("map.noise_nT")] = None,
    level_trend: Annotated[
        bool | None, setting("map.level_trend", "--level-trend/--no-level-trend")
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

    cfg = _stage_config(config, map_, locals(), recording)
    with console.status(f"mapping {recording.name}"):
        summary = map_recording(recording, out_path, json_out, cfg, lag)
    emit("map", summary["map"])
    _written(out_path, json_out)


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
    chosen = check_formats(_names(formats) or [], "--format")
    with console.status(f"exporting {recording.name}"):
        written = export_recording(recording, out_dir, chosen)
    for fmt, paths in written.items():
        for p in paths:
            say(f"{fmt}: {p}")


@app.command()
def enhance(
    recording: ProcessedArg,
    out_path: OutRecording,
    products: Annotated[str | None, setting("enhance.products", convert=_names)] = None,
    source: Annotated[str | None, setting("enhance.source")] = None,
    config: ConfigOption = None,
) -> None:
    """Map enhancements (harmonica): reduction to the pole, vertical and total horizontal
    derivatives, tilt angle, analytic signal, upward continuation -> /map/* grid channels."""
    from pipeline.run.commands import enhance_recording

    cfg = _stage_config(config, enhance, locals(), recording)
    with console.status(f"enhancing {recording.name}"):
        result = enhance_recording(recording, out_path, cfg)
    emit("enhance", result)
    _written(out_path)


@app.command()
def quality(
    recording: Annotated[Path, typer.Argument(help="Flight recording (.mcap), raw or processed.")],
    json_out: Annotated[
        Path, typer.Option("--json", help="Summary JSON to write (plots are written next to it).")
    ],
    overlap_m: Annotated[float | None, setting("quality.overlap_m", "--overlap-m")] = None,
    out_path: Annotated[
        Path | None,
        typer.Option("--out", help="Also write an output recording with the quality channels."),
    ] = None,
    noise_threshold: Annotated[float | None, setting("quality.noise_threshold_nT")] = None,
    height_tolerance: Annotated[float | None, setting("quality.height_tolerance_m")] = None,
    config: ConfigOption = None,
) -> None:
    """Heading error at overlap points, interpolated-map comparison, crossovers and survey QC
    (runs segmentation, the configured compensation models and gridding itself when needed)."""
    from pipeline.run.commands import quality_recording

    cfg = _stage_config(config, quality, locals(), recording)
    with console.status(f"quality statistics of {recording.name}"):
        summary = quality_recording(recording, json_out, cfg, out_path)
    emit("quality", summary["quality"])
    _written(out_path, json_out)


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
            help="Also write an output recording: /audit/finding, /aeromag/log, compensated "
            "fields.",
        ),
    ] = None,
    baseline: Annotated[str | None, setting("audit.baseline")] = None,
    alpha: Annotated[float | None, setting("audit.alpha")] = None,
    min_gain: Annotated[float | None, setting("audit.min_gain")] = None,
    config: ConfigOption = None,
) -> None:
    """Find what the baseline model gets wrong, name the cause, extend it, measure the gain
    (in the configured fit band)."""
    from pipeline.run.commands import audit_recording

    cfg = _stage_config(config, audit, locals(), recording)
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
    _written(out_path)
    say(f"report: {j['report']['markdown']}")
    say(f"audit: {json_out}")


@app.command()
def vector(
    recording: RecordingArg,
    out_path: OutRecording,
    json_out: SummaryJson,
    method: Annotated[str | None, setting("vector.method")] = None,
    config: ConfigOption = None,
) -> None:
    """Calibrate or compensate the vector magnetometer (papers 003 and 000)."""
    from pipeline.run.commands import vector_recording

    cfg = _stage_config(config, vector, locals(), recording)
    with console.status(f"vector stage ({cfg['vector']['method']}) on {recording.name}"):
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
    filter_: Annotated[str | None, setting("navigate.filter", "--filter")] = None,
    ins: Annotated[str | None, setting("navigate.ins")] = None,
    segments: Annotated[
        str,
        typer.Option(help="Segments navigated and scored: validation, survey (with ties) or all."),
    ] = "validation",
    seed: Annotated[int | None, setting("navigate.seed")] = None,
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

    cfg = _stage_config(config, navigate, locals(), recording, map_path)
    with console.status(f"navigating {recording.name} on {map_path.name}"):
        options = {"segments": segments, "map_sigma_nT": map_sigma}
        summary = navigate_recording(
            recording, map_path, json_out, cfg, out_path, map_channel, **options
        )
    emit("navigate", summary["navigation"])
    _written(out_path, json_out)


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
    from pipeline.run.navigate import navigability_recording

    cfg = _stage_config(config, navigability, locals(), recording)
    with console.status(f"navigability of {recording.name}'s map"):
        result = navigability_recording(recording, out_path, cfg, speed, heading)
    emit("navigability", result)
    _written(out_path)


def _run_postflight(recording: Path, out_dir: Path, config: Path | None = None) -> dict:
    from flows import archive as arch
    from flows import postflight as pf

    _check_config(config)
    # bad input fails here, in one line, before Prefect starts a run; a temporary server
    # starts while the recording is read, and the flow takes over the flight read
    with (
        console.status(f"checking {recording.name}") as status,
        arch.prefect_api(meanwhile=lambda: pf.checked(recording, out_dir)),
    ):
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
    emit("postflight", _run_postflight(recording, out_dir, config))


@app.command()
def reprocess(
    archive: Annotated[Path, typer.Argument(help="Folder of recordings (searched recursively).")],
    out_dir: Annotated[
        Path, typer.Option("--out", help="Output folder (job folders, index, quarantine).")
    ],
    workers: Workers = 2,
    dask_address: DaskAddress = None,
    config: ConfigOption = None,
) -> None:
    """Reprocess an archive on Dask: only recordings without an output for this input and
    configuration; bad files are quarantined, an index lists everything."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    from flows import archive as arch

    if not archive.is_dir():
        _fail(f"{archive}: not a folder")
    _dask_checks(workers, config)
    columns = ("{task.description}", BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
    with _on_dask(workers, dask_address) as runner, Progress(*columns, console=console) as prog:
        bar = prog.add_task("recordings", total=None)

        def progress(done, total, row):
            name = f"{Path(row['input']).name}: {row['status']}"
            prog.update(bar, completed=done, total=total, description=name)

        with arch.progress_to(progress):
            result = arch.reprocess_archive.with_options(task_runner=runner)(
                str(archive), str(out_dir), str(config) if config else None
            )
    emit("reprocess", result)


@app.command()
def campaign(
    folder: Annotated[
        Path, typer.Argument(help="Folder of processed recordings (*.processed.mcap), searched.")
    ],
    out_dir: Annotated[
        Path,
        typer.Option("--out", help="Output folder (campaign.mcap, exports, report, summary)."),
    ],
    workers: Workers = 2,
    dask_address: DaskAddress = None,
    config: ConfigOption = None,
) -> None:
    """Merge the processed flights of one area (several days, base stations): level them
    jointly on every crossover within and between flights, grid once, export."""
    from pipeline.campaign.sorties import validate_campaign

    _dask_checks(workers, config)
    # bad input fails here, in one line, before Prefect starts a server or a cluster
    with console.status(f"checking {folder}"):
        infos = validate_campaign(folder)
    from flows.campaign import campaign as campaign_flow

    with (
        _on_dask(workers, dask_address) as runner,
        console.status(f"campaign of {len(infos)} flights (Prefect flow 'campaign' on Dask)"),
    ):
        doc = campaign_flow.with_options(task_runner=runner)(
            str(folder), str(out_dir), str(config) if config else None
        )
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
    from pipeline.products.layout import write_layout

    panels = write_layout(file, out_path)
    say(f"layout: {out_path} ({len(panels)} panels: {', '.join(panels)})")


@app.command()
def demo(
    out_dir: Annotated[Path, typer.Option("--out", help="Output folder.")] = Path("demo-output"),
    seed: Annotated[int, typer.Option(help="Random seed of the simulated flight.")] = 1,
) -> None:
    """Simulate the built-in demo flight, run the post-flight flow on it, print the outputs."""
    from pipeline.simulate import simulate_recording

    t0 = time.perf_counter()
    out_dir.mkdir(parents=True, exist_ok=True)
    with console.status("simulating the demo flight (002-style UAV survey)"):
        sim = simulate_recording(
            "demo", seed, [], out_dir / "demo_flight.mcap", out_dir / "demo_truth.json"
        )
    say(f"simulated flight: {sim['out']} ({sim['duration_s'] / 60:.1f} min), truth: {sim['truth']}")
    emit("postflight", _run_postflight(Path(sim["out"]), out_dir))
    say(f"done in {time.perf_counter() - t0:.1f} s")


def _exit(message: str, code: int) -> None:
    console.print(message, markup=False, highlight=False, soft_wrap=True)
    sys.exit(code)


def main() -> None:
    """Console-script entry point: one-line errors, never a traceback."""
    try:
        app()
    except KeyboardInterrupt:
        _exit("aeromag: interrupted", 130)
    except Exception as exc:  # noqa: BLE001 - an internal bug still gets one line
        if os.environ.get("AEROMAG_DEBUG"):
            raise
        if isinstance(exc := user_error(exc), AeromagError):
            _exit(f"aeromag: error: {exc}", 2)
        text = " ".join(str(exc).split())
        why = f"{type(exc).__name__}: {text} (set AEROMAG_DEBUG=1 for the traceback)"
        _exit(f"aeromag: internal error: {why}", 3)


if __name__ == "__main__":
    main()
