"""The SLAM estimators behind one protocol, and the one registry that names and builds them.

The daemon, ``trundle slam``, the demo, replay and the fleet build an estimator only through
:func:`make_estimator`; ``--estimator`` offers :func:`choices`. The estimators:

- ``grid``: the grid SLAM (:class:`trundle.fusion.slam.grid_slam.Slam`): scans and odometry;
- ``grid-landmarks``: the grid SLAM with landmark sightings in its pose graph
  (:class:`trundle.fusion.slam.landmark_grid_slam.LandmarkConstraints`);
- ``ekf``: EKF-SLAM of the landmarks (:class:`trundle.fusion.slam.landmark_slam.EkfLandmarkSlam`);
- ``landmark-graph``: the landmark factor graph (:class:`trundle.fusion.slam.landmark_slam.GraphLandmarkSlam`).

``graph`` (:data:`AUTO`) asks for the pose-graph estimator that fits a log (:func:`resolve`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from trundle.logs.errors import UsageError

if TYPE_CHECKING:  # the registry's names load nothing heavy (``trundle --help`` lists them)
    import numpy as np

    from trundle.fusion.mapping.occupancy_grid import LogOddsGrid
    from trundle.fusion.odometry.diff_drive import DiffDriveOdometry
    from trundle.fusion.slam.config import SlamConfig
    from trundle.fusion.slam.landmark_slam import LandmarkMap
    from trundle.logs import messages as m


class Estimator(Protocol):
    """What every SLAM estimator does: take messages, finish, and give its results."""

    def process(self, topic: str, msg: m.Message) -> Any:
        """Take one message of ``topic`` (those it does not use are ignored)."""
        ...

    def finish(self) -> None:
        """End of the input: the final optimisation."""
        ...

    def trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Stamps (ns) and map poses (N, 3)."""
        ...

    def build_map(self) -> LogOddsGrid | None:
        """The occupancy grid it made (None: it makes none; its user maps the scans at its poses)."""
        ...

    def landmarks(self) -> LandmarkMap | None:
        """The landmark map (None: it maps no landmarks)."""
        ...

    def report(self) -> dict[str, Any]:
        """Its counts and figures over the run (JSON-able)."""
        ...


@dataclass(frozen=True)
class EstimatorInputs:
    """What an estimator may be built from: the ``[slam]`` options, the wheel model (None: Odometry
    messages), the laser mount (None: from ``/tf_static``), the LandmarkList topic (None: the
    estimators' default, ``/landmarks``) and the ``[landmarks]`` table."""

    slam: SlamConfig | None = None
    odometry: DiffDriveOdometry | None = None
    laser_pose: tuple[float, float, float] | None = None
    landmark_topic: str | None = None
    landmarks: Mapping[str, Any] = field(default_factory=dict)

    @property
    def topic(self) -> str:
        """The LandmarkList topic to use."""
        from trundle.logs.topics import LANDMARK_TOPIC
        return self.landmark_topic or LANDMARK_TOPIC


def _grid(inputs: EstimatorInputs) -> Estimator:
    from trundle.fusion.slam.grid_slam import Slam
    return Slam(inputs.slam, inputs.odometry, inputs.laser_pose)


def _grid_landmarks(inputs: EstimatorInputs) -> Estimator:
    from trundle.fusion.slam.grid_slam import Slam
    from trundle.fusion.slam.landmark_grid_slam import LandmarkConstraints
    return Slam(inputs.slam, inputs.odometry, inputs.laser_pose, LandmarkConstraints(inputs.slam, inputs.topic))


def _ekf(inputs: EstimatorInputs) -> Estimator:
    from trundle.fusion.slam.landmark_slam import EkfLandmarkSlam, landmark_configs
    return EkfLandmarkSlam(landmark_configs(inputs.landmarks)[0], inputs.topic)


def _landmark_graph(inputs: EstimatorInputs) -> Estimator:
    from trundle.fusion.slam.landmark_slam import GraphLandmarkSlam, landmark_configs
    return GraphLandmarkSlam(landmark_configs(inputs.landmarks)[1], inputs.topic)


ESTIMATORS: dict[str, Callable[[EstimatorInputs], Estimator]] = {
    "grid": _grid,
    "grid-landmarks": _grid_landmarks,
    "ekf": _ekf,
    "landmark-graph": _landmark_graph,
}
"""Every estimator by name, with the function that builds it."""

GRID = ("grid", "grid-landmarks")
"""The estimators that map from scans (the others from landmark sightings)."""

AUTO = "graph"
"""The choice that asks for the pose-graph estimator that fits the log (:func:`resolve`)."""


def choices() -> tuple[str, ...]:
    """What ``--estimator`` accepts: :data:`AUTO` and every estimator's name."""
    return (AUTO, *ESTIMATORS)


def resolve(choice: str | None, scans: bool, landmarks: bool) -> str:
    """The estimator for ``choice`` (None or :data:`AUTO`: the pose graph that fits the log: the grid
    SLAM, with landmarks when the log has sightings, and the landmark graph for sightings without
    scans) on a log with ``scans`` and/or landmark sightings; an unknown choice is a UsageError."""
    if choice not in (None, *choices()):
        raise UsageError(f"unknown estimator {choice!r} (choose {', '.join(choices())})")
    if choice in (None, AUTO):
        if not scans and landmarks:
            return "landmark-graph"
        return "grid-landmarks" if landmarks else "grid"
    return choice


def make_estimator(name: str, inputs: EstimatorInputs | None = None) -> Estimator:
    """The estimator ``name`` built from ``inputs`` (default: every default); an unknown name is a UsageError."""
    build = ESTIMATORS.get(name)
    if build is None:
        raise UsageError(f"unknown estimator {name!r} (choose {', '.join(ESTIMATORS)})")
    return build(inputs or EstimatorInputs())
