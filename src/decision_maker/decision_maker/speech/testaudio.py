"""Real test audio: commands spoken by espeak-ng, noise made by sox (used by tests and bench/).

Both are Debian packages (``apt-get install espeak-ng sox``); :func:`missing_tools` says which
are absent so callers can skip with a clear reason.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import wave
from dataclasses import dataclass

import numpy as np

from decision_maker.speech.sources import SAMPLE_RATE, pcm_to_float

#: espeak-ng voices and speeds (words per minute) the tests use.
VOICES: tuple[tuple[str, int], ...] = (("en-us", 170), ("en+m3", 140), ("en+f2", 170), ("en-us", 140))


def missing_tools() -> list[str]:
    """Names of the command-line tools this module needs that are not installed."""
    return [t for t in ("espeak-ng", "sox") if shutil.which(t) is None]


def _run(cmd: list[str]) -> None:
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)


def read_wav(path: str) -> np.ndarray:
    """``[n]`` float32 mono samples of a 16 kHz 16-bit WAV file."""
    with wave.open(path, "rb") as wf:
        if wf.getframerate() != SAMPLE_RATE:
            raise ValueError(f"{path}: {wf.getframerate()} Hz, expected {SAMPLE_RATE}")
        return pcm_to_float(wf.readframes(wf.getnframes()), wf.getsampwidth(), wf.getnchannels())


def write_wav(path: str, audio: np.ndarray) -> None:
    """Write ``[n]`` float32 samples as a 16 kHz mono 16-bit WAV file."""
    pcm = (np.clip(audio, -1.0, 1.0) * 32767.0).astype("<i2")
    with wave.open(path, "wb") as wf:
        wf.setnchannels(1)
        wf.setsampwidth(2)
        wf.setframerate(SAMPLE_RATE)
        wf.writeframes(pcm.tobytes())


def speak(text: str, voice: str = "en-us", speed: int = 170) -> np.ndarray:
    """``text`` spoken by espeak-ng, 16 kHz mono, leading and trailing silence trimmed.

    Returns:
        ``[n]`` float32 samples; the last sample is the end of speech.
    """
    with tempfile.TemporaryDirectory(prefix="voice_") as tmp:
        raw, out = os.path.join(tmp, "raw.wav"), os.path.join(tmp, "out.wav")
        _run(["espeak-ng", "-v", voice, "-s", str(speed), "-w", raw, text])
        _run(["sox", "-R", raw, "-r", str(SAMPLE_RATE), "-c", "1", "-b", "16", out,  # -R: repeatable dither
              "silence", "1", "0.02", "0.5%", "reverse", "silence", "1", "0.02", "0.5%", "reverse"])
        return read_wav(out)


def noise(kind: str, seconds: float, amplitude: float, seed: int = 1) -> np.ndarray:
    """Noise from sox (``pinknoise``, ``whitenoise``, ``brownnoise``) at ``amplitude`` (peak scale)."""
    with tempfile.TemporaryDirectory(prefix="voice_") as tmp:
        out = os.path.join(tmp, "noise.wav")
        _run(["sox", "-R", "-n", "-r", str(SAMPLE_RATE), "-c", "1", "-b", "16", out, "synth", f"{seconds:.3f}", kind,
              "vol", f"{amplitude}"])
        if seed != 1:  # a different stretch of noise: rotate deterministically
            a = read_wav(out)
            return np.roll(a, seed * 7919)
        return read_wav(out)


def silence(seconds: float) -> np.ndarray:
    return np.zeros(int(round(seconds * SAMPLE_RATE)), dtype=np.float32)


@dataclass(frozen=True)
class Utterance:
    """A command placed in a composed stream: ``text`` spoken in samples [start, end)."""

    text: str
    start: int
    end: int


def compose(parts: list[tuple[str | None, np.ndarray]], background: np.ndarray | None = None
            ) -> tuple[np.ndarray, list[Utterance]]:
    """Concatenate pieces of audio; pieces with a text are utterances.

    Args:
        parts: ``(text or None, [n] float32)`` in order.
        background: optional noise added under the whole stream (tiled to length).

    Returns:
        ``([N] float32 stream, utterances with their sample spans)``.
    """
    out: list[np.ndarray] = []
    utts: list[Utterance] = []
    pos = 0
    for text, audio in parts:
        if text is not None:
            utts.append(Utterance(text, pos, pos + audio.size))
        out.append(audio.astype(np.float32))
        pos += audio.size
    stream = np.concatenate(out) if out else np.zeros(0, dtype=np.float32)
    if background is not None and background.size:
        stream = stream + np.resize(background, stream.size)
    return stream, utts
