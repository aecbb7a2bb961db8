"""Micro-levelling / decorrugation (issue 19, item 3), judged against the true field.

A smooth synthetic anomaly field (15 sources, 60-300 m wide, ~16 nT RMS) is sampled along 21
north-south lines 50 m apart (0.7 m along, 0.5 m cross-track wander, 0.05 nT noise). The
corrugation is a per-line offset (1.5 nT RMS) plus a slow drift (1 nT RMS, 2.5 km period),
which no tie line saw. Errors are RMS of grid - truth over the block the lines cover, after
removing their mean (no levelling observes a common constant).
"""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.maps.microlevel import decorrugation_filter
from pipeline.simulate.corrugated import (
    error_nT,
    microlevelled,
    stripes_nT,
    survey,
    truth_field,
)


def test_corrugation_is_reduced_against_the_truth():
    """Defaults (cut-off 4 line spacings across, 10 along, clip 5 nT), 5 seeds: the grid error
    against the truth drops by >= 1.1x on every seed and >= 1.3x for the mean error (measured
    1.52, 1.91, 1.12, 1.24, 1.26; over 20 seeds median 1.25, range 1.12-2.02); its stripes
    (across-line wavelengths < 4 spacings) by >= 2x for the mean (20 seeds: 0.92 -> 0.41 nT).
    Not more: per-line errors are white across the lines, and their variance at across-line
    wavelengths beyond the cut-off (broad level shifts, not stripes) is the tie lines' job.
    The correction's RMS is 0.5-1.0 of the injected error's."""
    errs, stripes = [], []
    for seed in range(5):
        f = truth_field(seed)
        g, gm, m = microlevelled(survey(f, seed))
        before, after = error_nT(g, f), error_nT(gm, f)
        errs.append((before, after))
        stripes.append((stripes_nT(g, f), stripes_nT(gm, f)))
        assert before > 1.0
        assert before / after >= 1.1, (seed, before, after)
        assert 0.45 <= m.rms_nT / before <= 1.0
        assert m.clipped_fraction == 0.0
        s = m.summary()
        assert s["correction_rms_nT"] == pytest.approx(m.rms_nT) and s["lines"] == 21
    errs, stripes = np.array(errs), np.array(stripes)
    assert errs[:, 0].mean() / errs[:, 1].mean() >= 1.3, errs
    assert stripes[:, 0].mean() / stripes[:, 1].mean() >= 2.0, stripes


def test_uncorrugated_field_changes_little_but_not_nothing():
    """Without corrugation the grid changes by <= 0.6 nT RMS, <= 4 % of the field's RMS
    (measured 0.27, 0.31, 0.52 nT on fields of ~16 nT RMS): round geology has energy at
    short across-line wavelengths pointing across the lines too. Its error against the truth
    grows from ~0.05 nT (gridding) to <= 0.35 nT: the cost that keeps micro-levelling off by
    default."""
    for seed in range(3):
        f = truth_field(seed)
        g, gm, _ = microlevelled(survey(f, seed, 0.0, 0.0))
        change = gm.values - g.values
        change = change[np.isfinite(change)]
        rms = float(np.sqrt(np.mean(change**2)))
        e, n = np.meshgrid(*g.coordinates())
        assert rms <= 0.6 and rms <= 0.04 * np.std(f(e, n)), (seed, rms)
        assert error_nT(g, f) < 0.08
        assert error_nT(gm, f) <= 0.35


def test_a_ridge_parallel_to_the_lines_is_partly_removed():
    """A 10 nT Gaussian ridge along the lines (the geology micro-levelling cannot tell from
    corrugation): sigma 25 m (half a line spacing) loses ~40 % of its peak, 50 m ~13 %,
    100 m < 1 %. The clip bounds the loss: with clip 2 nT the 25 m ridge loses <= 2 nT."""
    lost = {}
    for sigma in (25.0, 50.0, 100.0):

        def f(e, n, s=sigma):
            return 10.0 * np.exp(-((e - 500.0) ** 2) / (2 * s**2)) + 0.0 * n

        g, gm, _ = microlevelled(survey(f, 0, 0.0, 0.0))
        e, n = g.coordinates()
        i, j = np.argmin(np.abs(n - 500.0)), np.argmin(np.abs(e - 500.0))
        lost[sigma] = 1.0 - gm.values[i, j] / g.values[i, j]
    assert 0.3 <= lost[25.0] <= 0.5
    assert 0.05 <= lost[50.0] <= 0.2
    assert lost[100.0] <= 0.01

    def f25(e, n):
        return 10.0 * np.exp(-((e - 500.0) ** 2) / (2 * 25.0**2)) + 0.0 * n

    g, gm, m = microlevelled(survey(f25, 0, 0.0, 0.0), clip_nT=2.0)
    e, n = g.coordinates()
    i, j = np.argmin(np.abs(n - 500.0)), np.argmin(np.abs(e - 500.0))
    assert g.values[i, j] - gm.values[i, j] <= 2.0 + 0.1
    assert m.clipped_fraction > 0


def test_filter_passes_stripes_and_rejects_along_line_variation():
    """The decorrugation filter keeps stripes along the lines (one line spacing period across)
    and removes a pattern that varies only along the lines or is long across them."""
    from pipeline.maps.grid import Grid

    cell = 12.5
    e, n = np.meshgrid(np.arange(80) * cell, np.arange(80) * cell)
    stripes = np.cos(2 * np.pi * e / 100.0)  # lines run north: stripes vary east
    along = np.cos(2 * np.pi * n / 100.0)
    broad = np.cos(2 * np.pi * e / 1000.0)
    for v, lo, hi in ((stripes, 0.9, 1.1), (along, 0.0, 0.05), (broad, 0.0, 0.05)):
        out = decorrugation_filter(Grid(v, 0.0, 0.0, cell), 0.0, 200.0)
        core = (slice(20, 60), slice(20, 60))
        ratio = np.std(out[core]) / np.std(v[core])
        assert lo <= ratio <= hi, ratio


def test_map_stage_micro_levels_a_simulated_survey_when_asked(tmp_path):
    """build_map with ``microlevel``: the survey lines are corrected and re-gridded and the map
    summary reports the corrugation removed (RMS of the correction). On this tie-levelled,
    uncorrugated simulated survey (7 lines) it costs accuracy: the error against the truth
    grows from ~0.05 nT to ~0.28 nT (benchmarks/bench_microlevel.py): why it is off by
    default."""
    from pipeline.compensate import FitSettings
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.maps.stage import MapSettings, build_map
    from pipeline.segment import segment_flight
    from pipeline.simulate import write_simulation
    from pipeline.simulate.truth import truth_on
    from tests.conftest import MAPPED_SURVEY, run_sim

    sim = run_sim(*MAPPED_SURVEY)
    flight = read_flight(write_simulation(sim, tmp_path / "m.mcap"))
    seg = segment_flight(flight)
    comp = run_compensation(flight, seg, FitSettings(model="agg-tl")).compensated_nT
    errors = {}
    for on in (False, True):
        mr = build_map(flight, seg, comp, MapSettings(arima=(1, 1, 1), microlevel=on))
        s = mr.summary()["microlevel"]
        truth = truth_on(sim, mr.grid, mr.frame)
        d = (mr.grid.values - truth)[np.isfinite(truth) & np.isfinite(mr.grid.values)]
        errors[on] = float(np.sqrt(np.mean((d - d.mean()) ** 2)))
        assert s["enabled"] is on
    assert s["correction_rms_nT"] > 0 and s["lines"] == 7
    assert 0 < s["grid_change_rms_nT"] < 0.5
    assert s["wavelength_m"] == pytest.approx(4 * mr.spacing_m)
    assert errors[False] < 0.08 and errors[False] < errors[True] <= 0.35, errors
    # both reports show the corrugation removed
    from pipeline.products.html import render_html
    from pipeline.products.log import map_lines
    from pipeline.products.markdown import report_markdown

    doc = {
        "aeromag_version": "test",
        "config": {"hash": "0" * 64, "version": 1, "source": "defaults"},
        "input": {"epochs": 1, "duration_s": 1.0, "sha256": "0" * 64},
        "map": mr.summary(),
    }
    removed = f"{s['correction_rms_nT']:.3f}"
    assert f"corrugation removed {removed} nT RMS" in report_markdown("x", doc, {})
    assert "Micro-levelling" in render_html("x", doc, {}) and removed in render_html("x", doc, {})
    assert any("micro-levelling removed" in text for _, text in map_lines(mr))


def test_configuration_checks_the_microlevel_keys():
    from pipeline.config import Config
    from pipeline.errors import AeromagError

    cfg = Config.load().with_values({"map.microlevel": True, "map.microlevel_along_m": 800.0})
    m = cfg.map_settings()
    assert m.microlevel and m.microlevel_along_m == 800.0
    for key, bad in (("map.microlevel_clip_nT", 0.0), ("map.microlevel_wavelength_m", -1.0)):
        with pytest.raises(AeromagError, match=key.split(".")[1]):
            Config.load().with_values({key: bad}).validate()
