"""A WAV reader for what recorders and sox write: PCM 8/16/24/32-bit and IEEE float 32/64-bit,
plain or ``WAVE_FORMAT_EXTENSIBLE`` (no ROS, numpy only).

Python's :mod:`wave` reads plain PCM only; ``sox in.wav -b 24 out.wav``, ``sox ... -e floating-point``
and most recorders write ``WAVE_FORMAT_EXTENSIBLE`` (format tag 0xFFFE, the real format in a
sub-format GUID) or IEEE float (tag 3). This module walks the RIFF chunks itself.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from decision_maker.speech.errors import AudioSourceError

WAVE_FORMAT_PCM = 0x0001
WAVE_FORMAT_IEEE_FLOAT = 0x0003
WAVE_FORMAT_EXTENSIBLE = 0xFFFE
#: Tail of the KSDATAFORMAT_SUBTYPE_* GUIDs: the first two bytes are the format tag.
_GUID_TAIL = bytes.fromhex("000000001000800000aa00389b71")
_FORMAT_NAMES = {0x0002: "Microsoft ADPCM", 0x0006: "A-law", 0x0007: "mu-law", 0x0011: "IMA ADPCM",
                 0x0055: "MP3", 0x0031: "GSM 6.10"}
_CONVERT_HINT = "convert with: sox in.wav -r 16000 -c 1 -b 16 out.wav"


@dataclass(frozen=True)
class WavInfo:
    """The format of a WAV file.

    Attributes:
        sample_rate: frames per second.
        channels: interleaved channels.
        bits: bits per sample as stored (container width: 8, 16, 24, 32 or 64).
        encoding: ``"pcm"`` (signed integers; unsigned for 8 bits) or ``"float"``.
        frames: number of frames read.
    """

    sample_rate: int
    channels: int
    bits: int
    encoding: str
    frames: int


#: Sample rates a WAV file may declare (Hz): telephone 8 kHz down to 1 kHz, studio 768 kHz at most; a header outside
#: this is broken, and resampling it to 16 kHz would take gigabytes
MIN_RATE, MAX_RATE = 1000, 768_000

def _decode(raw: bytes, bits: int, encoding: str) -> np.ndarray:
    """Little-endian samples → float32 in [-1, 1] (``[n]``, channels still interleaved)."""
    if encoding == "float":
        return np.frombuffer(raw, dtype="<f4" if bits == 32 else "<f8").astype(np.float32)
    if bits == 8:
        return (np.frombuffer(raw, dtype=np.uint8).astype(np.float32) - 128.0) / 128.0
    if bits == 16:
        return np.frombuffer(raw, dtype="<i2").astype(np.float32) / 32768.0
    if bits == 24:
        b = np.frombuffer(raw, dtype=np.uint8).reshape(-1, 3).astype(np.int32)  # [n, 3] little-endian bytes
        v = b[:, 0] | (b[:, 1] << 8) | (b[:, 2] << 16)
        v = np.where(v >= 1 << 23, v - (1 << 24), v)  # sign-extend
        return v.astype(np.float32) / 8388608.0
    return (np.frombuffer(raw, dtype="<i4").astype(np.float64) / 2147483648.0).astype(np.float32)


def read_wav_file(path: str) -> tuple[np.ndarray, WavInfo]:
    """Read a WAV file into mono float32.

    Args:
        path: the file.

    Returns:
        ``(samples [frames] float32 in [-1, 1] (channels averaged), info)``. Non-finite float
        samples become 0; float samples beyond ±1 are kept as written.

    Raises:
        AudioSourceError: missing or unreadable file, not RIFF/WAVE, or a format this reader does
            not decode (the message names the format and how to convert it).
    """
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except FileNotFoundError as exc:
        raise AudioSourceError(f"WAV file not found: {path}") from exc
    except OSError as exc:
        raise AudioSourceError(f"cannot read WAV file {path}: {exc}") from exc
    if len(data) < 12 or data[:4] not in (b"RIFF", b"RIFX", b"RF64") or data[8:12] != b"WAVE":
        what = "RIFX (big-endian)" if data[:4] == b"RIFX" else "not a RIFF/WAVE file"
        raise AudioSourceError(f"cannot read WAV file {path}: {what} ({_CONVERT_HINT})")
    if data[:4] != b"RIFF":
        raise AudioSourceError(f"cannot read WAV file {path}: {data[:4].decode('ascii')} files are not supported "
                               f"({_CONVERT_HINT})")
    fmt: bytes | None = None
    payload: bytes | None = None
    pos = 12
    while pos + 8 <= len(data):
        cid, size = data[pos:pos + 4], struct.unpack_from("<I", data, pos + 4)[0]
        body = data[pos + 8:pos + 8 + size]  # a streamed file may claim more than it holds: take what is there
        if cid == b"fmt ":
            fmt = body
        elif cid == b"data":
            payload = body
            if fmt is not None:
                break
        pos += 8 + size + (size & 1)  # chunks are padded to an even length
    if fmt is None or len(fmt) < 16:
        raise AudioSourceError(f"cannot read WAV file {path}: no valid 'fmt ' chunk ({_CONVERT_HINT})")
    if payload is None:
        raise AudioSourceError(f"cannot read WAV file {path}: no 'data' chunk")
    tag, channels, rate, _byte_rate, block_align, bits = struct.unpack_from("<HHIIHH", fmt, 0)
    if tag == WAVE_FORMAT_EXTENSIBLE:
        if len(fmt) < 40:
            raise AudioSourceError(f"cannot read WAV file {path}: WAVE_FORMAT_EXTENSIBLE 'fmt ' chunk is "
                                   f"{len(fmt)} bytes, expected 40")
        guid = fmt[24:40]
        if guid[2:] != _GUID_TAIL:
            raise AudioSourceError(f"cannot read WAV file {path}: unknown WAVE_FORMAT_EXTENSIBLE sub-format "
                                   f"{guid.hex()} ({_CONVERT_HINT})")
        tag = struct.unpack_from("<H", guid, 0)[0]
    if tag == WAVE_FORMAT_PCM and bits in (8, 16, 24, 32):
        encoding = "pcm"
    elif tag == WAVE_FORMAT_IEEE_FLOAT and bits in (32, 64):
        encoding = "float"
    else:
        name = {WAVE_FORMAT_PCM: "PCM", WAVE_FORMAT_IEEE_FLOAT: "IEEE float"}.get(tag) or _FORMAT_NAMES.get(
            tag, f"format tag 0x{tag:04x}")
        raise AudioSourceError(f"cannot read WAV file {path}: {name} with {bits} bits per sample is not supported "
                               f"(supported: PCM 8/16/24/32-bit, IEEE float 32/64-bit; {_CONVERT_HINT})")
    if not MIN_RATE <= rate <= MAX_RATE:
        raise AudioSourceError(f"cannot read WAV file {path}: a sample rate of {rate} Hz (a recording is "
                               f"{MIN_RATE}-{MAX_RATE} Hz; {_CONVERT_HINT})")
    if channels < 1 or block_align != channels * bits // 8:
        raise AudioSourceError(f"cannot read WAV file {path}: inconsistent header ({channels} channel(s), {rate} Hz, "
                               f"block align {block_align} for {bits}-bit samples)")
    frames = len(payload) // block_align
    samples = _decode(payload[:frames * block_align], bits, encoding)  # [frames * channels]
    if encoding == "float" and not np.isfinite(samples).all():
        samples = np.where(np.isfinite(samples), samples, np.float32(0.0))
    if channels > 1:
        samples = samples.reshape(frames, channels).mean(axis=1)
    return samples.astype(np.float32, copy=False), WavInfo(rate, channels, bits, encoding, frames)
