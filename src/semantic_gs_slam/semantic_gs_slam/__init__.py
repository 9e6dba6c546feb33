"""Semantic Gaussian-splatting RGB-D SLAM engine (pure Python/PyTorch, no rclpy).

Public API::

    from semantic_gs_slam import SLAM, SlamConfig, load_dataset

(imported on first use, so ``import semantic_gs_slam`` alone does not import torch).

Layout, by concept:

* ``slam`` — the engine (:class:`~semantic_gs_slam.slam.SLAM`): orchestrates the steps below per frame.
* ``render/`` — the differentiable renderer: the interface and back-end choice (``render/__init__``), the
  PyTorch reference, tile binning, the compiled CPU compositor (numba), gsplat (CUDA).
* ``tracking/`` — camera tracking: ICP against the rendered map, photometric refinement.
* ``mapping/`` — the Gaussian map, densification, the mapping loss and optimisation.
* ``loop/`` — loop detection, the pose graph, loop closure.
* ``io/`` — datasets, colour-to-depth registration, exposure.
* ``eval/`` — metrics (ATE, PSNR, SSIM, mIoU) and the evaluation of a run.
* ``synthetic/`` — the synthetic home the tests and the demo map use.
* ``labels/`` — semantic labels for frames (segmenters, class names).
* ``config``, ``errors``, ``devices``, ``device_guard``, ``geometry``, ``viewer``, ``run`` (the command line).

Old module paths (``semantic_gs_slam.datasets`` ...) still import, with a DeprecationWarning (:mod:`._moved`).
"""

import os

# torch's idle OpenMP workers spin briefly, then sleep (libgomp reads this once, when torch loads it, so only where
# this package is imported before torch, e.g. the nodes' entry points; scripts/env.sh sets it for every process): the
# tracking thread, the mapping thread and the robot's other nodes share a few cores (2 cores, `realtime` profile:
# 46 -> 72 FPS; the default profile unchanged). A value of the caller's own wins.
os.environ.setdefault("GOMP_SPINCOUNT", "20000")

from semantic_gs_slam import _moved  # noqa: E402

_moved.install()

__all__ = ["SLAM", "SlamConfig", "load_dataset"]


def __getattr__(name: str) -> object:
    if name == "SLAM":
        from semantic_gs_slam.slam import SLAM

        return SLAM
    if name == "SlamConfig":
        from semantic_gs_slam.config import SlamConfig

        return SlamConfig
    if name == "load_dataset":
        from semantic_gs_slam.io.datasets import load_dataset

        return load_dataset
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
