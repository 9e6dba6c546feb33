"""Differentiable Gaussian-splatting renderer: colour, depth, silhouette and semantic images.

Two back-ends behind one interface (:class:`~semantic_gs_slam.render_types.RenderBackend`), picked
once from the config by :func:`select_backend`:

* ``torch`` (this module, :func:`render_torch`) — the reference: pure PyTorch, any device, used on CPU
  and in tests. Tiles of ``tile x tile`` pixels; each tile composites its depth-sorted Gaussians in
  chunks and stops once every pixel is done. Compositing has a hand-written backward
  (:class:`_Composite`): with the transmittance kept, the gradient of a pixel value with respect to a
  Gaussian's alpha is ``T_i (g . f_i) - S_i / (1 - alpha_i)`` where ``S_i`` is the suffix sum of
  ``w_k (g . f_k)`` over the Gaussians behind it, so no autograd graph of the [tiles, Gaussians,
  pixels] tensors is kept. Each Gaussian's exponent (plus its log-opacity) over a tile is a quadratic
  in the tile-local pixel coordinates, written as six coefficients, so a tile batch's exponents are
  one matmul.
* ``gsplat`` (:mod:`semantic_gs_slam.render_gsplat`) — the CUDA fast path, only when gsplat and a GPU
  exist.

Conventions (gsplat 1.5.3's, see :mod:`semantic_gs_slam.render_types`): world-to-camera pose ``w2c``
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
from semantic_gs_slam.render_gsplat import gsplat_available, load_gsplat_extension, render_gsplat, require_gsplat
from semantic_gs_slam.render_numba import render_numba
from semantic_gs_slam.render_tiles import footprint, jacobian_limits, project, project_rows, tile_pairs
from semantic_gs_slam.render_types import (
    ALPHA_MIN,
    OPACITY_CAP,
    STOP_TRANSMITTANCE,
    Gaussians,
    RenderBackend,
    RenderOutput,
)

__all__ = ["ALPHA_MIN", "OPACITY_CAP", "Gaussians", "RenderBackend", "RenderOutput", "footprint", "jacobian_limits",
           "project", "project_rows", "render", "render_reference", "render_torch", "select_backend"]

EXP_FLOOR = -20.0  # exp() of smaller inputs is slow on CPU and below ALPHA_MIN anyway


def select_backend(cfg: RendererConfig, device: torch.device | str = "cpu") -> RenderBackend:
    """The renderer back-end ``cfg.backend`` names (chosen once; the engine keeps the result).

    Args:
        cfg: renderer settings; ``backend="auto"`` picks gsplat when ``device`` is CUDA, gsplat
            imports and its CUDA code loads (built now if needed, see
            :func:`~semantic_gs_slam.render_gsplat.load_gsplat_extension`; else a ``RuntimeWarning``),
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


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of a batch of tiles with a hand-written backward.

    Inputs: coef [B, K, 6] exponent coefficients (K depth-sorted), feats [B, K, C], mono [6, P]
    monomials of the tile-local pixel coordinates, chunk (int), stop (float: gsplat's transmittance
    stop, see :mod:`semantic_gs_slam.render_types`).
    Output: [B, C + 1, P] composited features, last channel the silhouette.

    A Gaussian is blended at a pixel only while the transmittance behind it stays above ``stop``;
    the product of ``1 - alpha`` over *all* Gaussians so far (``t_run``) is non-increasing, so the
    blended ones are a prefix and their transmittance in front is exactly that product.
    """

    @staticmethod
    def forward(ctx, coef: Tensor, feats: Tensor, mono: Tensor, chunk: int, stop: float) -> Tensor:  # noqa: D102
        b, kk, c = feats.shape
        p = mono.shape[1]
        fx = torch.cat([feats, feats.new_ones(b, kk, 1)], -1)  # [B, K, C+1]
        out = feats.new_zeros(b, c + 1, p)
        t_run = feats.new_ones(b, 1, p)
        on_cpu = feats.device.type == "cpu"
        alphas, weights = [], []
        done = 0
        for s in range(0, kk, chunk):
            e = min(kk, s + chunk)
            pw = (coef[:, s:e] @ mono).clamp_(min=EXP_FLOOR)  # [B, k, P]
            a = torch.exp(pw)
            a = a.masked_fill_(a < ALPHA_MIN, 0.0)
            tc = t_run * torch.cumprod(1 - a, dim=1)  # transmittance behind each Gaussian
            t_ex = torch.cat([t_run, tc[:, :-1]], 1)  # transmittance in front of each Gaussian
            t_run = tc[:, -1:]
            # on the CPU a look at the chunk's last transmittance (free there) skips the masking pass
            # when no pixel ends in this chunk; elsewhere it always runs (no host sync)
            lo, hi = t_run.aminmax() if on_cpu else (None, None)
            if not on_cpu or float(lo) <= stop:
                a = a.masked_fill_(tc <= stop, 0.0)  # gsplat: the pixel ends before this Gaussian
            w = t_ex.mul_(a)  # blending weights (t_ex is not needed afterwards)
            out += fx[:, s:e].transpose(1, 2) @ w
            alphas.append(a)
            weights.append(w)
            done = e
            if e < kk and float(hi if on_cpu else t_run.max()) <= stop:  # a host sync per chunk (none for one)
                break
        cat = (lambda xs: xs[0]) if len(alphas) == 1 else (lambda xs: torch.cat(xs, 1))
        ctx.save_for_backward(fx, mono, cat(alphas), cat(weights))
        ctx.done = done
        ctx.kk = kk
        return out

    @staticmethod
    def backward(ctx, gout: Tensor):  # noqa: D102
        fx, mono, a, w = ctx.saved_tensors  # alphas and blending weights w = alpha * T, [B, k, P]
        done = ctx.done
        fxd = fx[:, :done]
        h = fxd @ gout  # [B, k, P]: g . f_i per pixel
        wh = w * h
        suffix = torch.cumsum(wh, 1).neg_().add_(wh.sum(1, keepdim=True))  # sum over the Gaussians behind (k > i)
        # dL/dalpha_i = T_i h_i - suffix_i / (1 - alpha_i); alpha = exp(power) where kept, so
        # dL/dpower = alpha dL/dalpha = w h - alpha / (1 - alpha) suffix  (0 where alpha was dropped)
        d_pw = wh.sub_(suffix.mul_(a).div_(1 - a))
        g_coef = d_pw @ mono.T  # [B, k, 6]
        g_feat = (w @ gout.transpose(1, 2))[..., :-1]  # [B, k, C]
        if done < ctx.kk:
            b = fx.shape[0]
            g_coef = torch.cat([g_coef, g_coef.new_zeros(b, ctx.kk - done, 6)], 1)
            g_feat = torch.cat([g_feat, g_feat.new_zeros(b, ctx.kk - done, g_feat.shape[2])], 1)
        return g_coef, g_feat, None, None, None


def render_torch(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    """The pure-PyTorch tile back-end (the reference; any device). Arguments as :func:`render`."""
    tp = tile_pairs(g, w2c, k, cfg)
    dev, dt = g.means.device, g.means.dtype
    ts, ntx, nty = tp.tile, tp.ntx, tp.nty
    n_tiles = ntx * nty
    feats_all, pg, tcount, tstart, tiles_sorted = tp.feats, tp.pg, tp.tcount, tp.tstart, tp.tiles_sorted
    coef_pairs = tp.coef
    c_out = feats_all.shape[1]
    total = int(pg.numel())
    with torch.no_grad():
        li = torch.arange(ts, dtype=dt, device=dev)
        jj, ii = torch.meshgrid(li, li, indexing="ij")  # pixel p = j * ts + i
        ii, jj = ii.reshape(-1), jj.reshape(-1)
        mono = torch.stack([torch.ones_like(ii), ii, jj, ii * ii, ii * jj, jj * jj])  # [6, P]
    pad_row = torch.tensor([-30.0, 0, 0, 0, 0, 0], dtype=dt, device=dev)
    p = ts * ts
    outs, out_tiles = [], []
    i0 = 0
    counts = tcount[tiles_sorted].tolist()  # the one host copy of the tile loop (batch shapes)
    while i0 < len(counts):
        kb = counts[i0]
        nb = max(1, cfg.batch_elements // (kb * p))
        bt = tiles_sorted[i0:i0 + nb]
        with torch.no_grad():
            kr = torch.arange(kb, device=dev)
            mask = kr[None, :] < tcount[bt][:, None]  # [B, K]
            pidx = (tstart[bt][:, None] + kr[None, :]).clamp(max=max(total - 1, 0))
        flat = pidx.reshape(-1)
        cf = torch.where(mask[..., None], coef_pairs.index_select(0, flat).reshape(*pidx.shape, 6), pad_row)
        ft = feats_all.index_select(0, pg[flat]).reshape(*pidx.shape, c_out) * mask[..., None]
        outs.append(_Composite.apply(cf, ft, mono, cfg.chunk, cfg.stop_transmittance))
        out_tiles.append(bt)
        i0 += nb
    full = torch.zeros(n_tiles, c_out + 1, p, dtype=dt, device=dev)
    if outs:
        full = full.index_copy(0, torch.cat(out_tiles), torch.cat(outs))
    img = full.reshape(nty, ntx, c_out + 1, ts, ts).permute(2, 0, 3, 1, 4).reshape(c_out + 1, nty * ts, ntx * ts)
    img = img[:, :k.height, :k.width]
    sem = img[4:-1].permute(1, 2, 0) if g.semantic is not None else None
    return RenderOutput(img[:3].permute(1, 2, 0), img[3], img[-1], sem, tp.n_visible)


def render_reference(g: Gaussians, w2c: Tensor, k: Intrinsics, near: float = 0.05,
                     stop: float = STOP_TRANSMITTANCE) -> RenderOutput:
    """Dense per-pixel reference renderer (plain autograd, every Gaussian at every pixel). Tests only: O(N H W)."""
    pr = project(g, w2c, k, near)
    idx, uv, conic, log_o, z = pr["idx"], pr["uv"], pr["conic"], pr["log_o"], pr["z"]
    order = torch.argsort(z.detach())
    feats = [g.rgb[idx], z[:, None]]
    if g.semantic is not None:
        feats.append(g.semantic[idx])
    f = torch.cat(feats, -1)[order]  # [M, C]
    dev, dt = g.means.device, g.means.dtype
    v, u = torch.meshgrid(torch.arange(k.height, dtype=dt, device=dev), torch.arange(k.width, dtype=dt, device=dev),
                          indexing="ij")
    px = torch.stack([u.reshape(-1), v.reshape(-1)], -1)  # [P, 2]
    d = px[None] - uv[order][:, None]  # [M, P, 2]
    a_, b_, c_ = conic[order].unbind(-1)
    pw = -0.5 * (a_[:, None] * d[..., 0] ** 2 + 2 * b_[:, None] * d[..., 0] * d[..., 1] + c_[:, None] * d[..., 1] ** 2)
    alpha = torch.exp(pw + log_o[order][:, None])
    alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)
    t_behind = torch.cumprod(1 - alpha, 0)
    alpha = torch.where(t_behind.detach() <= stop, torch.zeros_like(alpha), alpha)
    t = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]], 0), 0)
    w = alpha * t  # [M, P]
    out = (w.T @ f).reshape(k.height, k.width, -1)
    sil = w.sum(0).reshape(k.height, k.width)
    sem = out[..., 4:] if g.semantic is not None else None
    return RenderOutput(out[..., :3], out[..., 3], sil, sem, int(idx.numel()))
