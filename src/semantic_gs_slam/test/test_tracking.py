"""Tracking: ICP against the rendered model recovers a perturbed pose."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.errors import TrackingError
from semantic_gs_slam.geometry import pose_error, se3_exp
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic import HomeRenderer, default_intrinsics, trajectory
from semantic_gs_slam.tracking import icp


@pytest.fixture(scope="module")
def scene():
    k = default_intrinsics(160, 90)
    poses = trajectory(60, 60.0)
    ren = HomeRenderer(0)
    frames = [ren.render(poses[i], k) for i in (0, 1)]
    eng = SLAM(SlamConfig(intrinsics=k, mapping=MappingConfig(first_frame_iters=30), device="cpu"))
    rgb, depth, sem = frames[0]
    eng.add_frame(rgb.astype(np.float32), depth.astype(np.float32), sem, gt_c2w=poses[0])
    return eng, k, poses, frames


def model(eng, c2w):
    out = eng.render_view(c2w, scale_shrink=0.35)
    valid = out.silhouette > 0.5
    return torch.where(valid, out.depth / out.silhouette.clamp_min(1e-6), torch.zeros_like(out.depth)), valid, out


@pytest.mark.parametrize("xi", [[0, 0, 0, 0.02, -0.01, 0.01], [0.02, -0.015, 0.01, 0, 0, 0],
                                [0.01, 0.01, -0.01, -0.015, 0.02, 0.0]])
def test_icp_recovers_a_perturbed_pose(scene, xi):
    eng, k, poses, frames = scene
    gt = torch.as_tensor(poses[0])
    md, valid, out = model(eng, poses[0])
    start = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ gt
    e0 = pose_error(start.numpy(), poses[0])
    r = icp(md, valid, gt, torch.as_tensor(frames[0][1]).float(), k, TrackingConfig(), out.rgb,
            torch.as_tensor(frames[0][0]).float(), start_c2w=start)
    e1 = pose_error(r.c2w.numpy(), poses[0])
    assert e0[0] > 0.01 or e0[1] > 0.5
    assert e1[0] < 0.004 and e1[1] < 0.2, (e0, e1)


def test_icp_tracks_the_next_frame_from_the_previous_pose(scene):
    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    rgb1, depth1, _ = frames[1]
    r = icp(md, valid, torch.as_tensor(poses[0]), torch.as_tensor(depth1).float(), k, TrackingConfig(), out.rgb,
            torch.as_tensor(rgb1).float())
    before = pose_error(poses[0], poses[1])
    after = pose_error(r.c2w.numpy(), poses[1])
    assert after[0] < 0.3 * before[0] and after[0] < 0.01, (before, after)


def test_icp_without_overlap_raises(scene):
    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    with pytest.raises(TrackingError, match="correspondences"):
        icp(md, torch.zeros_like(valid), torch.as_tensor(poses[0]), torch.as_tensor(frames[0][1]).float(), k,
            TrackingConfig())


def test_photometric_refinement_lowers_its_loss(scene):
    """The Adam refinement (SplaTAM-style, optional) lowers its colour + depth loss from a perturbed pose.
    (On this map its minimum is not closer to the true pose than ICP's; it is off by default.)"""
    from semantic_gs_slam.config import RendererConfig
    from semantic_gs_slam.tracking import photometric_loss, photometric_refine

    eng, k, poses, frames = scene
    gt = torch.as_tensor(poses[0])
    start = se3_exp(torch.tensor([0.0, 0.0, 0.0, 0.015, -0.01, 0.0], dtype=torch.float64)) @ gt
    rgb, depth, _ = frames[0]
    rgb_t, depth_t = torch.as_tensor(rgb).float(), torch.as_tensor(depth).float()
    g = eng.map.gaussians()
    out = photometric_refine(g, start, rgb_t, depth_t, k, RendererConfig(), TrackingConfig(photometric_iters=10))

    def loss(c2w):
        with torch.no_grad():
            return float(photometric_loss(g, torch.linalg.inv(c2w).float(), rgb_t, depth_t, k, RendererConfig(), 0.5))

    assert loss(out) < 0.9 * loss(start)


def test_plane_depth_is_unbiased_where_centre_depth_is_not():
    """A floor seen obliquely, tiled with Gaussians that carry its normal: blending the Gaussians'
    planes gives the true depth per pixel; blending their centre depths does not."""
    from semantic_gs_slam.config import Intrinsics, RendererConfig
    from semantic_gs_slam.render import Gaussians, render
    from semantic_gs_slam.tracking import plane_depth_features, plane_depth_image

    k = Intrinsics(64, 48, 40.0, 40.0, 31.5, 23.5)
    # camera 1 m above the floor y = 1 (camera y points down), looking along +z
    xs, zs = torch.meshgrid(torch.arange(-3.0, 3.0, 0.03), torch.arange(0.6, 6.0, 0.03), indexing="ij")
    means = torch.stack([xs.reshape(-1), torch.ones(xs.numel()), zs.reshape(-1)], -1)
    n = means.shape[0]
    normals = torch.tensor([[0.0, -1.0, 0.0]]).repeat(n, 1)
    g = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 1), float(np.log(0.02))),
                  torch.full((n, 1), 4.0), torch.rand(n, 3), plane_depth_features(means, normals, k))
    out = render(g, torch.eye(4), k, RendererConfig())
    v = torch.arange(k.height, dtype=torch.float32)[:, None].expand(k.height, k.width)
    below = (v > k.cy + 4) & (out.silhouette > 0.9)  # floor pixels, away from the horizon
    truth = k.fy / (v - k.cy)  # depth of the plane y = 1 along each pixel's ray
    centre = out.depth / out.silhouette
    plane = plane_depth_image(out.semantic, out.silhouette)
    err_c = ((centre - truth).abs() / truth)[below].median()
    err_p = ((plane - truth).abs() / truth)[below].median()
    assert int(below.sum()) > 300
    assert err_p < 0.01 and err_c > 5 * err_p, (float(err_c), float(err_p))  # measured 0.7 % vs 8 %
    # unknown normals (zero rows) fall back to the centre depth
    f0 = plane_depth_features(means, torch.zeros_like(normals), k)
    torch.testing.assert_close(f0, torch.stack([means[:, 2], torch.zeros(n), torch.zeros(n)], -1))


def test_graph_solver_matches_lapack():
    """The capture-safe 6x6 solver (Gauss-Jordan, no pivoting) equals torch.linalg.solve on SPD systems as
    ill-conditioned as ICP's (prior 400 against data weights up to 1e8)."""
    from semantic_gs_slam.tracking import _solve_spd6

    gen = torch.Generator().manual_seed(0)
    for scale in (1.0, 1e4, 1e8):
        j = torch.randn(500, 6, generator=gen, dtype=torch.float64) * torch.tensor([1, 1, 1, 0.1, 0.1, 0.01],
                                                                                     dtype=torch.float64)
        a = scale * j.T @ j + torch.diag(torch.tensor([400.0] * 6, dtype=torch.float64))
        b = torch.randn(6, generator=gen, dtype=torch.float64)
        ref = torch.linalg.solve(a, b)
        torch.testing.assert_close(_solve_spd6(a, b), ref, rtol=1e-9, atol=1e-14)


def test_icp_step_is_the_same_with_either_solver(scene):
    """The step the CUDA graph captures (with the graph's solver) gives the eager step's pose and statistics."""
    from semantic_gs_slam.geometry import backproject
    from semantic_gs_slam.tracking import _icp_step, _IcpModel, _IcpPoints, _solve_spd6

    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    g = torch.as_tensor(poses[0])
    vm = backproject(md.double(), k.fx, k.fy, k.cx, k.cy) @ g[:3, :3].T + g[:3, 3]
    from semantic_gs_slam.tracking import normal_map

    nm, nvalid = normal_map(vm, valid)
    im = out.rgb.double().mean(-1)
    col = torch.stack([im, torch.zeros_like(im), torch.zeros_like(im), valid.double()], -1).reshape(-1, 4)
    mdl = _IcpModel(vm.reshape(-1, 3), nm.reshape(-1, 3), nvalid.reshape(-1), col, torch.linalg.inv(g),
                    torch.eye(6, dtype=torch.float64) * 400)
    lp = backproject(torch.as_tensor(frames[1][1]).double(), k.fx, k.fy, k.cx, k.cy)[::2, ::2].reshape(-1, 3)
    pts = _IcpPoints(lp, lp[:, 2] > 0, torch.as_tensor(frames[1][0]).double().mean(-1)[::2, ::2].reshape(-1))
    start = se3_exp(torch.tensor([0.01, 0, 0, 0.01, 0, 0], dtype=torch.float64)) @ g
    for photometric in (False, True):
        e1, s1 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric)
        e2, s2 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric, _solve_spd6)
        torch.testing.assert_close(e1, e2, rtol=0, atol=1e-12)
        torch.testing.assert_close(s1, s2, rtol=1e-9, atol=0)
        assert s1[0] > 1000 and 0 < s1[1] < 0.05  # correspondences, residual RMS (m)


@pytest.mark.parametrize("case", ["runs out of steps", "converges", "loses the model"])
def test_icp_in_chunks_of_steps_equals_the_step_loop(scene, monkeypatch, case):
    """The CUDA graph's chunks of steps (run eagerly here: the capture itself needs a GPU) keep the step loop's
    rules on the device: the same pose, residual and correspondences when the iterations run out, when a step
    gets below 1e-6 mid-chunk, and the same TrackingError when the correspondences run out."""
    from semantic_gs_slam import tracking

    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    start = se3_exp(torch.tensor([0.01, 0.01, -0.01, -0.015, 0.02, 0.0], dtype=torch.float64)) @ torch.as_tensor(
        poses[0])
    cfg = {"runs out of steps": TrackingConfig(icp_iters=7),  # not a multiple of STEPS_PER_GRAPH
           "converges": TrackingConfig(icp_iters=40),
           "loses the model": TrackingConfig(min_correspondences=2000)}[case]
    live = torch.as_tensor(frames[0][1]).float()
    if case == "loses the model":
        live = live.clone()
        live[:, : k.width * 3 // 4] = 0  # only a quarter of the frame: too few points
    chunks = []

    def run():
        try:
            return icp(md, valid, torch.as_tensor(poses[0]), live, k, cfg, out.rgb,
                       torch.as_tensor(frames[0][0]).float(), start_c2w=start)
        except TrackingError as exc:
            return str(exc)

    ref = run()

    def chunked(pts, mdl, k_, cfg_, photometric):
        g = tracking._IcpGraph(pts, mdl, k_, cfg_, photometric, capture=False).load(pts, mdl)
        chunks.append(g)
        return g

    monkeypatch.setattr(tracking, "_use_graphs", lambda cfg_, dev: True)
    monkeypatch.setattr(tracking, "_graph_for", chunked)
    got = run()
    assert len(chunks) == (1 if case == "loses the model" else cfg.icp_levels)
    if case == "loses the model":
        assert isinstance(ref, str) and "correspondences" in ref and got == ref
        return
    torch.testing.assert_close(got.c2w, ref.c2w, rtol=0, atol=1e-9)
    assert got.inliers == ref.inliers and abs(got.residual - ref.residual) < 1e-9
    assert abs(got.agreement - ref.agreement) < 1e-12
    if case == "converges":  # the test means something only if a level stopped early
        steps = []
        monkeypatch.undo()
        orig = tracking._icp_step

        def counting(*a, **kw):
            steps.append(1)
            return orig(*a, **kw)

        monkeypatch.setattr(tracking, "_icp_step", counting)
        run()
        assert len(steps) < 2 * cfg.icp_iters


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_icp_cuda_graph_matches_the_eager_step(scene):
    """On CUDA, ICP with each step replayed from a captured graph gives the eager reference's pose, also on a
    second problem of the same shape (the graph is reused with new inputs)."""
    from semantic_gs_slam import tracking

    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    cuda = torch.device("cuda")
    results = {}
    for graphs in (False, True):
        tracking._GRAPHS.clear()
        for i, xi in enumerate(([0, 0, 0, 0.02, -0.01, 0.01], [0.01, 0.01, -0.01, -0.015, 0.02, 0.0])):
            start = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ torch.as_tensor(poses[0])
            r = icp(md.to(cuda), valid.to(cuda), torch.as_tensor(poses[0], device=cuda),
                    torch.as_tensor(frames[0][1]).float().to(cuda), k, TrackingConfig(cuda_graphs=graphs),
                    out.rgb.to(cuda), torch.as_tensor(frames[0][0]).float().to(cuda), start_c2w=start.to(cuda))
            results[graphs, i] = r
        if graphs:
            assert any(v is not None and v.graph is not None for v in tracking._GRAPHS.values()), "no graph captured"
    for i in (0, 1):
        a, b = results[False, i], results[True, i]
        torch.testing.assert_close(a.c2w, b.c2w, rtol=0, atol=1e-9)
        assert a.inliers == b.inliers and abs(a.residual - b.residual) < 1e-9
        assert pose_error(b.c2w.cpu().numpy(), poses[0])[0] < 0.004


def test_icp_step_count_follows_its_settings(scene, monkeypatch):
    """``icp_min_step`` ends a level early, ``icp_row_points`` sets how many live points a step uses, and both
    are checked."""
    from semantic_gs_slam import tracking
    from semantic_gs_slam.errors import ConfigError

    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    seen = []
    orig = tracking._icp_step

    def counting(est, pts, *a, **kw):
        seen.append(pts.lp.shape[0])
        return orig(est, pts, *a, **kw)

    monkeypatch.setattr(tracking, "_icp_step", counting)
    runs = {}
    for name, cfg in {"strict": TrackingConfig(icp_min_step=0.0), "loose": TrackingConfig(icp_min_step=1e-3),
                      "sparse": TrackingConfig(icp_min_step=0.0, icp_row_points=80)}.items():
        seen.clear()
        r = icp(md, valid, torch.as_tensor(poses[0]), torch.as_tensor(frames[1][1]).float(), k, cfg, out.rgb,
                torch.as_tensor(frames[1][0]).float())
        runs[name] = (len(seen), max(seen), r)
    assert runs["strict"][0] == 2 * TrackingConfig().icp_iters  # 0: never converged, every step runs
    assert runs["loose"][0] < runs["strict"][0]
    assert runs["sparse"][1] * 3 < runs["strict"][1]  # 160 -> 80 points per row (pixel stride 1 -> 2 at 160 px)
    for name in ("loose", "sparse"):
        assert pose_error(runs[name][2].c2w.numpy(), poses[1])[0] < 0.01
    for bad in ({"icp_row_points": 0}, {"icp_min_step": -1.0}, {"icp_min_step": float("nan")}):
        with pytest.raises(ConfigError):
            TrackingConfig(**bad).check()
