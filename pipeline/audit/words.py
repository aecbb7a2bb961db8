"""The audit's results in words: one sentence per event, nuisance and tie, shared by its
report, run log and console and by the post-flight reports. A leaf: it imports nothing of
the products, which import it."""

from __future__ import annotations

from typing import Any

# what data would tell a tie's explanations apart (the physics that separates them)
SEPARATED_BY = {
    frozenset({"sensor_lag", "eddy_decay"}): (
        "A late sensor delays the geology along the lines and decaying eddy currents do "
        "not: straight lines flown both ways over ground with gradients (or the sensor's "
        "filter setting) decide"
    ),
}


def plain(text: str) -> str:
    """A sentence of this module without its Markdown code marks, for the run log, the
    console, ``/audit/finding`` and HTML."""
    return text.replace("`", "")


def fmt_value(v: Any) -> str:
    """A JSON value in short: floats to 4 significant digits, None as ``-``."""
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list):
        return "[" + ", ".join(fmt_value(x) for x in v) + "]"
    return str(v)


def event_text(e: dict, t0_ns: int) -> str:
    """One ``unexplained.events`` entry in words; times in s from ``t0_ns`` (the flight's
    first epoch, ns)."""
    return (
        f"{e['kind']}: {e['size_nT']:.2f} nT, from {(e['start_ns'] - t0_ns) / 1e9:.1f} s to "
        f"{(e['end_ns'] - t0_ns) / 1e9:.1f} s ({e['evidence']})"
    )


def nuisance_text(n: dict) -> str:
    """One ``unexplained.nuisances`` entry in words: the null model's group, its held-out
    gain and estimate."""
    return f"nuisance `{n['name']}`: held-out gain {100 * n['heldout_gain']:.1f} %" + "".join(
        f", {k} {fmt_value(v)}" for k, v in n["estimate"].items()
    )


def unexplained_items(unexplained: dict, t0_ns: int) -> list[str]:
    """What the audit left unexplained, one sentence each (for the post-flight reports): the
    events, the null model's nuisances and the ties."""
    return (
        [event_text(e, t0_ns) for e in unexplained.get("events", [])]
        + [nuisance_text(n) for n in unexplained.get("nuisances", [])]
        + [ambiguity_text(a) for a in unexplained.get("ambiguities", [])]
    )


def ambiguity_text(a: dict) -> str:
    """One ``unexplained.ambiguities`` entry in words: the rivals' held-out gains, how far
    apart they put the lines and what data would separate them."""
    gains = ", ".join(f"`{k}` {100 * v:.1f} %" for k, v in a["heldout_gain"].items())
    text = f"ambiguity, nothing named: {gains} of the held-out residual each"
    diff = a.get("survey_difference_nT")
    if diff is not None:
        text += (
            f"; their compensated fields differ by {diff:.3g} nT RMS along the lines "
            "(each line's level removed)"
        )
    why = SEPARATED_BY.get(frozenset(a["candidates"]))
    return text + (f". {why}" if why else "")
