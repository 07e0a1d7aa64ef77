"""World simulator: ray casting against hand-computed distances, the sensor model, floor plans."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from trundle.logs.errors import UserError
from trundle.tools.sim.world import DEFAULT_WORLD, LaserModel, cast_rays, load_world, parse_world, simulate_scan

# A 4 m x 4 m room centred on the origin, walls listed counter-clockwise from the bottom one.
ROOM = np.array([[-2, -2, 2, -2], [2, -2, 2, 2], [2, 2, -2, 2], [-2, 2, -2, -2]], dtype=float)


def room_world(**extra):
    plan = {"walls": [{"points": [[-2, -2], [2, -2], [2, 2], [-2, 2]], "closed": True}],
            "route": [[0, 0], [1, 0]]}
    plan.update(extra)
    return parse_world(plan)


def test_rays_in_square_room_hit_hand_computed_distances():
    origin = (0.5, -1.0)
    angles = [0.0, math.pi / 2, math.pi, -math.pi / 2, math.pi / 4]
    hits = cast_rays(ROOM, origin, angles)
    # east wall 1.5 m; north 3 m; west 2.5 m; south 1 m; 45 deg meets x = 2 at y = 0.5 after 1.5*sqrt(2) m
    np.testing.assert_allclose(hits.distance, [1.5, 3.0, 2.5, 1.0, 1.5 * math.sqrt(2)], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(hits.segment, [1, 2, 3, 0, 1])
    # along = distance from each wall's first point: east (2, -2) -> y + 2; north (2, 2) -> 2 - x;
    # west (-2, 2) -> 2 - y; south (-2, -2) -> x + 2
    np.testing.assert_allclose(hits.along, [1.0, 1.5, 3.0, 2.5, 2.5], atol=1e-12)


def test_ray_that_meets_nothing_reports_inf_and_minus_one():
    hits = cast_rays(ROOM[:1], (0.0, 0.0), [math.pi / 2, -math.pi / 2, 0.0])
    assert hits.distance[0] == np.inf and hits.segment[0] == -1 and np.isnan(hits.along[0])
    assert hits.distance[1] == pytest.approx(2.0) and hits.segment[1] == 0
    assert hits.distance[2] == np.inf  # parallel to the only wall


def test_max_range_and_per_ray_origins():
    hits = cast_rays(ROOM, np.array([[0.0, 0.0], [1.9, 0.0]]), [0.0, 0.0], max_range=1.0)
    assert hits.distance[0] == np.inf
    assert hits.distance[1] == pytest.approx(0.1)


@settings(max_examples=100, deadline=None)
@given(st.floats(0.0, 0.95), st.floats(-math.pi, math.pi), st.floats(-math.pi, math.pi), st.integers(3, 9))
def test_ray_casting_matches_half_plane_formula_in_convex_polygons(radius, bearing, angle, sides):
    """Inside a regular polygon the exit distance is min over edges facing the ray of
    (d - n.o) / (n.dir) with edge lines n.p = d: an independent formula."""
    corners = (
        np.stack([np.cos(np.arange(sides) * 2 * np.pi / sides), np.sin(np.arange(sides) * 2 * np.pi / sides)], 1) * 2.0
    )
    segments = np.hstack([corners, np.roll(corners, -1, axis=0)])
    mids = (corners + np.roll(corners, -1, axis=0)) / 2
    normals = mids / np.linalg.norm(mids, axis=1, keepdims=True)
    offsets = (normals * mids).sum(1)
    origin = radius * offsets.min() * np.array([math.cos(bearing), math.sin(bearing)])  # strictly inside
    direction = np.array([math.cos(angle), math.sin(angle)])
    facing = normals @ direction
    expected = np.min((offsets - normals @ origin)[facing > 1e-12] / facing[facing > 1e-12])
    assert cast_rays(segments, origin, [angle]).distance[0] == pytest.approx(expected, abs=1e-9)


def test_exact_scan_with_min_range_max_range_and_grazing_beams():
    world = room_world()
    model = LaserModel(beams=4, angle_min=0.0, angle_max=3 * math.pi / 2, range_min=0.5, range_max=2.9,
                       max_incidence_rad=math.radians(80))
    ranges = simulate_scan(world, (1.6, 1.0, 0.0), model)
    # east 0.4 m < range_min -> -inf; north 1.0; west 3.6 > range_max -> +inf; south 3.0 > 2.9 -> +inf
    assert ranges[0] == -np.inf and ranges[1] == pytest.approx(1.0)
    assert ranges[2] == np.inf and ranges[3] == np.inf
    # a beam meeting the east wall 85 deg from its normal returns nothing
    grazing = LaserModel(
        beams=2, angle_min=math.radians(85), angle_max=math.radians(86), max_incidence_rad=math.radians(80)
    )
    assert np.isinf(simulate_scan(world, (-1.9, -1.9, -math.pi / 2), grazing)).all()


def test_noise_and_dropout_follow_the_model():
    world = room_world()
    model = LaserModel(beams=4000, angle_min=-0.3, angle_max=0.3, noise_sigma_m=0.02, dropout=0.25, range_min=0.0)
    exact = simulate_scan(world, (0.0, 0.0, 0.0), model)
    noisy = simulate_scan(world, (0.0, 0.0, 0.0), model, np.random.default_rng(5))
    returned = np.isfinite(noisy)
    assert 0.2 < 1 - returned.mean() < 0.3
    error = noisy[returned] - exact[returned]
    assert abs(error.mean()) < 0.003 and 0.017 < error.std() < 0.023


def test_default_office_has_a_corridor_loop_markers_and_objects():
    world = load_world()
    route_length = np.hypot(*np.diff(world.route, axis=0).T).sum()
    assert route_length >= 50.0
    assert np.allclose(world.route[0], world.route[-1], atol=1.0)
    assert len(world.markers) >= 6 and len(world.objects) >= 3
    assert len({d.marker_id for d in world.markers}) == len(world.markers)
    for decal in world.decals:
        # each decal hangs on a face that looks into free space (at least 1 m in front of it)
        start = np.array([decal.x, decal.y]) + 1e-3 * decal.normal
        assert cast_rays(world.segments, start, [decal.yaw]).distance[0] > 1.0, decal.name
        # its face's segment really contains it
        seg = world.segments[decal.segment]
        (ex, ey), (wx, wy) = seg[2:] - seg[:2], np.array([decal.x, decal.y]) - seg[:2]
        assert abs(ex * wy - ey * wx) < 1e-9
    # marker 3 faces west; a viewer looking east at it has north on the left: top-left is at y + size/2
    np.testing.assert_allclose(world.marker(3).corners()[0], [26.0, 5.25 + 0.125, 0.6 + 0.125])


def test_bad_floor_plans_are_one_line_user_errors(tmp_path):
    plan = json.loads(DEFAULT_WORLD.read_text())
    bad_key = copy.deepcopy(plan)
    bad_key["markers"][0]["sise"] = 0.2
    with pytest.raises(UserError, match="markers\\[0\\]: unknown key 'sise'"):
        parse_world(bad_key)
    floating = copy.deepcopy(plan)
    floating["markers"][0]["x"] = 20.0
    with pytest.raises(UserError, match="not flat on any wall"):
        parse_world(floating)
    path = tmp_path / "broken.json"
    path.write_text("{\"walls\": [")
    with pytest.raises(UserError, match="not valid JSON"):
        load_world(path)
    with pytest.raises(UserError, match="no such floor-plan JSON file"):
        load_world(tmp_path / "missing.json")
    path.write_bytes(bytes(range(256)))
    with pytest.raises(UserError, match="binary data"):
        load_world(path)


@settings(max_examples=100, deadline=None)
@given(st.data())
def test_mutated_floor_plans_load_or_raise_user_error(data):
    plan = json.loads(DEFAULT_WORLD.read_text())
    section = data.draw(st.sampled_from(["walls", "obstacles", "markers", "objects"]))
    item = data.draw(st.integers(0, len(plan[section]) - 1))
    key = data.draw(st.sampled_from(sorted(plan[section][item])))
    value = data.draw(st.one_of(st.none(), st.integers(-5, 300), st.floats(allow_nan=True), st.text(max_size=3),
                                st.lists(st.integers(-3, 3), max_size=3)))
    plan[section][item][key] = value
    try:
        parse_world(plan)
    except UserError as error:
        assert "\n" not in str(error)
