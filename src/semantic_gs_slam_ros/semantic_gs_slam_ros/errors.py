"""Typed errors of the SLAM streaming package."""


class StreamingError(Exception):
    """Base class of streaming errors."""


class ImageFormatError(StreamingError):
    """An image message has an unsupported encoding or inconsistent size/step/data."""


class OutputError(StreamingError):
    """The output directory cannot be written (missing permission, disk full, ...)."""
