"""Loop closure: the pose graph, Gaussians moved with their keyframes, and drift found and corrected."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from semantic_gs_slam.config import LoopConfig, MappingConfig, SlamConfig, TrackingConfig
from semantic_gs_slam.errors import ConfigError
from semantic_gs_slam.geometry import pose_error, quat_to_rotmat
from semantic_gs_slam.loop.posegraph import Edge, optimise, pose_exp, pose_log, so3_exp, so3_log
from semantic_gs_slam.mapping.gaussian_map import GaussianMap
from semantic_gs_slam.slam import SLAM
from semantic_gs_slam.synthetic.scenes import HomeRenderer, default_intrinsics, trajectory

pytestmark = pytest.mark.slow  # the SLAM runs over the out-and-back sequence (a module fixture)


def test_so3_log_inverts_exp_near_zero_and_near_pi():
    rng = np.random.default_rng(1)
    for w in [np.zeros(3), np.array([1e-8, 0, 0]), *rng.normal(0, 1, (5, 3)),
              np.array([np.pi - 1e-6, 0, 0]), np.array([0, 0, np.pi - 1e-3])]:
        r = so3_exp(w)
        assert np.allclose(so3_exp(so3_log(r)), r, atol=1e-6)
    t = pose_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0]))
    assert np.allclose(pose_exp(pose_log(t)), t)


def _chain(n: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ pose_exp(np.r_[rng.normal(0, 0.05, 3), rng.normal(0, 0.2, 3)]))
    return poses


def test_a_loop_edge_spreads_the_drift_of_biased_sequential_edges():
    truth = _chain(12)
    bias = pose_exp(np.array([0.0, 0.0, np.radians(0.4), 0.004, 0.0, 0.0]))  # every step measured a bit off
    seq = [Edge(i, i + 1, np.linalg.inv(truth[i]) @ truth[i + 1] @ bias, 0.005, 0.01) for i in range(11)]
    dead = [truth[0]]
    for e in seq:
        dead.append(dead[-1] @ e.rel)
    loop = Edge(0, 11, np.linalg.inv(truth[0]) @ truth[11], 0.0025, 0.005, "loop")
    new, before, after = optimise(dead, seq + [loop])
    assert after < 0.05 * before
    err_dead = [pose_error(d, t)[0] for d, t in zip(dead, truth, strict=True)]
    err_new = [pose_error(p, t)[0] for p, t in zip(new, truth, strict=True)]
    assert err_dead[-1] > 0.04  # 4.4 cm of drift accumulated
    assert err_new[-1] < 0.3 * err_dead[-1]
    assert np.mean(err_new) < 0.5 * np.mean(err_dead)
    assert np.allclose(new[0], truth[0])  # the gauge stays fixed
    # without the loop edge the chain is already consistent: nothing moves
    same, _, _ = optimise(dead, seq)
    assert max(np.abs(a - b).max() for a, b in zip(same, dead, strict=True)) < 1e-9


def test_batched_residuals_equal_the_scalar_definition():
    from semantic_gs_slam.loop.posegraph import _residuals, _rigid_inv, edge_residual

    rng = np.random.default_rng(3)
    ti, tj, rel = (np.stack([pose_exp(np.r_[rng.normal(0, 1, 3), rng.normal(0, 2, 3)]) for _ in range(8)])
                   for _ in range(3))
    tj[0] = ti[0] @ rel[0]  # a satisfied edge: zero residual
    tj[1] = ti[1] @ rel[1] @ pose_exp(np.array([np.pi - 1e-5, 0, 0, 0, 0, 0]))  # a residual near a half turn
    got = _residuals(ti, tj, _rigid_inv(rel))
    want = np.stack([edge_residual(a, b, c) for a, b, c in zip(ti, tj, rel, strict=True)])
    assert np.allclose(got, want, atol=1e-9) and np.abs(got[0]).max() < 1e-9


def test_optimise_refuses_an_edge_to_a_missing_pose():
    with pytest.raises(ValueError, match="does not join"):
        optimise([np.eye(4), np.eye(4)], [Edge(0, 2, np.eye(4), 0.01, 0.01)])


def test_gaussians_move_with_the_transform_of_the_frame_that_created_them():
    m = GaussianMap("cpu")
    pts = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    for frame, p in zip((0, 5, 9), pts, strict=True):
        m.add(p[None], torch.rand(1, 3), torch.zeros(1, dtype=torch.int64), torch.full((1,), 0.01), frame,
              normals=torch.tensor([[0.0, 0.0, 1.0]]))
    quats0 = m.params["unnorm_rotations"].detach().clone()
    t1 = pose_exp(np.array([0, 0, np.pi / 2, 1.0, 0, 0]))
    t2 = pose_exp(np.array([np.pi / 2, 0, 0, 0, 0, 2.0]))
    m.move_by_frame(torch.tensor([0, 4, 8]), torch.as_tensor(np.stack([np.eye(4), t1, t2])))
    means = m.params["means3D"].detach().numpy()
    assert np.allclose(means[0], [1, 0, 0], atol=1e-6)  # frame 0: identity
    assert np.allclose(means[1], t1[:3, :3] @ [0, 1, 0] + t1[:3, 3], atol=1e-6)  # frame 5: t1
    assert np.allclose(means[2], t2[:3, :3] @ [0, 0, 1] + t2[:3, 3], atol=1e-6)  # frame 9: t2
    rot = quat_to_rotmat(m.params["unnorm_rotations"].detach()).numpy()
    rot0 = quat_to_rotmat(quats0).numpy()
    assert np.allclose(rot[1], t1[:3, :3] @ rot0[1], atol=1e-6)
    assert np.allclose(rot[2], t2[:3, :3] @ rot0[2], atol=1e-6)
    assert np.allclose(m.normals.numpy()[2], t2[:3, :3] @ [0, 0, 1], atol=1e-6)
    assert m.params["means3D"].requires_grad  # still optimisable


def test_loop_config_is_validated():
    with pytest.raises(ConfigError, match="loop"):
        LoopConfig(min_overlap=0).check()
    with pytest.raises(ConfigError, match="loop"):
        LoopConfig(sigma_trans=0).check()
    with pytest.raises(ConfigError, match="own_correction_sigmas"):
        LoopConfig(own_correction_sigmas=-1).check()
    cfg = SlamConfig.from_dict({**SlamConfig(intrinsics=default_intrinsics(64, 36)).to_dict(),
                                "loop": {"enabled": False}})
    assert cfg.loop.enabled is False and cfg.loop.min_frame_gap == LoopConfig().min_frame_gap


def _out_and_back(n: int) -> list[np.ndarray]:
    """A path along the orbit and back the same way: its second half revisits the first."""
    out = trajectory(n, span_deg=50.0)
    return out + out[::-1]


@pytest.fixture(scope="module")
def frames():
    k = default_intrinsics(120, 68)
    ren = HomeRenderer(0)
    poses = _out_and_back(10)
    return k, poses, [ren.render(p, k) for p in poses]


def _drift(i: int) -> np.ndarray:
    """Injected drift at frame i: 0.15 deg and 0.35 cm per frame, in the world frame."""
    return pose_exp(np.array([0.0, 0.0, np.radians(0.15) * i, 0.0035 * i, 0.0, 0.0]))


def _run(k, poses, views, drift: bool, odometry: bool = False, with_odometry: bool = False,
         own_correction_sigmas: float = LoopConfig.own_correction_sigmas, frames: int = 0,
         until_first_loop: bool = False) -> SLAM:
    """The frames through a use_gt_pose engine (the first ``frames``, 0: all; or up to the frame whose keyframe
    closes the first loop)."""
    cfg = SlamConfig(intrinsics=k, threads=1, tracking=TrackingConfig(use_gt_pose=True),
                     mapping=MappingConfig(first_frame_iters=20, iters=4),
                     loop=LoopConfig(min_frame_gap=8, with_odometry=with_odometry,
                                     own_correction_sigmas=own_correction_sigmas))
    eng = SLAM(cfg, initial_c2w=poses[0])
    for i, (p, (rgb, depth, sem)) in enumerate(zip(poses[:frames or None], views, strict=False)):
        # the "ground truth" handed to a use_gt_pose engine is the drifting estimate of a tracker
        est = _drift(i) @ p if drift else p
        eng.add_frame(rgb, depth, sem, float(i), est, odom_c2w=est if odometry else None)
        if until_first_loop and eng.loops:
            break
    return eng


def test_drift_is_found_reported_and_corrected_where_the_camera_returns(frames, caplog):
    k, poses, views = frames
    with caplog.at_level(logging.WARNING, logger="semantic_gs_slam"):
        eng = _run(k, poses, views, drift=True)
    assert eng.loops, [lg.loop for lg in eng.logs if lg.keyframe]
    assert any("drift found" in r.message for r in caplog.records)
    for lp in eng.loops:
        f = lp["frame"]
        injected = pose_error(_drift(f) @ poses[f], poses[f])
        now = pose_error(eng.poses[f], poses[f])
        assert lp["found_cm"] > 1.0
        # the corrected pose is much closer to the truth than the drifted one (translation and rotation)
        assert now[0] < 0.5 * injected[0] and now[1] < 0.5 * injected[1], (f, injected, now)
    # the map moved with the keyframes: the keyframe poses kept in the engine are the corrected ones
    last = eng.loops[-1]["frame"]
    kf = next(kf for kf in eng.keyframes if kf.index == last)
    assert np.allclose(kf.c2w.numpy(), eng.poses[last])
    assert any(e.kind == "loop" for e in eng.edges)


def test_a_correction_within_the_loop_noise_moves_the_new_keyframe_with_the_previous_one(frames):
    """Up to the first correction (frame 12 here): with the threshold high, the new keyframe keeps its tracked
    place relative to the previous keyframe (the loop edge's pull on it alone is taken as noise, so the trajectory
    does not jump there); with 0 it moves by its own graph correction, centimetres away from that."""
    k, poses, views = frames
    first = None  # the first loop's frame: found by the first run, where it stops (before it, sigmas play no part)
    rel = {}
    for sigmas in (0.0, 1e9):
        eng = _run(k, poses, views, drift=True, own_correction_sigmas=sigmas, until_first_loop=True)
        first = eng.loops[0]["frame"] if first is None else first
        assert [lp["frame"] for lp in eng.loops] == [first] and len(eng.poses) == first + 1
        prev = [kf.index for kf in eng.keyframes if kf.index < first][-1]
        tracked = np.linalg.inv(_drift(prev) @ poses[prev]) @ (_drift(first) @ poses[first])  # what use_gt_pose took
        rel[sigmas] = pose_error(np.linalg.inv(eng.poses[prev]) @ eng.poses[first], tracked)
    assert rel[1e9][0] < 1e-6 and rel[1e9][1] < 1e-4, rel
    assert rel[0.0][0] > 0.01, rel  # the graph's own answer for the new keyframe is elsewhere: the test means something


def test_no_correction_without_drift(frames):
    k, poses, views = frames
    eng = _run(k, poses, views, drift=False)
    notes = [lg.loop for lg in eng.logs if lg.loop]
    assert notes, "loop detection never ran: the test would prove nothing"
    assert eng.loops == [], notes
    assert all("consistent" in n for n in notes), notes


def test_frames_with_odometry_are_left_to_the_odometry_unless_asked(frames):
    k, poses, views = frames
    assert _run(k, poses, views, drift=True, odometry=True).loops == []  # a robot's stream: off by default
    assert _run(k, poses, views, drift=True, odometry=True, with_odometry=True,  # the same frames, switched on
                until_first_loop=True).loops


def test_checkpoint_keeps_the_pose_graph(frames, tmp_path):
    k, poses, views = frames
    eng = _run(k, poses[:12], views[:12], drift=True)
    eng.checkpoint(str(tmp_path / "ck"))
    back = SLAM.resume(str(tmp_path / "ck"))
    assert [(e.i, e.j, e.kind) for e in back.edges] == [(e.i, e.j, e.kind) for e in eng.edges]
    assert np.allclose(np.stack([e.rel for e in back.edges]), np.stack([e.rel for e in eng.edges]))
