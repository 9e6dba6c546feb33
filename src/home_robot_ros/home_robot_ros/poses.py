"""geometry_msgs poses as matrices, checked: a message's pose is refused with the reason, never half-used."""

from __future__ import annotations

import math

import numpy as np

#: how far from unit length a quaternion may be (a serialised float32 one is well within this)
UNIT_TOLERANCE = 1e-2


def pose_to_matrix(msg) -> np.ndarray:
    """A ``geometry_msgs/PoseStamped`` (or a ``Pose``) -> [4, 4] float64 pose: rotation from the quaternion
    (normalised), translation from the position.

    Raises:
        ValueError: a non-finite value, or a quaternion farther than :data:`UNIT_TOLERANCE` from unit length
            (an all-zero one included).
    """
    pose = getattr(msg, "pose", msg)
    p, q = pose.position, pose.orientation
    vals = [p.x, p.y, p.z, q.w, q.x, q.y, q.z]
    if not all(math.isfinite(v) for v in vals):
        raise ValueError("pose has NaN or inf")
    n = math.sqrt(q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z)
    if abs(n - 1.0) > UNIT_TOLERANCE:
        raise ValueError(f"orientation is not a unit quaternion (norm {n:.3g})")
    w, x, y, z = q.w / n, q.x / n, q.y / n, q.z / n
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = (p.x, p.y, p.z)
    return m
