"""What building a node may raise because of how it was configured, for every node's ``main()``, and a checked
numeric parameter."""

from __future__ import annotations

import math

from rclpy.exceptions import NameValidationException, ParameterException

#: Errors a node's constructor raises for its configuration rather than a bug: a parameter of another type than
#: declared (``-p port:=abc``), a topic or service name rclpy refuses (``-p pose_topic:=bad//t``), and rclpy's
#: ValueError for an action name it refuses. A ``main()`` reports them in one line and exits 2, like its own
#: configuration errors, instead of a traceback.
CONFIG_ERRORS: tuple[type[Exception], ...] = (ParameterException, NameValidationException, ValueError)


def number_in(name: str, value: object, low: float, high: float) -> float:
    """A numeric parameter as a float within [low, high].

    Raises:
        ValueError: not a number, not finite, or outside the range (the message names the parameter; it is one of
            :data:`CONFIG_ERRORS`, so a ``main()`` reports it and exits 2).
    """
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        x = math.nan
    if isinstance(value, bool) or not (math.isfinite(x) and low <= x <= high):
        raise ValueError(f"{name} must be a number from {low:g} to {high:g}, got {str(value)[:40]}")
    return x
