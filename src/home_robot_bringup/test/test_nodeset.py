"""Unit tests of the node-set reader and parameter overrides (no ROS)."""

import os
import textwrap

import pytest

from home_robot_bringup.errors import BringupError, ExecutableNotFound, NodeSetError
from home_robot_bringup.launcher import apply_overrides
from home_robot_bringup.nodeset import NodeSpec, find_executable, format_param, load_nodeset, read_nodesets

REPO_CONFIG = os.path.join(os.path.dirname(__file__), "..", "config")


def test_every_node_set_has_its_launch_file():
    """``ros2 launch home_robot_bringup <set>.launch.py`` works for each set of nodesets.yaml, and a launch file
    names the set it is called after (each is the same three lines over nodeset_launch_common)."""
    import ast

    launch_dir = os.path.join(os.path.dirname(__file__), "..", "launch")
    files = {f[:-len(".launch.py")] for f in os.listdir(launch_dir) if f.endswith(".launch.py")}
    assert files == set(read_nodesets(REPO_CONFIG))
    for name in files:
        with open(os.path.join(launch_dir, f"{name}.launch.py")) as fh:
            tree = ast.parse(fh.read())
        calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") ==
                 "nodeset_launch_description"]
        assert [c.args[0].value for c in calls] == [name], name


def write_config(tmp_path, body: str, params: dict[str, str] | None = None) -> str:
    (tmp_path / "params").mkdir()
    (tmp_path / "nodesets.yaml").write_text(textwrap.dedent(body))
    for name, text in (params or {}).items():
        (tmp_path / "params" / name).write_text(text)
    return str(tmp_path)


def test_repository_node_sets_are_valid():
    """Every node set shipped in config/ loads: params files exist, no unknown keys, no dup names."""
    sets = read_nodesets(REPO_CONFIG)
    assert "object_query" in sets
    for name in sets:
        specs = load_nodeset(name, REPO_CONFIG)
        assert specs, f"node set {name} is empty"
        for spec in specs:
            assert all(os.path.isfile(f) for f in spec.params_files)


def test_include_order_and_param_paths(tmp_path):
    cfg = write_config(tmp_path, """
        nodesets:
          base:
            nodes:
              - {name: a, package: p, executable: ea, params: [a.yaml]}
          full:
            include: [base]
            nodes:
              - {name: b, package: p, executable: eb, parameters: {speed: 2.5}, ready: "ready:"}
        """, {"a.yaml": "a:\n  ros__parameters: {x: 1}\n"})
    specs = load_nodeset("full", cfg)
    assert [s.name for s in specs] == ["a", "b"]
    assert specs[0].params_files == (os.path.join(cfg, "params", "a.yaml"),)
    assert specs[1].ready == "ready:"
    args = specs[1].ros_args()
    assert args[:3] == ["--ros-args", "-r", "__node:=b"]
    assert args[-2:] == ["-p", "speed:=2.5"]


@pytest.mark.parametrize("body, message", [
    ("nodesets: {x: {nodes: [{name: a, package: p}]}}", "'executable'"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, colour: red}]}}", "unknown key"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, params: [nope.yaml]}]}}", "params file not found"),
    ("nodesets: {x: {include: [y]}, y: {include: [x]}}", "include cycle"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e}, {name: a, package: q, executable: e}]}}",
     "used twice"),
    ("nodes: []", "top-level 'nodesets:'"),
    ("nodesets: {x: [", "cannot read"),
    ("nodesets: {x: {include: 5}}", "'include' must be a list, got int"),
    ("nodesets: {x: {include: [[b]]}}", "'include' lists node set names"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, params: 5}]}}", "'params' must be a list"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, arguments: [[1]]}]}}", "'arguments' must be a"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, ready: '('}]}}", "'ready' must be a regular"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, ready: 5}]}}", "'ready' must be a regular"),
    ("nodesets: {x: {nodes: [{name: a, package: p, executable: e, parameters: {d: 2024-01-01}}]}}",
     "a parameter is a bool, a number, a string or a list"),
    ("nodesets: {x: {}}", "node set 'x' has no nodes"),
    ("nodesets: {x: [1]}", "node set 'x' must be a name with a mapping"),
    ("nodesets:\n  x: {nodes: [{name: a, package: p, executable: e}]}\n  x: {nodes: []}\n", "given twice: x"),
])
def test_malformed_node_sets_are_clear_errors(tmp_path, body, message):
    cfg = write_config(tmp_path, body)
    with pytest.raises(NodeSetError, match=message):
        load_nodeset("x", cfg)


def test_unknown_node_set_lists_known_ones(tmp_path):
    cfg = write_config(tmp_path, "nodesets: {alpha: {}, beta: {}}")
    with pytest.raises(NodeSetError, match="unknown node set 'gamma'; known: alpha, beta"):
        load_nodeset("gamma", cfg)


@pytest.mark.parametrize("value, text", [("123", '"123"'), ("/a b/c.npz", '"/a b/c.npz"'), (3, "3"),
                                         (2.5, "2.5"), (True, "true"), ([1, 2], "[1, 2]")])
def test_format_param_round_trips_through_yaml(value, text):
    import yaml

    assert format_param(value) == text
    assert yaml.safe_load(format_param(value)) == value


def test_overrides_parse_values_and_reject_bad_input():
    specs = [NodeSpec("srv", "p", "e"), NodeSpec("other", "p", "e")]
    out = apply_overrides(specs, ["srv.speed=3", "srv.path=/tmp/x.npz", "srv.flag=true", "srv.empty="])
    assert out[0].parameters == {"speed": 3, "path": "/tmp/x.npz", "flag": True, "empty": ""}
    assert out[1].parameters == {}
    for bad in ["srv", "srv=3", ".x=1", "nosuch.x=1"]:
        with pytest.raises(BringupError):
            apply_overrides(specs, [bad])
    for bad, words in [("srv.x=2024-01-01", "a parameter is a bool"), ("srv.x={a: 1}", "a parameter is a bool"),
                       ("srv.x=[1, a]", "a parameter is a bool"), ("srv.9x=1", "not a parameter name"),
                       ("srv.x=null", "needs a value"), ("srv.x=go \udc80", "not valid Unicode")]:
        with pytest.raises(BringupError, match=words):
            apply_overrides(specs, [bad])


def test_an_override_of_a_parameter_the_node_does_not_take_is_refused(tmp_path):
    """The params files list every parameter a node declares: a typo (voxel_sizee) would start it unchanged."""
    params = tmp_path / "srv.yaml"
    params.write_text("srv:\n  ros__parameters: {voxel_size: 0.1, map_path: ''}\n")
    specs = [NodeSpec("srv", "p", "e", params_files=(str(params),))]
    assert apply_overrides(specs, ["srv.voxel_size=0.2"])[0].parameters == {"voxel_size": 0.2}
    with pytest.raises(BringupError, match="srv has no parameter 'voxel_sizee'; its parameters: map_path, "
                                           "use_sim_time, voxel_size"):
        apply_overrides(specs, ["srv.voxel_sizee=0.2"])


def test_find_executable_uses_ros2_run_layout(tmp_path):
    exe = tmp_path / "prefix" / "lib" / "pkg" / "tool"
    exe.parent.mkdir(parents=True)
    exe.write_text("#!/bin/sh\n")
    exe.chmod(0o755)
    assert find_executable("pkg", "tool", f"/nonexistent:{tmp_path / 'prefix'}") == str(exe)
    with pytest.raises(ExecutableNotFound, match="make setup"):
        find_executable("pkg", "other", str(tmp_path / "prefix"))
