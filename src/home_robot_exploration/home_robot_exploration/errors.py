"""Typed errors of the exploration package."""


class ExplorationError(Exception):
    """Base class of this package's errors."""


class ConfigError(ExplorationError, ValueError):
    """A configuration value is unusable (the message says which and why)."""


class FrameError(ExplorationError, ValueError):
    """A camera frame cannot be used (wrong shape, non-finite pose, ...)."""
