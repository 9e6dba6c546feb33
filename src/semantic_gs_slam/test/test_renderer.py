"""Renderer: tile renderer vs dense reference, gradients vs finite differences, analytic cases."""

from __future__ import annotations

import math

import pytest
import torch

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.errors import BackendUnavailableError
from semantic_gs_slam.render import Gaussians, render_reference
from semantic_gs_slam.render import render as _render
from semantic_gs_slam.render.reference import _Composite

K = Intrinsics(40, 30, 30.0, 30.0, 19.5, 14.5)


def render(g, w2c, k, cfg=None):
    """The pure-PyTorch tiles (this file tests the reference, in float64; the compiled CPU compositor, which
    computes in float32, is checked against it in test_render_numba.py)."""
    return _render(g, w2c, k, cfg or RendererConfig(backend="torch"))

F64 = torch.float64


def random_scene(n: int = 60, seed: int = 0, dtype=F64) -> Gaussians:
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians(
        torch.randn(n, 3, generator=gen, dtype=dtype) * 0.5 + torch.tensor([0.0, 0.0, 3.0], dtype=dtype),
        torch.randn(n, 4, generator=gen, dtype=dtype),
        torch.log(torch.rand(n, 1, generator=gen, dtype=dtype) * 0.1 + 0.05),
        torch.randn(n, 1, generator=gen, dtype=dtype) * 2,
        torch.rand(n, 3, generator=gen, dtype=dtype),
        torch.rand(n, 2, generator=gen, dtype=dtype))
    for t in (g.means, g.log_scales, g.logit_opacities, g.rgb, g.semantic):
        t.requires_grad_(True)
    return g


def scalar(out) -> torch.Tensor:
    w = torch.linspace(0.5, 1.5, out.rgb.numel(), dtype=out.rgb.dtype).reshape(out.rgb.shape)
    return (out.rgb * w).sum() + (out.depth**2).sum() + out.silhouette.sum() + (out.semantic * 0.7).sum()


@pytest.mark.parametrize("cfg", [RendererConfig(backend="torch"),
                                 RendererConfig(tile=16, chunk=5, batch_elements=4000, backend="torch"),
                                 RendererConfig(tile=4, chunk=3, backend="torch")])
def test_tile_renderer_matches_dense_reference(cfg):
    g = random_scene()
    w2c = torch.eye(4, dtype=F64)
    a, b = render(g, w2c, K, cfg), render_reference(g, w2c, K)
    for name in ("rgb", "depth", "silhouette", "semantic"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=1e-10, atol=1e-10)
    params = [g.means, g.log_scales, g.logit_opacities, g.rgb, g.semantic]
    ga = torch.autograd.grad(scalar(a), params)
    gb = torch.autograd.grad(scalar(b), params)
    for x, y in zip(ga, gb, strict=True):
        torch.testing.assert_close(x, y, rtol=1e-8, atol=1e-9)
    assert a.silhouette.max() > 0.5  # the scene is not empty


def test_composite_backward_matches_finite_differences():
    gen = torch.Generator().manual_seed(1)
    ii, jj = torch.meshgrid(torch.arange(4.0, dtype=F64), torch.arange(4.0, dtype=F64), indexing="xy")
    ii, jj = ii.reshape(-1), jj.reshape(-1)
    mono = torch.stack([torch.ones_like(ii), ii, jj, ii * ii, ii * jj, jj * jj])
    # exponent = log(o) - 0.5 * |p - mu|^2 / s^2 written as coefficients, per (tile, Gaussian)
    b, k = 2, 5
    mu = torch.rand(b, k, 2, generator=gen, dtype=F64) * 3
    s2 = 1.0 + torch.rand(b, k, generator=gen, dtype=F64) * 2
    lo = torch.log(0.3 + 0.6 * torch.rand(b, k, generator=gen, dtype=F64))
    a = 1 / s2
    coef = torch.stack([lo - 0.5 * a * (mu[..., 0] ** 2 + mu[..., 1] ** 2), a * mu[..., 0], a * mu[..., 1],
                        -0.5 * a, torch.zeros_like(a), -0.5 * a], -1).requires_grad_(True)
    feats = torch.rand(b, k, 3, generator=gen, dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, f: _Composite.apply(c, f, mono, 2, 0.0), (coef, feats),
                                    eps=1e-6, atol=1e-7, rtol=1e-5)


def test_full_render_gradient_matches_finite_differences():
    g = random_scene(n=25, seed=3)
    w2c = torch.eye(4, dtype=F64)
    grads = torch.autograd.grad(scalar(render(g, w2c, K)), [g.means, g.log_scales, g.logit_opacities])
    gen = torch.Generator().manual_seed(5)
    for p, gr in zip([g.means, g.log_scales, g.logit_opacities], grads, strict=True):
        d = torch.randn(p.shape, generator=gen, dtype=F64)
        eps = 1e-6
        with torch.no_grad():
            p += eps * d
            up = scalar(render(g, w2c, K))
            p -= 2 * eps * d
            dn = scalar(render(g, w2c, K))
            p += eps * d
        fd = (up - dn) / (2 * eps)
        an = (gr * d).sum()
        assert abs(float(fd - an)) <= 1e-4 * max(1.0, abs(float(an))), (float(fd), float(an))


def test_single_gaussian_footprint_is_analytic():
    z, s = 4.0, 0.05
    logit = 2.0
    g = Gaussians(torch.tensor([[0.0, 0.0, z]], dtype=F64), torch.tensor([[1.0, 0, 0, 0]], dtype=F64),
                  torch.full((1, 1), math.log(s), dtype=F64), torch.full((1, 1), logit, dtype=F64),
                  torch.tensor([[1.0, 0.5, 0.25]], dtype=F64))
    k = Intrinsics(41, 41, 100.0, 100.0, 20.0, 20.0)  # centre lands on pixel (20, 20)
    out = render(g, torch.eye(4, dtype=F64), k)
    o = 0.99 / (1 + math.exp(-logit))
    var = (100.0 * s / z) ** 2 + 0.3  # projected variance in px^2 plus the anti-aliasing term
    for dx, dy in [(0, 0), (1, 0), (3, 0), (2, 2), (0, -4)]:
        want = o * math.exp(-0.5 * (dx * dx + dy * dy) / var)
        want = want if want >= 1 / 255 else 0.0
        got = float(out.silhouette[20 + dy, 20 + dx])
        assert got == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert float(out.depth[20 + dy, 20 + dx]) == pytest.approx(want * z, rel=1e-9, abs=1e-12)
        assert float(out.rgb[20 + dy, 20 + dx, 1]) == pytest.approx(want * 0.5, rel=1e-9, abs=1e-12)
    assert float(out.silhouette[0, 0]) == 0.0  # far outside the 1/255 footprint


def test_occlusion_order_front_gaussian_wins():
    def scene(z_red: float, z_blue: float) -> Gaussians:
        return Gaussians(torch.tensor([[0.0, 0, z_red], [0.0, 0, z_blue]], dtype=F64),
                         torch.tensor([[1.0, 0, 0, 0]] * 2, dtype=F64), torch.full((2, 1), math.log(0.5), dtype=F64),
                         torch.full((2, 1), 8.0, dtype=F64), torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=F64))

    k = Intrinsics(21, 21, 20.0, 20.0, 10.0, 10.0)
    a = render(scene(2.0, 3.0), torch.eye(4, dtype=F64), k)
    b = render(scene(3.0, 2.0), torch.eye(4, dtype=F64), k)
    assert a.rgb[10, 10, 0] > 0.95 and a.rgb[10, 10, 2] < 0.05
    assert b.rgb[10, 10, 2] > 0.95 and b.rgb[10, 10, 0] < 0.05
    assert float(a.depth[10, 10] / a.silhouette[10, 10]) == pytest.approx(2.0, abs=0.03)
    # input order must not matter: swapping rows gives the same image
    c = render(Gaussians(*(t.flip(0) for t in (scene(2.0, 3.0).means, scene(2.0, 3.0).quats,
                                                  scene(2.0, 3.0).log_scales, scene(2.0, 3.0).logit_opacities,
                                                  scene(2.0, 3.0).rgb))), torch.eye(4, dtype=F64), k)
    torch.testing.assert_close(c.rgb, a.rgb)


def test_silhouette_empty_behind_camera_and_opaque():
    k = Intrinsics(16, 16, 10.0, 10.0, 7.5, 7.5)
    behind = Gaussians(torch.tensor([[0.0, 0, -2.0]]), torch.tensor([[1.0, 0, 0, 0]]), torch.zeros(1, 1),
                       torch.full((1, 1), 5.0), torch.ones(1, 3))
    out = render(behind, torch.eye(4), k)
    assert float(out.silhouette.abs().max()) == 0.0 and out.n_visible == 0
    big = Gaussians(torch.tensor([[0.0, 0, 2.0]] * 3), torch.tensor([[1.0, 0, 0, 0]] * 3), torch.zeros(3, 1),
                    torch.full((3, 1), 10.0), torch.ones(3, 3))
    out = render(big, torch.eye(4), k)
    # three stacked opaque Gaussians: the third would take the transmittance below 1e-4, so (as in gsplat's
    # kernel) it is not blended: silhouette 1 - (1 - a)^2 with a the alpha at the pixel (0.5 px off centre)
    a = 0.99 * math.exp(-0.5 * 0.5 / (5.0**2 + 0.3))
    assert float(out.silhouette[7, 7]) == pytest.approx(1 - (1 - a) ** 2, abs=1e-5)  # float32


def test_shape_errors_are_clear():
    g = random_scene(n=4)
    with pytest.raises(ValueError, match="w2c must be"):
        render(g, torch.eye(3, dtype=F64), K)
    bad = Gaussians(g.means, g.quats[:3], g.log_scales, g.logit_opacities, g.rgb)
    with pytest.raises(ValueError, match="quats must be"):
        render(bad, torch.eye(4, dtype=F64), K)


def _gsplat_ok() -> bool:
    try:
        import gsplat  # noqa: F401
    except ImportError:
        return False
    return torch.cuda.is_available()


def test_gsplat_backend_unavailable_raises_typed_error():
    if _gsplat_ok():
        pytest.skip("gsplat and CUDA are present")
    with pytest.raises(BackendUnavailableError):
        render(random_scene(n=4), torch.eye(4, dtype=F64), K, RendererConfig(backend="gsplat"))


# the gsplat agreement tests (GPU) are in test_gsplat_gpu.py



@pytest.mark.parametrize("aniso", [False, True])
def test_culling_off_screen_gaussians_keeps_every_pair_and_its_exponent(aniso):
    """A wide scene, most of it outside the view, with large Gaussians whose centres lie just off the image
    borders (their footprints reach in): dropping what cannot reach the image before the differentiable projection
    (render.tiles.cull_bounds) leaves the same (tile, Gaussian) pairs in the same order, with the same exponent
    coefficients and features, so every pixel and gradient is unchanged."""
    from semantic_gs_slam.render.tiles import cull_bounds, tile_pairs

    gen = torch.Generator().manual_seed(3)
    n = 400
    means = torch.cat([(torch.rand(n, 3, generator=gen, dtype=F64) - 0.5) * torch.tensor([12.0, 9.0, 8.0], dtype=F64)
                       + torch.tensor([0.0, 0.0, 3.0], dtype=F64),
                       # just outside the left / right / top / bottom borders at z = 3 (fx = 30: 2 m half-width)
                       torch.tensor([[-2.2, 0.0, 3.0], [2.2, 0.3, 3.0], [0.2, -1.7, 3.0], [-0.4, 1.7, 3.0]],
                                    dtype=F64)])
    m = means.shape[0]
    scales = torch.log(torch.rand(m, 3 if aniso else 1, generator=gen, dtype=F64) * 0.1 + 0.03)
    scales[-4:] = math.log(0.35)  # the border ones: footprints several pixels into the image
    g = Gaussians(means, torch.randn(m, 4, generator=gen, dtype=F64), scales,
                  torch.randn(m, 1, generator=gen, dtype=F64) * 2 + 2, torch.rand(m, 3, generator=gen, dtype=F64),
                  torch.rand(m, 2, generator=gen, dtype=F64))
    w2c = torch.eye(4, dtype=F64)
    cfg = RendererConfig(tile=8, backend="torch")
    kept = cull_bounds(g.means, g.log_scales, K, cfg.near, 40, 32)
    assert 0 < int(kept.sum()) < m // 2 and bool(kept[-4:].all())  # most dropped; the border ones kept
    a = tile_pairs(g, w2c, K, cfg)  # culled
    b = tile_pairs(g, w2c, K, cfg, cull=False)
    ida, idb = torch.nonzero(kept).squeeze(1), torch.nonzero(g.means[:, 2] > cfg.near).squeeze(1)
    assert a.n_visible == b.n_visible > 0
    assert torch.equal(ida[a.pg], idb[b.pg]) and torch.equal(a.tstart, b.tstart) and torch.equal(a.tcount, b.tcount)
    torch.testing.assert_close(a.coef, b.coef, rtol=0, atol=0)
    torch.testing.assert_close(a.feats[a.pg], b.feats[b.pg], rtol=0, atol=0)
    border = set(range(m - 4, m))
    assert border <= set(ida[a.pg].tolist())  # the border ones reach into the image and are drawn
