"""The catalogue of physical effects, by id.

The simulator's switchable effects and the audit's candidate causes are the same five; the
ids are part of the audit's JSON contract (``findings[].effect``) and of the scenario files
(``[effects.<id>]``). A leaf module, so neither the audit nor the simulator imports the
other for it.
"""

EFFECTS = (
    "geomagnetic_gradient",
    "sensor_lag",
    "diurnal",
    "electrical_current",
    "vector_calibration",
)
