"""Integration: a scripted day with the living object memory, checked against the simulator's ground truth.

Real processes over ROS 2 (node set ``sim_robot``): the object database on a copy of the sample
map (so its memory is persisted next to it), the simulated base and arm, the decision maker. The
test speaks like a person (``/manual_command``), moves a cup by hand (``sim/move_object``), plays
the camera by rewriting the map as the SLAM engine would (objects where the simulator has them),
restarts the object database, and checks every answer against ``sim/world_state``.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import threading
import time

import numpy as np
import pytest
import yaml
from decision_maker_interfaces.srv import MoveObject
from object_query_interfaces.msg import ObjectMemory as ObjectMemoryMsg
from object_query_interfaces.srv import MemoryQuery
from std_msgs.msg import String

from decision_maker.execution.engine import TaskState, TaskStatus
from decision_maker.topics import COMMAND_QOS, STATUS_QOS
from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.testing import wait_for
from object_query.object_query_server import bundled_map_paths

from .test_decision_maker_ros import BIN_DROP, FAST, LATCHED, USER_DROP

pytestmark = pytest.mark.ros

SOFA_SPOT = (1.0, 4.5, 0.45)  # where a person puts the table cup


class Person:
    """Says commands, reads /task_status, watches the simulated world and the memory."""

    def __init__(self, node) -> None:
        self._lock = threading.Lock()  # guards statuses, world, memory
        self.statuses: list[TaskStatus] = []
        self.world: dict | None = None
        self.memory: ObjectMemoryMsg | None = None
        self._cmd = node.create_publisher(String, "manual_command", COMMAND_QOS)
        self._status = node.create_subscription(String, "task_status", self._on_status, STATUS_QOS)
        node.create_subscription(String, "sim/world_state", self._on_world, LATCHED)
        node.create_subscription(ObjectMemoryMsg, "object_memory", self._on_memory, LATCHED)
        self.move_client = node.create_client(MoveObject, "sim/move_object")
        self.query_client = node.create_client(MemoryQuery, "object_memory/query")

    def _on_status(self, msg: String) -> None:
        with self._lock:
            self.statuses.append(TaskStatus.from_json(msg.data))

    def _on_world(self, msg: String) -> None:
        with self._lock:
            self.world = json.loads(msg.data)

    def _on_memory(self, msg: ObjectMemoryMsg) -> None:
        with self._lock:
            self.memory = msg

    def say(self, text: str, timeout: float = 40.0) -> TaskStatus:
        """Send a command and return its one final status."""
        # a command published before the brain's subscription has matched ours is lost (a topic
        # has no acknowledgement): wait for the match first
        assert wait_for(lambda: self._cmd.get_subscription_count() > 0 and self._status.get_publisher_count() > 0,
                        20.0), "decision maker not connected"
        with self._lock:
            n = len(self.statuses)
        self._cmd.publish(String(data=text))

        def final() -> TaskStatus | None:
            with self._lock:
                return next((s for s in self.statuses[n:] if s.text == text and s.state.terminal), None)

        assert wait_for(lambda: final() is not None, timeout), f"no final status for {text!r}"
        return final()

    def steps_of(self, status: TaskStatus) -> list[str]:
        with self._lock:
            return [s.primitive for s in self.statuses if s.id == status.id and s.state is TaskState.RUNNING
                    and s.primitive]

    def truth(self, oid: str) -> tuple[float, float, float]:
        with self._lock:
            return tuple(self.world["objects"][oid]["position"])

    def beliefs(self, name: str) -> list:
        with self._lock:
            return [] if self.memory is None else [m for m in self.memory.instances if m.name == name]

    def revision(self) -> int:
        with self._lock:
            return -1 if self.memory is None else self.memory.revision

    def call(self, client, request, timeout: float = 10.0, resend_every: float = 0.0):
        """Call and wait for the answer. ``resend_every`` > 0: the server was just restarted, so the graph may
        still list the old one (``wait_for_service`` true at once) and a request sent before the new server
        matched the client is lost; send again every ``resend_every`` s until ``timeout``."""
        assert client.wait_for_service(timeout_sec=timeout)
        deadline = time.monotonic() + timeout
        future = client.call_async(request)
        while resend_every > 0 and not wait_for(future.done, resend_every) and time.monotonic() < deadline:
            client.remove_pending_request(future)
            future = client.call_async(request)
        assert wait_for(future.done, max(0.0, deadline - time.monotonic()) if resend_every > 0 else timeout)
        return future.result()


def positions_in(sentence: str) -> list[tuple[float, float, float]]:
    """Coordinates a sentence gives: "(at 1.30, 3.95, 0.75; ..."."""
    return [tuple(float(v) for v in m) for m in re.findall(r"at (-?\d+\.\d+), (-?\d+\.\d+), (-?\d+\.\d+)", sentence)]


def pos(m) -> tuple[float, float, float]:
    return (m.position.x, m.position.y, m.position.z)


def rewrite_map(src_npz: str, semantic: str, dst_npz: str, moves: list[tuple[str, tuple, tuple]]) -> None:
    """Play the SLAM engine: the Gaussians of each moved object (class, old centre, new centre) moved.

    Writes atomically (temporary file + rename), as the SLAM writer does.
    """
    with np.load(src_npz) as f:
        arrays = {k: f[k] for k in f.files}
    with open(semantic, encoding="utf-8") as fh:
        table = {int(e["id"]): e["class"] for e in json.load(fh)["segmentation"]}
    means = arrays["means3D"].copy()
    ids = arrays["semantic_ids"].reshape(-1)
    for cls, old, new in moves:
        cls_ids = [i for i, c in table.items() if c == cls]
        sel = np.isin(ids, cls_ids) & (np.linalg.norm(means[:, :3] - np.asarray(old), axis=1) < 0.3)
        assert sel.sum() > 10, (cls, old, int(sel.sum()))
        means[sel, :3] += np.asarray(new) - np.asarray(old)
    arrays["means3D"] = means
    tmp = dst_npz + ".tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, dst_npz)


def test_a_day_with_the_living_memory(launch_nodes, ros_node, tmp_path):
    map_src, sem_src = bundled_map_paths()
    map_path, sem_path = str(tmp_path / "home.npz"), str(tmp_path / "home.json")
    shutil.copy(map_src, map_path)
    shutil.copy(sem_src, sem_path)
    query_set = [f"object_query_server.map_path={map_path}", f"object_query_server.semantic_path={sem_path}"]
    specs = load_nodeset("sim_robot")
    query_spec = [s for s in specs if s.name == "object_query_server"]
    launch_nodes(nodes=[s for s in specs if s.name != "object_query_server"], set=FAST)
    query = launch_nodes(nodes=query_spec, set=query_set)
    person = Person(ros_node)
    assert wait_for(lambda: person.world is not None and person.world.get("robot") is not None
                    and person.beliefs("cup"), 20.0), "no world state / memory"
    with open(os.path.join(os.path.dirname(__file__), "..", "..", "home_robot_bringup", "config", "params",
                           "sim.yaml"), encoding="utf-8") as fh:
        sim = yaml.safe_load(fh)
    start = json.loads(sim["mock_grasp_server"]["ros__parameters"]["objects"])

    # 1. fetch the bottle: it is with the user, in the world and in the memory
    st = person.say("give me the bottle")
    assert st.state is TaskState.SUCCEEDED, st
    assert math.dist(person.truth("bottle"), USER_DROP) < 0.05
    assert wait_for(lambda: [b.place for b in person.beliefs("bottle")] == ["user"], 5.0)
    # "where is the bottle": from memory, matching the ground truth, nothing moves
    st = person.say("where is the bottle")
    assert st.state is TaskState.SUCCEEDED and "with you" in st.sentence, st
    assert math.dist(positions_in(st.sentence)[0], person.truth("bottle")) < 0.05, st.sentence

    # 2. the same request again: a static map would send the robot to the kitchen counter (and fail)
    robot_before = dict(person.world["robot"])
    st = person.say("could you bring me the bottle")
    assert st.state is TaskState.SUCCEEDED and "already with you" in st.sentence, st
    assert person.steps_of(st) == [] and person.world["robot"] == robot_before

    # 3. clean the table (the trash is found where the memory has it); a second time there is nothing to do
    st = person.say("clean table")
    assert st.state is TaskState.SUCCEEDED, st
    assert math.dist(person.truth("trash"), BIN_DROP) < 0.05
    st = person.say("please clear the table")
    assert st.state is TaskState.SUCCEEDED and "already clean" in st.sentence, st

    # 4. a person moves the table cup to the sofa; the robot is not told. The camera (a rewritten map,
    # as the SLAM engine writes it) shows the world as it is now.
    table_cup = min(person.beliefs("cup"), key=lambda m: math.dist(pos(m), tuple(start["cup_2"])))
    for bad, words in [(MoveObject.Request(id="x" * 10_000_000, position=_point(SOFA_SPOT)), "(at most 64)"),
                       (MoveObject.Request(id="cup_2", position=_point((1e308, 0.0, 0.0))), "outside the workspace")]:
        res = person.call(person.move_client, bad)  # refused with the reason, in a short message; nothing moves
        assert not res.success and words in res.message and len(res.message) < 300, res.message[:300]
    res = person.call(person.move_client, MoveObject.Request(id="cup_2", position=_point(SOFA_SPOT)))
    assert res.success, res.message
    rev = person.revision()
    rewrite_map(map_src, sem_src, map_path, [
        ("cup", tuple(start["cup_2"]), person.truth("cup_2")),
        ("bottle", tuple(start["bottle"]), person.truth("bottle")),
        ("trash", tuple(start["trash"]), person.truth("trash"))])
    assert wait_for(lambda: person.revision() > rev and any(
        math.dist(pos(b), SOFA_SPOT) < 0.1 for b in person.beliefs("cup")), 20.0), person.beliefs("cup")
    moved = next(b for b in person.beliefs("cup") if math.dist(pos(b), SOFA_SPOT) < 0.1)
    assert moved.id == table_cup.id and moved.source == "map"  # the same cup, moved: its id is kept

    # "where is the cup": both cups, each where the simulator has it
    st = person.say("where did you see my cup")
    assert st.state is TaskState.SUCCEEDED and "2 cups" in st.sentence, st
    said = positions_in(st.sentence)
    for oid in ("cup_1", "cup_2"):
        assert min(math.dist(p, person.truth(oid)) for p in said) < 0.1, (oid, st.sentence)

    # 5. "give me the cup" from the bin: both cups are about as far -> a question; the answer picks one
    st = person.say("give me the cup")
    assert st.state is TaskState.REJECTED and st.sentence.startswith("Which cup: the one at the kitchen counter"), st
    st = person.say("the one at the kitchen")
    assert st.state is TaskState.SUCCEEDED, st
    assert math.dist(person.truth("cup_1"), USER_DROP) < 0.05 and math.dist(person.truth("cup_2"), SOFA_SPOT) < 0.01

    # 6. the memory survives a restart of the object database (saved next to the map)
    assert os.path.exists(str(tmp_path / "home.memory.json"))
    query.stop()
    query = launch_nodes(nodes=query_spec, set=query_set)
    resp = person.call(person.query_client, MemoryQuery.Request(name="cup"), timeout=20.0, resend_every=2.0)
    assert resp.found and len(resp.instances) == 2
    where = {m.id: (m.place, pos(m)) for m in resp.instances}
    assert any(p == "user" and math.dist(xyz, person.truth("cup_1")) < 0.05 for p, xyz in where.values()), where
    assert where[table_cup.id][0] == "" and math.dist(where[table_cup.id][1], person.truth("cup_2")) < 0.1, where
    st = person.say("what do you see")
    assert st.state is TaskState.SUCCEEDED and "2 cups" in st.sentence and "a bottle (with you)" in st.sentence, st


def _point(p):
    from geometry_msgs.msg import Point

    return Point(x=float(p[0]), y=float(p[1]), z=float(p[2]))


def test_a_grasp_that_finds_nothing_is_negative_evidence(launch_nodes, ros_node):
    """A cup moved away unseen: the grasp fails, the memory doubts it, the next plan takes the other cup."""
    launch_nodes(nodeset="sim_robot", set=FAST)
    person = Person(ros_node)
    assert wait_for(lambda: person.world is not None and person.world.get("robot") is not None
                    and len(person.beliefs("cup")) == 2, 20.0), "no world state / memory"
    res = person.call(person.move_client, MoveObject.Request(id="cup_1", position=_point(SOFA_SPOT)))
    assert res.success, res.message  # the counter cup is gone; the map still shows it there
    counter = max(person.beliefs("cup"), key=lambda m: m.position.x)  # the counter cup, x ~ 4.6

    assert person.say("go to the kitchen").state is TaskState.SUCCEEDED
    st = person.say("give me the cup")  # the counter cup is the nearest: the robot tries it
    assert st.state is TaskState.FAILED and "nearest cup" in st.message, st
    assert wait_for(lambda: next(m for m in person.beliefs("cup") if m.id == counter.id).confidence < 0.5, 5.0)
    doubted = next(m for m in person.beliefs("cup") if m.id == counter.id)
    assert doubted.state == "unseen" and "found nothing" in doubted.note

    st = person.say("where is the cup")
    assert st.state is TaskState.SUCCEEDED and "not sure it is still there" in st.sentence, st

    st = person.say("give me the cup")  # not blindly the same cup again: the trusted table cup
    assert st.state is TaskState.SUCCEEDED, st
    assert math.dist(person.truth("cup_2"), USER_DROP) < 0.05
    assert math.dist(person.truth("cup_1"), SOFA_SPOT) < 0.01
