"""Unit tests of the exploration core: grid updates, frontiers, frontier choice, stop conditions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from home_robot_exploration.errors import ConfigError, FrameError
from home_robot_exploration.explorer import Exploration, ExplorerConfig, Finished, NavGoal
from home_robot_exploration.frontiers import (
    FrontierConfig,
    choose_frontier,
    clusters,
    find_frontiers,
    frontier_mask,
    wavefront,
)
from home_robot_exploration.occupancy import FREE, OCCUPIED, UNKNOWN, GridConfig, OccupancyGrid
from home_robot_exploration.simcam import CameraConfig

CAM = CameraConfig(width=60, height=34, mount_height=1.0, tilt_deg=20.0)


def wall_depth(cam: CameraConfig, c2w: np.ndarray, wall_x: float) -> np.ndarray:
    """Exact depth of a scene with a floor (z = 0) and a wall x = wall_x (the camera looks along +x)."""
    k = cam.k()
    v, u = np.meshgrid(np.arange(cam.height), np.arange(cam.width), indexing="ij")
    dirs = np.stack([(u - k[0, 2]) / k[0, 0], (v - k[1, 2]) / k[1, 1], np.ones(u.shape)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_floor = np.where(dirs[..., 2] < 0, -o[2] / dirs[..., 2], np.inf)
        t_wall = np.where(dirs[..., 0] > 0, (wall_x - o[0]) / dirs[..., 0], np.inf)
    return np.minimum(t_floor, t_wall)  # z-depth: directions have unit camera z


def test_grid_marks_floor_free_and_wall_occupied() -> None:
    grid = OccupancyGrid(GridConfig(resolution=0.05, origin_x=-1, origin_y=-3, width_m=6, height_m=6,
                                    pixel_stride=1))
    c2w = CAM.c2w(0.0, 0.0, 0.0)
    used = grid.integrate(wall_depth(CAM, c2w, 3.0), CAM.k(), c2w)
    assert used > 0
    st = grid.states()
    ix_wall, iy0 = grid.cell_of(3.0 + 0.01, 0.0)
    assert st[iy0, ix_wall] == OCCUPIED
    ix_mid, _ = grid.cell_of(2.0, 0.0)
    assert st[iy0, ix_mid] == FREE
    ix_behind, _ = grid.cell_of(-0.5, 0.0)
    assert st[iy0, ix_behind] == UNKNOWN  # behind the camera: never seen
    ix_past, _ = grid.cell_of(3.5, 0.0)
    assert st[iy0, ix_past] == UNKNOWN  # behind the wall


def test_grid_ignores_points_above_the_band_and_beyond_range() -> None:
    grid = OccupancyGrid(GridConfig(band_max_z=0.5, max_range_m=1.0))
    c2w = CameraConfig(tilt_deg=0.0).c2w(0.0, 0.0, 0.0)
    depth = np.full((170, 300), 3.0)  # a far wall seen at the camera's height: above the band and too far
    assert grid.integrate(depth, CameraConfig().k(), c2w) == 0
    assert (grid.states() == UNKNOWN).all()


def test_grid_rejects_bad_frames_and_configs() -> None:
    grid = OccupancyGrid()
    with pytest.raises(FrameError):
        grid.integrate(np.ones((4, 4)), np.eye(3), np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = math.nan
    with pytest.raises(FrameError):
        grid.integrate(np.ones((4, 4)), np.eye(3), bad)
    with pytest.raises(ConfigError):
        OccupancyGrid(GridConfig(band_min_z=1.0, band_max_z=0.5))
    with pytest.raises(ConfigError):
        OccupancyGrid(GridConfig(resolution=0.001, width_m=100, height_m=100))


def test_hits_win_over_a_single_free_pass() -> None:
    grid = OccupancyGrid(GridConfig(origin_x=-1, origin_y=-3, width_m=6, height_m=6, pixel_stride=1))
    c2w = CAM.c2w(0.0, 0.0, 0.0)
    for _ in range(3):
        grid.integrate(wall_depth(CAM, c2w, 2.0), CAM.k(), c2w)
    grid.integrate(wall_depth(CAM, c2w, 4.0), CAM.k(), c2w)  # the wall moved away once
    ix, iy = grid.cell_of(2.01, 0.0)
    assert grid.states()[iy, ix] == OCCUPIED


def grid_from(states: np.ndarray, res: float = 0.1) -> OccupancyGrid:
    ny, nx = states.shape
    grid = OccupancyGrid(GridConfig(resolution=res, origin_x=0, origin_y=0, width_m=nx * res, height_m=ny * res))
    grid.observed[:] = states != UNKNOWN
    grid.logodds[:] = np.where(states == OCCUPIED, 1.0, -1.0)
    return grid


def test_frontier_mask_and_clusters() -> None:
    st = np.full((10, 10), UNKNOWN, dtype=np.int8)
    st[2:8, 2:5] = FREE
    fm = frontier_mask(st)
    assert fm[2, 2] and fm[7, 4] and not fm[4, 3]  # border cells, not the interior
    st2 = np.full((10, 20), FREE, dtype=np.int8)
    st2[:, 8:12] = OCCUPIED
    st2[0, :] = UNKNOWN
    comps = clusters(frontier_mask(st2))
    assert sorted(len(c) for c in comps) == [8, 8]  # split by the wall


def test_wavefront_stops_at_walls() -> None:
    passable = np.ones((5, 5), dtype=bool)
    passable[:, 2] = False
    d = wavefront(passable, (0, 0))
    assert d[4, 1] == 4 and math.isinf(d[0, 3])


def test_choice_trades_gain_against_travel() -> None:
    # a corridor room: a long frontier far away (x = 29) and a short one near (y = 0 edge cells)
    st = np.full((12, 32), OCCUPIED, dtype=np.int8)
    st[1:11, 1:31] = FREE
    st[1:11, 31] = UNKNOWN  # far: 10 cells of frontier at x = 30
    st[0, 3:6] = UNKNOWN  # near: 3 cells at y = 1
    grid = grid_from(st)
    near_first = FrontierConfig(robot_radius=0.0, min_cluster_cells=1, gain_weight=1.0, cost_weight=1.0)
    best = choose_frontier(find_frontiers(grid, (0.45, 0.55), near_first))
    assert best is not None and best.goal is not None and best.goal[0] < 1.0  # travel dominates
    gain_first = FrontierConfig(robot_radius=0.0, min_cluster_cells=1, gain_weight=1.0, cost_weight=0.01)
    best = choose_frontier(find_frontiers(grid, (0.45, 0.55), gain_first))
    assert best is not None and best.goal is not None and best.goal[0] > 2.5  # gain dominates
    assert abs(best.heading) < 0.1  # facing the unknown side (+x)


def test_unreachable_frontier_is_not_chosen() -> None:
    st = np.full((10, 20), FREE, dtype=np.int8)
    st[:, 9:11] = OCCUPIED
    st[4:6, 15:18] = UNKNOWN  # behind the wall
    grid = grid_from(st)
    fr = find_frontiers(grid, (0.25, 0.5), FrontierConfig(robot_radius=0.0, min_cluster_cells=1))
    assert fr and all(f.goal is None for f in fr)
    assert choose_frontier(fr) is None


def fake_step(ex: Exploration, pose: list[float], now: float) -> NavGoal | Finished | None:
    a = ex.tick(pose[0], pose[1], pose[2], now)
    if isinstance(a, NavGoal):
        pose[:] = [a.x, a.y, a.yaw]
    return a


def test_look_around_then_stop_when_no_frontier() -> None:
    ex = Exploration(ExplorerConfig(look_steps=4, frame_timeout_s=5.0,
                                    grid=GridConfig(origin_x=-1, origin_y=-1, width_m=2, height_m=2)))
    pose = [0.0, 0.0, 0.0]
    yaws = []
    now = 0.0
    for _ in range(4):
        a = fake_step(ex, pose, now)
        assert isinstance(a, NavGoal) and a.kind == "look"
        yaws.append(a.yaw)
        assert fake_step(ex, pose, now + 0.1) is None  # the goal is running
        ex.goal_result(True, now + 0.5)
        assert fake_step(ex, pose, now + 1.0) is None  # waiting for a frame taken after arrival
        ex.integrate(np.zeros((4, 4)), np.eye(3), np.eye(4), now + 0.6)  # an empty frame still counts
        now += 2.0
    assert [round(math.degrees(y)) for y in yaws] == [90, 180, -90, 0]
    # nothing seen beyond the robot's own disc... whose border is a frontier with no standable goal
    # far from the visited start: the loop must end by itself within a few goals
    for _ in range(20):
        a = fake_step(ex, pose, now)
        if isinstance(a, Finished):
            break
        if isinstance(a, NavGoal):
            ex.goal_result(True, now + 0.5)
            ex.integrate(np.zeros((4, 4)), np.eye(3), np.eye(4), now + 0.6)
        now += 2.0
    assert ex.finished is not None


def test_time_budget_and_failures_end_the_run() -> None:
    ex = Exploration(ExplorerConfig(time_budget_s=10.0))
    assert isinstance(ex.tick(0, 0, 0, 100.0), NavGoal)
    a = ex.tick(0, 0, 0, 110.0)
    assert isinstance(a, Finished) and "time budget" in a.reason
    assert ex.tick(0, 0, 0, 111.0) is None and ex.progress().state == "done"
    ex = Exploration(ExplorerConfig(max_failures=2, frame_timeout_s=1.0))
    now = 0.0
    for _ in range(2):
        assert isinstance(ex.tick(0, 0, 0, now), NavGoal)
        ex.goal_result(False, now)
        now += 2.0  # no frame comes: the frame wait times out
    a = ex.tick(0, 0, 0, now)
    assert isinstance(a, Finished) and "failed" in a.reason


def test_cancel_ends_the_run() -> None:
    ex = Exploration()
    ex.tick(0, 0, 0, 0.0)
    assert ex.cancel("stop").reason == "stop"
    assert ex.tick(0, 0, 0, 1.0) is None


def test_configs_are_checked() -> None:
    with pytest.raises(ConfigError):
        Exploration(ExplorerConfig(look_steps=-1))
    with pytest.raises(ConfigError):
        CameraConfig(width=2).check()


def test_camera_pose_looks_along_the_heading_and_down() -> None:
    c2w = CameraConfig(mount_height=1.2, tilt_deg=30.0).c2w(1.0, 2.0, math.pi / 2)
    fwd = c2w[:3, 2]
    assert fwd[1] > 0.8 and fwd[2] < -0.4 and abs(fwd[0]) < 1e-9
    assert np.allclose(c2w[:3, 3], [1.0, 2.0, 1.2])
    assert np.allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3))
    assert np.linalg.det(c2w[:3, :3]) > 0
