"""ROS 2 shell of the object database (the logic is in :mod:`object_query.semantic_map`).

Services:
    ``/object_query`` (ObjectQuery): name → found, position, message (the seed's contract).
    ``/object_instances`` (ObjectInstances): every instance of a name with centre, box, point
    count and distance to an optional reference point, nearest first.
    ``/object_query_server/reload`` (std_srvs/Trigger): reload the map files now (served by the
    helper node ``object_query_server_maintenance`` so that reloads never delay queries).

Topics (transient local: late subscribers get the last message):
    ``/object_list`` (std_msgs/String): ``{"chair": [x, y, z], ...}``.
    ``/object_query_server/status`` (std_msgs/String, JSON): ``{"state": "provisional" | "ready" |
    "build_failed", "objects", "instances", "provisional_s", "build_s", "message"}``. At start the
    server answers from class centroids (``provisional``, said in every answer's message) while
    the instances are built in a background thread, then ``ready``.
    ``/object_markers`` (visualization_msgs/MarkerArray): a labelled box per instance.

Parameters (see docs/object_query.md):
    map_path, semantic_path (str): the map; empty = the bundled sample map.
    synonyms_path (str): synonyms YAML; empty = the bundled one, ``none`` = no synonyms.
    voxel_size, min_instance_points, min_opacity, centre_method, trim_fraction, query_position, min_label_views:
    how the database is built (:class:`object_query.semantic_map.DatabaseConfig`); changing any of
    them, or a path, at run time reloads the map.
    auto_reload (bool, true): reload when the files change on disk (polled every
    reload_poll_period seconds; a file must be unchanged for one period before it is read).
    frame_id (str): frame of the markers.
    memory_path (str): the object memory's file; empty = next to the map (``<map>.memory.json``)
    when ``map_path`` is set, not persisted for the bundled sample map; ``none`` = not persisted.
    memory_match_radius (m): a reloaded map's instance this close to a remembered one of its class
    is the same object (farther, it may have moved: see docs/object_query.md).

The living object memory (``/object_memory``, ``/object_memory/query``, ``/object_memory/report``)
is served by :class:`object_query.memory_ros.MemoryInterface`; ``/object_query`` and
``/object_list`` answer from it (the current belief), the map only for classes it holds nothing of.
"""

from __future__ import annotations

import colorsys
import hashlib
import json
import os
import threading
import traceback

import rclpy
from geometry_msgs.msg import Point
from object_query_interfaces.msg import ObjectInstance as ObjectInstanceMsg
from object_query_interfaces.srv import ObjectInstances, ObjectQuery
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import ColorRGBA, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from home_robot_ros.startup import build_node, number_in
from object_query.answers import answer_query, object_list
from object_query.errors import MapLoadError, SynonymsError
from object_query.memory import MemoryConfig
from object_query.memory_ros import MemoryInterface, default_memory_path
from object_query.names import load_synonyms, raw_name_error
from object_query.semantic_map import DatabaseConfig, FileSignature, ObjectDatabase, load_semantic_map
from object_query.staged import StagedBuild

#: Latched: a node that subscribes later still receives the last message.
OBJECT_LIST_QOS = QoSProfile(
    depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE
)
#: Smaller maps are built fully before the first answer (they take milliseconds): no provisional stage.
PROVISIONAL_MIN_POINTS = 500_000
#: Parameters that change what the database holds: setting one reloads the map.
_BUILD_PARAMS = ("map_path", "semantic_path", "synonyms_path", "voxel_size", "min_instance_points", "min_opacity",
                 "centre_method", "trim_fraction", "query_position", "min_label_views")


def bundled_map_paths() -> tuple[str, str]:
    """Paths of the sample map installed with this package (share/object_query/data)."""
    from ament_index_python.packages import get_package_share_directory

    share = get_package_share_directory("object_query")
    return os.path.join(share, "data", "params.npz"), os.path.join(share, "data", "semantic.json")


def bundled_synonyms_path() -> str:
    """Path of the synonyms file installed with this package (share/object_query/config)."""
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("object_query"), "config", "synonyms.yaml")


def class_colour(name: str, alpha: float) -> ColorRGBA:
    """A stable colour per class name (hue from a hash of the name)."""
    hue = int.from_bytes(hashlib.sha1(name.encode("utf-8")).digest()[:2], "big") / 65536.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.75, 0.95)
    return ColorRGBA(r=r, g=g, b=b, a=alpha)


def database_markers(db: ObjectDatabase, frame_id: str, stamp) -> MarkerArray:
    """A translucent box and a text label per instance, after a DELETEALL of older markers."""
    markers = [Marker(action=Marker.DELETEALL)]
    for i, inst in enumerate(db.all_instances()):
        lo, hi = inst.bbox_min, inst.bbox_max
        box = Marker(type=Marker.CUBE, action=Marker.ADD, ns="object_boxes", id=i)
        box.header.frame_id, box.header.stamp = frame_id, stamp
        box.pose.position = Point(x=(lo[0] + hi[0]) / 2, y=(lo[1] + hi[1]) / 2, z=(lo[2] + hi[2]) / 2)
        box.pose.orientation.w = 1.0
        box.scale.x, box.scale.y, box.scale.z = (max(hi[k] - lo[k], 0.01) for k in range(3))
        box.color = class_colour(inst.name, 0.35)
        text = Marker(type=Marker.TEXT_VIEW_FACING, action=Marker.ADD, ns="object_labels", id=i)
        text.header.frame_id, text.header.stamp = frame_id, stamp
        text.pose.position = Point(x=inst.centre[0], y=inst.centre[1], z=hi[2] + 0.1)
        text.pose.orientation.w = 1.0
        text.scale.z = 0.12
        text.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
        text.text = f"{inst.label} ({inst.point_count})"
        markers += [box, text]
    return MarkerArray(markers=markers)


class ObjectQueryServer(Node):
    """Serves the object database; reloads it atomically (on request, on file change, on parameter change).

    Threads: queries and parameters are handled by this node's executor (single-threaded: the
    lowest latency in rclpy 7.1.6). Reloads run on :attr:`maintenance_node`, a helper node
    (``<name>_maintenance``) with the reload service and the polling timer, spun by a second
    executor in another thread, so a reload (seconds for a 10 M map) never delays a query.
    """

    def __init__(self) -> None:
        super().__init__("object_query_server")
        defaults = DatabaseConfig()
        self.declare_parameter("map_path", "", ParameterDescriptor(description="params.npz; empty = bundled sample"))
        self.declare_parameter("semantic_path", "", ParameterDescriptor(description="semantic.json; empty = bundled"))
        self.declare_parameter("synonyms_path", "",
                               ParameterDescriptor(description="synonyms YAML; empty = bundled, 'none' = no synonyms"))
        # numbers accept int or double (`-p min_opacity:=0` is fine); DatabaseConfig validates the values
        number = ParameterDescriptor(dynamic_typing=True)
        self.declare_parameter("voxel_size", defaults.voxel_size, number)
        self.declare_parameter("min_instance_points", defaults.min_instance_points, number)
        self.declare_parameter("min_opacity", defaults.min_opacity, number)
        self.declare_parameter("centre_method", defaults.centre_method)
        self.declare_parameter("trim_fraction", defaults.trim_fraction, number)
        self.declare_parameter("query_position", defaults.query_position)
        self.declare_parameter("min_label_views", defaults.min_label_views, number)
        self.declare_parameter("auto_reload", True)
        self.declare_parameter("wait_for_map", False, ParameterDescriptor(
            read_only=True, description="a missing map at start: serve no objects and load it when it appears "
                                        "(a map SLAM is about to write); false = refuse to start"))
        self.declare_parameter("reload_poll_period", 1.0, ParameterDescriptor(read_only=True))
        self.declare_parameter("frame_id", "map")
        self.declare_parameter("memory_path", "", ParameterDescriptor(
            read_only=True, description="object memory file; empty = next to map_path (none for the bundled map)"))
        self.declare_parameter("memory_match_radius", MemoryConfig().match_radius,
                               ParameterDescriptor(read_only=True, dynamic_typing=True))
        self.declare_parameter("provisional_min_points", PROVISIONAL_MIN_POINTS, ParameterDescriptor(
            read_only=True, description="maps with at least this many Gaussians are served from class centroids "
                                        "while their instances are built; 0 = always"))

        self._lock = threading.Lock()  # guards _db, _signature, _failed_signature, _seen_signature, _pending
        self._reload_lock = threading.Lock()  # one reload at a time (service, timer, parameter change)
        self._db: ObjectDatabase | None = None
        self._signature = FileSignature()
        self._failed_signature: FileSignature | None = None
        self._seen_signature: FileSignature | None = None
        self._pending: str | None = None  # reason of a reload requested by a parameter change
        self._staged_started = False  # the start-up map's instances are built in the background
        self._staged: StagedBuild | None = None  # that build, waited for at shutdown

        self._list_pub = self.create_publisher(String, "object_list", OBJECT_LIST_QOS)
        self._marker_pub = self.create_publisher(MarkerArray, "object_markers", OBJECT_LIST_QOS)
        self.memory = self._make_memory()
        self._status_pub = self.create_publisher(String, "~/status", OBJECT_LIST_QOS)
        # Raises MapLoadError/SynonymsError/ValueError, reported by main(): nothing to serve without a map.
        staged = self._load_initial()

        # answers read an immutable snapshot taken under the lock: no lock is held while answering
        self._query_srv = self.create_service(ObjectQuery, "object_query", self._on_query)
        self._instances_srv = self.create_service(ObjectInstances, "object_instances", self._on_instances)
        # own node (no global remaps: `-r __node:=...` would rename it too), same namespace
        self.maintenance_node = rclpy.create_node(f"{self.get_name()}_maintenance", namespace=self.get_namespace(),
                                                  context=self.context, use_global_arguments=False,
                                                  start_parameter_services=False)
        self._reload_srv = self.maintenance_node.create_service(
            Trigger, f"{self.get_fully_qualified_name()}/reload", self._on_reload)
        period = number_in("reload_poll_period", self.get_parameter("reload_poll_period").value, 0.0, 3600.0)
        self._poll_timer = self.maintenance_node.create_timer(max(period, 0.05), self._on_poll)
        self.add_on_set_parameters_callback(self._validate_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        db = self._snapshot()
        self.get_logger().info(f"ready: {len(db.names())} objects from {self._paths()[0]} ({', '.join(db.names())})"
                               f"{'; provisional class centroids, instances being built' if db.provisional else ''}")
        if staged is not None and not staged.done:
            self._staged_started = True
            self._staged = staged.start()  # after the services exist: answers never wait for the instances

    def wait_background(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` seconds for the start-up map's background build; True when none runs.

        Called before the node is destroyed: a build thread still inside compiled code when the
        interpreter exits aborts the process ("terminate called without an active exception").
        """
        return self._staged is None or self._staged.wait(timeout_s)

    # -- settings --------------------------------------------------------------------------------

    def _paths(self) -> tuple[str, str, str]:
        """(map, semantic, synonyms) paths with the bundled defaults filled in ('' = no synonyms)."""
        default_map, default_sem = bundled_map_paths()
        map_path = self.get_parameter("map_path").value or default_map
        sem_path = self.get_parameter("semantic_path").value or default_sem
        syn = self.get_parameter("synonyms_path").value
        syn_path = "" if syn.strip().lower() == "none" else (syn or bundled_synonyms_path())
        return map_path, sem_path, syn_path

    def _config(self, overrides: dict[str, object] | None = None) -> DatabaseConfig:
        """The build configuration from the parameters (plus proposed ``overrides``); ValueError if bad."""
        values = {name: self.get_parameter(name).value for name in
                  ("voxel_size", "min_instance_points", "min_opacity", "centre_method", "trim_fraction",
                   "query_position", "min_label_views")}
        values.update(overrides or {})
        for name in ("min_instance_points", "min_label_views"):
            if isinstance(values[name], float) and not values[name].is_integer():
                raise ValueError(f"{name} must be an integer, got {values[name]}")
        for name in ("voxel_size", "min_instance_points", "min_opacity", "trim_fraction", "min_label_views"):
            if isinstance(values[name], bool) or not isinstance(values[name], int | float):
                raise ValueError(f"{name} must be a number, got {str(values[name])[:40]}")
        return DatabaseConfig(voxel_size=float(values["voxel_size"]),
                              min_instance_points=int(values["min_instance_points"]),
                              min_opacity=float(values["min_opacity"]), centre_method=str(values["centre_method"]),
                              trim_fraction=float(values["trim_fraction"]),
                              query_position=str(values["query_position"]),
                              min_label_views=int(values["min_label_views"]))

    def _validate_parameters(self, params: list[Parameter]) -> SetParametersResult:
        overrides = {p.name: p.value for p in params if p.name in _BUILD_PARAMS and not p.name.endswith("_path")}
        try:
            self._config(overrides)
        except (TypeError, ValueError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, params: list[Parameter]) -> None:
        changed = [p.name for p in params if p.name in _BUILD_PARAMS]
        if changed:
            with self._lock:
                self._pending = f"parameter(s) {', '.join(changed)} changed"

    # -- loading ---------------------------------------------------------------------------------

    def _signature_now(self) -> FileSignature:
        map_path, sem_path, syn_path = self._paths()
        return FileSignature.of(map_path, sem_path, *([syn_path] if syn_path else []))

    def _build(self, signature: FileSignature | None = None) -> tuple[ObjectDatabase, FileSignature]:
        """The database from the files; ``signature`` = the files' state taken before reading them."""
        map_path, sem_path, syn_path = self._paths()
        signature = signature or self._signature_now()
        db = ObjectDatabase.from_files(map_path, sem_path, self._config(), load_synonyms(syn_path))
        return db, signature

    def _load_initial(self) -> StagedBuild | None:
        """Read the map and serve its class centroids; the returned build (not started yet) makes
        the full database in a background thread and swaps it in (:meth:`_on_initial_build`).
        With ``wait_for_map`` and no map files yet: serve an empty database (None returned); the
        poll loads the map when it appears."""
        map_path, sem_path, syn_path = self._paths()
        signature = self._signature_now()
        if self.get_parameter("wait_for_map").value and not (os.path.isfile(map_path) and os.path.isfile(sem_path)):
            db = ObjectDatabase({}, synonyms=load_synonyms(syn_path))
            with self._lock:
                self._db, self._signature, self._seen_signature = db, signature, signature
            self._list_pub.publish(String(data=db.to_json()))
            self._publish_status(db, "waiting", f"no map yet at {map_path}; it is loaded when it appears")
            self.get_logger().info(f"no map yet at {map_path} (wait_for_map): serving no objects until it appears")
            return None
        semantic_map = load_semantic_map(map_path, sem_path)
        staged = StagedBuild(semantic_map, self._config(), load_synonyms(syn_path), self._on_initial_build,
                             self._on_initial_build_failed)
        if len(semantic_map.means) < int(self.get_parameter("provisional_min_points").value):
            staged.run_now()  # a small map: the full database before the first answer
            db = staged.final
            if db is None:  # the build failed (reported by _on_initial_build_failed): nothing to serve
                raise MapLoadError(str(staged.error))
            with self._lock:
                self._db, self._signature, self._seen_signature = db, signature, signature
            self._publish(db)
            self._log_loaded(db, "loaded")
            return staged
        db = staged.provisional
        with self._lock:
            self._db, self._signature, self._seen_signature = db, signature, signature
        self._list_pub.publish(String(data=db.to_json()))
        self._publish_status(db, "provisional", f"class centroids in {staged.provisional_s:.3f} s; "
                                                "instances being built")
        return staged

    def _on_initial_build(self, db: ObjectDatabase) -> None:
        """Build thread: the full database of the start-up map replaces the provisional one."""
        if not self._staged_started:
            return  # run_now() in __init__: _load_initial installs it
        with self._lock:
            current = self._db
            replace = current is not None and current.provisional  # a reload may have come first
            if replace:
                self._db = db
        if replace:
            self._publish(db)
            self._log_loaded(db, "instances built for")

    def _on_initial_build_failed(self, exc: Exception) -> None:
        if not self._staged_started:
            return  # run_now() in __init__: _load_initial raises
        message = f"building instances failed, answering from class centroids: {exc}"
        self.get_logger().error(message)
        self._publish_status(self._snapshot(), "build_failed", message)

    def _publish_status(self, db: ObjectDatabase, state: str, message: str) -> None:
        doc = {"state": state, "objects": len(db.names()), "instances": db.instance_count(),
               "provisional_s": None, "build_s": round(db.stats.build_s, 4), "message": message}
        if db.provisional:
            doc["provisional_s"], doc["build_s"] = doc["build_s"], None
        self._status_pub.publish(String(data=json.dumps(doc)))

    def _log_loaded(self, db: ObjectDatabase, verb: str) -> None:
        for warning in db.warnings:
            self.get_logger().warning(warning)
        self.get_logger().info(f"{verb} {self._paths()[0]}: {db.summary()}")

    def _make_memory(self) -> MemoryInterface:
        """The object memory, loaded from its file (see the memory_path parameter)."""
        raw = str(self.get_parameter("memory_path").value).strip()
        map_path = str(self.get_parameter("map_path").value)
        path = None if raw.lower() == "none" else (raw or (default_memory_path(map_path) if map_path else None))
        config = MemoryConfig(match_radius=float(self.get_parameter("memory_match_radius").value))
        return MemoryInterface(self, path, str(self.get_parameter("frame_id").value), self._publish_object_list,
                               config=config)

    def _publish_object_list(self) -> None:
        """``/object_list``: each name's ``/object_query`` position (answers.object_list)."""
        with self._lock:
            db = self._db
        if db is None:
            return
        self._list_pub.publish(String(data=json.dumps(object_list(self.memory.memory, db))))

    def _publish(self, db: ObjectDatabase) -> None:
        mtime = [m for (_, m, _) in self._signature_now().entries[:1] if m >= 0]
        summary = self.memory.map_loaded(db, mtime[0] / 1e9 if mtime else None)  # also republishes /object_list
        self.get_logger().info(summary)
        self._publish_status(db, "ready", db.summary())
        frame = self.get_parameter("frame_id").value
        self._marker_pub.publish(database_markers(db, frame, self.get_clock().now().to_msg()))

    def _snapshot(self) -> ObjectDatabase:
        with self._lock:
            assert self._db is not None  # set in __init__ before any service exists
            return self._db

    def reload(self, reason: str) -> tuple[bool, str]:
        """Build a new database from the files and swap it in; on error keep the old one.

        Returns:
            ``(success, message)``; the message says what was loaded or why the old map was kept.
        """
        with self._reload_lock:
            # taken before reading: if a writer replaces the files while we read them, the next
            # poll sees a newer signature and loads again (never a good file marked as failed)
            signature = self._signature_now()
            try:
                db, signature = self._build(signature)
            except Exception as exc:  # noqa: BLE001 - any failure keeps the old map and is answered with its reason
                if not isinstance(exc, (MapLoadError, SynonymsError, ValueError, OSError, MemoryError)):
                    self.get_logger().error(f"reload: unexpected {exc!r}\n{traceback.format_exc()}")
                with self._lock:
                    self._failed_signature = signature
                    old = self._db
                kept = f"{len(old.names())} objects" if old is not None else "nothing"
                message = f"reload ({reason}) failed, keeping the previous map ({kept}): {exc}"
                self.get_logger().error(message)
                return False, message
            with self._lock:
                self._db, self._signature, self._seen_signature = db, signature, signature
                self._failed_signature = None
            self._publish(db)
            self._log_loaded(db, f"reloaded ({reason})")
            return True, f"reloaded ({reason}): {db.summary()}"

    # -- callbacks -------------------------------------------------------------------------------

    def _on_query(self, request: ObjectQuery.Request, response: ObjectQuery.Response) -> ObjectQuery.Response:
        refused = raw_name_error(request.name)
        if refused:
            response.found, response.message = False, refused
            return response
        result = answer_query(self.memory.memory, self._snapshot(), request.name)
        response.found = result.found
        response.position.x, response.position.y, response.position.z = result.position
        response.message = result.message
        return response

    def _on_instances(self, request: ObjectInstances.Request, response: ObjectInstances.Response
                      ) -> ObjectInstances.Response:
        ref = request.reference
        reference = (ref.x, ref.y, ref.z) if request.use_reference else None
        refused = raw_name_error(request.name)
        if refused:
            response.found, response.message = False, refused
            return response
        result = self._snapshot().instances(request.name, reference)
        response.found, response.name, response.message = result.found, result.name, result.message
        for inst, dist in zip(result.instances, result.distances, strict=True):
            response.instances.append(ObjectInstanceMsg(
                name=inst.name, label=inst.label, index=inst.index,
                centre=Point(x=inst.centre[0], y=inst.centre[1], z=inst.centre[2]),
                bbox_min=Point(x=inst.bbox_min[0], y=inst.bbox_min[1], z=inst.bbox_min[2]),
                bbox_max=Point(x=inst.bbox_max[0], y=inst.bbox_max[1], z=inst.bbox_max[2]),
                point_count=inst.point_count, distance=dist))
        return response

    def _on_reload(self, _request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        response.success, response.message = self.reload("reload service")
        return response

    def _on_poll(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, None
        if pending:
            self.reload(pending)
            return
        if not self.get_parameter("auto_reload").value:
            return
        signature = FileSignature.of(*[p for p in self._paths() if p])
        with self._lock:
            unchanged = signature in (self._signature, self._failed_signature)
            settled = signature == self._seen_signature  # same as one poll ago: the writer is done
            self._seen_signature = signature
        if not unchanged and settled:
            self.reload("map files changed")


#: How long shutdown waits for the start-up map's background build (seconds).
BUILD_JOIN_S = 10.0


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    node = build_node(ObjectQueryServer, "object_query_server", (MapLoadError, SynonymsError, ValueError))
    if node is None:
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    maintenance = SingleThreadedExecutor()
    maintenance.add_node(node.maintenance_node)
    maintenance_thread = threading.Thread(target=_spin_quietly, args=(maintenance,), name="maintenance", daemon=True)
    maintenance_thread.start()
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        maintenance.shutdown(timeout_sec=2.0)
        executor.shutdown(timeout_sec=2.0)
        maintenance_thread.join(3.0)  # before destroying: a live spin thread at exit aborts the process
        if not node.wait_background(BUILD_JOIN_S):
            node.get_logger().warning(f"the instance build is still running after {BUILD_JOIN_S:.0f} s; exiting anyway")
        node.maintenance_node.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


def _spin_quietly(executor: SingleThreadedExecutor) -> None:
    """Spin the maintenance executor until shutdown; a callback that raises is logged and the spinning goes on (the
    reload service and the file poll must outlive one bad map file)."""
    while True:
        try:
            executor.spin()
            return
        except ExternalShutdownException:
            return
        except Exception:  # noqa: BLE001 - logged; the executor is spun again
            if not rclpy.ok():
                return
            rclpy.logging.get_logger("object_query_server").error(f"maintenance: {traceback.format_exc()}")


if __name__ == "__main__":
    raise SystemExit(main())
