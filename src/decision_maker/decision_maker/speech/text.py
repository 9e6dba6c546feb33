"""Text handling of transcripts: normalisation, word edit distance, the optional wake word."""

from __future__ import annotations

import re
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

_APOSTROPHES = re.compile(r"['\u2019`]")
_DECIMAL_POINT = re.compile(r"(?<=\d)[.,](?=\d)")
_NON_ALNUM = re.compile(r"(?:[^\w\u0001]|_)+")
_SPACES = re.compile(r"\s+")


def normalise(text: str) -> str:
    """The form the decision maker relies on: lower case, no punctuation, single spaces.

    Numbers are kept (``"3.5"`` stays ``"3.5"``: a point between digits is part of the number);
    apostrophes vanish without a space (``"don't"`` → ``"dont"``); every other character that is
    not a letter or a digit becomes a space.

    Args:
        text: raw transcript.

    Returns:
        The normalised text (may be empty).
    """
    t = text.lower()
    t = _APOSTROPHES.sub("", t)
    t = _DECIMAL_POINT.sub("\u0001", t)  # protect decimal points through the punctuation pass
    t = _NON_ALNUM.sub(" ", t).replace("\u0001", ".")
    return _SPACES.sub(" ", t).strip()


def words(text: str) -> list[str]:
    """Words of a text after :func:`normalise`."""
    n = normalise(text)
    return n.split(" ") if n else []


def edit_distance(a: Sequence[str], b: Sequence[str]) -> int:
    """Levenshtein distance between two sequences (of words, or the characters of a string)."""
    prev = list(range(len(b) + 1))
    for i, x in enumerate(a, 1):
        cur = [i]
        for j, y in enumerate(b, 1):
            cur.append(min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (x != y)))
        prev = cur
    return prev[-1]


def word_edit_distance(a: str, b: str) -> int:
    """Word-level edit distance between two texts, after normalisation of both."""
    return edit_distance(words(a), words(b))


@dataclass(frozen=True)
class WakeDecision:
    """What the wake-word gate made of a transcript.

    Attributes:
        command: text to publish (wake word stripped), or None.
        reason: why nothing is published (``"no_wake_word"``, ``"wake_word_only"``), or None.
    """

    command: str | None
    reason: str | None


class WakeWordGate:
    """Optional wake word ("robot, go home"): only addressed utterances pass, stripped of it.

    The wake word may be preceded by one filler word ("hey robot", "ok robot") and is matched
    with a tolerance of ``max_edits`` characters for words of 4+ letters (Whisper writes
    "robot" as "robo" or "robots"). Said alone, it arms the gate: the next utterance within
    ``timeout_s`` passes without it. An empty wake word disables the gate.

    Not thread-safe: one caller (the pipeline's result thread).

    Args:
        wake_word: the word(s) to require, e.g. ``"robot"``; empty = off.
        timeout_s: how long a lone wake word keeps the gate open.
        max_edits: character edits tolerated per word of the wake word.
        clock: monotonic clock (injected by tests).
    """

    def __init__(self, wake_word: str = "", timeout_s: float = 5.0, max_edits: int = 1,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.wake_words = words(wake_word)
        self.timeout_s = timeout_s
        self.max_edits = max_edits
        self._clock = clock
        self._armed_until = float("-inf")

    @property
    def enabled(self) -> bool:
        return bool(self.wake_words)

    def _word_matches(self, heard: str, wanted: str) -> bool:
        if heard == wanted:
            return True
        return len(wanted) >= 4 and edit_distance(heard, wanted) <= self.max_edits

    def _find(self, ws: list[str]) -> int | None:
        """Index just past the wake word if it starts ``ws`` (after at most one filler word)."""
        n = len(self.wake_words)
        for start in (0, 1):
            cand = ws[start:start + n]
            if len(cand) == n and all(self._word_matches(h, w) for h, w in zip(cand, self.wake_words, strict=True)):
                return start + n
        return None

    def process(self, text: str) -> WakeDecision:
        """Gate one normalised transcript.

        Args:
            text: normalised transcript (see :func:`normalise`).

        Returns:
            The command to publish or the reason for dropping it.
        """
        if not self.enabled:
            return WakeDecision(text or None, None if text else "empty")
        ws = text.split(" ") if text else []
        now = self._clock()
        end = self._find(ws)
        if end is not None:
            rest = " ".join(ws[end:])
            if rest:
                self._armed_until = float("-inf")
                return WakeDecision(rest, None)
            self._armed_until = now + self.timeout_s
            return WakeDecision(None, "wake_word_only")
        if ws and now <= self._armed_until:
            self._armed_until = float("-inf")
            return WakeDecision(text, None)
        return WakeDecision(None, "no_wake_word")
