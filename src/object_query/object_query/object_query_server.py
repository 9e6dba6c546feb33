"""ROS 2 shell of the object database: ``/object_query`` service and ``/object_list`` topic.

Parameters:
    map_path (str): ``params.npz`` of the map; empty = the bundled sample map.
    semantic_path (str): ``semantic.json`` of the map; empty = the bundled sample map's.
"""

from __future__ import annotations

import os

import rclpy
from object_query_interfaces.srv import ObjectQuery
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_msgs.msg import String

from object_query.errors import MapLoadError
from object_query.semantic_map import ObjectDatabase

#: Latched: a node that subscribes later still receives the last object list.
OBJECT_LIST_QOS = QoSProfile(
    depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE
)


def bundled_map_paths() -> tuple[str, str]:
    """Paths of the sample map installed with this package (share/object_query/data)."""
    from ament_index_python.packages import get_package_share_directory

    share = get_package_share_directory("object_query")
    return os.path.join(share, "data", "params.npz"), os.path.join(share, "data", "semantic.json")


class ObjectQueryServer(Node):
    def __init__(self) -> None:
        super().__init__("object_query_server")
        self.declare_parameter("map_path", "")
        self.declare_parameter("semantic_path", "")
        default_map, default_sem = bundled_map_paths()
        map_path = self.get_parameter("map_path").value or default_map
        semantic_path = self.get_parameter("semantic_path").value or default_sem
        # Raises MapLoadError, reported by main(): without a map there is nothing to serve.
        self._db = ObjectDatabase.from_files(map_path, semantic_path)
        self._list_pub = self.create_publisher(String, "object_list", OBJECT_LIST_QOS)
        self._srv = self.create_service(ObjectQuery, "object_query", self._on_query)
        self._list_pub.publish(String(data=self._db.to_json()))
        self.get_logger().info(
            f"ready: {len(self._db.names())} objects from {map_path} ({', '.join(self._db.names())})"
        )

    def _on_query(self, request: ObjectQuery.Request, response: ObjectQuery.Response) -> ObjectQuery.Response:
        result = self._db.query(request.name)
        response.found = result.found
        response.position.x, response.position.y, response.position.z = result.position
        response.message = result.message
        return response


def main(args: list[str] | None = None) -> int:
    rclpy.init(args=args)
    try:
        node = ObjectQueryServer()
    except MapLoadError as exc:
        rclpy.logging.get_logger("object_query_server").fatal(f"cannot load map: {exc}")
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


if __name__ == "__main__":
    raise SystemExit(main())
