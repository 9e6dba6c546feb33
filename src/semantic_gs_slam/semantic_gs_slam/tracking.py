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
from semantic_gs_slam.render import Gaussians, RenderBackend, RenderOutput, select_backend


@dataclass
class TrackResult:
    """Outcome of tracking one frame."""

    c2w: Tensor  # [4, 4] float64
    residual: float  # RMS point-to-plane residual of the last iteration (m)
    inliers: int  # correspondences used in the last iteration
    agreement: float = float("nan")  # of the live points that land on the model at the final pose, the share
    # within 3 sigma (point-to-plane) of its surface: low when the pose is wrong (see TrackingConfig.lost_agreement)


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


def plane_depth_features(means_c: Tensor, normals_c: Tensor, k: Intrinsics, min_cos: float = 0.2) -> Tensor:
    """Per-Gaussian features [N, 3] whose rendered blend gives depth along each pixel's ray.

    A Gaussian rendered with its centre depth ``Z`` is biased on oblique surfaces: a pixel ``d``
    pixels from the centre sees the surface at ``Z + d * dz/du``, not ``Z``. With a surface normal
    ``n`` the depth of the plane through the centre is, to first order around the centre pixel
    ``(u_c, v_c)``, ``z(u, v) = Z + a (u - u_c) + b (v - v_c)`` with ``a = -Z^2 n_x / (f_x n.mu)``,
    ``b = -Z^2 n_y / (f_y n.mu)``. Rendering ``F = [Z - a u_c - b v_c, a, b]`` as features and
    computing ``(F0 + u F1 + v F2) / silhouette`` per pixel blends these per-Gaussian planes instead
    of constant depths.

    Args:
        means_c: [N, 3] camera-frame centres. normals_c: [N, 3] camera-frame unit normals (zero rows:
            unknown). k: intrinsics. min_cos: planes seen more obliquely than this (|cos| of the angle
            between the normal and the viewing ray) fall back to the centre depth.

    Returns:
        [N, 3] features.
    """
    z = means_c[:, 2]
    nmu = (normals_c * means_c).sum(-1)
    cos = nmu.abs() / means_c.norm(dim=-1).clamp_min(1e-9)
    use = (cos >= min_cos) & (normals_c.norm(dim=-1) > 0.5)
    nmu = torch.where(use, nmu, torch.ones_like(nmu))
    a = torch.where(use, -z * z * normals_c[:, 0] / (k.fx * nmu), torch.zeros_like(z))
    b = torch.where(use, -z * z * normals_c[:, 1] / (k.fy * nmu), torch.zeros_like(z))
    uc = k.fx * means_c[:, 0] / z + k.cx
    vc = k.fy * means_c[:, 1] / z + k.cy
    return torch.stack([z - a * uc - b * vc, a, b], -1)


def plane_depth_image(feats_img: Tensor, silhouette: Tensor | None = None) -> Tensor:
    """Depth [H, W] from rendered :func:`plane_depth_features` [H, W, 3]: normalised by ``silhouette``
    when given, else the blend ``sum w_i z_i(u, v)`` (not normalised, like the renderer's depth)."""
    h, w = feats_img.shape[:2]
    v, u = torch.meshgrid(torch.arange(h, dtype=feats_img.dtype, device=feats_img.device),
                          torch.arange(w, dtype=feats_img.dtype, device=feats_img.device), indexing="ij")
    num = feats_img[..., 0] + u * feats_img[..., 1] + v * feats_img[..., 2]
    return num if silhouette is None else num / silhouette.clamp_min(1e-6)


def smooth_depth(depth: Tensor, valid: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Box-filter a depth image over its valid pixels (size x size window).

    Args:
        depth: [H, W] metres. valid: [H, W] bool. size: odd window edge.

    Returns:
        smoothed depth [H, W] and the pixels that stay valid (valid and with >= half the window valid).
    """
    import torch.nn.functional as F

    v = valid.to(depth.dtype)[None, None]
    num = F.avg_pool2d((depth * valid)[None, None], size, 1, size // 2, count_include_pad=False)
    den = F.avg_pool2d(v, size, 1, size // 2, count_include_pad=False)
    ok = valid & (den[0, 0] > 0.5)
    return torch.where(ok, num[0, 0] / den[0, 0].clamp_min(1e-6), torch.zeros_like(depth)), ok


def _so3_log(r: Tensor) -> Tensor:
    """Axis-angle [3] of a rotation [3, 3] (small-angle safe)."""
    c = ((r.diagonal().sum() - 1) / 2).clamp(-1.0, 1.0)
    th = torch.arccos(c)
    v = torch.stack([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    s = torch.where(th < 1e-6, torch.ones_like(th) * 0.5, th / (2 * torch.sin(th).clamp_min(1e-12)))
    return v * s


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
    if cfg.normal_smoothing > 1:
        model_depth, model_valid = smooth_depth(model_depth, model_valid, cfg.normal_smoothing)
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
    res_rms, n_in, agree = float("nan"), 0, float("nan")
    sg, sc = cfg.icp_sigma_geo, cfg.icp_sigma_col
    wg = cfg.geometric_weight
    dev = live_depth.device
    p_w = torch.diag(torch.tensor([1 / cfg.prior_sigma_rot**2] * 3 + [1 / cfg.prior_sigma_trans**2] * 3, dtype=dt,
                                  device=dev))
    eye6 = torch.eye(6, dtype=dt, device=dev)
    base = max(1, round(k.width / 160))  # about 160 live points per row at the finest level
    for level in reversed(range(cfg.icp_levels)):
        stride = base * 2**level
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
            # weak prior toward the guess: keeps directions the data leave free from drifting
            d = est @ w2c_g
            prior = torch.cat([_so3_log(d[:3, :3]), d[:3, 3]])
            a += p_w
            b += -(p_w @ prior)
            a += 1e-9 * eye6 * a.diagonal().mean()
            xi = torch.linalg.solve(a, b)
            est = se3_exp(xi) @ est
            on_model = ok.to(dt).sum().clamp_min(1.0)
            res_rms, step, agree = torch.stack([torch.sqrt((r * r).mean()), xi.abs().max(),
                                                (r.abs() < 3 * sg).to(dt).sum() / on_model]).tolist()  # one host copy
            if step < 1e-6:
                break
    return TrackResult(est, res_rms, n_in, agree)


def _quat_from_rot(r: Tensor) -> Tensor:
    from semantic_gs_slam.geometry import rotmat_to_quat

    return torch.as_tensor(rotmat_to_quat(r.detach().cpu().numpy()), device=r.device)


def photometric_loss(g: Gaussians, w2c: Tensor, rgb: Tensor, depth: Tensor, k: Intrinsics, rcfg: RendererConfig,
                     min_silhouette: float, backend: RenderBackend | None = None) -> Tensor:
    """Sum of L1 depth + 0.5 L1 colour (both normalised by the silhouette) over pixels with valid depth and
    silhouette > ``min_silhouette`` (0 when no pixel qualifies); a fixed-shape computation (a mask
    multiplies, no boolean indexing), so no host synchronisation."""
    out = (backend or select_backend(rcfg, g.means.device))(g, w2c, k, rcfg)
    return photometric_loss_of(out, rgb, depth, min_silhouette)


def photometric_loss_of(out: RenderOutput, rgb: Tensor, depth: Tensor, min_silhouette: float) -> Tensor:
    """:func:`photometric_loss` of a rendered view ``out`` against ``rgb`` [H, W, 3] and ``depth`` [H, W]."""
    m = ((out.silhouette.detach() > min_silhouette) & (depth > 0)).to(depth.dtype)
    sil = out.silhouette.clamp_min(1e-6)
    l_depth = ((out.depth / sil - depth).abs() * m).sum()
    return l_depth + 0.5 * ((out.rgb / sil[..., None] - rgb).abs().sum(-1) * m).sum()


def w2c_from_quat_trans(q: Tensor, t: Tensor) -> Tensor:
    """[4, 4] world-to-camera pose from an (unnormalised) quaternion [4] (wxyz) and a translation [3]."""
    bottom = torch.nn.functional.pad(torch.ones_like(t[:1]), (3, 0))[None]  # [[0, 0, 0, 1]], no host copy
    return torch.cat([torch.cat([quat_to_rotmat(q), t[:, None]], 1), bottom], 0)


def photometric_refine(g: Gaussians, c2w: Tensor, rgb: Tensor, depth: Tensor, k: Intrinsics,
                       rcfg: RendererConfig, cfg: TrackingConfig, backend: RenderBackend | None = None) -> Tensor:
    """Refine a pose with Adam (SplaTAM-style) on :func:`photometric_loss`.

    Args:
        g: the map (detached parameters are fine).
        c2w: [4, 4] start pose. rgb: [H, W, 3]. depth: [H, W].

    Returns:
        [4, 4] float64 refined camera-to-world pose (the iterate with the lowest loss).
    """
    w2c0 = torch.linalg.inv(c2w.double())
    q = _quat_from_rot(w2c0[:3, :3]).float().requires_grad_(True)
    t = w2c0[:3, 3].float().clone().requires_grad_(True)
    opt = torch.optim.Adam([{"params": [q], "lr": cfg.photometric_lr_rot},
                            {"params": [t], "lr": cfg.photometric_lr_trans}])
    gd = Gaussians(*(x.detach() for x in (g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb)), None)
    backend = backend or select_backend(rcfg, g.means.device)
    # the best iterate is kept on the device (no host round trip per iteration)
    best_loss = torch.full((), float("inf"), device=q.device)
    best_q, best_t = q.detach().clone(), t.detach().clone()
    for _ in range(cfg.photometric_iters):
        loss = photometric_loss(gd, w2c_from_quat_trans(q, t), rgb, depth, k, rcfg, cfg.min_silhouette, backend)
        with torch.no_grad():
            better = loss.detach() < best_loss
            best_loss = torch.where(better, loss.detach(), best_loss)
            best_q = torch.where(better, q.detach(), best_q)
            best_t = torch.where(better, t.detach(), best_t)
        opt.zero_grad()
        loss.backward()
        with torch.device(q.device):  # some torch versions (2.11) make Adam's step counter on the default device
            opt.step()
    with torch.no_grad():
        w2c = w2c_from_quat_trans(best_q.double(), best_t.double())
    return torch.linalg.inv(w2c)
