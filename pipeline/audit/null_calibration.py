"""The selection's false-finding rate, measured: a parametric bootstrap of the null model.

The null model (the baseline with the nuisances the data support,
:mod:`pipeline.audit.nuisances`) is fitted on the calibration; its residual's own spectrum is
kept and its phases randomised per contiguous block (a coloured-noise surrogate: the
residual's correlation, 1/f included, without any structure a candidate could follow), and
each surrogate added to the null model's prediction is a recording on which nothing is
hidden. On every draw each candidate's held-out statistic (the fraction of the held-out
residual RMS its columns remove beside the null model's, on the buffered contiguous folds
of :mod:`pipeline.compensate.heldout`) is recomputed and the largest over the candidates
kept: the whole selection's maximum statistic. A candidate with a competing explanation the
selection makes it beat (a current that follows the manoeuvres against the second-order
terms) is measured beside that rival too: otherwise the rival's physics, absent from the
null model and so from its draws, would count as the candidate's gain. The ridge parameters
are the recording's, so every fit is linear in the data and all draws share one band-pass
and one factorisation per fold and model: hundreds of draws cost seconds.

The threshold is the maximum statistic's 1 - alpha quantile over the draws (the order
statistic whose level holds for their finite number); the gate a candidate must reach is
it or the least gain worth a term, whichever is larger. The rate at
which such a gate names something on a flight with nothing hidden (``flight_alpha``) is
measured on draws that did not set it: the gate set on one half, counted on the other, both
ways round.

Scope: the candidates linear in the data judged on the scalar calibration (a gradient, each
recorded current, a change of the permanent field between calibration passes). A lag is
not: its first order in the lag lies in T-L's eddy columns (a delayed permanent field is the
rate of change of the direction cosines), so only the delay itself sees it, and the null
model's design delayed over the lag grid on these contiguous folds tells a late sensor from
eddy decay less well than the lag's own tests; it is judged against the null model with the
nuisances instead (:mod:`pipeline.audit.decide`). The diurnal is judged on crossovers, the
vector calibration on the fluxgate, the events on the survey; their tests are not in this
maximum (the events share the flight's rate with it by Bonferroni,
:class:`pipeline.audit.settings.AuditSettings`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.compensate.filters import (
    bandpass_blocks,
    bandpass_sos,
    contiguous_blocks,
    trim_samples,
)
from pipeline.compensate.heldout import fold_masks
from pipeline.compensate.plus import HeldOutSetup, ridge_theta
from pipeline.compensate.ridge import RidgeSVD

METHOD = "parametric_bootstrap"


@dataclass
class NullCalibration:
    """The measured null distribution of the selection's maximum statistic.

    Attributes
    ----------
    draws : int
        Null draws.
    alpha : float
        The level the maximum's threshold is set for (the flight's rate less the event
        tests' levels, :attr:`event_tests_alpha`).
    threshold_gain : float
        The maximum statistic's 1 - alpha quantile (fraction of held-out RMS;
        :func:`monte_carlo_threshold`).
    gate_gain : float
        What a candidate's held-out gain must reach: the threshold or the least gain worth a
        term, whichever is larger.
    flight_alpha : float
        Measured share of null draws on which some candidate reaches a gate set on other
        draws (:func:`crossfit_rate`).
    observed_gain : dict
        Each candidate's statistic on the recording.
    p_value : float
        The recording's maximum statistic against all null draws.
    event_tests_alpha : float
        Summed levels of the event tests outside the maximum (each calibrated by its own
        null simulation): the flight's false-finding rate is at most ``flight_alpha`` plus
        this (Bonferroni).
    """

    draws: int
    alpha: float
    threshold_gain: float
    gate_gain: float
    flight_alpha: float
    observed_gain: dict[str, float] = field(default_factory=dict)
    p_value: float = 1.0
    event_tests_alpha: float = 0.0

    def gate(self, confirmed: bool = False) -> float:
        """The held-out gain a candidate must reach: :attr:`gate_gain`, or, once evidence
        outside the calibration (the survey's crossovers, the channel's switches) has shown
        the gain matters (``confirmed``), :attr:`threshold_gain` alone: the least gain worth
        a term is waived as :meth:`pipeline.audit.result.Evaluation.gain_suffices` waives
        it, the whole selection's level stays."""
        return self.threshold_gain if confirmed else self.gate_gain

    def passes(self, key: str, confirmed: bool = False) -> bool:
        """Whether candidate ``key``'s statistic on the recording reaches :meth:`gate` (True
        for a candidate outside the bootstrap's scope)."""
        g = self.observed_gain.get(key)
        return g is None or g >= self.gate(confirmed)

    def to_dict(self) -> dict[str, Any]:
        """``null_calibration``: ``method``, ``draws``, ``flight_alpha`` (the whole flight's:
        the maximum's measured rate plus the event tests' levels; ``alpha`` its target) and
        the figures."""
        return {
            "method": METHOD,
            "draws": self.draws,
            "flight_alpha": self.flight_alpha + self.event_tests_alpha,
            "alpha": self.alpha + self.event_tests_alpha,
            "maximum_alpha": self.alpha,
            "maximum_flight_alpha": self.flight_alpha,
            "event_tests_alpha": self.event_tests_alpha,
            "threshold_gain": self.threshold_gain,
            "gate_gain": self.gate_gain,
            "observed_gain": self.observed_gain,
            "max_statistic_p_value": self.p_value,
        }


def surrogates(
    residual: np.ndarray, blocks: list[np.ndarray], draws: int, rng: np.random.Generator
) -> np.ndarray:
    """``draws`` coloured-noise copies of ``residual`` (n,) -> (n, draws): per contiguous
    block (index arrays ``blocks``), the linearly detrended residual's Fourier amplitudes with
    random phases, the trend added back; NaN outside the blocks."""
    out = np.full((residual.size, draws), np.nan)
    for b in blocks:
        r = residual[b]
        x = np.arange(b.size, dtype=float)
        trend = np.polyval(np.polyfit(x, r, 1), x) if b.size > 2 else np.full(b.size, r.mean())
        amp = np.abs(np.fft.rfft(r - trend))
        ph = rng.uniform(0.0, 2.0 * np.pi, (amp.size, draws))
        ph[0] = 0.0
        if b.size % 2 == 0:
            ph[-1] = 0.0
        out[b] = np.fft.irfft(amp[:, None] * np.exp(1j * ph), n=b.size, axis=0) + trend[:, None]
    return out


def _row_of(valid: np.ndarray) -> np.ndarray:
    """Each epoch's row among the ``valid`` epochs (-1: not valid)."""
    row = np.full(valid.size, -1)
    row[valid] = np.arange(int(valid.sum()))
    return row


def monte_carlo_threshold(top: np.ndarray, alpha: float) -> float:
    """The draws' ``top`` value that a new null draw reaches with probability at most
    ``alpha``: the ceil((n + 1)(1 - alpha))-th smallest of n (a Monte Carlo test's exact
    level for exchangeable draws; the plain quantile's level is alpha only as n grows)."""
    k = int(np.ceil((top.size + 1) * (1.0 - alpha)))
    return float(np.inf if k > top.size else np.sort(top)[k - 1])


def crossfit_rate(top: np.ndarray, alpha: float, min_gain: float) -> float:
    """The rate at which a gate set on one half of the null draws' maxima ``top`` (its
    1 - ``alpha`` quantile, at least ``min_gain``) is reached on the other half, averaged
    over both ways round: measured on draws the gate did not see."""
    a, b = top[: top.size // 2], top[top.size // 2 :]
    rates = [
        np.mean(test >= max(monte_carlo_threshold(fit, alpha), min_gain))
        for fit, test in ((a, b), (b, a))
    ]
    return float(np.mean(rates))


def _fold_sums(
    setup: HeldOutSetup, cols: np.ndarray, y: np.ndarray, models, valid: np.ndarray
) -> np.ndarray:
    """Held-out squared residuals summed over the folds: (models, draws), each model a
    column index list of ``cols``; ``y`` (rows, 1 + draws) holds the recording and its null
    draws.
    ``cols`` and ``y`` hold the ``valid`` epochs' rows only (every fold's rows are valid):
    the flight's other epochs would make each (epochs, draws) array the survey's size."""
    m, band = setup.meas, setup.band
    sos = bandpass_sos(band.band_hz, m.rate_hz, band.poles)
    trim = trim_samples(band.trim_s, m.rate_hz)
    row = _row_of(valid)
    both = np.column_stack([cols, y])
    p = cols.shape[1]
    out = np.zeros((len(models), y.shape[1]))
    for k in range(int(setup.fold.max()) + 1):
        train, test = fold_masks(m.time_s, setup.fold, k, setup.buffer_s)
        train, test = train & valid, test & valid
        if not train.any() or not test.any():
            continue
        tr, _ = bandpass_blocks(
            both, [row[b] for b in contiguous_blocks(train, m.time_s)], sos, trim
        )
        te, _ = bandpass_blocks(
            both, [row[b] for b in contiguous_blocks(test, m.time_s)], sos, trim
        )
        for i, idx in enumerate(models):
            kt, yt = tr[:, idx], tr[:, p:]
            solver = RidgeSVD.from_gram(kt, yt[:, 0])  # the recording's lambda, every draw
            lam = solver.lcurve().lambda_corner if setup.ridge == "auto" else float(setup.ridge)
            theta = np.linalg.solve(kt.T @ kt + lam * np.eye(kt.shape[1]), kt.T @ yt)
            out[i] += np.sum((te[:, p:] - te[:, idx] @ theta) ** 2, axis=0)
    return out


def _models(
    p0: int, candidates: dict[str, np.ndarray], rivals: dict[str, str], rival_cols: dict
) -> tuple[list[np.ndarray], list[list[int]], list[tuple[int, int]]]:
    """The extra column blocks after the null model's ``p0`` columns, every model's column
    indices (the null model first) and, per candidate, the (base, extended) model indices:
    the base is the null model with the candidate's rival (``rivals``: key -> name in
    ``rival_cols``) when it has one."""
    blocks, models, pairs, placed, at = [], [list(range(p0))], [], {}, p0

    def place(name: str, block: np.ndarray) -> list[int]:
        nonlocal at
        if name not in placed:
            blocks.append(block)
            placed[name] = list(range(at, at + block.shape[1]))
            at += block.shape[1]
        return placed[name]

    for c, block in candidates.items():
        r = rivals.get(c)
        base = models[0] + (place(f"rival:{r}", rival_cols[r]) if r else [])
        if base not in models:
            models.append(base)
        models.append(base + place(f"candidate:{c}", block))
        pairs.append((models.index(base), len(models) - 1))
    return blocks, models, pairs


def calibrate_null(
    setup: HeldOutSetup,
    null_columns: np.ndarray,
    candidates: dict[str, np.ndarray],
    alpha: float,
    min_gain: float,
    draws: int,
    seed: int,
    rivals: dict[str, str] | None = None,
    rival_columns: dict[str, np.ndarray] | None = None,
    event_tests_alpha: float = 0.0,
) -> NullCalibration:
    """The null distribution of the selection's maximum statistic (module docstring).

    Parameters
    ----------
    setup : HeldOutSetup
        The calibration's buffered folds and band (:mod:`pipeline.compensate.plus`).
    null_columns : ndarray, shape (n, p)
        The null model's design on every epoch.
    candidates : dict
        Candidate key -> its extra columns (n, q) on every epoch.
    alpha, min_gain : float
        Flight-level false-finding rate, and the least held-out gain worth a term.
    draws : int
        Null draws (at least 2).
    seed : int
        Seed of the phase randomisation.
    rivals, rival_columns : dict, optional
        Candidate key -> the name of its competing explanation, and name -> that
        explanation's columns (n, r) on every epoch: the candidate's statistic is then its
        gain beside the null model and the rival (what it must beat to be named).
    event_tests_alpha : float
        The summed levels of the event tests outside the maximum, which the flight's
        false-finding rate adds (:attr:`NullCalibration.event_tests_alpha`).
    """
    m = setup.meas
    ok = (setup.fold >= 0) & np.isfinite(m.scalar_nT) & np.all(np.isfinite(null_columns), axis=1)
    band = setup.band
    sos = bandpass_sos(band.band_hz, m.rate_hz, band.poles)
    trim = trim_samples(band.trim_s, m.rate_hz)
    kf, _ = bandpass_blocks(null_columns, contiguous_blocks(ok, m.time_s), sos, trim)
    yf, _ = bandpass_blocks(m.scalar_nT, contiguous_blocks(ok, m.time_s), sos, trim)
    theta = ridge_theta(kf, yf, setup.ridge)
    fitted = null_columns @ theta
    names = list(candidates)
    extra, models, pairs = _models(
        null_columns.shape[1], candidates, rivals or {}, rival_columns or {}
    )
    cols = np.column_stack([null_columns, *extra])
    valid = ok & np.all(np.isfinite(cols), axis=1)
    row, keep = _row_of(valid), np.flatnonzero(valid)
    blocks = [row[b] for b in contiguous_blocks(valid, m.time_s)]
    residual = (m.scalar_nT - fitted)[keep]
    noise = surrogates(residual, blocks, draws, np.random.default_rng(seed))
    y = np.column_stack([m.scalar_nT[keep], fitted[keep, None] + noise])
    ss = _fold_sums(setup, cols[keep], y, models, valid)
    # (candidates, 1 + draws): each candidate's gain over its own base model
    gains = np.array([1.0 - np.sqrt(ss[e] / ss[b]) for b, e in pairs]).reshape(-1, 1 + draws)
    top = gains.max(axis=0) if names else np.zeros(1 + draws)
    threshold = monte_carlo_threshold(top[1:], alpha)
    return NullCalibration(
        draws=draws,
        alpha=alpha,
        threshold_gain=threshold,
        gate_gain=max(threshold, min_gain),
        flight_alpha=crossfit_rate(top[1:], alpha, min_gain),
        observed_gain={c: float(gains[i, 0]) for i, c in enumerate(names)},
        p_value=float((1 + np.sum(top[1:] >= top[0])) / (1 + draws)),
        event_tests_alpha=event_tests_alpha,
    )
