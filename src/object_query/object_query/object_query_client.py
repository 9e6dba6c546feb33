"""Client of ``/object_query``: a small Python API and a command-line tool.

Command line::

    object_query_client chair [--timeout 5]   # prints the answer; exit 1 when not found
    object_query_client chair --all [--near X Y Z]   # every instance (nearest first with --near)

Python (inside a node that is spun by an executor in another thread)::

    client = ObjectQueryClient(node)
    client.wait_for_service(timeout_sec=5.0)
    result = client.query("bottle", timeout_sec=2.0)   # -> QueryResult
    chairs = client.query_instances("chair", reference=(0.5, 0.5, 0.0), timeout_sec=2.0)  # -> InstancesResult
"""

from __future__ import annotations

import argparse
import math
import sys
import threading
import time

import rclpy
from object_query_interfaces.srv import ObjectInstances, ObjectQuery
from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import CallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future
from rclpy.utilities import remove_ros_args

from object_query.errors import ObjectQueryError
from object_query.semantic_map import InstancesResult, ObjectInstance, QueryResult


class ObjectQueryTimeout(ObjectQueryError):
    """The service did not answer (or was not available) within the deadline."""


#: s; a request not answered this long is sent again (then after twice as long, ...) until the deadline. A service
#: answers before DDS has matched its reply writer to a new client's reader now and then (rclpy logs "failed to send
#: response (timeout)"), and that reply is lost; a query only reads, so a repeat is harmless
RESEND_S = 1.0


class ObjectQueryClient:
    """Asks ``/object_query``. ``query()`` blocks the *calling* thread only, never an executor.

    Use ``query()`` from a worker thread while the node is spun elsewhere, or pass
    ``spin=True`` in a single-threaded script (it then spins the node itself until the deadline).
    A request not answered within ``resend_s`` is sent again, then after twice as long, and so on, until the
    deadline (:data:`RESEND_S`; ``resends`` counts them).
    """

    def __init__(self, node: Node, service: str = "object_query", callback_group: CallbackGroup | None = None,
                 instances_service: str = "object_instances", resend_s: float = RESEND_S):
        if not resend_s > 0:
            raise ValueError(f"resend_s must be > 0, got {resend_s}")
        self.resend_s = float(resend_s)
        self.resends = 0
        self._node = node
        self._client = node.create_client(ObjectQuery, service, callback_group=callback_group)
        self._instances_client = node.create_client(ObjectInstances, instances_service, callback_group=callback_group)

    def wait_for_service(self, timeout_sec: float) -> bool:
        """True once ``/object_query`` is available; False after ``timeout_sec`` (must be > 0)."""
        return self._client.wait_for_service(timeout_sec=timeout_sec)

    def query_async(self, name: str) -> Future:
        """Send the request; the future's result is an ``ObjectQuery.Response``."""
        return self._client.call_async(ObjectQuery.Request(name=name))

    def query(self, name: str, timeout_sec: float = 2.0, spin: bool = False) -> QueryResult:
        """Ask where ``name`` is.

        Raises:
            ObjectQueryTimeout: no answer within ``timeout_sec``.
        """
        resp = self._call(self._client, ObjectQuery.Request(name=name), timeout_sec, spin)
        p = resp.position
        return QueryResult(resp.found, (p.x, p.y, p.z), resp.message)

    def query_instances(self, name: str, reference: tuple[float, float, float] | None = None,
                        timeout_sec: float = 2.0, spin: bool = False) -> InstancesResult:
        """Every instance of ``name``: nearest to ``reference`` first when given, else largest first.

        Raises:
            ObjectQueryTimeout: no answer within ``timeout_sec``.
        """
        request = ObjectInstances.Request(name=name, use_reference=reference is not None)
        if reference is not None:
            request.reference.x, request.reference.y, request.reference.z = (float(v) for v in reference)
        resp = self._call(self._instances_client, request, timeout_sec, spin)
        instances = tuple(
            ObjectInstance(i.name, i.index, (i.centre.x, i.centre.y, i.centre.z),
                           (i.bbox_min.x, i.bbox_min.y, i.bbox_min.z), (i.bbox_max.x, i.bbox_max.y, i.bbox_max.z),
                           i.point_count)
            for i in resp.instances)
        distances = tuple(i.distance for i in resp.instances)
        return InstancesResult(resp.found, resp.name, resp.message, instances, distances)

    def forget(self, future: Future) -> None:
        """Drop a request whose answer is no longer awaited (after a timeout or cancel)."""
        if not future.done():
            self._client.remove_pending_request(future)

    def _call(self, client, request, timeout_sec: float, spin: bool):
        """Send ``request`` and wait for the response (see the class docstring for ``spin``), sending it again
        when a copy is not answered within ``resend_s`` (doubling); the first answer to any copy is returned.

        ``timeout_sec`` bounds the whole call: waiting for the service and for the answer.
        """
        deadline = time.monotonic() + timeout_sec
        if not client.service_is_ready() and not client.wait_for_service(timeout_sec=timeout_sec):
            raise ObjectQueryTimeout(f"service {client.srv_name} not available after {timeout_sec:.1f} s")
        done = threading.Event()
        futures = []
        executor = None
        if spin:
            executor = SingleThreadedExecutor(context=self._node.context)
            executor.add_node(self._node)
        try:
            wait = self.resend_s
            while True:
                future = client.call_async(request)
                future.add_done_callback(lambda _f: done.set())
                futures.append(future)
                until = min(deadline, time.monotonic() + wait)
                if executor is not None:
                    while not done.is_set() and time.monotonic() < until:
                        executor.spin_once(timeout_sec=0.05)
                else:
                    done.wait(max(0.0, until - time.monotonic()))
                if done.is_set() or time.monotonic() >= deadline:
                    break
                self.resends += 1
                wait *= 2
        finally:
            if executor is not None:
                executor.remove_node(self._node)
        answered = next((f for f in futures if f.done()), None)
        for f in futures:
            if not f.done():
                client.remove_pending_request(f)
        if answered is None:
            raise ObjectQueryTimeout(f"no answer from {client.srv_name} within {timeout_sec:.1f} s")
        return answered.result()


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        ros_args = remove_ros_args(["prog", *argv])[1:]
    except (RCLError, UnicodeError) as exc:  # ROS arguments rcl cannot parse, or bytes that are not UTF-8
        print(f"error: bad arguments: {str(exc).split(', at ')[0][:200]}", file=sys.stderr)
        return 2
    parser = argparse.ArgumentParser(prog="object_query_client", description="Ask the robot where an object is.")
    parser.add_argument("name", nargs="+", help="object name, e.g. chair (several words allowed)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the service (default 5)")
    parser.add_argument("--all", action="store_true", help="list every instance (/object_instances)")
    parser.add_argument("--near", type=float, nargs=3, metavar=("X", "Y", "Z"),
                        help="with --all: sort by distance to this point")
    opts = parser.parse_args(ros_args)
    if not 0 < opts.timeout < math.inf:
        parser.error(f"--timeout must be a finite number of seconds > 0, got {opts.timeout}")
    name = " ".join(opts.name)
    rclpy.init(args=["prog", *argv])
    node = rclpy.create_node("object_query_client")
    try:
        client = ObjectQueryClient(node)
        if opts.all:
            many = client.query_instances(name, tuple(opts.near) if opts.near else None, opts.timeout, spin=True)
        else:
            result = client.query(name, timeout_sec=opts.timeout, spin=True)
    except ObjectQueryTimeout as exc:
        print(f"error: {exc} (is object_query_server running on ROS_DOMAIN_ID the same as ours?)", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except RCLError:  # Ctrl-C's shutdown while waiting invalidates the context under the wait
        if rclpy.ok():
            raise
        return 130
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    if opts.all:
        if not many.found:
            print(f"not found: {many.message}")
            return 1
        print(f"found: {many.message}")
        for inst, dist in zip(many.instances, many.distances, strict=True):
            (x, y, z), lo, hi = inst.centre, inst.bbox_min, inst.bbox_max
            far = f" distance={dist:.3f}" if dist >= 0 else ""
            print(f"  {inst.label}: x={x:.3f} y={y:.3f} z={z:.3f} points={inst.point_count}{far} "
                  f"box=[{lo[0]:.2f} {lo[1]:.2f} {lo[2]:.2f}]..[{hi[0]:.2f} {hi[1]:.2f} {hi[2]:.2f}]")
        return 0
    if result.found:
        x, y, z = result.position
        print(f"found: {name} at x={x:.3f} y={y:.3f} z={z:.3f} ({result.message})")
        return 0
    print(f"not found: {result.message}")
    return 1


if __name__ == "__main__":
    raise SystemExit(main())
