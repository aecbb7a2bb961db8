"""Regressor (design-matrix) columns of the Tolles-Lawson models.

All come from the vector magnetometer B (body frame: x forward, y right, z down, nT) and its
direction cosines u = B/|B|. Differences are central (one-sided at the ends).

- ``tl16`` (paper 002, eqs. 6-10): 3 permanent u_i; 5 induced u_i u_j (i <= j, u_z^2 dropped
  because sum u_i^2 = 1); 8 eddy u_i u'_j (u_z u_z' dropped because sum u_i u_i' = 0), u' the
  time derivative (1/s).
- ``tl18``: MagNav.jl's ``create_TL_A`` column for column (same order, same scaling):
  3 permanent u_i; 6 induced u_i B_j / Bt_scale (i <= j); 9 eddy u_i dB_j / Bt_scale with
  dB_j MagNav's ``fdm``, the **per-sample** central difference (B[k+1] - B[k-1]) / 2
  (one-sided at the ends), *not* divided by the sample interval; Bt_scale = 50 000 nT.
  The eddy coefficients therefore depend on the sample rate: a true eddy matrix E (seconds)
  gives E_ij Bt_scale / dt at sample interval dt, i.e. 10x larger at 10 Hz than the per-second
  set. A true induced matrix A gives (A_ij + A_ji) Bt_scale (i < j) and A_ii Bt_scale.
  MagNav's term options map to our column-name prefixes (:data:`MAGNAV_TERMS`):
  ``:permanent`` -> ``perm_``, ``:induced`` -> ``ind_``, ``:eddy`` -> ``eddy_``,
  ``:bias`` -> ``bias`` (a column of ones; our band-passed fits drop it, the unfiltered fit
  adds it, as MagNav's ``create_TL_coef`` users do).
- ``tl18-rate``: the same 18 columns with the eddy derivatives per second, dB_j/dt (nT/s), so
  that coefficients are comparable between recordings of different rates: E_ij Bt_scale.
- position (AGG-TL, paper 002 eqs. 11-21): e, n, e^2, e n, n^2, up in metres from a reference.
"""

from __future__ import annotations

import numpy as np

from pipeline.defaults import default_value

BT_SCALE_NT = float(default_value("compensation", "bt_scale_nT"))
AXES = "xyz"
PAIRS_UPPER = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
# MagNav.jl's term-group names (create_TL_A's `terms`) -> our column-name prefixes
MAGNAV_TERMS = {"permanent": "perm_", "induced": "ind_", "eddy": "eddy_", "bias": "bias"}
MAGNAV_ALIASES = {
    "permanent": "permanent",
    "p": "permanent",
    "permanent3": "permanent",
    "p3": "permanent",
    "induced": "induced",
    "i": "induced",
    "induced6": "induced",
    "i6": "induced",
    "eddy": "eddy",
    "e": "eddy",
    "eddy9": "eddy",
    "e9": "eddy",
    "bias": "bias",
    "b": "bias",
}
TL18_TERMS = ("permanent", "induced", "eddy")  # MagNav's default


def direction_cosines(b_nT: np.ndarray) -> np.ndarray:
    """Direction cosines u = B / |B| of each row of ``b_nT`` (n, 3), body frame (x forward,
    y right, z down); dimensionless.
    """
    b = np.asarray(b_nT, float)
    return b / np.linalg.norm(b, axis=1, keepdims=True)


def _permanent(u: np.ndarray) -> tuple[list[np.ndarray], list[str]]:
    """Permanent-field columns: the direction cosines themselves."""
    return [u[:, i] for i in range(3)], [f"perm_u{a}" for a in AXES]


def tl16_terms(b_nT: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """The 16 classic T-L columns from direction cosines, (n, 16)."""
    u = direction_cosines(b_nT)
    du = np.gradient(u, time_s, axis=0)
    cols, names = _permanent(u)
    for i, j in PAIRS_UPPER[:-1]:  # u_z^2 dropped
        cols.append(u[:, i] * u[:, j])
        names.append(f"ind_u{AXES[i]}u{AXES[j]}")
    for i in range(3):
        for j in range(3):
            if i == j == 2:  # u_z u_z' dropped
                continue
            cols.append(u[:, i] * du[:, j])
            names.append(f"eddy_u{AXES[i]}du{AXES[j]}")
    return np.column_stack(cols), names


def per_sample_difference(x: np.ndarray) -> np.ndarray:
    """MagNav.jl's ``fdm`` along axis 0: (x[k+1] - x[k-1]) / 2, one-sided at the ends.

    Parameters
    ----------
    x : (n, ...) array, any unit; n >= 2.

    Returns
    -------
    (n, ...) array in x's unit per sample (not per second).
    """
    return np.gradient(np.asarray(x, float), axis=0)


def per_nominal_sample_difference(x: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """:func:`per_sample_difference` on unevenly spaced samples: the derivative in time
    (central, one-sided at the ends) times the median sample interval, so that a recorder's
    uneven timing (jitter, a dropped sample) does not scale single differences. Equal to
    :func:`per_sample_difference` on even sampling, to rounding.

    Parameters
    ----------
    x : (n, ...) array, any unit; n >= 2.
    time_s : (n,) increasing sample times, s.

    Returns
    -------
    (n, ...) array in x's unit per median sample interval.
    """
    t = np.asarray(time_s, float)
    step = np.diff(t)
    if not np.all(step > 0):  # repeated or unordered times: no derivative in time
        return per_sample_difference(x)
    return np.gradient(np.asarray(x, float), t, axis=0) * float(np.median(step))


def five_point_difference(x: np.ndarray) -> np.ndarray:
    """The per-sample derivative to fourth order along axis 0: (x[k-2] - 8 x[k-1] +
    8 x[k+1] - x[k+2]) / 12; :func:`per_sample_difference` within two samples of the ends.

    MagNav's ``fdm`` reads a sinusoid of angular frequency w sampled every dt short by
    1 - sin(w dt) / (w dt), about (w dt)^2 / 6: 0.4 % at 0.25 Hz and 10 Hz, which a
    fixed-wing's eddy terms of tens of nT turn into a residual above the sensor's noise that
    follows the manoeuvres. This stencil's shortfall is about (w dt)^4 / 30. Argument and
    result as :func:`per_sample_difference`'s.
    """
    x = np.asarray(x, float)
    out = per_sample_difference(x)
    if x.shape[0] >= 5:
        out[2:-2] = (x[:-4] - 8.0 * x[1:-3] + 8.0 * x[3:-1] - x[4:]) / 12.0
    return out


def _tl18(
    b: np.ndarray, db: np.ndarray, terms: tuple[str, ...], bt_scale_nT: float, eddy_suffix: str
) -> tuple[np.ndarray, list[str]]:
    wanted = set()
    for t in terms:
        key = MAGNAV_ALIASES.get(str(t).lstrip(":"))
        if key is None:
            raise ValueError(f"unknown T-L term group {t!r} (use {', '.join(MAGNAV_TERMS)})")
        wanted.add(key)
    u = direction_cosines(b)
    cols: list[np.ndarray] = []
    names: list[str] = []
    # MagNav's create_TL_A adds the groups in this fixed order, whatever the order asked for
    if "permanent" in wanted:
        c, n = _permanent(u)
        cols, names = cols + c, names + n
    if "induced" in wanted:
        for i, j in PAIRS_UPPER:
            cols.append(u[:, i] * b[:, j] / bt_scale_nT)
            names.append(f"ind_u{AXES[i]}B{AXES[j]}")
    if "eddy" in wanted:
        for i in range(3):
            for j in range(3):
                cols.append(u[:, i] * db[:, j] / bt_scale_nT)
                names.append(f"eddy_u{AXES[i]}dB{AXES[j]}{eddy_suffix}")
    if "bias" in wanted:
        cols.append(np.ones(len(b)))
        names.append("bias")
    return np.column_stack(cols), names


def tl18_terms(
    b_nT: np.ndarray,
    time_s: np.ndarray | None = None,
    bt_scale_nT: float = BT_SCALE_NT,
    terms: tuple[str, ...] = TL18_TERMS,
    difference=per_sample_difference,
) -> tuple[np.ndarray, list[str]]:
    """MagNav.jl's Tolles-Lawson ``A`` matrix (``create_TL_A``), (n, 18) by default.

    Parameters
    ----------
    b_nT : (n, 3) vector magnetometer, body frame (x forward, y right, z down), nT.
    time_s : (n,) sample times, s, or None. The eddy columns are per-sample differences
        (MagNav's ``fdm``), so the eddy coefficients depend on the sample rate; with the
        times, MagNav's difference is taken per median sample interval
        (:func:`per_nominal_sample_difference`): the same columns on even sampling, and
        no noise from a recorder's uneven one.
    bt_scale_nT : MagNav's ``Bt_scale``, nT.
    terms : MagNav's term groups, with or without the leading colon: ``permanent`` (``p``),
        ``induced`` (``i``), ``eddy`` (``e``), ``bias`` (``b``). Columns come in MagNav's
        fixed order permanent, induced, eddy, bias.
    difference : the per-sample derivative of the eddy columns: MagNav's ``fdm``
        (:func:`per_sample_difference`, the compensation's, for parity with MagNav), or
        :func:`five_point_difference` (the audit's: see there).

    Returns
    -------
    columns : (n, p) array; permanent columns dimensionless, induced in nT / Bt_scale
        (dimensionless), eddy in nT per sample / Bt_scale, bias 1.
    names : the p column names (``perm_ux``, ``ind_uxBy``, ``eddy_uxdBy``, ``bias``).
    """
    b = np.asarray(b_nT, float)
    if time_s is not None and difference is per_sample_difference:
        db = per_nominal_sample_difference(b, time_s)
    else:
        db = difference(b)
    return _tl18(b, db, tuple(terms), bt_scale_nT, "")


def tl18_rate_terms(
    b_nT: np.ndarray, time_s: np.ndarray, bt_scale_nT: float = BT_SCALE_NT
) -> tuple[np.ndarray, list[str]]:
    """``tl18`` with rate-independent eddy columns u_i (dB_j/dt) / Bt_scale, (n, 18).

    Parameters
    ----------
    b_nT : (n, 3) vector magnetometer, body frame (x forward, y right, z down), nT.
    time_s : (n,) sample times, s (central differences in time, one-sided at the ends).
    bt_scale_nT : the induced/eddy column scale, nT.

    Returns
    -------
    columns, names : as :func:`tl18_terms`; eddy columns in (nT/s) / Bt_scale, named
        ``eddy_u{i}dB{j}dt``. Their coefficients are E_ij Bt_scale whatever the sample rate.
    """
    b = np.asarray(b_nT, float)
    return _tl18(
        b, np.gradient(b, np.asarray(time_s, float), axis=0), TL18_TERMS, bt_scale_nT, "dt"
    )


def position_terms(
    east_m: np.ndarray, north_m: np.ndarray, up_m: np.ndarray
) -> tuple[np.ndarray, list[str]]:
    """AGG-TL position columns: second-order horizontal Taylor terms and height, (n, 6)."""
    e, n, u = (np.asarray(a, float) for a in (east_m, north_m, up_m))
    return (
        np.column_stack([e, n, e * e, e * n, n * n, u]),
        ["pos_e", "pos_n", "pos_ee", "pos_en", "pos_nn", "pos_up"],
    )


def tl18_truth_coefficients(
    permanent_nT, induced, eddy_s, sample_interval_s: float, bt_scale_nT: float = BT_SCALE_NT
) -> np.ndarray:
    """The tl18 coefficients that a carrier with interference (p, A, E) has, to first order.

    Parameters
    ----------
    permanent_nT : (3,) permanent field at the scalar sensor, body frame, nT.
    induced : (3, 3) induced matrix, dimensionless (body frame).
    eddy_s : (3, 3) eddy-current matrix, s (nT per nT/s).
    sample_interval_s : the recording's sample interval, s: ``tl18``'s eddy columns are
        per-sample differences, so its eddy coefficients are E_ij Bt_scale / dt. Pass 1.0
        for :func:`tl18_rate_terms` (derivatives per second).
    bt_scale_nT : the induced/eddy column scale, nT.

    Returns
    -------
    (18,) coefficients in the column order of :func:`tl18_terms`, nT.
    """
    a, e = np.asarray(induced, float), np.asarray(eddy_s, float)
    ind = [
        (a[i, j] + a[j, i]) * bt_scale_nT if i != j else a[i, i] * bt_scale_nT
        for i, j in PAIRS_UPPER
    ]
    return np.concatenate(
        [np.asarray(permanent_nT, float), ind, (e * bt_scale_nT / float(sample_interval_s)).ravel()]
    )
