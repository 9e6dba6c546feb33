"""The one ``main()`` of this package's nodes: build, spin until Ctrl-C / shutdown, clean up."""

from __future__ import annotations

from collections.abc import Callable

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node

from home_robot_exploration.errors import ConfigError
from home_robot_ros.startup import CONFIG_ERRORS


def run_node(node_class: Callable[[], Node], name: str, args: list[str] | None = None) -> int:
    """Build the node (a :class:`ConfigError` is reported, exit code 2) and spin it in this thread.

    Returns:
        The process exit code (0 after Ctrl-C or an external shutdown).
    """
    rclpy.init(args=args)
    try:
        node = node_class()
    except (ConfigError, *CONFIG_ERRORS) as exc:
        rclpy.logging.get_logger(name).fatal(f"configuration error: {exc}")
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
