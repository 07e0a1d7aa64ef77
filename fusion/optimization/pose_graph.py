"""2-D pose graph (SE(2) nodes, relative-pose edges), optimised by the one Levenberg-Marquardt core.

The error of an edge i -> j with measurement z (pose j in the frame of pose i) is the g2o
``EDGE_SE2`` error ``e = t2v(z^-1 (x_i^-1 x_j))`` (metres, metres, radians wrapped to
[-pi, pi); :func:`trundle.fusion.observation_models.between_error`), weighted by the edge's 3x3
information matrix; ``chi2 = sum e^T I e``. ``optimize`` whitens each edge by the Cholesky
factor of its information, applies a robust kernel (:mod:`~trundle.fusion.optimization.robust_kernels`)
by iteratively reweighted least squares and hands the sparse normal equations to
:func:`~trundle.fusion.optimization.levenberg_marquardt.levenberg_marquardt`; vertex 0 (or any set
of vertices) stays fixed.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.sparse.csgraph import breadth_first_order

from trundle.fusion.geometry import wrap_angle
from trundle.fusion.observation_models import between_error
from trundle.fusion.optimization.levenberg_marquardt import (
    OptimizeResult,
    Settings,
    block_triplets,
    levenberg_marquardt,
    solve_spd,
    sparse_jacobian,
)
from trundle.fusion.optimization.robust_kernels import check_kernel, robust_loss
from trundle.logs.errors import UserError
from trundle.logs.outputs import write_text


class PoseGraph:
    """Nodes are planar poses (x, y, theta); edges are relative-pose measurements with information."""

    def __init__(self) -> None:
        self._poses: list[np.ndarray] = []
        self._edge_ij: list[tuple[int, int]] = []
        self._edge_z: list[np.ndarray] = []
        self._edge_info: list[np.ndarray] = []
        # the lists as arrays, until they change
        self._edge_arrays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self.fixed: set[int] = {0}

    # ----------------------------------------------------------------- building
    def add_node(self, pose_xyt) -> int:
        """Append a node with initial pose (x m, y m, theta rad); returns its id."""
        pose = np.asarray(pose_xyt, dtype=np.float64).reshape(3).copy()
        if not np.all(np.isfinite(pose)):
            raise ValueError(f"pose must be finite, got {pose}")
        self._poses.append(pose)
        return len(self._poses) - 1

    def add_edge(self, i: int, j: int, measurement_xyt, information) -> int:
        """Add a constraint: pose of node j in the frame of node i, with a 3x3 information matrix.

        Returns the edge index. The information must be symmetric positive definite.
        """
        n = len(self._poses)
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise ValueError(f"edge ({i}, {j}) needs two distinct existing nodes (have {n})")
        z = np.asarray(measurement_xyt, dtype=np.float64).reshape(3).copy()
        info = np.asarray(information, dtype=np.float64).reshape(3, 3).copy()
        if not np.all(np.isfinite(z)) or not np.allclose(info, info.T, rtol=1e-9, atol=1e-12):
            raise ValueError("measurement must be finite and information symmetric")
        try:
            np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            raise ValueError(f"information of edge ({i}, {j}) is not positive definite") from None
        self._edge_ij.append((int(i), int(j)))
        self._edge_z.append(z)
        self._edge_info.append(info)
        self._edge_arrays = None
        return len(self._edge_ij) - 1

    @property
    def poses(self) -> np.ndarray:
        """(N, 3) node poses (x, y, theta); a copy."""
        return np.array(self._poses, dtype=np.float64).reshape(-1, 3)

    @poses.setter
    def poses(self, values) -> None:
        values = np.asarray(values, dtype=np.float64)
        if values.shape != (len(self._poses), 3):
            raise ValueError(f"expected ({len(self._poses)}, 3) poses, got {values.shape}")
        self._poses = [row.copy() for row in values]

    @property
    def edges(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(E, 2) node ids, (E, 3) measurements, (E, 3, 3) information matrices; copies."""
        if self._edge_arrays is None:
            self._edge_arrays = (np.array(self._edge_ij, dtype=np.int64).reshape(-1, 2),
                                 np.array(self._edge_z, dtype=np.float64).reshape(-1, 3),
                                 np.array(self._edge_info, dtype=np.float64).reshape(-1, 3, 3))
        return tuple(a.copy() for a in self._edge_arrays)  # type: ignore[return-value]

    def remove_edges(self, indices) -> None:
        """Drop the edges at ``indices`` (e.g. loop closures found to be false)."""
        drop = set(int(k) for k in np.atleast_1d(indices))
        keep = [k for k in range(len(self._edge_ij)) if k not in drop]
        self._edge_ij = [self._edge_ij[k] for k in keep]
        self._edge_z = [self._edge_z[k] for k in keep]
        self._edge_info = [self._edge_info[k] for k in keep]
        self._edge_arrays = None

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def num_edges(self) -> int:
        return len(self._edge_ij)

    # ------------------------------------------------------------------ errors
    def edge_errors(self, poses: np.ndarray | None = None) -> np.ndarray:
        """(E, 3) errors ``t2v(z^-1 (x_i^-1 x_j))`` of every edge at ``poses`` (default: current)."""
        x = self.poses if poses is None else poses
        ij, z, _ = self.edges
        return between_error(x[ij[:, 0]], x[ij[:, 1]], z)[0]

    def edge_chi2(self, poses: np.ndarray | None = None) -> np.ndarray:
        """(E,) weighted squared error ``e^T I e`` of every edge."""
        e = self.edge_errors(poses)
        info = self.edges[2]
        return np.einsum("ei,eij,ej->e", e, info, e)

    def chi2(self, poses: np.ndarray | None = None) -> float:
        """Sum of the edges' weighted squared errors (no robust kernel)."""
        return float(self.edge_chi2(poses).sum())

    # ------------------------------------------------------------ initialise
    def initialize(self) -> None:
        """Linear initial guess in the manner of LAGO (Carlone et al., T-RO 2014); updates ``poses``.

        Orientations are first propagated along a breadth-first spanning tree from a fixed node,
        which fixes the 2-pi multiples of every edge's relative angle; all edges then give one
        weighted linear least-squares problem in the orientations, and with orientations known
        a second one in the positions. Both are solved with SciPy's sparse direct solver.
        Starting LM here instead of at dead reckoning avoids the local minima and the slow
        progress of large loops. Nodes not connected to a fixed node keep their poses.
        """
        x = self.poses
        ij, z, info = self.edges
        if len(ij) == 0 or len(x) < 2:
            return
        n = len(x)
        fixed = sorted(k for k in self.fixed if k < n) or [0]
        covariance = np.linalg.inv(info)
        # spanning tree: one edge per node pair, breadth first from the first fixed node
        low, high = ij.min(axis=1), ij.max(axis=1)
        _, first = np.unique(low * n + high, return_index=True)
        pairs = sp.coo_matrix((first + 1.0, (low[first], high[first])), shape=(n, n)).tocsr()
        order, predecessor = breadth_first_order(pairs + pairs.T, fixed[0], directed=False)
        children = order[1:]
        parents = predecessor[children]
        tree_edge = np.asarray((pairs + pairs.T)[parents, children]).reshape(-1).astype(np.int64) - 1
        sign = np.where(ij[tree_edge, 1] == children, 1.0, -1.0)
        # tree orientations: theta_child - theta_parent = sign * z_theta, root at its pose
        reached = np.zeros(n, dtype=bool)
        reached[order] = True
        theta = x[:, 2].copy()
        if len(children):
            index = np.full(n, -1, dtype=np.int64)
            index[children] = np.arange(len(children))
            rows = np.arange(len(children))
            is_root_parent = index[parents] < 0
            tree = sp.coo_matrix((np.concatenate([np.ones(len(children)), -np.ones(int((~is_root_parent).sum()))]),
                                  (np.concatenate([rows, rows[~is_root_parent]]),
                                   np.concatenate([rows, index[parents[~is_root_parent]]]))),
                                 shape=(len(children), len(children))).tocsc()
            rhs = sign * z[tree_edge, 2] + np.where(is_root_parent, theta[fixed[0]], 0.0)
            theta[children] = np.atleast_1d(spla.spsolve(tree, rhs))
        # all edges: unwrap each relative angle against the tree, then weighted least squares
        use = reached[ij[:, 0]] & reached[ij[:, 1]]
        e_ij, e_z, e_cov = ij[use], z[use], covariance[use]
        delta = e_z[:, 2] + 2.0 * np.pi * np.round((theta[e_ij[:, 1]] - theta[e_ij[:, 0]] - e_z[:, 2]) / (2.0 * np.pi))
        anchored = np.zeros(n, dtype=bool)
        anchored[fixed] = True
        anchored |= ~reached
        theta = _solve_linear_chain(theta[:, None], e_ij, delta[:, None], np.sqrt(1.0 / e_cov[:, 2, 2])[:, None, None],
                                    anchored)[:, 0]
        # positions: t_j - t_i = R(theta_i) z_t, weighted by the rotated marginal translation information
        c, s = np.cos(theta[e_ij[:, 0]]), np.sin(theta[e_ij[:, 0]])
        rot = np.stack([np.stack([c, -s], 1), np.stack([s, c], 1)], 1)
        measured = (rot @ e_z[:, :2, None])[:, :, 0]
        info_xy = np.linalg.inv(rot @ e_cov[:, :2, :2] @ rot.transpose(0, 2, 1))
        whitening = np.linalg.cholesky(info_xy).transpose(0, 2, 1)
        positions = _solve_linear_chain(x[:, :2], e_ij, measured, whitening, anchored)
        x[:, :2] = positions
        x[:, 2] = wrap_angle(theta)
        self._poses = [row.copy() for row in x]

    # ---------------------------------------------------------------- optimise
    def optimize(self, max_iterations: int = 100, robust_kernel: str | None = None,
                 kernel_width: float = 1.0, relative_tolerance: float = 1e-6,
                 absolute_tolerance: float = 1e-9, initial_lambda: float = 1e-5) -> OptimizeResult:
        """Minimise chi2 over the non-fixed poses by Levenberg-Marquardt; updates ``poses``.

        Parameters
        ----------
        max_iterations : LM iterations (accepted or rejected steps) at most.
        robust_kernel : None, ``"huber"`` or ``"cauchy"`` (IRLS with weights refreshed each step).
        kernel_width : kernel parameter k on the whitened error (chi2 units: ``k^2``).
        relative_tolerance, absolute_tolerance : stop when an accepted step lowers the cost by
            less than ``relative_tolerance * cost`` or below ``absolute_tolerance``.
        initial_lambda : Levenberg damping ``lambda I`` added to the normal matrix at the start
            (GTSAM's default; then the core's schedule, see :class:`Settings`).
        """
        check_kernel(robust_kernel)
        x = self.poses
        ij, z, info = self.edges
        if len(ij) == 0:
            return OptimizeResult(0.0, 0.0, 0, True)
        sqrt_info = np.linalg.cholesky(info).transpose(0, 2, 1)  # L^T: e^T I e = |L^T e|^2
        free = np.ones(len(x), dtype=bool)
        free[[k for k in self.fixed if k < len(x)]] = False
        column = np.full(len(x), -1, dtype=np.int64)
        column[free] = 3 * np.arange(int(free.sum()))
        rows = 3 * np.arange(len(ij))

        def placed(state: np.ndarray) -> np.ndarray:
            poses = x.copy()
            poses[free] = state.reshape(-1, 3)
            return poses

        def cost(state: np.ndarray) -> float:
            poses = placed(state)
            e = between_error(poses[ij[:, 0]], poses[ij[:, 1]], z)[0]
            s = np.einsum("ei,eij,ej->e", e, info, e)
            return float(robust_loss(s, robust_kernel, kernel_width)[0].sum())

        def linearize(state: np.ndarray) -> tuple[sp.csc_matrix, np.ndarray]:
            poses = placed(state)
            e, jac_i, jac_j = between_error(poses[ij[:, 0]], poses[ij[:, 1]], z)
            s = np.einsum("ei,eij,ej->e", e, info, e)
            a = np.sqrt(robust_loss(s, robust_kernel, kernel_width)[1])[:, None, None] * sqrt_info
            r = (a @ e[:, :, None])[:, :, 0].reshape(-1)
            jac = sparse_jacobian([block_triplets(a @ jac_i, rows, column[ij[:, 0]]),
                                   block_triplets(a @ jac_j, rows, column[ij[:, 1]])], (len(r), 3 * int(free.sum())))
            return (jac.T @ jac).tocsc(), jac.T @ r

        settings = Settings(initial_lambda=initial_lambda, relative_tolerance=relative_tolerance,
                            absolute_tolerance=absolute_tolerance)
        state, result = levenberg_marquardt(cost, linearize, x[free].reshape(-1), int(free.sum()), max_iterations,
                                            settings)
        self._poses = [row.copy() for row in placed(state)]
        return result

    # ----------------------------------------------------------------- g2o I/O
    @classmethod
    def read_g2o(cls, path: str | Path) -> PoseGraph:
        """Read ``VERTEX_SE2`` / ``EDGE_SE2`` (upper-triangle information) and ``FIX`` lines.

        Vertex ids may be any integers; they are renumbered in file order. Vertex 0 of the
        file order stays fixed unless ``FIX`` lines name others.
        """
        graph = cls()
        ids: dict[int, int] = {}
        edges: list[tuple[int, int, list[float], list[float]]] = []
        fixed: list[int] = []
        path = Path(path)
        with path.open("r", encoding="ascii", errors="replace") as handle:
            for number, line in enumerate(handle, 1):
                tokens = line.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                try:
                    if tokens[0] == "VERTEX_SE2" and len(tokens) == 5:
                        if int(tokens[1]) in ids:
                            raise ValueError(f"vertex {tokens[1]} defined twice")
                        ids[int(tokens[1])] = graph.add_node([float(t) for t in tokens[2:5]])
                    elif tokens[0] == "EDGE_SE2" and len(tokens) == 12:
                        values = [float(t) for t in tokens[3:12]]
                        edges.append((int(tokens[1]), int(tokens[2]), values[:3], values[3:]))
                    elif tokens[0] == "FIX":
                        fixed.extend(int(t) for t in tokens[1:])
                    else:
                        raise ValueError(f"unsupported record {tokens[0]!r} with {len(tokens)} fields")
                except ValueError as error:
                    raise UserError(f"{path}:{number}: not a 2-D g2o line ({error})") from None
        for i, j, z, upper in edges:
            if i not in ids or j not in ids:
                raise UserError(f"{path}: edge {i} -> {j} names a vertex that is not defined")
            a, b, c, d, e, f = upper
            try:
                graph.add_edge(ids[i], ids[j], z, [[a, b, c], [b, d, e], [c, e, f]])
            except ValueError as error:
                raise UserError(f"{path}: {error}") from None
        if fixed:
            graph.fixed = {ids[k] for k in fixed if k in ids}
        return graph

    def write_g2o(self, path: str | Path) -> None:
        """Write the graph as g2o text (``VERTEX_SE2``, ``EDGE_SE2``, one ``FIX`` line)."""
        ij, z, info = self.edges
        lines = [f"VERTEX_SE2 {k} {p[0]:.9g} {p[1]:.9g} {p[2]:.9g}" for k, p in enumerate(self.poses)]
        rows, cols = np.triu_indices(3)
        for (i, j), m, upper in zip(ij, z, info[:, rows, cols], strict=True):
            numbers = " ".join(f"{v:.17g}" for v in (*m, *upper))
            lines.append(f"EDGE_SE2 {i} {j} {numbers}")
        if self.fixed:
            lines.append("FIX " + " ".join(str(k) for k in sorted(self.fixed)))
        write_text(path, "\n".join(lines) + "\n", replace=True)


read_g2o = PoseGraph.read_g2o


def _solve_linear_chain(values: np.ndarray, ij: np.ndarray, measured: np.ndarray, whitening: np.ndarray,
                        anchored: np.ndarray) -> np.ndarray:
    """Weighted linear least squares ``v_j - v_i = m`` over the non-anchored nodes.

    ``values`` (N, d) holds the anchored nodes' values (kept) and is returned with the others
    solved; ``whitening`` (E, d, d) is the square root of each equation's information.
    """
    n, d = values.shape
    column = np.full(n, -1, dtype=np.int64)
    column[~anchored] = d * np.arange(int((~anchored).sum()))
    if (~anchored).sum() == 0:
        return values.copy()
    eye = np.broadcast_to(np.eye(d), (len(ij), d, d))
    rows = d * np.arange(len(ij))
    jac = sparse_jacobian([block_triplets(-whitening @ eye, rows, column[ij[:, 0]]),
                           block_triplets(whitening @ eye, rows, column[ij[:, 1]])],
                          (d * len(ij), d * int((~anchored).sum())))
    constant = values[ij[:, 1]] * anchored[ij[:, 1], None] - values[ij[:, 0]] * anchored[ij[:, 0], None]
    residual = (whitening @ (measured - constant)[:, :, None])[:, :, 0].reshape(-1)
    normal = (jac.T @ jac).tocsc()
    solution = solve_spd(normal, jac.T @ residual)
    out = values.copy()
    out[~anchored] = np.asarray(solution).reshape(-1, d)
    return out
