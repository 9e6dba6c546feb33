"""Projection and tile binning shared by the CPU renderer back-ends (no compositing here).

:func:`tile_pairs` projects the Gaussians, finds the tiles each one's footprint touches and lists the
(tile, Gaussian) pairs sorted by tile and, within a tile, by depth, with each pair's exponent as a
quadratic in the tile-local pixel coordinates (six coefficients). Both the pure-PyTorch compositor
(:mod:`semantic_gs_slam.render`, the reference) and the compiled CPU one
(:mod:`semantic_gs_slam.render.numba_backend`) composite these pairs; everything here is differentiable through
torch's autograd (the pair coefficients and features), so a compositor only returns the gradients of
its own inputs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.geometry import quat_to_rotmat
from semantic_gs_slam.render.types import BLUR_PX2, FOV_MARGIN, OPACITY_CAP, Gaussians

__all__ = ["TilePairs", "check_inputs", "cull_bounds", "footprint", "jacobian_limits", "project", "project_rows",
           "tile_pairs"]


def check_inputs(g: Gaussians, w2c: Tensor) -> None:
    """Raise ValueError on inconsistent Gaussians or a pose of the wrong shape or device."""
    g.check()
    if tuple(w2c.shape) != (4, 4):
        raise ValueError(f"w2c must be [4, 4], got {list(w2c.shape)}")
    if w2c.device != g.means.device:
        raise ValueError(f"w2c is on {w2c.device} but the Gaussians are on {g.means.device}")


def jacobian_limits(k: Intrinsics) -> tuple[float, float, float, float]:
    """Clamp range of x/z and y/z in the projection Jacobian: (x_neg, x_pos, y_neg, y_pos), gsplat's rule
    ``cx' / fx + 0.3 tan(fov_x / 2)`` with gsplat's principal point ``cx' = cx + 0.5``."""
    tx, ty = FOV_MARGIN * 0.5 * k.width / k.fx, FOV_MARGIN * 0.5 * k.height / k.fy
    return ((k.cx + 0.5) / k.fx + tx, (k.width - k.cx - 0.5) / k.fx + tx,
            (k.cy + 0.5) / k.fy + ty, (k.height - k.cy - 0.5) / k.fy + ty)


def project(g: Gaussians, w2c: Tensor, k: Intrinsics, near: float, cull: tuple[int, int] | None = None
            ) -> dict[str, Tensor]:
    """Project Gaussians to the image: centres, conics, log-opacities, depths and the visible index.

    Args:
        cull: (width, height) in pixels of the area drawn (the image rounded up to whole tiles): Gaussians whose
            footprint (:func:`footprint`, bounded from above: largest scale, opacity cap, the Jacobian's clamp)
            cannot reach it are dropped before the differentiable projection (:func:`cull_bounds`). None: only
            those behind ``near`` (the reference).

    Returns:
        dict with ``idx`` [M] (indices of Gaussians in front of the camera, within ``cull`` when given),
        ``uv`` [M, 2], ``conic`` [M, 3] (a, b, c of the inverse 2-D covariance), ``cov`` [M, 3] (xx, xy, yy),
        ``log_o`` [M], ``z`` [M].
    """
    pc = g.means @ w2c[:3, :3].T + w2c[:3, 3]  # [N, 3]
    if cull is None:
        idx = torch.nonzero(pc[:, 2].detach() > near).squeeze(1)
    else:
        idx = torch.nonzero(cull_bounds(pc.detach(), g.log_scales.detach(), k, near, *cull)).squeeze(1)
    ls = g.log_scales.index_select(0, idx)
    quats = g.quats.index_select(0, idx) if ls.shape[1] == 3 else None
    out = project_rows(pc.index_select(0, idx), ls, quats, g.logit_opacities.index_select(0, idx), w2c, k)
    out["idx"] = idx
    return out


def cull_bounds(pc: Tensor, log_scales: Tensor, k: Intrinsics, near: float, width: int, height: int) -> Tensor:
    """[N] bool: in front of ``near`` and, by an upper bound of its footprint, possibly touching the
    ``width`` x ``height`` pixels drawn (a superset of what :func:`tile_pairs` keeps: culling changes no pixel).

    The bound: a 2-D covariance's xx entry is at most ``s^2 (fx / z)^2 (1 + lim^2) + BLUR_PX2`` for the largest
    scale ``s`` (any rotation) and the Jacobian's clamp ``lim`` on ``|x / z|`` (:func:`jacobian_limits`), and the
    footprint's radius at most ``sqrt(2 ln(255 OPACITY_CAP))`` standard deviations (:func:`footprint`); 1 % and
    a pixel more for rounding.

    Args:
        pc: [N, 3] camera-frame centres. log_scales: [N, 1] or [N, 3].
    """
    x, y, z = pc.unbind(-1)
    front = z > near
    zs = torch.where(front, z, torch.ones_like(z))
    xn, xp, yn, yp = jacobian_limits(k)
    s2 = torch.exp(2 * log_scales.max(dim=1).values)
    rad = 1.01 * math.sqrt(2 * math.log(255.0 * OPACITY_CAP))
    hx = rad * torch.sqrt(s2 * (k.fx / zs) ** 2 * (1 + max(xn, xp) ** 2) + BLUR_PX2) + 1
    hy = rad * torch.sqrt(s2 * (k.fy / zs) ** 2 * (1 + max(yn, yp) ** 2) + BLUR_PX2) + 1
    u = k.fx * x / zs + k.cx
    v = k.fy * y / zs + k.cy
    return front & (u + hx >= -0.5) & (u - hx < width - 0.5) & (v + hy >= -0.5) & (v - hy < height - 0.5)


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


@dataclass
class TilePairs:
    """The (tile, Gaussian) pairs of one view, sorted by tile, then front to back.

    Tile ``t`` (row-major over ``ntx`` x ``nty`` tiles of ``tile`` x ``tile`` pixels) owns pairs
    ``tstart[t] .. tstart[t] + tcount[t] - 1``. A pair's exponent (log-opacity included) at the tile-local
    pixel (i, j) is ``coef . [1, i, j, i^2, i j, j^2]``; its alpha is the exponential of that.
    """

    tile: int  # tile edge in pixels
    ntx: int  # tiles per row
    nty: int  # tile rows
    coef: Tensor | None  # [pairs, 6] exponent coefficients (differentiable); None when not asked for
    feats: Tensor  # [M, C] features of the projected Gaussians: rgb, depth (z), semantic (differentiable)
    uv: Tensor  # [M, 2] projected centres (pixels; differentiable)
    conic: Tensor  # [M, 3] a, b, c of the inverse 2-D covariances (differentiable)
    log_o: Tensor  # [M] log-opacities (differentiable)
    pg: Tensor  # [pairs] int64: the pair's row of ``feats``
    tstart: Tensor  # [ntx * nty] int64: the tile's first pair
    tcount: Tensor  # [ntx * nty] int64: the tile's number of pairs
    tiles_sorted: Tensor  # [T'] int64: tiles with pairs, most pairs first
    n_visible: int  # Gaussians in front of the camera whose footprint touches the image


def bin_pairs_torch(x0: Tensor, x1: Tensor, y0: Tensor, y1: Tensor, kidx: Tensor, ntx: int,
                    n_tiles: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The (tile, Gaussian) pairs of the tile boxes ``[x0, x1] x [y0, y1]`` (int64 [M], clamped to the image's
    tiles) of the Gaussians ``kidx`` (front to back), sorted by tile and front to back within a tile: the
    reference (any device; a stable sort of all pairs by tile).

    Returns:
        ``pg`` [pairs] (the pair's Gaussian), ``ptile`` [pairs] (its tile), ``tcount`` and ``tstart`` [n_tiles].
    """
    dev = x0.device
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
    return pg, ptile, tcount, tstart


def tile_pairs(g: Gaussians, w2c: Tensor, k: Intrinsics, cfg: RendererConfig, bin_pairs=bin_pairs_torch,
               coefficients: bool = True, cull: bool = True) -> TilePairs:
    """Project ``g`` seen from ``w2c`` and bin the footprints into tiles (see :class:`TilePairs`).

    Args:
        bin_pairs: the binning (:func:`bin_pairs_torch`, or a compiled one with its signature and result).
        coefficients: compute the pairs' exponent coefficients (``False``: a compositor that computes them
            per tile from ``uv``, ``conic`` and ``log_o``).
        cull: drop the Gaussians whose footprint cannot reach the image before the differentiable projection
            (:func:`cull_bounds`: the same pairs, less autograd work; at 320x240 on the kitchen 6 in 10 of the
            map's Gaussians in front of a view are outside it). False: only those behind ``cfg.near``.

    Raises:
        ValueError: inconsistent Gaussians or a bad pose (:func:`check_inputs`).
    """
    check_inputs(g, w2c)
    dt = g.means.dtype
    ts = cfg.tile
    ntx, nty = (k.width + ts - 1) // ts, (k.height + ts - 1) // ts
    n_tiles = ntx * nty
    pr = project(g, w2c, k, cfg.near, cull=(ntx * ts, nty * ts) if cull else None)
    idx, uv, conic, cov, log_o, z = pr["idx"], pr["uv"], pr["conic"], pr["cov"], pr["log_o"], pr["z"]
    feats = [g.rgb.index_select(0, idx), z[:, None]]
    if g.semantic is not None:
        feats.append(g.semantic.index_select(0, idx))
    feats_all = torch.cat(feats, -1)  # [M, C]
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
        kidx = kidx[torch.argsort(z[kidx])]  # front to back
        pg, ptile, tcount, tstart = bin_pairs(x0, x1, y0, y1, kidx, ntx, n_tiles)
        tiles_sorted = torch.argsort(tcount, descending=True)
        tiles_sorted = tiles_sorted[tcount[tiles_sorted] > 0]
    if not coefficients:
        return TilePairs(ts, ntx, nty, None, feats_all, uv, conic, log_o, pg, tstart, tcount, tiles_sorted,
                         int(kidx.numel()))
    # exponent coefficients for every pair (one vectorised computation)
    tx0 = (ptile % ntx).to(dt) * ts
    ty0 = (ptile // ntx).to(dt) * ts
    # index_select (backward: index_add) rather than advanced indexing (backward: slow index_put)
    a_, b_, c_ = conic.index_select(0, pg).unbind(-1)
    uvp = uv.index_select(0, pg)
    du = uvp[:, 0] - tx0
    dv = uvp[:, 1] - ty0
    coef = torch.stack([
        -0.5 * a_ * du * du - b_ * du * dv - 0.5 * c_ * dv * dv + log_o.index_select(0, pg),
        a_ * du + b_ * dv, b_ * du + c_ * dv, -0.5 * a_, -b_, -0.5 * c_], -1)  # [pairs, 6]
    return TilePairs(ts, ntx, nty, coef, feats_all, uv, conic, log_o, pg, tstart, tcount, tiles_sorted,
                     int(kidx.numel()))
