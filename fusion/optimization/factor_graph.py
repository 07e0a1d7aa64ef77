"""Planar factor graph: SE(2) poses and 2-D points, optimised by sparse Levenberg-Marquardt.

The pose graph of :mod:`trundle.fusion.optimization.pose_graph` holds poses only; a landmark map needs points
too (a tree trunk, a barcode cylinder, a laser corner) and factors between a pose and a point.
Variables are poses ``(x, y, theta)`` and points ``(x, y)`` (metres, radians, map frame). Factors,
each with an information matrix (the inverse of its measurement covariance):

- ``between``: pose j in the frame of pose i, the g2o ``EDGE_SE2`` error of the pose graph (also
  a marker landmark, itself a pose, seen by a robot pose: Cartographer's landmark constraint);
- ``range_bearing``: a point seen from a pose, ``(range m, bearing rad)`` with the bearing
  counter-clockwise from the pose's x axis;
- ``position``: a point's position ``(x, y)`` in the frame of a pose;
- ``point_prior`` and ``pose_prior``: a variable's absolute value (a surveyed landmark).

``chi2 = sum e^T I e`` over all factors. ``optimize`` linearises with analytic Jacobians, whitens
each factor by the Cholesky factor of its information, applies per-kind robust kernels
(:mod:`~trundle.fusion.optimization.robust_kernels`) by iteratively reweighted least squares and
hands the sparse normal equations to the one Levenberg-Marquardt core
(:func:`~trundle.fusion.optimization.levenberg_marquardt.levenberg_marquardt`), as
:meth:`trundle.fusion.optimization.pose_graph.PoseGraph.optimize` does; fixed variables stay put.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from trundle.fusion.geometry import wrap_angle
from trundle.fusion.observation_models import between_error, range_bearing, relative_position
from trundle.fusion.optimization.levenberg_marquardt import (
    OptimizeResult,
    Settings,
    block_triplets,
    factor_spd,
    levenberg_marquardt,
    solve_spd,
    sparse_jacobian,
)
from trundle.fusion.optimization.pose_graph import PoseGraph
from trundle.fusion.optimization.robust_kernels import ROBUST_KERNELS, Kernel, robust_loss

POSE, POINT = "pose", "point"
BETWEEN, RANGE_BEARING, POSITION, POINT_PRIOR, POSE_PRIOR = (
    "between", "range_bearing", "position", "point_prior", "pose_prior")
# kind -> variable types it connects, and its error dimension
KINDS: dict[str, tuple[tuple[str, ...], int]] = {
    BETWEEN: ((POSE, POSE), 3), RANGE_BEARING: ((POSE, POINT), 2), POSITION: ((POSE, POINT), 2),
    POINT_PRIOR: ((POINT,), 2), POSE_PRIOR: ((POSE,), 3)}
MARGINAL_SOLVE_VALUES = 1 << 22   # right-hand side values per solve of marginal_covariances (32 MB)


@dataclass
class _FactorList:
    """Factors of one kind, kept as growing lists until ``arrays`` stacks them."""

    variables: list[tuple[int, ...]] = field(default_factory=list)
    measurements: list[np.ndarray] = field(default_factory=list)
    information: list[np.ndarray] = field(default_factory=list)

    def arrays(self, dim: int, arity: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return (np.array(self.variables, np.int64).reshape(-1, arity),
                np.array(self.measurements, np.float64).reshape(-1, dim),
                np.array(self.information, np.float64).reshape(-1, dim, dim))


class FactorGraph:
    """Poses and points with factors between them; see the module docstring for the factor kinds.

    ``fixed_poses`` and ``fixed_points`` hold the variables ``optimize`` leaves alone (default:
    pose 0, which fixes the gauge of a graph without priors).
    """

    def __init__(self) -> None:
        self._poses: list[np.ndarray] = []
        self._points: list[np.ndarray] = []
        self._factors: dict[str, _FactorList] = {kind: _FactorList() for kind in KINDS}
        self.fixed_poses: set[int] = {0}
        self.fixed_points: set[int] = set()

    @classmethod
    def from_pose_graph(cls, graph: PoseGraph) -> FactorGraph:
        """A factor graph with the nodes, edges and fixed nodes of a pose graph."""
        out = cls()
        out._poses = [p.copy() for p in graph.poses]
        ij, z, info = graph.edges
        out._factors[BETWEEN] = _FactorList([tuple(map(int, e)) for e in ij], list(z), list(info))
        out.fixed_poses = set(graph.fixed)
        return out

    # ----------------------------------------------------------------- building
    def add_pose(self, pose_xyt) -> int:
        """Append a pose variable (x m, y m, theta rad); returns its index."""
        self._poses.append(_finite(pose_xyt, 3, "pose"))
        return len(self._poses) - 1

    def add_point(self, point_xy) -> int:
        """Append a point variable (x m, y m); returns its index."""
        self._points.append(_finite(point_xy, 2, "point"))
        return len(self._points) - 1

    def add_between(self, i: int, j: int, measurement_xyt, information) -> int:
        """Pose j measured in the frame of pose i, 3x3 information; returns the factor's index in its kind."""
        if i == j:
            raise ValueError(f"between factor ({i}, {j}) needs two distinct poses")
        return self._add(BETWEEN, (i, j), measurement_xyt, information)

    def add_range_bearing(self, pose: int, point: int, range_m: float, bearing_rad: float, information) -> int:
        """A point seen from a pose at ``range_m`` and ``bearing_rad``; information over (range, bearing)."""
        return self._add(RANGE_BEARING, (pose, point), (range_m, bearing_rad), information)

    def add_position(self, pose: int, point: int, position_xy, information) -> int:
        """A point at ``position_xy`` (m) in the frame of a pose; 2x2 information."""
        return self._add(POSITION, (pose, point), position_xy, information)

    def add_point_prior(self, point: int, position_xy, information) -> int:
        """A point's absolute position (m, map frame); 2x2 information."""
        return self._add(POINT_PRIOR, (point,), position_xy, information)

    def add_pose_prior(self, pose: int, pose_xyt, information) -> int:
        """A pose's absolute value (map frame); 3x3 information."""
        return self._add(POSE_PRIOR, (pose,), pose_xyt, information)

    def _add(self, kind: str, variables: tuple[int, ...], measurement, information) -> int:
        types, dim = KINDS[kind]
        for index, kind_of in zip(variables, types, strict=True):
            count = len(self._poses) if kind_of == POSE else len(self._points)
            if not 0 <= index < count:
                raise ValueError(f"{kind} factor names {kind_of} {index}, but there are {count}")
        z = _finite(measurement, dim, f"{kind} measurement")
        info = np.asarray(information, dtype=np.float64).reshape(dim, dim).copy()
        if not np.abs(info - info.T).max() <= 1e-12 + 1e-9 * np.abs(info).max():
            raise ValueError(f"information of the {kind} factor {variables} is not symmetric")
        if not (np.all(np.isfinite(info)) and np.all(np.linalg.eigvalsh(info) > 0)):
            raise ValueError(f"information of the {kind} factor {variables} is not positive definite")
        factors = self._factors[kind]
        factors.variables.append(tuple(int(v) for v in variables))
        factors.measurements.append(z)
        factors.information.append(info)
        return len(factors.variables) - 1

    # ------------------------------------------------------------------ access
    @property
    def poses(self) -> np.ndarray:
        """(N, 3) pose variables; a copy."""
        return np.array(self._poses, dtype=np.float64).reshape(-1, 3)

    @poses.setter
    def poses(self, values) -> None:
        self._poses = [row.copy() for row in _shaped(values, (len(self._poses), 3))]

    def pose(self, index: int) -> np.ndarray:
        """One pose variable (3,); a copy."""
        return self._poses[index].copy()

    def set_pose(self, index: int, pose_xyt) -> None:
        """Replace one pose variable's value (e.g. by a filter's better estimate)."""
        self._poses[index] = _finite(pose_xyt, 3, "pose")

    @property
    def points(self) -> np.ndarray:
        """(M, 2) point variables; a copy."""
        return np.array(self._points, dtype=np.float64).reshape(-1, 2)

    @points.setter
    def points(self, values) -> None:
        self._points = [row.copy() for row in _shaped(values, (len(self._points), 2))]

    def factors(self, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Variables (F, arity), measurements (F, d) and information (F, d, d) of one kind's factors."""
        types, dim = KINDS[kind]
        return self._factors[kind].arrays(dim, len(types))

    @property
    def num_factors(self) -> int:
        return sum(len(f.variables) for f in self._factors.values())

    def __len__(self) -> int:
        """The number of variables (poses and points)."""
        return len(self._poses) + len(self._points)

    # ------------------------------------------------------------------ errors
    def _linearize(self, poses: np.ndarray, points: np.ndarray, kind: str) -> tuple[np.ndarray, list[np.ndarray]]:
        """Errors (F, d) of one kind and its Jacobians by each of its variables."""
        index, z, _ = self.factors(kind)
        if kind == BETWEEN:
            e, ji, jj = between_error(poses[index[:, 0]], poses[index[:, 1]], z)
            return e, [ji, jj]
        if kind in (RANGE_BEARING, POSITION):
            model = range_bearing if kind == RANGE_BEARING else relative_position
            h, jp, jl = model(poses[index[:, 0]], points[index[:, 1]])
            e = h - z
            if kind == RANGE_BEARING:
                e[:, 1] = wrap_angle(e[:, 1])
            return e, [jp, jl]
        if kind == POINT_PRIOR:
            return points[index[:, 0]] - z, [np.broadcast_to(np.eye(2), (len(z), 2, 2))]
        e = poses[index[:, 0]] - z
        e[:, 2] = wrap_angle(e[:, 2])
        return e, [np.broadcast_to(np.eye(3), (len(z), 3, 3))]

    def factor_errors(self, kind: str) -> np.ndarray:
        """(F, d) errors ``h - z`` of one kind's factors at the current estimate (angles wrapped)."""
        if not self._factors[kind].variables:
            return np.zeros((0, KINDS[kind][1]))
        return self._linearize(self.poses, self.points, kind)[0]

    def set_information(self, kind: str, information: np.ndarray) -> None:
        """Replace the information matrices (F, d, d) of one kind's factors (e.g. reweighted)."""
        factors = self._factors[kind]
        info = np.asarray(information, np.float64).reshape(len(factors.variables), *(KINDS[kind][1],) * 2)
        factors.information = [row.copy() for row in info]

    def factor_chi2(self, kind: str, poses: np.ndarray | None = None, points: np.ndarray | None = None) -> np.ndarray:
        """(F,) weighted squared error ``e^T I e`` of every factor of one kind."""
        x = self.poses if poses is None else poses
        p = self.points if points is None else points
        info = self.factors(kind)[2]
        if len(info) == 0:
            return np.zeros(0)
        e = self._linearize(x, p, kind)[0]
        return np.einsum("fi,fij,fj->f", e, info, e)

    def chi2(self, poses: np.ndarray | None = None, points: np.ndarray | None = None) -> float:
        """Sum of all factors' weighted squared errors (no robust kernel)."""
        return float(sum(self.factor_chi2(kind, poses, points).sum() for kind in KINDS))

    # ---------------------------------------------------------------- optimise
    def _columns(self) -> tuple[np.ndarray, np.ndarray, int]:
        """Column offset of every pose and point in the free state vector (-1: fixed) and its size."""
        pose_col = np.full(len(self._poses), -1, np.int64)
        point_col = np.full(len(self._points), -1, np.int64)
        free_poses = np.setdiff1d(np.arange(len(self._poses)), list(self.fixed_poses))
        free_points = np.setdiff1d(np.arange(len(self._points)), list(self.fixed_points))
        pose_col[free_poses] = 3 * np.arange(len(free_poses))
        point_col[free_points] = 3 * len(free_poses) + 2 * np.arange(len(free_points))
        return pose_col, point_col, 3 * len(free_poses) + 2 * len(free_points)

    def _system(self, poses: np.ndarray, points: np.ndarray, kernels: dict[str, Kernel], columns
                ) -> tuple[sp.csr_matrix, np.ndarray]:
        """Whitened, robustly weighted Jacobian (sparse) and residual vector at ``poses``, ``points``."""
        pose_col, point_col, n = columns
        triplets, residuals = [], []
        row = 0
        for kind, (types, dim) in KINDS.items():
            index, _, info = self.factors(kind)
            if len(index) == 0:
                continue
            e, jac = self._linearize(poses, points, kind)
            s = np.einsum("fi,fij,fj->f", e, info, e)
            kernel, width = kernels.get(kind, (None, 1.0))
            weight = np.sqrt(robust_loss(s, kernel, width)[1])[:, None, None]
            a = weight * np.linalg.cholesky(info).transpose(0, 2, 1)
            residuals.append((a @ e[:, :, None])[:, :, 0].reshape(-1))
            factor_rows = row + dim * np.arange(len(index))
            for k, kind_of in enumerate(types):
                triplets.append(block_triplets(a @ jac[k], factor_rows,
                                               (pose_col if kind_of == POSE else point_col)[index[:, k]]))
            row += dim * len(index)
        return sparse_jacobian(triplets, (row, n)), np.concatenate(residuals) if residuals else np.zeros(row)

    def _cost(self, poses: np.ndarray, points: np.ndarray, kernels: dict[str, Kernel]) -> float:
        total = 0.0
        for kind in KINDS:
            s = self.factor_chi2(kind, poses, points)
            kernel, width = kernels.get(kind, (None, 1.0))
            total += float(robust_loss(s, kernel, width)[0].sum())
        return total

    def optimize(self, max_iterations: int = 100, kernels: dict[str, Kernel] | None = None,
                 relative_tolerance: float = 1e-6, absolute_tolerance: float = 1e-9,
                 initial_lambda: float = 1e-5) -> OptimizeResult:
        """Minimise the (robust) cost over the free variables by Levenberg-Marquardt; updates them.

        Parameters
        ----------
        max_iterations : LM iterations (accepted or rejected steps) at most.
        kernels : robust kernel per factor kind, e.g. ``{"range_bearing": ("cauchy", 3.0)}``
            (width in whitened units); kinds not named get none.
        relative_tolerance, absolute_tolerance : stop when an accepted step lowers the cost by
            less than ``relative_tolerance * cost`` or below ``absolute_tolerance``.
        initial_lambda : Levenberg damping ``lambda I`` added to the normal matrix at the start
            (GTSAM's default; then the core's schedule, see :class:`Settings`).
        """
        kernels = dict(kernels or {})
        for kind, (kernel, _) in kernels.items():
            if kind not in KINDS or kernel not in ROBUST_KERNELS:
                raise ValueError(f"unknown factor kind or robust kernel {kind!r}: {kernel!r}")
        columns = self._columns()
        pose_col, point_col, n = columns
        x, p = self.poses, self.points
        if n == 0 or self.num_factors == 0:
            cost = self._cost(x, p, kernels)
            return OptimizeResult(cost, cost, 0, True)
        free_pose, free_point = pose_col >= 0, point_col >= 0
        head = 3 * int(free_pose.sum())

        def placed(state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            poses, points = x.copy(), p.copy()
            poses[free_pose] = state[:head].reshape(-1, 3)
            points[free_point] = state[head:].reshape(-1, 2)
            return poses, points

        def linearize(state: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray]:
            jac, r = self._system(*placed(state), kernels, columns)
            return (jac.T @ jac).tocsc(), jac.T @ r

        settings = Settings(initial_lambda=initial_lambda, relative_tolerance=relative_tolerance,
                            absolute_tolerance=absolute_tolerance)
        state, result = levenberg_marquardt(lambda state: self._cost(*placed(state), kernels), linearize,
                                            np.concatenate([x[free_pose].reshape(-1), p[free_point].reshape(-1)]),
                                            head // 3, max_iterations, settings)
        self.poses, self.points = placed(state)
        return result

    def redundancy(self, kind: str, select: np.ndarray | None = None, kernels: dict[str, Kernel] | None = None,
                   samples: int = 32, seed: int = 0) -> float:
        """Redundancy of a kind's factors (those in ``select``): their error dimensions less their share
        of the fit, ``sum_i (d_i - tr(A_i (J^T J)^-1 A_i^T))`` for the whitened Jacobian ``J`` and its
        rows ``A_i``: what their chi2 sums to when their noise model is right (Foerstner's variance
        component estimation). The trace is Hutchinson's estimate over ``samples`` random sign
        vectors, one solve each with one factorisation."""
        columns = self._columns()
        dim = KINDS[kind][1]
        chosen = np.ones(len(self._factors[kind].variables), bool) if select is None else np.asarray(select, bool)
        start = sum(KINDS[k][1] * len(self._factors[k].variables) for k in list(KINDS)[:list(KINDS).index(kind)])
        rows = (start + dim * np.flatnonzero(chosen)[:, None] + np.arange(dim)).reshape(-1)
        if columns[2] == 0 or len(rows) == 0:
            return float(len(rows))
        jac, _ = self._system(self.poses, self.points, dict(kernels or {}), columns)
        probes = np.zeros((jac.shape[0], samples))
        probes[rows] = np.random.default_rng(seed).choice([-1.0, 1.0], size=(len(rows), samples))
        solution = solve_spd((jac.T @ jac).tocsc(), np.asarray(jac.T @ probes))
        if solution.ndim != 2:
            return float(len(rows))
        fitted = jac @ solution
        return float(len(rows) - np.mean(np.einsum("rs,rs->s", probes[rows], fitted[rows])))

    def marginal_covariances(self, poses=(), points=(), kernels: dict[str, Kernel] | None = None
                             ) -> tuple[np.ndarray, np.ndarray]:
        """Marginal covariances at the current estimate of the chosen poses (P, 3, 3) and points (Q, 2, 2),
        map frame: blocks of the inverse of the (robustly weighted) Gauss-Newton normal matrix. A
        fixed variable has zero covariance; NaN when the graph leaves a chosen variable unconstrained."""
        pose_col, point_col, n = columns = self._columns()
        pose_ids, point_ids = np.asarray(poses, np.int64).reshape(-1), np.asarray(points, np.int64).reshape(-1)
        starts = np.concatenate([pose_col[pose_ids], point_col[point_ids]])
        widths = np.concatenate([np.full(len(pose_ids), 3), np.full(len(point_ids), 2)])
        blocks = [np.zeros((w, w)) for w in widths]
        free = np.flatnonzero(starts >= 0)
        if n and len(free):
            jac, _ = self._system(self.poses, self.points, dict(kernels or {}), columns)
            factor = factor_spd((jac.T @ jac).tocsc())
            # variables per solve: its right-hand side stays small
            per_solve = max(1, MARGINAL_SOLVE_VALUES // (3 * n))
            for chunk in np.array_split(free, -(-len(free) // per_solve)):
                picks = np.concatenate([starts[k] + np.arange(widths[k]) for k in chunk])
                rhs = np.zeros((n, len(picks)))
                rhs[picks, np.arange(len(picks))] = 1.0
                solution = factor.solve(rhs) if factor is not None else None
                offset = 0
                for k in chunk:
                    w = widths[k]
                    block = solution[picks[offset:offset + w], offset:offset + w] if solution is not None \
                        else np.full((w, w), np.nan)
                    blocks[k] = 0.5 * (block + block.T)
                    offset += w
        pose_blocks = np.array(blocks[:len(pose_ids)]).reshape(-1, 3, 3)
        point_blocks = np.array(blocks[len(pose_ids):]).reshape(-1, 2, 2)
        return pose_blocks, point_blocks


def _finite(values, size: int, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(size).copy()
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite, got {array}")
    return array


def _shaped(values, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"expected {shape}, got {array.shape}")
    return array

