#!/usr/bin/env python3
"""The seed's object_query_server, as its README describes it: the baseline of the start-up benchmark.

    python bench/object_query_naive_server.py MAP.npz SEMANTIC.json

Loads ``means3D`` and ``semantic_ids``, computes each class's centroid with one boolean mask over all
points per class (O(N·K)), publishes ``/object_list`` and serves ``/object_query``. Not a product node.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import rclpy
from object_query_interfaces.srv import ObjectQuery
from rclpy.node import Node
from std_msgs.msg import String


class NaiveObjectQueryServer(Node):
    def __init__(self, map_path: str, semantic_path: str) -> None:
        super().__init__("object_query_server")
        data = np.load(map_path)
        means, ids = data["means3D"], data["semantic_ids"].reshape(-1)
        with open(semantic_path, encoding="utf-8") as fh:
            classes = json.load(fh)["segmentation"]
        self.object_db: dict[str, np.ndarray] = {}
        for entry in classes:
            mask = ids == entry["id"]
            if mask.any():
                self.object_db[entry["class"].lower()] = means[mask].mean(axis=0)
        pub = self.create_publisher(String, "object_list", 10)
        pub.publish(String(data=json.dumps({k: v.tolist() for k, v in self.object_db.items()})))
        self.create_service(ObjectQuery, "object_query", self.on_query)
        self.get_logger().info(f"ready: {len(self.object_db)} objects")

    def on_query(self, request: ObjectQuery.Request, response: ObjectQuery.Response) -> ObjectQuery.Response:
        c = self.object_db.get(request.name.lower())
        response.found = c is not None
        if c is not None:
            response.position.x, response.position.y, response.position.z = (float(v) for v in c)
        response.message = "ok" if c is not None else "unknown"
        return response


def main() -> int:
    rclpy.init()
    node = NaiveObjectQueryServer(sys.argv[1], sys.argv[2])
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
