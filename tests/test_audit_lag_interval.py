"""The lag's interval (``pipeline.audit.evidence.lag.lag_interval``): delete-a-group
jackknives over the calibration's kinds of manoeuvre and its headings
(``AuditContext.jackknife_groups``), the wider, checked against the jackknife's closed form
with the refits replaced by costs of known least."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

import pipeline.audit.evidence.lag as lag_module
from pipeline.audit.context import AuditContext
from pipeline.audit.extended import ModelSpec

LAG_S = 0.12


def _ctx(kinds: list[str], headings: list[str]):
    """A calibration of 40 epochs per (kind, heading) pair, five stratified folds."""
    pairs = [(k, h) for k in kinds for h in headings]
    kind = np.repeat([k for k, _ in pairs], 40)
    heading = np.repeat([h for _, h in pairs], 40)
    fold = np.arange(kind.size) % 5
    mask = np.ones(kind.size, bool)
    ctx = SimpleNamespace(
        mask=mask,
        manoeuvre_kind=kind,
        leg_heading=heading,
        folds=[(fold != k, fold == k) for k in range(5)],
        s=SimpleNamespace(max_lag_s=1.0),
    )
    ctx.jackknife_groups = lambda: AuditContext.jackknife_groups(ctx)
    return ctx


def _with_shifts(monkeypatch, ctx, shift_s: dict[str, float]):
    """Each refit's cost is least at LAG_S plus the shifts of the groups it keeps whole
    (the mean shift of its epochs): what misfit that differs between groups does."""
    label = np.char.add(np.char.add(ctx.manoeuvre_kind, "/"), ctx.leg_heading)

    def costs_for(ctx_, spec, keep, key):
        kept = label[keep]
        centre = LAG_S + np.mean([sum(shift_s.get(p, 0.0) for p in lab.split("/")) for lab in kept])
        return lambda taus: (np.asarray(taus, float) - centre) ** 2 + 1.0

    monkeypatch.setattr(lag_module, "_lag_costs", costs_for)


def _jackknife(values: list[float]) -> float:
    x = np.asarray(values, float)
    g = x.size
    return float(stats.t.ppf(0.975, g - 1) * np.sqrt((g - 1) / g * np.sum((x - x.mean()) ** 2)))


@pytest.mark.parametrize(
    "shift",
    [
        {"roll": 0.004, "pitch": -0.003, "yaw": 0.001, "N": 0.0005},  # the kinds' wider
        {"roll": 0.0005, "N": 0.006, "S": -0.002},  # the headings'
    ],
)
def test_the_interval_is_the_wider_of_the_two_jackknives(monkeypatch, shift):
    kinds, headings = ["roll", "pitch", "yaw", "turn"], ["N", "E", "S", "W"]
    ctx = _ctx(kinds, headings)
    _with_shifts(monkeypatch, ctx, shift)
    lo, hi = lag_module.lag_interval(ctx, ModelSpec(), LAG_S)
    # leaving a kind out moves the mean shift by -(its shift - the mean of the others)/3
    by_kind = [
        LAG_S
        + np.mean([shift.get(k, 0.0) for k in kinds if k != out])
        + np.mean([shift.get(h, 0.0) for h in headings])
        for out in kinds
    ]
    by_heading = [
        LAG_S
        + np.mean([shift.get(k, 0.0) for k in kinds])
        + np.mean([shift.get(h, 0.0) for h in headings if h != out])
        for out in headings
    ]
    half = max(_jackknife(by_kind), _jackknife(by_heading))
    assert (hi - lo) / 2 == pytest.approx(half, rel=1e-2)
    assert (lo + hi) / 2 == pytest.approx(LAG_S, abs=1e-9)


def test_without_misfit_between_groups_the_interval_is_narrow(monkeypatch):
    ctx = _ctx(["roll", "pitch", "yaw"], ["N", "S"])
    _with_shifts(monkeypatch, ctx, {})
    lo, hi = lag_module.lag_interval(ctx, ModelSpec(), LAG_S)
    assert hi - lo < 1e-3


def test_a_calibration_of_one_kind_on_one_heading_uses_the_folds(monkeypatch):
    ctx = _ctx(["roll"], ["N"])
    seen = []

    def costs_for(ctx_, spec, keep, key):
        seen.append(key)
        return lambda taus: (np.asarray(taus, float) - LAG_S) ** 2

    monkeypatch.setattr(lag_module, "_lag_costs", costs_for)
    assert lag_module.lag_interval(ctx, ModelSpec(), LAG_S) is not None
    assert seen == [f"fold{k}" for k in range(5)]


def test_the_widest_interval_is_taken_per_key_and_per_entry():
    from pipeline.audit.crossval import widest_ci95

    a = {"k": [1.0, 2.0], "v": [[0.0, 1.0], [0.0, 3.0]], "name": None}
    b = {"k": [0.5, 2.1], "v": [[0.0, 2.0], None], "name": None}
    got = widest_ci95([a, b])
    assert got["k"] == pytest.approx([0.5, 2.1])
    assert got["v"][0] == pytest.approx([0.0, 2.0]) and got["v"][1] == pytest.approx([0.0, 3.0])
    assert got["name"] is None
