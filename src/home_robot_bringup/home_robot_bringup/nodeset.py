"""Node sets: which nodes run together, with which parameters (pure, no ROS).

``config/nodesets.yaml`` is the one source of truth, read both by the ``*.launch.py`` files
(``ros2 launch``) and by our launcher. Schema::

    nodesets:
      <set name>:
        description: text
        include: [<other set>, ...]          # optional; their nodes come first
        nodes:
          - name: object_query_server        # ROS node name (also the log prefix)
            package: object_query
            executable: object_query_server
            params: [object_query.yaml]      # files under config/params/ (ROS params-file format)
            parameters: {key: value}         # optional inline overrides
            arguments: []                    # optional extra CLI arguments
            ready: "ready"                   # optional regex on the node's output meaning "up"
            stdin: false                     # optional: node reads the launcher's terminal
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field, replace
from typing import Any

import yaml

from home_robot_bringup.errors import NodeSetError

_NODE_KEYS = {"name", "package", "executable", "params", "parameters", "arguments", "ready", "stdin"}


@dataclass(frozen=True)
class NodeSpec:
    """One node of a node set, with parameter files resolved to absolute paths."""

    name: str
    package: str
    executable: str
    params_files: tuple[str, ...] = ()
    parameters: dict[str, Any] = field(default_factory=dict)
    arguments: tuple[str, ...] = ()
    ready: str | None = None
    stdin: bool = False

    def ros_args(self) -> list[str]:
        """Command-line arguments for the node's executable (``--ros-args`` form)."""
        args = [*self.arguments, "--ros-args", "-r", f"__node:={self.name}"]
        for f in self.params_files:
            args += ["--params-file", f]
        for key, value in self.parameters.items():
            args += ["-p", f"{key}:={format_param(value)}"]
        return args

    def with_parameters(self, **overrides: Any) -> NodeSpec:
        return replace(self, parameters={**self.parameters, **overrides})


def format_param(value: Any) -> str:
    """A value as rcl's ``-p name:=value`` parser (YAML) reads it back unchanged.

    JSON is YAML: strings come out double-quoted, so ``"123"`` stays a string.
    """
    return json.dumps(value)


#: A ROS parameter's name: letters, digits, ``_`` and ``.`` (nested), not starting with a digit
_PARAM_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")


def param_error(name: Any, value: Any) -> str:
    """Why ``name: value`` cannot be a ROS parameter ("" when it can): a name rcl accepts, and a value that is a
    bool, a number, a string (valid Unicode) or a list of one of those kinds."""
    if not isinstance(name, str) or not _PARAM_NAME.fullmatch(name):
        return f"{str(name)[:60]!r} is not a parameter name (letters, digits, '_', '.')"
    items = value if isinstance(value, list) else [value]
    kinds = {bool if isinstance(v, bool) else float if isinstance(v, int | float) else type(v) for v in items}
    if not kinds <= {bool, float, str} or len(kinds) > 1 and isinstance(value, list):
        return (f"{name}: a parameter is a bool, a number, a string or a list of one of those, got "
                f"{str(value)[:60]!r}")
    for v in items:
        if isinstance(v, str):
            try:
                v.encode("utf-8")
            except UnicodeEncodeError:
                return f"{name}: the value is not valid Unicode text"
    return ""


def default_config_dir() -> str:
    """``share/home_robot_bringup/config`` of the installed package."""
    from ament_index_python.packages import get_package_share_directory

    return os.path.join(get_package_share_directory("home_robot_bringup"), "config")


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader, refusing a key given twice in one mapping (YAML would keep the last silently)."""

    def construct_mapping(self, node, deep=False):  # noqa: ANN001, ANN201 - PyYAML's signature
        keys = [self.construct_object(k, deep=deep) for k, _ in node.value]
        twice = sorted({str(k) for k in keys if keys.count(k) > 1})
        if twice:
            raise yaml.constructor.ConstructorError(None, None, f"key(s) given twice: {', '.join(twice)}",
                                                    node.start_mark)
        return super().construct_mapping(node, deep=deep)


def read_nodesets(config_dir: str) -> dict[str, Any]:
    path = os.path.join(config_dir, "nodesets.yaml")
    try:
        with open(path, encoding="utf-8") as fh:
            doc = yaml.load(fh, Loader=_UniqueKeyLoader)  # noqa: S506 - a SafeLoader
    except (OSError, yaml.YAMLError) as exc:
        raise NodeSetError(f"cannot read {path}: {exc}") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("nodesets"), dict):
        raise NodeSetError(f"{path}: expected a top-level 'nodesets:' mapping")
    for name, body in doc["nodesets"].items():
        if not isinstance(name, str) or not (body is None or isinstance(body, dict)):
            raise NodeSetError(f"{path}: node set {name!r} must be a name with a mapping under it")
    return doc["nodesets"]


def load_nodeset(name: str, config_dir: str | None = None) -> list[NodeSpec]:
    """The nodes of set ``name`` (includes expanded, in order), with absolute params-file paths.

    Raises:
        NodeSetError: unknown set, include cycle, unknown keys, missing fields or files.
    """
    config_dir = config_dir or default_config_dir()
    sets = read_nodesets(config_dir)
    specs: list[NodeSpec] = []
    _expand(name, sets, config_dir, specs, stack=())
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise NodeSetError(f"node set {name!r}: node name(s) used twice: {dup}")
    return specs


def _expand(name: str, sets: dict, config_dir: str, out: list[NodeSpec], stack: tuple[str, ...]) -> None:
    if name not in sets:
        raise NodeSetError(f"unknown node set {name!r}; known: {', '.join(sorted(sets))}")
    if name in stack:
        raise NodeSetError(f"include cycle: {' -> '.join((*stack, name))}")
    body = sets[name] or {}
    if not isinstance(body, dict):
        raise NodeSetError(f"node set {name!r} must be a mapping")
    for key in ("include", "nodes"):
        if not isinstance(body.get(key, []) or [], list):
            raise NodeSetError(f"node set {name!r}: {key!r} must be a list, got {type(body[key]).__name__}")
    for inc in body.get("include", []) or []:
        if not isinstance(inc, str):
            raise NodeSetError(f"node set {name!r}: 'include' lists node set names, got {inc!r}")
        _expand(inc, sets, config_dir, out, (*stack, name))
    if not stack and not body.get("nodes") and not body.get("include"):
        raise NodeSetError(f"node set {name!r} has no nodes")
    for i, node in enumerate(body.get("nodes", []) or []):
        where = f"node set {name!r}, node #{i}"
        if not isinstance(node, dict):
            raise NodeSetError(f"{where}: must be a mapping")
        unknown = set(node) - _NODE_KEYS
        if unknown:
            raise NodeSetError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(_NODE_KEYS)}")
        for req in ("name", "package", "executable"):
            if not isinstance(node.get(req), str) or not node[req]:
                raise NodeSetError(f"{where}: '{req}' (a non-empty string) is required")
        for key in ("params", "arguments"):
            value = node.get(key, []) or []
            if not isinstance(value, list) or not all(isinstance(v, str | int | float) and not isinstance(v, bool)
                                                      for v in value):
                raise NodeSetError(f"{where} ({node['name']}): {key!r} must be a list of strings, got {value!r}"[:300])
        ready = node.get("ready")
        if ready is not None:
            try:
                re.compile(ready)
            except (TypeError, re.error) as exc:
                raise NodeSetError(f"{where} ({node['name']}): 'ready' must be a regular expression ({exc})") from exc
        files = []
        for f in node.get("params", []) or []:
            path = f if os.path.isabs(f) else os.path.join(config_dir, "params", f)
            if not os.path.isfile(path):
                raise NodeSetError(f"{where} ({node['name']}): params file not found: {path}")
            files.append(path)
        params = node.get("parameters", {}) or {}
        if not isinstance(params, dict):
            raise NodeSetError(f"{where}: 'parameters' must be a mapping")
        for key, value in params.items():
            why = param_error(key, value)
            if why:
                raise NodeSetError(f"{where} ({node['name']}): {why}")
        out.append(
            NodeSpec(
                name=node["name"],
                package=node["package"],
                executable=node["executable"],
                params_files=tuple(files),
                parameters=dict(params),
                arguments=tuple(str(a) for a in node.get("arguments", []) or []),
                ready=node.get("ready"),
                stdin=bool(node.get("stdin", False)),
            )
        )


def find_executable(package: str, executable: str, prefixes: str | None = None) -> str:
    """``<prefix>/lib/<package>/<executable>`` from ``AMENT_PREFIX_PATH`` (the ``ros2 run`` layout)."""
    from home_robot_bringup.errors import ExecutableNotFound

    prefixes = os.environ.get("AMENT_PREFIX_PATH", "") if prefixes is None else prefixes
    for prefix in filter(None, prefixes.split(os.pathsep)):
        path = os.path.join(prefix, "lib", package, executable)
        if os.path.isfile(path) and os.access(path, os.X_OK):
            return path
    raise ExecutableNotFound(
        f"{package}/{executable} not found under AMENT_PREFIX_PATH — build the workspace "
        "(make setup) and `source scripts/env.sh`"
    )
