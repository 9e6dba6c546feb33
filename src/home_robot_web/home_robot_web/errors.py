"""Typed errors of the web UI."""


class WebUiError(Exception):
    """Base class of the web UI's errors."""


class ConfigError(WebUiError):
    """A parameter or the token file is unusable; the message says what to change."""


class TokenFileError(ConfigError):
    """The token file is missing, unreadable, too short or readable by others than its owner."""


class ProtocolError(WebUiError):
    """A message from the page is malformed or over a limit; sent back to the page as an error.

    Attributes:
        ref: the message's ``ref`` when it could be read (so the page ties the error to its request).
    """

    def __init__(self, message: str, ref: int | None = None) -> None:
        super().__init__(message)
        self.ref = ref


class ServerError(WebUiError):
    """The HTTP/websocket server could not start (address in use, no permission) or stop in time."""
