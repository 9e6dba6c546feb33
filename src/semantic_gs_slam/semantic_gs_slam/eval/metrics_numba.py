"""Compiled CPU SSIM with its gradient (numba): the fast path of :func:`semantic_gs_slam.eval.metrics.ssim`.

The reference is four lines of grouped ``conv2d`` (:func:`semantic_gs_slam.eval.metrics.ssim_reference`); on a CPU
those depthwise 1x11 convolutions run at about 1 GMAC/s, so SSIM took ~30 ms of a ~110 ms keyframe-mapping
iteration at 320x240 (forward and backward). Here the same separable Gaussian blurs (zero padding, as
``conv2d``'s ``padding``) are plain loops over image rows that the compiler vectorises, and the backward is
written out:

* forward, per channel: ``mx = G*x``, ``my = G*y``, ``sxx = G*x^2 - mx^2``, ``syy``, ``sxy = G*(xy) - mx my``,
  ``s = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sxx + syy + C2))``, the mean over pixels and channels;
  it also keeps ``ds/dmx``, ``ds/dE[x^2]`` and ``ds/dE[xy]`` per pixel.
* backward (``x`` only; ``y`` is the target): ``dL/dx = G*(g ds/dmx) + 2 x G*(g ds/dE[x^2]) + y G*(g ds/dE[xy])``
  (the blur is its own transpose: a symmetric kernel with zero padding).

One thread (no threading layer, safe from any Python thread), float32 images like the engine's.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.devices import require_cpu_kernel

__all__ = ["ssim_numba"]


@functools.cache
def _kernels():
    """The compiled kernels (:mod:`semantic_gs_slam.eval.numba_kernels`, which imports numba: only when used)."""
    from semantic_gs_slam.eval import numba_kernels as nk

    return nk.ssim_forward, nk.ssim_backward


class _SsimNumba(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a: Tensor, b: Tensor, window: Tensor) -> Tensor:  # noqa: D102
        fwd, _ = _kernels()
        x = a.detach().permute(2, 0, 1).contiguous().numpy()
        y = b.detach().permute(2, 0, 1).contiguous().numpy()
        g = window.detach().to(torch.float32).contiguous().numpy()
        s, d = fwd(x, y, g)
        ctx.state = (x, y, g, d)
        return torch.tensor(s, dtype=a.dtype, device=a.device)

    @staticmethod
    def backward(ctx, gout: Tensor):  # noqa: D102
        _, bwd = _kernels()
        x, y, g, d = ctx.state
        c, h, w = x.shape
        gx = bwd(x, y, g, d, np.float32(float(gout) / (c * h * w)))
        return torch.from_numpy(gx).permute(1, 2, 0), None, None


def ssim_numba(a: Tensor, b: Tensor, window: Tensor) -> Tensor:
    """Mean SSIM of ``a`` and ``b`` [H, W, C] (float32, CPU) with the 1-D Gaussian ``window`` [size] (odd).

    Differentiable in ``a`` only (``b`` is the target; its gradient is not computed).
    """
    require_cpu_kernel("mapping.ssim_backend", a.device)
    if b.requires_grad:
        raise ValueError("ssim_numba differentiates in its first image only; the second requires grad (use "
                         "metrics.ssim_reference)")
    if window.ndim != 1 or window.shape[0] % 2 != 1:
        raise ValueError(f"ssim_numba needs an odd 1-D window, got {list(window.shape)}")
    if a.dtype != torch.float32 or b.dtype != torch.float32 or a.device.type != "cpu" or b.device.type != "cpu":
        raise ValueError(f"ssim_numba takes float32 CPU images, got {a.dtype} on {a.device} and {b.dtype} on "
                         f"{b.device}")
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"ssim_numba needs two [H, W, C] images of one shape, got {list(a.shape)} and {list(b.shape)}")
    return _SsimNumba.apply(a, b, window)
