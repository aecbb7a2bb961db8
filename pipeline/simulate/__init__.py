"""Flight simulator: trajectories, fields, sensors and switchable effects."""

from pipeline.simulate.scenario import EFFECTS, Scenario, builtin_scenarios
from pipeline.simulate.simulator import (
    SimulatedFlight,
    simulate,
    simulate_recording,
    write_simulation,
)
from pipeline.simulate.variety import override_value, random_flight_overrides

__all__ = [
    "EFFECTS",
    "Scenario",
    "SimulatedFlight",
    "builtin_scenarios",
    "override_value",
    "random_flight_overrides",
    "simulate",
    "simulate_recording",
    "write_simulation",
]
