"""Integration: the object memory served by a real object_query_server process over ROS 2."""

from __future__ import annotations

import json
import math
import os
import shutil
import threading

import pytest
from geometry_msgs.msg import Point
from object_query_interfaces.msg import ObjectMemory as ObjectMemoryMsg
from object_query_interfaces.srv import MemoryQuery, MemoryReport

from home_robot_bringup.testing import wait_for
from object_query.memory_ros import MEMORY_QOS
from object_query.object_query_client import ObjectQueryClient, ObjectQueryTimeout
from object_query.object_query_server import bundled_map_paths

pytestmark = pytest.mark.ros


def call(node, srv_type, name: str, request, timeout: float = 20.0):
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=timeout), name
    future = client.call_async(request)
    assert wait_for(future.done, timeout), f"{name}: no answer"
    return future.result()


def report(node, event: str, name: str, position=None, place: str = "", source: str = "", detail: str = ""
           ) -> MemoryReport.Response:
    req = MemoryReport.Request(event=event, name=name, place=place, source=source, detail=detail)
    if position is not None:
        req.has_position = True
        req.position = Point(x=float(position[0]), y=float(position[1]), z=float(position[2]))
    return call(node, MemoryReport, "object_memory/report", req)


def map_copy(tmp_path) -> list[str]:
    src_map, src_sem = bundled_map_paths()
    shutil.copy(src_map, tmp_path / "home.npz")
    shutil.copy(src_sem, tmp_path / "home.json")
    return [f"object_query_server.map_path={tmp_path / 'home.npz'}",
            f"object_query_server.semantic_path={tmp_path / 'home.json'}"]


def test_reports_change_the_answer_and_bad_reports_are_refused(launch_nodes, ros_node):
    launch_nodes(nodeset="object_query")  # the bundled map: memory not persisted
    client = ObjectQueryClient(ros_node)
    assert client.wait_for_service(timeout_sec=20.0)
    latest: list[ObjectMemoryMsg] = []
    got = threading.Event()

    def on_memory(msg: ObjectMemoryMsg) -> None:
        latest.append(msg)
        got.set()

    ros_node.create_subscription(ObjectMemoryMsg, "object_memory", on_memory, MEMORY_QOS)
    assert got.wait(10.0), "late joiner did not receive /object_memory"
    first = latest[-1]
    bottles = [m for m in first.instances if m.name == "bottle"]
    assert len(bottles) == 1 and bottles[0].source == "map" and bottles[0].confidence == pytest.approx(1.0)

    # the robot grasps the bottle at the kitchen and puts it in the user's hands
    r = report(ros_node, "grasped", "bottle", (4.9, 1.1, 0.0))
    assert r.success and r.id == bottles[0].id, r.message
    assert [m.state for m in r.memory.instances if m.name == "bottle"] == ["held"]
    r = report(ros_node, "placed", "bottle", (1.3, 3.95, 0.75), place="user")
    assert r.success and r.memory.revision > first.revision
    answer = client.query("bottle", timeout_sec=5.0)
    assert answer.found and math.dist(answer.position, (1.3, 3.95, 0.75)) < 1e-6, answer
    assert "put down by the robot at user" in answer.message and "source action" in answer.message
    assert wait_for(lambda: latest[-1].revision == r.memory.revision, 5.0)  # the topic follows

    # negative evidence: a grasp that found no cup at the counter lowers that cup's confidence
    r = report(ros_node, "grasp_failed", "mug", (4.9, 1.1, 0.0))  # a synonym of cup
    assert r.success, r.message
    counter_cup = next(m for m in r.memory.instances if m.id == r.id)
    assert counter_cup.confidence < 0.5 and counter_cup.state == "unseen" and counter_cup.position.x > 4.0
    best = call(ros_node, MemoryQuery, "object_memory/query", MemoryQuery.Request(name="cups"))
    assert best.found and best.name == "cup" and best.instances[0].id != r.id  # the trusted cup first

    # malformed reports: refused with the reason, nothing changes, the server stays up
    rev = r.memory.revision
    for bad, words in [(("teleported", "cup", (0, 0, 0)), "unknown event"),
                       (("placed", "cup", None), "position is missing"),
                       (("set", "cup", (math.nan, 0, 0)), "finite"),
                       (("set", "cup", (1, 2, 3), "", "rumour"), "source must be"),
                       (("grasped", "", (0, 0, 0)), "name"),
                       (("set", "x" * 200_000, (1, 2, 3)), "name too long (200000 characters, at most 1024)"),
                       (("set", "x " * 300, (1, 2, 3)), "name too long (599 characters after normalisation"),
                       (("placed", "cup", (1, 2, 3), "y" * 5000), "place too long (5000 characters"),
                       (("set", "cup", (1e308, 1e308, 1e308)), "within 1000 m of the map's origin, got (1e+308"),
                       (("grasp_failed", "cup", (4.9, 1.1, 0.0), "", "", "z" * 20_000),
                        "detail too long (20000 characters, at most 1000)")]:
        r = report(ros_node, *bad)
        assert not r.success and words in r.message, (bad, r.message)
        assert r.memory.revision == rev
    # a name that NFKC makes 18 times longer (U+FDFA), a million of them: refused unread (it took the server
    # seconds to normalise, and a query asked meanwhile waited)
    answer = client.query("\ufdfa" * 1_000_000, timeout_sec=10.0)
    assert not answer.found and "object name too long (1000000 characters, at most 1024)" in answer.message
    long_query = call(ros_node, MemoryQuery, "object_memory/query", MemoryQuery.Request(name="\ufdfa" * 1_000_000))
    assert not long_query.found and "too long" in long_query.message
    assert client.query("table", timeout_sec=5.0).found


def _query_retrying(client, name: str, attempts: int = 4):
    """A fresh client's first request can be lost while DDS still matches the response writer
    (rmw: "failed to send response"): ask again; persistence, not discovery, is under test here."""
    for i in range(attempts):
        try:
            return client.query(name, timeout_sec=10.0)
        except ObjectQueryTimeout:
            if i == attempts - 1:
                raise
    raise AssertionError("unreachable")


def test_memory_persists_next_to_the_map_and_a_corrupt_file_is_set_aside(launch_nodes, ros_node, tmp_path):
    params = map_copy(tmp_path)
    memory_file = tmp_path / "home.memory.json"
    memory_file.write_text("{ this is not json")
    sup = launch_nodes(nodeset="object_query", set=params)
    assert wait_for(lambda: "is corrupt" in sup.get("object_query_server").output(), 10.0)
    assert [p for p in os.listdir(tmp_path) if p.startswith("home.memory.json.corrupt-")]
    r = report(ros_node, "set", "trash", (5.6, 4.5, 0.5), place="bin", source="user")
    assert r.success, r.message
    saved = json.loads(memory_file.read_text())
    assert any(b["name"] == "trash" and b["place"] == "bin" and b["source"] == "user" for b in saved["beliefs"])

    sup.stop()  # restart: the memory comes back from the file, newer than the map
    launch_nodes(nodeset="object_query", set=params)
    answer = ObjectQueryClient(ros_node)
    assert answer.wait_for_service(timeout_sec=20.0)
    trash = _query_retrying(answer, "trash")
    assert trash.found and math.dist(trash.position, (5.6, 4.5, 0.5)) < 1e-6, trash
