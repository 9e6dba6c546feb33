"""Typed errors of the speech core (no ROS)."""


class SpeechError(Exception):
    """Base class of every error raised by the speech core."""


class AudioSourceError(SpeechError):
    """An audio source cannot be opened or read (file missing, bad format, broken stream)."""


class AudioDeviceError(AudioSourceError):
    """The PortAudio input device is missing, busy or unusable.

    The message says what is wrong and how to fix it (list devices, who holds /dev/snd).
    """


class ModelLoadError(SpeechError):
    """The Whisper model cannot be found or loaded (never downloaded at run time)."""


class ConfigError(SpeechError):
    """A speech configuration value is invalid."""
