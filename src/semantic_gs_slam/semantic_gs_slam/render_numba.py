"""Compiled CPU compositor (numba): the fast path of the CPU renderer.

Same pairs (:func:`semantic_gs_slam.render_tiles.tile_pairs`), same compositing rules
(:mod:`semantic_gs_slam.render_types`) and same gradients as the pure-PyTorch compositor in
:mod:`semantic_gs_slam.render` (the reference it is tested against), but pixel by pixel in compiled
loops instead of dense [tiles, Gaussians, pixels] tensors:

* forward: each pixel walks its tile's pairs front to back, skips alphas below 1/255 and stops
  *before* the Gaussian that would take its transmittance to <= 1e-4; it keeps its final
  transmittance and how many pairs it walked, nothing else.
* backward: each pixel walks the same pairs back to front, recovering the transmittance in front of
  each Gaussian by dividing by ``1 - alpha`` (alpha <= 0.99), with the suffix sum of ``w_k (g . f_k)``
  as in the reference: ``dL/dpower_i = w_i (g . f_i) - alpha_i / (1 - alpha_i) * suffix_i``.

Every pair belongs to one tile and a tile is one thread's work, so the gradients need no atomics and
the result does not depend on the number of threads. Tiles are dealt round robin, most pairs first, to
the threads (as many as torch uses). numba's default threading layer is not safe for calls from two
Python threads at once, so calls hold :data:`_LOCK`.

numba is optional (a wheel-world dependency, as for :mod:`object_query.kernels`): without it,
``renderer.backend: auto`` keeps the reference. Compiling takes a few seconds on first use and is cached
on disk (``cache=True``).
"""

from __future__ import annotations

import functools
import math
import threading

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import BackendUnavailableError
from semantic_gs_slam.render_tiles import TilePairs, tile_pairs
from semantic_gs_slam.render_types import ALPHA_MIN, Gaussians, RenderOutput

__all__ = ["bin_pairs_numba", "composite_numba", "numba_available", "render_numba", "require_numba"]

_LOCK = threading.Lock()
#: exponent below which alpha < ALPHA_MIN for sure (the exact test is on alpha itself)
_LOG_ALPHA_SKIP = math.log(ALPHA_MIN) - 1e-3


def require_numba() -> None:
    """Raise :class:`BackendUnavailableError` unless numba is installed."""
    if not numba_available():
        raise BackendUnavailableError("renderer.backend 'numba' needs the numba package "
                                      "(pip install numba; requirements/python.in pins it)")


@functools.cache
def _kernels():  # pragma: no cover - compiled (its Python twin is the reference compositor)
    import numba

    f32 = numba.float32

    @numba.njit(cache=True, nogil=True, fastmath=True)
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

    @numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
    def forward(uv, conic, log_o, feat, pg, tstart, tcount, order, maxn, ntx, ts, height, width, stop, nw, out,
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
                            pw = (lc[p, 0] + lc[p, 1] * fi + lc[p, 2] * fj + lc[p, 3] * fii
                                  + lc[p, 4] * fij + lc[p, 5] * fjj)
                            if pw < skip:
                                continue
                            a = math.exp(pw)
                            if a < amin:
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

    @numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
    def backward(uv, conic, log_o, feat, pg, tstart, tcount, order, maxn, ntx, ts, height, width, nw, t_final, n_done,
                 gout, g_uv, g_conic, g_logo, g_feat):
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
                            pw = (lc[p, 0] + lc[p, 1] * fi + lc[p, 2] * fj + lc[p, 3] * fii
                                  + lc[p, 4] * fij + lc[p, 5] * fjj)
                            if pw < skip:
                                continue
                            a = math.exp(pw)
                            if a < amin:
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

    return forward, backward, bin_pairs


class _CompositeNumba(torch.autograd.Function):
    """Front-to-back compositing of all tiles' pairs (compiled forward and backward, CPU tensors).

    Inputs: uv [M, 2], conic [M, 3], log_o [M], feat [M, C] of the projected Gaussians; pg / tstart / tcount /
    order (int64, see :class:`~semantic_gs_slam.render_tiles.TilePairs`), ntx, tile, height, width, stop.
    Each tile computes its pairs' exponent coefficients itself (as ``tile_pairs`` would), so no per-pair
    tensor enters autograd. Output: [C + 1, H, W] composited features, the last channel the silhouette.
    """

    @staticmethod
    def forward(ctx, uv: Tensor, conic: Tensor, log_o: Tensor, feat: Tensor, pg: Tensor, tstart: Tensor,
                tcount: Tensor, order: Tensor, ntx: int, ts: int, height: int, width: int,
                stop: float) -> Tensor:  # noqa: D102
        fwd = _kernels()[0]
        arrs = tuple(x.detach().to(torch.float32).contiguous().numpy() for x in (uv, conic, log_o, feat))
        ints = tuple(x.contiguous().numpy() for x in (pg, tstart, tcount, order))
        c = arrs[3].shape[1]
        out = np.zeros((c + 1, height, width), np.float32)
        t_final = np.ones((height, width), np.float32)
        n_done = np.zeros((height, width), np.int64)
        nw = max(1, min(torch.get_num_threads(), len(ints[3])))
        maxn = max(1, int(ints[2].max())) if len(ints[2]) else 1
        with _LOCK:
            fwd(*arrs, *ints, maxn, ntx, ts, height, width, float(stop), nw, out, t_final, n_done)
        ctx.state = (arrs, ints, maxn, t_final, n_done, ntx, ts, height, width, nw)
        ctx.dtypes = tuple(x.dtype for x in (uv, conic, log_o, feat))
        return torch.from_numpy(out).to(feat.dtype)

    @staticmethod
    def backward(ctx, gout: Tensor):  # noqa: D102
        bwd = _kernels()[1]
        arrs, ints, maxn, t_final, n_done, ntx, ts, height, width, nw = ctx.state
        grads = tuple(np.zeros(x.shape, np.float32) for x in arrs)  # uv, conic, log_o, feat
        gn = gout.detach().to(torch.float32).contiguous().numpy()
        with _LOCK:
            bwd(*arrs, *ints, maxn, ntx, ts, height, width, nw, t_final, n_done, gn, *grads)
        out = tuple(torch.from_numpy(g).to(dt) for g, dt in zip(grads, ctx.dtypes, strict=True))
        return (*out, None, None, None, None, None, None, None, None, None)


def bin_pairs_numba(x0: Tensor, x1: Tensor, y0: Tensor, y1: Tensor, kidx: Tensor, ntx: int,
                    n_tiles: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """:func:`semantic_gs_slam.render_tiles.bin_pairs_torch` as a compiled counting sort (CPU tensors; the same
    pairs in the same order, no comparison sort of all pairs)."""
    out = _kernels()[2](x0.numpy(), x1.numpy(), y0.numpy(), y1.numpy(), kidx.numpy(), ntx, n_tiles)
    return tuple(torch.from_numpy(a) for a in out)


def composite_numba(tp: TilePairs, k: Intrinsics, cfg: RendererConfig) -> Tensor:
    """Composite the pairs ``tp`` into a [C + 1, H, W] image (last channel the silhouette)."""
    return _CompositeNumba.apply(tp.uv, tp.conic, tp.log_o, tp.feats, tp.pg, tp.tstart, tp.tcount, tp.tiles_sorted,
                                 tp.ntx, tp.tile, k.height, k.width, cfg.stop_transmittance)


def render_numba(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    """The compiled CPU back-end. Arguments and result as :func:`semantic_gs_slam.render.render`.

    Raises:
        BackendUnavailableError: numba missing.
        ValueError: Gaussians not on the CPU, or inconsistent inputs.
    """
    require_numba()
    if g.means.device.type != "cpu":
        raise ValueError(f"renderer.backend 'numba' renders on the CPU; the Gaussians are on {g.means.device}")
    tp = tile_pairs(g, w2c, k, cfg, bin_pairs_numba, coefficients=False)
    img = composite_numba(tp, k, cfg)
    sem = img[4:-1].permute(1, 2, 0) if g.semantic is not None else None
    return RenderOutput(img[:3].permute(1, 2, 0), img[3], img[-1], sem, tp.n_visible)
