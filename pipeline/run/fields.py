"""Which fields a run works on: the segmentation when the recording allows it, the
configured models this flight can fit, the compensated fields a recording already holds,
the field the map is made from and every state the quality stage compares.

Shared by the post-flight steps (:mod:`pipeline.run.steps`) and the single-stage commands
(:mod:`pipeline.run.commands`), so that both choose the same fields the same way.
"""

from __future__ import annotations

import numpy as np

from pipeline.compensate import FitSettings
from pipeline.compensate.stage import CompensationRun, run_compensation
from pipeline.config import Config
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.writer import OutputChannel
from pipeline.products.channels import compensated_channel, model_message
from pipeline.products.log import LOG_INFO, LOG_WARNING, compensation_lines
from pipeline.quality.stage import QualityRun, fom_table, run_quality
from pipeline.segment import Segmentation, segment_flight


def try_segment(flight: Flight) -> tuple[Segmentation | None, str]:
    """Segment when the recording allows it; otherwise say why not."""
    if not (flight.has("plan_kind") or flight.has("lat_deg", "lon_deg")):
        return None, "segmentation skipped: no /gnss/fix and no /plan/line"
    return segment_flight(flight), ""


def existing_compensated(flight: Flight) -> dict[str, np.ndarray]:
    """Compensated fields already in the recording (an earlier run), on the flight epochs.

    Returns model id -> nT per epoch, the final ``/mag/compensated`` model last.
    """
    from pipeline.io.contract import rule_for_topic
    from pipeline.io.reader import decode_topic, read_topics

    names = [
        t for t in flight.all_topics if t == "/mag/compensated" or t.startswith("/mag/compensated/")
    ]
    raw = read_topics(flight.source, names).topics if names else {}
    out: dict[str, np.ndarray] = {}
    t0 = flight.time_ns[0]
    for topic in sorted(raw, key=lambda t: (t == "/mag/compensated", t)):
        if not raw[topic].count:
            continue
        s = decode_topic(raw[topic], rule_for_topic(topic))
        if s.time_ns.size < 2:
            continue
        models = s.labels.get("model")
        name = str(models[0]) if models is not None and models.size else topic.rsplit("/", 1)[-1]
        out.pop(name, None)
        out[name] = np.interp(
            (flight.time_ns - t0) / 1e9,
            (s.time_ns - t0) / 1e9,
            s.values["total_nT"],
            left=np.nan,
            right=np.nan,
        )
    return out


def configured_models(flight: Flight, cfg: Config) -> list[str]:
    """The configuration's compensation models this flight can fit, in order (the last is
    the final one): AGG-TL needs positions."""
    return [
        m for m in cfg["compensation"]["models"] if m != "agg-tl" or flight.has("lat_deg", "alt_m")
    ]


def final_compensation(
    flight: Flight, seg: Segmentation, cfg: Config, stage: str
) -> tuple[np.ndarray, list[tuple[int, str]], list[OutputChannel], dict | None]:
    """The compensated field of a recording, the way the single-stage commands get it: its
    own ``/mag/compensated`` (an earlier run), else the configuration's final model this flight
    can fit, fitted with its settings as ``aeromag process`` does (no audit).

    Returns
    -------
    compensated_nT : ndarray
        Per epoch, nT.
    lines : list of (int, str)
        Log lines.
    channels : list of OutputChannel
        ``/mag/compensated`` and ``/compensation/model`` when fitted here (else empty).
    summary : dict or None
        The compensation summary when fitted here.
    """
    earlier = existing_compensated(flight)
    if earlier:
        return (
            list(earlier.values())[-1],
            [(LOG_INFO, f"{stage}: using /mag/compensated from the recording")],
            [],
            None,
        )
    models = configured_models(flight, cfg)
    if not models:
        raise AeromagError(
            "no configured compensation model fits this flight (agg-tl needs positions)",
            file=flight.source,
            channel="/gnss/fix",
        )
    run = run_compensation(flight, seg, cfg.fit_settings(models[-1]))
    return (
        run.compensated_nT,
        compensation_lines(run),
        [compensated_channel(flight, run), model_message(flight, run)],
        run.summary(),
    )


def final_field(runs: dict[str, CompensationRun], audit) -> tuple[str, np.ndarray] | None:
    """The field the map is made from: the audit's extended model when it found anything,
    else the last configured model."""
    if audit is not None and audit.findings:
        return "extended", audit.compensated["extended"]
    if runs:
        name = list(runs)[-1]
        return name, runs[name].compensated_nT
    return None


def compensable(flight: Flight, seg: Segmentation | None) -> bool:
    """Whether a compensation model can be fitted: a vector magnetometer and a calibration
    pass."""
    return seg is not None and flight.has("vector_x_nT") and seg.passes()


def uncompensated(flight: Flight) -> tuple[str, np.ndarray]:
    """``("raw", the scalar as recorded (despiked when the flight was), nT)``: what is mapped
    where nothing is :func:`compensable` (a towed bird, a stinger on a quiet carrier)."""
    return "raw", flight.data["scalar_nT"].to_numpy(float)


def mapped_field(flight: Flight, runs: dict[str, CompensationRun], audit) -> tuple[str, np.ndarray]:
    """The field the map is made from: :func:`final_field`, else :func:`uncompensated`: a
    survey flown without a vector magnetometer or a calibration pass still gets its map,
    said to be uncompensated."""
    final = final_field(runs, audit)
    return final if final is not None else uncompensated(flight)


def quality_fields(
    flight: Flight,
    seg: Segmentation,
    runs: dict[str, CompensationRun] | None = None,
    cfg: Config | None = None,
) -> tuple[dict[str, np.ndarray], list[tuple[int, str]], dict[str, CompensationRun]]:
    """Raw plus every compensated state: from ``runs``, else from the recording's own
    ``/mag/compensated*`` channels, else fitted here (the configuration's models with its
    settings, as ``aeromag process``; returned too)."""
    fields = {"raw": flight.data["scalar_nT"].to_numpy(float)}
    lines: list[tuple[int, str]] = []
    if runs is not None:  # the caller's runs (possibly none): never fitted here
        fields.update({m: r.compensated_nT for m, r in runs.items()})
        return fields, lines, {}
    earlier = existing_compensated(flight)
    if earlier:
        lines.append(
            (
                LOG_INFO,
                "quality: using the compensated fields in the recording: " + ", ".join(earlier),
            )
        )
        fields.update(earlier)
        return fields, lines, {}
    if not compensable(flight, seg):
        lines.append(
            (
                LOG_WARNING,
                "quality: no vector magnetometer or no calibration pass: "
                "only the raw field is assessed",
            )
        )
        return fields, lines, {}
    fitted = {}
    cfg = cfg or Config.load()
    for m in configured_models(flight, cfg):
        fitted[m] = run = run_compensation(flight, seg, cfg.fit_settings(m))
        lines += compensation_lines(run)
        fields[m] = run.compensated_nT
    return fields, lines, fitted


def tl_alias(fields: dict[str, np.ndarray], base: str | None = None) -> str | None:
    """The T-L model reported as ``tl``: the one with AGG-TL's term set ``base`` (None: the
    shipped ``compensation.agg_base``)."""
    base = base or FitSettings(model="agg-tl").base
    return base if base in fields else next((m for m in ("tl18", "tl16") if m in fields), None)


def fom_settings(cfg: Config) -> tuple[tuple[float, float], int]:
    """The band and filter order every FOM table of a run is measured in: the configured
    fit band (``compensation.band_hz``, ``poles``), as the compensation stage's own FOM."""
    c = cfg["compensation"]
    return tuple(c["band_hz"]), c["poles"]


def assess_quality(
    flight: Flight, seg: Segmentation, fields: dict[str, np.ndarray], cfg: Config
) -> QualityRun:
    """The quality stage on ``fields`` (``raw`` plus each compensated state, nT per epoch)
    with the configuration's settings, with the 12-box FOM table (in the configured fit band)
    when the calibration boxes were found.

    Returns
    -------
    QualityRun
    """
    t = flight.data["time_s"].to_numpy(float)
    fom = (
        fom_table(
            t,
            fields["raw"],
            {k: v for k, v in fields.items() if k != "raw"},
            seg.boxes(),
            *fom_settings(cfg),
        )
        if seg.boxes() and len(fields) > 1
        else None
    )
    return run_quality(
        flight,
        seg,
        fields,
        tl_alias(fields, cfg["compensation"]["agg_base"]),
        fom,
        cfg.quality_settings(),
    )
