"""Typed errors of the SLAM engine (no error tuples, no ``None`` returns)."""

from __future__ import annotations

#: a run (the dataset CLI, the streaming client, the streaming server's session) skips a frame it cannot use, and
#: stops, keeping the map of the frames mapped, after this many such frames in a row: a wrong dataset or camera,
#: not one bad file
MAX_BAD_IN_A_ROW = 10


class SlamError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(SlamError, ValueError):
    """A configuration value is out of range or inconsistent."""


class DatasetError(SlamError):
    """A dataset folder is missing files, has mismatched sizes or unreadable content."""


class FrameError(SlamError, ValueError):
    """A frame handed to :meth:`SLAM.add_frame` has the wrong shape, dtype or values (NaN, no depth)."""


class MapFormatError(SlamError):
    """A map file (``params.npz``, ``semantic.json``, checkpoint) is missing or malformed."""


class TrackingError(SlamError):
    """Tracking could not estimate a pose (e.g. too few valid depth correspondences)."""


class BackendUnavailableError(SlamError):
    """A renderer back-end was requested that cannot run here (``gsplat`` without CUDA)."""


class MappingError(SlamError):
    """The mapping thread failed (the cause is chained) or did not drain within the deadline."""
