"""Descriptor matching against hand-computed cases and an independent brute force (scipy cdist)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import cdist

from trundle.perception.matching import match, match_descriptors, nearest_neighbours, resolve_metric


def test_hand_computed_l2_l1_and_filters() -> None:
    d1 = np.array([[0.0, 0.0], [10.0, 0.0], [5.0, 5.0]], dtype=np.float32)
    d2 = np.array([[1.0, 0.0], [10.0, 2.0], [5.0, 4.0], [5.0, 6.5]], dtype=np.float32)
    # L2 nearest: 0 -> 0 (1.0; next 5.0 to [5,4]... sqrt(41)); 1 -> 1 (2.0); 2 -> 2 (1.0; next 1.5)
    found = match(d1, d2, "l2", cross_check=False)
    assert found.pairs.tolist() == [[0, 0], [1, 1], [2, 2]]
    assert found.distances == pytest.approx([1.0, 2.0, 1.0])
    index, distance = nearest_neighbours(d1, d2, "l2")
    assert distance[2] == pytest.approx([1.0, 1.5])
    # ratio 1.0/1.5 = 0.67 for row 2: rejected at 0.6, kept at 0.7
    assert match(d1, d2, "l2", cross_check=False, max_ratio=0.6).pairs[:, 0].tolist() == [0, 1]
    assert match(d1, d2, "l2", cross_check=False, max_ratio=0.7).pairs[:, 0].tolist() == [0, 1, 2]
    # difference 1.5 - 1.0 = 0.5 for row 2
    assert match(d1, d2, "l2", cross_check=False, min_difference=0.6).pairs[:, 0].tolist() == [0, 1]
    assert match(d1, d2, "l2", cross_check=False, max_distance=1.5).pairs[:, 0].tolist() == [0, 2]
    # L1: row 1 -> [10, 2] at 2, row 2 -> [5, 4] at 1
    assert match(d1, d2, "l1", cross_check=False).distances == pytest.approx([1.0, 2.0, 1.0])
    counts = match(d1, d2, "l2", max_ratio=0.7, min_difference=0.6, max_distance=1.5).counts
    assert counts == {"nearest": 3, "max_distance": 2, "ratio": 2, "difference": 1, "cross_check": 1}


def test_hamming_on_packed_bits_and_booleans() -> None:
    d1 = np.array([[0b00000000, 0xFF], [0b10101010, 0x00]], dtype=np.uint8)
    d2 = np.array([[0b00000001, 0xFF], [0b10101011, 0x0F]], dtype=np.uint8)
    found = match(d1, d2)
    assert resolve_metric(d1, None) == "hamming"
    assert found.pairs.tolist() == [[0, 0], [1, 1]] and found.distances.tolist() == [1.0, 5.0]
    bits = np.unpackbits(d1, axis=1).astype(bool)
    assert match(bits, np.unpackbits(d2, axis=1).astype(bool)).distances.tolist() == [1.0, 5.0]


def test_cross_check_keeps_mutual_nearest_only() -> None:
    d1 = np.array([[0.0], [0.4]], dtype=np.float32)
    d2 = np.array([[0.3], [5.0]], dtype=np.float32)
    # both rows of d1 pick d2[0]; d2[0] picks d1[1]: only (1, 0) is mutual
    assert match_descriptors(d1, d2, cross_check=True).tolist() == [[1, 0]]
    assert match_descriptors(d1, d2, cross_check=False).tolist() == [[0, 0], [1, 0]]


def test_edge_cases() -> None:
    empty = np.empty((0, 4), np.float32)
    some = np.ones((3, 4), np.float32)
    assert match_descriptors(empty, some).shape == (0, 2)
    assert match_descriptors(some, empty).shape == (0, 2)
    one = match(some[:1], some[:1] * 2, "l2", max_ratio=0.5)     # no second neighbour: ratio passes
    assert one.pairs.tolist() == [[0, 0]]
    with pytest.raises(ValueError):
        match(some, some, "cosine")


def _reference(d1: np.ndarray, d2: np.ndarray, metric: str, cross_check: bool, max_ratio: float,
               min_difference: float, max_distance: float) -> np.ndarray:
    name = {"l2": "euclidean", "l1": "cityblock", "hamming": "hamming"}[metric]
    if metric == "hamming":
        dist = cdist(np.unpackbits(d1, axis=1), np.unpackbits(d2, axis=1), name) * d1.shape[1] * 8
    else:
        dist = cdist(d1.astype(np.float64), d2.astype(np.float64), name)
    order = np.argsort(dist, axis=1, kind="stable")
    best = dist[np.arange(len(d1)), order[:, 0]]
    second = dist[np.arange(len(d1)), order[:, 1]] if d2.shape[0] > 1 else np.full(len(d1), math.inf)
    keep = (best <= max_distance) & ~(best > max_ratio * second) & ~(second - best < min_difference)
    if cross_check:
        back = np.argmin(dist, axis=0)
        keep &= back[order[:, 0]] == np.arange(len(d1))
    rows = np.flatnonzero(keep)
    return np.column_stack([rows, order[rows, 0]])


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(["l2", "l1", "hamming"]), st.integers(1, 40), st.integers(2, 40), st.booleans(),
       st.sampled_from([1.0, 0.9, 0.7]), st.sampled_from([0.0, 0.05, 3.0]), st.sampled_from([math.inf, 1.0, 60.0]),
       st.integers(0, 2**32 - 1))
def test_matches_an_independent_brute_force(metric: str, n1: int, n2: int, cross_check: bool, max_ratio: float,
                                            min_difference: float, max_distance: float, seed: int) -> None:
    rng = np.random.default_rng(seed)
    if metric == "hamming":
        d1 = rng.integers(0, 256, (n1, 32), dtype=np.uint8)
        d2 = rng.integers(0, 256, (n2, 32), dtype=np.uint8)
        # integer distances tie often: the reference and OpenCV may break ties differently
        dist = cdist(np.unpackbits(d1, axis=1), np.unpackbits(d2, axis=1), "hamming")
        if any(len(np.unique(row)) < len(row) for row in np.sort(dist, axis=1)[:, :2]) or \
                any(np.sum(col == col.min()) > 1 for col in dist.T):
            return
    else:
        d1 = rng.random((n1, 6), dtype=np.float32)
        d2 = rng.random((n2, 6), dtype=np.float32)
    expected = _reference(d1, d2, metric, cross_check, max_ratio, min_difference, max_distance)
    got = match_descriptors(d1, d2, metric, cross_check, max_distance, max_ratio, min_difference)
    assert got.tolist() == expected.tolist()


def test_flann_finds_the_exact_neighbours_on_separated_data() -> None:
    rng = np.random.default_rng(9)
    d2 = rng.random((300, 16), dtype=np.float32) * 10
    d1 = d2[::3] + rng.normal(0, 0.01, (100, 16)).astype(np.float32)
    pairs = match_descriptors(d1, d2, "l2", flann=True)
    assert len(pairs) >= 95 and (pairs[:, 1] == pairs[:, 0] * 3).all()
    binary = rng.integers(0, 256, (200, 32), dtype=np.uint8)
    flipped = binary.copy()
    flipped[:, 0] ^= 1
    pairs = match_descriptors(flipped, binary, flann=True)
    assert len(pairs) >= 150 and (pairs[:, 0] == pairs[:, 1]).all()
