"""Joint levelling of a campaign: every crossover within and between flights at once.

Within a flight the crossovers are its survey-tie crossings (as the map stage levels them);
between two flights every line of one is crossed with every line of the other (survey, tie,
either way), wherever the tracks meet at ``min_crossing_angle_deg`` or more
(:func:`pipeline.maps.level.crossovers`).

Each crossover says ``v_a - corr_a(t_a) = v_b - corr_b(t_b)``, where a line's correction is
its flight's offset plus the line's own offset (and, with ``trend``, a slope in time about the
line's median time). The flight offsets are what differs from day to day (the diurnal level a
base station's mean does not remove, another base station); the line offsets what a flight's
own levelling left. The unknowns are fixed only up to a common level and up to each flight's
mean line offset, so two sets of constraints make them unique: the line offsets of each flight
sum to zero (its level is its flight offset) and the flight offsets sum to zero (the datum:
the campaign keeps the flights' mean level). The constrained least-squares problem is solved
exactly through its sparse KKT system (``scipy.sparse.linalg.spsolve``); a small ridge keeps a
line without crossovers at zero correction.

The design matrix is written here by hand (two +-1 entries per crossover and unknown kind)
because no library builds crossover designs: it is an incidence matrix of the line graph.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from pipeline.maps.level import MIN_CROSSING_ANGLE_DEG, Crossover, crossovers

# relative ridge on every unknown (times the largest diagonal of the normal matrix): enough
# to fix a line without any crossover at zero, far too small to bias the others (1e-9 nT)
RIDGE = 1e-10


def flight_of(line_key: str) -> int:
    """``"2:L0010"`` -> 2."""
    return int(line_key.split(":", 1)[0])


def line_of(line_key: str) -> str:
    """``"2:L0010"`` -> ``"L0010"``."""
    return line_key.split(":", 1)[1]


def sortie_crossovers(a, b=None, min_angle_deg: float = MIN_CROSSING_ANGLE_DEG) -> list[Crossover]:
    """Crossovers of one sortie's survey lines with its tie lines (``b`` None), or of every
    line of sortie ``a`` with every line of sortie ``b``.

    Parameters
    ----------
    a, b : Sortie
        From :func:`pipeline.campaign.sorties.read_sortie`.
    min_angle_deg : float
        Tracks meeting at a shallower angle do not cross (degrees).

    Returns
    -------
    list of Crossover
        ``line_a`` / ``line_b`` are campaign line keys (``"<flight>:<line>"``).
    """
    if b is None:
        survey = [ln for ln in a.lines if ln.kind == "survey"]
        ties = [ln for ln in a.lines if ln.kind == "tie"]
        return crossovers(survey, ties, min_angle_deg)
    return crossovers(a.lines, b.lines, min_angle_deg)


@dataclass
class JointLeveling:
    """The joint solution: per-flight and per-line corrections (nT; subtracted), residuals."""

    flight_offsets_nT: np.ndarray  # one per flight (sum zero)
    line_offsets: dict[str, tuple[float, float, float]]  # key -> (dc nT, slope nT/s, t_ref s)
    crossovers: list[Crossover]
    before_nT: np.ndarray  # crossover differences as the flights came
    after_nT: np.ndarray  # after the joint corrections
    between: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # between flights?
    trend: bool = False

    def correction(self, line_key: str, time_s: np.ndarray) -> np.ndarray:
        """Correction of a line at ``time_s`` (s since 1970): flight + line offset (+ slope)."""
        dc, slope, t0 = self.line_offsets.get(line_key, (0.0, 0.0, 0.0))
        return self.flight_offsets_nT[flight_of(line_key)] + dc + slope * (np.asarray(time_s) - t0)

    def rms_nT(self) -> dict[str, dict[str, float | None]]:
        """Crossover RMS before and after, within flights and between flights (nT; None when
        there is no such crossover)."""

        def rms(x: np.ndarray) -> float | None:
            return float(np.sqrt(np.mean(x**2))) if x.size else None

        out = {}
        for key, m in (("within_flight", ~self.between), ("between_flights", self.between)):
            out[key] = {"before": rms(self.before_nT[m]), "after": rms(self.after_nT[m])}
        return out


def design(
    xs: list[Crossover], keys: list[str], n_flights: int, t_ref: dict[str, float], trend: bool
) -> sp.csr_matrix:
    """The crossover design: one row per crossover, columns line offsets (then line slopes,
    with ``trend``), then flight offsets; the row of a crossover of lines a and b is
    (corr_a - corr_b) at the two passes' times."""
    col = {k: i for i, k in enumerate(keys)}
    nl = len(keys)
    ncols = nl * (2 if trend else 1) + n_flights
    f0 = nl * (2 if trend else 1)
    rows, cols, vals = [], [], []
    for r, c in enumerate(xs):
        for key, t, sign in ((c.line_a, c.time_a_s, 1.0), (c.line_b, c.time_b_s, -1.0)):
            rows += [r, r]
            cols += [col[key], f0 + flight_of(key)]
            vals += [sign, sign]
            if trend:
                rows.append(r)
                cols.append(nl + col[key])
                vals.append(sign * (t - t_ref[key]))
    a = sp.coo_matrix((vals, (rows, cols)), shape=(len(xs), ncols)).tocsr()
    a.sum_duplicates()  # a within-flight crossover's two flight entries cancel
    a.eliminate_zeros()
    return a


def constraints(keys: list[str], n_flights: int, trend: bool) -> sp.csr_matrix:
    """Rows of C x = 0: per flight, its line offsets sum to zero; the flight offsets sum to
    zero (the datum)."""
    nl = len(keys)
    f0 = nl * (2 if trend else 1)
    rows = [flight_of(k) for k in keys] + [n_flights] * n_flights
    cols = list(range(nl)) + [f0 + f for f in range(n_flights)]
    return sp.csr_matrix((np.ones(len(cols)), (rows, cols)), shape=(n_flights + 1, f0 + n_flights))


def level_jointly(
    lines_time_s: dict[str, np.ndarray],
    n_flights: int,
    xs: list[Crossover],
    between: np.ndarray,
    trend: bool = False,
) -> JointLeveling:
    """Flight and line corrections from every crossover of a campaign (see the module
    docstring).

    Parameters
    ----------
    lines_time_s : dict
        Campaign line key (``"<flight>:<line>"``) -> the line's sample times (s since 1970).
    n_flights : int
        Flights in the campaign (keys' flight numbers are 0 .. n_flights - 1).
    xs : list of Crossover
        Within- and between-flight crossovers (``line_a``, ``line_b`` campaign keys).
    between : ndarray of bool
        Per crossover: between two flights.
    trend : bool
        A slope in time per line besides its offset.

    Returns
    -------
    JointLeveling
    """
    keys = sorted(lines_time_s)
    t_ref = {k: float(np.median(v)) for k, v in lines_time_s.items()}
    d = np.array([c.difference_nT for c in xs], float)
    nl = len(keys)
    nx = nl * (2 if trend else 1) + n_flights
    if not xs:
        zero = np.zeros(n_flights)
        return JointLeveling(zero, {k: (0.0, 0.0, t_ref[k]) for k in keys}, xs, d, d, between)
    a = design(xs, keys, n_flights, t_ref, trend)
    c = constraints(keys, n_flights, trend)
    ata = (a.T @ a).tocsr()
    ridge = RIDGE * float(ata.diagonal().max() or 1.0)
    kkt = sp.bmat([[ata + ridge * sp.identity(nx), c.T], [c, None]], format="csc")
    rhs = np.r_[a.T @ d, np.zeros(c.shape[0])]
    x = spsolve(kkt, rhs)[:nx]
    f0 = nl * (2 if trend else 1)
    offsets = {
        k: (float(x[i]), float(x[nl + i]) if trend else 0.0, t_ref[k]) for i, k in enumerate(keys)
    }
    return JointLeveling(x[f0:], offsets, xs, d, d - a @ x, np.asarray(between, bool), trend)
