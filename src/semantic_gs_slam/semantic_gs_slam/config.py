"""Dataclass configurations of the SLAM engine; every field documented, validated by ``check()``."""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from semantic_gs_slam.errors import ConfigError


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole camera (OpenCV convention: x right, y down, z forward), pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def check(self) -> None:
        """Raise :class:`ConfigError` when the values are not a usable camera."""
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"image size must be positive, got {self.width}x{self.height}")
        if not (math.isfinite(self.fx) and math.isfinite(self.fy) and self.fx > 0 and self.fy > 0):
            raise ConfigError(f"focal lengths must be finite and positive, got fx={self.fx} fy={self.fy}")
        if not (math.isfinite(self.cx) and math.isfinite(self.cy)):
            raise ConfigError(f"the principal point must be finite, got cx={self.cx} cy={self.cy}")

    def scaled(self, factor: float) -> Intrinsics:
        """The same camera for an image resized by ``factor`` (pixel-centre convention)."""
        w, h = round(self.width * factor), round(self.height * factor)
        return Intrinsics(w, h, self.fx * factor, self.fy * factor,
                          (self.cx + 0.5) * factor - 0.5, (self.cy + 0.5) * factor - 0.5)

    def as_matrix(self) -> list[list[float]]:
        """3x3 K matrix as nested lists."""
        return [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]]


def _check_device_dependent(name: str, value: Any, kind: type) -> None:
    """A device-dependent field (``DEVICE_DEFAULTS``) holds None (the device's value) or a ``kind`` (not a bool for
    int): a YAML ``"false"`` or ``auto`` would otherwise slip through as a string."""
    kinds = (int, float) if kind is float else kind  # a YAML 0 is a number too
    if value is None or (isinstance(value, kinds) and (kind is bool or not isinstance(value, bool))):
        return
    what = {bool: "true or false", int: "an integer", float: "a number"}[kind]
    raise ConfigError(f"{name} must be {what} or null (null: the device's value, config.DEVICE_DEFAULTS), "
                      f"got {value!r}")


@dataclass
class RendererConfig:
    """Pure-PyTorch tile renderer settings."""

    tile: int = 8  # tile edge in pixels
    near: float = 0.05  # metres; Gaussians closer to the camera are culled
    chunk: int = 128  # Gaussians composited per step (early stop between chunks)
    stop_transmittance: float = 1e-4  # a tile stops once every pixel's transmittance is below this
    batch_elements: int = 1_000_000  # bound on tiles x pixels x Gaussians per batch (memory)
    backend: str = "auto"  # "torch" (pure PyTorch, any device: the reference), "gsplat" (CUDA fast path),
    # "numba" (compiled CPU compositor) or "auto" (gsplat on CUDA when it imports, numba on the CPU when it is
    # installed, else torch)

    def check(self) -> None:
        if self.tile not in (4, 8, 16, 32):
            raise ConfigError(f"renderer.tile must be 4, 8, 16 or 32, got {self.tile}")
        if self.backend not in ("auto", "torch", "gsplat", "numba"):
            raise ConfigError(f"renderer.backend must be 'auto', 'torch', 'gsplat' or 'numba', got {self.backend!r}")
        if self.chunk <= 0 or self.batch_elements <= 0:
            raise ConfigError("renderer.chunk and renderer.batch_elements must be positive")


@dataclass
class TrackingConfig:
    """Per-frame camera tracking: point-to-plane ICP against the rendered model, then optional photometric steps."""

    icp_iters: int | None = None  # Gauss-Newton iterations per pyramid level (None: the device's, DEVICE_DEFAULTS)
    icp_levels: int = 2  # image pyramid levels (stride 2**level), coarse to fine
    icp_min_step: float = 1e-6  # a level ends once a step's largest component (rad or m) is below this
    icp_backend: str = "auto"  # the per-step sums: "torch" (the reference, any device), "numba" (compiled, CPU) or
    # "auto" (numba on the CPU when it is installed, else torch)
    icp_row_points: int = 160  # about this many live points per image row at the finest level (pixel stride
    # round(width / this)); the coarser levels halve it
    icp_max_dist: float = 0.10  # metres; associations farther apart are rejected
    icp_sigma_geo: float = 0.005  # metres; scale (and Huber threshold) of point-to-plane residuals
    icp_sigma_col: float = 0.05  # intensity units; scale (and Huber threshold) of photometric residuals (both
    # front ends)
    geometric_weight: float = 1.0  # weight of the point-to-plane term
    photometric_weight: float = 1.0  # weight of the photometric term inside the Gauss-Newton (0: geometry only; both
    # front ends)
    prior_sigma_trans: float = 0.05  # metres; weak Gaussian prior of the pose toward the constant-velocity guess
    prior_sigma_rot: float = 0.05  # radians
    render_scale_shrink: float = 0.7  # the model is rendered for tracking with Gaussian radii x this, on frames
    # without odometry (a handheld camera): full-size footprints blended bias depth toward the camera on oblique
    # surfaces, and on the Kinect sequence larger ones than 0.35 track better (docs/design/slam.md,
    # "Tracking": ATE 3.51 -> 3.28 cm, RPE 1.24 -> 0.87 cm, PSNR +0.36 dB; the synthetic home keeps its targets)
    render_scale_shrink_odometry: float = 0.35  # the same on frames tracked from an odometry guess (add_frame's
    # odom_c2w: a robot's stream): on the exploring robot's replays 0.7 put objects up to 11.5 cm off against 6.2
    normal_smoothing: int = 5  # box filter (pixels) on the model depth before vertices/normals (1: off)
    min_silhouette: float = 0.5  # model pixels used only where the map is this opaque (depth normalised by it)
    cuda_graphs: bool = True  # on CUDA, every 4 ICP steps are one captured CUDA graph (tracking.py: _IcpGraph)
    # instead of ~320 kernel launches and 4 host copies; off: the eager step loop (the reference, as on the CPU)
    min_correspondences: int = 100  # fewer raises TrackingError (the frame keeps the previous pose, is not mapped)
    lost_agreement: float = 0.25  # tracking is lost (reported; handled like too few correspondences) when fewer of
    # the frame's points that land on the map lie within 3 icp_sigma_geo of its surface at the tracked pose
    # (frames given odometry are never declared lost: the odometry prior holds them)
    photometric_iters: int = 0  # optional Adam steps on colour + depth L1 after ICP
    photometric_lr_rot: float = 4e-4
    photometric_lr_trans: float = 2e-3
    odometry_sigma_trans: float = 0.002  # metres; the prior's scale when the guess comes from odometry (add_frame's
    # odom_c2w): much tighter than the constant-velocity guess's, so partial views after a fast turn cannot drag
    # the pose (measured on the exploration camera: ATE 5.4 -> 3.8 cm, bench/slam_explore_replay.py)
    odometry_sigma_rot: float = 0.005  # radians
    odometry_fallback: bool = True  # frames given odom_c2w keep the odometry guess when ICP fails, e.g. a robot
    # turning in place faster than the map overlap allows; without odometry they keep the previous pose
    odometry_map_unverified: bool = False  # map frames whose pose is the odometry's guess (ICP failed or was
    # refused by the gate). Off: on four exploration runs such frames' labels and Gaussians put objects up to 19 cm
    # off (6.2 cm at most without them); the next tracked frame maps the view. On: a stream whose frames rarely
    # track still grows its map
    odometry_gate_trans: float = 0.05  # metres; frames given odometry: an ICP result farther than this (plus
    # odometry_gate_fraction of the step's own motion) from the odometry's guess is refused and the guess kept. One
    # step of wheel odometry is good to a few percent; ICP on a sparse, partial view can slide by decimetres
    # (measured on the exploring robot: single-frame jumps of 36 cm and 8 degrees). The frame's pose_source is then
    # odometry_refused. 0 (with odometry_gate_rot_deg 0) = no gate
    odometry_gate_rot_deg: float = 3.0  # degrees, the same for rotation
    odometry_gate_fraction: float = 0.1  # of the odometry step's translation (m) and rotation (degrees)
    use_gt_pose: bool = False  # debugging / mapping-only runs: take the ground-truth pose given to add_frame
    frontend: str = "render"  # "render": point-to-plane ICP against the map rendered at the guess (every frame
    # renders the map); "keyframe": the frame-rate front end (tracking/frontend.py) against the latest keyframe's
    # reference (its sensor depth and colour at its latest pose), with relocalisation when lost. With add_frame's
    # odom_c2w it starts from the odometry's guess instead of constant velocity; the odometry gate and prior are
    # "render"'s
    frontend_new_keyframe_coverage: float = 0.5  # "keyframe": a frame whose tracked points cover less of the
    # reference than this becomes a keyframe (a new reference), besides mapping.keyframe_every / keyframe_motion_*
    frontend_downsample: int = 1  # "keyframe": track on the frame shrunk by this factor (1, 2 or 4; edge-aware 2x2
    # means of depth): a 640x480 camera tracked at 320x240 costs the front end a quarter; the map keeps every pixel.
    # 0: auto, halved while the image stays at least 320 pixels wide
    frontend_sigma_geo_z2: float = 0.002  # "keyframe": 1/m; a point z metres deep weighs and agrees (lost or
    # trusted) at the scale max(1 cm, this * z^2) of its point-to-plane residual: a depth sensor's noise grows with
    # z^2 (a Kinect's, between two frames, about 0.002 z^2), so far points no longer read as disagreement. Chosen on
    # kitchen frames 0-249 (0, 0.002, 0.003, 0.005); 0: 1 cm everywhere
    frontend_trust_z2_per_roughness: float = 2.5  # "keyframe": against a reference whose depth roughness is r
    # (frontend_noisy_roughness), a frame's trust test (agreement) takes the z^2 scale max(frontend_sigma_geo_z2,
    # this * r): a noisier camera is judged at its own noise, and above frontend_sigma_geo_z2 the test associates a
    # point z deep up to max(max_dist, 3 * that scale * z^2) away; the pose is the same. A Kinect v1 (0.0007) stays
    # at 0.002 and the 5-cm gate; three times its noise (0.0036) reads at 0.009. Chosen on kitchen frames 0-249; 0: off
    frontend_model_smoothing: int = 1  # "keyframe": the reference depth averaged over this odd window (over
    # neighbours within 5 % of the centre's depth: no blur across edges; 1: raw), for every keyframe
    frontend_noisy_smoothing: int = 3  # "keyframe": ... and over this odd window for a keyframe whose depth is
    frontend_noisy_roughness: float = 0.0015  # rougher than this (1/m, frontend.depth_roughness: the median |depth -
    # the mean of its 4 neighbours| / depth^2; 0: never). A Kinect v1 at 320 x 240 reads 0.0007: its raw depth is
    # the reference. A camera with about twice its noise or more is smoothed: with three times, the raw reference
    # lost the kitchen; on clean frames smoothing bought nothing (docs/design/slam.md, "Real cameras")
    frontend_speckle_fill: float = 0.02  # "keyframe": a keyframe whose depth has more isolated holes than this
    # fraction of its pixels (a hole with 3 or 4 of its 4 neighbours valid) has them filled from its neighbours before
    # it becomes a reference: a normal needs its neighbours. A Kinect v1 reads 0.001-0.002; 30 % of its pixels
    # dropped at random (a speckled time-of-flight or stereo camera) about 0.17, and was lost from the first frames
    # without it; 0: never
    relocalise_every: int = 3  # "keyframe": a lost frame tries to relocalise on its first lost frame and then on
    # every k-th (each try costs about 100 ms of CPU against three keyframes); the others stay lost
    relocalise_candidates: int = 3  # keyframes tried per relocalisation: the best ranked by a 20x15 thumbnail of
    # depth and intensity (cheap), plus the one nearest the last trusted pose
    relocalise_confirm: int = 2  # trusted frames in a row (the relocalised one first) before mapping resumes
    velocity_max_scale: float = 3.0  # the constant-velocity guess takes the last step times the time since the last
    # frame over the time between the last two (frames dropped unevenly by a stream or a camera), up to this many
    # steps (a stalled stream's first frame after seconds: a longer extrapolation is a guess the ICP cannot start
    # from). 0: one step per frame, whatever the times
    lost_segment: bool = True  # "keyframe": lost frames are tracked among themselves from the first one's guessed
    # pose (their pose follows the camera instead of staying at the last trusted one, and is one more relocalisation
    # guess); once the map takes the camera back, the whole lost stretch is moved into the map's frame. Lost frames
    # are not mapped as they come: once joined, the segment's views join the backlog the refinement maps
    # (mapping.backlog_max > 0)
    lost_resume_after: int = 30  # "keyframe": a camera lost for this many frames in a row that no relocalisation
    # took back, whose lost segment tracked its last relocalise_confirm frames and started from a trustworthy guess
    # (the odometry's, or constant velocity extrapolated in full, within velocity_max_scale: not after a stalled
    # stream or a jump in time), resumes mapping on the segment's own track: the camera went on to ground no
    # keyframe saw (a quick turn) and would otherwise stay lost, mapping nothing, until it came back. The new ground
    # is mapped where the segment puts it, the first lost frame's guess being its anchor. 0: never (stay lost until
    # relocalised)
    reanchor_every: int = 15  # "keyframe": once mapping resumed on a lost segment's own track (lost_resume_after),
    # every k-th frame is relocalised against keyframes from before the loss (about 150 ms of CPU a try) until
    # one is, twice in a row (the next frame confirms): the resumed track, anchored at a guess, and everything mapped
    # on it then move into the map's frame (a camera carried elsewhere with no time passing resumes up to metres
    # off). 0: never
    relocalise_map_refine: bool = True  # "keyframe": a relocalised frame and the frames confirming it are refined by
    # the "render" front end's ICP against the map rendered at their pose (the map holds more of the scene than the
    # one keyframe they were relocalised against; a mapping thread finishes its job first). On the kitchen, after a
    # 60-frame gap: error 5.6-7.3 -> 4.8-5.7 cm; a kidnapped camera 0.8-1.8 -> 0.5-1.6 cm (test_recovery_real.py)

    def check(self) -> None:
        _check_device_dependent("tracking.icp_iters", self.icp_iters, int)
        if self.icp_backend not in ("auto", "torch", "numba"):
            raise ConfigError(f"tracking.icp_backend must be 'auto', 'torch' or 'numba', got {self.icp_backend!r}")
        if (self.icp_iters is not None and self.icp_iters < 0) or self.icp_levels < 1 or self.photometric_iters < 0 \
                or self.icp_row_points < 1 or not self.icp_min_step >= 0:
            raise ConfigError("tracking iteration counts and icp_min_step must be >= 0, icp_levels and icp_row_points "
                              ">= 1")
        for name in ("prior_sigma_trans", "prior_sigma_rot", "odometry_sigma_trans", "odometry_sigma_rot"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"tracking.{name} must be > 0, got {getattr(self, name)}")
        for name in ("odometry_gate_trans", "odometry_gate_rot_deg", "odometry_gate_fraction"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"tracking.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("render_scale_shrink", "render_scale_shrink_odometry"):
            if not 0 < getattr(self, name) < math.inf:
                raise ConfigError(f"tracking.{name} must be a finite number > 0, got {getattr(self, name)}")
        if self.frontend not in ("render", "keyframe"):
            raise ConfigError(f"tracking.frontend must be 'render' or 'keyframe', got {self.frontend!r}")
        for name in ("lost_resume_after", "reanchor_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"tracking.{name} must be an integer >= 0 (0: never), got {v!r}")
        if min(self.relocalise_every, self.relocalise_candidates, self.relocalise_confirm) < 1:
            raise ConfigError("tracking.relocalise_every, relocalise_candidates and relocalise_confirm must be >= 1")
        if not (math.isfinite(self.velocity_max_scale) and self.velocity_max_scale >= 0):
            raise ConfigError(f"tracking.velocity_max_scale must be a finite number >= 0, got "
                              f"{self.velocity_max_scale}")
        if self.frontend_downsample not in (0, 1, 2, 4):
            raise ConfigError(f"tracking.frontend_downsample must be 0 (auto), 1, 2 or 4, got "
                              f"{self.frontend_downsample!r}")
        if not (math.isfinite(self.frontend_sigma_geo_z2) and self.frontend_sigma_geo_z2 >= 0):
            raise ConfigError(f"tracking.frontend_sigma_geo_z2 must be a finite number >= 0, got "
                              f"{self.frontend_sigma_geo_z2!r}")
        for name in ("frontend_model_smoothing", "frontend_noisy_smoothing"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1 or v % 2 == 0:
                raise ConfigError(f"tracking.{name} must be an odd window >= 1, got {v!r}")
        if not (math.isfinite(self.frontend_trust_z2_per_roughness) and self.frontend_trust_z2_per_roughness >= 0):
            raise ConfigError(f"tracking.frontend_trust_z2_per_roughness must be a finite number >= 0, got "
                              f"{self.frontend_trust_z2_per_roughness!r}")
        if not (math.isfinite(self.frontend_noisy_roughness) and self.frontend_noisy_roughness >= 0):
            raise ConfigError(f"tracking.frontend_noisy_roughness must be a finite number >= 0, got "
                              f"{self.frontend_noisy_roughness!r}")
        if not 0 <= self.frontend_speckle_fill <= 1:
            raise ConfigError(f"tracking.frontend_speckle_fill must be in [0, 1], got {self.frontend_speckle_fill}")
        if not 0 <= self.frontend_new_keyframe_coverage <= 1:
            raise ConfigError("tracking.frontend_new_keyframe_coverage must be in [0, 1]")


@dataclass
class MappingConfig:
    """Keyframe mapping: densification, window optimisation, pruning."""

    keyframe_every: int = 4  # map on every k-th frame (and the first) ...
    keyframe_motion_m: float = 0.25  # ... and on any frame this far (m) or ...
    keyframe_motion_deg: float = 10.0  # ... this much turned from the last keyframe (a new view; 0 = off)
    defer_keyframes: bool = False  # SlamConfig.threaded: while the mapping thread is busy, a frame due as a keyframe
    # is tracked but not mapped; the next frame is due instead, so the map takes keyframes at the pace mapping keeps
    # (as ORB-SLAM's local mapping does) and add_frame never waits for the queue. A frame the front end needs as its
    # new reference (tracking.frontend_new_keyframe_coverage, or the reference keyframe_every frames old) becomes
    # one without being mapped. Off: the
    # synchronous run's keyframes
    backlog_motion_m: float = 0.06  # a deferred frame, or (defer_keyframes) a frame between keyframes while mapping
    # keeps up, is kept once it moved this far (m) ...
    backlog_motion_deg: float = 3.0  # ... or turned this much from the last kept frame or keyframe (times the
    # thinning factor; <= 0: off)
    backlog_max: int = 64  # frames kept as views (keyframe_every or backlog_motion_* apart, thinned to span the run
    # when full) for SLAM.refine / catch_up to map after the run; 0: none. Memory: one frame's colour, depth and
    # labels each
    densify_every_frame: bool | None = None  # also add Gaussians (without optimising) on non-keyframes (None: the
    # device's, DEVICE_DEFAULTS)
    iters: int | None = None  # Adam iterations per keyframe (None: the device's, DEVICE_DEFAULTS)
    first_frame_iters: int = 60  # iterations on the first frame
    window: int = 4  # keyframes optimised together (current + the most overlapping earlier ones)
    window_random: int = 2  # of the window's earlier keyframes, this many are drawn at random among the overlapping
    pixel_stride: int = 2  # new Gaussians seeded at every k-th pixel of the empty/occluding region
    keyframe_pixel_stride: int = 0  # the same on keyframes (0: pixel_stride). 1 on 7-Scenes (250 frames): ATE 3.98 ->
    # 3.60 cm, PSNR +0.3 dB, 2.5x the Gaussians and 31 % fewer frames per second on 2 cores: a setting for a GPU
    densify_silhouette: float = 0.5  # pixels below this silhouette get new Gaussians
    seed_holes: bool = True  # pixels without depth (a real sensor's near limit, shadows, dark or shiny surfaces) that
    # the map does not cover are seeded too, at depth filled in from their valid surroundings
    # (geometry.fill_depth_holes); their colour is then mapped like any other pixel's
    densify_depth_factor: float = 50.0  # ... or where the model is behind depth by > factor * median error
    radius_factor: float = 0.6  # new Gaussian std dev = radius_factor * pixel_stride * depth / f
    init_logit_opacity: float = 3.0
    rare_label_fraction: float = 0.02  # labels on < 2 % of a frame's valid pixels (small objects) are seeded
    # at every pixel (one-pixel radius) instead of every pixel_stride-th
    label_votes: bool = True  # every tracked frame's labels vote for the Gaussians it sees (depth-tested centres);
    # at each keyframe the class columns of Gaussians with >= min_votes votes are set to their vote shares, so the
    # map follows the majority over views, not the last keyframe (flickering labels, bench/slam_label_noise.py)
    min_votes: float = 2.0
    semantic_densify: bool = True  # keyframes also seed small-object pixels that the map renders with another label
    lr_means: float = 1e-4
    lr_rgb: float = 2.5e-3
    lr_semantic: float = 2.5e-3
    lr_opacity: float = 5e-2
    lr_scales: float = 5e-3
    lr_rotations: float = 1e-3
    w_colour: float = 2.0
    w_depth: float = 1.0
    plane_depth_loss: bool = False  # the depth loss on plane depth (SlamConfig.plane_depth): depth L1 6.4 -> 4.7 cm,
    # about 7 % slower
    w_semantic: float = 0.3
    semantic_balance: float = 0.5  # semantic L1 weighted by class frequency^-this per keyframe (0: off)
    w_ssim: float = 0.2  # share of (1 - SSIM) in the colour term
    ssim_backend: str = "auto"  # "torch" (grouped convolutions, any device: the reference), "numba" (compiled, float32
    # CPU images) or "auto" (numba on the CPU when it is installed, else torch)
    exposure_compensation: bool = True  # each tracked frame's exposure relative to the map (per-channel gain and
    # bias, exposure.fit) is taken out of its colour before it is mapped, and put back into renders for evaluation
    exposure_with_odometry: bool = False  # also on frames given odometry (a robot's stream): off, because on the
    # exploring robot's sparse views the fit is unreliable (a fixed-exposure simulated camera: gains up to 1.13)
    prune_opacity: float = 0.005
    prune_max_scale: float = 0.3  # metres; bigger Gaussians are removed
    prune_every: int = 5  # keyframes between pruning passes
    refine_coarse_share: float | None = None  # SLAM.refine(seconds=...): the share of a time budget spent at half
    # resolution before the rest at full resolution (None: the device's, DEVICE_DEFAULTS: 0.8 on the CPU, 0 on
    # CUDA, where it was not measured); 0: full resolution throughout. Chosen on kitchen frames 0-249
    # (docs/design/slam.md "Refinement at the end", bench/refine_schedule.py)
    refine_poses: bool = False  # SLAM.refine(poses=None) also optimises the poses of its views (keyframes and the
    # deferred frames it maps; a bundle adjustment through the renderer), each frame moved with the view before it.
    # The realtime profile turns it on: the views it maps after the run were placed by the front end alone
    # (docs/design/slam.md "Refinement at the end"); the CLI's --refine-poses / --no-refine-poses and the streaming
    # server's refine_poses choose per run
    refine_pose_prior: float = 0.001  # SLAM.refine(poses=True): weight w of a prior that holds each keyframe's pose
    # correction near zero, w * (|t|^2 / (1 cm)^2 + |q_v|^2 / 0.004^2) per rendered keyframe. Where pixels are too
    # coarse to see a pose error the poses would random-walk under Adam (2.7 cm on the synthetic home at 120x68);
    # 0.001 halves that at the 320x240 kitchen's quality (docs/design/slam.md "Refinement at the end"); 0 = no prior

    def check(self) -> None:
        if self.ssim_backend not in ("auto", "torch", "numba"):
            raise ConfigError(f"mapping.ssim_backend must be 'auto', 'torch' or 'numba', got {self.ssim_backend!r}")
        if self.window_random < 0:
            raise ConfigError("mapping.window_random must be >= 0")
        if self.keyframe_motion_m < 0 or self.keyframe_motion_deg < 0:
            raise ConfigError("mapping.keyframe_motion_m and keyframe_motion_deg must be >= 0 (0 = off)")
        if self.backlog_max < 0:
            raise ConfigError(f"mapping.backlog_max must be >= 0, got {self.backlog_max}")
        if self.keyframe_every < 1 or self.window < 1 or self.pixel_stride < 1:
            raise ConfigError("mapping.keyframe_every, window and pixel_stride must be >= 1")
        _check_device_dependent("mapping.iters", self.iters, int)
        _check_device_dependent("mapping.densify_every_frame", self.densify_every_frame, bool)
        if (self.iters is not None and self.iters < 0) or self.first_frame_iters < 0:
            raise ConfigError("mapping iteration counts must be >= 0")
        if self.keyframe_pixel_stride < 0:
            raise ConfigError("mapping.keyframe_pixel_stride must be >= 0 (0 = pixel_stride)")
        if not (math.isfinite(self.backlog_motion_m) and math.isfinite(self.backlog_motion_deg)):
            raise ConfigError(f"mapping.backlog_motion_m and backlog_motion_deg must be finite numbers (<= 0: off), "
                              f"got {self.backlog_motion_m}, {self.backlog_motion_deg}")
        _check_device_dependent("mapping.refine_coarse_share", self.refine_coarse_share, float)
        if self.refine_coarse_share is not None and not 0 <= self.refine_coarse_share < 1:
            raise ConfigError(f"mapping.refine_coarse_share must be in [0, 1) (the rest of a time budget renders at "
                              f"full resolution), got {self.refine_coarse_share}")
        if not (math.isfinite(self.refine_pose_prior) and self.refine_pose_prior >= 0):
            raise ConfigError(f"mapping.refine_pose_prior must be >= 0 (0 = no prior), got {self.refine_pose_prior}")


@dataclass
class LoopConfig:
    """Loop closure: each new keyframe is registered against the older keyframe it overlaps most; a
    disagreement with the tracked pose is drift, reported and spread over the keyframe pose graph."""

    enabled: bool = True
    with_odometry: bool = False  # also on frames given odometry (a robot's stream): off, because on the exploring
    # robot's sparse 45-degree-apart frames one raw depth image is too weak a reference (a false 49.6 cm
    # "correction" in 1 of 2 test runs with an 8-frame gap; docs/design/exploration.md)
    min_frame_gap: int = 30  # only keyframes at least this many frames older are loop candidates
    min_overlap: float = 0.4  # share of the new keyframe's points that must fall inside the candidate's view
    max_view_angle_deg: float = 25.0  # ... and the two cameras must look the same way within this (ICP between views
    # far apart is biased by what each sees that the other does not: 2-3 cm on the synthetic orbit's 60 degrees)
    max_view_distance_m: float = 0.6  # ... and stand within this of each other
    icp_iters: int = 15  # Gauss-Newton iterations per level of the keyframe-to-keyframe ICP (geometry only)
    icp_levels: int = 3
    icp_max_dist: float = 0.2  # metres; associations farther apart are rejected (the drift to be found)
    verify_dist: float = 0.03  # metres; after registration, a point within this of the candidate's surface agrees
    min_agreement: float = 0.6  # ... and at least this share of the overlapping points must agree
    min_correction_m: float = 0.01  # smaller disagreements are not drift worth a correction
    min_correction_deg: float = 0.5
    max_correction_m: float = 0.5  # larger ones are treated as a false match and ignored
    max_correction_deg: float = 15.0
    sigma_trans: float = 0.01  # metres; confidence of each sequential (tracked) keyframe-to-keyframe motion
    sigma_rot: float = 0.005  # radians
    loop_sigma_trans: float = 0.01  # metres; confidence of a verified loop registration: one raw depth image
    # registered against another, started at the reference poses, lands 1.2-2.5 cm / 0.4-0.6 deg from them on 7-Scenes
    # (median of 80 and 14 pairs), so a loop edge is no surer than a tracked keyframe step (ATE 4.05 -> 3.92 cm there;
    # half these sigmas 4.05, double 4.39)
    loop_sigma_rot: float = 0.005  # radians
    check_every: int = 1  # look for a loop at every k-th keyframe
    own_correction_sigmas: float = 2.0  # after a correction the new keyframe keeps its own place from the pose graph
    # only when that differs from where the previous keyframe's correction puts it by more than this many loop sigmas
    # (translation or rotation); else it moves with the previous keyframe, the difference being registration noise.
    # 0 = always its own. On 7-Scenes every correction (1-3 cm) made the new keyframe jump and the next frames jump
    # back to the map (one-frame RPE 0.8 -> 1.65 cm); at 2: PSNR +0.2-0.3 dB, ATE the same (docs/design/slam.md)
    candidates: int = 1  # old keyframes registered per check (the most overlapping, min_frame_gap // 2 apart)

    def check(self) -> None:
        if min(self.min_frame_gap, self.check_every, self.icp_levels, self.icp_iters, self.candidates) < 1:
            raise ConfigError("loop.min_frame_gap, check_every, icp_levels, icp_iters and candidates must be >= 1")
        if not self.own_correction_sigmas >= 0:
            raise ConfigError(f"loop.own_correction_sigmas must be >= 0, got {self.own_correction_sigmas}")
        if not 0 < self.min_overlap <= 1 or not 0 < self.min_agreement <= 1:
            raise ConfigError("loop.min_overlap and loop.min_agreement must be in (0, 1]")
        for name in ("sigma_trans", "sigma_rot", "loop_sigma_trans", "loop_sigma_rot", "verify_dist", "icp_max_dist",
                     "max_view_angle_deg", "max_view_distance_m"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"loop.{name} must be > 0, got {getattr(self, name)}")


# Settings whose default depends on the device the engine runs on (a field left at None takes its device's value
# when the engine starts: SlamConfig.resolved). Measured with bench/slam_gpu.py, docs/figures.md "SLAM on a GPU":
# on an H200 at 1200x680 (60 frames), the CUDA values take the engine from 23.5 to 33-36 FPS at ATE 0.12 cm,
# PSNR 34.1 dB, mIoU 0.97 (CPU values: 0.11 / 34.3 / 0.967). On the CPU at 300x170 the same values cost the
# synthetic home its mIoU target (0.897 < 0.92) and the Kinect data nothing, so the CPU keeps the thorough ones.
DEVICE_DEFAULTS: dict[str, dict[str, dict[str, Any]]] = {
    "cpu": {"tracking": {"icp_iters": 12},
            "mapping": {"iters": 10, "densify_every_frame": True, "refine_coarse_share": 0.8}},
    "cuda": {"tracking": {"icp_iters": 8},  # refine_coarse_share: measured on the CPU only; CUDA stays at full size
             "mapping": {"iters": 6, "densify_every_frame": False, "refine_coarse_share": 0.0}},
}


# Named sets of overrides (SlamConfig.with_profile, the CLI's and benchmarks' --profile, the streaming server's
# `profile` parameter). "realtime": every frame of a real camera at its rate on a robot's CPU: the frame-rate front end,
# mapping in a thread on keyframes chosen by motion and coverage, no per-frame densification. Figures:
# docs/figures.md "Real camera".
PROFILES: dict[str, dict[str, Any]] = {
    "default": {},
    "realtime": {"tracking": {"frontend": "keyframe", "frontend_downsample": 0}, "threaded": True,
                 "mapping": {"keyframe_every": 8, "densify_every_frame": False, "defer_keyframes": True,
                             "first_frame_iters": 15, "iters": 5, "refine_poses": True}},
}


def device_default(section: str, name: str, device_type: str) -> Any:
    """The value of a device-dependent field (``DEVICE_DEFAULTS``) on ``device_type`` (other than cuda: the CPU's)."""
    return DEVICE_DEFAULTS.get(device_type, DEVICE_DEFAULTS["cpu"])[section][name]


@dataclass
class SlamConfig:
    """Whole-engine configuration."""

    intrinsics: Intrinsics
    renderer: RendererConfig = field(default_factory=RendererConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    mapping: MappingConfig = field(default_factory=MappingConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    plane_depth: bool = True  # rendered depth (tracking, densification, evaluation; the mapping loss too with
    # mapping.plane_depth_loss) blends each Gaussian's seeded surface plane, not its centre depth (plane_depth_features)
    depth_min: float = 0.1  # metres; smaller depths are treated as missing
    depth_max: float = 10.0  # metres; larger depths are treated as missing
    checkpoint_every: int = 0  # frames between checkpoints (0: none), needs checkpoint_dir
    checkpoint_dir: str = ""
    threads: int = 0  # torch.set_num_threads when > 0 (the CLI and benchmark use 2); 0 leaves torch's setting
    seed: int = 0
    device: str = "auto"  # torch device of every tensor: "auto" (CUDA when present, else CPU), "cpu", "cuda[:N]"
    threaded: bool = False  # map in a worker thread (SLAM.finish drains it): add_frame returns once the frame is
    # tracked; keyframes (and, with label votes or densify_every_frame, the other frames' map updates) wait in a
    # bounded queue. Off: every frame is mapped inline (the reference: threaded runs that wait for each frame,
    # SLAM.drain, give the same poses). Needs tracking.frontend "keyframe" (the render front end reads the map)
    queue_size: int = 4  # mapping jobs the queue holds (threaded)
    queue_timeout_s: float = 2.0  # seconds a keyframe waits for room in a full queue; then it is not mapped (the
    # frame log's map_queue says "dropped", stats() counts it). Other frames' jobs never wait: dropped when full

    def check(self) -> None:
        """Validate all parts; raise :class:`ConfigError` naming the bad field."""
        self.intrinsics.check()
        self.renderer.check()
        self.tracking.check()
        self.mapping.check()
        self.loop.check()
        if not 0 < self.depth_min < self.depth_max:
            raise ConfigError(f"need 0 < depth_min < depth_max, got {self.depth_min}, {self.depth_max}")
        if self.checkpoint_every < 0 or (self.checkpoint_every > 0 and not self.checkpoint_dir):
            raise ConfigError("checkpoint_every > 0 needs checkpoint_dir")
        if self.threads < 0:
            raise ConfigError("threads must be >= 0")
        if self.threaded and self.tracking.frontend != "keyframe":
            raise ConfigError("threaded needs tracking.frontend 'keyframe' (the render front end reads the map "
                              "the mapping thread writes)")
        if self.queue_size < 1 or not self.queue_timeout_s >= 0:
            raise ConfigError("queue_size must be >= 1 and queue_timeout_s >= 0")
        if not re.match(r"^(auto|cpu|cuda(:\d+)?)$", str(self.device)):
            raise ConfigError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {self.device!r}")

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-serialisable)."""
        return asdict(self)

    @staticmethod
    def from_dict(d: dict[str, Any]) -> SlamConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise :class:`ConfigError`."""
        return _build(SlamConfig, d)

    def with_profile(self, name: str) -> SlamConfig:
        """A copy with the overrides of profile ``name`` (:data:`PROFILES`) applied; fields a profile does not name
        keep their values.

        Raises:
            ConfigError: unknown profile.
        """
        if name not in PROFILES:
            raise ConfigError(f"unknown profile {name!r}; known: {', '.join(PROFILES)}")
        d = self.to_dict()
        for section, vals in PROFILES[name].items():
            d[section] = {**d[section], **vals} if isinstance(vals, dict) else vals
        return SlamConfig.from_dict(d)

    def resolved(self, device_type: str) -> SlamConfig:
        """A copy with every device-dependent field left at None set to ``device_type``'s value
        (:data:`DEVICE_DEFAULTS`; devices other than ``cuda`` take the CPU's). Fields already set are kept."""
        table = DEVICE_DEFAULTS.get(device_type, DEVICE_DEFAULTS["cpu"])
        d = self.to_dict()
        for section, values in table.items():
            for name, value in values.items():
                if d[section][name] is None:
                    d[section][name] = value
        return SlamConfig.from_dict(d)

    def with_json(self, source: str) -> SlamConfig:
        """A copy with JSON overrides applied: ``source`` is a JSON file's path or, when it starts with ``{``, the
        JSON itself, e.g. ``{"tracking": {"icp_iters": 20}}``. A section's fields merge into the current ones (the
        others keep their values); a top-level field is replaced. The command line's and benchmarks' ``--config``.

        Raises:
            ConfigError: a missing or unreadable file, text that is not a JSON object, an unknown section or field,
                or a section given a non-object.
        """
        text = source.strip()
        if not text.startswith("{"):
            try:
                with open(source, encoding="utf-8") as fh:
                    text = fh.read()
            except OSError as exc:
                raise ConfigError(f"config overrides: cannot read {source!r} ({exc.strerror or exc}); give a JSON "
                                  "file or the JSON itself, e.g. '{\"tracking\": {\"icp_iters\": 20}}'") from exc
        try:
            over = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ConfigError(f"config overrides: not JSON ({exc})") from exc
        if not isinstance(over, dict):
            raise ConfigError(f"config overrides: need a JSON object of sections, got {type(over).__name__}")
        d = self.to_dict()
        for section, vals in over.items():
            if section not in d:
                raise ConfigError(f"config overrides: unknown section or field {section!r}; known: {', '.join(d)}")
            if isinstance(d[section], dict):
                if not isinstance(vals, dict):
                    raise ConfigError(f"config overrides: section {section!r} needs an object of fields, got "
                                      f"{vals!r}")
                d[section] = {**d[section], **vals}
            else:
                d[section] = vals
        return SlamConfig.from_dict(d)

    def with_overrides(self, sets: list[str]) -> SlamConfig:
        """A copy with ``SECTION.FIELD=VALUE`` (or top-level ``FIELD=VALUE``) overrides applied, each value
        parsed as the field's current type (booleans: true/false/1/0/yes/no). The benchmarks' ``--set``.

        Raises :class:`ConfigError` naming the override for an unknown field or a value of the wrong type."""
        d = self.to_dict()
        for item in sets:
            key, eq, val = item.partition("=")
            path = key.strip().split(".")
            where = d
            for part in path[:-1]:
                where = where.get(part) if isinstance(where, dict) else None
            if not eq or not isinstance(where, dict) or path[-1] not in where or isinstance(where[path[-1]], dict):
                raise ConfigError(f"override {item!r}: no setting {key!r} (SECTION.FIELD=VALUE, "
                                  "e.g. tracking.icp_iters=8)")
            cur = where[path[-1]]
            device_dependent = len(path) == 2 and path[-1] in DEVICE_DEFAULTS["cpu"].get(path[0], {})
            if device_dependent:  # parsed as its type; "none" / "null" / "auto" asks for the device's value
                if val.strip().lower() in ("none", "null", "auto"):
                    where[path[-1]] = None
                    continue
                cur = device_default(path[0], path[-1], "cpu")
            try:
                if isinstance(cur, bool):
                    low = val.strip().lower()
                    if low not in ("1", "0", "true", "false", "yes", "no"):
                        raise ValueError(val)
                    where[path[-1]] = low in ("1", "true", "yes")
                else:
                    where[path[-1]] = type(cur)(val)
            except ValueError as exc:
                raise ConfigError(f"override {item!r}: {val!r} is not of type {type(cur).__name__}") from exc
        return SlamConfig.from_dict(d)


def _build(cls: type, d: dict[str, Any]) -> Any:
    names = {f.name: f for f in fields(cls)}
    unknown = set(d) - set(names)
    if unknown:
        raise ConfigError(f"unknown {cls.__name__} field(s): {sorted(unknown)}")
    kw = {}
    sub = {"intrinsics": Intrinsics, "renderer": RendererConfig, "tracking": TrackingConfig, "mapping": MappingConfig,
           "loop": LoopConfig}
    for k, v in d.items():
        if k in sub and isinstance(v, dict):
            kw[k] = _build(sub[k], v)
        else:
            kw[k] = v
    return cls(**kw)
