"""Device discipline check: a ``TorchFunctionMode`` that records tensor factory calls without an explicit
device and host synchronisations made from inside the engine's modules.

Used by the CPU tests (a factory call that would put a tensor on the CPU while the engine runs on a
GPU fails them) and by ``bench/slam_synthetic.py --count-syncs`` (host round trips per frame)::

    with DeviceGuard() as guard:
        eng.add_frame(...)
        guard.end_frame()
    print(guard.syncs_per_frame, guard.violations)

A call is "from the engine" when the code calling torch (past torch's thin Python wrappers) is a
module of the ``semantic_gs_slam`` package (this module excluded); torch's internals are not counted.
Factories are allowed with ``device=`` given, and ``torch.tensor`` / ``torch.as_tensor`` of a tensor
(which keeps its device); ``*_like`` and ``Tensor.new_*`` calls take their source's device and are
not factories here. Host synchronisations
counted: ``.item()``, ``.cpu()``, ``.tolist()``, ``.numpy()``, ``bool()`` / ``float()`` / ``int()`` of
a tensor. (Data-dependent shapes, e.g. ``nonzero`` or boolean indexing, also wait for the GPU; they
are counted separately as ``implicit``.)
"""

from __future__ import annotations

import os
import sys
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

import torch
from torch.overrides import TorchFunctionMode

PACKAGE_DIR = os.path.dirname(os.path.abspath(__file__))
_TORCH_DIR = os.path.dirname(os.path.abspath(torch.__file__))
_SELF = os.path.abspath(__file__)

FACTORIES = {torch.zeros, torch.ones, torch.full, torch.empty, torch.arange, torch.linspace, torch.logspace,
             torch.eye, torch.rand, torch.randn, torch.randint, torch.randperm, torch.tensor, torch.as_tensor,
             torch.scalar_tensor, torch.empty_strided, torch.sparse_coo_tensor, torch.from_numpy}
SYNCS = {torch.Tensor.item: "item", torch.Tensor.cpu: "cpu", torch.Tensor.tolist: "tolist",
         torch.Tensor.numpy: "numpy", torch.Tensor.__bool__: "bool", torch.Tensor.__float__: "float",
         torch.Tensor.__int__: "int", torch.Tensor.__index__: "index"}
IMPLICIT = {torch.nonzero: "nonzero", torch.Tensor.nonzero: "nonzero", torch.unique: "unique",
            torch.Tensor.unique: "unique", torch.repeat_interleave: "repeat_interleave",
            torch.Tensor.repeat_interleave: "repeat_interleave", torch.masked_select: "masked_select",
            torch.Tensor.median: "median"}


_WRAPPERS = ("_tensor.py", "overrides.py", "functional.py")  # torch's thin Python wrappers of the public API


def _engine_caller() -> str | None:
    """``file:line`` of the code that called the torch function when it is an engine module, else None.

    torch's own internals (e.g. Adam reading its CPU step counter) are not the engine's calls."""
    f = sys._getframe(2)
    while f is not None:
        fn = os.path.abspath(f.f_code.co_filename)
        if fn == _SELF or (fn.startswith(_TORCH_DIR) and fn.endswith(_WRAPPERS)):
            f = f.f_back
            continue
        if fn.startswith(_TORCH_DIR):
            return None
        return f"{os.path.relpath(fn, PACKAGE_DIR)}:{f.f_lineno}" if fn.startswith(PACKAGE_DIR) else None
    return None


@dataclass
class DeviceGuard(TorchFunctionMode):
    """Records device-less factory calls (``violations``) and host syncs per frame from engine code.

    Attributes:
        violations: ``"file:line torch.zeros"`` of each factory call without a device.
        syncs: host synchronisations since the last :meth:`end_frame`, by kind.
        syncs_per_frame: total host synchronisations of each finished frame.
        sync_sites: ``file:line kind`` -> count over the whole run (where the syncs are).
        implicit_per_frame: data-dependent-shape operations of each finished frame.
    """

    violations: list[str] = field(default_factory=list)
    factory_calls: int = 0  # factory calls seen from engine code (with or without a device)
    syncs: Counter = field(default_factory=Counter)
    implicit: int = 0
    syncs_per_frame: list[int] = field(default_factory=list)
    implicit_per_frame: list[int] = field(default_factory=list)
    sync_sites: Counter = field(default_factory=Counter)

    def __post_init__(self) -> None:
        super().__init__()

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:  # noqa: D105
        kwargs = kwargs or {}
        if func in FACTORIES or func in SYNCS or func in IMPLICIT:
            where = _engine_caller()
            if where is not None:
                if func in FACTORIES:
                    self.factory_calls += 1
                    keeps = func in (torch.tensor, torch.as_tensor) and args and isinstance(args[0], torch.Tensor)
                    if kwargs.get("device") is None and not keeps:
                        self.violations.append(f"{where} torch.{getattr(func, '__name__', func)}")
                elif func in SYNCS:
                    self.syncs[SYNCS[func]] += 1
                    self.sync_sites[f"{where} {SYNCS[func]}"] += 1
                else:
                    self.implicit += 1
        return func(*args, **kwargs)

    def end_frame(self) -> int:
        """Close the current frame's counts; returns its number of host synchronisations."""
        n = sum(self.syncs.values())
        self.syncs_per_frame.append(n)
        self.implicit_per_frame.append(self.implicit)
        self.syncs = Counter()
        self.implicit = 0
        return n
