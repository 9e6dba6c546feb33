"""Mapping while exploring over real ROS 2 processes: the explorer starts a RunSlam goal on the real
streaming SLAM server, which maps the simulated camera's frames (tracking guided by the simulated
wheel odometry) while the robot explores; when exploration ends the map is written where the
object-query server (started with no map, ``wait_for_map``) reads it, and its objects are checked
against the simulator's ground truth, with the explored area (/map) against the home's free area.

A 150 x 85 camera and fewer Adam steps per keyframe (``FEWER_STEPS``: while the robot turns every frame is a new
view, so a keyframe, and mapping them was most of the run) keep the run short on 2 cores; everything in the loop is
real.
"""

from __future__ import annotations

import json
import math
import threading

import numpy as np
import pytest
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.testing import wait_for

# the run has its own deadline (600 s, below); pytest's 300 s default would cut it first on a loaded machine
pytestmark = [pytest.mark.ros, pytest.mark.slow, pytest.mark.timeout(900)]

# the engine's defaults on the CPU: mapping.iters 10, first_frame_iters 60, tracking.icp_iters 12. The objects'
# places come from the depth the Gaussians are seeded at (posed by the odometry and ICP), not from the extra steps.
FEWER_STEPS = """
mapping: {iters: 4, first_frame_iters: 30}
tracking: {icp_iters: 8}
"""

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def test_explores_maps_and_the_object_database_serves_the_self_built_map(launch_nodes, ros_node, tmp_path):
    from decision_maker.sim.world import SAMPLE_OBJECTS
    from semantic_gs_slam.synthetic.scenes import CLASSES

    got: dict[str, object] = {"lists": []}
    lock = threading.Lock()

    def on_progress(msg: String) -> None:
        with lock:
            got["progress"] = json.loads(msg.data)
            got.setdefault("states", []).append(got["progress"]["state"])

    def on_objects(msg: String) -> None:
        with lock:
            got["lists"].append(json.loads(msg.data))

    def on_map(msg) -> None:
        with lock:
            got["grid"] = msg

    from nav_msgs.msg import OccupancyGrid as GridMsg

    ros_node.create_subscription(String, "exploration/progress", on_progress, LATCHED)
    ros_node.create_subscription(String, "object_list", on_objects, LATCHED)
    ros_node.create_subscription(GridMsg, "map", on_map, LATCHED)
    map_dir = tmp_path / "map"
    (tmp_path / "slam.yaml").write_text(FEWER_STEPS)
    classes = json.dumps({str(i): name for i, name, _ in CLASSES if i > 0})
    specs = load_nodeset("explore") + load_nodeset("slam_sim_camera") + load_nodeset("object_query")
    specs = [s.with_parameters(slam_classes=classes) if s.name == "explorer" else s for s in specs]
    launch_nodes(nodes=specs, ready_timeout=120, set=[
        "sim_camera.width=150", "sim_camera.height=85", "sim_camera.rate_hz=1.5",
        "mock_nav_server.turn_rate=0.6", "explorer.look_steps=8", "explorer.time_budget_s=300.0",
        "explorer.slam_action=run_gs_slam", f"explorer.slam_map_dir={map_dir}",
        f"run_gs_slam_server.work_dir={tmp_path / 'work'}", f"run_gs_slam_server.map_dir={map_dir}",
        f"run_gs_slam_server.slam_config={tmp_path / 'slam.yaml'}",
        f"object_query_server.map_path={map_dir / 'params.npz'}",
        f"object_query_server.semantic_path={map_dir / 'semantic.json'}", "object_query_server.wait_for_map=true"])

    def done() -> bool:
        with lock:
            p = got.get("progress")
            return isinstance(p, dict) and p["state"] == "done"

    assert wait_for(done, timeout=600, interval=0.5), f"exploration and mapping did not end: {got.get('progress')}"
    # the SLAM server had the final map reloaded before it ended the run, so /object_query answers from it now;
    # /object_list, each name's /object_query position, was published by that reload, but this node may take it
    # after "done" (another subscription): wait until the last list received is the final map's
    from object_query.object_query_client import ObjectQueryClient

    queries = ObjectQueryClient(ros_node)
    assert queries.wait_for_service(20.0)
    answers = {n: queries.query(n, 10.0) for n in ("bottle", "trash", "cup")}

    def final_list() -> bool:
        with lock:
            last = got["lists"][-1] if got["lists"] else {}
        return all(n in last and math.dist(last[n], a.position) < 1e-3 for n, a in answers.items() if a.found)

    assert wait_for(final_list, 20.0), f"/object_list {got['lists'][-1:]} is not /object_query's {answers}"
    with lock:
        progress, states, lists = dict(got["progress"]), list(got["states"]), list(got["lists"])
    mapping = progress["mapping"]
    print(f"progress {progress}")
    assert mapping["state"] == "done", mapping
    assert "mapping" in states  # "done" came only after the map was finished
    assert mapping["frames"] >= 10 and mapping["map_path"] == str(map_dir / "params.npz")
    assert lists and lists[0] == {}  # the database started with no map ...
    objects = lists[-1]  # ... and serves the self-built one after the reload
    truth = json.loads(SAMPLE_OBJECTS)
    from object_query.semantic_map import ObjectDatabase

    db = ObjectDatabase.from_files(str(map_dir / "params.npz"), str(map_dir / "semantic.json"))
    for name in ("bottle", "trash", "cup"):  # what the answer was chosen from (read when an assertion below fails)
        print(name, [(tuple(round(v, 3) for v in i.centre), i.point_count) for i in db.instances(name).instances])
    assert {"bottle", "table", "trash"} <= set(objects), objects
    for name in ("bottle", "trash", "cup"):
        if name not in objects:
            continue
        nearest = min(math.dist(objects[name], p) for oid, p in truth.items() if oid.rstrip("_0123456789") == name)
        print(f"{name}: {objects[name]} error {nearest * 100:.1f} cm")
        assert nearest < 0.15, f"{name} at {objects[name]} is {nearest:.2f} m from the nearest true {name}"
    from home_robot_exploration.demo_explore import coverage_of

    assert wait_for(lambda: "grid" in got, 30)
    seen, total, cov = coverage_of(got["grid"])
    print(f"coverage {cov:.3f}: {seen:.1f} of {total:.1f} m2")
    assert cov > 0.85, f"only {cov:.0%} of the home's free area was seen"
    with np.load(map_dir / "params.npz") as z:
        assert len(z["timestamps"]) == z["cam_trans"].shape[-1] == mapping["frames"]
