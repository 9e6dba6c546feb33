"""The pure-PyTorch renderer, the reference every other back-end is tested against (``renderer.backend: torch``).

:func:`render_torch` composites tiles of ``tile x tile`` pixels; each tile composites its depth-sorted Gaussians in
chunks and stops once every pixel is done, with a hand-written backward (:class:`_Composite`, see the package
docstring of :mod:`semantic_gs_slam.render`). :func:`render_reference` is the dense per-pixel renderer the tests
check the tiles against.
"""

from __future__ import annotations

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.render.tiles import project, tile_pairs
from semantic_gs_slam.render.types import ALPHA_MIN, STOP_TRANSMITTANCE, Gaussians, RenderOutput

EXP_FLOOR = -20.0  # exp() of smaller inputs is slow on CPU and below ALPHA_MIN anyway


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of a batch of tiles with a hand-written backward.

    Inputs: coef [B, K, 6] exponent coefficients (K depth-sorted), feats [B, K, C], mono [6, P]
    monomials of the tile-local pixel coordinates, chunk (int), stop (float: gsplat's transmittance
    stop, see :mod:`semantic_gs_slam.render.types`).
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
