"""ROS 2 interface of the living object memory (the logic is in :mod:`object_query.memory`).

Attached to the object query server (:class:`MemoryInterface`):

Topic (latched: transient local, reliable, depth 1):
    ``/object_memory`` (object_query_interfaces/ObjectMemory): every instance with id, class,
    position, confidence, last_seen, source, state and place; published on every change, with a
    revision number that only grows.
Services:
    ``/object_memory/query`` (MemoryQuery): a class (synonyms allowed), an instance id or "" (all)
    → the instances, best first.
    ``/object_memory/report`` (MemoryReport): what happened to an object (``grasped``,
    ``grasp_failed``, ``placed`` by the robot; ``set`` by a person) → the memory after it.

Persistence: the memory is saved (atomically) after every change to ``memory_path`` and loaded
at start; a corrupt file is set aside with a warning (see :func:`object_query.memory.load_memory`).
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point
from object_query_interfaces.msg import MemoryInstance
from object_query_interfaces.msg import ObjectMemory as ObjectMemoryMsg
from object_query_interfaces.srv import MemoryQuery, MemoryReport
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

from object_query.errors import ObjectMemoryError
from object_query.memory import Belief, MapObservation, MemoryConfig, ObjectMemory, check_report, load_memory
from object_query.names import normalise_name, raw_name_error
from object_query.semantic_map import ObjectDatabase

#: Latched: a node that subscribes later still receives the current memory.
MEMORY_QOS = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)


def stamp_of(t: float) -> Time:
    sec = math.floor(t)
    return Time(sec=int(sec), nanosec=int((t - sec) * 1e9))


def belief_to_msg(b: Belief) -> MemoryInstance:
    return MemoryInstance(id=b.id, name=b.name, position=Point(x=b.position[0], y=b.position[1], z=b.position[2]),
                          confidence=float(b.confidence), last_seen=stamp_of(b.last_seen), source=b.source,
                          state=b.state, place=b.place, note=b.note)


def msg_to_belief(m: MemoryInstance) -> Belief:
    return Belief(id=m.id, name=m.name, position=(m.position.x, m.position.y, m.position.z),
                  confidence=float(m.confidence), last_seen=m.last_seen.sec + m.last_seen.nanosec * 1e-9,
                  source=m.source, state=m.state, place=m.place, note=m.note)


def memory_to_msg(beliefs: tuple[Belief, ...], revision: int, frame_id: str, stamp: Time) -> ObjectMemoryMsg:
    msg = ObjectMemoryMsg(revision=revision, instances=[belief_to_msg(b) for b in beliefs])
    msg.header.frame_id, msg.header.stamp = frame_id, stamp
    return msg


def default_memory_path(map_path: str) -> str:
    """``/maps/home.npz`` → ``/maps/home.memory.json`` (next to the map)."""
    return os.path.splitext(map_path)[0] + ".memory.json"


class MemoryInterface:
    """The memory's topic and services on ``node``, with persistence.

    Args:
        node: the object query server node.
        memory_path: the file (None = no persistence).
        frame_id: frame of the published positions.
        on_change: called after every change (e.g. to republish ``/object_list``).
        config: evidence weights of the memory.
    """

    def __init__(self, node: Node, memory_path: str | None, frame_id: str = "map",
                 on_change: Callable[[], None] | None = None, config: MemoryConfig | None = None) -> None:
        self._node = node
        self._path = memory_path
        self._frame = frame_id
        self._on_change = on_change
        self._save_lock = threading.Lock()  # one writer of the file at a time
        if memory_path:
            memory, message = load_memory(memory_path, config)
            (node.get_logger().warning if "corrupt" in message else node.get_logger().info)(message)
        else:
            memory = ObjectMemory(config)
            node.get_logger().info("memory: not persisted (memory_path none, or the bundled sample map)")
        self.memory = memory
        self._pub = node.create_publisher(ObjectMemoryMsg, "object_memory", MEMORY_QOS)
        self._query_srv = node.create_service(MemoryQuery, "object_memory/query", self._on_query)
        self._report_srv = node.create_service(MemoryReport, "object_memory/report", self._on_report)
        self._db: ObjectDatabase | None = None

    # -- events ------------------------------------------------------------------------------------

    def map_loaded(self, db: ObjectDatabase, observed_at: float | None) -> str:
        """Merge a (re)loaded map into the memory; returns the merge summary."""
        self._db = db
        report = self.memory.merge_map(
            (MapObservation(i.name, i.centre) for i in db.all_instances()), observed_at)
        self._changed()
        return report.summary()

    def apply(self, event: str, name: str, position: tuple[float, float, float] | None, place: str = "",
              source: str = "user", detail: str = "") -> Belief | None:
        """Apply one report (see MemoryReport.srv). Raises ObjectMemoryError on a malformed one."""
        check_report(event, name, position, place, detail)
        key = normalise_name(name)
        if event != "set" and self._db is not None and key:
            resolved, _ = self._db.resolve(key)
            key = resolved or key
        if event == "grasped":
            if not key:
                raise ObjectMemoryError("grasped: the object's name is missing")
            b = self.memory.grasped(key, position)
        elif event == "grasp_failed":
            b = self.memory.grasp_failed(key, position, detail)
        elif event == "placed":
            if position is None:
                raise ObjectMemoryError("placed: the position is missing")
            b = self.memory.placed(key, position, normalise_name(place))
        else:
            if position is None or not key:
                raise ObjectMemoryError("set: a name (or id) and a position are needed")
            b = self.memory.set_position(key, position, source or "user", normalise_name(place))
        self._changed()
        return b

    def _changed(self) -> None:
        if self._path:
            with self._save_lock:
                try:
                    self.memory.save(self._path)
                except OSError as exc:
                    self._node.get_logger().error(f"memory: cannot save {self._path}: {exc}")
        self._pub.publish(self.message())
        if self._on_change is not None:
            self._on_change()

    def message(self) -> ObjectMemoryMsg:
        return memory_to_msg(self.memory.snapshot(), self.memory.revision, self._frame,
                             self._node.get_clock().now().to_msg())

    # -- services -----------------------------------------------------------------------------------

    def _on_query(self, request: MemoryQuery.Request, response: MemoryQuery.Response) -> MemoryQuery.Response:
        response.revision = self.memory.revision
        refused = raw_name_error(request.name)
        if refused:
            response.found, response.message = False, refused
            return response
        name = normalise_name(request.name)
        if not name:
            beliefs = list(self.memory.snapshot())
            response.found, response.message = bool(beliefs), f"{len(beliefs)} instance(s)"
        else:
            one = self.memory.get(name.replace(" #", "#"))
            key = one.name if one else (self._db.resolve(name)[0] if self._db is not None else None) or name
            beliefs = [one] if one else self.memory.candidates(key)
            response.found = bool(beliefs)
            response.name = key if beliefs else ""
            response.message = (f"{len(beliefs)} instance(s) of {key}" if beliefs
                                else f"the memory holds no {name!r}")
        response.instances = [belief_to_msg(b) for b in beliefs]
        return response

    def _on_report(self, request: MemoryReport.Request, response: MemoryReport.Response) -> MemoryReport.Response:
        p = request.position
        position = (p.x, p.y, p.z) if request.has_position else None
        try:
            b = self.apply(request.event, request.name, position, request.place, request.source, request.detail)
        except ObjectMemoryError as exc:
            response.success, response.message = False, str(exc)
        else:
            response.success = True
            response.id = b.id if b is not None else ""
            response.message = (f"{request.event}: {b.id} ({b.state}, confidence {b.confidence:.2f})" if b
                                else f"{request.event}: the memory holds no {request.name!r}")
            self._node.get_logger().info(f"memory: {response.message}")
        response.memory = self.message()
        return response
