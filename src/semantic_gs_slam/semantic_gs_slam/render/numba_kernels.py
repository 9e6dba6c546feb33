"""The renderer's compiled CPU kernels (numba): compositing forward and backward, binning pairs by tile.

Imported only by :mod:`semantic_gs_slam.render.numba_backend` when it first renders, so the engine imports
without numba. The ICP and SSIM kernels live beside their users (:mod:`semantic_gs_slam.tracking.numba_kernels`,
:mod:`semantic_gs_slam.eval.numba_kernels`); compiling all of them takes about 16 s.

Plain numpy-in, numpy-out functions at module level, so numba's on-disk cache (``cache=True``) finds them again in
the next process (defined inside another function, they were compiled anew in every process).
Each has a PyTorch reference it is tested against; the glue module's docstring says which and how.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from semantic_gs_slam.render.types import ALPHA_MIN

f32 = numba.float32
#: exponent below which alpha < ALPHA_MIN for sure (the exact test is on alpha itself)
_LOG_ALPHA_SKIP = math.log(ALPHA_MIN) - 1e-3
# The compositing kernels use strict IEEE arithmetic: the backward must take the same alpha-threshold and
# early-stop decisions as the forward, which a contracted or reassociated exponent in one of the two could flip, and
# NaN must propagate as in the reference (the SSIM kernels, eval/numba_kernels.py, may reorder their sums).


@numba.njit(cache=True, nogil=True)
def tile_coefficients(uv, conic, log_o, pg, s0, n, x0, y0, lc):
    """The six exponent coefficients of the tile's pairs s0 .. s0 + n - 1 in tile-local pixels (as
    render_tiles.tile_pairs writes them) into lc[:n]; the tile's corner pixel is (x0, y0)."""
    half = f32(0.5)
    for q in range(n):
        i = pg[s0 + q]
        du = uv[i, 0] - f32(x0)
        dv = uv[i, 1] - f32(y0)
        a, b, c = conic[i, 0], conic[i, 1], conic[i, 2]
        lc[q, 0] = -half * a * du * du - b * du * dv - half * c * dv * dv + log_o[i]
        lc[q, 1] = a * du + b * dv
        lc[q, 2] = b * du + c * dv
        lc[q, 3] = -half * a
        lc[q, 4] = -b
        lc[q, 5] = -half * c

@numba.njit(cache=True, nogil=True, inline="always")
def pair_alpha(lc, p, fi, fj, fii, fij, fjj, skip, amin):
    """Alpha of the tile's pair p at the tile-local pixel (fi, fj), 0 where it is below 1/255. The forward and the
    backward both call this, so they take the same decisions to the last bit."""
    pw = lc[p, 0] + lc[p, 1] * fi + lc[p, 2] * fj + lc[p, 3] * fii + lc[p, 4] * fij + lc[p, 5] * fjj
    if pw < skip:
        return f32(0.0)
    a = math.exp(pw)
    if a < amin:
        return f32(0.0)
    return a


@numba.njit(cache=True, nogil=True, parallel=True)
def composite_forward(uv, conic, log_o, feat, pg, tstart, tcount, order, maxn, ntx, ts, height, width, stop, nw, out,
            t_final, n_done):
    c = feat.shape[1]
    n_t = order.shape[0]
    st = f32(stop)
    skip = f32(_LOG_ALPHA_SKIP)
    amin = f32(ALPHA_MIN)
    one = f32(1.0)
    for w in numba.prange(nw):
        acc = np.zeros(c + 1, np.float32)
        lc = np.empty((maxn, 6), np.float32)
        for q in range(w, n_t, nw):
            t = order[q]
            s0 = tstart[t]
            n = tcount[t]
            y0 = (t // ntx) * ts
            x0 = (t % ntx) * ts
            tile_coefficients(uv, conic, log_o, pg, s0, n, x0, y0, lc)
            for j in range(ts):
                y = y0 + j
                if y >= height:
                    break
                fj = f32(j)
                for i in range(ts):
                    x = x0 + i
                    if x >= width:
                        break
                    fi = f32(i)
                    fii, fij, fjj = fi * fi, fi * fj, fj * fj
                    for ch in range(c + 1):
                        acc[ch] = 0
                    tr = one
                    walked = n
                    for p in range(n):
                        a = pair_alpha(lc, p, fi, fj, fii, fij, fjj, skip, amin)
                        if a == 0:
                            continue
                        tn = tr * (one - a)
                        if tn <= st:
                            walked = p
                            break
                        wt = a * tr
                        gi = pg[s0 + p]
                        for ch in range(c):
                            acc[ch] += wt * feat[gi, ch]
                        acc[c] += wt
                        tr = tn
                    for ch in range(c + 1):
                        out[ch, y, x] = acc[ch]
                    t_final[y, x] = tr
                    n_done[y, x] = walked

@numba.njit(cache=True, nogil=True, parallel=True)
def composite_backward(uv, conic, log_o, feat, pg, tstart, tcount, order, maxn, ntx, ts, height, width, nw, t_final,
                       n_done, gout, g_uv, g_conic, g_logo, g_feat):
    c = feat.shape[1]
    n_t = order.shape[0]
    pairs = pg.shape[0]
    skip = f32(_LOG_ALPHA_SKIP)
    amin = f32(ALPHA_MIN)
    one = f32(1.0)
    half = f32(0.5)
    g_geo = np.zeros((pairs, 6), np.float32)  # per pair: d/du, d/dv, d/da, d/db, d/dc, d/dlog_o
    g_fp = np.zeros((pairs, c), np.float32)  # per pair: d/dfeature
    for w in numba.prange(nw):
        g = np.zeros(c + 1, np.float32)
        lc = np.empty((maxn, 6), np.float32)
        gl = np.empty((maxn, 6), np.float32)
        for q in range(w, n_t, nw):
            t = order[q]
            s0 = tstart[t]
            n = tcount[t]
            y0 = (t // ntx) * ts
            x0 = (t % ntx) * ts
            tile_coefficients(uv, conic, log_o, pg, s0, n, x0, y0, lc)
            for p in range(n):
                for e in range(6):
                    gl[p, e] = 0
            for j in range(ts):
                y = y0 + j
                if y >= height:
                    break
                fj = f32(j)
                for i in range(ts):
                    x = x0 + i
                    if x >= width:
                        break
                    fi = f32(i)
                    fii, fij, fjj = fi * fi, fi * fj, fj * fj
                    nz = False
                    for ch in range(c + 1):
                        g[ch] = gout[ch, y, x]
                        nz = nz or g[ch] != 0
                    if not nz:
                        continue
                    tr = t_final[y, x]
                    suffix = f32(0.0)
                    for p in range(n_done[y, x] - 1, -1, -1):
                        a = pair_alpha(lc, p, fi, fj, fii, fij, fjj, skip, amin)
                        if a == 0:
                            continue
                        tr = tr / (one - a)  # transmittance in front of this Gaussian
                        wt = a * tr
                        gi = pg[s0 + p]
                        h = g[c]
                        for ch in range(c):
                            h += g[ch] * feat[gi, ch]
                            g_fp[s0 + p, ch] += wt * g[ch]
                        d_pw = wt * h - a / (one - a) * suffix
                        suffix += wt * h
                        gl[p, 0] += d_pw
                        gl[p, 1] += d_pw * fi
                        gl[p, 2] += d_pw * fj
                        gl[p, 3] += d_pw * fii
                        gl[p, 4] += d_pw * fij
                        gl[p, 5] += d_pw * fjj
            # the coefficients' gradients to the pair's centre, conic and log-opacity (chain rule of
            # tile_coefficients)
            for p in range(n):
                i = pg[s0 + p]
                du = uv[i, 0] - f32(x0)
                dv = uv[i, 1] - f32(y0)
                a, b, cc = conic[i, 0], conic[i, 1], conic[i, 2]
                g0, g1, g2, g3, g4, g5 = gl[p, 0], gl[p, 1], gl[p, 2], gl[p, 3], gl[p, 4], gl[p, 5]
                g_geo[s0 + p, 0] = g0 * (-a * du - b * dv) + g1 * a + g2 * b
                g_geo[s0 + p, 1] = g0 * (-b * du - cc * dv) + g1 * b + g2 * cc
                g_geo[s0 + p, 2] = -half * g0 * du * du + g1 * du - half * g3
                g_geo[s0 + p, 3] = -g0 * du * dv + g1 * dv + g2 * du - g4
                g_geo[s0 + p, 4] = -half * g0 * dv * dv + g2 * dv - half * g5
                g_geo[s0 + p, 5] = g0
    # pairs to Gaussians, in pair order (one thread: deterministic, no atomics)
    for p in range(pairs):
        i = pg[p]
        g_uv[i, 0] += g_geo[p, 0]
        g_uv[i, 1] += g_geo[p, 1]
        g_conic[i, 0] += g_geo[p, 2]
        g_conic[i, 1] += g_geo[p, 3]
        g_conic[i, 2] += g_geo[p, 4]
        g_logo[i] += g_geo[p, 5]
        for ch in range(c):
            g_feat[i, ch] += g_fp[p, ch]

@numba.njit(cache=True, nogil=True)
def bin_pairs(x0, x1, y0, y1, kidx, ntx, n_tiles):
    """Counting sort of the pairs by tile: one pass counts, one fills (front to back within each tile)."""
    tcount = np.zeros(n_tiles, np.int64)
    for q in range(kidx.shape[0]):
        i = kidx[q]
        for ty in range(y0[i], y1[i] + 1):
            for tx in range(x0[i], x1[i] + 1):
                tcount[ty * ntx + tx] += 1
    tstart = np.zeros(n_tiles, np.int64)
    total = 0
    for t in range(n_tiles):
        tstart[t] = total
        total += tcount[t]
    pg = np.empty(total, np.int64)
    ptile = np.empty(total, np.int64)
    pos = tstart.copy()
    for q in range(kidx.shape[0]):
        i = kidx[q]
        for ty in range(y0[i], y1[i] + 1):
            for tx in range(x0[i], x1[i] + 1):
                t = ty * ntx + tx
                pg[pos[t]] = i
                ptile[pos[t]] = t
                pos[t] += 1
    return pg, ptile, tcount, tstart
