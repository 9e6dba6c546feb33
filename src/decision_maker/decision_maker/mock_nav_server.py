"""Simulated Nav2: a ``navigate_to_pose`` action server moving a kinematic robot base.

The base turns toward the goal and drives straight at ``speed`` (no obstacles), then turns to the
goal heading. Feedback carries ``current_pose`` and ``distance_remaining``; the pose is published
on ``robot_pose`` every tick. A new goal preempts (aborts) the running one. Cancel is honoured in
the next executor iteration; ``/cancel_command`` (or the brain's ``/hardware_stop``) stops the
base at once and aborts the goal unless its client cancels it within ``stop_grace_s``.

Parameters:
    speed (m/s, 1.0), turn_rate (rad/s, 2.0), rate_hz (simulation/feedback rate, 20),
    initial_pose ([x, y, theta], [0.5, 0.5, 0.0]), frame_id ("map"), action_name
    ("navigate_to_pose"), pose_topic ("robot_pose"), publish_tf (true: the pose also goes to ``/tf`` as
    frame_id -> base_frame, "base_link"), stop_grace_s (0.5),
    fault: "none" | "fail" (abort after fail_after_s) | "hang" (never moves or finishes; cancel works),
    fail_after_s (0.3), workspace_bound_m (100.0: goals with |x| or |y| beyond it are rejected).

Every goal is validated before it is accepted (finite numbers, inside ``workspace_bound_m``, a unit
quaternion, the right frame); a bad one is rejected with the reason in the log, and the node goes on.
The code defaults below are the params file's values (config/params/sim.yaml; a test compares them).
"""

from __future__ import annotations

import math
import time

from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseStamped
from nav2_msgs.action import NavigateToPose
from rclpy.action.server import ServerGoalHandle
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.command_types import Pose2D
from decision_maker.errors import ConfigError, SimError
from decision_maker.sim.actions import SimGoals, run_sim_node
from decision_maker.sim.world import BaseSim, check_coordinates, check_quaternion
from decision_maker.topics import HARDWARE_STOP
from home_robot_ros.startup import number_in, read_once

POSE_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
FAULTS = ("none", "fail", "hang")


def yaw_of(q) -> float:
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


#: Parameters and their defaults (= config/params/sim.yaml).
DEFAULTS: dict[str, object] = {
    "speed": 1.0, "turn_rate": 2.0, "rate_hz": 20.0, "initial_pose": [0.5, 0.5, 0.0], "frame_id": "map",
    "action_name": "navigate_to_pose", "pose_topic": "robot_pose", "stop_grace_s": 0.5, "fault": "none",
    "fail_after_s": 0.3, "workspace_bound_m": 100.0, "publish_tf": True, "base_frame": "base_link",
}
#: TF's topic and QoS (tf2_ros: reliable, volatile, depth 100)
TF_QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
_MAX_DURATION_S = 2.0**31 - 1  # builtin_interfaces/Duration.sec is an int32


def _duration(seconds: float) -> Duration:
    seconds = min(max(0.0, seconds), _MAX_DURATION_S) if math.isfinite(seconds) else 0.0
    return Duration(sec=int(seconds), nanosec=int((seconds % 1.0) * 1e9))


class MockNavServer(Node):
    def __init__(self) -> None:
        super().__init__("mock_nav_server")
        v = read_once(self, DEFAULTS)
        if v["fault"] not in FAULTS:
            raise ConfigError(f"fault must be one of {FAULTS}, got {v['fault']!r}")
        number_in("rate_hz", v["rate_hz"], 0.01, 1000.0)
        for k in ("speed", "turn_rate"):
            number_in(k, v[k], 1e-6, 1e3)
        number_in("stop_grace_s", v["stop_grace_s"], 0.0, 3600.0)
        init = [float(x) for x in v["initial_pose"]]
        if len(init) != 3:
            raise ConfigError(f"initial_pose must be [x, y, theta], got {init}")
        self._bound = float(v["workspace_bound_m"])
        if not self._bound > 0 or not math.isfinite(self._bound):
            raise ConfigError(f"workspace_bound_m must be a finite number > 0, got {v['workspace_bound_m']}")
        try:
            check_coordinates("initial_pose", tuple(init[:2]), self._bound)
        except SimError as exc:
            raise ConfigError(str(exc)) from exc
        self._base = BaseSim(Pose2D(*init), float(v["speed"]), float(v["turn_rate"]))
        self._frame = str(v["frame_id"])
        self._fault = str(v["fault"])
        self._fail_after = float(v["fail_after_s"])
        self._grace = float(v["stop_grace_s"])
        self._active: ServerGoalHandle | None = None
        self._started = 0.0
        self._stop_deadline: float | None = None  # abort the goal at this time (after /cancel_command)
        self._pose_pub = self.create_publisher(PoseStamped, str(v["pose_topic"]), POSE_QOS)
        self._base_frame = str(v["base_frame"])
        self._tf_pub = None
        if v["publish_tf"]:  # the pose as TF too (frame_id -> base_frame), for RViz and tf2 users
            from tf2_msgs.msg import TFMessage

            self._tf_msg = TFMessage
            self._tf_pub = self.create_publisher(TFMessage, "/tf", TF_QOS)
        self._goals = SimGoals(self, NavigateToPose, str(v["action_name"]), self._check_goal, self._start,
                               self._cancelled)
        self.create_subscription(String, "cancel_command", self._on_stop, 10)
        self.create_subscription(String, HARDWARE_STOP, self._on_stop, 10)  # the brain's own stop
        self._last = time.monotonic()
        self.create_timer(1.0 / float(v["rate_hz"]), self._tick)
        self._publish_pose()
        p = self._base.pose
        self.get_logger().info(
            f"ready: simulated nav at ({p.x:.2f}, {p.y:.2f}, {p.theta:.2f}), speed {self._base.speed:g} m/s, "
            f"fault {self._fault}"
        )

    # --- goals ------------------------------------------------------------------------------------

    def _check_goal(self, goal: NavigateToPose.Goal) -> str | None:
        pos, q = goal.pose.pose.position, goal.pose.pose.orientation
        frame = goal.pose.header.frame_id
        try:
            check_coordinates("goal", (pos.x, pos.y, pos.z), self._bound)
            check_quaternion("goal", q.x, q.y, q.z, q.w)
        except SimError as exc:
            return str(exc)
        if frame and frame != self._frame:
            return f"goal frame {frame[:40]!r} is not {self._frame!r}"
        return None

    def _start(self, gh: ServerGoalHandle) -> None:
        if self._active is not None:
            self._goals.finish(self._active, "abort", self._result(9000, "preempted by a new goal"))
        pose = gh.request.pose.pose
        self._active = gh
        self._started = time.monotonic()
        self._stop_deadline = None
        goal = Pose2D(pose.position.x, pose.position.y, yaw_of(pose.orientation))
        self._base.goal = None if self._fault == "hang" else goal
        self.get_logger().info(f"goal: ({goal.x:.2f}, {goal.y:.2f}, {goal.theta:.2f})")

    def _cancelled(self, gh: ServerGoalHandle) -> None:
        if gh is self._active:
            self._base.stop()
            self._active = None
            self.get_logger().info("goal cancelled: stopped")

    def _on_stop(self, msg: String) -> None:
        self._base.stop()
        if self._active is not None and self._stop_deadline is None:
            self._stop_deadline = time.monotonic() + self._grace
        self.get_logger().warn(f"/cancel_command: stopped ({msg.data[:80]!r})")

    def _result(self, code: int = 0, msg: str = "") -> NavigateToPose.Result:
        return self._goals.result(error_code=code, error_msg=msg)

    # --- simulation -------------------------------------------------------------------------------

    def _tick(self) -> None:
        now = time.monotonic()
        dt, self._last = now - self._last, now
        self._base.step(dt)
        self._publish_pose()
        gh = self._active
        if gh is None:
            return
        if self._stop_deadline is not None and now >= self._stop_deadline:
            self._finish(gh, "abort", self._result(9000, "stopped by /cancel_command"))
        elif self._fault == "fail" and now - self._started >= self._fail_after:
            self._finish(gh, "abort", self._result(9000, "simulated navigation failure"))
        elif self._base.arrived():
            self._finish(gh, "succeed", self._result())
        else:
            fb = NavigateToPose.Feedback()
            fb.current_pose = self._pose_msg()
            fb.distance_remaining = float(self._base.distance_remaining())
            fb.navigation_time = _duration(now - self._started)
            fb.estimated_time_remaining = _duration(self._base.distance_remaining() / self._base.speed)
            gh.publish_feedback(fb)

    def _finish(self, gh: ServerGoalHandle, kind: str, result: NavigateToPose.Result) -> None:
        self._active = None
        self._base.stop()
        self._goals.finish(gh, kind, result)

    def _pose_msg(self) -> PoseStamped:
        p = self._base.pose
        msg = PoseStamped()
        msg.header.frame_id = self._frame
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y = p.x, p.y
        msg.pose.orientation.z, msg.pose.orientation.w = math.sin(p.theta / 2), math.cos(p.theta / 2)
        return msg

    def _publish_pose(self) -> None:
        msg = self._pose_msg()
        self._pose_pub.publish(msg)
        if self._tf_pub is not None:
            from geometry_msgs.msg import TransformStamped

            t = TransformStamped()
            t.header = msg.header
            t.child_frame_id = self._base_frame
            t.transform.translation.x, t.transform.translation.y = msg.pose.position.x, msg.pose.position.y
            t.transform.rotation = msg.pose.orientation
            self._tf_pub.publish(self._tf_msg(transforms=[t]))


def main(args: list[str] | None = None) -> int:
    return run_sim_node(MockNavServer, "mock_nav_server", args)


if __name__ == "__main__":
    raise SystemExit(main())
