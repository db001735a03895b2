"""particles/poses: geometry_msgs/PoseArray written straight from numpy."""

from __future__ import annotations

from typing import Optional

import numpy as np
from geometry_msgs.msg import PoseArray

from .cdr import CdrWriter
from .stamp import stamp_from_seconds

IDENTITY_QUATERNION = np.array([0.0, 0.0, 0.0, 1.0])


def pose_rows(position: np.ndarray, orientation: Optional[np.ndarray]) -> np.ndarray:
    """Return an (n, 7) array x, y, z, qx, qy, qz, qw (identity without spin)."""
    n = position.shape[0]
    rows = np.empty((n, 7))
    rows[:, :3] = position
    rows[:, 3:] = IDENTITY_QUATERNION if orientation is None else orientation
    return rows


def pose_array_writer(position: np.ndarray, orientation: Optional[np.ndarray],
                      seconds: float, frame_id: str) -> CdrWriter:
    """Return the CDR writer holding a PoseArray (all particles, id order)."""
    writer = CdrWriter()
    writer.header(*stamp_from_seconds(seconds), frame_id)
    writer.uint32(position.shape[0])
    writer.float64s(pose_rows(position, orientation))
    return writer


def pose_array_bytes(position: np.ndarray, orientation: Optional[np.ndarray],
                     seconds: float, frame_id: str) -> bytes:
    """Return a serialised PoseArray ready for ``Publisher.publish``."""
    return pose_array_writer(position, orientation, seconds, frame_id).bytes()


def poses_from_pose_array(msg: PoseArray) -> tuple[np.ndarray, np.ndarray]:
    """Return positions (n, 3) and orientations (n, 4, x y z w) of a PoseArray."""
    rows = np.array([(p.position.x, p.position.y, p.position.z, p.orientation.x,
                      p.orientation.y, p.orientation.z, p.orientation.w)
                     for p in msg.poses], dtype=float).reshape(-1, 7)
    return rows[:, :3], rows[:, 3:]
