"""gsplat back-end against the torch tiles on a CUDA GPU: the same images and the same gradients.

Skipped without gsplat and CUDA (``bench/gpu.sh`` runs these on a GPU machine first thing).

Tolerances, and why. Both back-ends evaluate the same formula (see
``test_gsplat_conventions.py``, which holds them to 1e-9 in float64 on CPU), so what is left is
float32 arithmetic: gsplat uses ``__expf`` (fast exp, ~2 ulp) and its own summation order, and a
Gaussian whose alpha sits within rounding of 1/255, or whose transmittance step sits within rounding
of 1e-4, can be blended by one back-end and not the other. Such a flip moves one pixel by at most
``T * alpha <= 1/255`` of that Gaussian's feature. So per image: at most 0.5 % of the values may
differ by more than 1e-4 of the channel's range, and none by more than ``1/255`` of it (+1e-4).
Gradients are sums over many pixels in a different order, and gsplat's backward recovers
transmittance by dividing by ``1 - alpha`` (float32, alpha up to 0.99): each parameter's gradient
must agree to 2 % in relative L2 norm. A half-pixel shift, another Jacobian clamp, a missing low-pass
or opacity compensation each give errors of 10-100 % (see the CPU tests' negative controls).
"""

from __future__ import annotations

import math

import pytest
import torch

from semantic_gs_slam.config import Intrinsics, RendererConfig
from semantic_gs_slam.render import render_torch
from semantic_gs_slam.render.gsplat_backend import gsplat_available, render_gsplat
from semantic_gs_slam.render.types import Gaussians
from semantic_gs_slam.tracking.tracker import w2c_from_quat_trans

pytestmark = pytest.mark.skipif(not gsplat_available(), reason="needs gsplat and a CUDA GPU")

K = Intrinsics(96, 72, 80.0, 80.0, 47.3, 35.8)


def scene(kind: str, seed: int = 0) -> Gaussians:
    """``random``: scattered anisotropic Gaussians; ``surface``: a dense opaque wall (a SLAM-like map,
    many pixels reach the transmittance stop)."""
    gen = torch.Generator().manual_seed(seed)
    if kind == "random":
        n = 300
        means = torch.randn(n, 3, generator=gen) * torch.tensor([0.8, 0.6, 0.5]) + torch.tensor([0.0, 0.0, 2.5])
        log_scales = torch.log(torch.rand(n, 3, generator=gen) * 0.08 + 0.01)
        logits = torch.randn(n, 1, generator=gen) * 2
    else:
        u, v = torch.meshgrid(torch.linspace(-1, 1, 40), torch.linspace(-0.8, 0.8, 30), indexing="ij")
        n = u.numel()
        means = torch.stack([u.reshape(-1), v.reshape(-1), 2.0 + 0.3 * u.reshape(-1)], -1)
        means = means + torch.randn(n, 3, generator=gen) * 0.005
        log_scales = torch.full((n, 3), math.log(0.03)) + torch.randn(n, 3, generator=gen) * 0.1
        logits = torch.full((n, 1), 4.0)
    return Gaussians(means, torch.randn(n, 4, generator=gen), log_scales, logits, torch.rand(n, 3, generator=gen),
                     torch.rand(n, 5, generator=gen))


def _on_cuda(g: Gaussians) -> Gaussians:
    return Gaussians(*(t.detach().cuda().requires_grad_(True) for t in (g.means, g.quats, g.log_scales,
                                                                          g.logit_opacities, g.rgb, g.semantic)))


def _pose() -> tuple[torch.Tensor, torch.Tensor]:
    q = torch.tensor([0.995, 0.03, -0.05, 0.02], device="cuda", requires_grad=True)
    t = torch.tensor([0.02, -0.01, 0.05], device="cuda", requires_grad=True)
    return q, t


def _images(out) -> dict[str, torch.Tensor]:
    return {"rgb": out.rgb, "depth": out.depth, "silhouette": out.silhouette, "semantic": out.semantic}


def _check_image(name: str, a: torch.Tensor, b: torch.Tensor) -> None:
    scale = float(b.abs().max().clamp_min(1e-6))
    d = (a - b).abs() / scale
    frac = float((d > 1e-4).float().mean())
    assert frac <= 5e-3, f"{name}: {frac:.2%} of values differ by > 1e-4 of the range"
    assert float(d.max()) <= 1 / 255 + 1e-4, f"{name}: max difference {float(d.max()):.4f} of the range"


@pytest.mark.parametrize("kind", ["random", "surface"])
def test_gsplat_images_match_torch_backend(kind):
    g = _on_cuda(scene(kind))
    q, t = _pose()
    w2c = w2c_from_quat_trans(q, t)
    cfg = RendererConfig()
    a = render_torch(g, w2c, K, cfg)
    b = render_gsplat(g, w2c, K, cfg)
    assert float(b.silhouette.detach().max()) > 0.9  # not an empty image
    for name, x in _images(a).items():
        _check_image(name, x, _images(b)[name])


@pytest.mark.parametrize("kind", ["random", "surface"])
def test_gsplat_gradients_match_torch_backend(kind):
    base = scene(kind)
    grads = []
    for backend in (render_torch, render_gsplat):
        g = _on_cuda(base)
        q, t = _pose()
        out = backend(g, w2c_from_quat_trans(q, t), K, RendererConfig())
        gen = torch.Generator(device="cuda").manual_seed(1)
        loss = sum((x * torch.rand(x.shape, generator=gen, device="cuda")).sum() for x in _images(out).values())
        params = {"means": g.means, "quats": g.quats, "log_scales": g.log_scales, "logit_opacities": g.logit_opacities,
                  "rgb": g.rgb, "semantic": g.semantic, "pose_q": q, "pose_t": t}
        grads.append(dict(zip(params, torch.autograd.grad(loss, list(params.values())), strict=True)))
    for name in grads[0]:
        ga, gb = grads[0][name], grads[1][name]
        rel = float((ga - gb).norm() / gb.norm().clamp_min(1e-12))
        assert rel < 2e-2, f"gradient w.r.t. {name}: relative difference {rel:.3%}"


def test_engine_runs_on_cuda_with_both_backends(tiny_home):
    import numpy as np

    from semantic_gs_slam.config import MappingConfig, SlamConfig
    from semantic_gs_slam.io.datasets import load_dataset
    from semantic_gs_slam.slam import SLAM

    ds = load_dataset(str(tiny_home))
    poses = {}
    for backend in ("torch", "gsplat"):
        cfg = SlamConfig(intrinsics=ds.intrinsics, device="cuda", renderer=RendererConfig(backend=backend),
                         mapping=MappingConfig(first_frame_iters=40, iters=10))
        eng = SLAM(cfg, ds.classes)
        for i in range(6):
            f = ds[i]
            eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
        assert eng.map.params["means3D"].is_cuda and not any(lg.tracking_failed for lg in eng.logs)
        poses[backend] = np.stack(eng.poses)
        errs = [np.linalg.norm(p[:3, 3] - ds[i].gt_c2w[:3, 3]) for i, p in enumerate(eng.poses)]
        assert max(errs) < 0.02, f"{backend}: pose error {max(errs):.3f} m"


def test_refinement_with_poses_runs_on_cuda(tiny_home):
    """``SLAM.refine(poses=True)`` through gsplat on the GPU: a keyframe moved 5 cm comes most of the way back
    (the CPU test's case), the gauge stays, and the map and the keyframes' poses stay on the device."""
    import numpy as np

    from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig
    from semantic_gs_slam.geometry import pose_error
    from semantic_gs_slam.io.datasets import load_dataset
    from semantic_gs_slam.slam import SLAM

    ds = load_dataset(str(tiny_home))
    cfg = SlamConfig(intrinsics=ds.intrinsics, device="cuda", renderer=RendererConfig(backend="gsplat"),
                     mapping=MappingConfig(first_frame_iters=40, iters=10), tracking=TrackingConfig(use_gt_pose=True))
    cfg.loop.enabled = False
    eng = SLAM(cfg, ds.classes)
    for i in range(len(ds)):
        f = ds[i]
        eng.add_frame(f.rgb, f.depth, f.semantics, f.timestamp, f.gt_c2w)
    kf = eng.keyframes[1]
    shift = np.eye(4)
    shift[:3, 3] = [0.05, 0.0, 0.0]
    kf.c2w = torch.as_tensor(shift @ kf.c2w.cpu().numpy(), device=eng.device)
    first = eng.poses[0].copy()
    end = eng.keyframes[2].index if len(eng.keyframes) > 2 else len(eng.poses)
    for i in range(kf.index, end):  # the frames that follow keyframe 1
        eng.poses[i] = shift @ eng.poses[i]
    err0 = pose_error(eng.poses[kf.index], ds[kf.index].gt_c2w)[0]
    loss, done = eng.refine(300, poses=True)
    err1 = pose_error(eng.poses[kf.index], ds[kf.index].gt_c2w)[0]
    assert done == 300 and math.isfinite(loss)
    assert err0 > 0.049 and err1 < 0.5 * err0, (err0, err1)
    np.testing.assert_array_equal(eng.poses[0], first)
    assert eng.map.params["means3D"].is_cuda and eng.keyframes[1].c2w.is_cuda
