"""The engine's keyframe mapping steps: seeding Gaussians (densification), choosing the window of keyframes,
optimising the map over it, and the offline refinement with its pose corrections.

:class:`MappingSteps` is a mixin of :class:`~semantic_gs_slam.slam.SLAM` (which orchestrates: it calls these
steps from ``add_frame`` on keyframes); the methods use the engine's state: ``cfg``, ``k``, ``device``, ``map``,
``keyframes``, ``poses``, ``odom_poses``, ``_exposure``, ``render_view`` and ``_render``.
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics
from semantic_gs_slam.geometry import fill_depth_holes
from semantic_gs_slam.io.exposure import fit as fit_exposure
from semantic_gs_slam.io.exposure import to_map
from semantic_gs_slam.mapping.loss import _class_balance, mapping_loss, pose_prior
from semantic_gs_slam.tracking.tracker import w2c_from_quat_trans


@dataclass
class Keyframe:
    """A mapped frame kept for window optimisation."""

    index: int
    c2w: Tensor  # [4, 4] float64
    rgb: Tensor  # [H, W, 3]
    depth: Tensor  # [H, W]
    sem: Tensor | None  # [H, W] int64


def _any_of(a: Callable[[], bool] | None, b: Callable[[], bool] | None) -> Callable[[], bool] | None:
    """A stop that says True when either of two stops (None: never) does."""
    if a is None or b is None:
        return b if a is None else a
    return lambda: a() or b()


def half_resolution(k: Intrinsics) -> Intrinsics:
    """The camera of :func:`half_resolution_view`'s images: each pixel the average of a 2x2 block (an odd last row
    or column dropped)."""
    return replace(k.scaled(0.5), width=k.width // 2, height=k.height // 2)


def half_resolution_view(kf: Keyframe) -> Keyframe:
    """``kf`` at half resolution (the refinement's coarse phase): colour [H/2, W/2, 3] averaged over 2x2 pixels,
    depth averaged where all four pixels have depth (else 0: missing, so no depth edge is blurred into a surface
    that is not there), labels the top-left pixel's of each block."""
    h, w = kf.depth.shape[0] // 2 * 2, kf.depth.shape[1] // 2 * 2
    rgb = kf.rgb[:h, :w].reshape(h // 2, 2, w // 2, 2, -1).mean((1, 3))
    d = kf.depth[:h, :w].reshape(h // 2, 2, w // 2, 2)
    full = (d > 0).all(3).all(1)
    depth = torch.where(full, d.mean((1, 3)), torch.zeros_like(full, dtype=d.dtype))
    sem = None if kf.sem is None else kf.sem[:h:2, :w:2].contiguous()
    return Keyframe(kf.index, kf.c2w, rgb.contiguous(), depth.contiguous(), sem)


def spread_order(n: int) -> list[int]:
    """0..n-1 in an order that covers the range evenly at every prefix: the middle, then the middles of the two
    halves, of the four quarters, ... (e.g. 7 -> [3, 1, 5, 0, 2, 4, 6])."""
    out: list[int] = []
    spans = deque([(0, n - 1)])
    while spans:
        lo, hi = spans.popleft()
        if lo > hi:
            continue
        mid = (lo + hi) // 2
        out.append(mid)
        spans.extend(((lo, mid - 1), (mid + 1, hi)))
    return out


class MappingSteps:
    """Densification, keyframe window and map optimisation of :class:`~semantic_gs_slam.slam.SLAM` (a mixin)."""

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
            if mc.exposure_compensation and (self.odom_poses[min(idx, len(self.odom_poses) - 1)] is None or
                                             mc.exposure_with_odometry):
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

    def optimise(self, window: list[Keyframe], iters: int) -> float:
        """Adam over all Gaussian parameters on the keyframes of ``window`` (cycled). Returns the last loss."""
        return self._optimise(window, iters)[0]

    def _optimise(self, window: list[Keyframe], iters: int, pose_deltas: list[tuple[Tensor, Tensor]] | None = None,
                  should_stop: Callable[[], bool] | None = None, coarse_stop: Callable[[], bool] | None = None
                  ) -> tuple[float, int]:
        """:meth:`optimise`, returning (last loss, iterations done).

        Args:
            pose_deltas: per keyframe of ``window``, a rotation [3] (the vector part of a quaternion whose real
                part is 1) and a translation [3], leaf tensors that require grad: keyframe ``j`` is rendered
                at ``delta_j @ w2c_j`` and every delta but the first (the gauge) is optimised too, with the
                tracking's photometric learning rates and :func:`pose_prior` (``mapping.refine_pose_prior``).
                None: poses fixed.
            should_stop: asked before each iteration (cheap next to a render); True ends the loop there.
            coarse_stop: asked before each iteration until it says True: until then the iterations render and
                compare at half resolution (:func:`half_resolution`), 2.3-2.6 times as many per second; from then on at
                full resolution. None: full resolution throughout.
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
        coarse = coarse_stop is not None and not coarse_stop()
        views = self._loss_targets(window)
        if coarse:
            k_half, half = half_resolution(self.k), [half_resolution_view(kf) for kf in window]
            views_half = self._loss_targets(half)
        loss = None
        done = 0
        for it in range(iters):
            if should_stop is not None and should_stop():
                break
            if coarse and coarse_stop():
                coarse = False
            j = it % len(window)
            kf, (sem_img, labelled, sem_w) = (half[j], views_half[j]) if coarse else (window[j], views[j])
            w2c = w2cs[j] if pose_deltas is None else \
                w2c_from_quat_trans(torch.cat([one, pose_deltas[j][0]]), pose_deltas[j][1]) @ w2cs[j]
            out = self._render(self.map.gaussians(), w2c, plane=mc.plane_depth_loss, k=k_half if coarse else None)
            loss = mapping_loss(out, kf.rgb, kf.depth, sem_img, labelled, sem_w, mc)
            if pose_deltas is not None and j > 0 and mc.refine_pose_prior > 0:
                loss = loss + pose_prior(pose_deltas[j][0], pose_deltas[j][1], mc.refine_pose_prior)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            with torch.device(self.device):  # some torch versions (2.11) make Adam's step counter on the default device
                opt.step()
            done += 1
        return (float(loss.detach()) if loss is not None else float("nan")), done  # one host copy per keyframe

    def _loss_targets(self, views: list[Keyframe]) -> list[tuple[Tensor | None, Tensor | None, Tensor | None]]:
        """Per view, the semantic targets of :func:`mapping_loss`: the labels one-hot [H, W, C], the labelled mask
        [H, W] and the class-balance weights (each None without labels)."""
        mc = self.cfg.mapping
        return [(None, None, None) if kf.sem is None else
                (self.map.one_hot(kf.sem), (kf.sem > 0).float(),
                 _class_balance(kf.sem, mc.semantic_balance) if mc.semantic_balance > 0 else None) for kf in views]

    def _seeded_view(self, idx: int, rgb: Tensor, depth: Tensor, sem: Tensor | None, c2w: np.ndarray
                     ) -> tuple[Keyframe, int]:
        """Seed frame ``idx``'s Gaussians as on a keyframe (its exposure fitted into ``_exposure``) and make it a
        view at ``c2w`` ([4, 4]) with its colour in the map's exposure; returns (the view, Gaussians added)."""
        added = self._densify(idx, rgb, depth, sem, c2w, keyframe=True)
        if self._exposure is not None:
            rgb = to_map(rgb, self._exposure)
        return Keyframe(idx, torch.as_tensor(c2w, device=self.device), rgb, depth, sem), added

    def catch_up(self, should_stop: Callable[[], bool] | None = None) -> list[Keyframe]:
        """Map the frames deferred during the run (``mapping.defer_keyframes``; :attr:`backlog`): each seeds
        Gaussians where the map lacks them, at its current pose (loop closures included), and becomes a view of
        the refinement. Not keyframes of the pose graph. Spread order (the middle of the run, then the quarters, ...),
        so a deadline leaves gaps spread out; what a stop leaves stays in the backlog.

        Returns:
            The views made, ready for :meth:`_optimise`.
        """
        backlog, self.backlog = self.backlog, []
        views = []
        order = spread_order(len(backlog))
        for n, j in enumerate(order):
            if should_stop is not None and should_stop():
                self.backlog = [backlog[i] for i in sorted(order[n:])]  # kept for a later refinement
                break
            idx, rgb, depth, sem = backlog[j]
            with self._poses_lock:
                c2w = self.poses[idx].copy()
            self._exposure = None
            view, _ = self._seeded_view(idx, rgb, depth, sem, c2w)
            if self._exposure is not None:
                self.exposures[idx] = self._exposure
                self.exposure_fitted[idx] = True
            views.append(view)
        self.caught_up += len(views)
        return views

    def refine(self, iters: int, poses: bool | None = None, should_stop: Callable[[], bool] | None = None,
               backlog: bool = True, backlog_stop: Callable[[], bool] | None = None, seconds: float = 0.0
               ) -> tuple[float, int]:
        """Map refinement after the run: ``iters`` Adam steps cycling over all keyframes (and the deferred frames).

        Args:
            poses: also optimise the poses of the views, the keyframes and the deferred frames mapped here (a
                bundle adjustment through the renderer; the first keyframe stays where it is). Each view's
                correction then moves the frames from it to the next view, as a loop closure moves them. False:
                poses fixed; None: ``mapping.refine_poses`` (on in the ``realtime`` profile).
            should_stop: asked before each deferred frame and each iteration (a cancel request, a deadline); True
                ends the refinement there, and what is done is kept.
            backlog: first map the frames deferred while the mapping thread was busy (:meth:`catch_up`) and
                refine over them too.
            backlog_stop: asked before each deferred frame as well (e.g. half of a time budget, so that the
                iterations get the rest); None: only ``should_stop``.
            seconds: a time budget (> 0), counted from this call: the refinement ends when it is spent (or when
                ``should_stop`` says so), the deferred frames get at most its first half, and its first
                ``mapping.refine_coarse_share`` renders at half resolution (coarse to fine: 2.3-2.6 times the
                iterations there; the last part at full resolution sharpens). 0: no time budget, every iteration
                at full resolution.

        Returns:
            (the last loss, iterations done); (NaN, 0) when there is nothing to do. With ``poses`` the loss
            includes the pose prior (``mapping.refine_pose_prior``).
        """
        if not (math.isfinite(seconds) and seconds >= 0):
            raise ValueError(f"refine: seconds must be a finite number >= 0 (0: no time budget), got {seconds!r}")
        if poses is None:
            poses = self.cfg.mapping.refine_poses
        coarse_stop = None
        if seconds > 0:
            t0 = time.monotonic()
            should_stop = _any_of(should_stop, lambda: time.monotonic() > t0 + seconds)
            backlog_stop = _any_of(backlog_stop, lambda: time.monotonic() > t0 + seconds / 2)
            share = self.cfg.mapping.refine_coarse_share  # the device's value filled in when the engine started
            coarse_stop = (lambda: time.monotonic() > t0 + share * seconds) if share > 0 else None
        self.drain(600.0)  # a mapping thread (SlamConfig.threaded) finishes first
        if not self.keyframes:
            return float("nan"), 0
        stop = _any_of(should_stop, backlog_stop)
        extra = self.catch_up(stop) if backlog else []
        views = self.keyframes + sorted(extra, key=lambda v: v.index)
        deltas = None
        if poses:  # views[0], the first keyframe, is the gauge (_optimise leaves its delta out)
            deltas = [(torch.zeros(3, device=self.device, requires_grad=True),
                       torch.zeros(3, device=self.device, requires_grad=True)) for _ in views]
        try:
            loss, done = self._optimise(views, iters, deltas, should_stop, coarse_stop)
        finally:  # the map was fitted at the moved poses: they go with it, also when an iteration raised
            if deltas is not None:
                self._apply_view_deltas(views, deltas)
        self.map.prune(self.cfg.mapping.prune_opacity, self.cfg.mapping.prune_max_scale)
        return loss, done

    def _apply_view_deltas(self, views: list[Keyframe], deltas: list[tuple[Tensor, Tensor]]) -> None:
        """View ``j`` (a keyframe or a deferred frame mapped by the refinement) moves to ``inv(delta_j @ w2c_j)``;
        every frame from it to the next view (by frame index) takes the same world correction (``new @ inv(old)``).
        A delta still at zero (the gauge, a view never rendered, no iteration done) moves nothing, exactly."""
        order = sorted(range(len(views)), key=lambda j: views[j].index)
        with self._poses_lock:
            old = [self.poses[views[j].index] for j in order]
        corr = []
        one = torch.ones(1, dtype=torch.float64, device=self.device)
        with torch.no_grad():
            for j, o in zip(order, old, strict=True):
                view, (dq, dt) = views[j], deltas[j]
                if not (bool(dq.any()) or bool(dt.any())):
                    corr.append(np.eye(4))
                    continue
                d = w2c_from_quat_trans(torch.cat([one, dq.double()]), dt.double())
                view.c2w = torch.linalg.inv(d @ torch.linalg.inv(view.c2w.double()))
                corr.append(view.c2w.cpu().numpy() @ np.linalg.inv(o))
        self._move_frames([views[j].index for j in order], corr)

    def _move_frames(self, starts: list[int], corr: list[np.ndarray]) -> None:
        """Frame ``f`` takes the world correction ``corr[k]`` ([4, 4]) of the last segment start ``starts[k] <= f``
        (frames before the first start take the first)."""
        with self._poses_lock:  # the caller's thread appends poses meanwhile (SlamConfig.threaded)
            for f in range(len(self.poses)):
                slot = int(np.searchsorted(starts, f, side="right")) - 1
                self.poses[f] = corr[max(slot, 0)] @ self.poses[f]
