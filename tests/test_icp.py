"""Point-to-line ICP: exact recovery, scan-to-scan on the polygon world, normals, degeneracy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.planar_world import CORRIDOR, ROOM, scan
from trundle.fusion.geometry import inverse, relative, scan_to_points, transform_points, wrap_angle
from trundle.fusion.matching.icp import LineReference, icp


def test_exact_copy_is_recovered_exactly() -> None:
    reference = scan_to_points(scan(ROOM, np.array([0.0, 0.0, 0.0]), beams=360))
    truth = np.array([0.12, -0.08, math.radians(4.0)])
    moving = transform_points(inverse(truth), reference)  # the same points seen from pose `truth`
    result = icp(reference, moving, np.zeros(3))
    np.testing.assert_allclose(result.pose, truth, atol=1e-6)
    assert result.converged and result.inlier_fraction == 1.0 and result.residual_m < 1e-6


def test_normals_of_a_straight_wall_are_exact() -> None:
    x = np.linspace(0, 2, 41)
    wall = np.column_stack([x, 0.5 * x + 1.0])
    ref = LineReference(wall)
    expected = np.array([-0.5, 1.0]) / math.hypot(0.5, 1.0)
    np.testing.assert_allclose(np.abs(ref.normals @ expected), 1.0, atol=1e-9)
    assert np.all(ref.flatness > 0.999) and ref.is_line.all()


@pytest.mark.parametrize("step", [(0.3, 0.1, 5.0), (-0.2, 0.25, -8.0)])
def test_scan_to_scan_with_different_beam_sampling(step: tuple[float, float, float]) -> None:
    a = np.array([-0.5, 0.2, 0.4])
    b = a + np.array([step[0], step[1], math.radians(step[2])])
    reference = scan_to_points(scan(ROOM, a, beams=720, noise_m=0.005, seed=1))
    moving = scan_to_points(scan(ROOM, b, beams=360, noise_m=0.005, seed=2))
    truth = relative(a, b)
    result = icp(reference, moving, np.zeros(3))
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 0.01
    assert abs(wrap_angle(result.pose[2] - truth[2])) < math.radians(0.2)
    assert result.inlier_fraction > 0.9 and result.residual_m < 0.01


def test_corridor_axis_is_unconstrained() -> None:
    reference = scan_to_points(scan(CORRIDOR, np.zeros(3), beams=360, max_range=6.0))
    moving = scan_to_points(scan(CORRIDOR, np.array([0.0, 0.1, 0.0]), beams=360, max_range=6.0))
    result = icp(reference, moving, np.zeros(3))
    std = np.sqrt(np.diag(result.covariance))
    assert std[0] > 10 * std[1]
    assert result.pose[1] == pytest.approx(0.1, abs=0.01)
