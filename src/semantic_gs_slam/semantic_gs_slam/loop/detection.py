"""Loop detection: register a new keyframe against the older keyframe it overlaps most.

Frame-to-model tracking drifts slowly (each frame agrees with a map built from the same drifting
poses, so no per-frame test can see it). When the camera comes back to a place it saw long ago, that
old keyframe's own depth image is an independent reference: point-to-plane ICP of the new depth
against it (geometry only: colour and depth are not registered on many sensors) gives the pose the
old view implies. If that registration is verified (most overlapping points land on the old surface)
and disagrees with the tracked pose, the difference is drift: :class:`semantic_gs_slam.slam.SLAM`
reports it and spreads it over its keyframe pose graph (:mod:`semantic_gs_slam.loop.posegraph`).

Torch on the engine's device, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, LoopConfig, TrackingConfig
from semantic_gs_slam.errors import TrackingError
from semantic_gs_slam.geometry import backproject, pose_error
from semantic_gs_slam.tracking.tracker import IcpGraphs, icp


@dataclass
class LoopMatch:
    """A registration of the current keyframe against an older one."""

    candidate: int  # position of the old keyframe in the engine's keyframe list
    frame: int  # the old keyframe's frame index
    c2w: np.ndarray  # [4, 4] the current keyframe's pose implied by the old keyframe
    overlap: float  # share of the current points inside the old view
    agreement_before: float  # share of overlapping points on the old surface at the tracked pose
    agreement_after: float  # ... at the registered pose
    correction_m: float  # distance between the tracked and the registered pose
    correction_deg: float
    residual_m: float  # ICP's RMS point-to-plane residual

    def verdict(self, lc: LoopConfig) -> str:
        """``"correct"`` (verified drift), ``"consistent"`` (no drift worth a correction) or why it is rejected."""
        if self.agreement_after < lc.min_agreement:
            return f"rejected: only {self.agreement_after:.0%} of the points agree after registration"
        if self.agreement_after + 0.01 < self.agreement_before:
            return "rejected: registration agrees less than the tracked pose"
        if self.correction_m > lc.max_correction_m or self.correction_deg > lc.max_correction_deg:
            return (f"rejected: correction {self.correction_m * 100:.1f} cm / {self.correction_deg:.1f} deg "
                    "is too large to trust")
        if self.correction_m < lc.min_correction_m and self.correction_deg < lc.min_correction_deg:
            return "consistent"
        return "correct"


def sample_points(depth: Tensor, k: Intrinsics, step: int = 8) -> Tensor:
    """Camera-frame points [M, 3] float64 of every ``step``-th valid pixel of ``depth`` [H, W]."""
    pts = backproject(depth, k.fx, k.fy, k.cx, k.cy)[::step, ::step].reshape(-1, 3)
    return pts[pts[:, 2] > 0].double()


def _project(world: Tensor, c2w: Tensor, k: Intrinsics) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    w2c = torch.linalg.inv(c2w)
    pc = world @ w2c[:3, :3].T + w2c[:3, 3]
    z = pc[:, 2]
    u = k.fx * pc[:, 0] / z.clamp_min(1e-9) + k.cx
    v = k.fy * pc[:, 1] / z.clamp_min(1e-9) + k.cy
    inside = (z > 1e-3) & (u >= 0) & (u <= k.width - 1) & (v >= 0) & (v <= k.height - 1)
    return z, u, v, inside


def overlap(world: Tensor, c2w: Tensor, k: Intrinsics) -> float:
    """Share of ``world`` points [M, 3] inside the view of a camera at ``c2w`` [4, 4]."""
    if world.shape[0] == 0:
        return 0.0
    return float(_project(world, c2w, k)[3].double().mean())


def agreement(pts_c: Tensor, c2w: Tensor, ref_depth: Tensor, ref_c2w: Tensor, k: Intrinsics,
              dist: float) -> float:
    """Share of the points that land on the reference depth, among those that project onto it.

    Args:
        pts_c: [M, 3] camera-frame points of the current frame. c2w: [4, 4] its pose.
        ref_depth: [H, W] the reference keyframe's depth (0: missing). ref_c2w: [4, 4] its pose.
        dist: metres of tolerance (plus 1 % of the depth, for the sensor's noise).
    """
    world = pts_c @ c2w[:3, :3].T + c2w[:3, 3]
    z, u, v, inside = _project(world, ref_c2w.to(world), k)
    ui, vi = torch.round(u[inside]).long(), torch.round(v[inside]).long()
    d = ref_depth[vi, ui].to(world)
    zi = z[inside]
    seen = d > 0
    n = int(seen.sum())
    if n == 0:
        return 0.0
    ok = (zi - d).abs() < dist + 0.01 * d
    return float((ok & seen).sum()) / n


def find_loops(depth: Tensor, c2w: np.ndarray, frame: int, keyframes: list, k: Intrinsics, lc: LoopConfig,
               tc: TrackingConfig, kf_poses: list[np.ndarray] | None = None,
               graphs: IcpGraphs | None = None) -> list[LoopMatch]:
    """Register the current keyframe against its most overlapping old keyframes.

    Args:
        depth: [H, W] the current depth (metres, 0: missing), on the engine's device.
        c2w: [4, 4] the tracked pose.
        frame: the current frame index.
        keyframes: the engine's keyframes (``index``, ``c2w`` [4, 4] tensor, ``depth`` [H, W]).
        k: intrinsics. lc: loop settings. tc: tracking settings (the ICP's other knobs).
        kf_poses: the keyframes' poses as host copies (default: from ``keyframes``).
        graphs: the engine's captured ICP steps (CUDA), or None.

    Returns:
        Up to ``lc.candidates`` matches, best overlap first (judge each with :meth:`LoopMatch.verdict`),
        from keyframes at least ``lc.min_frame_gap`` frames old that overlap by ``lc.min_overlap``, see the
        scene from nearly the same viewpoint (``lc.max_view_angle_deg``, ``lc.max_view_distance_m``) and lie
        ``lc.min_frame_gap // 2`` frames apart from each other; empty when none qualifies or every
        registration found too few correspondences.
    """
    pts = sample_points(depth, k)
    if pts.shape[0] < 50:
        return []
    cur = torch.as_tensor(c2w, dtype=torch.float64, device=depth.device)
    world = pts @ cur[:3, :3].T + cur[:3, 3]
    scored = []
    c2w = np.asarray(c2w, np.float64)
    for i, kf in enumerate(keyframes):
        if kf.index > frame - lc.min_frame_gap:
            break
        kc = kf_poses[i] if kf_poses is not None else kf.c2w.detach().cpu().numpy().astype(np.float64)
        dist, angle = pose_error(kc, c2w)
        if dist > lc.max_view_distance_m or angle > lc.max_view_angle_deg:
            continue
        ov = overlap(world, kf.c2w.double(), k)
        if ov >= lc.min_overlap:
            scored.append((ov, i))
    picked: list[tuple[float, int]] = []
    for ov, i in sorted(scored, reverse=True):
        if all(abs(keyframes[i].index - keyframes[j].index) >= lc.min_frame_gap // 2 for _, j in picked):
            picked.append((ov, i))
        if len(picked) >= lc.candidates:
            break
    out = []
    for ov, i in picked:
        m = _register(pts, cur, depth, i, keyframes[i], ov, k, lc, tc, graphs)
        if m is not None:
            out.append(m)
    return out


def _register(pts: Tensor, cur: Tensor, depth: Tensor, pos: int, ref, ov: float, k: Intrinsics, lc: LoopConfig,
              tc: TrackingConfig, graphs: IcpGraphs | None = None) -> LoopMatch | None:
    ref_c2w = ref.c2w.double()
    before = agreement(pts, cur, ref.depth, ref_c2w, k, lc.verify_dist)
    cfg = replace(tc, icp_iters=lc.icp_iters, icp_levels=lc.icp_levels, icp_max_dist=lc.icp_max_dist,
                  photometric_weight=0.0, prior_sigma_trans=1e3, prior_sigma_rot=1e3)
    try:
        res = icp(ref.depth, ref.depth > 0, ref_c2w, depth, k, cfg, start_c2w=cur, graphs=graphs)
    except TrackingError:
        return None
    reg = res.c2w.to(torch.float64)
    after = agreement(pts, reg, ref.depth, ref_c2w, k, lc.verify_dist)
    reg_np = reg.cpu().numpy()
    dt, dr = pose_error(cur.cpu().numpy(), reg_np)
    return LoopMatch(pos, ref.index, reg_np, ov, before, after, dt, dr, res.residual)
