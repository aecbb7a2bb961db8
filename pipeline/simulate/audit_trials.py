"""Audit trials: a randomised flight hiding one catalogue effect (or nothing, or a step in the
carrier's permanent field outside the catalogue), audited from its recording alone and scored
against the simulator's truth. The test bed of ``tests/test_audit_variety.py`` and
``benchmarks/bench_audit_variety.py``.

Each flight is drawn by :func:`pipeline.simulate.random_flight_overrides`; the effects do not
take the audit's functional forms only (a lag is a pure delay or a first-order response, a
current coupling may drift with temperature).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from pipeline.audit import EFFECTS, run_audit
from pipeline.compensate.terms import direction_cosines
from pipeline.io.reader import read_flight
from pipeline.segment import segment_flight
from pipeline.simulate.scenario import Scenario
from pipeline.simulate.simulator import simulate, write_simulation
from pipeline.simulate.variety import TIED_SURVEY, override_value, random_flight_overrides

CLASSES = ("none", *EFFECTS, "step")
# an unexplained event within this of a hidden step counts as finding it
EVENT_WINDOW_S = 120.0


# effect sizes drawn with ``sizes``: log-uniform, from under what matters to a survey (a
# survey error of SURVEY_ERROR_MATTERS_NT, see survey_error_nT) to well above it
LAG_S = (0.02, 0.3)
COUPLING_NT_PER_A = (0.1, 6.0)
# the size of survey error that matters: the 0.1 nT noise envelope high-resolution survey
# specifications allow
SURVEY_ERROR_MATTERS_NT = 0.1


def hidden_overrides(kind: str, rng: np.random.Generator, sizes: bool = False) -> list[str]:
    """Scenario overrides hiding ``kind`` (a catalogue effect), with varied forms; with
    ``sizes`` the lag and the current coupling are drawn log-uniform over :data:`LAG_S` and
    :data:`COUPLING_NT_PER_A` (after the other draws: without it the flights are unchanged)."""
    if kind in ("none", "step"):
        return []
    out = [f"effects.{kind}.enabled=true"]
    if kind == "sensor_lag":
        out.append(f'effects.sensor_lag.response="{rng.choice(["delay", "first_order"])}"')
    if kind == "electrical_current" and rng.random() < 0.5:
        out.append(
            f"effects.electrical_current.temperature_coefficient_per_K={rng.uniform(0.005, 0.03)!r}"
        )
    if sizes and kind == "sensor_lag":
        out.append(f"effects.sensor_lag.lag_s={float(np.exp(rng.uniform(*np.log(LAG_S))))!r}")
    if sizes and kind == "electrical_current":
        k = float(np.exp(rng.uniform(*np.log(COUPLING_NT_PER_A))))
        out.append(f"effects.electrical_current.coupling_nT_per_A={k!r}")
    return out


def survey_error_nT(kind: str, sim) -> float | None:
    """What the hidden effect, left uncompensated, does to the survey and tie lines (nT RMS):
    a lag of tau reads the field tau late, an error of tau dB/dt with B the true field
    along the track; a current coupling k along body direction d adds k (u . d) I with u
    the field's direction, less its mean (a constant is the carrier's permanent field).
    None for the other classes."""
    if kind not in ("sensor_lag", "electrical_current"):
        return None
    t = (sim.series["time_ns"] - sim.start_ns) / 1e9
    lines = np.zeros(t.size, bool)
    for g in sim.truth["segments"]:
        if g["label"] in ("survey", "tie"):
            lines |= (t >= float(g["start_s"])) & (t < float(g["end_s"]))
    if lines.sum() < 10:
        return None
    if kind == "sensor_lag":
        tau = float(sim.scenario.effect("sensor_lag")["lag_s"])
        err = tau * np.gradient(sim.series["earth_total_nT"], t)
    else:
        cur = sim.scenario.effect("electrical_current")
        aux = sim.streams[f"/aux/{cur['channel']}"]
        current = np.interp(t, aux["t"], next(iter(aux["cols"].values())))
        d = np.asarray(cur["direction_body"], float)
        u = unit_field_at(sim, t)
        err = float(cur["coupling_nT_per_A"]) * (u @ (d / np.linalg.norm(d))) * current
    e = err[lines]
    return float(np.sqrt(np.mean((e - e.mean()) ** 2)))


def unit_field_at(sim, t_s: np.ndarray) -> np.ndarray:
    """The simulated fluxgate's field direction (n, 3), body frame, at times ``t_s`` (s from
    the start), interpolated from ``/mag/vector``."""
    v = sim.streams["/mag/vector"]
    vec = np.stack([np.interp(t_s, v["t"], v["cols"][k]) for k in ("x_nT", "y_nT", "z_nT")], -1)
    return direction_cosines(vec)


def add_permanent_step(sim, rng: np.random.Generator) -> dict:
    """A step of 3-8 nT in the carrier's permanent field (body frame) at a random time in
    the middle of the survey: the scalar reading changes by u . dp afterwards."""
    s = sim.streams["/mag/scalar"]
    survey = [g for g in sim.truth["segments"] if g["label"] == "survey"]
    t0, t1 = float(survey[0]["start_s"]), float(survey[-1]["end_s"])
    t_step = float(rng.uniform(t0 + 0.3 * (t1 - t0), t0 + 0.7 * (t1 - t0)))
    dp = rng.normal(size=3)
    dp *= rng.uniform(3.0, 8.0) / np.linalg.norm(dp)
    u = unit_field_at(sim, s["t"])
    after = s["t"] > t_step
    s["cols"]["total_nT"] = s["cols"]["total_nT"] + after * (u @ dp)
    return {"time_s": t_step, "dp_nT": dp.tolist()}


def within_ci(effect: str, f: dict, truth: dict) -> list[bool]:
    """Does each 95 % interval of a finding cover the simulator's truth?"""
    ci, out = f.get("estimate_ci95") or {}, []

    def cover(key, value, tol=0.0):
        iv = ci.get(key)
        if iv is not None:
            out.append(iv[0] - tol <= value <= iv[1] + tol)

    if effect == "geomagnetic_gradient":
        # the estimate is the total field's gradient: the injected one plus the main field's
        # own (IGRF), which the finding reports beside it
        g = truth["effective"]["gradient_nT_per_m"]
        est = f.get("estimate") or {}
        cover("east_nT_per_m", g[0] + est.get("main_field_east_nT_per_m", 0.0))
        cover("north_nT_per_m", g[1] + est.get("main_field_north_nT_per_m", 0.0))
    elif effect == "sensor_lag":
        cover("lag_s", truth["effective"]["sensor_lag_s"])
    elif effect == "diurnal":
        # the simulator puts the same variation into the airborne and the base reading
        cover("base_coefficient", 1.0)
    elif effect == "electrical_current":
        # only a finding on the channel that carries the coupling has a truth to cover; one
        # that drifts with the temperature is covered at its flight mean, what one constant
        # coupling estimates
        cur = truth["effects"]["electrical_current"]
        k = truth["effective"].get("current_coupling_nT_per_A", cur["coupling_nT_per_A"])
        if str((f.get("estimate") or {}).get("channel", "")).endswith(cur["channel"]):
            cover("nT_per_unit", k)
    return out


def one_flight(kind: str, seed: int, folder: Path, sizes: bool = False, **ranges) -> dict:
    """Simulate, audit and score one flight; ``ranges`` narrow
    :func:`random_flight_overrides`' draws (the CI subset flies milder flights); ``sizes``
    draws the lag's and the current's sizes (:func:`hidden_overrides`)."""
    rng = np.random.default_rng(seed)
    overrides = random_flight_overrides(rng, **ranges) + hidden_overrides(kind, rng, sizes)
    profile = override_value(overrides, "profile")
    overrides += TIED_SURVEY[profile]
    sim = simulate(Scenario.load("uav-small", overrides), int(rng.integers(2**31)))
    step = add_permanent_step(sim, rng) if kind == "step" else None
    path = write_simulation(sim, folder / f"{kind}-{seed}.mcap")
    t = time.perf_counter()
    flight = read_flight(path)
    res = run_audit(flight, segment_flight(flight)).to_json()
    named = sorted(f["effect"] for f in res["findings"])
    events = res["unexplained"]["events"]
    hit = None
    if step is not None:
        ts = int(flight.time_ns[0]) + step["time_s"] * 1e9
        w = EVENT_WINDOW_S * 1e9
        hit = any(e["start_ns"] - w <= ts <= e["end_ns"] + w for e in events)
    cover = []
    for f in res["findings"]:
        if f["effect"] == kind:
            cover += within_ci(kind, f, sim.truth)
    path.unlink()
    return {
        "kind": kind,
        "seed": seed,
        "named": named,
        "events": len(events),
        "hit": hit,
        "event_kinds": [e["kind"] for e in events],
        "event_evidence": [e["evidence"] for e in events],
        "estimates": {f["effect"]: f["estimate"] for f in res["findings"]},
        "ci95": {f["effect"]: f.get("estimate_ci95") for f in res["findings"]},
        "truth": {
            "effects": {k: sim.truth["effects"][k] for k in sim.truth["enabled_effects"]},
            "effective": sim.truth.get("effective"),
        },
        "covered": cover,
        "audit_s": time.perf_counter() - t,
        "gap": res["baseline"]["generalization_gap"],
        "noise_floor_nT": res["noise_floor_nT"],
        "noise_floor_is_upper_bound": res.get("noise_floor_is_upper_bound"),
        "true_noise_nT": float(override_value(overrides, "sensors.scalar_noise_nT")),
        "vibration": override_value(overrides, "interference.outside_basis.vibration_nT")
        is not None,
        "overrides": overrides,
        "survey_error_nT": survey_error_nT(kind, sim),
        "ambiguities": res["unexplained"].get("ambiguities", []),
        "null_p_values": null_p_values(res),
    }


def null_p_values(res: dict) -> dict:
    """The p-values a flight with nothing hidden should spread uniformly: the whole
    selection's maximum statistic against the null bootstrap, and each first-round
    candidate's nested F-test and held-out test (before any rule or gate)."""
    first = res["rounds"][0] if res.get("rounds") else []
    nc = res.get("null_calibration") or {}
    return {
        "max_statistic": nc.get("max_statistic_p_value"),
        "f_test": {c["key"]: c.get("p_value") for c in first},
        "heldout": {c["key"]: (c.get("heldout") or {}).get("p_value") for c in first},
    }


def correct(row: dict) -> bool:
    """Named exactly right: the hidden catalogue effect alone; nothing for clean and step
    flights (a step must show as an event instead)."""
    if row["kind"] == "none":
        return row["named"] == []
    if row["kind"] == "step":
        return row["named"] == [] and bool(row["hit"])
    return set(row["named"]) == {row["kind"]}
