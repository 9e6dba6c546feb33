"""The keyframe front end in the engine and the mapping thread: a threaded run that waits for each frame gives the
synchronous run's poses and map; finish drains; a mapping failure surfaces in the caller; a full queue drops
frames by its documented policy and says so."""

from __future__ import annotations

import threading
from dataclasses import replace

import numpy as np
import pytest

from semantic_gs_slam.config import LoopConfig, MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.errors import ConfigError, MappingError
from semantic_gs_slam.geometry import pose_error
from semantic_gs_slam.mapping.steps import spread_order
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory


@pytest.fixture(scope="module")
def views():
    k = default_intrinsics(120, 68)
    poses = trajectory(9, span_deg=16.0)
    ren = HomeRenderer(0)
    return k, poses, [ren.render(p, k) for p in poses]


def _cfg(k, threaded: bool, **kw) -> SlamConfig:
    return SlamConfig(intrinsics=k, threads=1, threaded=threaded, tracking=TrackingConfig(frontend="keyframe"),
                      mapping=MappingConfig(first_frame_iters=15, iters=3, keyframe_every=3),
                      loop=LoopConfig(enabled=False), **kw)


def _feed(eng: SLAM, frames, wait: bool = False) -> None:
    for i, (rgb, depth, sem) in enumerate(frames):
        eng.add_frame(rgb, depth, sem, float(i))
        if wait:
            eng.drain(120.0)


def test_threaded_run_waiting_for_each_frame_gives_the_synchronous_poses_and_map(views):
    k, poses, frames = views
    sync = SLAM(_cfg(k, False), initial_c2w=poses[0])
    _feed(sync, frames)
    thr = SLAM(_cfg(k, True), initial_c2w=poses[0])
    _feed(thr, frames, wait=True)
    thr.finish(120.0)
    np.testing.assert_array_equal(np.stack(thr.poses), np.stack(sync.poses))
    assert [kf.index for kf in thr.keyframes] == [kf.index for kf in sync.keyframes]
    assert len(thr.map) == len(sync.map)
    assert all(lg.map_queue == "queued" for lg in thr.logs) and all(lg.map_queue == "inline" for lg in sync.logs)
    assert [lg.added for lg in thr.logs] == [lg.added for lg in sync.logs]
    for est, gt in zip(sync.poses, poses, strict=True):  # and the front end tracks the orbit
        assert pose_error(est, gt)[0] < 0.02
    assert sync.stats()["lost_frames"] == [] and sync.stats()["recoveries"] == []


def test_the_photometric_settings_reach_the_keyframe_front_end(views):
    """``tracking.photometric_weight`` and ``icp_sigma_col`` weigh the keyframe front end's intensity term as the
    render front end's: geometry only (weight 0) tracks the orbit on other poses than the default."""
    k, poses, frames = views

    def run(**tracking):
        cfg = replace(_cfg(k, False), tracking=TrackingConfig(frontend="keyframe", **tracking))
        eng = SLAM(cfg, initial_c2w=poses[0])
        _feed(eng, frames[:4])
        return np.stack(eng.poses)

    default, geometric, wide = run(), run(photometric_weight=0.0), run(icp_sigma_col=0.5)
    assert not np.array_equal(default, geometric) and not np.array_equal(default, wide)
    for est in (geometric, wide):
        for c2w, gt in zip(est, poses, strict=False):
            assert pose_error(c2w, gt)[0] < 0.02


def test_finish_drains_every_queued_frame(views):
    k, poses, frames = views
    eng = SLAM(_cfg(k, True, queue_size=len(frames)), initial_c2w=poses[0])
    _feed(eng, frames)  # no waiting: the tracker runs ahead of the mapping thread
    eng.finish(120.0)
    assert [lg.map_queue for lg in eng.logs] == ["queued"] * len(frames)
    assert [kf.index for kf in eng.keyframes] == [lg.index for lg in eng.logs if lg.keyframe]
    assert all(lg.n_gaussians > 0 and lg.map_s > 0 for lg in eng.logs)  # every job ran and filled its log


class _FailingMap(SLAM):
    def _map_keyframe(self, idx, rgb, depth, sem):
        if idx >= 3:
            raise RuntimeError("disk full")  # a failure inside the mapping thread
        return super()._map_keyframe(idx, rgb, depth, sem)


def test_a_mapping_thread_failure_surfaces_in_the_caller(views):
    k, poses, frames = views
    eng = _FailingMap(_cfg(k, True), initial_c2w=poses[0])
    _feed(eng, frames[:4])
    with pytest.raises(MappingError, match="disk full") as err:
        eng.drain(120.0)
    assert isinstance(err.value.__cause__, RuntimeError)
    with pytest.raises(MappingError):  # and every later call says so, instead of tracking on an unmapped map
        eng.add_frame(*frames[4][:2])


class _SlowMap(SLAM):
    gate: threading.Event

    def _map_frame(self, *args):
        self.gate.wait(60.0)  # the mapping thread is held until the test has queued every frame
        super()._map_frame(*args)


def test_a_full_queue_drops_frames_and_reports_them(views):
    k, poses, frames = views
    eng = _SlowMap(_cfg(k, True, queue_size=1, queue_timeout_s=0.01), initial_c2w=poses[0])
    eng.gate = threading.Event()
    _feed(eng, frames)
    eng.gate.set()
    eng.finish(120.0)
    dropped = [lg.index for lg in eng.logs if lg.map_queue == "dropped"]
    queued = [lg.index for lg in eng.logs if lg.map_queue == "queued"]
    assert len(dropped) >= len(frames) - 2  # one job running, one waiting: the others found no room
    assert sorted(dropped + queued) == list(range(len(frames))) and eng.stats()["dropped"] == dropped
    assert {kf.index for kf in eng.keyframes} == {i for i in queued if eng.logs[i].keyframe}
    assert len(eng.poses) == len(frames)  # tracking went on for every frame


def test_threaded_needs_the_keyframe_front_end(views):
    k = views[0]
    with pytest.raises(ConfigError, match="threaded"):
        SlamConfig(intrinsics=k, threaded=True).check()
    with pytest.raises(ConfigError, match="frontend"):
        SlamConfig(intrinsics=k, tracking=TrackingConfig(frontend="orb")).check()


def _held_deferring(k, poses, **kw) -> _SlowMap:
    """A threaded engine deferring keyframes whose mapping thread is held (``gate``) until the test lets it go."""
    cfg = _cfg(k, True, queue_size=4, **kw)
    cfg.mapping.defer_keyframes = True
    eng = _SlowMap(cfg, initial_c2w=poses[0])
    eng.gate = threading.Event()
    return eng


def test_busy_mapping_defers_keyframes_and_the_next_free_frame_takes_it(views):
    k, poses, frames = views
    eng = _held_deferring(k, poses)
    _feed(eng, frames[:5])  # frame 0's map update holds the thread: frame 3, due by keyframe_every, is deferred
    assert [lg.index for lg in eng.logs if lg.keyframe] == [0]
    assert eng.stats()["deferred_keyframes"] == 2  # frames 3 and 4 (the due keyframe waits for a free thread)
    # the thread is busy: the next frame would be deferred too, so the labelling stage is not told to label it
    # (labelling every deferred frame kept a CPU engine at the labelling's pace)
    assert not eng.keyframe_expected(poses[5])
    assert eng._fe_ref_idx == 3  # the front end renewed its reference, keyframe_every frames old, without mapping
    eng.gate.set()
    eng.drain(120.0)
    assert eng.keyframe_expected(poses[5])  # the thread is free: the due keyframe is mapped next, labelled
    _feed_from(eng, frames, 5)
    eng.finish(120.0)
    kfs = [lg.index for lg in eng.logs if lg.keyframe]
    # a keyframe is never dropped (deferred, or it waits for room); another frame's label votes may be when the queue
    # is full, which depends on how fast this machine tracks against how fast it maps
    assert kfs[:2] == [0, 5] and all(lg.map_queue != "dropped" for lg in eng.logs if lg.keyframe)
    for est, gt in zip(eng.poses, poses, strict=True):  # deferring changes which frames map, not the tracking
        assert pose_error(est, gt)[0] < 0.02


def test_without_defer_a_busy_thread_still_gets_every_due_keyframe(views):
    k, poses, frames = views
    eng = _SlowMap(_cfg(k, True, queue_size=4), initial_c2w=poses[0])
    eng.gate = threading.Event()
    _feed(eng, frames[:5])
    eng.gate.set()
    eng.finish(120.0)
    assert [lg.index for lg in eng.logs if lg.keyframe] == [0, 3] and eng.stats()["deferred_keyframes"] == 0


def _feed_from(eng: SLAM, frames, start: int) -> None:
    for i in range(start, len(frames)):
        eng.add_frame(*frames[i], float(i))


def test_frontend_downsample_tracks_the_orbit_on_a_quarter_of_the_pixels(views):
    k, poses, frames = views
    k2 = default_intrinsics(480, 272)
    ren = HomeRenderer(0)
    big = [ren.render(p, k2) for p in poses]
    cfg = _cfg(k2, False)
    cfg.tracking.frontend_downsample = 2
    cfg.mapping.first_frame_iters, cfg.mapping.iters = 1, 1  # the front end tracks sensor depth, not the map
    eng = SLAM(cfg, initial_c2w=poses[0])
    _feed(eng, big)
    assert eng._fe_k.width == 240 and eng._fe_k.height == 136
    for est, gt in zip(eng.poses, poses, strict=True):
        assert pose_error(est, gt)[0] < 0.02
    auto = SLAM(SlamConfig(intrinsics=default_intrinsics(1280, 720), tracking=TrackingConfig(
        frontend="keyframe", frontend_downsample=0)))
    assert auto._fe_halvings == 2  # 1280 -> 320 pixels wide
    with pytest.raises(ConfigError, match="frontend_downsample"):
        SlamConfig(intrinsics=k, tracking=TrackingConfig(frontend="keyframe", frontend_downsample=3)).check()
    for bad in ({"frontend_model_smoothing": 2}, {"frontend_model_smoothing": 0}, {"frontend_noisy_smoothing": 4},
                {"frontend_noisy_smoothing": True}, {"frontend_noisy_roughness": -1.0},
                {"frontend_noisy_roughness": float("inf")}, {"frontend_trust_z2_per_roughness": -0.5},
                {"frontend_sigma_geo_z2": -0.001}, {"frontend_sigma_geo_z2": float("nan")},
                {"frontend_speckle_fill": -0.1}, {"frontend_speckle_fill": float("nan")}):
        with pytest.raises(ConfigError, match=next(iter(bad))):
            SlamConfig(intrinsics=k, tracking=TrackingConfig(frontend="keyframe", **bad)).check()


def test_profiles_apply_their_overrides_and_unknown_names_are_refused(views):
    k = views[0]
    rt = SlamConfig(intrinsics=k, threads=2).with_profile("realtime")
    rt.check()
    assert rt.threaded and rt.tracking.frontend == "keyframe" and rt.mapping.defer_keyframes and rt.threads == 2
    assert SlamConfig(intrinsics=k).with_profile("default") == SlamConfig(intrinsics=k)
    with pytest.raises(ConfigError, match="unknown profile 'fast'.*realtime"):
        SlamConfig(intrinsics=k).with_profile("fast")


def test_spread_order_covers_the_run_evenly_at_every_prefix():
    assert spread_order(7) == [3, 1, 5, 0, 2, 4, 6]
    for n in range(0, 40):
        order = spread_order(n)
        assert sorted(order) == list(range(n))
        if n >= 3:  # the middle, then the middles of the two halves
            m = (n - 1) // 2
            assert order[:3] == [m, (m - 1) // 2, (m + n) // 2]


def test_deferred_frames_are_kept_and_mapped_by_the_refinement(views):
    k, poses, frames = views
    eng = _held_deferring(k, poses)
    eng.cfg.mapping.backlog_motion_m = eng.cfg.mapping.backlog_motion_deg = 0.0  # kept by frame count alone
    _feed(eng, frames)  # frame 0's mapping holds the thread: every later due keyframe is deferred
    assert [i for i, *_ in eng.backlog] == [3, 6]  # keyframe_every (3) apart, counted from the last keyframe
    eng.gate.set()
    n_before = len(eng.map)
    assert eng.refine(1, backlog_stop=lambda: True)[1] == 1 and eng.caught_up == 0  # a stop for the deferred
    assert [i for i, *_ in eng.backlog] == [3, 6]  # frames alone: none mapped, the iteration runs, they stay
    loss, done = eng.refine(4)
    assert done == 4 and np.isfinite(loss) and eng.backlog == [] and eng.stats()["caught_up"] == 2
    assert len(eng.map) > n_before  # the deferred views seeded what frame 0 did not see
    assert [kf.index for kf in eng.keyframes] == [0]  # not pose-graph keyframes


@pytest.mark.parametrize("poses", [None, False])
def test_the_refinement_places_its_deferred_views_and_moves_their_frames(views, poses):
    """With ``mapping.refine_poses`` (the realtime profile's) the refinement optimises the deferred frames' poses
    too: a view 5 cm off its true pose comes most of the way back and the frames after it, up to the next view,
    take its correction; the first keyframe (the gauge) stays. ``poses=False`` overrides the setting: nothing
    moves. (Measured: 5.1 -> 2.2 cm after 200 iterations, 2.0 after 300; at this size 5 cm is 1-2 pixels.)"""
    k, poses_true, frames = views
    eng = _held_deferring(k, poses_true)
    eng.cfg.mapping.backlog_motion_m = eng.cfg.mapping.backlog_motion_deg = 0.0
    eng.cfg.mapping.refine_poses = True
    _feed(eng, frames)
    assert [i for i, *_ in eng.backlog] == [3, 6]
    eng.gate.set()
    eng.drain(120.0)
    for i in (3, 4, 5):  # view 3 and the frames it starts, moved 5 cm sideways
        eng.poses[i] = eng.poses[i].copy()
        eng.poses[i][:3, 3] += eng.poses[i][:3, 0] * 0.05
    before = [p.copy() for p in eng.poses]
    err0 = pose_error(eng.poses[3], poses_true[3])[0]
    _, done = eng.refine(300, poses=poses)
    assert done == 300
    np.testing.assert_array_equal(eng.poses[0], before[0])  # the gauge
    if poses is False:
        assert all(np.array_equal(a, b) for a, b in zip(before, eng.poses, strict=True))
        return
    err1 = pose_error(eng.poses[3], poses_true[3])[0]
    assert err0 > 0.049 and err1 < 0.5 * err0, (err0, err1)
    corr = eng.poses[3] @ np.linalg.inv(before[3])
    np.testing.assert_allclose(eng.poses[5], corr @ before[5], atol=1e-12)  # frame 5 moved with view 3
    assert not np.array_equal(eng.poses[6], before[6])  # view 6 was placed on its own



def _kept_while_held(cfg: SlamConfig, poses, frames) -> list[int]:
    """The frames a deferring engine keeps while its mapping thread is held through ``frames`` (then let go and
    drained)."""
    eng = _SlowMap(cfg, initial_c2w=poses[0])
    eng.gate = threading.Event()
    _feed(eng, frames)
    kept = [i for i, *_ in eng.backlog]
    eng.gate.set()
    eng.finish(120.0)
    return kept


def test_a_deferred_frame_that_moved_far_enough_is_kept_before_keyframe_every(views):
    """A camera turning fast (here 1.4 degrees a frame against a 2.5-degree backlog_motion_deg) has its deferred
    frames kept as soon as they turned that far from the last kept one, not only keyframe_every frames apart."""
    k, poses, frames = views
    cfg = _cfg(k, True, queue_size=4)
    cfg.mapping.defer_keyframes, cfg.mapping.keyframe_every = True, 5
    cfg.mapping.keyframe_motion_deg = 1.5  # frame 1 is due, deferred, and from then on every frame is due
    cfg.mapping.backlog_motion_deg, cfg.mapping.backlog_motion_m = 2.5, 0.0
    kept = _kept_while_held(cfg, poses, frames)
    assert kept == [2, 4, 6, 8], kept  # every 2nd frame (2.8 degrees), where keyframe_every alone keeps frame 5
    cfg.mapping.backlog_motion_deg = 0.0
    assert _kept_while_held(cfg, poses, frames) == [5], "the motion rule off: keyframe_every apart"


def test_views_between_keyframes_are_kept_while_mapping_keeps_up(views):
    """A camera read slowly (here 1.4 degrees a frame against a 2.5-degree backlog_motion_deg) lets the mapping thread
    keep up, so no keyframe is deferred; the frames between keyframes that moved far enough are still kept as views
    for the refinement, which maps them."""
    k, poses, frames = views
    cfg = _cfg(k, True, queue_size=4)
    cfg.mapping.defer_keyframes, cfg.mapping.keyframe_every = True, 5
    cfg.mapping.backlog_motion_deg, cfg.mapping.backlog_motion_m = 2.5, 0.0
    cfg.mapping.keyframe_motion_m = cfg.mapping.keyframe_motion_deg = 0.0  # (frame 4 is 0.251 m from frame 0)
    eng = SLAM(cfg, initial_c2w=poses[0])
    _feed(eng, frames, wait=True)  # the thread is idle at every frame
    # keyframes by keyframe_every; none deferred
    assert [lg.index for lg in eng.logs if lg.keyframe] == [0, 5] and eng.stats()["deferred_keyframes"] == 0
    assert [i for i, *_ in eng.backlog] == [2, 4, 7], "2.8 degrees past keyframe 0, frame 2 and keyframe 5"
    n_before = len(eng.map)
    eng.refine(2)
    assert eng.backlog == [] and eng.stats()["caught_up"] == 3 and len(eng.map) >= n_before
    eng.finish(120.0)
    cfg.mapping.defer_keyframes = False  # keyframes mapped whenever due: the refinement has the keyframes only
    eng = SLAM(cfg, initial_c2w=poses[0])
    _feed(eng, frames, wait=True)
    assert eng.backlog == []
    eng.finish(120.0)


def test_a_full_backlog_thins_out_to_span_the_run(views):
    k, poses, frames = views
    cfg = _cfg(k, True, queue_size=len(frames))
    cfg.mapping.defer_keyframes, cfg.mapping.keyframe_every, cfg.mapping.backlog_max = True, 1, 3
    kept = _kept_while_held(cfg, poses, frames)
    assert 1 <= len(kept) <= 3 and kept[-1] >= len(frames) - 2 and kept == sorted(kept)
    with pytest.raises(ConfigError, match="backlog_max"):
        SlamConfig(intrinsics=k, mapping=MappingConfig(backlog_max=-1)).check()
    with pytest.raises(ConfigError, match="backlog_motion"):
        SlamConfig(intrinsics=k, mapping=MappingConfig(backlog_motion_m=float("nan"))).check()


def test_the_keyframe_front_end_starts_from_the_odometry_when_given():
    k = default_intrinsics(120, 68)
    poses = trajectory(9, span_deg=24.0)  # 3 degrees a frame
    ren = HomeRenderer(0)
    frames = [ren.render(p, k) for p in poses]
    order = [0, 1, 2, 8]  # a jump of 18 degrees where constant velocity guesses 3
    for odom in (False, True):
        eng = SLAM(_cfg(k, False), initial_c2w=poses[0])
        for i in order:
            eng.add_frame(*frames[i], float(i), odom_c2w=poses[i] if odom else None)
        err = pose_error(eng.poses[-1], poses[8])[0]
        if odom:
            assert err < 0.02 and eng.logs[-1].pose_source == "tracking", (err, eng.logs[-1].pose_source)
        else:  # what the odometry is for: without it the jump is lost or tracked wrong
            assert err > 0.02 or eng.logs[-1].pose_source != "tracking", err


@pytest.mark.parametrize("refine", [True, False])
def test_a_kidnapped_camera_is_relocalised_and_refined_on_the_map_while_the_mapping_thread_runs(views, refine):
    """Lost on a view turned away, then back on ground the map holds: relocalised against a keyframe; with
    tracking.relocalise_map_refine the pose is then refined on the map (after the mapping thread's job)."""
    k, poses, frames = views
    away = poses[4].copy()
    turn = np.array([[-1.0, 0, 0], [0, 1, 0], [0, 0, -1]])  # half a turn about the camera's vertical axis
    away[:3, :3] = away[:3, :3] @ turn
    lost_view = HomeRenderer(0).render(away, k)
    cfg = _cfg(k, True)
    cfg.tracking.relocalise_map_refine = refine
    cfg.tracking.relocalise_every = 1  # the first frame back tries at once
    eng = SLAM(cfg, initial_c2w=poses[0])
    order = [0, 1, 2, 3, 4, 5, 6, None, 3, 4, 5]  # None: the view turned away
    for n, i in enumerate(order):
        rgb, depth, sem = lost_view if i is None else frames[i]
        eng.add_frame(rgb, depth, sem, float(n))
    eng.finish(120.0)
    sources = [lg.pose_source for lg in eng.logs]
    assert sources[7] == "lost" and sources[8] == "relocalised", sources
    assert eng.stats()["recoveries"] and eng.stats()["recoveries"][0][0] == 7
    # refined on the map: the render front end's agreement is logged (the keyframe front end logs none)
    assert [np.isfinite(eng.logs[n].track_agreement) for n in (7, 8, 9)] == [False, refine, refine]
    for n in (8, 9, 10):
        assert pose_error(eng.poses[n], poses[order[n]])[0] < 0.02, (n, sources)


def test_a_background_checkpoint_holds_the_frames_tracked_until_it_was_asked_for(views, tmp_path):
    """``checkpoint_in_background`` returns at once while the mapping thread is busy; the thread writes it after
    the jobs queued before it, with the frames tracked until the call (not those tracked meanwhile), and
    :meth:`SLAM.resume` continues from there."""
    k, poses, frames = views
    cfg = _cfg(k, True, queue_size=4)
    cfg.mapping.defer_keyframes = True
    cfg.mapping.densify_every_frame = cfg.mapping.label_votes = False  # keyframe jobs only, as in realtime
    eng = _SlowMap(cfg, initial_c2w=poses[0])
    eng.gate = threading.Event()
    _feed(eng, frames[:5])  # frame 0's mapping job is held
    done: list = []
    assert eng.checkpoint_in_background(str(tmp_path / "ck"), done.append)
    _feed_from(eng, frames[:8], 5)  # tracking goes on while the checkpoint waits behind frame 0's job
    assert done == [] and not (tmp_path / "ck").exists()
    at_call = [p.copy() for p in eng.poses[:5]]
    eng.gate.set()
    eng.drain(120.0)
    assert done == [None]
    back = SLAM.resume(str(tmp_path / "ck"))
    assert len(back.poses) == 5 and len(eng.poses) == 8
    for a, b in zip(back.poses, at_call, strict=True):
        np.testing.assert_array_equal(a, b)
    assert [kf.index for kf in back.keyframes] == [0] and len(back.map) == len(eng.map) > 0
    assert len(back.exposures) == len(back.timestamps) == 5


def test_a_background_checkpoint_that_cannot_be_written_says_so_and_mapping_goes_on(views, tmp_path):
    k, poses, frames = views
    eng = SLAM(_cfg(k, True), initial_c2w=poses[0])
    _feed(eng, frames[:3])
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    done: list = []
    assert eng.checkpoint_in_background(str(blocker / "ck"), done.append)
    _feed_from(eng, frames[:6], 3)
    eng.drain(120.0)  # the mapping thread did not stop on it
    assert len(done) == 1 and isinstance(done[0], OSError)
    assert not eng._worker.failed
    eng.finish(120.0)
    sync = SLAM(_cfg(k, False), initial_c2w=poses[0])  # without a mapping thread: written at once
    _feed(sync, frames[:2])
    assert sync.checkpoint_in_background(str(tmp_path / "ck2"), done.append) and done[-1] is None
    assert len(SLAM.resume(str(tmp_path / "ck2")).poses) == 2
