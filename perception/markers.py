"""ArUco markers: detection with ids and sub-pixel corners, and each marker's pose.

Detection is OpenCV's ``cv2.aruco.ArucoDetector``, its corners then refined on the marker's edges
(:func:`refine_on_edges`); the pose is ``cv2.solvePnPGeneric`` with
``SOLVEPNP_IPPE_SQUARE`` (refined) from the camera's CameraInfo and the marker's side length. Corners
are in pixels, in OpenCV's order: top-left, top-right, bottom-right, bottom-left of the marker
as printed. Poses are in the camera's optical frame (x right, y down, z forward; metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from trundle.logs.errors import UserError
from trundle.logs.messages import CameraInfo

FALLBACK_PX = 1.0   # RMS reprojection error above which IPPE is deemed to have failed
CORNER_REFINEMENT = {"none": cv2.aruco.CORNER_REFINE_NONE, "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
                     "contour": cv2.aruco.CORNER_REFINE_CONTOUR, "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
                     "edges": cv2.aruco.CORNER_REFINE_SUBPIX}  # sub-pixel corners, then refine_on_edges
EDGE_SPAN = (0.15, 0.85)  # share of each side sampled for its edge: corners' blur left out
MIN_CONTRAST = 20.0       # grey levels between a profile's black and white ends, else the profile is skipped


def refine_on_edges(grey: np.ndarray, corners: np.ndarray, bits: int) -> np.ndarray:
    """Corners (4, 2) as the intersections of lines fitted to the marker's four outer edges.

    A corner finder on a blurred convex corner (any real lens, or a mip-mapped render) puts the corner
    inside the black square, by 0.1-0.3 px on a 30-90 px marker, so PnP sees the marker smaller and
    farther than it is (0.3-0.9 % of the range, measured on rendered markers). A straight edge under
    a symmetric blur keeps its edge where it is: across each side, away from its corners, the
    profile from the black border (0.6 of its module inside: ``bits`` modules span the marker across
    the side, foreshortening included) to the white paper
    (outside) is sampled and the edge found from the area under it; a line through those edge
    points per side, and the four lines intersected. ``corners`` are returned unchanged when a side has too few
    usable profiles (low contrast, clipped by the image edge).
    """
    corners = np.asarray(corners, np.float64).reshape(4, 2)
    image = np.asarray(grey, np.float32)
    centre = corners.mean(axis=0)
    lines = []
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        length = float(np.linalg.norm(b - a))
        if length < 3 * bits:
            return corners
        along = (b - a) / length
        normal = np.array([along[1], -along[0]])
        if normal @ ((a + b) / 2 - centre) < 0:
            normal = -normal  # outwards, from the black border to the paper
        opposite = (corners[(i + 2) % 4] + corners[(i + 3) % 4]) / 2
        reach = 0.6 * abs(float((opposite - a) @ normal)) / bits  # within the border module across this side
        offsets = np.linspace(-reach, reach, max(9, int(np.ceil(4 * reach)) | 1))
        spots = a + np.linspace(*EDGE_SPAN, max(5, int(length * (EDGE_SPAN[1] - EDGE_SPAN[0]))))[:, None] * (b - a)
        samples = spots[:, None, :] + offsets[None, :, None] * normal
        profile = cv2.remap(image, samples[..., 0].astype(np.float32), samples[..., 1].astype(np.float32),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        quarter = max(1, len(offsets) // 4)
        dark, light = profile[:, :quarter].mean(axis=1), profile[:, -quarter:].mean(axis=1)
        ok = np.isfinite(profile).all(axis=1) & (light - dark >= MIN_CONTRAST)
        # A step from 0 to 1 at u_e integrates to (u_max - u_e) over the profile: the edge from the area
        # under the normalised profile, exact for any symmetric blur and for area-sampled pixels
        # (the half-way crossing of interpolated pixels is not: up to 0.1 px off on a sharp edge).
        rising = (profile[ok] - dark[ok, None]) / (light - dark)[ok, None]
        spread = 0.5 * (rising[:, 1:] + rising[:, :-1]) * np.diff(offsets)[None, :]
        edge = offsets[-1] - spread.sum(axis=1)
        points = spots[ok] + edge[:, None] * normal
        if len(points) < 5:
            return corners
        vx, vy, x0, y0 = cv2.fitLine(np.array(points, np.float32), cv2.DIST_L2, 0, 0.01, 0.01).ravel()
        lines.append((np.array([x0, y0], np.float64), np.array([vx, vy], np.float64)))
    refined = np.empty((4, 2))
    for i in range(4):  # corner i lies on side i-1 (from corner i-1) and side i (to corner i+1)
        (p, u), (q, v) = lines[i - 1], lines[i]
        cross = u[0] * v[1] - u[1] * v[0]
        if abs(cross) < 1e-6:
            return corners
        t = ((q[0] - p[0]) * v[1] - (q[1] - p[1]) * v[0]) / cross
        refined[i] = p + t * u
    if np.abs(refined - corners).max() > 2.0:  # not the edges of this marker: keep the detector's corners
        return corners
    return refined


def dictionary_by_name(name: str) -> cv2.aruco.Dictionary:
    """A predefined dictionary by name, e.g. ``DICT_6X6_250``, ``6X6_250`` or ``APRILTAG_36h11``."""
    known = {n.upper(): n for n in dir(cv2.aruco) if n.startswith("DICT_")}
    key = name.strip().upper()
    key = key if key.startswith("DICT_") else "DICT_" + key
    if key not in known:
        raise UserError(f"unknown ArUco dictionary {name!r} (known: {', '.join(sorted(known.values()))})")
    return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, known[key]))


@dataclass(frozen=True, eq=False)
class Marker:
    """One detected marker: its id and (4, 2) corners in pixels (TL, TR, BR, BL)."""

    id: int
    corners: np.ndarray

    @property
    def centre(self) -> tuple[float, float]:
        """Intersection of the diagonals (the projected marker centre), in pixels."""
        p = self.corners
        d1, d2 = p[2] - p[0], p[3] - p[1]
        s = np.linalg.solve(np.column_stack([d1, -d2]), p[1] - p[0])[0]
        x, y = p[0] + s * d1
        return float(x), float(y)


@dataclass(frozen=True, eq=False)
class MarkerPose:
    """Pose of a marker in the camera optical frame: rotation (3x3) and translation (m).

    ``rvec`` is the same rotation as a Rodrigues vector; ``error`` the RMS reprojection error
    of the four corners in pixels.
    """

    id: int
    rotation: np.ndarray
    translation: np.ndarray
    rvec: np.ndarray
    error: float

    def quaternion(self) -> np.ndarray:
        """The rotation as a unit quaternion (x, y, z, w), as ROS orders it."""
        return Rotation.from_matrix(self.rotation).as_quat()


def resolvable(corners: np.ndarray, cells: int) -> bool:
    """True when every side of the quad ``corners`` (4, 2) spans at least one pixel per cell of a
    marker ``cells`` wide (bits plus border). A narrower candidate cannot show its bits: OpenCV
    still reads a code from it, and a noisy JPEG frame gave a valid id of a marker that was not in
    the image (7 x 22 px for a 6x6 marker's 8 cells)."""
    sides = np.hypot(*(np.roll(corners, -1, axis=0) - corners).T)
    return bool(sides.min() >= cells)


class MarkerDetector:
    """An ArUco detector for one dictionary (it keeps OpenCV's detector object between frames).

    dictionary: predefined dictionary name. refinement: corner refinement, "edges" (default:
    sub-pixel corners refined on the marker's edges, :func:`refine_on_edges`), "subpix" (OpenCV's
    sub-pixel corners), "none" (contour vertices), "contour" or "apriltag". Further keyword
    arguments set ``cv2.aruco.DetectorParameters`` attributes by name.
    """

    def __init__(self, dictionary: str = "DICT_6X6_250", refinement: str = "edges", **parameters: float) -> None:
        if refinement not in CORNER_REFINEMENT:
            raise UserError(f"unknown corner refinement {refinement!r} (choose {', '.join(CORNER_REFINEMENT)})")
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = CORNER_REFINEMENT[refinement]
        for name, value in parameters.items():
            if not hasattr(params, name):
                raise UserError(f"unknown ArUco detector parameter {name!r}")
            setattr(params, name, value)
        self.dictionary_name = dictionary
        self.refinement = refinement
        self._bits = dictionary_by_name(dictionary).markerSize + 2
        self._detector = cv2.aruco.ArucoDetector(dictionary_by_name(dictionary), params)

    def detect(self, image: np.ndarray) -> list[Marker]:
        """Markers in a grey or BGR uint8 image, ordered by id."""
        corners, ids, _ = self._detector.detectMarkers(image)
        if ids is None:
            return []
        found = [
            Marker(int(i), np.asarray(c, dtype=np.float64).reshape(4, 2))
            for i, c in zip(ids.ravel(), corners, strict=True)
        ]
        found = [f for f in found if resolvable(f.corners, self._bits)]
        if self.refinement == "edges":
            grey = (image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)).astype(np.float32)
            found = [Marker(f.id, refine_on_edges(grey, f.corners, self._bits)) for f in found]
        return sorted(found, key=lambda m: m.id)


def marker_object_points(size: float) -> np.ndarray:
    """The marker's corners in its own frame (z out of the marker, x right, y up), metres.

    Order TL, TR, BR, BL as ``SOLVEPNP_IPPE_SQUARE`` requires.
    """
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def marker_pose(marker: Marker, camera: CameraInfo, size: float) -> MarkerPose:
    """Pose of a detected marker of side ``size`` metres seen by the calibrated ``camera``.

    Uses K and the plumb-bob/rational distortion D of the CameraInfo. Both IPPE solutions and
    their Gauss-Newton (virtual visual servoing) refinements are candidates, and when none
    reprojects within ``FALLBACK_PX`` the SQPnP solution and its refinement too; the smallest
    RMS reprojection error wins. Measured on rendered markers: OpenCV's IPPE closed form alone
    errs by degrees near fronto-parallel views (2.8 deg with 0.1 px corner error) and returns
    the identity rotation (60 px reprojection error) for a marker centred on the optical axis
    facing the camera.
    """
    if size <= 0:
        raise ValueError("marker size must be positive")
    points = marker_object_points(size)

    def rms(rvec: np.ndarray, tvec: np.ndarray) -> float:
        projected, _ = cv2.projectPoints(points, rvec, tvec, camera.k, camera.d)
        return float(np.sqrt(((projected.reshape(4, 2) - marker.corners) ** 2).sum(axis=1).mean()))

    def refined(candidates: list[tuple[np.ndarray, np.ndarray]]) -> list[tuple[float, np.ndarray, np.ndarray]]:
        out = []
        for rvec, tvec in candidates:
            out.append((rms(rvec, tvec), rvec, tvec))
            rvec, tvec = cv2.solvePnPRefineVVS(points, marker.corners, camera.k, camera.d, rvec.copy(), tvec.copy())
            out.append((rms(rvec, tvec), rvec, tvec))
        return out

    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(points, marker.corners, camera.k, camera.d,
                                                 flags=cv2.SOLVEPNP_IPPE_SQUARE)
    scored = refined(list(zip(rvecs, tvecs, strict=True))) if count else []
    if not scored or min(c[0] for c in scored) > FALLBACK_PX:
        ok, rvec, tvec = cv2.solvePnP(points, marker.corners, camera.k, camera.d, flags=cv2.SOLVEPNP_SQPNP)
        scored += refined([(rvec, tvec)]) if ok else []
    if not scored:
        raise ValueError(f"no pose for marker {marker.id}")
    error, rvec, tvec = min(scored, key=lambda c: c[0])
    return MarkerPose(marker.id, cv2.Rodrigues(rvec)[0], tvec.ravel(), rvec.ravel(), error)
