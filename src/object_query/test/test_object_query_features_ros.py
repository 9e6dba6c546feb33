"""Integration: instances, synonyms, markers, reloads and parameters of a real object_query_server process."""

import json
import os
import shutil
import subprocess
import threading
import time

import numpy as np
import pytest
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, ParameterValue
from rcl_interfaces.srv import SetParameters
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from home_robot_bringup.nodeset import find_executable
from home_robot_bringup.process import node_environment
from home_robot_bringup.testing import wait_for
from object_query.object_query_client import ObjectQueryClient

pytestmark = pytest.mark.ros

REPO = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", "..", ".."))
LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def call(node, srv_type, name, request, timeout=10.0):
    """Call a service from the test thread while the fixture's executor spins the node."""
    client = node.create_client(srv_type, name)
    assert client.wait_for_service(timeout_sec=20.0), f"{name} not available"
    done = threading.Event()
    future = client.call_async(request)
    future.add_done_callback(lambda _f: done.set())
    assert done.wait(timeout), f"no answer from {name}"
    node.destroy_client(client)
    return future.result()


class Latest:
    """Keeps the latest message of a latched topic."""

    def __init__(self, node, msg_type, topic):
        self.msgs = []
        self._lock = threading.Lock()
        node.create_subscription(msg_type, topic, self._on_msg, LATCHED)

    def _on_msg(self, msg):
        with self._lock:
            self.msgs.append(msg)

    def last(self):
        with self._lock:
            return self.msgs[-1] if self.msgs else None


def copy_sample_map(folder):
    shutil.copy(os.path.join(REPO, "data", "params.npz"), folder / "params.npz")
    shutil.copy(os.path.join(REPO, "data", "semantic.json"), folder / "semantic.json")
    return str(folder / "params.npz"), str(folder / "semantic.json")


def rewrite_map(map_path, shift_bottle=(0.0, 0.0, 0.0)):
    """Rewrite the map atomically (write a temporary file, then rename), with the bottle moved."""
    with np.load(map_path) as npz:
        arrays = {k: npz[k] for k in npz.files}
    bottle = arrays["semantic_ids"] == 7
    arrays["means3D"][bottle] += np.asarray(shift_bottle, np.float32)
    tmp = map_path + ".tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, map_path)


def test_instances_synonyms_names_and_markers(launch_nodes, ros_node, ros_domain):
    launch_nodes(nodeset="object_query")
    client = ObjectQueryClient(ros_node)
    assert client.wait_for_service(timeout_sec=20.0)

    chairs = client.query_instances("Chairs", reference=(2.5, 3.6, 0.0), timeout_sec=5.0)
    assert chairs.found and chairs.name == "chair" and len(chairs.instances) == 3, chairs.message
    nearest = chairs.instances[0]
    assert abs(nearest.centre[0] - 2.5) < 0.1 and abs(nearest.centre[1] - 3.4) < 0.1
    assert list(chairs.distances) == sorted(chairs.distances) and chairs.distances[0] < 0.7
    assert all(i.bbox_min[k] <= i.centre[k] <= i.bbox_max[k] for i in chairs.instances for k in range(3))
    assert all(i.point_count > 100 for i in chairs.instances)

    third = client.query("chair#3", timeout_sec=5.0)  # one instance by its label
    by_index = {i.index: i.centre for i in chairs.instances}
    assert third.found and third.message.startswith("chair#3 at")
    assert np.allclose(third.position, by_index[3], atol=1e-6)

    cups = client.query_instances("mug", timeout_sec=5.0)  # synonym, no reference: largest first
    assert cups.found and cups.name == "cup" and len(cups.instances) == 2 and cups.distances == (-1.0, -1.0)
    one_cup = client.query("cup", timeout_sec=5.0)
    assert one_cup.found and "2 instances of cup" in one_cup.message

    for spoken, cls in [("couch", "sofa"), ("Trash_Can", "bin"), ("REFRIGERATOR", "fridge")]:
        r = client.query(spoken, timeout_sec=5.0)
        assert r.found and r.message.startswith(f"{cls} at"), r.message

    typo = client.query("botle", timeout_sec=5.0)
    assert not typo.found and "did you mean: bottle" in typo.message
    for bad, why in [("", "empty object name"), ("x" * 20_000, "too long"), ("椅子 🪑", "unknown object '椅子 🪑'")]:
        r = client.query(bad, timeout_sec=5.0)
        assert not r.found and why in r.message, r.message
        assert not client.query_instances(bad, timeout_sec=5.0).found
    assert client.query("bottle", timeout_sec=5.0).found  # the server survived all of that

    markers = Latest(ros_node, MarkerArray, "object_markers")
    assert wait_for(lambda: markers.last() is not None, 10.0), "late joiner got no /object_markers"
    ms = markers.last().markers
    assert ms[0].action == Marker.DELETEALL
    boxes = [m for m in ms if m.type == Marker.CUBE]
    texts = sorted(m.text for m in ms if m.type == Marker.TEXT_VIEW_FACING)
    assert len(boxes) == 14 and {b.header.frame_id for b in boxes} == {"map"}
    assert [t for t in texts if t.startswith("chair#")] and sum(t.startswith("cup#") for t in texts) == 2

    # command line: every instance, nearest first
    exe = find_executable("object_query", "object_query_client")
    env = node_environment(ros_domain)
    out = subprocess.run([exe, "chair", "--all", "--near", "3.6", "2.5", "0"], env=env, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    lines = [ln for ln in out.stdout.splitlines() if "chair#" in ln]
    assert len(lines) == 3 and "distance=" in lines[0]
    assert abs(float(lines[0].split("x=")[1].split()[0]) - 3.7) < 0.05, lines[0]  # the chair nearest (3.6, 2.5)


def test_reload_is_atomic_and_a_bad_file_keeps_the_old_map(launch_nodes, ros_node, tmp_path):
    map_path, sem_path = copy_sample_map(tmp_path)
    sup = launch_nodes(nodeset="object_query", set=[f"object_query_server.map_path={map_path}",
                                                    f"object_query_server.semantic_path={sem_path}",
                                                    "object_query_server.auto_reload=false"])
    client = ObjectQueryClient(ros_node)
    assert client.wait_for_service(timeout_sec=20.0)
    before = client.query("bottle", timeout_sec=5.0).position
    object_list = Latest(ros_node, String, "object_list")

    # answers keep coming while the map is rebuilt again and again; every one is complete
    answers, stop = [], threading.Event()

    def hammer():
        while not stop.is_set():
            answers.append(client.query("bottle", timeout_sec=5.0))

    worker = threading.Thread(target=hammer)
    worker.start()
    try:
        for i in range(4):  # the bottle jumps 1 m back and forth
            rewrite_map(map_path, shift_bottle=(1.0, 0.0, 0.0) if i % 2 == 0 else (-1.0, 0.0, 0.0))
            ok = call(ros_node, Trigger, "/object_query_server/reload", Trigger.Request())
            assert ok.success, ok.message
            assert "reloaded (reload service)" in ok.message
    finally:
        stop.set()
        worker.join(10.0)
    moved = (before[0] + 1.0, before[1], before[2])
    assert len(answers) > 5 and all(a.found for a in answers)
    assert all(np.allclose(a.position, before, atol=1e-4) or np.allclose(a.position, moved, atol=1e-4)
               for a in answers)
    assert any(np.allclose(a.position, moved, atol=1e-4) for a in answers)

    # a broken map file: the reload fails, says why, and the old map still answers
    with open(map_path, "wb") as fh:
        fh.write(b"half a file")
    bad = call(ros_node, Trigger, "/object_query_server/reload", Trigger.Request())
    assert not bad.success and "keeping the previous map" in bad.message and "not a readable .npz" in bad.message
    assert wait_for(lambda: "keeping the previous map" in sup.output(), 5.0)
    still = client.query("bottle", timeout_sec=5.0)
    assert still.found and np.allclose(still.position, before)

    # a broken class table: same
    shutil.copy(os.path.join(REPO, "data", "params.npz"), map_path)
    with open(sem_path, "w") as fh:
        fh.write('{"segmentation": [{"id": 1}]}')
    bad = call(ros_node, Trigger, "/object_query_server/reload", Trigger.Request())
    assert not bad.success and "needs 'id' and 'class'" in bad.message
    assert client.query("chair", timeout_sec=5.0).found

    # a good map again: the new answer and a new latched object list
    shutil.copy(os.path.join(REPO, "data", "semantic.json"), sem_path)
    rewrite_map(map_path, shift_bottle=(-1.0, 0.0, 0.0))
    good = call(ros_node, Trigger, "/object_query_server/reload", Trigger.Request())
    assert good.success, good.message
    after = client.query("bottle", timeout_sec=5.0).position
    assert abs(after[0] - (before[0] - 1.0)) < 0.01
    assert wait_for(lambda: object_list.last() is not None
                    and abs(json.loads(object_list.last().data)["bottle"][0] - after[0]) < 1e-3, 10.0)


def test_auto_reload_on_file_change_and_parameter_changes(launch_nodes, ros_node, tmp_path):
    map_path, sem_path = copy_sample_map(tmp_path)
    sup = launch_nodes(nodeset="object_query", set=[f"object_query_server.map_path={map_path}",
                                                    f"object_query_server.semantic_path={sem_path}",
                                                    "object_query_server.auto_reload=true",
                                                    "object_query_server.reload_poll_period=0.1"])
    client = ObjectQueryClient(ros_node)
    assert client.wait_for_service(timeout_sec=20.0)
    before = client.query("bottle", timeout_sec=5.0).position

    rewrite_map(map_path, shift_bottle=(0.0, 0.5, 0.0))  # what the SLAM server does
    assert wait_for(lambda: client.query("bottle", timeout_sec=5.0).position[1] > before[1] + 0.4, 15.0)
    assert wait_for(lambda: "reloaded (map files changed)" in sup.output(), 10.0)

    # a file that becomes unreadable is reported once and the map stays
    with open(map_path, "wb") as fh:
        fh.write(b"\x00" * 10)
    assert wait_for(lambda: "reload (map files changed) failed" in sup.output(), 15.0)
    assert client.query("bottle", timeout_sec=5.0).found
    time.sleep(0.5)
    assert sup.output().count("reload (map files changed) failed") == 1

    def set_param(name, value):
        if isinstance(value, float):
            pv = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=value)
        else:
            pv = ParameterValue(type=ParameterType.PARAMETER_STRING, string_value=value)
        req = SetParameters.Request(parameters=[ParameterMsg(name=name, value=pv)])
        return call(ros_node, SetParameters, "/object_query_server/set_parameters", req).results[0]

    rejected = set_param("voxel_size", -1.0)
    assert not rejected.successful and "voxel_size must be > 0" in rejected.reason
    rejected = set_param("centre_method", "mode")
    assert not rejected.successful and "centre_method" in rejected.reason

    shutil.copy(os.path.join(REPO, "data", "params.npz"), map_path)
    assert wait_for(lambda: abs(client.query("bottle", timeout_sec=5.0).position[1] - before[1]) < 1e-3, 15.0)
    assert set_param("query_position", "class").successful
    assert wait_for(lambda: "2 instances of cup, this is the centre of all of them"
                    in client.query("cup", timeout_sec=5.0).message, 15.0)
