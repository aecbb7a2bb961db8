"""Simulation scenarios: small TOML files, merged over profile defaults.

A scenario names a carrier profile (``uav`` or ``fixed-wing``) and overrides any default below.
Unknown keys are an error (a typo must not silently fall back to a default). Every quantity
carries its unit in its name. Effects are switched on by name under ``[effects.<id>]``.

Options added for flight variety (``_OPTIONAL`` below: calibration heading and manoeuvre
order, randomised manoeuvre blocks, interference outside the Tolles-Lawson basis, a filtering
scalar sensor, a temperature-dependent current coupling) are all off by default. They are
written to the truth document only when they differ from their default, so a flight that does
not use them has the same recording *and* the same truth document as before they existed.
"""

from __future__ import annotations

import copy
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from pipeline.effects import EFFECTS
from pipeline.errors import AeromagError

_COMMON: dict[str, Any] = {
    "name": "custom",
    "description": "",
    "profile": "uav",
    "start_time": "2026-06-15T01:00:00Z",
    "site": {
        "latitude_deg": 34.25,
        "longitude_deg": 108.90,
        "ground_altitude_m": 400.0,  # ellipsoidal height of the (flat) ground
    },
    "flight": {
        "speed_m_s": 7.0,
        "transit_s": 20.0,  # straight run at the start and end of the recording
        "turn_radius_m": 20.0,  # bank-limited: v^2 / (g tan(bank)); 20 m at 7 m/s is 14 deg
        "max_bank_deg": 35.0,
        "roll_in_s": 0.7,  # time scale of rolling into and out of a turn
        "cruise_pitch_deg": -3.0,  # multicopters tilt nose-down to fly forward
        "kinematics": "multicopter",  # multicopter | fixed-wing: how manoeuvres move the sensor
        "master_rate_hz": 50.0,
    },
    "calibration": {
        "passes": 2,  # boxes flown: 1 = before the survey, 2 = before and after
        "altitude_m": 100.0,  # above ground
        "centre_east_m": -500.0,  # box centre, relative to the survey's south-west corner
        "centre_north_m": -300.0,
        "headings_deg": [0.0, 90.0, 180.0, 270.0],
        "roll_amplitude_deg": 10.0,
        "pitch_amplitude_deg": 5.0,
        "yaw_amplitude_deg": 5.0,
        "roll_period_s": 6.0,
        "pitch_period_s": 5.0,
        "yaw_period_s": 8.0,
        "cycles": 3,
        "steady_s": 4.0,  # straight, level flight before, between and after manoeuvres
    },
    "survey": {
        "enabled": True,  # false: calibration boxes only
        "east_m": 0.0,  # south-west corner relative to the site
        "north_m": 0.0,
        "line_heading_deg": 0.0,  # survey lines run along this heading (tie lines across)
        "length_m": 2000.0,
        "width_m": 700.0,
        "line_spacing_m": 50.0,
        "tie_spacing_m": 500.0,
        "altitude_m": 100.0,  # above ground
        "validation": True,  # fly the diagonal "X" validation lines
    },
    "sensors": {
        "scalar_id": "cpt",
        "scalar_rate_hz": 10.0,
        "scalar_noise_nT": 0.05,
        "scalar_drift_nT_per_sqrt_s": 0.0005,
        "vector_id": "fluxgate",
        "vector_rate_hz": 20.0,
        "vector_noise_nT": 0.5,
        "attitude_rate_hz": 20.0,
        "attitude_noise_deg": 0.01,
        "gnss_rate_hz": 5.0,
        "gnss_noise_m": 0.05,
        "base_station": True,
        "base_rate_hz": 1.0,
        "base_noise_nT": 0.05,
        "aux_rate_hz": 5.0,
        "plan_markers": False,  # write /plan/line (a recorder that knows the plan)
        # clock offsets of each stream's first sample (s): sensors are not aligned
        "clock_offset_s": {
            "scalar": 0.0,
            "vector": 0.013,
            "attitude": 0.007,
            "gnss": 0.031,
            "base": 0.25,
            "aux": 0.041,
        },
        "dropouts": [],  # [{topic = "/mag/scalar", start_s = 100.0, duration_s = 2.0}]
    },
    "interference": {  # at the scalar sensor, body frame
        "permanent_nT": [35.0, -22.0, 48.0],
        "induced": [[0.0012, 0.0004, -0.0007], [0.0004, 0.0009, 0.0003], [-0.0007, 0.0003, 0.0021]],
        "eddy_s": [[0.0030, 0.0010, -0.0008], [-0.0006, 0.0024, 0.0011], [0.0009, -0.0013, 0.0018]],
    },
    "vector_interference": {  # at the fluxgate, body frame
        "permanent_nT": [12.0, -8.0, 15.0],
        "induced": [[0.0004, 0.0001, 0.0], [0.0001, 0.0003, 0.0001], [0.0, 0.0001, 0.0006]],
        "eddy_s": [[0.0005, 0.0, 0.0], [0.0, 0.0005, 0.0], [0.0, 0.0, 0.0005]],
    },
    "interference_enabled": True,
    "anomaly": {
        "dipoles": 30,
        "depth_m": [80.0, 400.0],  # below ground
        "moment_A_m2": [2.0e5, 2.0e7],  # log-uniform
        "remanent_fraction": 0.3,
        "margin_m": 300.0,  # sources also this far outside the survey area
        "quiet_calibration_m": 0.0,  # > 0: no source this close (horizontally) to the box
        "grid_cell_m": 10.0,  # cell of the truth anomaly grid
    },
    "aux": {
        "motor_hover_A": 18.0,
        "payload_levels_A": [0.6, 1.9],
        "payload_switch_s": [40.0, 160.0],  # random dwell between switches
    },
    "effects": {
        "geomagnetic_gradient": {
            "enabled": False,
            "east_nT_per_m": 0.318,
            "north_nT_per_m": 0.318,
            "up_nT_per_m": 0.05,
        },
        "sensor_lag": {"enabled": False, "lag_s": 0.1},
        "diurnal": {
            "enabled": False,
            "amplitude_nT": 15.0,
            "period_s": 5400.0,
            "random_walk_nT_per_sqrt_s": 0.02,
        },
        "electrical_current": {
            "enabled": False,
            "channel": "payload_current",
            "coupling_nT_per_A": 3.0,
            "direction_body": [0.2, -0.3, 0.93],
        },
        # an uncalibrated low-cost UAV fluxgate: percent-level scale, degree-level axes
        "vector_calibration": {
            "enabled": False,
            "scale_error": [0.02, -0.015, 0.01],
            "nonorthogonality_deg": [1.0, -0.8, 0.9],
            "offset_nT": [150.0, -100.0, 80.0],
        },
    },
}

# Variety options (issue 16): every one is off by default, and draws its random numbers from a
# generator of its own (created only when the option is on), so a flight that leaves them
# alone is unchanged. Omitted from the truth document while at their default.
_OPTIONAL: dict[str, Any] = {
    "calibration": {
        # order of the legs of each box: "" = as listed in headings_deg; a permutation of the
        # letters N, E, S, W (e.g. "WNES"); or "random" (a fresh permutation each pass)
        "heading_order": "",
        "manoeuvre_order": "",  # "" = roll, pitch, yaw on every leg; "random": shuffled per leg
        # Randomised manoeuvre blocks, each drawn uniformly per block (every manoeuvre of every
        # leg) from the flight's seed; [] = the fixed values above:
        "block_duration_s": [],  # [lo, hi]: block length (cycles = length / period)
        "period_range_s": [],  # [lo, hi]: oscillation period (instead of <kind>_period_s)
        "amplitude_range_deg": [],  # [lo, hi]: amplitude (instead of <kind>_amplitude_deg)
    },
    "interference": {
        # Interference at the scalar sensor that no Tolles-Lawson (tl18) model can represent.
        # Each *_nT is the RMS, over the calibration legs, of the part of that term's scalar
        # contribution left after a least-squares fit of the tl18 terms (plus a constant) on the
        # true body-frame field: the share a perfect tl18 calibration cannot remove. 0 = off.
        # With several terms on, all are scaled by one common factor so that the total's share
        # is the root-sum-square of the requests (the terms' left-over parts may correlate).
        # The truth document reports the RMS achieved on calibration and survey.
        # Independent of interference_enabled.
        "outside_basis": {
            # second-order induced field: b_i = sum_jk Q_ijk b_j b_k / 50 000 nT (random Q)
            "second_order_nT": 0.0,
            # eddy currents that decay with an L/R time constant: E (lowpass_tau(db/dt) - db/dt)
            # with E the airframe's eddy matrix (the part of a lagging eddy response that the
            # instantaneous E db/dt of T-L misses)
            "eddy_lag_nT": 0.0,
            "eddy_tau_s": 0.5,
            # a current with no /aux channel (heater, servo, radio), switching on and off at
            # random dwell times (settling 1 s), along a random body direction
            "unrecorded_current_nT": 0.0,
            "unrecorded_switch_s": [5.0, 40.0],
            # vibration of conductive parts (motor arms, rotors): angular jitter at vibration_hz
            # (scaled by the square root of the motor load on a multicopter) whose eddy
            # currents the 10 Hz scalar samples aliased
            "vibration_nT": 0.0,
            "vibration_hz": 23.3,
        },
    },
    "aux": {
        # /aux/temperature: start + rise * tanh(t / time)
        "temperature_start_degC": 24.0,
        "temperature_rise_K": 3.0,
        "temperature_time_s": 900.0,
    },
    "anomaly": {
        # >= 0: the crustal sources come from a generator of their own seeded with this, not
        # from the flight's seed: sorties of one campaign (different seeds) fly over the same
        # geology. -1: drawn from the flight's generator (as before).
        "seed": -1,
    },
    "survey": {
        # flight lines (survey, tie, validation) shifted across the survey lines by this (m);
        # the block (its crustal sources, the truth grid) stays: a re-flight with other lines
        "line_offset_m": 0.0,
    },
    "effects": {
        # a constant added to the diurnal variation (nT): the day's level, which the base
        # station's mean does not remove (the level a campaign's per-flight offset recovers)
        "diurnal": {"offset_nT": 0.0},
        # "delay": the scalar reads the field lag_s late; "first_order": the scalar passes
        # through a first-order low-pass with time constant lag_s (group delay lag_s at low
        # frequency, and an amplitude loss 1/sqrt(1 + (w lag_s)^2))
        "sensor_lag": {"response": "delay"},
        # coupling x (1 + k (T - T0)): T the /aux/temperature truth, T0 its value at t = 0
        "electrical_current": {"temperature_coefficient_per_K": 0.0},
    },
}

_PROFILES: dict[str, dict[str, Any]] = {
    "uav": {},
    "fixed-wing": {
        "site": {"latitude_deg": 45.3, "longitude_deg": -76.4, "ground_altitude_m": 80.0},
        "flight": {
            "speed_m_s": 60.0,
            "transit_s": 30.0,
            "turn_radius_m": 640.0,
            "max_bank_deg": 35.0,
            "roll_in_s": 2.0,
            "cruise_pitch_deg": 2.0,
            "kinematics": "fixed-wing",
        },
        "calibration": {
            "altitude_m": 1800.0,
            "centre_east_m": -16000.0,
            "centre_north_m": -12000.0,
        },
        "survey": {
            "length_m": 12000.0,
            "width_m": 4000.0,
            "line_spacing_m": 400.0,
            "tie_spacing_m": 4000.0,
            "altitude_m": 300.0,
        },
        "sensors": {"gnss_noise_m": 0.5, "attitude_noise_deg": 0.02},
        "interference": {
            "permanent_nT": [120.0, -260.0, 310.0],
            "induced": [[0.006, 0.002, -0.003], [0.002, 0.004, 0.001], [-0.003, 0.001, 0.009]],
            "eddy_s": [[0.02, 0.006, -0.004], [-0.003, 0.015, 0.007], [0.005, -0.008, 0.011]],
        },
        "aux": {"motor_hover_A": 45.0},
        "anomaly": {
            "depth_m": [300.0, 2500.0],
            "moment_A_m2": [1.0e8, 5.0e9],
            "margin_m": 2000.0,
            "grid_cell_m": 100.0,
        },
    },
}


def _merge(base: dict[str, Any], over: dict[str, Any], where: str, strict: bool) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for k, v in over.items():
        path = f"{where}.{k}" if where else k
        if k not in out:
            if strict:
                raise KeyError(path)
            out[k] = copy.deepcopy(v)
        elif isinstance(out[k], dict) and isinstance(v, dict):
            out[k] = _merge(out[k], v, path, strict)
        else:
            out[k] = copy.deepcopy(v)
    return out


@dataclass
class Scenario:
    """A resolved scenario: profile defaults with the file's and the caller's overrides."""

    config: dict[str, Any]
    source: str

    @property
    def name(self) -> str:
        """The scenario's name (``config["name"]``)."""
        return str(self.config["name"])

    def __getitem__(self, key: str) -> Any:
        return self.config[key]

    def effect(self, name: str) -> dict[str, Any] | None:
        """Parameters of an enabled effect, or None when it is off."""
        e = self.config["effects"][name]
        return e if e.get("enabled") else None

    def enabled_effects(self) -> list[str]:
        """Names of the effects switched on, in ``EFFECTS`` order."""
        return [n for n in EFFECTS if self.config["effects"][n].get("enabled")]

    def recorded_config(self) -> dict[str, Any]:
        """The configuration as written to the truth document: variety options at their
        default are left out (truth documents of flights that do not use them stay as they
        were before the options existed)."""
        return _strip_defaults(self.config, _OPTIONAL)

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> Scenario:
        """Resolve a scenario from a dict of overrides on its profile's defaults.

        Parameters
        ----------
        data : dict
            Scenario keys (as in a scenario TOML); ``profile`` is ``uav`` (default) or
            ``fixed-wing``.
        source : str
            Where ``data`` came from, for error messages.

        Returns
        -------
        Scenario

        Raises
        ------
        AeromagError
            Unknown profile or key.
        """
        profile = data.get("profile", "uav")
        if profile not in _PROFILES:
            raise AeromagError(f"unknown profile {profile!r} (use uav or fixed-wing)", file=source)
        base = _merge(_COMMON, _PROFILES[profile], "", strict=False)
        base = _merge(base, _OPTIONAL, "", strict=False)
        try:
            cfg = _merge(base, data, "", strict=True)
        except KeyError as exc:
            raise AeromagError(f"unknown scenario key {exc.args[0]!r}", file=source) from None
        return cls(cfg, source)

    @classmethod
    def load(
        cls, name_or_path: str | Path | None = None, overrides: list[str] | None = None
    ) -> Scenario:
        """Load a built-in scenario by name (default ``demo``) or a TOML file by path, then
        apply ``key.sub=value`` overrides (values parsed as TOML, bare words as strings)."""
        name_or_path = name_or_path or "demo"
        path = Path(name_or_path)
        if not path.suffix:
            builtin = resources.files("pipeline.simulate") / "scenarios" / f"{name_or_path}.toml"
            if not builtin.is_file():
                raise AeromagError(
                    f"unknown scenario {str(name_or_path)!r} (built-in: "
                    f"{', '.join(builtin_scenarios())})"
                )
            text, source = builtin.read_text(), f"scenario:{name_or_path}"
        else:
            if not path.is_file():
                raise AeromagError("scenario file not found", file=path)
            text, source = path.read_text(), str(path)
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise AeromagError(f"not valid TOML ({exc})", file=source) from None
        for item in overrides or []:
            data = _merge(data, parse_override(item), "", strict=False)
        return cls.from_dict(data, source)


def _strip_defaults(cfg: dict[str, Any], optional: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(cfg)
    for k, default in optional.items():
        if k not in out:
            continue
        if isinstance(default, dict) and isinstance(out[k], dict):
            inner = _strip_defaults(out[k], default)
            if set(out[k]) - set(default):  # a section with older keys: strip the new ones
                out[k] = inner
            elif not inner:  # a new section (interference.outside_basis) left at its default
                del out[k]
            # else: a new section in use is recorded whole (its time constants too)
        elif out[k] == default:
            del out[k]
    return out


def parse_override(item: str) -> dict[str, Any]:
    """``a.b.c=value`` -> nested dict; value parsed as TOML (numbers, lists, booleans)."""
    if "=" not in item:
        raise AeromagError(f"override {item!r} is not key=value")
    key, raw = item.split("=", 1)
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    out: dict[str, Any] = {}
    cur = out
    parts = key.strip().split(".")
    for p in parts[:-1]:
        cur = cur.setdefault(p, {})
    cur[parts[-1]] = value
    return out


def builtin_scenarios() -> list[str]:
    """Names of the built-in scenarios (``aeromag scenarios``), sorted."""
    folder = resources.files("pipeline.simulate") / "scenarios"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))
