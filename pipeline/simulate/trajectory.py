"""Flight plans and trajectories.

A plan is a list of straight legs (calibration headings, survey lines, tie lines, the "X"
validation lines, transits); consecutive legs are joined by Dubins turns (arc-line-arc at the
profile's turn radius) flown at the same speed (labelled ``turn`` inside a block, ``transit``
between blocks). The carrier flies at constant speed; attitude follows the path
(coordinated-turn bank from curvature) plus the calibration manoeuvres. Manoeuvres also
*move* the sensor, as the airframe's kinematics dictate; this is what makes a geomagnetic
gradient leak into the calibration band:

- multicopter: tilting accelerates it (a_right = g tan(roll), a_forward = -g tan(pitch));
- fixed-wing: banking turns it (a_right = g tan(roll), heading rate = g tan(roll)/V) and
  pitching climbs (v_up = V sin(pitch)).

Positions are local east/north/up metres about the site; angles in degrees; time in seconds
from the start of the recording. The trajectory is a cubic spline in time, so every sensor can
be sampled at its own epochs.

Calibration variety (all off by default): the legs of a box can be flown in any heading order
(``calibration.heading_order``: letters such as "WNES", or "random"), the manoeuvres of a leg
in any order (``manoeuvre_order = "random"``), and each manoeuvre block can draw its length,
period and amplitude from ranges (``block_duration_s``, ``period_range_s``,
``amplitude_range_deg``). The random draws use a generator seeded from the flight's seed and
created only when one of these options is on.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.ndimage import gaussian_filter1d

from pipeline.errors import AeromagError
from pipeline.simulate.scenario import Scenario

G = 9.80665
CARDINALS = {0: "N", 90: "E", 180: "S", 270: "W"}
HEADING_OF = {"N": 0.0, "E": 90.0, "S": 180.0, "W": 270.0}
KINDS = ("roll", "pitch", "yaw")


@dataclass
class Manoeuvre:
    """An attitude manoeuvre within a leg: a tapered sinusoid of one attitude angle.

    Attributes
    ----------
    kind : str
        ``roll``, ``pitch`` or ``yaw``.
    start_s : float
        Start, s from the start of its leg.
    period_s : float
        Period, s.
    amplitude_deg : float
        Amplitude, deg.
    cycles : float
        Number of cycles (whole by default; a randomised block may end mid-cycle).
    """

    kind: str  # roll | pitch | yaw
    start_s: float  # from the start of its leg
    period_s: float
    amplitude_deg: float
    cycles: float  # whole cycles by default; a randomised block may end mid-cycle

    @property
    def duration_s(self) -> float:
        """Length of the manoeuvre, s (period x cycles)."""
        return self.period_s * self.cycles


@dataclass
class Leg:
    """A straight, planned leg at constant height above ground."""

    label: str  # calibration | survey | tie | validation | transit
    line_id: str
    block: str  # legs of one block are joined by turns, of different blocks by transits
    start_en: np.ndarray
    end_en: np.ndarray
    alt_agl_m: float
    manoeuvres: list[Manoeuvre] = field(default_factory=list)
    cardinal: str = ""

    @property
    def length_m(self) -> float:
        """Horizontal length of the leg, m."""
        return float(np.linalg.norm(self.end_en - self.start_en))

    @property
    def direction(self) -> np.ndarray:
        """Unit vector of the leg, (east, north)."""
        d = self.end_en - self.start_en
        return d / np.linalg.norm(d)

    @property
    def heading_deg(self) -> float:
        """Track direction, degrees clockwise from true north, 0-360."""
        d = self.direction
        return float(np.degrees(np.arctan2(d[0], d[1])) % 360.0)


def _unit(heading_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """Along (heading) and right-hand unit vectors in (east, north)."""
    h = np.radians(heading_deg)
    return np.array([np.sin(h), np.cos(h)]), np.array([np.cos(h), -np.sin(h)])


def calibration_variety(sc: Scenario) -> bool:
    """True when a calibration variety option (order, randomised blocks) is on."""
    cal = sc["calibration"]
    return bool(
        cal["heading_order"]
        or cal["manoeuvre_order"]
        or cal["block_duration_s"]
        or cal["period_range_s"]
        or cal["amplitude_range_deg"]
    )


def plan_rng(seed: int) -> np.random.Generator:
    """The flight plan's own generator (independent of the simulator's main stream)."""
    return np.random.default_rng([int(seed), 16, 1])


def _range(cal: dict, key: str) -> tuple[float, float] | None:
    r = cal[key]
    if not r:
        return None
    if len(r) != 2 or not 0 < float(r[0]) <= float(r[1]):
        raise AeromagError(f"calibration.{key} must be [lo, hi] with 0 < lo <= hi, not {r!r}")
    return float(r[0]), float(r[1])


def _headings(cal: dict, rng: np.random.Generator | None) -> list[float]:
    order = str(cal["heading_order"])
    listed = [float(h) for h in cal["headings_deg"]]
    if not order:
        return listed
    if order.lower() == "random":
        assert rng is not None
        return [listed[i] for i in rng.permutation(len(listed))]
    letters = order.upper()
    if not letters or set(letters) - set(HEADING_OF):
        raise AeromagError(
            f'calibration.heading_order {order!r}: use letters N, E, S, W (e.g. "WNES") or "random"'
        )
    return [HEADING_OF[c] for c in letters]


def _leg_manoeuvres(cal: dict, rng: np.random.Generator | None) -> list[Manoeuvre]:
    """Roll, pitch and yaw blocks of one leg, separated by steady flight."""
    steady = cal["steady_s"]
    kinds = list(KINDS)
    if cal["manoeuvre_order"]:
        if str(cal["manoeuvre_order"]).lower() != "random":
            raise AeromagError(
                f"calibration.manoeuvre_order {cal['manoeuvre_order']!r}: use "
                '"random" (or leave it empty)'
            )
        assert rng is not None
        kinds = [kinds[i] for i in rng.permutation(3)]
    blocks, periods, amps = (
        _range(cal, k) for k in ("block_duration_s", "period_range_s", "amplitude_range_deg")
    )
    man: list[Manoeuvre] = []
    t = steady
    for kind in kinds:
        period = float(rng.uniform(*periods)) if periods and rng else cal[f"{kind}_period_s"]
        amp = float(rng.uniform(*amps)) if amps and rng else cal[f"{kind}_amplitude_deg"]
        if blocks and rng:
            cycles: float = float(rng.uniform(*blocks)) / period
        else:
            cycles = int(cal["cycles"])
        m = Manoeuvre(kind, t, period, amp, cycles)
        man.append(m)
        t += m.duration_s + steady
    return man


def calibration_legs(
    sc: Scenario, pass_no: int, rng: np.random.Generator | None = None
) -> list[Leg]:
    """The calibration box: one leg per heading, each with roll, pitch and yaw oscillations.

    ``rng`` (the plan's generator, see :func:`plan_rng`) draws the variety options; without
    it, or with them off, every leg flies the same fixed manoeuvres.
    """
    cal, v = sc["calibration"], sc["flight"]["speed_m_s"]
    survey = sc["survey"]
    centre = np.array(
        [survey["east_m"] + cal["centre_east_m"], survey["north_m"] + cal["centre_north_m"]]
    )
    variety = calibration_variety(sc)
    if variety and rng is None:
        rng = plan_rng(0)
    headings = _headings(cal, rng if variety else None)
    fixed = None if variety else _leg_manoeuvres(cal, None)
    legs = []
    for h in headings:
        man = _leg_manoeuvres(cal, rng) if variety else fixed
        assert man is not None
        length = v * (man[-1].start_s + man[-1].duration_s + cal["steady_s"])
        half = length / 2 + sc["flight"]["turn_radius_m"]
        along, right = _unit(h)
        mid = centre - half * right
        card = CARDINALS.get(round(h) % 360, f"{h:g}")
        legs.append(
            Leg(
                "calibration",
                f"C{pass_no}{card}",
                f"cal{pass_no}",
                mid - along * length / 2,
                mid + along * length / 2,
                cal["altitude_m"],
                [Manoeuvre(**vars(m)) for m in man],
                card,
            )
        )
    return legs


def _nearest_order(
    lines: list[tuple[np.ndarray, np.ndarray]], here: np.ndarray
) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """Fly parallel lines serpentine, starting with the line end nearest ``here``.

    Returns (index into ``lines``, start, end) in flying order.
    """
    first, last = lines[0], lines[-1]
    ends = (first[0], first[1], last[0], last[1])
    best = int(np.argmin([np.linalg.norm(p - here) for p in ends]))
    order = range(len(lines)) if best < 2 else range(len(lines) - 1, -1, -1)
    flip = best in (1, 3)
    out = []
    for k, i in enumerate(order):
        a, b = lines[i]
        out.append((i, b, a) if (k % 2 == 1) != flip else (i, a, b))
    return out


def survey_legs(sc: Scenario, here: np.ndarray) -> list[Leg]:
    """Serpentine survey lines, then tie lines across them, then the "X" validation lines."""
    s = sc["survey"]
    along, across = _unit(s["line_heading_deg"])
    # the flight lines, shifted across them by line_offset_m (the block itself stays)
    corner = np.array([s["east_m"], s["north_m"]]) + float(s["line_offset_m"]) * across
    L, W = s["length_m"], s["width_m"]
    n_lines = int(np.floor(W / s["line_spacing_m"] + 1e-9)) + 1
    lines = [
        (
            corner + i * s["line_spacing_m"] * across,
            corner + i * s["line_spacing_m"] * across + L * along,
        )
        for i in range(n_lines)
    ]
    legs: list[Leg] = []
    for num, a, b in _nearest_order(lines, here):
        legs.append(Leg("survey", f"L{10 * (num + 1):04d}", "survey", a, b, s["altitude_m"]))
    here = legs[-1].end_en
    n_ties = int(np.floor(L / s["tie_spacing_m"] + 1e-9)) + 1
    ties = [
        (
            corner + j * s["tie_spacing_m"] * along,
            corner + j * s["tie_spacing_m"] * along + W * across,
        )
        for j in range(n_ties)
    ]
    for num, a, b in _nearest_order(ties, here):
        legs.append(Leg("tie", f"T{10 * (num + 1):04d}", "survey", a, b, s["altitude_m"]))
    if s["validation"]:
        here = legs[-1].end_en
        diag = [
            (corner, corner + L * along + W * across),
            (corner + W * across, corner + L * along),
        ]
        # first diagonal from its end nearest the current position, second likewise
        for k, (a, b) in enumerate(diag):
            if np.linalg.norm(b - here) < np.linalg.norm(a - here):
                a, b = b, a
            legs.append(Leg("validation", f"V{10 * (k + 1):04d}", "survey", a, b, s["altitude_m"]))
            here = b
    return legs


def plan_legs(sc: Scenario, seed: int = 0) -> list[Leg]:
    """The whole flight plan, in flying order (transit legs at both ends).

    ``seed`` (the flight's) matters only when a calibration variety option is on.
    """
    v, tr = sc["flight"]["speed_m_s"], sc["flight"]["transit_s"]
    home = np.zeros(2)
    rng = plan_rng(seed) if calibration_variety(sc) else None
    cal1 = calibration_legs(sc, 1, rng)
    d0 = cal1[0].start_en - home
    d0 = d0 / (np.linalg.norm(d0) or 1.0)
    legs = [Leg("transit", "", "start", home, home + v * tr * d0, sc["calibration"]["altitude_m"])]
    legs += cal1
    if sc["survey"]["enabled"]:
        legs += survey_legs(sc, cal1[-1].end_en)
    if int(sc["calibration"]["passes"]) >= 2:
        legs += calibration_legs(sc, 2, rng)
    last = legs[-1]
    back = home - last.end_en
    back = back / (np.linalg.norm(back) or 1.0)
    start = last.end_en + 2 * sc["flight"]["turn_radius_m"] * last.direction
    legs.append(Leg("transit", "", "end", start, start + v * tr * back, last.alt_agl_m))
    return [leg for leg in legs if leg.length_m > 1e-6]


# --------------------------------------------------------------------------------------------
@dataclass
class Piece:
    """A flown piece: a leg, or the connection between two legs."""

    label: str
    line_id: str
    leg: Leg | None
    t0_s: float
    t1_s: float
    heading_deg: float | None
    cardinal: str = ""


class _Dubins:
    """Shortest arc-line-arc (Dubins CSC) path between two planar poses at turn radius R.

    Fixed-wing aircraft and multicopters in forward flight turn at a bounded bank angle, so
    their turns between lines are constant-radius arcs joined by a straight; for adjacent lines
    closer than 2R this is the familiar "bulb" turn. Angles here are mathematical (CCW from
    east); positions are (east, north) metres.
    """

    def __init__(self, p0, d0, p1, d1, radius: float):
        self.r = r = float(radius)
        a0, a1 = float(np.arctan2(d0[1], d0[0])), float(np.arctan2(d1[1], d1[0]))
        two_pi = 2 * np.pi

        def centre(p, a, side):  # side +1: left (CCW) circle, -1: right (CW) circle
            return np.asarray(p, float) + side * r * np.array([-np.sin(a), np.cos(a)])

        best = None
        for s0, s1 in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
            c0, c1 = centre(p0, a0, s0), centre(p1, a1, s1)
            v = c1 - c0
            dist = float(np.hypot(*v))
            phi = float(np.arctan2(v[1], v[0]))
            if s0 == s1:
                beta, straight = phi, dist
            else:
                if dist < 2 * r:
                    continue
                straight = float(np.sqrt(dist**2 - 4 * r**2))
                # c1 - c0 = straight * (cos b, sin b) + 2r s1 (-sin b, cos b)
                beta = phi - s1 * np.arctan2(2 * r, straight)
            arc0 = ((beta - a0) * s0) % two_pi
            arc1 = ((a1 - beta) * s1) % two_pi
            total = r * (arc0 + arc1) + straight
            if best is None or total < best[0]:
                best = (total, s0, s1, c0, c1, arc0, arc1, straight, beta)
        assert best is not None
        self.length, self.s0, self.s1, self.c0, self.c1, arc0, arc1, self.straight, self.beta = best
        self.l0, self.l1 = r * arc0, r * arc1
        self.a0 = a0
        # start of the straight: end of the first arc
        a_end0 = a0 + self.s0 * arc0
        self.q0 = self.c0 + self.s0 * r * np.array([np.sin(a_end0), -np.cos(a_end0)])

    def evaluate(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (n, 2), heading angle (math, rad) and signed curvature (CCW +) at arc
        length ``s``."""
        s = np.clip(np.asarray(s, float), 0.0, self.length)
        r = self.r
        pos = np.zeros((s.size, 2))
        ang = np.zeros(s.size)
        kap = np.zeros(s.size)
        m0 = s <= self.l0
        m1 = (s > self.l0) & (s <= self.l0 + self.straight)
        m2 = s > self.l0 + self.straight
        a = self.a0 + self.s0 * s[m0] / r
        pos[m0] = self.c0 + self.s0 * r * np.stack([np.sin(a), -np.cos(a)], -1)
        ang[m0], kap[m0] = a, self.s0 / r
        d = s[m1] - self.l0
        pos[m1] = self.q0 + np.outer(d, [np.cos(self.beta), np.sin(self.beta)])
        ang[m1] = self.beta
        sr = s[m2] - self.l0 - self.straight
        a = self.beta + self.s1 * sr / r
        pos[m2] = self.c1 + self.s1 * r * np.stack([np.sin(a), -np.cos(a)], -1)
        ang[m2], kap[m2] = a, self.s1 / r
        return pos, ang, kap


@dataclass
class Trajectory:
    """Carrier state as smooth functions of time since the start of the recording."""

    duration_s: float
    pieces: list[Piece]
    _spline: CubicSpline
    master_t: np.ndarray
    motor_load: np.ndarray  # manoeuvre intensity on the master grid (drives motor current)

    def state(self, t_s) -> dict[str, np.ndarray]:
        """east_m, north_m, up_m (above ground), roll_deg, pitch_deg, yaw_deg (0-360)."""
        v = self._spline(np.asarray(t_s, float))
        return {
            "east_m": v[..., 0],
            "north_m": v[..., 1],
            "up_m": v[..., 2],
            "roll_deg": v[..., 3],
            "pitch_deg": v[..., 4],
            "yaw_deg": np.mod(v[..., 5], 360),
        }

    def motor_load_at(self, t_s) -> np.ndarray:
        """Manoeuvre intensity (drives the simulated motor current) at times ``t_s``.

        Parameters
        ----------
        t_s : float or ndarray
            s since the start of the flight.

        Returns
        -------
        ndarray
            Dimensionless load, interpolated from the master time grid.
        """
        return np.interp(t_s, self.master_t, self.motor_load)


def _envelope(t: np.ndarray, duration: float, ramp: float) -> np.ndarray:
    """Raised-cosine ramps at both ends: angle *and* rate start and stop at zero, as a real
    airframe must (a bare sinusoid would demand an infinite angular acceleration)."""
    up = np.clip(t / ramp, 0.0, 1.0)
    down = np.clip((duration - t) / ramp, 0.0, 1.0)
    return 0.5 * (1 - np.cos(np.pi * np.minimum(up, down)))


def _oscillation(x: np.ndarray, omega: float, dt: float, order: int) -> np.ndarray:
    """Steady-state integral (order 1) or double integral (order 2) of a harmonic signal.

    For x = X sin(w t): the integral is -x'/w^2 and the double integral -x/w^2. This is the
    oscillating excursion about the held track (the autopilot or pilot removes the drift a bare
    numerical integral would accumulate), exact for a pure manoeuvre harmonic.
    """
    if order == 2:
        return -x / omega**2
    return -np.gradient(x, dt) / omega**2


def build_trajectory(sc: Scenario, seed: int = 0) -> Trajectory:
    """Fly the scenario's plan: constant speed, smooth turns, calibration manoeuvres.

    ``seed`` (the flight's) matters only when a calibration variety option is on.
    """
    fl = sc["flight"]
    v, radius = float(fl["speed_m_s"]), float(fl["turn_radius_m"])
    dt = 1.0 / float(fl["master_rate_hz"])
    legs = plan_legs(sc, seed)

    # Pieces in time order, each with a geometry evaluator.
    pieces: list[Piece] = []
    geoms: list[tuple[str, object, float, float]] = []  # kind, geom, alt0, alt1
    t = 0.0
    for i, leg in enumerate(legs):
        if i > 0:
            prev = legs[i - 1]
            curve = _Dubins(prev.end_en, prev.direction, leg.start_en, leg.direction, radius)
            same = prev.block == leg.block or {prev.block, leg.block} <= {"survey"}
            dur = curve.length / v
            pieces.append(Piece("turn" if same else "transit", "", None, t, t + dur, None))
            geoms.append(("curve", curve, prev.alt_agl_m, leg.alt_agl_m))
            t += dur
        dur = leg.length_m / v
        pieces.append(Piece(leg.label, leg.line_id, leg, t, t + dur, leg.heading_deg, leg.cardinal))
        geoms.append(("leg", leg, leg.alt_agl_m, leg.alt_agl_m))
        t += dur
    duration = t
    tm = np.arange(0.0, duration + dt, dt)
    n = tm.size
    east, north, up = np.zeros(n), np.zeros(n), np.zeros(n)
    heading, roll = np.zeros(n), np.zeros(n)
    d_roll, d_pitch, d_yaw = np.zeros(n), np.zeros(n), np.zeros(n)
    disp_f, disp_r, disp_u, turn_yaw = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    max_bank = float(fl["max_bank_deg"])
    fixed_wing = fl["kinematics"] == "fixed-wing"
    climb_pitch = np.zeros(n)

    for piece, (kind, geom, alt0, alt1) in zip(pieces, geoms, strict=True):
        sel = (
            (tm >= piece.t0_s) & (tm < piece.t1_s)
            if piece is not pieces[-1]
            else (tm >= piece.t0_s)
        )
        s = np.clip((tm[sel] - piece.t0_s) * v, 0.0, None)
        length = (piece.t1_s - piece.t0_s) * v
        frac = np.clip(s / length, 0.0, 1.0) if length > 0 else np.zeros_like(s)
        up[sel] = alt0 + (alt1 - alt0) * frac
        if fixed_wing and length > 0:
            climb_pitch[sel] = np.degrees(np.arctan2(alt1 - alt0, length))
        if kind == "leg":
            leg: Leg = geom  # type: ignore[assignment]
            p = leg.start_en + np.outer(np.minimum(s, leg.length_m), leg.direction)
            east[sel], north[sel] = p[:, 0], p[:, 1]
            heading[sel] = leg.heading_deg
            idx = np.flatnonzero(sel)
            for m in leg.manoeuvres:
                w = idx[
                    (tm[idx] >= piece.t0_s + m.start_s)
                    & (tm[idx] <= piece.t0_s + m.start_s + m.duration_s)
                ]
                if w.size < 3:
                    continue
                tt = tm[w] - tm[w[0]]
                delta = (
                    m.amplitude_deg
                    * np.sin(2 * np.pi * tt / m.period_s)
                    * _envelope(tt, m.duration_s, m.period_s / 2)
                )
                omega = 2 * np.pi / m.period_s
                if m.kind == "roll":
                    d_roll[w] = delta
                    a_right = G * np.tan(np.radians(delta))
                    disp_r[w] = _oscillation(a_right, omega, dt, 2)
                    if fixed_wing:
                        turn_yaw[w] = np.degrees(_oscillation(a_right / v, omega, dt, 1))
                elif m.kind == "pitch":
                    d_pitch[w] = delta
                    if fixed_wing:
                        disp_u[w] = _oscillation(v * np.sin(np.radians(delta)), omega, dt, 1)
                    else:
                        disp_f[w] = _oscillation(-G * np.tan(np.radians(delta)), omega, dt, 2)
                else:
                    d_yaw[w] = delta
        else:
            curve: _Dubins = geom  # type: ignore[assignment]
            p, ang, kappa = curve.evaluate(s)
            east[sel], north[sel] = p[:, 0], p[:, 1]
            heading[sel] = 90.0 - np.degrees(ang)
            # Counter-clockwise curvature is a left turn: bank is negative.
            roll[sel] = np.clip(np.degrees(np.arctan(-(v**2) * kappa / G)), -max_bank, max_bank)

    # Roll-in and pitch changes take time: smooth the piecewise-constant bank and climb angles.
    sigma = float(fl["roll_in_s"]) / dt
    roll = gaussian_filter1d(roll, sigma, mode="nearest")
    climb_pitch = gaussian_filter1d(climb_pitch, sigma, mode="nearest")

    # Heading rate follows the bank (coordinated turn), so it too ramps in over roll_in_s; the
    # few-degree difference from the track at arc ends is a realistic crab angle.
    hd = gaussian_filter1d(np.unwrap(np.radians(heading)), sigma, mode="nearest")
    along = np.stack([np.sin(hd), np.cos(hd)], axis=1)
    right = np.stack([np.cos(hd), -np.sin(hd)], axis=1)
    east += disp_f * along[:, 0] + disp_r * right[:, 0]
    north += disp_f * along[:, 1] + disp_r * right[:, 1]
    up += disp_u
    yaw = np.degrees(hd) + d_yaw + turn_yaw
    roll_all = roll + d_roll
    pitch_all = float(fl["cruise_pitch_deg"]) + climb_pitch + d_pitch
    spline = CubicSpline(tm, np.stack([east, north, up, roll_all, pitch_all, yaw], axis=1), axis=0)
    load = np.abs(d_roll) / 10.0 + np.abs(d_pitch) / 5.0 + np.abs(d_yaw) / 5.0
    return Trajectory(duration, pieces, spline, tm, load)


def manoeuvre_truth(traj: Trajectory) -> list[dict]:
    """Every calibration manoeuvre block as flown: leg, kind, times, period and amplitude."""
    out = []
    for p in traj.pieces:
        if p.leg is None:
            continue
        for m in p.leg.manoeuvres:
            out.append(
                {
                    "line_id": p.line_id,
                    "cardinal": p.cardinal,
                    "heading_deg": round(float(p.heading_deg or 0.0), 3),
                    "kind": m.kind,
                    "start_s": float(p.t0_s + m.start_s),
                    "end_s": float(p.t0_s + m.start_s + m.duration_s),
                    "period_s": float(m.period_s),
                    "amplitude_deg": float(m.amplitude_deg),
                    "cycles": float(m.cycles),
                }
            )
    return out


def segment_truth(traj: Trajectory) -> list[dict]:
    """Labelled time intervals: pieces, with calibration legs split into their manoeuvres."""
    out: list[dict] = []
    for p in traj.pieces:
        base = {
            "label": p.label,
            "line_id": p.line_id,
            "heading_deg": None if p.heading_deg is None else round(p.heading_deg, 3),
            "manoeuvre": "",
            "cardinal": p.cardinal,
        }
        if p.leg is None or not p.leg.manoeuvres:
            out.append({**base, "start_s": p.t0_s, "end_s": p.t1_s})
            continue
        cur = p.t0_s
        for m in p.leg.manoeuvres:
            a, b = p.t0_s + m.start_s, p.t0_s + m.start_s + m.duration_s
            if a > cur:
                out.append({**base, "manoeuvre": "steady", "start_s": cur, "end_s": a})
            out.append({**base, "manoeuvre": m.kind, "start_s": a, "end_s": b})
            cur = b
        if cur < p.t1_s:
            out.append({**base, "manoeuvre": "steady", "start_s": cur, "end_s": p.t1_s})
    return out
