"""Data association of anonymous landmark sightings: nearest neighbour and joint compatibility (JCBB).

Inputs are plain arrays so any filter can use them: ``innovations`` (k, m, 2) of k observations
against m candidate landmarks (``z_i - h_j``, angles wrapped), ``prediction_cov`` (2m, 2m), the
joint covariance ``H P H^T`` of the m predicted measurements (with their correlations through the
robot pose, the reason one pose error shifts every prediction alike), and ``measurement_cov``
(k, 2, 2). Pairing i with j has innovation covariance ``S_ij = C_jj + R_i``.

- :func:`nearest_neighbour`: each observation takes its individually nearest landmark within a
  Mahalanobis gate. Cheap, and wrong when the pose is uncertain and landmarks are close: one bad
  pairing then corrupts the map.
- :func:`jcbb`: Neira and Tardos, "Data association in stochastic mapping using the joint
  compatibility test", IEEE T-RA 17(6), 2001. Branch and bound over the observations for the
  hypothesis with the most pairings whose *joint* innovation passes the chi-square test with
  ``2 * pairings`` degrees of freedom (ties: the smallest joint distance), so pairings must agree
  on one pose error. Unpaired observations are new landmarks or clutter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

UNPAIRED = -1


@dataclass(frozen=True)
class Association:
    """Landmark index per observation (``UNPAIRED`` when none), the hypothesis' joint squared
    Mahalanobis distance and, for JCBB, the search nodes visited (``complete`` False when the
    node budget ran out first and the best hypothesis found so far is returned)."""

    pairs: np.ndarray
    joint_d2: float
    nodes: int = 0
    complete: bool = True

    @property
    def paired(self) -> int:
        return int((self.pairs != UNPAIRED).sum())


def individual_d2(innovations: np.ndarray, prediction_cov: np.ndarray, measurement_cov: np.ndarray) -> np.ndarray:
    """(k, m) squared Mahalanobis distance of every observation-landmark pairing."""
    nu = np.asarray(innovations, np.float64)
    k, m = nu.shape[:2]
    if k == 0 or m == 0:
        return np.zeros((k, m))
    c = np.asarray(prediction_cov, np.float64).reshape(m, 2, m, 2)[np.arange(m), :, np.arange(m), :]  # (m, 2, 2)
    s = c[None, :, :, :] + np.asarray(measurement_cov, np.float64)[:, None, :, :]
    return np.einsum("kmi,kmi->km", nu, np.linalg.solve(s, nu[..., None])[..., 0])


def joint_d2(pairs: np.ndarray, innovations: np.ndarray, prediction_cov: np.ndarray,
             measurement_cov: np.ndarray) -> float:
    """Joint squared Mahalanobis distance of a hypothesis (``pairs`` per observation, -1 unpaired)."""
    obs = np.flatnonzero(np.asarray(pairs) != UNPAIRED)
    if len(obs) == 0:
        return 0.0
    lms = np.asarray(pairs)[obs]
    nu = np.asarray(innovations)[obs, lms].reshape(-1)
    cols = (2 * lms[:, None] + np.arange(2)).reshape(-1)
    s = np.asarray(prediction_cov)[np.ix_(cols, cols)].copy()
    for n, i in enumerate(obs):
        s[2 * n:2 * n + 2, 2 * n:2 * n + 2] += measurement_cov[i]
    return float(nu @ np.linalg.solve(s, nu))


def nearest_neighbour(innovations: np.ndarray, prediction_cov: np.ndarray, measurement_cov: np.ndarray,
                      gate_chi2: float = float(chi2.ppf(0.99, 2))) -> Association:
    """Each observation paired with its nearest landmark (Mahalanobis) if within ``gate_chi2``."""
    d2 = individual_d2(innovations, prediction_cov, measurement_cov)
    k = d2.shape[0]
    pairs = np.full(k, UNPAIRED, np.int64)
    if d2.size:
        best = np.argmin(d2, axis=1)
        ok = d2[np.arange(k), best] <= gate_chi2
        pairs[ok] = best[ok]
    return Association(pairs, joint_d2(pairs, innovations, prediction_cov, measurement_cov))


def jcbb(innovations: np.ndarray, prediction_cov: np.ndarray, measurement_cov: np.ndarray,
         gate_chi2: float = float(chi2.ppf(0.99, 2)), confidence: float = 0.99,
         max_nodes: int = 20000) -> Association:
    """The largest jointly compatible hypothesis (Neira and Tardos 2001).

    Parameters
    ----------
    gate_chi2 : individual compatibility gate (2 degrees of freedom) for a pairing to be considered.
    confidence : the joint test accepts ``D^2 <= chi2.ppf(confidence, 2 * pairings)``.
    max_nodes : search budget (nodes of the interpretation tree); the best hypothesis found when
        it runs out is returned with ``complete=False``.
    """
    nu = np.asarray(innovations, np.float64)
    r = np.asarray(measurement_cov, np.float64)
    c = np.asarray(prediction_cov, np.float64)
    k = nu.shape[0]
    d2 = individual_d2(nu, c, r)
    candidates = [list(np.flatnonzero(d2[i] <= gate_chi2)[np.argsort(d2[i][d2[i] <= gate_chi2])]) for i in range(k)]
    limits = {n: float(chi2.ppf(confidence, 2 * n)) for n in range(1, k + 1)}
    best_pairs = np.full(k, UNPAIRED, np.int64)
    best = (0, 0.0)  # (pairings, joint d2) of the best hypothesis so far
    nodes = 0
    pairs = np.full(k, UNPAIRED, np.int64)
    # remaining[i]: how many observations from i on could still be paired at all (for the bound)
    remaining = np.concatenate([np.cumsum([bool(cands) for cands in candidates][::-1])[::-1], [0]])

    def search(i: int, paired: int, used: set[int]) -> None:
        nonlocal best, best_pairs, nodes
        if paired + remaining[i] < best[0] or nodes >= max_nodes:
            return
        if i == k:
            d = joint_d2(pairs, nu, c, r) if paired else 0.0
            if paired > best[0] or (paired == best[0] and d < best[1]):
                best, best_pairs = (paired, d), pairs.copy()
            return
        for j in candidates[i]:
            if j in used:
                continue
            nodes += 1
            pairs[i] = j
            if joint_d2(pairs, nu, c, r) <= limits[paired + 1]:
                used.add(j)
                search(i + 1, paired + 1, used)
                used.discard(j)
            pairs[i] = UNPAIRED
        nodes += 1
        search(i + 1, paired, used)  # observation i unpaired

    search(0, 0, set())
    return Association(best_pairs, best[1], nodes, nodes < max_nodes)
