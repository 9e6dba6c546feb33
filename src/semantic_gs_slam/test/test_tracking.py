"""Tracking: ICP against the rendered model recovers a perturbed pose."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig, device_default
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import TrackingError
from semantic_gs_slam.geometry import pose_error, se3_exp
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
from semantic_gs_slam.tracking.tracker import icp


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
    from semantic_gs_slam.tracking.tracker import photometric_loss, photometric_refine

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
    from semantic_gs_slam.tracking.tracker import plane_depth_features, plane_depth_image

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
    from semantic_gs_slam.tracking.tracker import _solve_spd6

    gen = torch.Generator().manual_seed(0)
    for scale in (1.0, 1e4, 1e8):
        j = torch.randn(500, 6, generator=gen, dtype=torch.float64) * torch.tensor([1, 1, 1, 0.1, 0.1, 0.01],
                                                                                     dtype=torch.float64)
        a = scale * j.T @ j + torch.diag(torch.tensor([400.0] * 6, dtype=torch.float64))
        b = torch.randn(6, generator=gen, dtype=torch.float64)
        ref = torch.linalg.solve(a, b)
        torch.testing.assert_close(_solve_spd6(a, b), ref, rtol=1e-9, atol=1e-14)


def _problem(eng, k, pose, live):
    """An ICP problem as :func:`icp` builds it: the model rendered at ``pose``, the live frame ``live``'s points
    at pixel stride 2, intensity gradients of the rendered colour."""
    from semantic_gs_slam.geometry import backproject
    from semantic_gs_slam.tracking.tracker import _IcpModel, _IcpPoints, normal_map

    md, valid, out = model(eng, pose)
    g = torch.as_tensor(pose)
    vm = backproject(md.double(), k.fx, k.fy, k.cx, k.cy) @ g[:3, :3].T + g[:3, 3]
    nm, nvalid = normal_map(vm, valid)
    im = out.rgb.double().mean(-1)
    gx, gy = torch.zeros_like(im), torch.zeros_like(im)
    gx[:, 1:-1] = 0.5 * (im[:, 2:] - im[:, :-2])
    gy[1:-1] = 0.5 * (im[2:] - im[:-2])
    col = torch.stack([im, gx, gy, valid.double()], -1).reshape(-1, 4)
    mdl = _IcpModel(vm.reshape(-1, 3), nm.reshape(-1, 3), nvalid.reshape(-1), col, torch.linalg.inv(g),
                    torch.eye(6, dtype=torch.float64) * 400)
    lp = backproject(torch.as_tensor(live[1]).double(), k.fx, k.fy, k.cx, k.cy)[::2, ::2].reshape(-1, 3)
    pts = _IcpPoints(lp, lp[:, 2] > 0, torch.as_tensor(live[0]).double().mean(-1)[::2, ::2].reshape(-1))
    return pts, mdl


def test_icp_step_is_the_same_with_either_solver(scene):
    """The step the CUDA graph captures (with the graph's solver) gives the eager step's pose and statistics,
    with and without the photometric term (which changes the step: the gradients are real)."""
    from semantic_gs_slam.tracking.tracker import _icp_step, _solve_spd6

    eng, k, poses, frames = scene
    pts, mdl = _problem(eng, k, poses[0], frames[1])
    start = se3_exp(torch.tensor([0.01, 0, 0, 0.01, 0, 0], dtype=torch.float64)) @ torch.as_tensor(poses[0])
    steps = {}
    for photometric in (False, True):
        e1, s1 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric)
        e2, s2 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric, _solve_spd6)
        torch.testing.assert_close(e1, e2, rtol=0, atol=1e-12)
        torch.testing.assert_close(s1, s2, rtol=1e-9, atol=0)
        assert s1[0] > 1000 and 0 < s1[1] < 0.05  # correspondences, residual RMS (m)
        steps[photometric] = e1
    assert (steps[True] - steps[False]).abs().max() > 1e-7  # the colour term took part


def test_chunk_of_steps_keeps_the_loop_rules_on_the_device(monkeypatch):
    """:func:`_icp_steps` with scripted steps: it accepts steps while steps are left, stops after a step below
    ``icp_min_step`` (that step still accepted), refuses a step with too few correspondences (not applied, its count
    reported), counts the steps left, and reports the last accepted step's statistics."""
    from semantic_gs_slam.tracking import tracker as tracking

    script = []

    def scripted(est, *a, **kw):
        n, step = script.pop(0)
        return est + 1.0, torch.tensor([n, 0.01 * n, step, 0.5], dtype=torch.float64)

    monkeypatch.setattr(tracking, "_icp_step", scripted)
    cfg = TrackingConfig(min_correspondences=100, icp_min_step=1e-6)
    est0 = torch.zeros(4, 4, dtype=torch.float64)

    def run(steps, left):
        script[:] = steps
        est, lft, st = tracking._icp_steps(est0, torch.tensor(float(left), dtype=torch.float64), None, None, None,
                                           cfg, False, len(steps))
        return float(est[0, 0]), float(lft), st.tolist()

    assert run([(500, 1e-3)] * 4, 10) == (4.0, 6.0, [6.0, -1.0, 500.0, 5.0, 1e-3, 0.5])  # all accepted
    assert run([(500, 1e-3)] * 4, 2)[:2] == (2.0, 0.0)  # only the steps left are taken
    est, left, st = run([(300, 1e-3), (400, 1e-7), (500, 1e-3), (600, 1e-3)], 10)
    assert (est, left) == (2.0, 0.0) and st[1:3] == [-1.0, 400.0]  # converged at the 2nd step, which counts
    est, left, st = run([(300, 1e-3), (50, 1e-3), (500, 1e-3), (600, 1e-3)], 10)
    assert (est, left) == (1.0, 0.0) and st[1:3] == [50.0, 300.0]  # refused at the 2nd, the 1st is the last
    est, left, st = run([(500, 1e-3)] * 4, 0)
    assert est == 0.0 and st[2] != st[2]  # nothing left: nothing accepted (NaN statistics)


@pytest.mark.parametrize("case", ["runs out of steps", "converges", "loses the model"])
def test_icp_in_chunks_of_steps_equals_the_step_loop(scene, monkeypatch, case):
    """The CUDA graph's chunks of steps (run eagerly here: the capture itself needs a GPU) give the step loop's
    pose, residual and correspondences when the iterations run out, when a step gets below ``icp_min_step``
    mid-chunk, and the same TrackingError when the correspondences run out."""
    from semantic_gs_slam.tracking import tracker as tracking

    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    start = se3_exp(torch.tensor([0.01, 0.01, -0.01, -0.015, 0.02, 0.0], dtype=torch.float64)) @ torch.as_tensor(
        poses[0])
    # the chunks always sum with the tensor reference (the graph path is for CUDA): so does the step loop here
    cfg = {"runs out of steps": TrackingConfig(icp_iters=7, icp_min_step=0.0, icp_backend="torch"),  # 7: not a
           # multiple of 4
           "converges": TrackingConfig(icp_iters=40, icp_min_step=1e-4, icp_backend="torch"),
           "loses the model": TrackingConfig(min_correspondences=2000, icp_backend="torch")}[case]
    live = torch.as_tensor(frames[0][1]).float()
    if case == "loses the model":
        live = live.clone()
        live[:, : k.width * 3 // 4] = 0  # only a quarter of the frame: too few points
    steps = []
    orig = tracking._icp_step

    def counting(*a, **kw):
        steps.append(1)
        return orig(*a, **kw)

    monkeypatch.setattr(tracking, "_icp_step", counting)

    def run(graphs):
        steps.clear()
        try:
            return icp(md, valid, torch.as_tensor(poses[0]), live, k, cfg, out.rgb,
                       torch.as_tensor(frames[0][0]).float(), start_c2w=start, graphs=graphs)
        except TrackingError as exc:
            return str(exc)

    ref = run(None)
    ref_steps = len(steps)
    cache = tracking.IcpGraphs(capture=False)
    got = run(cache)
    assert len(cache) == (1 if case == "loses the model" else cfg.icp_levels)  # the chunked path ran
    if case == "loses the model":
        assert isinstance(ref, str) and "correspondences" in ref and got == ref
        return
    torch.testing.assert_close(got.c2w, ref.c2w, rtol=0, atol=1e-12)
    assert got.inliers == ref.inliers and abs(got.residual - ref.residual) < 1e-12
    assert abs(got.agreement - ref.agreement) < 1e-12
    if case == "runs out of steps":
        assert ref_steps == 2 * 7
    else:  # the test means something only if a level stopped early
        assert ref_steps < 2 * cfg.icp_iters
    # a second problem of the same shape through the same cache: its model replaces the first one's
    md, valid, out = model(eng, poses[1])
    live = torch.as_tensor(frames[1][1]).float()
    second = [icp(md, valid, torch.as_tensor(poses[1]), live, k, cfg, out.rgb, torch.as_tensor(frames[1][0]).float(),
                  graphs=g) for g in (None, cache)]
    torch.testing.assert_close(second[1].c2w, second[0].c2w, rtol=0, atol=1e-12)
    assert (second[1].c2w - got.c2w).abs().max() > 1e-4  # a different answer from the first problem's


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_icp_cuda_graph_matches_the_eager_step(scene):
    """On CUDA, ICP with each chunk of steps replayed from a captured graph gives the eager reference's pose, also
    on a second problem of the same shape (another model and live frame: the graph is reused with new inputs)."""
    from semantic_gs_slam.tracking import tracker as tracking

    eng, k, poses, frames = scene
    cuda = torch.device("cuda")
    problems = []
    for model_pose, live, xi in ((poses[0], frames[0], [0, 0, 0, 0.02, -0.01, 0.01]),
                                 (poses[1], frames[1], [0.01, 0.01, -0.01, -0.015, 0.02, 0.0])):
        md, valid, out = model(eng, model_pose)
        start = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ torch.as_tensor(model_pose)
        problems.append((md, valid, out, model_pose, live, start))
    results = {}
    for graphs in (None, tracking.IcpGraphs()):
        for i, (md, valid, out, model_pose, live, start) in enumerate(problems):
            results[graphs is not None, i] = icp(
                md.to(cuda), valid.to(cuda), torch.as_tensor(model_pose, device=cuda),
                torch.as_tensor(live[1]).float().to(cuda), k, TrackingConfig(), out.rgb.to(cuda),
                torch.as_tensor(live[0]).float().to(cuda), start_c2w=start.to(cuda), graphs=graphs)
        if graphs is not None:
            assert len(graphs) > 0, "no graph was captured"
    for i in (0, 1):
        a, b = results[False, i], results[True, i]
        torch.testing.assert_close(a.c2w, b.c2w, rtol=0, atol=1e-9)
        assert a.inliers == b.inliers and abs(a.residual - b.residual) < 1e-9
        assert pose_error(b.c2w.cpu().numpy(), problems[i][3])[0] < 0.004
    assert (results[True, 0].c2w - results[True, 1].c2w).abs().max() > 1e-3  # two different answers


def test_icp_step_count_follows_its_settings(scene, monkeypatch):
    """``icp_min_step`` ends a level early, ``icp_row_points`` sets how many live points a step uses, and both
    are checked."""
    from semantic_gs_slam.errors import ConfigError
    from semantic_gs_slam.tracking import tracker as tracking

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
    # icp_min_step 0: never converged, every step runs
    assert runs["strict"][0] == 2 * device_default("tracking", "icp_iters", "cpu")
    assert runs["loose"][0] < runs["strict"][0]
    assert runs["sparse"][1] * 3 < runs["strict"][1]  # 160 -> 80 points per row (pixel stride 1 -> 2 at 160 px)
    for name in ("loose", "sparse"):
        assert pose_error(runs[name][2].c2w.numpy(), poses[1])[0] < 0.01
    for bad in ({"icp_row_points": 0}, {"icp_min_step": -1.0}, {"icp_min_step": float("nan")}):
        with pytest.raises(ConfigError):
            TrackingConfig(**bad).check()


@pytest.mark.skipif(not numba_available(), reason="numba not installed (the reference is used)")
def test_numba_normal_equations_match_the_reference(scene):
    """The compiled CPU sums of an ICP step equal the tensor reference's, with and without the photometric term,
    from a start off the model's pose (so the geometric residuals, Huber weights and rejections all take part)."""
    from semantic_gs_slam.tracking.icp_numba import normal_equations_numba
    from semantic_gs_slam.tracking.tracker import icp_normal_equations

    eng, k, poses, frames = scene
    pts, mdl = _problem(eng, k, poses[0], frames[1])
    for xi in ([0.01, 0, 0, 0.01, 0, 0], [0.0, 0.015, -0.01, 0.02, -0.025, 0.015]):
        start = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ torch.as_tensor(poses[0])
        for photometric in (False, True):
            for cfg in (TrackingConfig(), TrackingConfig(icp_max_dist=0.02, icp_sigma_geo=0.002)):
                a1, b1, s1 = icp_normal_equations(start, pts, mdl, k, cfg, photometric)
                a2, b2, s2 = normal_equations_numba(start, pts.lp, pts.lvalid, pts.il, mdl.vm, mdl.nm, mdl.nvalid,
                                                    mdl.col, mdl.w2c_g, k, cfg, photometric)
                torch.testing.assert_close(a2, a1, rtol=1e-9, atol=1e-6)
                torch.testing.assert_close(b2, b1, rtol=1e-9, atol=1e-6)
                assert s2[0] == s1[0] and s2[2] == s1[2] and s2[3] == s1[3], (s1, s2)
                torch.testing.assert_close(s2[1], s1[1], rtol=1e-9, atol=0)
                assert 100 < float(s1[0]) < float(s1[3])  # correspondences, and some rejected as too far


@pytest.mark.skipif(not numba_available(), reason="numba not installed (the reference is used)")
def test_icp_with_the_numba_sums_equals_the_reference(scene):
    eng, k, poses, frames = scene
    md, valid, out = model(eng, poses[0])
    start = se3_exp(torch.tensor([0.01, 0.01, -0.01, -0.015, 0.02, 0.0], dtype=torch.float64)) @ torch.as_tensor(
        poses[0])
    res = {}
    for backend in ("torch", "numba", "auto"):
        res[backend] = icp(md, valid, torch.as_tensor(poses[0]), torch.as_tensor(frames[1][1]).float(), k,
                           TrackingConfig(icp_backend=backend), out.rgb, torch.as_tensor(frames[1][0]).float(),
                           start_c2w=start)
    for backend in ("numba", "auto"):
        torch.testing.assert_close(res[backend].c2w, res["torch"].c2w, rtol=0, atol=1e-9)
        assert res[backend].inliers == res["torch"].inliers
        assert abs(res[backend].residual - res["torch"].residual) < 1e-9


def test_icp_backend_is_checked_and_a_missing_numba_is_a_typed_error(monkeypatch):
    import semantic_gs_slam.devices as devices
    from semantic_gs_slam.errors import BackendUnavailableError, ConfigError
    from semantic_gs_slam.tracking import tracker as tracking

    with pytest.raises(ConfigError, match="icp_backend"):
        TrackingConfig(icp_backend="fast").check()
    monkeypatch.setattr(tracking, "numba_available", lambda: False)
    monkeypatch.setattr(devices, "numba_available", lambda: False)
    with pytest.raises(BackendUnavailableError, match="numba"):
        tracking.icp_uses_numba(TrackingConfig(icp_backend="numba"), torch.device("cpu"))
    assert not tracking.icp_uses_numba(TrackingConfig(), torch.device("cpu"))  # auto: the reference
    monkeypatch.setattr(tracking, "numba_available", lambda: True)
    monkeypatch.setattr(devices, "numba_available", lambda: True)
    assert tracking.icp_uses_numba(TrackingConfig(), torch.device("cpu"))
    assert not tracking.icp_uses_numba(TrackingConfig(), torch.device("cuda"))  # never on a GPU
    with pytest.raises(BackendUnavailableError, match="CPU"):
        tracking.icp_uses_numba(TrackingConfig(icp_backend="numba"), torch.device("cuda"))


@pytest.mark.skipif(not numba_available(), reason="numba not installed (the reference is used)")
def test_numba_icp_step_equals_the_reference_step(scene):
    """The whole fast step (compiled sums, prior, solve and pose update in numpy) against the tensor step."""
    from semantic_gs_slam.tracking.tracker import _icp_step

    eng, k, poses, frames = scene
    pts, mdl = _problem(eng, k, poses[0], frames[1])
    for xi in ([0.01, 0, 0, 0.01, 0, 0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [-0.02, 0.01, 0.005, 0.0, 0.02, -0.01]):
        start = se3_exp(torch.tensor(xi, dtype=torch.float64)) @ torch.as_tensor(poses[0])
        for photometric in (False, True):
            e1, s1 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric)
            e2, s2 = _icp_step(start, pts, mdl, k, TrackingConfig(), photometric, fast=True)
            torch.testing.assert_close(e2, e1, rtol=0, atol=1e-11)
            torch.testing.assert_close(s2, s1, rtol=1e-9, atol=1e-12)
            assert e2.dtype == torch.float64 and s2.shape == (4,)


def test_velocity_guess_scales_the_last_step_by_the_frame_times():
    from semantic_gs_slam.geometry import velocity_guess
    from semantic_gs_slam.loop.posegraph import so3_exp, so3_log

    step = np.eye(4)
    step[:3, :3] = so3_exp(np.array([0.0, 0.03, 0.01]))  # 1.8 degrees about a tilted axis
    step[:3, 3] = [0.02, -0.01, 0.005]
    prev2 = np.eye(4)
    prev2[:3, 3] = [1.0, 2.0, 0.5]
    prev = prev2 @ step
    even = velocity_guess(prev2, prev, 1 / 30, 1 / 30, 3.0)
    np.testing.assert_allclose(even, prev @ step, atol=1e-12)  # evenly spaced: one step
    two = velocity_guess(prev2, prev, 1 / 30, 2 / 30, 3.0)  # one frame dropped: two steps of the same motion
    np.testing.assert_allclose(so3_log((np.linalg.inv(prev) @ two)[:3, :3]), [0.0, 0.06, 0.02], atol=1e-9)
    np.testing.assert_allclose((np.linalg.inv(prev) @ two)[:3, 3], 2 * step[:3, 3], atol=1e-12)
    far = velocity_guess(prev2, prev, 1 / 30, 3.0, 3.0)  # a stalled stream: at most max_scale steps
    np.testing.assert_allclose((np.linalg.inv(prev) @ far)[:3, 3], 3 * step[:3, 3], atol=1e-12)
    for dt_prev, dt, cap in ((0.0, 1 / 30, 3.0), (1 / 30, float("nan"), 3.0), (-1.0, 1.0, 3.0), (1 / 30, 0.1, 0.0)):
        np.testing.assert_allclose(velocity_guess(prev2, prev, dt_prev, dt, cap), prev @ step, atol=1e-12)
    half = velocity_guess(prev2, prev, 2 / 30, 1 / 30, 3.0)  # a faster frame than the last: half a step
    np.testing.assert_allclose((np.linalg.inv(prev) @ half)[:3, 3], 0.5 * step[:3, 3], atol=1e-12)


def test_the_engine_guesses_from_the_times_add_frame_was_given():
    """add_frame's timestamps reach the constant-velocity guess: a frame two periods after the last is guessed two
    steps on (tracking.velocity_max_scale), and with the scale off one step, as from evenly spaced frames."""
    from semantic_gs_slam.geometry import velocity_guess

    k = default_intrinsics(32, 24)
    step = np.eye(4)
    step[:3, 3] = [0.03, 0.0, 0.0]
    for cap, steps in ((3.0, 2.0), (0.0, 1.0)):
        eng = SLAM(SlamConfig(intrinsics=k, device="cpu", tracking=TrackingConfig(velocity_max_scale=cap)))
        eng.poses, eng.timestamps = [np.eye(4), step.copy()], [10.0, 10.1]
        eng._frame_time = 10.3  # what add_frame sets before it tracks
        guess = eng._velocity_guess(eng.poses[0], eng.poses[1])
        assert guess[0, 3] == pytest.approx(0.03 * (1 + steps))
        np.testing.assert_allclose(guess, velocity_guess(eng.poses[0], eng.poses[1], 0.1, 0.2, cap))
