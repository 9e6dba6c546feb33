"""Which run a cancel request is for: the SLAM server's cancel bookkeeping (plain Python, no rclpy).

A goal's cancel can arrive before its run has a session (the server is still waiting for ``camera_info`` or
making the engine), and it can name a goal other than the running one (two goals accepted at once, the second
refused when it starts). :class:`CancelRouter` cancels the running session only for its own goal and keeps an
early cancel until that goal's run starts.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Protocol


class Cancellable(Protocol):
    def cancel(self) -> None: ...


class CancelRouter:
    """Routes cancel requests by goal id (bytes) to the running session (thread-safe; callbacks never block)."""

    def __init__(self, remember: int = 64) -> None:
        """``remember``: at most this many early cancels are kept (the oldest are forgotten), so cancels for goals
        that never start cannot pile up."""
        if remember < 1:
            raise ValueError("remember must be >= 1")
        self._lock = threading.Lock()
        self._remember = remember
        self._running: tuple[bytes, Cancellable] | None = None
        self._early: OrderedDict[bytes, None] = OrderedDict()

    def request(self, goal_id: bytes) -> bool:
        """A cancel for ``goal_id``: the running session is cancelled if it is that goal's (returns True), else the
        request is kept for :meth:`start` (returns False)."""
        with self._lock:
            target = self._running[1] if self._running is not None and self._running[0] == goal_id else None
            if target is None:
                self._early[goal_id] = None
                self._early.move_to_end(goal_id)
                while len(self._early) > self._remember:
                    self._early.popitem(last=False)
        if target is not None:
            target.cancel()
        return target is not None

    def start(self, goal_id: bytes, session: Cancellable) -> bool:
        """``goal_id``'s run now has ``session``; a cancel that came first cancels it now (returns True)."""
        with self._lock:
            self._running = (goal_id, session)
            early = goal_id in self._early
            self._early.pop(goal_id, None)
        if early:
            session.cancel()
        return early

    def finish(self, goal_id: bytes) -> None:
        """``goal_id``'s run is over (also when it never started): its session and any early cancel are dropped."""
        with self._lock:
            if self._running is not None and self._running[0] == goal_id:
                self._running = None
            self._early.pop(goal_id, None)

    @property
    def pending(self) -> int:
        """Early cancels kept."""
        with self._lock:
            return len(self._early)
