"""Prewhitening of a regression whose errors are autocorrelated, block by block.

The audit's scans for steps (inside calibration legs, :mod:`pipeline.audit.calibration_events`;
against the fluxgate over a whole flight, :mod:`pipeline.audit.vector_reference`) regress 1 s
means whose residual is strongly autocorrelated (manoeuvres, turns, unmodelled interference
last seconds). Both fit an AR model to the no-step residual by least squares on its own lags
and filter the data and every column with it (Cochrane-Orcutt), separately in each contiguous
block (a leg, a stretch between gaps), dropping each block's first ``order`` rows.

Hand-written: statsmodels' GLSAR whitens one series as a whole; here blocks are separate
records whose first rows have no past.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def _block_bounds(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start and end (exclusive) rows of each run of equal ``block`` labels."""
    starts = np.flatnonzero(np.r_[True, np.diff(block) != 0])
    return starts, np.r_[starts[1:], block.size]


def ar_coefficients(resid: np.ndarray, block: np.ndarray, order: int) -> np.ndarray:
    """AR(``order``) coefficients of ``resid`` by least squares on its lags within blocks.

    Parameters
    ----------
    resid : ndarray, shape (n,)
        Residual of the model without the effect tested.
    block : ndarray of int, shape (n,)
        Block label of each row; rows of one block are contiguous.
    order : int
        AR order.

    Returns
    -------
    ndarray, shape (order,)
        phi, with ``e_k = sum_j phi_j e_{k-1-j} + w_k``.
    """
    lagged, target = [], []
    for a, b in zip(*_block_bounds(block), strict=True):
        r = resid[a:b]
        if r.size <= order:
            continue
        target.append(r[order:])
        lagged.append(np.column_stack([r[order - 1 - j : r.size - 1 - j] for j in range(order)]))
    phi, *_ = np.linalg.lstsq(np.vstack(lagged), np.concatenate(target), rcond=None)
    return phi


def kept_rows(block: np.ndarray, order: int) -> np.ndarray:
    """The rows :func:`ar_whitener`'s filter of that ``order`` keeps, in its output's order
    (each block's rows after its first ``order``; blocks no longer than that left out)."""
    starts, ends = _block_bounds(block)
    return np.concatenate(
        [np.arange(a + order, b) for a, b in zip(starts, ends, strict=True) if b - a > order]
        or [np.zeros(0, int)]
    )


def ar_whitener(phi: np.ndarray, block: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """The Cochrane-Orcutt filter with coefficients ``phi`` within each block of ``block``
    (the first ``len(phi)`` rows of each block dropped, blocks no longer than that left
    out): a function of an (n,) or (n, k) array."""
    p = phi.size
    bounds = list(zip(*_block_bounds(block), strict=True))

    def whiten(x: np.ndarray) -> np.ndarray:
        out = []
        for a, b in bounds:
            xi = x[a:b]
            if xi.shape[0] <= p:
                continue
            w = xi[p:].copy()
            for j in range(p):
                w = w - phi[j] * xi[p - 1 - j : xi.shape[0] - 1 - j]
            out.append(w)
        return np.concatenate(out)

    return whiten
