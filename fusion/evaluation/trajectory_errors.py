"""SLAM accuracy: the relation-based error of Kuemmerle et al. (2009), ATE and RPE, and their inputs.

A *relation* is the pose of the robot at time ``t2`` expressed in its frame at ``t1``. The
relation error compares the estimated relative motion ``delta = x1^-1 (+) x2`` with the reference
relation: translational error ``|t_delta - t_ref|`` (m), rotational error
``|wrap(theta_delta - theta_ref)|``; reported as mean and standard deviation (population, ddof 0)
of the absolute and squared errors over all relations, as in Kuemmerle et al., Autonomous Robots
27(4), 2009 and the tables of Hess et al., ICRA 2016. Relations come from a Freiburg
``.relations`` file or from a reference trajectory (consecutive scans, or every ``step`` scans).
ATE aligns the estimate to the reference by the least-squares rigid motion in SE(2) (Umeyama 1991
without scale) and reports position errors; RPE (Sturm et al. 2012) is the RMSE of the relation
errors at a fixed separation.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from trundle.fusion.geometry import compose, relative, wrap_angle
from trundle.fusion.mapping.map_io import read_trajectory_csv
from trundle.logs.errors import DataError, UserError
from trundle.logs.paths import input_file
from trundle.logs.stamps import seconds_ns

DEFAULT_TOLERANCE_NS = 1_000_000  # 1 ms: scans are tens of milliseconds apart


@dataclass(frozen=True)
class Trajectory:
    """Poses (N, 3) ``x, y, theta`` (m, rad) at ``stamps_ns`` (N,) int64 nanoseconds."""

    stamps_ns: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_ns, dtype=np.int64).reshape(-1)
        poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 3)
        if len(stamps) != len(poses):
            raise ValueError(f"{len(stamps)} stamps for {len(poses)} poses")
        object.__setattr__(self, "stamps_ns", stamps)
        object.__setattr__(self, "poses", poses)

    def __len__(self) -> int:
        return len(self.stamps_ns)


@dataclass(frozen=True)
class Relations:
    """Reference relations: pose at ``t2_ns`` in the frame of the pose at ``t1_ns``, ``deltas`` (M, 3)."""

    t1_ns: np.ndarray
    t2_ns: np.ndarray
    deltas: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "t1_ns", np.asarray(self.t1_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "t2_ns", np.asarray(self.t2_ns, dtype=np.int64).reshape(-1))
        object.__setattr__(self, "deltas", np.asarray(self.deltas, dtype=np.float64).reshape(-1, 3))

    def __len__(self) -> int:
        return len(self.t1_ns)


@dataclass(frozen=True)
class MeanStd:
    mean: float
    std: float


@dataclass(frozen=True)
class RelationError:
    """Kuemmerle's four statistics over ``count`` relations (``missing`` had no estimated pose)."""

    count: int
    missing: int
    translation_abs_m: MeanStd
    translation_sq_m2: MeanStd
    rotation_abs_deg: MeanStd
    rotation_sq_deg2: MeanStd
    translation_max_m: float
    rotation_max_deg: float


@dataclass(frozen=True)
class AbsoluteError:
    """ATE after SE(2) alignment: position error statistics (m), heading RMSE (deg), the alignment."""

    count: int
    rmse_m: float
    mean_m: float
    median_m: float
    std_m: float
    max_m: float
    rotation_rmse_deg: float
    alignment_xyt: tuple[float, float, float]


@dataclass(frozen=True)
class RelativeError:
    """RPE at a separation of ``step`` poses: RMSE and mean of translational (m) and rotational (deg) error."""

    step: int
    count: int
    translation_rmse_m: float
    translation_mean_m: float
    rotation_rmse_deg: float
    rotation_mean_deg: float


# --- inputs ----------------------------------------------------------------------------------

def read_relations(path: str | Path) -> Relations:
    """A Freiburg ``.relations`` file: ``t1 t2 x y z roll pitch yaw`` per line (s, m, rad)."""
    path = Path(path)
    t1, t2, deltas = [], [], []
    with path.open("r", encoding="utf-8") as handle:
        for number, line in enumerate(handle, 1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            try:
                if len(tokens) != 8:
                    raise ValueError
                values = [float(t) for t in tokens[2:]]
                if not all(math.isfinite(v) for v in values):
                    raise ValueError
                t1.append(seconds_ns(tokens[0]))
                t2.append(seconds_ns(tokens[1]))
            except ValueError:
                raise DataError(
                    f"{path}:{number}: expected 't1 t2 x y z roll pitch yaw', got {line.strip()!r}"
                ) from None
            deltas.append([values[0], values[1], values[5]])
    if not deltas:
        raise DataError(f"{path}: no relations")
    return Relations(np.array(t1), np.array(t2), np.array(deltas))


def read_carmen_trajectory(path: str | Path) -> Trajectory:
    """The robot poses of a CARMEN log's front-laser lines (FLASER, ROBOTLASER1), at their ipc times."""
    from trundle.logs.importers.carmen import read_carmen, scan_poses

    stamps, poses = scan_poses(read_carmen(path))
    if not len(stamps):
        raise DataError(f"{path}: no FLASER or ROBOTLASER1 line with a pose")
    return Trajectory(stamps, poses)


def read_reference(path: str | Path) -> Trajectory | Relations:
    """A reference for evaluation: ``.relations`` file, ``t_ns,x,y,theta`` CSV, or CARMEN log."""
    path = input_file(path, "reference or trajectory file")
    if path.suffix == ".relations":
        return read_relations(path)
    with path.open("rb") as handle:
        start = handle.read(64)
    if start.startswith(b"t_ns,"):
        return Trajectory(*read_trajectory_csv(path))
    return read_carmen_trajectory(path)


# --- relations -------------------------------------------------------------------------------

def trajectory_relations(reference: Trajectory, step: int = 1) -> Relations:
    """Relations between poses ``step`` apart in a reference trajectory (1 = consecutive scans)."""
    if step < 1:
        raise ValueError("step must be at least 1")
    a, b = reference.poses[:-step], reference.poses[step:]
    return Relations(reference.stamps_ns[:-step], reference.stamps_ns[step:], relative(a, b))


MAX_REVISIT_POSES = 5000      # a reference thinned evenly to this many poses before pairing
MAX_REVISIT_RELATIONS = 1_000_000  # and its revisit pairs thinned evenly to this many


def revisit_relations(reference: Trajectory, max_distance_m: float = 3.0, min_gap_s: float = 30.0) -> Relations:
    """Relations between pairs of reference poses less than ``max_distance_m`` apart and more than
    ``min_gap_s`` apart in time: the places the robot came back to, where a map is doubled if it is
    (consecutive relations cannot show that; loop closure is judged here). A dense reference (100 Hz
    motion capture) is thinned evenly to ``MAX_REVISIT_POSES`` poses, and the pairs to
    ``MAX_REVISIT_RELATIONS``, so memory stays bounded; the mean error of an even sample is the
    same figure."""
    from scipy.spatial import cKDTree

    keep = np.arange(0, len(reference), max(1, -(-len(reference) // MAX_REVISIT_POSES)))
    stamps, poses = reference.stamps_ns[keep], reference.poses[keep]
    pairs = cKDTree(poses[:, :2]).query_pairs(max_distance_m, output_type="ndarray").reshape(-1, 2)
    pairs = pairs[np.abs(stamps[pairs[:, 0]] - stamps[pairs[:, 1]]) > round(min_gap_s * 1e9)]
    pairs = pairs[np.lexsort((pairs[:, 1], pairs[:, 0]))]
    if len(pairs) > MAX_REVISIT_RELATIONS:
        pairs = pairs[np.linspace(0, len(pairs) - 1, MAX_REVISIT_RELATIONS).astype(np.int64)]
    return Relations(stamps[pairs[:, 0]], stamps[pairs[:, 1]], relative(poses[pairs[:, 0]], poses[pairs[:, 1]]))


def poses_at(trajectory: Trajectory, stamps_ns: np.ndarray, tolerance_ns: int = DEFAULT_TOLERANCE_NS
             ) -> tuple[np.ndarray, np.ndarray]:
    """Poses (M, 3) of ``trajectory`` nearest to each stamp and a mask of those within ``tolerance_ns``."""
    stamps = np.asarray(stamps_ns, dtype=np.int64)
    if len(trajectory) == 0:
        return np.full((len(stamps), 3), np.nan), np.zeros(len(stamps), bool)
    order = np.argsort(trajectory.stamps_ns, kind="stable")
    sorted_stamps = trajectory.stamps_ns[order]
    right = np.clip(np.searchsorted(sorted_stamps, stamps), 0, len(order) - 1)
    left = np.clip(right - 1, 0, len(order) - 1)
    pick = np.where(np.abs(sorted_stamps[left] - stamps) <= np.abs(sorted_stamps[right] - stamps), left, right)
    found = np.abs(sorted_stamps[pick] - stamps) <= tolerance_ns
    return trajectory.poses[order[pick]], found


def relation_errors(estimate: Trajectory, relations: Relations, tolerance_ns: int = DEFAULT_TOLERANCE_NS
                    ) -> tuple[np.ndarray, np.ndarray, int]:
    """Per-relation translational (m) and rotational (rad, absolute) errors, and how many were missing."""
    p1, found1 = poses_at(estimate, relations.t1_ns, tolerance_ns)
    p2, found2 = poses_at(estimate, relations.t2_ns, tolerance_ns)
    found = found1 & found2
    delta = relative(p1[found], p2[found])
    reference = relations.deltas[found]
    translation = np.hypot(delta[:, 0] - reference[:, 0], delta[:, 1] - reference[:, 1])
    rotation = np.abs(wrap_angle(delta[:, 2] - reference[:, 2]))
    return translation, np.asarray(rotation, dtype=np.float64).reshape(-1), int((~found).sum())


def relation_error(estimate: Trajectory, relations: Relations, tolerance_ns: int = DEFAULT_TOLERANCE_NS
                   ) -> RelationError:
    """Kuemmerle et al.'s relation-based error of ``estimate`` against ``relations``."""
    translation, rotation, missing = relation_errors(estimate, relations, tolerance_ns)
    if len(translation) == 0:
        raise DataError(f"no relation has estimated poses at both times ({missing} relations, "
                        f"time tolerance {tolerance_ns / 1e6:g} ms): do the timestamps match?")
    degrees = np.degrees(rotation)

    def stats(values: np.ndarray) -> MeanStd:
        return MeanStd(float(values.mean()), float(values.std()))

    return RelationError(len(translation), missing, stats(translation), stats(translation ** 2), stats(degrees),
                         stats(degrees ** 2), float(translation.max()), float(degrees.max()))


def relative_pose_error(estimate: Trajectory, reference: Trajectory, step: int = 1,
                        tolerance_ns: int = DEFAULT_TOLERANCE_NS) -> RelativeError:
    """RPE over reference poses ``step`` apart (RMSE and mean, translation m and rotation deg)."""
    translation, rotation, _ = relation_errors(estimate, trajectory_relations(reference, step), tolerance_ns)
    if len(translation) == 0:
        raise DataError("no reference pose pair has estimated poses at both times: do the timestamps match?")
    degrees = np.degrees(rotation)
    return RelativeError(step, len(translation), float(np.sqrt(np.mean(translation ** 2))), float(translation.mean()),
                         float(np.sqrt(np.mean(degrees ** 2))), float(degrees.mean()))


# --- absolute error --------------------------------------------------------------------------

def align_se2(source_xy: np.ndarray, target_xy: np.ndarray) -> np.ndarray:
    """The rigid motion ``(x, y, theta)`` minimising ``sum |R source + t - target|^2`` (Umeyama, no scale)."""
    source = np.asarray(source_xy, dtype=np.float64).reshape(-1, 2)
    target = np.asarray(target_xy, dtype=np.float64).reshape(-1, 2)
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    s, t = source - ms, target - mt
    theta = math.atan2(
        float(np.sum(s[:, 0] * t[:, 1] - s[:, 1] * t[:, 0])), float(np.sum(s[:, 0] * t[:, 0] + s[:, 1] * t[:, 1]))
    )
    c, si = math.cos(theta), math.sin(theta)
    shift = mt - np.array([c * ms[0] - si * ms[1], si * ms[0] + c * ms[1]])
    return np.array([shift[0], shift[1], theta])


def absolute_trajectory_error(estimate: Trajectory, reference: Trajectory, tolerance_ns: int = DEFAULT_TOLERANCE_NS,
                              align: bool = True) -> AbsoluteError:
    """ATE: position errors of the estimate at the reference's stamps after SE(2) alignment."""
    poses, found = poses_at(estimate, reference.stamps_ns, tolerance_ns)
    if not found.any():
        raise DataError("no reference pose has an estimated pose at its time: do the timestamps match?")
    estimated, truth = poses[found], reference.poses[found]
    alignment = align_se2(estimated[:, :2], truth[:, :2]) if align else np.zeros(3)
    aligned = compose(alignment, estimated)
    error = np.hypot(aligned[:, 0] - truth[:, 0], aligned[:, 1] - truth[:, 1])
    heading = np.degrees(wrap_angle(aligned[:, 2] - truth[:, 2]))
    return AbsoluteError(int(found.sum()), float(np.sqrt(np.mean(error ** 2))), float(error.mean()),
                         float(np.median(error)), float(error.std()), float(error.max()),
                         float(np.sqrt(np.mean(np.square(heading)))),
                         (float(alignment[0]), float(alignment[1]), float(alignment[2])))


@dataclass(frozen=True)
class LandmarkError:
    """Mapped landmarks against surveyed ones after an SE(2) alignment: position errors (m) over the
    ``count`` landmarks in both, and the ids only in the reference (``missing``) or only mapped (``extra``)."""

    count: int
    mean_m: float
    rmse_m: float
    median_m: float
    max_m: float
    per_landmark_m: dict[str, float]
    missing: list[str]
    extra: list[str]


def landmark_error(ids: list[str], positions: np.ndarray, reference_ids: list[str], reference_positions: np.ndarray,
                   alignment_xyt) -> LandmarkError:
    """Errors of mapped landmarks (map frame) against the reference, the map placed by ``alignment_xyt``
    (e.g. the trajectory's ATE alignment, so map and path are judged in one frame)."""
    reference = {name: np.asarray(p, np.float64) for name, p in zip(reference_ids, reference_positions, strict=True)}
    mapped = {name: np.asarray(p, np.float64) for name, p in zip(ids, positions, strict=True)}
    common = [name for name in mapped if name in reference]
    if not common:
        raise DataError("no mapped landmark has an id of the reference landmarks")
    aligned = compose(np.asarray(alignment_xyt, np.float64),
                      np.column_stack([np.array([mapped[n] for n in common]), np.zeros(len(common))]))[:, :2]
    errors = np.hypot(*(aligned - np.array([reference[n] for n in common])).T)
    return LandmarkError(len(common), float(errors.mean()), float(np.sqrt(np.mean(errors ** 2))),
                         float(np.median(errors)), float(errors.max()),
                         {n: float(e) for n, e in zip(common, errors, strict=True)},
                         sorted(set(reference) - set(mapped)), sorted(set(mapped) - set(reference)))


def evaluate(result: Trajectory, reference: Trajectory | Relations, step: int = 1, tolerance_ns: int = 1_000_000,
             revisit_m: float = 3.0, revisit_s: float = 30.0) -> dict:
    """All metrics as a JSON-ready dict (``ate``, ``rpe`` and ``revisits`` only for a reference trajectory)."""
    if step < 1:
        raise UserError(f"--step must be at least 1, got {step}")
    if isinstance(reference, Trajectory):
        if len(reference) <= step:
            raise UserError(f"the reference has {len(reference)} poses: too few for relations {step} apart")
        report = {"relations": f"reference poses {step} apart",
                  "relation_error": asdict(relation_error(result, trajectory_relations(reference, step), tolerance_ns)),
                  "ate": asdict(absolute_trajectory_error(result, reference, tolerance_ns)),
                  "rpe": asdict(relative_pose_error(result, reference, step, tolerance_ns)),
                  "revisits": {"max_distance_m": revisit_m, "min_gap_s": revisit_s,
                               **_revisit_error(result, revisit_relations(reference, revisit_m, revisit_s),
                                                tolerance_ns)}}
    else:
        report = {
            "relations": "relations file",
            "relation_error": asdict(relation_error(result, reference, tolerance_ns)),
        }
    return report


def _revisit_error(result: Trajectory, relations: Relations, tolerance_ns: int) -> dict:
    """The relation error over revisits, or ``{"count": 0}`` when the reference (or the part of it the
    result covers) never comes back to a place."""
    covered = poses_at(result, relations.t1_ns, tolerance_ns)[1] & poses_at(result, relations.t2_ns,
                                                                                 tolerance_ns)[1]
    return asdict(relation_error(result, relations, tolerance_ns)) if covered.any() else {"count": 0}
