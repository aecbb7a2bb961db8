"""Randomised flights for benchmarks and tests: the variety real flights have.

:func:`random_flight_overrides` draws a flight within given ranges and returns it as
``--set``-style overrides, so a benchmark can log, replay and shrink it::

    rng = np.random.default_rng(42)
    overrides = random_flight_overrides(rng)
    sim = simulate(Scenario.load("uav-small", overrides), seed=int(rng.integers(2**31)))

The overrides set the profile (multicopter ``uav`` or ``fixed-wing``), the number of
calibration passes, the heading order of the box, the ranges each manoeuvre block draws its
length, period and amplitude from (drawn by the simulator from the flight's seed), the scalar
noise, and interference outside the Tolles-Lawson basis: a total size (the RMS on calibration
that no tl18 fit can remove) split at random among a random non-empty subset of the terms.
With ``short`` (the default) the survey is a small block without tie-line repeats or
validation lines and manoeuvre blocks last at most 30 s: a UAV flight then lasts about 10-25
minutes, a fixed-wing one 20-45, and either simulates in one to three seconds.
"""

from __future__ import annotations

import numpy as np

OUTSIDE_TERMS = ("second_order", "eddy_lag", "unrecorded_current", "vibration")

_SHORT = {
    "uav": [
        "survey.length_m=400.0",
        "survey.width_m=100.0",
        "survey.line_spacing_m=50.0",
        "survey.tie_spacing_m=400.0",
        "survey.validation=false",
        "survey.enabled=true",
        "calibration.centre_east_m=-250.0",
        "calibration.centre_north_m=-250.0",
        "flight.transit_s=10.0",
        "anomaly.dipoles=8",
        "anomaly.margin_m=200.0",
    ],
    "fixed-wing": [
        "survey.length_m=3000.0",
        "survey.width_m=800.0",
        "survey.line_spacing_m=400.0",
        "survey.tie_spacing_m=3000.0",
        "survey.validation=false",
        "survey.enabled=true",
        "calibration.centre_east_m=-5000.0",
        "calibration.centre_north_m=-4000.0",
        "flight.transit_s=10.0",
        "anomaly.dipoles=8",
        "anomaly.margin_m=1000.0",
    ],
}

# a survey as crews fly it: tie lines inside the block (the short flights' only ties lie on
# the line ends, where they are turns), so that crossovers exist for the survey-side tests
# and the calibration box over quiet ground, as crews choose its site: 2-3 km from the block's
# sources (with the box 300 m from the block, as the short flights have it, the sources give
# a real 0.02-0.04 nT/m gradient over the box, which the audit rightly reports)
TIED_SURVEY = {
    "uav": [
        "survey.width_m=200.0",
        "survey.tie_spacing_m=150.0",
        "calibration.centre_east_m=-2000.0",
        "calibration.centre_north_m=-2000.0",
        "anomaly.quiet_calibration_m=1000.0",
    ],
    "fixed-wing": [
        "survey.width_m=1600.0",
        "survey.tie_spacing_m=1000.0",
        "anomaly.quiet_calibration_m=1500.0",
    ],
}


def _fmt(x: float) -> str:
    return repr(float(x))


def override_value(overrides: list[str], key: str) -> str | None:
    """The value of ``key`` in ``key=value`` scenario overrides (the last one given), or
    None when ``key`` is not among them: what :func:`random_flight_overrides` drew."""
    values = [o.split("=", 1)[1] for o in overrides if o.split("=", 1)[0] == key]
    return values[-1] if values else None


def random_flight_overrides(
    rng: np.random.Generator,
    *,
    short: bool = True,
    profiles: tuple[str, ...] = ("uav", "fixed-wing"),
    passes: tuple[int, int] = (1, 2),
    block_duration_s: tuple[float, float] = (15.0, 60.0),
    period_range_s: tuple[float, float] = (3.0, 10.0),
    amplitude_range_deg: tuple[float, float] = (3.0, 15.0),
    noise_nT: tuple[float, float] = (0.02, 0.5),
    outside_basis_nT: tuple[float, float] = (0.0, 1.0),
    outside_terms: tuple[str, ...] = OUTSIDE_TERMS,
) -> list[str]:
    """A random flight within the given ranges, as ``key=value`` scenario overrides.

    ``noise_nT`` is drawn log-uniformly, ``outside_basis_nT`` (the total RMS outside the tl18
    basis on calibration; the terms' squares add up to its square) uniformly. ``short``
    caps ``block_duration_s`` at 30 s. Deterministic for a given ``rng`` state.
    """
    if short:
        block_duration_s = (
            block_duration_s[0],
            max(block_duration_s[0], min(block_duration_s[1], 30.0)),
        )
    profile = str(rng.choice(list(profiles)))
    out = [
        f"profile={profile}",
        "name=random-flight",
        f"calibration.passes={int(rng.integers(passes[0], passes[1] + 1))}",
        f'calibration.heading_order="{"".join(rng.permutation(list("NESW")))}"',
        f"calibration.block_duration_s=[{_fmt(block_duration_s[0])}, {_fmt(block_duration_s[1])}]",
        f"calibration.period_range_s=[{_fmt(period_range_s[0])}, {_fmt(period_range_s[1])}]",
        f"calibration.amplitude_range_deg=[{_fmt(amplitude_range_deg[0])}, "
        f"{_fmt(amplitude_range_deg[1])}]",
    ]
    lo, hi = np.log(noise_nT[0]), np.log(noise_nT[1])
    out.append(f"sensors.scalar_noise_nT={_fmt(np.exp(rng.uniform(lo, hi)))}")
    total = float(rng.uniform(*outside_basis_nT))
    if total > 0 and outside_terms:
        n = int(rng.integers(1, len(outside_terms) + 1))
        chosen = [outside_terms[i] for i in sorted(rng.permutation(len(outside_terms))[:n])]
        weights = rng.dirichlet(np.ones(n))
        for term, w in zip(chosen, weights, strict=True):
            out.append(f"interference.outside_basis.{term}_nT={_fmt(total * np.sqrt(w))}")
        if "eddy_lag" in chosen:
            out.append(f"interference.outside_basis.eddy_tau_s={_fmt(rng.uniform(0.2, 1.5))}")
        if "vibration" in chosen:
            out.append(f"interference.outside_basis.vibration_hz={_fmt(rng.uniform(12, 40))}")
    if short:
        out += _SHORT.get(profile, _SHORT["uav"])
    return out
