"""Per-frame exposure: the fit recovers a known gain, refuses what it cannot judge, and the engine keeps its map
in the first frame's exposure when a camera's auto-exposure changes the colours of later frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.eval.evaluate import evaluate
from semantic_gs_slam.io import exposure as exposure
from semantic_gs_slam.slam import SLAM


def _scene(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    render = torch.rand(40, 60, 3, generator=g) * 0.8 + 0.1
    sil = torch.ones(40, 60)
    depth = torch.full((40, 60), 2.0)
    return render, sil, depth


def test_fit_recovers_a_per_channel_gain_and_round_trips():
    render, sil, depth = _scene()
    gain = torch.tensor([1.3, 0.9, 0.75])
    live = (render * gain).clamp(0, 1)
    e = exposure.fit(render, sil, live, depth)
    assert e.shape == (2, 3)
    torch.testing.assert_close(e[0], gain, atol=0.02, rtol=0)
    assert torch.all(e[1] == 0)
    back = exposure.to_frame(exposure.to_map(live, e), e)
    assert float((back - live).abs().max()) < 0.03


def test_fit_uses_only_what_the_map_covers_and_the_frame_measured():
    render, sil, depth = _scene(1)
    live = render * 1.2
    sil[:, :30] = 0.2  # the map does not cover the left half ...
    live[:, :30] = 1.0  # ... where the frame sees something bright the map has not got yet
    depth[:5] = 0.0  # no depth: not used either
    live[:5] = 0.0
    e = exposure.fit(render, sil, live.clamp(0, 1), depth)
    torch.testing.assert_close(e[0], torch.full((3,), 1.2), atol=0.03, rtol=0)


def test_fit_returns_the_identity_when_it_cannot_judge_and_clamps_wild_gains():
    render, sil, depth = _scene(2)
    none = exposure.fit(render, torch.zeros_like(sil), render * 1.5, depth)  # nothing covered
    assert torch.equal(none, exposure.identity())
    few = torch.zeros_like(sil)
    few[0, :10] = 1.0
    assert torch.equal(exposure.fit(render, few, render * 1.5, depth, min_pixels=500), exposure.identity())
    wild = exposure.fit(render, sil, torch.zeros_like(render), depth)  # a black frame is no exposure change
    assert float(wild[0].min()) == pytest.approx(0.5)


def _run(auto_exposure: bool, compensate: bool, odometry: bool = False, with_odometry: bool = False
         ) -> tuple[SLAM, list]:
    """The synthetic home (orbit), the camera's auto-exposure brightening frames 6.. by 30 % in red."""
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

    k = default_intrinsics(96, 54)
    ren = HomeRenderer(0)
    poses = trajectory(10, span_deg=20.0)
    cfg = SlamConfig(intrinsics=k, threads=1, tracking=TrackingConfig(use_gt_pose=True),
                     mapping=MappingConfig(first_frame_iters=30, iters=6, keyframe_every=2,
                                           exposure_compensation=compensate,
                                           exposure_with_odometry=with_odometry))
    eng = SLAM(cfg)
    frames = []
    for i, p in enumerate(poses):
        rgb, depth, _ = ren.render(p, k)
        rgb, depth = rgb.astype(np.float32), depth.astype(np.float32)  # as a dataset gives them
        if auto_exposure and i >= 6:
            rgb = np.clip(rgb * np.array([1.3, 1.0, 1.0], np.float32), 0, 1)
        frames.append((rgb, depth, p))
        eng.add_frame(rgb, depth, None, float(i), p, odom_c2w=p if odometry else None)
    return eng, frames


class _Frames:
    """The minimal dataset evaluate() reads: indexable frames with rgb, depth, semantics, gt_c2w."""

    def __init__(self, frames):
        from semantic_gs_slam.io.datasets import Frame

        self.f = [Frame(i, float(i), rgb, depth, None, p) for i, (rgb, depth, p) in enumerate(frames)]

    def __getitem__(self, i):
        return self.f[i]


@pytest.mark.slow
def test_the_map_keeps_the_first_frames_exposure_and_renders_in_each_frames():
    eng, frames = _run(auto_exposure=True, compensate=True)
    gains = torch.stack(eng.exposures)[:, 0].numpy()  # [T, 3]
    assert np.allclose(gains[:6], 1.0, atol=0.03), gains[:6]
    assert np.allclose(gains[7:, 0], 1.3, atol=0.08) and np.allclose(gains[7:, 1:], 1.0, atol=0.05), gains[7:]
    # the map's red stayed in the first frames' exposure: rendered at a late frame, without the frame's gain, it
    # matches the frame's red divided by 1.3
    out = eng.render_view(frames[9][2])
    m = (out.silhouette > 0.95) & (torch.as_tensor(frames[9][1]) > 0)
    red_map = float(out.rgb[..., 0][m].mean())
    red_frame = float(torch.as_tensor(frames[9][0])[..., 0][m].mean())
    assert red_map == pytest.approx(red_frame / 1.3, rel=0.06)
    # evaluation renders each frame in its own exposure; without compensation the map is a blend of both
    res_on = evaluate(eng, _Frames(frames), list(range(10)))
    off, _ = _run(auto_exposure=True, compensate=False)
    res_off = evaluate(off, _Frames(frames), list(range(10)))
    assert res_on["psnr"] > res_off["psnr"] + 1.0, (res_on["psnr"], res_off["psnr"])


def test_a_camera_without_auto_exposure_is_left_alone_and_the_exposures_survive_a_checkpoint(tmp_path):
    eng, _ = _run(auto_exposure=False, compensate=True)
    gains = torch.stack(eng.exposures)[:, 0].numpy()
    assert np.allclose(gains, 1.0, atol=0.03), gains
    eng.checkpoint(str(tmp_path / "ck"))
    back = SLAM.resume(str(tmp_path / "ck"))
    assert len(back.exposures) == len(eng.exposures)
    assert torch.allclose(torch.stack(back.exposures), torch.stack(eng.exposures))
    off = SlamConfig.from_dict({**eng.cfg.to_dict(), "mapping": {**eng.cfg.to_dict()["mapping"],
                                                                 "exposure_compensation": False}})
    assert SLAM(off).exposure_of(0) is None


@pytest.mark.slow
def test_frames_with_odometry_are_left_alone_unless_asked():
    robot, _ = _run(auto_exposure=True, compensate=True, odometry=True)  # a robot's stream: off by default
    assert torch.equal(torch.stack(robot.exposures)[:, 0], torch.ones(10, 3))
    asked, _ = _run(auto_exposure=True, compensate=True, odometry=True, with_odometry=True)
    assert float(torch.stack(asked.exposures)[9, 0, 0]) == pytest.approx(1.3, abs=0.08)


def test_frames_between_keyframes_take_the_blend_of_the_fitted_exposures_around_them(tmp_path):
    """Keyframes only (densify_every_frame off, as the realtime profile): the exposure brightens red by 4 % a frame;
    a frame between keyframes reads the blend of theirs (not the last keyframe's), and the fits survive a checkpoint."""
    from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

    k = default_intrinsics(96, 54)
    ren = HomeRenderer(0)
    poses = trajectory(10, span_deg=20.0)
    cfg = SlamConfig(intrinsics=k, threads=1, tracking=TrackingConfig(use_gt_pose=True),
                     mapping=MappingConfig(first_frame_iters=30, iters=6, keyframe_every=4,
                                           densify_every_frame=False))
    eng = SLAM(cfg)
    for i, p in enumerate(poses):
        rgb, depth, _ = ren.render(p, k)
        rgb = np.clip(rgb.astype(np.float32) * np.array([1.0 + 0.04 * i, 1.0, 1.0], np.float32), 0, 1)
        eng.add_frame(rgb, depth.astype(np.float32), None, float(i), p)
    assert eng.exposure_fitted == [i % 4 == 0 for i in range(10)]
    red = [float(eng.exposure_of(i)[0, 0]) for i in range(10)]
    assert red[4] == pytest.approx(1.16, abs=0.05) and red[8] == pytest.approx(1.32, abs=0.06), red
    assert red[6] == pytest.approx((red[4] + red[8]) / 2, abs=1e-5) and red[6] == pytest.approx(1.24, abs=0.05)
    assert red[9] == red[8]  # past the last fitted frame: its exposure
    eng.checkpoint(str(tmp_path / "ck"))
    back = SLAM.resume(str(tmp_path / "ck"))
    assert back.exposure_fitted == eng.exposure_fitted
    assert float(back.exposure_of(6)[0, 0]) == pytest.approx(red[6], abs=1e-6)
