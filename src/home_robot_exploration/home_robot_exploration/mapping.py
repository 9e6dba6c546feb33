"""Mapping while exploring: the life of the SLAM run that the explorer drives (no ROS).

The explorer node starts a ``RunSlam`` goal on the streaming SLAM server before the robot moves,
explores while the server maps the camera's frames, and when exploration ends asks the server to
finish (``data_transfer_done``; a stop cancels the goal instead, which also saves the map). The
server then writes the map where ``object_query_server`` reads it and asks it to reload.
Exploration is ``done`` only after that, so commands held by the decision maker run on the map the
robot has just built. Every phase has a deadline; a SLAM server that never answers makes the run
``failed``, with the reason, and never blocks exploration or its end.

States: ``off`` (no mapping configured) → ``connecting`` (waiting for the action server and the
goal's acceptance) → ``waiting_start`` (accepted; waiting for the server's start signal: frames
sent before it are lost) → ``running`` → ``finishing`` (exploration ended; the server maps its
backlog and saves) → ``done`` | ``failed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from home_robot_exploration.errors import ConfigError

STATES = ("off", "connecting", "waiting_start", "running", "finishing", "done", "failed")


@dataclass(frozen=True)
class MappingConfig:
    """Attributes:
        enabled: drive a SLAM run (the node's ``slam_action`` is not empty).
        start_timeout_s: longest wait for the server, the goal's acceptance and its start signal;
            then exploration goes on without mapping (``failed``).
        finish_timeout_s: longest wait for the map after exploration ended.
    """

    enabled: bool = False
    start_timeout_s: float = 60.0
    finish_timeout_s: float = 600.0

    def check(self) -> None:
        for name in ("start_timeout_s", "finish_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ConfigError(f"{name} must be a positive number of seconds, got {v}")


@dataclass
class MappingResult:
    """What the SLAM run produced (filled from the action's result)."""

    success: bool = False
    map_path: str = ""
    frames: int = 0
    message: str = ""


class MappingRun:
    """The SLAM run's state machine; the node calls these methods from its (single) executor thread."""

    def __init__(self, cfg: MappingConfig, now: float) -> None:
        cfg.check()
        self.cfg = cfg
        self.state = "connecting" if cfg.enabled else "off"
        self._since = now
        self.goal_id = ""
        self.frames = 0  # frames the server has mapped (feedback)
        self.gaussians = 0
        self.result = MappingResult()
        self.reason = ""

    # --- start -------------------------------------------------------------------------------------

    def accepted(self, goal_id: str, now: float) -> None:
        """The server accepted the goal (``goal_id``: the goal's uuid in hex)."""
        if self.state == "connecting":
            self.goal_id, self.state, self._since = goal_id, "waiting_start", now

    def start_signal(self, goal_id: str) -> bool:
        """The server's ``slam_start_signal`` names ``goal_id``; True when it is ours (now running)."""
        if self.state == "waiting_start" and goal_id == self.goal_id:
            self.state = "running"
            return True
        return False

    def rejected(self, reason: str) -> None:
        """The goal was refused or could not be sent: exploration goes on without a map."""
        if self.state in ("connecting", "waiting_start"):
            self.state, self.reason = "failed", reason

    def ready_to_explore(self) -> bool:
        """Whether the robot may move: mapping is running, not wanted, or gave up."""
        return self.state in ("off", "running", "failed", "done")

    # --- progress and end --------------------------------------------------------------------------

    def feedback(self, frames: int, gaussians: int) -> None:
        self.frames, self.gaussians = int(frames), int(gaussians)

    def finish(self, now: float) -> bool:
        """Exploration ended. True when the server must be asked to finish (the run is live)."""
        if self.state in ("running", "waiting_start"):
            self.state, self._since = "finishing", now
            return True
        if self.state == "connecting":
            self.state, self.reason = "failed", "exploration ended before the SLAM run started"
        return False

    def ended(self, result: MappingResult) -> None:
        """The action's result arrived (whatever the state: a server may also end a run by itself)."""
        self.result = result
        if result.frames:
            self.frames = result.frames
        if self.state in ("done", "failed", "off"):
            return
        self.state = "done" if result.success else "failed"
        self.reason = result.message

    def tick(self, now: float) -> str | None:
        """Deadlines; returns a reason when one just passed (the run is then ``failed``)."""
        if self.state in ("connecting", "waiting_start") and now - self._since > self.cfg.start_timeout_s:
            self.state = "failed"
            self.reason = (f"no SLAM run started within {self.cfg.start_timeout_s:g} s "
                           f"({'server not available' if not self.goal_id else 'no start signal'}); exploring "
                           "without mapping")
            return self.reason
        if self.state == "finishing" and now - self._since > self.cfg.finish_timeout_s:
            self.state = "failed"
            self.reason = f"the SLAM server did not finish the map within {self.cfg.finish_timeout_s:g} s"
            return self.reason
        return None

    def settled(self) -> bool:
        """Nothing more will happen: exploration may report ``done``."""
        return self.state in ("off", "done", "failed")

    def summary(self) -> dict[str, object]:
        """For the progress message."""
        return {"state": self.state, "frames": self.frames, "gaussians": self.gaussians,
                "map_path": self.result.map_path, "message": (self.reason or self.result.message)[:200]}
