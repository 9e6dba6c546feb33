"""WAV formats that recorders and sox write, read back against the 16-bit original (no ROS).

The files are made by the real ``sox`` (Debian package), as a user would: ``sox in.wav -b 24 out.wav``,
``sox in.wav -e floating-point out.wav``; the float ``WAVE_FORMAT_EXTENSIBLE`` file, which sox does
not write, is built from sox's float file by rewriting its header the way libsndfile writes it.
"""

from __future__ import annotations

import shutil
import struct
import subprocess

import numpy as np
import pytest

from decision_maker.speech.errors import AudioSourceError
from decision_maker.speech.sources import WavFileSource
from decision_maker.speech.wavfile import WAVE_FORMAT_EXTENSIBLE, read_wav_file

pytestmark = pytest.mark.skipif(shutil.which("sox") is None, reason="needs sox (apt-get install sox)")


def sox(*args: str) -> None:
    subprocess.run(["sox", *args], check=True, capture_output=True, timeout=60)


def format_tag(path) -> int:
    with open(path, "rb") as fh:
        head = fh.read(22)
    return struct.unpack_from("<H", head, 20)[0]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """A 16 kHz mono 16-bit sox file (a chirp at half scale) and its samples."""
    path = tmp_path_factory.mktemp("wav") / "ref.wav"
    sox("-n", "-r", "16000", "-c", "1", "-b", "16", str(path), "synth", "0.5", "sine", "200-3000", "vol", "0.5")
    samples, info = read_wav_file(str(path))
    assert (info.sample_rate, info.channels, info.bits, info.encoding) == (16000, 1, 16, "pcm")
    assert info.frames == 8000 and 0.4 < np.abs(samples).max() < 0.51  # sox dithers
    return path, samples


@pytest.mark.parametrize(("args", "bits", "encoding", "extensible", "atol"), [
    (("-b", "24"), 24, "pcm", True, 1e-6),
    (("-b", "32"), 32, "pcm", True, 1e-6),
    (("-e", "floating-point", "-b", "32"), 32, "float", False, 1e-6),
    (("-e", "floating-point", "-b", "64"), 64, "float", False, 1e-6),
    (("-b", "8"), 8, "pcm", False, 2.0 / 128 + 1e-6),  # quantisation + sox dither
])
def test_sox_formats_read_like_the_16_bit_original(reference, tmp_path, args, bits, encoding, extensible, atol):
    ref_path, ref = reference
    out = tmp_path / "out.wav"
    sox(str(ref_path), *args, str(out))
    assert (format_tag(out) == WAVE_FORMAT_EXTENSIBLE) == extensible  # what sox really writes
    got, info = read_wav_file(str(out))
    assert (info.bits, info.encoding, info.frames, info.sample_rate) == (bits, encoding, 8000, 16000)
    np.testing.assert_allclose(got, ref, atol=atol)


def test_24_bit_stereo_44k_through_the_source(reference, tmp_path):
    ref_path, ref = reference
    out = tmp_path / "s24.wav"
    sox(str(ref_path), "-r", "44100", "-c", "2", "-b", "24", str(out))
    src = WavFileSource(str(out), pacing=0)
    assert src.info.channels == 2 and src.info.bits == 24
    assert abs(src.audio.size - ref.size) <= 2
    n = min(src.audio.size, ref.size)
    assert np.corrcoef(src.audio[:n], ref[:n])[0, 1] > 0.99


def test_float_wave_format_extensible(reference, tmp_path):
    """IEEE float inside WAVE_FORMAT_EXTENSIBLE (libsndfile/Audacity write this)."""
    ref_path, ref = reference
    plain = tmp_path / "f32.wav"
    sox(str(ref_path), "-e", "floating-point", "-b", "32", str(plain))
    payload = read_data_chunk(plain)
    guid = struct.pack("<H", 3) + bytes.fromhex("000000001000800000aa00389b71")
    fmt = struct.pack("<HHIIHHHHI", WAVE_FORMAT_EXTENSIBLE, 1, 16000, 64000, 4, 32, 22, 32, 4) + guid
    body = b"WAVE" + b"fmt " + struct.pack("<I", len(fmt)) + fmt + b"data" + struct.pack("<I", len(payload)) + payload
    ext = tmp_path / "f32ext.wav"
    ext.write_bytes(b"RIFF" + struct.pack("<I", len(body)) + body)
    got, info = read_wav_file(str(ext))
    assert info.encoding == "float" and info.bits == 32
    np.testing.assert_allclose(got, ref, atol=1e-6)


def read_data_chunk(path) -> bytes:
    data = path.read_bytes()
    pos = 12
    while pos + 8 <= len(data):
        cid, size = data[pos:pos + 4], struct.unpack_from("<I", data, pos + 4)[0]
        if cid == b"data":
            return data[pos + 8:pos + 8 + size]
        pos += 8 + size + (size & 1)
    raise AssertionError("no data chunk")


@pytest.mark.parametrize(("encoding", "name"), [("a-law", "A-law"), ("u-law", "mu-law"),
                                                ("ms-adpcm", "Microsoft ADPCM"), ("ima-adpcm", "IMA ADPCM")])
def test_unsupported_encodings_get_a_clear_error(reference, tmp_path, encoding, name):
    ref_path, _ = reference
    out = tmp_path / "x.wav"
    sox(str(ref_path), "-e", encoding, str(out))
    with pytest.raises(AudioSourceError, match=rf"{name} with \d+ bits per sample is not supported.*sox in.wav"):
        WavFileSource(str(out), pacing=0)


def test_truncated_and_broken_files(reference, tmp_path):
    ref_path, ref = reference
    data = ref_path.read_bytes()
    cut = tmp_path / "cut.wav"
    cut.write_bytes(data[:-1001])  # a recorder killed mid-write: the header claims more than is there
    got, info = read_wav_file(str(cut))
    assert info.frames == 8000 - 501
    np.testing.assert_allclose(got, ref[:info.frames], atol=1e-6)
    (tmp_path / "nofmt.wav").write_bytes(b"RIFF\x04\x00\x00\x00WAVE")
    with pytest.raises(AudioSourceError, match="no valid 'fmt ' chunk"):
        read_wav_file(str(tmp_path / "nofmt.wav"))
    (tmp_path / "text.wav").write_bytes(b"hello, this is not audio")
    with pytest.raises(AudioSourceError, match="not a RIFF/WAVE file"):
        read_wav_file(str(tmp_path / "text.wav"))
    with pytest.raises(AudioSourceError, match="not found"):
        read_wav_file(str(tmp_path / "missing.wav"))


@pytest.mark.parametrize("rate", [1, 999, 768_001, 4_294_967_295])
def test_a_header_with_a_sample_rate_no_recording_has_is_refused(reference, tmp_path, rate):
    """A header claiming 1 Hz asked the resampler for 24 GB (the audio thread died and the node ran on, deaf); one
    claiming 4.3 GHz played nothing, silently."""
    import struct

    data = bytearray(reference[0].read_bytes())
    at = data.index(b"fmt ") + 12  # the sample rate: after the chunk id, size, format tag and channel count
    data[at:at + 4] = struct.pack("<I", rate)
    (tmp_path / "rate.wav").write_bytes(bytes(data))
    with pytest.raises(AudioSourceError, match=f"a sample rate of {rate} Hz \\(a recording is 1000-768000 Hz"):
        read_wav_file(str(tmp_path / "rate.wav"))


def test_a_wav_file_without_samples_is_said_not_played_as_silence(reference, tmp_path):
    from decision_maker.speech.sources import WavFileSource

    data = bytearray(reference[0].read_bytes())
    at = data.index(b"data")
    empty = data[:at] + b"data" + (0).to_bytes(4, "little")
    (tmp_path / "empty.wav").write_bytes(bytes(empty))
    with pytest.raises(AudioSourceError, match="holds no audio samples"):
        WavFileSource(str(tmp_path / "empty.wav"))
