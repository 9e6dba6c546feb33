"""Lag control with hysteresis (pure): stop taking images when the backlog is too long."""

from __future__ import annotations

from enum import Enum


class LagAction(Enum):
    NONE = "none"
    UNSUBSCRIBE = "unsubscribe"
    RESUBSCRIBE = "resubscribe"


class LagController:
    """Unsubscribe when backlog > ``high``; resubscribe when backlog < ``low`` (seed: 300 / 150)."""

    def __init__(self, high: int = 300, low: int = 150) -> None:
        if not 0 <= low < high:
            raise ValueError(f"need 0 <= low < high, got low={low} high={high}")
        self.high, self.low = high, low
        self.subscribed = True
        self.pauses = 0

    def update(self, backlog: int) -> LagAction:
        """Feed the current backlog (frames written but not yet processed); returns what to do."""
        if self.subscribed and backlog > self.high:
            self.subscribed = False
            self.pauses += 1
            return LagAction.UNSUBSCRIBE
        if not self.subscribed and backlog < self.low:
            self.subscribed = True
            return LagAction.RESUBSCRIBE
        return LagAction.NONE
