"""The grid SLAM's options: the ``[slam]`` table of a robot config, one sub-table per component.

``[slam.scan]`` (which scans, which returns), ``[slam.tracking]`` (scan-to-submap matching),
``[slam.keyframes]`` (the motion filter), ``[slam.submaps]``, ``[slam.odometry]`` (its noise
model and check), ``[slam.loop_closure]``, ``[slam.optimization]`` and ``[slam.map_check]``.
Metres, radians, seconds. Each model is a strict, frozen :class:`trundle.logs.schema.Schema`:
every float is finite and inside the range its field declares, an integer refuses 25.7, a number
refuses a string, an unknown key is refused with the known ones named. Importing this module
costs pydantic and NumPy only (no SciPy), so a config is checked before any SLAM is loaded.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, Field, model_validator

from trundle.fusion.odometry.ekf import GATE_CHI2_99
from trundle.logs.schema import Name, Pair, Schema, parse
from trundle.logs.topics import SCAN_TOPIC

ANGLE = math.pi


def _within(limit: float) -> Callable[[tuple[float, float]], tuple[float, float]]:
    """A check of a search window (low, high): both in [0, ``limit``], low <= high."""

    def check(value: tuple[float, float]) -> tuple[float, float]:
        low, high = value
        if not 0.0 <= low <= high <= limit:
            raise ValueError(f"expected [low, high] with 0 <= low <= high <= {limit:g}")
        return value

    return check


Metres = Annotated[float, Field(ge=0.0, le=100.0)]
"""A distance, 0-100 m."""
Radians = Annotated[float, Field(ge=0.0, le=ANGLE)]
"""An angle, 0-pi rad."""
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
"""A score or share, 0-1."""
Count = Annotated[int, Field(ge=0, le=1_000_000)]
"""A number of keyframes or candidates, 0-1e6."""
WindowXY = Annotated[Pair, AfterValidator(_within(100.0))]
"""A search window's translation bounds (low, high), 0-100 m."""
WindowTheta = Annotated[Pair, AfterValidator(_within(ANGLE))]
"""A search window's rotation bounds (low, high), 0-pi rad."""


class ScanOptions(Schema):
    """Which scans and which of their returns: ``topic``; returns outside ``min_range_m`` ..
    ``max_range_m`` are dropped; points thinned to one per ``voxel_m`` cell for matching; a scan is
    de-skewed by the velocity when the previous one is at most ``deskew_max_gap_s`` old; beams
    without a return clear ``no_return_clear_m`` of free space (0: none)."""

    topic: Name = SCAN_TOPIC
    min_range_m: Metres = 0.0
    max_range_m: Annotated[float, Field(gt=0.0, le=1000.0)] = 30.0
    voxel_m: Annotated[float, Field(ge=0.0, le=1.0)] = 0.05
    deskew: bool = True
    deskew_max_gap_s: Annotated[float, Field(ge=0.0, le=60.0)] = 0.5
    no_return_clear_m: Metres = 0.0

    @model_validator(mode="after")
    def _ranges(self) -> ScanOptions:
        if self.max_range_m <= self.min_range_m:
            raise ValueError(f"max_range_m {self.max_range_m} must be above min_range_m {self.min_range_m}")
        return self


class TrackingOptions(Schema):
    """Scan-to-submap matching: search windows are three standard deviations of the prediction,
    clipped to ``search_window_*`` (low, high); a match below ``min_match_score`` is none, a poorer
    than usual one is believed only within ``gate_chi2`` (squared Mahalanobis, 3 dof) of the
    prediction; without odometry the motion model starts from ``motion_prior_sigma_*`` per scan."""

    search_window_xy_m: WindowXY = (0.1, 2.0)
    search_window_theta_rad: WindowTheta = (math.radians(3.0), math.radians(45.0))
    search_angular_step_rad: Annotated[float, Field(gt=0.0, le=0.5)] = math.radians(0.5)
    search_prior_scale: Annotated[float, Field(gt=0.0, le=100.0)] = 2.0
    min_match_score: Fraction = 0.3
    gate_chi2: Annotated[float, Field(gt=0.0, le=1e4)] = GATE_CHI2_99
    motion_prior_sigma_xy_m: Annotated[float, Field(gt=0.0, le=10.0)] = 0.3
    motion_prior_sigma_theta_rad: Annotated[float, Field(gt=0.0, le=ANGLE)] = math.radians(10.0)


class KeyframeOptions(Schema):
    """The motion filter: a scan becomes a keyframe after ``distance_m``, ``angle_rad`` or ``time_s``."""

    distance_m: Metres = 0.2
    angle_rad: Radians = math.radians(10.0)
    time_s: Annotated[float, Field(ge=0.0, le=3600.0)] = 5.0


class SubmapOptions(Schema):
    """Submaps: grid ``resolution`` (m per cell, 1 mm - 1 m) and keyframes per submap."""

    resolution: Annotated[float, Field(ge=0.001, le=1.0)] = 0.05
    scans_per_submap: Annotated[int, Field(ge=1, le=100_000)] = 25


class OdometryOptions(Schema):
    """The odometry noise per scan step: a floor (``sigma_xy_m``, ``sigma_theta_rad``) plus per metre
    travelled and radian turned; readings further than ``timeout_s`` from a scan count as missing;
    ``check``: test each increment against the scan match and bridge those the laser contradicts."""

    sigma_xy_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.01
    sigma_theta_rad: Radians = math.radians(0.5)
    sigma_xy_per_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.2
    sigma_theta_per_m: Annotated[float, Field(ge=0.0, le=10.0)] = math.radians(5.0)
    sigma_theta_per_rad: Annotated[float, Field(ge=0.0, le=10.0)] = 0.2
    timeout_s: Annotated[float, Field(ge=0.0, le=60.0)] = 0.25
    check: bool = True


class LoopClosureOptions(Schema):
    """Loop closure: every ``every_keyframes``-th keyframe searches the ``max_candidates`` nearest
    finished submaps within ``search_radius_m`` at least ``min_node_gap`` keyframes old (and
    ``cooldown_keyframes`` after the last closure to each); windows grow ``window_per_m`` per metre
    travelled within ``window_*`` (low, high); a match needs ``min_score`` and ``min_inliers`` and
    point-to-line ICP within ``verify_*``; its covariance is at least ``min_std_*``."""

    enabled: bool = True
    every_keyframes: Annotated[int, Field(ge=1, le=1_000_000)] = 3
    min_node_gap: Count = 30
    search_radius_m: Annotated[float, Field(ge=0.0, le=1000.0)] = 6.0
    max_candidates: Count = 3
    cooldown_keyframes: Count = 5
    window_xy_m: WindowXY = (0.5, 3.0)
    window_theta_rad: WindowTheta = (math.radians(10.0), math.radians(30.0))
    window_per_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.05
    angular_step_rad: Annotated[float, Field(gt=0.0, le=0.5)] = math.radians(1.0)
    min_score: Fraction = 0.55
    min_inliers: Fraction = 0.6
    verify_xy_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.1
    verify_theta_rad: Radians = math.radians(2.0)
    min_std_xy_m: Annotated[float, Field(ge=0.0, le=10.0)] = 0.05
    min_std_theta_rad: Radians = math.radians(1.0)


class OptimizationOptions(Schema):
    """Pose-graph optimisation: after new loops, at most every ``every_keyframes`` keyframes, under
    ``robust_kernel`` (``none``: least squares)."""

    every_keyframes: Annotated[int, Field(ge=1, le=1_000_000)] = 10
    robust_kernel: Literal["cauchy", "huber", "none"] = "cauchy"

    @property
    def kernel(self) -> str | None:
        """The kernel's name for the optimiser (None: none)."""
        return None if self.robust_kernel == "none" else self.robust_kernel


class MapCheckOptions(Schema):
    """The map self-check (:func:`trundle.fusion.mapping.map_check.check_map`): a keyframe agrees within
    ``tolerance_cells``; a stretch of at least ``min_stretch`` disagreeing keyframes fails the map."""

    tolerance_cells: Annotated[float, Field(gt=0.0, le=100.0)] = 2.0
    min_stretch: Annotated[int, Field(ge=1, le=1_000_000)] = 5


class SessionOptions(Schema):
    """Continuing a map with a new session (:mod:`trundle.fusion.slam.sessions`): two consecutive submaps of
    the new session found in the old map agree on its placement within ``agree_m`` / ``agree_rad``; a session
    that joins as a new area is drawn ``new_area_gap_m`` beside the old map."""

    agree_m: Metres = 0.3
    agree_rad: Radians = math.radians(3.0)
    new_area_gap_m: Metres = 5.0


class SlamConfig(Schema):
    """Parameters of :class:`trundle.fusion.slam.grid_slam.Slam` (the ``[slam]`` table), by component."""

    scan: ScanOptions = ScanOptions()
    tracking: TrackingOptions = TrackingOptions()
    keyframes: KeyframeOptions = KeyframeOptions()
    submaps: SubmapOptions = SubmapOptions()
    odometry: OdometryOptions = OdometryOptions()
    loop_closure: LoopClosureOptions = LoopClosureOptions()
    optimization: OptimizationOptions = OptimizationOptions()
    map_check: MapCheckOptions = MapCheckOptions()
    sessions: SessionOptions = SessionOptions()

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any] | None, where: str = "slam") -> SlamConfig:
        """The config of a ``[slam]`` table (None: the defaults), or one ConfigError line naming the key
        (``where`` its prefix), the value and what was expected."""
        return parse(cls, table, where)

    def replace(self, component: str, **values: Any) -> SlamConfig:
        """A copy with ``values`` changed in ``component`` (e.g. ``replace("loop_closure", enabled=False)``),
        checked like a table."""
        table = self.model_dump()
        table[component].update(values)
        return parse(SlamConfig, table, "slam")
