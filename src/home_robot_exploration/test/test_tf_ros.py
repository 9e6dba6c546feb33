"""The simulated robot's pose as TF (real processes): map -> base_link on /tf from mock_nav_server, equal
to robot_pose, and base_link -> camera on /tf_static from sim_camera_node, equal to the mounting."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from tf2_msgs.msg import TFMessage

from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.testing import wait_for
from home_robot_exploration.simcam import CameraConfig

pytestmark = pytest.mark.ros

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def test_robot_pose_and_camera_mounting_are_published_as_tf(launch_nodes, ros_node):
    got: dict[str, object] = {"tf": []}
    lock = threading.Lock()

    def on_tf(msg: TFMessage) -> None:
        with lock:
            got["tf"].extend(msg.transforms)

    def on_static(msg: TFMessage) -> None:
        with lock:
            got["static"] = list(msg.transforms)

    def on_pose(msg: PoseStamped) -> None:
        with lock:
            got["pose"] = msg

    ros_node.create_subscription(TFMessage, "/tf", on_tf, QoSProfile(depth=100))
    ros_node.create_subscription(TFMessage, "/tf_static", on_static, LATCHED)
    ros_node.create_subscription(PoseStamped, "robot_pose", on_pose, LATCHED)
    specs = [s for s in load_nodeset("explore") if s.name in ("mock_nav_server", "sim_camera")]
    launch_nodes(nodes=specs, set=["sim_camera.width=40", "sim_camera.height=24",
                                   "mock_nav_server.initial_pose=[1.5, 2.0, 0.7]"])
    assert wait_for(lambda: got["tf"] and "static" in got and "pose" in got, 30), got.keys()
    with lock:
        tf, static, pose = got["tf"][-1], got["static"], got["pose"]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "base_link")
    t, q = tf.transform.translation, tf.transform.rotation
    assert (t.x, t.y, t.z) == (pose.pose.position.x, pose.pose.position.y, pose.pose.position.z) == (1.5, 2.0, 0.0)
    assert math.isclose(2 * math.atan2(q.z, q.w), 0.7, abs_tol=1e-9)
    (mount,) = static
    assert (mount.header.frame_id, mount.child_frame_id) == ("base_link", "camera")
    m = CameraConfig(40, 24).c2w(0.0, 0.0, 0.0)  # the default mounting: 1 m high, tilted 20 deg down
    mt, mq = mount.transform.translation, mount.transform.rotation
    np.testing.assert_allclose([mt.x, mt.y, mt.z], m[:3, 3], atol=1e-9)
    w, x, y, z = mq.w, mq.x, mq.y, mq.z
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    np.testing.assert_allclose(r, m[:3, :3], atol=1e-9)  # optical axes: z forward, pitched down
