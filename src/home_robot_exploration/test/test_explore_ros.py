"""Stage 0 over real ROS 2 processes: mock_nav_server + sim_camera_node + explorer_node explore the
simulated home; the published /map is scored against the home's ground truth.

A small camera (100 x 57 pixels, ~0.2 s a frame) keeps the run within a couple of minutes on
2 cores; the navigation server, the renderer, the image transport and the explorer are all real.
"""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from nav_msgs.msg import OccupancyGrid as GridMsg
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from home_robot_bringup.testing import wait_for
from home_robot_exploration.occupancy import GridConfig, OccupancyGrid
from home_robot_exploration.simcam import true_free_mask

pytestmark = [pytest.mark.ros, pytest.mark.slow]

LATCHED = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def test_explores_the_home_and_maps_its_free_space(launch_nodes, ros_node):
    got: dict[str, object] = {}
    lock = threading.Lock()

    def on_progress(msg: String) -> None:
        with lock:
            got["progress"] = json.loads(msg.data)
            got.setdefault("states", set()).add(got["progress"]["state"])

    def on_map(msg: GridMsg) -> None:
        with lock:
            got["map"] = msg

    ros_node.create_subscription(String, "exploration/progress", on_progress, LATCHED)
    ros_node.create_subscription(GridMsg, "map", on_map, LATCHED)
    launch_nodes(nodeset="explore", set=["sim_camera.width=100", "sim_camera.height=57", "sim_camera.rate_hz=3.0",
                                         "explorer.time_budget_s=400.0"], ready_timeout=120)

    def done() -> bool:
        with lock:
            p = got.get("progress")
            return isinstance(p, dict) and p["state"] == "done"

    assert wait_for(done, timeout=480, interval=0.5), f"exploration did not end: {got.get('progress')}"
    assert wait_for(lambda: "map" in got, timeout=30)
    with lock:
        progress, msg = dict(got["progress"]), got["map"]
    assert progress["reason"] == "no reachable frontier left", progress
    assert progress["frames"] >= 10 and progress["goals"] >= 4
    grid = OccupancyGrid(GridConfig(resolution=msg.info.resolution, origin_x=msg.info.origin.position.x,
                                    origin_y=msg.info.origin.position.y,
                                    width_m=msg.info.width * msg.info.resolution,
                                    height_m=msg.info.height * msg.info.resolution))
    states = np.array(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    truth = true_free_mask(grid)
    covered = float(((states == 0) & truth).sum()) / truth.sum()
    cx, cy = grid.centre_of(*np.meshgrid(np.arange(grid.nx), np.arange(grid.ny), indexing="xy"))
    outside = (states == 0) & ~((cx > 0) & (cx < 6.0) & (cy > 0) & (cy < 5.0))
    print(f"coverage {covered:.3f} of {truth.sum() * grid.cfg.resolution**2:.1f} m2, progress {progress}")
    assert covered > 0.85, f"only {covered:.0%} of the home's free area was seen"
    assert outside.sum() * grid.cfg.resolution**2 < 0.5  # nothing free beyond the walls
