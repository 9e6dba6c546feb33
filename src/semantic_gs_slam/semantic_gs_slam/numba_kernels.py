"""The compiled CPU kernels (numba), all in one module: imported only by the glue modules that use them
(:mod:`semantic_gs_slam.render_numba`, :mod:`semantic_gs_slam.tracking_numba`,
:mod:`semantic_gs_slam.metrics_numba`), so the engine imports without numba.

Plain numpy-in, numpy-out functions at module level, so numba's on-disk cache (``cache=True``) finds them again in
the next process (compiling all of them takes about 16 s; defined inside another function, they were compiled anew
in every process).
Each has a PyTorch reference it is tested against; the glue modules' docstrings say which and how.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from semantic_gs_slam.render_types import ALPHA_MIN

f32 = numba.float32
#: exponent below which alpha < ALPHA_MIN for sure (the exact test is on alpha itself)
_LOG_ALPHA_SKIP = math.log(ALPHA_MIN) - 1e-3
C1, C2 = 0.01**2, 0.03**2  # SSIM's constants (for images in [0, 1])
# The compositing kernels use strict IEEE arithmetic: the backward must take the same alpha-threshold and
# early-stop decisions as the forward, which a contracted or reassociated exponent in one of the two could flip, and
# NaN must propagate as in the reference. SSIM may reorder its sums (vectorised blurs), but keeps NaN and inf.
SSIM_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

# ---------------------------------------------------------------- renderer (render_numba)

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


# ---------------------------------------------------------------- ICP (tracking_numba)

@numba.njit(cache=True, nogil=True)
def icp_accumulate(est, w2c_g, lp, lvalid, il, vm, nm, nvalid, col, fx, fy, cx, cy, width, height, max_dist, sg,
               w_geo, photometric, sc, w_col, a, b, stats):
    jac = np.zeros(6)
    n_close = 0.0
    rr = 0.0
    n_agree = 0.0
    n_ok = 0.0
    for m in range(lp.shape[0]):
        if not lvalid[m]:
            continue
        p0, p1, p2 = lp[m, 0], lp[m, 1], lp[m, 2]
        x0 = est[0, 0] * p0 + est[0, 1] * p1 + est[0, 2] * p2 + est[0, 3]
        x1 = est[1, 0] * p0 + est[1, 1] * p1 + est[1, 2] * p2 + est[1, 3]
        x2 = est[2, 0] * p0 + est[2, 1] * p1 + est[2, 2] * p2 + est[2, 3]
        c0 = w2c_g[0, 0] * x0 + w2c_g[0, 1] * x1 + w2c_g[0, 2] * x2 + w2c_g[0, 3]
        c1 = w2c_g[1, 0] * x0 + w2c_g[1, 1] * x1 + w2c_g[1, 2] * x2 + w2c_g[1, 3]
        c2 = w2c_g[2, 0] * x0 + w2c_g[2, 1] * x1 + w2c_g[2, 2] * x2 + w2c_g[2, 3]
        if not c2 > 1e-3:  # (also false for NaN)
            continue
        z = c2
        uf = fx * c0 / z + cx
        vf = fy * c1 / z + cy
        if not (uf > -1.0 and uf < width + 1.0 and vf > -1.0 and vf < height + 1.0):
            continue
        u = np.rint(uf)  # round half to even, as torch.round
        v = np.rint(vf)
        if u < 0 or u >= width or v < 0 or v >= height:
            continue
        pix = int(v) * width + int(u)
        if nvalid[pix]:
            n_ok += 1.0
            n0, n1, n2 = nm[pix, 0], nm[pix, 1], nm[pix, 2]
            d0, d1, d2 = x0 - vm[pix, 0], x1 - vm[pix, 1], x2 - vm[pix, 2]
            if np.sqrt(d0 * d0 + d1 * d1 + d2 * d2) < max_dist:
                r = d0 * n0 + d1 * n1 + d2 * n2
                ar = abs(r)
                w = (1.0 if ar < sg else sg / max(ar, 1e-30)) * (w_geo / (sg * sg))
                jac[0] = x1 * n2 - x2 * n1
                jac[1] = x2 * n0 - x0 * n2
                jac[2] = x0 * n1 - x1 * n0
                jac[3], jac[4], jac[5] = n0, n1, n2
                for i in range(6):
                    wi = w * jac[i]
                    b[i] -= wi * r
                    for j in range(i + 1):
                        a[i, j] += wi * jac[j]
                n_close += 1.0
                rr += r * r
                if ar < 3 * sg:
                    n_agree += 1.0
        if photometric and uf >= 0 and uf < width - 1 and vf >= 0 and vf < height - 1:
            u0 = np.floor(uf)
            v0 = np.floor(vf)
            fu, fv = uf - u0, vf - v0
            q00 = int(v0) * width + int(u0)
            w00, w01, w10, w11 = (1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv
            q01, q10, q11 = q00 + 1, q00 + width, q00 + width + 1
            s0 = w00 * col[q00, 0] + w01 * col[q01, 0] + w10 * col[q10, 0] + w11 * col[q11, 0]
            s1 = w00 * col[q00, 1] + w01 * col[q01, 1] + w10 * col[q10, 1] + w11 * col[q11, 1]
            s2 = w00 * col[q00, 2] + w01 * col[q01, 2] + w10 * col[q10, 2] + w11 * col[q11, 2]
            s3 = w00 * col[q00, 3] + w01 * col[q01, 3] + w10 * col[q10, 3] + w11 * col[q11, 3]
            if s3 > 0.999:
                rc = s0 - il[m]
                # d I / d camera point, then to the world point through the model camera's rotation
                e0 = s1 * fx / z
                e1 = s2 * fy / z
                e2 = -(s1 * fx * c0 + s2 * fy * c1) / (z * z)
                g0 = e0 * w2c_g[0, 0] + e1 * w2c_g[1, 0] + e2 * w2c_g[2, 0]
                g1 = e0 * w2c_g[0, 1] + e1 * w2c_g[1, 1] + e2 * w2c_g[2, 1]
                g2 = e0 * w2c_g[0, 2] + e1 * w2c_g[1, 2] + e2 * w2c_g[2, 2]
                jac[0] = x1 * g2 - x2 * g1
                jac[1] = x2 * g0 - x0 * g2
                jac[2] = x0 * g1 - x1 * g0
                jac[3], jac[4], jac[5] = g0, g1, g2
                arc = abs(rc)
                wc = (1.0 if arc < sc else sc / max(arc, 1e-30)) * (w_col / (sc * sc))
                for i in range(6):
                    wi = wc * jac[i]
                    b[i] -= wi * rc
                    for j in range(i + 1):
                        a[i, j] += wi * jac[j]
    for i in range(6):
        for j in range(i):
            a[j, i] = a[i, j]
    stats[0] = n_close
    stats[1] = rr
    stats[2] = n_agree
    stats[3] = n_ok


# ---------------------------------------------------------------- SSIM (metrics_numba)

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
