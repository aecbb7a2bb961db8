"""tl-plus and tl-nn (issue 36): tl18's extensions, chosen on held-out calibration.

Judged on a second calibration box the fit never saw (the calibration-only scenario flies
two; the models are fitted on the first) and, where the simulator adds interference outside
the tl18 basis, against tl18 on that box: not against the models' own residuals.

* nothing outside the basis: neither extension is worse than tl18 by more than 2 % on the
  second box (a handful of seeds here; ``-m slow`` runs 30);
* eddy currents that decay with 0.5 s: tl-plus takes the eddy-decay group with a time
  constant near the true one and removes most of what tl18 leaves on the second box;
  tl-nn, when its held-out gain passes the fold-level test, beats tl18 there too;
* the command's contract: summary keys, channels, one-line errors (exit 2).
"""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import numpy as np
import pytest

from pipeline.compensate import FitSettings, Measurements, bandpassed, fit_compensation
from pipeline.compensate.heldout import block_folds, filter_support_s, fold_masks
from pipeline.io.reader import read_flight, read_topics
from pipeline.segment import segment_flight
from pipeline.simulate import write_simulation
from tests.cli import run as cli
from tests.conftest import FIXTURES, run_sim

MAX_WORSE = 1.02  # issue 36: an extension may cost at most 2 % against tl18 held out


def _two_boxes(seed: int, overrides: list[str] | None = None):
    """A two-box calibration flight: (measurements, first box's epochs, second box's)."""
    sim = run_sim("calibration-only", seed, overrides or [])
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "s.mcap"))
    passes = segment_flight(fl).passes()
    meas = Measurements.from_flight(fl)
    fit, test = (np.zeros(meas.time_s.size, bool) for _ in range(2))
    fit[passes[0]] = True
    test[passes[1]] = True
    return meas, fit, test


def _second_box_rms(meas, fit, test, model: str):
    """(band-passed RMS of the compensated field on the second box (nT), fitted model)."""
    m = fit_compensation(meas, fit, FitSettings(model))
    comp, _ = m.compensate(meas)
    bp = bandpassed(meas.time_s, np.where(test, comp, np.nan), (0.1, 0.9), 4)
    return float(np.sqrt(np.nanmean(bp[test] ** 2))), m


def _no_worse(seed: int, models: tuple[str, ...]) -> None:
    meas, fit, test = _two_boxes(seed)
    base, _ = _second_box_rms(meas, fit, test, "tl18")
    for model in models:
        rms, m = _second_box_rms(meas, fit, test, model)
        ext = m.extension
        assert rms <= MAX_WORSE * base, (seed, model, rms, base, ext["reason"])
        if not m.used:  # tl18's own field, not the tl18 part of the extension's fit
            assert abs(rms - base) <= 1e-9 * base, (seed, model, rms, base)
        # what the product applies is never worse than tl18 on its own held-out blocks
        applied = (
            ext["candidate_heldout_residual_nT"] if m.used else ext["tl18_heldout_residual_nT"]
        )
        assert applied <= ext["tl18_heldout_residual_nT"] * (1 + 1e-9)


@pytest.mark.parametrize("seed", [2, 3])
def test_tl_plus_no_worse_than_tl18_inside_the_basis(seed):
    _no_worse(seed, ("tl-plus",))


def test_tl_nn_no_worse_than_tl18_inside_the_basis():
    _no_worse(4, ("tl-plus", "tl-nn"))


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(10, 40))
def test_extensions_no_worse_than_tl18_inside_the_basis_30_seeds(seed):
    _no_worse(seed, ("tl-plus", "tl-nn"))


def test_extensions_take_decaying_eddy_currents():
    meas, fit, test = _two_boxes(1, ["interference.outside_basis.eddy_lag_nT=0.5"])
    base, _ = _second_box_rms(meas, fit, test, "tl18")
    plus, m = _second_box_rms(meas, fit, test, "tl-plus")
    assert m.used and "eddy_decay" in m.groups, m.extension["reason"]
    assert 0.25 <= m.tau_s <= 1.0  # the simulator's 0.5 s, on a grid of factor ~1.9
    assert plus < 0.5 * base, (plus, base)
    groups = m.extension["term_groups"]
    assert groups["eddy_decay"]["selected"] and groups["eddy_decay"]["reduction_pct"] > 20
    nn, m = _second_box_rms(meas, fit, test, "tl-nn")
    # the learner's held-out gain on this calibration is a few percent, spread unevenly over
    # the folds: the fold-level test may keep tl18, and then the field is tl18's
    if m.used:
        assert nn < 0.95 * base, (nn, base)
    else:
        assert "over the folds" in m.extension["reason"], m.extension["reason"]
        assert abs(nn - base) <= 1e-9 * base
    imp = m.extension["feature_importance"]
    assert set(imp) >= {"tl_terms", "tl_rates", "attitude", "attitude_rates"}
    assert abs(sum(v["share"] for v in imp.values()) - 1.0) < 1e-9


def test_heldout_folds_are_buffered_by_the_filter_support():
    support = filter_support_s((0.1, 0.9), 10.0, 4)
    assert 4.0 < support < 20.0
    # a physical time: the same at another sample rate
    assert abs(filter_support_s((0.1, 0.9), 20.0, 4) - support) < 0.2
    t = np.arange(0.0, 600.0, 0.1)
    mask = (t > 50) & (t < 550)
    fold = block_folds(mask, 5)
    assert set(np.unique(fold)) == {-1, 0, 1, 2, 3, 4}
    for k in range(5):
        train, test = fold_masks(t, fold, k, support)
        assert not (train & test).any()
        gap = np.min(np.abs(t[train][:, None] - t[test][None, ::50]))
        assert gap > support


def test_compensate_tl_plus_contract(tmp_path, box_path):
    out, js = tmp_path / "o.mcap", tmp_path / "o.json"
    res = cli(
        "compensate", str(box_path), "--out", str(out), "--json", str(js), "--model", "tl-plus"
    )
    assert res.returncode == 0, res.stderr
    s = json.loads(js.read_text())
    c = s["compensation"]["tl-plus"]
    assert s["compensation"]["final"] == "tl-plus"
    assert c["heldout_residual_nT"] > 0
    assert {"eddy_decay", "second_order"} <= set(c["term_groups"])
    assert isinstance(c["extension"]["used"], bool) and c["extension"]["reason"]
    topics = set(read_topics(out).topics)
    assert {"/mag/compensated", "/mag/compensated/tl-plus", "/compensation/model"} <= topics


def test_compensate_extensions_bad_input(tmp_path, box_path):
    src = FIXTURES / "box_scalar_vector_only.mcap"  # no attitude, no GNSS
    args = ["--calibration", "all", "--model", "tl-nn"]
    res = cli(
        "compensate",
        str(src),
        "--out",
        str(tmp_path / "a.mcap"),
        "--json",
        str(tmp_path / "a.json"),
        *args,
    )
    assert res.returncode == 2 and "/ins/attitude" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "a.mcap").exists() and not (tmp_path / "a.json").exists()
    args = ["--calibration", "0:60", "--model", "tl-plus"]
    res = cli(
        "compensate",
        str(box_path),
        "--out",
        str(tmp_path / "b.mcap"),
        "--json",
        str(tmp_path / "b.json"),
        *args,
    )
    assert res.returncode == 2 and "calibration" in res.stderr, res.stderr
    assert len(res.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "b.mcap").exists()


def test_audit_nuisances_are_read_defensively():
    from pipeline.compensate.plus import audit_nuisances

    assert audit_nuisances(None) == {} and audit_nuisances({}) == {}
    assert audit_nuisances({"unexplained": None}) == {}
    assert audit_nuisances({"unexplained": {"nuisances": "eddy_decay"}}) == {}
    got = audit_nuisances(
        {
            "unexplained": {
                "nuisances": [
                    {"name": "eddy_decay", "heldout_gain": 0.3, "estimate": {"tau_s": 0.4}},
                    {"name": "current:cur_strobe", "heldout_gain": 0.5},
                    {"name": "current:"},  # no channel
                    {"name": "wobble"},  # not a tl-plus group
                    {"heldout_gain": 0.1},  # no name
                    "second_order",  # not a record
                ]
            }
        }
    )
    assert set(got) == {"eddy_decay", "current:cur_strobe"}
    assert got["eddy_decay"] == {"heldout_gain": 0.3, "estimate": {"tau_s": 0.4}}
    assert got["current:cur_strobe"]["estimate"] is None


def test_tl_plus_tries_the_audits_groups_first_and_the_report_says_so():
    from pipeline.compensate.stage import run_compensation
    from pipeline.products.markdown import extension_lines

    audit = {"unexplained": {"nuisances": [{"name": "eddy_decay", "heldout_gain": 0.6}]}}
    sim = run_sim("calibration-only", 1, ["interference.outside_basis.eddy_lag_nT=0.5"])
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "s.mcap"))
    run = run_compensation(fl, segment_flight(fl), FitSettings("tl-plus"), audit=audit)
    s = run.summary()
    assert s["extension"]["seeded_by_audit"] == ["eddy_decay"]
    g = s["term_groups"]["eddy_decay"]
    assert g["selected"] and g["seeded_by_audit"] == {"heldout_gain": 0.6, "estimate": None}
    # the seeded group was tested on its own: its Holm adjustment is over one hypothesis
    assert g["p_value_folds_adjusted"] < 0.01
    assert "crossover_rms_nT" in s and s["heldout_residual_nT"] > 0
    lines = extension_lines({"final": "tl-plus", "tl-plus": s})
    assert any("named by the audit): eddy_decay" in x for x in lines)
    assert any("term groups: eddy_decay" in x for x in lines)
    # no survey lines: the heading-level correction has no crossovers to confirm it
    assert not s["extension"]["heading_levels"]["used"]
    assert any("heading levels of the calibration legs" in x for x in lines)
    nn = {
        "extension": {"used": True, "reason": "held-out residual lower"},
        "feature_importance": {
            "aux:cur_strobe": {"heldout_rms_increase_nT": 0.024, "share": 0.7},
            "tl_rates": {"heldout_rms_increase_nT": 0.010, "share": 0.3},
        },
    }
    (imp,) = [x for x in extension_lines({"tl-nn": nn}) if "importance" in x]
    assert imp.index("aux:cur_strobe 0.0240 nT (70 %)") < imp.index("tl_rates")


def test_agg_tl_takes_the_calibration_legs_gradient():
    from pipeline.compensate.stage import run_compensation

    over = [
        "effects.geomagnetic_gradient.enabled=true",
        "effects.geomagnetic_gradient.east_nT_per_m=-0.25",
        "effects.geomagnetic_gradient.north_nT_per_m=0.15",
        "effects.geomagnetic_gradient.up_nT_per_m=0.0",
        # crews fly the box over quiet ground: the legs measure the crust's gradient there too
        "anomaly.quiet_calibration_m=400",
    ]
    sim = run_sim("uav-small", 5, over)
    fl = read_flight(write_simulation(sim, Path(tempfile.mkdtemp()) / "g.mcap"))
    seg = segment_flight(fl)
    # the default fits the gradient from the position columns; "legs" takes the legs' value
    assert run_compensation(fl, seg, FitSettings("agg-tl")).summary().get("gradient_evidence") in (
        None,
        {},
    )
    run = run_compensation(fl, seg, FitSettings("agg-tl", agg_gradient="legs"))
    ev = run.summary()["gradient_evidence"]
    assert ev["source"] == "calibration legs", ev
    assert ev["east_nT_per_m"] == pytest.approx(-0.25, abs=0.01)
    assert ev["north_nT_per_m"] == pytest.approx(0.15, abs=0.01)
    g = run.summary()["gradient_nT_per_m"]
    assert (g["east"], g["north"]) == (ev["east_nT_per_m"], ev["north_nT_per_m"])
    # without a segmentation there are no legs: the band-passed fit alone, as before
    mask = np.zeros(fl.data["time_s"].size, bool)
    for span in seg.passes():
        mask[span] = True
    _agg_auto_chooses_by_held_out_data(fl, seg, mask, ev)
    plain = fit_compensation(
        Measurements.from_flight(fl), mask, FitSettings("agg-tl", agg_gradient="legs")
    )
    assert plain.gradient_evidence == {}


def _agg_auto_chooses_by_held_out_data(fl, seg, mask, legs_evidence):
    """``agg_gradient = "auto"`` keeps the legs' gradient on a quiet box, and takes the
    band-passed fit's when the legs' estimate is corrupted: a base-station reading that
    ramps with position (0.2 nT/m east), which the legs take out of their field and read
    as a gradient 0.2 nT/m off."""
    from pipeline.compensate.agg_legs import _enu
    from pipeline.compensate.stage import calibration_legs, run_compensation

    ev = run_compensation(fl, seg, FitSettings("agg-tl", agg_gradient="auto")).summary()[
        "gradient_evidence"
    ]
    assert ev["choice"] == "legs" and ev["source"] == "calibration legs", ev
    assert ev["east_nT_per_m"] == pytest.approx(legs_evidence["east_nT_per_m"], abs=1e-9)
    assert ev["heldout"]["p_fit_better_folds"] > 0.01
    meas = Measurements.from_flight(fl)
    s = FitSettings("agg-tl", agg_gradient="auto")
    legs, base = calibration_legs(fl, seg, mask, s)
    ref = {
        "latitude_deg": float(np.mean(meas.lat_deg[mask])),
        "longitude_deg": float(np.mean(meas.lon_deg[mask])),
        "altitude_m": float(np.mean(meas.alt_m[mask])),
    }
    ramp = 0.2 * _enu(meas, ref)[:, 0] + (0.0 if base is None else np.nan_to_num(base))
    bad = fit_compensation(meas, mask, s, legs, ramp).gradient_evidence
    assert bad["choice"] == "fit" and bad["source"] == "band-passed fit", bad
    assert bad["east_nT_per_m"] == bad["fit_east_nT_per_m"]
    # the legs read the ramp as gradient (less the part the base's 60-s smoothing takes)
    assert bad["legs_east_nT_per_m"] == pytest.approx(bad["fit_east_nT_per_m"] - 0.2, abs=0.05)
    assert bad["heldout"]["fit_heldout_residual_nT"] < bad["heldout"]["legs_heldout_residual_nT"]


def test_eddy_decay_columns_span_a_lagging_eddy_current():
    """A lagging eddy current E lowpass_tau(dB/dt) (:mod:`pipeline.physics.outside_basis`)
    in the magnitude, u . E lowpass_tau(dB/dt), is a combination of the eddy-decay columns
    at that tau to rounding, while the response of tl18's products u_i dB_j (what the columns
    filtered before) leaves a share of it as the field direction turns in the manoeuvres."""
    from pipeline.compensate.nuisance import eddy_decay
    from pipeline.compensate.plus import group_columns
    from pipeline.compensate.terms import direction_cosines, tl18_terms
    from pipeline.physics.outside_basis import lagging_eddy_vector

    rate_hz, tau_s = 10.0, 0.6
    t = np.arange(0.0, 120.0, 1.0 / rate_hz)
    roll, pitch = np.radians(15.0) * np.sin(t / 1.3), np.radians(10.0) * np.sin(t / 2.1 + 1)
    b = 50_000.0 * np.column_stack(
        [np.cos(pitch) * 0.4, np.sin(roll) * 0.6 + 0.2 * np.sin(pitch), np.cos(roll) * 0.8]
    )
    e_s = np.random.default_rng(3).normal(0, 0.002, (3, 3))
    db_per_sample = np.gradient(b, axis=0)
    # the lagging current's field with the derivative per sample (tl18's eddy scale)
    lag = lagging_eddy_vector(db_per_sample, 1.0 / rate_hz, tau_s, e_s)  # outside tl18
    u = direction_cosines(b)
    y = np.einsum("ij,ij->i", u, lag + db_per_sample @ e_s.T)
    outside_nT = float(np.sqrt(np.mean(np.einsum("ij,ij->i", u, lag) ** 2)))
    meas = Measurements(t, np.zeros(t.size), b)
    new, _ = group_columns("eddy_decay", meas, tau_s)
    k, names = tl18_terms(b)
    old = eddy_decay(k[:, [i for i, n in enumerate(names) if n.startswith("eddy_")]], t, tau_s)

    def left(cols):
        coef, *_ = np.linalg.lstsq(cols, y, rcond=None)
        return float(np.sqrt(np.mean((y - cols @ coef) ** 2))) / outside_nT  # share left

    assert left(new) < 1e-6
    assert left(old) > 0.02
