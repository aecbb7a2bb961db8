"""An extensible compensation model: T-L plus the physical effects the audit can add.

The baseline is the post-flight T-L model (``tl18`` or ``tl16`` terms; constant Earth field
during calibration, no lag, no auxiliary couplings, vector sensor as calibrated). A
:class:`ModelSpec` switches extensions on:

* ``gradient``: AGG-TL's band-passed position columns (fitted, not subtracted: geology);
* ``lag_s``: the scalar sensor reports late, by a pure delay (``lag_response="delay"``:
  the stream is read ``lag_s`` later) or through a first-order filter of time constant
  ``lag_s`` (``"first_order"``: the stream is deconvolved, y + lag_s dy/dt);
* ``aux``: auxiliary channels (currents) coupling into the scalar sensor along a fixed body
  direction d: interference c I (u . d), i.e. the columns I u_x, I u_y, I u_z (subtracted);
* ``vector_cal``: direction cosines from the recalibrated fluxgate.

Body frame: x forward, y right, z down; positions are local east/north/up metres about the
calibration site. These models are term sets of the one T-L estimator
(:mod:`pipeline.compensate.estimator`) that :func:`pipeline.compensate.fit_compensation`
also uses: band-pass per contiguous block, trim, ridge.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import lfilter

from pipeline.audit.vector_cal import VectorCalibration
from pipeline.compensate.estimator import bandpassed_design, fit_ridge
from pipeline.compensate.filters import (
    bandpass_blocks,
    bandpass_sos,
    contiguous_blocks,
    trim_samples,
)
from pipeline.compensate.heldout import CALIBRATION_PAD_S, calibration_window
from pipeline.compensate.nuisance import (
    SECOND_ORDER_RATE_PER_S,  # noqa: F401 (re-exported: the audit's name for it)
    current_columns,
    eddy_decay,  # noqa: F401 (re-exported: the audit's name for it)
    eddy_decay_columns,
    second_order_columns,
)
from pipeline.compensate.ridge import RidgeSVD
from pipeline.compensate.terms import (
    BT_SCALE_NT,
    direction_cosines,
    five_point_difference,
    per_sample_difference,
    position_terms,
    tl16_terms,
    tl18_terms,
)
from pipeline.defaults import default_field
from pipeline.flight import Flight
from pipeline.geo.local import LocalFrame
from pipeline.geo.track import smooth_track
from pipeline.io.series import NS
from pipeline.physics.interference import CarrierInterference, scalar_reading_nT
from pipeline.physics.outside_basis import first_order_filter


@dataclass
class AuditData:
    """Everything the audit's models may use, on the scalar epochs."""

    time_s: np.ndarray
    scalar_nT: np.ndarray
    vector_nT: np.ndarray
    enu_m: np.ndarray | None  # (n, 3) about the calibration site, or None without GNSS
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    aux_units: dict[str, str] = field(default_factory=dict)

    @classmethod
    def from_flight(cls, flight: Flight, calibration_mask: np.ndarray) -> AuditData:
        """The audit's inputs from a flight, on its scalar epochs.

        Positions, when the flight has them, become local east/north/up metres about the mean
        position of the calibration epochs, with the receiver's sample-to-sample noise smoothed
        out (:mod:`pipeline.geo.track`: a gradient would turn it into field noise); every
        ``aux_*`` column becomes an auxiliary channel (keyed without the prefix) with its unit.

        Parameters
        ----------
        flight : Flight
            Needs the vector channels (body frame: x forward, y right, z down; nT).
        calibration_mask : ndarray of bool
            The calibration epochs (they place the local frame's origin).

        Returns
        -------
        AuditData

        Raises
        ------
        AeromagError
            The flight has no vector channel.
        """
        flight.require("vector_x_nT", "vector_y_nT", "vector_z_nT", purpose="the model audit")
        d = flight.data
        enu = None
        if flight.has("lat_deg", "lon_deg", "alt_m"):
            lat, lon, alt = (d[c].to_numpy(float) for c in ("lat_deg", "lon_deg", "alt_m"))
            sel = calibration_mask & np.isfinite(lat)
            frame = LocalFrame(
                float(np.mean(lat[sel])), float(np.mean(lon[sel])), float(np.mean(alt[sel]))
            )
            enu = np.column_stack(frame.to_enu(lat, lon, alt))
            enu = _smoothed_enu(flight, frame, enu)
        aux = {c[4:]: d[c].to_numpy(float) for c in d.columns if c.startswith("aux_")}
        units = {k: flight.units.get(f"aux_{k}", "") for k in aux}
        return cls(
            d["time_s"].to_numpy(float),
            d["scalar_nT"].to_numpy(float),
            d[["vector_x_nT", "vector_y_nT", "vector_z_nT"]].to_numpy(float),
            enu,
            aux,
            units,
        )

    @property
    def rate_hz(self) -> float:
        """Sample rate, Hz (from the median sample interval)."""
        return 1.0 / float(np.median(np.diff(self.time_s)))

    def take(self, idx: np.ndarray) -> AuditData:
        """The same inputs on the epochs ``idx`` (indices or a mask)."""
        return AuditData(
            self.time_s[idx],
            self.scalar_nT[idx],
            self.vector_nT[idx],
            None if self.enu_m is None else self.enu_m[idx],
            {k: v[idx] for k, v in self.aux.items()},
            dict(self.aux_units),
        )

    def calibration_part(
        self, mask: np.ndarray, pad_s: float = CALIBRATION_PAD_S
    ) -> tuple[AuditData, np.ndarray, np.ndarray]:
        """(data, mask, epoch indices) on the epochs within ``pad_s`` s of ``mask``
        (:func:`pipeline.compensate.heldout.calibration_window`): every design a fit or a
        test band-passes over ``mask``'s blocks is built there, not on the whole flight."""
        idx = calibration_window(self.time_s, mask, pad_s)
        return self.take(idx), mask[idx], idx


def _smoothed_enu(flight: Flight, frame: LocalFrame, enu: np.ndarray) -> np.ndarray:
    """The track in ``frame``, smoothed at the receiver's own samples and read at the scalar
    epochs; epochs ``enu`` (the interpolated track) leaves empty stay empty."""
    series = flight.series.get(flight.topic_of.get("position", ""))
    if series is None or series.time_ns.size < 8:
        return enu
    raw = np.column_stack(
        frame.to_enu(
            series.values["latitude"], series.values["longitude"], series.values["altitude"]
        )
    )
    t = (series.time_ns - flight.time_ns[0]) / NS
    out = smooth_track(t, raw, flight.data["time_s"].to_numpy(float))
    out[~np.isfinite(enu)] = np.nan
    return out


@dataclass(frozen=True)
class ModelSpec:
    """Which extensions a model has (all off: the baseline)."""

    base: str = "tl18"
    gradient: bool = False
    lag_s: float = 0.0
    lag_response: str = "delay"  # "delay" | "first_order" (a sensor filter's response)
    aux: tuple[str, ...] = ()
    vector_cal: VectorCalibration | None = None
    diurnal: bool = False  # subtract the base station in the reduction (maps, crossovers)
    # eddy currents that decay with a time constant: E (dB/dt - tau d2B/dt2) adds the
    # columns u_i d2B_j/dt2; the competing explanation of a lag-like residual
    eddy_rate: bool = False
    # eddy currents that decay with this time constant (s): the T-L eddy columns seen
    # through a first-order response, which the rate columns above only approximate to
    # first order in w tau (poor at tau ~ 0.5 s against 3-10 s manoeuvres)
    eddy_tau_s: float = 0.0
    # what T-L's first order leaves out: induced magnetisation that is not linear in the
    # field, u_i B_j B_k / s^2, and the magnitude's second-order term in the eddy field,
    # |E dB_perp|^2 / 2|B|, quadratic in the rate of change (dB_j/dt dB_k/dt); the competing
    # explanation of a residual that follows the manoeuvres' size (as a motor's current does)
    second_order: bool = False
    # the carrier's permanent field changed at this time (s; an out-of-catalogue step the
    # survey showed between two calibration passes): permanent columns after it, u_i [t > t_s]
    permanent_step_s: float | None = None
    # further changes of the permanent field (s), each its own u_i [t > t_k] columns: the
    # placebo steps against which a found step is judged (pipeline.audit.events)
    further_steps_s: tuple[float, ...] = ()
    # the field's gradient measured along the calibration legs (east, north, up; nT/m),
    # taken out of the scalar before the fit and put back into the compensated field: the
    # gradient extension without parameters to fit (pipeline.audit.legs)
    known_gradient_nT_per_m: tuple[float, float, float] | None = None
    # channels' couplings measured outside the calibration ((name, nT per unit) as the total
    # field sees them: their switches, pipeline.audit.switching), taken out of the scalar
    # before the fit as interference: a coupling the calibration cannot resolve is not fitted
    # there (three free columns of a channel that hardly varies there fit other residual)
    known_aux: tuple[tuple[str, float], ...] = ()
    # the eddy columns' per-sample derivative, a key of EDDY_DIFFERENCES: the audit's five
    # points (AUDIT_DIFFERENCE) or MagNav's central difference, the compensation's
    eddy_difference: str = "five_point"

    def with_(self, **kw) -> ModelSpec:
        """A copy with the given fields replaced."""
        return replace(self, **kw)

    def label(self) -> list[str]:
        """Names of the model's parts for reports: the base term set, then whichever of
        ``geomagnetic_gradient``, ``sensor_lag``, ``electrical_current``, ``vector_calibration`` and
        ``diurnal`` are switched on.
        """
        out = [self.base]
        if self.gradient or self.known_gradient_nT_per_m is not None:
            out.append("geomagnetic_gradient")
        if self.lag_s:
            out.append("sensor_lag")
        if self.aux or self.known_aux:
            out.append("electrical_current")
        if self.vector_cal is not None:
            out.append("vector_calibration")
        if self.diurnal:
            out.append("diurnal")
        return out


@dataclass
class Design:
    """A model's design on every epoch, before band-passing (:func:`design`).

    Attributes
    ----------
    columns : ndarray, shape (n, p)
        Regressor columns, unfiltered.
    names : list of str
        Column names.
    subtract : ndarray of bool, shape (p,)
        True for compensating columns (carrier interference, subtracted); False for columns
        that are fitted only (the position columns: geology).
    y : ndarray, shape (n,)
        The scalar field, nT, corrected for the sensor lag when the model has one, less
        ``field_nT``.
    field_nT : ndarray or None, shape (n,)
        Field taken out of ``y`` before the fit that belongs to the measured field (a known
        gradient's change over position), added back when compensating; None: nothing.
    """

    columns: np.ndarray  # (n, p) unfiltered
    names: list[str]
    subtract: np.ndarray  # (p,) bool: compensating columns
    y: np.ndarray  # the (lag-corrected) scalar field
    field_nT: np.ndarray | None = None

    @property
    def measured_nT(self) -> np.ndarray:
        """The (lag-corrected) scalar reading with ``field_nT`` put back, nT."""
        return self.y if self.field_nT is None else self.y + self.field_nT


LAG_RESPONSES = ("delay", "first_order")
# the audit's per-sample derivative of the eddy columns: MagNav's central difference (the
# compensation's, for parity) reads the manoeuvres' dB/dt short by (w dt)^2 / 6, a residual
# that follows the manoeuvres, which a short eddy decay and a lag then take up
EDDY_DIFFERENCES = {"five_point": five_point_difference, "per_sample": per_sample_difference}
AUDIT_DIFFERENCE = EDDY_DIFFERENCES[ModelSpec.eddy_difference]


def scalar_series(data: AuditData, lag_s: float, response: str = "delay") -> np.ndarray:
    """The scalar field (nT) as the sensor would have read it without its lag.

    ``delay``: re-timed, read ``lag_s`` seconds later (a cubic spline through each
    contiguous block; NaN where the re-timed epoch leaves it). ``first_order``: a sensor
    whose reading follows the field through 1 / (1 + s lag_s) is inverted exactly by
    y + lag_s dy/dt (per contiguous block, dy by :data:`AUDIT_DIFFERENCE`; the derivative
    amplifies noise only above the calibration band). See :func:`scalar_retimer`, which
    builds the splines or derivatives once for many lags.
    """
    if not lag_s:
        return data.scalar_nT
    return scalar_retimer(data, response)(lag_s)


def scalar_retimer(data: AuditData, response: str = "delay") -> Callable[[float], np.ndarray]:
    """:func:`scalar_series` of ``data`` at any lag, the cubic splines (``delay``) or the
    derivatives (``first_order``) of each contiguous block built once: a lag search
    evaluates hundreds of lags on the same record.

    Parameters
    ----------
    data : AuditData
        The record (times s, scalar nT).
    response : str
        ``delay`` or ``first_order`` (:data:`LAG_RESPONSES`).

    Returns
    -------
    callable
        ``retime(lag_s)``: the scalar (nT) the sensor would have read without a lag of
        ``lag_s`` seconds, the same numbers as :func:`scalar_series`.
    """
    if response not in LAG_RESPONSES:
        raise ValueError(f"unknown lag response {response!r} ({', '.join(LAG_RESPONSES)})")
    t, y = data.time_s, data.scalar_nT
    blocks = [b for b in contiguous_blocks(np.isfinite(y), t) if b.size >= 5]
    if response == "first_order":
        rates = [(b, y[b], AUDIT_DIFFERENCE(y[b]), float(np.median(np.diff(t[b])))) for b in blocks]

        def fill(out: np.ndarray, lag_s: float) -> None:
            for b, yb, rate, dt in rates:
                out[b] = yb + lag_s * rate / dt

    else:
        # a cubic spline, not a straight line, between the samples: a fixed-wing's
        # interference swings by tens of nT in a manoeuvre, and a line misses its curvature
        # by up to (w dt)^2 / 8 of the swing, which reads as a decay beside a biased lag
        splines = [(b, t[b], CubicSpline(t[b], y[b])) for b in blocks]

        def fill(out: np.ndarray, lag_s: float) -> None:
            for b, tb, spline in splines:
                tq = tb + lag_s
                inside = (tq >= tb[0]) & (tq <= tb[-1])
                out[b[inside]] = spline(tq[inside])

    def retime(lag_s: float) -> np.ndarray:
        if not lag_s:
            return y
        out = np.full(y.shape, np.nan)
        fill(out, lag_s)
        return out

    return retime


def sensor_filtered(rows: np.ndarray, where: np.ndarray, dt_s: float, tau_s: float) -> np.ndarray:
    """Regression rows (``(m,)`` or ``(m, p)``, one per epoch index of ``where``) passed
    through a first-order sensor filter of time constant ``tau_s`` (s) along each run of
    consecutive epochs; ``tau_s < 0`` runs it backwards in time.

    A ``first_order`` lag's record is deconvolved, y + tau dy/dt, which multiplies the
    sensor's white noise by |1 + i w tau| (1.35x in RMS over a 0.1-0.9 Hz band at tau 0.26
    s): fitted so, the form reads a large sensor filter worse than a delay or a decay, and
    the noise in the derivative pulls tau towards zero. The sensor's own filter applied to
    the rows (the deconvolved record and the columns alike) undoes that amplification and
    leaves the coefficients' meaning unchanged: generalised least squares of the same model.
    """
    x = np.asarray(rows, float)
    if not tau_s or x.shape[0] == 0:
        return x.copy()
    # first_order_lowpass's filter on each run, its coefficients found once for all runs
    num, den, zi = first_order_filter(dt_s, abs(tau_s))
    out = np.empty_like(x)
    starts = np.r_[0, np.flatnonzero(np.diff(where) != 1) + 1, where.size]
    for i, j in zip(starts[:-1], starts[1:], strict=True):
        run = x[i:j] if tau_s > 0 else x[i:j][::-1]
        y, _ = lfilter(num, den, run, axis=0, zi=zi * run[:1])
        out[i:j] = y if tau_s > 0 else y[::-1]
    return out


def design(data: AuditData, spec: ModelSpec) -> Design:
    """The design matrix of ``spec`` on ``data``.

    T-L columns (``tl18`` or ``tl16``) from the body-frame vector field (recalibrated with
    ``spec.vector_cal`` when set), then, as switched on: auxiliary-current couplings, eddy-rate,
    second-order induced and permanent-step columns (all compensating), and the position
    columns of the gradient (local east/north/up m; fitted, not subtracted).

    Parameters
    ----------
    data : AuditData
    spec : ModelSpec

    Returns
    -------
    Design

    Raises
    ------
    ValueError
        ``spec.gradient`` or ``spec.known_gradient_nT_per_m`` is set but ``data`` has no
        positions.
    """
    v = data.vector_nT if spec.vector_cal is None else spec.vector_cal.apply(data.vector_nT)
    difference = EDDY_DIFFERENCES[spec.eddy_difference]
    if spec.base == "tl18":
        k, names = tl18_terms(v, data.time_s, difference=difference)
    else:
        k, names = tl16_terms(v, data.time_s)
    if spec.eddy_tau_s > 0:
        kd, dn = eddy_decay_columns(v, data.time_s, spec.eddy_tau_s, difference=difference)
    sub = [True] * k.shape[1]
    cols = [k]
    if spec.eddy_tau_s > 0:
        cols.append(kd)
        names = names + dn
        sub += [True] * len(dn)
    for name in spec.aux:
        ka, an = current_columns(v, data.aux[name], name)
        cols.append(ka)
        names = names + an
        sub += [True] * 3
    if spec.eddy_rate:
        u = direction_cosines(v)
        d2b = np.gradient(np.gradient(v, data.time_s, axis=0), data.time_s, axis=0)
        cols.append(
            np.column_stack([u[:, i] * d2b[:, j] / BT_SCALE_NT for i in range(3) for j in range(3)])
        )
        names = names + [f"eddy_rate_u{a}d2B{b}" for a in "xyz" for b in "xyz"]
        sub += [True] * 9
    if spec.second_order:
        ks, sn = second_order_columns(v, data.time_s)
        cols.append(ks)
        names = names + sn
        sub += [True] * len(sn)
    steps = [] if spec.permanent_step_s is None else [("perm_step", spec.permanent_step_s)]
    steps += [(f"perm_step{i + 2}", t) for i, t in enumerate(spec.further_steps_s)]
    if steps:
        u = direction_cosines(v)
    for label, t_step in steps:
        cols.append(u * (data.time_s > t_step).astype(float)[:, None])
        names = names + [f"{label}_u{a}" for a in "xyz"]
        sub += [True] * 3
    if spec.gradient:
        if data.enu_m is None:
            raise ValueError("the gradient terms need positions (/gnss/fix)")
        kp, pn = position_terms(*data.enu_m.T)
        cols.append(kp)
        names = names + pn
        sub += [False] * kp.shape[1]
    y, known = design_record(data, spec)
    return Design(np.column_stack(cols), names, np.array(sub), y, known)


def design_record(data: AuditData, spec: ModelSpec) -> tuple[np.ndarray, np.ndarray | None]:
    """The record :func:`design` regresses on its columns: the scalar (nT) re-timed by
    ``spec``'s lag, less what ``spec`` takes as known (a measured gradient's field, known
    couplings); and the known gradient's field (nT; None without one)."""
    y = scalar_series(data, spec.lag_s, spec.lag_response)
    known = None
    if spec.known_gradient_nT_per_m is not None:
        if data.enu_m is None:
            raise ValueError("a known gradient needs positions (/gnss/fix)")
        known = data.enu_m @ np.asarray(spec.known_gradient_nT_per_m, float)
        y = y - known
    for name, k in spec.known_aux:
        y = y - k * data.aux[name]
    return y, known


@dataclass
class BandSettings:
    """The fit band (defaults: the shipped configuration's [compensation] values)."""

    band_hz: tuple[float, float] = default_field("compensation", "band_hz", tuple)
    poles: int = default_field("compensation", "poles")
    trim_s: float = default_field("compensation", "trim_s")  # per block end (s)

    def trim_at(self, rate_hz: float) -> int:
        """Samples trimmed per block end at ``rate_hz``."""
        return trim_samples(self.trim_s, rate_hz)


def bandpassed_rows(
    data: AuditData, des: Design, mask: np.ndarray, bs: BandSettings, keep: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K_bp, y_bp, epoch indices) over the contiguous blocks of ``mask``; with ``keep``
    (epoch mask) only the rows of kept epochs, band-passed with all of ``mask`` (folds of
    short blocks select rows of the once-filtered calibration)."""
    return bandpassed_design(
        des.columns, des.y, data.time_s, data.rate_hz, mask, bs.band_hz, bs.poles, bs.trim_s, keep
    )


@dataclass
class CalibrationRows:
    """A model's regression rows over the whole calibration (:func:`calibration_rows`): what
    every fit and held-out residual of that model selects its rows from.

    Attributes
    ----------
    names : list of str
        Column names.
    subtract : ndarray of bool, shape (p,)
        Compensating columns (see :class:`Design`).
    kf : ndarray, shape (m, p)
        Band-passed design rows (nT), read-only.
    yf : ndarray, shape (m,)
        Band-passed (lag-corrected) scalar field, nT, read-only.
    where : ndarray of int, shape (m,)
        Epoch index of each row.
    columns_ok, valid : ndarray of bool, optional
        Over the epochs of the calibration part the rows were built on: those of the mask
        where every column is finite, and of those where the record is too (the blocks'
        epochs); None when not kept.
    columns_bp : ndarray, shape (m, p), optional
        The band-passed columns before a ``first_order`` lag's sensor filter
        (:func:`sensor_filtered`); None when ``kf`` is unfiltered.
    """

    names: list[str]
    subtract: np.ndarray
    kf: np.ndarray
    yf: np.ndarray
    where: np.ndarray
    columns_ok: np.ndarray | None = None
    valid: np.ndarray | None = None
    columns_bp: np.ndarray | None = None

    @property
    def bandpassed_columns(self) -> np.ndarray:
        """The band-passed columns, without any sensor filter: what a model differing in
        its lag only shares."""
        return self.kf if self.columns_bp is None else self.columns_bp

    def select(self, keep: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(K_bp, y_bp, epoch indices) of the rows of ``keep`` (epoch mask; all when None),
        the rows :func:`bandpassed_rows` gives with the same ``keep``."""
        if keep is None:
            return self.kf, self.yf, self.where
        rows = keep[self.where]
        return self.kf[rows], self.yf[rows], self.where[rows]


def calibration_rows(
    data: AuditData,
    spec: ModelSpec,
    mask: np.ndarray,
    bs: BandSettings,
    like: CalibrationRows | None = None,
) -> CalibrationRows:
    """``spec``'s design on ``data``, band-passed over the blocks of ``mask`` (arrays made
    read-only: they are shared by every fit that selects rows from them).

    Parameters
    ----------
    data : AuditData
    spec : ModelSpec
    mask : ndarray of bool
        The calibration epochs.
    bs : BandSettings
    like : CalibrationRows, optional
        The rows of a model that differs from ``spec`` in its lag only, on the same
        ``data``, ``mask`` and ``bs``: its band-passed columns are reused (the same numbers)
        when the re-timed record is finite on the same epochs.

    Returns
    -------
    CalibrationRows
    """
    sub, sub_mask, idx = data.calibration_part(mask)
    if like is not None and like.columns_ok is not None:
        # only the scalar moves with the lag: the columns' band-passed rows are the twin's
        # when the record is finite on the same epochs (then the blocks are the same)
        y, _ = design_record(sub, spec)
        valid = like.columns_ok & np.isfinite(y)
        if np.array_equal(valid, like.valid):
            _, yf, _ = bandpassed_design(
                np.zeros((y.size, 1)),  # the record beside a zero column (the filter takes one)
                y,
                sub.time_s,
                sub.rate_hz,
                valid,
                bs.band_hz,
                bs.poles,
                bs.trim_s,
            )
            yf.flags.writeable = False
            return _through_the_sensor(
                replace(like, kf=like.bandpassed_columns, yf=yf, columns_bp=None), spec, sub
            )
    des = design(sub, spec)
    kf, yf, where = bandpassed_rows(sub, des, sub_mask, bs)
    where = idx[where]
    for a in (kf, yf, where):
        a.flags.writeable = False
    columns_ok = sub_mask & np.all(np.isfinite(des.columns), axis=1)
    rows = CalibrationRows(
        des.names, des.subtract, kf, yf, where, columns_ok, columns_ok & np.isfinite(des.y)
    )
    return _through_the_sensor(rows, spec, sub)


def _through_the_sensor(rows: CalibrationRows, spec: ModelSpec, data: AuditData) -> CalibrationRows:
    """``rows`` of a ``first_order`` lag passed through the sensor's filter
    (:func:`sensor_filtered`), the unfiltered columns kept; other rows unchanged."""
    if spec.lag_response != "first_order" or not spec.lag_s:
        return rows
    dt = 1.0 / data.rate_hz
    kf = sensor_filtered(rows.kf, rows.where, dt, spec.lag_s)
    yf = sensor_filtered(rows.yf, rows.where, dt, spec.lag_s)
    for a in (kf, yf):
        a.flags.writeable = False
    return replace(rows, kf=kf, yf=yf, columns_bp=rows.kf)


@dataclass
class FittedModel:
    """A :class:`ModelSpec` fitted by ridge regression on band-passed calibration data.

    Attributes
    ----------
    spec : ModelSpec
    names : list of str
        Column names, one per coefficient.
    subtract : ndarray of bool
        Compensating columns (see :class:`Design`).
    theta : ndarray
        Coefficients, in the columns' order.
    lambda_ : float
        Ridge parameter used.
    n_fit : int
        Band-passed rows fitted.
    fit_residual_nT : float
        RMS fit residual, nT.
    """

    spec: ModelSpec
    names: list[str]
    subtract: np.ndarray
    theta: np.ndarray
    lambda_: float
    n_fit: int
    fit_residual_nT: float

    def coefficient(self, prefix: str) -> np.ndarray:
        """The coefficients of the columns whose names start with ``prefix``, in column order."""
        return np.array(
            [c for n, c in zip(self.names, self.theta, strict=True) if n.startswith(prefix)]
        )

    def compensate(self, data: AuditData) -> tuple[np.ndarray, np.ndarray]:
        """(compensated field, interference) at every epoch, nT."""
        des = design(data, self.spec)
        interference = des.columns[:, self.subtract] @ self.theta[self.subtract]
        return des.measured_nT - interference, interference

    def residual_bp(
        self,
        data: AuditData,
        mask: np.ndarray,
        bs: BandSettings,
        keep: np.ndarray | None = None,
        rows: CalibrationRows | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Band-passed measured minus model (all columns) over ``mask`` (rows of ``keep``
        only, when given): (residual, epochs). ``rows``: this model's
        :func:`calibration_rows` on the same ``data``, ``mask`` and ``bs``, when already
        made (the audit's folds share them)."""
        rows = rows or calibration_rows(data, self.spec, mask, bs)
        kf, yf, where = rows.select(keep)
        return yf - kf @ self.theta, where


def fit_model(
    data: AuditData,
    spec: ModelSpec,
    mask: np.ndarray,
    bs: BandSettings | None = None,
    ridge: float | str = "auto",
    keep: np.ndarray | None = None,
    folds: np.ndarray | None = None,
    rows: CalibrationRows | None = None,
) -> FittedModel:
    """Fit ``spec`` on the epochs of ``mask`` (only the rows of ``keep`` when given).

    ``ridge``: ``"auto"`` (L-curve corner), ``"cv"`` (inner cross-validation over the fold
    numbers ``folds`` of the fitted rows, see :mod:`pipeline.audit.crossval`) or a value.
    ``rows``: ``spec``'s :func:`calibration_rows` on the same ``data``, ``mask`` and ``bs``,
    when already made (the audit's fits of one model share them).
    """
    bs = bs or BandSettings()
    rows = rows or calibration_rows(data, spec, mask, bs)
    kf, yf, where = rows.select(keep)
    fit = fit_ridge(kf, yf, ridge, None if folds is None else folds[where])
    return FittedModel(
        spec,
        rows.names,
        rows.subtract,
        fit.theta,
        fit.lambda_,
        fit.n_rows,
        fit.residual_rms,
    )


def lag_cost(
    data: AuditData,
    spec: ModelSpec,
    mask: np.ndarray,
    bs: BandSettings,
    lam: float,
    max_lag_s: float,
    keep: np.ndarray | None = None,
    like: CalibrationRows | None = None,
):
    """costs(taus, ridge_lambda=lam): fit residual RMS (nT) of ``spec`` refitted with the
    scalar re-timed by each tau of the array ``taus`` (s).

    Only the scalar moves with the lag, so the design matrix and its SVD are built once for
    every candidate |tau| <= ``max_lag_s`` (the flight's first and last ``max_lag_s`` seconds
    are left out, so that every candidate uses the same rows). With ``keep``, only the rows
    of kept epochs count (band-passed with all of ``mask``). ``like``: ``spec``'s rows at any
    lag (:func:`calibration_rows`), whose band-passed columns are these when they were built
    on the same epochs.
    """
    # the flight's first and last max_lag_s seconds: the window's own ends when the
    # calibration reaches them, else pad (>= max_lag_s) outside the calibration
    flight_start, flight_end = data.time_s[0], data.time_s[-1]
    pad_s = max(CALIBRATION_PAD_S, 2.0 * max_lag_s)
    data, mask, idx = data.calibration_part(mask, pad_s)
    keep = None if keep is None else keep[idx]
    t = data.time_s
    inner = mask & (t >= flight_start + max_lag_s) & (t <= flight_end - max_lag_s)
    y0, _ = design_record(data, spec.with_(lag_s=0.0))
    kf = where = None
    if like is not None and like.columns_ok is not None and pad_s == CALIBRATION_PAD_S:
        valid = inner & np.isfinite(y0) & like.columns_ok
        if np.array_equal(valid, like.valid):  # the same blocks: the same filtered columns
            kf, where = like.bandpassed_columns, np.searchsorted(idx, like.where)
    if kf is None:
        des = design(data, spec.with_(lag_s=0.0))
        valid = inner & np.isfinite(des.y) & np.all(np.isfinite(des.columns), axis=1)
    blocks = contiguous_blocks(valid, t)
    sos = bandpass_sos(bs.band_hz, data.rate_hz, bs.poles)
    if kf is None:
        kf, where = bandpass_blocks(des.columns, blocks, sos, bs.trim_at(data.rate_hz))
    rows = np.ones(where.size, bool) if keep is None else keep[where]
    used = int(np.count_nonzero(rows))
    if used < 2 * kf.shape[1]:
        raise ValueError(f"only {used} usable calibration samples for {kf.shape[1]} terms")
    # what the spec takes as known (a measured gradient's field, known couplings) leaves the
    # record before the fit at every candidate lag, as in design()
    known = data.scalar_nT - y0
    retime = scalar_retimer(data, spec.lag_response)
    if spec.lag_response == "first_order":
        return _first_order_costs(kf, where, rows, blocks, sos, bs, data, known, retime, lam)
    kf = kf[rows]
    solver = RidgeSVD(kf, np.zeros(kf.shape[0]))

    def costs(taus: np.ndarray, ridge_lambda: float = lam) -> np.ndarray:
        # every candidate's re-timed record band-passed in one call (the filter runs along
        # the rows, the candidates are columns): the same numbers as one call each
        y = np.column_stack([retime(float(tau)) for tau in taus])
        yf, _ = bandpass_blocks(y - known[:, None], blocks, sos, bs.trim_at(data.rate_hz))
        yf = yf[rows]
        r = yf - kf @ solver.solve_for(yf, ridge_lambda)
        out = np.sqrt(np.mean(r**2, axis=0))
        return np.where(np.all(np.isfinite(yf), axis=0), out, np.inf)

    return costs


def _first_order_costs(kf, where, rows, blocks, sos, bs, data, known, retime, lam):
    """:func:`lag_cost`'s costs for a ``first_order`` response: at each tau the deconvolved
    record and the columns pass through the sensor's filter (:func:`sensor_filtered`), so
    the design changes with tau and each candidate is solved on its own normal equations."""
    dt = 1.0 / data.rate_hz

    def cost(tau: float, yf: np.ndarray, ridge_lambda: float) -> float:
        if not np.all(np.isfinite(yf)):
            return np.inf
        both = sensor_filtered(np.column_stack([kf, yf]), where, dt, tau)[rows]
        k, y = both[:, :-1], both[:, -1]
        gram = k.T @ k
        try:  # the ridge solution (K'K + lambda I)^-1 K'y, as RidgeSVD.solve gives it
            theta = np.linalg.solve(gram + ridge_lambda * np.eye(gram.shape[0]), k.T @ y)
        except np.linalg.LinAlgError:
            theta = RidgeSVD.from_gram(k, y).solve(ridge_lambda)
        return float(np.sqrt(np.mean((y - k @ theta) ** 2)))

    def costs(taus: np.ndarray, ridge_lambda: float = lam) -> np.ndarray:
        # every candidate's deconvolved record band-passed in one call, as for a delay
        y = np.column_stack([retime(float(tau)) for tau in taus])
        yf, _ = bandpass_blocks(y - known[:, None], blocks, sos, bs.trim_at(data.rate_hz))
        return np.array([cost(float(t), yf[:, i], ridge_lambda) for i, t in enumerate(taus)])

    return costs


# --------------------------------------------------------------------------------------------
def carrier_from_coefficients(
    fitted: FittedModel, mean_field_nT: float, sample_interval_s: float
) -> tuple[CarrierInterference, np.ndarray]:
    """The physical interference (p, A, E) a fitted T-L model stands for, and the coupling
    vectors (nT per unit, body frame) of its auxiliary channels.

    tl18 columns are u_i, u_i B_j / s, u_i dB_j / s (s = 50 000 nT; dB_j MagNav's per-sample
    central difference, nT per sample), so the coefficients map exactly: p_i; A_ii = c/s,
    A_ij = A_ji = c/(2s); E_ij = c dt / s (seconds, dt = ``sample_interval_s``). tl16's u_i u_j
    and u_i u_j' (u' per second) stand for u_i B_j / |B| and u_i B_j' / |B|: they map with the
    mean field instead.
    """
    c = dict(zip(fitted.names, fitted.theta, strict=True))
    scale = BT_SCALE_NT if fitted.spec.base == "tl18" else mean_field_nT
    eddy_per_s = float(sample_interval_s) if fitted.spec.base == "tl18" else 1.0
    p = np.array([c.get(f"perm_u{a}", 0.0) for a in "xyz"])
    a = np.zeros((3, 3))
    e = np.zeros((3, 3))
    sym = "B" if fitted.spec.base == "tl18" else "u"
    for i, ai in enumerate("xyz"):
        for j, aj in enumerate("xyz"):
            v = c.get(f"ind_u{ai}{sym}{aj}")
            if v is not None:
                if i == j:
                    a[i, i] = v / scale
                else:
                    a[i, j] = a[j, i] = v / (2 * scale)
            ed = c.get(f"eddy_u{ai}d{sym}{aj}")
            if ed is not None:
                e[i, j] = ed * eddy_per_s / scale
    aux = {name: np.array([c[f"aux_{name}_u{ax}"] for ax in "xyz"]) for name in fitted.spec.aux}
    return CarrierInterference(p, a, e), aux


def simulate_measurement(
    data: AuditData, fitted: FittedModel, earth_total_nT: np.ndarray
) -> np.ndarray:
    """The scalar reading the project's simulator physics predicts for this flight.

    Driven by the measured vector field (its direction; calibrated when the model says so),
    the measured auxiliary channels, the fitted interference and an Earth field of magnitude
    ``earth_total_nT`` (plus, with the gradient extension, the fitted position terms). With a
    lag the prediction is for the re-timed stream. Exact |b + b_int|, not the linearised T-L.
    """
    v = (
        data.vector_nT
        if fitted.spec.vector_cal is None
        else fitted.spec.vector_cal.apply(data.vector_nT)
    )
    u = direction_cosines(v)
    earth = np.asarray(earth_total_nT, float).copy()
    if fitted.spec.gradient and data.enu_m is not None:
        kp, pn = position_terms(*data.enu_m.T)
        c = dict(zip(fitted.names, fitted.theta, strict=True))
        earth = earth + kp @ np.array([c[n] for n in pn])
    dt = float(np.median(np.diff(data.time_s)))
    carrier, aux = carrier_from_coefficients(
        fitted, float(np.nanmean(np.linalg.norm(v, axis=1))), dt
    )
    b = u * earth[:, None]
    if fitted.spec.base == "tl18":  # per-sample differences, as the tl18 columns, in nT/s
        b_in, db = v, EDDY_DIFFERENCES[fitted.spec.eddy_difference](v) / dt
    else:  # tl16 columns are built from direction cosines alone
        norm = np.nanmean(np.linalg.norm(v, axis=1))
        b_in, db = u * norm, np.gradient(u, data.time_s, axis=0) * norm
    b_int = carrier.vector_nT(b_in, db)
    for name, coupling in aux.items():
        b_int = b_int + data.aux[name][:, None] * coupling[None, :]
    for name, k in fitted.spec.known_aux:  # along the field: the total field's coupling
        b_int = b_int + (k * data.aux[name])[:, None] * u
    return scalar_reading_nT(b, b_int)
