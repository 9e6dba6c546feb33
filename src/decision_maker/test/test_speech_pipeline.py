"""The pipeline's scheduling (speculative transcription, order, end of stream) with real VAD on
espeak audio and a stand-in transcriber that reports what audio it was given."""

import threading
import time

import numpy as np
import pytest

from decision_maker.speech import testaudio as ta
from decision_maker.speech.pipeline import PipelineConfig, VoicePipeline
from decision_maker.speech.segmentation import VadConfig
from decision_maker.speech.sources import WavFileSource
from decision_maker.speech.transcriber import Transcript
from decision_maker.speech.vocabulary import Vocabulary

from .voice_testing import MISSING, SKIP_REASON

pytestmark = pytest.mark.skipif(bool(MISSING), reason=SKIP_REASON)


class EchoTranscriber:
    """Returns "heard N ms" for the audio it gets; can be slowed down to keep the worker busy."""

    def __init__(self, delay_s: float = 0.0) -> None:
        self.delay_s = delay_s
        self.lock = threading.Lock()  # guards calls
        self.calls: list[tuple[int, str]] = []

    def __call__(self, audio: np.ndarray, prompt: str, vad_filter: bool, grammar=None) -> Transcript:  # noqa: ANN001
        with self.lock:
            self.calls.append((audio.size, prompt))
        threading.Event().wait(self.delay_s)
        return Transcript(f"heard {audio.size * 1000 // 16000} ms", -0.2, 0.01, 1.0, audio.size / 16000, self.delay_s)


class GatedEchoTranscriber(EchoTranscriber):
    """An EchoTranscriber whose calls wait for ``gate`` (deadline 60 s)."""

    def __init__(self, gate: threading.Event) -> None:
        super().__init__()
        self.gate = gate

    def __call__(self, audio: np.ndarray, prompt: str, vad_filter: bool, grammar=None) -> Transcript:  # noqa: ANN001
        assert self.gate.wait(60.0), "the stream was never read to its end"
        return super().__call__(audio, prompt, vad_filter, grammar)


class HoldingSource:
    """Wraps a source; holds back the samples from ``at`` on until ``ready()`` (deadline 60 s)."""

    def __init__(self, inner: WavFileSource, at: int, ready) -> None:  # noqa: ANN001
        self.inner, self.at, self.ready, self.name = inner, at, ready, inner.name
        self.pos = 0

    def read(self) -> np.ndarray | None:
        if self.pos >= self.at:
            deadline = time.monotonic() + 60.0
            while not self.ready():
                assert time.monotonic() < deadline, "held stream: condition never met"
                threading.Event().wait(0.01)
        block = self.inner.read()
        if block is not None:
            self.pos += block.size
        return block

    def close(self) -> None:
        self.inner.close()


class EndSignallingSource:
    """Wraps a source; sets ``event`` when it reports the end of the stream."""

    def __init__(self, inner: WavFileSource, event: threading.Event) -> None:
        self.inner, self.event, self.name = inner, event, inner.name

    def read(self) -> np.ndarray | None:
        block = self.inner.read()
        if block is None:
            self.event.set()
        return block

    def close(self) -> None:
        self.inner.close()


def make_wav(tmp_path, parts):
    stream, utts = ta.compose(parts)
    path = str(tmp_path / "s.wav")
    ta.write_wav(path, stream)
    return path, utts


def test_speculative_transcripts_are_used_and_withdrawn_on_resume(tmp_path):
    # "go home" twice with a 250 ms pause (< 400 ms min silence): one utterance, so the tentative
    # transcript started at the pause must be thrown away and the whole utterance transcribed.
    go = ta.speak("go home", "en-us", 170)
    path, utts = make_wav(tmp_path, [(None, ta.silence(0.5)), ("go home", go), (None, ta.silence(1.0)),
                                     ("go home go home", go), (None, ta.silence(0.25)), (None, go),
                                     (None, ta.silence(1.0))])
    results, fake = [], EchoTranscriber()
    pipe = VoicePipeline(PipelineConfig(vad=VadConfig(min_silence_ms=400, speculative_ms=100)), fake,
                         Vocabulary(), results.append)
    # the second utterance is read only once the first is transcribed: the worker is idle at its
    # pause whatever the load (a paced stream alone does not guarantee that on a busy machine)
    pipe.run(HoldingSource(WavFileSource(path, pacing=4.0), utts[1].start, lambda: len(results) >= 1))
    assert len(results) == 2, [r.to_json() for r in results]
    first_ms, second_ms = (int(r.command.split()[1]) for r in results)
    go_ms = go.size * 1000 // 16000
    assert go_ms < first_ms < go_ms + 450  # one "go home" plus pads
    assert 2 * go_ms + 250 <= second_ms < 2 * go_ms + 250 + 450  # both halves, not the tentative part
    assert results[0].speculative and pipe.speculative_hits >= 1 and pipe.speculative_misses >= 1
    assert all(prompt == Vocabulary().prompt() for _, prompt in fake.calls)


def test_busy_worker_gets_no_speculative_work_and_order_is_kept(tmp_path):
    parts = [(None, ta.silence(0.3))]
    for text in ("stop", "go home", "cancel", "clean table"):
        parts += [(text, ta.speak(text, "en-us", 170)), (None, ta.silence(0.6))]
    path, utts = make_wav(tmp_path, parts)
    # the worker stays busy until the whole stream is read (a gate, not a delay: on a loaded
    # machine reading can be slower than any fixed transcription delay)
    end_of_stream = threading.Event()
    results, fake = [], GatedEchoTranscriber(end_of_stream)
    source = EndSignallingSource(WavFileSource(path, pacing=0), end_of_stream)
    VoicePipeline(PipelineConfig(), fake, Vocabulary(), results.append).run(source)
    assert [r.utterance for r in results] == [1, 2, 3, 4]
    # tentative ends after the first find the worker busy, so nothing is transcribed twice
    assert len(fake.calls) <= len(utts) + 1


def test_vocabulary_update_reaches_the_next_transcription(tmp_path):
    path, _ = make_wav(tmp_path, [(None, ta.silence(0.3)), ("stop", ta.speak("stop")), (None, ta.silence(0.8))])
    fake = EchoTranscriber()
    pipe = VoicePipeline(PipelineConfig(), fake, Vocabulary(), lambda r: None)
    pipe.set_vocabulary(Vocabulary().with_objects(["teapot"]))
    pipe.run(WavFileSource(path, pacing=0))
    assert fake.calls and all("teapot" in prompt for _, prompt in fake.calls)
