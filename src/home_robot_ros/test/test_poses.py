"""home_robot_ros.poses: a geometry_msgs pose as a checked matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest
from geometry_msgs.msg import Pose, PoseStamped

from home_robot_ros.poses import pose_to_matrix


def _pose(x=0.0, y=0.0, z=0.0, qx=0.0, qy=0.0, qz=0.0, qw=1.0) -> PoseStamped:
    msg = PoseStamped()
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = x, y, z
    o = msg.pose.orientation
    o.x, o.y, o.z, o.w = qx, qy, qz, qw
    return msg


def test_a_pose_becomes_its_matrix_and_a_nearly_unit_quaternion_is_normalised():
    s = math.sqrt(0.5)
    m = pose_to_matrix(_pose(1.0, 2.0, 3.0, qz=s * 1.005, qw=s * 1.005))  # 90 degrees about z, 0.5 % long
    np.testing.assert_allclose(m[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_array_equal(m[:3, 3], [1.0, 2.0, 3.0])
    plain = Pose()
    plain.orientation.w = 1.0
    np.testing.assert_array_equal(pose_to_matrix(plain), np.eye(4))  # a Pose as well as a PoseStamped


@pytest.mark.parametrize("pose, words", [
    (_pose(qw=0.0), "not a unit quaternion (norm 0)"),
    (_pose(qx=1e4, qw=0.0), "not a unit quaternion (norm 1e+04)"),
    (_pose(qw=2.0), "not a unit quaternion (norm 2)"),
    (_pose(x=math.nan), "NaN or inf"),
    (_pose(qw=math.inf), "NaN or inf"),
])
def test_a_pose_that_is_no_rigid_motion_is_refused_with_the_reason(pose, words):
    with pytest.raises(ValueError, match=words.replace("(", r"\(").replace(")", r"\)").replace("+", r"\+")):
        pose_to_matrix(pose)
