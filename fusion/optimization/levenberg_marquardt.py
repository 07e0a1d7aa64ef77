"""The one Levenberg-Marquardt loop: damped normal equations, SE(2) retraction, GTSAM's damping schedule.

A problem is a state vector ``x`` whose first ``3 P`` entries are ``P`` planar poses
``(x m, y m, theta rad)`` and whose remaining entries are Euclidean (points, metres), and two
functions: ``cost(x)``, the (robust) sum of squared whitened errors, and ``linearize(x)``, the
Gauss-Newton normal equations ``(H, g) = (J^T W J, J^T W r)`` of the whitened residuals ``r``
with IRLS weights ``W`` at ``x``. ``H`` is a SciPy sparse matrix (a graph: solved by SuperLU with
a fill-reducing order) or a small dense array (a scan match: solved densely); the loop is the
same. Each step solves ``(H + lambda D) dx = -g`` with ``D = I`` (Levenberg) or the clamped
diagonal of ``H`` (Marquardt, GTSAM's ``diagonalDamping``), moves the poses along SE(2)'s
exponential map (:func:`retract`) and the rest additively, and is accepted when the cost falls by
more than ``min_model_fidelity`` of what the linearisation predicts; then ``lambda`` is divided
by ``lambda_factor``, else multiplied (GTSAM's ``LevenbergMarquardtOptimizer`` schedule).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from trundle.fusion.geometry import wrap_angle

Sparse: TypeAlias = sp.spmatrix | sp.sparray
Matrix: TypeAlias = np.ndarray | Sparse
# What ``linearize`` returns: ``H`` dense, or sparse in CSC (SuperLU's format; the graphs build it with ``tocsc()``).
Hessian: TypeAlias = np.ndarray | sp.csc_matrix
Linearization: TypeAlias = tuple[Hessian, np.ndarray]


@dataclass(frozen=True)
class OptimizeResult:
    """Outcome of an optimisation.

    ``chi2`` and ``initial_chi2`` are the (robustified, when a kernel is used) sums of
    weighted squared errors; ``iterations`` counts accepted and rejected LM steps;
    ``converged`` is False when ``max_iterations`` ran out first.
    """

    chi2: float
    initial_chi2: float
    iterations: int
    converged: bool


@dataclass(frozen=True)
class Settings:
    """Damping schedule and stopping rules of :func:`levenberg_marquardt` (defaults: GTSAM's, for graphs).

    initial_lambda : damping at the start.
    lambda_factor : ``lambda`` is divided by it after an accepted step, multiplied after a rejected one.
    min_lambda : floor of ``lambda`` after accepted steps.
    max_lambda : stop (converged) when ``lambda`` grows beyond it: no step can lower the cost.
    min_model_fidelity : a step is accepted when the cost falls by more than this share of the
        decrease the linearisation predicts (0: any decrease).
    diagonal_damping : damp with ``lambda diag(H)`` (each diagonal entry at least ``min_diagonal``)
        instead of ``lambda I``: scale-invariant, for small problems whose variables differ in scale.
    relative_tolerance, absolute_tolerance : stop when an accepted step lowers the cost by less
        than ``relative_tolerance * cost`` or below ``absolute_tolerance``.
    step_tolerance : bounds of ``|dx|``, one for every entry of the state (or one for all); stop
        when a step, accepted or not, is below them in every entry. None: no such rule.
    """

    initial_lambda: float = 1e-5
    lambda_factor: float = 10.0
    min_lambda: float = 0.0
    max_lambda: float = 1e16
    min_model_fidelity: float = 1e-3
    diagonal_damping: bool = False
    min_diagonal: float = 1e-6
    relative_tolerance: float = 1e-6
    absolute_tolerance: float = 1e-9
    step_tolerance: tuple[float, ...] | None = None


def retract(poses: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Poses (N, 3) moved by a Gauss-Newton ``step`` (map-frame first-order increments, (N, 3)) along SE(2)'s
    exponential map: ``x (+) Exp(d)`` with ``d`` the step in the pose's own frame.

    To first order this is ``x + step``, so the Jacobians stay those of the additive update; along
    the exponential map a turning step moves a pose on an arc, not a chord. Measured on the
    Victoria Park graph: from GTSAM's initial values, the additive update stops in a local minimum
    with chi2 342,000, this one (GTSAM's ``Pose2`` retraction) at GTSAM's 210,000.
    As planar rotations commute, the body-frame step ``R^T dt`` mapped back by ``R`` leaves the
    translation ``V(w) dt``: ``dt`` turned by ``w / 2`` and scaled by ``sin(w / 2) / (w / 2)``.
    """
    half = 0.5 * step[:, 2]
    scale = np.sinc(half / np.pi)   # sin(h) / h, 1 at h = 0
    c, s = scale * np.cos(half), scale * np.sin(half)
    out = poses + step
    out[:, 0] = poses[:, 0] + c * step[:, 0] - s * step[:, 1]
    out[:, 1] = poses[:, 1] + s * step[:, 0] + c * step[:, 1]
    out[:, 2] = wrap_angle(out[:, 2])
    return out


def update(x: np.ndarray, dx: np.ndarray, poses: int) -> np.ndarray:
    """The state ``x`` moved by ``dx``: its first ``poses`` poses by :func:`retract`, the rest additively."""
    out = x + dx
    head = 3 * poses
    if head:   # a scan match's pose is Euclidean to the loop (poses 0): nothing to retract, many times a scan
        out[:head] = retract(x[:head].reshape(-1, 3), dx[:head].reshape(-1, 3)).reshape(-1)
    return out


def factor_spd(matrix: Sparse) -> spla.SuperLU | None:
    """SuperLU factors (COLAMD order, diagonal pivots) of a sparse symmetric positive-definite matrix;
    None when it is exactly singular."""
    try:
        return spla.splu(sp.csc_matrix(matrix), permc_spec="COLAMD", diag_pivot_thresh=0.0,
                         options={"SymmetricMode": True})
    except RuntimeError:
        return None


def solve_spd(matrix: Matrix, rhs: np.ndarray) -> np.ndarray:
    """Solve a symmetric positive-definite system, sparse (SuperLU) or dense; NaN when it is singular."""
    if isinstance(matrix, np.ndarray):   # not sparse
        try:
            return np.linalg.solve(matrix, rhs)
        except np.linalg.LinAlgError:
            return np.full(np.shape(rhs), np.nan)
    factor = factor_spd(matrix)
    return np.full(np.shape(rhs), np.nan) if factor is None else factor.solve(rhs)


def block_triplets(blocks: np.ndarray, first_row: np.ndarray, first_column: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Values, rows and columns of per-factor Jacobian blocks (F, d, w) placed at ``first_row`` (F,) and
    ``first_column`` (F,) of a sparse matrix; blocks whose column is negative (a fixed variable) are left out."""
    count, d, w = blocks.shape
    keep = first_column >= 0
    rows = np.broadcast_to(first_row[keep][:, None, None] + np.arange(d)[None, :, None], (int(keep.sum()), d, w))
    cols = np.broadcast_to(first_column[keep][:, None, None] + np.arange(w)[None, None, :], (int(keep.sum()), d, w))
    return blocks[keep].reshape(-1), rows.reshape(-1), cols.reshape(-1)


def sparse_jacobian(triplets: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], shape: tuple[int, int]
                    ) -> sp.csr_matrix:
    """A sparse (rows, columns) matrix of :func:`block_triplets` pieces (duplicates add up)."""
    if not triplets:
        return sp.csr_matrix(shape)
    data, rows, cols = (np.concatenate(part) for part in zip(*triplets, strict=True))
    return sp.csr_matrix((data, (rows, cols)), shape=shape)


def _damped(hessian: Hessian, settings: Settings) -> Callable[[float], Hessian]:
    """``lambda -> H + lambda D`` with ``D`` the identity, or the clamped diagonal of ``H``; sparse when ``H`` is."""
    n = hessian.shape[0]
    diagonal = np.maximum(np.asarray(hessian.diagonal()), settings.min_diagonal) if settings.diagonal_damping else None
    if isinstance(hessian, np.ndarray):   # dense
        dense = np.eye(n) if diagonal is None else np.diag(diagonal)
        return lambda lam: hessian + lam * dense
    sparse = sp.identity(n, format="csc") if diagonal is None else sp.diags(diagonal, format="csc")
    return lambda lam: hessian + lam * sparse


def levenberg_marquardt(cost: Callable[[np.ndarray], float], linearize: Callable[[np.ndarray], Linearization],
                        x0: np.ndarray, poses: int, max_iterations: int, settings: Settings = Settings()
                        ) -> tuple[np.ndarray, OptimizeResult]:
    """Minimise ``cost`` from ``x0`` (flat; its first ``poses`` triples are SE(2) poses); see the module docstring.

    ``linearize(x)`` is only called at a state that ``cost`` was called with last, so a problem
    may compute both at once. Returns the final state and the :class:`OptimizeResult`.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    current = initial = float(cost(x))
    if x.size == 0:
        return x, OptimizeResult(current, initial, 0, True)
    tolerance = None if settings.step_tolerance is None else np.asarray(settings.step_tolerance, dtype=np.float64)
    lam = settings.initial_lambda
    iterations, converged = 0, False
    while iterations < max_iterations:
        hessian, gradient = linearize(x)
        damped = _damped(hessian, settings)
        accepted = False
        while iterations < max_iterations and not accepted:
            iterations += 1
            dx = solve_spd(damped(lam), -gradient)
            if not np.isfinite(dx).all():
                lam *= settings.lambda_factor
                continue
            candidate = update(x, dx, poses)
            new_cost = float(cost(candidate))
            predicted = -2.0 * float(dx @ gradient) - float(dx @ (hessian @ dx))
            fidelity = (current - new_cost) / predicted if predicted > 0 else -1.0
            small = tolerance is not None and bool((np.abs(dx) < tolerance).all())
            if fidelity > settings.min_model_fidelity:
                accepted = True
                decrease = current - new_cost
                x, current = candidate, new_cost
                lam = max(lam / settings.lambda_factor, settings.min_lambda)
                converged = (small or decrease < settings.relative_tolerance * current
                             or decrease < settings.absolute_tolerance)
            elif small:   # even the step that failed to help was negligible
                converged = True
                break
            else:
                lam *= settings.lambda_factor
                if lam > settings.max_lambda:
                    converged = True
                    break
        if converged or not accepted:
            break
    return x, OptimizeResult(current, initial, iterations, converged)
