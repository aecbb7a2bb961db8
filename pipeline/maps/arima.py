"""ARIMA model of a map profile and the Kalman filter built on it (paper 004).

A gridded map, read in acquisition order (along the flight lines, serpentine), is a 1-D
sequence. It is tested for stationarity (reverse arrangements) and normality (skewness,
kurtosis), differenced until stationary, an ARMA(p, q) is fitted to the differences with the
orders chosen by BIC (statsmodels), and the integrated model ARIMA(p, d, q) is written in
companion state-space form **by multiplying out the fitted polynomials** (the paper prints a
wrong sign for the last coefficient of its ARIMA(2,1,1); deriving it avoids copying that).
The Kalman filter then runs on the sequence with process noise from the model's innovation
variance and measurement noise from the sensor.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.polynomial import polynomial as P
from scipy.signal import lfilter, lfiltic, ss2tf
from scipy.stats import kurtosis, norm, skew


# --------------------------------------------------------------------------------------------
# tests
@dataclass
class ReverseArrangements:
    """Reverse-arrangements (trend) test on the means of ``segments`` sub-series."""

    arrangements: int
    expected: float
    variance: float
    u: float
    stationary: bool
    segments: int

    def to_dict(self) -> dict:
        """JSON-ready: A, its expectation and variance, u, the verdict and the segment count."""
        return {
            "A": self.arrangements,
            "E_A": self.expected,
            "Var_A": self.variance,
            "u": self.u,
            "stationary": self.stationary,
            "segments": self.segments,
        }


def reverse_arrangements(
    x: np.ndarray, segments: int = 20, alpha: float = 0.05
) -> ReverseArrangements:
    """Stationary at level ``alpha`` when |u| <= z_(1-alpha/2) (1.96 for 5 %).

    The series is split into ``segments`` sub-series; A counts pairs i < j with
    mean_i > mean_j. For N means, E[A] = N(N-1)/4 and Var[A] = N(2N+5)(N-1)/72, and
    u = (A - E[A] + 1/2) / sqrt(Var[A]) (continuity-corrected).
    """
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    n = segments
    means = np.array([c.mean() for c in np.array_split(x, n)])
    a = int(sum(np.sum(means[i] > means[i + 1 :]) for i in range(n - 1)))
    e = n * (n - 1) / 4.0
    var = n * (2 * n + 5) * (n - 1) / 72.0
    u = (a - e + 0.5) / np.sqrt(var)
    return ReverseArrangements(a, e, var, float(u), bool(abs(u) <= norm.ppf(1 - alpha / 2)), n)


def normality(x: np.ndarray) -> dict[str, float]:
    """Skewness (0 for a normal law) and kurtosis (3 for a normal law, Pearson's)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return {"skewness": float(skew(x)), "kurtosis": float(kurtosis(x, fisher=False))}


# --------------------------------------------------------------------------------------------
# model
@dataclass
class ArimaModel:
    """ARIMA(p, d, q): (1 - sum phi_i B^i)(1 - B)^d x_k = (1 + sum theta_j B^j) e_k."""

    p: int
    d: int
    q: int
    ar: np.ndarray  # phi_1..phi_p
    ma: np.ndarray  # theta_1..theta_q
    sigma2: float  # innovation variance
    bic: float = float("nan")
    tests: dict = field(default_factory=dict)

    @property
    def order(self) -> tuple[int, int, int]:
        """The order (p, d, q)."""
        return (self.p, self.d, self.q)

    def integrated_ar(self) -> np.ndarray:
        """Coefficients a_1..a_(p+d) of x_k = sum a_i x_(k-i) + ...: the product
        (1 - sum phi_i B^i)(1 - B)^d, multiplied out."""
        phi_poly = np.r_[1.0, -np.asarray(self.ar, float)]
        diff_poly = np.array([1.0])
        for _ in range(self.d):
            diff_poly = P.polymul(diff_poly, [1.0, -1.0])
        full = P.polymul(phi_poly, diff_poly)
        return -full[1:]

    def companion(self) -> np.ndarray:
        """The paper's transition matrix for the lagged state [x_k, x_(k-1), ...]: first row
        the integrated AR coefficients, identity below (exact for the AR part)."""
        a = self.integrated_ar()
        r = max(len(a), 1)
        f = np.zeros((r, r))
        f[0, : len(a)] = a
        f[1:, :-1] = np.eye(r - 1)
        return f

    def harvey(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """State space (T, R, Z) in Harvey's form, exact for the MA part too.

        alpha_k = T alpha_(k-1) + R e_k, x_k = Z alpha_k, with T's first column the integrated
        AR coefficients and a shifted identity above the diagonal, R = (1, theta_1, ...),
        Z = (1, 0, ...). This is also statsmodels' SARIMAX representation.
        """
        a = self.integrated_ar()
        r = max(len(a), self.q + 1, 1)
        t = np.zeros((r, r))
        t[: len(a), 0] = a
        t[:-1, 1:] = np.eye(r - 1)
        rr = np.zeros(r)
        rr[0] = 1.0
        rr[1 : 1 + self.q] = self.ma
        z = np.zeros(r)
        z[0] = 1.0
        return t, rr, z

    def to_dict(self) -> dict:
        """JSON-ready: order, AR and MA coefficients, innovation variance, the integrated AR
        coefficients, BIC and the test results.
        """
        return {
            "order": list(self.order),
            "ar": [float(v) for v in self.ar],
            "ma": [float(v) for v in self.ma],
            "sigma2": float(self.sigma2),
            "integrated_ar": [float(v) for v in self.integrated_ar()],
            "bic": float(self.bic),
            **self.tests,
        }


def choose_d(x: np.ndarray, max_d: int = 2, segments: int = 20) -> tuple[int, list[dict]]:
    """Difference until the reverse-arrangements test accepts stationarity (NaN kept, so a
    difference across a missing stretch is missing, not a jump between distant cells)."""
    y = np.asarray(x, float)
    steps = []
    for d in range(max_d + 1):
        t = reverse_arrangements(y, segments)
        steps.append({"d": d, **t.to_dict()})
        if t.stationary or d == max_d:
            return d, steps
        y = np.diff(y)
    return max_d, steps


ROOT_MARGIN = 0.01  # AR or MA roots closer than this to the unit circle: a degenerate fit
# order search on a sequence longer than SCREEN_ABOVE samples (the map stage's identification
# stretch of a survey of ~4 h and more): every candidate is ranked by its BIC under Whittle's
# likelihood (pipeline.maps.whittle: one FFT, no Kalman filter) on the whole sequence, and
# the best whose Whittle estimates pass the exact likelihood's checks (one filter pass) is
# the model; only when none of the SHORTLIST best does are they fitted exactly (an exact
# fit costs ~100 filter passes)
SCREEN_ABOVE = 10_000
SHORTLIST = 3


def _min_root_modulus(coefs: np.ndarray, sign: float) -> float:
    """Smallest |root| of 1 + sign * sum c_i B^i (inf for no coefficient)."""
    c = np.asarray(coefs, float)
    if c.size == 0 or not np.any(c):
        return float("inf")
    return float(np.min(np.abs(np.roots(np.r_[1.0, sign * c][::-1]))))


def degenerate(res, measurement_var: float | None) -> str | None:
    """Why a fitted statsmodels ARIMA/SARIMAX result is not a usable model, or None.

    * **impossible likelihood**: with a known white measurement variance R every one-step
      prediction variance is >= R, so ln L <= -n/2 ln(2 pi R) over the n scored samples; a
      larger value is a numerical failure of the likelihood (the stationary initialisation
      of a unit-root candidate is singular), not a good fit (seen: ln L = 0.0 on 1 701 cells
      with R = 1 nT^2, BIC 30 against ~6 300 for every sane candidate);
    * **AR root on the unit circle** (|root| < 1 + ``ROOT_MARGIN``): the differences are
      not stationary, the series needs one more difference (a serpentine map makes the
      reverse-arrangements test accept a random walk: its segment means do not trend);
    * **MA root on the unit circle**: non-invertible, the innovations cannot be recovered and
      the filter built on it does not remove noise (AR ~ [0, 1] with MA ~ 1, i.e.
      x_k = x_(k-2) + e_k + e_(k-1), made the filter worsen the map 14-fold).
    """
    llf = float(res.llf)
    if not np.isfinite(llf) or not np.isfinite(res.bic):
        return "non-finite likelihood"
    if measurement_var is not None and measurement_var > 0:
        n = int(res.nobs) - int(getattr(res, "loglikelihood_burn", 0))
        bound = -0.5 * n * np.log(2 * np.pi * measurement_var)
        if llf > bound + 1e-6 * abs(bound):
            return f"ln L {llf:.1f} above its bound {bound:.1f} (numerical failure)"
    ar = np.asarray(getattr(res, "arparams", []), float)
    ma = np.asarray(getattr(res, "maparams", []), float)
    if _min_root_modulus(ar, -1.0) < 1.0 + ROOT_MARGIN:
        return "AR root on the unit circle (under-differenced)"
    if _min_root_modulus(ma, 1.0) < 1.0 + ROOT_MARGIN:
        return "MA root on the unit circle (non-invertible)"
    return None


def fit_arima(
    x: np.ndarray,
    order: tuple[int, int, int] | None = None,
    max_p: int = 3,
    max_q: int = 2,
    max_d: int = 2,
    measurement_var: float | None = None,
) -> ArimaModel:
    """Fit ARIMA to a 1-D sequence: orders by BIC unless ``order`` is given.

    ``d`` starts from the reverse-arrangements test (difference until stationary); (p, q) by
    BIC = k ln(n) - 2 ln L over p <= max_p, q <= max_q, by statsmodels' exact likelihood. On
    a sequence longer than SCREEN_ABOVE the candidates are first ranked by BIC under Whittle's
    likelihood (:func:`pipeline.maps.whittle.whittle_fit`); the first of the SHORTLIST best
    whose Whittle estimates make a usable model under the exact likelihood is the model,
    without optimising the exact likelihood (``tests["estimated_by"]``: ``whittle``). When
    none is, the shortlist is fitted exactly and BIC chooses, and when none of those is
    usable either d goes up (at the largest d the others are fitted too).
    Candidates that are :func:`degenerate` (impossible likelihood, AR or MA root on the unit
    circle) are rejected; when every candidate at d is, d goes up by one (up to ``max_d``),
    and when none is left at any d the model is the local level ARIMA(0, 1, 0) (a random
    walk signal), which is always well posed. NaNs inside the sequence stay as missing
    values; leading and trailing ones are dropped.

    With ``measurement_var`` (the sequence's white-noise variance, same units squared) the
    sequence is modelled as an ARIMA *signal plus white measurement noise* of that (known)
    variance, so the innovation variance describes the signal alone: fitting a plain ARIMA
    to noisy data would fold the noise into the process noise and the Kalman filter would
    then count it twice.

    An explicit ``order`` is fitted as given; if it is degenerate the reason is kept in the
    model's ``tests["degenerate"]``.
    """
    x = np.asarray(x, float)
    # masked cells stay in as missing values (NaN): the likelihood predicts through a gap of
    # its true length instead of joining the cells on either side as neighbours
    fin = np.flatnonzero(np.isfinite(x))
    if fin.size == 0:
        raise ValueError("no finite sample to fit")
    x = x[fin[0] : fin[-1] + 1]
    if order is None:
        d0, steps = choose_d(x, max_d)
    else:
        d0, steps = order[1], []

    found = _search(x, order, d0, (max_p, max_q, max_d), measurement_var)
    if found.best is None:
        raise ValueError("no ARIMA candidate could be fitted: " + "; ".join(found.failed))
    tests = {
        "stationarity": steps,
        "samples": int(np.isfinite(x).sum()),
        "missing_inside": int((~np.isfinite(x)).sum()),
        "measurement_var": measurement_var,
        "failed_candidates": found.failed,
        "d_from_test": d0,
        "screened": found.screened,
        "estimated_by": found.estimated_by,
    }
    if found.bad_explicit is not None:
        tests["degenerate"] = found.bad_explicit
    return _model_of(found.best, x, tests)


@dataclass
class _Search:
    """What the order search found: the chosen fit ``(result, p, d, q)`` (or None), the
    candidates rejected and why, the shortlists Whittle's likelihood kept (d -> [[p, q]]),
    which likelihood estimated the model, and why an explicit order is degenerate."""

    best: Any = None
    failed: list[str] = field(default_factory=list)
    screened: dict[str, list] = field(default_factory=dict)
    estimated_by: str = "exact likelihood"
    bad_explicit: str | None = None


def _search(
    x: np.ndarray,
    order: tuple[int, int, int] | None,
    d0: int,
    limits: tuple[int, int, int],
    measurement_var: float | None,
) -> _Search:
    """The order search of :func:`fit_arima` on ``x`` from ``d0`` (``limits``: max p, q,
    d); an explicit ``order`` is fitted as given."""
    max_p, max_q, max_d = limits
    starts: dict[tuple[int, int, int], np.ndarray] = {}  # a screening's estimates
    out = _Search()

    def fit_one(p: int, d: int, q: int):
        return _likelihood(x, (p, d, q), measurement_var, starts.get((p, d, q)), optimise=True)

    def at_whittle(p: int, d: int, q: int):
        # the exact likelihood at the screening's estimates, without optimising: Whittle's
        # estimator is asymptotically as efficient as the exact likelihood's, and the
        # filter's output with either differs by a small share of the noise
        return _likelihood(x, (p, d, q), measurement_var, starts[(p, d, q)], optimise=False)

    d_range = [d0] if order else list(range(d0, max(max_d, d0) + 1))
    # imported before the filter: statsmodels' import puts "always" filters for its own
    # warnings in front of any set earlier
    import statsmodels.tsa.arima.model  # noqa: F401
    import statsmodels.tsa.statespace.sarimax  # noqa: F401

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # convergence chatter on poor candidates
        for d in d_range:
            candidates = (
                [(order[0], order[2])]
                if order
                else [(p, q) for p in range(max_p + 1) for q in range(max_q + 1) if p + q > 0]
            )
            ranked: int | None = None
            if order is None and x.size > SCREEN_ABOVE:
                short = _shortlist(candidates, d, x, measurement_var, starts)
                # none of the shortlist usable: d goes up (at the last d the rest compete)
                rest = [c for c in candidates if c not in short] if d == d_range[-1] else []
                candidates = short + rest
                out.screened[str(d)] = [list(c) for c in short]
                ranked = len(short)
                out.best = _first_usable(at_whittle, d, short, starts, measurement_var, out.failed)
                if out.best is not None:
                    out.estimated_by = "whittle"
                    break
            out.best, why = _best_at(
                fit_one, d, candidates, ranked, order is not None, measurement_var, out.failed
            )
            out.bad_explicit = out.bad_explicit or why
            if out.best is not None:
                break
        if out.best is None and order is None and measurement_var is not None:
            # every candidate degenerate: the local level model (random walk + noise)
            res = fit_one(0, max(d0, 1), 0)
            if np.isfinite(res.llf):
                out.best = (res, 0, max(d0, 1), 0)
                out.failed.append("fell back to ARIMA(0,1,0): local level")
    return out


def _likelihood(
    z: np.ndarray,
    order: tuple[int, int, int],
    measurement_var: float | None,
    start: np.ndarray | None,
    optimise: bool,
):
    """statsmodels' exact-likelihood result of ARIMA ``order`` on ``z`` (plus white noise of
    the known ``measurement_var``, None: none): fitted from ``start`` (AR, MA, innovation
    variance; None: statsmodels' own) when ``optimise``, else filtered once at ``start``.
    No parameter covariance: only the estimates and the likelihood are used."""
    from statsmodels.tsa.arima.model import ARIMA
    from statsmodels.tsa.statespace.sarimax import SARIMAX

    p, d, q = order
    if measurement_var is None:
        y = np.diff(z, n=d) if d else z  # differences across a gap are NaN, not joined
        mod = ARIMA(y, order=(p, 0, q), trend="n")
        if not optimise:
            return mod.filter(start, cov_type="none")
        return mod.fit(start_params=start, cov_type="none")
    mod = SARIMAX(z, order=(p, d, q), measurement_error=True, trend="n")
    fixed = {"var.measurement_error": float(measurement_var)}
    if not optimise:
        with mod.fix_params(fixed):
            return mod.filter(start, cov_type="none")
    if start is not None:  # the fixed measurement variance sits before sigma2
        start = np.r_[start[:-1], float(measurement_var), start[-1]]
    return mod.fit_constrained(
        fixed, start_params=start, includes_fixed=True, disp=False, cov_type="none"
    )


def _model_of(best, x: np.ndarray, tests: dict) -> ArimaModel:
    """The :class:`ArimaModel` of a chosen fit ``(result, p, d, q)`` of ``x``; ``tests``
    gains the normality of the differenced sequence."""
    res, p, d, q = best
    y = np.diff(x, n=d) if d else x
    params = dict(zip(res.model.param_names, res.params, strict=True))
    ar = np.array([params[f"ar.L{i}"] for i in range(1, p + 1)])
    ma = np.array([params[f"ma.L{i}"] for i in range(1, q + 1)])
    tests = {**tests, "normality_differenced": normality(y)}
    return ArimaModel(p, d, q, ar, ma, float(params["sigma2"]), float(res.bic), tests)


def _best_at(
    fit_one,
    d: int,
    candidates: list[tuple[int, int]],
    n_short: int | None,
    explicit: bool,
    measurement_var: float | None,
    failed: list[str],
):
    """The lowest-BIC usable fit ``(result, p, d, q)`` of ``candidates`` (p, q) at ``d`` (or
    None), and why an ``explicit`` order is degenerate (or None); unusable ones are noted in
    ``failed``. With ``n_short``, the candidates after the first ``n_short`` (a shortlist) are
    fitted only when none of those is usable."""
    best, bad = None, None
    for k, (p, q) in enumerate(candidates):
        if n_short is not None and k == n_short and best is not None:
            break  # a shortlisted candidate is usable: the rest are not fitted
        res = _tried(fit_one, (p, d, q), failed)
        if res is None:
            continue
        why = degenerate(res, measurement_var)
        if why is not None and not explicit:
            failed.append(f"ARIMA({p},{d},{q}): {why}")
            continue
        if why is not None:
            bad = why
        if best is None or res.bic < best[0].bic:
            best = (res, p, d, q)
    return best, bad


# how a shortlisted order judged at Whittle's estimates is named in ``failed_candidates``
WHITTLE_LABEL = " at Whittle's estimates"


def _tried(fit, order: tuple[int, int, int], failed: list[str], label: str = ""):
    """``fit(p, d, q)``'s statsmodels result, or None with why noted in ``failed`` (the
    order's name, then ``label``): an optimiser or a filter can step onto a (near) unit root
    where the stationary initialisation is singular; that candidate is out, the others
    compete."""
    try:
        return fit(*order)
    except (np.linalg.LinAlgError, ValueError) as exc:
        failed.append(f"ARIMA({order[0]},{order[1]},{order[2]}){label}: {type(exc).__name__}")
        return None


def _first_usable(
    at_whittle,
    d: int,
    short: list[tuple[int, int]],
    starts: dict,
    measurement_var: float | None,
    failed: list[str],
):
    """The first of the shortlist ``short`` (in Whittle BIC order) whose Whittle estimates
    (``starts``) give a usable model under the exact likelihood (:func:`degenerate`), as
    ``(result, p, d, q)``, or None: the Whittle likelihood both estimates and chooses, the
    exact one only vets the choice and gives its BIC. Those passed over are noted in
    ``failed`` (their exact fits may still be usable, and are tried when none is)."""
    for p, q in short:
        name = f"ARIMA({p},{d},{q}){WHITTLE_LABEL}"
        if (p, d, q) not in starts:
            failed.append(f"{name}: AR or MA root on the unit circle")
            continue
        res = _tried(at_whittle, (p, d, q), failed, WHITTLE_LABEL)
        if res is None:
            continue
        why = degenerate(res, measurement_var)
        if why is None:
            return res, p, d, q
        failed.append(f"{name}: {why}")
    return None


def _shortlist(
    candidates: list[tuple[int, int]],
    d: int,
    x: np.ndarray,
    measurement_var: float | None,
    starts: dict[tuple[int, int, int], np.ndarray],
) -> list[tuple[int, int]]:
    """The SHORTLIST orders (p, q) with the lowest Whittle BIC at ``d`` on ``x``
    (:func:`pipeline.maps.whittle.whittle_fit`); the estimates (AR, MA, innovation variance)
    of each with no AR or MA root on the unit circle go into ``starts`` under (p, d, q). A
    root there is no verdict: the frequency-domain fit reads a signal with no power left at
    the Nyquist frequency (a smooth map under white noise) as an MA root at -1, where the
    exact fit can settle inside; :func:`degenerate` judges the exact fits."""
    from pipeline.maps.whittle import Periodograms, whittle_fit

    try:
        pg = Periodograms.of(x, d)
    except ValueError:
        return []
    scored = []
    for p, q in candidates:
        fit = whittle_fit(pg, p, d, q, measurement_var)
        if not np.isfinite(fit.bic):
            continue
        scored.append((fit.bic, p, q))
        if min(_min_root_modulus(fit.ar, -1.0), _min_root_modulus(fit.ma, 1.0)) > 1 + ROOT_MARGIN:
            starts[(p, d, q)] = np.r_[fit.ar, fit.ma, fit.sigma2]
    return [(p, q) for _, p, q in sorted(scored)[:SHORTLIST]]


# --------------------------------------------------------------------------------------------
# filter
@dataclass
class KalmanResult:
    """Filtered sequence (NaN where the input is missing) and the steady-state gain."""

    filtered: np.ndarray
    gain_steady: np.ndarray
    exact_steps: int  # samples run through the full Riccati recursion (the rest: modal IIR)


def _advance(
    t: np.ndarray, q: np.ndarray, x: np.ndarray, pm: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray]:
    """m prediction steps at once: x <- T^m x, P <- T^m P T^m' + sum_j T^j Q T^j'.

    Binary doubling of (T^n, S_n), S_n = sum_(j<n) T^j Q T^j', so a gap costs O(log m)."""
    acc_t, acc_s = np.eye(len(x)), np.zeros_like(pm)
    base_t, base_s = t, q
    while m:
        if m & 1:
            acc_t, acc_s = base_t @ acc_t, base_t @ acc_s @ base_t.T + base_s
        base_t, base_s = base_t @ base_t, base_t @ base_s @ base_t.T + base_s
        m >>= 1
    return acc_t @ x, acc_t @ pm @ acc_t.T + acc_s


def _modal_run(
    a: np.ndarray, gain: np.ndarray, z: np.ndarray, x0: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Outputs z x_k and the last state of x_k = A x_(k-1) + gain y_k over a gap-free run.

    A is diagonalised, A = V diag(l) V^-1; each mode w_i = l_i w_i + c_i y is a first-order
    IIR filter run by scipy.signal.lfilter (C speed), and x = V w."""
    lam, v = np.linalg.eig(a)
    vinv = np.linalg.inv(v)
    c = vinv @ gain
    w0 = vinv @ x0
    out = np.zeros(y.size, complex)
    last = np.zeros(len(lam), complex)
    zv = z @ v
    for i, li in enumerate(lam):
        wi, _ = lfilter([c[i]], [1.0, -li], y.astype(complex), zi=[li * w0[i]])
        out += zv[i] * wi
        last[i] = wi[-1]
    return out.real, (v @ last).real


def _steady_run(
    a: np.ndarray, gain: np.ndarray, z: np.ndarray, x0: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Same as :func:`_modal_run`, as one real IIR filter (about 5x faster).

    The steady-state filter x_k = A x_(k-1) + g y_k, out_k = z x_k is the transfer function
    (z A, z g) / det(I - A q^-1) (scipy.signal.ss2tf) run by one real lfilter; the free response
    to x0 continues z A^(k+1) x0 with the same denominator (Cayley-Hamilton); the last state
    follows from the last d outputs through the observability matrix of (A, z). Falls back to
    the modal filters when that matrix is ill-conditioned."""
    d, n = len(x0), y.size
    if n <= d:
        out = np.empty(n)
        x = x0
        for k in range(n):
            x = a @ x + gain * y[k]
            out[k] = z @ x
        return out, x
    powers = [np.eye(d)]
    for _ in range(d):
        powers.append(a @ powers[-1])
    obs = np.array([z @ p for p in powers[:d]])
    if np.linalg.cond(obs) > 1e8:
        return _modal_run(a, gain, z, x0, y)
    num, den = ss2tf(a, gain.reshape(-1, 1), (z @ a).reshape(1, -1), np.array([[z @ gain]]))
    out = lfilter(num[0], den, y)
    free = np.array([z @ powers[k + 1] @ x0 for k in range(d)])
    # the free response decays like rho^k (the steady-state filter is stable): run it only
    # until it is below double precision of its start
    rho = float(np.max(np.abs(np.linalg.eigvals(a))))
    span = n - d if rho >= 1.0 else min(n - d, int(np.ceil(-40.0 / np.log(max(rho, 1e-300)))) + d)
    rest = lfilter([1.0], den, np.zeros(span), zi=lfiltic([1.0], den, free[::-1]))[0]
    out[:d] += free
    out[d : d + span] += rest
    # x_(n-d) from out_(n-d+i) = z A^i x_(n-d) + sum_(j=1..i) z A^(i-j) g y_(n-d+j)
    ys, outs = y[n - d :], out[n - d :]
    rhs = np.array(
        [outs[i] - sum(z @ powers[i - j] @ gain * ys[j] for j in range(1, i + 1)) for i in range(d)]
    )
    x = np.linalg.solve(obs, rhs)
    for j in range(1, d):
        x = a @ x + gain * ys[j]
    return out, x


def kalman_filter(
    y: np.ndarray,
    model: ArimaModel,
    measurement_var: float,
    process_var: float | None = None,
    x0: np.ndarray | None = None,
    p0: np.ndarray | None = None,
    tol: float = 1e-13,
) -> KalmanResult:
    """Kalman filter of ``y`` (NaN = missing) with the ARIMA model as the state equation.

    Process noise: ``process_var`` (default: the model's innovation variance) through R;
    measurement noise: ``measurement_var``. Each gap-free run starts with the exact Riccati
    recursion; once the gain is constant to ``tol`` (relative) the identical steady-state
    filter runs as modal IIR filters. Missing samples are predicted through (O(log gap)) and
    returned as NaN.

    The initial state defaults to the first value in every component (a level that the
    integrated model keeps) with a covariance 1e6 x the sequence variance (near-diffuse).
    """
    y = np.asarray(y, float)
    t, rr, z = model.harvey()
    q = (model.sigma2 if process_var is None else process_var) * np.outer(rr, rr)
    r = float(measurement_var)
    dim = t.shape[0]
    finite = np.isfinite(y)
    out = np.full(y.size, np.nan)
    if not finite.any():
        return KalmanResult(out, np.zeros(dim), 0)
    first = int(np.flatnonzero(finite)[0])
    if x0 is None:
        x = _level_state(t, y[first])
    else:
        x = np.asarray(x0, float)
    pm = (
        np.eye(dim) * 1e6 * max(float(np.nanvar(y)), 1e-12) if p0 is None else np.asarray(p0, float)
    )
    # runs of finite samples
    edges = np.flatnonzero(np.diff(np.r_[0, finite.astype(int), 0]))
    runs = list(zip(edges[::2], edges[1::2], strict=True))
    pos = 0  # samples already accounted for (predicted through or filtered)
    gain = np.zeros(dim)
    exact = 0
    for a, b in runs:
        if a > pos:  # predict through the gap
            x, pm = _advance(t, q, x, pm, a - pos)
        k = a
        prev = None
        while k < b:
            x = t @ x
            pm = t @ pm @ t.T + q
            s_ = z @ pm @ z + r
            gain = pm @ z / s_
            x = x + gain * (y[k] - z @ x)
            pm = pm - np.outer(gain, z @ pm)
            pm = 0.5 * (pm + pm.T)
            out[k] = z @ x
            k += 1
            exact += 1
            if prev is not None and np.max(np.abs(gain - prev)) <= tol * np.max(np.abs(gain)):
                break
            prev = gain
        if k < b:  # steady state for the rest of the run: P is already at its fixed point
            closed = (np.eye(dim) - np.outer(gain, z)) @ t
            out[k:b], x = _steady_run(closed, gain, z, x, y[k:b])
        pos = b
    return KalmanResult(out, gain, exact)


def _level_state(t: np.ndarray, value: float) -> np.ndarray:
    """Harvey state of a series that has stayed at ``value``: x_k = value and, for the
    integrated model, alpha solving alpha = T alpha with alpha_0 = value (least squares when
    the model is not integrated)."""
    dim = t.shape[0]
    a = np.vstack([np.eye(dim) - t, np.eye(dim)[:1]])
    b = np.r_[np.zeros(dim), value]
    return np.linalg.lstsq(a, b, rcond=None)[0]


# --------------------------------------------------------------------------------------------
# fixed-interval (Rauch-Tung-Striebel) smoother
SMOOTH_CHUNK = 200_000  # samples per statsmodels smoother call (its memory: ~2 kB per sample)
SMOOTH_OVERLAP = 2_000  # samples each side a chunk runs beyond the part it returns


def rts_smooth(y: np.ndarray, model: ArimaModel, measurement_var: float | np.ndarray) -> np.ndarray:
    """Fixed-interval smoothed signal E[x_k | all of y] of ``y`` = ARIMA signal + white noise.

    statsmodels' state-space smoother (SARIMAX in Harvey form, the fitted AR/MA coefficients
    and innovation variance held fixed, the default diffuse-like initialisation) does the
    Rauch-Tung-Striebel recursions; missing samples (NaN) are predicted through, and their
    smoothed values are returned as NaN. ``measurement_var`` may be one variance or one per
    sample (nT^2): the noise of a gridded map differs between cells on a flight line and
    cells interpolated between lines.

    Long sequences are smoothed in chunks of ``SMOOTH_CHUNK`` samples that overlap by
    ``SMOOTH_OVERLAP`` on each side (only each chunk's middle is kept): statsmodels keeps
    every covariance, about 2 kB per sample, so 10^6 cells in one call would need ~2 GB.
    The steady-state smoother forgets its far end within a few hundred samples for the
    models BIC picks on maps, so the overlap changes nothing measurable.
    """
    from statsmodels.tsa.statespace.sarimax import SARIMAX

    y = np.asarray(y, float)
    n = y.size
    r = np.broadcast_to(np.asarray(measurement_var, float), (n,))
    params = np.r_[model.ar, model.ma, model.sigma2]
    out = np.full(n, np.nan)
    start = 0
    while start < n:
        stop = min(start + SMOOTH_CHUNK, n)
        a, b = max(start - SMOOTH_OVERLAP, 0), min(stop + SMOOTH_OVERLAP, n)
        seg = y[a:b]
        if np.isfinite(seg).any():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mod = SARIMAX(seg, order=model.order, trend="n")
                # after construction: SARIMAX's update() owns AR/MA/sigma2, not obs_cov
                mod.ssm["obs_cov"] = r[a:b].reshape(1, 1, -1).copy()
                res = mod.smooth(params)
            sm = np.asarray(res.smoother_results.smoothed_forecasts)[0]
            out[start:stop] = sm[start - a : stop - a]
        start = stop
    out[~np.isfinite(y)] = np.nan
    return out
