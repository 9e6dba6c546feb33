"""gsplat 1.5.3's conventions, matched on CPU (no CUDA, nothing compiled).

* Projection: our :func:`~semantic_gs_slam.render.project` against ``gsplat.cuda._torch_impl``
  (2-D means, 2-D covariances with the +0.3 px^2 low-pass, conics, depths, near-plane and off-screen
  culling, footprint radii).
* Compositing: our tile renderer against a literal per-pixel transcription of gsplat's CUDA kernel
  ``RasterizeToPixels3DGSFwd.cu`` (pixel centres at +0.5, tiles from ``_isect_tiles``' box rule, the
  opacity-aware radius of ``ProjectionEWA3DGSFused.cu``, ``alpha = min(0.999, o exp(-sigma))``, skip
  ``alpha < 1/255``, stop before ``T (1 - alpha) <= 1e-4``, ``RGB+D`` depth as sum w_i z_i).

gsplat is a CPU test dependency (``requirements/slam.in``); the tests skip where it is missing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.render import footprint, project, render_torch
from semantic_gs_slam.render.gsplat_backend import GSPLAT_TILE, gsplat_inputs, gsplat_intrinsics
from semantic_gs_slam.render.types import Gaussians

torch_impl = pytest.importorskip("gsplat.cuda._torch_impl", reason="gsplat (CPU test dependency) not installed")

F64 = torch.float64
K = Intrinsics(40, 30, 32.0, 30.0, 17.3, 16.1)  # principal point off centre on purpose
NEAR = 0.05


def scene(seed: int = 0) -> tuple[Gaussians, torch.Tensor]:
    """Anisotropic Gaussians in front, behind, inside the near plane and off-screen, plus an opaque
    stack in the middle (drives pixels to the transmittance stop); a rotated, translated camera."""
    gen = torch.Generator().manual_seed(seed)
    n = 70
    means = torch.randn(n, 3, generator=gen, dtype=F64) * torch.tensor([1.2, 0.9, 0.8], dtype=F64)
    means[:, 2] += 2.5
    means[:4] = torch.tensor([[0, 0, -1.0], [0, 0, 0.02], [0, 0, 0.049], [0, 0, 0.051]], dtype=F64)  # behind,
    # inside the near plane, just past it (on the optical axis)
    means[4:8, 0] = torch.tensor([-6.0, 6.0, 3.1, -3.0], dtype=F64)  # far off-screen and at the edges
    stack = torch.tensor([[0.1, 0.0, 1.5], [0.12, 0.02, 1.6], [0.08, -0.02, 1.7], [0.1, 0.01, 1.8]], dtype=F64)
    means = torch.cat([means, stack])  # camera frame; scene() moves them to the world
    m = means.shape[0]
    log_scales = torch.log(torch.rand(m, 3, generator=gen, dtype=F64) * 0.15 + 0.02)
    log_scales[-4:] = math.log(0.25)
    logits = torch.randn(m, 1, generator=gen, dtype=F64) * 2
    logits[-4:] = 8.0
    g = Gaussians(means, torch.randn(m, 4, generator=gen, dtype=F64), log_scales, logits,
                  torch.rand(m, 3, generator=gen, dtype=F64), torch.rand(m, 2, generator=gen, dtype=F64))
    ang = 0.1
    c, s = math.cos(ang), math.sin(ang)
    w2c = torch.tensor([[c, 0, s, 0.05], [0, 1, 0, -0.03], [-s, 0, c, 0.1], [0, 0, 0, 1]], dtype=F64)
    g.means = (g.means - w2c[:3, 3]) @ w2c[:3, :3]  # the positions above are camera-frame ones
    return g, w2c


def gsplat_projection(g: Gaussians, w2c: torch.Tensor, k: Intrinsics, kmat: torch.Tensor | None = None):
    quats, scales, opac, _ = gsplat_inputs(g)
    covars, _ = torch_impl._quat_scale_to_covar_preci(quats, scales, True, False, False)
    kmat = gsplat_intrinsics(k, F64, g.means.device) if kmat is None else kmat
    radii, means2d, depths, conics, _ = torch_impl._fully_fused_projection(
        g.means, covars, w2c[None], kmat[None], k.width, k.height, eps2d=0.3, near_plane=NEAR)
    means_c, covars_c = torch_impl._world_to_cam(g.means, covars, w2c[None])
    _, cov2d = torch_impl._persp_proj(means_c, covars_c, kmat[None], k.width, k.height)
    return radii[0], means2d[0], depths[0], conics[0], cov2d[0] + 0.3 * torch.eye(2, dtype=F64), opac


def test_projection_matches_gsplat_torch_impl():
    g, w2c = scene()
    pr = project(g, w2c, K, NEAR)
    idx = pr["idx"]
    radii, means2d, depths, conics, cov2d, opac = gsplat_projection(g, w2c, K)
    # 2-D means: gsplat's pixel (c, r) is centred at (c + 0.5, r + 0.5), ours at (c, r)
    torch.testing.assert_close(pr["uv"] + 0.5, means2d[idx], rtol=1e-12, atol=1e-10)
    torch.testing.assert_close(pr["z"], depths[idx], rtol=1e-12, atol=1e-12)
    ours_cov = torch.stack([pr["cov"][:, 0], pr["cov"][:, 1], pr["cov"][:, 1], pr["cov"][:, 2]], -1).reshape(-1, 2, 2)
    torch.testing.assert_close(ours_cov, cov2d[idx], rtol=1e-10, atol=1e-10)  # Jacobian clamp and +0.3 px^2
    torch.testing.assert_close(pr["conic"], conics[idx], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(pr["log_o"], torch.log(opac[idx]), rtol=1e-12, atol=1e-12)
    # culling: gsplat keeps only Gaussians past the near plane whose 3.33-sigma box meets the image
    kept = set(torch.nonzero(radii.amax(-1) > 0)[:, 0].tolist())
    ours = idx.tolist()
    assert kept <= set(ours) and {0, 1, 2} & set(ours) == set() and 3 in kept
    keep, hx, hy = footprint(pr["log_o"], pr["cov"])
    u, v = pr["uv"].unbind(-1)
    for row, gi in enumerate(ours):
        if gi in kept:  # our exact footprint lies inside gsplat's box, so gsplat visits every pixel we blend
            assert hx[row] <= radii[gi, 0] + 1e-9 and hy[row] <= radii[gi, 1] + 1e-9
        else:  # culled by gsplat: our footprint touches no pixel centre either
            assert (u[row] + hx[row] < 0) or (u[row] - hx[row] > K.width - 1) or \
                   (v[row] + hy[row] < 0) or (v[row] - hy[row] > K.height - 1) or not keep[row]
    assert len(kept) < len(ours)  # the scene does have off-screen Gaussians in front of the camera


def gsplat_kernel_image(g: Gaussians, w2c: torch.Tensor, k: Intrinsics, kmat: torch.Tensor | None = None
                        ) -> tuple[np.ndarray, np.ndarray, int]:
    """Literal float64 transcription of gsplat 1.5.3's forward rasterisation for one camera.

    Returns:
        features [H, W, C + 1] (colour, semantic, depth last as in RGB+D), alpha [H, W], and the
        number of pixels that stopped on the transmittance rule.
    """
    radii, means2d, depths, conics, _, opac = gsplat_projection(g, w2c, k, kmat)
    feats = torch.cat([g.rgb, g.semantic, depths[:, None]], -1).detach().numpy()
    means2d, conics, opac, depths = (t.detach().numpy() for t in (means2d, conics, opac, depths))
    # ProjectionEWA3DGSFused.cu: opacity-aware extent, radius = ceil(extend * sigma), culled when 0
    cov_xx = 1 / (conics[:, 0] - conics[:, 1] ** 2 / conics[:, 2])  # marginal variances from the conic
    cov_yy = 1 / (conics[:, 2] - conics[:, 1] ** 2 / conics[:, 0])
    with np.errstate(invalid="ignore", divide="ignore"):
        extend = np.minimum(3.33, np.sqrt(2 * np.log(opac * 255.0)))
    rx, ry = np.ceil(extend * np.sqrt(cov_xx)), np.ceil(extend * np.sqrt(cov_yy))
    visible = (radii.amax(-1) > 0).numpy() & (opac >= 1 / 255)
    ts = GSPLAT_TILE
    # _isect_tiles: tile range [floor((m - r) / ts), ceil((m + r) / ts)) clamped to the grid
    t0x, t1x = np.floor((means2d[:, 0] - rx) / ts), np.ceil((means2d[:, 0] + rx) / ts)
    t0y, t1y = np.floor((means2d[:, 1] - ry) / ts), np.ceil((means2d[:, 1] + ry) / ts)
    order = [i for i in np.argsort(depths, kind="stable") if visible[i]]
    h, w = k.height, k.width
    img = np.zeros((h, w, feats.shape[1]))
    alpha_img = np.zeros((h, w))
    stopped = 0
    for i in range(h):
        for j in range(w):
            px, py = j + 0.5, i + 0.5
            tx, ty = j // ts, i // ts
            t_acc = 1.0
            for gi in order:
                if not (t0x[gi] <= tx < t1x[gi] and t0y[gi] <= ty < t1y[gi]):
                    continue
                dx, dy = means2d[gi, 0] - px, means2d[gi, 1] - py
                sigma = 0.5 * (conics[gi, 0] * dx * dx + conics[gi, 2] * dy * dy) + conics[gi, 1] * dx * dy
                alpha = min(0.999, opac[gi] * math.exp(-sigma))
                if sigma < 0 or alpha < 1.0 / 255.0:
                    continue
                next_t = t_acc * (1 - alpha)
                if next_t <= 1e-4:  # this pixel is done: exclusive
                    stopped += 1
                    break
                img[i, j] += feats[gi] * alpha * t_acc
                t_acc = next_t
            alpha_img[i, j] = 1 - t_acc
    return img, alpha_img, stopped


def test_compositing_matches_gsplat_kernel_rules():
    g, w2c = scene()
    ref, alpha, stopped = gsplat_kernel_image(g, w2c, K)
    out = render_torch(g, w2c, K, RendererConfig(near=NEAR, chunk=16))
    assert stopped > 10 and alpha.max() > 0.999  # the opaque stack does reach the transmittance stop
    np.testing.assert_allclose(out.rgb.numpy(), ref[..., :3], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.semantic.numpy(), ref[..., 3:5], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.depth.numpy(), ref[..., 5], rtol=0, atol=1e-9)
    np.testing.assert_allclose(out.silhouette.numpy(), alpha, rtol=0, atol=1e-9)


def test_kernel_transcription_sees_a_half_pixel_shift():
    # negative control: with gsplat given our K unshifted, the images differ clearly
    g, w2c = scene()
    kmat = torch.tensor(K.as_matrix(), dtype=F64)
    ref, _, _ = gsplat_kernel_image(g, w2c, K, kmat)
    out = render_torch(g, w2c, K, RendererConfig(near=NEAR))
    assert np.abs(out.rgb.numpy() - ref[..., :3]).max() > 0.05
    # and without the transmittance stop rule the opaque stack's pixels differ
    ref, _, _ = gsplat_kernel_image(g, w2c, K)
    no_stop = render_torch(g, w2c, K, RendererConfig(near=NEAR, stop_transmittance=0.0))
    assert np.abs(no_stop.silhouette.numpy() - _silhouette(ref, g, w2c)).max() > 1e-4


def _silhouette(ref: np.ndarray, g: Gaussians, w2c: torch.Tensor) -> np.ndarray:
    return gsplat_kernel_image(g, w2c, K)[1]
