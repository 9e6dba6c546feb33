"""Stage 0 with the brain, over real ROS 2 processes: the whole simulated robot (object database,
simulated hardware, decision maker with ``exploration_mode``), the camera and the explorer.

A command sent while the robot explores is queued with "Still exploring ...; I will do it after."
and runs when exploration ends; a stop during exploration ends it.
"""

from __future__ import annotations

import json
import threading

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import COMMAND_QOS, STATUS_QOS
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.testing import wait_for

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
SMALL_CAMERA = ["sim_camera.width=100", "sim_camera.height=57", "sim_camera.rate_hz=3.0"]


def specs(with_query: bool):
    robot = [s for s in load_nodeset("sim_robot") if with_query or s.name != "object_query_server"]
    return robot + [s for s in load_nodeset("explore") if s.name in ("sim_camera", "explorer")]


class Watch:
    """Statuses and exploration progress seen by the test."""

    def __init__(self, node) -> None:
        self._lock = threading.Lock()  # guards statuses, progress
        self.statuses: list[TaskStatus] = []
        self.progress: list[dict] = []
        self.cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
        self.status_sub = node.create_subscription(String, "task_status", self._on_status, STATUS_QOS)
        node.create_subscription(String, "exploration/progress", self._on_progress, LATCHED)

    def _on_status(self, msg: String) -> None:
        with self._lock:
            self.statuses.append(TaskStatus.from_json(msg.data))

    def _on_progress(self, msg: String) -> None:
        with self._lock:
            self.progress.append(json.loads(msg.data))

    def of(self, text: str) -> list[TaskStatus]:
        with self._lock:
            return [s for s in self.statuses if s.text == text]

    def last_progress(self) -> dict:
        with self._lock:
            return dict(self.progress[-1]) if self.progress else {}


def test_command_waits_for_exploration_then_runs(launch_nodes, ros_node):
    launch_nodes(nodes=specs(True), set=SMALL_CAMERA + ["decision_maker.exploration_mode=queue"], ready_timeout=120)
    w = Watch(ros_node)
    assert wait_for(lambda: w.cmd.get_subscription_count() > 0 and w.status_sub.get_publisher_count() > 0, 20.0)
    w.cmd.publish(String(data="give me the bottle"))
    assert wait_for(lambda: w.of("give me the bottle"), 20.0)
    first = w.of("give me the bottle")[0]
    assert first.state is TaskState.QUEUED and first.sentence.startswith("Still exploring"), first
    assert first.sentence.endswith("I will do it after."), first
    assert wait_for(lambda: any(s.state.terminal for s in w.of("give me the bottle")), 300.0, 0.5), \
        f"no final status; exploration {w.last_progress()}"
    final = [s for s in w.of("give me the bottle") if s.state.terminal][0]
    assert final.state is TaskState.SUCCEEDED, final
    p = w.last_progress()
    assert p["state"] == "done" and p["reason"] == "no reachable frontier left", p  # it ran after exploring
    running = [s for s in w.of("give me the bottle") if s.state is TaskState.RUNNING]
    assert running and running[0].stamp >= first.stamp


def test_stop_ends_exploration(launch_nodes, ros_node):
    launch_nodes(nodes=specs(False), set=SMALL_CAMERA + ["decision_maker.exploration_mode=queue"], ready_timeout=120)
    w = Watch(ros_node)
    assert wait_for(lambda: w.cmd.get_subscription_count() > 0 and w.status_sub.get_publisher_count() > 0, 20.0)
    assert wait_for(lambda: w.last_progress().get("goals", 0) >= 1, 60.0), w.last_progress()
    w.cmd.publish(String(data="stop"))
    assert wait_for(lambda: w.last_progress().get("state") == "done", 30.0), w.last_progress()
    assert "cancelled" in w.last_progress()["reason"]
