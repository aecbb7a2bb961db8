"""The audit's human-readable products: figures, a Markdown report, log lines, channel."""

from __future__ import annotations

from typing import Any

from pipeline.audit.result import AuditResult
from pipeline.audit.words import ambiguity_text, event_text, fmt_value, nuisance_text, plain
from pipeline.flight import Flight
from pipeline.io.writer import OutputChannel
from pipeline.products.summary import jsonable


def labels(res: AuditResult) -> dict[str, str]:
    """Legend labels of the two models: ``{"baseline": ..., "extended": ...}``."""
    return {
        "baseline": f"baseline ({res.baseline.spec.base})",
        "extended": "extended (" + " + ".join(res.extended.spec.label()) + ")",
    }


def figures(res: AuditResult, flight: Flight) -> dict[str, Any]:
    """The audit's figures (built by :mod:`pipeline.products.figures`).

    Parameters
    ----------
    res : AuditResult
    flight : Flight
        The audited flight; its ``yaw_deg`` (when present) gives the residual-vs-heading figure.

    Returns
    -------
    dict
        Figure name -> figure: ``residual_time``, ``residual_position`` (with positions),
        ``residual_heading`` (with a heading) and ``gain``.
    """
    from pipeline.products.figures import (
        audit_gain_figure,
        audit_heading_figure,
        audit_position_figure,
        audit_time_figure,
    )

    lab = labels(res)
    w = res.residual_epochs
    out = {"residual_time": audit_time_figure(res.data.time_s, w, res.simulated, lab)}
    if res.data.enu_m is not None:
        out["residual_position"] = audit_position_figure(
            res.data.enu_m[w, 0], res.data.enu_m[w, 1], res.simulated, lab
        )
    heading = flight.data["yaw_deg"].to_numpy(float)[w] if flight.has("yaw_deg") else None
    if heading is not None:
        by = {k: v["by_heading"] for k, v in res.quality.items()} if res.quality else None
        out["residual_heading"] = audit_heading_figure(heading, res.simulated, lab, by)
    out["gain"] = audit_gain_figure(res.gain)
    return out


def _estimate(est: dict) -> str:
    return ", ".join(
        f"{k} {fmt_value(v)}"
        for k, v in est.items()
        if k != "at_acceptance" and not k.endswith("_by_fold_s")
    )


def log_lines(res: AuditResult) -> list[tuple[int, str]]:
    """The audit's run-log lines as (level, text): the baseline's held-out residual and the noise
    floor, each finding (warning), the extended model's residual, unexplained structure
    (warning) and the gains.
    """
    from pipeline.products.log import LOG_INFO, LOG_WARNING

    j = res.to_json()
    out = [
        (
            LOG_INFO,
            f"audit: baseline {j['baseline']['model']}: held-out calibration "
            f"residual {j['baseline']['residual_rms_nT']:.4f} nT, noise floor in the same band "
            f"{j['band_noise_floor_nT']:.4f} nT",
        )
    ]
    for f in res.findings:
        g = f.heldout
        out.append(
            (
                LOG_WARNING,
                f"audit: finding {f.effect}: {_estimate(f.estimate)}; "
                f"delta BIC {f.test.delta_bic:.1f}, p {f.p_adjusted:.2g}; "
                f"{f.metric.replace('_', ' ')} {g.rms_before_nT:.4f} -> "
                f"{g.rms_after_nT:.4f} nT",
            )
        )
    if not res.findings:
        out.append(
            (LOG_INFO, "audit: no finding: no candidate effect improves held-out data beyond noise")
        )
    out.append(
        (
            LOG_INFO,
            f"audit: extended model {' + '.join(j['extended_model'])}: "
            f"held-out residual {j['unexplained_rms_nT']:.4f} nT",
        )
    )
    if res.unexplained.get("note"):
        out.append((LOG_WARNING, f"audit: unexplained: {res.unexplained['note']}"))
    for a in res.unexplained.get("ambiguities", []):
        out.append((LOG_WARNING, f"audit: {plain(ambiguity_text(a))}"))
    for k, v in res.gain.items():
        if v["before"] is not None:
            out.append((LOG_INFO, f"audit: gain {k}: {v['before']:.4f} -> {v['after']:.4f}"))
    return out


def finding_channel(flight: Flight, res: AuditResult) -> OutputChannel:
    """``/audit/finding``: one message per accepted effect (and one for unexplained
    structure), at the first epoch, 1 ns apart."""
    ch = OutputChannel("/audit/finding", "aeromag.AuditFinding")
    t0 = int(flight.time_ns[0])
    for k, f in enumerate(res.findings):
        ch.add(
            t0 + k,
            {
                "effect": f.effect,
                "accepted": True,
                "estimate": jsonable(f.estimate),
                "estimate_ci95": jsonable(f.ci95),
                "delta_bic": f.test.delta_bic if f.test else None,
                "p_value": f.test.p_value if f.test else None,
                "p_value_holm": f.p_adjusted,
                "heldout_p_value": f.heldout.p_value if f.heldout else None,
                "gain_metric": f.metric,
                "before_nT": f.heldout.rms_before_nT if f.heldout else None,
                "after_nT": f.heldout.rms_after_nT if f.heldout else None,
                "message": f"{f.effect}: {_estimate(f.estimate)}",
            },
        )
    if res.unexplained.get("note"):
        u = res.unexplained
        ch.add(
            t0 + len(res.findings),
            _unexplained(
                u,
                u["note"],
                before_nT=u.get("band_noise_floor_nT", res.band_noise_floor_nT),
                after_nT=u.get("rms_nT", res.heldout_extended_nT),
            ),
        )
    # each tie, beside the note: a viewer of the recording sees what was left unnamed and
    # what it does to the lines, also when the residual is at the noise floor (no note)
    for k, a in enumerate(res.unexplained.get("ambiguities", [])):
        ch.add(t0 + len(res.findings) + 1 + k, _unexplained(a, plain(ambiguity_text(a))))
    events = sorted(res.unexplained["events"], key=lambda e: e["start_ns"])
    for k, e in enumerate(events):  # on the timeline where they happen
        ch.add(
            int(e["start_ns"]) + len(res.findings) + 1 + k,
            _unexplained(
                e,
                f"unexplained {e['kind']} of {e['size_nT']:.2f} nT ({e['evidence']})",
                gain_metric=e["evidence"],
                p_value=e.get("p_value"),
                with_ci95=True,
            ),
        )
    return ch


def _unexplained(
    estimate: dict,
    message: str,
    gain_metric: str = "heldout_calibration_residual_rms",
    p_value: float | None = None,
    before_nT: float | None = None,
    after_nT: float | None = None,
    with_ci95: bool = False,
) -> dict[str, Any]:
    """An ``/audit/finding`` message of what the audit left unexplained (its note, a tie, an
    event): nothing accepted, no model test, the keys in the findings' order."""
    msg: dict[str, Any] = {
        "effect": "unexplained",
        "accepted": False,
        "estimate": jsonable(estimate),
    }
    if with_ci95:
        msg["estimate_ci95"] = None
    msg.update(
        delta_bic=None,
        p_value=p_value,
        p_value_holm=None,
        heldout_p_value=None,
        gain_metric=gain_metric,
        before_nT=before_nT,
        after_nT=after_nT,
        message=message,
    )
    return msg


def markdown(res: AuditResult, source: str, images: dict[str, str]) -> str:
    """The audit report as Markdown.

    Parameters
    ----------
    res : AuditResult
    source : str
        Name of the audited recording (the title).
    images : dict of str to str
        Figure name (as from :func:`figures`) -> path of its image, linked in the report.

    Returns
    -------
    str
    """
    j = res.to_json()
    lines = [
        f"# Model audit: {source}",
        "",
        f"Baseline: **{j['baseline']['model']}** (T-L with eddy terms, constant Earth "
        "field during calibration, no lag, no diurnal, no auxiliary couplings, vector "
        "sensor taken as calibrated). Held-out calibration residual "
        f"{j['baseline']['residual_rms_nT']:.4f} nT; noise floor in the same band "
        f"{j['band_noise_floor_nT']:.4f} nT (the sensor's white noise, `noise_floor_nT`: "
        f"{j['noise_floor_nT']:.4f} nT per sample"
        + ("; an upper bound, see the notes)." if j["noise_floor_is_upper_bound"] else ")."),
        "",
        "## Findings",
        "",
    ]
    lines += _finding_lines(res)
    lines += [
        "",
        f"Extended model: **{' + '.join(j['extended_model'])}**; held-out residual "
        f"{j['unexplained_rms_nT']:.4f} nT.",
        "",
    ]
    if res.unexplained.get("note"):
        lines += ["## Unexplained", "", res.unexplained["note"] + ".", ""]
        lines += [f"- {event_text(e, int(res.t0_ns))}" for e in res.unexplained["events"]]
        lines.append("")
    lines += _null_model_lines(res)
    lines += ["## Gain", "", "| metric | baseline | extended |", "|---|---|---|"]
    for k, v in res.gain.items():
        lines.append(f"| {k} | {fmt_value(v['before'])} | {fmt_value(v['after'])} |")
    lines += _round_lines(res)
    lines += ["", "## Measured vs simulated", ""]
    captions = {
        "residual_time": "Residual vs time (calibration passes, band-passed)",
        "residual_position": "Residual vs position",
        "residual_heading": "Residual vs heading; heading error at validation intersections",
        "gain": "Gain",
    }
    for name, path in images.items():
        lines += [f"### {captions.get(name, name)}", "", f"![{name}]({path})", ""]
    if res.notes:
        lines += ["## Notes", ""] + [f"- {n}" for n in res.notes] + [""]
    return "\n".join(lines)


def _finding_lines(res: AuditResult) -> list[str]:
    """The findings' table, and for each decided outside the calibration, on what."""
    lines: list[str] = []
    if res.findings:
        lines += [
            "| effect | estimate | delta BIC | p (Holm) | held-out p | gain metric | "
            "before nT | after nT |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for f in res.findings:
            lines.append(
                f"| `{f.effect}` | {_estimate(f.estimate)} | {f.test.delta_bic:.1f} | "
                f"{f.p_adjusted:.2g} | {f.heldout.p_value:.2g} | {f.metric} | "
                f"{f.heldout.rms_before_nT:.4f} | {f.heldout.rms_after_nT:.4f} |"
            )
        for f in res.findings:
            if f.decided_outside and f.effect == "geomagnetic_gradient":
                e = f.estimate
                lines += [
                    "",
                    f"`{f.effect}` was named on the calibration legs' ramps ("
                    f"{e.get('calibration_legs_excess_ramp_rms_nT', float('nan')):.3g} nT RMS "
                    "beyond the main field's, p "
                    f"{e.get('calibration_legs_excess_p_value', float('nan')):.2g}): "
                    "the band-passed calibration sees a gradient only "
                    "through the manoeuvres' small moves; its held-out residual above only "
                    "shows it does not contradict them.",
                ]
            elif f.decided_outside and f.effect == "electrical_current":
                e = f.estimate.get("at_acceptance", f.estimate)
                lines += [
                    "",
                    f"`{f.effect}` ({e.get('channel', '')}) was named on the survey's "
                    f"{e.get('confirmed_by', 'evidence')} over the whole flight: the "
                    "calibration's band-passed tests hardly see a load switched a few times; "
                    "its held-out residual above only shows it does not contradict them.",
                ]
    else:
        lines.append("No finding: no candidate effect improves held-out data beyond noise.")
    return lines


def _round_lines(res: AuditResult) -> list[str]:
    """Every round's candidates: tests, held-out residuals and the decision."""
    lines: list[str] = []
    lines += [
        "",
        "## Candidates, round by round",
        "",
        "| round | candidate | F p (Holm) | delta BIC | held-out before / after nT | "
        "held-out p | decision |",
        "|---|---|---|---|---|---|---|",
    ]
    for r, rnd in enumerate(res.rounds, 1):
        for e in rnd:
            h = e.heldout
            lines.append(
                f"| {r} | `{e.key}` | {fmt_value(e.p_adjusted) if e.test else '-'} | "
                f"{fmt_value(e.test.delta_bic) if e.test else '-'} | "
                f"{'-' if h is None else f'{h.rms_before_nT:.4f} / {h.rms_after_nT:.4f}'} | "
                f"{'-' if h is None else fmt_value(h.p_value)} | "
                f"{'accepted' if e.accepted else e.reason} |"
            )
    return lines


def _null_model_lines(res) -> list[str]:
    """The report's null-model section: the nuisances it took, the ties left unnamed and the
    bootstrap's flight-level false-finding rate."""
    nuis = res.unexplained.get("nuisances", [])
    amb = res.unexplained.get("ambiguities", [])
    nc = res.null_calibration
    out = ["## Null model", ""]
    if nuis:
        out += [f"- {nuisance_text(n)}" for n in nuis]
    else:
        out.append("- no nuisance beyond the baseline: T-L's basis holds the carrier's field")
    out += [f"- {ambiguity_text(a)}" for a in amb]
    if nc:
        out.append(
            f"- {nc['method']} of the null model, {nc['draws']} draws: gate "
            f"{100 * nc['gate_gain']:.1f} % held-out gain, measured flight-level "
            f"false-finding rate {nc['flight_alpha']:.3f} (target {nc['alpha']:g})"
        )
    return out + [""]
