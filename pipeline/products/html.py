"""The post-flight report as one self-contained HTML page (figures embedded as PNG data URIs).

One file, no scripts, no network: it opens from a mail attachment or an archive folder the same
way, and prints. Built from the summary document and the figure files of the same run, so every
number in it is also in ``<stem>.summary.json``.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from pipeline.products.markdown import (
    extension_lines,
    navigability_text,
    uncompensated_map_note,
)

# figure name -> caption; the report places figures by name, unknown ones go to "Other figures"
CAPTIONS = {
    "flight_map": "Flight track coloured by segment (local east/north metres).",
    "compensation": "Total field band-passed 0.1-0.9 Hz: recorded and after each model, "
    "calibration passes shaded.",
    "lcurve": "L-curve of the ridge parameter of the final calibration fit.",
    "heading_error": "Heading error: RMS of B_validation - B_map at the track intersections, "
    "per model (paper 002, Fig. 5).",
    "validation_profiles": "Validation-line profiles against the map and their difference "
    "per model (paper 002, Fig. 6).",
    "audit_residual_time": "Audit: measured minus simulated interference against time, before "
    "and after the extended model.",
    "audit_residual_position": "Audit: measured minus simulated residual against position.",
    "audit_residual_heading": "Audit: residual against heading, with the heading-error bars.",
    "audit_gain": "Audit: what the extended model gained on held-out data.",
    "anomaly": "Anomaly map before ARIMA-Kalman filtering (levelled, gridded).",
    "anomaly_filtered": "Anomaly map after ARIMA-Kalman filtering.",
    "crossovers": "Tie-line crossover differences before and after leveling.",
    "navigation_track": "Navigation on the validation lines: the reference track (/gnss/fix), "
    "the simulated INS alone and the map-aided track over the map (dotted: unscored turns).",
    "navigability": "Navigability: the position CRLB (DRMS, m, log colour scale) a vehicle "
    "reaches flying a straight line into each cell from any of four headings, with the flight "
    "lines over it.",
    "navigation_error": "Horizontal position error against time, INS only and map-aided, with "
    "the posterior CRLB (DRMS); below, the map-aided north/east errors within ± CRLB "
    "(grey: unscored epochs).",
}

CSS = """
body { font-family: sans-serif; margin: 2em auto; max-width: 1150px; color: #222; }
h1 { border-bottom: 2px solid #444; } h2 { border-bottom: 1px solid #bbb; margin-top: 2em; }
table { border-collapse: collapse; margin: 0.6em 0 1.2em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th { background: #eee; } td:first-child, th:first-child { text-align: left; }
td.bad { background: #fdd; } td.good { background: #dfd; }
figure { margin: 1em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #555; }
.pair { display: flex; gap: 1em; flex-wrap: wrap; } .pair figure { flex: 1 1 45%; }
.note { color: #8a5a00; }
"""


def _f(x: Any, fmt: str = ".3f") -> str:
    if x is None:
        return "-"
    if isinstance(x, bool | str):
        return str(x)
    try:
        return format(x, fmt)
    except (TypeError, ValueError):
        return html.escape(str(x))


def _table(
    header: Iterable[str], rows: Iterable[Iterable[Any]], cls: Mapping[int, str] | None = None
) -> str:
    """An HTML table; ``cls`` gives a CSS class per row index (e.g. 'bad')."""
    cls = cls or {}
    out = ["<table>", "<tr>" + "".join(f"<th>{html.escape(h)}</th>" for h in header) + "</tr>"]
    for k, row in enumerate(rows):
        c = f' class="{cls[k]}"' if k in cls else ""
        out.append("<tr>" + "".join(f"<td{c}>{v}</td>" for v in row) + "</tr>")
    out.append("</table>")
    return "\n".join(out)


def _figure(name: str, path: Path) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    caption = html.escape(CAPTIONS.get(name, name.replace("_", " ")))
    return (
        f'<figure id="fig-{html.escape(name)}"><img alt="{html.escape(name)}" '
        f'src="data:image/png;base64,{data}"><figcaption>{caption}</figcaption></figure>'
    )


class _Figures:
    """Figures placed once each; what no section claimed goes to the end."""

    def __init__(self, images: Mapping[str, Path]):
        self.images = dict(images)
        self.used: set[str] = set()

    def take(self, *names: str, pair: bool = False) -> str:
        parts = []
        for n in names:
            if n in self.images and n not in self.used:
                parts.append(_figure(n, self.images[n]))
                self.used.add(n)
        if not parts:
            return ""
        return f'<div class="pair">{"".join(parts)}</div>' if pair else "".join(parts)

    def rest(self) -> str:
        return self.take(*[n for n in self.images if n not in self.used])


def _input_section(s: dict) -> list[str]:
    inp = s.get("input", {})
    out = [
        "<h2>Recording</h2>",
        f"<p>{html.escape(str(inp.get('file', '')))}: {inp.get('epochs', '-')} epochs over "
        f"{_f(inp.get('duration_s'), '.1f')} s; sha256 <code>"
        f"{html.escape(inp.get('sha256', '')[:16])}</code>.</p>",
    ]
    topics = inp.get("topics", {})
    if topics:
        out.append(
            _table(
                ["channel", "schema", "samples", "rate Hz"],
                [
                    [
                        html.escape(t),
                        html.escape(v["schema"]),
                        v["samples"],
                        _f(v["rate_hz"], ".2f"),
                    ]
                    for t, v in topics.items()
                ],
            )
        )
    for g in inp.get("gaps", []):
        out.append(
            f'<p class="note">gap on {html.escape(g["topic"])} at '
            f"{_f(g['start_s'], '.1f')} s for {_f(g['duration_s'], '.1f')} s</p>"
        )
    notes = list(dict.fromkeys(inp.get("notes", [])))  # one line per distinct note
    if notes:
        out.append(
            "<ul>" + "".join(f'<li class="note">{html.escape(n)}</li>' for n in notes) + "</ul>"
        )
    for x in inp.get("losses", []):
        out.append(f'<p class="note">data lost: {html.escape(x["description"])}</p>')
    dropped = inp.get("dropped") or {}
    if dropped:
        out += [
            "<h3>Messages dropped</h3>",
            _table(
                ["channel", "dropped", "of", "time ranges s", "why"],
                [
                    [
                        html.escape(t),
                        d["samples"],
                        d["of"],
                        "; ".join(f"{a:.1f}-{b:.1f}" for a, b in d["ranges_s"][:8])
                        + (" ..." if len(d["ranges_s"]) > 8 else ""),
                        html.escape("; ".join(d["problems"])),
                    ]
                    for t, d in dropped.items()
                ],
                {k: "bad" for k in range(len(dropped))},
            ),
        ]
    return out


def _segments_section(s: dict, figs: _Figures) -> list[str]:
    seg = s.get("segments")
    if not seg:
        return []
    total = max(sum(seg["epochs"].values()), 1)
    return [
        "<h2>Flight and segments</h2>",
        f"<p>Segments {html.escape(seg['source'])}: {seg['calibration_passes']} calibration "
        f"passes, {seg['boxes']} boxes.</p>",
        _table(
            ["segment", "epochs", "share %"],
            [[lab, n, _f(100 * n / total, ".1f")] for lab, n in seg["epochs"].items()],
        ),
        figs.take("flight_map"),
    ]


def _despike_section(s: dict) -> list[str]:
    d = s.get("despike")
    if not d:
        return []
    return [
        "<h2>Despiking</h2>",
        _table(
            [
                "spikes",
                "fraction %",
                "threshold sigma",
                "window",
                "noise nT",
                "largest spike nT",
                "level steps left",
            ],
            [
                [
                    d["spikes"],
                    _f(100 * d["fraction"], ".3f"),
                    _f(d["threshold_sigma"], "g"),
                    (f"{d['window_s']:g} s, " if "window_s" in d else "")
                    + f"{d['window_samples']} samples",
                    _f(d["noise_nT"], ".4f"),
                    _f(d.get("max_abs_amplitude_nT"), ".2f"),
                    d.get("steps_left", 0),
                ]
            ],
        ),
    ]


def _compensation_section(s: dict, figs: _Figures) -> list[str]:
    comp = s.get("compensation")
    if not comp:
        return []
    models = [m for m in comp if m != "final"]
    rows = []
    for m in models:
        r = comp[m]
        g = r.get("gradient_nT_per_m")
        fom = r["fom_nT"]
        ratio = fom["uncompensated"] / fom["compensated"] if fom.get("compensated") else None
        rows.append(
            [
                m,
                _f(fom["uncompensated"], ".2f"),
                _f(fom["compensated"], ".2f"),
                _f(ratio, ".1f"),
                _f(r.get("lambda"), ".3g"),
                _f(r.get("fit_residual_nT"), ".4f"),
                _f(r["residual_std_nT"].get("calibration")),
                _f(r["residual_std_nT"].get("survey")),
                "-" if not g else "/".join(_f(g[k], ".3f") for k in ("east", "north", "up")),
                _f(r.get("heldout_residual_nT"), ".4f"),
                _f(r.get("crossover_rms_nT")),
            ]
        )
    out = [
        "<h2>Calibration and compensation</h2>",
        f"<p>Final model: <b>{html.escape(str(comp['final']))}</b>. FOM = sum of the 12 "
        f"box peak-to-peaks of the band-passed field over one calibration pass.</p>",
        _table(
            [
                "model",
                "FOM raw nT",
                "FOM compensated nT",
                "improvement ratio",
                "lambda",
                "fit residual nT",
                "calibration residual nT",
                "survey residual nT",
                "gradient E/N/U nT/m",
                "held-out residual nT",
                "crossover RMS nT",
            ],
            rows,
        ),
    ]
    ext = extension_lines(comp)
    if ext:
        items = "".join(
            f"<li>{html.escape(x.strip().lstrip('- ').replace('**', ''))}</li>"
            for x in ext
            if x.strip()
        )
        out += ["<h3>Extensions of tl18 (tl-plus, tl-nn)</h3>", f"<ul>{items}</ul>"]
    boxes = (s.get("quality") or {}).get("fom_boxes") or comp[models[-1]]["fom_nT"].get("boxes")
    if boxes:
        cols = [k for k in boxes[0] if k.endswith("_nT")]
        out += [
            "<h3>Calibration FOM per box (peak-to-peak, nT)</h3>",
            _table(
                ["pass", "heading", "manoeuvre", "samples", *[c[:-3] for c in cols]],
                [
                    [
                        b["pass"],
                        b["cardinal"],
                        b["manoeuvre"],
                        b["samples"],
                        *[_f(b[c], ".3f") for c in cols],
                    ]
                    for b in boxes
                ],
            ),
        ]
    guards = [(m, comp[m].get("calibration_guards")) for m in models]
    rows = [
        [
            m,
            _f(g.get("condition_number"), ".3g"),
            _f(g.get("condition_limit"), ".0e"),
            " ".join(f"{c} {v:.0f} s" for c, v in g.get("headings_s", {}).items()),
            "ok" if g["ok"] else f"{len(g['warnings'])} warning(s)",
        ]
        for m, g in guards
        if g
    ]
    if rows:
        out += [
            "<h3>Calibration quality guards</h3>",
            _table(
                ["model", "condition number", "limit", "time per heading", "verdict"],
                rows,
                {k: ("good" if r[-1] == "ok" else "bad") for k, r in enumerate(rows)},
            ),
        ]
    for _, g in guards:
        for w in (g or {}).get("warnings", []):
            out.append(f'<p class="note">calibration warning: {html.escape(w)}</p>')
    out.append(figs.take("compensation", "lcurve"))
    return out


def _quality_section(s: dict, figs: _Figures) -> list[str]:
    q = s.get("quality")
    if not q:
        return []
    inter = q.get("intersection_rms_nT", q["heading_error_rms_nT"])
    less = q.get("overlap_pair_gradient_removed_rms_nT", {})  # older summaries: none
    rows = [
        [
            html.escape(st),
            _f(q["overlap_pair_rms_nT"].get(st)),
            _f(less.get(st)),
            _f(inter.get(st)),
            _f(q["interpolated_rms_nT"].get(st)),
        ]
        for st in q["states"]
    ]
    out = [
        "<h2>Heading error: T-L vs AGG-TL</h2>",
        f"<p>{q['intersections']} validation-line intersections, {q['overlap_pairs']} "
        f"sample pairs closer than {_f(q['overlap_m'], '.2f')} m; white-noise floor at the "
        f"intersections {_f(q.get('heading_error_noise_floor_nT'))} nT. "
        f"T-L = {html.escape(str(q.get('tl_alias')))}. Pairs and the interpolated map are "
        f"paper 002's statistics; the intersections are ours (both fields interpolated "
        f"along track to the crossing, so the gradient x distance of a pair drops out), as are the "
        f"pairs less the field's gradient across each pair's offset. "
        f"Headline heading error: "
        f"{html.escape(str(q.get('heading_error_method', 'intersections')))}.</p>",
        _table(
            [
                "state",
                "pairs RMS nT (paper's)",
                "pairs less gradient RMS nT (ours)",
                "intersections RMS nT (ours)",
                "interpolated map RMS nT (paper's)",
            ],
            rows,
        ),
    ]
    inter = q.get("heading_error", {}).get("intersections", {}).get("by_state", {})
    if inter:
        heads = []
        for st, v in inter.items():
            for h in v.get("by_heading", []):
                heads.append(
                    [
                        html.escape(st),
                        _f(h["validation_heading_deg"], ".0f"),
                        _f(h["map_heading_deg"], ".0f"),
                        h["count"],
                        _f(h["mean_nT"]),
                        "±" + _f(h["ci_nT"]),
                    ]
                )
        out += [
            "<h3>Heading DC offsets (mean of B_validation - B_map, 95 % interval)</h3>",
            _table(
                [
                    "state",
                    "validation heading deg",
                    "map heading deg",
                    "points",
                    "mean nT",
                    "95 % CI nT",
                ],
                heads,
            ),
        ]
    out.append(figs.take("heading_error", "validation_profiles"))
    return out


def _audit_section(s: dict, figs: _Figures) -> list[str]:
    a = s.get("audit")
    if not a:
        return []
    out = [
        "<h2>Model audit: what the simulation gets wrong</h2>",
        f"<p>Baseline {html.escape(a['baseline']['model'])}; extended model <b>"
        f"{html.escape(' + '.join(a['extended_model']))}</b>. Held-out residual "
        f"{_f(a['baseline']['residual_rms_nT'], '.4f')} → {_f(a['unexplained_rms_nT'], '.4f')}"
        f" nT (noise floor in the same band {_f(a.get('band_noise_floor_nT'), '.4f')} nT;"
        f" sensor noise {_f(a['noise_floor_nT'], '.4f')} nT per sample).</p>",
    ]
    rows = []
    for fd in a.get("findings", []):
        est = ", ".join(
            f"{html.escape(k)} {_f(v, '.4g')}"
            for k, v in fd["estimate"].items()
            if k != "at_acceptance" and not isinstance(v, list | dict)
        )
        g = fd.get("gain", {})
        rows.append(
            [
                html.escape(fd["effect"]),
                est,
                _f(fd.get("delta_bic"), ".1f"),
                _f(fd.get("p_value_holm"), ".2g"),
                _f(fd.get("heldout_p_value"), ".2g"),
                f"{_f(g.get('before_nT'), '.4f')} → {_f(g.get('after_nT'), '.4f')}",
            ]
        )
    out.append(
        _table(
            ["effect found", "estimate", "ΔBIC", "p (Holm)", "held-out p", "held-out residual nT"],
            rows,
        )
        if rows
        else "<p>No effect beyond the baseline model was found.</p>"
    )
    if (a.get("unexplained") or {}).get("note"):
        out.append(f'<p class="note">unexplained: {html.escape(a["unexplained"]["note"])}</p>')
    from pipeline.audit.words import plain, unexplained_items

    items = unexplained_items(a.get("unexplained") or {}, int(s["input"].get("start_ns", 0)))
    if items:
        out.append(
            "<ul>"
            + "".join(f'<li class="note">{html.escape(plain(x))}</li>' for x in items)
            + "</ul>"
        )
    gain = a.get("gain") or {}
    if gain:
        out += [
            "<h3>Gain of the extended model</h3>",
            _table(
                ["measure", "before nT", "after nT"],
                [
                    [html.escape(k), _f(v.get("before"), ".4f"), _f(v.get("after"), ".4f")]
                    for k, v in gain.items()
                ],
            ),
        ]
    out.append(
        figs.take(
            "audit_residual_time", "audit_residual_position", "audit_residual_heading", "audit_gain"
        )
    )
    return out


def _map_section(s: dict, figs: _Figures) -> list[str]:
    m = s.get("map")
    if not m:
        return []
    xo = m.get("crossover_rms_nT") or {}
    return [
        "<h2>Anomaly map</h2>",
        _table(
            [
                "grid",
                "cell m",
                "line spacing m",
                "ARIMA order",
                "crossover RMS nT before → after leveling",
                "anomaly range nT",
            ],
            [
                [
                    f"{m['grid_shape'][0]} × {m['grid_shape'][1]}",
                    _f(m["cell_m"], ".2f"),
                    _f(m.get("line_spacing_m"), ".1f"),
                    html.escape(str(tuple(m["arima_order"]))),
                    f"{_f(xo.get('before'))} → {_f(xo.get('after'))}",
                    " to ".join(_f(v, ".1f") for v in m.get("anomaly_range_nT") or []),
                ]
            ],
        ),
        _microlevel_row(m.get("microlevel") or {}),
        f"<p><b>{html.escape(uncompensated_map_note())}</b></p>" if m.get("field") == "raw" else "",
        "<h3>Before and after ARIMA-Kalman filtering</h3>",
        figs.take("anomaly", "anomaly_filtered", pair=True),
        figs.take("crossovers"),
        *_enhancements(m, figs),
    ]


def _navigation_section(s: dict, figs: _Figures) -> list[str]:
    nv = s.get("navigation")
    if not nv:
        return []
    if "skipped" in nv:
        return [
            "<h2>Navigation on the map</h2>",
            f"<p>Skipped: {html.escape(str(nv['skipped']))}.</p>",
        ]
    st, d, c = nv["settings"], nv["drms_m"], nv["cep50_m"]
    rows = [
        [
            "all",
            str(nv["epochs"]["selected"]),
            _f(d["ins_only"], ".1f"),
            _f(d["map_aided"], ".2f"),
            _f(d["crlb"], ".2f"),
            _f(c["ins_only"], ".1f"),
            _f(c["map_aided"], ".2f"),
        ]
    ]
    for sid, g in nv["segments"].items():
        rows.append(
            [
                html.escape(str(sid)),
                str(g["epochs"]),
                _f(g["ins_only"]["drms_m"], ".1f"),
                _f(g["map_aided"]["drms_m"], ".2f"),
                _f(g["crlb_drms_m"], ".2f"),
                _f(g["ins_only"]["cep50_m"], ".1f"),
                _f(g["map_aided"]["cep50_m"], ".2f"),
            ]
        )
    return [
        "<h2>Navigation on the map</h2>",
        f"<p>The validation lines flown with a simulated {html.escape(str(st['ins']))}-grade "
        f"INS (seed {st['seed']}) and the {html.escape(str(st['filter']))} aided by "
        f"{html.escape(str(nv['map']['file']))}; errors against "
        f"{html.escape(str(nv['reference']))}.</p>",
        _table(
            [
                "segment",
                "epochs",
                "DRMS m: INS only",
                "map-aided",
                "CRLB",
                "CEP50 m: INS only",
                "map-aided",
            ],
            rows,
        ),
        figs.take("navigation_track"),
        figs.take("navigation_error"),
    ]


def _navigability_section(s: dict, figs: _Figures) -> list[str]:
    nb = s.get("navigability")
    if not nb:
        return []
    return [
        "<h2>Navigability of the map</h2>",
        f"<p>{html.escape(navigability_text(nb))}</p>",
        figs.take("navigability"),
    ]


def _enhancements(m: dict, figs: _Figures) -> list[str]:
    names = [f"enhance_{t.removeprefix('/map/')}" for t in m.get("enhancements") or []]
    if not names:
        return []
    return [
        "<h3>Enhancements</h3>",
        "<p>FFT enhancements of the filtered anomaly grid (harmonica); the reduction to the "
        "pole uses the IGRF direction at the survey centre "
        f"(inclination {_f((m.get('main_field') or {}).get('inclination_deg'), '.2f')}°, "
        f"declination {_f((m.get('main_field') or {}).get('declination_deg'), '.2f')}°).</p>",
        figs.take(*names, pair=True),
    ]


def _microlevel_row(ml: dict) -> str:
    if not ml.get("enabled"):
        return ""
    return "<h3>Micro-levelling</h3>\n" + _table(
        [
            "corrugation removed nT RMS",
            "max nT",
            "clipped %",
            "clip nT",
            "cut-off across m",
            "low-pass along m",
            "grid change nT RMS",
        ],
        [
            [
                _f(ml["correction_rms_nT"]),
                _f(ml["correction_max_abs_nT"]),
                _f(100 * ml["clipped_fraction"], ".1f"),
                _f(ml["clip_nT"], "g"),
                _f(ml["wavelength_m"], ".0f"),
                _f(ml["along_m"], ".0f"),
                _f(ml["grid_change_rms_nT"]),
            ]
        ],
    )


def _qc_section(s: dict) -> list[str]:
    qc = (s.get("quality") or {}).get("qc")
    if not qc:
        return []
    out = [
        "<h2>Quality control</h2>",
        f"<p>Checked on the {html.escape(str(qc.get('field')))} field.</p>",
    ]
    noise = qc.get("noise")
    if noise:
        lines = noise["per_line_nT"]
        over = set(noise.get("lines_over", []))
        names = list(lines)
        out += [
            f"<h3>Noise per line (4th difference, threshold {_f(noise['threshold_nT'])} nT)</h3>",
            _table(
                ["line", "noise nT", "verdict"],
                [
                    [html.escape(n), _f(lines[n], ".4f"), "over" if n in over else "ok"]
                    for n in names
                ],
                {k: ("bad" if n in over else "good") for k, n in enumerate(names)},
            ),
        ]
    checks = []
    h = qc.get("flight_height")
    if h:
        checks.append(
            [
                "flight height",
                f"max deviation {_f(h['max_abs_deviation_m'], '.2f')} m",
                f"{_f(h['tolerance_m'], '.1f')} m",
                len(h.get("lines_over", [])),
            ]
        )
    sp = qc.get("line_spacing")
    if sp:
        checks.append(
            [
                "line spacing",
                f"nominal {_f(sp['nominal_m'], '.1f')} m, max deviation "
                f"{_f(100 * sp['max_deviation_fraction'], '.1f')} %",
                f"{_f(100 * sp['tolerance_fraction'], '.0f')} %",
                len(sp.get("pairs_over", [])),
            ]
        )
    v = qc.get("speed")
    if v:
        checks.append(
            [
                "ground speed",
                f"median {_f(v['median_m_s'], '.2f')} m/s "
                f"({_f(v['min_m_s'], '.2f')}-{_f(v['max_m_s'], '.2f')})",
                f"{_f(100 * v['tolerance_fraction'], '.0f')} %",
                len(v.get("spans", [])),
            ]
        )
    d = qc.get("diurnal")
    if d and d.get("available"):
        checks.append(
            [
                "diurnal (base station)",
                f"max {_f(d['chord_s'], '.0f')} s chord deviation "
                f"{_f(d['max_chord_deviation_nT'])} nT, range {_f(d['range_nT'], '.2f')} nT",
                f"{_f(d['tolerance_nT'], '.1f')} nT",
                len(d.get("spans_over", [])),
            ]
        )
    if checks:
        out += [
            "<h3>Survey specifications</h3>",
            _table(
                ["check", "measured", "tolerance", "violations"],
                checks,
                {k: ("bad" if c[3] else "good") for k, c in enumerate(checks)},
            ),
        ]
    for n in (s.get("quality") or {}).get("notes", []):
        out.append(f'<p class="note">{html.escape(n)}</p>')
    return out


def _vector_section(s: dict) -> list[str]:
    v = s.get("vector")
    if not v:
        return []
    out = [
        "<h2>Vector magnetometer</h2>",
        f"<p>{html.escape(v['method'])} → <code>{html.escape(v['output_topic'])}</code></p>",
    ]
    mag = v.get("magnitude_vs_reference_rms_nT")
    if mag:
        out.append(
            _table(
                ["measure", "before nT", "after nT"],
                [
                    [
                        "RMS(|vector| - reference field)",
                        _f(mag["before"], ".2f"),
                        _f(mag["after"], ".2f"),
                    ]
                ],
            )
        )
    return out


def render_html(stem: str, summary: dict, images: Mapping[str, str | Path]) -> str:
    """The report page for one processed recording.

    Parameters
    ----------
    stem
        Recording name (file name without ``.mcap``).
    summary
        The summary document of the run.
    images
        Figure name -> PNG file; each is embedded once, in its section.
    """
    s = summary
    figs = _Figures({k: Path(v) for k, v in images.items()})
    cfg = s.get("config", {})
    body = [
        f"<h1>Post-flight report: {html.escape(stem)}</h1>",
        f"<p>aeromag {html.escape(str(s.get('aeromag_version', '')))}, configuration "
        f"<code>{html.escape(str(cfg.get('hash', ''))[:12])}</code> (version "
        f"{html.escape(str(cfg.get('version', '')))}, {html.escape(str(cfg.get('source', '')))}"
        ")</p>",
    ]
    body += _input_section(s)
    body += _segments_section(s, figs)
    body += _despike_section(s)
    body += _compensation_section(s, figs)
    body += _quality_section(s, figs)
    body += _audit_section(s, figs)
    body += _map_section(s, figs)
    body += _navigation_section(s, figs)
    body += _navigability_section(s, figs)
    body += _qc_section(s)
    body += _vector_section(s)
    rest = figs.rest()
    if rest:
        body += ["<h2>Other figures</h2>", rest]
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>aeromag report: {html.escape(stem)}</title><style>{CSS}</style></head>"
        "<body>\n" + "\n".join(p for p in body if p) + "\n</body></html>\n"
    )
