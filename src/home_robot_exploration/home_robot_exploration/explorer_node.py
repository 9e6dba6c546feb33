"""``explorer_node``: frontier exploration of the home (thin ROS shell over :mod:`.explorer`).

Inputs: ``depth`` (sensor_msgs/Image 32FC1 metres, or 16UC1 millimetres), ``camera_pose``
(PoseStamped, camera-to-map, OpenCV axes; matched to a depth image by equal stamps, as
``sim_camera_node`` publishes them), ``camera_info``, ``robot_pose`` (PoseStamped),
``cancel_command`` and ``exploration/cancel`` (std_msgs/String: any message ends exploration;
the running goal is cancelled).

Outputs: ``map`` (nav_msgs/OccupancyGrid, latched, published at ``map_publish_hz`` while it
changes), ``exploration/progress`` (std_msgs/String JSON, latched: ``state``, ``explored_m2``,
``seen_percent``, ``frontiers_left``, ``elapsed_s``, ``goals``, ``frames``, ``reason``; ``state``
is ``done`` at the end), and ``NavigateToPose`` goals on ``action_name`` (the navigation server:
``mock_nav_server`` or a real Nav2).

Mapping while exploring (``slam_action`` set, e.g. ``run_gs_slam``; "" = no mapping): before the robot
moves, a ``RunSlam`` goal starts the streaming SLAM server on the camera's topics (``map_dir`` =
``slam_map_dir``, class names ``slam_classes``) and exploration waits for its ``slam_start_signal``;
when exploration ends, ``data_transfer_done`` asks the server to map its backlog and save (a stop
cancels the goal, which also saves). Meanwhile ``state`` is ``mapping``; it becomes ``done`` when the
map is written and the object-query server asked to reload it (or a deadline passed: ``mapping``
says why). The ``mapping`` field of the progress has the run's state, frames, Gaussians and map path.
See :mod:`.mapping`.

Every decision is taken in a timer (``tick_hz``) that never waits: goals and results are chained
with ``add_done_callback``. The navigation server must appear within ``server_timeout_s``, else
exploration ends with that reason. A malformed frame is logged and skipped.

The code defaults below are config/params/explorer.yaml's values (a test compares them).
"""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np
from action_msgs.msg import GoalStatus
from geometry_msgs.msg import PoseStamped
from nav2_msgs.action import NavigateToPose
from nav_msgs.msg import OccupancyGrid as GridMsg
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import String

from home_robot_exploration.errors import ConfigError, ExplorationError
from home_robot_exploration.explorer import Exploration, ExplorerConfig, Finished, NavGoal
from home_robot_exploration.frontiers import FrontierConfig
from home_robot_exploration.mapping import MappingConfig, MappingResult, MappingRun
from home_robot_exploration.occupancy import UNKNOWN, GridConfig
from home_robot_ros.actions import ActionClient
from home_robot_ros.poses import pose_to_matrix
from home_robot_ros.startup import action_name, number_in, read_once, spin_node

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
IMAGE_QOS = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)

#: Parameters and their defaults (= config/params/explorer.yaml).
DEFAULTS: dict[str, object] = {
    "time_budget_s": 600.0, "look_steps": 4, "frame_timeout_s": 10.0, "max_goals": 200, "max_failures": 5,
    "resolution": 0.05, "origin_x": -2.0, "origin_y": -2.0, "width_m": 12.0, "height_m": 12.0,
    "floor_max_z": 0.08, "band_min_z": 0.08, "band_max_z": 1.6, "max_range_m": 6.0, "pixel_stride": 3,
    "robot_radius": 0.25, "min_cluster_cells": 8, "gain_weight": 1.0, "cost_weight": 0.5, "visited_radius": 0.5,
    "action_name": "navigate_to_pose", "pose_topic": "robot_pose", "map_frame": "map", "tick_hz": 5.0,
    "map_publish_hz": 1.0, "server_timeout_s": 30.0,
    "slam_action": "", "slam_map_dir": "", "slam_classes": "", "slam_start_timeout_s": 60.0,
    "slam_finish_timeout_s": 600.0,
}


def seen_percent(states: np.ndarray) -> float:
    """Known cells / cells of the known area's bounding box, in percent: a rough estimate for a closed
    home (it cannot know the rooms it has not seen yet)."""
    known = states != UNKNOWN
    if not known.any():
        return 0.0
    ys, xs = np.nonzero(known)
    box = states[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
    return 100.0 * float((box != UNKNOWN).sum()) / box.size


class ExplorerNode(Node):
    def __init__(self) -> None:
        super().__init__("explorer")
        v = read_once(self, DEFAULTS)
        grid = GridConfig(float(v["resolution"]), float(v["origin_x"]), float(v["origin_y"]), float(v["width_m"]),
                          float(v["height_m"]), float(v["floor_max_z"]), float(v["band_min_z"]),
                          float(v["band_max_z"]), float(v["max_range_m"]), int(v["pixel_stride"]))
        frontier = FrontierConfig(float(v["robot_radius"]), int(v["min_cluster_cells"]), float(v["gain_weight"]),
                                  float(v["cost_weight"]), float(v["visited_radius"]))
        self.cfg = ExplorerConfig(float(v["time_budget_s"]), int(v["look_steps"]), float(v["frame_timeout_s"]),
                                  int(v["max_goals"]), int(v["max_failures"]), grid, frontier)
        self.core = Exploration(self.cfg)  # checks the config (ConfigError)
        for name in ("tick_hz", "map_publish_hz"):
            number_in(name, v[name], 0.01, 1000.0)
        number_in("server_timeout_s", v["server_timeout_s"], 1e-3, 86400.0)
        self._map_frame = str(v["map_frame"])
        self._server_timeout = float(v["server_timeout_s"])
        self._map_period = 1.0 / float(v["map_publish_hz"])
        # All callbacks run in one thread (rclpy.spin, single-threaded executor): no locks needed.
        self._pose: tuple[float, float, float] | None = None
        self._k: np.ndarray | None = None
        self._depths: dict[int, np.ndarray] = {}  # stamp (ns) -> depth [H, W] metres, waiting for its pose
        self._poses: dict[int, np.ndarray] = {}  # stamp (ns) -> c2w [4, 4], waiting for its depth
        self._goal_handle = None
        self._goal_seq = 0  # tells results of old goals apart
        self._started_wall = time.monotonic()
        self._last_map = -math.inf
        self._map_dirty = True
        self._nav = ActionClient(self, NavigateToPose, action_name(self, str(v["action_name"])))
        self._slam_action = str(v["slam_action"])
        map_dir = str(v["slam_map_dir"])  # relative: this node's working folder (the server needs it absolute)
        self._slam_goal = (os.path.abspath(map_dir) if map_dir else "", str(v["slam_classes"]))
        self.mapping = MappingRun(MappingConfig(bool(self._slam_action), float(v["slam_start_timeout_s"]),
                                                float(v["slam_finish_timeout_s"])), time.monotonic())
        self._slam = None
        self._slam_handle = None
        self._slam_sent = False
        self._done_reported = False
        if self._slam_action:
            from semantic_gs_slam_interfaces.action import RunSlam

            self._slam = ActionClient(self, RunSlam, action_name(self, self._slam_action))
            self._done_pub = self.create_publisher(String, "data_transfer_done", LATCHED)
            self.create_subscription(String, "slam_start_signal", self._on_slam_start, LATCHED)
        self._map_pub = self.create_publisher(GridMsg, "map", LATCHED)
        self._progress_pub = self.create_publisher(String, "exploration/progress", LATCHED)
        self.create_subscription(Image, "depth", self._on_depth, IMAGE_QOS)
        self.create_subscription(PoseStamped, "camera_pose", self._on_camera_pose, IMAGE_QOS)
        self.create_subscription(CameraInfo, "camera_info", self._on_info, IMAGE_QOS)
        self.create_subscription(PoseStamped, str(v["pose_topic"]), self._on_pose, LATCHED)
        self.create_subscription(String, "cancel_command", self._on_cancel, 10)
        self.create_subscription(String, "exploration/cancel", self._on_cancel, 10)
        self.create_timer(1.0 / float(v["tick_hz"]), self._tick)
        self.get_logger().info(
            f"ready: exploring for at most {self.cfg.time_budget_s:g} s, grid {self.core.grid.nx}x{self.core.grid.ny} "
            f"at {grid.resolution:g} m, goals to {v['action_name']}")

    # --- inputs -------------------------------------------------------------------------------------

    @staticmethod
    def _ns(stamp) -> int:
        return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)

    def _on_info(self, msg: CameraInfo) -> None:
        k = np.array(msg.k, dtype=np.float64).reshape(3, 3)
        if np.isfinite(k).all() and k[0, 0] > 0 and k[1, 1] > 0:
            self._k = k
        else:
            self.get_logger().warn("camera_info with an unusable K: ignored")

    def _on_pose(self, msg: PoseStamped) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
        if all(math.isfinite(a) for a in (p.x, p.y, yaw)):
            self._pose = (p.x, p.y, yaw)

    def _on_depth(self, msg: Image) -> None:
        from semantic_gs_slam_ros.errors import ImageFormatError
        from semantic_gs_slam_ros.images import image_to_array

        try:
            depth = image_to_array(msg)
        except ImageFormatError as exc:
            self.get_logger().warn(f"depth image skipped: {exc}")
            return
        if depth.ndim != 2:
            self.get_logger().warn(f"depth image skipped: need one channel, got {list(depth.shape)}")
            return
        depth = depth.astype(np.float32) / (1000.0 if msg.encoding in ("16UC1", "mono16") else 1.0)
        self._depths[self._ns(msg.header.stamp)] = depth
        self._match()

    def _on_camera_pose(self, msg: PoseStamped) -> None:
        try:
            c2w = pose_to_matrix(msg)
        except ValueError as exc:
            self.get_logger().warn(f"camera pose skipped: {exc}")
            return
        self._poses[self._ns(msg.header.stamp)] = c2w
        self._match()

    def _match(self) -> None:
        for stamp in sorted(set(self._depths) & set(self._poses)):
            depth, c2w = self._depths.pop(stamp), self._poses.pop(stamp)
            if self._k is None:
                self.get_logger().warn("frame skipped: no usable camera_info yet")
                continue
            try:
                self.core.integrate(depth, self._k, c2w, stamp * 1e-9)
                self._map_dirty = True
            except ExplorationError as exc:
                self.get_logger().warn(f"frame skipped: {exc}")
        for pending in (self._depths, self._poses):  # unmatched leftovers: keep the newest few
            for stamp in sorted(pending)[:-5]:
                del pending[stamp]

    def _on_cancel(self, msg: String) -> None:
        if self.core.finished is None:
            self._finish(self.core.cancel(f"cancelled ({msg.data[:60]!r})"))
        elif self.mapping.state == "finishing" and self._slam_handle is not None:
            self.get_logger().info("stop while the map is being finished: SLAM run cancelled (it still saves)")
            self._slam_handle.cancel_goal_async()

    # --- the SLAM run (mapping while exploring) -----------------------------------------------------

    def _send_slam_goal(self) -> None:
        from semantic_gs_slam_interfaces.action import RunSlam

        goal = RunSlam.Goal()
        goal.map_dir, goal.semantic_classes = self._slam_goal
        goal.dataset_name = "exploration"
        self._slam_sent = True
        self.get_logger().info(f"starting the SLAM run on {self._slam_action}")
        self._slam.send_goal_async(goal, feedback_callback=self._on_slam_feedback).add_done_callback(
            self._on_slam_accepted)

    def _on_slam_accepted(self, future) -> None:
        gh = future.result() if future.exception() is None else None
        if gh is None or not gh.accepted:
            self.mapping.rejected(f"{self._slam_action} refused the goal (a run already in progress?)")
            self.get_logger().warn(f"SLAM run not started: {self.mapping.reason}; exploring without mapping")
            return
        self._slam_handle = gh
        self.mapping.accepted(bytes(gh.goal_id.uuid).hex(), time.monotonic())
        gh.get_result_async().add_done_callback(self._on_slam_result)

    def _on_slam_start(self, msg: String) -> None:
        try:
            goal = json.loads(msg.data)["goal"]
        except (ValueError, KeyError, TypeError, RecursionError):
            self.get_logger().warn(f"malformed slam_start_signal {msg.data[:80]!r} ignored")
            return
        if self.mapping.start_signal(str(goal)):
            self.get_logger().info("SLAM run started: exploring")

    def _on_slam_feedback(self, msg) -> None:
        fb = msg.feedback
        self.mapping.feedback(fb.frames_processed, fb.num_gaussians)

    def _on_slam_result(self, future) -> None:
        self._slam_handle = None
        if future.exception() is not None:
            self.mapping.ended(MappingResult(False, "", 0, f"SLAM result failed: {future.exception()}"))
        else:
            r = future.result().result
            self.mapping.ended(MappingResult(bool(r.success), r.map_path, int(r.frames_processed), r.message))
        (self.get_logger().info if self.mapping.state == "done" else self.get_logger().warn)(
            f"SLAM run ended ({self.mapping.state}): {self.mapping.result.message}")
        self._publish(self._now())

    # --- loop ---------------------------------------------------------------------------------------

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _tick(self) -> None:
        now = self._now()
        late = self.mapping.tick(time.monotonic())
        if late:
            self.get_logger().warn(late)
            if self._slam_handle is not None and self.mapping.state == "failed":
                self._slam_handle.cancel_goal_async()
        if self.core.finished is not None:
            if not self._done_reported and (self.mapping.settled() or now - self._last_map >= self._map_period):
                self._publish(now)  # "mapping" now and then, "done" once the map is written
            return
        if self._pose is None:
            return
        if not self._nav.server_is_ready():
            if time.monotonic() - self._started_wall > self._server_timeout:
                self._finish(self.core.cancel(f"navigation server not available after {self._server_timeout:g} s"))
            return
        if self.mapping.state == "connecting" and not self._slam_sent and self._slam.server_is_ready():
            self._send_slam_goal()
        if not self.mapping.ready_to_explore():
            return
        action = self.core.tick(*self._pose, now)
        if isinstance(action, NavGoal):
            self._send(action)
        elif isinstance(action, Finished):
            self._finish(action)
        if now - self._last_map >= self._map_period:
            self._publish(now)

    def _send(self, goal: NavGoal) -> None:
        msg = NavigateToPose.Goal()
        msg.pose.header.frame_id = self._map_frame
        msg.pose.header.stamp = self.get_clock().now().to_msg()
        msg.pose.pose.position.x, msg.pose.pose.position.y = float(goal.x), float(goal.y)
        msg.pose.pose.orientation.z, msg.pose.pose.orientation.w = math.sin(goal.yaw / 2), math.cos(goal.yaw / 2)
        self._goal_seq += 1
        seq = self._goal_seq
        if goal.kind == "frontier":
            self.get_logger().info(f"frontier goal {self.core.goals}: ({goal.x:.2f}, {goal.y:.2f})")
        self._nav.send_goal_async(msg).add_done_callback(lambda f: self._on_goal_response(f, seq))

    def _on_goal_response(self, future, seq: int) -> None:
        if seq != self._goal_seq or self.core.finished is not None:
            return
        gh = future.result() if future.exception() is None else None
        if gh is None or not gh.accepted:
            self.get_logger().warn("navigation goal rejected")
            self.core.goal_result(False, self._now())
            return
        self._goal_handle = gh
        gh.get_result_async().add_done_callback(lambda f: self._on_result(f, seq))

    def _on_result(self, future, seq: int) -> None:
        if seq != self._goal_seq or self.core.finished is not None:
            return
        self._goal_handle = None
        ok = future.exception() is None and future.result().status == GoalStatus.STATUS_SUCCEEDED
        if not ok:
            self.get_logger().warn("navigation goal did not succeed")
        self.core.goal_result(ok, self._now())

    def _finish(self, fin: Finished) -> None:
        if self._goal_handle is not None:
            self._goal_handle.cancel_goal_async()
            self._goal_handle = None
        self._goal_seq += 1  # results still in flight are ignored
        self._map_dirty = True
        if self.mapping.finish(time.monotonic()):
            if fin.reason.startswith("cancelled") and self._slam_handle is not None:
                self._slam_handle.cancel_goal_async()  # a stop: the server stops at once and still saves
            else:
                self._done_pub.publish(String(data=json.dumps({"goal": self.mapping.goal_id, "frames_sent": 0})))
            self.get_logger().info("exploration ended: the SLAM server finishes and saves the map")
        self._publish(self._now())
        p = self.core.progress()
        self.get_logger().info(f"done: {fin.reason}; explored {p.explored_m2:.1f} m2 with {p.goals} goals, "
                               f"{p.frames} frames in {p.elapsed_s:.0f} s")

    def _publish(self, now: float) -> None:
        self._last_map = now
        states = self.core.grid.states()
        if self._map_dirty:
            self._map_dirty = False
            g = self.core.grid
            msg = GridMsg()
            msg.header.frame_id = self._map_frame
            msg.header.stamp = self.get_clock().now().to_msg()
            msg.info.resolution = float(g.cfg.resolution)
            msg.info.width, msg.info.height = g.nx, g.ny
            msg.info.origin.position.x, msg.info.origin.position.y = g.cfg.origin_x, g.cfg.origin_y
            msg.info.origin.orientation.w = 1.0
            msg.data = states.reshape(-1).tolist()
            self._map_pub.publish(msg)
        p = self.core.progress(now)
        seen = seen_percent(states) if p.frames else 0.0
        state = p.state
        if state == "done" and not self.mapping.settled():
            state = "mapping"
        elif state == "done":
            self._done_reported = True
        doc = {"state": state, "explored_m2": round(p.explored_m2, 2), "seen_percent": round(seen, 1),
               "frontiers_left": p.frontiers_left, "elapsed_s": round(p.elapsed_s, 1), "goals": p.goals,
               "frames": p.frames, "reason": p.reason, "mapping": self.mapping.summary()}
        self._progress_pub.publish(String(data=json.dumps(doc)))


def main(args: list[str] | None = None) -> int:
    return spin_node(ExplorerNode, "explorer", args, (ConfigError,))


if __name__ == "__main__":
    raise SystemExit(main())
