"""Flight simulator: what a recorder on the carrier would have written, plus the truth.

The recording holds only contract channels (scalar and vector magnetometers, attitude, GNSS,
base station, auxiliary channels, optionally plan markers), each at its own rate and clock.
Everything a processing stage must *find* — interference coefficients, effect magnitudes, the
anomaly map, segment labels — goes to the separate truth document.

Physics (shared with the processing models through :mod:`pipeline.physics`):

- Earth field (NED) = IGRF main field (ppigrf) + crustal dipoles + optional regional gradient
  and diurnal variation, both along the main-field direction;
- body-frame field from the attitude (Z-Y-X), and its time derivative;
- carrier interference p + A b + E db/dt at each sensor (plus an electrical-current term,
  optionally with a temperature-dependent coupling);
- optional scalar interference outside the T-L basis (``interference.outside_basis``: second-
  order induced, lagging eddy currents, an unrecorded current, vibration), see
  :mod:`pipeline.physics.outside_basis`;
- scalar sensor reads |b + b_int| (+ white noise and drift, optionally lagged: a pure delay or
  a first-order sensor filter);
- fluxgate reads its own interference through its scale/non-orthogonality/offset errors.

Every optional feature draws its random numbers from a generator of its own, created only when
the feature is on: a flight that does not use it is unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.errors import AeromagError
from pipeline.geo.frames import ned_to_body
from pipeline.geo.igrf import igrf_ned_nT
from pipeline.geo.local import LocalFrame
from pipeline.io.writer import McapOutput, encode, stamp, write_json_atomic
from pipeline.physics.dipoles import DipoleSource, dipole_field_ned_nT, total_field_anomaly_nT
from pipeline.physics.interference import CarrierInterference, scalar_reading_nT
from pipeline.physics.outside_basis import (
    first_order_lowpass,
    lagging_eddy_vector,
    outside_part,
    second_order_vector,
    tl18_basis,
    vibration_vector,
)
from pipeline.physics.vector_sensor import FluxgateErrors
from pipeline.simulate.scenario import Scenario
from pipeline.simulate.trajectory import (
    Trajectory,
    build_trajectory,
    calibration_variety,
    manoeuvre_truth,
    segment_truth,
)

NS = 1_000_000_000
DERIV_STEP_S = 0.005  # central-difference step for db/dt on the continuous trajectory
OUTSIDE_TERMS = ("second_order", "eddy_lag", "unrecorded_current", "vibration")
SURVEY_LABELS = ("survey", "tie", "validation")
VIBRATION_MODES = (1.0, 1.13, 0.87)  # vibration frequency ratios about body x, y, z


def parse_time(text: str) -> datetime:
    """Parse an ISO 8601 instant (``Z`` allowed) into an aware UTC datetime."""
    return datetime.fromisoformat(text.replace("Z", "+00:00")).astimezone(UTC)


@dataclass
class EarthField:
    """The field a sensor at (east, north, up) would see at time t, NED nT.

    ``up`` is height above ground; ``frame.alt0_m`` is the ground's ellipsoidal height.
    The main field is evaluated along the flown track once a second and interpolated in time:
    ppigrf costs ~40 us a point and the main field changes by under 0.02 nT within a second.
    """

    frame: LocalFrame
    when: datetime
    dipoles: list[DipoleSource]
    main_t: np.ndarray
    main_ned: np.ndarray
    b_hat: np.ndarray  # main-field unit vector at the site (NED)
    gradient_nT_per_m: np.ndarray  # east, north, up (zero when the effect is off)
    gradient_ref_enu: np.ndarray
    diurnal_t: np.ndarray
    diurnal_nT: np.ndarray

    def main(self, t: np.ndarray) -> np.ndarray:
        """Main (IGRF) field along the flown track, interpolated at times ``t``.

        Parameters
        ----------
        t : ndarray
            s since the start of the flight.

        Returns
        -------
        ndarray, shape (n, 3)
            NED, nT.
        """
        return np.stack([np.interp(t, self.main_t, self.main_ned[:, k]) for k in range(3)], -1)

    def diurnal(self, t: np.ndarray) -> np.ndarray:
        """Diurnal variation at times ``t`` (s since the start of the flight), nT."""
        return np.interp(t, self.diurnal_t, self.diurnal_nT)

    def crust(self, east, north, up) -> np.ndarray:
        """Field of the crustal dipoles at local positions.

        Parameters
        ----------
        east, north : ndarray
            m in the local frame.
        up : ndarray
            m above ground.

        Returns
        -------
        ndarray, shape (n, 3)
            NED, nT.
        """
        return dipole_field_ned_nT(self.dipoles, east, north, up)

    def regional(self, east, north, up) -> np.ndarray:
        """Regional gradient field along the main-field direction (zero when the effect is off).

        Parameters
        ----------
        east, north : ndarray
            m in the local frame.
        up : ndarray
            m above ground.

        Returns
        -------
        ndarray, shape (n, 3)
            NED, nT: gradient (nT/m) times the offset from the survey's reference point, times
            the main-field unit vector at the site.
        """
        d = np.stack([east, north, up], -1) - self.gradient_ref_enu
        return (d @ self.gradient_nT_per_m)[:, None] * self.b_hat

    def ned(self, t, east, north, up) -> np.ndarray:
        """The total Earth field: main + crustal + regional + diurnal.

        Parameters
        ----------
        t : ndarray
            s since the start of the flight.
        east, north : ndarray
            m in the local frame.
        up : ndarray
            m above ground.

        Returns
        -------
        ndarray, shape (n, 3)
            NED, nT.
        """
        return (
            self.main(t)
            + self.crust(east, north, up)
            + self.regional(east, north, up)
            + self.diurnal(t)[:, None] * self.b_hat
        )


@dataclass
class SimulatedFlight:
    """One simulated flight (:func:`simulate`), ready for :func:`write_simulation`.

    Attributes
    ----------
    scenario : Scenario
    seed : int
    start_ns : int
        Start time, ns since 1970 (UTC).
    streams : dict
        Topic -> its schema, sample times ``t`` (s from the start) and payload columns.
    truth : dict
        The simulation's truth (written as the truth JSON).
    trajectory : Trajectory
    series : dict of str to ndarray
        Per-sample truth at the scalar epochs (in memory only).
    """

    scenario: Scenario
    seed: int
    start_ns: int
    streams: dict[str, dict[str, Any]]  # topic -> {schema, t (s from the start), columns}
    truth: dict[str, Any]
    trajectory: Trajectory = field(repr=False)
    # per-sample truth at the scalar epochs (in memory only: tests compare against it)
    series: dict[str, np.ndarray] = field(default_factory=dict, repr=False)


def _draw_dipoles(
    sc: Scenario,
    rng: np.random.Generator,
    b_hat: np.ndarray,
    calibration_en: np.ndarray | None = None,
) -> list[DipoleSource]:
    """Crustal sources under and around the survey block.

    With ``anomaly.quiet_calibration_m`` > 0 no source lies closer than that (horizontally)
    to the calibration legs (``calibration_en``, points east/north m): crews fly the box over
    magnetically quiet ground, because T-L (and AGG-TL's second-order expansion) cannot
    represent a local anomaly under the manoeuvres. Rejected draws are redrawn.
    """
    a, s = sc["anomaly"], sc["survey"]
    quiet = float(a.get("quiet_calibration_m", 0.0))
    along = np.array(
        [np.sin(np.radians(s["line_heading_deg"])), np.cos(np.radians(s["line_heading_deg"]))]
    )
    across = np.array([along[1], -along[0]])
    out = []
    for _ in range(int(a["dipoles"])):
        for _attempt in range(1000):
            u = rng.uniform(-a["margin_m"], s["length_m"] + a["margin_m"])
            w = rng.uniform(-a["margin_m"], s["width_m"] + a["margin_m"])
            e, n = np.array([s["east_m"], s["north_m"]]) + u * along + w * across
            if (
                quiet <= 0
                or calibration_en is None
                or not calibration_en.size
                or np.min(np.hypot(calibration_en[:, 0] - e, calibration_en[:, 1] - n)) >= quiet
            ):
                break
        depth = rng.uniform(*a["depth_m"])
        m = np.exp(rng.uniform(np.log(a["moment_A_m2"][0]), np.log(a["moment_A_m2"][1])))
        direction = b_hat.copy()
        if rng.random() < a["remanent_fraction"]:
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
        out.append(DipoleSource(float(e), float(n), float(-depth), tuple(m * direction)))
    return out


def _times(duration_s: float, rate_hz: float, offset_s: float, margin_s: float) -> np.ndarray:
    return np.arange(margin_s + offset_s, duration_s - margin_s, 1.0 / rate_hz)


def _drop(t: np.ndarray, topic: str, dropouts: list[dict]) -> np.ndarray:
    keep = np.ones(t.size, bool)
    for d in dropouts:
        if d["topic"] == topic:
            keep &= ~((t >= d["start_s"]) & (t < d["start_s"] + d["duration_s"]))
    return keep


def _switching(levels, switch_s, rng: np.random.Generator, duration: float, settle_s: float = 2.0):
    """A current switching between two levels at random dwell times (A)."""
    lo, hi = levels
    t_sw, level, t = [0.0], [lo], 0.0
    while t < duration:
        t += rng.uniform(*switch_s)
        t_sw.append(t)
        level.append(hi if level[-1] == lo else lo)
    t_sw, level = np.array(t_sw), np.array(level)

    def current(tt: np.ndarray) -> np.ndarray:
        k = np.searchsorted(t_sw, tt, side="right") - 1
        # first-order settling after each switch: real supplies do not step instantly
        prev = np.where(k > 0, level[np.maximum(k - 1, 0)], level[0])
        frac = 1 - np.exp(-(tt - t_sw[k]) / settle_s)
        return prev + (level[k] - prev) * frac

    return current


def _payload_current(sc: Scenario, rng: np.random.Generator, duration: float):
    """The payload current: two levels, random dwell, 2 s settling (A)."""
    return _switching(sc["aux"]["payload_levels_A"], sc["aux"]["payload_switch_s"], rng, duration)


def _piece_mask(traj: Trajectory, t: np.ndarray, labels: tuple[str, ...]) -> np.ndarray:
    mask = np.zeros(t.size, bool)
    for p in traj.pieces:
        if p.label in labels:
            mask |= (t >= p.t0_s) & (t < p.t1_s)
    return mask


def _outside_basis(
    sc: Scenario,
    seed: int,
    traj: Trajectory,
    t: np.ndarray,
    b: np.ndarray,
    db: np.ndarray,
    dt: float,
) -> tuple[dict[str, np.ndarray], dict[str, dict[str, float]]]:
    """Body-frame interference vectors outside the T-L basis at the scalar epochs ``t``.

    Each enabled term gets a generator of its own (its shape does not depend on which other
    terms are on) and is scaled so that the RMS over the calibration legs of its scalar
    contribution, after a least-squares tl18 fit on the true field, is the requested nT. The
    left-over parts of different terms can be correlated (second-order induced and lagging
    eddy fields both follow the manoeuvres), so with several terms all are then scaled by one
    common factor that makes the total's left-over RMS the root-sum-square of the requests.
    """
    ob = sc["interference"]["outside_basis"]
    wanted = {k: float(ob[f"{k}_nT"]) for k in OUTSIDE_TERMS if float(ob[f"{k}_nT"]) > 0}
    if not wanted:
        return {}, {}
    eddy = np.asarray(sc["interference"]["eddy_s"], float)
    if not np.any(eddy):
        eddy = np.eye(3) * 0.002
    u = b / np.linalg.norm(b, axis=1, keepdims=True)
    basis = tl18_basis(b, db)
    cal = _piece_mask(traj, t, ("calibration",))
    if cal.sum() < 4 * basis.shape[1]:
        cal = np.ones(t.size, bool)
    vectors: dict[str, np.ndarray] = {}
    info: dict[str, dict[str, float]] = {}
    left: dict[str, np.ndarray] = {}
    for k, name in enumerate(OUTSIDE_TERMS):
        if name not in wanted:
            continue
        rng = np.random.default_rng([int(seed), 16, 2, k])
        if name == "second_order":
            q = rng.normal(size=(3, 3, 3))
            shape = second_order_vector(b, (q + q.transpose(0, 2, 1)) / 2)
        elif name == "eddy_lag":
            shape = lagging_eddy_vector(db, dt, float(ob["eddy_tau_s"]), eddy)
        elif name == "unrecorded_current":
            current = _switching(
                (0.0, 1.0), ob["unrecorded_switch_s"], rng, float(t[-1]) + 10.0, settle_s=1.0
            )
            d = rng.normal(size=3)
            shape = current(t)[:, None] * (d / np.linalg.norm(d))
        else:  # vibration
            f = float(ob["vibration_hz"]) * np.ones(traj.master_t.size)
            if sc["flight"]["kinematics"] != "fixed-wing":  # rotor speed follows the thrust
                f = f * np.sqrt(1.0 + 0.25 * traj.motor_load)
            phase = (
                np.concatenate([[0.0], np.cumsum((f[1:] + f[:-1]) / 2 * np.diff(traj.master_t))])
                * 2
                * np.pi
            )
            ph = np.interp(t, traj.master_t, phase)
            fr = np.interp(t, traj.master_t, f)
            ratio = np.asarray(VIBRATION_MODES)  # each axis its own mode
            amp, phi = rng.uniform(0.5, 1.0, 3), rng.uniform(0, 2 * np.pi, 3)
            w = amp * 2 * np.pi * ratio * fr[:, None] * np.cos(ratio * ph[:, None] + phi)
            shape = vibration_vector(b, np.radians(0.05) * w, eddy)
        proj = np.einsum("ij,ij->i", u, shape)
        out = outside_part(proj, basis, cal)
        rms = float(np.sqrt(np.mean(out[cal] ** 2)))
        scale = wanted[name] / rms if rms > 0 else 0.0
        vectors[name] = shape * scale
        info[name] = {"requested_nT": wanted[name], "scale": scale}
        left[name] = out * scale
    if len(vectors) > 1:
        rms = float(np.sqrt(np.mean(sum(left.values())[cal] ** 2)))
        common = float(np.sqrt(sum(v**2 for v in wanted.values()))) / rms if rms > 0 else 1.0
        for name in vectors:
            vectors[name] = vectors[name] * common
            info[name]["scale"] *= common
            info[name]["common_factor"] = common
    return vectors, info


def _rms(x: np.ndarray, mask: np.ndarray) -> float | None:
    return float(np.sqrt(np.mean(x[mask] ** 2))) if mask.any() else None


def simulate(sc: Scenario, seed: int) -> SimulatedFlight:
    """Simulate one flight of scenario ``sc`` (deterministic for a given ``seed``)."""
    rng = np.random.default_rng(seed)
    site, sens = sc["site"], sc["sensors"]
    when = parse_time(sc["start_time"])
    start_ns = int(round(when.timestamp())) * NS
    frame = LocalFrame(site["latitude_deg"], site["longitude_deg"], site["ground_altitude_m"])
    traj = build_trajectory(sc, seed)
    T = traj.duration_s

    # Main field once a second along the track; unit vector at the site for projections.
    t_main = np.arange(0.0, T + 1.0, 1.0)
    st = traj.state(np.clip(t_main, 0, T))
    lat, lon, alt = frame.to_geodetic(st["east_m"], st["north_m"], st["up_m"])
    main_ned = igrf_ned_nT(lat, lon, alt, when)
    survey_alt = sc["survey"]["altitude_m"]
    b0 = igrf_ned_nT(
        site["latitude_deg"], site["longitude_deg"], site["ground_altitude_m"] + survey_alt, when
    )[0]
    b_hat = b0 / np.linalg.norm(b0)

    cal_t = np.concatenate(
        [np.arange(p.t0_s, p.t1_s, 1.0) for p in traj.pieces if p.label == "calibration"]
        or [np.zeros(0)]
    )
    cal_st = traj.state(cal_t)
    anomaly_seed = int(sc["anomaly"]["seed"])
    dip_rng = np.random.default_rng([anomaly_seed, 19, 4]) if anomaly_seed >= 0 else rng
    dipoles = _draw_dipoles(
        sc, dip_rng, b_hat, np.column_stack([cal_st["east_m"], cal_st["north_m"]])
    )
    grad = sc.effect("geomagnetic_gradient")
    gvec = (
        np.array([grad["east_nT_per_m"], grad["north_nT_per_m"], grad["up_nT_per_m"]])
        if grad
        else np.zeros(3)
    )
    s = sc["survey"]
    ref = np.array([s["east_m"], s["north_m"], survey_alt])
    diu = sc.effect("diurnal")
    t_d = np.arange(-10.0, T + 11.0, 1.0)
    if diu:
        phase = rng.uniform(0, 2 * np.pi)
        walk = np.cumsum(rng.normal(0, diu["random_walk_nT_per_sqrt_s"], t_d.size))
        d_nT = diu["amplitude_nT"] * np.sin(2 * np.pi * t_d / diu["period_s"] + phase) + walk
        d_nT = d_nT + float(diu["offset_nT"])
    else:
        d_nT = np.zeros(t_d.size)
    field_model = EarthField(frame, when, dipoles, t_main, main_ned, b_hat, gvec, ref, t_d, d_nT)

    on = bool(sc["interference_enabled"])
    tl = {k: v for k, v in sc["interference"].items() if k != "outside_basis"}
    scalar_int = CarrierInterference(**tl) if on else CarrierInterference.none()
    vector_int = (
        CarrierInterference(**sc["vector_interference"]) if on else CarrierInterference.none()
    )
    vcal = sc.effect("vector_calibration")
    flux_err = (
        FluxgateErrors(vcal["scale_error"], vcal["nonorthogonality_deg"], vcal["offset_nT"])
        if vcal
        else FluxgateErrors()
    )
    lag = sc.effect("sensor_lag")
    lag_s = float(lag["lag_s"]) if lag else 0.0
    response = str(lag["response"]) if lag else "delay"
    if response not in ("delay", "first_order"):
        raise AeromagError(
            f"effects.sensor_lag.response {response!r}: use delay or first_order", file=sc.source
        )
    delay_s = lag_s if response == "delay" else 0.0  # physics read this much earlier
    cur = sc.effect("electrical_current")
    payload_current = _payload_current(sc, rng, T + 10.0)
    hover = float(sc["aux"]["motor_hover_A"])
    temp0, temp_rise, temp_time = (
        float(sc["aux"][k])
        for k in ("temperature_start_degC", "temperature_rise_K", "temperature_time_s")
    )

    def motor_current(tt: np.ndarray) -> np.ndarray:
        return hover * (1.0 + 0.25 * traj.motor_load_at(tt))

    aux_funcs = {
        "motor_current": (motor_current, "A", 0.15),
        "payload_current": (payload_current, "A", 0.01),
        "bus_voltage": (lambda tt: 25.2 - 0.012 * motor_current(tt) - 0.0002 * tt, "V", 0.01),
        "temperature": (lambda tt: temp0 + temp_rise * np.tanh(tt / temp_time), "degC", 0.05),
    }

    def body_field(t: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """Body-frame Earth field and its time derivative at times t (central difference)."""
        out = []
        for dt in (0.0, -DERIV_STEP_S, DERIV_STEP_S):
            x = traj.state(t + dt)
            ned = field_model.ned(t + dt, x["east_m"], x["north_m"], x["up_m"])
            out.append((ned_to_body(ned, x["roll_deg"], x["pitch_deg"], x["yaw_deg"]), x))
        db = (out[2][0] - out[1][0]) / (2 * DERIV_STEP_S)
        return out[0][0], db, out[0][1]

    margin = 2 * DERIV_STEP_S + lag_s
    offs = sens["clock_offset_s"]
    drops = sens["dropouts"]
    streams: dict[str, dict[str, Any]] = {}

    # scalar magnetometer: reads the physics lag_s earlier than its time stamp ("delay"), or
    # through a first-order filter of time constant lag_s ("first_order")
    t_s = _times(T, sens["scalar_rate_hz"], offs.get("scalar", 0.0), margin)
    t_phys = t_s - delay_s
    b, db, _x = body_field(t_phys)
    b_int = scalar_int.vector_nT(b, db)
    coupling_mean = None  # a drifting coupling's mean: what a constant coupling estimates
    if cur:
        d = np.asarray(cur["direction_body"], float)
        coupling = cur["coupling_nT_per_A"]
        k_temp = float(cur["temperature_coefficient_per_K"])
        if k_temp:  # the coupling drifts with the (recorded) temperature
            temp = aux_funcs["temperature"][0]
            coupling = coupling * (1.0 + k_temp * (temp(t_phys) - temp(np.zeros(1))))
        b_int = b_int + (coupling * aux_funcs[cur["channel"]][0](t_phys))[:, None] * (
            d / np.linalg.norm(d)
        )
        if k_temp:
            coupling_mean = float(np.mean(coupling))
    dt_s = 1.0 / float(sens["scalar_rate_hz"])
    outside, outside_info = _outside_basis(sc, seed, traj, t_phys, b, db, dt_s)
    earth_total = np.linalg.norm(b, axis=1)
    if outside:
        without = scalar_reading_nT(b, b_int)
        b_int = b_int + sum(outside.values())
    clean = scalar_reading_nT(b, b_int)
    if response == "first_order" and lag_s > 0:
        clean = first_order_lowpass(clean, dt_s, lag_s)
        earth_total = first_order_lowpass(earth_total, dt_s, lag_s)
    noise = rng.normal(0, sens["scalar_noise_nT"], t_s.size)
    drift = np.cumsum(
        rng.normal(
            0, sens["scalar_drift_nT_per_sqrt_s"] * np.sqrt(1 / sens["scalar_rate_hz"]), t_s.size
        )
    )
    keep = _drop(t_s, "/mag/scalar", drops)
    streams["/mag/scalar"] = {
        "schema": "aeromag.ScalarField",
        "t": t_s[keep],
        "sensor_id": sens["scalar_id"],
        "cols": {"total_nT": (clean + noise + drift)[keep]},
    }
    scalar_truth = {
        "time_ns": start_ns + np.round(t_s * NS).astype(np.int64),
        "earth_total_nT": earth_total,
        "interference_nT": clean - earth_total,
        "noise_nT": noise + drift,
    }
    outside_truth = None
    if outside:
        u = b / np.linalg.norm(b, axis=1, keepdims=True)
        total = scalar_reading_nT(b, b_int) - without
        scalar_truth["outside_basis_nT"] = total
        cal = _piece_mask(traj, t_phys, ("calibration",))
        srv = _piece_mask(traj, t_phys, SURVEY_LABELS)
        basis = tl18_basis(b, db)
        terms = {}
        for name, vec in outside.items():
            proj = np.einsum("ij,ij->i", u, vec)
            scalar_truth[f"outside_basis_{name}_nT"] = proj
            terms[name] = {
                **outside_info[name],
                "calibration_rms_nT": _rms(proj, cal),
                "calibration_outside_tl18_rms_nT": _rms(outside_part(proj, basis, cal), cal),
                "survey_rms_nT": _rms(proj, srv),
            }
        outside_truth = {
            "calibration_rms_nT": _rms(total, cal),
            "calibration_outside_tl18_rms_nT": _rms(outside_part(total, basis, cal), cal),
            "survey_rms_nT": _rms(total, srv),
            "survey_outside_tl18_rms_nT": (
                _rms(outside_part(total, basis, srv), srv)
                if srv.sum() > 4 * basis.shape[1]
                else None
            ),
            "terms": terms,
        }

    # vector magnetometer
    t_v = _times(T, sens["vector_rate_hz"], offs.get("vector", 0.0), margin)
    bv, dbv, _ = body_field(t_v)
    meas = flux_err.apply(bv + vector_int.vector_nT(bv, dbv))
    meas = meas + rng.normal(0, sens["vector_noise_nT"], meas.shape)
    keep = _drop(t_v, "/mag/vector", drops)
    streams["/mag/vector"] = {
        "schema": "aeromag.VectorField",
        "t": t_v[keep],
        "sensor_id": sens["vector_id"],
        "cols": {"x_nT": meas[keep, 0], "y_nT": meas[keep, 1], "z_nT": meas[keep, 2]},
    }

    # attitude
    t_a = _times(T, sens["attitude_rate_hz"], offs.get("attitude", 0.0), margin)
    xa = traj.state(t_a)
    na = sens["attitude_noise_deg"]
    keep = _drop(t_a, "/ins/attitude", drops)
    streams["/ins/attitude"] = {
        "schema": "aeromag.Attitude",
        "t": t_a[keep],
        "cols": {
            "roll_deg": (xa["roll_deg"] + rng.normal(0, na, t_a.size))[keep],
            "pitch_deg": (xa["pitch_deg"] + rng.normal(0, na, t_a.size))[keep],
            "yaw_deg": np.mod(xa["yaw_deg"] + rng.normal(0, na, t_a.size), 360.0)[keep],
        },
    }

    # GNSS
    t_g = _times(T, sens["gnss_rate_hz"], offs.get("gnss", 0.0), margin)
    xg = traj.state(t_g)
    ng = sens["gnss_noise_m"]
    lat_g, lon_g, alt_g = frame.to_geodetic(
        xg["east_m"] + rng.normal(0, ng, t_g.size),
        xg["north_m"] + rng.normal(0, ng, t_g.size),
        xg["up_m"] + rng.normal(0, 2 * ng, t_g.size),
    )
    keep = _drop(t_g, "/gnss/fix", drops)
    var = ng**2
    streams["/gnss/fix"] = {
        "schema": "foxglove.LocationFix",
        "t": t_g[keep],
        "cols": {"latitude": lat_g[keep], "longitude": lon_g[keep], "altitude": alt_g[keep]},
        "const": {
            "frame_id": "gnss",
            "position_covariance": [var, 0.0, 0.0, 0.0, var, 0.0, 0.0, 0.0, 4 * var],
            "position_covariance_type": 2,
        },
    }

    # base station: fixed on the ground at the site, sees the main field and the diurnal
    if sens["base_station"]:
        t_b = _times(T, sens["base_rate_hz"], offs.get("base", 0.0), 0.0)
        b_base = igrf_ned_nT(
            site["latitude_deg"], site["longitude_deg"], site["ground_altitude_m"] + 1.0, when
        )[0]
        b_base = b_base + field_model.crust(np.zeros(1), np.zeros(1), np.ones(1))[0]
        tot = np.linalg.norm(b_base + field_model.diurnal(t_b)[:, None] * b_hat, axis=1)
        keep = _drop(t_b, "/base/scalar", drops)
        streams["/base/scalar"] = {
            "schema": "aeromag.ScalarField",
            "t": t_b[keep],
            "sensor_id": "base",
            "cols": {"total_nT": (tot + rng.normal(0, sens["base_noise_nT"], t_b.size))[keep]},
        }

    # auxiliary channels
    t_x = _times(T, sens["aux_rate_hz"], offs.get("aux", 0.0), margin)
    for name, (fn, unit, sigma) in aux_funcs.items():
        topic = f"/aux/{name}"
        keep = _drop(t_x, topic, drops)
        streams[topic] = {
            "schema": "aeromag.Scalar",
            "t": t_x[keep],
            "unit": unit,
            "cols": {"value": (fn(t_x) + rng.normal(0, sigma, t_x.size))[keep]},
        }

    segments = segment_truth(traj)
    if sens["plan_markers"]:
        tp = np.array([max(sg["start_s"], 0.0) for sg in segments])
        first = np.concatenate(
            [
                [True],
                [
                    segments[i]["label"] != segments[i - 1]["label"]
                    or segments[i]["line_id"] != segments[i - 1]["line_id"]
                    for i in range(1, len(segments))
                ],
            ]
        )
        streams["/plan/line"] = {
            "schema": "aeromag.LineMarker",
            "t": tp[first],
            "labels": {
                "line_id": [sg["line_id"] for sg, f in zip(segments, first, strict=True) if f],
                "kind": [sg["label"] for sg, f in zip(segments, first, strict=True) if f],
            },
        }

    truth = _truth(
        sc,
        seed,
        start_ns,
        traj,
        field_model,
        b0,
        scalar_int,
        vector_int,
        flux_err,
        lag_s,
        segments,
        scalar_truth,
    )
    # variety options report only when on: older truth documents stay as they were
    if calibration_variety(sc):
        truth["calibration_manoeuvres"] = manoeuvre_truth(traj)
    if outside_truth is not None:
        truth["outside_basis_interference"] = outside_truth
    if coupling_mean is not None:
        truth["effective"]["current_coupling_nT_per_A"] = coupling_mean
    return SimulatedFlight(sc, seed, start_ns, streams, truth, traj, scalar_truth)


def _truth(
    sc,
    seed,
    start_ns,
    traj,
    fm: EarthField,
    b0,
    scalar_int,
    vector_int,
    flux_err,
    lag_s,
    segments,
    scalar_truth,
) -> dict[str, Any]:
    s, a = sc["survey"], sc["anomaly"]
    cell = float(a["grid_cell_m"])
    along = np.array(
        [np.sin(np.radians(s["line_heading_deg"])), np.cos(np.radians(s["line_heading_deg"]))]
    )
    # Truth grid: axis-aligned east/north box around the survey area at survey height.
    corners = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], float)
    across = np.array([along[1], -along[0]])
    pts = (
        np.array([s["east_m"], s["north_m"]])
        + np.outer(corners[:, 0], s["length_m"] * along)
        + np.outer(corners[:, 1], s["width_m"] * across)
    )
    e0, n0 = pts.min(axis=0)
    e1, n1 = pts.max(axis=0)
    ne = int(np.floor((e1 - e0) / cell)) + 1
    nn = int(np.floor((n1 - n0) / cell)) + 1
    ge, gn = np.meshgrid(e0 + cell * np.arange(ne), n0 + cell * np.arange(nn))
    crust = fm.crust(ge.ravel(), gn.ravel(), np.full(ge.size, float(s["altitude_m"])))
    anom = total_field_anomaly_nT(crust, np.broadcast_to(b0, crust.shape)).reshape(nn, ne)
    total_b0 = float(np.linalg.norm(b0))
    recorded = sc.recorded_config()
    effects = {}
    for name, params in recorded["effects"].items():
        effects[name] = {k: v for k, v in params.items()}
    sens = sc["sensors"]
    return {
        "format": "aeromag.truth/1",
        "scenario": recorded,
        "seed": seed,
        "start_time_ns": start_ns,
        "duration_s": traj.duration_s,
        "site": {
            "latitude_deg": sc["site"]["latitude_deg"],
            "longitude_deg": sc["site"]["longitude_deg"],
            "ground_altitude_m": sc["site"]["ground_altitude_m"],
            "local_frame": fm.frame.crs,
        },
        "main_field": {
            "ned_nT": b0.tolist(),
            "total_nT": total_b0,
            "inclination_deg": float(np.degrees(np.arcsin(b0[2] / total_b0))),
            "declination_deg": float(np.degrees(np.arctan2(b0[1], b0[0]))),
        },
        "interference": {
            "scalar": scalar_int.to_dict(),
            "vector": vector_int.to_dict(),
            "enabled": bool(sc["interference_enabled"]),
        },
        "fluxgate_errors": flux_err.to_dict(),
        "effects": effects,
        "enabled_effects": sc.enabled_effects(),
        "effective": {"sensor_lag_s": lag_s, "gradient_nT_per_m": fm.gradient_nT_per_m.tolist()},
        "noise": {
            "scalar_nT": sens["scalar_noise_nT"],
            "vector_nT": sens["vector_noise_nT"],
            "attitude_deg": sens["attitude_noise_deg"],
            "gnss_m": sens["gnss_noise_m"],
            "base_nT": sens["base_noise_nT"],
            "scalar_drift_nT_per_sqrt_s": sens["scalar_drift_nT_per_sqrt_s"],
        },
        "segments": segments,
        "scalar_interference_nT": {
            "rms": float(np.sqrt(np.mean(scalar_truth["interference_nT"] ** 2))),
            "peak_to_peak": float(np.ptp(scalar_truth["interference_nT"])),
        },
        "anomaly": {
            "dipoles": [
                {
                    "east_m": d.east_m,
                    "north_m": d.north_m,
                    "up_m": d.up_m,
                    "moment_ned_A_m2": list(d.moment_ned_A_m2),
                }
                for d in fm.dipoles
            ],
            "grid": {
                "east0_m": float(e0),
                "north0_m": float(n0),
                "cell_m": cell,
                "shape": [nn, ne],
                "height_agl_m": float(s["altitude_m"]),
                "values_nT": np.round(anom, 4).tolist(),
            },
            "peak_abs_nT": float(np.max(np.abs(anom))),
        },
    }


def write_simulation(
    sim: SimulatedFlight,
    out: str | Path,
    truth_out: str | Path | None = None,
    topics: list[str] | None = None,
) -> Path:
    """Write the recording (streams merged in time order; only ``topics`` when given) and the
    truth JSON."""
    rows: list[tuple[int, str, int]] = []
    streams = {t: st for t, st in sim.streams.items() if topics is None or t in topics}
    for topic, st in streams.items():
        ns = sim.start_ns + np.round(np.asarray(st["t"]) * NS).astype(np.int64)
        st["ns"] = ns
        rows.extend((int(t), topic, i) for i, t in enumerate(ns))
    rows.sort(key=lambda r: (r[0], r[1]))
    out = Path(out)
    with McapOutput(out) as w:
        chan = {topic: w.channel(topic, st["schema"]) for topic, st in streams.items()}
        for t, topic, i in rows:
            st = streams[topic]
            payload: dict[str, Any] = {"timestamp": stamp(t)}
            if "sensor_id" in st:
                payload["sensor_id"] = st["sensor_id"]
            for k, col in st.get("cols", {}).items():
                payload[k] = float(col[i])
            for k, col in st.get("labels", {}).items():
                payload[k] = col[i]
            if "unit" in st:
                payload["unit"] = st["unit"]
            payload.update(st.get("const", {}))
            w.write(chan[topic], t, encode(payload))
    if truth_out is not None:
        write_json_atomic(truth_out, sim.truth)
    return out


def simulate_recording(
    scenario: str, seed: int, overrides: list[str], dst: Path, truth: Path | None = None
) -> dict[str, Any]:
    """``aeromag simulate`` (and the demo's flight): a built-in scenario or a TOML file, with
    ``key.sub=VALUE`` overrides, simulated with ``seed`` and written to ``dst`` (the truth
    document to ``truth`` when given).

    Returns
    -------
    dict
        ``out``, ``truth``, ``scenario``, ``duration_s``, ``messages``, ``effects``.
    """
    sc = Scenario.load(scenario, overrides)
    sim = simulate(sc, seed)
    write_simulation(sim, dst, truth)
    return {
        "out": str(dst),
        "truth": str(truth) if truth else None,
        "scenario": sc.name,
        "duration_s": float(sim.trajectory.duration_s),
        "messages": int(sum(len(s["t"]) for s in sim.streams.values())),
        "effects": list(sc.enabled_effects()),
    }
