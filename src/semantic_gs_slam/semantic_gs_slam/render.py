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

import math

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.geometry import quat_to_rotmat
from semantic_gs_slam.render_gsplat import gsplat_available, render_gsplat, require_gsplat
from semantic_gs_slam.render_types import (
    ALPHA_MIN,
    BLUR_PX2,
    FOV_MARGIN,
    OPACITY_CAP,
    STOP_TRANSMITTANCE,
    Gaussians,
    RenderBackend,
    RenderOutput,
)

__all__ = ["ALPHA_MIN", "OPACITY_CAP", "Gaussians", "RenderBackend", "RenderOutput", "footprint", "project", "render",
           "render_reference", "render_torch", "select_backend"]

EXP_FLOOR = -20.0  # exp() of smaller inputs is slow on CPU and below ALPHA_MIN anyway


def _check_inputs(g: Gaussians, w2c: Tensor) -> None:
    g.check()
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must be [4, 4], got {list(w2c.shape)}")
    if w2c.device != g.means.device:
        raise ValueError(f"w2c is on {w2c.device} but the Gaussians are on {g.means.device}")


def select_backend(cfg: RendererConfig, device: torch.device | str = "cpu") -> RenderBackend:
    """The renderer back-end ``cfg.backend`` names (chosen once; the engine keeps the result).

    Args:
        cfg: renderer settings; ``backend="auto"`` picks gsplat when ``device`` is CUDA and gsplat
            imports, else the torch tiles.
        device: the device the Gaussians live on.

    Raises:
        BackendUnavailableError: ``gsplat`` asked for where gsplat or CUDA is missing.
    """
    if cfg.backend == "gsplat":
        require_gsplat()
        return render_gsplat
    if cfg.backend == "auto" and torch.device(device).type == "cuda" and gsplat_available():
        return render_gsplat
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


def jacobian_limits(k: Intrinsics) -> tuple[float, float, float, float]:
    """Clamp range of x/z and y/z in the projection Jacobian: (x_neg, x_pos, y_neg, y_pos), gsplat's rule
    ``cx' / fx + 0.3 tan(fov_x / 2)`` with gsplat's principal point ``cx' = cx + 0.5``."""
    tx, ty = FOV_MARGIN * 0.5 * k.width / k.fx, FOV_MARGIN * 0.5 * k.height / k.fy
    return ((k.cx + 0.5) / k.fx + tx, (k.width - k.cx - 0.5) / k.fx + tx,
            (k.cy + 0.5) / k.fy + ty, (k.height - k.cy - 0.5) / k.fy + ty)


def project(g: Gaussians, w2c: Tensor, k: Intrinsics, near: float) -> dict[str, Tensor]:
    """Project Gaussians to the image: centres, conics, log-opacities, depths and the visible index.

    Returns:
        dict with ``idx`` [M] (indices of Gaussians in front of the camera), ``uv`` [M, 2], ``conic``
        [M, 3] (a, b, c of the inverse 2-D covariance), ``cov`` [M, 3] (xx, xy, yy), ``log_o`` [M],
        ``z`` [M].
    """
    pc = g.means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    idx = torch.nonzero(pc[:, 2].detach() > near).squeeze(1)
    ls = g.log_scales.index_select(0, idx)
    quats = g.quats.index_select(0, idx) if ls.shape[1] == 3 else None
    out = project_rows(pc.index_select(0, idx), ls, quats, g.logit_opacities.index_select(0, idx), w2c, k)
    out["idx"] = idx
    return out


def project_rows(pc: Tensor, log_scales: Tensor, quats: Tensor | None, logit_opacities: Tensor, w2c: Tensor,
                 k: Intrinsics) -> dict[str, Tensor]:
    """The projection maths of :func:`project` on given rows (fixed shapes: no culling, no host sync).

    Args:
        pc: [M, 3] camera-frame centres (z > 0). log_scales: [M, 1] or [M, 3]. quats: [M, 4] (anisotropic
            scales only) or None. logit_opacities: [M, 1]. w2c: [4, 4]. k: intrinsics.

    Returns:
        dict with ``uv`` [M, 2], ``conic`` [M, 3], ``cov`` [M, 3], ``log_o`` [M], ``z`` [M].
    """
    x, y, z = pc.unbind(-1)
    # clamp the Jacobian's x/z, y/z to the view plus a margin (as gsplat / 3DGS), else near off-screen
    # Gaussians blow up
    xn, xp, yn, yp = jacobian_limits(k)
    tx = (x / z).clamp(-xn, xp) * z
    ty = (y / z).clamp(-yn, yp) * z
    zero = torch.zeros_like(z)
    j = torch.stack([k.fx / z, zero, -k.fx * tx / (z * z), zero, k.fy / z, -k.fy * ty / (z * z)], -1).reshape(-1, 2, 3)
    ls = log_scales
    if ls.shape[1] == 1:
        s2 = torch.exp(2 * ls[:, 0])  # isotropic: covariance s^2 I in every frame
        jj = j @ j.transpose(1, 2)  # [M, 2, 2]
        cov2 = s2[:, None, None] * jj
    else:
        r = quat_to_rotmat(quats)  # [M, 3, 3]
        m = w2c[:3, :3] @ r * torch.exp(ls)[:, None, :]  # camera-frame R S
        cov2 = j @ m @ m.transpose(1, 2) @ j.transpose(1, 2)
    cxx = cov2[:, 0, 0] + BLUR_PX2
    cxy = cov2[:, 0, 1]
    cyy = cov2[:, 1, 1] + BLUR_PX2
    det = (cxx * cyy - cxy * cxy).clamp_min(1e-12)
    conic = torch.stack([cyy / det, -cxy / det, cxx / det], -1)
    uv = torch.stack([k.fx * x / z + k.cx, k.fy * y / z + k.cy], -1)
    log_o = math.log(OPACITY_CAP) + torch.nn.functional.logsigmoid(logit_opacities[:, 0])
    return {"uv": uv, "conic": conic, "cov": torch.stack([cxx, cxy, cyy], -1), "log_o": log_o, "z": z}


def footprint(log_o: Tensor, cov: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Exact pixel box where a projected Gaussian's alpha is >= 1/255.

    ``alpha >= 1/255  <=>  d^2 <= 2 ln(255 o)`` (Mahalanobis ``d``); the box's half extents are that
    radius times the marginal standard deviations. gsplat's box is ``ceil(min(3.33, that radius) sigma)``,
    never smaller (0.99 * 255 gives a radius of 3.327), so both back-ends blend the same pixels.

    Args:
        log_o: [M] log-opacities. cov: [M, 3] 2-D covariances (xx, xy, yy) with the low-pass added.

    Returns:
        keep [M] (opacity >= 1/255), half extents hx [M] and hy [M] in pixels.
    """
    r2 = 2 * (log_o + math.log(255.0))
    rad = torch.sqrt(r2.clamp_min(0))
    return r2 > 0, rad * torch.sqrt(cov[:, 0]), rad * torch.sqrt(cov[:, 2])


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
    _check_inputs(g, w2c)
    dev, dt = g.means.device, g.means.dtype
    ts = cfg.tile
    ntx, nty = (k.width + ts - 1) // ts, (k.height + ts - 1) // ts
    n_tiles = ntx * nty
    pr = project(g, w2c, k, cfg.near)
    idx, uv, conic, cov, log_o, z = pr["idx"], pr["uv"], pr["conic"], pr["cov"], pr["log_o"], pr["z"]
    feats = [g.rgb.index_select(0, idx), z[:, None]]
    if g.semantic is not None:
        feats.append(g.semantic.index_select(0, idx))
    feats_all = torch.cat(feats, -1)  # [M, C]
    c_out = feats_all.shape[1]
    with torch.no_grad():
        keep, hx, hy = footprint(log_o, cov)
        x0 = torch.floor((uv[:, 0] - hx + 0.5) / ts).long()
        x1 = torch.floor((uv[:, 0] + hx + 0.5) / ts).long()
        y0 = torch.floor((uv[:, 1] - hy + 0.5) / ts).long()
        y1 = torch.floor((uv[:, 1] + hy + 0.5) / ts).long()
        keep &= (x1 >= 0) & (x0 < ntx) & (y1 >= 0) & (y0 < nty)
        x0, x1 = x0.clamp(0, ntx - 1), x1.clamp(0, ntx - 1)
        y0, y1 = y0.clamp(0, nty - 1), y1.clamp(0, nty - 1)
        kidx = torch.nonzero(keep).squeeze(1)
        # depth order first, then a stable sort by tile keeps depth order within each tile
        kidx = kidx[torch.argsort(z[kidx])]
        wx, wy = (x1 - x0 + 1)[kidx], (y1 - y0 + 1)[kidx]
        cnt = wx * wy
        total = int(cnt.sum())
        pg = torch.repeat_interleave(kidx, cnt)  # pair -> projected-Gaussian index
        start = torch.cumsum(cnt, 0) - cnt
        local = torch.arange(total, device=dev) - torch.repeat_interleave(start, cnt)
        wxr = torch.repeat_interleave(wx, cnt)
        ptile = (y0[pg] + local // wxr) * ntx + (x0[pg] + local % wxr)
        order = torch.sort(ptile, stable=True).indices
        pg, ptile = pg[order], ptile[order]
        tcount = torch.bincount(ptile, minlength=n_tiles)
        tstart = torch.cumsum(tcount, 0) - tcount
        tiles_sorted = torch.argsort(tcount, descending=True)
        tiles_sorted = tiles_sorted[tcount[tiles_sorted] > 0]
        li = torch.arange(ts, dtype=dt, device=dev)
        jj, ii = torch.meshgrid(li, li, indexing="ij")  # pixel p = j * ts + i
        ii, jj = ii.reshape(-1), jj.reshape(-1)
        mono = torch.stack([torch.ones_like(ii), ii, jj, ii * ii, ii * jj, jj * jj])  # [6, P]
    # exponent coefficients for every pair (one vectorised computation)
    tx0 = (ptile % ntx).to(dt) * ts
    ty0 = (ptile // ntx).to(dt) * ts
    # index_select (backward: index_add) rather than advanced indexing (backward: slow index_put)
    a_, b_, c_ = conic.index_select(0, pg).unbind(-1)
    uvp = uv.index_select(0, pg)
    du = uvp[:, 0] - tx0
    dv = uvp[:, 1] - ty0
    coef_pairs = torch.stack([
        -0.5 * a_ * du * du - b_ * du * dv - 0.5 * c_ * dv * dv + log_o.index_select(0, pg),
        a_ * du + b_ * dv, b_ * du + c_ * dv, -0.5 * a_, -b_, -0.5 * c_], -1)  # [pairs, 6]
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
    return RenderOutput(img[:3].permute(1, 2, 0), img[3], img[-1], sem, int(kidx.numel()))


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
