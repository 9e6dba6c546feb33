"""Audio sources: PortAudio microphone, WAV file, raw stdin stream — all as 16 kHz mono float32.

Every source has ``read() -> np.ndarray | None``: the next block of samples (``[n]`` float32 in
[-1, 1] at :data:`SAMPLE_RATE`), an empty block when nothing arrived within its timeout, and
None at the end of the stream. Blocks are returned when their audio has "happened": a WAV file
is paced at ``pacing`` × real time (0 = as fast as it can be read), stdin at the writer's pace,
a microphone at the speaker's.
"""

from __future__ import annotations

import glob
import os
import queue
import shutil
import subprocess
import time
from typing import BinaryIO, Protocol

import numpy as np

from decision_maker.speech.errors import AudioDeviceError, AudioSourceError
from decision_maker.speech.wavfile import read_wav_file

SAMPLE_RATE = 16000


class AudioSource(Protocol):
    """What the pipeline reads audio from."""

    name: str

    def read(self) -> np.ndarray | None:
        """Next block (``[n]`` float32, 16 kHz mono); empty = nothing yet; None = end of stream."""

    def close(self) -> None:
        """Release the device/file; idempotent."""


def resample(audio: np.ndarray, rate: int, target: int = SAMPLE_RATE) -> np.ndarray:
    """Linear-interpolation resampling (good enough for speech into Whisper's 16 kHz).

    Args:
        audio: ``[n]`` float32 samples at ``rate``.
        rate: their sample rate (Hz).
        target: wanted rate (Hz).

    Returns:
        ``[round(n * target / rate)]`` float32 samples.
    """
    if rate == target or audio.size == 0:
        return audio.astype(np.float32, copy=False)
    n_out = int(round(audio.size * target / rate))
    x_out = np.arange(n_out, dtype=np.float64) * (rate / target)
    return np.interp(x_out, np.arange(audio.size, dtype=np.float64), audio).astype(np.float32)


def pcm_to_float(raw: bytes, sample_width: int, channels: int) -> np.ndarray:
    """Interleaved PCM bytes → ``[frames]`` float32 mono (channels averaged).

    Raises:
        AudioSourceError: unsupported sample width.
    """
    if sample_width == 2:
        data = np.frombuffer(raw, dtype="<i2").astype(np.float32) / 32768.0
    elif sample_width == 4:
        data = np.frombuffer(raw, dtype="<i4").astype(np.float32) / 2147483648.0
    elif sample_width == 1:
        data = (np.frombuffer(raw, dtype=np.uint8).astype(np.float32) - 128.0) / 128.0
    else:
        raise AudioSourceError(f"unsupported PCM sample width {sample_width} bytes (use 8, 16 or 32-bit PCM)")
    if channels > 1:
        data = data[: data.size // channels * channels].reshape(-1, channels).mean(axis=1)
    return data


class WavFileSource:
    """A WAV file, paced like a live stream.

    Args:
        path: the WAV file: PCM 8/16/24/32-bit or IEEE float 32/64-bit, plain or
            ``WAVE_FORMAT_EXTENSIBLE`` (:mod:`decision_maker.speech.wavfile`), any rate, any
            channel count.
        pacing: speed relative to real time (1.0 = real time, 4.0 = four times faster,
            0 = as fast as possible).
        block_s: block length in seconds.

    Raises:
        AudioSourceError: missing or unreadable file, a WAV format that is not supported, or a file without samples
            (nothing to listen to: said, not played as silence).
    """

    def __init__(self, path: str, pacing: float = 1.0, block_s: float = 0.032) -> None:
        if pacing < 0:
            raise AudioSourceError(f"pacing must be >= 0, got {pacing}")
        self.name = f"wav:{path}"
        samples, self.info = read_wav_file(path)  # [n] float32 mono at info.sample_rate
        if len(samples) == 0:
            raise AudioSourceError(f"WAV file {path} holds no audio samples (its data chunk is empty)")
        self.audio = resample(samples, self.info.sample_rate)  # [n] float32, 16 kHz
        self.pacing = pacing
        self.block = max(1, int(round(block_s * SAMPLE_RATE)))
        self._pos = 0
        self._t0: float | None = None

    @property
    def duration_s(self) -> float:
        return self.audio.size / SAMPLE_RATE

    def read(self) -> np.ndarray | None:
        if self._pos >= self.audio.size:
            return None
        end = min(self._pos + self.block, self.audio.size)
        if self.pacing > 0:
            if self._t0 is None:
                self._t0 = time.monotonic()
            due = self._t0 + end / SAMPLE_RATE / self.pacing
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        block = self.audio[self._pos:end]
        self._pos = end
        return block

    def close(self) -> None:
        self._pos = self.audio.size


class RawStreamSource:
    """Raw signed 16-bit little-endian mono PCM from a byte stream (stdin by default).

    ``arecord -f S16_LE -r 16000 -c 1 -t raw | audio_command_node --ros-args -p source:=stdin``
    or ``sox in.wav -t raw -r 16000 -c 1 -b 16 -e signed - | ...``.

    Args:
        stream: binary stream; None = the process's stdin.
        sample_rate: rate of the incoming samples (resampled to 16 kHz).
        block_s: block length in seconds.
    """

    def __init__(self, stream: BinaryIO | None = None, sample_rate: int = SAMPLE_RATE, block_s: float = 0.032) -> None:
        import sys

        self.name = "stdin"
        self._stream = stream if stream is not None else sys.stdin.buffer
        if sample_rate <= 0:
            raise AudioSourceError(f"sample_rate must be > 0, got {sample_rate}")
        self.sample_rate = sample_rate
        self._nbytes = 2 * max(1, int(round(block_s * sample_rate)))
        self._eof = False

    def read(self) -> np.ndarray | None:
        if self._eof:
            return None
        chunks: list[bytes] = []
        got = 0
        while got < self._nbytes:
            data = self._stream.read(self._nbytes - got)
            if not data:
                self._eof = True
                break
            chunks.append(data)
            got += len(data)
        raw = b"".join(chunks)
        raw = raw[: len(raw) // 2 * 2]
        if not raw:
            return None
        return resample(pcm_to_float(raw, 2, 1), self.sample_rate)

    def close(self) -> None:
        self._eof = True


def _import_sounddevice():  # noqa: ANN202 - the module
    try:
        import sounddevice
    except OSError as exc:  # the PortAudio shared library is missing
        raise AudioDeviceError(
            f"PortAudio is not installed ({exc}).\n"
            "  fix: install it, e.g. `sudo apt-get install libportaudio2`, or use a WAV/stdin source "
            "(source:=wav wav_path:=FILE, or source:=stdin)"
        ) from exc
    return sounddevice


def list_input_devices() -> list[str]:
    """``"index: name (channels, default rate)"`` of every PortAudio input device ([] if none)."""
    try:
        sd = _import_sounddevice()
        devices = sd.query_devices()
    except Exception:  # noqa: BLE001 - best effort inside an error message
        return []
    return [f"{d['index']}: {d['name']} ({d['max_input_channels']} ch, {d['default_samplerate']:.0f} Hz)"
            for d in devices if d.get("max_input_channels", 0) > 0]


def sound_device_holders() -> str:
    """Which processes hold ``/dev/snd/*`` (``fuser -v``), or why that is unknown."""
    nodes = sorted(glob.glob("/dev/snd/*"))
    if not nodes:
        return "no /dev/snd on this machine: no sound card is visible (in a container: run it with --device /dev/snd)"
    if shutil.which("fuser") is None:
        return "install psmisc (`fuser`) to see which process holds /dev/snd"
    try:
        out = subprocess.run(["fuser", "-v", *nodes], capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"fuser failed: {exc}"
    text = (out.stdout + out.stderr).strip()
    return text if text else "no process holds /dev/snd right now"


def describe_device_problem(exc: BaseException, device: str | int | None) -> str:
    """A message saying what is wrong with the input device and how to fix it."""
    devices = list_input_devices()
    which = "the default input device" if device in (None, "") else f"input device {device!r}"
    lines = [f"cannot open {which}: {exc}"]
    lines.append("  input devices: " + ("; ".join(devices) if devices else "none found"))
    lines.append("  holders of /dev/snd: " + sound_device_holders().replace("\n", "\n    "))
    lines.append("  fix: close programs that hold the microphone (video calls, another audio_command_node, "
                 "arecord); list devices with `python -m sounddevice` or `arecord -l`; pick one with "
                 "-p input_device:=NAME_OR_INDEX; or use -p source:=wav -p wav_path:=FILE / -p source:=stdin")
    return "\n".join(lines)


class PortAudioSource:
    """The default microphone or a named input device, through PortAudio (``sounddevice``).

    Args:
        device: device name (substring) or index; empty/None = the default input device.
        block_s: block length in seconds.
        timeout_s: how long :meth:`read` waits for a block before returning an empty one.

    Raises:
        AudioDeviceError: PortAudio missing, device missing or busy; the message says how to fix it.
    """

    def __init__(self, device: str | int | None = None, block_s: float = 0.032, timeout_s: float = 0.5) -> None:
        sd = _import_sounddevice()
        if isinstance(device, str) and device.strip().lstrip("-").isdigit():
            device = int(device)
        self.device = device if device not in ("", None) else None
        self.name = f"microphone:{self.device if self.device is not None else 'default'}"
        self._timeout_s = timeout_s
        self._queue: queue.Queue[np.ndarray] = queue.Queue(maxsize=1000)
        self.overflows = 0  # written by the PortAudio callback thread only
        self._closed = False
        try:
            self._stream = sd.InputStream(samplerate=SAMPLE_RATE, channels=1, dtype="float32", device=self.device,
                                          blocksize=max(1, int(round(block_s * SAMPLE_RATE))),
                                          callback=self._callback)
            self._stream.start()
        except (sd.PortAudioError, ValueError) as exc:
            raise AudioDeviceError(describe_device_problem(exc, self.device)) from exc

    def _callback(self, indata: np.ndarray, frames: int, time_info: object, status: object) -> None:
        if status:
            self.overflows += 1
        try:
            self._queue.put_nowait(indata[:, 0].copy())
        except queue.Full:
            self.overflows += 1

    def read(self) -> np.ndarray | None:
        if self._closed:
            return None
        try:
            return self._queue.get(timeout=self._timeout_s)
        except queue.Empty:
            if not self._stream.active:
                raise AudioDeviceError(describe_device_problem(RuntimeError("the input stream stopped"),
                                                               self.device)) from None
            return np.zeros(0, dtype=np.float32)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            try:
                self._stream.stop()
                self._stream.close()
            except Exception:  # noqa: BLE001, S110 - closing a broken device must not raise
                pass


def open_source(kind: str, *, device: str = "", wav_path: str = "", pacing: float = 1.0,
                sample_rate: int = SAMPLE_RATE, block_s: float = 0.032) -> AudioSource:
    """Open a source by kind: ``microphone``, ``wav`` or ``stdin``.

    Raises:
        AudioSourceError: unknown kind or unreadable input (AudioDeviceError for the microphone).
    """
    if kind == "microphone":
        return PortAudioSource(device or None, block_s=block_s)
    if kind == "wav":
        if not wav_path:
            raise AudioSourceError("source 'wav' needs wav_path")
        return WavFileSource(os.path.expanduser(wav_path), pacing=pacing, block_s=block_s)
    if kind == "stdin":
        return RawStreamSource(sample_rate=sample_rate, block_s=block_s)
    raise AudioSourceError(f"unknown source {kind!r} (microphone, wav or stdin)")
