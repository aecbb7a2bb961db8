"""tl-plus's heading-level correction (pipeline/compensate/heading_levels.py): a permanent
field fitted to the calibration legs' levels, kept when the survey-tie crossovers confirm it.

The fit is checked against an analytic box (levels made by a known permanent field and a
crust level, legs at four headings); the crossover test against its exact permutation
distribution; and the whole step on a simulated flight whose heading error comes from
physics tl18 and the correction do not model (a lagging eddy current and second-order
induction), judged against the simulator's true field.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from pipeline.compensate.heading_levels import crossover_improvement_p, fit_heading_correction

RATE_HZ = 10.0


def _box(
    p_nT, crust_nT=30.0, noise_nT=0.0, headings_deg=(0, 90, 180, 270), seed=0, gradient=(0, 0)
):
    """A box of 1 km legs flown at 20 m/s, two per heading (each heading on its own side),
    level attitude with a little yaw jitter: the reduced field is the crust's level, the
    permanent field's projection and a horizontal gradient (nT/m) across the box."""
    rng = np.random.default_rng(seed)
    b_h, b_z = 20_000.0, 45_000.0
    t0, rows = 0.0, []
    for k, h in enumerate(np.repeat(headings_deg, 2)):
        n = int(50 * RATE_HZ)
        psi = np.radians(h + rng.normal(0, 2, n))
        b = np.column_stack([b_h * np.cos(psi), -b_h * np.sin(psi), np.full(n, b_z)])
        u = b / np.linalg.norm(b, axis=1, keepdims=True)
        t = t0 + np.arange(n) / RATE_HZ
        t0 = t[-1] + 20.0
        # a clockwise box: north leg on the west side, east leg on the north side, ...
        along = -500.0 + 20.0 * (t - t[0])
        side = {0: (-500.0, None), 90: (None, 500.0), 180: (500.0, None), 270: (None, -500.0)}
        e_fix, n_fix = side[int(h) % 360]
        sgn = 1.0 if int(h) % 360 in (0, 90) else -1.0
        east = np.full(n, e_fix) if e_fix is not None else sgn * along
        north = np.full(n, n_fix) if n_fix is not None else sgn * along
        y = (
            crust_nT
            + u[:, :2] @ np.asarray(p_nT)
            + gradient[0] * east
            + gradient[1] * north
            + rng.normal(0, noise_nT, n)
        )
        head = np.full(n, list(headings_deg).index(h))
        rows.append((y, u, np.full(n, k), head, t, east, north))
    return tuple(np.concatenate(c) for c in zip(*rows, strict=True))


def test_the_permanent_field_is_recovered_from_the_legs_levels():
    p = np.array([1.7, -0.9])
    corr = fit_heading_correction(*_box(p)[:5])
    assert corr is not None
    assert corr.legs == 8 and corr.headings == 4
    np.testing.assert_allclose(corr.p_nT, p, atol=1e-6)
    assert corr.residual_spread_nT < 1e-6 < corr.level_spread_nT
    # with noise on each epoch the leg means still carry it
    noisy = fit_heading_correction(*_box(p, noise_nT=0.2, seed=3)[:5])
    np.testing.assert_allclose(noisy.p_nT, p, atol=0.05)


def test_a_gradient_across_the_box_is_told_from_the_heading_error_by_the_ramps():
    # each heading is flown on its own side of the box, so a gradient across it puts a
    # level into each heading just as a permanent field does; the ramps along the legs
    # measure the gradient and separate the two
    p, grad = np.array([0.8, -0.4]), (0.004, -0.003)
    box = _box(p, gradient=grad, noise_nT=0.05, seed=5)
    corr = fit_heading_correction(*box)
    np.testing.assert_allclose(corr.p_nT, p, atol=0.05)
    np.testing.assert_allclose(corr.gradient_nT_per_m, grad, atol=2e-4)
    # without the positions the gradient's levels are read as a heading error
    blind = fit_heading_correction(*box[:5])
    assert np.max(np.abs(blind.p_nT - p)) > 1.0


def test_no_correction_from_fewer_than_three_headings():
    with pytest.raises(ValueError, match="2 headings, fewer than 3"):
        fit_heading_correction(*_box([1.0, 1.0], headings_deg=(0, 180))[:5])


def test_the_correction_is_applied_along_the_unit_field():
    y, u, leg, heading, t, _, _ = _box([2.0, 0.5])
    corr = fit_heading_correction(y, u, leg, heading, t)
    left = y - corr.interference_nT(u)
    # what is left is the crust's level, the same on every heading
    assert np.ptp([left[heading == h].mean() for h in range(4)]) < 1e-6


def test_the_crossover_test_uses_the_line_as_its_unit():
    lines = ["L1", "L1", "L2", "L2", "L3", "L4", "L5"]
    before = np.array([1.0, -1.2, 0.8, 0.9, -1.1, 1.0, 0.7])
    p_all, n = crossover_improvement_p(lines, before, before / 4)
    assert n == 5
    assert p_all == pytest.approx(1 / 32)  # every line better: the exact test's least p
    p_none, _ = crossover_improvement_p(lines, before / 4, before)
    assert p_none == pytest.approx(1.0)


def _truth_rms(flight, seg, field_nT, truth_file) -> float:
    d = np.load(truth_file)
    truth = np.interp(flight.time_ns.astype(float), d["t_ns"].astype(float), d["field_true_nT"])
    x = (field_nT - truth)[seg.mask("survey") | seg.mask("tie")]
    x = x - np.nanmean(x)
    return float(np.sqrt(np.nanmean(x**2)))


@pytest.mark.parametrize(
    "name", ["realism_geomagnetic_gradient", pytest.param("realism_none", marks=pytest.mark.slow)]
)
def test_the_step_on_independent_flights_against_their_true_field(name):
    # flights of a generator that is not aeromag's (the true field per epoch beside them):
    # over a gradient the manoeuvres sway the sensor through, tl18's coefficients leave a
    # heading error the band-passed fit cannot see and the legs' levels measure; on the
    # clean flight the legs' levels hold the crust's gradient over the box, which the ramps
    # take, and the crossovers do not confirm what is left
    from pipeline.compensate import FitSettings, Measurements
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight
    from tests.recordings import INDEPENDENT

    path = INDEPENDENT / f"{name}.mcap"
    if not path.exists():
        pytest.skip(f"{path} absent")
    flight = read_flight(path)
    seg = segment_flight(flight)
    run = run_compensation(flight, seg, FitSettings(model="tl-plus"))
    rec = run.model.extension["heading_levels"]
    truth_file = INDEPENDENT / f"{name}.field.npz"
    with_it = _truth_rms(flight, seg, run.compensated_nT, truth_file)
    if name == "realism_geomagnetic_gradient":
        assert rec["used"], rec
        meas = Measurements.from_flight(flight)
        without = replace(run.model, heading=None).compensate(meas)[0]
        assert with_it < 0.7 * _truth_rms(flight, seg, without, truth_file)
        assert rec["crossover_rms_after_nT"] < rec["crossover_rms_before_nT"]
    else:
        assert not rec["used"], rec
        assert max(abs(g) for g in rec["gradient_nT_per_m"]) < 0.02


def test_a_gap_in_the_positions_on_a_leg_is_no_failure():
    # the reader leaves NaN where the GNSS has no fix: the frame is centred on the fixes,
    # and the leg's blocks use the epochs with a position
    from pipeline.compensate import FitSettings
    from pipeline.compensate.stage import run_compensation
    from pipeline.io.reader import read_flight
    from pipeline.segment import segment_flight
    from tests.recordings import INDEPENDENT

    path = INDEPENDENT / "realism_geomagnetic_gradient.mcap"
    if not path.exists():
        pytest.skip(f"{path} absent")
    flight = read_flight(path)
    seg = segment_flight(flight)
    legs = np.flatnonzero(np.isin(np.asarray(seg.cardinal).astype(str), ["N", "E", "S", "W"]))
    flight.data.loc[flight.data.index[legs[:50]], ["lat_deg", "lon_deg"]] = np.nan
    rec = run_compensation(flight, seg, FitSettings(model="tl-plus")).model.extension[
        "heading_levels"
    ]
    assert rec["used"], rec


def test_the_report_line_says_what_was_applied_and_why():
    from pipeline.products.markdown import heading_levels_text

    kept = {
        "used": True,
        "p_nT": [-1.14, 0.45],
        "crossover_rms_before_nT": 0.983,
        "crossover_rms_after_nT": 0.469,
        "crossover_p": 1 / 32,
        "crossover_lines": 5,
    }
    text = heading_levels_text(kept)
    assert "applied" in text and "not applied" not in text
    assert "0.983 -> 0.469 nT (p 0.031 over 5 lines)" in text
    assert "not applied" in heading_levels_text({**kept, "used": False})
    none = heading_levels_text(
        {"used": False, "reason": "calibration legs on fewer than 3 headings"}
    )
    assert none == "no correction (calibration legs on fewer than 3 headings)"
