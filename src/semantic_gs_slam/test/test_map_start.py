"""Starting on a saved map (``SLAM.from_map``) on the synthetic home: the first frame is relocalised in the saved
map's frame (not fixed to the identity or to the pose given with it), frames are mapped only once the pose is
confirmed, mapping continues into the same Gaussians; a view the map never saw stays lost; bad maps are typed
errors; a checkpoint taken before the relocalisation resumes relocalising."""

from __future__ import annotations

import logging
import os
from dataclasses import replace

import numpy as np
import pytest

from semantic_gs_slam.config import LoopConfig, MappingConfig, SlamConfig
from semantic_gs_slam.errors import FrameError, MapFormatError
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.mapping.gaussian_map import load_params, map_views
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

K = default_intrinsics(128, 72)


def _cfg() -> SlamConfig:
    return SlamConfig(intrinsics=K, threads=1, mapping=MappingConfig(first_frame_iters=10, iters=3),
                      loop=LoopConfig(enabled=False))


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    """The first run: 6 frames of an orbit (30 degrees), its map frame the world's; the map saved."""
    ren = HomeRenderer(0)
    poses = trajectory(13, span_deg=60.0)  # the first run flies 0-5; the restart starts at 3 and goes on to 12
    eng = SLAM(_cfg(), initial_c2w=poses[0])
    for i in range(6):
        rgb, depth, sem = ren.render(poses[i], K)
        eng.add_frame(rgb, depth, sem, float(i))
    out = tmp_path_factory.mktemp("map")
    eng.save(str(out), ply=False)
    return str(out), eng, poses, ren


def test_a_restart_is_relocalised_in_the_saved_map_and_maps_into_it(saved, caplog):
    out, first, poses, ren = saved
    eng = SLAM.from_map(out, _cfg())
    n0 = len(eng.map)
    assert n0 == len(first.map) and not eng.localised
    assert eng.classes == {i: c for i, c in first.classes.items() if i > 0}
    with caplog.at_level(logging.WARNING, logger="semantic_gs_slam"):
        for n, i in enumerate(range(3, 13)):
            rgb, depth, sem = ren.render(poses[i], K)
            # the pose given with the first frame (here: the identity, as a robot's fresh odometry) fixes nothing
            eng.add_frame(rgb, depth, sem, 100.0 + n, gt_c2w=np.eye(4), odom_c2w=np.eye(4) if n == 0 else None)
    sources = [lg.pose_source for lg in eng.logs]
    # tracking.relocalise_confirm (2): the relocalised frame, then one more tracked against the map
    assert sources[:2] == ["relocalised", "recovered"], sources
    assert "relocalised in the saved map" in caplog.text
    # not mapped until confirmed: the map is the saved one until the recovered frame, which is a keyframe
    assert eng.logs[0].n_gaussians == n0 and not eng.logs[0].keyframe and eng.lost_frames == [0]
    assert eng.logs[1].keyframe and eng.localised and eng.stats()["recoveries"] == [[0, 1]]
    assert set(sources[2:]) == {"tracking"}
    # in the saved map's frame (the world's here): the first frame within 2 cm / 1 degree, the rest as tracking
    err = [pose_error(p, poses[i]) for p, i in zip(eng.poses, range(3, 13), strict=True)]
    assert err[0][0] < 0.02 and err[0][1] < 1.0, err[0]
    assert max(e[0] for e in err) < 0.03, err
    assert len(eng.map) > n0  # frames 6-12 saw more of the room: mapping continued into the same Gaussians
    # saved again: the views it started from, then its own keyframes (what the next restart relocalises against)
    again = os.path.join(out, "again")
    eng.save(again, ply=False)
    views = map_views(load_params(os.path.join(again, "params.npz")))
    assert len(views) == len(eng.start_views) + len(eng.keyframes)
    np.testing.assert_allclose(views[-1], eng.poses[eng.keyframes[-1].index])


def test_a_view_the_saved_map_never_saw_stays_lost(saved, caplog):
    out, first, poses, ren = saved
    eng = SLAM.from_map(out, _cfg())
    n0 = len(eng.map)
    back = poses[2] @ np.diag([-1.0, 1.0, -1.0, 1.0])  # the camera turned round: the wall behind it, never mapped
    with caplog.at_level(logging.WARNING, logger="semantic_gs_slam"):
        for n in range(3):
            rgb, depth, sem = ren.render(back, K)
            pose = eng.add_frame(rgb, depth, sem, float(n))
            np.testing.assert_allclose(pose, first.poses[-1], atol=1e-5)  # the prior: where the saved run ended
    assert [lg.pose_source for lg in eng.logs] == ["lost"] * 3
    assert eng.lost_frames == [0, 1, 2] and not eng.localised and not eng.keyframes
    assert len(eng.map) == n0 and "not relocalised in the saved map yet" in caplog.text


def test_a_checkpoint_before_the_relocalisation_resumes_relocalising(saved, tmp_path):
    out, first, poses, ren = saved
    eng = SLAM.from_map(out, _cfg())
    rgb, depth, sem = ren.render(poses[2] @ np.diag([-1.0, 1.0, -1.0, 1.0]), K)
    eng.add_frame(rgb, depth, sem, 0.0)  # lost
    eng.checkpoint(str(tmp_path / "ck"))
    back = SLAM.resume(str(tmp_path / "ck"))
    assert not back.localised and len(back.start_views) == len(eng.start_views)
    rgb, depth, sem = ren.render(poses[4], K)
    back.add_frame(rgb, depth, sem, 1.0)
    assert back.logs[-1].pose_source == "relocalised"
    assert pose_error(back.poses[-1], poses[4])[0] < 0.02


def test_bad_saved_maps_are_typed_errors(saved, tmp_path):
    out, first, poses, ren = saved
    with pytest.raises(MapFormatError, match="not a folder"):
        SLAM.from_map(str(tmp_path / "nowhere"), _cfg())
    (tmp_path / "empty").mkdir()
    with pytest.raises(MapFormatError, match="map file not found"):
        SLAM.from_map(str(tmp_path / "empty"), _cfg())
    (tmp_path / "corrupt").mkdir()
    (tmp_path / "corrupt" / "params.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(MapFormatError, match="not a readable .npz"):
        SLAM.from_map(str(tmp_path / "corrupt"), _cfg())
    (tmp_path / "noposes").mkdir()
    np.savez(tmp_path / "noposes" / "params.npz", means3D=np.zeros((3, 3), np.float32))
    with pytest.raises(MapFormatError, match="no camera poses to relocalise against"):
        SLAM.from_map(str(tmp_path / "noposes"), _cfg())
    # a map without poses starts from views given explicitly; views must be rigid poses
    assert len(SLAM.from_map(str(tmp_path / "noposes"), _cfg(), views=[poses[0]]).start_views) == 1
    with pytest.raises(FrameError, match="views\\[0\\]"):
        SLAM.from_map(out, _cfg(), views=[np.ones((4, 4))])


def test_a_wide_camera_is_relocalised_on_subsampled_images_and_refined_at_full_size(saved, monkeypatch):
    """A 256x144 camera on the map a 128x72 one saved (the camera may change), relocalised at 128x72."""
    from semantic_gs_slam.tracking import map_start

    out, first, poses, ren = saved
    monkeypatch.setattr(map_start, "MAX_START_WIDTH", 128)  # every 2nd pixel of every 2nd row
    wide = default_intrinsics(256, 144)
    eng = SLAM.from_map(out, replace(_cfg(), intrinsics=wide))
    assert eng._ms_step == 2 and (eng._ms_k.width, eng._ms_k.height) == (128, 72)
    for n, i in enumerate((3, 4)):
        rgb, depth, sem = ren.render(poses[i], wide)
        eng.add_frame(rgb, depth, sem, float(n))
    assert [lg.pose_source for lg in eng.logs] == ["relocalised", "recovered"]
    assert all(pose_error(p, poses[i])[0] < 0.02 for p, i in zip(eng.poses, (3, 4), strict=True))
