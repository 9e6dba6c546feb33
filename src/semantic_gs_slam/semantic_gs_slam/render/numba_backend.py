"""Compiled CPU compositor (numba): the fast path of the CPU renderer.

Same pairs (:func:`semantic_gs_slam.render.tiles.tile_pairs`), same compositing rules
(:mod:`semantic_gs_slam.render.types`) and same gradients as the pure-PyTorch compositor in
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
the threads (as many as torch uses). Calls hold :data:`_LOCK`: numba's ``workqueue`` threading layer (the one
it falls back to without OpenMP or TBB) aborts when two Python threads enter it at once.

numba is optional (a wheel-world dependency, as for :mod:`object_query.kernels`): without it,
``renderer.backend: auto`` keeps the reference. The kernels live in :mod:`semantic_gs_slam.render.numba_kernels`;
compiling all of them takes about 16 s once after a change of their source, then numba's on-disk cache loads
them (about 0.8 s with numba's import).
"""

from __future__ import annotations

import functools
import threading

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.devices import require_cpu_kernel
from semantic_gs_slam.render.reference import render_torch
from semantic_gs_slam.render.tiles import TilePairs, tile_pairs
from semantic_gs_slam.render.types import Gaussians, RenderOutput

__all__ = ["bin_pairs_numba", "composite_numba", "render_numba"]

_LOCK = threading.Lock()


@functools.cache
def _kernels():
    """The compiled kernels (:mod:`semantic_gs_slam.render.numba_kernels`, which imports numba: only when used)."""
    from semantic_gs_slam.render import numba_kernels as nk

    return nk.composite_forward, nk.composite_backward, nk.bin_pairs


class _CompositeNumba(torch.autograd.Function):
    """Front-to-back compositing of all tiles' pairs (compiled forward and backward, CPU tensors).

    Inputs: uv [M, 2], conic [M, 3], log_o [M], feat [M, C] of the projected Gaussians; pg / tstart / tcount /
    order (int64, see :class:`~semantic_gs_slam.render.tiles.TilePairs`), ntx, tile, height, width, stop.
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
    """:func:`semantic_gs_slam.render.tiles.bin_pairs_torch` as a compiled counting sort (CPU tensors; the same
    pairs in the same order, no comparison sort of all pairs)."""
    out = _kernels()[2](x0.numpy(), x1.numpy(), y0.numpy(), y1.numpy(), kidx.numpy(), ntx, n_tiles)
    return tuple(torch.from_numpy(a) for a in out)


def composite_numba(tp: TilePairs, k: Intrinsics, cfg: RendererConfig) -> Tensor:
    """Composite the pairs ``tp`` into a [C + 1, H, W] image (last channel the silhouette)."""
    return _CompositeNumba.apply(tp.uv, tp.conic, tp.log_o, tp.feats, tp.pg, tp.tstart, tp.tcount, tp.tiles_sorted,
                                 tp.ntx, tp.tile, k.height, k.width, cfg.stop_transmittance)


def render_numba(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    """The compiled CPU back-end. Arguments and result as :func:`semantic_gs_slam.render.render`.

    It composites in float32 (as gsplat does; the engine's tensors are float32). Float64 Gaussians go to the
    reference, :func:`semantic_gs_slam.render.reference.render_torch`, which keeps their precision.

    Raises:
        BackendUnavailableError: numba missing, or Gaussians off the CPU.
        ValueError: inconsistent inputs.
    """
    require_cpu_kernel("renderer.backend", g.means.device)
    if g.means.dtype != torch.float32:
        return render_torch(g, w2c, k, cfg)
    tp = tile_pairs(g, w2c, k, cfg, bin_pairs_numba, coefficients=False)
    img = composite_numba(tp, k, cfg)
    sem = img[4:-1].permute(1, 2, 0) if g.semantic is not None else None
    return RenderOutput(img[:3].permute(1, 2, 0), img[3], img[-1], sem, tp.n_visible)
