"""No import cycle between the modules of the workspace's Python packages, read from the source with ``ast``.

Every package under ``src/`` (a folder with ``__init__.py`` whose parent has none) and every module in it is read;
the edges are its ``import`` and ``from ... import`` statements, absolute and relative, at module level and
inside functions, methods, ``try`` and ``if`` blocks alike. An import inside a function still couples the two
modules both ways and runs whenever the function does; it is the usual way a cycle is hidden (the renderer and its
compiled back-end were one such pair), so it counts. Not counted: the parent packages an import runs implicitly
(``import a.b.c`` runs ``a/__init__`` and ``a/b/__init__`` first, complete, before ``c``; counting them would make
every package that imports its own submodules a cycle), imports of modules outside ``src/``, and names built at
run time (``importlib.import_module(text)``).

``from package import name`` is an edge to the submodule ``package.name`` when there is one, else to the
package's ``__init__`` (where the name must then be defined).
"""

from __future__ import annotations

import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def find_modules(src: str) -> dict[str, str]:
    """Dotted module name -> file, for every package under ``src`` (``pkg/__init__.py`` is ``pkg``)."""
    modules = {}
    for dirpath, dirnames, filenames in os.walk(src):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and d != "__pycache__")
        if "__init__.py" not in filenames or os.path.isfile(os.path.join(os.path.dirname(dirpath), "__init__.py")):
            continue  # not a top-level package (its subpackages are walked from it below)
        top = os.path.dirname(dirpath)
        for sub, subdirs, files in os.walk(dirpath):
            subdirs[:] = sorted(d for d in subdirs if os.path.isfile(os.path.join(sub, d, "__init__.py")))
            parts = os.path.relpath(sub, top).split(os.sep)
            for f in files:
                if f.endswith(".py"):
                    name = parts if f == "__init__.py" else parts + [f[:-3]]
                    modules[".".join(name)] = os.path.join(sub, f)
        dirnames[:] = []  # the package's tree is done
    return modules


def imports_of(name: str, path: str, modules: dict[str, str]) -> set[str]:
    """The modules of ``modules`` that module ``name`` (file ``path``) imports anywhere in its source."""
    is_package = os.path.basename(path) == "__init__.py"
    package = name if is_package else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(open(path, encoding="utf-8").read(), path)):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join(base_parts + ([node.module] if node.module else []))
            else:
                base = node.module
            for a in node.names:
                sub = f"{base}.{a.name}"
                if sub in modules:
                    found.add(sub)
                elif base in modules:
                    found.add(base)
    found.discard(name)
    return found


def import_graph(src: str) -> dict[str, set[str]]:
    """Module -> the modules it imports, for every package under ``src``."""
    modules = find_modules(src)
    return {m: imports_of(m, p, modules) for m, p in modules.items()}


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle ``[a, b, ..., a]`` per strongly connected group of more than one module (Tarjan), sorted."""
    index, low, stack, on_stack, groups = {}, {}, [], set(), []
    counter = [0]

    def connect(v: str) -> None:  # recursion depth: the longest import chain (tens), well under the limit
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.add(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            connect(v)
    cycles = []
    for group in groups:  # a shortest path back to the group's first module, within the group (breadth first)
        start = min(group)
        prev, frontier = {start: None}, [start]
        while frontier and start not in [w for v in frontier for w in graph[v]]:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v] & group):
                    if w not in prev:
                        prev[w] = v
                        nxt.append(w)
            frontier = nxt
        last = next(v for v in frontier if start in graph[v])
        path = [last]
        while prev[path[-1]] is not None:
            path.append(prev[path[-1]])
        cycles.append(path[::-1] + [start])
    return sorted(cycles)


def test_no_import_cycle_in_any_package_under_src():
    graph = import_graph(os.path.join(ROOT, "src"))
    assert "semantic_gs_slam.render.numba_backend" in graph and "decision_maker.decision_maker_node" in graph
    assert "semantic_gs_slam.render.types" in graph["semantic_gs_slam.render.numba_backend"]  # edges are found
    cycles = find_cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles)


def _write(root, files: dict[str, str]) -> str:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return str(root)


def test_a_cycle_through_an_import_inside_a_function_is_found_and_named(tmp_path):
    src = _write(tmp_path, {
        "pkg/pkg/__init__.py": "",
        "pkg/pkg/a.py": "from pkg import b\n",
        "pkg/pkg/b.py": "import os\n\ndef f():\n    from . import a\n    return a, os\n",
        "pkg/pkg/c.py": "from pkg.b import f\n",  # into the cycle, not part of it
    })
    graph = import_graph(src)
    assert graph["pkg.c"] == {"pkg.b"} and graph["pkg.b"] == {"pkg.a"}  # os is outside src: no edge
    assert find_cycles(graph) == [["pkg.a", "pkg.b", "pkg.a"]]


def test_relative_imports_subpackages_and_a_package_init_in_a_cycle(tmp_path):
    src = _write(tmp_path, {
        "top/top/__init__.py": "from top.sub.x import X\n",
        "top/top/sub/__init__.py": "",
        "top/top/sub/x.py": "from ..util import helper\nX = 1\n",
        "top/top/util.py": "from top import X  # the package __init__, which imports sub.x\n",
        "other/other/__init__.py": "from .ok import Y\n",
        "other/other/ok.py": "import other.leaf\nY = other.leaf\n",
        "other/other/leaf.py": "import json\n",
    })
    graph = import_graph(src)
    assert graph["top.sub.x"] == {"top.util"} and graph["top.util"] == {"top"}
    assert graph["other"] == {"other.ok"} and graph["other.ok"] == {"other.leaf"}
    assert find_cycles(graph) == [["top", "top.sub.x", "top.util", "top"]]


@pytest.mark.parametrize("text", ["import pkg.a\n", "from pkg import a as alias\n", "from .a import thing\n",
                                  "try:\n    from pkg.a import thing\nexcept ImportError:\n    pass\n"])
def test_each_form_of_import_closes_a_cycle(tmp_path, text):
    src = _write(tmp_path, {"pkg/pkg/__init__.py": "", "pkg/pkg/a.py": "from pkg.b import x\n",
                            "pkg/pkg/b.py": "x = 1\n" + text})
    assert find_cycles(import_graph(src)) == [["pkg.a", "pkg.b", "pkg.a"]]
