"""The incremental SLAM engine: ``SLAM(config)``, ``add_frame(...) -> pose``, ``save``, checkpoints.

Per frame: tracking (constant-velocity guess, point-to-plane ICP against the depth rendered from
the map, optional photometric refinement), then on keyframes mapping (densify where the map is
empty or behind the measured depth, optimise a window of overlapping keyframes, prune).

This module orchestrates; the steps live with their concept: tracking in :mod:`semantic_gs_slam.tracking`,
densification and optimisation in :mod:`semantic_gs_slam.mapping.steps`, loop closure in
:mod:`semantic_gs_slam.loop.closing`, rendering in :mod:`semantic_gs_slam.render`.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from torch import Tensor

from semantic_gs_slam.config import Intrinsics, SlamConfig
from semantic_gs_slam.devices import require_cpu_kernel, resolve_device
from semantic_gs_slam.errors import FrameError, MapFormatError, MappingError, TrackingError
from semantic_gs_slam.geometry import pose_error, rigid_error, velocity_guess
from semantic_gs_slam.io.exposure import identity as exposure_identity
from semantic_gs_slam.io.host_frame import check_counts, host_frame
from semantic_gs_slam.loop.closing import LoopClosing
from semantic_gs_slam.loop.posegraph import Edge
from semantic_gs_slam.mapping.gaussian_map import (
    GaussianMap,
    export_ply,
    load_params,
    load_semantic_json,
    map_views,
    save_params,
    save_semantic_json,
    trajectory_from_params,
)
from semantic_gs_slam.mapping.steps import Keyframe, MappingSteps
from semantic_gs_slam.mapping.worker import MappingWorker
from semantic_gs_slam.render import Gaussians, RenderOutput, select_backend
from semantic_gs_slam.tracking.keyframe_tracking import KeyframeTracking
from semantic_gs_slam.tracking.map_start import MapStart
from semantic_gs_slam.tracking.tracker import (
    IcpGraphs,
    icp,
    icp_uses_numba,
    photometric_refine,
    plane_depth_features,
    plane_depth_image,
)

log = logging.getLogger("semantic_gs_slam")


def check_pose(c2w: np.ndarray, name: str) -> np.ndarray:
    """A [4, 4] finite rigid transform as float64, else :class:`FrameError` naming ``name``."""
    m = np.asarray(c2w, np.float64)
    if m.shape != (4, 4) or not np.all(np.isfinite(m)):
        raise FrameError(f"{name} must be a finite [4, 4] matrix, got shape {list(m.shape)}")
    if rigid_error(m, 1e-3, row_atol=1e-9):
        raise FrameError(f"{name} is not a rigid transform (rotation not orthonormal or last row not 0 0 0 1)")
    return m


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
    # tracking.frontend "keyframe" adds the pose sources lost (not trusted: the previous pose, not mapped),
    # relocalised and confirming (trusted, not mapped until tracking.relocalise_confirm frames in a row), recovered and
    # resumed (mapped again on the lost frames' own track after tracking.lost_resume_after lost frames)
    # (with either front end too while a start on a saved map is not confirmed: SLAM.from_map)
    track_coverage: float = float("nan")  # "keyframe" front end: share of the frame's points on the reference
    map_queue: str = "inline"  # inline (mapped in add_frame) | queued (SlamConfig.threaded; added, pruned, map_loss
    # and map_s are filled in when the mapping thread has run it) | dropped (the queue stayed full: not mapped) |
    # none (nothing to map)


class SLAM(MappingSteps, LoopClosing, KeyframeTracking, MapStart):
    """Semantic Gaussian-splatting RGB-D SLAM, fed frame by frame.

    The map frame is the first frame's pose: ``initial_c2w`` if given, else the ``odom_c2w`` passed
    with the first frame (so a robot's map is in its odometry frame), else the ``gt_c2w`` passed with
    the first frame, else the identity. An engine started on a saved map (:meth:`from_map`) keeps that
    map's frame instead: its first frames are relocalised in the map.
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
        self._frame_time = math.nan  # the time of the frame add_frame is tracking (seconds)
        self.keyframes: list[Keyframe] = []
        self.logs: list[FrameLog] = []
        self.edges: list[Edge] = []  # keyframe pose graph (nodes: positions in self.keyframes)
        self.loops: list[dict] = []  # every loop correction: frame, old keyframe frame, cm, deg, agreement
        self.exposures: list[Tensor] = []  # [2, 3] per frame: live colour = gain * map colour + bias (exposure.fit)
        self.exposure_fitted: list[bool] = []  # per frame: its exposure was fitted (densified, or the map's first
        # frame); the others' are read between their fitted neighbours (exposure_of)
        self._since_prune = 0
        self._loop_note = ""
        self._agreement = float("nan")
        self._exposure: Tensor | None = None  # this frame's, once densification has fitted it
        self._icp_graphs = IcpGraphs()  # captured ICP steps on CUDA (tracking.IcpGraphs); unused elsewhere
        # guards self.poses between the caller's thread (appends, reads of the last poses) and the mapping thread
        # (loop closure moves every pose: _move_frames); every other field is written by one thread only
        self._poses_lock = threading.RLock()
        self._last_kf_index = -1  # the last frame made a keyframe (the caller's thread; the map may lag, threaded)
        self.lost_frames: list[int] = []  # frames whose tracking was lost (not mapped)
        self.recoveries: list[list[int]] = []  # [first lost frame, frame tracking was trusted and mapped again]
        self.resumed: list[list[int]] = []  # the recoveries where mapping resumed on the lost frames' own track
        # (tracking.lost_resume_after), not relocalised in the map
        self.reanchored: list[list[float]] = []  # resumed tracks moved into the map's frame (tracking.reanchor_every):
        # [first frame moved, frame relocalised, cm, deg the camera moved]
        self.dropped_jobs: list[int] = []  # frames whose map update found the queue full (threaded)
        self.deferred_keyframes = 0  # frames due as keyframes but deferred while mapping was busy (defer_keyframes)
        self._kf_due = False  # a deferred keyframe is due on the next frame
        self.backlog: list[tuple[int, Tensor, Tensor, Tensor | None]] = []  # deferred frames kept for catch_up
        self._backlog_spacing = 1  # kept frames lie keyframe_every * this apart (doubles when the backlog fills)
        self.caught_up = 0  # deferred frames mapped by catch_up
        self._lost_views: dict[int, tuple] = {}  # a lost segment's views (host frames), kept until it is joined or not
        self._lost_at: int | None = None
        self._worker: MappingWorker | None = None
        self._fe_init()
        self.start_views: list[np.ndarray] = []  # from_map: the saved map's views, relocalised against, kept by save()
        self._ms_state = "done"  # from_map: relocalising | confirming | done (tracking/map_start.py)

    def __getstate__(self) -> dict:
        """Copies (copy.deepcopy, pickle) take the engine's state without its lock, its mapping thread and its
        captured ICP graphs (CUDA graphs cannot be copied; the copy captures its own on demand)."""
        state = self.__dict__.copy()
        state["_poses_lock"], state["_worker"] = None, None
        state["_icp_graphs"] = IcpGraphs(self._icp_graphs.max_graphs, self._icp_graphs.capture)
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._poses_lock = threading.RLock()

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
        check_counts(bad_rgb, bad_depth, negative, n_valid, depth_t.numel(), self.cfg.depth_min, self.cfg.depth_max)
        if sem_t is not None:
            for i in torch.unique(sem_t).tolist():
                if i > 0:  # unknown labels get a placeholder name in semantic.json
                    self.classes.setdefault(int(i), f"class_{int(i)}")
        return rgb_t, torch.where(valid, depth_t, torch.zeros_like(depth_t)), sem_t

    def _host_frame(self, rgb: np.ndarray, depth: np.ndarray, sem: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """:meth:`_tensors`' checks on the host, for the keyframe front end (which works on host arrays): returns
        our own copies, rgb [H, W, 3] float32 in [0, 1], depth [H, W] float32 metres (0 outside depth_min..max),
        labels [H, W] int64 or None. No device round trip: a frame that is not mapped never goes to the device,
        and on a GPU the tracker never waits behind the mapping thread's kernels."""
        k = self.k
        rgb, depth = np.asarray(rgb), np.asarray(depth)
        if rgb.shape != (k.height, k.width, 3):
            raise FrameError(f"rgb must be [{k.height}, {k.width}, 3] (intrinsics), got {list(rgb.shape)}")
        if depth.shape != (k.height, k.width):
            raise FrameError(f"depth must be [{k.height}, {k.width}] metres, got {list(depth.shape)}")
        if sem is not None and np.asarray(sem).shape != (k.height, k.width):
            raise FrameError(f"semantics must be [{k.height}, {k.width}] ids, got {list(np.asarray(sem).shape)}")
        try:
            sem_i = None if sem is None else np.asarray(sem).astype(np.int64)
        except (TypeError, ValueError) as exc:
            raise FrameError(f"frame arrays must be numeric: {exc}") from exc
        rgb_f, depth_f = host_frame(rgb, depth, self.cfg.depth_min, self.cfg.depth_max)
        if sem_i is not None:
            for i in np.unique(sem_i).tolist():
                if i > 0:  # unknown labels get a placeholder name in semantic.json
                    self.classes.setdefault(int(i), f"class_{int(i)}")
        return rgb_f, depth_f, sem_i

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
        if self._worker is not None:
            self._worker.raise_if_failed()  # a mapping thread's failure surfaces on the next call
        t0 = time.perf_counter()
        keyframe_fe = self.cfg.tracking.frontend == "keyframe"
        if keyframe_fe:  # checked on the host; on the device only when the frame is mapped or kept (lazily)
            host = self._host_frame(rgb, depth, semantics)
            rgb_t = depth_t = sem_t = None
            depth_np, rgb_np = self._fe_frame(host[1], host[0])
        else:
            rgb_t, depth_t, sem_t = self._tensors(rgb, depth, semantics)
        has_sem = semantics is not None
        idx = len(self.poses)
        self._frame_time = float(idx if timestamp is None else timestamp)  # the velocity guess scales by the times
        gt = None if gt_c2w is None else np.asarray(gt_c2w, np.float64)
        odom = None if odom_c2w is None else check_pose(odom_c2w, "odom_c2w")
        residual, inliers, failed, source = float("nan"), 0, False, "tracking"
        coverage = float("nan")
        self._agreement = float("nan")
        fe_tracked = False  # tracked by the keyframe front end (against a keyframe the back end may move)
        if self._ms_state != "done":  # started on a saved map and not relocalised in it yet (tracking/map_start.py)
            if rgb_t is None:
                rgb_t, depth_t, sem_t = self._device_frame(host)
            c2w, residual, inliers, failed, source, coverage = self._ms_track(
                idx, rgb_t, depth_t,
                host[0].astype(np.float64) if keyframe_fe else rgb_t.cpu().numpy().astype(np.float64),
                host[1].astype(np.float64) if keyframe_fe else depth_t.cpu().numpy().astype(np.float64))
        elif idx == 0:
            source = "first"
            c2w = next((p for p in (self.initial_c2w, odom, gt) if p is not None), np.eye(4))
        elif self.cfg.tracking.use_gt_pose and gt is not None:
            c2w, source = gt, "ground_truth"
        elif keyframe_fe and self._fe_views:
            c2w, residual, inliers, failed, source, coverage = self._track_keyframe(idx, rgb_np, depth_np,
                                                                                     self.odometry_guess(odom))
            fe_tracked = True
            if source in ("relocalised", "confirming", "recovered") and self.cfg.tracking.relocalise_map_refine:
                refined = self._refine_on_map(idx, host, c2w)
                if refined is not None:  # in the map's current frame: no reference-keyframe correction below
                    c2w, residual, inliers, fe_tracked = refined[0], refined[1], refined[2], False
        else:
            if rgb_t is None:  # the keyframe front end before its first reference (e.g. use_gt_pose on frame 0)
                rgb_t, depth_t, sem_t = self._device_frame(host)
            c2w, residual, inliers, failed, source = self._track(rgb_t, depth_t, self.odometry_guess(odom))
        with self._poses_lock:
            if source != "lost" and fe_tracked:  # the mapping thread may have moved the reference's
                # keyframe (loop closure) while this frame was tracked against its old pose: move the frame with it
                ref_idx, ref_c2w = self._fe_used
                if not np.array_equal(self.poses[ref_idx], ref_c2w):
                    c2w = self.poses[ref_idx] @ np.linalg.inv(ref_c2w) @ c2w
            self.poses.append(np.asarray(c2w, np.float64))
        if source == "lost" and self._fe_segment is not None and self._fe_segment.views[-1] == idx:
            self._keep_lost_view(idx, host)
        elif source in ("recovered", "resumed"):
            self._join_lost_views(idx)
        self.gt_poses.append(gt)
        self.odom_poses.append(odom)
        self.timestamps.append(self._frame_time)
        t1 = time.perf_counter()
        # a pose that tracking did not confirm (the odometry's guess, kept because ICP failed or was refused by the
        # odometry gate) is not mapped unless tracking.odometry_map_unverified: measured on four exploration runs,
        # the labels and Gaussians such frames added put objects up to 19 cm off (6.2 cm at most without them)
        unverified = source in ("odometry", "odometry_refused")
        unmapped = failed or (unverified and not self.cfg.tracking.odometry_map_unverified) or \
            source in ("relocalised", "confirming")
        self._note_lost(idx, failed or source == "relocalised", unmapped, source)
        due = idx % self.cfg.mapping.keyframe_every == 0 or self._new_view(self.poses[-1]) or self._kf_due
        needed = source in ("recovered", "resumed") or coverage < self.cfg.tracking.frontend_new_keyframe_coverage
        new_reference = False  # the front end takes this frame as its reference without mapping it now
        if (due or needed) and not unmapped and idx > 0 and self._mapping_busy():
            # mapping.defer_keyframes: the next frame is due instead; a reference the front end needs is taken
            # (or one keyframe_every frames old: a stale reference makes the front end drift)
            # (threaded, so the keyframe front end)
            stale = idx - self._fe_ref_idx >= self.cfg.mapping.keyframe_every
            self._kf_due, due, new_reference, needed = True, False, needed or stale, False
            self.deferred_keyframes += 1
        is_kf = (due or needed) and not unmapped
        if is_kf:
            self._kf_due = False
            self._last_kf_index = idx
        elif not unmapped and idx > 0 and self._defers() and self._keeps(idx):
            # a deferred keyframe, or a frame between keyframes far enough from the last kept one, is kept as a view
            # for the refinement whether or not mapping is busy: a camera read at 5 Hz lets the thread keep up, and
            # the refinement then had only the keyframes as views
            self._keep_deferred(idx, *self._device_frame(host))
        if (is_kf or new_reference) and keyframe_fe:
            self._fe_add_keyframe(idx, depth_np, rgb_np)
        if not unmapped and source != "ground_truth":
            self._fe_last_trusted = idx
        # frames not densified (unmapped, or densify_every_frame off) are not fitted: exposure_of reads theirs
        # between the fitted frames around them (until one after them is fitted: the last one before)
        self.exposures.append(self.exposures[-1] if self.exposures else exposure_identity(self.device))
        self.exposure_fitted.append(idx == 0 and len(self.map) == 0)  # a new map's first frame sets its exposure
        entry = FrameLog(idx, self.timestamps[-1], is_kf, len(self.map), 0, 0, residual, inliers, failed,
                         float("nan"), t1 - t0, 0.0, source, self._agreement, "", coverage)
        self.logs.append(entry)
        if self.reanchor_due is not None:  # before this frame's map update is queued (it reads the moved pose)
            self._reanchor(idx)
        wants_map = not unmapped and (is_kf or self.cfg.mapping.densify_every_frame or
                                      (has_sem and self.cfg.mapping.label_votes))
        if wants_map and rgb_t is None:
            rgb_t, depth_t, sem_t = self._device_frame(host)
        if not wants_map:
            entry.map_queue = "none"
        elif self._worker is None and not self.cfg.threaded:
            self._map_frame(idx, rgb_t, depth_t, sem_t, is_kf, entry)
        else:
            if self._worker is None:
                self._worker = MappingWorker(self.cfg.queue_size, self.cfg.queue_timeout_s)
            job = lambda: self._map_frame(idx, rgb_t, depth_t, sem_t, is_kf, entry)  # noqa: E731
            if self._worker.submit(job, wait=is_kf):
                entry.map_queue = "queued"
            else:
                entry.map_queue = "dropped"
                self.dropped_jobs.append(idx)
                log.warning("frame %d: mapping queue full (%d jobs); %s not mapped", idx, self.cfg.queue_size,
                            "keyframe" if is_kf else "frame")
        ce = self.cfg.checkpoint_every
        if ce > 0 and (idx + 1) % ce == 0:
            self.checkpoint(self.cfg.checkpoint_dir)
        with self._poses_lock:
            return self.poses[idx].copy()

    def _refine_on_map(self, idx: int, host: tuple[np.ndarray, np.ndarray, np.ndarray | None], c2w: np.ndarray
                       ) -> tuple[np.ndarray, float, int] | None:
        """A relocalised (or confirming) frame's pose ``c2w`` refined by the render front end's ICP against the map
        rendered there (``tracking.relocalise_map_refine``); None when the map does not confirm it or a mapping
        thread did not finish its job within ``queue_timeout_s`` (the front end's pose is kept).

        Returns:
            (pose [4, 4], residual (m), correspondences).
        """
        if not self._drain_for(idx, "relocalised pose not refined on the map"):  # the map must not change under
            return None  # the render: the mapping thread's jobs first
        rgb_t, depth_t, _ = self._device_frame(host)
        out, residual, inliers, failed, _ = self._track(
            rgb_t, depth_t, None, guess=c2w, on_failure="the map does not confirm the relocalised pose; the front "
                                                          "end's is kept")
        return None if failed else (out, residual, inliers)

    def _device_frame(self, host: tuple[np.ndarray, np.ndarray, np.ndarray | None]
                      ) -> tuple[Tensor, Tensor, Tensor | None]:
        """:meth:`_host_frame`'s arrays on the engine's device (on the CPU they share the arrays' memory, our own)."""
        rgb, depth, sem = host
        dev = self.device
        return (torch.as_tensor(rgb, device=dev), torch.as_tensor(depth, device=dev),
                None if sem is None else torch.as_tensor(sem, device=dev))

    def _keeps(self, idx: int) -> bool:
        """Whether frame ``idx`` (deferred, or between keyframes) goes into the backlog: ``mapping.backlog_max`` > 0
        and it lies ``keyframe_every`` frames past the last keyframe or kept frame, or moved or turned past
        ``mapping.backlog_motion_*`` from it (both times the thinning factor). A camera read at 5 or 15 Hz moves
        that far in fewer frames, so the refinement's views stay about as far apart as at 30 Hz (kitchen frames
        0-249 after 30 s, every 6th frame: 8 -> 23 views, PSNR 22.90 -> 24.47 dB; every 2nd: 15 -> 30 views,
        25.42 -> 25.95; every frame: 30 -> 35 views, 26.52 -> 26.50)."""
        mc = self.cfg.mapping
        if mc.backlog_max <= 0:
            return False
        last = max(self._last_kf_index, self.backlog[-1][0] if self.backlog else -1)
        if idx - last >= mc.keyframe_every * self._backlog_spacing:
            return True
        return self._new_view(self.poses[idx], since=last,
                              motion=(mc.backlog_motion_m * self._backlog_spacing,
                                      mc.backlog_motion_deg * self._backlog_spacing))

    def _keep_deferred(self, idx: int, rgb_t: Tensor, depth_t: Tensor, sem_t: Tensor | None) -> None:
        """Keep deferred frame ``idx`` (one :meth:`_keeps` accepted) for :meth:`catch_up`; a full backlog
        (``mapping.backlog_max``) drops every second frame and keeps half as many from then on, so it spans the
        whole run."""
        mc = self.cfg.mapping
        if len(self.backlog) >= mc.backlog_max:
            self.backlog = self.backlog[1::2]
            self._backlog_spacing *= 2
        self.backlog.append((idx, rgb_t, depth_t, sem_t))

    def _keep_lost_view(self, idx: int, host: tuple[np.ndarray, np.ndarray, np.ndarray | None]) -> None:
        """Keep lost frame ``idx``, a new view of the lost segment (tracking.lost_segment), until the segment is
        joined to the map or dropped (a new segment forgets the old one's); with ``mapping.backlog_max`` 0, none. At
        most ``backlog_max``: every second one is dropped when full."""
        if self.cfg.mapping.backlog_max <= 0:
            return
        if self._fe_segment.frames[0] == idx:
            self._lost_views.clear()
        if len(self._lost_views) >= self.cfg.mapping.backlog_max:
            self._lost_views = dict(list(self._lost_views.items())[1::2])
        self._lost_views[idx] = host

    def _join_lost_views(self, idx: int) -> None:
        """Frame ``idx`` recovered: the lost segment it was relocalised from is re-posed in the map's frame
        (:meth:`_fe_rejoin`) and its kept views join the backlog, mapped by :meth:`catch_up` (the refinement) at their
        poses then, as deferred keyframes are."""
        views = [v for v in self._fe_rejoin(idx) if v in self._lost_views]
        for v in views:
            self._keep_deferred(v, *self._device_frame(self._lost_views[v]))
        if views:
            self.backlog.sort(key=lambda b: b[0])
            log.info("frame %d: %d views of the lost stretch kept for the refinement (frames %s)", idx, len(views),
                     views)
        self._lost_views.clear()

    def _drain_for(self, idx: int, otherwise: str) -> bool:
        """Let a mapping thread finish its queued jobs before frame ``idx`` changes what they read (the map, the
        poses), at most ``queue_timeout_s``. Returns False (and logs ``otherwise`` with why) when they did not finish
        in time; re-raises when the thread failed."""
        if self._worker is None:
            return True
        try:
            self._worker.drain(self.cfg.queue_timeout_s)
        except MappingError as exc:
            if self._worker.failed:
                raise
            log.warning("frame %d: %s (%s)", idx, otherwise, exc)
            return False
        return True

    def _reanchor(self, idx: int) -> bool:
        """Apply the front end's confirmed re-anchoring (``reanchor_due``: a resumed track relocalised in the
        keyframes from before the loss): the correction that puts the relocalised frame on the pose found, taken
        relative to the keyframe it was found against now (a mapping thread may have moved it since), moves every
        frame from the resumed segment's first on, the keyframes among them and the Gaussians they made, and the
        pose-graph edges from the keyframes before to those after take the corrected relative poses (the old ones
        held the guessed anchor). A mapping thread finishes its jobs first; when it does not within
        ``queue_timeout_s``, the re-anchoring waits for the next frame (or :meth:`finish`). Returns whether it was
        applied."""
        first, at, kf, rel = self.reanchor_due
        if not self._drain_for(idx, "the resumed track is not moved yet"):
            return False
        self.reanchor_due = None
        with self._poses_lock:
            corr = self.poses[kf] @ rel @ np.linalg.inv(self.poses[at])
            before = self.poses[at].copy()
            self._move_frames([0, first], [np.eye(4), corr])
            after = self.poses[at].copy()
        slot = next((n for n, k in enumerate(self.keyframes) if k.index >= first), len(self.keyframes))
        for k in self.keyframes[slot:]:
            k.c2w = torch.as_tensor(corr, dtype=k.c2w.dtype, device=k.c2w.device) @ k.c2w
        kf_poses = [k.c2w.double().cpu().numpy() for k in self.keyframes]
        for e in self.edges:
            if e.i < slot <= e.j < len(kf_poses):
                e.rel = np.linalg.inv(kf_poses[e.i]) @ kf_poses[e.j]
        self.map.move_by_frame(torch.as_tensor([0, first], dtype=torch.int64, device=self.device),
                               torch.as_tensor(np.stack([np.eye(4), corr]), dtype=torch.float32, device=self.device))
        cm, deg = pose_error(before, after)
        self.reanchored.append([first, at, round(100 * cm, 1), round(deg, 2)])
        return True

    def _velocity_guess(self, prev2: np.ndarray, prev: np.ndarray) -> np.ndarray:
        """The constant-velocity guess [4, 4] for the frame being added: the last frame's pose ``prev`` moved on by the
        step from the one before (``prev2``), scaled by the frames' times (``tracking.velocity_max_scale``)."""
        dt_prev, dt = self._time_steps()
        return velocity_guess(prev2, prev, dt_prev, dt, self.cfg.tracking.velocity_max_scale)

    def _time_steps(self) -> tuple[float, float]:
        """(time between the last two frames, time from the last frame to the one being added), seconds; NaN both
        before two frames."""
        ts = self.timestamps
        return (ts[-1] - ts[-2], self._frame_time - ts[-1]) if len(ts) >= 2 else (math.nan, math.nan)

    def _steady_step(self) -> bool:
        """Whether the frame being added follows the last one by no more than ``tracking.velocity_max_scale`` times
        the step before (at least once; no stall, no jump in time): its constant-velocity guess is then extrapolated
        in full, a pose (a lost segment starting there may resume mapping, tracking.lost_resume_after)."""
        dt_prev, dt = self._time_steps()  # NaN before two frames: False
        return 0 < dt <= max(self.cfg.tracking.velocity_max_scale, 1.0) * dt_prev

    def _defers(self) -> bool:
        """Whether keyframes are deferred while the mapping thread is busy (mapping.defer_keyframes, threaded)."""
        return bool(self.cfg.threaded and self.cfg.mapping.defer_keyframes and self._worker is not None)

    def _mapping_busy(self) -> bool:
        """Whether keyframes are deferred now (:meth:`_defers`): the mapping thread has work."""
        return self._defers() and self._worker.pending > 0

    def _note_lost(self, idx: int, failed: bool, unmapped: bool, source: str = "") -> None:
        """Record lost frames (tracking failed; a frame relocalised at once counts too) and lost -> recovered spans
        (stats(): lost_frames, recoveries; resumed: the spans whose mapping resumed on the lost frames' own track,
        tracking.lost_resume_after)."""
        if failed:
            self.lost_frames.append(idx)
            if self._lost_at is None:
                self._lost_at = idx
        elif not unmapped and self._lost_at is not None:
            self.recoveries.append([self._lost_at, idx])
            if source == "resumed":
                self.resumed.append([self._lost_at, idx])
            else:
                log.warning("frame %d: tracking recovered (lost since frame %d)", idx, self._lost_at)
            self._lost_at = None

    def _map_frame(self, idx: int, rgb_t: Tensor, depth_t: Tensor, sem_t: Tensor | None, is_kf: bool,
                   entry: FrameLog) -> None:
        """Frame ``idx``'s map update (label votes, keyframe mapping or densification): in add_frame, or in the
        mapping thread (SlamConfig.threaded), where it fills in ``entry``'s mapping fields."""
        t1 = time.perf_counter()
        self._exposure = None
        with self._poses_lock:
            c2w = self.poses[idx].copy()
        if sem_t is not None and self.cfg.mapping.label_votes:
            w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32, device=self.device)
            self.map.vote(sem_t, depth_t, w2c, self.k)
        added = pruned = 0
        loss = float("nan")
        if is_kf:
            added, pruned, loss = self._map_keyframe(idx, rgb_t, depth_t, sem_t)
        elif self.cfg.mapping.densify_every_frame:
            added = self._densify(idx, rgb_t, depth_t, sem_t, c2w)
        if self._exposure is not None:
            self.exposures[idx] = self._exposure
            self.exposure_fitted[idx] = True
        entry.added, entry.pruned, entry.map_loss, entry.n_gaussians = added, pruned, loss, len(self.map)
        entry.loop = self._loop_note if is_kf else ""
        entry.map_s = time.perf_counter() - t1

    def drain(self, timeout: float = 60.0) -> None:
        """Wait until the mapping thread (SlamConfig.threaded) has mapped every queued frame, at most ``timeout``
        seconds (0: only check); a re-anchoring still due (``tracking.reanchor_every``: the thread was busy) is
        applied then. Returns at once when mapping is inline.

        Raises:
            MappingError: the mapping thread failed (the cause chained) or jobs were pending at the deadline.
        """
        if self._worker is not None:
            self._worker.drain(timeout)
        if self.reanchor_due is not None:
            self._reanchor(len(self.poses) - 1)

    def finish(self, timeout: float = 60.0) -> None:
        """Drain the mapping thread (see :meth:`drain`) and stop it; a later add_frame starts a new one. A
        re-anchoring still due (``tracking.reanchor_every``: the thread was busy) is applied then.

        Raises:
            MappingError: as :meth:`drain`.
        """
        w, self._worker = self._worker, None
        if w is not None:
            w.close(timeout)
        if self.reanchor_due is not None:
            self._reanchor(len(self.poses) - 1)

    def exposure_of(self, n: int) -> Tensor | None:
        """Frame ``n``'s exposure [2, 3] (gain, bias) when compensation is on, else None (renders as they are).

        A frame whose exposure was not fitted (not densified: a non-keyframe with ``densify_every_frame`` off, a
        deferred frame) takes the linear blend of the nearest fitted frames before and after it (one side's when
        the other has none). On the kitchen with the ``realtime`` profile (every 2nd of 500 frames, 30 s to refine)
        that is 19.7 -> 23.4 dB PSNR against keeping the last fitted exposure: the camera's exposure changes
        between keyframes.
        """
        if not self.cfg.mapping.exposure_compensation or n >= len(self.exposures):
            return None
        fitted = self.exposure_fitted
        if n >= len(fitted) or fitted[n]:
            return self.exposures[n]
        lo = next((i for i in range(n - 1, -1, -1) if fitted[i]), None)
        hi = next((i for i in range(n + 1, len(fitted)) if fitted[i]), None)
        if lo is None or hi is None:
            return self.exposures[n if lo is None and hi is None else (hi if lo is None else lo)]
        w = (n - lo) / (hi - lo)
        return self.exposures[lo] * (1.0 - w) + self.exposures[hi] * w

    def keyframe_expected(self, guess_c2w: np.ndarray) -> bool:
        """Whether the next frame will be a keyframe if it is tracked near ``guess_c2w`` ([4, 4], e.g. the
        constant-velocity or odometry guess): its index is a multiple of ``mapping.keyframe_every``, or the guess
        moved past ``mapping.keyframe_motion_*`` from the last keyframe, and a mapping thread that defers keyframes
        (``mapping.defer_keyframes``) is free to map it now. What the labelling stage asks before the frame is added
        (``LabelConfig.every``); the engine decides after tracking, with the tracked pose. While the thread is busy
        a due keyframe is deferred frame after frame: labelling each of them (most of a frame's time on a CPU) kept
        the thread busy and the engine at the labelling's pace."""
        if self._mapping_busy():
            return False
        return len(self.poses) % self.cfg.mapping.keyframe_every == 0 or self._kf_due or \
            self._new_view(np.asarray(guess_c2w))

    def _new_view(self, c2w: np.ndarray, since: int | None = None, motion: tuple[float, float] | None = None
                  ) -> bool:
        """Whether ``c2w`` moved or turned past ``motion`` (metres, degrees; None: ``mapping.keyframe_motion_*``)
        from frame ``since``'s pose (None: the last keyframe's); a limit <= 0 is off."""
        mc = self.cfg.mapping
        metres, degrees = (mc.keyframe_motion_m, mc.keyframe_motion_deg) if motion is None else motion
        since = self._last_kf_index if since is None else since
        if since < 0 or (metres <= 0 and degrees <= 0):
            return False
        with self._poses_lock:
            last = self.poses[since]
        rel = np.linalg.inv(last) @ c2w  # numpy: no device round trip
        angle = math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(rel[:3, :3])) - 1) / 2))))
        return bool((metres > 0 and np.linalg.norm(rel[:3, 3]) > metres) or (degrees > 0 and angle > degrees))

    def odometry_guess(self, odom: np.ndarray | None) -> np.ndarray | None:
        """The last estimate moved by the odometry's relative motion since the last frame with odometry."""
        if odom is None:
            return None
        for est, prev_odom in zip(reversed(self.poses), reversed(self.odom_poses), strict=True):
            if prev_odom is not None:
                return est @ (np.linalg.inv(prev_odom) @ odom)
        return None

    def _track(self, rgb: Tensor, depth: Tensor, odom_guess: np.ndarray | None = None,
               guess: np.ndarray | None = None, *, on_failure: str = "keeping the previous pose, not mapping this frame"
               ) -> tuple[np.ndarray, float, int, bool, str]:
        """ICP against the map rendered at ``odom_guess`` (tight prior, see add_frame), else at ``guess``, else at
        the constant-velocity guess. ``on_failure``: what the warning of a failed ICP says the caller does."""
        prev = self.poses[-1] if self.poses else guess  # no pose yet: a start on a saved map (map_start.py)
        if odom_guess is not None:
            guess = odom_guess
        elif guess is None:
            guess = self._velocity_guess(self.poses[-2], prev) if len(self.poses) >= 2 else prev
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
            log.warning("frame %d: %s; %s", len(self.poses), exc, on_failure)
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

    def _render(self, g: Gaussians, w2c: Tensor, plane: bool = True, k: Intrinsics | None = None) -> RenderOutput:
        """Render ``g`` with camera ``k`` (default: the engine's); with ``plane`` and ``plane_depth`` the depth output
        blends each Gaussian's surface plane (:func:`~semantic_gs_slam.tracking.tracker.plane_depth_features`)
        instead of its centre depth."""
        k = self.k if k is None else k
        if not (plane and self._plane_depth_on()):
            return self.backend(g, w2c, k, self.cfg.renderer)
        means_c = g.means @ w2c[:3, :3].T + w2c[:3, 3]
        pf = plane_depth_features(means_c, self.map.normals.to(means_c) @ w2c[:3, :3].T, k)
        c = 0 if g.semantic is None else g.semantic.shape[1]
        feats = pf if g.semantic is None else torch.cat([g.semantic, pf], -1)
        out = self.backend(Gaussians(g.means, g.quats, g.log_scales, g.logit_opacities, g.rgb, feats), w2c, k,
                           self.cfg.renderer)
        depth = plane_depth_image(out.semantic[..., c:])  # sum w_i z_i(u, v), like the centre-depth channel
        return replace(out, depth=depth, semantic=out.semantic[..., :c] if c else None)

    def render_view(self, c2w: np.ndarray, scale_shrink: float = 1.0, semantic: bool = True,
                    k: Intrinsics | None = None) -> RenderOutput:
        """Render the map at a camera-to-world pose (gradients off); ``scale_shrink`` multiplies all radii;
        ``semantic=False`` skips the class columns (cheaper: tracking and densification do not need them); ``k``:
        the camera (default: the engine's)."""
        w2c = torch.as_tensor(np.linalg.inv(c2w), dtype=torch.float32, device=self.device)
        with torch.no_grad():
            g = self.map.gaussians()
            ls = g.log_scales.detach() + math.log(scale_shrink)
            g = Gaussians(g.means.detach(), g.quats.detach(), ls, g.logit_opacities.detach(), g.rgb.detach(),
                          None if g.semantic is None or not semantic else g.semantic.detach())
            return self._render(g, w2c, k=k)

    # ------------------------------------------------------------------ mapping (the steps: mapping/, loop/)
    def _map_keyframe(self, idx: int, rgb: Tensor, depth: Tensor, sem: Tensor | None) -> tuple[int, int, float]:
        mc = self.cfg.mapping
        self._loop_note = self._close_loop(idx, depth)
        with self._poses_lock:
            c2w = self.poses[idx].copy()
        kf, added = self._seeded_view(idx, rgb, depth, sem, c2w)
        if self.keyframes:
            lc = self.cfg.loop
            with self._poses_lock:
                prev = self.poses[self.keyframes[-1].index].copy()
            self.edges.append(Edge(len(self.keyframes) - 1, len(self.keyframes), np.linalg.inv(prev) @ c2w,
                                   lc.sigma_rot, lc.sigma_trans))
        self.keyframes.append(kf)
        window = self._window(kf)
        if mc.label_votes:
            self.map.voted_features(mc.min_votes)
        iters = mc.first_frame_iters if idx == 0 and not self.start_views else mc.iters
        loss_v = self.optimise(window, iters)
        pruned = 0
        self._since_prune += 1
        if self._since_prune >= mc.prune_every:
            pruned = self.map.prune(mc.prune_opacity, mc.prune_max_scale)
            self._since_prune = 0
        return added, pruned, loss_v

    # ------------------------------------------------------------------ output
    def semantic_ids(self) -> np.ndarray:
        """Per-Gaussian class id [N]: the largest optimised class column (0: none)."""
        return self.map.class_ids()

    def save(self, out_dir: str, ply: bool = True) -> dict[str, str]:
        """Write ``params.npz``, ``semantic.json`` (and ``map.ply``) into ``out_dir``; returns the paths.
        A mapping thread is drained first (:meth:`drain`, 60 s).

        ``params.npz`` keeps this run's trajectory and keyframes, and in ``view_c2w`` the poses the map was seen
        from (the views of the map this run started on, if any, then this run's keyframes'): what :meth:`from_map`
        relocalises against."""
        self.drain()
        return self._save(out_dir, ply)

    def _save(self, out_dir: str, ply: bool = True, frames: int | None = None) -> dict[str, str]:
        """:meth:`save` without draining (the mapping thread's own jobs call it), of the first ``frames`` frames
        (None: all)."""
        os.makedirs(out_dir, exist_ok=True)
        paths = {"params": os.path.join(out_dir, "params.npz"), "semantic": os.path.join(out_dir, "semantic.json")}
        with self._poses_lock:
            n = len(self.poses) if frames is None else frames
            w2c = [np.linalg.inv(p) for p in self.poses[:n]]
            views = list(self.start_views) + [self.poses[kf.index].copy() for kf in self.keyframes]
        gt = [None if g is None else np.linalg.inv(g) for g in self.gt_poses[:n]]
        save_params(paths["params"], self.map, self.k, w2c, gt, [kf.index for kf in self.keyframes],
                    self.timestamps[:n], views)
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
        self.drain()
        with self._poses_lock:
            n = len(self.poses)
        self._write_checkpoint(ckpt_dir, n)

    def checkpoint_in_background(self, ckpt_dir: str, then: Callable[[BaseException | None], None]) -> bool:
        """:meth:`checkpoint` without waiting for it: with a mapping thread (``SlamConfig.threaded``) the checkpoint
        is that thread's next job, after the jobs queued before it, so it holds the frames tracked until this call
        and the map they made, while the caller goes on tracking. ``then(error)`` runs in the mapping thread once
        the files are written (``error`` None) or could not be (an ``OSError``, which does not stop mapping).
        Without a mapping thread the checkpoint is written now and ``then`` called here.

        Returns:
            True when written or queued; False when the mapping queue was full (nothing written, ``then`` not
            called).
        """
        if self._worker is None:
            try:
                self.checkpoint(ckpt_dir)
            except OSError as exc:
                then(exc)
            else:
                then(None)
            return True
        with self._poses_lock:
            n = len(self.poses)

        def job() -> None:
            try:
                self._write_checkpoint(ckpt_dir, n)
            except OSError as exc:
                log.warning("checkpoint of frame %d not written: %s", n - 1, exc)
                then(exc)
            else:
                then(None)

        return self._worker.submit(job, wait=False)

    def _write_checkpoint(self, ckpt_dir: str, n: int) -> None:
        """The files of :meth:`checkpoint` for the first ``n`` frames (the mapping thread idle or the caller)."""
        final = ckpt_dir.rstrip("/")
        ckpt_dir = final + ".tmp"
        shutil.rmtree(ckpt_dir, ignore_errors=True)
        os.makedirs(ckpt_dir)
        self._save(ckpt_dir, ply=False, frames=n)
        kfs = self.keyframes
        with self._poses_lock:
            poses = np.stack(self.poses[:n])
        state = {
            "poses": poses, "timestamps": np.array(self.timestamps[:n]),
            "gt_poses": np.stack([g if g is not None else np.full((4, 4), np.nan) for g in self.gt_poses[:n]]),
            "odom_poses": np.stack([o if o is not None else np.full((4, 4), np.nan) for o in self.odom_poses[:n]]),
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
            "exposures": torch.stack(self.exposures[:n]).cpu().numpy() if n else np.zeros((0, 2, 3)),
            "exposure_fitted": np.array(self.exposure_fitted[:n], bool)}
        np.savez_compressed(os.path.join(ckpt_dir, "state.npz"), **state)
        meta = {"config": self.given_cfg.to_dict(), "classes": {str(k): v for k, v in self.classes.items()},
                "frames": n, "initial_c2w": None if self.initial_c2w is None else
                self.initial_c2w.tolist(), "start_views": len(self.start_views),
                "start_pending": None if self.localised else self._ms_prior.tolist()}
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
        eng._last_kf_index = eng.keyframes[-1].index if eng.keyframes else -1
        ex = st["exposures"] if "exposures" in st and len(st["exposures"]) == len(eng.poses) else \
            np.tile(np.array(exposure_identity().tolist(), np.float32), (len(eng.poses), 1, 1))  # older checkpoints
        eng.exposures = [torch.as_tensor(e, dtype=torch.float32, device=dev) for e in ex]
        fit = st["exposure_fitted"] if "exposure_fitted" in st and len(st["exposure_fitted"]) == len(ex) else \
            np.ones(len(ex), bool)  # older checkpoints: each frame's exposure as it was kept
        eng.exposure_fitted = [bool(f) for f in fit]
        if "edge_ij" in st:
            eng.edges = [Edge(int(ij[0]), int(ij[1]), rel, float(sg[0]), float(sg[1]), "loop" if lp else "sequential")
                         for ij, rel, sg, lp in zip(st["edge_ij"], st["edge_rel"], st["edge_sigma"], st["edge_loop"],
                                                    strict=True)]
        n_start = int(meta.get("start_views", 0))  # started on a saved map: its views lead params.npz's view_c2w
        if n_start:
            views = map_views(arr)[:n_start]
            if meta.get("start_pending") is not None:  # not relocalised in it yet: relocalise again
                eng._ms_init(views, np.asarray(meta["start_pending"], np.float64))
            else:
                eng.start_views = views
        return eng

    @classmethod
    def from_map(cls, map_dir: str, config: SlamConfig, classes: dict[int, str] | None = None,
                 views: list[np.ndarray] | None = None, prior_c2w: np.ndarray | None = None) -> SLAM:
        """An engine that continues a saved map (:meth:`save`'s ``params.npz`` + ``semantic.json``, or a SplaTAM /
        SGS-SLAM one) in that map's frame, e.g. after a reboot, so positions in it (objects, a robot's ``map``
        frame) stay valid.

        The first frames are relocalised in the map (tracking/map_start.py): until a frame is relocalised against
        the map rendered at its saved views and confirmed on ``tracking.relocalise_confirm`` frames in a row, frames
        keep ``prior_c2w``, are logged ``lost`` (``tracking_failed``) and are not mapped, and :attr:`localised` is
        False; a view the map never saw stays lost (a warning per frame). Then every frame tracks and maps into the
        same Gaussians. ``gt_c2w`` / ``odom_c2w`` given with the first frame do not fix the frame here.

        Args:
            map_dir: folder holding ``params.npz`` (``semantic.json`` optional).
            config: the engine's settings (the camera may differ from the saved run's).
            classes: class names; the saved ``semantic.json``'s are added to them.
            views: [4, 4] camera-to-world poses to relocalise against (e.g. from a trajectory file); default: the
                map's own (:func:`~semantic_gs_slam.mapping.gaussian_map.map_views`).
            prior_c2w: [4, 4] the pose kept until relocalised (and one more guess); default: the saved run's last
                pose, else the first view.

        Raises:
            MapFormatError: no such folder, a missing or unreadable ``params.npz`` or ``semantic.json``, rows that do
                not agree, no poses to relocalise against.
            FrameError: ``views`` or ``prior_c2w`` are not rigid [4, 4] poses.
        """
        if not os.path.isdir(map_dir):
            raise MapFormatError(f"no saved map at {map_dir!r} (not a folder)")
        arr = load_params(os.path.join(map_dir, "params.npz"))
        sp = os.path.join(map_dir, "semantic.json")
        names = load_semantic_json(sp) if os.path.isfile(sp) else {}
        if views is None:
            views = map_views(arr)
        else:
            views = [check_pose(v, f"views[{i}]") for i, v in enumerate(views)]
            if not views:
                raise MapFormatError("views is empty: nothing to relocalise against")
        if prior_c2w is not None:
            prior = check_pose(prior_c2w, "prior_c2w")
        else:
            traj = trajectory_from_params(arr) if "cam_trans" in arr else []
            prior = traj[-1] if traj and np.all(np.isfinite(traj[-1])) else views[0]
        eng = cls(config, {**names, **(classes or {})})
        try:
            eng.map = GaussianMap.from_arrays(arr, eng.device)
        except (ValueError, TypeError) as exc:
            raise MapFormatError(f"{map_dir}/params.npz: malformed map arrays ({exc})") from exc
        # the saved Gaussians belong to no frame of this run: a loop closure's corrections (anchored at this run's
        # first keyframe, which stays put) leave them where they are
        eng.map.timestep = torch.full_like(eng.map.timestep, -1)
        eng._ms_init(views, prior)
        log.info("started on the saved map %s: %d Gaussians, %d views", map_dir, len(eng.map), len(eng.start_views))
        return eng

    @staticmethod
    def load_map(out_dir: str) -> tuple[GaussianMap, dict[int, str], dict[str, np.ndarray]]:
        """Load a saved map (ours or SplaTAM / SGS-SLAM's ``params.npz`` + ``semantic.json``)."""
        arr = load_params(os.path.join(out_dir, "params.npz"))
        sp = os.path.join(out_dir, "semantic.json")
        classes = load_semantic_json(sp) if os.path.isfile(sp) else {}
        return GaussianMap.from_arrays(arr), classes, arr

    def stats(self) -> dict:
        """Summary for logs: frames, keyframes, Gaussians, lost frames, lost -> recovered spans ([first lost frame,
        frame mapped again]; ``resumed``: those where mapping resumed on the lost frames' own track), frames whose
        map update the full queue dropped (threaded), whether the frames are in the map's frame (:attr:`localised`:
        False while a start on a saved map is not relocalised), the keyframe front end's noisy references (keyframes
        whose depth was smoothed: tracking.frontend_noisy_roughness) and the last reference's depth roughness, last
        frame log."""
        return {"frames": len(self.poses), "keyframes": len(self.keyframes), "gaussians": len(self.map),
                "localised": self.localised,
                "lost_frames": list(self.lost_frames), "recoveries": [list(r) for r in self.recoveries],
                "resumed": [list(r) for r in self.resumed],
                "dropped": list(self.dropped_jobs), "deferred_keyframes": self.deferred_keyframes,
                "backlog": len(self.backlog), "caught_up": self.caught_up,
                "noisy_references": len(self._fe_noisy), "reference_roughness": self._fe_roughness,
                "rejoined_frames": self.rejoined_frames, "reanchored": [list(r) for r in self.reanchored],
                "last": asdict(self.logs[-1]) if self.logs else None}
