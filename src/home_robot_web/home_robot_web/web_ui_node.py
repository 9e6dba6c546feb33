"""``web_ui_node``: the robot's web page (thin ROS shell over :mod:`.server`).

Serves one page at ``http://127.0.0.1:<port>/`` (printed in the ``ready:`` line): a command box
(through the decision maker's acknowledged ``submit_command`` service), the task status as a live
log, a STOP button (``/cancel_command``), the object memory and the 3-D map with the robot, its path
and the objects. With ``expose: true`` it binds ``bind_address`` (the home network) and every request
needs the pairing token (printed once, or kept in ``token_file``, owner-only).

Topics and services:
    submit_command (decision_maker_interfaces/srv/SubmitCommand, client): commands typed on the page.
    /cancel_command (std_msgs/String, out): the page's STOP.
    /task_status (std_msgs/String JSON, in): shown as the task log.
    /object_memory (object_query_interfaces/ObjectMemory, in, latched): the object list and the map's objects.
    ``pose_topic`` (geometry_msgs/PoseStamped, in, latched): the robot and its path.
    ``nav_status_topic`` (action_msgs/GoalStatusArray, in): the navigation goal's state (CANCELED after STOP).

Every callback hands its event to the server's thread (never blocks); a malformed message is logged
and skipped. The code defaults below are config/params/web_ui.yaml's values (a test compares them).
"""

from __future__ import annotations

import collections
import math
import os
import socket
import time
from importlib import resources
from typing import Any

from action_msgs.msg import GoalStatus, GoalStatusArray
from geometry_msgs.msg import PoseStamped
from object_query_interfaces.msg import ObjectMemory
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.client.command_client import Ack, CommandClient
from decision_maker.topics import CANCEL_COMMAND, CANCEL_QOS, STATUS_QOS, TASK_STATUS
from home_robot_ros.startup import read_once, spin_node
from home_robot_web.auth import AttemptLimiter, Gate, generate_token, read_token_file
from home_robot_web.errors import ConfigError, ServerError
from home_robot_web.protocol import goal_event, memory_event, robot_event, status_event
from home_robot_web.scene import Path2D, map_points, yaw_of
from home_robot_web.server import ServerConfig, WebServer, loggable

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
#: Action status topics are latched; a few entries so no change is missed in a burst.
GOAL_STATUS_QOS = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL,
                             reliability=ReliabilityPolicy.RELIABLE)
GOAL_STATES = {GoalStatus.STATUS_ACCEPTED: "accepted", GoalStatus.STATUS_EXECUTING: "executing",
               GoalStatus.STATUS_CANCELING: "canceling", GoalStatus.STATUS_SUCCEEDED: "succeeded",
               GoalStatus.STATUS_CANCELED: "canceled", GoalStatus.STATUS_ABORTED: "aborted"}

#: Parameters and their defaults (= config/params/web_ui.yaml).
DEFAULTS: dict[str, Any] = {
    "expose": False, "bind_address": "0.0.0.0", "port": 8090, "token_file": "",
    "max_failures": 5, "failure_window_s": 60.0, "lockout_s": 60.0,
    "max_message_bytes": 4096, "max_text_chars": 500, "max_clients": 16, "messages_per_s": 20.0,
    "status_history": 200, "answer_timeout_s": 5.0,
    "map_path": "", "max_map_points": 20000, "pose_topic": "robot_pose",
    "nav_status_topic": "navigate_to_pose/_action/status",
}


def bundled_map() -> str:
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("object_query"), "data", "params.npz")


def page_html() -> bytes:
    return resources.files("home_robot_web").joinpath("static/index.html").read_bytes()


class WebUiNode(Node):
    def __init__(self) -> None:
        super().__init__("web_ui")
        v = read_once(self, DEFAULTS)
        expose = bool(v["expose"])
        host = str(v["bind_address"]) if expose else "127.0.0.1"
        config = ServerConfig(host=host, port=int(v["port"]), max_message_bytes=int(v["max_message_bytes"]),
                              max_text_chars=int(v["max_text_chars"]), max_clients=int(v["max_clients"]),
                              messages_per_s=float(v["messages_per_s"]), status_history=int(v["status_history"]))
        token, told = self._token(expose, str(v["token_file"]))
        limiter = AttemptLimiter(int(v["max_failures"]), float(v["failure_window_s"]), float(v["lockout_s"]))
        gate = Gate(token, limiter, loopback_only=not expose)
        if not float(v["answer_timeout_s"]) > 0:
            raise ConfigError(f"answer_timeout_s must be > 0, got {v['answer_timeout_s']}")

        group = ReentrantCallbackGroup()
        self._commands = CommandClient(self, callback_group=group, answer_timeout_s=float(v["answer_timeout_s"]))
        self._cancel_pub = self.create_publisher(String, CANCEL_COMMAND, CANCEL_QOS)
        self._path = Path2D()
        self._goals: collections.OrderedDict[bytes, int] = collections.OrderedDict()  # goal id -> last status

        self.server = WebServer(config, gate, self, page_html(), self._log)
        self.server.start()  # raises ServerError (a ConfigError for main: address in use, ...)
        self._show_map(str(v["map_path"]) or bundled_map(), int(v["max_map_points"]))

        self.create_subscription(String, TASK_STATUS, self._on_status, STATUS_QOS, callback_group=group)
        self.create_subscription(ObjectMemory, "object_memory", self._on_memory, LATCHED, callback_group=group)
        self.create_subscription(PoseStamped, str(v["pose_topic"]), self._on_pose, LATCHED, callback_group=group)
        self.create_subscription(GoalStatusArray, str(v["nav_status_topic"]), self._on_goals, GOAL_STATUS_QOS,
                                 callback_group=group)
        url = self.server.url if not expose else f"http://{self._public_host(host)}:{self.server.port}/"
        if token is not None and told:
            # shown once, on this terminal only: not through the logger, which also writes /rosout and ~/.ros/log
            print(f"pairing token (shown once): {token} — open {url}?token={token}", flush=True)
        where = f"exposed on {host}, pairing token required" if expose else "loopback only"
        self.get_logger().info(f"ready: web UI at {url} ({where}; commands via {self._commands.service_name})")

    # --- setup helpers --------------------------------------------------------------------------------

    def _token(self, expose: bool, token_file: str) -> tuple[str | None, bool]:
        """The pairing token (None on loopback), and whether it must be printed (a new one)."""
        if not expose:
            return None, False
        if not token_file:
            return generate_token(), True
        token, created = read_token_file(os.path.expanduser(token_file))
        self.get_logger().info(f"pairing token {'written to' if created else 'read from'} {token_file} (owner only)")
        return token, created

    @staticmethod
    def _public_host(host: str) -> str:
        return socket.gethostname() if host in ("0.0.0.0", "::") else host

    def _show_map(self, path: str, max_points: int) -> None:
        try:
            event = map_points(path, max_points)
        except ConfigError as exc:  # the page works without a map (the robot and objects are still drawn)
            self.get_logger().warn(f"map not shown: {exc}")
            return
        self.server.publish(event)
        self.get_logger().info(f"map: {event['n']} points from {path}")

    def _log(self, level: str, text: str) -> None:
        # one call site per severity: rclpy refuses two severities from one line. A request's bytes that are not
        # UTF-8 (websockets keeps them as lone surrogates) are written escaped: rclpy's logger refuses such text
        text = loggable(text)
        log = self.get_logger()
        if level == "error":
            log.error(text)
        elif level == "warn":
            log.warn(text)
        else:
            log.info(text)

    # --- Robot (called from the server's thread; never blocks) -------------------------------------------

    def submit(self, text: str, done) -> None:
        def on_ack(ack: Ack) -> None:
            done({"accepted": ack.accepted, "id": ack.id, "state": ack.state, "message": ack.message,
                  "via": ack.via})

        self._commands.submit_async(text, on_ack)

    def stop(self, reason: str) -> dict[str, Any]:
        self._cancel_pub.publish(String(data=f"web page: {reason}"))
        listeners = self._cancel_pub.get_subscription_count()
        self.get_logger().warn(f"STOP from the web page: /{CANCEL_COMMAND} sent to {listeners} listener(s)")
        return {"listeners": listeners}

    # --- callbacks -------------------------------------------------------------------------------------

    def _on_status(self, msg: String) -> None:
        try:
            self.server.publish(status_event(msg.data))
        except ValueError as exc:
            self.get_logger().warn(f"/{TASK_STATUS} message skipped: {exc}")

    def _on_memory(self, msg: ObjectMemory) -> None:
        out = []
        for inst in msg.instances:
            p = inst.position
            if not (math.isfinite(p.x) and math.isfinite(p.y) and math.isfinite(p.z)
                    and math.isfinite(inst.confidence)):
                continue
            out.append({"id": inst.id[:80], "name": inst.name[:80], "x": p.x, "y": p.y, "z": p.z,
                        "confidence": round(float(inst.confidence), 3),
                        "last_seen": inst.last_seen.sec + inst.last_seen.nanosec * 1e-9,
                        "source": inst.source[:20], "state": inst.state[:20], "place": inst.place[:40],
                        "note": inst.note[:200]})
        self.server.publish(memory_event(out, int(msg.revision)))

    def _on_pose(self, msg: PoseStamped) -> None:
        p, q = msg.pose.position, msg.pose.orientation
        yaw = yaw_of(q.x, q.y, q.z, q.w)
        if not all(math.isfinite(a) for a in (p.x, p.y, yaw)):
            self.get_logger().warn("robot pose skipped: not finite")
            return
        self.server.publish(robot_event(p.x, p.y, yaw, self._path.add(p.x, p.y)))

    def _on_goals(self, msg: GoalStatusArray) -> None:
        now = time.time()
        for st in msg.status_list:
            key = bytes(st.goal_info.goal_id.uuid)
            if self._goals.get(key) == st.status or st.status not in GOAL_STATES:
                continue
            self._goals[key] = st.status
            self._goals.move_to_end(key)
            while len(self._goals) > 100:
                self._goals.popitem(last=False)
            self.server.publish(goal_event(key.hex(), GOAL_STATES[st.status], now))

    def destroy_node(self) -> None:
        self.server.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    return spin_node(WebUiNode, "web_ui", args, (ConfigError, ServerError))  # ServerError: the port taken, ...


if __name__ == "__main__":
    raise SystemExit(main())
