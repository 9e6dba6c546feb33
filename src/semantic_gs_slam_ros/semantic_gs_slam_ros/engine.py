"""The SLAM engine as the streaming session uses it: :class:`semantic_gs_slam.slam.SLAM` kept in
memory for the whole run (no rclpy here)."""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from semantic_gs_slam_ros.errors import FrameRefusedError, StreamingError


class EngineAdapter:
    """Wraps :class:`semantic_gs_slam.slam.SLAM` in the session's ``SlamEngine`` protocol."""

    def __init__(self, slam: Any, labels: Any = None) -> None:
        self.slam = slam
        self.labels = labels  # semantic_gs_slam.labels.LabelStage or None (the streamed labels as they are)
        if labels is not None:
            labels.reserve_ids(slam.classes)

    def add_frame(self, rgb: np.ndarray, depth: np.ndarray, semantics: np.ndarray | None,
                  timestamp: float, odom_c2w: np.ndarray | None = None) -> np.ndarray:
        """The session's ``SlamEngine.add_frame``; a frame the engine cannot use raises
        :class:`~semantic_gs_slam_ros.errors.FrameRefusedError` and changes nothing (not the labelling stage either).
        Any other exception is the engine failing (a bug, out of memory), which ends the run."""
        from semantic_gs_slam.errors import FrameError

        try:
            return self._add_frame(rgb, depth, semantics, timestamp, odom_c2w)
        except FrameError as exc:
            raise FrameRefusedError(str(exc)) from exc

    def _add_frame(self, rgb: np.ndarray, depth: np.ndarray, semantics: np.ndarray | None,
                   timestamp: float, odom_c2w: np.ndarray | None) -> np.ndarray:
        if self.labels is not None:
            from semantic_gs_slam.labels import predict_pose

            if self.labels.stateful:  # it keeps state across frames: refuse a bad frame before it gets there
                self.slam.check_frame(rgb, depth, semantics)
            guess = self.slam.odometry_guess(odom_c2w) if odom_c2w is not None and self.slam.poses else None
            if guess is None:
                guess = odom_c2w if odom_c2w is not None and not self.slam.poses else \
                    predict_pose(self.slam.poses, self.slam.initial_c2w)
            semantics = self.labels(rgb, depth, semantics, guess, index=len(self.slam.poses),
                                    keyframe=self.slam.keyframe_expected(guess))
            if self.labels.mode != "dataset":
                self.slam.classes.update(self.labels.classes)
        if odom_c2w is None:
            return self.slam.add_frame(rgb, depth, semantics, timestamp)
        return self.slam.add_frame(rgb, depth, semantics, timestamp, odom_c2w=odom_c2w)

    def save_map(self, out_dir: str) -> tuple[str, str]:
        paths = self.slam.save(out_dir, ply=False)
        return paths["params"], paths["semantic"]

    def save_checkpoint(self, ckpt_dir: str) -> None:
        self.slam.checkpoint(ckpt_dir)

    def save_checkpoint_in_background(self, ckpt_dir: str, then: Callable[[BaseException | None], None]) -> bool:
        """The checkpoint written by the mapping thread between its jobs (the frames given so far), ``then(error)``
        called there once it is; without a mapping thread written now and ``then`` called here
        (:meth:`semantic_gs_slam.slam.SLAM.checkpoint_in_background`). False: not queued (the mapping queue was
        full)."""
        return self.slam.checkpoint_in_background(ckpt_dir, then)

    def refine(self, iters: int, poses: bool | None = None, should_stop: Callable[[], bool] | None = None,
               seconds: float = 0.0) -> int:
        """``iters`` Adam iterations over all keyframes, within ``seconds`` when > 0
        (:meth:`semantic_gs_slam.slam.SLAM.refine`; ``poses``: the views' poses too, None: the engine's
        ``mapping.refine_poses``); returns the iterations done (fewer when ``should_stop`` said so or the time ran
        out)."""
        return self.slam.refine(iters, poses=poses, should_stop=should_stop, seconds=seconds)[1]

    @property
    def num_gaussians(self) -> int:
        return len(self.slam.map)

    @property
    def localised(self) -> bool:
        """False while a run started on a saved map has not relocalised in it (its frames are not mapped)."""
        return bool(self.slam.localised)

    @property
    def num_keyframes(self) -> int:
        return len(self.slam.keyframes)

    @property
    def refines_poses(self) -> bool:
        """Whether :meth:`refine` with ``poses`` None optimises the views' poses too (``mapping.refine_poses``)."""
        return bool(self.slam.cfg.mapping.refine_poses)

    def run_note(self) -> str:
        """What the engine did with the frames it was given (the session logs it at the end of a run): frames
        tracked, keyframes, keyframes deferred while the mapping thread was busy (``mapping.defer_keyframes``) and
        what became of them, frames lost (and how many of them were re-posed in the map once it took the camera back:
        ``tracking.lost_segment``; how often mapping resumed on the lost frames' own track instead:
        ``tracking.lost_resume_after``; and how many of those tracks were later moved into the map's frame:
        ``tracking.reanchor_every``), map updates dropped by a full queue, and keyframes whose depth read as a
        noisy camera's (smoothed before tracking against them: ``tracking.frontend_noisy_roughness``)."""
        s = self.slam.stats()
        notes = ([f"{s['rejoined_frames']} re-posed in the map once recovered"] if s["rejoined_frames"] else []) + \
            ([f"mapping resumed {len(s['resumed'])} time(s) on the lost frames' own track, not relocalised in the map "
              f"(from frames {', '.join(str(a) for a, _ in s['resumed'])})"] if s.get("resumed") else []) + \
            ([f"{len(s['reanchored'])} resumed track(s) later relocalised and moved into the map's frame (from frames "
              f"{', '.join(str(int(a)) for a, *_ in s['reanchored'])})"] if s.get("reanchored") else [])
        rejoined = f" ({'; '.join(notes)})" if notes else ""
        noisy = (f", {s['noisy_references']} keyframes' depth smoothed as a noisy camera's (roughness "
                 f"{s['reference_roughness']:.4f} /m)" if s["noisy_references"] else "")
        return (f"{s['frames']} frames tracked, {s['keyframes']} keyframes, {s['deferred_keyframes']} keyframes "
                f"deferred while mapping was busy ({s['backlog']} kept for the refinement, {s['caught_up']} mapped "
                f"by it), {len(s['lost_frames'])} frames lost{rejoined}, {len(s['dropped'])} map updates "
                f"dropped{noisy}")

    def frame_report(self) -> tuple[bool, bool, str]:
        """(tracking lost, drift corrected, loop-closure note) of the last frame: what the session reports and
        counts."""
        if not self.slam.logs:
            return False, False, ""
        lg = self.slam.logs[-1]
        corrected = bool(self.slam.loops) and self.slam.loops[-1]["frame"] == lg.index
        return bool(lg.tracking_failed), corrected, lg.loop


def load_slam_config(path: str, intrinsics: tuple[float, float, float, float, int, int],
                     overrides: dict[str, Any] | None = None, profile: str = "") -> Any:
    """SlamConfig from a named ``profile`` (``semantic_gs_slam.config.PROFILES``; "" = none), a YAML file over it
    (any subset of its fields; "" = defaults), top-level ``overrides`` (e.g. the server's ``device`` parameter) and
    the camera."""
    import yaml

    from semantic_gs_slam.config import Intrinsics, SlamConfig
    from semantic_gs_slam.errors import ConfigError

    doc: dict[str, Any] = {}
    if path:
        try:
            with open(path, encoding="utf-8") as fh:
                doc = yaml.safe_load(fh) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise StreamingError(f"cannot read slam_config {path!r}: {exc}") from exc
    fx, fy, cx, cy, w, h = intrinsics
    cam = {"width": int(w), "height": int(h), "fx": fx, "fy": fy, "cx": cx, "cy": cy}
    if not isinstance(doc, dict):
        raise StreamingError(f"bad slam_config {path!r}: a mapping of SlamConfig fields expected, got "
                             f"{type(doc).__name__}")
    try:
        base = SlamConfig.from_dict({"intrinsics": cam}).with_profile(profile).to_dict() if profile else {}
    except ConfigError as exc:
        raise StreamingError(f"bad profile: {exc}") from exc
    for key, val in doc.items():  # the YAML over the profile, field by field within a section
        base[key] = {**base[key], **val} if isinstance(val, dict) and isinstance(base.get(key), dict) else val
    doc = {**base, **(overrides or {}), "intrinsics": cam}
    try:
        cfg = SlamConfig.from_dict(doc)
        cfg.check()
    except (ConfigError, TypeError) as exc:
        raise StreamingError(f"bad slam_config {path!r}: {exc}") from exc
    return cfg, Intrinsics


def camera_info_intrinsics(k: Any, d: Any, width: int, height: int, distortion_model: str = ""
                           ) -> tuple[tuple[float, float, float, float, int, int], str]:
    """The camera a ``sensor_msgs/CameraInfo`` describes: ((fx, fy, cx, cy, width, height), note).

    Args:
        k: the message's ``k`` (row-major 3x3 camera matrix). d: its ``d`` (distortion coefficients).
        width, height: its image size. distortion_model: its ``distortion_model`` (for the note only).

    Returns:
        The intrinsics, and a note for the log ("" when none): the images are taken as pinhole, so a message that
        publishes lens distortion is told to send rectified images instead.

    Raises:
        StreamingError: not a usable pinhole camera (a size of 0, a focal length that is not finite and positive,
            a principal point that is not finite); the message says which value.
    """
    from semantic_gs_slam.config import Intrinsics
    from semantic_gs_slam.errors import ConfigError

    try:
        vals = [float(v) for v in k]
    except (TypeError, ValueError) as exc:
        raise StreamingError(f"camera_info k is not 9 numbers: {exc}") from exc
    if len(vals) != 9:
        raise StreamingError(f"camera_info k must hold 9 numbers (3x3), got {len(vals)}")
    if width <= 0 or height <= 0:
        raise StreamingError(f"camera_info width and height must be the calibrated image size, got {width}x{height}")
    fx, fy, cx, cy = vals[0], vals[4], vals[2], vals[5]
    try:
        Intrinsics(int(width), int(height), fx, fy, cx, cy).check()
    except ConfigError as exc:
        raise StreamingError(f"camera_info k is not a usable camera: {exc}") from exc
    coeffs = [float(v) for v in d]
    note = ""
    if any(not np.isfinite(c) or abs(c) > 1e-6 for c in coeffs):
        note = (f"camera_info publishes lens distortion ({distortion_model or 'model not named'}: "
                f"{' '.join(f'{c:g}' for c in coeffs)}), which is not corrected: the images are taken as a pinhole "
                "camera's. Feed rectified images (image_proc's rectify) for the best tracking")
    return (fx, fy, cx, cy, int(width), int(height)), note


def scaled_intrinsics(k: tuple[float, float, float, float, int, int], width: int, height: int
                      ) -> tuple[float, float, float, float, int, int]:
    """Camera of the streamed images (``k``) after the server resized them to width × height."""
    fx, fy, cx, cy, w, h = k
    if not width or not height or (w, h) == (width, height):
        return k
    sx, sy = width / w, height / h
    return fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5, width, height


def make_labels(mode: str, onnx_model: str, intrinsics: Any, streamed_labels: bool, every: int = 1) -> Any:
    """The labelling stage for a run (:class:`semantic_gs_slam.labels.LabelStage`).

    Args:
        mode: ``auto`` | ``dataset`` | ``geometry`` | ``onnx`` | ``none`` (auto: the streamed labels when
            the server takes a ``semantic`` stream, else the COCO detector, else geometry).
        onnx_model: ONNX file for modes ``onnx`` and ``auto`` ("" = the installed COCO detector).
        intrinsics: the engine's :class:`~semantic_gs_slam.config.Intrinsics`.
        streamed_labels: whether a ``semantic`` stream comes with the images.
        every: geometry / onnx labels on every k-th engine frame only (``LabelConfig.every``).

    Raises:
        StreamingError: a bad mode or ``every``, a missing or unloadable model.
    """
    from semantic_gs_slam.errors import ConfigError
    from semantic_gs_slam.labels import LabelConfig, LabelStage

    try:
        return LabelStage(LabelConfig(mode=mode, onnx_model=onnx_model, every=every), intrinsics, streamed_labels)
    except ConfigError as exc:
        raise StreamingError(f"labels: {exc}") from exc


#: s; Python's lock hand-over for a server whose engine runs on the CPU. At Python's 0.005 its threads (executor,
#: frame writer, SLAM loop, mapping thread) waited up to 5 ms to run again after every wait, several times per
#: message: on 2 cores the server took 21 frames a second of a 30-Hz camera; at 0.0005 all 30 (docs/figures.md, "At a
#: camera's rate"). On CUDA a shorter interval made the realtime engine far slower (H200: 250 frames not done in
#: 110 s against 19.4 FPS; docs/design/slam.md, "Tried and dropped"): it keeps Python's
CPU_SWITCH_INTERVAL = 0.0005


def switch_interval_for(device: str) -> float:
    """The lock hand-over interval (s) for an engine on ``device`` (the server's ``device`` parameter: auto, cpu,
    cuda, cuda:N): :data:`CPU_SWITCH_INTERVAL` when it resolves to the CPU, 0 (leave Python's) otherwise, also when
    it cannot be had (the goal reports that)."""
    if device == "cpu":
        return CPU_SWITCH_INTERVAL
    from semantic_gs_slam.devices import resolve_device
    from semantic_gs_slam.errors import ConfigError

    try:
        return CPU_SWITCH_INTERVAL if resolve_device(device).type == "cpu" else 0.0
    except ConfigError:
        return 0.0


def prepare_renderer(device: str, log: Callable[[str], None]) -> None:
    """Load gsplat's CUDA code now when ``device`` resolves to CUDA and gsplat is installed.

    The first use after an install, or after gsplat's build flags changed, builds it: 1-2 minutes. The
    server calls this before it says it is ready, so that no goal waits for a build (a client gives the
    server ``server_timeout``, 30 s, to start a run). On the CPU, or with ``device: cpu``, it does nothing;
    a device that cannot be had is left to the goal, which reports it.
    """
    if device == "cpu":
        return
    from semantic_gs_slam.devices import resolve_device
    from semantic_gs_slam.errors import ConfigError
    from semantic_gs_slam.render.gsplat_backend import gsplat_available, load_gsplat_extension

    try:
        dev = resolve_device(device)
    except ConfigError:
        return
    if dev.type != "cuda" or not gsplat_available():
        return
    log("loading gsplat's CUDA code (built on its first use: 1-2 minutes)")
    t0 = time.monotonic()
    ok, why = load_gsplat_extension()
    log(f"gsplat's CUDA code loaded in {time.monotonic() - t0:.1f} s" if ok else
        f"gsplat's CUDA code did not build or load ({why}): renderer 'auto' will use the PyTorch tiles, "
        "'gsplat' will refuse the goal")


def make_engine(slam_config: str, wait_intrinsics: Callable[[], Any], cfg: Any,
                classes: dict[int, str] | None = None, resume_dir: str | None = None,
                overrides: dict[str, Any] | None = None, start_map: str = "",
                labels: tuple[str, str] = ("dataset", ""), labels_every: int = 1, profile: str = "") -> EngineAdapter:
    """Create (or resume) the engine for a run.

    Args:
        slam_config: YAML path of engine settings ("" = defaults).
        wait_intrinsics: returns (fx, fy, cx, cy, width, height) of the streamed images, or None.
        cfg: the session config (its width/height are the resize target).
        classes: semantic id → class name.
        resume_dir: checkpoint folder to resume from, or None (it wins over ``start_map``: a checkpoint of a run
            that started on a saved map holds that map and where the run got to).
        start_map: folder of a saved map (``params.npz``, ``semantic.json``) to continue in its frame
            (:meth:`semantic_gs_slam.slam.SLAM.from_map`: frames are mapped once one is relocalised in it), or "".
        overrides: top-level SlamConfig fields that win over the YAML (e.g. ``{"device": "cuda"}``).
        labels: (mode, onnx model path) of the labelling stage (:func:`make_labels`; ``cfg.use_semantic``
            says whether labels are streamed).
        labels_every: computed labels on every k-th engine frame only (``LabelConfig.every``; checked in every
            mode, though only geometry and onnx use it).
        profile: named SlamConfig overrides under the YAML (:func:`load_slam_config`; "" = none).

    Raises:
        StreamingError: no camera intrinsics, bad settings, unusable checkpoint, a ``start_map`` that is not a
            readable saved map.
    """
    from semantic_gs_slam.errors import ConfigError, SlamError
    from semantic_gs_slam.labels import LabelConfig
    from semantic_gs_slam.slam import SLAM

    try:  # the labelling stage's own check, in every mode (dataset labels never use the value)
        LabelConfig(every=labels_every).check()
    except ConfigError as exc:
        raise StreamingError(f"labels_every must be an integer >= 1, got {labels_every!r}") from exc
    k = wait_intrinsics()
    if k is None:
        raise StreamingError("no camera_info received: publish sensor_msgs/CameraInfo on 'camera_info'")
    config, _ = load_slam_config(slam_config, scaled_intrinsics(k, cfg.width, cfg.height), overrides, profile)
    stage = None
    if labels[0] != "dataset":
        stage = make_labels(labels[0], labels[1], config.intrinsics, bool(getattr(cfg, "use_semantic", False)),
                            labels_every)
    try:
        if resume_dir and os.path.isdir(resume_dir):
            return EngineAdapter(SLAM.resume(os.path.join(resume_dir, "engine"), config), stage)
        if start_map:
            return EngineAdapter(SLAM.from_map(start_map, config, classes), stage)
        return EngineAdapter(SLAM(config, classes), stage)
    except SlamError as exc:
        what = f"cannot continue the saved map {start_map!r}" if start_map and not (
            resume_dir and os.path.isdir(resume_dir)) else "cannot start the SLAM engine"
        raise StreamingError(f"{what}: {exc}") from exc


def pose_msg_fields(c2w: list[list[float]]) -> tuple[float, float, float, float, float, float, float]:
    """c2w [4,4] → (x, y, z, qw, qx, qy, qz)."""
    from semantic_gs_slam.geometry import rotmat_to_quat

    m = np.asarray(c2w, dtype=float)
    qw, qx, qy, qz = (float(v) for v in rotmat_to_quat(m[:3, :3]))
    return float(m[0, 3]), float(m[1, 3]), float(m[2, 3]), qw, qx, qy, qz
