"""Strapdown INS error model (Pinson dynamics) and its simulation along a flown track.

The formulation follows MagNav.jl's 17/18-state navigation model
(``src/model_functions.jl``: ``get_pinson``, ``create_P0``, ``create_Qd``; MIT-AI-Accelerator/
MagNav.jl), itself the standard Pinson error model (Titterton & Weston, *Strapdown Inertial
Navigation Technology*, ch. 12) with a third-order barometric altitude loop. The states are
*errors* of the INS (indicated minus true), in the navigation frame NED:

====  ==========  ======  =====================================================
 idx  name        unit    meaning
====  ==========  ======  =====================================================
 0    dn_m        m       north position error (MagNav: latitude error, rad)
 1    de_m        m       east position error (MagNav: longitude error, rad)
 2    dalt_m      m       altitude error (up)
 3-5  dv_ned_mps  m/s     velocity error, NED
 6-8  tilt_rad    rad     attitude (tilt) error about N, E, D
 9    baro_m      m       barometer aiding altitude bias (first-order Gauss-Markov)
 10   baro_acc    m/s^2   barometer aiding vertical-acceleration state
 11-13 acc_mps2   m/s^2   accelerometer biases, body x y z (first-order Gauss-Markov)
 14-16 gyro_radps rad/s   gyroscope biases, body x y z (first-order Gauss-Markov)
 17   mag_bias_nT nT      magnetometer/map catch-all bias (FOGM; filters only)
====  ==========  ======  =====================================================

Positions are kept in metres rather than MagNav's radians (better conditioned for a filter
on a local map): the Pinson matrix is written in radians and transformed by the diagonal
similarity ``T = diag(R, R cos(lat), 1, ...)``; the transition over a step is
``T_k expm(F dt) T_{k-1}^-1`` (an exact change of variables: the filters reproduce MagNav's
numbers, ``tests/test_magnav_peer.py``). MagNav's error states are true minus indicated in
``get_h`` (``map(lat + x)``); ours indicated minus true: the Pinson dynamics are the same
(every INS state changes sign), the position rows of ``H`` change sign.

The model (this module) is kept apart from the filters (:mod:`ekf`, :mod:`pf`, :mod:`crlb`),
which take its transition matrices and noise, statsmodels style.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_filter

from pipeline.geo.frames import attitude_rotation

R_EARTH_M = 6_378_137.0  # WGS-84 equatorial radius (MagNav's r_earth)
OMEGA_EARTH_RADPS = 7.2921151467e-5
G_MPS2 = 9.80665
N_INS = 17  # INS error states; the filters add the magnetometer bias (18)
STATE_NAMES = (
    "dn_m",
    "de_m",
    "dalt_m",
    "dvn_mps",
    "dve_mps",
    "dvd_mps",
    "tilt_n_rad",
    "tilt_e_rad",
    "tilt_d_rad",
    "baro_m",
    "baro_acc_mps2",
    "acc_x_mps2",
    "acc_y_mps2",
    "acc_z_mps2",
    "gyro_x_radps",
    "gyro_y_radps",
    "gyro_z_radps",
    "mag_bias_nT",
)
DEG_PER_H = np.pi / 180.0 / 3600.0  # 1 deg/h in rad/s
UG = G_MPS2 * 1e-6  # 1 micro-g in m/s^2


@dataclass(frozen=True)
class InsGrade:
    """Error budget of an inertial unit (one-sigma values).

    Biases are first-order Gauss-Markov processes (sigma, correlation time); random walks are
    white noise on the velocity (VRW, m/s/sqrt(s)) and the attitude (ARW, rad/sqrt(s)). The
    values of each grade live in ``pipeline/default_config.toml`` (``[navigate.grades.*]``,
    with their sources).
    """

    name: str
    acc_bias_mps2: float
    gyro_bias_radps: float
    vrw_mps_rt_s: float
    arw_rad_rt_s: float
    acc_tau_s: float
    gyro_tau_s: float
    baro_sigma_m: float
    baro_tau_s: float
    init_pos_m: float
    init_alt_m: float
    init_vel_mps: float
    init_att_rad: float
    init_baro_m: float
    init_baro_acc_mps2: float

    @classmethod
    def from_config(cls, name: str, values: dict[str, float]) -> InsGrade:
        """A grade from its ``[navigate.grades.NAME]`` table (every field, floats)."""
        return cls(name, **{k: float(v) for k, v in values.items()})


def _grades() -> dict[str, InsGrade]:
    from pipeline.defaults import default_value

    return {k: InsGrade.from_config(k, v) for k, v in default_value("navigate", "grades").items()}


# navigation: MagNav.jl's create_model defaults; tactical: a tactical-grade unit (sources in
# the configuration file's comments and docs/navigation.md)
GRADES: dict[str, InsGrade] = _grades()


@dataclass
class Trajectory:
    """What the error dynamics need of the true track, per epoch (N samples).

    Attributes
    ----------
    time_s : (N,) seconds
    lat_rad : (N,) geodetic latitude
    vel_ned_mps : (N, 3) velocity, NED
    force_ned_mps2 : (N, 3) specific force (acceleration minus gravity), NED
    c_nb : (N, 3, 3) rotation body -> NED
    """

    time_s: np.ndarray
    lat_rad: np.ndarray
    vel_ned_mps: np.ndarray
    force_ned_mps2: np.ndarray
    c_nb: np.ndarray

    @classmethod
    def from_track(
        cls,
        time_s: np.ndarray,
        north_m: np.ndarray,
        east_m: np.ndarray,
        up_m: np.ndarray,
        lat_deg: np.ndarray,
        roll_deg: np.ndarray | None = None,
        pitch_deg: np.ndarray | None = None,
        yaw_deg: np.ndarray | None = None,
        smooth_s: float = 3.0,
    ) -> Trajectory:
        """Velocity and specific force from positions (local metres), attitude from angles.

        Positions are differentiated with a Savitzky-Golay filter over ``smooth_s``: GNSS
        noise (decimetres at 5-10 Hz) differenced twice would swamp the specific force. With
        no attitude, the body is aligned with the velocity (level, heading along track).
        """
        t = np.asarray(time_s, float)
        dt = float(np.median(np.diff(t)))
        win = max(5, int(round(smooth_s / dt)) | 1)
        ned = np.stack([north_m, east_m, -np.asarray(up_m, float)], axis=1)
        if len(t) <= win:
            vel = np.gradient(ned, t, axis=0)
            acc = np.gradient(vel, t, axis=0)
        else:
            vel = savgol_filter(ned, win, 2, deriv=1, delta=dt, axis=0)
            acc = savgol_filter(ned, win, 2, deriv=2, delta=dt, axis=0)
        force = acc - np.array([0.0, 0.0, G_MPS2])
        if roll_deg is None or pitch_deg is None or yaw_deg is None:
            yaw = np.degrees(np.arctan2(vel[:, 1], vel[:, 0]))
            roll_deg = pitch_deg = np.zeros_like(yaw)
            yaw_deg = yaw
        c_nb = attitude_rotation(roll_deg, pitch_deg, yaw_deg).as_matrix().reshape(-1, 3, 3)
        return cls(t, np.radians(np.asarray(lat_deg, float)), vel, force, c_nb)

    def __len__(self) -> int:
        return self.time_s.size


@dataclass
class InsErrorModel:
    """Linear error dynamics ``dx/dt = F(t) x + w`` of an INS and the magnetometer bias.

    Parameters
    ----------
    grade : InsGrade
        The inertial unit's error budget.
    mag_bias_nT, mag_bias_tau_s : float
        FOGM catch-all of the magnetic measurement (map and compensation errors that vary
        slowly along track; MagNav's ``fogm_sigma`` / ``fogm_tau``).
    baro_k : (k1, k2, k3)
        Third-order barometric altitude loop gains (MagNav's defaults, 1/s, 1/s^2, 1/s^3).
    """

    grade: InsGrade
    mag_bias_nT: float = 1.0
    mag_bias_tau_s: float = 600.0
    baro_k: tuple[float, float, float] = (3e-2, 3e-4, 1e-6)
    n: int = field(default=N_INS + 1, init=False)

    # ---------------------------------------------------------------------------- dynamics
    def dynamics_rad(self, traj: Trajectory) -> np.ndarray:
        """Continuous Pinson matrices F (N, 18, 18) in MagNav's states (latitude and longitude
        errors in radians), term by term ``get_pinson``."""
        g = self.grade
        k1, k2, k3 = self.baro_k
        r, w = R_EARTH_M, OMEGA_EARTH_RADPS
        lat = traj.lat_rad
        vn, ve, vd = traj.vel_ned_mps.T
        fn, fe, fd = traj.force_ned_mps2.T
        s, c, tn = np.sin(lat), np.cos(lat), np.tan(lat)
        F = np.zeros((lat.size, self.n, self.n))
        # position (lat, lon rad; alt m)
        F[:, 0, 2] = -vn / r**2
        F[:, 0, 3] = 1.0 / r
        F[:, 1, 0] = ve * tn / (r * c)
        F[:, 1, 2] = -ve / (c * r**2)
        F[:, 1, 4] = 1.0 / (r * c)
        F[:, 2, 2] = -k1
        F[:, 2, 5] = -1.0
        F[:, 2, 9] = k1
        # velocity: Coriolis and transport rate, specific force x tilt
        F[:, 3, 0] = -ve * (2 * w * c + ve / (r * c**2))
        F[:, 3, 2] = (ve**2 * tn - vn * vd) / r**2
        F[:, 3, 3] = vd / r
        F[:, 3, 4] = -2 * (w * s + ve * tn / r)
        F[:, 3, 5] = vn / r
        F[:, 3, 7] = -fd
        F[:, 3, 8] = fe
        F[:, 4, 0] = 2 * w * (vn * c - vd * s) + vn * ve / (r * c**2)
        F[:, 4, 2] = -ve * (vn * tn + vd) / r**2
        F[:, 4, 3] = 2 * w * s + ve * tn / r
        F[:, 4, 4] = (vn * tn + vd) / r
        F[:, 4, 5] = 2 * w * c + ve / r
        F[:, 4, 6] = fd
        F[:, 4, 8] = -fn
        F[:, 5, 0] = 2 * w * ve * s
        F[:, 5, 2] = (vn**2 + ve**2) / r**2 + k2
        F[:, 5, 3] = -2 * vn / r
        F[:, 5, 4] = -2 * (w * c + ve / r)
        F[:, 5, 6] = -fe
        F[:, 5, 7] = fn
        F[:, 5, 9] = -k2
        F[:, 5, 10] = 1.0
        # attitude
        F[:, 6, 0] = -w * s
        F[:, 6, 2] = -(ve**2) / r**2
        F[:, 6, 4] = 1.0 / r
        F[:, 6, 7] = -w * s - ve * tn / r
        F[:, 6, 8] = vn / r
        F[:, 7, 2] = vn / r**2
        F[:, 7, 3] = -1.0 / r
        F[:, 7, 6] = w * s + ve * tn / r
        F[:, 7, 8] = w * c + ve / r
        F[:, 8, 0] = -w * c - ve / (r * c**2)
        F[:, 8, 2] = ve * tn / r**2
        F[:, 8, 4] = -tn / r
        F[:, 8, 6] = -vn / r
        F[:, 8, 7] = -w * c - ve / r
        # barometer loop and Gauss-Markov biases
        F[:, 9, 9] = -1.0 / g.baro_tau_s
        F[:, 10, 2] = k3
        F[:, 10, 9] = -k3
        for i in (11, 12, 13):
            F[:, i, i] = -1.0 / g.acc_tau_s
        for i in (14, 15, 16):
            F[:, i, i] = -1.0 / g.gyro_tau_s
        F[:, 3:6, 11:14] = traj.c_nb
        F[:, 6:9, 14:17] = -traj.c_nb
        F[:, 17, 17] = -1.0 / self.mag_bias_tau_s
        return F

    def metre_scale(self, lat_rad: np.ndarray) -> np.ndarray:
        """Diagonal of ``T`` (N, 18): metre states = ``T`` x MagNav's radian states (north
        ``R dlat``, east ``R cos(lat) dlon``, every other state unchanged)."""
        lat = np.atleast_1d(np.asarray(lat_rad, float))
        t = np.ones((lat.size, self.n))
        t[:, 0] = R_EARTH_M
        t[:, 1] = R_EARTH_M * np.cos(lat)
        return t

    def dynamics(self, traj: Trajectory) -> np.ndarray:
        """Continuous Pinson matrices F (N, 18, 18) in the metre states, ``T F T^-1`` at each
        epoch's latitude (see module doc)."""
        t = self.metre_scale(traj.lat_rad)
        return self.dynamics_rad(traj) * t[:, :, None] / t[:, None, :]

    def transitions(self, traj: Trajectory) -> np.ndarray:
        """Discrete transition matrices ``Phi[k]`` from epoch k-1 to k (``Phi[0] = I``).

        ``Phi[k] = T_k expm(F_{k-1} dt_k) T_{k-1}^-1``: the dynamics of the departure epoch
        held over the step (MagNav's ``ekf`` propagates with ``get_Phi`` at the epoch it
        leaves), and the metre scaling of each end's latitude, so the metre states are an
        exact change of variables of MagNav's radian ones. ``expm`` by :func:`expm_taylor`,
        batched: scipy's ``expm`` on 36 000 matrices takes ~8 s; a third-order series (this
        module's earlier choice) was off by 3e-5 of the largest entry at dt 1 s.
        """
        Fr = self.dynamics_rad(traj)
        tt = self.metre_scale(traj.lat_rad)
        dt = np.diff(traj.time_s, prepend=traj.time_s[0])
        E = np.empty_like(Fr)
        E[0] = np.eye(self.n)
        # in chunks: a few MB at a time stay in cache (whole-array temporaries were slower)
        for a in range(1, len(traj), 2048):
            b = min(a + 2048, len(traj))
            E[a:b] = expm_taylor(Fr[a - 1 : b - 1] * dt[a:b, None, None])
            E[a:b] *= tt[a:b, :, None] / tt[a - 1 : b - 1, None, :]
        return E

    def process_noise(self, dt_s: float | np.ndarray) -> np.ndarray:
        """Diagonal of the discrete process noise ``Qd = Q dt`` (MagNav's create_Qd form):
        VRW and ARW variances, and ``2 sigma^2 / tau`` FOGM driving noise of the biases."""
        g = self.grade
        q = np.zeros(self.n)
        q[0:3] = 1e-30
        q[3:6] = g.vrw_mps_rt_s**2
        q[6:9] = g.arw_rad_rt_s**2
        q[9] = 2 * g.baro_sigma_m**2 / g.baro_tau_s
        q[10] = 1e-30
        q[11:14] = 2 * g.acc_bias_mps2**2 / g.acc_tau_s
        q[14:17] = 2 * g.gyro_bias_radps**2 / g.gyro_tau_s
        q[17] = 2 * self.mag_bias_nT**2 / self.mag_bias_tau_s
        return np.multiply.outer(np.asarray(dt_s, float), q)

    def initial_covariance(self, init_pos_m: float | None = None) -> np.ndarray:
        """Initial error covariance P0 (18 x 18, diagonal), MagNav's create_P0 layout."""
        g = self.grade
        sd = np.zeros(self.n)
        sd[0:2] = g.init_pos_m if init_pos_m is None else init_pos_m
        sd[2] = g.init_alt_m
        sd[3:6] = g.init_vel_mps
        sd[6:9] = g.init_att_rad
        sd[9] = g.init_baro_m
        sd[10] = g.init_baro_acc_mps2
        sd[11:14] = g.acc_bias_mps2
        sd[14:17] = g.gyro_bias_radps
        sd[17] = self.mag_bias_nT
        return np.diag(sd**2)


def expm_taylor(A: np.ndarray, max_step: float = 0.125) -> np.ndarray:
    """``expm`` of a batch (N, n, n) of Pinson-type matrices ``F dt``: a degree-6 Taylor
    polynomial (Paterson-Stockmeyer: three products) of ``A / 2^s``, squared ``s`` times,
    ``s`` the smallest with ``max|dt| / 2^s <= max_step`` s (``max_step`` in the units of
    ``A``'s time step; the caller passes ``F dt`` with ``dt`` in s, and ``A``'s largest
    entries are the specific force, ~10 per s). Off by < 1e-12 of the largest entry of
    scipy's ``expm`` at dt 0.1 s and 1 s (``tests/test_navigation_model.py``)."""
    # the specific-force entries (~g per s) bound the time step the polynomial can take
    scale = np.abs(A).max() / 10.0 if A.size else 0.0
    s = int(max(0, np.ceil(np.log2(scale / max_step)))) if scale > max_step else 0
    X = A / 2.0**s
    eye = np.eye(A.shape[-1])
    X2 = X @ X
    X3 = X2 @ X
    low = eye + X + X2 / 2.0 + X3 / 6.0
    high = X / 24.0 + X2 / 120.0 + X3 / 720.0
    E = low + X3 @ high
    for _ in range(s):
        E = E @ E
    return E


def simulate_ins_errors(
    model: InsErrorModel,
    traj: Trajectory,
    seed: int,
    phi: np.ndarray | None = None,
    init_pos_m: float | None = None,
    p0: np.ndarray | None = None,
) -> np.ndarray:
    """One realisation of the INS errors along ``traj``: x0 ~ N(0, P0), x_k = Phi_k x_{k-1} +
    w_k with w_k ~ N(0, Qd) (MagNav's create_ins does the same on its error model).

    ``p0``: the initial covariance (full; e.g. a GNSS-aided run's,
    :func:`pipeline.navigation.alignment.gnss_aided_covariance`); default the grade's
    alignment covariance (``init_pos_m`` overriding its position sigma).

    Returns
    -------
    ndarray (N, 17)
        The INS error states (indicated minus true; position errors north, east, up in m).
    """
    rng = np.random.default_rng(seed)
    phi = model.transitions(traj) if phi is None else phi
    n = N_INS
    dt = np.diff(traj.time_s, prepend=traj.time_s[0])
    q = model.process_noise(dt)[:, :n]
    cov0 = model.initial_covariance(init_pos_m) if p0 is None else np.asarray(p0, float)
    c = 0.5 * (cov0[:n, :n] + cov0[:n, :n].T)
    if np.count_nonzero(c - np.diag(np.diag(c))) == 0:
        root = np.diag(np.sqrt(np.diag(c)))
    else:  # by eigen-decomposition: a GNSS-aided covariance is nearly singular
        lam, vec = np.linalg.eigh(c)
        root = vec * np.sqrt(np.clip(lam, 0.0, None))
    w = rng.standard_normal((len(traj), n)) * np.sqrt(q)
    x = np.empty((len(traj), n))
    x[0] = root @ rng.standard_normal(n)
    p = phi[:, :n, :n]
    for k in range(1, len(traj)):
        x[k] = p[k] @ x[k - 1] + w[k]
    return x
