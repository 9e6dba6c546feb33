"""Cutting a live stream into utterances: Silero-VAD endpointing, or the seed's fixed chunks.

The endpointer is pure logic over per-frame speech probabilities (frames of 512 samples =
32 ms at 16 kHz), so it is tested with hand-made probability sequences; :class:`StreamingVad`
produces those probabilities with the Silero VAD model that faster-whisper ships (ONNX,
onnxruntime), carrying the LSTM state across calls so that streaming equals offline.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass

import numpy as np

from decision_maker.speech.errors import ConfigError
from decision_maker.speech.sources import SAMPLE_RATE

FRAME = 512  # samples per VAD frame (32 ms at 16 kHz), fixed by the Silero model
_CONTEXT = 64  # samples of left context the Silero v6 model takes with each frame


@dataclass(frozen=True)
class VadConfig:
    """Endpointing parameters.

    Attributes:
        threshold: speech probability at or above which a frame is speech.
        neg_threshold: probability below which a frame is silence (None = threshold - 0.15);
            frames in between continue the current state.
        min_speech_ms: utterances with less speech than this are discarded (clicks, coughs).
        min_silence_ms: silence after speech that ends an utterance.
        speech_pad_ms: audio kept before the first and after the last speech frame.
        max_utterance_s: an utterance is cut after this long even if speech goes on.
        speculative_ms: silence after which a tentative end is announced (transcription may
            start before the utterance is final); None = never.
    """

    threshold: float = 0.5
    neg_threshold: float | None = None
    min_speech_ms: float = 150.0
    min_silence_ms: float = 400.0
    speech_pad_ms: float = 200.0
    max_utterance_s: float = 10.0
    speculative_ms: float | None = 100.0

    def __post_init__(self) -> None:
        if not 0.0 < self.threshold < 1.0:
            raise ConfigError(f"vad threshold must be in (0, 1), got {self.threshold}")
        if self.neg_threshold is not None and not 0.0 <= self.neg_threshold <= self.threshold:
            raise ConfigError(f"neg_threshold must be in [0, threshold], got {self.neg_threshold}")
        if self.min_silence_ms < 32 or self.max_utterance_s <= 0.5 or self.speech_pad_ms < 0 or self.min_speech_ms < 0:
            raise ConfigError("min_silence_ms >= 32, max_utterance_s > 0.5, speech_pad_ms >= 0, min_speech_ms >= 0")

    @property
    def low(self) -> float:
        return self.neg_threshold if self.neg_threshold is not None else max(self.threshold - 0.15, 0.01)


@dataclass(frozen=True)
class SegmentEvent:
    """Something the segmenter noticed.

    Attributes:
        kind: ``"tentative"`` (speech paused: the utterance may be over), ``"resume"`` (it was not),
            ``"final"`` (the utterance is over: transcribe ``audio``).
        utterance: running number of the utterance.
        audio: ``[n]`` float32 samples to transcribe (tentative, final), else None.
        speech_end_time: clock time at which the last speech sample arrived (final/tentative).
        start_sample: stream index of ``audio[0]``.
        cut: the utterance was cut by ``max_utterance_s`` or a fixed chunk boundary.
    """

    kind: str
    utterance: int
    audio: np.ndarray | None = None
    speech_end_time: float = 0.0
    start_sample: int = 0
    cut: bool = False


class StreamingVad:
    """Silero VAD (faster-whisper's ONNX model) over a stream, one probability per 512 samples."""

    def __init__(self) -> None:
        from faster_whisper.vad import get_vad_model

        self._session = get_vad_model().session
        self.reset()

    def reset(self) -> None:
        self._h = np.zeros((1, 1, 128), dtype=np.float32)
        self._c = np.zeros((1, 1, 128), dtype=np.float32)
        self._context = np.zeros(_CONTEXT, dtype=np.float32)
        self._pending = np.zeros(0, dtype=np.float32)

    def push(self, audio: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Feed samples; returns the complete frames so far and their speech probabilities.

        Args:
            audio: ``[n]`` float32 samples, 16 kHz.

        Returns:
            ``(frames [k, 512] float32, probs [k] float32)``; leftover samples wait for the next call.
        """
        buf = np.concatenate([self._pending, audio.astype(np.float32, copy=False)])
        k = buf.size // FRAME
        self._pending = buf[k * FRAME:]
        if k == 0:
            return np.zeros((0, FRAME), dtype=np.float32), np.zeros(0, dtype=np.float32)
        frames = buf[: k * FRAME].reshape(k, FRAME)  # [k, 512]
        contexts = np.concatenate([self._context[None], frames[:-1, -_CONTEXT:]], axis=0)  # [k, 64]
        batch = np.concatenate([contexts, frames], axis=1)  # [k, 576]
        probs, self._h, self._c = self._session.run(None, {"input": batch, "h": self._h, "c": self._c})
        self._context = frames[-1, -_CONTEXT:].copy()
        return frames, np.asarray(probs, dtype=np.float32).reshape(k)


class VadEndpointer:
    """Utterance endpointing over per-frame speech probabilities (pure state machine).

    Args:
        config: thresholds and durations.
    """

    def __init__(self, config: VadConfig) -> None:
        self.config = config
        ms = 1000.0 * FRAME / SAMPLE_RATE
        self._pad_frames = int(round(config.speech_pad_ms / ms))
        self._min_silence_frames = max(1, int(np.ceil(config.min_silence_ms / ms)))
        self._min_speech_frames = int(np.ceil(config.min_speech_ms / ms))
        self._max_frames = int(config.max_utterance_s * 1000.0 / ms)
        self._spec_frames = None if config.speculative_ms is None else max(1, int(np.ceil(config.speculative_ms / ms)))
        self._preroll: collections.deque[np.ndarray] = collections.deque(maxlen=max(self._pad_frames, 1))
        self._frame_index = 0  # stream index of the next frame
        self._utterance = 0
        self._active = False
        self._frames: list[np.ndarray] = []  # frames of the current utterance (pre-roll included)
        self._start_frame = 0  # stream frame index of _frames[0]
        self._speech_frames = 0
        self._last_speech = -1  # index in _frames of the last speech frame
        self._last_speech_time = 0.0
        self._silence = 0  # consecutive silent frames after the last speech frame
        self._tentative_sent = False

    @property
    def active(self) -> bool:
        """An utterance is in progress."""
        return self._active

    def _audio(self, upto: int) -> np.ndarray:
        return np.concatenate(self._frames[:upto]) if upto > 0 else np.zeros(0, dtype=np.float32)

    def _final(self, cut: bool) -> list[SegmentEvent]:
        events: list[SegmentEvent] = []
        if self._speech_frames >= self._min_speech_frames:
            upto = min(len(self._frames), self._last_speech + 1 + self._pad_frames)
            events.append(SegmentEvent("final", self._utterance, self._audio(upto), self._last_speech_time,
                                       self._start_frame * FRAME, cut))
        elif self._tentative_sent:
            events.append(SegmentEvent("resume", self._utterance))  # withdraw the tentative end
        tail = self._frames[self._last_speech + 1:] if not cut else []
        self._preroll.clear()
        self._preroll.extend(tail[-self._preroll.maxlen:] if tail else [])
        self._active = False
        self._frames = []
        return events

    def push(self, frames: np.ndarray, probs: np.ndarray, now: float) -> list[SegmentEvent]:
        """Feed frames and their speech probabilities.

        Args:
            frames: ``[k, 512]`` float32 samples.
            probs: ``[k]`` speech probabilities.
            now: clock time at which these frames arrived.

        Returns:
            The events, in order.

        Raises:
            ValueError: shapes do not match.
        """
        if frames.ndim != 2 or frames.shape[1] != FRAME or probs.shape != (frames.shape[0],):
            raise ValueError(f"frames must be [k, {FRAME}] and probs [k], got {frames.shape} and {probs.shape}")
        cfg = self.config
        events: list[SegmentEvent] = []
        for frame, p in zip(frames, probs, strict=True):
            idx = self._frame_index
            self._frame_index += 1
            if not self._active:
                if p >= cfg.threshold:
                    self._utterance += 1
                    self._active = True
                    self._frames = [*self._preroll, frame]
                    self._start_frame = idx - len(self._preroll)
                    self._speech_frames = 1
                    self._last_speech = len(self._frames) - 1
                    self._last_speech_time = now
                    self._silence = 0
                    self._tentative_sent = False
                else:
                    self._preroll.append(frame)
                continue
            self._frames.append(frame)
            speech = p >= cfg.threshold or (p >= cfg.low and self._silence == 0)
            if speech:
                self._speech_frames += 1
                self._last_speech = len(self._frames) - 1
                self._last_speech_time = now
                self._silence = 0
                if self._tentative_sent:
                    self._tentative_sent = False
                    events.append(SegmentEvent("resume", self._utterance))
            else:
                self._silence += 1
                if (self._spec_frames is not None and not self._tentative_sent and self._silence >= self._spec_frames
                        and self._speech_frames >= self._min_speech_frames):
                    self._tentative_sent = True
                    events.append(SegmentEvent("tentative", self._utterance, self._audio(len(self._frames)),
                                               self._last_speech_time, self._start_frame * FRAME))
                if self._silence >= self._min_silence_frames:
                    events += self._final(cut=False)
                    continue
            if len(self._frames) >= self._max_frames:
                if self._tentative_sent:
                    self._tentative_sent = False
                    events.append(SegmentEvent("resume", self._utterance))
                events += self._final(cut=True)
        return events

    def flush(self) -> list[SegmentEvent]:
        """End of stream: finish the utterance in progress, if any."""
        return self._final(cut=False) if self._active else []


class FixedChunker:
    """The seed's behaviour: blind chunks of ``chunk_s`` seconds, each transcribed as it fills.

    Args:
        chunk_s: chunk length in seconds.
        min_tail_s: at the end of the stream, a last partial chunk shorter than this is dropped.
    """

    def __init__(self, chunk_s: float = 5.0, min_tail_s: float = 0.3) -> None:
        if chunk_s <= 0.5:
            raise ConfigError(f"chunk_s must be > 0.5, got {chunk_s}")
        self._size = int(round(chunk_s * SAMPLE_RATE))
        self._min_tail = int(round(min_tail_s * SAMPLE_RATE))
        self._parts: list[np.ndarray] = []
        self._count = 0
        self._start = 0
        self._chunk = 0

    def push(self, audio: np.ndarray, now: float) -> list[SegmentEvent]:
        """Feed ``[n]`` float32 samples that arrived at ``now``; returns one final per full chunk."""
        events: list[SegmentEvent] = []
        while audio.size:
            take = min(audio.size, self._size - self._count)
            self._parts.append(audio[:take])
            self._count += take
            audio = audio[take:]
            if self._count == self._size:
                events.append(self._emit(now))
        return events

    def _emit(self, now: float) -> SegmentEvent:
        self._chunk += 1
        ev = SegmentEvent("final", self._chunk, np.concatenate(self._parts), now, self._start, cut=True)
        self._start += self._count
        self._parts, self._count = [], 0
        return ev

    def flush(self, now: float) -> list[SegmentEvent]:
        """End of stream: the partial last chunk, if long enough."""
        return [self._emit(now)] if self._count >= self._min_tail else []
