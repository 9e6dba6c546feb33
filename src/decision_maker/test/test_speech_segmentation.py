"""Endpointing and fixed chunks over hand-made probabilities; Silero streaming on real speech."""

import numpy as np
import pytest

from decision_maker.speech import testaudio
from decision_maker.speech.errors import ConfigError
from decision_maker.speech.segmentation import FRAME, FixedChunker, StreamingVad, VadConfig, VadEndpointer

# 32 ms frames: 400 ms silence = 13 frames, 200 ms pad = 6 frames, 100 ms speculative = 4 frames
CFG = VadConfig(threshold=0.5, min_silence_ms=400, speech_pad_ms=200, min_speech_ms=150, max_utterance_s=10,
                speculative_ms=100)


def frames_for(probs):
    """Frames whose first sample encodes the frame index, so spans can be checked."""
    f = np.zeros((len(probs), FRAME), dtype=np.float32)
    f[:, 0] = np.arange(len(probs), dtype=np.float32)
    return f, np.asarray(probs, dtype=np.float32)


def run(endpointer, probs, start_time=0.0):
    frames, p = frames_for(probs)
    events = []
    for i in range(len(p)):  # one frame per call, like a live stream
        events += [(i, e) for e in endpointer.push(frames[i:i + 1], p[i:i + 1], start_time + i)]
    return events


def frame_ids(audio):
    return audio.reshape(-1, FRAME)[:, 0].astype(int).tolist()


def test_one_utterance_tentative_then_final_with_padding():
    probs = [0.0] * 20 + [0.9] * 30 + [0.0] * 20
    events = run(VadEndpointer(CFG), probs)
    kinds = [(i, e.kind) for i, e in events]
    assert kinds == [(53, "tentative"), (62, "final")]  # 4 and 13 silent frames after speech ends at 49
    final = events[1][1]
    assert frame_ids(final.audio) == list(range(14, 56))  # 6 frames of pre-roll, speech, 6 of post-pad
    assert final.speech_end_time == 49.0 and final.start_sample == 14 * FRAME and not final.cut


def test_pause_shorter_than_min_silence_resumes_the_same_utterance():
    probs = [0.0] * 10 + [0.9] * 10 + [0.0] * 8 + [0.9] * 10 + [0.0] * 20
    events = run(VadEndpointer(CFG), probs)
    assert [e.kind for _, e in events] == ["tentative", "resume", "tentative", "final"]
    assert len({e.utterance for _, e in events}) == 1
    final = events[-1][1]
    assert frame_ids(final.audio)[0] == 4 and frame_ids(final.audio)[-1] == 37 + 6


def test_hysteresis_between_thresholds_continues_speech():
    probs = [0.0] * 5 + [0.9] * 10 + [0.4] * 20 + [0.0] * 20  # 0.4 >= low (0.35): still speech
    events = run(VadEndpointer(CFG), probs)
    final = [e for _, e in events if e.kind == "final"][0]
    assert final.speech_end_time == 34.0


def test_short_blip_is_not_an_utterance():
    events = run(VadEndpointer(CFG), [0.0] * 10 + [0.9] * 3 + [0.0] * 30)  # 96 ms < 150 ms
    assert [e.kind for _, e in events] == []


def test_long_speech_is_cut_at_max_utterance():
    cfg = VadConfig(max_utterance_s=2.0, speculative_ms=None)
    events = run(VadEndpointer(cfg), [0.9] * 130 + [0.0] * 20)
    finals = [e for _, e in events if e.kind == "final"]
    assert len(finals) == 3 and finals[0].cut and finals[1].cut and not finals[2].cut
    assert sum(f.audio.size for f in finals[:2]) == 2 * 62 * FRAME  # 2 s = 62 frames each


def test_flush_finishes_the_utterance_in_progress():
    ep = VadEndpointer(CFG)
    run(ep, [0.0] * 5 + [0.9] * 10)
    (final,) = ep.flush()
    assert final.kind == "final" and frame_ids(final.audio) == list(range(0, 15))
    assert ep.flush() == []


def test_shapes_are_checked():
    with pytest.raises(ValueError):
        VadEndpointer(CFG).push(np.zeros((2, 100), np.float32), np.zeros(2, np.float32), 0.0)
    with pytest.raises(ConfigError):
        VadConfig(threshold=1.5)


def test_fixed_chunker_emits_every_chunk_and_the_tail():
    ch = FixedChunker(chunk_s=1.0, min_tail_s=0.3)
    events = []
    for i in range(25):  # 25 × 0.1 s
        events += ch.push(np.full(1600, i, np.float32), float(i))
    assert [e.audio.size for e in events] == [16000, 16000]
    assert [e.start_sample for e in events] == [0, 16000]
    assert events[0].audio[0] == 0 and events[1].audio[0] == 10 and events[0].cut
    (tail,) = ch.flush(99.0)
    assert tail.audio.size == 8000 and tail.start_sample == 32000
    ch2 = FixedChunker(chunk_s=1.0, min_tail_s=0.3)
    ch2.push(np.zeros(1600, np.float32), 0.0)
    assert ch2.flush(1.0) == []  # 0.1 s tail: dropped


@pytest.mark.skipif(bool(testaudio.missing_tools()), reason=f"needs {testaudio.missing_tools()} (apt-get install)")
def test_silero_streaming_equals_offline_and_finds_the_speech():
    from faster_whisper.vad import get_vad_model

    speech = testaudio.speak("give me the bottle")
    stream = np.concatenate([testaudio.silence(1.0), speech, testaudio.silence(1.0)])
    stream = stream[: stream.size // FRAME * FRAME]
    offline = np.asarray(get_vad_model()(stream)).reshape(-1)
    vad = StreamingVad()
    probs = []
    for block in np.array_split(stream, 37):  # odd block sizes: frames straddle blocks
        probs.append(vad.push(block)[1])
    streamed = np.concatenate(probs)
    assert streamed.shape == offline.shape
    np.testing.assert_allclose(streamed, offline, atol=1e-4)
    speech_frames = np.flatnonzero(streamed >= 0.5)
    start_s, end_s = speech_frames[0] * FRAME / 16000, (speech_frames[-1] + 1) * FRAME / 16000
    assert 0.9 <= start_s <= 1.15 and abs(end_s - (1.0 + speech.size / 16000)) < 0.25
