"""The decision maker's link to the object memory (ROS shell; the logic is in memory.world / object_query.memory).

* Reads the latched ``/object_memory`` topic into a local snapshot (the newest revision wins),
  which planning reads without waiting.
* Reports the robot's own grasps and places to ``/object_memory/report`` (worker thread, waits at
  most ``timeout_s``); the reply carries the memory after the report, so the next plan already
  sees it (no race with the topic).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

from object_query_interfaces.msg import ObjectMemory as ObjectMemoryMsg
from object_query_interfaces.srv import MemoryReport
from rclpy.callback_groups import CallbackGroup
from rclpy.node import Node

from decision_maker.execution.engine import ActionOutcome
from decision_maker.memory.world import aliases_for
from object_query.memory import Belief
from object_query.memory_ros import MEMORY_QOS, msg_to_belief


class MemoryLink:
    """Local copy of the object memory plus the report client.

    Args:
        node: the decision maker node (spun elsewhere).
        input_group: callback group of the ``/object_memory`` subscription.
        client_group: callback group of the report client.
        timeout_s: longest wait for a report's answer (> 0); a report not answered in time is
            logged, its answer dropped (the action's own result stands; the memory publishes the change on
            ``/object_memory`` once it records it).
    """

    def __init__(self, node: Node, input_group: CallbackGroup, client_group: CallbackGroup,
                 timeout_s: float = 5.0) -> None:
        self._node = node
        self._timeout_s = timeout_s
        self._lock = threading.Lock()  # guards _revision, _beliefs
        self._revision = -1
        self._beliefs: tuple[Belief, ...] = ()
        node.create_subscription(ObjectMemoryMsg, "object_memory", self._on_memory, MEMORY_QOS,
                                 callback_group=input_group)
        self._client = node.create_client(MemoryReport, "object_memory/report", callback_group=client_group)
        self._synonym_groups = _bundled_synonym_groups(node)

    def aliases(self, known: Iterable[str]) -> dict[str, str]:
        """Other names of the ``known`` objects → their class, from the object database's synonyms."""
        return aliases_for(known, self._synonym_groups)

    def snapshot(self) -> tuple[Belief, ...]:
        """The newest memory received (empty before the first)."""
        with self._lock:
            return self._beliefs

    def _on_memory(self, msg: ObjectMemoryMsg) -> None:
        self._take(msg)

    def _take(self, msg: ObjectMemoryMsg) -> None:
        try:
            beliefs = tuple(msg_to_belief(m) for m in msg.instances)
        except (TypeError, ValueError) as exc:
            self._node.get_logger().warning(f"ignoring a malformed /object_memory: {exc}")
            return
        with self._lock:
            if msg.revision >= self._revision or msg.revision == 0:  # 0: the server restarted
                self._revision, self._beliefs = msg.revision, beliefs

    def report(self, outcome: ActionOutcome) -> None:
        """Tell the memory what an action did (worker thread; waits at most ``timeout_s``)."""
        if not self._client.service_is_ready():
            self._node.get_logger().warning(f"object memory not available: {outcome.event} {outcome.name} not recorded")
            return
        req = MemoryReport.Request(event=outcome.event, name=outcome.name, place=outcome.place,
                                   detail=outcome.detail[:200], source="action")
        if outcome.position is not None:
            p = outcome.position
            req.has_position = True
            req.position.x, req.position.y, req.position.z = p.x, p.y, p.z
        elif outcome.robot is not None:
            req.has_position = True
            req.position.x, req.position.y = outcome.robot.x, outcome.robot.y
        done = threading.Event()
        future = self._client.call_async(req)
        future.add_done_callback(lambda _f: done.set())
        deadline = time.monotonic() + self._timeout_s
        done.wait(max(0.0, deadline - time.monotonic()))
        if not future.done():
            self._client.remove_pending_request(future)
            self._node.get_logger().warning(f"object memory did not answer within {self._timeout_s:g} s: "
                                            f"{outcome.event} {outcome.name}")
            return
        resp = future.result()
        if resp is None or not resp.success:
            self._node.get_logger().warning(f"object memory refused {outcome.event} {outcome.name}: "
                                            f"{getattr(resp, 'message', 'no answer')}")
            return
        self._take(resp.memory)
        self._node.get_logger().info(f"memory: {resp.message}")


def _bundled_synonym_groups(node: Node) -> tuple[tuple[str, ...], ...]:
    """The object database's bundled synonym groups (empty, with a warning, when unreadable)."""
    try:
        from object_query.names import load_synonyms
        from object_query.object_query_server import bundled_synonyms_path

        return load_synonyms(bundled_synonyms_path()).groups
    except Exception as exc:  # synonyms only help; never fatal
        node.get_logger().warning(f"no object synonyms for slot filling: {exc}")
        return ()
