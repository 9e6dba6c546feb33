"""Frontiers on an occupancy grid, reachability, and the choice of the next goal (no ROS).

* A frontier cell is a free cell with an unknown 4-neighbour; frontier cells are grouped into
  clusters by 8-connectivity.
* The robot may stand on a free cell farther than ``robot_radius`` from every occupied cell
  (unknown cells are not obstacles here, or no frontier could ever be reached). Reachability is a
  wavefront from the robot's cell over those cells (8-connected; path length in metres, diagonal
  steps counted as one cell, i.e. a slight underestimate).
* Each cluster's goal is its reachable cell nearest to the cluster's centroid; its utility is
  ``gain_weight * frontier length (m) - cost_weight * travel (m)``. Goals near an earlier goal
  (``visited_radius``) are skipped, so exploration always ends.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.occupancy import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

_N8 = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


@dataclass(frozen=True)
class FrontierConfig:
    """Frontier choice settings.

    Attributes:
        robot_radius: the base's radius (m): cells this close to an occupied cell are not standable.
        min_cluster_cells: smaller frontier clusters are noise and ignored.
        gain_weight: utility per metre of frontier.
        cost_weight: utility lost per metre of travel.
        visited_radius: a goal candidate this close (m) to an earlier goal is skipped.
    """

    robot_radius: float = 0.25
    min_cluster_cells: int = 8
    gain_weight: float = 1.0
    cost_weight: float = 0.5
    visited_radius: float = 0.5

    def check(self) -> None:
        if not (self.robot_radius >= 0 and self.visited_radius >= 0 and self.min_cluster_cells >= 1):
            raise ConfigError("robot_radius and visited_radius must be >= 0 and min_cluster_cells >= 1")
        if not (self.gain_weight >= 0 and self.cost_weight >= 0):
            raise ConfigError("gain_weight and cost_weight must be >= 0")


@dataclass(frozen=True)
class Frontier:
    """One frontier cluster and its goal."""

    cells: int  # frontier cells in the cluster
    centroid: tuple[float, float]  # map frame (m)
    goal: tuple[float, float] | None  # reachable standing point (m); None: unreachable
    heading: float  # rad: from the goal toward the centroid's unknown side
    travel_m: float  # path length from the robot (inf when unreachable)
    utility: float


def _shift(a: np.ndarray, dy: int, dx: int, fill: bool = False) -> np.ndarray:
    """``out[y, x] = a[y + dy, x + dx]`` (``fill`` outside)."""
    out = np.full_like(a, fill)
    h, w = a.shape
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = a[ys, xs]
    return out


def frontier_mask(states: np.ndarray) -> np.ndarray:
    """[ny, nx] bool: free cells with an unknown 4-neighbour."""
    unknown = states == UNKNOWN
    near = np.zeros_like(unknown)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        near |= _shift(unknown, dy, dx)
    return (states == FREE) & near


def inflate(occupied: np.ndarray, radius_cells: float) -> np.ndarray:
    """[ny, nx] bool: cells within ``radius_cells`` of an occupied cell (a disc dilation)."""
    out = occupied.copy()
    n = int(math.floor(radius_cells))
    for dy in range(-n, n + 1):
        for dx in range(-n, n + 1):
            if (dx or dy) and dx * dx + dy * dy <= radius_cells * radius_cells:
                out |= _shift(occupied, dy, dx)
    return out


def standable(states: np.ndarray, resolution: float, robot_radius: float) -> np.ndarray:
    """[ny, nx] bool: free and not within ``robot_radius`` of an occupied cell."""
    return (states == FREE) & ~inflate(states == OCCUPIED, robot_radius / resolution)


def wavefront(passable: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """[ny, nx] float: steps (8-connected) from ``start`` = (ix, iy) over ``passable``; inf where unreachable.

    The start cell counts as passable (the robot is there)."""
    dist = np.full(passable.shape, np.inf)
    ix, iy = start
    if not (0 <= iy < passable.shape[0] and 0 <= ix < passable.shape[1]):
        return dist
    reached = np.zeros_like(passable)
    reached[iy, ix] = True
    front = reached.copy()
    dist[iy, ix] = 0
    step = 0
    while front.any():
        step += 1
        grown = np.zeros_like(front)
        for dy, dx in _N8:
            grown |= _shift(front, dy, dx)
        front = grown & passable & ~reached
        reached |= front
        dist[front] = step
    return dist


def clusters(mask: np.ndarray) -> list[np.ndarray]:
    """8-connected components of ``mask``: a list of [K, 2] (iy, ix) index arrays."""
    todo = set(zip(*np.nonzero(mask), strict=True))
    out = []
    while todo:
        seed = todo.pop()
        comp = [seed]
        q = deque([seed])
        while q:
            y, x = q.popleft()
            for dy, dx in _N8:
                nb = (y + dy, x + dx)
                if nb in todo:
                    todo.remove(nb)
                    comp.append(nb)
                    q.append(nb)
        out.append(np.array(comp, dtype=np.int64))
    return out


def find_frontiers(grid: OccupancyGrid, robot_xy: tuple[float, float], cfg: FrontierConfig,
                   visited: list[tuple[float, float]] | None = None) -> list[Frontier]:
    """Every frontier cluster of at least ``min_cluster_cells``, best utility first (unreachable last).

    Args:
        grid: the occupancy grid.
        robot_xy: the robot's position (map frame, m).
        cfg: choice settings.
        visited: earlier goals (m); candidates within ``visited_radius`` of one are not used.
    """
    res = grid.cfg.resolution
    states = grid.states()
    ok = standable(states, res, cfg.robot_radius)
    rx, ry = grid.cell_of(robot_xy[0], robot_xy[1])
    dist = wavefront(ok, (int(rx), int(ry)))
    if visited:
        cx, cy = grid.centre_of(*np.meshgrid(np.arange(grid.nx), np.arange(grid.ny), indexing="xy"))
        for vx, vy in visited:
            dist[(cx - vx) ** 2 + (cy - vy) ** 2 <= cfg.visited_radius**2] = np.inf
    unknown = states == UNKNOWN
    out = []
    for comp in clusters(frontier_mask(states)):
        if len(comp) < cfg.min_cluster_cells:
            continue
        iy, ix = comp[:, 0], comp[:, 1]
        mx, my = grid.centre_of(ix, iy)
        centroid = (float(mx.mean()), float(my.mean()))
        # the side the unknown lies on: mean offset from frontier cells to their unknown neighbours
        ux = uy = 0.0
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ny_, nx_ = np.clip(iy + dy, 0, grid.ny - 1), np.clip(ix + dx, 0, grid.nx - 1)
            hit = unknown[ny_, nx_]
            ux += float(dx * hit.sum())
            uy += float(dy * hit.sum())
        d = dist[iy, ix]
        reach = np.isfinite(d)
        length = len(comp) * res
        if not reach.any():
            out.append(Frontier(len(comp), centroid, None, math.atan2(uy, ux), math.inf, -math.inf))
            continue
        j = np.flatnonzero(reach)[np.argmin((mx[reach] - centroid[0]) ** 2 + (my[reach] - centroid[1]) ** 2)]
        goal = (float(mx[j]), float(my[j]))
        travel = float(d[j]) * res
        out.append(Frontier(len(comp), centroid, goal, math.atan2(uy, ux), travel,
                            cfg.gain_weight * length - cfg.cost_weight * travel))
    out.sort(key=lambda f: -f.utility)
    return out


def choose_frontier(frontiers: list[Frontier]) -> Frontier | None:
    """The reachable frontier of highest utility, or None when none is reachable."""
    for f in frontiers:
        if f.goal is not None:
            return f
    return None


__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "Frontier", "FrontierConfig", "choose_frontier", "clusters",
           "find_frontiers", "frontier_mask", "inflate", "standable", "wavefront"]
