"""The post-flight flow: ingest -> (stages added by later issues) -> write outputs.

Tasks are thin wrappers of ``pipeline`` functions; all logic lives there.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, task

from pipeline import __version__
from pipeline.io.reader import Flight, read_flight
from pipeline.io.writer import OutputChannel, write_json_atomic, write_with_new_channels
from pipeline.report import flight_summary, ingest_lines, log_channel, run_metadata


def output_paths(recording: str | Path, out_dir: str | Path) -> dict[str, Path]:
    stem = Path(recording).stem
    out = Path(out_dir)
    return {"mcap": out / f"{stem}.processed.mcap", "summary": out / f"{stem}.summary.json"}


@task(name="ingest")
def ingest(recording: str) -> Flight:
    return read_flight(recording)


@task(name="write-outputs")
def write_outputs(recording: str, out_dir: str, channels: list[OutputChannel],
                  summary: dict[str, Any]) -> dict[str, str]:
    paths = output_paths(recording, out_dir)
    write_with_new_channels(recording, paths["mcap"], channels,
                            metadata={"aeromag.run": run_metadata()})
    summary = {**summary, "outputs": {k: str(v) for k, v in paths.items()},
               "channels_written": sorted({c.topic for c in channels})}
    write_json_atomic(paths["summary"], summary)
    return {k: str(v) for k, v in paths.items()}


@flow(name="postflight", log_prints=False)
def postflight(recording: str, out_dir: str) -> dict[str, Any]:
    """Process one flight recording into an output MCAP and a summary JSON in ``out_dir``."""
    recording, out_dir = str(recording), str(out_dir)
    flight = ingest(recording)
    channels = [log_channel(flight, ingest_lines(flight), "ingest")]
    summary: dict[str, Any] = {"aeromag_version": __version__, "input": flight_summary(flight)}
    outputs = write_outputs(recording, out_dir, channels, summary)
    return {**summary, "outputs": outputs}
