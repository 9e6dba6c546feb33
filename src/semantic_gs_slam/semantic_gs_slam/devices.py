"""Which torch device the engine runs on: ``SlamConfig.device`` resolved once (``auto`` = CUDA when present),
and whether the compiled CPU kernels (numba) can be used."""

from __future__ import annotations

import functools
import importlib.util
import re

import torch

from semantic_gs_slam.errors import BackendUnavailableError, ConfigError

DEVICE_PATTERN = re.compile(r"^(auto|cpu|cuda(:\d+)?)$")


@functools.cache
def numba_available() -> bool:
    """Whether numba is installed (without importing it: that costs ~0.4 s). numba is a wheel-world dependency
    (requirements/python.in); with a system ROS 2 it may be missing, and every ``auto`` choice then keeps the
    pure-PyTorch reference."""
    return importlib.util.find_spec("numba") is not None


def require_cpu_kernel(setting: str, device: torch.device | str) -> None:
    """Raise :class:`BackendUnavailableError` unless a compiled CPU kernel (numba) can run for ``device``.

    Args:
        setting: the setting that asked for it (``renderer.backend``, ``tracking.icp_backend``,
            ``mapping.ssim_backend``), named in the message.
        device: where the engine's tensors live.
    """
    if not numba_available():
        raise BackendUnavailableError(f"{setting} 'numba' needs the numba package (pip install numba; "
                                      "requirements/python.in pins it), or set it to 'auto' or 'torch'")
    if torch.device(device).type != "cpu":
        raise BackendUnavailableError(f"{setting} 'numba' runs on the CPU, the engine is on {device}; set it to "
                                      "'auto' or 'torch'")


def resolve_device(name: str | torch.device) -> torch.device:
    """The torch device for a config value.

    Args:
        name: ``"auto"`` (the first CUDA device when ``torch.cuda.is_available()``, else the CPU),
            ``"cpu"``, ``"cuda"`` or ``"cuda:N"`` (or a ``torch.device``).

    Returns:
        The device every tensor of the engine lives on.

    Raises:
        ConfigError: an unknown name, or CUDA asked for where this torch has none.
    """
    if isinstance(name, torch.device):
        return name
    if not DEVICE_PATTERN.match(name):
        raise ConfigError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {name!r}")
    if name == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    dev = torch.device(name)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"device {name!r} asked for, but torch {torch.__version__} sees no CUDA device; "
                              "use device 'auto' or 'cpu' (a CUDA machine: `make setup-gpu`)")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s) here")
    return dev
