"""Integration: the whole simulated robot as real processes over ROS 2 (node set ``sim_robot``).

The test process publishes commands and cancels like the input nodes do, and watches
``/task_status``, ``/cancel_command`` and the simulated world (``sim/world_state``).
Simulation speeds are raised so the scenarios take seconds.
"""

from __future__ import annotations

import json
import math
import subprocess
import threading
import time

import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import COMMAND_QOS, STATUS_QOS
from home_robot_bringup.nodeset import find_executable, load_nodeset
from home_robot_bringup.process import node_environment
from home_robot_bringup.testing import wait_for

pytestmark = pytest.mark.ros

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
FAST = ["mock_nav_server.speed=8.0", "mock_nav_server.turn_rate=30.0",
        "mock_grasp_server.grasp_duration_s=0.2", "mock_grasp_server.place_duration_s=0.2"]
USER_DROP = (1.3, 3.95, 0.75)
BIN_DROP = (5.6, 4.5, 0.5)


class Robot:
    """The test's view of the robot: sends commands/cancels, records statuses, cancels, world state."""

    def __init__(self, node) -> None:
        self._lock = threading.Lock()  # guards statuses, cancels, world, world_count
        self.statuses: list[TaskStatus] = []
        self.cancels: list[tuple[float, str]] = []
        self.world: dict | None = None
        self.world_count = 0  # world states received
        self.status_times: list[float] = []
        self._cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
        self._cancel = node.create_publisher(String, "cancel_command", QoSProfile(depth=10))
        self._status = node.create_subscription(String, "task_status", self._on_status, STATUS_QOS)
        node.create_subscription(String, "cancel_command", self._on_cancel, 10)
        node.create_subscription(String, "hardware_stop", self._on_cancel, 10)  # the brain's own stop
        node.create_subscription(String, "sim/world_state", self._on_world, LATCHED)

    def _on_status(self, msg: String) -> None:
        st = TaskStatus.from_json(msg.data)
        with self._lock:
            self.statuses.append(st)
            self.status_times.append(time.monotonic())

    def _on_cancel(self, msg: String) -> None:
        with self._lock:
            self.cancels.append((time.monotonic(), msg.data))

    def _on_world(self, msg: String) -> None:
        with self._lock:
            self.world = json.loads(msg.data)
            self.world_count += 1

    def fresh_world(self, n: int = 2, timeout: float = 15.0) -> dict:
        """The world state once ``n`` more have arrived: published after this call, whatever the
        load (a fixed sleep may still see a state that was in flight before)."""
        with self._lock:
            start = self.world_count
        assert wait_for(lambda: self.world_count >= start + n, timeout), f"fewer than {n} world states in {timeout} s"
        return self.snapshot()

    def wait_connected(self) -> None:
        assert wait_for(lambda: self._cmd.get_subscription_count() > 0 and self._cancel.get_subscription_count() > 0
                        and self._status.get_publisher_count() > 0, 20.0), "decision maker not connected"
        assert wait_for(lambda: (self.snapshot() or {}).get("robot") is not None, 20.0), "no world state"

    def wait_knows(self, name: str, timeout: float = 40.0) -> None:
        """Until the brain knows where ``name`` is (its object memory/list has arrived): asks
        "where is the <name>" (a question: nothing moves) until the answer is not "I don't know".
        Discovery of the latched object topics can lag the brain's readiness on a loaded machine."""
        text = f"where is the {name}"
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            before = len([s for s in self.of(text) if s.state.terminal])
            self.send(text)
            wait_for(lambda n=before: len([s for s in self.of(text) if s.state.terminal]) > n, 15.0)
            finals = [s for s in self.of(text) if s.state.terminal]
            if len(finals) > before and "don't know" not in finals[-1].sentence:
                return
            time.sleep(0.5)
        raise AssertionError(f"the decision maker never learnt where the {name} is: {self.of(text)}")

    def send(self, text: str) -> None:
        self._cmd.publish(String(data=text))

    def cancel(self, reason: str = "test") -> float:
        t = time.monotonic()
        self._cancel.publish(String(data=reason))
        return t

    def snapshot(self) -> dict | None:
        with self._lock:
            return None if self.world is None else json.loads(json.dumps(self.world))

    def of(self, text: str) -> list[TaskStatus]:
        with self._lock:
            return [s for s in self.statuses if s.text == text]

    def final(self, text: str, timeout: float = 30.0) -> TaskStatus:
        assert wait_for(lambda: any(s.state.terminal for s in self.of(text)), timeout), \
            f"no final status for {text!r}: {self.of(text)}"
        finals = [s for s in self.of(text) if s.state.terminal]
        assert len(finals) == 1, finals
        return finals[0]


def near(pos, target, tol=0.05) -> bool:
    return math.dist(pos, target) <= tol


def robot_specs(with_query: bool = True):
    return [s for s in load_nodeset("sim_robot") if with_query or s.name != "object_query_server"]


def test_three_scenarios_via_nl_command_node(launch_nodes, ros_node, ros_domain):
    """The main job: the three scenarios typed into nl_command_node (piped stdin), final world checked."""
    launch_nodes(nodes=robot_specs(), set=FAST)
    robot = Robot(ros_node)
    robot.wait_connected()
    start = robot.snapshot()
    assert start["held"] is None and near(start["objects"]["bottle"]["position"], (5.2, 0.3, 1.02))

    exe = find_executable("decision_maker", "nl_command_node")
    proc = subprocess.run([exe, "--timeout", "60"], input="Give me the bottle!\ngo home\nclean table\n",
                          env=node_environment(ros_domain), capture_output=True, text=True, timeout=90)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    # the node printed the statuses readably
    assert "[#1 succeeded 3/3]" in proc.stdout and "Step 2 of 3: picking up the bottle" in proc.stdout

    for text in ("Give me the bottle!", "go home", "clean table"):
        assert robot.final(text).state is TaskState.SUCCEEDED
    steps = [(s.step, s.steps, s.primitive) for s in robot.of("Give me the bottle!") if s.state is TaskState.RUNNING
             and s.steps]
    assert steps == [(1, 3, "goto:kitchen"), (2, 3, "grasp:bottle"), (3, 3, "place:user")]
    assert wait_for(lambda: robot.snapshot()["held"] is None
                    and near(robot.snapshot()["objects"]["trash"]["position"], BIN_DROP), 5.0)
    world = robot.snapshot()
    assert near(world["objects"]["bottle"]["position"], USER_DROP), world  # the bottle is with the user
    assert near(world["objects"]["trash"]["position"], BIN_DROP), world  # the trash is in the bin
    assert near(world["objects"]["cup_1"]["position"], (4.6, 0.35, 0.95)), world  # nothing else moved
    assert near((world["robot"]["x"], world["robot"]["y"]), (5.0, 4.1)), world  # it ended at the bin
    assert not robot.cancels


def test_cancel_during_navigation_then_batch_watchdog(launch_nodes, ros_node, ros_domain):
    sup = launch_nodes(nodes=robot_specs(), set=["mock_nav_server.speed=0.5", "decision_maker.batch_timeout_s=3.0"])
    robot = Robot(ros_node)
    robot.wait_connected()
    robot.send("go to the kitchen")
    robot.send("go home")
    robot.send("clean table")
    assert wait_for(lambda: robot.snapshot()["robot"]["x"] > 0.8, 10.0), "robot did not start moving"
    assert [s.state for s in robot.of("clean table")] == [TaskState.QUEUED]
    t_cancel = robot.cancel("operator pressed Enter")
    final = robot.final("go to the kitchen", 10.0)
    with robot._lock:
        t_status = robot.status_times[robot.statuses.index(final)]
    print(f"\ncancel -> task_status cancelled: {(t_status - t_cancel) * 1000:.1f} ms")
    assert final.state is TaskState.CANCELLED and "operator pressed Enter" in final.message
    # the queue is empty: both waiting commands were cancelled, none ran
    for text in ("go home", "clean table"):
        assert robot.final(text, 5.0).state is TaskState.CANCELLED
        assert not [s for s in robot.of(text) if s.state is TaskState.RUNNING]
    # the robot stopped where it was (the world state comes at 2 Hz: compare two fresh ones, >= 1 s apart)
    x0 = robot.fresh_world(2)["robot"]["x"]
    pose = robot.fresh_world(2)["robot"]
    assert abs(pose["x"] - x0) < 0.05 and pose["x"] < 4.0, pose

    # it takes new commands after a cancel
    robot.send(f"goto:{pose['x'] + 0.3:.3f},{pose['y']:.3f},0")
    assert robot.final(f"goto:{pose['x'] + 0.3:.3f},{pose['y']:.3f},0", 15.0).state is TaskState.SUCCEEDED

    # batch watchdog: five 0.5 m legs at 0.5 m/s do not fit in 3 s; the batch stops and /cancel_command goes out
    x, y = robot.snapshot()["robot"]["x"], robot.snapshot()["robot"]["y"]
    legs = "; ".join(f"goto:{x + 0.5 * k:.2f},{y:.2f},0" for k in range(1, 6))
    n_cancels = len(robot.cancels)
    robot.send(legs)
    final = robot.final(legs, 15.0)
    assert final.state is TaskState.TIMED_OUT and "batch" in final.message, final
    assert 2 <= final.step <= 5
    assert wait_for(lambda: len(robot.cancels) > n_cancels, 5.0)
    assert "decision_maker" in robot.cancels[-1][1]

    # cancel_command_node: Enter sends a cancel (idle: nothing to cancel), EOF ends it cleanly
    exe = find_executable("decision_maker", "cancel_command_node")
    env = node_environment(ros_domain)
    proc = subprocess.run([exe], input="\n", env=env, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0 and "cancel sent" in proc.stdout, proc.stdout + proc.stderr
    brain = sup.get("decision_maker")
    assert wait_for(lambda: "/cancel_command (operator: Enter): cancelled 0 command(s)" in brain.output(), 5.0)
    proc = subprocess.run([exe], stdin=subprocess.DEVNULL, env=env, capture_output=True, text=True, timeout=30)
    assert proc.returncode == 0, proc.stderr


def test_nav_hang_timeout_and_object_query_absent(launch_nodes, ros_node, ros_domain):
    """No object database; navigation hangs: both end in clear statuses, a hang stops the hardware."""
    sup = launch_nodes(nodes=robot_specs(with_query=False), set=[
        "mock_nav_server.fault=hang", "decision_maker.nav_timeout_s=1.0", "decision_maker.query_timeout_s=5.0"])
    robot = Robot(ros_node)
    robot.wait_connected()

    # cancel while the brain waits for the (absent) object query service
    robot.send("grasp:cup")
    assert wait_for(lambda: any(s.steps == 1 for s in robot.of("grasp:cup")), 10.0)
    time.sleep(0.3)
    robot.cancel("cancel while waiting for a server")
    final = robot.final("grasp:cup", 10.0)
    assert final.state is TaskState.CANCELLED and "waiting for a server" in final.message, final

    robot.send("grasp:bottle")
    final = robot.final("grasp:bottle", 15.0)
    assert final.state is TaskState.FAILED and "object query service" in final.message, final

    robot.send("go home")
    robot.send("clean table")
    final = robot.final("go home", 15.0)
    # (on a loaded machine the 1 s may already run out before the goal is accepted)
    assert final.state is TaskState.TIMED_OUT and "navigation" in final.message and "within 1.0 s" in final.message, \
        final
    assert wait_for(lambda: any("decision_maker" in c for _, c in robot.cancels), 5.0), robot.cancels
    # the hung goal was cancelled on the server, and the timeout also cleared the queue
    assert wait_for(lambda: "goal cancelled" in sup.get("mock_nav_server").output(), 5.0)
    queued = robot.final("clean table", 5.0)
    assert queued.state is TaskState.CANCELLED and "timed out" in queued.message, queued


def test_bad_inputs_and_flood(launch_nodes, ros_node, ros_domain):
    # (this robot's world is made from the object database's /object_list instead of sim.yaml)
    launch_nodes(nodes=robot_specs(), set=[*FAST, "decision_maker.max_queue=3",
                                           "mock_grasp_server.grasp_duration_s=4.0",
                                           "mock_grasp_server.objects_source=object_list"])
    robot = Robot(ros_node)
    robot.wait_connected()
    assert wait_for(lambda: set(robot.snapshot()["objects"]) == {"bottle", "cup", "trash"}, 10.0), robot.snapshot()
    bottle = robot.snapshot()["objects"]["bottle"]["position"]

    # cancel while grasping: the gripper stays empty, the bottle where it was
    robot.send("give me the bottle")
    assert wait_for(lambda: any(s.step == 2 for s in robot.of("give me the bottle")), 15.0)
    time.sleep(0.5)
    robot.cancel("cancel while grasping")
    final = robot.final("give me the bottle", 10.0)
    assert final.state is TaskState.CANCELLED and final.step == 2, final
    # longer than the grasp would have taken (4 s: the cancel, 0.5 s in, has 3.5 s to land even on a busy machine)
    time.sleep(4.0)
    assert robot.snapshot()["held"] is None and robot.snapshot()["objects"]["bottle"]["position"] == bottle
    cases = {
        "dance for me": (TaskState.REJECTED, "don't know how"),
        "give me the unicorn": (TaskState.FAILED, "unicorn"),
        "goto:1,2": (TaskState.REJECTED, "3 numbers"),
        "goto:attic": (TaskState.REJECTED, "unknown location"),
        "go to the moon": (TaskState.REJECTED, "unknown location"),
        "   ": (TaskState.REJECTED, "empty"),
        "x" * 20000: (TaskState.REJECTED, "too long"),
        "¿dónde? 机器人 🤖 ‮": (TaskState.REJECTED, "don't know how"),
        "GO\tHOME!!! 🏠": (TaskState.SUCCEEDED, "done"),
    }
    from decision_maker.command_types import sanitize_text, shorten

    for text, (state, words) in cases.items():
        robot.send(text)
        final = robot.final(shorten(sanitize_text(text), 200), 20.0)
        assert final.state is state and words in final.message, (text[:40], final)
    world = robot.snapshot()
    assert world["held"] is None and near(world["objects"]["bottle"]["position"], (5.2, 0.3, 1.02), 0.15)

    # a flood: 40 commands at once; the queue holds 3 (+1 running): every command gets exactly one
    # final status, the overflow is rejected explicitly, nothing is lost
    texts = [f"go home {i}" for i in range(40)]
    for t in texts:
        robot.send(t)
    finals = {t: robot.final(t, 30.0) for t in texts}
    states = [f.state for f in finals.values()]
    rejected = [f for f in finals.values() if f.state is TaskState.REJECTED]
    assert set(states) <= {TaskState.SUCCEEDED, TaskState.REJECTED}, states
    assert len(rejected) >= 40 - 4 - 10 and all("queue full" in f.message for f in rejected)
    assert states.count(TaskState.SUCCEEDED) >= 4


def test_payloads_that_break_number_conversion_or_nesting_leave_the_brain_and_the_arm_running(launch_nodes,
                                                                                                ros_node):
    """JSON that parses but is no usable payload: an integer too large for a float (OverflowError in Python), or
    lists nested deeper than the parser recurses (RecursionError), on /object_list and exploration/progress. The
    brain and the simulated arm each say why and keep running, and take the next good list."""
    from decision_maker.topics import OBJECT_LIST_QOS

    sup = launch_nodes(nodes=robot_specs(with_query=False),
                       set=[*FAST, "mock_grasp_server.objects_source=object_list",
                            "decision_maker.exploration_mode=queue"])
    brain, arm = sup.get("decision_maker"), sup.get("mock_grasp_server")
    objects = ros_node.create_publisher(String, "/object_list", OBJECT_LIST_QOS)
    progress = ros_node.create_publisher(String, "exploration/progress", OBJECT_LIST_QOS)
    assert wait_for(lambda: objects.get_subscription_count() >= 2 and progress.get_subscription_count() >= 1, 20.0)
    huge = "1" + "0" * 400
    for pub, data, said in [
            (objects, '{"cup": [1.0, 2.0, ' + huge + "]}", lambda: brain.output().count("malformed /object_list") >= 1
             and arm.output().count("malformed /object_list") >= 1),
            (objects, "[" * 100_000, lambda: brain.output().count("malformed /object_list") >= 2
             and arm.output().count("malformed /object_list") >= 2),
            (progress, '{"state": "exploring", "seen_percent": ' + huge + "}",
             lambda: brain.output().count("ignoring exploration progress") >= 1),
            (progress, "[" * 100_000, lambda: brain.output().count("ignoring exploration progress") >= 2)]:
        pub.publish(String(data=data))
        assert wait_for(said, 20.0), (data[:40], brain.output()[-1500:], arm.output()[-1500:])
    objects.publish(String(data=json.dumps({"bottle": [5.2, 0.3, 1.02], "cup": [4.8, -0.2, 0.95]})))
    assert wait_for(lambda: "object list: bottle, cup" in brain.output()
                    and "world objects from /object_list: bottle, cup" in arm.output(), 20.0), \
        (brain.output()[-1500:], arm.output()[-1500:])
    assert brain.returncode() is None and arm.returncode() is None


@pytest.mark.parametrize("param", ["memory_report_timeout_s:=0.0", "server_wait_s:=-1.0"])
def test_a_wait_that_is_not_positive_is_refused_at_start(ros_domain, param):
    """The node's own waits must be > 0: it exits with status 2 and says which parameter, before any ROS traffic."""
    run = subprocess.run([find_executable("decision_maker", "decision_maker_node"), "--ros-args", "-p", param],
                         env=node_environment(ros_domain), capture_output=True, text=True, timeout=60,
                         stdin=subprocess.DEVNULL)
    name = param.split(":=")[0]
    assert run.returncode == 2 and f"{name} must be > 0" in run.stdout + run.stderr, run.stdout + run.stderr
    assert "Traceback" not in run.stdout + run.stderr
