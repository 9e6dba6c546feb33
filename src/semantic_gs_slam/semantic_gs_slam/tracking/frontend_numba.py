"""Compiled CPU kernels of the tracking front end (numba, ``nogil=True``: a mapping thread runs beside them).

Each has a NumPy reference in :mod:`semantic_gs_slam.tracking.frontend` that ``test_tracking_frontend.py`` checks
it against:

* :func:`half_depth` - ``_half_depth`` (one pyramid step of a depth image);
* :func:`model_level` - ``_backproject`` + ``_normals`` + the move to world coordinates in ``build_reference``;
* :func:`live_points` - the strided back-projection in ``prepare_live``;
* :func:`icp_level` - one pyramid level of ``track``'s Gauss-Newton loop: the sums of
  :func:`semantic_gs_slam.tracking.numba_kernels.icp_accumulate` (called from here, compiled together), the prior toward
  the guess, a Cholesky solve of the 6x6 system and the pose update, so a level is one call from Python instead of
  one per step (the per-step Python and NumPy glue cost as much as the sums at 320x240).

Plain numpy-in, numpy-out functions at module level (numba's on-disk cache finds them again); numba has no BLAS
here (no SciPy), so the small products are written out.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from semantic_gs_slam.tracking.numba_kernels import icp_accumulate

__all__ = ["half_depth", "icp_level", "live_points", "model_level"]


@numba.njit(cache=True, nogil=True)
def half_depth(depth, jump, out):
    """out [H/2, W/2] = mean of each 2x2 cell of depth [H, W] whose four pixels have depth and agree within
    ``jump`` times their mean; 0 elsewhere."""
    for y in range(out.shape[0]):
        for x in range(out.shape[1]):
            a = depth[2 * y, 2 * x]
            b = depth[2 * y, 2 * x + 1]
            c = depth[2 * y + 1, 2 * x]
            d = depth[2 * y + 1, 2 * x + 1]
            lo = min(min(a, b), min(c, d))
            hi = max(max(a, b), max(c, d))
            mean = (((a + b) + c) + d) / 4.0
            out[y, x] = mean if (lo > 0 and hi - lo < jump * mean) else 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def _vertex(depth, x, y, fx, fy, cx, cy):
    d = depth[y, x]
    return (x - cx) / fx * d, (y - cy) / fy * d, d


@numba.njit(cache=True, nogil=True)
def model_level(depth, fx, fy, cx, cy, c2w, r, jump, vm, nm, nvalid):
    """World vertices vm [H*W, 3], unit normals nm [H*W, 3] (facing the camera; central differences over ``r``
    pixels, none across a depth jump) and their validity nvalid [H*W] of depth [H, W] seen from c2w [4, 4]."""
    h, w = depth.shape
    for y in range(h):
        for x in range(w):
            p = y * w + x
            d = depth[y, x]
            nvalid[p] = False
            for i in range(3):
                vm[p, i] = 0.0
                nm[p, i] = 0.0
            if not d > 0:
                continue
            v0, v1, v2 = _vertex(depth, x, y, fx, fy, cx, cy)
            for i in range(3):
                vm[p, i] = c2w[i, 0] * v0 + c2w[i, 1] * v1 + c2w[i, 2] * v2 + c2w[i, 3]
            if x < r or x >= w - r or y < r or y >= h - r:
                continue
            if not (depth[y, x + r] > 0 and depth[y, x - r] > 0 and depth[y + r, x] > 0 and depth[y - r, x] > 0):
                continue
            a0, a1, a2 = _vertex(depth, x + r, y, fx, fy, cx, cy)
            b0, b1, b2 = _vertex(depth, x - r, y, fx, fy, cx, cy)
            dx0, dx1, dx2 = a0 - b0, a1 - b1, a2 - b2
            a0, a1, a2 = _vertex(depth, x, y + r, fx, fy, cx, cy)
            b0, b1, b2 = _vertex(depth, x, y - r, fx, fy, cx, cy)
            dy0, dy1, dy2 = a0 - b0, a1 - b1, a2 - b2
            lim = 2 * r * jump * d
            if not (abs(dx2) < lim and abs(dy2) < lim):
                continue
            n0 = dx1 * dy2 - dx2 * dy1
            n1 = dx2 * dy0 - dx0 * dy2
            n2 = dx0 * dy1 - dx1 * dy0
            norm = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
            if not norm > 1e-12:
                continue
            n0, n1, n2 = n0 / norm, n1 / norm, n2 / norm
            if n0 * v0 + n1 * v1 + n2 * v2 > 0:
                n0, n1, n2 = -n0, -n1, -n2
            for i in range(3):
                nm[p, i] = c2w[i, 0] * n0 + c2w[i, 1] * n1 + c2w[i, 2] * n2
            nvalid[p] = True


@numba.njit(cache=True, nogil=True)
def live_points(depth, fx, fy, cx, cy, stride, pts, valid):
    """pts [M, 3] camera-frame points and valid [M] of every ``stride``-th pixel of depth [H, W] (row-major)."""
    h, w = depth.shape
    m = 0
    for y in range(0, h, stride):
        for x in range(0, w, stride):
            v0, v1, v2 = _vertex(depth, x, y, fx, fy, cx, cy)
            pts[m, 0], pts[m, 1], pts[m, 2] = v0, v1, v2
            valid[m] = v2 > 0
            m += 1


@numba.njit(cache=True, nogil=True, inline="always")
def _matmul4(a, b, out):
    for i in range(4):
        for j in range(4):
            s = 0.0
            for q in range(4):
                s += a[i, q] * b[q, j]
            out[i, j] = s


@numba.njit(cache=True, nogil=True)
def _so3_log(r, out):
    c = min(1.0, max(-1.0, (r[0, 0] + r[1, 1] + r[2, 2] - 1) / 2))
    th = math.acos(c)
    s = 0.5 if th < 1e-6 else th / (2 * max(math.sin(th), 1e-12))
    out[0] = (r[2, 1] - r[1, 2]) * s
    out[1] = (r[0, 2] - r[2, 0]) * s
    out[2] = (r[1, 0] - r[0, 1]) * s


@numba.njit(cache=True, nogil=True)
def _se3_exp(xi, t):
    w0, w1, w2 = xi[0], xi[1], xi[2]
    theta2 = w0 * w0 + w1 * w1 + w2 * w2
    theta = math.sqrt(theta2 + 1e-24)
    if theta2 < 1e-10:
        a = 1 - theta2 / 6
        b = 0.5 - theta2 / 24
    else:
        a = math.sin(theta) / theta
        b = (1 - math.cos(theta)) / (theta2 + 1e-24)
    k = np.array([[0.0, -w2, w1], [w2, 0.0, -w0], [-w1, w0, 0.0]])
    for i in range(3):
        for j in range(3):
            kk = 0.0
            for q in range(3):
                kk += k[i, q] * k[q, j]
            t[i, j] = (1.0 if i == j else 0.0) + a * k[i, j] + b * kk
        t[i, 3] = xi[3 + i]
        t[3, i] = 0.0
    t[3, 3] = 1.0


@numba.njit(cache=True, nogil=True)
def _solve_spd6(h, g, x):
    """x = h^-1 g for a symmetric positive definite [6, 6] h (Cholesky)."""
    lo = np.zeros((6, 6))
    for i in range(6):
        for j in range(i + 1):
            s = h[i, j]
            for q in range(j):
                s -= lo[i, q] * lo[j, q]
            if i == j:
                lo[i, i] = math.sqrt(max(s, 1e-300))
            else:
                lo[i, j] = s / lo[j, j]
    y = np.zeros(6)
    for i in range(6):
        s = g[i]
        for q in range(i):
            s -= lo[i, q] * y[q]
        y[i] = s / lo[i, i]
    for i in range(5, -1, -1):
        s = y[i]
        for q in range(i + 1, 6):
            s -= lo[q, i] * x[q]
        x[i] = s / lo[i, i]


@numba.njit(cache=True, nogil=True)
def icp_level(est, guess_inv, prior_diag, w2c, lp, lvalid, il, vm, nm, nvalid, col, fx, fy, cx, cy, width, height,
              max_dist, sg, photometric, sc, w_col, iters, min_step):
    """Up to ``iters`` Gauss-Newton steps of one pyramid level, updating est [4, 4] in place; returns the number
    of steps taken. A step: the sums (:func:`icp_accumulate`), plus the prior ``prior_diag`` [6] toward the guess
    (``guess_inv`` [4, 4] its inverse), solved; stops early once a step's largest component is below
    ``min_step``, or when fewer than 6 points correspond."""
    a = np.zeros((6, 6))
    b = np.zeros(6)
    stats = np.zeros(4)
    d = np.zeros((4, 4))
    t = np.zeros((4, 4))
    new = np.zeros((4, 4))
    rot = np.zeros(3)
    xi = np.zeros(6)
    g = np.zeros(6)
    steps = 0
    for _ in range(iters):
        a[:] = 0.0
        b[:] = 0.0
        stats[:] = 0.0
        icp_accumulate(est, w2c, lp, lvalid, il, vm, nm, nvalid, col, fx, fy, cx, cy, width, height, max_dist, sg,
                       1.0, photometric, sc, w_col, a, b, stats)
        if stats[0] < 6:
            break
        _matmul4(est, guess_inv, d)
        _so3_log(d, rot)
        mean_diag = 0.0
        for i in range(6):
            a[i, i] += prior_diag[i]
            mean_diag += a[i, i]
        mean_diag /= 6.0
        for i in range(6):
            a[i, i] += 1e-9 * mean_diag
            prior = rot[i] if i < 3 else d[i - 3, 3]
            g[i] = b[i] - prior_diag[i] * prior
        _solve_spd6(a, g, xi)
        _se3_exp(xi, t)
        _matmul4(t, est, new)
        est[:, :] = new
        steps += 1
        big = 0.0
        for i in range(6):
            big = max(big, abs(xi[i]))
        if big < min_step:
            break
    return steps
