"""The camera and the explorer as real processes: what the camera publishes, and bad input that
neither node may die of."""

from __future__ import annotations

import math
import threading

import pytest
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from home_robot_bringup.nodeset import NodeSpec
from home_robot_bringup.testing import wait_for

pytestmark = pytest.mark.ros

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
IMAGE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)


def camera_spec(**params) -> NodeSpec:
    return NodeSpec("sim_camera", "home_robot_exploration", "sim_camera_node",
                    parameters={"width": 64, "height": 36, "rate_hz": 4.0, **params}, ready="ready:")


def test_camera_publishes_consistent_frames_at_the_robot_pose(launch_nodes, ros_node):
    got: dict[str, list] = {k: [] for k in ("rgb", "depth", "semantic", "camera_info", "camera_pose")}
    lock = threading.Lock()

    def keep(name: str):
        def cb(msg) -> None:
            with lock:
                got[name].append(msg)
        return cb

    for name in ("rgb", "depth", "semantic"):
        ros_node.create_subscription(Image, name, keep(name), IMAGE_QOS)
    ros_node.create_subscription(CameraInfo, "camera_info", keep("camera_info"), IMAGE_QOS)
    ros_node.create_subscription(PoseStamped, "camera_pose", keep("camera_pose"), IMAGE_QOS)
    pose_pub = ros_node.create_publisher(PoseStamped, "robot_pose", LATCHED)
    launch_nodes(nodes=[camera_spec(mount_height=1.2)])
    bad = PoseStamped()
    bad.pose.position.x = math.nan
    pose_pub.publish(bad)  # ignored, with a warning; the camera waits for a usable pose
    good = PoseStamped()
    good.pose.position.x, good.pose.position.y = 2.0, 1.0
    good.pose.orientation.w = 1.0
    pose_pub.publish(good)
    assert wait_for(lambda: all(len(v) >= 2 for v in got.values()), 60.0), {k: len(v) for k, v in got.items()}
    with lock:
        rgb, depth, sem, info, pose = (got[k][0] for k in ("rgb", "depth", "semantic", "camera_info", "camera_pose"))
    stamps = {(m.header.stamp.sec, m.header.stamp.nanosec) for m in (rgb, depth, sem, info, pose)}
    assert len(stamps) == 1, stamps  # one stamp per frame on every stream
    assert (rgb.width, rgb.height, rgb.encoding) == (64, 36, "rgb8")
    assert (depth.encoding, sem.encoding) == ("32FC1", "mono8")
    assert info.k[0] == pytest.approx(32.0)  # 90 degrees horizontal field of view
    p = pose.pose.position
    assert (p.x, p.y, p.z) == pytest.approx((2.0, 1.0, 1.2))


def test_explorer_survives_bad_input(launch_nodes, ros_node):
    sup = launch_nodes(nodes=[NodeSpec("explorer", "home_robot_exploration", "explorer_node",
                                       parameters={"server_timeout_s": 300.0}, ready="ready:")])
    depth_pub = ros_node.create_publisher(Image, "depth", IMAGE_QOS)
    pose_pub = ros_node.create_publisher(PoseStamped, "camera_pose", IMAGE_QOS)
    info_pub = ros_node.create_publisher(CameraInfo, "camera_info", IMAGE_QOS)
    assert wait_for(lambda: depth_pub.get_subscription_count() > 0 and info_pub.get_subscription_count() > 0, 20.0)
    info_pub.publish(CameraInfo(k=[0.0] * 9))  # unusable K
    info_pub.publish(CameraInfo(k=[32.0, 0.0, 31.5, 0.0, 32.0, 17.5, 0.0, 0.0, 1.0]))
    depth_pub.publish(Image(height=2, width=2, encoding="weird", step=2, data=[0, 0, 0, 0]))
    depth_pub.publish(Image(height=36, width=64, encoding="32FC1", step=256, data=[0] * 10))  # too short
    rgb_as_depth = Image(height=2, width=2, encoding="rgb8", step=6, data=[0] * 12)
    depth_pub.publish(rgb_as_depth)
    frame = Image(height=2, width=2, encoding="32FC1", step=8, data=[0] * 16)
    frame.header.stamp.sec = 5
    depth_pub.publish(frame)
    nan_pose = PoseStamped()
    nan_pose.header.stamp.sec = 5
    nan_pose.pose.orientation.w = math.nan
    pose_pub.publish(nan_pose)  # a non-finite pose, skipped
    long_quaternion = PoseStamped()  # 10^4 long: once a rotation that scaled the frame into a 71-GiB grid update
    long_quaternion.header.stamp.sec = 5
    long_quaternion.pose.orientation.x = 1e4
    pose_pub.publish(long_quaternion)
    proc = sup.get("explorer")
    assert wait_for(lambda: "depth image skipped" in proc.output() and "camera pose skipped: pose has NaN or inf"
                    in proc.output() and "camera pose skipped: orientation is not a unit quaternion (norm 1e+04)"
                    in proc.output() and "unusable K" in proc.output(), 20.0), proc.output()[-2000:]
    ros_node.create_publisher(String, "exploration/cancel", 10).publish(String(data="test"))
    assert proc.returncode() is None, proc.output()[-2000:]  # still running
