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
