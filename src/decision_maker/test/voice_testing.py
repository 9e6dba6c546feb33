"""Shared helpers of the voice tests (imported by test_speech_* / test_audio_command_*)."""

from __future__ import annotations

from decision_maker.speech import testaudio
from decision_maker.speech.text import word_edit_distance, words

MISSING = testaudio.missing_tools()
SKIP_REASON = f"needs {' and '.join(MISSING)} (apt-get install espeak-ng sox)"


def matches(heard: str | None, expected: str) -> bool:
    """Word-level match, tolerant of harmless differences: equal after normalisation, or one
    word edit for commands of 3+ words ("give me a bottle" for "give me the bottle")."""
    if heard is None:
        return False
    if words(heard) == words(expected):
        return True
    return len(words(expected)) >= 3 and word_edit_distance(heard, expected) <= 1
