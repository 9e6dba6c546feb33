"""Spinning an executor whose node destroys entities while it spins.

rclpy's executor collects a node's waitables (a subscription's QoS event handlers among them), enters each one's
handle and then adds them all to its wait set. A subscription destroyed by another thread in between (a
MultiThreadedExecutor's callback that unsubscribes) is skipped by the first step but not by the second, and
``executor.spin()`` ends with ``InvalidHandle: cannot use Destroyable because destruction was requested``
(ros2/rclpy issues 1206 and 1284). The node then dies, with every goal it was serving. The executor itself is
sound afterwards: its next wait set is built from the node's entities as they are now. :func:`spin` goes on.
"""

from __future__ import annotations

import time
from collections import deque

from rclpy.exceptions import InvalidHandle
from rclpy.executors import Executor

#: more than this many trips within :data:`TRIP_WINDOW_S` seconds is not the transient race: the error is raised
TRIP_LIMIT = 1000
TRIP_WINDOW_S = 1.0


def spin(executor: Executor, logger=None) -> None:
    """``executor.spin()`` until the context shuts down, going on past the transient ``InvalidHandle`` of an entity
    another thread destroyed while the executor built its wait set (module docstring). Each trip is logged at debug
    level on ``logger`` (an rclpy logger) when given.

    Raises:
        InvalidHandle: more than :data:`TRIP_LIMIT` trips within :data:`TRIP_WINDOW_S` seconds (not that race).
        ExternalShutdownException, KeyboardInterrupt: as ``executor.spin()`` does.
    """
    trips: deque[float] = deque(maxlen=TRIP_LIMIT + 1)
    while True:
        try:
            executor.spin()
            return
        except InvalidHandle as exc:
            now = time.monotonic()
            trips.append(now)
            if len(trips) > TRIP_LIMIT and now - trips[0] < TRIP_WINDOW_S:
                raise
            if logger is not None:
                logger.debug(f"executor tripped over an entity destroyed while it waited ({exc}); spinning on")
