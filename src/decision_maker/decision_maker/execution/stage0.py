"""Stage 0 for the brain: while the robot explores its home, commands wait (or are refused) (no ROS).

The explorer publishes its progress (``exploration/progress``, JSON with ``state`` and
``seen_percent``; see ``home_robot_exploration.explorer_node``). :class:`ExplorationGate` turns
that into a :class:`Hold` the execution engine consults: with ``mode="queue"`` a command is queued
and answered "Still exploring (62 % of the home seen); I will do it after." and runs when
exploration ends; with ``mode="reject"`` it is refused with the same reason. ``mode="off"`` (the
default) never holds anything. The gate opens when the progress says ``done``, or after
``timeout_s`` without a ``done`` (an explorer that never reports must not block the robot forever;
the reason is logged by the node).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from decision_maker.errors import ConfigError

MODES = ("off", "queue", "reject")


@dataclass(frozen=True)
class Hold:
    """Why commands do not run now."""

    reason: str  # machine-oriented: "still exploring (62 % of the home seen)"
    sentence: str  # for a person: "Still exploring (62 % of the home seen)"
    reject: bool  # True: refuse new commands; False: queue them until the gate opens


class ExplorationGate:
    """Thread-safe: :meth:`on_progress` from a callback, :meth:`hold` from anywhere.

    Args:
        mode: "off" | "queue" | "reject".
        timeout_s: the gate opens by itself this long after construction (> 0).
        clock: monotonic seconds (injectable for tests).
    """

    def __init__(self, mode: str = "off", timeout_s: float = 900.0,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if mode not in MODES:
            raise ConfigError(f"exploration_mode must be one of {MODES}, got {mode!r}")
        if not (timeout_s > 0 and math.isfinite(timeout_s)):
            raise ConfigError(f"exploration_timeout_s must be a finite number > 0, got {timeout_s}")
        self.mode = mode
        self._clock = clock
        self._deadline = clock() + timeout_s
        self._lock = threading.Lock()  # guards _done, _seen, _reason
        self._done = mode == "off"
        self._seen: float | None = None
        self._reason = ""
        self._state = ""

    def on_progress(self, data: str) -> bool:
        """Take one progress message. Returns True when it ends exploration (first ``done``).

        Raises:
            ValueError: not a progress message (the gate is unchanged).
        """
        try:
            doc = json.loads(data)
            state = str(doc["state"])
            seen = float(doc.get("seen_percent", math.nan))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, RecursionError, OverflowError) as exc:
            raise ValueError(f"not an exploration progress message: {str(data)[:60]!r}") from exc
        with self._lock:
            if math.isfinite(seen):
                self._seen = min(100.0, max(0.0, seen))
            self._state = state[:40]
            if state == "done" and not self._done:
                self._done = True
                self._reason = str(doc.get("reason", ""))[:200]
                return True
        return False

    def timed_out(self) -> bool:
        """True once: the gate opened by its deadline (call it from a timer to log it)."""
        with self._lock:
            if not self._done and self._clock() >= self._deadline:
                self._done = True
                self._reason = "no end of exploration reported in time"
                return True
        return False

    @property
    def done_reason(self) -> str:
        with self._lock:
            return self._reason

    def hold(self) -> Hold | None:
        """The hold while exploring, or None (commands run)."""
        with self._lock:
            if self._done:
                return None
            if self._clock() >= self._deadline:
                return None
            seen = "" if self._seen is None else f" ({self._seen:.0f} % of the home seen)"
            mapping = self._state == "mapping"
        if mapping:  # explored; the SLAM map of what was seen is being finished
            return Hold(f"still finishing the map{seen}", f"Still finishing the map{seen}", self.mode == "reject")
        return Hold(f"still exploring{seen}", f"Still exploring{seen}", self.mode == "reject")
