"""Camera renderer: what cv2.aruco and plain geometry find in the rendered frames."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from trundle.tools.sim.camera_render import CameraPose, CameraRenderer, PinholeCamera, optical_rotation, project
from trundle.tools.sim.world import load_world

# Poses along the office corridors, each looking at one or two markers.
VIEWS = [CameraPose(22.0, 5.25, 0.45, 0.0), CameraPose(10.0, 5.25, 0.45, 0.0),
         CameraPose(24.75, 12.0, 0.45, math.pi / 2), CameraPose(8.0, 14.75, 0.45, math.pi),
         CameraPose(5.25, 7.5, 0.45, -math.pi / 2), CameraPose(24.0, 12.5, 0.45, 1.35)]


@pytest.fixture(scope="module")
def renderer():
    return CameraRenderer(load_world())


def detect(image):
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_6X6_250), params)
    corners, ids, _ = detector.detectMarkers(image)
    return {} if ids is None else {int(i): c.reshape(4, 2) for i, c in zip(ids.ravel(), corners, strict=True)}


@pytest.mark.parametrize("pose", VIEWS)
def test_markers_in_view_are_detected_with_their_id_at_the_projected_corners(renderer, pose):
    """Every marker the renderer says is clearly in view is detected, at its projected corners;
    anything else detected (small, oblique) is a real marker at its projected corners too."""
    image = renderer.render(pose, np.random.default_rng(0))
    found = detect(image)
    expected = {d.marker_id for d, _ in renderer.visible_decals(pose) if d.kind == "marker"}
    assert expected, "each view looks at a marker"
    assert expected <= set(found)
    for marker_id, corners in found.items():
        projected, depth = project(renderer.world.marker(marker_id).corners(), pose, renderer.camera)
        assert (depth > 0).all()
        assert np.abs(corners - projected).max() < (1.0 if marker_id in expected else 2.0), marker_id


def test_marker_pose_from_detection_matches_its_place_in_the_world(renderer):
    """solvePnP (IPPE square) on the detected corners puts the marker where the world file says."""
    world, camera = renderer.world, renderer.camera
    pose = CameraPose(23.5, 5.6, 0.45, -0.15)
    found = detect(renderer.render(pose))
    marker = world.marker(3)
    assert 3 in found
    half = marker.width / 2
    square = np.array([[-half, half, 0], [half, half, 0], [half, -half, 0], [-half, -half, 0]])
    ok, rvec, tvec = cv2.solvePnP(square, found[3], camera.matrix(), np.zeros(5), flags=cv2.SOLVEPNP_IPPE_SQUARE)
    assert ok
    centre = optical_rotation(pose.yaw) @ tvec.ravel() + np.array([pose.x, pose.y, pose.z])
    np.testing.assert_allclose(centre, [marker.x, marker.y, marker.z], atol=0.02)
    normal = optical_rotation(pose.yaw) @ cv2.Rodrigues(rvec)[0][:, 2]  # marker z axis points at the viewer
    assert math.degrees(math.acos(np.clip(normal @ [*marker.normal, 0.0], -1, 1))) < 3.0


def test_wall_foot_and_skirting_are_at_the_hand_computed_rows(renderer):
    """Facing the east wall (x = 26) from 2 m with the camera 0.45 m up, the wall meets the floor
    at row cy + fy * 0.45 / 2 = 357.625 and the 0.1 m skirting starts at cy + fy * 0.35 / 2 = 331.375."""
    world = renderer.world
    image = renderer.render(CameraPose(24.0, 8.75, 0.45, 0.0)).astype(float)
    column = image[:, 320].sum(axis=1)
    floor = sorted(sum(c) for c in world.floor_bgr)
    assert floor[0] <= column[358] <= floor[1] and column[357] < 300
    wall, skirting = np.median(column[250:320]), np.median(column[340:356])
    crossing = np.flatnonzero(column[300:358] < (wall + skirting) / 2)[0] + 300
    assert abs(crossing - 331.375) <= 1.0  # first row past the halfway brightness


def test_an_occluded_marker_is_neither_drawn_nor_expected(renderer):
    # from (10, 4.25) the cabinet (x 13-14, y 4-4.5) hides marker 3 on the east wall; marker 96
    # on the cabinet's west face is straight ahead
    pose = CameraPose(10.0, 4.25, 0.45, 0.0)
    found = detect(renderer.render(pose))
    expected = {d.marker_id for d, _ in renderer.visible_decals(pose) if d.kind == "marker"}
    assert expected == set(found) == {96}
    # from the open corridor both are in view
    pose = CameraPose(10.0, 5.4, 0.45, 0.0)
    assert {96, 3} <= set(detect(renderer.render(pose)))


def test_coloured_object_lands_at_its_projected_centre(renderer):
    pose = CameraPose(22.0, 6.0, 0.45, 0.1)
    image = renderer.render(pose)
    red = renderer.world.objects[0]
    assert red.name == "red square"
    mask = (image[:, :, 2] > 150) & (image[:, :, 1] < 80) & (image[:, :, 0] < 80)
    ys, xs = np.nonzero(mask)
    centre, _ = project(np.array([[red.x, red.y, red.z]]), pose, renderer.camera)
    corners, _ = project(red.corners(), pose, renderer.camera)
    (ax, ay), (bx, by) = corners[2] - corners[0], corners[3] - corners[1]
    area = 0.5 * abs(ax * by - ay * bx)
    assert abs(xs.mean() - centre[0, 0]) < 0.5 and abs(ys.mean() - centre[0, 1]) < 0.5
    assert mask.sum() == pytest.approx(area, rel=0.05)


def test_camera_info_and_scaling():
    camera = PinholeCamera()
    info = camera.camera_info(5, "camera_optical")
    np.testing.assert_array_equal(info.k, camera.matrix())
    assert (info.width, info.height) == (640, 480)
    big = camera.scaled(1280, 960)
    assert big.fx == big.fy == 1050.0 and big.cx == pytest.approx(639.5) and big.cy == pytest.approx(479.5)
    wide = camera.scaled(1280, 720)  # 16:9 crop of the 4:3 sensor: square pixels, same horizontal view
    assert wide.fx == wide.fy == 1050.0 and wide.cy == pytest.approx(359.5)


def test_calibration_file_loads_as_the_same_camera_info(tmp_path):
    from trundle.drivers.camera_info import load_camera_info
    camera = PinholeCamera().scaled(1280, 720)
    path = tmp_path / "camera.yaml"
    path.write_text(camera.calibration_yaml())
    info = load_camera_info(path, "camera_optical")
    assert info == camera.camera_info(0, "camera_optical")


def test_render_rejects_a_camera_outside_the_room_height(renderer):
    with pytest.raises(ValueError):
        renderer.render(CameraPose(10.0, 5.25, 3.0, 0.0))


def test_corners_on_the_edges_are_where_the_marker_is_and_subpix_corners_are_inside(renderer):
    """Seen from 1.2-3.5 m, on markers 40-200 px a side: OpenCV's sub-pixel corners lie inside the
    projected square (the render's mip-map blur rounds the corners, as a lens does), the edge-refined
    corners on it. Truth: the corners projected from the world file."""
    from trundle.perception.markers import MarkerDetector

    offsets: dict[str, list[float]] = {"subpix": [], "edges": []}
    for k in range(60):
        marker = renderer.world.markers[k % len(renderer.world.markers)]
        distance = 1.2 + 2.3 * (k / 59)
        yaw = math.atan2(-marker.normal[1], -marker.normal[0]) + math.radians(25.0 * math.sin(k))
        pose = CameraPose(marker.x - distance * math.cos(yaw), marker.y - distance * math.sin(yaw), 0.45, yaw)
        image = renderer.render(pose)
        projected, _ = project(marker.corners(), pose, renderer.camera)
        side = np.linalg.norm(projected[0] - projected[1])
        for refinement in offsets:
            found = {m.id: m for m in MarkerDetector(renderer.world.aruco_dictionary, refinement).detect(image)}
            if marker.marker_id in found and side >= 40:
                centre = projected.mean(axis=0)
                offsets[refinement].append(
                    float(
                        np.mean(
                            np.linalg.norm(found[marker.marker_id].corners - centre, axis=1)
                            - np.linalg.norm(projected - centre, axis=1)
                        )
                    )
                )
    assert len(offsets["edges"]) >= 30 and len(offsets["subpix"]) == len(offsets["edges"])
    assert np.mean(offsets["subpix"]) < -0.08  # pixels inwards
    assert abs(np.mean(offsets["edges"])) < 0.02
