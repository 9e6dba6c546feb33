"""The engine's :class:`~decision_maker.execution.engine.RobotPort` over ROS 2 actions and the object query.

Blocking methods run in the execution thread only; they wait on ``threading.Event`` objects that
future done-callbacks (executor threads) and the batch's abort token set, always with a deadline.
Nothing here spins the node: the node is spun by the decision maker's MultiThreadedExecutor.

Each action call follows the initialise / update / terminate shape: send the goal (after the
server is available), wait for the result while watching the deadline and the abort token, and on
timeout or abort cancel the goal and wait a bounded time (``cancel_wait_s``) for the server to
confirm.

Servers are watched while a call waits: every :data:`WATCH_PERIOD_S` the waiting (execution)
thread asks the ROS graph whether the server is still there (``server_is_ready()`` of the action
client, the object query service's readiness). Gone for :data:`LOST_AFTER_S` → the call fails at
once with :class:`~decision_maker.errors.ServerLost` ("navigation server /navigate_to_pose
disappeared ..."), instead of waiting out the action's timeout. How soon the graph shows a killed
process depends on the DDS participant lease: 2 s with the project's Fast DDS profile
(config/dds/fastdds_liveliness.xml, set by scripts/env.sh), 20 s with Fast DDS's defaults.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

from action_msgs.msg import GoalStatus
from decision_maker_interfaces.action import Grasp, Place
from geometry_msgs.msg import PointStamped, PoseStamped
from nav2_msgs.action import NavigateToPose
from rclpy.action.client import ClientGoalHandle
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node
from rclpy.task import Future
from std_msgs.msg import String

from decision_maker.command_types import FrameTransform, NamedLocation, Point3, Pose2D
from decision_maker.errors import (
    ActionCancelled,
    ActionFailed,
    ActionTimeout,
    ObjectNotFound,
    ServerLost,
    ServerUnavailable,
)
from decision_maker.execution.engine import AbortToken
from home_robot_ros.actions import ActionClient
from home_robot_ros.startup import action_name
from object_query.object_query_client import ObjectQueryClient

_STATUS_NAMES = {GoalStatus.STATUS_SUCCEEDED: "succeeded", GoalStatus.STATUS_ABORTED: "aborted",
                 GoalStatus.STATUS_CANCELED: "canceled"}


#: Prefix of the hardware stops the decision maker publishes (informative only: the topic, not the text,
#: tells them apart from an operator's /cancel_command).
OWN_STOP_PREFIX = "decision_maker: "

#: How often a waiting call checks that its server is still in the ROS graph (seconds).
WATCH_PERIOD_S = 0.1
#: How long a server must be missing from the graph before the call fails (seconds; > one period, so
#: a single odd graph read does not fail a goal).
LOST_AFTER_S = 0.25


class _Watch:
    """Tells a waiting call that its server left the graph (execution thread only; no locks).

    Args:
        present: reads the graph: True while the server is there (never blocks).
        what: the server, for the message ("navigation server /navigate_to_pose").
    """

    def __init__(self, present: Callable[[], bool], what: str) -> None:
        self._present = present
        self._what = what
        self._missing_since: float | None = None

    def check(self) -> None:
        """Raises ServerLost when the server has been missing for LOST_AFTER_S."""
        now = time.monotonic()
        if self._present():
            self._missing_since = None
        elif self._missing_since is None:
            self._missing_since = now
        elif now - self._missing_since >= LOST_AFTER_S:
            raise ServerLost(f"{self._what} disappeared from the ROS graph while waiting for it "
                             "(process died or lost its network)")



def _wait_ready(ready: Callable[[], bool], deadline: float, abort: AbortToken, unavailable: str) -> None:
    """Poll ``ready()`` every 50 ms (an abort wakes it at once) until it holds or ``deadline``.

    Raises:
        ActionCancelled: the abort token was set first.
        ServerUnavailable: ``deadline`` passed (message ``unavailable``).
    """
    wake = threading.Event()
    remove = abort.add_waker(wake)
    try:
        while not ready():
            if abort.is_set():
                raise ActionCancelled(abort.reason)
            left = deadline - time.monotonic()
            if left <= 0:
                raise ServerUnavailable(unavailable)
            wake.wait(min(0.05, left))
            wake.clear()
    finally:
        remove()

class RosRobot:
    """Navigation, grasp, place and object lookup for the execution engine.

    Args:
        node: the decision maker node (spun elsewhere).
        group: callback group of the action/service clients (not the input group).
        cancel_publisher: publisher of the hardware stop (``/hardware_stop``, ``std_msgs/String``: the
            reason), which the hardware layer obeys like ``/cancel_command``.
        frames: map → command frame transform (Isaac Sim etc.; identity by default).
        server_wait_s: longest wait for an action server / the query service per call (> 0).
        cancel_wait_s: longest wait for a cancelled goal's final result (> 0).
        names: action / service names: ``nav``, ``grasp``, ``place``, ``query``.
        on_goal_sent: called with the action name right after a goal is sent (for logs/benchmarks).
    """

    def __init__(self, node: Node, group: CallbackGroup, cancel_publisher, frames: FrameTransform,
                 server_wait_s: float = 5.0, cancel_wait_s: float = 2.0, names: dict[str, str] | None = None,
                 on_goal_sent: Callable[[str], None] | None = None) -> None:
        names = {"nav": "navigate_to_pose", "grasp": "grasp", "place": "place", "query": "object_query",
                 **(names or {})}
        self._node = node
        self._frames = frames
        self._server_wait_s = server_wait_s
        self._cancel_wait_s = cancel_wait_s
        self._cancel_pub = cancel_publisher
        self._on_goal_sent = on_goal_sent
        self._nav = ActionClient(node, NavigateToPose, action_name(node, names["nav"]), callback_group=group)
        self._grasp = ActionClient(node, Grasp, action_name(node, names["grasp"]), callback_group=group)
        self._place = ActionClient(node, Place, action_name(node, names["place"]), callback_group=group)
        self._query = ObjectQueryClient(node, names["query"], callback_group=group)
        self._query_name = names["query"]
        self._names = {id(self._nav): names["nav"], id(self._grasp): names["grasp"], id(self._place): names["place"]}
        self._lock = threading.Lock()  # guards _active
        self._active: list[ClientGoalHandle] = []  # goals accepted and not finished

    # --- RobotPort ---------------------------------------------------------------------------------

    def navigate(self, pose: Pose2D, timeout_s: float, abort: AbortToken) -> None:
        p = self._frames.pose(pose)
        goal = NavigateToPose.Goal()
        goal.pose = self._pose_stamped(p.x, p.y, 0.0, p.theta)
        result = self._run_action(self._nav, goal, timeout_s, abort, "navigation")
        if result.error_code != 0:
            raise ActionFailed(f"navigation failed (error {result.error_code}: {result.error_msg})")

    def locate(self, name: str, timeout_s: float, abort: AbortToken) -> Point3:
        deadline = time.monotonic() + timeout_s
        _wait_ready(lambda: self._query.wait_for_service(timeout_sec=0.0), deadline, abort,
                    f"object query service /{self._query_name} not available after {timeout_s:.1f} s")
        future = self._query.query_async(name)
        watch = _Watch(lambda: self._query.wait_for_service(timeout_sec=0.0),
                       f"object query service /{self._query_name}")
        try:
            answered = self._wait_future(future, deadline, abort, watch)
        except ServerLost:
            self._query.forget(future)
            raise
        if not answered:
            self._query.forget(future)
            if abort.is_set():
                raise ActionCancelled(abort.reason)
            raise ServerUnavailable(f"object query gave no answer within {timeout_s:.1f} s")
        resp = future.result()
        if not resp.found:
            raise ObjectNotFound(resp.message or f"unknown object {name!r}")
        return self._frames.point(Point3(resp.position.x, resp.position.y, resp.position.z))

    def grasp(self, name: str, target: Point3, timeout_s: float, abort: AbortToken) -> None:
        goal = Grasp.Goal()
        goal.object_name = name
        goal.target = PointStamped()
        goal.target.header.frame_id = self._frames.frame_id
        goal.target.header.stamp = self._node.get_clock().now().to_msg()
        goal.target.point.x, goal.target.point.y, goal.target.point.z = target.x, target.y, target.z
        result = self._run_action(self._grasp, goal, timeout_s, abort, "grasp")
        if not result.success:
            raise ActionFailed(result.message or "grasp failed")

    def place(self, location: NamedLocation, target: Point3, timeout_s: float, abort: AbortToken) -> None:
        t = self._frames.point(target)
        goal = Place.Goal()
        goal.location_name = location.name
        goal.target_pose = self._pose_stamped(t.x, t.y, t.z, self._frames.pose(location.pose).theta)
        result = self._run_action(self._place, goal, timeout_s, abort, "place")
        if not result.success:
            raise ActionFailed(result.message or "place failed")

    def cancel_active(self) -> None:
        with self._lock:
            handles = list(self._active)
        for gh in handles:
            self._cancel(gh)

    def _cancel(self, gh: ClientGoalHandle) -> None:
        try:
            gh.cancel_goal_async()
        except Exception as exc:  # context already shut down (Ctrl-C), ...
            print(f"decision_maker: cancel of an active goal failed: {exc!r}", flush=True)

    def emergency_stop(self, reason: str) -> None:
        self._node.get_logger().warn(f"publishing /{self._cancel_pub.topic_name.lstrip('/')}: {reason}")
        self._cancel_pub.publish(String(data=f"{OWN_STOP_PREFIX}{reason}"))

    # --- helpers -----------------------------------------------------------------------------------

    def _pose_stamped(self, x: float, y: float, z: float, theta: float) -> PoseStamped:
        msg = PoseStamped()
        msg.header.frame_id = self._frames.frame_id
        msg.header.stamp = self._node.get_clock().now().to_msg()
        msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = x, y, z
        msg.pose.orientation.z, msg.pose.orientation.w = math.sin(theta / 2), math.cos(theta / 2)
        return msg

    @staticmethod
    def _wait_future(future: Future, deadline: float, abort: AbortToken | None, watch: _Watch | None = None) -> bool:
        """Wait until ``future`` is done (True), ``deadline`` passes or ``abort`` is set (False).

        Raises:
            ServerLost: ``watch`` saw the server leave the graph (checked every WATCH_PERIOD_S).
        """
        wake = threading.Event()
        future.add_done_callback(lambda _f: wake.set())
        remove = abort.add_waker(wake) if abort is not None else (lambda: None)
        try:
            while not future.done():
                if abort is not None and abort.is_set():
                    return False
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                if watch is not None:
                    watch.check()
                    left = min(left, WATCH_PERIOD_S)
                wake.wait(left)
                wake.clear()
            return True
        finally:
            remove()

    def _run_action(self, client: ActionClient, goal, timeout_s: float, abort: AbortToken, what: str):
        """Send ``goal`` and wait for its result; cancel it on timeout/abort. Returns the result message.

        Raises:
            ServerUnavailable, ActionFailed, ActionTimeout (goal cancelled), ActionCancelled.
        """
        start = time.monotonic()
        deadline = start + timeout_s
        server_deadline = min(deadline, start + self._server_wait_s)
        _wait_ready(client.server_is_ready, server_deadline, abort,
                    f"{what} server /{self._names[id(client)]} not available after {server_deadline - start:.1f} s")
        send_future = client.send_goal_async(goal)
        if self._on_goal_sent is not None:
            self._on_goal_sent(what)
        watch = _Watch(client.server_is_ready, f"{what} server /{self._names[id(client)]}")
        accepted = self._wait_future(send_future, deadline, abort, watch)
        if not accepted:
            # the goal may still be accepted: give it a bounded chance, then cancel it
            if self._wait_future(send_future, time.monotonic() + self._cancel_wait_s, None):
                gh = send_future.result()
                if gh.accepted:
                    self._cancel(gh)
            if abort.is_set():
                raise ActionCancelled(abort.reason)
            raise ActionTimeout(f"{what} goal not accepted within {timeout_s:.1f} s")
        gh: ClientGoalHandle = send_future.result()
        if not gh.accepted:
            raise ActionFailed(f"{what} goal rejected by the server")
        with self._lock:
            self._active.append(gh)
        try:
            if abort.is_set():  # a cancel arrived while the goal was being accepted
                self._cancel(gh)
            result_future = gh.get_result_async()
            if not self._wait_future(result_future, deadline, abort, watch):
                timed_out = not abort.is_set()
                self._cancel(gh)  # (again, if the cancel path already did: harmless)
                self._wait_future(result_future, time.monotonic() + self._cancel_wait_s, None)
                if timed_out:
                    raise ActionTimeout(f"{what} did not finish within {timeout_s:.1f} s; goal cancelled")
                raise ActionCancelled(abort.reason)
            response = result_future.result()
        finally:
            with self._lock:
                if gh in self._active:
                    self._active.remove(gh)
        if response.status == GoalStatus.STATUS_SUCCEEDED:
            return response.result
        if response.status == GoalStatus.STATUS_CANCELED:
            raise ActionCancelled(abort.reason if abort.is_set() else f"{what} goal was cancelled")
        msg = getattr(response.result, "message", "") or getattr(response.result, "error_msg", "")
        state = _STATUS_NAMES.get(response.status, f"status {response.status}")
        raise ActionFailed(f"{what} {state}" + (f": {msg}" if msg else ""))
