"""Navigation re-flown on a recording: INS errors simulated along the true track, corrected by
the map-aided filter, checked against ``/gnss/fix`` (the reference) and the CRLB.

The INS starts at the first epoch of the selected segments (validation lines by default) and
runs without a break to the last one; the map is used on the selected segments' epochs whose
indicated position is on the map (turns between lines are dead reckoning). Errors are
reported on the selected epochs. The measured anomaly is the compensated field reduced as the
map was (IGRF and the smoothed base-station diurnal, :func:`pipeline.maps.reduce.reduce_to_anomaly`)
with the IGRF taken at the INS-indicated position (the true one is what navigation lacks).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from pipeline.defaults import default_field
from pipeline.errors import AeromagError
from pipeline.flight import Flight
from pipeline.io.contract import INS_FIELDS
from pipeline.maps.reduce import igrf_total_gradient_nT_per_m, reduce_to_anomaly
from pipeline.navigation.alignment import gnss_aided_covariance
from pipeline.navigation.crlb import crlb
from pipeline.navigation.ekf import (
    FilterResult,
    MeasurementModel,
    correlated_error_scale,
    ekf,
    gate_sigma_of,
)
from pipeline.navigation.ins import (
    GRADES,
    N_INS,
    InsErrorModel,
    Trajectory,
    simulate_ins_errors,
)
from pipeline.navigation.map_io import GeoMap
from pipeline.navigation.map_model import (
    MapModel,
    upward_continue,
    vertical_derivative,
    wiener_smooth,
)
from pipeline.navigation.pf import particle_filter
from pipeline.noise import white_noise_nT
from pipeline.segment import Segmentation

# the map's vertical derivative is smoothed by continuing the map up this many cells first
# (unsmoothed, its gridding noise made the filter overconfident: docs/navigation.md)
VERTICAL_SMOOTHING_CELLS = 4.0
SEGMENT_LABELS = {"validation": ("validation",), "survey": ("survey", "tie"), "all": ()}
# the INS navigated: the recording's own (/ins/solution), a simulated one of a grade, or
# "auto": the recording's when it has one, else a simulated navigation-grade INS
INS_CHOICES = ("auto", "recorded", *GRADES)
# the error model (process noise, transitions) a recorded INS is filtered with: its own
# errors are in the record, its grade is not
RECORDED_INS_MODEL = "navigation"


@dataclass
class NavigationSettings:
    """Settings of a navigation run.

    ``max_uncovered`` is the largest fraction of the selected epochs whose true position may be
    off the map. ``map_sigma_nT``: the map's 1-sigma error everywhere (nT, ``--map-sigma``);
    None: the map's own error grid when it has one, else ``default_map_sigma_nT``.
    ``sensor_sigma_nT`` None: the track's white noise (4th differences).
    ``gate_probability``: the chi-square probability of the innovation gate (0: no gate).
    """

    filter: str = default_field("navigate", "filter")
    ins: str = default_field("navigate", "ins")
    segments: str = "validation"
    seed: int = default_field("navigate", "seed")
    particles: int = 1000
    # the particle filter hands over to the EKF once its cloud stays within this DRMS, m
    # (None: particles to the end)
    pf_handover_m: float | None = 5.0
    mag_bias_nT: float = 1.0
    mag_bias_tau_s: float = 600.0
    map_sigma_nT: float | None = None
    default_map_sigma_nT: float = default_field("navigate", "map_sigma_nT")
    gate_probability: float = default_field("navigate", "gate_probability")
    map_error_length_m: float = default_field("navigate", "map_error_length_m")
    sensor_sigma_nT: float | None = None
    max_uncovered: float = 0.5
    # the window starts from a GNSS-aided INS's covariance (pipeline.navigation.alignment)
    gnss_aided_s: float = default_field("navigate", "gnss_aided_s")
    gnss_sigma_m: float = default_field("navigate", "gnss_sigma_m")

    def check(self) -> None:
        """Raise :class:`AeromagError` (one line) for an unknown filter, INS grade or segment
        choice."""
        if self.filter not in ("ekf", "pf"):
            raise AeromagError(f"--filter {self.filter!r}: use ekf or pf")
        if self.ins not in INS_CHOICES:
            raise AeromagError(f"--ins {self.ins!r}: use {', '.join(INS_CHOICES)}")
        if self.segments not in SEGMENT_LABELS:
            raise AeromagError(f"--segments {self.segments!r}: use validation, survey or all")
        for name, v in (
            ("--map-sigma", self.map_sigma_nT),
            ("map_sigma_nT", self.default_map_sigma_nT),
            ("--sensor-sigma", self.sensor_sigma_nT),
            ("map_error_length_m", self.map_error_length_m),
        ):
            if v is not None and not (np.isfinite(v) and v >= 0):
                raise AeromagError(f"{name} {v!r}: a 1-sigma error in nT must be >= 0")
        if not (0.0 <= self.gate_probability < 1.0):
            raise AeromagError(
                f"gate_probability {self.gate_probability!r}: use a probability in (0, 1), "
                "or 0 for no gate"
            )
        if not (self.gnss_aided_s > 0 and self.gnss_sigma_m > 0):
            raise AeromagError(
                f"gnss_aided_s {self.gnss_aided_s!r} and gnss_sigma_m {self.gnss_sigma_m!r}: "
                "both must be > 0"
            )


def _metrics(dn: np.ndarray, de: np.ndarray) -> dict[str, float]:
    r = np.hypot(dn, de)
    return {
        "drms_m": float(np.sqrt(np.mean(r * r))),
        "cep50_m": float(np.median(r)),
        "max_m": float(r.max()),
        "final_m": float(r[-1]),
    }


@dataclass
class NavigationRun:
    """A navigation run over the window ``index`` (flight epochs)."""

    index: np.ndarray
    selected: np.ndarray  # (N,) bool: the chosen segments' epochs within the window
    segment_id: np.ndarray  # (N,) line id (or label) per epoch
    time_ns: np.ndarray
    true_en: np.ndarray  # (N, 2) east, north in the map frame, m
    true_alt_m: np.ndarray
    ins_error: np.ndarray  # (N, 17) simulated INS error states
    result: FilterResult
    crlb_cov_m2: np.ndarray  # (N, 2, 2) north/east bound
    ins_cov_m2: np.ndarray  # (N, 2, 2) INS-only covariance (no map)
    anomaly_nT: np.ndarray
    r_nT2: float
    sensor_sigma_nT: float
    map_sigma_nT: float
    settings: NavigationSettings
    geomap: GeoMap
    map_model: MapModel
    coverage: float
    notes: list[str] = field(default_factory=list)
    timings_s: dict[str, float] = field(default_factory=dict)
    ins_source: str = "simulated"  # or "recorded": the recording's /ins/solution
    # (N, 2, 2) map-frame (east, north) m per (north, east) m (GeoMap.ned_to_map; None: axes
    # along north and east)
    ned_to_map: np.ndarray | None = None
    map_sigma_source: str = "grid"  # grid (the map's own) | user (--map-sigma) | default
    map_var_scale: float = 1.0  # the map error variance's inflation (correlated_error_scale)

    def settings_grade(self):
        """The INS grade's error budget (:class:`pipeline.navigation.ins.InsGrade`)."""
        return GRADES[self.settings.ins]

    # positions ----------------------------------------------------------------------
    def _to_map(self, ne: np.ndarray) -> np.ndarray:
        """(n, 2) north/east offsets (m) as map-frame east/north offsets."""
        if self.ned_to_map is None:
            return ne[:, [1, 0]]
        return np.einsum("kij,kj->ki", self.ned_to_map, ne)

    def ins_en(self) -> np.ndarray:
        """INS-indicated positions, (n, 2) east/north m in the map's frame."""
        return self.true_en + self._to_map(self.ins_error[:, :2])

    def aided_en(self) -> np.ndarray:
        """Map-aided positions (INS corrected by the filter's error estimate), (n, 2) east/north
        m in the map's frame."""
        return self.true_en + self._to_map(self.aided_error_ne())

    def ins_error_ne(self) -> np.ndarray:
        """INS position error (indicated minus true), (n, 2) north/east m."""
        return self.ins_error[:, :2]

    def aided_error_ne(self) -> np.ndarray:
        """Map-aided position error (indicated minus true), (n, 2) north/east m."""
        return self.ins_error[:, :2] - self.result.state[:, :2]

    # statistics ---------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """NAV.json's ``navigation`` block: DRMS (INS-only, map-aided, CRLB) and CEP50 in m
        over the selected epochs, errors per segment, the map and the settings used."""
        sel = self.selected
        ins = self.ins_error_ne()[sel]
        aid = self.aided_error_ne()[sel]
        c = self.crlb_cov_m2[sel]
        crlb_drms = float(np.sqrt(np.mean(c[:, 0, 0] + c[:, 1, 1])))
        p = self.result.pos_cov_m2[sel]
        m_ins, m_aid = _metrics(*ins.T), _metrics(*aid.T)
        per: dict[str, Any] = {}
        for sid in dict.fromkeys(self.segment_id[sel]):
            k = sel & (self.segment_id == sid)
            cc = self.crlb_cov_m2[k]
            per[str(sid)] = {
                "epochs": int(k.sum()),
                "ins_only": _metrics(*self.ins_error_ne()[k].T),
                "map_aided": _metrics(*self.aided_error_ne()[k].T),
                "crlb_drms_m": float(np.sqrt(np.mean(cc[:, 0, 0] + cc[:, 1, 1]))),
            }
        innov = self.result.innovation_nT
        ok = np.isfinite(innov)
        nis = innov[ok] ** 2 / self.result.innovation_var_nT2[ok]
        aid_all = self.aided_error_ne()
        pinv = np.linalg.inv(self.result.pos_cov_m2[sel])
        nees = np.einsum("ki,kij,kj->k", aid_all[sel], pinv, aid_all[sel])
        t = (self.time_ns - self.time_ns[0]) / 1e9
        return {
            "drms_m": {
                "ins_only": m_ins["drms_m"],
                "map_aided": m_aid["drms_m"],
                "crlb": crlb_drms,
            },
            "cep50_m": {"ins_only": m_ins["cep50_m"], "map_aided": m_aid["cep50_m"]},
            "max_m": {"ins_only": m_ins["max_m"], "map_aided": m_aid["max_m"]},
            "filter_drms_m": float(np.sqrt(np.mean(p[:, 0, 0] + p[:, 1, 1]))),
            "ratio_map_aided_to_ins_only": m_aid["drms_m"] / max(m_ins["drms_m"], 1e-12),
            "ratio_map_aided_to_crlb": m_aid["drms_m"] / max(crlb_drms, 1e-12),
            "segments": per,
            "epochs": {
                "window": int(self.index.size),
                "selected": int(sel.sum()),
                "map_updates": int(self.result.updated.sum()),
                "duration_s": float(t[-1]),
                "start_ns": int(self.time_ns[0]),
            },
            "coverage": self.coverage,
            "nees": consistency(nees, 2, correlated=True),
            "nis": consistency(nis, 1, correlated=False),
            "measurement": {
                "sensor_sigma_nT": self.sensor_sigma_nT,
                "map_sigma_nT": self.map_sigma_nT,
                "map_sigma_source": self.map_sigma_source,
                "map_error_length_m": self.geomap.error_length_m
                or self.settings.map_error_length_m,
                "map_variance_scale": self.map_var_scale,
                "gate_probability": self.settings.gate_probability,
                "rejected_by_gate": int(self.result.rejected),
                "r_nT2": self.r_nT2,
                "mag_bias_sigma_nT": self.settings.mag_bias_nT,
                "mag_bias_tau_s": self.settings.mag_bias_tau_s,
                "innovation_rms_nT": float(np.sqrt(np.mean(innov[ok] ** 2))) if ok.any() else None,
                "normalised_innovation_mean": float(np.mean(nis)) if ok.any() else None,
            },
            "covariance": {
                "min_eigenvalue": self.result.min_eigenvalue,
                "max_asymmetry": self.result.max_asymmetry,
            },
            "ins": {
                "source": self.ins_source,
                "grade": self.settings.ins,
                **_grade_dict(self.settings.ins),
            },
            "map": {**self.geomap.describe(), "used_altitude_m": self.map_model.altitude_m},
            "settings": asdict(self.settings),
            "reference": "/gnss/fix",
            "notes": self.notes,
            "timings_s": self.timings_s,
        }


def _effective_count(x: np.ndarray) -> float:
    """Independent samples in a series: its length over the integrated autocorrelation time
    (``1 + 2 sum rho_k``, summed to the first non-positive ``rho_k``)."""
    n = x.size
    if n < 3 or np.std(x) == 0:
        return float(n)
    d = x - x.mean()
    f = np.fft.rfft(d, 2 * n)
    ac = np.fft.irfft(f * np.conj(f))[:n]
    rho = ac / ac[0]
    stop = np.flatnonzero(rho[1:] <= 0.0)
    cut = int(stop[0]) + 1 if stop.size else n
    tau = 1.0 + 2.0 * float(np.sum(rho[1:cut]))
    return float(max(1.0, n / tau))


def consistency(values: np.ndarray, dof: int, correlated: bool) -> dict[str, Any]:
    """A normalised squared error's time average and its 95 % chi-square band.

    For a consistent filter each value is chi-square with ``dof`` degrees of freedom, so the
    mean of K independent ones is ``chi2(dof K) / K``: ``band95`` is its 2.5 and 97.5 %
    quantiles. ``correlated``: K is the series' effective count (:func:`_effective_count`;
    estimation errors are correlated over many epochs), else its length (innovations of a
    consistent filter are white).
    """
    from scipy.stats import chi2

    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"mean": None, "band95": None, "within_band": None, "samples": 0}
    k = _effective_count(v) if correlated else float(v.size)
    lo, hi = (float(chi2.ppf(q, dof * k) / k) for q in (0.025, 0.975))
    m = float(v.mean())
    return {
        "mean": m,
        "band95": [lo, hi],
        "within_band": bool(lo <= m <= hi),
        "dof": dof,
        "samples": int(v.size),
        "independent_samples": k,
    }


def _grade_dict(name: str) -> dict[str, float]:
    g = GRADES[name]
    return {k: (float(v) if not isinstance(v, str) else v) for k, v in asdict(g).items()}


def select_window(
    flight: Flight, seg: Segmentation | None, segments: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The navigation window (epoch indices), the selected epochs in it, and each epoch's
    segment id (line id on lines, else the label)."""
    d = flight.data
    ok = np.ones(flight.time_ns.size, bool)
    for c in ("lat_deg", "lon_deg", "alt_m"):
        ok &= np.isfinite(d[c].to_numpy(float))
    labels = SEGMENT_LABELS[segments]
    if labels:
        if seg is None:
            raise AeromagError(
                f"--segments {segments} needs the flight's segmentation (none found); "
                "use --segments all",
                file=flight.source,
                channel="/flight/segment",
            )
        chosen = seg.mask(*labels) & ok
        ids = np.where(seg.line_id != "", seg.line_id, seg.label).astype(str)
    else:
        chosen = ok
        ids = np.full(ok.size, "all")
    if chosen.sum() < 10:
        raise AeromagError(
            f"no {segments} epochs with a position to navigate on",
            file=flight.source,
            channel="/flight/segment" if labels else "/gnss/fix",
        )
    ix = np.flatnonzero(chosen)
    win = np.arange(ix[0], ix[-1] + 1)
    win = win[ok[win]]
    return win, chosen[win], ids[win]


def check_coverage(
    geomap: GeoMap, east_m: np.ndarray, north_m: np.ndarray, settings: NavigationSettings
) -> float:
    """The fraction of the points (true positions of the scored epochs) on the map; raises a
    one-line error naming the uncovered fraction above ``settings.max_uncovered``."""
    on = MapModel(geomap.grid).inside(east_m, north_m)
    uncovered = 1.0 - float(on.mean()) if on.size else 1.0
    if uncovered > settings.max_uncovered:
        raise AeromagError(
            f"the map does not cover the track: {uncovered:.0%} of the {settings.segments} "
            f"epochs ({int((~on).sum())} of {on.size}) are off the map (at most "
            f"{settings.max_uncovered:.0%} allowed)",
            file=geomap.source,
        )
    return 1.0 - uncovered


def track_coverage(
    flight: Flight, seg: Segmentation | None, geomap: GeoMap, settings: NavigationSettings
) -> float:
    """:func:`check_coverage` on a flight's scored epochs (before any compensation is run)."""
    win, selected, _ = select_window(flight, seg, settings.segments)
    lat = flight.data["lat_deg"].to_numpy(float)[win][selected]
    lon = flight.data["lon_deg"].to_numpy(float)[win][selected]
    e, n = geomap.to_local(lat, lon)
    return check_coverage(geomap, np.asarray(e, float), np.asarray(n, float), settings)


def _trajectory(
    flight: Flight, idx: np.ndarray, east_m, north_m, up_m, notes: list[str]
) -> Trajectory:
    """The true track of epochs ``idx`` (positions in the map's frame, attitude when whole)."""
    d = flight.data
    att = (
        [d[c].to_numpy(float)[idx] for c in ("roll_deg", "pitch_deg", "yaw_deg")]
        if flight.has("roll_deg", "pitch_deg", "yaw_deg")
        else [None, None, None]
    )
    if att[0] is not None and not all(np.isfinite(a).all() for a in att):
        att = [None, None, None]
        notes.append("attitude incomplete in the window: body axes taken along the track")
    t = d["time_s"].to_numpy(float)[idx]
    lat = d["lat_deg"].to_numpy(float)[idx]
    return Trajectory.from_track(t, north_m, east_m, up_m, lat, *att)


def _gnss_aided_p0(
    flight: Flight,
    win: np.ndarray,
    geomap: GeoMap,
    model: InsErrorModel,
    window_traj: Trajectory,
    s: NavigationSettings,
    notes: list[str],
) -> np.ndarray:
    """The initial covariance of the window: a GNSS-aided run over the ``s.gnss_aided_s``
    seconds of track before it (or, when less than a tenth of that precedes it, over the
    window's own first ``s.gnss_aided_s`` seconds, noted)."""
    d = flight.data
    t_all = d["time_s"].to_numpy(float)
    ok = np.ones(t_all.size, bool)
    for c in ("lat_deg", "lon_deg", "alt_m"):
        ok &= np.isfinite(d[c].to_numpy(float))
    before = np.flatnonzero(ok[: win[0]] & (t_all[: win[0]] >= t_all[win[0]] - s.gnss_aided_s))
    if before.size > 10 and t_all[before[-1]] - t_all[before[0]] >= 0.1 * s.gnss_aided_s:
        lat, lon = d["lat_deg"].to_numpy(float), d["lon_deg"].to_numpy(float)
        alt = d["alt_m"].to_numpy(float)
        e, n = (np.asarray(v, float) for v in geomap.to_local(lat[before], lon[before]))
        aided = _trajectory(flight, before, e, n, alt[before] - np.mean(alt[before]), [])
        span = t_all[before[-1]] - t_all[before[0]]
        notes.append(f"initial covariance: GNSS-aided INS over the {span:.0f} s before the window")
    else:
        k = np.searchsorted(window_traj.time_s, window_traj.time_s[0] + s.gnss_aided_s)
        k = max(k, min(10, len(window_traj)))
        w = window_traj
        aided = Trajectory(
            w.time_s[:k], w.lat_rad[:k], w.vel_ned_mps[:k], w.force_ned_mps2[:k], w.c_nb[:k]
        )
        notes.append(
            "initial covariance: GNSS-aided INS over the window's first "
            f"{w.time_s[k - 1] - w.time_s[0]:.0f} s (no track flown before it)"
        )
    return gnss_aided_covariance(model, aided, s.gnss_sigma_m)


def _measurement_model(
    mm: MapModel, time_ns, ins_lat_deg, ins_lon_deg, ins_alt_m, notes: list[str]
) -> MeasurementModel:
    """The filters' measurement: the map, its vertical derivative times the height above the
    map (when the map's altitude is known), and the core field's gradient at the indicated
    position (the measurement is the total field reduced with the IGRF there)."""
    vertical, above = None, None
    if mm.altitude_m is not None:
        # the derivative's |k| amplifies the gridding noise of the shortest wavelengths, which
        # no map resolves: it is taken on the map continued up by four cells (a line spacing
        # for aeromag's maps, whose cells are a quarter of it)
        smooth = upward_continue(mm.grid, VERTICAL_SMOOTHING_CELLS * mm.grid.cell_m)
        vertical = MapModel(vertical_derivative(smooth), method=mm.method)
        above = np.asarray(ins_alt_m, float) - mm.altitude_m
    else:
        notes.append("map altitude unknown: no altitude term in the measurement")
    grad = igrf_total_gradient_nT_per_m(time_ns, ins_lat_deg, ins_lon_deg, ins_alt_m)
    return MeasurementModel(mm, None, vertical, above, grad)


def ins_source(flight: Flight, choice: str) -> tuple[str, str]:
    """(``"recorded"`` or ``"simulated"``, the error model's grade) for ``--ins choice``.

    Raises
    ------
    AeromagError
        ``recorded`` asked of a recording without ``/ins/solution``.
    """
    has = flight.has(*(f"ins_{name}" for name in INS_FIELDS))
    if choice == "recorded" and not has:
        raise AeromagError(
            "--ins recorded: the recording has no INS solution",
            file=flight.source,
            channel="/ins/solution",
        )
    if choice == "recorded" or (choice == "auto" and has):
        return "recorded", RECORDED_INS_MODEL
    return "simulated", "navigation" if choice == "auto" else choice


def recorded_ins_errors(flight: Flight, win: np.ndarray, traj: Trajectory) -> np.ndarray:
    """The recorded INS's errors over the window: its position (m, north/east along the
    geodesic from the true position, up) and NED velocity (m/s) less the true track's, as
    the first six of the ``N_INS`` error states (indicated minus true, NED like the Pinson
    states, not the map grid's axes); the others, which no record holds, zero.

    Raises
    ------
    AeromagError
        The recorded INS does not cover every epoch of the window.
    """
    d = flight.data
    cols = {name: d[f"ins_{name}"].to_numpy(float)[win] for name in INS_FIELDS}
    missing = ~np.all(np.isfinite(np.column_stack(list(cols.values()))), axis=1)
    if missing.any():
        raise AeromagError(
            f"the recorded INS does not cover the navigated track: {int(missing.sum())} of "
            f"{missing.size} epochs without it",
            file=flight.source,
            channel="/ins/solution",
        )
    from pyproj import Geod

    lat, lon = d["lat_deg"].to_numpy(float)[win], d["lon_deg"].to_numpy(float)[win]
    az, _, dist = Geod(ellps="WGS84").inv(lon, lat, cols["longitude_deg"], cols["latitude_deg"])
    az = np.radians(np.asarray(az, float))
    x = np.zeros((win.size, N_INS))
    x[:, 0], x[:, 1] = dist * np.cos(az), dist * np.sin(az)
    x[:, 2] = cols["altitude_m"] - d["alt_m"].to_numpy(float)[win]
    v = np.column_stack(
        [cols["velocity_north_m_s"], cols["velocity_east_m_s"], cols["velocity_down_m_s"]]
    )
    x[:, 3:6] = v - traj.vel_ned_mps
    return x


def run_navigation(
    flight: Flight,
    seg: Segmentation | None,
    compensated_nT: np.ndarray,
    geomap: GeoMap,
    settings: NavigationSettings | None = None,
) -> NavigationRun:
    """Simulate the INS along the flight, run the map-aided filter and the CRLB.

    Parameters
    ----------
    flight : Flight
        The recording (true track from ``/gnss/fix`` and ``/ins/attitude``).
    seg : Segmentation or None
        Its segmentation (needed unless ``settings.segments == "all"``).
    compensated_nT : (epochs,) ndarray
        The compensated total field on the flight's epochs, nT.
    geomap : GeoMap
        The map and its placement.
    """
    import time

    s = settings or NavigationSettings()
    s.check()
    source, grade = ins_source(flight, s.ins)
    s = replace(s, ins=grade)  # the error model's grade from here on
    clock = {"start": time.perf_counter()}
    d = flight.data
    win, selected, ids = select_window(flight, seg, s.segments)
    lat = d["lat_deg"].to_numpy(float)
    lon = d["lon_deg"].to_numpy(float)
    alt = d["alt_m"].to_numpy(float)
    e_all, n_all = geomap.to_local(lat[win], lon[win])
    e_all, n_all = np.asarray(e_all, float), np.asarray(n_all, float)
    notes = list(geomap.notes)
    coverage = check_coverage(geomap, e_all[selected], n_all[selected], s)
    # the map's white noise filtered out at its error's level (a noisy gradient misleads the
    # filter), then the map at the flight's altitude
    level = _map_sigma_level(geomap, s)
    smooth, removed, left = wiener_smooth(geomap.grid, level)
    notes.append(
        f"map Wiener-filtered against {level:.2g} nT of white noise: {removed:.2g} nT RMS "
        f"removed, {left:.0%} of the map's error variance left"
    )
    mm = MapModel(smooth, 0.0, geomap.altitude_m)
    flight_alt = float(np.mean(alt[win][selected]))
    mm, how = mm.continued_to(flight_alt)
    notes.append(how)
    # true track and INS errors, from the covariance a GNSS-aided INS has at GNSS loss
    t = d["time_s"].to_numpy(float)[win]
    traj = _trajectory(flight, win, e_all, n_all, alt[win] - flight_alt, notes)
    model = InsErrorModel(GRADES[s.ins], s.mag_bias_nT, s.mag_bias_tau_s)
    phi = model.transitions(traj)
    qd = model.process_noise(np.diff(t, prepend=t[0]))
    p0 = _gnss_aided_p0(flight, win, geomap, model, traj, s, notes)
    if source == "recorded":
        x_ins = recorded_ins_errors(flight, win, traj)
        notes.append(
            f"INS: the recording's own /ins/solution, filtered with the {grade}-grade error model"
        )
    else:
        x_ins = simulate_ins_errors(model, traj, s.seed, phi, p0=p0)
    clock["ins"] = time.perf_counter()
    # measured anomaly, reduced as the map: IGRF at the INS-indicated position
    # NED errors into the map's axes (turned from north by the meridian convergence)
    j_true = geomap.ned_to_map(lat[win], lon[win])
    off = np.einsum("kij,kj->ki", j_true, x_ins[:, :2])
    ins_e, ins_n = e_all + off[:, 0], n_all + off[:, 1]
    ins_lat, ins_lon = geomap.to_geodetic(ins_e, ins_n)
    lat_r, lon_r, alt_r = lat.copy(), lon.copy(), alt.copy()
    lat_r[win], lon_r[win], alt_r[win] = ins_lat, ins_lon, alt[win] + x_ins[:, 2]
    base = d["base_nT"].to_numpy(float) if flight.has("base_nT") else None
    red = reduce_to_anomaly(flight.time_ns, compensated_nT, lat_r, lon_r, alt_r, base)
    z = red.anomaly_nT[win]
    if not np.isfinite(z[selected]).any():
        raise AeromagError(
            "no compensated field on the selected epochs",
            file=flight.source,
            channel="/mag/compensated",
        )
    if base is None:
        notes.append("no base station: diurnal not removed (the mapping did the same)")
    meas = _measurement_model(mm, flight.time_ns[win], lat_r[win], lon_r[win], alt_r[win], notes)
    meas.ned_to_map = geomap.ned_to_map(ins_lat, ins_lon)
    # measurement noise: the sensor's white noise (the track's) and the map's error
    sensor = s.sensor_sigma_nT
    if sensor is None:
        sensor = white_noise_nT(z[selected])
    sensor = float(sensor) if np.isfinite(sensor) else 0.1
    sigma_source = _map_error(meas, geomap, s, notes)
    step = np.hypot(np.diff(ins_e), np.diff(ins_n))
    meas.map_var_left = left
    length = geomap.error_length_m or s.map_error_length_m
    meas.map_var_scale = correlated_error_scale(
        length, float(np.median(step)) if step.size else np.nan
    )
    why = "the map's own" if geomap.error_length_m else "[navigate] map_error_length_m"
    notes.append(f"map error taken as correlated over {length:.0f} m along the track ({why})")
    r = sensor**2
    gate = gate_sigma_of(s.gate_probability) if s.gate_probability > 0 else None
    # the map's error may be an offset as much as anything: the bias state's prior holds it
    p0f = p0.copy()
    p0f[-1, -1] += level**2
    qd = _line_offsets(qd, selected, ids, p0f[-1, -1])
    # filter and bound
    update = selected & np.isfinite(z)
    if s.filter == "ekf":
        res = ekf(phi, qd, p0f, z, ins_e, ins_n, meas, r, update, gate_sigma=gate)
    else:
        res = particle_filter(
            phi,
            qd,
            p0f,
            z,
            ins_e,
            ins_n,
            replace(meas, vertical=None, alt_above_map_m=None, core_grad=None),
            r,
            s.seed + 1,
            s.particles,
            update,
            t,
            handover_m=s.pf_handover_m,
        )
        if res.handover_epoch is not None:
            notes.append(
                f"particle filter handed over to the EKF after {t[res.handover_epoch] - t[0]:.1f} s"
                f" (cloud DRMS below {s.pf_handover_m:g} m for 10 s)"
            )
        else:
            notes.append("particle filter to the end (its cloud never settled for a handover)")
    clock["filter"] = time.perf_counter()
    bound = crlb(phi, qd, p0f, e_all, n_all, meas, r, update)
    free = crlb(phi, qd, p0, e_all, n_all, meas, r, np.zeros(t.size, bool))
    clock["crlb"] = time.perf_counter()
    on = update & mm.inside(e_all, n_all)
    # the map's 1 sigma along the track (median), as the map gives it (before the inflation)
    var_on = meas.map_var_nT2(e_all[on], n_all[on]) / meas.map_var_scale
    map_sigma = float(np.sqrt(np.median(var_on))) if on.any() else meas.map_sigma_nT
    timings = {
        "ins_s": clock["ins"] - clock["start"],
        "filter_s": clock["filter"] - clock["ins"],
        "crlb_s": clock["crlb"] - clock["filter"],
    }
    return NavigationRun(
        win,
        selected,
        ids,
        flight.time_ns[win],
        np.stack([e_all, n_all], axis=1),
        alt[win],
        x_ins,
        res,
        bound,
        free,
        z,
        r + meas.map_var_scale * map_sigma**2,
        sensor,
        map_sigma,
        s,
        geomap,
        mm,
        coverage,
        notes,
        timings,
        source,
        j_true,
        sigma_source,
        meas.map_var_scale,
    )


def _line_offsets(
    qd: np.ndarray, selected: np.ndarray, ids: np.ndarray, offset_var_nT2: float
) -> np.ndarray:
    """``qd`` with ``offset_var_nT2`` added to the bias state's process noise at the first
    epoch of every selected line after the window's first.

    A line's level against the map is not the previous line's: the compensation's residual
    depends on heading, and the diurnal and the map's levelling error change between lines
    (what tie-line levelling removes from a survey's own lines, and a navigated line does not
    get). Taken as the same slowly drifting bias, a new line's offset is read as a position
    error until the bias state catches up; each line's offset is as unknown as the first
    line's (the bias state's prior)."""
    sel = np.asarray(selected, bool)
    prev_sel = np.r_[False, sel[:-1]]
    prev_id = np.r_[ids[:1], ids[:-1]]
    start = sel & (~prev_sel | (ids != prev_id))
    start[np.argmax(sel)] = False  # the window's first line starts from the prior itself
    out = np.array(qd, float)
    out[start, -1] += offset_var_nT2
    return out


def _map_sigma_level(geomap: GeoMap, s: NavigationSettings) -> float:
    """One 1-sigma value of the map's error, nT: ``--map-sigma``, else the median of the
    map's own error grid, else ``[navigate] map_sigma_nT``."""
    if s.map_sigma_nT is not None:
        return float(s.map_sigma_nT)
    if geomap.sigma is not None and np.isfinite(geomap.sigma.values).any():
        return float(np.nanmedian(geomap.sigma.values))
    return float(s.default_map_sigma_nT)


def _map_error(meas: MeasurementModel, geomap: GeoMap, s: NavigationSettings, notes) -> str:
    """Set the measurement's map error: ``--map-sigma`` when given, else the map's own error
    grid, else ``[navigate] map_sigma_nT``; returns which (user, grid, default) and notes it."""
    if s.map_sigma_nT is not None:
        meas.map_sigma_nT = float(s.map_sigma_nT)
        notes.append(f"map error: {s.map_sigma_nT:g} nT (1 sigma, --map-sigma)")
        return "user"
    if geomap.sigma is not None:
        meas.sigma = MapModel(geomap.sigma, method="linear")
        meas.map_sigma_nT = float(np.nanmax(geomap.sigma.values))
        notes.append("map error: the map's own per-cell 1 sigma, at the estimated position")
        return "grid"
    meas.map_sigma_nT = float(s.default_map_sigma_nT)
    notes.append(
        f"map error: not in the map; {s.default_map_sigma_nT:g} nT (1 sigma, "
        "[navigate] map_sigma_nT; give --map-sigma for this map)"
    )
    return "default"
