"""Starting a node: what building it may raise because of how it was configured, the one way every ``main()``
reports that (:func:`build_node`, :func:`spin_node`), and checked parameters."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import rclpy
from rcl_interfaces.msg import SetParametersResult
from rclpy.exceptions import InvalidTopicNameException, NameValidationException, ParameterException
from rclpy.executors import ExternalShutdownException
from rclpy.expand_topic_name import expand_topic_name
from rclpy.node import Node
from rclpy.validate_full_topic_name import validate_full_topic_name


class ParameterError(ValueError):
    """A parameter's value the node cannot work with (:func:`number_in`); the message names the parameter."""


#: Errors a node's constructor raises for its configuration rather than a bug: a parameter of another type than
#: declared (``-p port:=abc``), a topic, service or action name rclpy refuses (``-p pose_topic:=bad//t``;
#: :func:`action_name`), a value out of range (:class:`ParameterError`). A ``main()`` reports them in one line and
#: exits 2, like its own configuration errors, instead of a traceback.
CONFIG_ERRORS: tuple[type[Exception], ...] = (ParameterException, NameValidationException, ParameterError)

N = TypeVar("N", bound=Node)


def build_node(factory: Callable[[], N], name: str, errors: tuple[type[Exception], ...] = ()) -> N | None:
    """``factory()`` (rclpy initialised), or None when it raised one of :data:`CONFIG_ERRORS` or ``errors`` (the
    node's own: a bad setting, a missing file, a port taken): then one FATAL line ``cannot start: <reason>`` is
    logged as ``name`` and rclpy is shut down, and the ``main()`` returns 2."""
    try:
        return factory()
    except (*CONFIG_ERRORS, *errors) as exc:
        rclpy.logging.get_logger(name).fatal(f"cannot start: {exc}")
        rclpy.try_shutdown()
        return None


def spin_node(factory: Callable[[], Node], name: str, args: list[str] | None = None,
              errors: tuple[type[Exception], ...] = ()) -> int:
    """The whole ``main()`` of a node that needs nothing but spinning: initialise rclpy with ``args``, build the node
    (:func:`build_node`), spin it in this thread until Ctrl-C or an external shutdown, destroy it.

    Returns:
        The process exit code: 0, or 2 when the node could not start.
    """
    rclpy.init(args=args)
    node = build_node(factory, name, errors)
    if node is None:
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def action_name(node, name: str) -> str:
    """``name`` when rclpy can make an action of it on ``node`` (checked as the topic names an action is made of).

    Raises:
        NameValidationException: the reason, as for a topic (rclpy raises a bare ValueError for an action).
    """
    try:
        full = expand_topic_name(name, node.get_name(), node.get_namespace())
    except ValueError as exc:  # rclpy's expansion refuses some names before the validation sees them
        raise InvalidTopicNameException(name, str(exc).split(", at ")[0], 0) from exc
    validate_full_topic_name(full)
    return name


def number_in(name: str, value: object, low: float, high: float) -> float:
    """A numeric parameter as a float within [low, high].

    Raises:
        ParameterError: not a number, not finite, or outside the range (the message names the parameter; one of
            :data:`CONFIG_ERRORS`, so a ``main()`` reports it and exits 2).
    """
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):
        x = math.nan
    if isinstance(value, bool) or not (math.isfinite(x) and low <= x <= high):
        raise ParameterError(f"{name} must be a number from {low:g} to {high:g}, got {str(value)[:40]}")
    return x


def read_once(node: Node, defaults: Mapping[str, Any]) -> dict[str, Any]:
    """Declare each of ``defaults`` (name -> default value, which sets its type) on ``node`` and return their values
    as started (``--ros-args -p name:=value`` overrides). The node reads them only now, so a later change
    (``ros2 param set``) would be silently ignored: it is refused instead, with the reason; parameters not in
    ``defaults`` (rclpy's ``use_sim_time``) are left to rclpy."""
    for name, default in defaults.items():
        node.declare_parameter(name, default)
    who = node.get_name()

    def refuse(params: list) -> SetParametersResult:
        own = [p.name for p in params if p.name in defaults]
        if not own:
            return SetParametersResult(successful=True)
        return SetParametersResult(successful=False, reason=f"{who} reads {', '.join(own)} at start only; restart "
                                                            "the node with the new value")

    node.add_on_set_parameters_callback(refuse)
    return {name: node.get_parameter(name).value for name in defaults}
