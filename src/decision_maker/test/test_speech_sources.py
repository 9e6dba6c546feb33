"""Audio sources: WAV files (any PCM format), raw streams, and the PortAudio error path."""

import io
import wave

import numpy as np
import pytest

from decision_maker.speech.errors import AudioDeviceError, AudioSourceError
from decision_maker.speech.sources import (
    PortAudioSource,
    RawStreamSource,
    WavFileSource,
    describe_device_problem,
    list_input_devices,
    open_source,
    resample,
)


def write(path, data: np.ndarray, rate: int, channels: int = 1, width: int = 2):
    with wave.open(str(path), "wb") as wf:
        wf.setnchannels(channels)
        wf.setsampwidth(width)
        wf.setframerate(rate)
        wf.writeframes(data.tobytes())


def read_all(src):
    out = []
    while (b := src.read()) is not None:
        out.append(b)
    return np.concatenate(out)


def test_wav_16k_mono_round_trip(tmp_path):
    pcm = (np.sin(np.arange(16000) / 10) * 10000).astype("<i2")
    write(tmp_path / "a.wav", pcm, 16000)
    src = WavFileSource(str(tmp_path / "a.wav"), pacing=0, block_s=0.032)
    got = read_all(src)
    np.testing.assert_allclose(got, pcm / 32768.0, atol=1e-6)
    assert src.read() is None and src.duration_s == 1.0


def test_wav_stereo_44k_is_mixed_and_resampled(tmp_path):
    t = np.arange(44100) / 44100
    left = (np.sin(2 * np.pi * 440 * t) * 8000).astype("<i2")
    stereo = np.stack([left, left], axis=1).reshape(-1)
    write(tmp_path / "s.wav", stereo, 44100, channels=2)
    got = read_all(WavFileSource(str(tmp_path / "s.wav"), pacing=0))
    assert got.size == 16000
    ref = np.sin(2 * np.pi * 440 * np.arange(16000) / 16000) * 8000 / 32768
    assert np.abs(got[10:-10] - ref[10:-10]).max() < 0.02


def test_wav_errors_are_typed(tmp_path):
    with pytest.raises(AudioSourceError, match="not found"):
        WavFileSource(str(tmp_path / "missing.wav"))
    (tmp_path / "junk.wav").write_bytes(b"not a wav file at all")
    with pytest.raises(AudioSourceError, match="sox"):
        WavFileSource(str(tmp_path / "junk.wav"))
    with pytest.raises(AudioSourceError, match="unknown source"):
        open_source("radio")
    with pytest.raises(AudioSourceError, match="wav_path"):
        open_source("wav")


def test_raw_stream_reads_partial_blocks_until_eof():
    pcm = (np.arange(1000, dtype=np.int16) * 7).astype("<i2")
    src = RawStreamSource(io.BytesIO(pcm.tobytes()), block_s=0.032)  # 512-sample blocks
    blocks = []
    while (b := src.read()) is not None:
        blocks.append(b)
    assert [b.size for b in blocks] == [512, 488]
    np.testing.assert_allclose(np.concatenate(blocks), pcm / 32768.0, atol=1e-6)


def test_raw_stream_at_8k_is_resampled():
    pcm = np.zeros(8000, dtype="<i2")
    got = read_all(RawStreamSource(io.BytesIO(pcm.tobytes()), sample_rate=8000))
    assert got.size == 16000


def test_resample_lengths():
    assert resample(np.zeros(48000, np.float32), 48000).size == 16000
    assert resample(np.zeros(0, np.float32), 8000).size == 0


def test_missing_microphone_is_a_clear_error_not_a_traceback():
    if list_input_devices():
        pytest.skip("this machine has an input device; the missing-device path cannot be exercised")
    with pytest.raises(AudioDeviceError) as err:
        PortAudioSource(None)
    msg = str(err.value)
    assert "cannot open the default input device" in msg or "PortAudio is not installed" in msg
    assert "fix:" in msg
    named = describe_device_problem(RuntimeError("busy"), "USB Mic")
    assert "input device 'USB Mic': busy" in named and "/dev/snd" in named and "arecord -l" in named
