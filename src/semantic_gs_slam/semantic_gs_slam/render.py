"""Differentiable Gaussian-splatting renderer: colour, depth, silhouette and semantic images.

Two back-ends behind :func:`render`:

* ``torch`` (this module) — pure PyTorch, any device, used on CPU and in tests. Tiles of
  ``tile x tile`` pixels; each tile composites its depth-sorted Gaussians in chunks and stops once
  every pixel is opaque. Compositing has a hand-written backward (:class:`_Composite`): with the
  transmittance kept, the gradient of a pixel value with respect to a Gaussian's alpha is
  ``T_i (g . f_i) - S_i / (1 - alpha_i)`` where ``S_i`` is the suffix sum of ``w_k (g . f_k)`` over
  the Gaussians behind it, so no autograd graph of the [tiles, Gaussians, pixels] tensors is kept.
  Each Gaussian's exponent (plus its log-opacity) over a tile is a quadratic in the tile-local pixel
  coordinates, written as six coefficients, so a tile batch's exponents are one matmul.
* ``gsplat`` (:mod:`semantic_gs_slam.render_gsplat`) — CUDA, only when gsplat and a GPU exist.

Conventions: world-to-camera pose ``w2c`` [4, 4] (OpenCV camera), pixel (col c, row r) has its
centre at (c, r), opacity = 0.99 * sigmoid(logit) (so alpha <= 0.99 as 3DGS clamps it), alphas below
1/255 are dropped, the 2-D covariance gets +0.3 px^2 (anti-aliasing as in 3DGS), and the projection
Jacobian clamps x/z, y/z to 1.3x the field of view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.geometry import quat_to_rotmat

ALPHA_MIN = 1.0 / 255.0
OPACITY_CAP = 0.99
EXP_FLOOR = -20.0  # exp() of smaller inputs is slow on CPU and below ALPHA_MIN anyway


@dataclass
class RenderOutput:
    """Rendered images (differentiable)."""

    rgb: Tensor  # [H, W, 3]
    depth: Tensor  # [H, W] sum of w_i z_i (not normalised by the silhouette, as SplaTAM renders it)
    silhouette: Tensor  # [H, W] accumulated opacity
    semantic: Tensor | None  # [H, W, S] or None
    n_visible: int = 0  # Gaussians in front of the camera that touch the image


@dataclass
class Gaussians:
    """Gaussian parameters as tensors (any of them may require grad)."""

    means: Tensor  # [N, 3] world
    quats: Tensor  # [N, 4] wxyz, unnormalised
    log_scales: Tensor  # [N, 1] isotropic or [N, 3]
    logit_opacities: Tensor  # [N, 1]
    rgb: Tensor  # [N, 3]
    semantic: Tensor | None = None  # [N, S]

    def check(self) -> None:
        """Raise ValueError on inconsistent shapes."""
        n = self.means.shape[0]
        want = {"means": (n, 3), "quats": (n, 4), "logit_opacities": (n, 1), "rgb": (n, 3)}
        for name, shape in want.items():
            if tuple(getattr(self, name).shape) != shape:
                raise ValueError(f"{name} must be {list(shape)}, got {list(getattr(self, name).shape)}")
        if self.log_scales.shape not in ((n, 1), (n, 3)):
            raise ValueError(f"log_scales must be [N, 1] or [N, 3], got {list(self.log_scales.shape)}")
        if self.semantic is not None and (self.semantic.ndim != 2 or self.semantic.shape[0] != n):
            raise ValueError(f"semantic must be [N, S], got {list(self.semantic.shape)}")


def render(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig | None = None) -> RenderOutput:
    """Render colour, depth, silhouette (and semantic) images.

    Args:
        g: the Gaussians.
        w2c: [4, 4] world-to-camera pose (may require grad).
        k: camera intrinsics (image size included).
        cfg: renderer settings (back-end choice included).

    Returns:
        :class:`RenderOutput`.
    """
    cfg = cfg or RendererConfig()
    g.check()
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must be [4, 4], got {list(w2c.shape)}")
    if cfg.backend == "gsplat":
        from semantic_gs_slam.render_gsplat import render_gsplat

        return render_gsplat(g, w2c, k, cfg)
    return _render_torch(g, w2c, k, cfg)


def project(g: Gaussians, w2c: Tensor, k: Intrinsics, near: float) -> dict[str, Tensor]:
    """Project Gaussians to the image: centres, conics, log-opacities, depths and the visible index.

    Returns:
        dict with ``idx`` [M] (indices of Gaussians in front of the camera), ``uv`` [M, 2], ``conic``
        [M, 3] (a, b, c of the inverse 2-D covariance), ``cov`` [M, 3] (xx, xy, yy), ``log_o`` [M],
        ``z`` [M].
    """
    pc = g.means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    idx = torch.nonzero(pc[:, 2].detach() > near).squeeze(1)
    pc = pc[idx]
    x, y, z = pc.unbind(-1)
    # clamp the Jacobian's x/z, y/z to 1.3x the field of view (as 3DGS), else near off-screen Gaussians blow up
    tx = (x / z).clamp(-1.3 * (k.cx + 0.5) / k.fx, 1.3 * (k.width - k.cx - 0.5) / k.fx) * z
    ty = (y / z).clamp(-1.3 * (k.cy + 0.5) / k.fy, 1.3 * (k.height - k.cy - 0.5) / k.fy) * z
    zero = torch.zeros_like(z)
    j = torch.stack([k.fx / z, zero, -k.fx * tx / (z * z), zero, k.fy / z, -k.fy * ty / (z * z)], -1).reshape(-1, 2, 3)
    ls = g.log_scales[idx]
    if ls.shape[1] == 1:
        s2 = torch.exp(2 * ls[:, 0])  # isotropic: covariance s^2 I in every frame
        jj = j @ j.transpose(1, 2)  # [M, 2, 2]
        cov2 = s2[:, None, None] * jj
    else:
        r = quat_to_rotmat(g.quats[idx])  # [M, 3, 3]
        m = w2c[:3, :3] @ r * torch.exp(ls)[:, None, :]  # camera-frame R S
        cov2 = j @ m @ m.transpose(1, 2) @ j.transpose(1, 2)
    cxx = cov2[:, 0, 0] + 0.3
    cxy = cov2[:, 0, 1]
    cyy = cov2[:, 1, 1] + 0.3
    det = (cxx * cyy - cxy * cxy).clamp_min(1e-12)
    conic = torch.stack([cyy / det, -cxy / det, cxx / det], -1)
    uv = torch.stack([k.fx * x / z + k.cx, k.fy * y / z + k.cy], -1)
    log_o = math.log(OPACITY_CAP) + torch.nn.functional.logsigmoid(g.logit_opacities[idx, 0])
    return {"idx": idx, "uv": uv, "conic": conic, "cov": torch.stack([cxx, cxy, cyy], -1), "log_o": log_o, "z": z}


class _Composite(torch.autograd.Function):
    """Front-to-back alpha compositing of a batch of tiles with a hand-written backward.

    Inputs: coef [B, K, 6] exponent coefficients (K depth-sorted), feats [B, K, C], mono [6, P]
    monomials of the tile-local pixel coordinates, chunk (int), stop (float).
    Output: [B, C + 1, P] composited features, last channel the silhouette.
    """

    @staticmethod
    def forward(ctx, coef: Tensor, feats: Tensor, mono: Tensor, chunk: int, stop: float) -> Tensor:  # noqa: D102
        b, kk, c = feats.shape
        p = mono.shape[1]
        ones = torch.ones(b, kk, 1, dtype=feats.dtype, device=feats.device)
        fx = torch.cat([feats, ones], -1)  # [B, K, C+1]
        out = torch.zeros(b, c + 1, p, dtype=feats.dtype, device=feats.device)
        t_run = torch.ones(b, 1, p, dtype=feats.dtype, device=feats.device)
        alphas, trans = [], []
        done = 0
        for s in range(0, kk, chunk):
            e = min(kk, s + chunk)
            pw = (coef[:, s:e] @ mono).clamp_(min=EXP_FLOOR)  # [B, k, P]
            a = torch.exp(pw)
            a = a.masked_fill_(a < ALPHA_MIN, 0.0)
            tc = torch.cumprod(1 - a, dim=1)
            t_ex = torch.cat([t_run, t_run * tc[:, :-1]], 1)  # transmittance in front of each Gaussian
            w = a * t_ex
            out += fx[:, s:e].transpose(1, 2) @ w
            t_run = t_run * tc[:, -1:]
            alphas.append(a)
            trans.append(t_ex)
            done = e
            if float(t_run.max()) < stop:
                break
        ctx.save_for_backward(fx, mono, torch.cat(alphas, 1), torch.cat(trans, 1))
        ctx.done = done
        ctx.kk = kk
        return out

    @staticmethod
    def backward(ctx, gout: Tensor):  # noqa: D102
        fx, mono, a, t_ex = ctx.saved_tensors
        done = ctx.done
        fxd = fx[:, :done]
        w = a * t_ex  # [B, k, P]
        h = fxd @ gout  # [B, k, P]: g . f_i per pixel
        wh = w * h
        suffix = wh.sum(1, keepdim=True) - torch.cumsum(wh, 1)  # sum over the Gaussians behind (k > i)
        # dL/dalpha_i = T_i h_i - suffix_i / (1 - alpha_i); alpha = exp(power) where kept, so
        # dL/dpower = alpha dL/dalpha = w h - alpha / (1 - alpha) suffix  (0 where alpha was dropped)
        d_pw = wh - a / (1 - a) * suffix
        g_coef = d_pw @ mono.T  # [B, k, 6]
        g_feat = (w @ gout.transpose(1, 2))[..., :-1]  # [B, k, C]
        if done < ctx.kk:
            b = fx.shape[0]
            g_coef = torch.cat([g_coef, g_coef.new_zeros(b, ctx.kk - done, 6)], 1)
            g_feat = torch.cat([g_feat, g_feat.new_zeros(b, ctx.kk - done, g_feat.shape[2])], 1)
        return g_coef, g_feat, None, None, None


def _render_torch(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig) -> RenderOutput:
    dev, dt = g.means.device, g.means.dtype
    ts = cfg.tile
    ntx, nty = (k.width + ts - 1) // ts, (k.height + ts - 1) // ts
    n_tiles = ntx * nty
    pr = project(g, w2c, k, cfg.near)
    idx, uv, conic, cov, log_o, z = pr["idx"], pr["uv"], pr["conic"], pr["cov"], pr["log_o"], pr["z"]
    feats = [g.rgb[idx], z[:, None]]
    if g.semantic is not None:
        feats.append(g.semantic[idx])
    feats_all = torch.cat(feats, -1)  # [M, C]
    c_out = feats_all.shape[1]
    with torch.no_grad():
        # footprint: alpha >= 1/255  <=>  d^2 <= 2 ln(255 o); box from the marginal std devs
        r2 = 2 * (log_o + math.log(255.0))
        keep = r2 > 0
        rad = torch.sqrt(r2.clamp_min(0))
        hx, hy = rad * torch.sqrt(cov[:, 0]), rad * torch.sqrt(cov[:, 2])
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
    a_, b_, c_ = conic[pg].unbind(-1)
    du = uv[pg, 0] - tx0
    dv = uv[pg, 1] - ty0
    coef_pairs = torch.stack([
        -0.5 * a_ * du * du - b_ * du * dv - 0.5 * c_ * dv * dv + log_o[pg],
        a_ * du + b_ * dv, b_ * du + c_ * dv, -0.5 * a_, -b_, -0.5 * c_], -1)  # [pairs, 6]
    pad_row = torch.tensor([-30.0, 0, 0, 0, 0, 0], dtype=dt, device=dev)
    p = ts * ts
    outs, out_tiles = [], []
    i0 = 0
    tl = tiles_sorted.tolist()
    counts = tcount[tiles_sorted].tolist()
    while i0 < len(tl):
        kb = counts[i0]
        nb = max(1, cfg.batch_elements // (kb * p))
        bt = tiles_sorted[i0:i0 + nb]
        with torch.no_grad():
            kr = torch.arange(kb, device=dev)
            mask = kr[None, :] < tcount[bt][:, None]  # [B, K]
            pidx = (tstart[bt][:, None] + kr[None, :]).clamp(max=max(total - 1, 0))
        cf = torch.where(mask[..., None], coef_pairs[pidx], pad_row)
        ft = feats_all[pg[pidx]] * mask[..., None]
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


def render_reference(g: Gaussians, w2c: Tensor, k: Intrinsics, near: float = 0.05) -> RenderOutput:
    """Dense per-pixel reference renderer (plain autograd, every Gaussian at every pixel). Tests only: O(N H W)."""
    pr = project(g, w2c, k, near)
    idx, uv, conic, log_o, z = pr["idx"], pr["uv"], pr["conic"], pr["log_o"], pr["z"]
    order = torch.argsort(z.detach())
    feats = [g.rgb[idx], z[:, None]]
    if g.semantic is not None:
        feats.append(g.semantic[idx])
    f = torch.cat(feats, -1)[order]  # [M, C]
    v, u = torch.meshgrid(torch.arange(k.height, dtype=g.means.dtype), torch.arange(k.width, dtype=g.means.dtype),
                          indexing="ij")
    px = torch.stack([u.reshape(-1), v.reshape(-1)], -1)  # [P, 2]
    d = px[None] - uv[order][:, None]  # [M, P, 2]
    a_, b_, c_ = conic[order].unbind(-1)
    pw = -0.5 * (a_[:, None] * d[..., 0] ** 2 + 2 * b_[:, None] * d[..., 0] * d[..., 1] + c_[:, None] * d[..., 1] ** 2)
    alpha = torch.exp(pw + log_o[order][:, None])
    alpha = torch.where(alpha < ALPHA_MIN, torch.zeros_like(alpha), alpha)
    t = torch.cumprod(torch.cat([torch.ones_like(alpha[:1]), 1 - alpha[:-1]], 0), 0)
    w = alpha * t  # [M, P]
    out = (w.T @ f).reshape(k.height, k.width, -1)
    sil = w.sum(0).reshape(k.height, k.width)
    sem = out[..., 4:] if g.semantic is not None else None
    return RenderOutput(out[..., :3], out[..., 3], sil, sem, int(idx.numel()))
