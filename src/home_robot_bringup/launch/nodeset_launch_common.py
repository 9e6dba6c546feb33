"""Shared helper of the launch files: a node set of config/nodesets.yaml → launch_ros Nodes.

Imported by the ``*.launch.py`` files next to it; reads the same YAML as our launcher.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch_ros.actions import Node


def nodeset_launch_description(nodeset: str) -> LaunchDescription:
    import yaml

    config_dir = os.path.join(get_package_share_directory("home_robot_bringup"), "config")
    with open(os.path.join(config_dir, "nodesets.yaml"), encoding="utf-8") as fh:
        sets = yaml.safe_load(fh)["nodesets"]

    def expand(name, seen=()):
        if name in seen:
            raise RuntimeError(f"include cycle at {name}")
        body = sets[name] or {}
        nodes = []
        for inc in body.get("include", []) or []:
            nodes += expand(inc, (*seen, name))
        return nodes + list(body.get("nodes", []) or [])

    actions = []
    for spec in expand(nodeset):
        params = [p if os.path.isabs(p) else os.path.join(config_dir, "params", p) for p in spec.get("params", [])]
        if spec.get("parameters"):
            params.append(dict(spec["parameters"]))
        actions.append(
            Node(
                package=spec["package"],
                executable=spec["executable"],
                name=spec["name"],
                parameters=params,
                arguments=[str(a) for a in spec.get("arguments", []) or []],
                output="screen",
                emulate_tty=True,
            )
        )
    return LaunchDescription(actions)
