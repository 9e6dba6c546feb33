"""The incremental SLAM engine: ``SLAM(config)``, ``add_frame(...) -> pose``, ``save``, checkpoints.

Per frame: tracking (constant-velocity guess, point-to-plane ICP against the depth rendered from
the map, optional photometric refinement), then on keyframes mapping (densify where the map is
empty or behind the measured depth, optimise a window of overlapping keyframes, prune).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, MappingConfig, SlamConfig
from semantic_gs_slam.devices import require_cpu_kernel, resolve_device
from semantic_gs_slam.errors import FrameError, MapFormatError, TrackingError
from semantic_gs_slam.exposure import fit as fit_exposure
from semantic_gs_slam.exposure import identity as exposure_identity
from semantic_gs_slam.exposure import to_map
from semantic_gs_slam.gaussian_map import (
    GaussianMap,
    export_ply,
    load_params,
    load_semantic_json,
    save_params,
    save_semantic_json,
)
from semantic_gs_slam.geometry import fill_depth_holes, pose_error
from semantic_gs_slam.loop import LoopMatch, find_loops
from semantic_gs_slam.metrics import ssim
from semantic_gs_slam.posegraph import Edge
from semantic_gs_slam.posegraph import optimise as optimise_graph
from semantic_gs_slam.render import Gaussians, RenderOutput, select_backend
from semantic_gs_slam.tracking import (
    IcpGraphs,
    icp,
    icp_uses_numba,
    photometric_refine,
    plane_depth_features,
    plane_depth_image,
    w2c_from_quat_trans,
)

log = logging.getLogger("semantic_gs_slam")


@dataclass
class Keyframe:
    """A mapped frame kept for window optimisation."""

    index: int
    c2w: Tensor  # [4, 4] float64
    rgb: Tensor  # [H, W, 3]
    depth: Tensor  # [H, W]
    sem: Tensor | None  # [H, W] int64


def check_pose(c2w: np.ndarray, name: str) -> np.ndarray:
    """A [4, 4] finite rigid transform as float64, else :class:`FrameError` naming ``name``."""
    m = np.asarray(c2w, np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise FrameError(f"{name} must be a finite [4, 4] matrix, got shape {list(m.shape)}")
    r = m[:3, :3]
    if np.abs(r.T @ r - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(r) - 1.0) > 1e-3 or \
            np.abs(m[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise FrameError(f"{name} is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return m


def _class_balance(sem: Tensor, power: float, cap: float = 20.0) -> Tensor:
    """Per-pixel weights [H, W] proportional to (class pixel frequency)^-power, mean 1, capped."""
    counts = torch.bincount(sem.reshape(-1).clamp_min(0)).double()
    w = (counts.clamp_min(1) / sem.numel()) ** (-power)
    pix = w[sem.clamp_min(0)]
    pix = (pix / pix.mean()).clamp(max=cap)
    return (pix / pix.mean()).float()


def mapping_loss(out: RenderOutput, rgb: Tensor, depth: Tensor, sem_img: Tensor | None, labelled: Tensor | None,
                 sem_w: Tensor | None, mc: MappingConfig) -> Tensor:
    """Keyframe mapping loss: depth L1 over valid depth + colour (L1 and SSIM) + class-balanced semantic L1.

    Fixed-shape (masks multiply; no boolean indexing), so it runs without host synchronisation.

    Args:
        out: the rendered view.
        rgb: [H, W, 3] keyframe colour. depth: [H, W] metres (0: missing).
        sem_img: [H, W, C] one-hot labels or None. labelled: [H, W] 1 where a label is known, or None.
        sem_w: [H, W] class-balance weights or None.
        mc: mapping settings (weights).

    Returns:
        Scalar loss.
    """
    valid = (depth > 0).to(depth.dtype)
    l_depth = ((out.depth - depth).abs() * valid).sum() / valid.sum().clamp_min(1.0)
    l1 = (out.rgb - rgb).abs().mean()
    fast = {"auto": None, "torch": False, "numba": True}[mc.ssim_backend]
    l_col = (1 - mc.w_ssim) * l1 + mc.w_ssim * (1 - ssim(out.rgb, rgb, fast=fast)) if mc.w_ssim > 0 else l1
    loss = mc.w_depth * l_depth + mc.w_colour * l_col
    if sem_img is not None and out.semantic is not None and mc.w_semantic > 0:
        err = (out.semantic - sem_img).abs().sum(-1) * labelled  # [H, W]; label 0 = unknown
        if sem_w is not None:
            err = err * sem_w
        loss = loss + mc.w_semantic * err.mean() / 2
    return loss


POSE_PRIOR_TRANS_M = 0.01  # scale of a keyframe's translation correction in pose_prior (1 cm)
POSE_PRIOR_ROT_QV = 0.004  # scale of its rotation correction, as a quaternion's vector part (~0.46 degrees)


def pose_prior(dq: Tensor, dt: Tensor, weight: float) -> Tensor:
    """``weight * (|dt|^2 / (1 cm)^2 + |dq|^2 / 0.004^2)``: the refinement's pull of a keyframe's pose correction
    (``dq`` [3], the vector part of a quaternion whose real part is 1; ``dt`` [3], metres) toward none. Scalar."""
    return weight * ((dt * dt).sum() / POSE_PRIOR_TRANS_M ** 2 + (dq * dq).sum() / POSE_PRIOR_ROT_QV ** 2)


@dataclass
class FrameLog:
    """What happened to one frame (printed per frame by the CLI)."""

    index: int
    timestamp: float
    keyframe: bool
    n_gaussians: int
    added: int
    pruned: int
    track_residual_m: float
    track_inliers: int
    tracking_failed: bool
    map_loss: float
    track_s: float
    map_s: float
    pose_source: str = "tracking"  # tracking | odometry (tracking failed, the odometry guess was kept) |
    # odometry_refused (ICP's pose was farther from the odometry's guess than tracking.odometry_gate_* allow: the
    # guess was kept) | previous (tracking failed, no odometry: previous pose) | first | ground_truth. Frames
    # with odometry, odometry_refused or previous are not mapped (see tracking.odometry_map_unverified)
    track_agreement: float = float("nan")  # TrackResult.agreement (share of the frame on the map's surface)
    loop: str = ""  # keyframes: what loop detection found ("" = not checked; see SLAM._close_loop)


class SLAM:
    """Semantic Gaussian-splatting RGB-D SLAM, fed frame by frame.

    The map frame is the first frame's pose: ``initial_c2w`` if given, else the ``odom_c2w`` passed
    with the first frame (so a robot's map is in its odometry frame), else the ``gt_c2w`` passed with
    the first frame, else the identity.
    """

    def __init__(self, config: SlamConfig, classes: dict[int, str] | None = None,
                 initial_c2w: np.ndarray | None = None) -> None:
        config.check()
        self.device = resolve_device(config.device)
        self.given_cfg = config  # as given: what a checkpoint keeps, so a resume on another device takes its values
        self.cfg = config.resolved(self.device.type)  # device-dependent defaults filled in (config.DEVICE_DEFAULTS)
        config = self.cfg
        self.k: Intrinsics = config.intrinsics
        self.classes = dict(classes or {})
        self.initial_c2w = None if initial_c2w is None else np.asarray(initial_c2w, np.float64)
        if config.threads > 0:
            torch.set_num_threads(config.threads)
        torch.manual_seed(config.seed)
        self.backend = select_backend(config.renderer, self.device)  # the renderer, chosen once
        icp_uses_numba(config.tracking, self.device)  # a compiled kernel asked for where it cannot run: say so now
        if config.mapping.ssim_backend == "numba":
            require_cpu_kernel("mapping.ssim_backend", self.device)
        self.map = GaussianMap(self.device)
        self.poses: list[np.ndarray] = []  # estimated c2w per frame
        self.gt_poses: list[np.ndarray | None] = []
        self.odom_poses: list[np.ndarray | None] = []  # the odometry c2w given with each frame, if any
        self.timestamps: list[float] = []
        self.keyframes: list[Keyframe] = []
        self.logs: list[FrameLog] = []
        self.edges: list[Edge] = []  # keyframe pose graph (nodes: positions in self.keyframes)
        self.loops: list[dict] = []  # every loop correction: frame, old keyframe frame, cm, deg, agreement
        self.exposures: list[Tensor] = []  # [2, 3] per frame: live colour = gain * map colour + bias (exposure.fit)
        self._since_prune = 0
        self._loop_note = ""
        self._agreement = float("nan")
        self._exposure: Tensor | None = None  # this frame's, once densification has fitted it
        self._icp_graphs = IcpGraphs()  # captured ICP steps on CUDA (tracking.IcpGraphs); unused elsewhere

    # ------------------------------------------------------------------ input
    def _tensors(self, rgb: np.ndarray, depth: np.ndarray, sem: np.ndarray | None
                 ) -> tuple[Tensor, Tensor, Tensor | None]:
        """Check one frame and move it to the device: shapes on the host, values on the device with one host copy
        of their counts (a 1200x680 frame's host-side checks and label sort took 21 ms, measured on the GPU
        machine; the arrays travel as given, uint8 colour included, and are converted there)."""
        k = self.k
        rgb = np.asarray(rgb)
        depth = np.asarray(depth)
        if rgb.shape != (k.height, k.width, 3):
            raise FrameError(f"rgb must be [{k.height}, {k.width}, 3] (intrinsics), got {list(rgb.shape)}")
        if depth.shape != (k.height, k.width):
            raise FrameError(f"depth must be [{k.height}, {k.width}] metres, got {list(depth.shape)}")
        if sem is not None:
            sem = np.asarray(sem)
            if sem.shape != (k.height, k.width):
                raise FrameError(f"semantics must be [{k.height}, {k.width}] ids, got {list(sem.shape)}")
        dev = self.device
        try:  # dtypes torch converts everywhere travel as they are, others are converted on the host first;
            # contiguous, because torch takes no negative strides (a BGR array flipped to RGB, a flipped image)
            rgb_np = np.ascontiguousarray(rgb if rgb.dtype == np.uint8 else rgb.astype(np.float32, copy=False))
            depth_np = np.ascontiguousarray(depth.astype(np.float32, copy=False))
            sem_np = None if sem is None else np.ascontiguousarray(
                sem if sem.dtype in (np.int64, np.int32, np.int16, np.uint8) else sem.astype(np.int64))
        except (TypeError, ValueError) as exc:
            raise FrameError(f"frame arrays must be numeric: {exc}") from exc
        own = dev.type == "cpu"  # on the CPU torch would share the caller's memory: keyframes keep these tensors
        rgb_t = torch.as_tensor(rgb_np, device=dev)
        depth_t = torch.as_tensor(depth_np, device=dev)
        sem_t = None if sem_np is None else torch.as_tensor(sem_np, device=dev).to(torch.int64, copy=own)
        rgb_t = rgb_t.to(torch.float32) / 255.0 if rgb_t.dtype == torch.uint8 else rgb_t.to(torch.float32, copy=own)
        valid = (depth_t >= self.cfg.depth_min) & (depth_t <= self.cfg.depth_max)
        bad_rgb, bad_depth, negative, n_valid = torch.stack([(~torch.isfinite(rgb_t)).sum(), (~torch.isfinite(
            depth_t)).sum(), (depth_t < 0).sum(), valid.sum()]).tolist()  # one host copy
        if bad_rgb:
            raise FrameError("rgb contains NaN or inf")
        if bad_depth:
            raise FrameError(f"depth contains {bad_depth} NaN/inf values (use 0 for missing)")
        if negative:
            raise FrameError("depth has negative values")
        frac = n_valid / depth_t.numel()
        if frac < 0.05:
            raise FrameError(f"only {frac * 100:.1f} % of depth pixels are valid "
                             f"(in [{self.cfg.depth_min}, {self.cfg.depth_max}] m); is the depth in metres?")
        if sem_t is not None:
            for i in torch.unique(sem_t).tolist():
                if i > 0:  # unknown labels get a placeholder name in semantic.json
                    self.classes.setdefault(int(i), f"class_{int(i)}")
        return rgb_t, torch.where(valid, depth_t, torch.zeros_like(depth_t)), sem_t

    def check_frame(self, rgb: np.ndarray, depth: np.ndarray, semantics: np.ndarray | None = None) -> None:
        """Refuse what :meth:`add_frame` would refuse (shapes, non-numeric arrays, NaN, negative or almost no
        valid depth) without changing anything, e.g. before a labelling stage that keeps state across frames.

        Args:
            rgb: [H, W, 3]. depth: [H, W] metres. semantics: [H, W] ids or None.

        Raises:
            FrameError: what is wrong with the frame.
        """
        if semantics is not None and np.asarray(semantics).shape != (self.k.height, self.k.width):
            raise FrameError(f"semantics must be [{self.k.height}, {self.k.width}] ids, "
                             f"got {list(np.asarray(semantics).shape)}")
        self._tensors(rgb, depth, None)  # the value checks; without labels it records nothing

    # ------------------------------------------------------------------ main step
    def add_frame(self, rgb: np.ndarray, depth: np.ndarray, semantics: np.ndarray | None = None,
                  timestamp: float | None = None, gt_c2w: np.ndarray | None = None,
                  odom_c2w: np.ndarray | None = None) -> np.ndarray:
        """Track one frame and (on keyframes) update the map.

        Args:
            rgb: [H, W, 3] uint8 or float in [0, 1].
            depth: [H, W] metres, 0 = missing.
            semantics: [H, W] integer class ids (0 = unlabelled) or None.
            timestamp: seconds (defaults to the frame index).
            gt_c2w: [4, 4] ground-truth pose, kept for evaluation (used for tracking only when
                ``tracking.use_gt_pose``; fixes the map frame on the first frame).
            odom_c2w: [4, 4] camera-to-world pose from odometry (a robot's wheel odometry moved to the
                camera), or None. The tracking guess is then the last estimate moved by the odometry's
                motion since the last frame that had odometry (instead of constant velocity); when
                tracking fails (``tracking.odometry_fallback``) or its pose is refused by the odometry
                gate (``tracking.odometry_gate_*``) that guess is kept, and the frame is not mapped
                unless ``tracking.odometry_map_unverified``. Fixes the map frame on the first frame.

        Returns:
            [4, 4] estimated camera-to-world pose (float64).

        Raises:
            FrameError: bad shapes, NaN depth, almost no valid depth.
        """
        t0 = time.perf_counter()
        rgb_t, depth_t, sem_t = self._tensors(rgb, depth, semantics)
        idx = len(self.poses)
        gt = None if gt_c2w is None else np.asarray(gt_c2w, np.float64)
        odom = None if odom_c2w is None else check_pose(odom_c2w, "odom_c2w")
        residual, inliers, failed, source = float("nan"), 0, False, "tracking"
        self._agreement = float("nan")
        self._exposure = None
        if idx == 0:
            source = "first"
            c2w = next((p for p in (self.initial_c2w, odom, gt) if p is not None), np.eye(4))
        elif self.cfg.tracking.use_gt_pose and gt is not None:
            c2w, source = gt, "ground_truth"
        else:
            c2w, residual, inliers, failed, source = self._track(rgb_t, depth_t, self.odometry_guess(odom))
        self.poses.append(np.asarray(c2w, np.float64))
        self.gt_poses.append(gt)
        self.odom_poses.append(odom)
        self.timestamps.append(float(idx if timestamp is None else timestamp))
        t1 = time.perf_counter()
        # a pose that tracking did not confirm (the odometry's guess, kept because ICP failed or was refused by the
        # odometry gate) is not mapped unless tracking.odometry_map_unverified: measured on four exploration runs,
        # the labels and Gaussians such frames added put objects up to 19 cm off (6.2 cm at most without them)
        unverified = source in ("odometry", "odometry_refused")
        unmapped = failed or (unverified and not self.cfg.tracking.odometry_map_unverified)
        if sem_t is not None and self.cfg.mapping.label_votes and not unmapped:
            w2c = torch.as_tensor(np.linalg.inv(self.poses[-1]), dtype=torch.float32, device=self.device)
            self.map.vote(sem_t, depth_t, w2c, self.k)
        is_kf = (idx % self.cfg.mapping.keyframe_every == 0 or self._new_view(self.poses[-1])) and not unmapped
        added = pruned = 0
        loss = float("nan")
        if is_kf:
            added, pruned, loss = self._map_keyframe(idx, rgb_t, depth_t, sem_t)
        elif self.cfg.mapping.densify_every_frame and not unmapped:
            added = self._densify(idx, rgb_t, depth_t, sem_t, self.poses[-1])
        # frames not densified (unmapped, or densify_every_frame off) keep the last exposure: it changes slowly
        self.exposures.append(self._exposure if self._exposure is not None else
                              self.exposures[-1] if self.exposures else exposure_identity(self.device))
        t2 = time.perf_counter()
        entry = FrameLog(idx, self.timestamps[-1], is_kf, len(self.map), added, pruned, residual, inliers, failed,
                         loss, t1 - t0, t2 - t1, source, self._agreement, self._loop_note if is_kf else "")
        self.logs.append(entry)
        ce = self.cfg.checkpoint_every
        if ce > 0 and (idx + 1) % ce == 0:
            self.checkpoint(self.cfg.checkpoint_dir)
        return self.poses[-1].copy()

    def exposure_of(self, n: int) -> Tensor | None:
        """Frame ``n``'s exposure [2, 3] (gain, bias) when compensation is on, else None (renders as they are)."""
        if not self.cfg.mapping.exposure_compensation or n >= len(self.exposures):
            return None
        return self.exposures[n]

    def keyframe_expected(self, guess_c2w: np.ndarray) -> bool:
        """Whether the next frame will be a keyframe if it is tracked near ``guess_c2w`` ([4, 4], e.g. the
        constant-velocity or odometry guess): its index is a multiple of ``mapping.keyframe_every``, or the guess
        moved past ``mapping.keyframe_motion_*`` from the last keyframe. What the labelling stage asks before the
        frame is added (``LabelConfig.every``); the engine decides after tracking, with the tracked pose."""
        return len(self.poses) % self.cfg.mapping.keyframe_every == 0 or self._new_view(np.asarray(guess_c2w))

    def _new_view(self, c2w: np.ndarray) -> bool:
        """Whether ``c2w`` moved or turned past ``mapping.keyframe_motion_*`` from the last keyframe."""
        mc = self.cfg.mapping
        if not self.keyframes or (mc.keyframe_motion_m <= 0 and mc.keyframe_motion_deg <= 0):
            return False
        rel = np.linalg.inv(self.poses[self.keyframes[-1].index]) @ c2w  # numpy: no device round trip
        angle = math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(rel[:3, :3])) - 1) / 2))))
        return bool((mc.keyframe_motion_m > 0 and np.linalg.norm(rel[:3, 3]) > mc.keyframe_motion_m) or
                    (mc.keyframe_motion_deg > 0 and angle > mc.keyframe_motion_deg))

    def odometry_guess(self, odom: np.ndarray | None) -> np.ndarray | None:
        """The last estimate moved by the odometry's relative motion since the last frame with odometry."""
        if odom is None:
            return None
        for est, prev_odom in zip(reversed(self.poses), reversed(self.odom_poses), strict=True):
            if prev_odom is not None:
                return est @ (np.linalg.inv(prev_odom) @ odom)
        return None

    def _track(self, rgb: Tensor, depth: Tensor, odom_guess: np.ndarray | None = None
               ) -> tuple[np.ndarray, float, int, bool, str]:
        prev = self.poses[-1]
        if odom_guess is not None:
            guess = odom_guess
        else:
            guess = prev @ (np.linalg.inv(self.poses[-2]) @ prev) if len(self.poses) >= 2 else prev
        g = torch.as_tensor(guess, device=self.device)
        tc = self.cfg.tracking
        shrink = tc.render_scale_shrink if odom_guess is None else tc.render_scale_shrink_odometry
        out = self.render_view(guess, scale_shrink=shrink, semantic=False)
        sil = out.silhouette
        valid = sil > tc.min_silhouette
        md = out.depth / sil.clamp_min(1e-6)
        model_depth = torch.where(valid & (md > 0), md, torch.zeros_like(out.depth))
        icp_cfg = tc if odom_guess is None else replace(tc, prior_sigma_trans=tc.odometry_sigma_trans,
                                                         prior_sigma_rot=tc.odometry_sigma_rot)
        try:
            res = icp(model_depth, valid, g, depth, self.k, icp_cfg, out.rgb, rgb, graphs=self._icp_graphs)
            self._agreement = res.agreement
            # with odometry the tight prior holds the pose; low agreement there is mostly new geometry (an
            # exploring robot's 45-degree turns: 14-25 %), and falling back to odometry would only add its drift
            if odom_guess is None and res.agreement < tc.lost_agreement:
                raise TrackingError(f"tracking lost: only {res.agreement:.0%} of the frame's points on the map lie on "
                                    f"its surface (< {tc.lost_agreement:.0%})")
            icp_c2w = res.c2w.cpu().numpy()  # [4, 4] float64: the one host copy of the tracked pose
            if odom_guess is not None:
                refusal = self._odometry_gate(prev, odom_guess, icp_c2w)
                if refusal:
                    log.warning("frame %d: %s; keeping the odometry guess", len(self.poses), refusal)
                    return odom_guess, float("nan"), 0, False, "odometry_refused"
        except TrackingError as exc:
            if odom_guess is not None and tc.odometry_fallback:
                log.warning("frame %d: %s; keeping the odometry guess", len(self.poses), exc)
                return odom_guess, float("nan"), 0, False, "odometry"
            log.warning("frame %d: %s; keeping the previous pose, not mapping this frame", len(self.poses), exc)
            return prev, float("nan"), 0, True, "previous"
        if self.cfg.tracking.photometric_iters > 0:
            icp_c2w = photometric_refine(self.map.gaussians(), res.c2w, rgb, depth, self.k, self.cfg.renderer,
                                         self.cfg.tracking, self.backend).cpu().numpy()
        return icp_c2w, res.residual, res.inliers, False, "tracking"

    def _odometry_gate(self, prev: np.ndarray, odom_guess: np.ndarray, c2w: np.ndarray) -> str:
        """Why an ICP pose is farther from the odometry's guess than one odometry step can be wrong, or "".

        The limit is ``odometry_gate_trans`` (``_rot_deg``) plus ``odometry_gate_fraction`` of the step's own
        motion; 0 for both turns the gate off.
        """
        tc = self.cfg.tracking
        if tc.odometry_gate_trans <= 0 and tc.odometry_gate_rot_deg <= 0:
            return ""
        dev_t, dev_r = pose_error(odom_guess, c2w)
        step_t, step_r = pose_error(prev, odom_guess)
        lim_t = tc.odometry_gate_trans + tc.odometry_gate_fraction * step_t
        lim_r = tc.odometry_gate_rot_deg + tc.odometry_gate_fraction * step_r
        if (tc.odometry_gate_trans > 0 and dev_t > lim_t) or (tc.odometry_gate_rot_deg > 0 and dev_r > lim_r):
            return (f"ICP moved the pose {dev_t * 100:.1f} cm / {dev_r:.1f} deg from the odometry's guess, more than "
                    f"one odometry step can be off ({lim_t * 100:.1f} cm / {lim_r:.1f} deg)")
        return ""

    def _plane_depth_on(self) -> bool:
        return self.cfg.plane_depth and self.map.has_normals

    def _render(self, g: Gaussians, w2c: Tensor, plane: bool = True) -> RenderOutput:
        """Render ``g``; with ``plane`` and ``plane_depth`` the depth output blends each Gaussian's surface
        plane (:func:`~semantic_gs_slam.tracking.plane_depth_features`) instead of its centre depth."""
        if not (plane and self._plane_depth_on()):
            return self.backend(g, w2c, self.k, self.cfg.renderer)
        means_c = g.means @ w2c[:3, :3].T + w2c[:3, 3]
        pf = plane_depth_features(means_c, self.map.normals.to(means_c) @ w2c[:3, :3].T, self.k)
        c = 0 if g.semantic is None else g.semantic.shape[1]
        feats = pf if g.semantic is None else torch.cat([g.semantic, pf], -1)
        out = self.backend(Gaussians(g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb, feats), w2c, self.k,
                           self.cfg.renderer)
        depth = plane_depth_image(out.semantic[..., c:])  # sum w_i z_i(u, v), like the centre-depth channel
        return replace(out, depth=depth, semantic=out.semantic[..., :c] if c else None)

    def render_view(self, c2w: np.ndarray, scale_shrink: float = 1.0, semantic: bool = True) -> RenderOutput:
        """Render the map at a camera-to-world pose (gradients off); ``scale_shrink`` multiplies all radii;
        ``semantic=False`` skips the class columns (cheaper: tracking and densification do not need them)."""
        w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32, device=self.device)
        with torch.no_grad():
            g = self.map.gaussians()
            ls = g.log_scales.detach() + math.log(scale_shrink)
            g = Gaussians(g.means.detach(), g.quats.detach(), ls, g.logit_opacities.detach(), g.rgb.detach(),
                          None if g.semantic is None or not semantic else g.semantic.detach())
            return self._render(g, w2c)

    # ------------------------------------------------------------------ mapping
    def _densify(self, idx: int, rgb: Tensor, depth: Tensor, sem: Tensor | None, c2w: np.ndarray,
                 keyframe: bool = False) -> int:
        mc = self.cfg.mapping
        valid = depth > 0
        fine = None
        if sem is not None and mc.rare_label_fraction > 0:
            # small objects: labels on few of this frame's valid pixels are seeded at every pixel
            counts = torch.bincount(sem[valid].clamp_min(0), minlength=1)
            rare = torch.nonzero((counts > 0) & (counts < mc.rare_label_fraction * max(int(valid.sum()), 1)))[:, 0]
            rare = rare[rare > 0]
            fine = torch.isin(sem, rare) & valid if rare.numel() else None
        seed_depth, holes = depth, None
        if mc.seed_holes:
            seed_depth = fill_depth_holes(depth)
            holes = ~valid & (seed_depth > 0)
        if len(self.map) == 0:
            mask = valid if holes is None else valid | holes
        else:
            want_sem = keyframe and fine is not None and mc.semantic_densify
            out = self.render_view(c2w, semantic=want_sem)
            err = (out.depth - depth).abs() * valid
            med = float(err[valid].median()) if bool(valid.any()) else 0.0
            behind = (out.depth > depth) & (err > mc.densify_depth_factor * med)
            empty = out.silhouette < mc.densify_silhouette
            mask = valid & (empty | behind)
            if holes is not None:
                mask = mask | (holes & empty)
            if mc.exposure_compensation and (self.odom_poses[-1] is None or mc.exposure_with_odometry):
                # the frame's exposure against the map rendered at its pose; the new
                # Gaussians (and a keyframe's stored colour, _map_keyframe) take the map's exposure
                self._exposure = fit_exposure(out.rgb, out.silhouette, rgb, depth)
                rgb = to_map(rgb, self._exposure)
            if want_sem and out.semantic is not None:
                # where the map renders a small object's pixels with another label, add Gaussians there
                pred = self.map.labels_from_features(out.semantic / out.silhouette.clamp_min(1e-6)[..., None])
                mask = mask | (fine & (pred != sem))
        stride = mc.keyframe_pixel_stride if keyframe and mc.keyframe_pixel_stride > 0 else mc.pixel_stride
        pose = torch.as_tensor(c2w, dtype=torch.float32, device=self.device)
        return self.map.add_from_frame(rgb, seed_depth, sem, pose, self.k, mask, stride, idx, mc.radius_factor,
                                       mc.init_logit_opacity, fine)

    def _window(self, current: Keyframe) -> list[Keyframe]:
        n = self.cfg.mapping.window - 1
        if n <= 0 or len(self.keyframes) <= 1:
            return [current]
        from semantic_gs_slam.geometry import backproject

        k = self.k
        pts = backproject(current.depth, k.fx, k.fy, k.cx, k.cy)[::8, ::8].reshape(-1, 3)
        pts = pts[pts[:, 2] > 0].double()
        world = pts @ current.c2w[:3, :3].T + current.c2w[:3, 3]
        scores = []
        for kf in self.keyframes[:-1]:
            w2c = torch.linalg.inv(kf.c2w)
            pc = world @ w2c[:3, :3].T + w2c[:3, 3]
            z = pc[:, 2]
            u = k.fx * pc[:, 0] / z + k.cx
            v = k.fy * pc[:, 1] / z + k.cy
            inside = (z > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
            scores.append(float(inside.double().mean()))
        order = [i for i in np.argsort(scores)[::-1] if scores[i] > 0]
        r = min(self.cfg.mapping.window_random, n, max(len(order) - n, 0))
        # `r` slots go to other overlapping keyframes drawn at random, so areas first seen long ago keep
        # being optimised against their own views, not only against the latest (most overlapping) ones
        rest = order[n - r:]
        drawn = np.random.default_rng(current.index).choice(len(rest), r, replace=False) if r else []
        pick = order[:n - r] + [rest[int(i)] for i in drawn]
        return [current] + [self.keyframes[i] for i in pick]

    def _close_loop(self, idx: int, depth: Tensor) -> str:
        """Loop closure at a new keyframe (before it is added): register it against its most overlapping old
        keyframes (``loop.candidates``); verified drift is logged, added to the pose graph as loop edges and
        spread over the keyframes (poses, keyframe poses and the Gaussians they created move together).
        Returns a note for the frame's log."""
        lc = self.cfg.loop
        n_kf = len(self.keyframes)
        if not lc.enabled or n_kf < 2 or n_kf % lc.check_every or \
                (self.odom_poses[-1] is not None and not lc.with_odometry):
            return ""
        matches = find_loops(depth, self.poses[-1], idx, self.keyframes, self.k, lc, self.cfg.tracking,
                             [self.poses[kf.index] for kf in self.keyframes], self._icp_graphs)
        notes, correct, usable = [], [], []
        for m in matches:
            verdict = m.verdict(lc)
            notes.append(f"loop with frame {m.frame}: {verdict} ({m.correction_m * 100:.1f} cm, "
                         f"{m.correction_deg:.2f} deg, agreement {m.agreement_before:.0%} -> {m.agreement_after:.0%})")
            correct += [m] if verdict == "correct" else []
            usable += [m] if verdict in ("correct", "consistent") else []
        if correct:
            m = correct[0]
            log.warning("frame %d: drift found against the keyframe of frame %d: %.1f cm, %.2f deg; correcting the "
                        "trajectory and the map", idx, m.frame, m.correction_m * 100, m.correction_deg)
            self._apply_loop(idx, usable)  # verified registrations that agree with the tracking constrain too
        return "; ".join(notes)

    def _apply_loop(self, idx: int, matches: list[LoopMatch]) -> None:
        """Add the current keyframe and the loop edges to the pose graph, optimise it, move poses and Gaussians."""
        lc = self.cfg.loop
        old = [self.poses[kf.index] for kf in self.keyframes] + [self.poses[-1]]  # host copies of the kf poses
        cur = len(old) - 1
        loops = [Edge(m.candidate, cur, np.linalg.inv(old[m.candidate]) @ m.c2w, lc.loop_sigma_rot,
                      lc.loop_sigma_trans, "loop") for m in matches]
        seq = Edge(cur - 1, cur, np.linalg.inv(old[cur - 1]) @ old[cur], lc.sigma_rot, lc.sigma_trans)
        new, cost0, cost1 = optimise_graph(old, self.edges + [seq] + loops, fixed=0, iters=5)
        self.edges.extend(loops)  # the loop edges stay; the sequential one is added with the keyframe
        corr = [n @ np.linalg.inv(o) for n, o in zip(new, old, strict=True)]
        if lc.own_correction_sigmas > 0 and cur > 0:  # a difference within the loop edges' noise is noise
            extra_m, extra_deg = pose_error(corr[cur - 1] @ old[cur], new[cur])
            if extra_m < lc.own_correction_sigmas * lc.loop_sigma_trans and \
                    np.radians(extra_deg) < lc.own_correction_sigmas * lc.loop_sigma_rot:
                corr[cur] = corr[cur - 1]
                new[cur] = corr[cur] @ old[cur]
        starts = [kf.index for kf in self.keyframes] + [idx]
        self._move_frames(starts, corr)
        for kf, n in zip(self.keyframes, new[:-1], strict=False):
            kf.c2w = torch.as_tensor(n, device=self.device)
        self.map.move_by_frame(torch.as_tensor(starts, dtype=torch.int64, device=self.device),
                               torch.as_tensor(np.stack(corr), dtype=torch.float32, device=self.device))
        et, er = pose_error(np.eye(4), corr[-1])
        m = max(matches, key=lambda x: x.correction_m)
        self.loops.append({"frame": idx, "with_frame": m.frame, "found_cm": m.correction_m * 100,
                           "found_deg": m.correction_deg, "moved_cm": et * 100, "moved_deg": er,
                           "agreement_before": m.agreement_before, "agreement_after": m.agreement_after,
                           "edges": len(matches), "graph_cost_before": cost0, "graph_cost_after": cost1})

    def _map_keyframe(self, idx: int, rgb: Tensor, depth: Tensor, sem: Tensor | None) -> tuple[int, int, float]:
        mc = self.cfg.mapping
        self._loop_note = self._close_loop(idx, depth)
        c2w = self.poses[-1]
        added = self._densify(idx, rgb, depth, sem, c2w, keyframe=True)
        if self._exposure is not None:
            rgb = to_map(rgb, self._exposure)
        kf = Keyframe(idx, torch.as_tensor(c2w, device=self.device), rgb, depth, sem)
        if self.keyframes:
            lc = self.cfg.loop
            prev = self.poses[self.keyframes[-1].index]
            self.edges.append(Edge(len(self.keyframes) - 1, len(self.keyframes), np.linalg.inv(prev) @ c2w,
                                   lc.sigma_rot, lc.sigma_trans))
        self.keyframes.append(kf)
        window = self._window(kf)
        if mc.label_votes:
            self.map.voted_features(mc.min_votes)
        iters = mc.first_frame_iters if idx == 0 else mc.iters
        loss_v = self.optimise(window, iters)
        pruned = 0
        self._since_prune += 1
        if self._since_prune >= mc.prune_every:
            pruned = self.map.prune(mc.prune_opacity, mc.prune_max_scale)
            self._since_prune = 0
        return added, pruned, loss_v

    def optimise(self, window: list[Keyframe], iters: int) -> float:
        """Adam over all Gaussian parameters on the keyframes of ``window`` (cycled). Returns the last loss."""
        return self._optimise(window, iters)[0]

    def _optimise(self, window: list[Keyframe], iters: int, pose_deltas: list[tuple[Tensor, Tensor]] | None = None,
                  should_stop: Callable[[], bool] | None = None) -> tuple[float, int]:
        """:meth:`optimise`, returning (last loss, iterations done).

        Args:
            pose_deltas: per keyframe of ``window``, a rotation [3] (the vector part of a quaternion whose real
                part is 1) and a translation [3], leaf tensors that require grad: keyframe ``j`` is rendered
                at ``delta_j @ w2c_j`` and every delta but the first (the gauge) is optimised too, with the
                tracking's photometric learning rates and :func:`pose_prior` (``mapping.refine_pose_prior``).
                None: poses fixed.
            should_stop: asked before each iteration (cheap next to a render); True ends the loop there.
        """
        if iters <= 0 or len(self.map) == 0:
            return float("nan"), 0
        mc = self.cfg.mapping
        p = self.map.params
        groups = [
            {"params": [p["means3D"]], "lr": mc.lr_means}, {"params": [p["rgb_colors"]], "lr": mc.lr_rgb},
            {"params": [p["unnorm_rotations"]], "lr": mc.lr_rotations},
            {"params": [p["logit_opacities"]], "lr": mc.lr_opacity},
            {"params": [p["log_scales"]], "lr": mc.lr_scales},
            {"params": [p["semantic_features"]], "lr": mc.lr_semantic}]
        if pose_deltas is not None and len(pose_deltas) > 1:
            tc = self.cfg.tracking
            groups += [{"params": [d[0] for d in pose_deltas[1:]], "lr": tc.photometric_lr_rot},
                       {"params": [d[1] for d in pose_deltas[1:]], "lr": tc.photometric_lr_trans}]
        opt = torch.optim.Adam(groups, fused=self.device.type == "cuda")  # on CUDA one kernel per step instead
        # of ~50 (measured: 2.2 ms of host time per step at 1200x680, H200); the CPU keeps the default implementation
        w2cs = [torch.linalg.inv(kf.c2w).float() for kf in window]
        one = torch.ones(1, device=self.device)
        sem_imgs = [None if kf.sem is None else self.map.one_hot(kf.sem) for kf in window]  # [H, W, C]
        labelled = [None if kf.sem is None else (kf.sem > 0).float() for kf in window]
        sem_w = [None if (kf.sem is None or mc.semantic_balance <= 0) else _class_balance(kf.sem, mc.semantic_balance)
                 for kf in window]
        loss = None
        done = 0
        for it in range(iters):
            if should_stop is not None and should_stop():
                break
            j = it % len(window)
            kf = window[j]
            w2c = w2cs[j] if pose_deltas is None else \
                w2c_from_quat_trans(torch.cat([one, pose_deltas[j][0]]), pose_deltas[j][1]) @ w2cs[j]
            out = self._render(self.map.gaussians(), w2c, plane=mc.plane_depth_loss)
            loss = mapping_loss(out, kf.rgb, kf.depth, sem_imgs[j], labelled[j], sem_w[j], mc)
            if pose_deltas is not None and j > 0 and mc.refine_pose_prior > 0:
                loss = loss + pose_prior(pose_deltas[j][0], pose_deltas[j][1], mc.refine_pose_prior)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            with torch.device(self.device):  # some torch versions (2.11) make Adam's step counter on the default device
                opt.step()
            done += 1
        return (float(loss.detach()) if loss is not None else float("nan")), done  # one host copy per keyframe

    def refine(self, iters: int, poses: bool = False,
               should_stop: Callable[[], bool] | None = None) -> tuple[float, int]:
        """Offline map refinement after the run: ``iters`` Adam steps cycling over all keyframes.

        Args:
            poses: also optimise the keyframes' poses (a bundle adjustment through the renderer; the first
                keyframe stays where it is). Each keyframe's correction then moves the frames it starts, as a
                loop closure moves them. False: poses fixed.
            should_stop: asked before each iteration (a cancel request); True ends the refinement there,
                and what is done is kept.

        Returns:
            (the last loss, iterations done); (NaN, 0) when there is nothing to do. With ``poses`` the loss
            includes the pose prior (``mapping.refine_pose_prior``).
        """
        if not self.keyframes:
            return float("nan"), 0
        deltas = None
        if poses:
            deltas = [(torch.zeros(3, device=self.device, requires_grad=True),
                       torch.zeros(3, device=self.device, requires_grad=True)) for _ in self.keyframes]
        try:
            loss, done = self._optimise(self.keyframes, iters, deltas, should_stop)
        finally:  # the map was fitted at the moved poses: they go with it, also when an iteration raised
            if deltas is not None:
                self._apply_keyframe_deltas(deltas)
        self.map.prune(self.cfg.mapping.prune_opacity, self.cfg.mapping.prune_max_scale)
        return loss, done

    def _apply_keyframe_deltas(self, deltas: list[tuple[Tensor, Tensor]]) -> None:
        """Keyframe ``j`` moves to ``inv(delta_j @ w2c_j)``; every frame from it to the next keyframe takes the same
        world correction (``new @ inv(old)``). A delta still at zero (the gauge, a keyframe never visited, no
        iteration done) moves nothing, exactly."""
        old = [self.poses[kf.index] for kf in self.keyframes]
        corr = []
        one = torch.ones(1, dtype=torch.float64, device=self.device)
        with torch.no_grad():
            for j, (kf, (dq, dt), o) in enumerate(zip(self.keyframes, deltas, old, strict=True)):
                if j == 0 or not (bool(dq.any()) or bool(dt.any())):
                    corr.append(np.eye(4))
                    continue
                d = w2c_from_quat_trans(torch.cat([one, dq.double()]), dt.double())
                kf.c2w = torch.linalg.inv(d @ torch.linalg.inv(kf.c2w.double()))
                corr.append(kf.c2w.cpu().numpy() @ np.linalg.inv(o))
        self._move_frames([kf.index for kf in self.keyframes], corr)

    def _move_frames(self, starts: list[int], corr: list[np.ndarray]) -> None:
        """Frame ``f`` takes the world correction ``corr[k]`` ([4, 4]) of the last segment start ``starts[k] <= f``
        (frames before the first start take the first)."""
        for f in range(len(self.poses)):
            slot = int(np.searchsorted(starts, f, side="right")) - 1
            self.poses[f] = corr[max(slot, 0)] @ self.poses[f]

    # ------------------------------------------------------------------ output
    def semantic_ids(self) -> np.ndarray:
        """Per-Gaussian class id [N]: the largest optimised class column (0: none)."""
        return self.map.class_ids()

    def save(self, out_dir: str, ply: bool = True) -> dict[str, str]:
        """Write ``params.npz``, ``semantic.json`` (and ``map.ply``) into ``out_dir``; returns the paths."""
        os.makedirs(out_dir, exist_ok=True)
        paths = {"params": os.path.join(out_dir, "params.npz"), "semantic": os.path.join(out_dir, "semantic.json")}
        w2c = [np.linalg.inv(p) for p in self.poses]
        gt = [None if g is None else np.linalg.inv(g) for g in self.gt_poses]
        save_params(paths["params"], self.map, self.k, w2c, gt, [kf.index for kf in self.keyframes], self.timestamps)
        save_semantic_json(paths["semantic"], {i: c for i, c in self.classes.items() if i > 0})
        if ply:
            paths["ply"] = os.path.join(out_dir, "map.ply")
            export_ply(paths["ply"], self.map)
        return paths

    def checkpoint(self, ckpt_dir: str) -> None:
        """Write everything needed to :meth:`resume` (map, poses, keyframes, config).

        The files are written into ``<ckpt_dir>.tmp`` which then replaces ``ckpt_dir`` (the previous
        checkpoint is kept as ``<ckpt_dir>.old`` until the swap is done), so a crash mid-write leaves
        a complete checkpoint behind; :meth:`resume` falls back to ``.old`` when needed.
        """
        final = ckpt_dir.rstrip("/")
        ckpt_dir = final + ".tmp"
        shutil.rmtree(ckpt_dir, ignore_errors=True)
        os.makedirs(ckpt_dir)
        self.save(ckpt_dir, ply=False)
        kfs = self.keyframes
        state = {
            "poses": np.stack(self.poses), "timestamps": np.array(self.timestamps),
            "gt_poses": np.stack([g if g is not None else np.full((4, 4), np.nan) for g in self.gt_poses]),
            "odom_poses": np.stack([o if o is not None else np.full((4, 4), np.nan) for o in self.odom_poses]),
            "kf_index": np.array([kf.index for kf in kfs], np.int64),
            "kf_c2w": np.stack([kf.c2w.cpu().numpy() for kf in kfs]) if kfs else np.zeros((0, 4, 4)),
            "kf_rgb": np.stack([(kf.rgb.cpu().numpy() * 255 + 0.5).astype(np.uint8) for kf in kfs]) if kfs
            else np.zeros(0),
            "kf_depth": np.stack([kf.depth.cpu().numpy() for kf in kfs]) if kfs else np.zeros(0),
            "kf_sem": np.stack([kf.sem.cpu().numpy() if kf.sem is not None else np.full(kf.depth.shape, -1)
                                for kf in kfs]) if kfs else np.zeros(0),
            "map_semantic_ids_raw": self.map.semantic_ids.cpu().numpy(),
            "edge_ij": np.array([[e.i, e.j] for e in self.edges], np.int64).reshape(-1, 2),
            "edge_rel": np.stack([e.rel for e in self.edges]) if self.edges else np.zeros((0, 4, 4)),
            "edge_sigma": np.array([[e.sigma_rot, e.sigma_trans] for e in self.edges]).reshape(-1, 2),
            "edge_loop": np.array([e.kind == "loop" for e in self.edges], bool),
            "since_prune": np.array(self._since_prune),
            "exposures": torch.stack(self.exposures).cpu().numpy() if self.exposures else np.zeros((0, 2, 3))}
        np.savez_compressed(os.path.join(ckpt_dir, "state.npz"), **state)
        meta = {"config": self.given_cfg.to_dict(), "classes": {str(k): v for k, v in self.classes.items()},
                "frames": len(self.poses), "initial_c2w": None if self.initial_c2w is None else
                self.initial_c2w.tolist()}
        with open(os.path.join(ckpt_dir, "checkpoint.json"), "w") as fh:
            json.dump(meta, fh)
        old = final + ".old"
        shutil.rmtree(old, ignore_errors=True)
        if os.path.isdir(final):
            os.replace(final, old)
        os.replace(ckpt_dir, final)
        shutil.rmtree(old, ignore_errors=True)

    @classmethod
    def resume(cls, ckpt_dir: str, config: SlamConfig | None = None) -> SLAM:
        """Rebuild an engine from :meth:`checkpoint` output; continue with the next frame.

        Args:
            ckpt_dir: the checkpoint folder.
            config: overrides the stored configuration when given.

        Raises:
            MapFormatError: missing or inconsistent checkpoint files.
        """
        ckpt_dir = ckpt_dir.rstrip("/")
        if not os.path.isfile(os.path.join(ckpt_dir, "checkpoint.json")) and \
                os.path.isfile(os.path.join(ckpt_dir + ".old", "checkpoint.json")):
            ckpt_dir += ".old"  # a crash between the two renames of checkpoint()
        meta_p = os.path.join(ckpt_dir, "checkpoint.json")
        if not os.path.isfile(meta_p):
            raise MapFormatError(f"no checkpoint in {ckpt_dir} (checkpoint.json missing)")
        with open(meta_p) as fh:
            meta = json.load(fh)
        cfg = config or SlamConfig.from_dict(meta["config"])
        eng = cls(cfg, {int(k): v for k, v in meta["classes"].items()}, meta.get("initial_c2w"))
        arr = load_params(os.path.join(ckpt_dir, "params.npz"))
        st = load_params(os.path.join(ckpt_dir, "state.npz"))
        dev = eng.device
        eng.map = GaussianMap.from_arrays(arr, dev)
        eng.map.semantic_ids = torch.as_tensor(st["map_semantic_ids_raw"].astype(np.int64), device=dev)
        if len(st["poses"]) != meta["frames"]:
            raise MapFormatError(f"{ckpt_dir}: state has {len(st['poses'])} poses, "
                                 f"checkpoint.json says {meta['frames']}")
        eng.poses = [p for p in st["poses"]]
        eng.timestamps = [float(t) for t in st["timestamps"]]
        eng.gt_poses = [None if np.isnan(g).any() else g for g in st["gt_poses"]]
        odom = st["odom_poses"] if "odom_poses" in st else np.full((len(eng.poses), 4, 4), np.nan)
        eng.odom_poses = [None if np.isnan(o).any() else o for o in odom]
        for i in range(len(st["kf_index"])):
            sem = st["kf_sem"][i]
            eng.keyframes.append(Keyframe(int(st["kf_index"][i]), torch.as_tensor(st["kf_c2w"][i], device=dev),
                                          torch.as_tensor(st["kf_rgb"][i].astype(np.float32) / 255.0, device=dev),
                                          torch.as_tensor(st["kf_depth"][i], device=dev),
                                          None if (sem < 0).all() else
                                          torch.as_tensor(sem.astype(np.int64), device=dev)))
        eng._since_prune = int(st["since_prune"])
        ex = st["exposures"] if "exposures" in st and len(st["exposures"]) == len(eng.poses) else \
            np.tile(np.array(exposure_identity().tolist(), np.float32), (len(eng.poses), 1, 1))  # older checkpoints
        eng.exposures = [torch.as_tensor(e, dtype=torch.float32, device=dev) for e in ex]
        if "edge_ij" in st:
            eng.edges = [Edge(int(ij[0]), int(ij[1]), rel, float(sg[0]), float(sg[1]), "loop" if lp else "sequential")
                         for ij, rel, sg, lp in zip(st["edge_ij"], st["edge_rel"], st["edge_sigma"], st["edge_loop"],
                                                    strict=True)]
        return eng

    @staticmethod
    def load_map(out_dir: str) -> tuple[GaussianMap, dict[int, str], dict[str, np.ndarray]]:
        """Load a saved map (ours or SplaTAM / SGS-SLAM's ``params.npz`` + ``semantic.json``)."""
        arr = load_params(os.path.join(out_dir, "params.npz"))
        sp = os.path.join(out_dir, "semantic.json")
        classes = load_semantic_json(sp) if os.path.isfile(sp) else {}
        return GaussianMap.from_arrays(arr), classes, arr

    def stats(self) -> dict:
        """Summary for logs: frames, keyframes, Gaussians, last frame log."""
        return {"frames": len(self.poses), "keyframes": len(self.keyframes), "gaussians": len(self.map),
                "last": asdict(self.logs[-1]) if self.logs else None}
