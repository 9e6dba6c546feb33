"""Matching colour, depth (and optional semantic) images by timestamp (pure).

A colour image is paired with the depth (and semantic) image whose stamp is nearest to it, only
if that is within ``tolerance`` AND the colour image is also the nearest colour image to that
depth stamp (mutual nearest neighbours), so frames are never mispaired — an ambiguous or
unmatched image is dropped and counted instead. Images may arrive out of order; one that waited
longer than ``max_wait`` seconds (wall clock, since it arrived) for its partner is dropped. Wall
clock, not stream time: a recording may be streamed much faster than it was recorded.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

STREAMS = ("rgb", "depth", "semantic")


@dataclass
class MatchedFrame:
    """One synchronised frame; ``stamp`` is the colour image's (seconds)."""

    stamp: float
    rgb: Any
    depth: Any
    semantic: Any | None = None


@dataclass
class MatchStats:
    matched: int = 0
    dropped: dict[str, int] = field(default_factory=lambda: dict.fromkeys(STREAMS, 0))
    duplicates: int = 0


class FrameMatcher:
    """Args:
        tolerance: largest |stamp difference| (s) of a pair; keep it below half the frame period.
        use_semantic: also require a semantic image per frame.
        max_wait: seconds (wall clock) an image may wait for its partner before it is dropped.
        max_pending: bound on waiting images per stream (oldest dropped first).
        clock: monotonic clock in seconds (tests pass a fake one).
    """

    def __init__(self, tolerance: float = 0.02, use_semantic: bool = False, max_wait: float = 2.0,
                 max_pending: int = 64, clock: Callable[[], float] = time.monotonic) -> None:
        if tolerance < 0 or max_wait <= 0 or max_pending <= 0:
            raise ValueError("tolerance must be >= 0, max_wait and max_pending > 0")
        self.tolerance, self.max_wait, self.max_pending = tolerance, max_wait, max_pending
        self.streams = STREAMS if use_semantic else STREAMS[:2]
        self._pending: dict[str, dict[float, Any]] = {s: {} for s in self.streams}
        self._arrived: dict[str, dict[float, float]] = {s: {} for s in self.streams}  # stamp -> arrival time
        self._clock = clock
        self.stats = MatchStats()

    def push(self, stream: str, stamp: float, image: Any) -> list[MatchedFrame]:
        """Add one image; returns the frames that became complete (oldest first)."""
        if stream not in self._pending:
            raise ValueError(f"unknown stream {stream!r}; expected one of {self.streams}")
        pending = self._pending[stream]
        if stamp in pending:
            self.stats.duplicates += 1  # same stamp twice on one stream: keep the first
            return []
        pending[stamp] = image
        self._arrived[stream][stamp] = self._clock()
        out = self._match()
        self._expire()
        return out

    def _nearest(self, stream: str, stamp: float) -> float | None:
        best = None
        for t in self._pending[stream]:
            if abs(t - stamp) <= self.tolerance and (best is None or abs(t - stamp) < abs(best - stamp)):
                best = t
        return best

    def _match(self) -> list[MatchedFrame]:
        out = []
        for t_rgb in sorted(self._pending["rgb"]):
            partners = {}
            for s in self.streams[1:]:
                t = self._nearest(s, t_rgb)
                if t is None or self._nearest("rgb", t) != t_rgb:
                    break
                partners[s] = t
            else:
                rgb = self._take("rgb", t_rgb)
                imgs = {s: self._take(s, t) for s, t in partners.items()}
                out.append(MatchedFrame(t_rgb, rgb, imgs["depth"], imgs.get("semantic")))
                self.stats.matched += 1
        return out

    def _take(self, stream: str, stamp: float) -> Any:
        self._arrived[stream].pop(stamp, None)
        return self._pending[stream].pop(stamp)

    def _expire(self) -> None:
        now = self._clock()
        for s, pending in self._pending.items():
            arrived = self._arrived[s]
            old = {t for t in pending if now - arrived[t] > self.max_wait}
            rest = sorted(t for t in pending if t not in old)
            old.update(rest[: max(0, len(rest) - self.max_pending)])
            for t in old:
                self._take(s, t)
                self.stats.dropped[s] += 1

    def flush(self) -> None:
        """End of stream: everything still waiting is unmatched."""
        for s, pending in self._pending.items():
            self.stats.dropped[s] += len(pending)
            pending.clear()
            self._arrived[s].clear()

    def pending(self) -> dict[str, int]:
        return {s: len(p) for s, p in self._pending.items()}
