"""Differentiable Gaussian-splatting renderer: colour, depth, silhouette and semantic images.

This package's interface (:func:`render`, :func:`select_backend`) is the one place the back-end is chosen;
the back-ends behind it (:class:`~semantic_gs_slam.render.types.RenderBackend`) are picked once from the
config by :func:`select_backend`:

* ``torch`` (:mod:`semantic_gs_slam.render.reference`, :func:`render_torch`) — the reference: pure PyTorch, any
  device, used on CPU and in tests. Tiles of ``tile x tile`` pixels; each tile composites its depth-sorted Gaussians in
  chunks and stops once every pixel is done. Compositing has a hand-written backward
  (:class:`_Composite`): with the transmittance kept, the gradient of a pixel value with respect to a
  Gaussian's alpha is ``T_i (g . f_i) - S_i / (1 - alpha_i)`` where ``S_i`` is the suffix sum of
  ``w_k (g . f_k)`` over the Gaussians behind it, so no autograd graph of the [tiles, Gaussians,
  pixels] tensors is kept. Each Gaussian's exponent (plus its log-opacity) over a tile is a quadratic
  in the tile-local pixel coordinates, written as six coefficients, so a tile batch's exponents are
  one matmul.
* ``numba`` (:mod:`semantic_gs_slam.render.numba_backend`, kernels in
  :mod:`semantic_gs_slam.render.numba_kernels`) — the compiled CPU compositor.
* ``gsplat`` (:mod:`semantic_gs_slam.render.gsplat_backend`) — the CUDA fast path, only when gsplat and a GPU
  exist.

Projection and tile binning, shared by the CPU back-ends, are in :mod:`semantic_gs_slam.render.tiles`; the
types and gsplat's constants in :mod:`semantic_gs_slam.render.types`.

Conventions (gsplat 1.5.3's, see :mod:`semantic_gs_slam.render.types`): world-to-camera pose ``w2c``
[4, 4] (OpenCV camera); pixel (col c, row r) has its centre at (c, r) in our coordinates (gsplat puts
it at (c + 0.5, r + 0.5), so the gsplat adapter shifts the principal point by half a pixel);
opacity = 0.99 * sigmoid(logit); alphas below 1/255 are dropped; a pixel stops before the Gaussian
that would take its transmittance to <= 1e-4; the 2-D covariance gets +0.3 px^2 (classic mode: no
opacity compensation); the projection Jacobian clamps x/z, y/z to the image plus 0.15 x its size.
"""

from __future__ import annotations

import warnings

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.devices import numba_available, require_cpu_kernel
from semantic_gs_slam.render.gsplat_backend import (
    gsplat_available,
    load_gsplat_extension,
    render_gsplat,
    require_gsplat,
)
from semantic_gs_slam.render.numba_backend import render_numba
from semantic_gs_slam.render.reference import render_reference, render_torch
from semantic_gs_slam.render.tiles import footprint, jacobian_limits, project, project_rows
from semantic_gs_slam.render.types import (
    ALPHA_MIN,
    OPACITY_CAP,
    Gaussians,
    RenderBackend,
    RenderOutput,
)

__all__ = ["ALPHA_MIN", "OPACITY_CAP", "Gaussians", "RenderBackend", "RenderOutput", "footprint", "jacobian_limits",
           "project", "project_rows", "render", "render_reference", "render_torch", "select_backend"]

def select_backend(cfg: RendererConfig, device: torch.device | str = "cpu") -> RenderBackend:
    """The renderer back-end ``cfg.backend`` names (chosen once; the engine keeps the result).

    Args:
        cfg: renderer settings; ``backend="auto"`` picks gsplat when ``device`` is CUDA, gsplat
            imports and its CUDA code loads (built now if needed, see
            :func:`~semantic_gs_slam.render.gsplat_backend.load_gsplat_extension`; else a ``RuntimeWarning``),
            the compiled CPU compositor (numba) when ``device`` is the CPU and numba is installed, else
            the torch tiles (the reference).
        device: the device the Gaussians live on.

    Raises:
        BackendUnavailableError: ``gsplat`` or ``numba`` asked for where it (or CUDA, or gsplat's built CUDA
            code) is missing.
    """
    dev = torch.device(device).type
    if cfg.backend == "gsplat":
        require_gsplat()
        return render_gsplat
    if cfg.backend == "numba":
        require_cpu_kernel("renderer.backend", device)
        return render_numba
    if cfg.backend == "auto" and dev == "cuda" and gsplat_available():
        ok, why = load_gsplat_extension()
        if ok:
            return render_gsplat
        warnings.warn(f"renderer backend 'auto' on CUDA: gsplat's CUDA code did not build or load ({why}); "
                      "rendering with the PyTorch tiles instead (slower). `make setup-gpu` shows the build.",
                      RuntimeWarning, stacklevel=2)
    if cfg.backend == "auto" and dev == "cpu" and numba_available():
        return render_numba
    return render_torch


def render(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig | None = None) -> RenderOutput:
    """Render colour, depth, silhouette (and semantic) images with the back-end ``cfg`` names.

    Args:
        g: the Gaussians.
        w2c: [4, 4] world-to-camera pose (may require grad), on the Gaussians' device.
        k: camera intrinsics (image size included).
        cfg: renderer settings (back-end choice included).

    Returns:
        :class:`RenderOutput`.
    """
    cfg = cfg or RendererConfig()
    return select_backend(cfg, g.means.device)(g, w2c, k, cfg)
