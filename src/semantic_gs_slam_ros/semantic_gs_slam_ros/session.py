"""One streaming SLAM run (pure; no rclpy): images in, frames on disk, map out.

Threads (the ROS shell provides the first and the last):

* image callbacks → :meth:`StreamingSession.on_image` — convert, resize, match by timestamp,
  hand the frame to the disk writer; never blocks on disk or on SLAM;
* the writer thread (:class:`~semantic_gs_slam_ros.writer.AsyncFrameWriter`) — writes the files
  and queues the fully written frame for SLAM;
* the caller of :meth:`StreamingSession.run` (the action's execute thread) — the SLAM loop: feeds
  written frames to the engine kept in memory (never a process per frame), checkpoints every N
  frames, exports the map every M frames and at the end, and returns the result.
"""

from __future__ import annotations

import collections
import json
import math
import os
import shutil
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from semantic_gs_slam.errors import MAX_BAD_IN_A_ROW
from semantic_gs_slam_ros.errors import FrameRefusedError, ImageFormatError, OutputError, StreamingError
from semantic_gs_slam_ros.images import depth_to_mm, resize_nearest, resize_rgb, rgb_of
from semantic_gs_slam_ros.lag import LagAction, LagController
from semantic_gs_slam_ros.sync import FrameMatcher
from semantic_gs_slam_ros.writer import AsyncFrameWriter, WrittenFrame, prepare_output_dir

#: odometry poses kept for matching (the newest; at 30 Hz a minute of them)
ODOMETRY_KEEP = 2000
#: seconds a frame waits for an odometry pose published after its images
ODOMETRY_WAIT = 0.5
#: seconds between two log lines about frames skipped by ``max_behind`` (the first is logged at once)
BEHIND_LOG_EVERY = 5.0


class SlamEngine(Protocol):
    """What the session needs of a SLAM engine (see :mod:`semantic_gs_slam_ros.engine`)."""

    def add_frame(self, rgb: np.ndarray, depth: np.ndarray, semantics: np.ndarray | None,
                  timestamp: float, odom_c2w: np.ndarray | None = None) -> np.ndarray:
        """rgb uint8 [H,W,3], depth float32 metres [H,W], semantics int [H,W] or None, the odometry's
        camera-to-world pose [4,4] or None → c2w [4,4].

        Raises:
            FrameRefusedError: this frame cannot be used (the session skips it). Any other exception is the engine
                failing: the session ends the run and writes the map it has.
        """

    def save_map(self, out_dir: str) -> tuple[str, str]:
        """Write ``params.npz`` + ``semantic.json`` into ``out_dir``; returns their paths."""

    def save_checkpoint(self, ckpt_dir: str) -> None:
        """Write everything needed to resume into ``ckpt_dir``."""

    @property
    def num_gaussians(self) -> int: ...

    # optional: ``refine(iters, poses, should_stop, seconds) -> iterations done`` (Adam steps over all keyframes,
    # within a time budget when ``seconds`` > 0),
    # ``num_keyframes`` (logged with the refinement),
    # ``frame_report() -> (lost, corrected, note)``, ``run_note() -> str`` (logged at the end) and ``localised``
    # (False while a run started on a saved map is not relocalised in it); the session asks with getattr


@dataclass
class SessionConfig:
    """Settings of one run (node parameters + goal fields).

    Attributes:
        work_dir: where frames/, depths/, semantics/, completed.jsonl and checkpoints go.
        width, height: images are resized to this (seed: 1200×680); 0 = keep the input size.
        depth_scale: units per metre of the depth PNGs (1000 → mm).
        sync_tolerance: largest colour/depth stamp difference of a frame (s).
        sync_max_wait: seconds an image waits for its partner before it is dropped as unmatched.
        use_semantic: also wait for a semantic-id image per frame.
        use_odometry: pair each frame with the odometry pose of the same stamp (within
            ``sync_tolerance``; :meth:`StreamingSession.on_odometry`) and give it to the engine as
            its prior; a frame without one is tracked without.
        min_motion_m, min_motion_deg: with odometry, a frame whose odometry moved less than both
            since the last frame given to SLAM is skipped (a robot standing still, 0 = take all).
        lag_high, lag_low: unsubscribe above / resubscribe below this backlog (frames).
        max_behind: a live camera's bound on the lag: a new frame that finds this many frames waiting for SLAM
            (written, or waiting to be written) first skips the oldest of them (counted in ``Progress.behind``,
            logged, reported in the result), so SLAM works at most this many frames behind the camera (plus the
            one it is on and the one being written) and, when it is slower than the camera, on evenly spaced
            frames. 0 = never skip (a recording loses nothing; ``lag_high`` pauses the intake).
        checkpoint_every: save an engine checkpoint every N processed frames (0 = never).
        export_every: write the map to ``map_dir`` every N processed frames (0 = only at the end).
        map_dir: where the object-query server reads params.npz + semantic.json ("" = work_dir/map).
        max_frames: stop after this many processed frames (0 = until the client is done).
        refine_iters: after the last frame and before the final map is written, this many Adam iterations
            over all keyframes (what ``semantic_gs_slam.run --refine-iters`` does). 0 = none; a cancelled run
            skips it, and a cancel during it keeps what is done and writes the map.
        refine_poses: the refinement also optimises the poses of its views (keyframes and deferred frames;
            ``--refine-poses``); False: as the engine's settings say (``mapping.refine_poses``, on in the
            ``realtime`` profile).
        refine_seconds: the refinement ends after this many seconds at most (0 = no limit; with refine_iters 0,
            it runs for exactly this long). It first maps the frames deferred while the mapping thread was busy
            (the engine's ``mapping.defer_keyframes``), for at most half of this time.
        clean_start: remove frames of an earlier run from work_dir at start.
        frames_before: frames processed by the run this one resumes (checkpoint bookkeeping).
    """

    work_dir: str
    width: int = 1200
    height: int = 680
    depth_scale: float = 1000.0
    sync_tolerance: float = 0.02
    sync_max_wait: float = 5.0
    use_semantic: bool = False
    use_odometry: bool = False
    min_motion_m: float = 0.0
    min_motion_deg: float = 0.0
    lag_high: int = 300
    lag_low: int = 150
    max_behind: int = 0
    checkpoint_every: int = 20
    export_every: int = 0
    map_dir: str = ""
    max_frames: int = 0
    refine_iters: int = 0
    refine_poses: bool = False
    refine_seconds: float = 0.0
    clean_start: bool = True
    frames_before: int = 0

    def __post_init__(self) -> None:
        for name in ("sync_tolerance", "sync_max_wait", "min_motion_m", "min_motion_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise StreamingError(f"{name} must be a finite number >= 0, got {value}")
        if not (math.isfinite(self.depth_scale) and self.depth_scale > 0):
            raise StreamingError(f"depth_scale must be a finite number > 0 (16UC1 units per metre), got "
                                 f"{self.depth_scale}")
        if self.width < 0 or self.height < 0:
            raise StreamingError(f"width and height must be >= 0 (0: the images' size), got {self.width}x{self.height}")
        if not 0 <= self.lag_low < self.lag_high:
            raise StreamingError(f"lag_low and lag_high must satisfy 0 <= lag_low < lag_high, got {self.lag_low} and "
                                 f"{self.lag_high}")
        if self.max_behind < 0:
            raise StreamingError(f"max_behind must be >= 0 (0 = never skip a frame), got {self.max_behind}")
        if self.refine_iters < 0:
            raise StreamingError(f"refine_iters must be >= 0 (0 = no refinement), got {self.refine_iters}")
        if not self.refine_seconds >= 0:
            raise StreamingError(f"refine_seconds must be >= 0 (0 = no limit), got {self.refine_seconds}")
        if self.refine_poses and self.refine_iters == 0 and self.refine_seconds == 0:
            raise StreamingError("refine_poses needs refine_iters > 0 or refine_seconds > 0: it says what the "
                                 "refinement also optimises")

    def resolved_map_dir(self) -> str:
        return self.map_dir or os.path.join(self.work_dir, "map")


@dataclass
class Progress:
    received: dict[str, int] = field(default_factory=lambda: {"rgb": 0, "depth": 0, "semantic": 0})
    matched: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    written: int = 0
    processed: int = 0
    refused: int = 0  # the writer could not take them (queue full or failed): never written
    skipped: int = 0  # written, then refused by SLAM (FrameRefusedError: no valid depth, wrong size)
    backlog: int = 0
    subscribed: bool = True
    pauses: int = 0
    gaussians: int = 0
    pose: list[list[float]] | None = None  # last c2w [4,4]
    with_odometry: int = 0  # processed frames that had an odometry pose
    after_done: int = 0  # images that arrived after data_transfer_done (ignored)
    still: int = 0  # frames skipped because the odometry says the camera had not moved (min_motion_*)
    lost: int = 0  # frames whose tracking was lost (reported by the engine; not mapped)
    behind: int = 0  # frames skipped because SLAM was max_behind frames behind (live camera; written or not)
    writing: int = 0  # frames waiting for the disk writer (part of the backlog)
    drift_corrections: int = 0  # loop closures that found and corrected drift


@dataclass
class SessionResult:
    success: bool
    map_path: str
    semantic_path: str
    frames_processed: int
    message: str


def atomic_publish_map(src_dir: str, map_dir: str) -> tuple[str, str]:
    """Move a freshly saved map into ``map_dir`` so a reader never sees half a map.

    ``semantic.json`` is replaced first, then ``params.npz``, each by ``os.replace`` (atomic on one
    file system), so a reader that loads both after the ``params.npz`` change sees a matching pair.
    """
    os.makedirs(map_dir, exist_ok=True)
    out = []
    for name in ("semantic.json", "params.npz"):
        tmp = os.path.join(map_dir, f".{name}.incoming")
        shutil.copyfile(os.path.join(src_dir, name), tmp)
        os.replace(tmp, os.path.join(map_dir, name))
        out.append(os.path.join(map_dir, name))
    return out[1], out[0]


class StreamingSession:
    """Args:
        config: the run's settings.
        engine: the SLAM engine (kept in memory for the whole run); None = record only (frames
            are written to disk, no map is made).
        on_map: called (on the SLAM thread) with (params.npz, semantic.json) after each export,
            e.g. to ask the object-query server to reload.
        log: called with human-readable log lines.
    """

    def __init__(self, config: SessionConfig, engine: SlamEngine | None,
                 on_map: Callable[[str, str], None] | None = None,
                 log: Callable[[str], None] | None = None) -> None:
        self.cfg = config
        self.engine = engine
        self._on_map = on_map or (lambda _m, _s: None)
        self._log = log or (lambda _line: None)
        prepare_output_dir(config.work_dir, clean=config.clean_start)
        self._lock = threading.Lock()  # guards _matcher, _progress counters, _done_sending, _cancelled
        self._matcher = FrameMatcher(config.sync_tolerance, config.use_semantic, max_wait=config.sync_max_wait)
        self._lag = LagController(config.lag_high, config.lag_low)
        self._progress = Progress()
        self._done_sending = False
        self._cancelled = False
        self._ready: collections.deque[WrittenFrame] = collections.deque()  # written, not yet processed
        self._wake = threading.Event()  # set when a frame is written, or on done/cancel
        self._odometry: collections.OrderedDict[float, np.ndarray] = collections.OrderedDict()  # stamp -> c2w
        self._last_odom: np.ndarray | None = None  # odometry of the last frame given to SLAM
        self._unwritten = 0  # frames max_behind took out of the writer's queue (never written); guarded by _lock
        self._behind_logged = (0, -float("inf"))  # (Progress.behind, time) at the last line about it; by _lock
        # after a resume the folder keeps the earlier frames: continue their numbering
        self._writer = AsyncFrameWriter(config.work_dir, self._on_written,
                                        start_index=0 if config.clean_start else _frames_on_record(config.work_dir))
        # a checkpoint of an engine with a mapping thread is written by that thread between its jobs
        # (save_checkpoint_in_background), so the frames do not wait for it; one at a time: a checkpoint due while
        # the last one is still being written is skipped (counted). Without a mapping thread it is written at once
        self._ckpt_lock = threading.Lock()  # guards _ckpt_busy, _ckpt_error, _ckpt_skipped
        self._ckpt_busy = False
        self._ckpt_error: BaseException | None = None  # a background checkpoint's failure, reported by the run loop
        self._ckpt_skipped = 0

    # ---------------------------------------------------------------- producer side (callbacks)
    def on_image(self, stream: str, stamp: float, image: np.ndarray) -> None:
        """One decoded image (``rgb`` uint8 [H,W,3]; ``depth`` float metres or uint16 in
        1/depth_scale m; ``semantic`` int ids) with its stamp in seconds. Never blocks."""
        image = self._prepare(stream, image)
        with self._lock:
            self._progress.received[stream] = self._progress.received.get(stream, 0) + 1
            if self._cancelled:
                return
            if self._done_sending:  # a live camera goes on after "done": its later images are not this run's
                self._progress.after_done += 1
                return
            frames = self._matcher.push(stream, stamp, image)
            self._progress.matched = self._matcher.stats.matched
            self._progress.dropped = dict(self._matcher.stats.dropped)
        for frame in frames:
            self._make_room()
            if not self._writer.submit(frame):
                with self._lock:
                    self._progress.refused += 1

    def on_odometry(self, stamp: float, c2w: np.ndarray) -> None:
        """The odometry's camera-to-world pose [4, 4] at ``stamp`` (seconds). Never blocks.

        Raises:
            StreamingError: not a finite [4, 4] matrix.
        """
        m = np.asarray(c2w, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise StreamingError(f"odometry pose must be a finite [4, 4] matrix, got shape {list(m.shape)}")
        with self._lock:
            self._odometry[stamp] = m
            while len(self._odometry) > ODOMETRY_KEEP:
                self._odometry.popitem(last=False)

    def _odometry_at(self, stamp: float) -> np.ndarray | None:
        with self._lock:
            best = min(self._odometry, key=lambda t: abs(t - stamp), default=None)
            if best is None or abs(best - stamp) > self.cfg.sync_tolerance:
                return None
            return self._odometry[best]

    def _prepare(self, stream: str, image: np.ndarray) -> np.ndarray:
        w, h = self.cfg.width, self.cfg.height
        if stream == "rgb" and not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] in (3, 4))):
            raise ImageFormatError(f"colour image must be [H, W, 3|4] or mono, got {list(image.shape)}")
        if stream in ("depth", "semantic") and image.ndim != 2:
            raise ImageFormatError(f"{stream} image must be single-channel [H, W], got {list(image.shape)}")
        if stream == "rgb":
            img = rgb_of(image)
            return resize_rgb(img, w, h) if w and h else img
        if stream == "depth":  # nearest-neighbour picks pixels: converting after it is the same, on fewer pixels
            return depth_to_mm(resize_nearest(image, w, h) if w and h else image, self.cfg.depth_scale)
        if stream == "semantic":
            ids = np.asarray(image)
            return resize_nearest(ids, w, h) if w and h else ids
        raise StreamingError(f"unknown image stream {stream!r}")

    def data_transfer_done(self) -> None:
        """The client sent everything: finish once the backlog is empty."""
        with self._lock:
            self._done_sending = True
            self._matcher.flush()
            self._progress.dropped = dict(self._matcher.stats.dropped)
        self._wake.set()

    def cancel(self) -> None:
        """Stop after the frame being processed; the map so far is still saved."""
        with self._lock:
            self._cancelled = True
        self._wake.set()

    def _on_written(self, frame: WrittenFrame) -> None:  # writer thread
        with self._lock:
            self._ready.append(frame)
            self._progress.written += 1
        self._wake.set()

    def matcher_streams(self) -> tuple[str, ...]:
        """The image streams a frame needs (rgb, depth, and semantic if enabled)."""
        return self._matcher.streams

    # ---------------------------------------------------------------- status
    def progress(self) -> Progress:
        with self._lock:
            p = Progress(**{k: (dict(v) if isinstance(v, dict) else v) for k, v in vars(self._progress).items()})
        p.backlog = p.matched - p.refused - p.processed - p.skipped - p.still - p.behind  # matched, not yet done
        p.writing = self._writer.pending()
        return p

    def lag_action(self) -> LagAction:
        """Poll periodically (e.g. from a timer): whether to unsubscribe / resubscribe the image topics."""
        p = self.progress()
        with self._lock:
            action = self._lag.update(p.backlog)
            self._progress.subscribed = self._lag.subscribed
            self._progress.pauses = self._lag.pauses
        if action is not LagAction.NONE:
            self._log(f"backlog {p.backlog} frames: {action.value} image topics")
        return action

    # ---------------------------------------------------------------- SLAM loop
    def run(self, on_progress: Callable[[Progress], None] | None = None, poll: float = 0.1) -> SessionResult:
        """Process frames until the client is done and the backlog is empty, ``max_frames`` are
        processed, or :meth:`cancel`; then export the map. Blocks the calling thread."""
        try:
            return self._run(on_progress, poll)
        finally:
            self._writer.close()

    def _run(self, on_progress: Callable[[Progress], None] | None, poll: float) -> SessionResult:
        ckpt_dir = os.path.join(self.cfg.work_dir, "checkpoint")
        message = ""
        failed = False  # the run ended early for a reason that makes it unsuccessful (the map is still written)
        engine_failed = False  # ... because the engine raised something else than a refused frame
        refused_in_a_row = 0
        t0 = time.monotonic()
        while True:
            with self._lock:
                frame = self._ready.popleft() if self._ready else None
                cancelled = self._cancelled
                finished = self._done_sending and not self._ready and self._writer.pending() == 0 \
                    and self._progress.written + self._unwritten >= self._progress.matched - self._progress.refused
            if self._writer.error is not None:
                message = str(self._writer.error)
                break
            if cancelled:
                message = "cancelled"
                break
            if frame is None:
                if finished:
                    break
                self._wake.wait(poll)
                self._wake.clear()
                continue
            f = frame.frame
            if self.engine is None:
                with self._lock:
                    self._progress.processed += 1
                    n = self._progress.processed
                if on_progress is not None:
                    on_progress(self.progress())
                continue
            depth_m = f.depth.astype(np.float32) / np.float32(self.cfg.depth_scale)
            odom = self._odometry_at(f.stamp) if self.cfg.use_odometry else None
            if odom is None and self.cfg.use_odometry:
                odom = self._wait_odometry(f.stamp)
            if odom is not None and self._still(odom):
                with self._lock:
                    self._progress.still += 1
                continue
            try:
                c2w = self.engine.add_frame(f.rgb, depth_m, f.semantic, f.stamp, odom) if odom is not None \
                    else self.engine.add_frame(f.rgb, depth_m, f.semantic, f.stamp)
            except FrameRefusedError as exc:  # this frame cannot be used (e.g. no valid depth): skip it
                refused_in_a_row += 1
                self._log(f"frame {frame.index} skipped by SLAM: {exc}")
                with self._lock:
                    self._progress.skipped += 1
                if on_progress is not None:
                    on_progress(self.progress())
                if refused_in_a_row >= MAX_BAD_IN_A_ROW:  # a wrong camera or topic, not one bad frame
                    message = f"{refused_in_a_row} frames in a row could not be used (the last, frame {frame.index}: " \
                              f"{exc})"
                    failed = True
                    break
                continue
            except Exception as exc:  # noqa: BLE001  the engine failed (a bug, out of memory): stop, keep the map
                self._log(f"SLAM failed on frame {frame.index}: {type(exc).__name__}: {exc}\n"
                          f"{traceback.format_exc()}the run stops; the map of the frames mapped so far is written")
                message = f"SLAM failed on frame {frame.index} ({type(exc).__name__}: {exc})"
                failed = engine_failed = True
                break
            refused_in_a_row = 0
            report = getattr(self.engine, "frame_report", None)
            lost, corrected, loop = report() if report is not None else (False, False, "")
            if lost and not getattr(self.engine, "localised", True):
                self._log(f"frame {frame.index}: not relocalised in the saved map yet (not mapped; the next frames "
                          "try again)")
            elif lost:
                self._log(f"frame {frame.index}: tracking lost (not mapped; the next frames try again from the "
                          "last good pose)")
            if corrected:
                self._log(f"frame {frame.index}: drift corrected: {loop}")
            with self._lock:
                self._progress.lost += lost
                self._progress.drift_corrections += corrected
                self._progress.processed += 1
                self._progress.gaussians = int(self.engine.num_gaussians)
                self._progress.pose = np.asarray(c2w, dtype=float).tolist()
                self._progress.with_odometry += odom is not None
                n = self._progress.processed
            with self._ckpt_lock:
                ckpt_error = self._ckpt_error
            try:
                if ckpt_error is not None:
                    raise ckpt_error
                if self.cfg.checkpoint_every and n % self.cfg.checkpoint_every == 0:
                    self._checkpoint(ckpt_dir, frame)
                if self.cfg.export_every and n % self.cfg.export_every == 0:
                    self._export()
            except (OSError, StreamingError) as exc:
                message = f"cannot write the checkpoint or map: {exc}"
                break
            if on_progress is not None:
                on_progress(self.progress())
            if self.cfg.max_frames and n >= self.cfg.max_frames:
                message = f"reached max_frames={self.cfg.max_frames}"
                break
        self._writer.close()  # write what is still queued before reporting
        p = self.progress()
        n = p.processed
        dropped = {k: v for k, v in p.dropped.items() if v}
        if dropped or p.refused or p.skipped:
            self._log(f"unmatched images dropped: {dropped or 0}; frames the writer refused: {p.refused}; frames "
                      f"skipped by SLAM: {p.skipped}")
        if p.still or p.after_done:
            self._log(f"frames skipped while the camera stood still: {p.still}; images after "
                      f"data_transfer_done ignored: {p.after_done}")
        with self._ckpt_lock:
            ckpt_skipped, ckpt_error = self._ckpt_skipped, self._ckpt_error
        if ckpt_skipped:
            self._log(f"checkpoints skipped while the last one was still being written: {ckpt_skipped}")
        if ckpt_error is not None and not message:
            self._log(f"the last checkpoint could not be written: {ckpt_error}")
        if p.behind:
            self._log(f"frames skipped while SLAM was more than max_behind={self.cfg.max_behind} frames behind: "
                      f"{p.behind}")
        if n == 0:
            return SessionResult(False, "", "", 0, message or "no frame was processed")
        if self.engine is None:
            ok = self._writer.error is None
            return SessionResult(ok, "", "", n, f"{message + ': ' if message else ''}recorded {n} frames "
                                                f"to {self.cfg.work_dir} (no SLAM)")
        rate = n / max(time.monotonic() - t0, 1e-9)  # frames over the time until the last one, not the refinement
        # refined after a normal end only (not after a cancel, or a writer / checkpoint failure)
        refined = self._refine() if not message or message.startswith("reached max_frames") else ""
        try:
            map_path, sem_path = self._export()
        except (OSError, StreamingError) as exc:
            return SessionResult(False, "", "", n, f"{message + ': ' if message else ''}cannot write the map: {exc}")
        except Exception as exc:  # noqa: BLE001  only after the engine failed: its state may not save; say so
            if not engine_failed:
                raise
            self._log(f"the map could not be written after the engine failed: {type(exc).__name__}: {exc}")
            return SessionResult(False, "", "", n, f"{message}; the map could not be written ({type(exc).__name__}: "
                                                   f"{exc})")
        run_note = getattr(self.engine, "run_note", None)
        if run_note is not None:
            try:
                self._log(f"engine: {run_note()}")
            except Exception as exc:  # noqa: BLE001  a note never fails a run whose map is written
                self._log(f"engine: no note ({type(exc).__name__}: {exc})")
        ok = self._writer.error is None and not failed
        p = self.progress()
        summary = f"{n} frames processed ({rate:.2f} frames/s), {p.gaussians} Gaussians{refined}"
        if p.behind:
            summary += f", {p.behind} frames skipped while SLAM was more than {self.cfg.max_behind} frames behind"
        if p.lost or p.drift_corrections:
            summary += f", tracking lost on {p.lost} frames, drift corrected {p.drift_corrections} times"
        return SessionResult(ok, map_path, sem_path, n, f"{message + ': ' if message else ''}{summary}")

    def _make_room(self) -> None:
        """``max_behind``: before a new frame is queued, skip the oldest waiting ones (written and waiting for SLAM
        first, then waiting to be written) until fewer than ``max_behind`` wait; counted and logged (the first time
        at once, then at most every ``BEHIND_LOG_EVERY`` s)."""
        limit = self.cfg.max_behind
        if limit <= 0:
            return
        line = ""
        with self._lock:
            n = 0
            while len(self._ready) + self._writer.pending() >= limit:
                if self._ready:
                    self._ready.popleft()
                elif self._writer.drop_oldest():
                    self._unwritten += 1
                else:
                    break
                n += 1
            if n == 0:
                return
            self._progress.behind += n
            total, (before, at) = self._progress.behind, self._behind_logged
            now = time.monotonic()
            if now - at >= BEHIND_LOG_EVERY:
                self._behind_logged = (total, now)
                line = (f"SLAM is more than max_behind={limit} frames behind the camera: skipping the oldest waiting "
                        f"frames ({total - before} since the last such line, {total} in all)")
        if line:
            self._log(line)

    def _refine(self) -> str:
        """``refine_iters`` iterations of the engine's map refinement, which looks at a cancel request before each
        iteration; returns the summary's note ("" when none ran)."""
        refine = getattr(self.engine, "refine", None)
        total, seconds = self.cfg.refine_iters, self.cfg.refine_seconds
        if (total <= 0 and seconds <= 0) or refine is None:
            return ""
        poses = self.cfg.refine_poses or bool(getattr(self.engine, "refines_poses", False))
        what = "the map and its views' poses" if poses else "the map"
        count = getattr(self.engine, "num_keyframes", None)
        over = f"all {count} keyframes" if count is not None else "all keyframes"
        budget = (f"{total} iterations" if total > 0 else "iterations") + (f" (at most {seconds:g} s)" if seconds > 0
                                                                           else "")
        self._log(f"refining {what}: {budget} over {over} in turn before the map is written")
        total = total if total > 0 else 10 ** 9
        t0 = time.monotonic()

        def cancelled() -> bool:
            with self._lock:
                return self._cancelled

        try:  # the engine splits a time budget (deferred frames, coarse to fine: SLAM.refine's seconds)
            extra = {"seconds": seconds} if seconds > 0 else {}
            done = int(refine(total, poses=True if self.cfg.refine_poses else None, should_stop=cancelled,
                              **extra))
        except Exception as exc:  # noqa: BLE001  (the map as it is is still written)
            self._log(f"map refinement failed: {exc}; the map is written as it is")
            note = f"map refinement failed ({exc})"
        else:
            of = f" of {total}" if total < 10 ** 9 else ""
            note = f"refined {done}{of} iterations in {time.monotonic() - t0:.1f} s"
            with self._lock:
                why = " (cancelled)" if self._cancelled else " (time budget)" if done < total else ""
            self._log(f"map {note}{why}")
        with self._lock:
            self._progress.gaussians = int(self.engine.num_gaussians)
        return f", {note}"

    def _still(self, odom: np.ndarray) -> bool:
        """Whether the camera moved less than ``min_motion_*`` since the last frame given to SLAM (which
        ``odom`` then becomes, when it did move)."""
        last = self._last_odom
        if last is not None and (self.cfg.min_motion_m > 0 or self.cfg.min_motion_deg > 0):
            rel = np.linalg.inv(last) @ odom
            angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1.0, 1.0)))
            if np.linalg.norm(rel[:3, 3]) < self.cfg.min_motion_m and angle < self.cfg.min_motion_deg:
                return True
        self._last_odom = odom
        return False

    def _wait_odometry(self, stamp: float) -> np.ndarray | None:
        """The frame's odometry pose when it is late (published after the images), at most
        ``ODOMETRY_WAIT`` seconds; None if it never comes (the frame is tracked without it)."""
        deadline = time.monotonic() + ODOMETRY_WAIT
        while time.monotonic() < deadline:
            time.sleep(0.02)
            odom = self._odometry_at(stamp)
            if odom is not None:
                return odom
        return None

    def _checkpoint(self, ckpt_dir: str, frame: WrittenFrame) -> None:
        """The engine's checkpoint and the session's place in the stream (``session.json``), written into
        ``<ckpt_dir>.incoming`` and then moved to ``ckpt_dir``. An engine with a mapping thread writes its part in
        that thread (``save_checkpoint_in_background``; the move follows there, and a failure there ends the run at
        the next frame); one without writes it now."""
        tmp = ckpt_dir + ".incoming"
        place = {"last_index": frame.index, "last_stamp": frame.stamp,
                 "processed": self.cfg.frames_before + self.progress().processed}

        def publish() -> None:
            with open(os.path.join(tmp, "session.json"), "w") as fh:
                json.dump(place, fh)
            if os.path.isdir(ckpt_dir):
                shutil.rmtree(ckpt_dir)
            os.replace(tmp, ckpt_dir)

        background = getattr(self.engine, "save_checkpoint_in_background", None)
        if background is None:  # an engine that only writes its checkpoint when asked
            os.makedirs(tmp, exist_ok=True)
            self.engine.save_checkpoint(os.path.join(tmp, "engine"))
            publish()
            return
        with self._ckpt_lock:
            if self._ckpt_busy:
                self._ckpt_skipped += 1
                return
            self._ckpt_busy = True

        def then(error: BaseException | None) -> None:  # the mapping thread
            if error is None:
                try:
                    publish()
                except OSError as exc:
                    error = exc
            with self._ckpt_lock:
                self._ckpt_busy = False
                if error is not None and self._ckpt_error is None:
                    self._ckpt_error = error

        os.makedirs(tmp, exist_ok=True)
        queued = background(os.path.join(tmp, "engine"), then)
        with self._ckpt_lock:
            if not queued:
                self._ckpt_busy = False
                self._ckpt_skipped += 1
            error, self._ckpt_error = self._ckpt_error, None
        if error is not None:  # written (or not) already, without a mapping thread; or an earlier one's failure
            raise error

    def _export(self) -> tuple[str, str]:
        staging = os.path.join(self.cfg.work_dir, "map.staging")
        os.makedirs(staging, exist_ok=True)
        self.engine.save_map(staging)
        try:
            paths = atomic_publish_map(staging, self.cfg.resolved_map_dir())
        except OSError as exc:
            raise OutputError(f"cannot publish the map to {self.cfg.resolved_map_dir()!r}: {exc}") from exc
        self._log(f"map written: {paths[0]}")
        self._on_map(*paths)
        return paths


def _frames_on_record(work_dir: str) -> int:
    """Index after the last frame recorded in ``work_dir/completed.jsonl`` (0 if none)."""
    last = -1
    try:
        with open(os.path.join(work_dir, "completed.jsonl"), encoding="utf-8") as fh:
            for line in fh:
                try:
                    last = max(last, int(json.loads(line)["index"]))
                except (ValueError, KeyError, TypeError):
                    continue
    except OSError:
        return 0
    return last + 1


def checkpoint_state(work_dir: str) -> dict[str, Any] | None:
    """The session state of the last checkpoint in ``work_dir``, or None."""
    path = os.path.join(work_dir, "checkpoint", "session.json")
    try:
        with open(path) as fh:
            return json.load(fh)
    except (OSError, json.JSONDecodeError):
        return None
