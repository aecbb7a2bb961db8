"""What the ``aeromag`` commands print: each command's result (its summary) as lines and
tables of text, rendered by the CLI (``flows/cli.py``) with rich. Paths are printed as they
are, so that they survive copy and paste.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import PurePath


@dataclass
class TextTable:
    """A table of text: a title, its columns (left or right justified) and its rows."""

    title: str
    title_justify: str = "left"
    columns: list[tuple[str, str]] = field(default_factory=list)  # (name, justify)
    rows: list[tuple[str, ...]] = field(default_factory=list)

    def add_column(self, name: str, justify: str = "left") -> None:
        """Append a column (``justify``: left or right)."""
        self.columns.append((name, justify))

    def add_row(self, *cells: str) -> None:
        """Append a row of cells, one per column."""
        self.rows.append(cells)


Block = str | TextTable


def _f3(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def quality_text(q: dict) -> list[Block]:
    """``aeromag quality`` (and ``demo``): the paper-002 table, heading error per processing
    state (``q``: the summary's ``quality``)."""
    out: list[Block] = []
    floor = q["heading_error_noise_floor_nT"]
    out.append(
        f"heading error, validation X lines vs map lines: {q['intersections']} intersections, "
        f"{q['overlap_pairs']} pairs < {q['overlap_m']:g} m; white-noise floor at the "
        f"intersections {'-' if floor is None else f'{floor:.3f} nT'}; headline "
        f"heading_error_rms_nT = {q.get('heading_error_method', 'intersections')}"
    )
    inter = q.get("intersection_rms_nT", q["heading_error_rms_nT"])
    table = TextTable(
        title="RMS of B_validation - B_map (pairs, interpolated map: paper 002's "
        "statistics; intersections: ours)",
        title_justify="left",
    )
    for col in ("state", "pairs RMS nT", "intersections RMS nT", "interpolated map RMS nT"):
        table.add_column(col, justify="left" if col == "state" else "right")

    f = _f3
    for s in q["states"]:
        name = s + (" (= tl)" if q.get("tl_alias") and s == q["tl_alias"].replace("-", "_") else "")
        table.add_row(
            name, f(q["overlap_pair_rms_nT"][s]), f(inter[s]), f(q["interpolated_rms_nT"][s])
        )
    out.append(table)
    xo, n = q["crossover_rms_nT"], q["noise_4th_diff_nT"]
    out.append(
        f"crossovers: RMS {f(xo['before'])} -> {f(xo['after'])} nT after leveling; "
        f"4th-difference noise {f(n)} nT"
    )
    return out


def audit_text(j: dict) -> list[Block]:
    """``aeromag audit``: the baseline, the findings table, the extended model, the gains."""
    out: list[Block] = []
    b = j["baseline"]
    out.append(
        f"baseline {b['model']}: held-out calibration residual {b['residual_rms_nT']:.4f} nT; "
        f"noise floor in the same band {j['band_noise_floor_nT']:.4f} nT; sensor noise "
        f"{j['noise_floor_nT']:.4f} nT per sample"
    )
    table = TextTable(title="findings", title_justify="left")
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
        out.append(table)
    else:
        out.append("no finding: no candidate effect improves held-out data beyond noise")
    out.append(
        f"extended model: {' + '.join(j['extended_model'])}; unexplained (held-out) "
        f"{j['unexplained_rms_nT']:.4f} nT"
    )
    if (j.get("unexplained") or {}).get("note"):
        out.append(f"unexplained: {j['unexplained']['note']}")
    if (j.get("unexplained") or {}).get("ambiguities"):
        from pipeline.audit.words import ambiguity_text, plain

        out += [plain(ambiguity_text(a)) for a in j["unexplained"]["ambiguities"]]
    for k, v in j["gain"].items():
        if v["before"] is not None:
            out.append(f"gain {k}: {v['before']:.4f} -> {v['after']:.4f}")
    return out


def compensation_text(result: dict) -> list[Block]:
    """The post-flight summary's compensation table (one row per model) and warnings."""
    out: list[Block] = []
    comp = result.get("compensation")
    if not comp or not any(m in comp for m in ("tl16", "tl18", "agg-tl")):
        return out
    table = TextTable(
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
    out.append(table)
    for m in ("tl16", "tl18", "agg-tl"):
        for w in ((comp.get(m) or {}).get("calibration_guards") or {}).get("warnings", []):
            out.append(f"warning: {w}")
    return out


def outputs_text(result: dict) -> list[Block]:
    """Where the post-flight flow wrote its outputs."""
    out: list[Block] = []
    o = result["outputs"]
    out.append(f"output recording: {o['mcap']}")
    out.append(f"summary: {o['summary']}")
    out.append(
        f"report: {o['report_html']} (open in a browser; Markdown: {o['report']}); "
        f"Foxglove layout: {o['layout']}"
    )
    for fmt, paths in (result.get("exports") or {}).items():
        out.append(f"export ({fmt}): {', '.join(paths)}")
    return out


def compensate_text(summary: dict) -> list[Block]:
    """``aeromag compensate``: an extension's verdict, the model, its ridge and fit residual,
    the FOM."""
    fom = summary["fom_nT"]
    out: list[Block] = []
    ext = summary.get("extension")
    if ext:  # tl-plus / tl-nn: used or not, and why
        out.append(f"{summary['model']}: {'used' if ext['used'] else 'not used'}: {ext['reason']}")
        if isinstance(ext.get("heading_levels"), dict):
            from pipeline.products.markdown import heading_levels_text

            out.append(f"heading levels: {heading_levels_text(ext['heading_levels'])}")
    out.append(
        f"{summary['model']}: lambda {summary['lambda']:.3g}, {summary['samples']} samples, "
        f"fit residual {summary['fit_residual_nT']:.4f} nT"
    )
    if fom["uncompensated"] is not None:
        out.append(
            f"FOM: {fom['uncompensated']:.2f} nT uncompensated -> {fom['compensated']:.2f} nT"
        )
    return out


def map_text(m: dict) -> list[Block]:
    """``aeromag map`` (``m``: the summary's ``map``): the grid, the levelling, the ARIMA."""
    xo = m["crossover_rms_nT"]  # None without crossing lines
    raw = "uncompensated field (no model could be fitted): " if m.get("field") == "raw" else ""
    return [
        f"{raw}grid {m['grid_shape'][0]} x {m['grid_shape'][1]} cells of {m['cell_m']:.2f} m; "
        + (
            "no crossovers"
            if xo["before"] is None
            else f"crossover RMS {_f3(xo['before'])} -> {_f3(xo['after'])} nT"
        )
        + f"; ARIMA{tuple(m['arima_order'])}"
    ]


def enhance_text(result: dict) -> list[Block]:
    """``aeromag enhance``: the channels written and the main-field direction of the RTP."""
    return [
        *result["channels"],
        f"from /map/{result['source']}; IGRF inclination "
        f"{result['inclination_deg']:.2f} deg, declination {result['declination_deg']:.2f} deg",
        *result.get("skipped", []),
    ]


def vector_text(v: dict) -> list[Block]:
    """``aeromag vector`` (``v``: the summary's ``vector``): each figure before -> after."""
    return [
        f"{k}: {val['before']:.2f} -> {val['after']:.2f} nT"
        for k, val in v.items()
        if isinstance(val, dict) and "before" in val and not isinstance(val["before"], list)
    ]


def navigate_text(nav: dict) -> list[Block]:
    """``aeromag navigate`` (``nav``: the summary's ``navigation``): DRMS and CEP50 of the
    INS alone and map-aided against the CRLB, and the run's notes."""
    d, c, st = nav["drms_m"], nav["cep50_m"], nav["settings"]
    return [
        f"{st['filter']} on {st['segments']} ({nav['epochs']['selected']} epochs, "
        f"{st['ins']}-grade INS, seed {st['seed']}): DRMS INS-only {d['ins_only']:.1f} m, "
        f"map-aided {d['map_aided']:.2f} m, CRLB {d['crlb']:.2f} m; "
        f"CEP50 {c['ins_only']:.1f} -> {c['map_aided']:.2f} m",
        *(f"note: {note}" for note in nav["notes"]),
    ]


def campaign_text(doc: dict) -> list[Block]:
    """``aeromag campaign``: each flight's offset, the crossover RMS within and between
    flights, the warnings, the grid and the outputs."""
    r, g, o = doc["crossover_rms_nT"], doc["grid"], doc["outputs"]
    w, b = r["within_flight"], r["between_flights"]
    return [
        f"{len(doc['flights'])} flights: "
        + ", ".join(f"{k} {v:+.3f} nT" for k, v in doc["flight_offsets_nT"].items()),
        f"crossover RMS within flights {_f3(w['before'])} -> {_f3(w['after'])} nT "
        f"({doc['crossovers']['within_flight']}), between flights {_f3(b['before'])} -> "
        f"{_f3(b['after'])} nT ({doc['crossovers']['between_flights']})",
        *(f"warning: {x}" for x in doc["warnings"]),
        f"grid: {g['shape'][0]} x {g['shape'][1]} cells of {g['cell_m']:.2f} m",
        f"output recording: {o['mcap']}",
        f"summary: {o['summary']}",
        f"report: {o['report']}",
        *(f"export ({fmt}): {', '.join(p)}" for fmt, p in (doc.get("exports") or {}).items()),
    ]


def postflight_text(result: dict) -> list[Block]:
    """``aeromag process`` and ``aeromag demo``: the post-flight summary in brief (what the
    recording lost, compensation, map, audit with its ties, quality), then where its
    outputs are."""
    inp = result["input"]
    out: list[Block] = [
        f"ingested {inp['epochs']} epochs, {len(inp['topics'])} channels, "
        f"{inp['duration_s']:.0f} s",
        *(f"warning: data lost: {x['description']}" for x in inp.get("losses", [])),
        *compensation_text(result),
    ]
    m = result.get("map")
    if m and "grid_shape" in m:  # a skipped stage's summary holds only why
        out.append(
            f"map: {m['grid_shape'][0]} x {m['grid_shape'][1]} cells of {m['cell_m']:.1f} m; "
            f"crossover RMS {_f3(m['crossover_rms_nT']['before'])} -> "
            f"{_f3(m['crossover_rms_nT']['after'])} nT; ARIMA{tuple(m['arima_order'])} + "
            f"Kalman; figures in {PurePath(result['outputs']['mcap']).parent}"
        )
    if (result.get("audit") or {}).get("findings") is not None:
        a = result["audit"]
        out.append(
            "audit: "
            + ("; ".join(f"{f['effect']} found" for f in a["findings"]) or "no finding")
            + f"; extended model {' + '.join(a['extended_model'])}"
        )
        from pipeline.audit.words import ambiguity_text, plain

        for amb in (a.get("unexplained") or {}).get("ambiguities", []):
            out.append("audit: " + plain(ambiguity_text(amb)))
    if "states" in (result.get("quality") or {}):
        out += quality_text(result["quality"])
    return out + outputs_text(result)


def inspect_text(d: dict) -> list[Block]:
    """``aeromag inspect`` (``d``: the report's dict with ``file`` and ``warnings``): one row
    per topic (schema, messages, rate, gaps), then the warnings."""
    table = TextTable(title=f"{d['file']}  ({d['duration_s']:.1f} s)")
    for col in ("topic", "schema", "messages", "rate Hz", "gaps"):
        table.add_column(col, justify="right" if col in ("messages", "rate Hz", "gaps") else "left")
    for t in d["topics"]:
        rate = "" if t["rate_hz"] is None else f"{t['rate_hz']:.2f}"
        table.add_row(t["topic"], t["schema"], str(t["messages"]), rate, str(len(t["gaps"])))
    return [table, *(f"warning: {w}" for w in d["warnings"])]


def simulation_text(result: dict) -> list[Block]:
    """``aeromag simulate``: the recording written, its length, messages and hidden effects."""
    return [
        f"{result['out']}: {result['duration_s'] / 60:.1f} min flight, {result['messages']} "
        f"messages, effects: {', '.join(result['effects']) or 'none'}",
        *([f"{result['truth']}: truth"] if result["truth"] else []),
    ]


def reprocess_text(result: dict) -> list[Block]:
    """``aeromag reprocess``: how many recordings were processed, done before, quarantined."""
    return [
        f"{result['recordings']} recordings: {result['processed']} processed, "
        f"{result['done']} already done, {result['quarantined']} quarantined",
        f"index: {result['index']['csv']}",
    ]


def navigability_text(result: dict) -> list[Block]:
    """``aeromag navigability``: the speed and headings assumed, the noise levels used and the
    spread of the per-cell position bound."""
    d = result["drms_m"]
    sigma = result["map_sigma"]
    return [
        f"{result['channel']}: {result['speed_mps']:.1f} m/s, headings "
        f"{', '.join(f'{h:g}' for h in result['headings_deg'])} deg; sensor "
        f"{result['sensor_sigma_nT']:.3f} nT, map "
        + ("its own /map/uncertainty" if sigma == "grid" else f"{sigma:g} nT"),
        f"position bound (CRLB DRMS) per cell: median {d['median']:.1f} m, 10-90 % "
        f"{d['p10']:.1f}-{d['p90']:.1f} m",
    ]
