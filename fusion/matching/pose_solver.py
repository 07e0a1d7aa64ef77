"""The scan matcher's refinement, compiled: the whole Levenberg-Marquardt solve of one planar pose against
a match field window in one call (numba, cached on disk).

Each evaluation places the points, reads their residuals (:func:`field_residuals`, point to field or to
line), weighs them with the Huber kernel and, once accepted, forms the 3 x 3 normal equations; the
loop follows :func:`trundle.fusion.optimization.levenberg_marquardt.levenberg_marquardt` step for step
with Marquardt's diagonal damping (the schedule is :data:`trundle.fusion.matching.scan_matching.MATCH_SETTINGS`,
passed in). In Python the loop cost a dozen small numpy calls per evaluation and the normal equations
a LAPACK call per step; a match makes five to twenty of each.

A window holds the fields only where a match asked for them: when a pose places a point beyond it,
the solve stops with ``GROW`` and the box (continuous cell coordinates) it needs, and the caller grows
the window and solves again from the start (the distances are exact wherever the window reaches, so the
values read do not depend on its extent; the Python loop read the grown window from that step on instead).
"""

from __future__ import annotations

import math

import numpy as np

from trundle.fusion.compiled import kernel
from trundle.fusion.matching.field_residuals import field_residuals

DONE, GROW = 0, 1


@kernel
def solve3(matrix: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``matrix^-1 rhs`` of a 3 x 3 system by LU with partial pivoting (LAPACK's ``gesv`` order of
    operations); NaN when a pivot is exactly zero (singular, where numpy raises)."""
    a = matrix.copy()
    x = rhs.copy()
    for k in range(3):
        p = k
        for i in range(k + 1, 3):
            if abs(a[i, k]) > abs(a[p, k]):
                p = i
        if a[p, k] == 0.0:
            return np.full(3, np.nan)
        if p != k:
            for j in range(3):
                a[k, j], a[p, j] = a[p, j], a[k, j]
            x[k], x[p] = x[p], x[k]
        inverse = 1.0 / a[k, k]
        for i in range(k + 1, 3):
            a[i, k] *= inverse
            for j in range(k + 1, 3):
                a[i, j] -= a[i, k] * a[k, j]
    for i in range(3):
        for j in range(i):
            x[i] -= a[i, j] * x[j]
    for i in range(2, -1, -1):
        for j in range(i + 1, 3):
            x[i] -= a[i, j] * x[j]
        x[i] /= a[i, i]
    return x


@kernel
def _evaluate(squared: np.ndarray, distances: np.ndarray, occupied: np.ndarray, starts: np.ndarray, cols: np.ndarray,
              occupied_row0: int, occupied_col0: int, radius: int, nearest: np.ndarray, mean: np.ndarray,
              normal: np.ndarray, is_line: np.ndarray, bounds: np.ndarray, extent: np.ndarray, px: np.ndarray,
              py: np.ndarray, pose: np.ndarray, origin: np.ndarray, resolution: float, max_distance_m: float,
              huber_m: float
              ) -> tuple[bool, np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Huber cost, residuals, Jacobian, IRLS weights and active mask of the points at ``pose``; first,
    whether the window ``bounds`` (r0, r1, c0, c1) holds them within the fields' ``extent`` (r0, r1, c0, c1; off
    it every field has its far value) and the box (c_min, c_max, r_min, r_max) they need."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    n = px.shape[0]
    rx, ry, cx, cy = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    tx, ty = pose[0] - origin[0], pose[1] - origin[1]
    for i in range(n):   # numpy's four expressions element by element, in one pass
        rx[i] = c * px[i] - s * py[i]
        ry[i] = s * px[i] + c * py[i]
        cx[i] = (rx[i] + tx) / resolution
        cy[i] = (ry[i] + ty) / resolution
    box = np.array([np.min(cx), np.max(cx), np.min(cy), np.max(cy)]) if len(cx) else np.zeros(4)
    if len(cx):
        c_lo, c_hi = max(int(np.floor(box[0])) - 1, extent[2]), min(int(np.floor(box[1])) + 2, extent[3])
        r_lo, r_hi = max(int(np.floor(box[2])) - 1, extent[0]), min(int(np.floor(box[3])) + 2, extent[1])
        if r_lo < bounds[0] or r_hi > bounds[1] or c_lo < bounds[2] or c_hi > bounds[3]:
            empty = np.zeros(0)
            return False, box, 0.0, empty, np.zeros((0, 3)), empty, np.zeros(0, np.bool_)
    d, jac, active = field_residuals(squared, distances, occupied, starts, cols, occupied_row0, occupied_col0, radius,
                                     nearest, mean, normal, is_line, bounds[0], bounds[2], cx, cy, pose[0], pose[1],
                                     rx, ry, resolution, max_distance_m)
    k2 = huber_m * huber_m
    weight = np.empty(len(d))
    cost = 0.0
    for i in range(len(d)):
        r2 = d[i] * d[i]
        if r2 <= k2:
            cost += r2
            weight[i] = 1.0
        else:
            root = math.sqrt(max(r2, 1e-300))
            cost += 2.0 * huber_m * root - k2
            weight[i] = huber_m / root
    return True, box, cost, d, jac, weight, active


@kernel
def solve_pose_in_window(squared: np.ndarray, distances: np.ndarray, occupied: np.ndarray, starts: np.ndarray,
                         cols: np.ndarray, occupied_row0: int, occupied_col0: int, radius: int, nearest: np.ndarray,
                         mean: np.ndarray, normal: np.ndarray, is_line: np.ndarray, bounds: np.ndarray,
                         extent: np.ndarray, px: np.ndarray, py: np.ndarray, initial_pose: np.ndarray,
                         origin: np.ndarray, resolution: float, max_distance_m: float, huber_m: float,
                         max_iterations: int, schedule: np.ndarray, step_tolerance: np.ndarray
                         ) -> tuple[int, np.ndarray, np.ndarray, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over one pose (x m, y m, theta rad; Euclidean, theta wrapped at the end) minimising
    the Huber cost of the points (``px``, ``py``, robot frame) against the window (grid cell (0, 0) at
    ``origin``; the window's fields and walls as :func:`field_residuals` takes them, ``is_line`` empty: point
    to field; the cells it may hold, ``extent``, as :func:`_evaluate` takes it).

    ``schedule`` = initial lambda, lambda factor, min lambda, max lambda, min model fidelity, min diagonal,
    relative tolerance, absolute tolerance (Marquardt damping). Returns the status (``DONE`` or ``GROW``),
    the box needed (``GROW``), the pose, the iterations and the last evaluation's residuals, Jacobian,
    weights and active mask (at the pose before its angle is wrapped).
    """
    initial_lambda, factor, min_lambda, max_lambda = schedule[0], schedule[1], schedule[2], schedule[3]
    min_fidelity, min_diagonal, relative, absolute = schedule[4], schedule[5], schedule[6], schedule[7]
    x = initial_pose.copy()
    ok, box, current, d, jac, weight, active = _evaluate(
        squared, distances, occupied, starts, cols, occupied_row0, occupied_col0, radius, nearest, mean, normal,
        is_line, bounds, extent, px, py, x, origin, resolution, max_distance_m, huber_m)
    if not ok:
        return GROW, box, x, 0, d, jac, weight, active
    lam = initial_lambda
    iterations = 0
    converged = False
    hessian = np.zeros((3, 3))
    gradient = np.zeros(3)
    while iterations < max_iterations:
        hessian[:] = 0.0
        gradient[:] = 0.0
        for i in range(len(d)):
            for a in range(3):
                jw = jac[i, a] * weight[i]
                gradient[a] += jw * d[i]
                for b in range(3):
                    hessian[a, b] += jw * jac[i, b]
        diagonal = np.array([max(hessian[0, 0], min_diagonal), max(hessian[1, 1], min_diagonal),
                             max(hessian[2, 2], min_diagonal)])
        accepted = False
        while iterations < max_iterations and not accepted:
            iterations += 1
            damped = hessian.copy()
            for a in range(3):
                damped[a, a] += lam * diagonal[a]
            dx = solve3(damped, -gradient)
            if not (math.isfinite(dx[0]) and math.isfinite(dx[1]) and math.isfinite(dx[2])):
                lam *= factor
                continue
            candidate = x + dx
            ok, box, new_cost, nd, njac, nweight, nactive = _evaluate(
                squared, distances, occupied, starts, cols, occupied_row0, occupied_col0, radius, nearest, mean,
                normal, is_line, bounds, extent, px, py, candidate, origin, resolution, max_distance_m, huber_m)
            if not ok:
                return GROW, box, x, iterations, d, jac, weight, active
            predicted = 0.0   # -2 dx.g - dx.H.dx
            small = True
            for a in range(3):
                predicted -= 2.0 * dx[a] * gradient[a]
                for b in range(3):
                    predicted -= dx[a] * hessian[a, b] * dx[b]
                small = small and abs(dx[a]) < step_tolerance[a]
            fidelity = (current - new_cost) / predicted if predicted > 0 else -1.0
            if fidelity > min_fidelity:
                accepted = True
                decrease = current - new_cost
                x, current = candidate, new_cost
                d, jac, weight, active = nd, njac, nweight, nactive
                lam = max(lam / factor, min_lambda)
                converged = small or decrease < relative * current or decrease < absolute
            elif small:
                converged = True
                break
            else:
                lam *= factor
                if lam > max_lambda:
                    converged = True
                    break
        if converged or not accepted:
            break
    x[2] = (x[2] + math.pi) % (2.0 * math.pi) - math.pi
    return DONE, box, x, iterations, d, jac, weight, active
