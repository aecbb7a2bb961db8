"""The CI-sized subset of benchmarks/bench_audit_variety.py: short multicopter flights of
our simulator with random calibration schedules (one or two passes, any heading order,
blocks of 15-30 s at 3-10 s periods and 3-15 deg), scalar noise 0.02-0.1 nT and up to 0.2 nT
of interference outside the tl18 basis, two fixed seeds per class. Each must come out right:
the hidden catalogue effect named alone, nothing on a clean flight, and a step in the
carrier's permanent field (outside the catalogue) as an unexplained event within +-120 s.
The full benchmark (30 flights per class, wider ranges, fixed-wing too) is in docs.

Marked ``slow`` (not in the default run) until it passes: issue 16 asks for this subset to
run in CI and be all right; today 11 of 14 are (``pytest -m slow tests/test_audit_variety.py``).
Wrong: a first-order sensor lag and a temperature-drifting current are named with an extra
``geomagnetic_gradient`` (the position terms absorb what the lag / current model leaves), and
one flight's survey is not segmented (no survey or tie line found: 2 passes, box E-S-W-N), so
its diurnal cannot be tested."""

from __future__ import annotations

import pytest

from benchmarks.bench_audit_variety import CLASSES, correct, one_flight

pytestmark = pytest.mark.slow

MILD = {"profiles": ("uav",), "noise_nT": (0.02, 0.1), "outside_basis_nT": (0.0, 0.2)}
SEEDS = (11, 12)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("kind", CLASSES)
def test_audit_names_the_hidden_effect_on_varied_flights(kind, seed, tmp_path):
    row = one_flight(kind, seed, tmp_path, **MILD)
    assert correct(row), row
