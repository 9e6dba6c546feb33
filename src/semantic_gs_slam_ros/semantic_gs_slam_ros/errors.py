"""Typed errors of the SLAM streaming package."""


class StreamingError(Exception):
    """Base class of streaming errors."""


class ImageFormatError(StreamingError):
    """An image message has an unsupported encoding or inconsistent size/step/data."""


class OutputError(StreamingError):
    """The output directory cannot be written (missing permission, disk full, ...)."""


class FrameRefusedError(StreamingError):
    """The SLAM engine cannot use one frame (wrong size, NaN or almost no valid depth): the session skips it and
    goes on; many in a row end the run with the map of the frames mapped."""
