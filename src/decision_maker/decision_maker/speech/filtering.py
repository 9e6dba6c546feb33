"""Dropping what Whisper invents: silence, noise, junk and echoes of the prompt."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from decision_maker.planning.stop_words import is_stop_command
from decision_maker.speech.errors import ConfigError
from decision_maker.speech.text import normalise

#: Phrases Whisper is known to produce from silence or noise (training-data artefacts).
DEFAULT_BLOCKLIST: tuple[str, ...] = (
    "you", "thank you", "thanks for watching", "thank you for watching", "bye", "okay", "oh",
    "subtitles by the amaraorg community", "please subscribe",
)


@dataclass(frozen=True)
class FilterConfig:
    """Thresholds of the hallucination filter.

    Attributes:
        max_no_speech_prob: drop when Whisper's no-speech probability is above this.
        min_avg_logprob: drop when the mean token log-probability is below this.
        min_stop_avg_logprob: the same for a stop ("stop", "cancel", "abort", ...), lower: a missed stop
            is worse than a spurious one (it only cancels).
        max_compression_ratio: drop repetitive text (gzip ratio above this; Whisper uses 2.4).
        min_chars: drop texts with fewer letters/digits than this.
        max_words: drop texts with more words than this (commands are short).
        max_prompt_echo_words: drop texts that repeat this many consecutive prompt words.
        blocklist: normalised texts dropped outright.
    """

    max_no_speech_prob: float = 0.6
    min_avg_logprob: float = -1.0
    min_stop_avg_logprob: float = -1.6
    max_compression_ratio: float = 2.4
    min_chars: int = 2
    max_words: int = 30
    max_prompt_echo_words: int = 8
    blocklist: tuple[str, ...] = field(default=DEFAULT_BLOCKLIST)

    def __post_init__(self) -> None:
        if not 0.0 <= self.max_no_speech_prob <= 1.0:
            raise ConfigError(f"max_no_speech_prob must be in [0, 1], got {self.max_no_speech_prob}")
        if self.min_avg_logprob > 0.0:
            raise ConfigError(f"min_avg_logprob must be <= 0, got {self.min_avg_logprob}")
        if self.min_stop_avg_logprob > 0.0:
            raise ConfigError(f"min_stop_avg_logprob must be <= 0, got {self.min_stop_avg_logprob}")
        if self.min_chars < 0 or self.max_words < 1 or self.max_prompt_echo_words < 2:
            raise ConfigError("min_chars >= 0, max_words >= 1 and max_prompt_echo_words >= 2 are required")


@dataclass(frozen=True)
class Verdict:
    """Outcome of the filter: ``reason`` is None when the text is kept."""

    text: str
    reason: str | None

    @property
    def kept(self) -> bool:
        return self.reason is None


def longest_common_run(a: Sequence[str], b: Sequence[str]) -> int:
    """Length of the longest run of consecutive words found in both sequences."""
    best = 0
    prev = [0] * (len(b) + 1)
    for x in a:
        cur = [0] * (len(b) + 1)
        for j, y in enumerate(b, 1):
            if x == y:
                cur[j] = prev[j - 1] + 1
                best = max(best, cur[j])
        prev = cur
    return best


def judge(raw_text: str, no_speech_prob: float, avg_logprob: float, compression_ratio: float,
          config: FilterConfig, prompt_words: Sequence[str] = ()) -> Verdict:
    """Decide whether a transcript is speech worth publishing.

    Args:
        raw_text: Whisper's text.
        no_speech_prob: probability of the no-speech token (max over segments).
        avg_logprob: mean token log-probability (length-weighted over segments).
        compression_ratio: gzip compression ratio of the text (max over segments).
        config: thresholds.
        prompt_words: normalised words of the prompt that was given to Whisper.

    Returns:
        The normalised text and the reason it is dropped (None = keep).
    """
    text = normalise(raw_text)
    ws = text.split(" ") if text else []
    if not text:
        return Verdict(text, "empty")
    if no_speech_prob > config.max_no_speech_prob:
        return Verdict(text, "no_speech")
    floor = config.min_stop_avg_logprob if is_stop_command(text) else config.min_avg_logprob
    if avg_logprob < floor:
        return Verdict(text, "low_logprob")
    if compression_ratio > config.max_compression_ratio:
        return Verdict(text, "repetitive")
    if sum(ch.isalnum() for ch in text) < config.min_chars:
        return Verdict(text, "too_short")
    if len(ws) > config.max_words:
        return Verdict(text, "too_long")
    if text in {normalise(b) for b in config.blocklist}:
        return Verdict(text, "blocklisted")
    if prompt_words and longest_common_run(ws, prompt_words) >= config.max_prompt_echo_words:
        return Verdict(text, "prompt_echo")
    return Verdict(text, None)
