"""EKF-SLAM: the robot pose and every landmark in one state, one covariance (features as states).

State ``(x, y, theta, l1x, l1y, l2x, l2y, ...)`` in the map frame (metres, radians) with its full
covariance, so a re-sighted landmark corrects the pose and, through their correlations, every
other landmark (the feature-map SLAM of Smith, Self and Cheeseman; Thrun, Burgard and Fox,
"Probabilistic Robotics", ch. 10). The map frame is the robot's pose at the start.

- :meth:`EkfSlam.predict` moves the pose by an odometry increment (robot frame) with its covariance
  (:class:`trundle.fusion.odometry.motion_model.IncrementAccumulator` composes many readings into one);
  only the pose rows and columns change, O(n).
- :meth:`EkfSlam.update` takes one instant's :class:`trundle.logs.messages.LandmarkObservation` s
  (range, bearing and their covariance in the robot frame). A sighting with an id goes to that
  landmark, a first sighting of an id augments the state (landmark placed by the inverse
  range-bearing model, its covariance and cross-covariances from both Jacobians); a sighting
  farther than ``outlier_chi2`` (Mahalanobis) from its landmark is rejected as an outlier. An
  anonymous sighting is associated with the anonymous landmarks by JCBB (default) or nearest
  neighbour (:mod:`trundle.fusion.slam.data_association`); one left unpaired becomes a new landmark
  only when it is far (``new_landmark_chi2``) from every landmark, else it is dropped as
  ambiguous. All pairings of an instant update the state together, O(n^2).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2

from trundle.fusion.geometry import wrap_angle
from trundle.fusion.observation_models import point_from_range_bearing, range_bearing
from trundle.fusion.odometry.increments import MotionNoise, compose_jacobians
from trundle.fusion.slam.data_association import UNPAIRED, Association, jcbb, nearest_neighbour
from trundle.logs.messages import LandmarkObservation

ASSOCIATIONS = ("jcbb", "nn")


@dataclass
class EkfSlamConfig:
    """Parameters of :class:`EkfSlam` (chi-square values are squared Mahalanobis distances, 2 dof)."""

    motion: MotionNoise = field(default_factory=MotionNoise)
    association: str = "jcbb"
    gate_chi2: float = float(chi2.ppf(0.99, 2))
    joint_confidence: float = 0.99
    new_landmark_chi2: float = float(chi2.ppf(0.9999, 2))
    outlier_chi2: float = float(chi2.ppf(0.999, 2))
    max_association_nodes: int = 20000
    iterations: int = 1

    def __post_init__(self) -> None:
        if self.association not in ASSOCIATIONS:
            raise ValueError(f"association must be one of {ASSOCIATIONS}, got {self.association!r}")


@dataclass
class EkfSlamStats:
    """Counts over the run: predictions, updates (instants), sightings used, landmarks added,
    known-id outliers rejected, anonymous sightings paired, made new, and dropped as ambiguous."""

    predictions: int = 0
    updates: int = 0
    used: int = 0
    added: int = 0
    outliers: int = 0
    paired: int = 0
    ambiguous: int = 0
    incomplete_associations: int = 0


@dataclass(frozen=True)
class UpdateReport:
    """What one :meth:`EkfSlam.update` did: landmark index per observation (-1 unused), which were
    new, which rejected, and the anonymous association."""

    landmark: np.ndarray
    added: np.ndarray
    rejected: np.ndarray
    association: Association | None


class EkfSlam:
    """The EKF-SLAM state; see the module docstring. ``pose`` and ``pose_covariance`` start it."""

    def __init__(self, config: EkfSlamConfig | None = None, pose=(0.0, 0.0, 0.0), pose_covariance=None) -> None:
        self.config = config or EkfSlamConfig()
        self._x = np.zeros(3 + 2 * 16)
        self._p = np.zeros((len(self._x), len(self._x)))
        self._n = 3
        self._x[:3] = np.asarray(pose, np.float64).reshape(3)
        if pose_covariance is not None:
            self._p[:3, :3] = np.asarray(pose_covariance, np.float64).reshape(3, 3)
        self.ids: list[str] = []
        self._anonymous: list[bool] = []
        self._index: dict[str, int] = {}
        self.stats = EkfSlamStats()

    # --- state ---------------------------------------------------------------------------------
    @property
    def size(self) -> int:
        """Length of the state vector, 3 + 2 * landmarks."""
        return self._n

    @property
    def mean(self) -> np.ndarray:
        return self._x[: self._n].copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._p[: self._n, : self._n].copy()

    @property
    def pose(self) -> np.ndarray:
        return self._x[:3].copy()

    @property
    def pose_covariance(self) -> np.ndarray:
        return self._p[:3, :3].copy()

    def landmarks(self) -> tuple[list[str], np.ndarray, np.ndarray]:
        """Ids, positions (m, 2) and marginal covariances (m, 2, 2) of the mapped landmarks."""
        m = len(self.ids)
        positions = self._x[3: self._n].reshape(m, 2).copy()
        idx = 3 + 2 * np.arange(m)
        covariances = np.stack([self._p[i:i + 2, i:i + 2] for i in idx]) if m else np.zeros((0, 2, 2))
        return list(self.ids), positions, covariances

    def index_of(self, landmark_id: str) -> int | None:
        """The landmark number of an id (None if not mapped)."""
        return self._index.get(landmark_id)

    # --- predict -------------------------------------------------------------------------------
    def predict(self, delta_xyt, covariance) -> None:
        """Move the pose by ``delta_xyt`` (robot frame at the motion's start) with its 3x3 covariance."""
        u = np.asarray(delta_xyt, np.float64).reshape(3)
        ja, jb = compose_jacobians(self._x[:3], u)
        c, s = np.cos(self._x[2]), np.sin(self._x[2])
        self._x[:3] = (self._x[0] + c * u[0] - s * u[1], self._x[1] + s * u[0] + c * u[1],
                       wrap_angle(float(self._x[2] + u[2])))
        n = self._n
        p = self._p
        p[:3, :3] = ja @ p[:3, :3] @ ja.T + jb @ np.asarray(covariance, np.float64).reshape(3, 3) @ jb.T
        if n > 3:
            p[:3, 3:n] = ja @ p[:3, 3:n]
            p[3:n, :3] = p[:3, 3:n].T
        self.stats.predictions += 1

    # --- update --------------------------------------------------------------------------------
    def update(self, observations: Sequence[LandmarkObservation]) -> UpdateReport:
        """Fuse one instant's sightings; returns what became of each (see :class:`UpdateReport`)."""
        k = len(observations)
        landmark = np.full(k, UNPAIRED, np.int64)
        added = np.zeros(k, bool)
        rejected = np.zeros(k, bool)
        self.stats.updates += 1
        if k == 0:
            return UpdateReport(landmark, added, rejected, None)
        z = np.array([[o.range, o.bearing] for o in observations])
        r = np.array([o.covariance for o in observations])
        known = np.array([bool(o.id) for o in observations])
        new_known: list[int] = []
        for i in np.flatnonzero(known).tolist():
            j = self._index.get(observations[i].id)
            if j is None:
                new_known.append(int(i))
            else:
                landmark[i] = j
        # a known-id sighting far from its landmark is an outlier
        chosen = np.flatnonzero(landmark >= 0)
        if len(chosen):
            nu, s = self._innovations(z[chosen], r[chosen], landmark[chosen])
            d2 = np.einsum("ki,ki->k", nu, np.linalg.solve(s, nu[..., None])[..., 0])
            bad = chosen[d2 > self.config.outlier_chi2]
            landmark[bad], rejected[bad] = UNPAIRED, True
            self.stats.outliers += len(bad)
        association = None
        new_anonymous: list[int] = []
        anonymous = np.flatnonzero(~known)
        if len(anonymous):
            association, new_anonymous = self._associate(z[anonymous], r[anonymous])
            paired = association.pairs != UNPAIRED
            landmark[anonymous[paired]] = association.pairs[paired]
            new_anonymous = [int(anonymous[i]) for i in new_anonymous]
            self.stats.paired += int(paired.sum())
            self.stats.ambiguous += int((~paired).sum()) - len(new_anonymous)
            self.stats.incomplete_associations += int(not association.complete)
        use = np.flatnonzero(landmark >= 0)
        if len(use):
            self._correct(z[use], r[use], landmark[use])
            self.stats.used += len(use)
        for i in new_known + new_anonymous:
            landmark[i] = self._augment(observations[i].id, z[i], r[i])
            added[i] = True
        return UpdateReport(landmark, added, rejected, association)

    def _predicted(self, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predicted (range, bearing) (p, 2), Jacobians by the pose (p, 2, 3) and by the landmark (p, 2, 2),
        and the landmarks' state offsets (p,)."""
        offsets = 3 + 2 * np.asarray(landmarks, np.int64)
        points = np.stack([self._x[offsets], self._x[offsets + 1]], axis=1)
        h, h_pose, h_point = range_bearing(np.broadcast_to(self._x[:3], (len(offsets), 3)), points)
        return h, h_pose, h_point, offsets

    def _innovations(self, z: np.ndarray, r: np.ndarray, landmarks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Innovations (p, 2) and their marginal covariances (p, 2, 2) of pairings with ``landmarks``."""
        h, hx, hl, off = self._predicted(landmarks)
        nu = z - h
        nu[:, 1] = wrap_angle(nu[:, 1])
        p = self._p
        pxx = p[:3, :3]
        pxl = np.stack([p[:3, o:o + 2] for o in off])          # (p, 3, 2)
        pll = np.stack([p[o:o + 2, o:o + 2] for o in off])     # (p, 2, 2)
        cross = hx @ pxl @ hl.transpose(0, 2, 1)
        s = hx @ pxx @ hx.transpose(0, 2, 1) + cross + cross.transpose(0, 2, 1) + hl @ pll @ hl.transpose(0, 2, 1) + r
        return nu, s

    def _associate(self, z: np.ndarray, r: np.ndarray) -> tuple[Association, list[int]]:
        """JCBB (or nearest neighbour) of anonymous sightings against the anonymous landmarks, and
        the sightings (indices into ``z``) far enough from every landmark to start a new one."""
        cfg = self.config
        k = len(z)
        pool = np.flatnonzero(self._anonymous)
        if len(pool) == 0:
            return Association(np.full(k, UNPAIRED, np.int64), 0.0), list(range(k))
        # every pairing's marginal distance first; the joint covariance only over landmarks some sighting may be
        nu_all, s_all = zip(*(self._innovations(np.repeat(z[i:i + 1], len(pool), 0),
                                                np.repeat(r[i:i + 1], len(pool), 0), pool) for i in range(k)),
                            strict=True)
        nu_all, s_all = np.stack(nu_all), np.stack(s_all)
        d2 = np.einsum("kmi,kmi->km", nu_all, np.linalg.solve(s_all, nu_all[..., None])[..., 0])
        near = np.flatnonzero((d2 <= cfg.gate_chi2).any(axis=0))
        fresh = [i for i in range(k) if d2[i].min() >= cfg.new_landmark_chi2]
        if len(near) == 0:
            return Association(np.full(k, UNPAIRED, np.int64), 0.0), fresh
        cov = self._prediction_covariance(pool[near])
        nu = nu_all[:, near]
        finder = jcbb if cfg.association == "jcbb" else nearest_neighbour
        extra = {"confidence": cfg.joint_confidence, "max_nodes": cfg.max_association_nodes} if finder is jcbb else {}
        found = finder(nu, cov, r, gate_chi2=cfg.gate_chi2, **extra)
        pairs = np.where(found.pairs == UNPAIRED, UNPAIRED, pool[near][np.maximum(found.pairs, 0)])
        fresh = [i for i in fresh if pairs[i] == UNPAIRED]
        return Association(pairs, found.joint_d2, found.nodes, found.complete), fresh

    def _prediction_covariance(self, landmarks: np.ndarray) -> np.ndarray:
        """Joint covariance ``H P H^T`` (2m, 2m) of the predicted measurements of ``landmarks``."""
        _, hx, hl, off = self._predicted(landmarks)
        m = len(off)
        cols = np.concatenate([np.arange(3), (off[:, None] + np.arange(2)).reshape(-1)])
        h = np.zeros((2 * m, 3 + 2 * m))
        for j in range(m):
            h[2 * j:2 * j + 2, :3] = hx[j]
            h[2 * j:2 * j + 2, 3 + 2 * j:5 + 2 * j] = hl[j]
        return h @ self._p[np.ix_(cols, cols)] @ h.T

    def _correct(self, z: np.ndarray, r: np.ndarray, landmarks: np.ndarray) -> None:
        """One joint Kalman update with the sightings ``z`` of ``landmarks``, iterated
        (``config.iterations`` > 1: the iterated EKF, relinearising at each new estimate)."""
        n = self._n
        prior = self._x[:n].copy()
        p = self._p[:n, :n]
        for _ in range(max(1, self.config.iterations)):
            h, hx, hl, off = self._predicted(landmarks)
            # P H^T without forming H: the pose columns and each landmark's two columns
            pht = np.concatenate([p[:, :3] @ hx[j].T + p[:, o:o + 2] @ hl[j].T for j, o in enumerate(off)], axis=1)
            s = np.zeros((2 * len(off), 2 * len(off)))
            for j, o in enumerate(off):
                s[2 * j:2 * j + 2] = hx[j] @ pht[:3] + hl[j] @ pht[o:o + 2]
            s = 0.5 * (s + s.T)
            for j in range(len(off)):
                s[2 * j:2 * j + 2, 2 * j:2 * j + 2] += r[j]
            nu = z - h
            nu[:, 1] = wrap_angle(nu[:, 1])
            moved = self._x[:n] - prior
            moved[2] = wrap_angle(float(moved[2]))
            for j, o in enumerate(off):  # iterated: the innovation at the prior, linearised here
                nu[j] += hx[j] @ moved[:3] + hl[j] @ moved[o:o + 2]
            gain = np.linalg.solve(s, pht.T).T
            self._x[:n] = prior + gain @ nu.reshape(-1)
            self._x[2] = wrap_angle(float(self._x[2]))
        p -= gain @ pht.T
        self._p[:n, :n] = 0.5 * (p + p.T)

    def _augment(self, landmark_id: str, z: np.ndarray, r: np.ndarray) -> int:
        """Add a landmark seen at ``z`` (range, bearing) with covariance ``r``; returns its number."""
        n = self._n
        if n + 2 > len(self._x):
            grow = len(self._x) * 2
            x, p = np.zeros(grow), np.zeros((grow, grow))
            x[:n], p[:n, :n] = self._x[:n], self._p[:n, :n]
            self._x, self._p = x, p
        point, g_pose, g_z = point_from_range_bearing(self._x[:3][None], z[None])
        g_pose, g_z = g_pose[0], g_z[0]
        self._x[n:n + 2] = point[0]
        cross = g_pose @ self._p[:3, :n]                           # (2, n)
        self._p[n:n + 2, :n] = cross
        self._p[:n, n:n + 2] = cross.T
        self._p[n:n + 2, n:n + 2] = g_pose @ self._p[:3, :3] @ g_pose.T + g_z @ r @ g_z.T
        number = len(self.ids)
        self.ids.append(landmark_id or f"f{number}")
        self._anonymous.append(not landmark_id)
        if landmark_id:
            self._index[landmark_id] = number
        self._n = n + 2
        self.stats.added += 1
        return number
