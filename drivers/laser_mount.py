"""Where a laser sits on the robot: the static transform a laser driver publishes on ``/tf_static``."""

from __future__ import annotations

from typing import Any

from trundle.logs import messages as m


def laser_transform(config: Any, stamp_ns: int) -> m.TFMessage:
    """The static transform ``parent_frame`` -> ``frame_id`` at ``x, y, z`` (m), ``yaw`` (rad) of a
    laser driver's config (REP 105: base_link -> laser)."""
    return m.TFMessage((m.TransformStamped.planar(stamp_ns, config.parent_frame, config.frame_id, config.x, config.y,
                                                  config.yaw, config.z),))
