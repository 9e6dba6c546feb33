"""Client of ``/object_query``: a small Python API and a command-line tool.

Command line::

    object_query_client chair [--timeout 5]   # prints the answer; exit 1 when not found

Python (inside a node that is spun by an executor in another thread)::

    client = ObjectQueryClient(node)
    client.wait_for_service(timeout_sec=5.0)
    result = client.query("bottle", timeout_sec=2.0)   # -> QueryResult
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import rclpy
from object_query_interfaces.srv import ObjectQuery
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

from object_query.errors import ObjectQueryError
from object_query.semantic_map import QueryResult


class ObjectQueryTimeout(ObjectQueryError):
    """The service did not answer (or was not available) within the deadline."""


class ObjectQueryClient:
    """Asks ``/object_query``. ``query()`` blocks the *calling* thread only, never an executor.

    Use ``query()`` from a worker thread while the node is spun elsewhere, or pass
    ``spin=True`` in a single-threaded script (it then spins the node itself until the deadline).
    """

    def __init__(self, node: Node, service: str = "object_query", callback_group: CallbackGroup | None = None):
        self._node = node
        self._client = node.create_client(ObjectQuery, service, callback_group=callback_group)

    def wait_for_service(self, timeout_sec: float) -> bool:
        """True once the service is available; False after ``timeout_sec`` (must be > 0)."""
        return self._client.wait_for_service(timeout_sec=timeout_sec)

    def query_async(self, name: str) -> Future:
        return self._client.call_async(ObjectQuery.Request(name=name))

    def query(self, name: str, timeout_sec: float = 2.0, spin: bool = False) -> QueryResult:
        """Ask where ``name`` is.

        Raises:
            ObjectQueryTimeout: no answer within ``timeout_sec``.
        """
        if not self._client.service_is_ready() and not self._client.wait_for_service(timeout_sec=timeout_sec):
            raise ObjectQueryTimeout(f"service {self._client.srv_name} not available after {timeout_sec:.1f} s")
        future = self.query_async(name)
        if spin:
            executor = SingleThreadedExecutor(context=self._node.context)
            executor.add_node(self._node)
            deadline = time.monotonic() + timeout_sec
            while not future.done() and time.monotonic() < deadline:
                executor.spin_once(timeout_sec=0.05)
            executor.remove_node(self._node)
        else:
            done = threading.Event()
            future.add_done_callback(lambda _f: done.set())
            done.wait(timeout_sec)
        if not future.done():
            self._client.remove_pending_request(future)
            raise ObjectQueryTimeout(f"no answer from {self._client.srv_name} within {timeout_sec:.1f} s")
        resp = future.result()
        p = resp.position
        return QueryResult(resp.found, (p.x, p.y, p.z), resp.message)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ros_args = remove_ros_args(["prog", *argv])[1:]
    parser = argparse.ArgumentParser(prog="object_query_client", description="Ask the robot where an object is.")
    parser.add_argument("name", nargs="+", help="object name, e.g. chair (several words allowed)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the service (default 5)")
    opts = parser.parse_args(ros_args)
    rclpy.init(args=["prog", *argv])
    node = rclpy.create_node("object_query_client")
    try:
        result = ObjectQueryClient(node).query(" ".join(opts.name), timeout_sec=opts.timeout, spin=True)
    except ObjectQueryTimeout as exc:
        print(f"error: {exc} (is object_query_server running on ROS_DOMAIN_ID the same as ours?)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if result.found:
        x, y, z = result.position
        print(f"found: {' '.join(opts.name)} at x={x:.3f} y={y:.3f} z={z:.3f} ({result.message})")
        return 0
    print(f"not found: {result.message}")
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
