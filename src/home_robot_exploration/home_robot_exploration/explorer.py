"""The exploration loop as a plain state machine (no ROS): look around, go to a frontier, repeat.

The ROS node (``explorer_node``) feeds it depth frames (:meth:`Exploration.integrate`), calls
:meth:`Exploration.tick` on a timer with the robot's pose and the clock, sends each
:class:`NavGoal` it returns as a ``NavigateToPose`` goal and reports the outcome with
:meth:`Exploration.goal_result`. Times are seconds on one clock (the node uses ROS time, the
same clock that stamps the camera frames).

Cycle: at the start and after arriving at each frontier goal the robot turns in place in
``look_steps`` steps (each a goal with the same position); after every goal it waits for a frame
taken after the arrival (at most ``frame_timeout_s``) before it decides again, so a slow camera
never leaves a gap in the map. It ends (:class:`Finished`) when no reachable frontier is left, the
time budget is spent, ``max_goals`` goals were sent, or :meth:`Exploration.cancel` is called.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from home_robot_exploration.errors import ConfigError
from home_robot_exploration.frontiers import Frontier, FrontierConfig, choose_frontier, find_frontiers
from home_robot_exploration.occupancy import GridConfig, OccupancyGrid


@dataclass(frozen=True)
class ExplorerConfig:
    """Exploration loop settings.

    Attributes:
        time_budget_s: exploration ends after this long (s).
        look_steps: turn-in-place steps of a look-around (0: no look-around); 4 = every 90 degrees.
        frame_timeout_s: longest wait for a fresh frame after a goal (s).
        max_goals: exploration ends after this many navigation goals.
        max_failures: exploration ends after this many failed goals in a row.
    """

    time_budget_s: float = 600.0
    look_steps: int = 4
    frame_timeout_s: float = 10.0
    max_goals: int = 200
    max_failures: int = 5
    grid: GridConfig = field(default_factory=GridConfig)
    frontier: FrontierConfig = field(default_factory=FrontierConfig)

    def check(self) -> None:
        if not (self.time_budget_s > 0 and self.frame_timeout_s > 0):
            raise ConfigError("time_budget_s and frame_timeout_s must be > 0")
        if self.look_steps < 0 or self.max_goals < 1 or self.max_failures < 1:
            raise ConfigError("look_steps must be >= 0, max_goals and max_failures >= 1")
        self.grid.check()
        self.frontier.check()


@dataclass(frozen=True)
class NavGoal:
    """Send the base here (map frame): ``kind`` is ``look`` (turn in place) or ``frontier``."""

    x: float
    y: float
    yaw: float
    kind: str


@dataclass(frozen=True)
class Finished:
    """Exploration is over; ``reason`` says why."""

    reason: str


@dataclass(frozen=True)
class Progress:
    """What the progress topic carries."""

    state: str  # "starting" | "looking" | "travelling" | "waiting_frame" | "planning" | "done"
    explored_m2: float
    frontiers_left: int
    elapsed_s: float
    goals: int
    frames: int
    reason: str = ""


class Exploration:
    """One exploration run; see the module docstring."""

    def __init__(self, cfg: ExplorerConfig | None = None) -> None:
        self.cfg = cfg or ExplorerConfig()
        self.cfg.check()
        self.grid = OccupancyGrid(self.cfg.grid)
        self.visited: list[tuple[float, float]] = []
        self.path: list[tuple[float, float]] = []
        self.frontiers: list[Frontier] = []
        self.started: float | None = None
        self.finished: Finished | None = None
        self.goals = 0
        self._failures = 0
        self._goal_active = False
        self._active_kind = ""
        self._looks: list[float] = []
        self._wait_since: float | None = None
        self._last_frame_stamp = -math.inf
        self._now = 0.0

    # --- inputs -------------------------------------------------------------------------------------

    def integrate(self, depth: np.ndarray, k: np.ndarray, c2w: np.ndarray, stamp: float) -> None:
        """Add a depth frame taken at ``stamp`` (see :meth:`OccupancyGrid.integrate`).

        Raises:
            FrameError: unusable frame (the grid is unchanged).
        """
        self.grid.integrate(depth, k, c2w)
        self._last_frame_stamp = max(self._last_frame_stamp, stamp)

    def goal_result(self, succeeded: bool, now: float) -> None:
        """The goal last returned by :meth:`tick` ended (reached, or failed/rejected/cancelled)."""
        self._goal_active = False
        self._wait_since = now
        if succeeded:
            self._failures = 0
        else:
            self._failures += 1
            self._looks = []  # a failed turn or frontier: plan afresh

    def cancel(self, reason: str = "cancelled") -> Finished:
        if self.finished is None:
            self.finished = Finished(reason)
        return self.finished

    # --- decisions ----------------------------------------------------------------------------------

    def tick(self, x: float, y: float, yaw: float, now: float) -> NavGoal | Finished | None:
        """Decide: a goal to send, the end, or None (keep waiting: a goal or a frame is pending)."""
        self._now = now
        if self.finished is not None:
            return None
        if self.started is None:
            self.started = now
            self._looks = self._look_yaws(yaw)
        if not self.path or math.hypot(self.path[-1][0] - x, self.path[-1][1] - y) > 0.05:
            self.path.append((x, y))
        self.grid.mark_free_disc(x, y, self.cfg.frontier.robot_radius)
        if now - self.started >= self.cfg.time_budget_s:
            return self.cancel(f"time budget of {self.cfg.time_budget_s:g} s spent")
        if self._goal_active:
            return None
        if self._failures >= self.cfg.max_failures:
            return self.cancel(f"{self._failures} navigation goals failed in a row")
        if self._wait_since is not None:
            fresh = self._last_frame_stamp >= self._wait_since
            if not fresh and now - self._wait_since < self.cfg.frame_timeout_s:
                return None
            self._wait_since = None
        if self.goals >= self.cfg.max_goals:
            return self.cancel(f"{self.goals} goals sent (max_goals)")
        if self._looks:
            return self._send(NavGoal(x, y, self._looks.pop(0), "look"))
        self.frontiers = find_frontiers(self.grid, (x, y), self.cfg.frontier, self.visited)
        best = choose_frontier(self.frontiers)
        if best is None:
            return self.cancel("no reachable frontier left")
        assert best.goal is not None
        self.visited.append(best.goal)
        self._looks = self._look_yaws(best.heading)
        return self._send(NavGoal(best.goal[0], best.goal[1], best.heading, "frontier"))

    def _send(self, goal: NavGoal) -> NavGoal:
        self.goals += 1
        self._goal_active = True
        self._active_kind = goal.kind
        return goal

    def _look_yaws(self, yaw: float) -> list[float]:
        n = self.cfg.look_steps
        return [math.remainder(yaw + 2 * math.pi * (i + 1) / n, 2 * math.pi) for i in range(n)]

    def progress(self, now: float | None = None) -> Progress:
        now = self._now if now is None else now
        if self.finished is not None:
            state = "done"
        elif self.started is None:
            state = "starting"
        elif self._goal_active:
            state = "looking" if self._active_kind == "look" else "travelling"
        elif self._wait_since is not None:
            state = "waiting_frame"
        else:
            state = "planning"
        return Progress(state, self.grid.free_area_m2(), sum(f.goal is not None for f in self.frontiers),
                        0.0 if self.started is None else now - self.started, self.goals, self.grid.frames,
                        "" if self.finished is None else self.finished.reason)
