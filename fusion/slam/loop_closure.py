"""Loop-closure search and verification of the back end: a new keyframe against the finished submaps.

Each searched keyframe is matched, by branch-and-bound correlative search with a window that grows
with the distance travelled since, against finished submaps near its current estimate; a match that
scores well and that point-to-line ICP against the submap's occupied cells confirms is a closure
candidate. It is accepted when the correction it asks for is within the uncertainty of the chain
of keyframes, or when another candidate made shortly before asks for the same correction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from trundle.fusion.geometry import compose, relative, rotate_covariance, wrap_angle
from trundle.fusion.mapping.submaps import Submap, SubmapStack
from trundle.fusion.matching.icp import LineReference, icp
from trundle.fusion.matching.scan_matching import match_scan
from trundle.fusion.slam.config import SlamConfig
from trundle.fusion.slam.stats import SlamStats

# chi-square 3 dof: 99.9 % quantile, for loop closures that disagree with the graph
CHI2_3DOF_999 = 16.266236196238129


@dataclass(frozen=True)
class Closure:
    """A verified loop-closure candidate: submap ``anchor`` node -> ``node`` with its measurement and
    covariance (anchor frame), and the map pose it implies for ``node`` with that covariance (map frame)."""

    anchor: int
    node: int
    submap: int
    measurement: np.ndarray
    covariance: np.ndarray
    implied: np.ndarray
    implied_covariance: np.ndarray


class LoopCloser:
    """Finds loop closures for new keyframes in ``submaps`` (see the module docstring); keeps the
    summed covariance and the path length of the chain of keyframes up to each."""

    def __init__(self, config: SlamConfig, stats: SlamStats, submaps: SubmapStack) -> None:
        self.config = config
        self.stats = stats
        self.submaps = submaps
        self._chain: list[np.ndarray] = []  # summed covariance (map frame) of the sequential edges up to each keyframe
        self._path_m: list[float] = []
        self._pending: list[Closure] = []
        self._last_loop_node: dict[int, int] = {}
        self.dropped: list[Closure] = []  # verified candidates no partner or chain agreed with

    def add_keyframe(self, edge_covariance: np.ndarray | None, previous_heading: float, path_m: float,
                     start_covariance: np.ndarray | None = None) -> None:
        """A keyframe's sequential edge covariance (previous keyframe's frame; None for the first of a chain,
        whose own uncertainty is ``start_covariance``, map frame, default none), that keyframe's heading (rad)
        and the path length to the new one (m)."""
        if edge_covariance is None:
            self._chain.append(np.zeros((3, 3)) if start_covariance is None else np.array(start_covariance))
        else:
            self._chain.append(self._chain[-1] + rotate_covariance(edge_covariance, previous_heading))
        self._path_m.append(path_m)

    def search(self, node: int, points: np.ndarray, poses: np.ndarray, dense: bool) -> list[Closure]:
        """The closures to add for keyframe ``node`` (its voxel-filtered ``points``) at the graph's ``poses``:
        none, one, or one with the partner that agrees with it. A finished submap that leaves the search
        radius lets go of its matching fields and pyramids (most of the memory of a long run: 1.2 of
        1.4 GB on fr079), so memory follows the submaps near the robot, not the length of the run."""
        opts = self.config.loop_closure
        here = poses[node]
        candidates = []
        for submap in self.submaps.finished:
            frame = submap.local_to_map(poses[submap.anchor_node])
            guess = relative(frame, here)
            distance = float(np.hypot(*(guess[:2] - submap.centre())))
            if distance > opts.search_radius_m:
                submap.grid.release_cache()  # out of reach: its fields are computed again on a return
                continue
            if node - submap.nodes[-1] < opts.min_node_gap:
                continue
            if node - self._last_loop_node.get(submap.index, -(1 << 30)) < opts.cooldown_keyframes:
                continue
            candidates.append((distance, submap, guess))
        candidates.sort(key=lambda c: c[0])
        for _, submap, guess in candidates[: opts.max_candidates]:
            travelled = self._path_m[node] - self._path_m[submap.nodes[-1]]
            window_xy = float(np.clip(opts.window_per_m * travelled, *opts.window_xy_m))
            window_theta = float(np.clip(opts.window_per_m * travelled, *opts.window_theta_rad))
            self.stats.loop_attempts += 1
            result = match_scan(submap.grid, points, guess, window_xy_m=window_xy, window_theta_rad=window_theta,
                                angular_step_rad=opts.angular_step_rad, min_score=opts.min_score,
                                min_std_xy_m=opts.min_std_xy_m, min_std_theta_rad=opts.min_std_theta_rad,
                                shaped_covariance=True, wall_lines=dense)
            if result is None or result.score < opts.min_score or result.inlier_fraction < opts.min_inliers:
                continue
            if not self._verified(submap, points, result.pose):
                self.stats.loop_unverified += 1
                continue
            frame = submap.local_to_map(poses[submap.anchor_node])
            closure = Closure(submap.anchor_node, node, submap.index, relative(submap.anchor_local, result.pose),
                              rotate_covariance(result.covariance, -float(submap.anchor_local[2])),
                              compose(frame, result.pose), rotate_covariance(result.covariance, float(frame[2])))
            accepted = self._consider(closure, poses)
            for c in accepted:
                self._last_loop_node[c.submap] = c.node
            return accepted
        return []

    def _chain_covariance(self, first: int, last: int) -> np.ndarray:
        """Covariance (map frame) of the relative pose of keyframes ``first`` -> ``last`` along the
        sequential edges: their summed covariances, and the translation a heading error causes over
        the distance between them."""
        chain = self._chain[last] - self._chain[first]
        distance = self._path_m[last] - self._path_m[first]
        chain[:2, :2] += np.eye(2) * chain[2, 2] * distance ** 2
        return chain

    def _consider(self, closure: Closure, poses: np.ndarray) -> list[Closure]:
        """A verified loop closure is accepted if it agrees with the chain of keyframes (the correction
        it asks for is within the chain's own uncertainty) or with another closure made shortly before
        (both ask for one correction: both are accepted); otherwise it waits for such a partner for
        ``2 * scans_per_submap`` keyframes and is then dropped (``loop_inconsistent``)."""
        correction = closure.implied - poses[closure.node]
        correction[2] = wrap_angle(correction[2])
        covariance = self._chain_covariance(closure.anchor, closure.node) + closure.implied_covariance
        if float(correction @ np.linalg.solve(covariance, correction)) <= CHI2_3DOF_999:
            return [closure]
        horizon = 2 * self.config.submaps.scans_per_submap
        expired = [p for p in self._pending if closure.node - p.node > horizon]
        self.stats.loop_inconsistent += len(expired)
        self.dropped.extend(expired)
        self._pending = [p for p in self._pending if closure.node - p.node <= horizon]
        for partner in self._pending:
            predicted = compose(partner.implied, relative(poses[partner.node], poses[closure.node]))
            difference = closure.implied - predicted
            difference[2] = wrap_angle(difference[2])
            spread = (partner.implied_covariance + closure.implied_covariance
                      + self._chain_covariance(partner.node, closure.node))
            if float(difference @ np.linalg.solve(spread, difference)) <= CHI2_3DOF_999:
                self._pending.remove(partner)
                self.stats.loop_paired += 2
                return [partner, closure]
        self._pending.append(closure)
        return []

    def _verified(self, submap: Submap, points: np.ndarray, pose: np.ndarray) -> bool:
        """Does point-to-line ICP against the submap's occupied cells agree with the grid match?"""
        opts, resolution = self.config.loop_closure, self.config.submaps.resolution
        cells = submap.grid.occupied_points()
        if len(cells) < 10:
            return False
        reference = submap.grid.cached(("icp_reference",), lambda: LineReference(cells))
        check = icp(reference, points, pose, max_correspondence_m=3 * resolution, huber_m=resolution,
                    inlier_m=2 * resolution)
        step = relative(pose, check.pose)
        return (float(np.hypot(step[0], step[1])) <= opts.verify_xy_m
                and abs(float(step[2])) <= opts.verify_theta_rad
                and check.inlier_fraction >= opts.min_inliers)
