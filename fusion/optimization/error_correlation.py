"""Time-correlated sighting errors: their correlation time from residuals, and the weights it implies.

A sensor that sees one landmark many times a second does not make a fresh error each time: a
camera's range from a barcode's apparent size stays wrong the same way while the view changes
little (measured on MRCLAM robot 1 against Vicon: consecutive sightings of a landmark 0.5-1 s apart
have range errors correlated at 0.9). Counted as independent, such sightings weigh many times what
they know. Modelling each error component as a first-order Gauss-Markov process,
``rho(dt) = exp(-dt / tau)``, a sighting ``dt`` after the previous one of the same landmark adds
about ``(1 - rho) / (1 + rho)`` of an independent sighting's information (the AR(1) effective
sample size), and ``tau`` can be read from the data itself: the correlation of the whitened
residuals of consecutive sightings, against their time apart, after a first fit.
"""

from __future__ import annotations

import numpy as np

MIN_PAIRS = 30        # fewer consecutive pairs than this in a lag bin say nothing about the correlation
LAG_BINS = 8


def previous_gaps(groups: np.ndarray, stamps_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each sighting, the time (s) since the previous sighting of the same group (landmark), inf
    for a first one, and the index of that previous sighting (-1)."""
    groups, stamps = np.asarray(groups), np.asarray(stamps_s, np.float64)
    order = np.lexsort((stamps, groups))
    gaps = np.full(len(groups), np.inf)
    previous = np.full(len(groups), -1, np.int64)
    same = groups[order][1:] == groups[order][:-1]
    gaps[order[1:][same]] = stamps[order][1:][same] - stamps[order][:-1][same]
    previous[order[1:][same]] = order[:-1][same]
    return gaps, previous


def correlation_time(whitened: np.ndarray, groups: np.ndarray, stamps_s: np.ndarray, outlier: float = 3.0,
                     max_tau_s: float = 60.0) -> np.ndarray:
    """Correlation time (s) of each error component (columns of ``whitened``, residuals divided by
    their nominal standard deviation), 0 where the data show none.

    Pairs of consecutive sightings of one group, both within ``outlier`` in every component, are
    binned by their time apart (quantiles, at least ``MIN_PAIRS`` each); per bin the Pearson
    correlation is taken, and ``log rho = -dt / tau`` is fitted through the origin over the bins
    with 0 < rho < 1, weighted by pairs.
    """
    r = np.asarray(whitened, np.float64)
    gaps, previous = previous_gaps(groups, stamps_s)
    pair = np.flatnonzero((previous >= 0) & np.isfinite(gaps) & (gaps > 0))
    pair = pair[(np.abs(r[pair]) <= outlier).all(axis=1) & (np.abs(r[previous[pair]]) <= outlier).all(axis=1)]
    tau = np.zeros(r.shape[1])
    if len(pair) < 2 * MIN_PAIRS:
        return tau
    bins = max(1, min(LAG_BINS, len(pair) // MIN_PAIRS))
    edges = np.quantile(gaps[pair], np.linspace(0.0, 1.0, bins + 1))
    which = np.clip(np.searchsorted(edges, gaps[pair], side="right") - 1, 0, bins - 1)
    for c in range(r.shape[1]):
        lags, logs, weights = [], [], []
        for b in range(bins):
            members = pair[which == b]
            if len(members) < MIN_PAIRS:
                continue
            a, p = r[members, c], r[previous[members], c]
            if a.std() == 0 or p.std() == 0:
                continue
            rho = float(np.corrcoef(a, p)[0, 1])
            if 0.0 < rho < 1.0:
                lags.append(float(np.median(gaps[members])))
                logs.append(np.log(rho))
                weights.append(len(members))
        if lags:
            lag, log_rho, w = np.array(lags), np.array(logs), np.array(weights, np.float64)
            slope = float(np.sum(w * lag * log_rho) / np.sum(w * lag * lag))
            tau[c] = min(-1.0 / slope, max_tau_s) if slope < 0 else 0.0
    return tau


def ar1_weights(gaps_s: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
    """(F, d) information weight of each sighting's components: ``(1 - rho) / (1 + rho)`` with
    ``rho = exp(-gap / tau)`` (1 for a first sighting or a component with ``tau`` 0)."""
    gaps = np.asarray(gaps_s, np.float64)[:, None]
    tau = np.asarray(tau_s, np.float64)[None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(tau > 0, np.exp(-gaps / np.where(tau > 0, tau, 1.0)), 0.0)
    return (1.0 - rho) / (1.0 + rho)


def decorrelated_information(information: np.ndarray, errors: np.ndarray, groups: np.ndarray,
                             stamps_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sightings' nominal information matrices (F, d, d) reweighted for their correlated errors, and
    the correlation time (d,) read from the ``errors`` (F, d) of a first fit, per component."""
    info = np.asarray(information, np.float64)
    sigma = np.sqrt(np.diagonal(np.linalg.inv(info), axis1=1, axis2=2))
    tau = correlation_time(np.asarray(errors, np.float64) / sigma, groups, stamps_s)
    weights = np.sqrt(ar1_weights(previous_gaps(groups, stamps_s)[0], tau))
    return info * weights[:, :, None] * weights[:, None, :], tau
