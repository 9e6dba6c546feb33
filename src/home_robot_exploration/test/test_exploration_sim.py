"""The exploration loop on the simulated home's real renderer (no ROS): coverage vs ground truth."""

from __future__ import annotations

import math

import pytest

from home_robot_exploration.explorer import Exploration, ExplorerConfig, Finished, NavGoal
from home_robot_exploration.simcam import CameraConfig, coverage


@pytest.mark.slow
def test_explores_the_simulated_home_to_high_coverage() -> None:
    from semantic_gs_slam.config import Intrinsics
    from semantic_gs_slam.synthetic.scenes import HomeRenderer

    cam = CameraConfig(width=100, height=57)
    k = cam.k()
    renderer = HomeRenderer(0)
    ex = Exploration(ExplorerConfig())
    x, y, yaw, now = 0.5, 0.5, 0.0, 0.0
    for _ in range(300):
        c2w = cam.c2w(x, y, yaw)
        _, depth, _ = renderer.render(c2w, Intrinsics(cam.width, cam.height, k[0, 0], k[1, 1], k[0, 2], k[1, 2]))
        ex.integrate(depth, k, c2w, now)
        now += 1.0
        a = ex.tick(x, y, yaw, now)
        if isinstance(a, Finished):
            break
        if isinstance(a, NavGoal):  # a teleporting base: the loop, not the driving, is under test
            now += math.hypot(a.x - x, a.y - y) + 1.0
            x, y, yaw = a.x, a.y, a.yaw
            ex.goal_result(True, now)
    assert ex.finished is not None and ex.finished.reason == "no reachable frontier left"
    assert coverage(ex.grid) > 0.9
