"""SSIM's compiled CPU kernels (numba): separable blurs, value and gradient.

Imported only by :mod:`semantic_gs_slam.eval.metrics_numba` when it first runs, so the engine imports without numba.
Plain numpy-in, numpy-out functions at module level, so numba's on-disk cache (``cache=True``) finds them again in
the next process (defined inside another function, they were compiled anew in every process).
Their PyTorch reference and how they are compared: :mod:`semantic_gs_slam.eval.metrics_numba`.
"""

from __future__ import annotations

import numba
import numpy as np

C1, C2 = 0.01**2, 0.03**2  # SSIM's constants (for images in [0, 1])
# SSIM may reorder its sums (vectorised blurs), but keeps NaN and inf (the compositing kernels use strict IEEE
# arithmetic, see render/numba_kernels.py).
SSIM_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(cache=True, nogil=True, fastmath=SSIM_FASTMATH)
def ssim_blur(src, g, tmp, dst):
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

@numba.njit(cache=True, nogil=True, fastmath=SSIM_FASTMATH)
def ssim_forward(x, y, g):
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
    ssim_blur(stack, g, tmp, bl)
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

@numba.njit(cache=True, nogil=True, fastmath=SSIM_FASTMATH)
def ssim_backward(x, y, g, d, scale):
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
    ssim_blur(src, g, tmp, bl)
    gx = np.empty((c, h, w), np.float32)
    for k in range(c):
        for i in range(h):
            for j in range(w):
                gx[k, i, j] = (bl[3 * k, i, j] + 2 * x[k, i, j] * bl[3 * k + 1, i, j]
                               + y[k, i, j] * bl[3 * k + 2, i, j])
    return gx
