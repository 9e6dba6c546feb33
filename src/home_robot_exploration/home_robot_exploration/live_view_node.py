"""``live_view_node``: the browser view of exploration (thin ROS shell over :mod:`.live_view`).

Serves a viser page at ``http://<host>:<port>`` (printed in the ``ready:`` line; loopback only by
default) showing the Gaussian map at ``map_path`` (reloaded when the file changes, checked every
``map_check_s``), ``map`` (nav_msgs/OccupancyGrid) with its frontiers, ``robot_pose`` and the path,
and ``object_list`` labels. Every message is drawn from its callback (viser queues it; nothing
waits); a malformed one is logged and skipped.

The code defaults below are config/params/live_view.yaml's values (a test compares them).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import OccupancyGrid as GridMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.live_view import LiveView, splats_from_params
from home_robot_ros.startup import number_in, read_once, spin_node

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)

#: Parameters and their defaults (= config/params/live_view.yaml).
DEFAULTS: dict[str, object] = {
    "host": "127.0.0.1", "port": 8080, "map_path": "", "map_check_s": 5.0, "pose_topic": "robot_pose",
    "max_splats": 60000,
}


def bundled_map() -> str:
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("object_query"), "data", "params.npz")


class LiveViewNode(Node):
    def __init__(self) -> None:
        super().__init__("live_view")
        v = read_once(self, DEFAULTS)
        number_in("map_check_s", v["map_check_s"], 0.01, 3600.0)
        if int(v["max_splats"]) < 1:
            raise ConfigError(f"max_splats must be >= 1, got {v['max_splats']}")
        self._map_path = str(v["map_path"]) or bundled_map()
        self._max_splats = int(v["max_splats"])
        self._map_mtime: float | None = None
        try:
            self.view = LiveView(str(v["host"]), int(v["port"]))
        except OSError as exc:
            raise ConfigError(f"cannot serve the view on {v['host']}:{v['port']}: {exc}") from exc
        self._browsers = 0
        self.create_subscription(GridMsg, "map", self._on_grid, LATCHED)
        self.create_subscription(PoseStamped, str(v["pose_topic"]), self._on_pose, LATCHED)
        self.create_subscription(String, "object_list", self._on_objects, LATCHED)
        self.create_timer(float(v["map_check_s"]), self._check_map)
        self.create_timer(1.0, self._check_clients)
        self._check_map()
        self.get_logger().info(f"ready: live view at {self.view.url} ({self.view.splats} Gaussians from "
                               f"{self._map_path})")

    def _check_map(self) -> None:
        try:
            mtime = os.stat(self._map_path).st_mtime
        except OSError:
            return  # no map yet (a SLAM run writes it later)
        if mtime == self._map_mtime:
            return
        self._map_mtime = mtime
        try:
            self.view.show_gaussians(*splats_from_params(self._map_path, self._max_splats))
            self.get_logger().info(f"map: {self.view.splats} Gaussians from {self._map_path}")
        except ConfigError as exc:
            self.get_logger().warn(f"map not shown: {exc}")

    def _check_clients(self) -> None:
        n = self.view.clients()
        if n != self._browsers:
            self._browsers = n
            self.get_logger().info(f"browser clients: {n} (scene: {self.view.splats} Gaussians)")

    def _on_grid(self, msg: GridMsg) -> None:
        w, h, res = int(msg.info.width), int(msg.info.height), float(msg.info.resolution)
        if w * h != len(msg.data) or not (res > 0 and math.isfinite(res)) or w * h == 0:
            self.get_logger().warn(f"occupancy grid skipped: {w}x{h} cells but {len(msg.data)} values")
            return
        states = np.asarray(msg.data, dtype=np.int8).reshape(h, w)
        self.view.show_grid(states, res, msg.info.origin.position.x, msg.info.origin.position.y)

    def _on_pose(self, msg: PoseStamped) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        if all(math.isfinite(a) for a in (p.x, p.y, yaw)):
            self.view.show_robot(p.x, p.y, yaw)

    def _on_objects(self, msg: String) -> None:
        try:
            doc = json.loads(msg.data)
            objects = {str(k)[:40]: [float(c) for c in v] for k, v in doc.items()
                       if isinstance(v, list) and len(v) == 3}
        except (AttributeError, TypeError, ValueError, OverflowError, RecursionError):
            self.get_logger().warn("object_list skipped: not {name: [x, y, z]}")
            return
        self.view.show_objects({k: v for k, v in objects.items() if all(math.isfinite(c) for c in v)})

    def destroy_node(self) -> None:
        self.view.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return spin_node(LiveViewNode, "live_view", args, (ConfigError,))


if __name__ == "__main__":
    raise SystemExit(main())
