"""The run's log: ``/aeromag/log`` (foxglove.Log) messages and the ingest lines."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.flight import Flight
from pipeline.io.writer import OutputChannel
from pipeline.products.markdown import uncompensated_map_note

if TYPE_CHECKING:
    from pipeline.compensate.stage import CompensationRun
    from pipeline.despike import DespikeResult
    from pipeline.quality.stage import QualityRun

LOG_TOPIC = "/aeromag/log"
LOG_INFO, LOG_WARNING = 2, 3  # foxglove.Log levels


def log_channel(flight: Flight, lines: list[tuple[int, str]], stage: str) -> OutputChannel:
    """foxglove.Log messages (``/aeromag/log``), stamped at the flight's first epoch.

    ``lines`` are (level, text) pairs.
    """
    ch = OutputChannel(LOG_TOPIC, "foxglove.Log")
    t0 = int(flight.time_ns[0])
    for k, (level, text) in enumerate(lines):
        # one ns apart keeps the viewer's order equal to the report's order
        ch.add(
            t0 + k,
            {"level": level, "message": text, "name": f"aeromag.{stage}", "file": "", "line": 0},
        )
    return ch


def ingest_lines(flight: Flight) -> list[tuple[int, str]]:
    """What ingest found: streams, rates, alignment and problems."""
    lines = [
        (
            LOG_INFO,
            f"ingest: {flight.source.name}: {len(flight.time_ns)} epochs on "
            f"{flight.topic_of['scalar']} over {flight.data['time_s'].iloc[-1]:.1f} s",
        )
    ]
    for topic, s in sorted(flight.series.items()):
        lines.append(
            (
                LOG_INFO,
                f"ingest: {topic} ({s.rule.schema_name}): {s.time_ns.size} "
                f"samples at {s.rate_hz:.2f} Hz",
            )
        )
    for t in flight.unknown_topics:
        lines.append((LOG_INFO, f"ingest: {t}: outside the channel contract, copied unchanged"))
    for note in flight.notes:
        lines.append((LOG_WARNING, f"ingest: {note}"))
    return lines


def compensation_lines(run: CompensationRun) -> list[tuple[int, str]]:
    """Log lines of a compensation run: terms, lambda, fit residual and FOM (nT), the
    AGG-TL gradient (nT/m, east / north / up) and the calibration warnings.

    Returns
    -------
    list of (int, str)
        ``(level, text)`` pairs.
    """
    m = run.model
    fom = run.fom.total if run.fom else None
    text = (
        f"compensate: {m.model}: {len(m.terms)} terms, lambda {m.lambda_:.3g}, "
        f"{m.n_fit} samples, fit residual {m.fit_residual_nT:.4f} nT"
    )
    if fom and fom["uncompensated"] is not None:
        text += f", FOM {fom['uncompensated']:.2f} -> {fom['compensated']:.2f} nT"
    lines = [(LOG_INFO, text)]
    g = m.gradient_nT_per_m()
    if g:
        lines.append(
            (
                LOG_INFO,
                f"compensate: {m.model}: gradient at the calibration site "
                f"{g['east']:.3f} E, {g['north']:.3f} N, {g['up']:.3f} U nT/m",
            )
        )
    if run.check is not None:
        lines += [
            (LOG_WARNING, f"compensate: calibration warning: {w}") for w in run.check.warnings
        ]
    return lines


def despike_lines(res: DespikeResult | None) -> list[tuple[int, str]]:
    """Log line of the despike step: spikes found (count, fraction, largest, nT)."""
    if res is None:
        return []
    s = res.summary()
    text = (
        f"despike: {s['spikes']} spikes ({100 * s['fraction']:.3f} % of samples) above "
        f"{s['threshold_sigma']:g} sigma of the 4th difference; noise {s['noise_nT']:.4f} nT"
    )
    if s["spikes"]:
        text += f", largest {s['max_abs_amplitude_nT']:.2f} nT"
    if s["steps_left"]:
        text += f"; {s['steps_left']} level steps left alone"
    return [(LOG_WARNING if s["fraction"] > 0.01 else LOG_INFO, text)]


def _map_crossovers(s: dict) -> str:
    """The map summary's crossover line; a survey without crossing lines has none."""
    xo = s["crossover_rms_nT"]
    if xo["before"] is None or xo["after"] is None:
        return "map: no crossovers (no lines cross): not levelled on crossovers"
    return (
        f"map: crossover RMS {xo['before']:.3f} -> {xo['after']:.3f} nT "
        f"({s['leveling']['crossovers']} crossovers)"
    )


def map_lines(mr) -> list[tuple[int, str]]:
    """Log lines of a map run: grid size and cell (m), crossover RMS before and after
    leveling (nT), ARIMA order and coefficients, Kalman measurement noise (nT).

    Returns
    -------
    list of (int, str)
        ``(level, text)`` pairs.
    """
    s = mr.summary()
    o = s["origin"]  # a survey across UTM zones gridded in one of them: said as a warning
    spans = len(o["utm_zones_spanned"]) > 1 and not o["crs_choice"].endswith("map.crs")
    out = [(LOG_WARNING, f"map: {uncompensated_map_note()}")] if s.get("field") == "raw" else []
    out += [
        (LOG_WARNING if spans else LOG_INFO, f"map: gridded in {s['origin']['crs_choice']}"),
        (
            LOG_INFO,
            f"map: grid {s['grid_shape'][0]} x {s['grid_shape'][1]} cells of "
            f"{s['cell_m']:.2f} m, line spacing {s['line_spacing_m']:.1f} m",
        ),
        (LOG_INFO, _map_crossovers(s)),
        (
            LOG_INFO,
            f"map: ARIMA{tuple(s['arima_order'])} "
            f"ar {np.round(s['arima_coefficients']['ar'], 4).tolist()} "
            f"ma {np.round(s['arima_coefficients']['ma'], 4).tolist()}; "
            f"Kalman measurement noise {s['kalman']['measurement_noise_nT']:.3f} nT",
        ),
    ]
    return out + microlevel_lines(s["microlevel"])


def microlevel_lines(m: dict[str, Any]) -> list[tuple[int, str]]:
    """Log line of the micro-levelling (the map summary's ``microlevel`` block): the
    corrugation removed (RMS of the correction, nT), its largest value and the grid change.

    Returns
    -------
    list of (int, str)
        One ``(level, text)`` pair, none when micro-levelling was off.
    """
    if not m.get("enabled"):
        return []
    return [
        (
            LOG_INFO,
            f"map: micro-levelling removed {m['correction_rms_nT']:.3f} nT RMS of corrugation "
            f"(max {m['correction_max_abs_nT']:.3f} nT, {100 * m['clipped_fraction']:.1f} % "
            f"clipped at {m['clip_nT']:g} nT; cut-off {m['wavelength_m']:.0f} m across, "
            f"{m['along_m']:.0f} m along); grid changed {m['grid_change_rms_nT']:.3f} nT RMS",
        )
    ]


def quality_lines(q: QualityRun) -> list[tuple[int, str]]:
    """Log lines of a quality run: heading-error RMS (nT) at intersections, overlap pairs
    and against the interpolated map, crossover RMS, noise and QC checks out of tolerance.

    Returns
    -------
    list of (int, str)
        ``(level, text)`` pairs (warnings for failed checks).
    """
    s = q.summary()

    def row(d):
        return ", ".join(f"{k} {v:.3f}" if v is not None else f"{k} -" for k, v in d.items())

    out = [
        (
            LOG_INFO,
            f"quality: heading error RMS at {s['overlap_pairs']} pairs closer than "
            f"{s['overlap_m']:g} m (paper 002's statistic, nT): "
            f"{row(s['overlap_pair_rms_nT'])}",
        ),
        (
            LOG_INFO,
            f"quality: heading error RMS at {s['intersections']} track "
            f"intersections (ours, nT): {row(s['intersection_rms_nT'])}",
        ),
        (LOG_INFO, f"quality: headline heading_error_rms_nT = {s['heading_error_method']}"),
        (
            LOG_INFO,
            f"quality: validation vs interpolated map RMS (nT): {row(s['interpolated_rms_nT'])}",
        ),
    ]
    xo = s["crossover_rms_nT"]
    if xo["before"] is not None:
        out.append(
            (
                LOG_INFO,
                f"quality: crossover RMS {xo['before']:.3f} -> {xo['after']:.3f} "
                f"nT ({s['crossovers']['count']} crossovers)",
            )
        )
    qc = s["qc"]
    noise = qc["noise"]
    if noise.get("median_nT") is not None:
        out.append(
            (
                LOG_WARNING if noise["lines_over"] else LOG_INFO,
                f"quality: 4th-difference noise median {noise['median_nT']:.4f} nT, max "
                f"{noise['max_nT']:.4f} nT; lines over {noise['threshold_nT']:g} nT: "
                f"{', '.join(noise['lines_over']) or 'none'}",
            )
        )
    for key, what in (
        ("flight_height", "lines_over"),
        ("line_spacing", "pairs_over"),
        ("speed", "spans"),
        ("diurnal", "spans_over"),
    ):
        bad = qc.get(key, {}).get(what) or []
        if bad:
            shown = ", ".join(
                str(b if isinstance(b, str) else b.get("line_id", b)) for b in bad[:6]
            )
            out.append(
                (
                    LOG_WARNING,
                    f"quality: {key.replace('_', ' ')} out of tolerance: "
                    f"{shown}{' ...' if len(bad) > 6 else ''}",
                )
            )
    out += [(LOG_WARNING, f"quality: {n}") for n in q.notes]
    return out


def navigation_lines(nav) -> list[tuple[int, str]]:
    """Log lines of a navigation run (the flow's :func:`navigate_stage` and ``aeromag
    navigate``), or of why it was skipped."""
    if isinstance(nav, str):
        return [(LOG_INFO, f"navigate: skipped: {nav}")]
    d, st = nav.summary()["drms_m"], nav.settings
    ins = (
        "the recorded INS"
        if nav.ins_source == "recorded"
        else f"a {st.ins}-grade INS (seed {st.seed})"
    )
    return [
        (
            LOG_INFO,
            f"navigate: {st.filter} on {st.segments} with {ins}: "
            f"DRMS INS-only {d['ins_only']:.1f} m, map-aided {d['map_aided']:.2f} m, "
            f"CRLB {d['crlb']:.2f} m",
        )
    ] + [(LOG_INFO, f"navigate: {n}") for n in nav.notes]


def navigability_lines(result) -> list[tuple[int, str]]:
    """Log line of the flow's navigability step (a (grid, summary) pair), or of why it was
    skipped."""
    if isinstance(result, str):
        return [(LOG_INFO, f"navigability: skipped: {result}")]
    from pipeline.products.markdown import line_range_s

    s = result[1]
    d = s["drms_m"]
    return [
        (
            LOG_INFO,
            f"navigability: /map/navigability, CRLB DRMS median {d['median']:.1f} m "
            f"(10-90 %: {d['p10']:.1f}-{d['p90']:.1f} m) on {line_range_s(s)} s lines at "
            f"{s['speed_mps']:.1f} m/s",
        )
    ]
