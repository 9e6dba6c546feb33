"""Camera tracking: point-to-plane ICP of the live depth against the depth rendered from the map.

The model is rendered once at the constant-velocity guess; its depth (normalised by the silhouette,
used only where the silhouette is high) gives a vertex and a normal map in world coordinates.
Live points are associated projectively through the guess camera (KinectFusion-style) and the
pose is updated by Gauss-Newton on the point-to-plane residuals, coarse to fine. An optional
photometric refinement then runs Adam on the pose against colour and depth L1.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, RendererConfig, TrackingConfig
from semantic_gs_slam.errors import TrackingError
from semantic_gs_slam.geometry import backproject, quat_to_rotmat, se3_exp
from semantic_gs_slam.render import Gaussians, render


@dataclass
class TrackResult:
    """Outcome of tracking one frame."""

    c2w: Tensor  # [4, 4] float64
    residual: float  # RMS point-to-plane residual of the last iteration (m)
    inliers: int  # correspondences used in the last iteration


def normal_map(v: Tensor, valid: Tensor) -> tuple[Tensor, Tensor]:
    """Normals of a vertex map by central-ish differences.

    Args:
        v: [H, W, 3] points. valid: [H, W] bool.

    Returns:
        normals [H, W, 3] (unit), valid [H, W] (neighbours valid too).
    """
    dx = torch.zeros_like(v)
    dy = torch.zeros_like(v)
    dx[:, :-1] = v[:, 1:] - v[:, :-1]
    dy[:-1] = v[1:] - v[:-1]
    n = torch.cross(dx, dy, dim=-1)
    norm = n.norm(dim=-1, keepdim=True)
    ok = valid.clone()
    ok[:, -1] = False
    ok[-1] = False
    ok[:, :-1] &= valid[:, 1:]
    ok[:-1] &= valid[1:]
    ok &= norm[..., 0] > 1e-12
    # no normals across depth discontinuities (neighbour steps longer than 5 % of the distance)
    lim = 0.05 * v.norm(dim=-1)
    ok &= (dx.norm(dim=-1) < lim) & (dy.norm(dim=-1) < lim)
    return n / norm.clamp_min(1e-12), ok


def _bilinear(img: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Sample [H, W, C] at float pixel coordinates u, v [M] (caller keeps them inside [0, W-1) x [0, H-1))."""
    u0, v0 = torch.floor(u).long(), torch.floor(v).long()
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    return ((1 - fu) * (1 - fv) * img[v0, u0] + fu * (1 - fv) * img[v0, u0 + 1]
            + (1 - fu) * fv * img[v0 + 1, u0] + fu * fv * img[v0 + 1, u0 + 1])


def icp(model_depth: Tensor, model_valid: Tensor, guess_c2w: Tensor, live_depth: Tensor, k: Intrinsics,
        cfg: TrackingConfig, model_rgb: Tensor | None = None, live_rgb: Tensor | None = None,
        start_c2w: Tensor | None = None) -> TrackResult:
    """Point-to-plane ICP (plus an optional photometric term) of a live frame against a model frame
    rendered at ``guess_c2w``.

    The joint Gauss-Newton minimises ``sum w_g (n . (T x - q))^2 / s_g^2 + sum w_c (I_m(pi(T x)) - I_l)^2 / s_c^2``
    with Huber weights; the photometric term pins down the directions that planes leave free (a camera
    sliding along a wall).

    Args:
        model_depth: [H, W] metres (rendered at the guess pose).
        model_valid: [H, W] bool.
        guess_c2w: [4, 4] float64 pose the model was rendered at (also the start).
        live_depth: [H, W] metres, 0 = missing.
        k: intrinsics.
        cfg: tracking settings.
        model_rgb: [H, W, 3] colour rendered at the guess pose, or None (geometry only).
        live_rgb: [H, W, 3] live colour, or None.
        start_c2w: [4, 4] initial estimate (default: ``guess_c2w``).

    Returns:
        :class:`TrackResult`.

    Raises:
        TrackingError: fewer than ``cfg.min_correspondences`` associations.
    """
    dt = torch.float64
    g = guess_c2w.to(dt)
    vm_c = backproject(model_depth.to(dt), k.fx, k.fy, k.cx, k.cy)
    vm = vm_c @ g[:3, :3].T + g[:3, 3]  # world vertex map [H, W, 3]
    nm, nvalid = normal_map(vm, model_valid)
    w2c_g = torch.linalg.inv(g)
    est = g.clone() if start_c2w is None else start_c2w.to(dt).clone()
    live_all = backproject(live_depth.to(dt), k.fx, k.fy, k.cx, k.cy)
    use_col = model_rgb is not None and live_rgb is not None and cfg.photometric_weight > 0
    if use_col:
        im = model_rgb.to(dt).mean(-1)  # [H, W] intensity
        il_all = live_rgb.to(dt).mean(-1)
        gx = torch.zeros_like(im)
        gy = torch.zeros_like(im)
        gx[:, 1:-1] = 0.5 * (im[:, 2:] - im[:, :-2])
        gy[1:-1] = 0.5 * (im[2:] - im[:-2])
        okm = model_valid.clone()
        okm[:, 1:-1] &= model_valid[:, 2:] & model_valid[:, :-2]
        okm[1:-1] &= model_valid[2:] & model_valid[:-2]
        okm[:, [0, -1]] = False
        okm[[0, -1]] = False
        col_img = torch.stack([im, gx, gy, okm.to(dt)], -1)  # [H, W, 4]
    res_rms, n_in = float("nan"), 0
    sg, sc = cfg.icp_sigma_geo, cfg.icp_sigma_col
    wg = cfg.geometric_weight
    for level in reversed(range(cfg.icp_levels)):
        stride = 2 ** (level + 1)
        lp = live_all[::stride, ::stride].reshape(-1, 3)
        keep = lp[:, 2] > 0
        lp = lp[keep]
        il = il_all[::stride, ::stride].reshape(-1)[keep] if use_col else None
        for _ in range(cfg.icp_iters):
            x = lp @ est[:3, :3].T + est[:3, 3]  # world
            xc = x @ w2c_g[:3, :3].T + w2c_g[:3, 3]
            z = xc[:, 2].clamp_min(1e-6)
            uf = k.fx * xc[:, 0] / z + k.cx
            vf = k.fy * xc[:, 1] / z + k.cy
            u, v = torch.round(uf).long(), torch.round(vf).long()
            inside = (xc[:, 2] > 1e-3) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
            ii = torch.nonzero(inside).squeeze(1)
            ok = nvalid[v[ii], u[ii]]
            ii = ii[ok]
            q, n = vm[v[ii], u[ii]], nm[v[ii], u[ii]]
            xs = x[ii]
            diff = xs - q
            close = diff.norm(dim=-1) < cfg.icp_max_dist
            ii, xs, n, diff = ii[close], xs[close], n[close], diff[close]
            r = (diff * n).sum(-1)
            n_in = int(r.numel())
            if n_in < cfg.min_correspondences:
                raise TrackingError(f"ICP found only {n_in} correspondences (< {cfg.min_correspondences})")
            w = torch.where(r.abs() < sg, torch.ones_like(r), sg / r.abs()) * wg / (sg * sg)
            jac = torch.cat([torch.cross(xs, n, dim=-1), n], -1)  # [M, 6]
            a = (jac * w[:, None]).T @ jac
            b = -(jac * w[:, None]).T @ r
            if use_col and level == 0:  # photometric term only at the finest level (small basin)
                inb = inside & (uf >= 0) & (uf < k.width - 1) & (vf >= 0) & (vf < k.height - 1)
                jj = torch.nonzero(inb).squeeze(1)
                smp = _bilinear(col_img, uf[jj], vf[jj])
                good = smp[:, 3] > 0.999
                jj, smp = jj[good], smp[good]
                rc = smp[:, 0] - il[jj]
                xw, xcj, zj = x[jj], xc[jj], z[jj]
                # d(pixel)/d(camera point), camera point = R_gw (world point); world point moves by w x X + t
                du = torch.stack([k.fx / zj, torch.zeros_like(zj), -k.fx * xcj[:, 0] / (zj * zj)], -1)
                dv = torch.stack([torch.zeros_like(zj), k.fy / zj, -k.fy * xcj[:, 1] / (zj * zj)], -1)
                gvec = (smp[:, 1:2] * du + smp[:, 2:3] * dv) @ w2c_g[:3, :3]  # [M, 3] d I / d world point
                jc = torch.cat([torch.cross(xw, gvec, dim=-1), gvec], -1)
                wc = torch.where(rc.abs() < sc, torch.ones_like(rc), sc / rc.abs()) * cfg.photometric_weight / (sc * sc)
                a += (jc * wc[:, None]).T @ jc
                b += -(jc * wc[:, None]).T @ rc
            a += 1e-6 * torch.eye(6, dtype=dt) * a.diagonal().mean()
            xi = torch.linalg.solve(a, b)
            est = se3_exp(xi) @ est
            res_rms = float(torch.sqrt((r * r).mean()))
            if float(xi.abs().max()) < 1e-7:
                break
    return TrackResult(est, res_rms, n_in)


def _quat_from_rot(r: Tensor) -> Tensor:
    from semantic_gs_slam.geometry import rotmat_to_quat

    return torch.as_tensor(rotmat_to_quat(r.detach().cpu().numpy()))


def photometric_refine(g: Gaussians, c2w: Tensor, rgb: Tensor, depth: Tensor, k: Intrinsics,
                       rcfg: RendererConfig, cfg: TrackingConfig) -> Tensor:
    """Refine a pose with Adam on L1 colour + depth over well-observed pixels (silhouette > min).

    Args:
        g: the map (detached parameters are fine).
        c2w: [4, 4] start pose. rgb: [H, W, 3]. depth: [H, W].

    Returns:
        [4, 4] float64 refined camera-to-world pose.
    """
    w2c0 = torch.linalg.inv(c2w.double())
    q = _quat_from_rot(w2c0[:3, :3]).float().requires_grad_(True)
    t = w2c0[:3, 3].float().clone().requires_grad_(True)
    opt = torch.optim.Adam([{"params": [q], "lr": cfg.photometric_lr_rot},
                            {"params": [t], "lr": cfg.photometric_lr_trans}])
    gd = Gaussians(*(x.detach() for x in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb)), None)
    valid = depth > 0
    for _ in range(cfg.photometric_iters):
        w2c = torch.eye(4)
        w2c = torch.cat([torch.cat([quat_to_rotmat(q), t[:, None]], 1), w2c[3:]], 0)
        out = render(gd, w2c, k, rcfg)
        m = (out.silhouette.detach() > cfg.min_silhouette) & valid
        if int(m.sum()) < cfg.min_correspondences:
            break
        loss = (out.depth - depth).abs()[m].sum() + 0.5 * (out.rgb - rgb).abs().sum(-1)[m].sum()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        w2c = torch.eye(4, dtype=torch.float64)
        w2c[:3, :3] = quat_to_rotmat(q.double())
        w2c[:3, 3] = t.double()
    return torch.linalg.inv(w2c)
