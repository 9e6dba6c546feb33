"""Lost -> recovered on the shared 7-Scenes kitchen (skipped when the sequence is not here), keyframe front end:
a 60-frame gap and a kidnapped camera (frames from earlier in the sequence) are relocalised within a few frames,
confirmed before mapping resumes, and tracked as well as before; a view never seen stays lost (no false pose); frames
lost on ground no keyframe saw are re-posed in the map once it takes the camera back, or, when it does not, mapping
resumes on their own track."""

from __future__ import annotations

import logging
import os

import numpy as np
import pytest

from semantic_gs_slam.config import LoopConfig, MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.io.datasets import load_dataset
from semantic_gs_slam.io.degrade import DegradedDataset, drop_frames
from semantic_gs_slam.slam import SLAM


def _shared_sequence() -> str:
    """The shared sequence in the nearest folder above this file that has ``shared/data`` (a checkout or a worktree
    of one), or ""."""
    here = os.path.dirname(os.path.abspath(__file__))
    while True:
        cand = os.path.join(here, "shared", "data", "7scenes-redkitchen-0-499")
        if os.path.isdir(cand):
            return cand
        up = os.path.dirname(here)
        if up == here:
            return ""
        here = up


SHARED_7SCENES = _shared_sequence()

# a minute of mapping on an idle machine; pytest's 300 s default cut it at load 15 (the checks are not about time)
pytestmark = [pytest.mark.skipif(not SHARED_7SCENES, reason="the shared 7-Scenes sequence is not here"),
              pytest.mark.slow, pytest.mark.timeout(900)]

# frame numbers of the sequence fed in this order (stride 2): a stretch, a 60-frame gap, a jump back to ground seen
# at the start (kidnapped), then a part of the kitchen none of the earlier frames saw
PARTS = {"start": range(0, 100, 2), "gap": range(158, 190, 2), "kidnapped": range(20, 52, 2),
         "unseen": range(300, 316, 2)}


def _run(parts: dict[str, range | list[int]] = PARTS, depth_noise: float = 0.0, recorded_times: bool = False,
         threaded: bool = False, **tracking):
    """One run through every part (10 s of mapping on 2 cores): the one test below checks all of it. ``depth_noise``:
    times a Kinect's noise added to the depth; ``recorded_times``: each frame stamped with its time in the recording
    (else one second per frame fed); ``threaded``: map in the engine's thread (SlamConfig.threaded; drained at the
    end); ``tracking``: TrackingConfig fields."""
    ds = DegradedDataset(load_dataset(SHARED_7SCENES, size=(320, 240)), depth_noise=depth_noise)
    order = [i for part in parts.values() for i in part]
    cfg = SlamConfig(intrinsics=ds.intrinsics, threads=2, tracking=TrackingConfig(frontend="keyframe", **tracking),
                     mapping=MappingConfig(first_frame_iters=5, iters=1, densify_every_frame=False),
                     loop=LoopConfig(enabled=False), threaded=threaded)
    eng = SLAM(cfg, initial_c2w=ds[order[0]].gt_c2w)  # the map frame: the first frame fed
    gts = []
    for n, i in enumerate(order):
        f = ds[i]
        gts.append(f.gt_c2w)
        eng.add_frame(f.rgb, f.depth, None, f.timestamp if recorded_times else float(n))
    eng.finish()
    err = np.array([pose_error(p, g)[0] for p, g in zip(eng.poses, gts, strict=True)])
    starts = np.cumsum([0] + [len(p) for p in parts.values()])
    return eng, err, dict(zip(parts, zip(starts[:-1], starts[1:], strict=True), strict=False))


def _recovery(eng: SLAM, first: int, end: int) -> tuple[int, int]:
    found = [r for r in eng.stats()["recoveries"] if first <= r[0] < end]
    assert found, (eng.stats(), [(lg.index, lg.pose_source) for lg in eng.logs[first:end]])
    return found[0][0], found[0][1]


# the error allowed after the recovery: no larger than before the camera was lost, or than the same frames' error when
# tracked without the gap, whichever is larger. A relocalisation lands in the map, so its error is at least the map's
# own error where the camera comes back: after the gap that is where the map's drift at the last frame before it
# (3.7 cm there) put 1.5-2 m away (measured: 4.9-5.7 cm after the recovery, 4.9-6.3 cm without the gap).
# The kidnapped camera lands on keyframes of its own ground (0.5-1.6 cm, before: up to 3.7 cm).
UNBROKEN = {"start": range(0, 158, 2), "gap": range(158, 190, 2)}  # the first two parts without the gap


def test_a_lost_camera_is_relocalised_within_a_few_frames_and_a_view_never_seen_stays_lost():
    run = _run()
    unbroken = _run(UNBROKEN)
    a, b = unbroken[2]["gap"]
    without_gap = {"gap": unbroken[1][a:b].max(), "kidnapped": 0.0}
    for part in ("gap", "kidnapped"):
        _check_relocalised(run, part, without_gap[part])
    _check_stays_lost(run)


def _check_relocalised(run, part: str, without_gap: float) -> None:
    """A gap or a kidnapping: relocalised within a few frames, not mapped until confirmed, tracking as before."""
    eng, err, span = run
    a, b = span[part]
    s0, s1 = span["start"]
    assert not [i for i in eng.lost_frames if i < s1]  # the first stretch tracks throughout
    lost_at, back_at = _recovery(eng, a, b)
    assert lost_at == a and back_at - lost_at <= 4, eng.stats()
    sources = [eng.logs[i].pose_source for i in range(a, back_at + 1)]
    assert "relocalised" in sources and sources[-1] == "recovered"
    # not mapped until confirmed: no keyframe between the first lost frame and the recovery
    assert not any(eng.logs[i].keyframe for i in range(a, back_at))
    before = err[s0:s1].max()
    after = err[back_at:b]
    assert after.max() <= max(before, without_gap), (part, before, without_gap, after)


def _check_stays_lost(run) -> None:
    """A view no earlier frame saw: every frame reported lost, none mapped, no false pose."""
    eng, err, span = run
    a, b = span["unseen"]
    assert all(eng.logs[i].pose_source == "lost" for i in range(a, b)), \
        [(lg.index, lg.pose_source, round(float(err[lg.index]), 3)) for lg in eng.logs[a:b]]
    assert list(range(a, b)) == [i for i in eng.lost_frames if i >= a]
    assert not any(eng.logs[i].keyframe for i in range(a, b))


def test_a_fast_move_is_tracked_again_against_the_previous_frame(caplog):
    """Every 10th frame (3 Hz: up to 14 cm and 7 degrees a step): a frame the reference loses is tracked again, with
    more steps, against the frame before it, which becomes the reference; no frame is lost."""
    parts = {"fast": range(0, 500, 10)}
    with caplog.at_level(logging.INFO, logger="semantic_gs_slam"):
        eng, err, _ = _run(parts)
    retried = [r.getMessage() for r in caplog.records if "the new reference" in r.getMessage()]
    assert retried, "no frame needed the previous frame: the sequence no longer tests it"
    assert eng.lost_frames == [], (eng.lost_frames, retried)
    assert err.max() < 0.25, err.round(3)


def test_a_camera_three_and_four_times_noisier_than_a_kinect_is_tracked_at_its_own_noise():
    """Three and four times a Kinect's depth noise added (frames 0-249, every 2nd): the keyframes' depth reads as
    noisy, is smoothed before it becomes a reference, and the trust test judges frames at the camera's noise (its
    scale and association gate): no frame is lost. Judged at a Kinect's noise against raw references (smoothing and
    the trust scaling off), the same frames with three times the noise were lost from frame 90 on: the last run
    below shows it still is, so this test can fail."""
    parts = {"noisy": range(0, 250, 2)}
    for noise in (3.0, 4.0):
        eng, err, _ = _run(parts, depth_noise=noise)
        assert eng.stats()["noisy_references"] > 0 and eng.stats()["reference_roughness"] > 0.0015, eng.stats()
        assert eng.lost_frames == [], (noise, eng.lost_frames)
        assert err.max() < 0.15, (noise, err.round(3))
    raw, raw_err, _ = _run(parts, depth_noise=3.0, frontend_noisy_roughness=0.0, frontend_trust_z2_per_roughness=0.0)
    assert raw.stats()["noisy_references"] == 0
    assert len(raw.lost_frames) > 10, (raw.lost_frames, raw_err.round(3))


def test_frames_lost_on_ground_no_keyframe_saw_are_re_posed_in_the_map_when_it_takes_the_camera_back():
    """Every 2nd frame of 0-149, then a 90-frame gap onto ground none of them saw (240-319): the camera is lost for
    about 19 frames until it sees mapped ground again. Meanwhile the lost frames are tracked among themselves (a
    lost segment, not mapped), and once recovered the segment is moved into the map's frame and its views are kept
    for the refinement, which maps them. Measured: the lost
    frames' error 8.8 cm at most against 75 cm when they keep the last trusted pose (tracking.lost_segment off: the
    second run below, so this test can fail)."""
    parts = {"start": range(0, 150, 2), "gap": range(240, 320, 2)}
    eng, err, span = _run(parts, lost_resume_after=0)  # stay lost until relocalised (the frames are fed as a stream)
    a, b = span["gap"]
    lost_at, back_at = _recovery(eng, a, b)
    lost = [i for i in eng.lost_frames if lost_at <= i < back_at]
    assert lost_at == a and len(lost) >= 10, eng.stats()
    assert not any(eng.logs[i].keyframe for i in range(lost_at, back_at))  # lost frames are still not mapped
    assert eng.stats()["rejoined_frames"] >= len(lost) - 2, eng.stats()  # all but the relocalised frame(s)
    assert err[lost].max() < 0.15, err[lost].round(3)
    assert err[back_at:b].max() < 0.15, err[back_at:b].round(3)
    # the ground seen while lost is mapped at the refinement: the segment's views joined the backlog, at their poses
    views = [v[0] for v in eng.backlog if lost_at <= v[0] < back_at]
    assert views, [v[0] for v in eng.backlog]
    eng.refine(1)
    assert eng.caught_up >= len(views) and not eng.backlog
    frozen, frozen_err, _ = _run(parts, lost_segment=False, lost_resume_after=0)
    assert not [v[0] for v in frozen.backlog if lost_at <= v[0] < back_at]
    assert frozen.stats()["rejoined_frames"] == 0
    assert frozen_err[lost].max() > 0.3, frozen_err[lost].round(3)


def test_a_camera_lost_on_ground_no_keyframe_saw_resumes_mapping_on_its_own_track_unless_time_jumped():
    """Every 2nd frame of 0-99, then of 350-429, ground none of them saw and the map never takes the camera back.
    Fed as a steady stream (one second per frame), the lost frames' guess is a pose: after
    tracking.lost_resume_after lost frames whose segment tracks, mapping resumes on the segment's own track (its
    frames keep their poses; the new ground is mapped). Fed with the recording's times, the 8.4-s jump makes the
    first lost frame's guess no pose: the camera stays lost and nothing is mapped. Here the jump is a kidnapping, so
    the resumed track is anchored 1.7 m off (the guess); its shape is the camera's: measured 1.9 cm RMSE aligned by
    itself."""
    from semantic_gs_slam.geometry import umeyama_rigid

    parts = {"start": range(0, 100, 2), "unseen": range(350, 430, 2)}
    after = 12
    eng, err, span = _run(parts, lost_resume_after=after)
    a, b = span["unseen"]
    st = eng.stats()
    assert not [i for i in eng.lost_frames if i < a]
    assert st["resumed"] == st["recoveries"] and len(st["resumed"]) == 1, st
    lost_at, back_at = st["resumed"][0]
    assert lost_at == a and back_at - lost_at + 1 <= after + 4, st  # the segment tracks: as soon as allowed
    assert eng.logs[back_at].pose_source == "resumed" and eng.logs[back_at].keyframe
    assert all(eng.logs[i].pose_source == "tracking" for i in range(back_at + 1, b)), \
        [lg.pose_source for lg in eng.logs[back_at:b]]
    assert sum(eng.logs[i].keyframe for i in range(back_at, b)) >= 3  # the new ground is mapped
    ds = load_dataset(SHARED_7SCENES, size=(320, 240))
    est = np.stack([p[:3, 3] for p in eng.poses[a:b]])
    gt = np.stack([ds[i].gt_c2w[:3, 3] for i in parts["unseen"]])
    t = umeyama_rigid(est, gt)
    shape = np.linalg.norm(est @ t[:3, :3].T + t[:3, 3] - gt, axis=1)
    assert np.sqrt((shape ** 2).mean()) < 0.05, shape.round(3)  # the lost and resumed frames move as the camera
    jumped, _, _ = _run(parts, recorded_times=True, lost_resume_after=after)
    assert jumped.stats()["resumed"] == [] and jumped.stats()["recoveries"] == [], jumped.stats()
    assert all(jumped.logs[i].pose_source == "lost" for i in range(a, b))
    assert not any(jumped.logs[i].keyframe for i in range(a, b))
    assert len(jumped.map) < len(eng.map)


@pytest.mark.parametrize("threaded", [False, True], ids=["inline", "threaded"])
def test_a_resumed_track_anchored_at_a_wrong_guess_moves_into_the_map_when_the_camera_sees_mapped_ground(threaded):
    """Every 2nd frame of 150-249, then of 390-449 (ground none of them saw) and 450-499 (back in view of the
    mapped kitchen, 1 m away), as one steady stream: a kidnapping the frame times do not tell. Mapping resumes on
    the lost frames' own track, anchored at the first one's guess (1.1 m off); once a frame of that track is
    relocalised twice against the keyframes from before the loss, every frame since, the keyframes among them and
    the Gaussians they made move into the map's frame (measured: the resumed frames 3.6-5.7 cm off, the frames back
    in view 4.1-8.4 cm; without it 106-111 cm). Threaded, the mapping thread finishes its jobs before anything
    moves."""
    parts = {"start": range(150, 250, 2), "unseen": range(390, 450, 2), "back": range(450, 500, 2)}
    eng, err, span = _run(parts, threaded=threaded, lost_resume_after=12)
    st = eng.stats()
    a, _ = span["unseen"]
    assert len(st["resumed"]) == 1 and st["resumed"][0][0] == a, st
    assert len(st["reanchored"]) == 1, st
    first, at, moved_cm, _ = st["reanchored"][0]
    assert first == a and at >= span["back"][0] and moved_cm > 50, st
    assert err[a:].max() < 0.15, (err[a:] * 100).round(1)  # the whole resumed stretch, not only the frames after
    assert err[:a].max() < 0.06, (err[:a] * 100).round(1)  # the frames before the loss stay (measured: 3.8 cm)
    for kf in eng.keyframes:  # the keyframes moved with their frames
        np.testing.assert_allclose(kf.c2w.double().cpu().numpy(), eng.poses[kf.index], atol=1e-5)
    slot = next(n for n, kf in enumerate(eng.keyframes) if kf.index >= a)
    across = [e for e in eng.edges if e.i < slot <= e.j]
    assert across  # the pose graph's edges across the loss hold the corrected relative poses, not the guessed anchor
    for e in across:
        np.testing.assert_allclose(e.rel, np.linalg.inv(eng.poses[eng.keyframes[e.i].index])
                                   @ eng.poses[eng.keyframes[e.j].index], atol=1e-5)
    # the Gaussians a keyframe of the resumed track made lie on its depth seen from its (moved) pose
    kf = next(k for k in eng.keyframes if a <= k.index < at)
    mine = (eng.map.timestep == kf.index).nonzero().squeeze(1)
    assert len(mine) > 50
    means = eng.map.params["means3D"][mine].detach().double().cpu().numpy()[::max(1, len(mine) // 400)]
    depth = kf.depth.double().cpu().numpy()
    k = eng.k
    v, u = np.nonzero(depth > 0)
    v, u = v[::16], u[::16]
    z = depth[v, u]
    pts = np.stack([(u - k.cx) * z / k.fx, (v - k.cy) * z / k.fy, z], -1) @ eng.poses[kf.index][:3, :3].T + \
        eng.poses[kf.index][:3, 3]
    near = np.sqrt(((means[:, None, :] - pts[None]) ** 2).sum(-1)).min(1)
    assert np.median(near) < 0.05, np.percentile(near, [50, 90]).round(3)
    if threaded:
        return
    kept, kept_err, _ = _run(parts, lost_resume_after=12, reanchor_every=0)
    assert kept.stats()["reanchored"] == [] and kept_err[span["back"][0]:].min() > 0.5  # the wrong anchor stays


def test_a_guess_scaled_by_the_frame_times_is_nearer_the_camera_when_frames_are_dropped():
    """The recording's own poses, frames 0-249 with three in four dropped at random (steps of 1-15 frames): the
    constant-velocity guess from the two frames before, scaled by their times (tracking.velocity_max_scale 3), lands
    nearer the next frame's pose than one step per frame (measured: 1.09 against 2.21 cm on average)."""
    from semantic_gs_slam.geometry import velocity_guess

    ds = load_dataset(SHARED_7SCENES)
    order = drop_frames(range(0, 250), 0.75)
    scaled, one_step = [], []
    for a, b, c in zip(order, order[1:], order[2:], strict=False):
        dt_prev, dt = ds.timestamps[b] - ds.timestamps[a], ds.timestamps[c] - ds.timestamps[b]
        scaled.append(pose_error(velocity_guess(ds.poses[a], ds.poses[b], dt_prev, dt, 3.0), ds.poses[c])[0])
        one_step.append(pose_error(velocity_guess(ds.poses[a], ds.poses[b], dt_prev, dt, 0.0), ds.poses[c])[0])
    assert len(set(np.diff(order).tolist())) >= 5  # uneven steps
    assert np.mean(scaled) < 0.7 * np.mean(one_step), (np.mean(scaled), np.mean(one_step))


def test_frames_dropped_unevenly_are_tracked_and_a_loss_is_recovered_on_the_next_frame():
    """Frames 250-499, three in four dropped at random (65 left, steps of up to 15 frames on the kitchen's fastest
    turn), stamped with their recorded times: at most one frame is lost, it is relocalised at once and confirmed on
    the next frame, and no pose is more than 15 cm off (measured: frame 466 lost and relocalised, 10.2 cm at most)."""
    order = drop_frames(range(250, 500), 0.75)
    eng, err, _ = _run({"dropped": order}, recorded_times=True)
    assert len(eng.lost_frames) <= 1, [order[i] for i in eng.lost_frames]
    assert all(back - lost <= 2 for lost, back in eng.stats()["recoveries"]), eng.stats()["recoveries"]
    assert err.max() < 0.15, err.round(3)
