"""The post-flight steps in order, as one plain function.

ingest -> despike (the scalar magnetometer) -> segment -> compensate (each configured T-L
model and AGG-TL) -> audit -> extended model -> vector stage (when a fluxgate exists) ->
anomaly reduction, leveling, gridding, ARIMA-Kalman filter -> quality -> navigation on the
flight's own map (validation lines, ``[navigate]``) -> navigability of that map (``[navigate]
navigability``) -> write (output MCAP, summary JSON,
report, figures).

:func:`postflight_steps` calls each stage through a ``call`` hook: ``flows/postflight.py``
passes Prefect tasks (persisted, resumable), :func:`run_plain` (archive workers, benchmarks)
plain calls.
"""

from __future__ import annotations

import hashlib
import importlib.util
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from pipeline.compensate.plus import audit_nuisances
from pipeline.config import Config
from pipeline.despike import repaired_flight
from pipeline.flight import Flight
from pipeline.io.reader import read_flight
from pipeline.maps.stage import map_refusal
from pipeline.products.summary import sha256_file
from pipeline.run import steps
from pipeline.run.fields import compensable, configured_models, mapped_field, try_segment
from pipeline.run.outputs import require_readable, require_writable, write_outputs


@dataclass(frozen=True)
class Step:
    """One stage of the post-flight flow: its name (the Prefect task's name and cache key)
    and the function that runs it."""

    name: str
    function: Callable[..., Any]


INGEST = Step("ingest", steps.ingest_stage)
DESPIKE = Step("despike", steps.despike_step)
SEGMENT = Step("segment", try_segment)
COMPENSATE = Step("compensate", steps.compensate_stage)
AUDIT = Step("audit", steps.audit_stage)
VECTOR = Step("vector", steps.vector_stage)
MAP = Step("map", steps.map_stage)
QUALITY = Step("quality", steps.quality_stage)
NAVIGATE = Step("navigate", steps.navigate_stage)
NAVIGABILITY = Step("navigability", steps.navigability_stage)
WRITE = Step("write", write_outputs)
STEPS = (
    INGEST,
    DESPIKE,
    SEGMENT,
    COMPENSATE,
    AUDIT,
    VECTOR,
    MAP,
    QUALITY,
    NAVIGATE,
    NAVIGABILITY,
    WRITE,
)


def postflight_steps(
    recording: str,
    out_dir: str,
    cfg: Config,
    call: Callable[..., Any],
    flight: Flight | None = None,
    read_s: float = 0.0,
) -> dict[str, Any]:
    """Every stage in order; ``call(step, *args)`` runs one :class:`Step` (see the module
    docstring): ``step.function(*args)``, or a Prefect task around it.

    ``flight``: the recording already read (and checked) by the caller, ``read_s`` seconds
    it took; None: the ingest step reads it. The seconds of each stage (summed over calls:
    ``compensate`` covers every model) go to the write stage, which puts them in the
    summary (``timings_s``).
    """
    timings: dict[str, float] = {"ingest": read_s}
    plain_call = call

    def call(step: Step, *args):
        t0 = time.perf_counter()
        try:
            return plain_call(step, *args)
        finally:
            timings[step.name] = timings.get(step.name, 0.0) + time.perf_counter() - t0

    if flight is None:
        flight = call(INGEST, recording)
    despiked = None
    if cfg["despike"]["enabled"]:  # every later stage sees the despiked scalar
        despiked = call(DESPIKE, flight, cfg)
        flight = repaired_flight(flight, despiked)
    seg, why = call(SEGMENT, flight)
    res = steps.FlightResults(flight, seg, why, despiked=despiked)
    if compensable(flight, seg):
        for m in configured_models(flight, cfg):
            res.runs[m] = call(COMPENSATE, flight, seg, m, cfg)
        if cfg["audit"]["enabled"]:
            res.audit = call(AUDIT, flight, seg, cfg)
            # the audit's "extend the model" step: nuisances it found become tl-plus's first
            # candidate groups (the key is absent from audits that name none)
            audit_json = res.audit.to_json() if res.audit is not None else None
            if "tl-plus" in res.runs and audit_nuisances(audit_json):
                res.runs["tl-plus"] = call(COMPENSATE, flight, seg, "tl-plus", cfg, audit_json)
    if cfg["vector"]["enabled"] and flight.has("vector_x_nT", "roll_deg"):
        res.vector = call(VECTOR, flight, seg, cfg)
    final = mapped_field(flight, res.runs, res.audit)  # the raw scalar without a model
    res.map_skipped = map_refusal(flight, seg) or ""
    if not res.map_skipped:
        res.map_run = call(MAP, flight, seg, final[1], cfg, final[0])
        res.quality = call(QUALITY, flight, seg, res.runs, res.audit, cfg)
    no_map = f"no map ({res.map_skipped})"
    if cfg["navigate"]["enabled"]:  # skipped (one log line) without validation lines or map
        res.nav = (
            call(NAVIGATE, flight, seg, final[1], res.map_run, cfg)
            if res.map_run is not None
            else no_map
        )
    if cfg["navigate"]["navigability"]:  # needs the map only, not validation lines
        res.navigability = (
            call(NAVIGABILITY, flight, final[1], res.map_run, cfg)
            if res.map_run is not None
            else no_map
        )
    return call(WRITE, recording, out_dir, cfg, res, timings)


def run_plain(recording: str, out_dir: str, config_path: str | None = None) -> dict[str, Any]:
    """The post-flight steps without Prefect (archive workers, benchmarks).

    Returns
    -------
    dict
        The summary.
    """
    cfg = Config.load(config_path)
    cfg.validate()
    return postflight_steps(
        str(recording), str(out_dir), cfg, lambda step, *args: step.function(*args)
    )


# The flight the CLI read to check a recording before the flow (the recording's stat key,
# the flight, seconds to read it): set only inside :func:`checked`, so the flow it starts
# does not read the recording twice.
_CHECKED: ContextVar[tuple[tuple, Flight, float] | None] = ContextVar(
    "aeromag_checked_flight", default=None
)


def _stat_key(recording: str | Path) -> tuple:
    st = Path(recording).stat()
    return str(Path(recording).resolve()), st.st_size, st.st_mtime_ns


@contextmanager
def checked(recording: str | Path, out_dir: str | Path | None = None) -> Iterator[Flight]:
    """Read and check a recording (scan, channel contract, units) and that ``out_dir`` can
    be written before any flow starts, so that bad input fails with one line and no Prefect
    run at all; a :func:`postflight` run on the same, unchanged file inside the block takes
    this flight over.

    Raises
    ------
    AeromagError
        Missing, empty or unreadable file, no scalar magnetometer, wrong units; an output
        folder that cannot be made or written.
    """
    require_readable(Path(recording))
    if out_dir is not None:
        require_writable(Path(out_dir), folder=True)
    t0 = time.perf_counter()
    flight = read_flight(recording)
    token = _CHECKED.set((_stat_key(recording), flight, time.perf_counter() - t0))
    try:
        yield flight
    finally:
        _CHECKED.reset(token)


def take_checked(recording: str) -> tuple[Flight | None, float]:
    """The flight :func:`checked` read and its read time (s), when ``recording`` is that
    same, unchanged file; else None and 0."""
    found = _CHECKED.get()
    if found is None:
        return None, 0.0
    try:
        same = found[0] == _stat_key(recording)
    except OSError:
        return None, 0.0
    return (found[1], found[2]) if same else (None, 0.0)


@cache
def code_fingerprint() -> str:
    """Hash of the installed pipeline and flow code: resumable results of one version are
    never unpickled into another (a stage's objects change shape between versions)."""
    h = hashlib.sha256()
    flows = importlib.util.find_spec("flows")  # located, not imported (it imports Prefect)
    roots = [Path(__file__).parents[1]]
    roots += [Path(p) for p in (flows.submodule_search_locations or [])] if flows else []
    for root in roots:
        for p in sorted(root.rglob("*.py")):
            h.update(p.read_bytes())
    return h.hexdigest()[:12]


def run_key(recording: str, cfg: Config) -> str:
    """Cache folder name of one recording, configuration and code version."""
    return f"{sha256_file(recording)[:16]}-{cfg.hash[:16]}-{code_fingerprint()}"
