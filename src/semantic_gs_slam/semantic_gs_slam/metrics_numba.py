"""Compiled CPU SSIM with its gradient (numba): the fast path of :func:`semantic_gs_slam.metrics.ssim`.

The reference is four lines of grouped ``conv2d`` (:func:`semantic_gs_slam.metrics.ssim_reference`); on a CPU
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

__all__ = ["ssim_numba"]

C1, C2 = 0.01**2, 0.03**2


@functools.cache
def _kernels():  # pragma: no cover - compiled (its twin is metrics.ssim_reference)
    import numba

    @numba.njit(cache=True, nogil=True, fastmath=True)
    def blur(src, g, tmp, dst):
        """Separable blur of src [M, H, W] with the odd kernel g (zero padding) into dst; tmp is scratch."""
        m_, h, w = src.shape
        k = g.shape[0]
        r = k // 2
        pad = np.zeros(w + 2 * r, np.float32)  # one row with its zero border
        for m in range(m_):
            for y in range(h):
                pad[r:r + w] = src[m, y]
                for x in range(w):  # each output a short dot product (kept in a register)
                    acc = np.float32(0.0)
                    for t in range(k):
                        acc += g[t] * pad[x + t]
                    tmp[m, y, x] = acc
            for y in range(h):  # whole rows scaled and added (vectorised)
                for x in range(w):
                    dst[m, y, x] = 0.0
                for t in range(k):
                    yy = y + t - r
                    if 0 <= yy < h:
                        gt = g[t]
                        for x in range(w):
                            dst[m, y, x] += gt * tmp[m, yy, x]

    @numba.njit(cache=True, nogil=True, fastmath=True)
    def forward(x, y, g):
        """x, y [C, H, W] float32 -> (mean SSIM, d [3, C, H, W] per-pixel derivatives of s)."""
        c, h, w = x.shape
        stack = np.empty((5 * c, h, w), np.float32)
        for k in range(c):
            for i in range(h):
                for j in range(w):
                    a = x[k, i, j]
                    b = y[k, i, j]
                    stack[5 * k, i, j] = a
                    stack[5 * k + 1, i, j] = b
                    stack[5 * k + 2, i, j] = a * a
                    stack[5 * k + 3, i, j] = b * b
                    stack[5 * k + 4, i, j] = a * b
        tmp = np.empty_like(stack)
        bl = np.empty_like(stack)
        blur(stack, g, tmp, bl)
        d = np.empty((3, c, h, w), np.float32)
        total = 0.0
        for k in range(c):
            for i in range(h):
                row = np.float32(0.0)
                for j in range(w):
                    mx = bl[5 * k, i, j]
                    my = bl[5 * k + 1, i, j]
                    sxx = bl[5 * k + 2, i, j] - mx * mx
                    syy = bl[5 * k + 3, i, j] - my * my
                    sxy = bl[5 * k + 4, i, j] - mx * my
                    a1 = 2 * mx * my + np.float32(C1)
                    a2 = 2 * sxy + np.float32(C2)
                    b1 = mx * mx + my * my + np.float32(C1)
                    b2 = sxx + syy + np.float32(C2)
                    inv = np.float32(1.0) / (b1 * b2)  # the one division
                    sv = a1 * a2 * inv
                    row += sv
                    # ds/dmx = 2 my (a2 - a1) / (b1 b2) - s 2 mx (1 / b1 - 1 / b2), with 1/b1 = b2 inv, 1/b2 = b1 inv
                    d[0, k, i, j] = 2 * my * (a2 - a1) * inv - sv * 2 * mx * (b2 - b1) * inv
                    d[1, k, i, j] = -sv * b1 * inv  # ds/dE[x^2] = -s / b2
                    d[2, k, i, j] = 2 * a1 * inv  # ds/dE[xy] = 2 a1 / (b1 b2)
                total += row
        return total / (c * h * w), d

    @numba.njit(cache=True, nogil=True, fastmath=True)
    def backward(x, y, g, d, scale):
        """dL/dx [C, H, W] for dL/dSSIM = scale * N (the mean's 1/N folded into scale)."""
        c, h, w = x.shape
        src = np.empty((3 * c, h, w), np.float32)
        for q in range(3):
            for k in range(c):
                for i in range(h):
                    for j in range(w):
                        src[3 * k + q, i, j] = d[q, k, i, j] * scale
        tmp = np.empty_like(src)
        bl = np.empty_like(src)
        blur(src, g, tmp, bl)
        gx = np.empty((c, h, w), np.float32)
        for k in range(c):
            for i in range(h):
                for j in range(w):
                    gx[k, i, j] = (bl[3 * k, i, j] + 2 * x[k, i, j] * bl[3 * k + 1, i, j]
                                   + y[k, i, j] * bl[3 * k + 2, i, j])
        return gx

    return forward, backward


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
    if a.dtype != torch.float32 or b.dtype != torch.float32 or a.device.type != "cpu" or b.device.type != "cpu":
        raise ValueError(f"ssim_numba takes float32 CPU images, got {a.dtype} on {a.device} and {b.dtype} on "
                         f"{b.device}")
    if a.shape != b.shape or a.ndim != 3:
        raise ValueError(f"ssim_numba needs two [H, W, C] images of one shape, got {list(a.shape)} and {list(b.shape)}")
    return _SsimNumba.apply(a, b, window)
