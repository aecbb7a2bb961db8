"""Flight simulator: trajectories, fields, sensors and switchable effects."""

from pipeline.simulate.scenario import EFFECTS, Scenario, builtin_scenarios
from pipeline.simulate.simulator import SimulatedFlight, simulate, write_simulation

__all__ = ["EFFECTS", "Scenario", "SimulatedFlight", "builtin_scenarios", "simulate",
           "write_simulation"]
