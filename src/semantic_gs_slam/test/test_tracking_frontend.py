"""The frame-rate front end: compiled sums equal the reference, ICP converges, lost is detected, relocalisation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.devices import numba_available
from semantic_gs_slam.errors import ConfigError, FrameError, TrackingError
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory
from semantic_gs_slam.tracking.frontend import (
    FrameTracker,
    FrontendConfig,
    RelocalisationError,
    build_reference,
    depth_roughness,
    depth_speckle,
    downsample_frame,
    fill_isolated_holes,
    normal_equations,
    normal_equations_reference,
    prepare_live,
    relocalise,
    track,
)
from semantic_gs_slam.tracking.icp_numba import _se3_exp

needs_numba = pytest.mark.skipif(not numba_available(), reason="numba not installed")
CFG = FrontendConfig(backend="numpy")


@pytest.fixture(scope="module")
def scene():
    """Two views of the synthetic home 160x120 (keyframe, live 3 orbit steps on) and a far-away view."""
    k = default_intrinsics(160, 120)
    poses = trajectory(60, 60.0)
    ren = HomeRenderer(0)
    views = {i: ren.render(poses[i], k) for i in (0, 3, 45)}
    return k, poses, views


def perturb(c2w: np.ndarray, xi: list[float]) -> np.ndarray:
    return _se3_exp(np.asarray(xi, np.float64)) @ c2w


@needs_numba
@pytest.mark.parametrize(("photometric", "z2", "gate_z2"), [(0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (0.0, 0.01, 0.0),
                                                       (0.5, 0.01, 0.0), (0.5, 0.01, 0.2)])
def test_compiled_sums_equal_the_reference(scene, photometric, z2, gate_z2):
    k, poses, views = scene
    cfg = replace(CFG, photometric_weight=photometric, sigma_geo_z2=z2)  # 0.01: every point beyond 1 m scaled
    rgb0, d0, _ = views[0]
    rgb1, d1, _ = views[3]
    model = build_reference(d0, poses[0], k, cfg, rgb=rgb0)
    live = prepare_live(d1, k, cfg, rgb=rgb1)
    est = perturb(poses[3], [0.01, -0.02, 0.005, 0.02, 0.0, -0.01])
    wider = []  # with the gate widened: more points associated than within max_dist
    for lv in range(cfg.levels):
        args = (est, live.points[lv], live.valid[lv], live.intensity if lv == 0 else None, model.levels[lv],
                model.w2c, cfg.max_dist[lv], cfg, lv == 0, gate_z2)  # 0.2: the gate past 0.05 m beyond 0.5 m
        a, b, st = normal_equations(*args)
        ar, br, sr = normal_equations_reference(*args)
        assert st[0] > 100
        np.testing.assert_array_equal(st[[0, 2, 3]], sr[[0, 2, 3]])
        np.testing.assert_allclose(st[1], sr[1], rtol=1e-9)
        np.testing.assert_allclose(a, ar, rtol=1e-9, atol=1e-9 * np.abs(ar).max())
        np.testing.assert_allclose(b, br, rtol=1e-9, atol=1e-9 * np.abs(br).max())
        if gate_z2:
            wider.append(st[0] > normal_equations(*args[:-1], 0.0)[2][0])
    assert not gate_z2 or any(wider)


@needs_numba
def test_compiled_model_live_points_and_track_equal_the_reference(scene):
    k, poses, views = scene
    fast = replace(CFG, backend="numba")
    d0, d1 = views[0][1], views[3][1]
    m_ref, m_fast = build_reference(d0, poses[0], k, CFG), build_reference(d0, poses[0], k, fast)
    for a, b in zip(m_ref.levels, m_fast.levels, strict=True):
        assert a.k == b.k and a.nvalid.sum() > 100
        np.testing.assert_array_equal(a.nvalid, b.nvalid)
        np.testing.assert_allclose(a.vm, b.vm, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.nm, b.nm, rtol=0, atol=1e-12)
    l_ref, l_fast = prepare_live(d1, k, CFG), prepare_live(d1, k, fast)
    for a, b, va, vb in zip(l_ref.points, l_fast.points, l_ref.valid, l_fast.valid, strict=True):
        np.testing.assert_array_equal(va, vb)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    start = perturb(poses[3], [0.02, -0.01, 0.01, 0.03, -0.02, 0.01])
    r_ref, r_fast = track(l_ref, m_ref, start, CFG), track(l_fast, m_fast, start, fast)
    assert r_ref.steps == r_fast.steps > 0
    np.testing.assert_allclose(r_ref.c2w, r_fast.c2w, rtol=0, atol=1e-9)
    assert r_ref.quality.correspondences == r_fast.quality.correspondences
    # with colour: the intensity term on the finest level (one compiled call for all levels: frontend_numba.icp_track)
    c0, c1 = views[0][0], views[3][0]
    m_ref, m_fast = build_reference(d0, poses[0], k, CFG, rgb=c0), build_reference(d0, poses[0], k, fast, rgb=c0)
    l_ref, l_fast = prepare_live(d1, k, CFG, c1), prepare_live(d1, k, fast, c1)
    r_ref, r_fast = track(l_ref, m_ref, start, CFG), track(l_fast, m_fast, start, fast)
    assert r_ref.steps == r_fast.steps > 0
    np.testing.assert_allclose(r_ref.c2w, r_fast.c2w, rtol=0, atol=1e-9)
    assert r_ref.quality.correspondences == r_fast.quality.correspondences
    assert r_ref.quality.agreement == pytest.approx(r_fast.quality.agreement, abs=1e-12)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=needs_numba)])
@pytest.mark.parametrize("xi", [[0, 0, 0, 0.04, -0.03, 0.02], [0.04, -0.03, 0.02, 0, 0, 0]])
def test_converges_from_a_perturbed_pose(scene, backend, xi):
    k, poses, views = scene
    cfg = replace(CFG, backend=backend)
    model = build_reference(views[0][1], poses[0], k, cfg)
    res = track(prepare_live(views[3][1], k, cfg), model, perturb(poses[3], xi), cfg)
    et, er = pose_error(res.c2w, poses[3])
    assert et < 0.005 and er < 0.3, (et, er)
    assert res.quality.trusted, res.quality
    assert res.quality.agreement > 0.9 and res.quality.coverage > 0.5


def test_garbage_depth_is_lost(scene):
    k, poses, views = scene
    model = build_reference(views[0][1], poses[0], k, CFG)
    rng = np.random.default_rng(0)
    garbage = rng.uniform(0.3, 3.5, (k.height, k.width))  # depth noise: no surface agrees with the map
    res = track(prepare_live(garbage, k, CFG), model, poses[3], CFG)
    assert not res.quality.trusted
    assert "agreement" in res.quality.reason or "coverage" in res.quality.reason
    empty = track(prepare_live(np.zeros((k.height, k.width)), k, CFG), model, poses[3], CFG)
    assert not empty.quality.trusted and "correspondences" in empty.quality.reason


def test_noisy_far_depth_agrees_at_its_own_scale(scene):
    """Two frames of a depth sensor whose noise grows with z^2 (0.0025 z^2 each: 1.6 cm at 2.5 m) from one pose:
    at a fixed 1 cm scale the far points read as disagreement and the frame is lost; at the depth's own scale
    (the default sigma_geo_z2) it is trusted, at the right pose."""
    k, poses, views = scene
    depth = views[0][1]
    noisy = []
    for seed in (0, 1):
        rng = np.random.default_rng(seed)
        noisy.append(np.where(depth > 0, depth + rng.standard_normal(depth.shape) * 0.0025 * depth ** 2, 0.0))
    res = {}
    for z2 in (0.0, FrontendConfig().sigma_geo_z2):
        cfg = replace(CFG, sigma_geo_z2=z2, photometric_weight=0.0, noisy_roughness=0.0,  # raw: the scale alone
                      trust_z2_per_roughness=0.0)
        res[z2] = track(prepare_live(noisy[1], k, cfg), build_reference(noisy[0], poses[0], k, cfg), poses[0], cfg)
    fixed, scaled = res[0.0].quality, res[FrontendConfig().sigma_geo_z2].quality
    assert not fixed.trusted and "agreement" in fixed.reason, fixed
    assert scaled.trusted and scaled.agreement > fixed.agreement + 0.03, scaled
    assert pose_error(res[FrontendConfig().sigma_geo_z2].c2w, poses[0])[0] < 0.01


def test_depth_roughness_reads_a_noise_that_grows_with_depth_squared(scene):
    """A rendered view is smooth; noise a z^2 reads about 0.75 a (the median of |the 4-neighbour Laplacian| of
    Gaussian noise), near and far alike; too few usable pixels read 0 (no evidence)."""
    depth = scene[2][0][1]
    assert depth_roughness(depth) < 1e-4
    for a in (0.001, 0.002):
        rng = np.random.default_rng(0)
        noisy = np.where(depth > 0, depth + rng.standard_normal(depth.shape) * a * depth ** 2, 0.0)
        assert 0.6 * a < depth_roughness(noisy) < 0.9 * a
    assert depth_roughness(np.zeros((20, 20))) == 0.0 and depth_roughness(depth[:10, :10]) == 0.0


@needs_numba
def test_compiled_depth_roughness_gives_the_numpy_roughness(scene):
    from semantic_gs_slam.tracking import frontend_numba as fk

    depth = scene[2][0][1]
    rng = np.random.default_rng(3)
    noisy = np.where(depth > 0, depth + rng.standard_normal(depth.shape) * 0.002 * depth ** 2, 0.0)
    noisy[40:60, 50:90] = 0.0  # a hole
    for d in (depth, noisy, np.zeros((20, 20)), noisy[:10, :10]):
        d = np.ascontiguousarray(d)
        assert fk.depth_roughness(d, 0.05, 500) == pytest.approx(depth_roughness(d, 0.05, 500), rel=1e-12, abs=0)
    fast = replace(CFG, backend="numba")
    assert build_reference(noisy, np.eye(4), scene[0], fast).roughness == pytest.approx(
        build_reference(noisy, np.eye(4), scene[0], CFG).roughness, rel=1e-12)


def test_a_noisy_reference_is_smoothed_and_tracks_closer(scene):
    """Depth with noise 0.01 z^2 (about 5 times a Kinect's at 2 m) in both frames: the reference reads as noisy and
    is averaged over 3 x 3 pixels; the live frame then agrees with it more and lands within 1 cm, where the raw
    reference (the smoothing off) leaves 3-13 cm."""
    k, poses, views = scene
    d0, d3 = views[0][1], views[3][1]
    for seed in range(3):
        rng = np.random.default_rng(seed)
        n0, n3 = (np.where(d > 0, d + rng.standard_normal(d.shape) * 0.01 * d ** 2, 0.0) for d in (d0, d3))
        res = {}
        for rough in (0.0, FrontendConfig().noisy_roughness):
            cfg = replace(CFG, photometric_weight=0.0, noisy_roughness=rough, trust_z2_per_roughness=0.0)
            model = build_reference(n0, poses[0], k, cfg)
            assert model.smoothing == (1 if rough == 0.0 else 3) and (model.roughness > rough) == (rough > 0)
            res[rough] = (track(prepare_live(n3, k, cfg), model, poses[0], cfg), model)
        raw, smooth = res[0.0][0], res[FrontendConfig().noisy_roughness][0]
        assert smooth.quality.agreement > raw.quality.agreement + 0.05, (raw.quality, smooth.quality)
        assert pose_error(smooth.c2w, poses[3])[0] < 0.01
        assert pose_error(raw.c2w, poses[3])[0] > 0.02
    clean = build_reference(d0, poses[0], k, CFG)  # a clean view stays raw
    assert clean.smoothing == 1 and clean.roughness < CFG.noisy_roughness
    # a roughness already known (the same depth at a moved pose) is taken as given, not measured again
    told = build_reference(d0, poses[3], k, CFG, roughness=0.01)
    assert told.roughness == 0.01 and told.smoothing == 3
    with pytest.raises(ConfigError, match="noisy_smoothing"):
        build_reference(d0, poses[0], k, replace(CFG, noisy_smoothing=2))
    with pytest.raises(ConfigError, match="noisy_roughness"):
        build_reference(d0, poses[0], k, replace(CFG, noisy_roughness=float("nan")))


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=needs_numba)])
def test_a_noisy_camera_is_trusted_at_its_own_noise_with_the_same_pose(scene, backend):
    """Both frames with noise 0.006 z^2 (about three times a Kinect's), raw references, the association gate
    widened (15 cm) so that the trust tolerance decides: at the fixed z^2 scale the frame reads as lost
    (agreement); with the trust test at the reference's roughness (the default) it is trusted. Only the test
    changes: the pose is the same to the last bit, and a clean reference keeps the fixed scale."""
    k, poses, views = scene
    d0, d3 = views[0][1], views[3][1]
    rng = np.random.default_rng(5)
    n0, n3 = (np.where(d > 0, d + rng.standard_normal(d.shape) * 0.006 * d ** 2, 0.0) for d in (d0, d3))
    res = {}
    for c in (0.0, FrontendConfig().trust_z2_per_roughness):
        cfg = replace(CFG, backend=backend, photometric_weight=0.0, trust_z2_per_roughness=c, noisy_roughness=0.0,
                      max_dist=(0.15, 0.2, 0.3))
        res[c] = track(prepare_live(n3, k, cfg), build_reference(n0, poses[0], k, cfg), poses[0], cfg)
    fixed, own = res[0.0], res[FrontendConfig().trust_z2_per_roughness]
    assert not fixed.quality.trusted and "agreement" in fixed.quality.reason, fixed.quality
    assert own.quality.trusted and own.quality.agreement > fixed.quality.agreement + 0.08, own.quality
    np.testing.assert_array_equal(own.c2w, fixed.c2w)
    assert pose_error(own.c2w, poses[3])[0] < 0.02
    clean = replace(CFG, backend=backend)
    model = build_reference(d0, poses[0], k, clean)
    assert clean.trust_z2_per_roughness * model.roughness < clean.sigma_geo_z2  # a clean view: the fixed scale
    with pytest.raises(ConfigError, match="trust_z2_per_roughness"):
        build_reference(d0, poses[0], k, replace(CFG, trust_z2_per_roughness=-1.0))


@needs_numba
def test_compiled_speckle_and_hole_filling_give_the_numpy_ones_exactly(scene):
    from semantic_gs_slam.tracking import frontend_numba as fk

    depth = scene[2][0][1].astype(np.float64)
    rng = np.random.default_rng(4)
    holed = np.where(rng.random(depth.shape) < 0.4, 0.0, depth)
    holed[5, 7], holed[9, 3] = 9.0, 0.05  # out of the front end's range: missing
    for d in (depth, holed, np.zeros((6, 8)), holed[:3, :4]):
        d = np.ascontiguousarray(d)
        assert fk.depth_speckle(d) == depth_speckle(d)
        out = np.empty_like(d)
        fk.fill_isolated_holes(d, CFG.depth_min, CFG.depth_max, CFG.depth_jump, out)
        ref = fill_isolated_holes(np.where((d >= CFG.depth_min) & (d <= CFG.depth_max), d, 0.0), CFG.depth_jump)
        np.testing.assert_array_equal(out, ref)


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=needs_numba)])
def test_a_speckled_camera_has_its_isolated_holes_filled_and_tracks(scene, backend):
    """30 % of both frames' depth pixels dropped at random: the reference reads as speckled, its isolated holes are
    filled (a normal needs its neighbours) and so are the live frame's; the frame is then trusted within 2 cm, where
    without the filling it is not trusted (coverage). A clean view is left as it is."""
    k, poses, views = scene
    (rgb0, d0, _), (rgb3, d3, _) = views[0], views[3]
    rng = np.random.default_rng(2)
    h0, h3 = (np.where(rng.random(d.shape) < 0.3, 0.0, d) for d in (d0, d3))
    fill = FrontendConfig().speckle_fill
    assert depth_speckle(d0) < fill < depth_speckle(h0)
    res = {}
    for f in (0.0, fill):
        cfg = replace(CFG, backend=backend, speckle_fill=f)
        model = build_reference(h0, poses[0], k, cfg, rgb=rgb0)
        res[f] = model, track(prepare_live(h3, k, cfg, rgb=rgb3, fill_holes=f > 0), model, poses[0], cfg)
    (m_off, off), (m_on, on) = res[0.0], res[fill]
    assert m_on.speckle > fill and m_on.levels[0].nvalid.mean() > 2 * m_off.levels[0].nvalid.mean()
    assert on.quality.trusted and pose_error(on.c2w, poses[3])[0] < 0.02, on.quality
    assert not off.quality.trusted and "coverage" in off.quality.reason, off.quality
    clean, raw = (build_reference(d0, poses[0], k, replace(CFG, backend=backend, speckle_fill=f)) for f in (fill, 0.0))
    np.testing.assert_array_equal(clean.levels[0].vm, raw.levels[0].vm)
    # a hole between two surfaces (a depth edge) stays a hole; one inside a surface takes its neighbours' mean
    edge = np.full((5, 6), 1.0)
    edge[:, 3:] = 2.0
    edge[2, 2] = edge[2, 4] = 0.0
    out = fill_isolated_holes(edge)
    assert out[2, 2] == 0.0 and out[2, 4] == pytest.approx(2.0)
    with pytest.raises(ConfigError, match="speckle_fill"):
        build_reference(d0, poses[0], k, replace(CFG, speckle_fill=2.0))


def test_a_lone_plane_is_ill_conditioned():
    k = default_intrinsics(80, 60)
    wall = np.full((k.height, k.width), 2.0)  # a fronto-parallel wall leaves three directions free
    res = track(prepare_live(wall, k, CFG), build_reference(wall, np.eye(4), k, CFG), np.eye(4), CFG)
    assert not res.quality.trusted and "condition" in res.quality.reason


def test_relocalises_from_a_wrong_guess(scene):
    k, poses, views = scene
    model = build_reference(views[0][1], poses[0], k, CFG, keyframe_id=0)
    far = build_reference(views[45][1], poses[45], k, CFG, keyframe_id=45)
    live = prepare_live(views[3][1], k, CFG)
    wrong = poses[3] @ _se3_exp(np.array([0.0, 0.6, 0.0, 0.0, 0.0, 0.0]))  # turned 34 degrees: plain ICP fails
    assert not track(live, model, wrong, CFG).quality.trusted
    res = relocalise(live, [far, model], CFG, extra_guesses=[wrong])
    et, er = pose_error(res.c2w, poses[3])
    assert res.quality.trusted and res.keyframe_id == 0
    assert et < 0.01 and er < 0.5, (et, er)
    garbage = prepare_live(np.random.default_rng(1).uniform(0.3, 3.5, (k.height, k.width)), k, CFG)
    with pytest.raises(RelocalisationError, match="no trusted pose"):
        relocalise(garbage, [model], CFG)


def test_frame_tracker_tracks_reports_lost_and_recovers(scene):
    k, poses, views = scene
    tr = FrameTracker(k, CFG)
    with pytest.raises(TrackingError, match="no reference"):
        tr.track_frame(views[3][1])
    tr.set_reference(build_reference(views[0][1], poses[0], k, CFG, keyframe_id=0))
    assert tr.track_frame(views[0][1]).quality.trusted
    res = tr.track_frame(views[3][1])
    assert res.quality.trusted and pose_error(res.c2w, poses[3])[0] < 0.01
    lost = tr.track_frame(np.random.default_rng(2).uniform(0.3, 3.5, (k.height, k.width)))
    assert tr.lost and not lost.quality.trusted
    back = tr.track_frame(views[3][1])  # relocalised against the kept keyframe
    assert not tr.lost and pose_error(back.c2w, poses[3])[0] < 0.01


def test_bad_input_is_refused(scene):
    k, poses, views = scene
    with pytest.raises(FrameError, match="shape"):
        prepare_live(np.zeros((10, 10)), k, CFG)
    with pytest.raises(FrameError, match="NaN"):
        prepare_live(np.full((k.height, k.width), np.nan), k, CFG)
    with pytest.raises(FrameError, match="float"):
        prepare_live(np.zeros((k.height, k.width), np.uint16), k, CFG)
    with pytest.raises(FrameError, match="pose"):
        build_reference(views[0][1], np.eye(3), k, CFG)
    with pytest.raises(ConfigError, match="one value per level"):
        FrontendConfig(levels=2).check()


@pytest.mark.parametrize("backend", ["numpy", "numba"])
def test_downsample_frame_means_each_2x2_cell_and_never_averages_across_an_edge(backend):
    if backend == "numba" and not numba_available():
        pytest.skip("numba not installed")
    cfg = FrontendConfig(backend=backend)
    rng = np.random.default_rng(3)
    rgb = rng.random((17, 19, 3)).astype(np.float32)  # odd sizes: the last row and column are dropped
    depth = np.full((17, 19), 2.0)
    depth[0, 0] = 0.0  # a cell with a hole
    depth[2:4, 2:4] = [[1.0, 2.0], [1.0, 2.0]]  # a cell across an edge
    depth[4:6, 4:6] = [[2.0, 2.04], [2.02, 2.06]]  # a cell within depth_jump: its mean
    k = Intrinsics(fx=16.0, fy=16.0, cx=9.0, cy=8.0, width=19, height=17)
    d, c, k2 = downsample_frame(depth, rgb, k, 1, cfg)
    assert d.shape == (8, 9) and c.shape == (8, 9, 3) and (k2.width, k2.height) == (9, 8)
    want = rgb[:16, :18].reshape(8, 2, 9, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(c, want, rtol=1e-6)
    assert d[0, 0] == 0.0 and d[1, 1] == 0.0
    assert d[2, 2] == pytest.approx(2.03)
    assert d[0, 1] == pytest.approx(2.0)


@pytest.mark.parametrize("times", [1, 2])
def test_compiled_shrink_gives_the_numpy_shrink_exactly(times):
    """downsample_frame's one compiled call (tracking.frontend_numba.shrink_frame) against its NumPy steps, on a
    float32 camera frame with holes and edges: the same float64 depth and colour, bit for bit."""
    if not numba_available():
        pytest.skip("numba not installed")
    rng = np.random.default_rng(5)
    rgb = rng.random((49, 67, 3)).astype(np.float32)
    depth = (1.0 + rng.random((49, 67)) * 0.02).astype(np.float32)
    depth[rng.random((49, 67)) < 0.03] = 0.0  # holes
    depth[:, 30:] += 0.5  # an edge
    k = Intrinsics(fx=40.0, fy=40.0, cx=33.0, cy=24.0, width=67, height=49)
    d_np, c_np, k_np = downsample_frame(depth, rgb, k, times, FrontendConfig(backend="numpy"))
    d_nb, c_nb, k_nb = downsample_frame(depth, rgb, k, times, FrontendConfig(backend="numba"))
    assert d_nb.dtype == c_nb.dtype == np.float64 and k_nb == k_np
    np.testing.assert_array_equal(c_nb, c_np)
    np.testing.assert_allclose(d_nb, d_np, rtol=1e-15, atol=0)  # half_depth's mean: the kernels' summation order
    assert ((d_nb > 0) == (d_np > 0)).all() and 0.2 < (d_nb > 0).mean() < 0.95


def test_compiled_live_frame_gives_the_numpy_points_and_refuses_the_same_frames():
    """prepare_live's one compiled call (tracking.frontend_numba.live_frame) against its NumPy steps: the same points,
    validity and intensity on every level, and the same errors for NaN depth or colour."""
    if not numba_available():
        pytest.skip("numba not installed")
    rng = np.random.default_rng(8)
    k = Intrinsics(fx=60.0, fy=60.0, cx=39.5, cy=29.5, width=80, height=60)
    depth = (1.0 + rng.random((60, 80)) * 0.03).astype(np.float32)
    depth[rng.random((60, 80)) < 0.05] = 0.0
    depth[:, 50:] += 3.5  # beyond depth_max 4 m: dropped
    rgb = rng.random((60, 80, 3)).astype(np.float32)
    fast = prepare_live(depth, k, FrontendConfig(backend="numba"), rgb)
    ref = prepare_live(depth, k, FrontendConfig(backend="numpy"), rgb)
    for a, b, va, vb in zip(fast.points, ref.points, fast.valid, ref.valid, strict=True):
        np.testing.assert_array_equal(va, vb)
        np.testing.assert_allclose(a[va], b[vb], rtol=1e-12, atol=0)
        assert 0.2 < va.mean() < 0.9
    np.testing.assert_allclose(fast.intensity, ref.intensity, rtol=1e-12, atol=0)
    assert prepare_live(depth, k, FrontendConfig(backend="numba")).intensity is None
    for backend in ("numba", "numpy"):
        bad = depth.copy()
        bad[5, 5] = np.nan
        with pytest.raises(FrameError, match="depth has NaN"):
            prepare_live(bad, k, FrontendConfig(backend=backend), rgb)
        bad = rgb.copy()
        bad[1, 1, 2] = np.inf  # a pixel no level samples (stride 2 on the finest)
        with pytest.raises(FrameError, match="rgb has NaN"):
            prepare_live(depth, k, FrontendConfig(backend=backend), bad)
