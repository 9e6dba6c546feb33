"""The voice pipeline: source → segmenter → Whisper → filter → wake word → command (no ROS).

Threads: the caller's thread runs :meth:`VoicePipeline.run` (reads the source, segments it,
schedules transcriptions); one worker thread transcribes (Whisper never runs twice at once);
one result thread takes finished utterances in order, filters them and calls ``on_result``.

Speculative transcription (VAD mode): when speech pauses for ``speculative_ms`` the audio so far
is handed to Whisper at once; if the pause becomes the end of the utterance (``min_silence_ms``)
that transcript is used, so the silence wait and the transcription overlap. If speech resumes
the speculative transcript is thrown away.
"""

from __future__ import annotations

import json
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field

import numpy as np

from decision_maker.speech.errors import ConfigError
from decision_maker.speech.filtering import FilterConfig, judge
from decision_maker.speech.segmentation import FixedChunker, SegmentEvent, StreamingVad, VadConfig, VadEndpointer
from decision_maker.speech.sources import SAMPLE_RATE, AudioSource
from decision_maker.speech.text import WakeWordGate
from decision_maker.speech.transcriber import Transcript
from decision_maker.speech.vocabulary import Vocabulary

SEGMENTATIONS = ("vad", "fixed")

#: ``transcribe(audio [n] float32, prompt, vad_filter, grammar) -> Transcript`` (Transcriber.transcribe);
#: ``grammar(text) -> bool`` says whether a transcript is a command the vocabulary can form.
TranscribeFn = Callable[[np.ndarray, str, bool, Callable[[str], bool] | None], Transcript]


@dataclass(frozen=True)
class PipelineConfig:
    """Behaviour of the pipeline.

    Attributes:
        segmentation: ``"vad"`` (utterance endpointing) or ``"fixed"`` (the seed's blind chunks).
        vad: endpointing parameters (VAD mode).
        chunk_s: chunk length (fixed mode).
        fixed_vad_filter: in fixed mode, let faster-whisper's VAD drop non-speech in a chunk.
        filter: hallucination filter thresholds.
        wake_word: required wake word; empty = off.
        wake_word_timeout_s: how long a lone wake word opens the gate.
        grammar_rescoring: pass the vocabulary's command grammar to the transcriber, so that a
            transcript outside it can be replaced by an in-grammar beam hypothesis.
    """

    segmentation: str = "vad"
    vad: VadConfig = field(default_factory=VadConfig)
    chunk_s: float = 5.0
    fixed_vad_filter: bool = True
    filter: FilterConfig = field(default_factory=FilterConfig)
    wake_word: str = ""
    wake_word_timeout_s: float = 5.0
    grammar_rescoring: bool = True

    def __post_init__(self) -> None:
        if self.segmentation not in SEGMENTATIONS:
            raise ConfigError(f"segmentation must be one of {SEGMENTATIONS}, got {self.segmentation!r}")


@dataclass(frozen=True)
class Result:
    """One utterance, published or dropped (the status line).

    Attributes:
        command: normalised text to publish on /manual_command, or None when dropped.
        text: normalised transcript (before the wake word is stripped).
        raw: Whisper's text.
        dropped: why nothing was published (filter or wake-word reason), or None.
        confidence: exp(mean token log-probability).
        no_speech_prob: Whisper's no-speech probability.
        avg_logprob: mean token log-probability.
        audio_s: seconds of audio transcribed.
        transcribe_s: wall time of the transcription.
        latency_s: from the arrival of the last speech sample (VAD) or of the chunk's last sample
            (fixed) to this result.
        speculative: the transcript was started before the end of the utterance was confirmed.
        cut: the audio was cut by a chunk boundary or the maximum utterance length.
        mode: segmentation mode.
        utterance: running number.
        rescored_from: Whisper's best text when an in-grammar hypothesis replaced it, else "".
    """

    command: str | None
    text: str
    raw: str
    dropped: str | None
    confidence: float
    no_speech_prob: float
    avg_logprob: float
    audio_s: float
    transcribe_s: float
    latency_s: float
    speculative: bool
    cut: bool
    mode: str
    utterance: int
    rescored_from: str = ""

    def to_json(self) -> str:
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, float):
                d[k] = round(v, 4)
        return json.dumps({"event": "utterance", **d})


_END = object()


class VoicePipeline:
    """Turns an audio stream into commands.

    Args:
        config: behaviour (segmentation, filter, wake word).
        transcribe: the transcription function (``Transcriber.transcribe``).
        vocabulary: initial vocabulary (Whisper's prompt); replace it with :meth:`set_vocabulary`.
        on_result: called from the result thread with every :class:`Result`, in order.
        clock: monotonic clock.
    """

    def __init__(self, config: PipelineConfig, transcribe: TranscribeFn, vocabulary: Vocabulary,
                 on_result: Callable[[Result], None], clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self._transcribe = transcribe
        self._on_result = on_result
        self._clock = clock
        self._lock = threading.Lock()  # guards _vocabulary, _prompt, _prompt_words, _filter, _wake
        self._vocabulary = vocabulary
        self._prompt = vocabulary.prompt()
        self._prompt_words = vocabulary.prompt_words()
        self._filter = config.filter
        self._wake = WakeWordGate(config.wake_word, config.wake_word_timeout_s, clock=clock)
        # Touched only by the thread running run() (created per run):
        self._worker: ThreadPoolExecutor | None = None
        self._results: queue.Queue[object] = queue.Queue()
        self._speculative: dict[int, Future[Transcript]] = {}
        self._inflight: list[Future[Transcript]] = []
        self.speculative_hits = 0
        self.speculative_misses = 0

    # --- run-time settings --------------------------------------------------------------------
    @property
    def vocabulary(self) -> Vocabulary:
        with self._lock:
            return self._vocabulary

    @property
    def prompt(self) -> str:
        with self._lock:
            return self._prompt

    def set_vocabulary(self, vocabulary: Vocabulary) -> None:
        """Use a new vocabulary for the next transcriptions (thread-safe)."""
        with self._lock:
            self._vocabulary = vocabulary
            self._prompt = vocabulary.prompt()
            self._prompt_words = vocabulary.prompt_words()

    def set_filter(self, config: FilterConfig) -> None:
        with self._lock:
            self._filter = config

    def set_wake_word(self, wake_word: str, timeout_s: float) -> None:
        with self._lock:
            self._wake = WakeWordGate(wake_word, timeout_s, clock=self._clock)
            self._vocabulary = Vocabulary(self._vocabulary.command_phrases, self._vocabulary.objects,
                                          self._vocabulary.places, wake_word)
            self._prompt = self._vocabulary.prompt()
            self._prompt_words = self._vocabulary.prompt_words()

    # --- the stream -----------------------------------------------------------------------------
    def run(self, source: AudioSource, stop: threading.Event | None = None) -> None:
        """Read ``source`` until its end (or ``stop``), then finish every pending utterance.

        Blocks the calling thread; results arrive through ``on_result`` meanwhile. Exceptions of
        the source (e.g. AudioDeviceError) propagate after pending work is finished. May be
        called again (with a new source) after it returned.
        """
        stop = stop or threading.Event()
        fixed = self.config.segmentation == "fixed"
        chunker = FixedChunker(self.config.chunk_s) if fixed else None
        vad = None if fixed else StreamingVad()
        endpointer = None if fixed else VadEndpointer(self.config.vad)
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="whisper")
        self._results = queue.Queue()
        self._speculative, self._inflight = {}, []
        result_thread = threading.Thread(target=self._result_loop, args=(self._results,), name="voice-results",
                                         daemon=True)
        result_thread.start()
        try:
            while not stop.is_set():
                block = source.read()
                if block is None:
                    break
                if block.size == 0:
                    continue
                now = self._clock()
                if chunker is not None:
                    events = chunker.push(block, now)
                else:
                    frames, probs = vad.push(block)
                    events = endpointer.push(frames, probs, now) if probs.size else []
                for ev in events:
                    self._handle(ev)
        finally:
            tail = chunker.flush(self._clock()) if chunker is not None else endpointer.flush()
            for ev in tail:
                self._handle(ev)
            self._results.put(_END)
            result_thread.join()
            self._worker.shutdown(wait=True)

    def _submit(self, audio: np.ndarray, vad_filter: bool) -> Future[Transcript]:
        with self._lock:
            prompt = self._prompt
            grammar = self._vocabulary.in_grammar if self.config.grammar_rescoring else None
        if self._worker is None:
            raise RuntimeError("_submit outside run()")
        fut = self._worker.submit(self._transcribe, audio, prompt, vad_filter, grammar)
        self._inflight = [f for f in self._inflight if not f.done()] + [fut]
        return fut

    def _handle(self, ev: SegmentEvent) -> None:
        fixed = self.config.segmentation == "fixed"
        if ev.kind == "tentative":
            idle = all(f.done() for f in self._inflight)
            if idle and ev.audio is not None:
                self._speculative[ev.utterance] = self._submit(ev.audio, False)
        elif ev.kind == "resume":
            fut = self._speculative.pop(ev.utterance, None)
            if fut is not None:
                fut.cancel()
                self.speculative_misses += 1
        elif ev.kind == "final" and ev.audio is not None:
            fut = self._speculative.pop(ev.utterance, None)
            speculative = fut is not None and not fut.cancelled()
            if speculative:
                self.speculative_hits += 1
            else:
                fut = self._submit(ev.audio, fixed and self.config.fixed_vad_filter)
            self._results.put((ev, fut, speculative))

    def _result_loop(self, results: queue.Queue[object]) -> None:
        while True:
            item = results.get()
            if item is _END:
                return
            ev, fut, speculative = item  # type: ignore[misc]
            try:
                tr: Transcript = fut.result()
            except Exception as exc:  # noqa: BLE001 - report, keep listening
                tr = Transcript(f"<transcription failed: {exc}>", -99.0, 1.0, 0.0,
                                ev.audio.size / SAMPLE_RATE, 0.0)
            self._on_result(self._decide(ev, tr, speculative))

    def _decide(self, ev: SegmentEvent, tr: Transcript, speculative: bool) -> Result:
        with self._lock:
            cfg, prompt_words, wake = self._filter, self._prompt_words, self._wake
        verdict = judge(tr.text, tr.no_speech_prob, tr.avg_logprob, tr.compression_ratio, cfg, prompt_words)
        command, dropped = None, verdict.reason
        if verdict.kept:
            decision = wake.process(verdict.text)
            command, dropped = decision.command, decision.reason
        return Result(command=command, text=verdict.text, raw=tr.text, dropped=dropped, confidence=tr.confidence,
                      no_speech_prob=tr.no_speech_prob, avg_logprob=tr.avg_logprob, audio_s=tr.audio_s,
                      transcribe_s=tr.elapsed_s, latency_s=self._clock() - ev.speech_end_time,
                      speculative=speculative, cut=ev.cut, mode=self.config.segmentation, utterance=ev.utterance,
                      rescored_from=tr.rescored_from)
