"""Matching colour, depth (and optional semantic) images by timestamp (pure).

A colour image is paired with the depth (and semantic) image whose stamp is nearest to it, only
if that is within ``tolerance`` AND the colour image is also the nearest colour image to that
depth stamp (mutual nearest neighbours), so frames are never mispaired — an ambiguous or
unmatched image is dropped and counted instead. Images may arrive out of order; one that waited
longer than ``max_wait`` (in stream time: newest stamp seen minus its stamp) is dropped.
"""

from __future__ import annotations

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
        max_wait: stream-time (s) an image may wait for its partner before it is dropped.
        max_pending: bound on waiting images per stream (oldest dropped first).
    """

    def __init__(self, tolerance: float = 0.02, use_semantic: bool = False, max_wait: float = 0.5,
                 max_pending: int = 64) -> None:
        if tolerance < 0 or max_wait <= 0 or max_pending <= 0:
            raise ValueError("tolerance must be >= 0, max_wait and max_pending > 0")
        self.tolerance, self.max_wait, self.max_pending = tolerance, max_wait, max_pending
        self.streams = STREAMS if use_semantic else STREAMS[:2]
        self._pending: dict[str, dict[float, Any]] = {s: {} for s in self.streams}
        self._newest = float("-inf")
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
        self._newest = max(self._newest, stamp)
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
                rgb = self._pending["rgb"].pop(t_rgb)
                imgs = {s: self._pending[s].pop(t) for s, t in partners.items()}
                out.append(MatchedFrame(t_rgb, rgb, imgs["depth"], imgs.get("semantic")))
                self.stats.matched += 1
        return out

    def _expire(self) -> None:
        for s, pending in self._pending.items():
            old = [t for t in pending if self._newest - t > self.max_wait]
            old += sorted(t for t in pending if t not in old)[: max(0, len(pending) - len(old) - self.max_pending)]
            for t in old:
                pending.pop(t, None)
                self.stats.dropped[s] += 1

    def flush(self) -> None:
        """End of stream: everything still waiting is unmatched."""
        for s, pending in self._pending.items():
            self.stats.dropped[s] += len(pending)
            pending.clear()

    def pending(self) -> dict[str, int]:
        return {s: len(p) for s, p in self._pending.items()}
