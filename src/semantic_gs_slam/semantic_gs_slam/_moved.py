"""The engine's old module paths (from before it was laid out by concept), importable for one more release.

The package's ``__init__`` calls :func:`install`, which puts :class:`MovedFinder` on ``sys.meta_path``:
``import semantic_gs_slam.datasets`` then yields the module ``semantic_gs_slam.io.datasets`` itself (the same
object, so monkeypatching either name patches both) and a ``DeprecationWarning`` naming the new path. Three old
modules became packages of the same name (``tracking``, ``loop``, ``synthetic``); their old names
(``semantic_gs_slam.tracking.icp``) are forwarded, with the same warning, by the ``__getattr__`` that
:func:`forward` gives those packages. ``numba_kernels`` has no old path: it was split into one module per user
(``render``, ``tracking``, ``eval``) and only the engine's glue modules imported it.

The old commands ``python -m semantic_gs_slam.colour_registration`` and ``python -m semantic_gs_slam.demo_map``
(now ``semantic_gs_slam.io.calibrate_colour`` and ``semantic_gs_slam.synthetic.demo_map``) keep working, without a
warning (:data:`COMMANDS`): runpy asks the finder for the
old name's code, which is the new module's.

Nothing the engine writes names a module (maps and checkpoints are ``.npz`` arrays and JSON, read with
``allow_pickle=False``), so the move breaks no saved file.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import importlib.util
import sys
import warnings
from collections.abc import Callable
from types import ModuleType

_P = "semantic_gs_slam."

#: old module path -> new module path (whole modules moved, nothing else changed)
MOVED = {_P + old: _P + new for old, new in {
    "render_types": "render.types",
    "render_tiles": "render.tiles",
    "render_numba": "render.numba_backend",
    "render_gsplat": "render.gsplat_backend",
    "tracking_numba": "tracking.icp_numba",
    "gaussian_map": "mapping.gaussian_map",
    "posegraph": "loop.posegraph",
    "datasets": "io.datasets",
    "colour_registration": "io.colour_registration",
    "exposure": "io.exposure",
    "evaluate": "eval.evaluate",
    "metrics": "eval.metrics",
    "metrics_numba": "eval.metrics_numba",
    "demo_map": "synthetic.demo_map",
}.items()}

#: old module that is now a package of the same name -> the module its contents moved to
RENAMED_TO_PACKAGE = {_P + old: _P + new for old, new in {
    "tracking": "tracking.tracker",
    "loop": "loop.detection",
    "synthetic": "synthetic.scenes",
}.items()}

#: ``python -m OLD`` -> the module run as ``__main__`` (documented commands: no warning)
COMMANDS = {
    _P + "colour_registration": _P + "io.calibrate_colour",
    _P + "demo_map": _P + "synthetic.demo_map",
}


def _warn(old: str, new: str) -> None:
    """A DeprecationWarning attributed to the importer: the first frame outside this module and importlib's
    bootstrap (which ``warnings`` skips by itself when it counts ``stacklevel``)."""
    frame, level = sys._getframe(1), 2
    while frame is not None:
        name = frame.f_code.co_filename
        if name == __file__:
            level += 1
        elif not ("importlib" in name and "_bootstrap" in name):
            break
        frame = frame.f_back
    warnings.warn(f"{old} moved to {new}; the old path goes in the next release", DeprecationWarning,
                  stacklevel=level)


class _AliasLoader(importlib.abc.Loader):
    """Loads an old path as the already imported new module (no second copy)."""

    def __init__(self, old: str, new: str) -> None:
        self.old, self.new = old, new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:  # noqa: D102
        _warn(self.old, self.new)
        module = importlib.import_module(self.new)
        self._own_spec = module.__spec__
        return module

    def exec_module(self, module: ModuleType) -> None:  # noqa: D102
        # the import system has just set the alias spec on the module: give it back its own
        module.__spec__ = self._own_spec

    def is_package(self, fullname: str) -> bool:  # noqa: D102
        return False

    def get_code(self, fullname: str):  # noqa: D102, ANN201 (runpy: ``python -m OLD``)
        target = COMMANDS.get(self.old, self.new)
        return importlib.util.find_spec(target).loader.get_code(target)


class MovedFinder(importlib.abc.MetaPathFinder):
    """Finds the old module paths of :data:`MOVED` (and nothing else)."""

    def find_spec(self, fullname: str, path=None, target=None) -> importlib.machinery.ModuleSpec | None:  # noqa: D102
        new = MOVED.get(fullname)
        if new is None:
            return None
        run = COMMANDS.get(fullname, new)
        origin = importlib.util.find_spec(run).origin  # for ``python -m OLD``: __file__ and sys.argv[0]
        return importlib.util.spec_from_loader(fullname, _AliasLoader(fullname, new), origin=origin)


def install() -> None:
    """Put one :class:`MovedFinder` on ``sys.meta_path`` (idempotent)."""
    if not any(isinstance(f, MovedFinder) for f in sys.meta_path):
        sys.meta_path.append(MovedFinder())


def forward(package: str) -> Callable[[str], object]:
    """A module ``__getattr__`` for ``package``: names of the old module of that name, with a DeprecationWarning."""
    target = RENAMED_TO_PACKAGE[package]

    def __getattr__(name: str) -> object:
        if name.startswith("__"):
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        try:
            value = getattr(importlib.import_module(target), name)
        except AttributeError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        _warn(f"{package}.{name}", f"{target}.{name}")
        setattr(sys.modules[package], name, value)  # warned once: ``from package import name`` looks twice
        return value

    return __getattr__
