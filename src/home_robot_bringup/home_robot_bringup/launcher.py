"""``launch``: start a node set from ``config/nodesets.yaml`` as supervised processes.

The same node set and parameter files the ``*.launch.py`` files use, for machines without
ros2cli/launch_ros (e.g. ROS 2 from PyPI wheels)::

    ros_run home_robot_bringup launch object_query
    ros_run home_robot_bringup launch object_query --set object_query_server.map_path=/maps/params.npz
    ros_run home_robot_bringup launch --list

Each node's output lines are prefixed with its name (coloured on a terminal). Ctrl-C, SIGTERM,
or the death of any node stops all nodes (SIGINT → SIGTERM → SIGKILL). Exit code: 0 after
Ctrl-C/SIGTERM, else the exit code of the node that died.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys

import yaml

from home_robot_bringup.errors import BringupError
from home_robot_bringup.nodeset import NodeSpec, default_config_dir, load_nodeset, param_error, read_nodesets
from home_robot_bringup.process import Supervisor, node_environment


def declared_parameters(spec: NodeSpec) -> set[str]:
    """The parameters a node takes: those its params files list under its name (the files hold every parameter a
    node declares: ``test_param_defaults.py``), its inline ones, and ``use_sim_time``; empty when it has no file."""
    names: set[str] = set()
    for path in spec.params_files:
        try:
            with open(path, encoding="utf-8") as fh:
                doc = yaml.safe_load(fh) or {}
        except (OSError, yaml.YAMLError):
            continue
        for key in (spec.name, f"/{spec.name}", "/**"):
            section = doc.get(key) if isinstance(doc, dict) else None
            params = section.get("ros__parameters") if isinstance(section, dict) else None
            if isinstance(params, dict):
                names |= set(params)
    return names | set(spec.parameters) | {"use_sim_time"} if names else set()


def apply_overrides(specs: list[NodeSpec], sets: list[str]) -> list[NodeSpec]:
    """Apply ``NODE.PARAM=VALUE`` overrides (VALUE parsed as YAML: 3 → int, true → bool).

    Raises:
        BringupError: malformed override or unknown node name.
    """
    by_name = {s.name: s for s in specs}
    for item in sets:
        key, sep, raw = item.partition("=")
        node, dot, param = key.partition(".")
        if not sep or not dot or not node or not param:
            raise BringupError(f"--set {item!r}: expected NODE.PARAM=VALUE")
        if node not in by_name:
            raise BringupError(f"--set {item!r}: no node {node!r} in this set ({', '.join(by_name)})")
        try:
            value = yaml.safe_load(raw) if raw else ""
        except yaml.YAMLError:
            value = raw
        if value is None:
            raise BringupError(f"--set {item!r}: a parameter needs a value (null is none)")
        why = param_error(param, value)
        if why:
            raise BringupError(f"--set {item[:80]!r}: {why}")
        known = declared_parameters(by_name[node])
        if known and param not in known:  # a typo would start the node without the change
            raise BringupError(f"--set {item[:80]!r}: {node} has no parameter {param!r}; its parameters: "
                               f"{', '.join(sorted(known))}")
        by_name[node] = by_name[node].with_parameters(**{param: value})
    return [by_name[s.name] for s in specs]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="launch", description="Start a node set of the home robot.")
    ap.add_argument("nodeset", nargs="?", help="node set name (see --list)")
    ap.add_argument("--list", action="store_true", help="list the node sets and exit")
    ap.add_argument("--config-dir", default=None, help="config folder (default: installed home_robot_bringup/config)")
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE", help="override a parameter")
    ap.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for the nodes (default: inherited)")
    ap.add_argument("--ready-timeout", type=float, default=60.0, help="seconds to wait for every node to be ready")
    ap.add_argument("--no-color", action="store_true", help="plain prefixes")
    opts = ap.parse_args(argv)
    if not 0 < opts.ready_timeout < math.inf:
        ap.error(f"--ready-timeout must be a finite number of seconds > 0, got {opts.ready_timeout}")
    if opts.domain_id is not None and not 0 <= opts.domain_id <= 232:
        ap.error(f"--domain-id must be 0..232 (ROS 2's domain ids), got {opts.domain_id}")

    try:
        config_dir = opts.config_dir or default_config_dir()
        if opts.list or not opts.nodeset:
            for name, body in read_nodesets(config_dir).items():
                print(f"{name:20s} {(body or {}).get('description', '')}")
            return 0 if opts.list else 2
        specs = apply_overrides(load_nodeset(opts.nodeset, config_dir), opts.set)
    except BringupError as exc:
        print(f"launch: error: {exc}", file=sys.stderr)
        return 2

    env = node_environment(opts.domain_id)
    sup = Supervisor(specs, env, echo=sys.stdout, colour=False if opts.no_color else None)

    def _on_signal(signum: int, _frame: object) -> None:
        sup.request_stop()

    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    print(f"launch: node set {opts.nodeset!r}: {', '.join(s.name for s in specs)} "
          f"(ROS_DOMAIN_ID={env.get('ROS_DOMAIN_ID', '0')}, discovery LOCALHOST)", flush=True)
    try:
        sup.start()
        for p in sup.processes:
            print(f"launch: started {p.name} (pid {p.popen.pid})", flush=True)
        sup.wait_ready(opts.ready_timeout)
        print(f"launch: all {len(specs)} nodes ready (Ctrl-C stops them)", flush=True)
    except BringupError as exc:
        sup.stop()
        print(f"launch: error: {exc}", file=sys.stderr)
        return 1
    code = sup.wait()
    dead = [p for p in sup.processes if p.returncode() not in (None, 0, -signal.SIGINT, -signal.SIGTERM)]
    if code != 0:
        print(f"launch: stopped because a node exited (code {code})", file=sys.stderr)
    elif dead:
        print(f"launch: stopped; {', '.join(p.name for p in dead)} exited uncleanly", file=sys.stderr)
    else:
        print("launch: all nodes stopped", flush=True)
    return code


if __name__ == "__main__":
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    raise SystemExit(main())
