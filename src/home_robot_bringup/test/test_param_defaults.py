"""Every node's declared parameter defaults equal its params file in config/params/ (one truth).

The code defaults are the source of truth (``ros2 run <pkg> <exe>`` with no parameters must do
what the node sets do); the YAML files are the documented copy the launchers load. This test
builds each node in one child process with no parameters (real node classes, nothing patched),
reads what it declared, and compares names, types and values with the YAML. Change one side
only, and it fails.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from home_robot_bringup.nodeset import load_nodeset
from home_robot_bringup.process import node_environment

PARAMS_DIR = Path(__file__).resolve().parents[1] / "config" / "params"
NODESETS = Path(__file__).resolve().parents[1] / "config" / "nodesets.yaml"

#: node name (the params file key) -> (package, executable, "module:Class" that declares its parameters)
NODES = {
    "object_query_server": ("object_query", "object_query_server",
                            "object_query.object_query_server:ObjectQueryServer"),
    "decision_maker": ("decision_maker", "decision_maker_node", "decision_maker.decision_maker_node:DecisionMakerNode"),
    "mock_nav_server": ("decision_maker", "mock_nav_server", "decision_maker.mock_nav_server:MockNavServer"),
    "mock_grasp_server": ("decision_maker", "mock_grasp_server", "decision_maker.mock_grasp_server:MockGraspServer"),
    "audio_command_node": ("decision_maker", "audio_command_node",
                           "decision_maker.audio_command_node:AudioCommandNode"),
    "run_gs_slam_server": ("semantic_gs_slam_ros", "run_gs_slam_server",
                           "semantic_gs_slam_ros.run_gs_slam_server:SlamServer"),
    "run_gs_slam_client": ("semantic_gs_slam_ros", "run_gs_slam_client",
                           "semantic_gs_slam_ros.run_gs_slam_client:SlamClient"),
    "sim_camera": ("home_robot_exploration", "sim_camera_node", "home_robot_exploration.sim_camera_node:SimCameraNode"),
    "explorer": ("home_robot_exploration", "explorer_node", "home_robot_exploration.explorer_node:ExplorerNode"),
    "live_view": ("home_robot_exploration", "live_view_node", "home_robot_exploration.live_view_node:LiveViewNode"),
    "web_ui": ("home_robot_web", "web_ui_node", "home_robot_web.web_ui_node:WebUiNode"),
}
#: parameters every rclpy node has (not ours to document)
BUILTIN = {"use_sim_time", "start_type_description_service"}

_DUMP = """
import importlib, json, os, sys, traceback
import rclpy
rclpy.init()
out = {}
for target in sys.argv[1:]:
    try:
        mod, cls = target.split(":")
        node = getattr(importlib.import_module(mod), cls)()
        out[target] = {n: p.value for n, p in node.get_parameters_by_prefix("").items()}
        node.destroy_node()
    except Exception:
        out[target] = "did not build with no parameters:\\n" + traceback.format_exc()
print("PARAMS=" + json.dumps(out), flush=True)
os._exit(0)  # a node's own threads (web server, viewer) must not keep the process alive
"""


def yaml_params() -> dict[str, dict[str, object]]:
    """node name -> its ros__parameters, over every file in config/params/ (a node appears once)."""
    out: dict[str, dict[str, object]] = {}
    for path in sorted(PARAMS_DIR.glob("*.yaml")):
        doc = yaml.safe_load(path.read_text()) or {}
        for node, body in doc.items():
            assert node not in out, f"{node} is in two params files"
            out[node] = dict((body or {}).get("ros__parameters") or {})
    return out


def declared_defaults(targets: list[str], domain: int) -> dict[str, object]:
    """``module:Class`` -> the parameters that class declares when built with none (one child process builds them
    all in turn: real node classes, nothing patched; one interpreter and rclpy start instead of one per node)."""
    env = node_environment(domain)
    proc = subprocess.run([sys.executable, "-c", _DUMP, *targets], env=env, capture_output=True, text=True,
                          timeout=240, stdin=subprocess.DEVNULL)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("PARAMS=")]
    assert proc.returncode == 0 and lines, f"the nodes were not built:\n{proc.stdout}\n{proc.stderr}"
    dumped = json.loads(lines[-1][len("PARAMS="):])
    failed = [f"{t} {v}" for t, v in dumped.items() if isinstance(v, str)]
    assert not failed, "\n".join(failed) + "\n" + proc.stderr
    return {t: {k: v for k, v in params.items() if k not in BUILTIN} for t, params in dumped.items()}


def same(a: object, b: object) -> bool:
    """Equal with the same ROS parameter type (a YAML 1 is an integer, 1.0 a double)."""
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if type(a) is not type(b):
        return False
    return math.isclose(a, b) if isinstance(a, float) else a == b


def test_every_node_is_covered():
    """A node in nodesets.yaml or a params file without an entry here would escape the check."""
    in_sets = set()
    doc = yaml.safe_load(NODESETS.read_text())
    for name in doc["nodesets"]:
        in_sets |= {spec.name for spec in load_nodeset(name)}
    assert in_sets <= set(NODES), f"add these nodes to NODES: {sorted(in_sets - set(NODES))}"
    assert set(yaml_params()) == set(NODES), f"params files vs NODES: {sorted(set(yaml_params()) ^ set(NODES))}"


def compare(node: str, declared: dict[str, object], documented: dict[str, object]) -> list[str]:
    # (an empty list cannot be written in a ROS params file: its type is unknown; the YAML comments it)
    problems = [f"{node}.{k}: declared in code, missing in the params file" for k in sorted(declared.keys()
                                                                                           - documented.keys())
                if declared[k] != []]
    problems += [f"{node}.{k}: in the params file, not declared by the node" for k in sorted(documented.keys()
                                                                                            - declared.keys())]
    problems += [f"{node}.{k}: code default {declared[k]!r} != params file {documented[k]!r}"
                 for k in sorted(declared.keys() & documented.keys()) if not same(declared[k], documented[k])]
    return problems


def test_compare_finds_a_difference():
    """The comparison itself can fail: a changed value, a changed type, a missing name."""
    assert compare("n", {"a": 1.0, "b": "x"}, {"a": 1.0, "b": "x"}) == []
    assert compare("n", {"a": 1.0}, {"a": 2.0}) and compare("n", {"a": 1.0}, {"a": 1})
    assert compare("n", {"a": 1.0}, {}) and compare("n", {}, {"a": 1.0})
    assert compare("n", {"a": [1.0, 2.0]}, {"a": [1.0, 2]})
    assert compare("n", {"a": []}, {}) == []


@pytest.mark.ros
@pytest.mark.slow
def test_declared_defaults_equal_params_files(ros_domain):
    documented = yaml_params()
    by_target = declared_defaults([NODES[n][2] for n in NODES], ros_domain)
    declared = {n: by_target[NODES[n][2]] for n in NODES}
    problems = [p for node in NODES for p in compare(node, declared[node], documented.get(node, {}))]
    assert not problems, "code defaults and config/params/*.yaml disagree:\n  " + "\n  ".join(problems)
