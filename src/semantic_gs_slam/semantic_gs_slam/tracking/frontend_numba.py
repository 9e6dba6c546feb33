"""Compiled CPU kernels of the tracking front end (numba, ``nogil=True``: a mapping thread runs beside them).

Each has a NumPy reference in :mod:`semantic_gs_slam.tracking.frontend` that ``test_tracking_frontend.py`` checks
it against:

* :func:`half_depth` - ``_half_depth`` (one pyramid step of a depth image);
* :func:`shrink_frame` - ``downsample_frame`` (depth and colour halved, in one call);
* :func:`model_level` - ``_backproject`` + ``_normals`` + the move to world coordinates in ``build_reference``;
* :func:`live_points` - the strided back-projection in ``prepare_live``;
* :func:`live_frame` - the whole of ``prepare_live`` in one call (the depth range, the pyramid, every level's points,
  the intensity);
* :func:`icp_level` - one pyramid level of ``track``'s Gauss-Newton loop: the sums of
  :func:`semantic_gs_slam.tracking.numba_kernels.icp_accumulate` (called from here, compiled together), the prior toward
  the guess, a Cholesky solve of the 6x6 system and the pose update, so a level is one call from Python instead of
  one per step (the per-step Python and NumPy glue cost as much as the sums at 320x240);
* :func:`icp_track` - every level of ``track`` and its score in one call;
* :func:`depth_speckle`, :func:`fill_isolated_holes` - their namesakes (a speckled camera's frames, every frame).

Plain numpy-in, numpy-out functions at module level (numba's on-disk cache finds them again); numba has no BLAS
here (no SciPy), so the small products are written out.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from semantic_gs_slam.tracking.numba_kernels import icp_accumulate

__all__ = ["depth_speckle", "fill_isolated_holes", "half_depth", "icp_level", "icp_track", "live_frame", "live_points",
           "model_level", "shrink_frame"]


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


@numba.njit(cache=True, nogil=True)
def shrink_frame(depth, rgb, times, jump, out_depth, out_rgb):
    """``downsample_frame`` in one call (the GIL is let go once, not once per NumPy operation): depth [H, W] and
    rgb [H, W, 3] (any float type) halved ``times`` times in float64 into out_depth [H / 2^t, W / 2^t] and out_rgb
    [H / 2^t, W / 2^t, 3]; depth as :func:`half_depth`, colour the mean of each 2x2 cell summed in NumPy's
    order ((top-left + bottom-left) + top-right) + bottom-right."""
    d = np.empty(depth.shape)
    c = np.empty(rgb.shape)
    for y in range(depth.shape[0]):
        for x in range(depth.shape[1]):
            d[y, x] = depth[y, x]
            for ch in range(3):
                c[y, x, ch] = rgb[y, x, ch]
    for _ in range(times):
        h, w = d.shape[0] // 2, d.shape[1] // 2
        d2 = np.empty((h, w))
        half_depth(d, jump, d2)
        c2 = np.empty((h, w, 3))
        for y in range(h):
            for x in range(w):
                for ch in range(3):
                    c2[y, x, ch] = (((c[2 * y, 2 * x, ch] + c[2 * y + 1, 2 * x, ch]) + c[2 * y, 2 * x + 1, ch])
                                    + c[2 * y + 1, 2 * x + 1, ch]) * 0.25
        d, c = d2, c2
    out_depth[:, :] = d
    out_rgb[:, :, :] = c


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


@numba.njit(cache=True, nogil=True)
def live_frame(depth, rgb, check_rgb, depth_min, depth_max, jump, fx, fy, cx, cy, strides, offsets, intensity, pts,
               valid, il):
    """``prepare_live`` in one call: depth [H, W] (float) limited to [depth_min, depth_max] and halved per level
    (:func:`half_depth`), every ``strides[l]``-th pixel of level l (camera fx[l], fy[l], cx[l], cy[l]) into rows
    offsets[l]..offsets[l + 1] of pts [M, 3] and valid [M], and, when ``intensity``, the mean colour of rgb
    [H, W, 3] at level 0's points into il [M_0]. Returns the counts of depth values and (when ``check_rgb``)
    colour values that are not finite (the caller refuses such a frame)."""
    bad_depth = 0
    bad_rgb = 0
    d = np.empty(depth.shape)
    for y in range(depth.shape[0]):
        for x in range(depth.shape[1]):
            v = np.float64(depth[y, x])
            if not np.isfinite(v):
                bad_depth += 1
            d[y, x] = v if (v >= depth_min and v <= depth_max) else 0.0
    if check_rgb:
        for y in range(rgb.shape[0]):
            for x in range(rgb.shape[1]):
                for ch in range(3):
                    if not np.isfinite(rgb[y, x, ch]):
                        bad_rgb += 1
    if intensity:
        s = strides[0]
        m = 0
        for y in range(0, rgb.shape[0], s):
            for x in range(0, rgb.shape[1], s):
                il[m] = ((np.float64(rgb[y, x, 0]) + np.float64(rgb[y, x, 1])) + np.float64(rgb[y, x, 2])) / 3.0
                m += 1
    for lv in range(len(strides)):
        if lv > 0:
            d2 = np.empty((d.shape[0] // 2, d.shape[1] // 2))
            half_depth(d, jump, d2)
            d = d2
        a, b = offsets[lv], offsets[lv + 1]
        live_points(d, fx[lv], fy[lv], cx[lv], cy[lv], strides[lv], pts[a:b], valid[a:b])
    return bad_depth, bad_rgb


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
              max_dist, sg, sg_z2, photometric, sc, w_col, iters, min_step):
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
                       sg_z2, 1.0, photometric, sc, w_col, a, b, stats, 0.0)
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


@numba.njit(cache=True, nogil=True)
def depth_roughness(depth, jump, min_pixels):
    """:func:`semantic_gs_slam.tracking.frontend.depth_roughness` of depth [H, W] in one call (its NumPy steps
    each wait for the GIL beside a mapping thread): the median of |d - the mean of the 4 neighbours| / d^2 over
    the pixels whose 4 neighbours have depth within ``jump`` times d; 0.0 below ``min_pixels`` such pixels."""
    h, w = depth.shape
    out = np.empty(max((h - 2) * (w - 2), 1))
    n = 0
    for y in range(1, h - 1):
        for x in range(1, w - 1):
            c = depth[y, x]
            if not c > 0:
                continue
            a0, a1, a2, a3 = depth[y - 1, x], depth[y + 1, x], depth[y, x - 1], depth[y, x + 1]
            lim = jump * c
            if not (a0 > 0 and a1 > 0 and a2 > 0 and a3 > 0 and abs(a0 - c) < lim and abs(a1 - c) < lim
                    and abs(a2 - c) < lim and abs(a3 - c) < lim):
                continue
            out[n] = abs(c - 0.25 * (a0 + a1 + a2 + a3)) / (c * c)
            n += 1
    if n < min_pixels:
        return 0.0
    return np.median(out[:n])


@numba.njit(cache=True, nogil=True)
def icp_track(est, guess_inv, prior_diag, w2c, lps, lvalids, il, vms, nms, nvalids, col, fx, fy, cx, cy, width,
              height, max_dist, sg, sg_z2, photometric, sc, w_col, iters, min_step, order, a, b, stats, score_z2,
              gate_z2):
    """``track``'s whole Gauss-Newton loop in one call: :func:`icp_level` on the levels in ``order`` (the tuples
    ``lps``, ``lvalids``, ``vms``, ``nms``, ``nvalids`` and the arrays fx ... max_dist, iters hold one entry per level;
    the intensity term, when ``photometric``, on level 0 only), then the sums at the last level's final estimate into
    a [6, 6], b [6] and stats [4] (:func:`icp_accumulate`, the score, at the scale ``score_z2`` instead of
    ``sg_z2``, a point z deep associated up to max(max_dist, ``gate_z2`` z^2) away). Returns (steps taken, live
    points with depth at the last level)."""
    steps = 0
    for n in range(len(order)):
        lv = order[n]
        steps += icp_level(est, guess_inv, prior_diag, w2c, lps[lv], lvalids[lv], il, vms[lv], nms[lv], nvalids[lv],
                           col, fx[lv], fy[lv], cx[lv], cy[lv], width[lv], height[lv], max_dist[lv], sg,
                           sg_z2, photometric and lv == 0, sc, w_col, iters[lv], min_step)
    last = order[len(order) - 1]
    icp_accumulate(est, w2c, lps[last], lvalids[last], il, vms[last], nms[last], nvalids[last], col, fx[last],
                   fy[last], cx[last], cy[last], width[last], height[last], max_dist[last], sg, score_z2, 1.0,
                   photometric and last == 0, sc, w_col, a, b, stats, gate_z2)
    n_live = 0
    for i in range(lvalids[last].shape[0]):
        if lvalids[last][i]:
            n_live += 1
    return steps, n_live


@numba.njit(cache=True, nogil=True)
def depth_speckle(depth):
    """:func:`semantic_gs_slam.tracking.frontend.depth_speckle` of depth [H, W] in one call: the fraction of pixels
    without depth whose 4 neighbours (outside the image: none) have depth for 3 or 4 of them."""
    h, w = depth.shape
    n = 0
    for y in range(h):
        for x in range(w):
            if depth[y, x] > 0:
                continue
            k = 0
            if y > 0 and depth[y - 1, x] > 0:
                k += 1
            if y < h - 1 and depth[y + 1, x] > 0:
                k += 1
            if x > 0 and depth[y, x - 1] > 0:
                k += 1
            if x < w - 1 and depth[y, x + 1] > 0:
                k += 1
            if k >= 3:
                n += 1
    return n / max(h * w, 1)


@numba.njit(cache=True, nogil=True)
def fill_isolated_holes(depth, lo, hi, jump, out):
    """:func:`semantic_gs_slam.tracking.frontend.fill_isolated_holes` of depth [H, W] with depth outside [lo, hi]
    taken as missing first (as ``prepare_live`` does), into out [H, W]: a hole with 4 or more of its 8 neighbours
    in range, all within ``jump`` times their mean of each other, takes that mean."""
    h, w = depth.shape
    for y in range(h):
        for x in range(w):
            c = depth[y, x]
            if c >= lo and c <= hi:
                out[y, x] = c
                continue
            out[y, x] = 0.0
            n = 0
            s = 0.0
            mx = -np.inf
            mn = np.inf
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    if dy == 0 and dx == 0:
                        continue
                    yy, xx = y + dy, x + dx
                    if yy < 0 or yy >= h or xx < 0 or xx >= w:
                        continue
                    v = depth[yy, xx]
                    if not (v >= lo and v <= hi and v > 0):
                        continue
                    n += 1
                    s += v
                    mx = max(mx, v)
                    mn = min(mn, v)
            if n >= 4:
                mean = s / n
                if mx - mn <= jump * mean:
                    out[y, x] = mean
