"""The post-flight report in Markdown, rendered from the summary document
(:func:`pipeline.products.summary.build_summary`); the HTML report renders the same document
(:mod:`pipeline.products.html`)."""

from __future__ import annotations


def uncompensated_map_note() -> str:
    """What a map of the uncompensated scalar field (``map.field`` "raw") is, in words."""
    return (
        "The map is of the uncompensated scalar field: no compensation model could be fitted "
        "(no vector magnetometer or no calibration pass); the carrier's interference is in it."
    )


def _window(d: dict) -> str:
    """The despike window: seconds and its samples (summaries before ``window_s``: samples)."""
    n = f"{d['window_samples']} samples"
    return f"{d['window_s']:g} s, {n}" if "window_s" in d else n


def line_range_s(nb: dict) -> str:
    """The navigability lines' durations (s, one per heading) as ``58`` or ``58-120``."""
    lo, hi = min(nb["line_s"]), max(nb["line_s"])
    return f"{lo:.0f}" if round(lo) == round(hi) else f"{lo:.0f}-{hi:.0f}"


def navigability_text(nb: dict) -> str:
    """The report's one line on the navigability map (summary ``navigability``)."""
    if "skipped" in nb:
        return f"Navigability map skipped: {nb['skipped']}."
    d = nb["drms_m"]
    sigma = "its uncertainty grid" if nb["map_sigma"] == "grid" else f"{nb['map_sigma']} nT"
    return (
        f"Navigability (/map/navigability): a vehicle flying {line_range_s(nb)} s straight "
        f"lines at {nb['speed_mps']:.1f} m/s into each cell, its INS known to "
        f"{nb['start_sigma_m']:g} m at the line's start, reaches a position CRLB (DRMS) of "
        f"{d['median']:.1f} m at the median "
        f"cell ({d['p10']:.1f} m at the best 10 %, {d['p90']:.1f} m at the worst 10 %), "
        f"with {nb['sensor_sigma_nT']:.3f} nT sensor noise and the map's error from {sigma}."
    )


def _input_warnings(inp: dict) -> list[str]:
    """What the recording lacked, as the HTML report says it: data a damaged file lost, gaps
    in a channel, the reader's notes (the Markdown is also the flow's Prefect artifact)."""
    lines = [f"- **data lost**: {x['description']}" for x in inp.get("losses", [])]
    lines += [
        f"- gap on {g['topic']} at {g['start_s']:.1f} s for {g['duration_s']:.1f} s"
        for g in inp.get("gaps", [])
    ]
    lost = [x["description"] for x in inp.get("losses", [])]
    notes = dict.fromkeys(n for n in inp.get("notes", []) if not any(d in n for d in lost))
    lines += [f"- {n}" for n in notes]
    return [*lines, ""] if lines else []


def report_markdown(stem: str, s: dict, images: dict[str, str]) -> str:
    """The post-flight report: the tables people look at, and the figures."""

    def f(x, fmt=".3f"):
        return "-" if x is None else format(x, fmt)

    out = [
        f"# Post-flight report: {stem}",
        "",
        f"aeromag {s['aeromag_version']}, configuration {s['config']['hash'][:12]} "
        f"(version {s['config']['version']}, {s['config']['source']})",
        "",
        f"Input: {s['input'].get('epochs', '-')} epochs, "
        f"{f(s['input'].get('duration_s'), '.0f')} s, sha256 "
        f"{s['input'].get('sha256', '')[:16]}",
        "",
    ]
    out += _input_warnings(s["input"])
    d = s.get("despike")
    if d:
        out += [
            "## Despiking",
            "",
            f"{d['spikes']} spikes ({100 * d['fraction']:.3f} % of samples) replaced before "
            f"compensation: Hampel test at {d['threshold_sigma']:g} sigma on the 4th "
            f"difference (window {_window(d)}); noise {f(d['noise_nT'], '.4f')} "
            f"nT, largest spike {f(d['max_abs_amplitude_nT'], '.2f')} nT",
            "",
        ]
    comp = s.get("compensation")
    if comp:
        out += [
            "## Compensation",
            "",
            f"Final: **{comp['final']}**",
            "",
            "| model | FOM raw nT | FOM compensated nT | lambda | survey residual nT "
            "| held-out residual nT | crossover RMS nT |",
            "|---|---|---|---|---|---|---|",
        ]
        for m, r in comp.items():
            if m == "final":
                continue
            out.append(
                f"| {m} | {f(r['fom_nT']['uncompensated'], '.2f')} | "
                f"{f(r['fom_nT']['compensated'], '.2f')} | {f(r['lambda'], '.3g')} | "
                f"{f(r['residual_std_nT']['survey'])} | {f(r.get('heldout_residual_nT'), '.4f')} "
                f"| {f(r.get('crossover_rms_nT'))} |"
            )
        out.append("")
        out += extension_lines(comp)
    a = s.get("audit")
    if a:
        out += [
            "## Model audit",
            "",
            f"Extended model: **{' + '.join(a['extended_model'])}**; held-out residual "
            f"{f(a['baseline']['residual_rms_nT'], '.4f')} -> "
            f"{f(a['unexplained_rms_nT'], '.4f')} nT (noise floor "
            f"{f(a.get('band_noise_floor_nT'), '.4f')} nT in the same band; sensor noise "
            f"{f(a['noise_floor_nT'], '.4f')} nT per sample)",
            "",
        ]
        for fd in a["findings"]:
            out.append(
                f"- `{fd['effect']}`: "
                + ", ".join(
                    f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                    for k, v in fd["estimate"].items()
                    if k != "at_acceptance" and not isinstance(v, list | dict)
                )
            )
        if (a.get("unexplained") or {}).get("note"):
            out.append(f"- unexplained: {a['unexplained']['note']}")
        from pipeline.audit.words import unexplained_items

        t0 = int(s["input"].get("start_ns", 0))
        out += [f"- {x}" for x in unexplained_items(a.get("unexplained") or {}, t0)]
        out.append("")
    q = s.get("quality")
    if q:
        out += [
            "## Heading error and quality",
            "",
            f"{q['intersections']} intersections, {q['overlap_pairs']} pairs < "
            f"{q['overlap_m']} m; headline heading_error_rms_nT = "
            f"{q.get('heading_error_method', 'intersections')}",
            "",
            "| state | pairs RMS nT (paper 002) | pairs less gradient RMS nT (ours) | "
            "intersections RMS nT (ours) | interpolated map RMS nT (paper 002) |",
            "|---|---|---|---|---|",
        ]
        inter = q.get("intersection_rms_nT", q["heading_error_rms_nT"])
        less = q.get("overlap_pair_gradient_removed_rms_nT", {})  # older summaries: none
        for st in q["states"]:
            out.append(
                f"| {st} | {f(q['overlap_pair_rms_nT'][st])} | {f(less.get(st))} | "
                f"{f(inter[st])} | "
                f"{f(q['interpolated_rms_nT'][st])} |"
            )
        xo = q["crossover_rms_nT"]
        out += [
            "",
            f"Crossovers: RMS {f(xo['before'])} -> {f(xo['after'])} nT after "
            f"leveling; 4th-difference noise {f(q['noise_4th_diff_nT'], '.4f')} nT",
            "",
        ]
    m = s.get("map")
    if m:
        out += [
            "## Map",
            "",
            f"{m['grid_shape'][0]} x {m['grid_shape'][1]} cells of "
            f"{m['cell_m']:.2f} m; ARIMA{tuple(m['arima_order'])} + Kalman",
            "",
        ]
        if m.get("field") == "raw":
            out += [f"**{uncompensated_map_note()}**", ""]
        crs = (m.get("origin") or {}).get("crs_choice")
        if crs:
            out += [f"Gridded in {crs}; the exported GeoTIFF and netCDF hold these cells.", ""]
        ml = m.get("microlevel") or {}
        if ml.get("enabled"):
            out += [
                f"Micro-levelling: corrugation removed {f(ml['correction_rms_nT'])} nT RMS "
                f"(max {f(ml['correction_max_abs_nT'])} nT, clip {ml['clip_nT']:g} nT); grid "
                f"changed {f(ml['grid_change_rms_nT'])} nT RMS",
                "",
            ]
    nv = s.get("navigation")
    if nv:
        out += ["## Navigation on the map", ""]
        if "skipped" in nv:
            out += [f"Skipped: {nv['skipped']}.", ""]
        else:
            st, d, c = nv["settings"], nv["drms_m"], nv["cep50_m"]
            out += [
                f"Validation lines flown with a simulated {st['ins']}-grade INS (seed "
                f"{st['seed']}), {st['filter']} aided by {nv['map']['file']}; reference "
                f"{nv['reference']}",
                "",
                "| segment | epochs | DRMS m: INS only | map-aided | CRLB | CEP50 m: INS only "
                "| map-aided |",
                "|---|---|---|---|---|---|---|",
                f"| all | {nv['epochs']['selected']} | {f(d['ins_only'], '.1f')} | "
                f"{f(d['map_aided'], '.2f')} | {f(d['crlb'], '.2f')} | "
                f"{f(c['ins_only'], '.1f')} | {f(c['map_aided'], '.2f')} |",
            ]
            for sid, g in nv["segments"].items():
                out.append(
                    f"| {sid} | {g['epochs']} | {f(g['ins_only']['drms_m'], '.1f')} | "
                    f"{f(g['map_aided']['drms_m'], '.2f')} | {f(g['crlb_drms_m'], '.2f')} | "
                    f"{f(g['ins_only']['cep50_m'], '.1f')} | "
                    f"{f(g['map_aided']['cep50_m'], '.2f')} |"
                )
            out.append("")
    nb = s.get("navigability")
    if nb:
        out += ["## Navigability of the map", "", navigability_text(nb), ""]
    v = s.get("vector")
    if v:
        out += ["## Vector magnetometer", "", f"{v['method']} -> `{v['output_topic']}`", ""]
    if images:
        out += ["## Figures", ""] + [f"![{k}]({p})" for k, p in images.items()] + [""]
    return "\n".join(out)


def heading_levels_text(hl: dict) -> str:
    """tl-plus's heading-level correction in one line: applied or not, its size and the
    crossovers' verdict."""
    if "p_nT" not in hl:
        return f"no correction ({hl.get('reason', '')})"
    px, py = hl["p_nT"]
    size = f"permanent field {px:.2f} nT forward, {py:.2f} nT right"
    if "crossover_p" not in hl:
        return f"{size}, not applied ({hl.get('reason', '')})"
    xo = (
        f"survey-tie crossovers {hl['crossover_rms_before_nT']:.3f} -> "
        f"{hl['crossover_rms_after_nT']:.3f} nT (p {hl['crossover_p']:.2g} over "
        f"{hl['crossover_lines']} lines)"
    )
    return f"{size}, {'applied' if hl.get('used') else 'not applied'}: {xo}"


def extension_lines(comp: dict) -> list[str]:
    """Markdown lines on tl-plus / tl-nn: used or not and why, tl-plus's groups (with the
    audit's seeds), tl-nn's feature-group importance (held-out RMS increase when permuted)."""
    out: list[str] = []
    for m, r in comp.items():
        ext = r.get("extension") if isinstance(r, dict) else None
        if not ext:
            continue
        verdict = "used" if ext.get("used") else "not used, tl18 kept"
        out.append(f"- **{m}**: {verdict}: {ext.get('reason', '')}")
        groups = [g for g, t in (r.get("term_groups") or {}).items() if t.get("selected")]
        if groups:
            out.append(f"  - term groups: {', '.join(groups)}")
        if ext.get("seeded_by_audit"):
            out.append(f"  - tried first (named by the audit): {', '.join(ext['seeded_by_audit'])}")
        hl = ext.get("heading_levels")
        if isinstance(hl, dict):
            out.append(f"  - heading levels of the calibration legs: {heading_levels_text(hl)}")
        imp = r.get("feature_importance") or {}
        if imp:
            key = "heldout_rms_increase_nT"
            ranked = sorted(imp.items(), key=lambda kv: -kv[1].get(key, 0.0))
            parts = [
                f"{g} {v.get(key, 0.0):.4f} nT ({100 * v.get('share', 0.0):.0f} %)"
                for g, v in ranked
            ]
            out.append("  - feature-group importance: " + ", ".join(parts))
    return out + ([""] if out else [])
