"""A lost track is detected and reported (never mapped), and tracking picks up again when the view returns."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from semantic_gs_slam.config import MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.loop.posegraph import pose_exp
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory


@pytest.fixture(scope="module")
def views():
    k = default_intrinsics(120, 68)
    ren = HomeRenderer(0)
    poses = trajectory(8, span_deg=20.0)
    # one frame from 50 cm away (the camera knocked aside for a moment): its view overlaps the map, so ICP
    # returns a pose with enough correspondences, but a wrong one
    away = pose_exp(np.array([0.0, 0.0, 0.0, 0.4, 0.3, 0.0])) @ poses[4]
    order = poses[:5] + [away] + poses[5:]
    return k, order, [ren.render(p, k) for p in order]


def _run(k, poses, frames, lost_agreement: float) -> SLAM:
    cfg = SlamConfig(intrinsics=k, threads=1, tracking=TrackingConfig(lost_agreement=lost_agreement),
                     mapping=MappingConfig(first_frame_iters=30, iters=6))
    eng = SLAM(cfg, initial_c2w=poses[0])
    for i, (rgb, depth, sem) in enumerate(frames):
        eng.add_frame(rgb, depth, sem, float(i))
    return eng


def test_a_frame_from_elsewhere_is_reported_lost_not_mapped_and_tracking_recovers(views, caplog):
    k, poses, frames = views
    with caplog.at_level(logging.WARNING, logger="semantic_gs_slam"):
        eng = _run(k, poses, frames, lost_agreement=0.25)
    lost = [lg.index for lg in eng.logs if lg.tracking_failed]
    assert lost == [5], [(lg.index, lg.track_agreement) for lg in eng.logs]
    assert eng.logs[5].track_agreement < 0.25 and eng.logs[5].pose_source == "previous"
    assert eng.logs[5].added == 0 and not eng.logs[5].keyframe  # nothing of the wrong view enters the map
    assert any("tracking lost" in r.message for r in caplog.records)
    assert min(lg.track_agreement for lg in eng.logs[1:5]) > 0.45  # ordinary frames agree with the map
    for i in (6, 7, 8):  # the view is back: tracked again, close to the truth
        assert not eng.logs[i].tracking_failed
        assert pose_error(eng.poses[i], poses[i])[0] < 0.03, i


def test_without_the_check_the_wrong_view_is_tracked_silently(views):
    k, poses, frames = views
    eng = _run(k, poses, frames, lost_agreement=0.0)
    assert not eng.logs[5].tracking_failed  # the check above is what caught it
    assert eng.logs[5].track_agreement < 0.25


def test_frames_lost_on_the_far_side_are_re_posed_when_the_camera_comes_back():
    """The keyframe front end round the synthetic home's table: every 2nd of the first 30 frames of a full orbit
    (120 frames), then from frame 60 on (the camera jumps to the far side, where no keyframe saw the table from)
    until it comes round to the start. The frames lost meanwhile are tracked among themselves and, once the map takes
    the camera back, re-posed in the map's frame (measured: 1.3 cm off at most). Keeping the last trusted pose instead
    (``tracking.lost_segment`` off: the second run, so this test can fail) leaves them metres off."""
    k = default_intrinsics(160, 120)
    poses = trajectory(120, span_deg=360.0)
    ren = HomeRenderer(0)
    order = list(range(0, 30, 2)) + list(range(60, 120, 2))
    frames = [ren.render(poses[i], k) for i in order]
    errors = {}
    for segment in (True, False):
        cfg = SlamConfig(intrinsics=k, threads=2,
                         tracking=TrackingConfig(frontend="keyframe", lost_segment=segment),
                         mapping=MappingConfig(first_frame_iters=5, iters=1, densify_every_frame=False))
        cfg.loop.enabled = False
        eng = SLAM(cfg, initial_c2w=poses[order[0]])
        for rgb, depth, _ in frames:
            eng.add_frame(rgb, depth, None)
        st = eng.stats()
        assert len(st["recoveries"]) == 1 and st["recoveries"][0][0] == 15, st  # lost at the jump, then recovered
        lost = st["lost_frames"]
        assert len(lost) >= 10 and not any(eng.logs[i].keyframe for i in lost)  # lost frames are not mapped
        err = np.array([pose_error(eng.poses[n], poses[i])[0] for n, i in enumerate(order)])
        errors[segment] = err[lost].max()
        assert st["rejoined_frames"] == (len(lost) - 1 if segment else 0), st  # all but the relocalised frame
    assert errors[True] < 0.05 and errors[False] > 1.0, errors
