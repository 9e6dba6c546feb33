"""Integration: acknowledged commands, stops that always stop, bad inputs, dead servers.

Real processes on a leased ROS_DOMAIN_ID (node set ``sim_robot``); the test process is the
operator / the attacker. No timing asserts: every wait has a generous deadline, and "fast" means
well inside the old failure (61 s to reject a 10 MB command; a dead server noticed after 60 s).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import threading
import time

import pytest
from decision_maker_interfaces.action import Grasp, Place
from geometry_msgs.msg import PoseStamped
from nav2_msgs.action import NavigateToPose
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from decision_maker.client.command_client import Ack, CommandClient
from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import COMMAND_QOS, STATUS_HISTORY_QOS
from home_robot_bringup.testing import wait_for
from home_robot_ros.actions import ActionClient

pytestmark = pytest.mark.ros

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)

#: Fast DDS profile with a participant lease far above any freeze below (the project's is 2 s). A brain frozen longer
#: than the lease is dropped by its peers, and Fast DDS then sometimes never sends its endpoints again (the operator
#: never hears from it, nor it from the operator): a lost participant, not the late answer a test means to make.
LONG_LEASE_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<dds xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <profiles>
    <participant profile_name="long_lease_participant" is_default_profile="true">
      <rtps><builtin><discovery_config>
        <leaseDuration><sec>300</sec></leaseDuration>
        <leaseAnnouncement><nanosec>250000000</nanosec></leaseAnnouncement>
      </discovery_config></builtin></rtps>
    </participant>
  </profiles>
</dds>
"""


class Operator:
    """Sends commands (service and topic) and cancels; records every /task_status (the brain's kept ones too)."""

    def __init__(self, node) -> None:
        self._lock = threading.Lock()  # guards statuses, world
        self.statuses: list[TaskStatus] = []
        self._seen: set[str] = set()  # messages received: one matched again gets the kept updates a second time
        self.world: str | None = None
        self.client = CommandClient(node, answer_timeout_s=30.0)
        self._cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
        self._cancel = node.create_publisher(String, "cancel_command", QoSProfile(depth=10))
        self._status = node.create_subscription(String, "task_status", self._on_status, STATUS_HISTORY_QOS)
        node.create_subscription(String, "sim/world_state", self._on_world, LATCHED)

    def _on_status(self, msg: String) -> None:
        with self._lock:
            if msg.data not in self._seen:  # each update is stamped: an identical message is the same update
                self._seen.add(msg.data)
                self.statuses.append(TaskStatus.from_json(msg.data))

    def _on_world(self, msg: String) -> None:
        with self._lock:
            self.world = msg.data

    def wait_connected(self) -> None:
        assert self.client.wait_for_service(30.0), "no submit_command service"
        assert wait_for(lambda: self._cmd.get_subscription_count() > 0 and self._cancel.get_subscription_count() > 0
                        and self._status.get_publisher_count() > 0, 20.0), "decision maker not connected"

    def by_id(self, cid: int) -> list[TaskStatus]:
        with self._lock:
            return [s for s in self.statuses if s.id == cid]

    def final(self, cid: int, timeout: float = 30.0) -> TaskStatus:
        assert wait_for(lambda: any(s.state.terminal for s in self.by_id(cid)), timeout), self.by_id(cid)
        finals = [s for s in self.by_id(cid) if s.state.terminal]
        assert len(finals) == 1, finals
        return finals[0]

    def running(self, cid: int, step: int = 1, timeout: float = 20.0) -> None:
        assert wait_for(lambda: any(s.state is TaskState.RUNNING and s.step >= step for s in self.by_id(cid)),
                        timeout), self.by_id(cid)

    def submit(self, text: str) -> Ack:
        ack = self.client.submit(text, 30.0)
        assert ack.via == "service" and ack.state != "no_answer", ack
        return ack

    def publish(self, text: str) -> None:
        self._cmd.publish(String(data=text))

    def cancel(self, text: str) -> None:
        self._cancel.publish(String(data=text))


@pytest.mark.slow
def test_acknowledged_burst_spoofed_cancel_huge_command_and_spoken_stop(launch_nodes, ros_node):
    # slow enough that the first command still drives when the burst has been answered, also on a loaded machine
    # (at 0.3 m/s and load 15 it reached the kitchen first); every drive below is cancelled on the way
    launch_nodes(nodeset="sim_robot", set=["mock_nav_server.speed=0.1"])
    op = Operator(ros_node)
    op.wait_connected()

    # 1. a burst through the service: every command gets an id or an explicit rejection, none lost
    n = 1000
    acks: list[Ack] = []
    lock = threading.Lock()

    def keep(ack: Ack) -> None:
        with lock:
            acks.append(ack)

    for _ in range(n):
        op.client.submit_async("go to the kitchen", keep)
    assert wait_for(lambda: len(acks) == n, 120.0), f"{len(acks)} of {n} answered"
    assert all(a.via == "service" and a.state != "no_answer" for a in acks), [a for a in acks if a.state == "no_answer"]
    taken = [a for a in acks if a.accepted]
    refused = [a for a in acks if not a.accepted]
    assert all(a.state == "queued" and a.id > 0 for a in taken)
    assert all(a.state == "rejected" and "queue full" in a.message for a in refused)
    assert len({a.id for a in acks}) == n  # one id each, rejected ones included
    assert len(taken) == 11 and len(refused) == n - 11  # the running one + a queue of 10
    print(f"\nburst of {n} via submit_command: {len(taken)} queued, {len(refused)} rejected, 0 lost")

    # 2. an operator's cancel that starts with "decision_maker: " still stops everything
    first = min(a.id for a in taken)
    op.running(first)
    op.cancel("decision_maker: operator stop that looks like the brain's echo")
    for a in taken:
        assert op.final(a.id, 20.0).state is TaskState.CANCELLED

    # 3. 10 MB of U+FDFA on the topic while a command runs: rejected unnormalised, cancel still prompt
    active = op.submit("go to the kitchen")
    op.running(active.id)
    t_sent = len(op.statuses)
    t0 = time.monotonic()
    op.publish("\ufdfa" * 3_500_000)
    assert wait_for(lambda: any(s.state is TaskState.REJECTED and "before normalisation" in s.message
                                for s in op.statuses[t_sent:]), 30.0), op.statuses[t_sent:]
    t1 = time.monotonic()
    op.cancel("stop after the huge command")
    final = op.final(active.id, 10.0)
    assert final.state is TaskState.CANCELLED and "huge command" in final.message, final
    print(f"10 MB U+FDFA command: rejected {t1 - t0:.2f} s after publishing; "
          f"cancel -> cancelled {time.monotonic() - t1:.2f} s")

    # 4. a spoken/typed stop is never queued: through the service ...
    moving = op.submit("go to the kitchen")
    waiting = op.submit("go home")
    op.running(moving.id)
    stop = op.submit("Stop it!")
    assert stop.accepted and stop.state == "succeeded" and "cancelled 2 command(s)" in stop.message, stop
    assert op.final(moving.id, 10.0).state is TaskState.CANCELLED
    assert op.final(waiting.id, 10.0).state is TaskState.CANCELLED
    # ... and on /manual_command
    moving = op.submit("go home")
    op.running(moving.id)
    op.publish("cancel")
    final = op.final(moving.id, 10.0)
    assert final.state is TaskState.CANCELLED and "spoken stop" in final.message, final


def _goal_rejected(client: ActionClient, goal, timeout: float = 15.0) -> bool:
    future = client.send_goal_async(goal)
    assert wait_for(future.done, timeout), "no answer to a goal"
    return not future.result().accepted


def _nav_goal(x: float, y: float, frame: str = "map", qw: float = 1.0) -> NavigateToPose.Goal:
    goal = NavigateToPose.Goal()
    goal.pose.header.frame_id = frame
    goal.pose.pose.position.x, goal.pose.pose.position.y = x, y
    goal.pose.pose.orientation.w = qw
    return goal


def test_mock_servers_survive_fuzz_and_reject_with_reasons(launch_nodes, ros_node):
    sup = launch_nodes(nodeset="mock_actions", set=["mock_nav_server.speed=8.0", "mock_nav_server.turn_rate=30.0"])
    nav = ActionClient(ros_node, NavigateToPose, "navigate_to_pose")
    grasp = ActionClient(ros_node, Grasp, "grasp")
    place = ActionClient(ros_node, Place, "place")
    assert nav.wait_for_server(timeout_sec=20.0) and grasp.wait_for_server(timeout_sec=20.0)
    assert place.wait_for_server(timeout_sec=20.0)
    nan, inf, big, huge = math.nan, math.inf, 1.7e308, "x" * 1_000_000
    tried = 0

    # navigate_to_pose: not finite, overflowing, outside the workspace, bad orientation, wrong/huge frames
    for goal in (_nav_goal(nan, 0.0), _nav_goal(inf, 1.0), _nav_goal(big, 0.0), _nav_goal(-big, big),
                 _nav_goal(1e6, 0.0), _nav_goal(1e10, 1e10), _nav_goal(1.0, 1.0, qw=0.0), _nav_goal(1.0, 1.0, qw=nan),
                 _nav_goal(1.0, 1.0, frame="odom"), _nav_goal(1.0, 1.0, frame=huge)):
        assert _goal_rejected(nav, goal), goal.pose
        tried += 1
    # grasp and place: bad points, names, frames
    for name, (x, y, z), frame in (("bottle", (nan, 0.0, 0.0), "map"), ("bottle", (big, 0.0, 0.0), "map"),
                                   ("bottle", (0.0, inf, 0.0), "map"), (huge, (5.2, 0.3, 1.0), "map"),
                                   ("", (5.2, 0.3, 1.0), "map"), ("bottle", (5.2, 0.3, 1.0), "odom")):
        g = Grasp.Goal(object_name=name)
        g.target.header.frame_id = frame
        g.target.point.x, g.target.point.y, g.target.point.z = x, y, z
        assert _goal_rejected(grasp, g), (name[:10], x, y, z, frame)
        p = Place.Goal(location_name=name or "")
        p.target_pose.header.frame_id = frame
        p.target_pose.pose.position.x, p.target_pose.pose.position.y, p.target_pose.pose.position.z = x, y, z
        p.target_pose.pose.orientation.w = 1.0
        assert _goal_rejected(place, p), (name[:10], x, y, z, frame)
        tried += 2

    # subscribed topics: robot_pose (not finite / far / wrong frame), cancel_command, hardware_stop
    pose_pub = ros_node.create_publisher(PoseStamped, "robot_pose", LATCHED)  # the simulated nav's QoS
    world: list[str] = []
    ros_node.create_subscription(String, "sim/world_state", lambda m: world.append(m.data), LATCHED)
    assert wait_for(lambda: pose_pub.get_subscription_count() >= 1, 20.0)
    for x, y, frame, qw in ((nan, 0.0, "map", 1.0), (inf, -inf, "map", 1.0), (big, big, "map", 1.0),
                            (1.0, 1.0, "odom", 1.0), (1.0, 1.0, "map", nan), (1.0, 1.0, huge, 1.0)):
        msg = PoseStamped()
        msg.header.frame_id = frame
        msg.pose.position.x, msg.pose.position.y = x, y
        msg.pose.orientation.w = qw
        pose_pub.publish(msg)
        tried += 1
        time.sleep(0.05)  # depth 1: let each one be taken before the next replaces it
    for topic in ("cancel_command", "hardware_stop"):
        pub = ros_node.create_publisher(String, topic, QoSProfile(depth=10))
        assert wait_for(lambda p=pub: p.get_subscription_count() >= 2, 20.0)
        for text in (huge, "\ufdfa" * 100_000, "\x00\x1b[31m", ""):
            pub.publish(String(data=text))
            tried += 1
    assert wait_for(lambda: len(world) >= 3, 20.0)
    # every world state after the fuzz has a finite robot pose; both servers still run
    assert wait_for(lambda: "ignoring a robot_pose" in sup.get("mock_grasp_server").output(), 10.0)
    assert all("NaN" not in w and "Infinity" not in w for w in world), [w for w in world if "NaN" in w][:1]
    for proc in ("mock_nav_server", "mock_grasp_server"):
        assert sup.get(proc).returncode() is None, sup.get(proc).output()
    # and they still work: a valid goal is accepted and reached
    future = nav.send_goal_async(_nav_goal(1.0, 0.5))
    assert wait_for(future.done, 15.0) and future.result().accepted
    result = future.result().get_result_async()
    assert wait_for(result.done, 20.0) and result.result().result.error_code == 0
    assert "goal rejected: goal x = 1.7e+308 is outside the workspace" in sup.get("mock_nav_server").output()
    print(f"\nfuzz: {tried} bad goals/messages to 3 action servers and 3 topics; 0 nodes died")


def test_killed_nav_server_fails_the_goal_fast_and_keeps_the_queue(launch_nodes, ros_node):
    sup = launch_nodes(nodeset="sim_robot", set=["mock_nav_server.speed=0.3", "decision_maker.nav_timeout_s=60.0"])
    op = Operator(ros_node)
    op.wait_connected()
    moving = op.submit("go to the kitchen")
    queued = op.submit("go home")
    op.running(moving.id)
    nav = sup.get("mock_nav_server")
    assert wait_for(lambda: "goal: (" in nav.output(), 30.0), nav.output()  # the goal is active on the server
    t_kill = time.monotonic()
    os.kill(nav.popen.pid, signal.SIGKILL)
    final = op.final(moving.id, 40.0)
    took = time.monotonic() - t_kill
    print(f"\nnav server killed -> command failed after {took:.2f} s (nav_timeout_s 60 s)")
    assert final.state is TaskState.FAILED and "disappeared" in final.message, final
    assert took < 30.0  # half the navigation timeout: the timeout did not end it, the watch did
    # the queue was kept: the next command ran, and failed on the missing server within its own wait
    nxt = op.final(queued.id, 40.0)
    assert nxt.state is TaskState.FAILED and "not available" in nxt.message, nxt

    # the object database killed: the next object query fails with the reason within query_timeout_s
    db = sup.get("object_query_server")
    os.kill(db.popen.pid, signal.SIGKILL)
    t_kill = time.monotonic()
    grasp = op.submit("grasp:cup")
    final = op.final(grasp.id, 40.0)
    print(f"object database killed -> grasp:cup failed after {time.monotonic() - t_kill:.2f} s (query_timeout_s 5 s)")
    assert final.state is TaskState.FAILED and "object query" in final.message, final


def _stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (SIGSTOP): state ``T`` in /proc/PID/stat."""
    with open(f"/proc/{pid}/stat") as f:
        return f.read().rsplit(")", 1)[1].split()[0] == "T"


#: How long the brain is frozen: under the participant lease (2 s, scripts/env.sh's Fast DDS profile) with margin.
FREEZE_S = 1.2


def test_a_call_whose_answer_is_late_is_sent_again_and_run_once(launch_nodes, ros_node, tmp_path):
    """The brain frozen (SIGSTOP) while a command is in flight: the client sends the same call again
    (same key); thawed, the brain runs the command once and answers every copy with its id.

    A late answer, not a lost participant: a freeze past the participant lease makes the peers drop each other,
    and Fast DDS then sometimes never sends the endpoints again (see LONG_LEASE_PROFILE; the brain drops the
    operator's process too, whose lease is 2 s). So a helper process thaws the brain after FREEZE_S, however
    starved this process is (pytest -n 3 on 2 cores), and the nodes get a long lease besides. An operator that
    joins after the command started still gets its updates (/task_status keeps them)."""
    profile = tmp_path / "long_lease.xml"
    profile.write_text(LONG_LEASE_PROFILE)
    sup = launch_nodes(nodeset="sim_robot", set=["mock_nav_server.speed=0.1"],
                       env={name: str(profile) for name in ("FASTRTPS_DEFAULT_PROFILES_FILE",
                                                            "FASTDDS_DEFAULT_PROFILES_FILE")})
    op = Operator(ros_node)
    op.wait_connected()
    client = CommandClient(ros_node, answer_timeout_s=60.0, retry_s=0.2)
    assert client.wait_for_service(30.0)
    acks: list[Ack] = []
    brain = sup.get("decision_maker").popen.pid
    freezer = subprocess.Popen(["sh", "-c", f"kill -STOP {brain} && sleep {FREEZE_S} && kill -CONT {brain}"])
    try:
        assert wait_for(lambda: _stopped(brain), 10.0), "the brain was not stopped"
        client.submit_async("go to the kitchen", acks.append)
        wait_for(lambda: client.resends >= 2 or not _stopped(brain), 30.0)
        repeats = client.resends  # sent while the brain was frozen (the first at 0.2 s, the next at 0.6 s)
        assert freezer.wait(30.0) == 0
    finally:
        os.kill(brain, signal.SIGCONT)
        if freezer.poll() is None:
            freezer.kill()
    assert repeats >= 1, "no answer, yet the call was not sent again"
    assert wait_for(lambda: len(acks) == 1, 60.0), acks
    ack = acks[0]
    assert ack.via == "service" and ack.accepted and ack.state == "queued" and ack.id > 0, ack
    op.running(ack.id)
    late = Operator(ros_node)  # joins now: gets the updates kept by the brain
    late.running(ack.id)
    assert [s.state for s in late.by_id(ack.id)][:2] == [TaskState.QUEUED, TaskState.RUNNING], late.by_id(ack.id)
    op.cancel("end of the test")
    assert op.final(ack.id).state is TaskState.CANCELLED
    with op._lock:
        ran = {s.id for s in op.statuses if s.text == "go to the kitchen"}
    assert ran == {ack.id}, op.statuses  # once, whatever the number of copies sent
    assert client.pending() == 0 and len(acks) == 1
    assert "call repeated" in sup.get("decision_maker").output()
    print(f"\nbrain frozen: {client.resends} repeats of one call, 1 command run (#{ack.id}), 1 answer reported")


def test_nl_command_node_falls_back_to_the_topic_with_a_warning(ros_node, ros_domain):
    """No brain (no submit_command service): the command still goes out on /manual_command, and says so."""
    from home_robot_bringup.nodeset import find_executable
    from home_robot_bringup.process import node_environment

    got: list[str] = []
    ros_node.create_subscription(String, "manual_command", lambda m: got.append(m.data), COMMAND_QOS)
    proc = subprocess.run([find_executable("decision_maker", "nl_command_node"), "--no-wait", "--discovery-timeout",
                           "3", "--brain", "test_client"], input="go home\n", env=node_environment(ros_domain),
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "submit_command service is not available" in proc.stderr and "without acknowledgement" in proc.stderr
    assert wait_for(lambda: got == ["go home"], 10.0), got


def test_the_client_answers_text_no_ros_string_can_carry_at_once(ros_node):
    """A lone surrogate (a web page's JSON "\\ud800") cannot be serialised: the client says so in the ack instead of
    raising in its resend timer, which once ended the web page's node."""
    client = CommandClient(ros_node, answer_timeout_s=5.0, retry_s=0.2)
    acks: list[Ack] = []
    client.submit_async("go home \ud800", acks.append)
    assert len(acks) == 1 and not acks[0].accepted and acks[0].state == "rejected"
    assert "not valid Unicode text" in acks[0].message and client.pending() == 0
