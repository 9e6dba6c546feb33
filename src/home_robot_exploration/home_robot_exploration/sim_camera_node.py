"""``sim_camera_node``: the simulated robot's RGB-D camera (renders the synthetic home at the robot's pose).

Subscribes ``robot_pose`` (``geometry_msgs/PoseStamped``, what ``mock_nav_server`` publishes) and,
at ``rate_hz``, renders :mod:`semantic_gs_slam.synthetic.scenes`'s home from the camera on the base
(:class:`~home_robot_exploration.simcam.CameraConfig`: ``mount_height``, ``tilt_deg``,
``hfov_deg``, ``forward_offset``, ``width`` x ``height``). Publishes, all with the same stamp (the
time the pose was taken) and ``frame_id``:

* ``rgb`` (rgb8), ``depth`` (32FC1, metres along the optical axis), ``semantic`` (mono8 class ids
  of :data:`semantic_gs_slam.synthetic.scenes.CLASSES`), ``camera_info`` — the names the streaming SLAM
  server subscribes, so it maps what this camera sees with no remapping;
* ``camera_pose`` (``PoseStamped`` in ``map_frame``): the camera-to-map pose (OpenCV camera axes),
  the ground truth the explorer builds its grid with and SLAM is scored against;
* ``/tf_static`` (``publish_tf``): ``base_frame`` -> ``frame_id``, where the camera sits on the base
  (with ``mock_nav_server``'s ``map`` -> ``base_link`` on ``/tf``, RViz can show the camera);
* ``odom_camera_pose`` (``PoseStamped``, same stamp): the same camera pose as the robot's wheel
  odometry estimates it (:class:`~home_robot_exploration.simcam.WheelOdometry`: systematic scale
  errors ``odom_trans_scale_error`` / ``odom_rot_scale_error`` plus ``odom_noise``, integrated over
  every ``robot_pose`` update), the prior a SLAM server takes with ``odometry_topic``. It drifts as
  a real base's odometry does; all zero = perfect odometry.

Rendering runs on one worker thread (the callbacks never wait on it); a tick that finds the worker
still busy is skipped (counted in the log), so the real rate is at most what the CPU renders. A
300 x 170 frame takes 0.47 s on an idle core here (1.6 s at load 10 on 2 cores), hence the 1 Hz default.

The code defaults below are config/params/sim_camera.yaml's values (a test compares them).
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np
from geometry_msgs.msg import PoseStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rclpy.time import Time
from sensor_msgs.msg import CameraInfo, Image

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.simcam import CameraConfig, OdometryConfig, WheelOdometry
from home_robot_ros.startup import read_once, spin_node

POSE_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
IMAGE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)

#: Parameters and their defaults (= config/params/sim_camera.yaml).
DEFAULTS: dict[str, object] = {
    "width": 300, "height": 170, "hfov_deg": 90.0, "mount_height": 1.0, "tilt_deg": 20.0,
    "forward_offset": 0.0, "rate_hz": 1.0, "pose_topic": "robot_pose", "frame_id": "camera",
    "map_frame": "map", "seed": 0, "supersample": 1,
    "odom_trans_scale_error": 0.02, "odom_rot_scale_error": 0.02, "odom_noise": 0.01,
    "publish_tf": True, "base_frame": "base_link",
}


def yaw_of(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def quaternion_of(r: np.ndarray) -> tuple[float, float, float, float]:
    """[3, 3] rotation -> (x, y, z, w)."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0, r[1, 0] - r[0, 1])
    return x, y, z, w


class SimCameraNode(Node):
    def __init__(self) -> None:
        super().__init__("sim_camera")
        v = read_once(self, DEFAULTS)
        self.cam = CameraConfig(int(v["width"]), int(v["height"]), float(v["hfov_deg"]), float(v["mount_height"]),
                                float(v["tilt_deg"]), float(v["forward_offset"]))
        self.cam.check()
        rate = float(v["rate_hz"])
        if not 0 < rate <= 100:
            raise ConfigError(f"rate_hz must be in (0, 100], got {rate}")
        self._supersample = int(v["supersample"])
        if self._supersample < 1 or self._supersample % 2 == 0:
            raise ConfigError(f"supersample must be an odd integer >= 1, got {self._supersample}")
        self._frame_id, self._map_frame = str(v["frame_id"]), str(v["map_frame"])
        from semantic_gs_slam.config import Intrinsics
        from semantic_gs_slam.synthetic.scenes import HomeRenderer

        k = self.cam.k()
        self._k = k
        self._intrinsics = Intrinsics(self.cam.width, self.cam.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        if int(v["seed"]) < 0:
            raise ConfigError(f"seed must be >= 0, got {v['seed']}")
        self._renderer = HomeRenderer(int(v["seed"]))
        self._odometry = WheelOdometry(OdometryConfig(float(v["odom_trans_scale_error"]),
                                                      float(v["odom_rot_scale_error"]), float(v["odom_noise"]),
                                                      int(v["seed"])))
        self._lock = threading.Lock()  # guards _pose, _odom, _busy, _skipped
        self._pose: tuple[float, float, float] | None = None
        self._odom: tuple[float, float, float] | None = None  # the odometry estimate of _pose
        self._busy: Future | None = None
        self._skipped = 0
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="render")
        self._pubs = {s: self.create_publisher(Image, s, IMAGE_QOS) for s in ("rgb", "depth", "semantic")}
        self._info_pub = self.create_publisher(CameraInfo, "camera_info", IMAGE_QOS)
        self._pose_pub = self.create_publisher(PoseStamped, "camera_pose", IMAGE_QOS)
        self._odom_pub = self.create_publisher(PoseStamped, "odom_camera_pose", IMAGE_QOS)
        self.create_subscription(PoseStamped, str(v["pose_topic"]), self._on_pose, POSE_QOS)
        if v["publish_tf"]:  # where the camera sits on the base, once, latched (tf2's /tf_static)
            from tf2_msgs.msg import TFMessage

            self._tf_static = self.create_publisher(TFMessage, "/tf_static", POSE_QOS)
            self._tf_static.publish(TFMessage(transforms=[self._mount_transform(str(v["base_frame"]))]))
        self.create_timer(1.0 / rate, self._tick)
        self.frames = 0
        self.get_logger().info(
            f"ready: simulated camera {self.cam.width}x{self.cam.height}, hfov {self.cam.hfov_deg:g} deg, "
            f"{self.cam.mount_height:g} m high, tilt {self.cam.tilt_deg:g} deg, {rate:g} Hz, pose from "
            f"{v['pose_topic']}")

    def _mount_transform(self, base_frame: str):
        """base_frame -> the camera's frame_id (OpenCV optical axes), from the mounting."""
        from geometry_msgs.msg import TransformStamped

        m = self.cam.c2w(0.0, 0.0, 0.0)  # the camera in the frame of a base at the origin, heading +x
        t = TransformStamped()
        t.header.stamp = self.get_clock().now().to_msg()
        t.header.frame_id, t.child_frame_id = base_frame, self._frame_id
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(a) for a in m[:3, 3])
        r = t.transform.rotation
        r.x, r.y, r.z, r.w = quaternion_of(m[:3, :3])
        return t

    def _on_pose(self, msg: PoseStamped) -> None:
        p = msg.pose.position
        yaw = yaw_of(msg.pose.orientation)
        if not all(math.isfinite(a) for a in (p.x, p.y, yaw)):
            self.get_logger().warn("robot pose is not finite: ignored")
            return
        with self._lock:
            self._pose = (p.x, p.y, yaw)
            self._odom = self._odometry.update(p.x, p.y, yaw)

    def _tick(self) -> None:
        with self._lock:
            pose, odom = self._pose, self._odom
            if pose is None or odom is None:
                return
            if self._busy is not None and not self._busy.done():
                self._skipped += 1
                return
            stamp = self.get_clock().now()
            self._busy = self._worker.submit(self._render_and_publish, pose, odom, stamp)

    def _render_and_publish(self, pose: tuple[float, float, float], odom: tuple[float, float, float],
                            stamp: Time) -> None:
        try:
            c2w = self.cam.c2w(*pose)
            rgb, depth, sem = self._renderer.render(c2w, self._intrinsics, self._supersample)
            header_stamp = stamp.to_msg()
            for name, arr, enc in (("rgb", (rgb * 255 + 0.5).astype(np.uint8), "rgb8"),
                                   ("depth", depth.astype(np.float32), "32FC1"), ("semantic", sem, "mono8")):
                msg = image_msg(arr, enc)
                msg.header.stamp, msg.header.frame_id = header_stamp, self._frame_id
                self._pubs[name].publish(msg)
            info = CameraInfo()
            info.header.stamp, info.header.frame_id = header_stamp, self._frame_id
            info.width, info.height = self.cam.width, self.cam.height
            k = self._k
            info.k = [k[0, 0], 0.0, k[0, 2], 0.0, k[1, 1], k[1, 2], 0.0, 0.0, 1.0]
            info.p = [k[0, 0], 0.0, k[0, 2], 0.0, 0.0, k[1, 1], k[1, 2], 0.0, 0.0, 0.0, 1.0, 0.0]
            info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
            info.distortion_model = "plumb_bob"
            info.d = [0.0] * 5
            self._info_pub.publish(info)
            self._pose_pub.publish(pose_msg(c2w, header_stamp, self._map_frame))
            self._odom_pub.publish(pose_msg(self.cam.c2w(*odom), header_stamp, self._map_frame))
            self.frames += 1
        except Exception as exc:  # noqa: BLE001 - a failed frame is logged, the camera goes on
            self.get_logger().error(f"frame failed: {type(exc).__name__}: {exc}")

    def destroy_node(self) -> None:
        self._worker.shutdown(wait=True, cancel_futures=True)  # at most one render (bounded) is running
        super().destroy_node()


def pose_msg(c2w: np.ndarray, stamp, frame_id: str) -> PoseStamped:
    """[4, 4] pose -> PoseStamped."""
    pm = PoseStamped()
    pm.header.stamp, pm.header.frame_id = stamp, frame_id
    pm.pose.position.x, pm.pose.position.y, pm.pose.position.z = (float(a) for a in c2w[:3, 3])
    q = quaternion_of(c2w[:3, :3])
    pm.pose.orientation.x, pm.pose.orientation.y, pm.pose.orientation.z, pm.pose.orientation.w = q
    return pm


def image_msg(array: np.ndarray, encoding: str) -> Image:
    from semantic_gs_slam_ros.images import array_to_image_fields

    return Image(**array_to_image_fields(array, encoding))


def main(args: list[str] | None = None) -> int:
    return spin_node(SimCameraNode, "sim_camera", args, (ConfigError,))


if __name__ == "__main__":
    raise SystemExit(main())
